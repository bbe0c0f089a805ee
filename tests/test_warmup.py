"""The demo's compiling helper (pihim._warmup): it compiles the specializations the demo runs, and the demo
waits for it only while it lives."""

import json
import os
import subprocess
import sys
import time
import types

from pihim import _resources, _warmup

#: In a fresh process: the helper's calls, then the quick demo without a helper; the compiled kernels'
#: signatures after each (numba's dispatchers list what was compiled or loaded in the process).
_SCRIPT = r"""
import json, sys, tempfile
from pathlib import Path
from pihim import _warmup
from pihim.demo import DemoSettings, run_demo
from pihim.inspection import _kernels
from pihim.render.kernel import _kernel

_warmup.compile_kernels()
before = {"render": [str(s) for s in _kernel.signatures], "solve": [str(s) for s in _kernels.solve.signatures]}
with tempfile.TemporaryDirectory() as tmp:
    run_demo(Path(tmp) / "d", DemoSettings(pairs=1, width_px=612, height_px=512), compile_helper=False)
after = {"render": [str(s) for s in _kernel.signatures], "solve": [str(s) for s in _kernels.solve.signatures]}
json.dump({"before": before, "after": after}, sys.stdout)
"""


def test_the_helper_compiles_the_specializations_the_demo_runs():
    """Were a type of the demo's calls different (an array's dtype or layout, a literal), the demo would add
    a second signature and compile it itself: the helper would be wasted."""
    out = subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    rec = json.loads(out.stdout)
    for name in ("render", "solve"):
        assert len(rec["before"][name]) == 1, rec
        assert rec["after"][name] == rec["before"][name], name


def _fake_kernel(tmp_path, name):
    index = tmp_path / f"mod.{name}-10.py311.nbi"
    files = types.SimpleNamespace(_index_path=str(index))
    kernel = types.SimpleNamespace(_cache=types.SimpleNamespace(_cache_file=files, _cache_path=str(tmp_path)))
    return index, kernel


def test_cached_needs_the_index_and_a_data_file(tmp_path, monkeypatch):
    index, kernel = _fake_kernel(tmp_path, "k")
    monkeypatch.setitem(sys.modules, "fake_kernels", types.SimpleNamespace(k=kernel, plain=object()))
    monkeypatch.setattr(_warmup, "KERNELS", {"k": ("fake_kernels", "k"), "plain": ("fake_kernels", "plain")})
    assert not _warmup.cached("k")
    index.write_bytes(b"index")
    assert not _warmup.cached("k")  # numba writes the index first: the data may not be there yet
    (tmp_path / "mod.k-10.py311.1.nbc").write_bytes(b"data")
    assert _warmup.cached("k")
    assert not _warmup.cached("plain")  # no cache attributes (numba changed, or JIT off): uncached
    assert _warmup.writable("k") and not _warmup.writable("plain")
    tmp_path.chmod(0o500)
    try:
        if os.access(tmp_path, os.W_OK):  # root writes anywhere
            return
        assert not _warmup.writable("k")
    finally:
        tmp_path.chmod(0o700)


def test_no_helper_when_cached_uncachable_or_jit_disabled(monkeypatch):
    from numba.core import config

    spawned = []
    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: spawned.append(a) or "proc")
    monkeypatch.setattr(_warmup, "writable", lambda what: True)
    monkeypatch.setattr(_warmup, "cached", lambda what: True)
    assert _warmup.start() is None
    monkeypatch.setattr(_warmup, "cached", lambda what: False)
    monkeypatch.setattr(_warmup, "writable", lambda what: what != "solve")
    assert _warmup.start() is None  # a kernel numba cannot cache: the demo would wait for nothing
    monkeypatch.setattr(_warmup, "writable", lambda what: True)
    monkeypatch.setattr(_resources, "available_memory", lambda: _warmup.HELPER_BYTES - 1)
    assert _warmup.start() is None  # no room for the helper
    monkeypatch.setattr(_resources, "available_memory", lambda: None)
    monkeypatch.setattr(config, "DISABLE_JIT", True)
    assert _warmup.start() is None
    monkeypatch.setattr(config, "DISABLE_JIT", False)
    assert _warmup.start() == "proc"
    assert spawned == [([sys.executable, "-m", "pihim._warmup"],)]


def test_wait_for_returns_when_cached_when_the_helper_ends_or_on_timeout(monkeypatch):
    monkeypatch.setattr(_warmup, "cached", lambda what: False)
    _warmup.wait_for(None, "render")  # no helper: no wait
    quick = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(0.3)"])
    t0 = time.monotonic()
    _warmup.wait_for(quick, "render", timeout_s=30)
    assert quick.poll() is not None and time.monotonic() - t0 < 10
    slow = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        t0 = time.monotonic()
        _warmup.wait_for(slow, "render", timeout_s=0.5)
        assert 0.4 < time.monotonic() - t0 < 5 and slow.poll() is None
        monkeypatch.setattr(_warmup, "cached", lambda what: what == "render")
        t0 = time.monotonic()
        _warmup.wait_for(slow, "render", timeout_s=30)
        assert time.monotonic() - t0 < 1
    finally:
        _warmup.stop(slow)
    assert slow.returncode is not None  # terminated and reaped
    _warmup.stop(None)  # no helper: nothing to do
