"""The ``pihim`` process (``pihim.__main__``): Ctrl-C pressed several times stops it once, cleanly."""

import os
import signal
import subprocess
import sys
import time

import pytest

from pihim.__main__ import REPEAT_S, Interrupts

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="process groups and forked workers")


def test_the_first_ctrl_c_raises_repeats_are_absorbed_and_a_late_one_ends_the_process():
    now = [100.0]
    stopped = []
    handler = Interrupts(clock=lambda: now[0], stop=stopped.append)
    with pytest.raises(KeyboardInterrupt):
        handler(signal.SIGINT, None)
    now[0] += 0.5 * REPEAT_S
    assert handler(signal.SIGINT, None) is None and stopped == []  # the same request, pressed again
    now[0] += REPEAT_S
    handler(signal.SIGINT, None)
    assert stopped == [130]


#: ``pihim windows`` whose sweep runs pieces of 60 s in two forked workers; it prints "start" once they run. After
#: Ctrl-C its clean-up takes 0.4 s and leaves the file "cleaned" ("stuck": it never ends, and no KeyboardInterrupt
#: cuts it); the interpreter's exit takes 0.4 s more (printing "exiting" first) and leaves "exited".
_CHILD = """
import atexit, pathlib, sys, time
import pihim.planning.windows as windows
from pihim import _forked
marks, case = pathlib.Path(sys.argv[1]).parent, sys.argv[2]

def sweep_day(*args, **kwargs):
    pieces = _forked.imap_unordered(lambda i: time.sleep(60) or i, 4, 2)
    try:
        time.sleep(0.5)
        print("start", flush=True)
        return list(pieces)
    except KeyboardInterrupt:
        while case == "stuck":
            try:
                time.sleep(0.01)
            except KeyboardInterrupt:
                pass
        time.sleep(0.4)
        (marks / "cleaned").touch()
        raise

def leaving():
    print("exiting", flush=True)
    time.sleep(0.4)
    (marks / "exited").touch()

atexit.register(leaving)
windows.sweep_day = sweep_day
from pihim.__main__ import run
sys.argv = ["pihim", "windows", "--date", "2021-05-13", "--out", sys.argv[1]]
sys.exit(run())
"""


def _interrupted(tmp_path, case, presses, *, at_exit=False):
    """Run the child, press Ctrl-C (to the whole group, as a terminal does) after each delay of ``presses`` --
    the last one once the interpreter's exit began with ``at_exit`` -- and return the exit status, stderr and
    the time from the first press to the end."""
    out = tmp_path / "w"
    child = subprocess.Popen([sys.executable, "-c", _CHILD, str(out), case], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert child.stdout.readline() == "start\n"
        t0 = time.perf_counter()
        for k, delay in enumerate(presses):
            if at_exit and k == len(presses) - 1:
                assert child.stdout.readline() == "exiting\n"
            time.sleep(delay)
            os.killpg(child.pid, signal.SIGINT)
        _, err = child.communicate(timeout=30)
        took = time.perf_counter() - t0
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
    time.sleep(0.2)
    with pytest.raises(ProcessLookupError):  # no worker left behind
        os.killpg(child.pid, 0)
    assert not out.exists()
    return child.returncode, err, took


@linux
@pytest.mark.parametrize("presses", [(0.0, 0.005, 0.02), (0.0, 0.1, 0.3)])
def test_ctrl_c_pressed_again_at_once_lets_the_clean_up_finish(tmp_path, presses):
    """Presses after the first within REPEAT_S are the same request: before, each raised KeyboardInterrupt
    again, inside the clean-up the first one had started (temporaries left, "Exception ignored" tracebacks)."""
    rc, err, took = _interrupted(tmp_path, "plain", presses)
    # -2: a press that came in the interpreter's last steps, once Python has put the default handler back
    # (death by SIGINT, which a shell reports as 130 too)
    assert rc in (130, -signal.SIGINT) and err == "pihim: aborted\n" and took < 5.0
    assert (tmp_path / "cleaned").exists()


@linux
def test_ctrl_c_during_the_interpreters_exit_ends_it_at_once(tmp_path):
    """The command is over: a press now ends the process (before, a traceback from the interrupted atexit
    callback, or an exit waiting for good on workers no longer told to stop)."""
    rc, err, _ = _interrupted(tmp_path, "plain", (0.0, 0.1), at_exit=True)
    assert (rc, err) == (130, "pihim: aborted\n")
    assert (tmp_path / "cleaned").exists() and not (tmp_path / "exited").exists()


@linux
def test_ctrl_c_again_later_ends_a_stuck_clean_up_at_once(tmp_path):
    rc, err, took = _interrupted(tmp_path, "stuck", (0.0, 1.5 * REPEAT_S))
    assert (rc, err) == (130, "") and took < 1.5 * REPEAT_S + 3.0
    assert not (tmp_path / "cleaned").exists()
