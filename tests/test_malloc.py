"""pihim._malloc: freed blocks kept for reuse, measured by the page faults of allocating again."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from pihim._malloc import keep_freed_memory

# In a fresh process: rounds of six 4 MB blocks allocated, touched and freed together, as a computation's
# temporaries come and go; the minor page faults of three rounds after three warm-up rounds are counted.
# With glibc's defaults the free space left at the top of the heap passes the (adaptive) trim threshold, is
# returned to the system and faulted in again the next round, a fault per 4 kB page (17,000 faults here on
# the 2-core machine); kept, it is reused and nothing faults.
_FAULTS = r"""
import json, resource, sys
import numpy as np
from pihim._malloc import keep_freed_memory
kept = keep_freed_memory() if sys.argv[1] == "keep" else None
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
def round_of_temporaries():
    blocks = [np.ones(500_000) for _ in range(6)]
    del blocks
for _ in range(3):
    round_of_temporaries()
before = faults()
for _ in range(3):
    round_of_temporaries()
print(json.dumps({"kept": kept, "faults": faults() - before}))
"""



def _glibc() -> bool:
    try:
        return sys.platform.startswith("linux") and bool(os.confstr("CS_GNU_LIBC_VERSION"))
    except (AttributeError, ValueError, OSError):
        return False


GLIBC = _glibc()


def _run(mode: str, **env: str) -> dict:
    environ = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    environ.update(env, PYTHONPATH=os.pathsep.join(sys.path))
    done = subprocess.run([sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, env=environ,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not GLIBC, reason="glibc's mallopt")
def test_freed_memory_is_reused_without_page_faults():
    default = _run("default")
    kept = _run("keep")
    assert kept["kept"] is True
    assert default["faults"] > 5000  # (72 MB of blocks: at most 18,000 faults)
    assert kept["faults"] < 100


@pytest.mark.skipif(not GLIBC, reason="glibc's mallopt")
@pytest.mark.parametrize("env", [{"MALLOC_TRIM_THRESHOLD_": "131072"},
                                 {"GLIBC_TUNABLES": "glibc.malloc.trim_threshold=131072"}])
def test_the_users_malloc_settings_win(env):
    got = _run("keep", **env)
    assert got["kept"] is False
    assert got["faults"] > 5000  # glibc's behaviour, as the user set it


@pytest.mark.parametrize("value", [-1, 2**31, 2**32 + 5])
def test_a_threshold_a_c_int_cannot_hold_is_refused(value):
    with pytest.raises(ValueError, match="2\\*\\*31"):
        keep_freed_memory(mmap_threshold=value)


def test_nothing_changes_off_linux(monkeypatch):
    monkeypatch.setattr(sys, "platform", "darwin")
    assert keep_freed_memory() is False
