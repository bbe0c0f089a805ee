"""The demo's compiling helper (pihim._warmup): it compiles the specializations the demo runs, the demo
waits for its reports only while it lives, and reaps it."""

import io
import json
import os
import subprocess
import sys
import time
import types
from pathlib import Path

import pytest

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


def _fake_kernel(tmp_path, index):
    files = types.SimpleNamespace(_load_index=lambda: dict(index))
    return types.SimpleNamespace(_cache=types.SimpleNamespace(_cache_file=files, _cache_path=str(tmp_path)))


def test_cached_needs_a_valid_index_entry_and_its_data_file(tmp_path, monkeypatch):
    """numba's index is empty when the source or numba changed (a stale cache is no cache)."""
    kernels = {"stale": _fake_kernel(tmp_path, {}), "k": _fake_kernel(tmp_path, {("sig",): "mod.k-10.py311.1.nbc"}),
               "plain": object()}
    monkeypatch.setitem(sys.modules, "fake_kernels", types.SimpleNamespace(**kernels))
    monkeypatch.setattr(_warmup, "KERNELS", {k: ("fake_kernels", k) for k in kernels})
    assert not _warmup.cached("stale")
    assert not _warmup.cached("k")  # numba writes the index before the data file
    (tmp_path / "mod.k-10.py311.1.nbc").write_bytes(b"data")
    assert _warmup.cached("k")
    assert not _warmup.cached("plain")  # no cache (numba changed, or JIT off): uncached
    assert _warmup.writable("k") and not _warmup.writable("plain")


class _FakeProc:
    def __init__(self, output=""):
        self.stdout = io.StringIO(output)
        self.returncode = None

    def poll(self):
        return self.returncode


def test_no_helper_when_cached_uncachable_single_cpu_short_of_memory_or_jit_disabled(monkeypatch):
    from numba.core import config

    spawned = []

    def popen(args, **kw):
        # its standard input a pipe of the demo's: the helper leaves when that pipe closes (at once on DEVNULL)
        assert kw["stdin"] is subprocess.PIPE
        spawned.append((args, kw["env"]["PYTHONPATH"].split(os.pathsep)[0]))
        return _FakeProc()

    monkeypatch.setattr(subprocess, "Popen", popen)
    monkeypatch.setattr(_warmup, "writable", lambda what: True)
    monkeypatch.setattr(_warmup, "_cpus", lambda: 2)
    monkeypatch.setattr(_resources, "available_memory", lambda: None)
    monkeypatch.setattr(_warmup, "cached", lambda what: True)
    assert _warmup.start() is None
    monkeypatch.setattr(_warmup, "cached", lambda what: what == "render")  # one of them missing: a helper
    assert _warmup.start() is not None
    monkeypatch.setattr(_warmup, "cached", lambda what: False)
    for name, value in (("writable", lambda what: what != "solve"), ("_cpus", lambda: 1)):
        with monkeypatch.context() as m:
            m.setattr(_warmup, name, value)
            assert _warmup.start() is None
    with monkeypatch.context() as m:
        m.setattr(_resources, "available_memory", lambda: _warmup.HELPER_BYTES - 1)
        assert _warmup.start() is None
    with monkeypatch.context() as m:
        m.setattr(config, "DISABLE_JIT", True)
        assert _warmup.start() is None
    helper = _warmup.start()
    assert isinstance(helper, _warmup.Helper)
    # this pihim first on the helper's path, whatever the working folder holds
    root = str(Path(_warmup.__file__).resolve().parents[1])
    assert spawned[-1] == ([sys.executable, "-m", "pihim._warmup", str(os.getpid())], root)


def _helper(code):
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    return _warmup.Helper(proc)


def test_wait_for_returns_on_the_report_when_the_helper_ends_or_on_timeout():
    _warmup.wait_for(None, "render")  # no helper: no wait
    helper = _helper("import time; time.sleep(0.3); print('render', flush=True); time.sleep(60)")
    try:
        t0 = time.monotonic()
        _warmup.wait_for(helper, "render", timeout_s=30)
        assert helper.reported["render"].is_set() and time.monotonic() - t0 < 10
        t0 = time.monotonic()
        _warmup.wait_for(helper, "solve", timeout_s=0.5)  # not reported: the timeout
        assert 0.4 < time.monotonic() - t0 < 5 and helper.proc.poll() is None
    finally:
        _warmup.stop(helper)
    assert helper.proc.returncode is not None  # terminated and reaped
    ended = _helper("pass")  # ends without a report: nothing more is waited for
    t0 = time.monotonic()
    _warmup.wait_for(ended, "solve", timeout_s=30)
    assert time.monotonic() - t0 < 10
    _warmup.stop(ended)
    _warmup.stop(None)  # no helper: nothing to do


def test_the_demo_waits_for_the_helper_and_reaps_it_even_when_it_fails(tmp_path, monkeypatch):
    import pihim.demo
    from pihim.demo import DemoSettings, run_demo
    from pihim.errors import PihimInputError

    calls = []
    helper = _helper("import time; time.sleep(60)")
    monkeypatch.setattr(_warmup, "start", lambda: helper)
    monkeypatch.setattr(_warmup, "wait_for", lambda h, what, timeout_s=60.0: calls.append((h, what)))
    run_demo(tmp_path / "d", DemoSettings(pairs=1, width_px=612, height_px=512))
    assert calls == [(helper, "render"), (helper, "solve")]  # before the first frame and the first inspection
    assert helper.proc.returncode is not None  # reaped when the demo returned

    failing = _helper("import time; time.sleep(60)")
    monkeypatch.setattr(_warmup, "start", lambda: failing)

    def fail(*args, **kw):
        raise PihimInputError("planning failed")

    monkeypatch.setattr(pihim.demo, "_run_demo", fail)
    with pytest.raises(PihimInputError):
        run_demo(tmp_path / "e", DemoSettings(pairs=1, width_px=612, height_px=512))
    assert failing.proc.returncode is not None


def _started(pid):
    """The start time of process ``pid`` (clock ticks after boot, /proc/PID/stat), None if there is none."""
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19])
    except (FileNotFoundError, IndexError, ValueError):
        return None


def _gone(pid, started):
    """Whether the process ``pid`` started at ``started`` has ended (a zombie, or its pid unused or reused)."""
    try:
        state = Path(f"/proc/{pid}/status").read_text().split("State:")[1].split()[0]
    except (FileNotFoundError, IndexError):
        return True
    return state in ("Z", "X") or _started(pid) != started


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc")
def test_the_helper_leaves_at_once_when_the_demo_is_killed(tmp_path):
    import signal

    # a stand-in for the demo: starts the helper as start() does, reports its pid, then idles
    parent_code = ("import os, subprocess, sys, time\n"
                   "p = subprocess.Popen([sys.executable, '-m', 'pihim._warmup', str(os.getpid())],"
                   " stdin=subprocess.PIPE, stdout=subprocess.DEVNULL)\n"
                   "print(p.pid, flush=True)\n"
                   "time.sleep(120)\n")
    root = str(Path(_warmup.__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])]),
           "NUMBA_CACHE_DIR": str(tmp_path)}  # an empty cache: the helper's first stage compiles for 15-20 s
    parent = subprocess.Popen([sys.executable, "-c", parent_code], stdout=subprocess.PIPE, text=True, env=env)
    helper_pid = int(parent.stdout.readline())
    started = _started(helper_pid)
    try:
        time.sleep(1.5)  # the helper is importing or compiling
        assert started is not None and not _gone(helper_pid, started)
        parent.send_signal(signal.SIGKILL)  # no chance to stop() it
        parent.wait()
        deadline = time.monotonic() + 3.0
        while not _gone(helper_pid, started) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _gone(helper_pid, started)  # it used to compile on until its stage ended (15-20 s)
    finally:
        if started is not None and not _gone(helper_pid, started):
            os.kill(helper_pid, signal.SIGKILL)
        parent.stdout.close()
