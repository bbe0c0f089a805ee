"""Work shared among forked workers (pihim._forked): the serial results, in order, nothing lost."""

import os
import signal
import sys
import time

import numpy as np
import pytest

from pihim import _forked
from pihim.errors import PihimInputError

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="workers are forked on Linux only")


@linux
def test_pieces_run_in_other_processes_and_come_back_in_order(tmp_path):
    big = np.arange(1_000_000, dtype=np.float64)  # inherited by the fork, never pickled
    pids = tmp_path / "pids"

    def job(i: int) -> tuple[int, float]:
        with pids.open("a") as fh:
            fh.write(f"{os.getpid()}\n")
        return i, float(big[i * 1000: (i + 1) * 1000].sum())

    got = _forked.map_pieces(job, 40, 2)
    assert got == [job(i) for i in range(40)]  # the serial values, in the pieces' order
    workers = {int(v) for v in pids.read_text().split()} - {os.getpid()}
    assert 1 <= len(workers) <= 2
    assert list(_forked.imap(lambda i: i * i, 25, 2)) == [i * i for i in range(25)]
    assert sorted(_forked.imap_unordered(lambda i: -i, 9, 2)) == [(i, -i) for i in range(9)]


def test_one_worker_runs_here_in_order():
    seen = []

    def job(i: int) -> int:
        seen.append((i, os.getpid()))
        return 2 * i

    assert _forked.map_pieces(job, 5, 1) == [0, 2, 4, 6, 8]
    assert seen == [(i, os.getpid()) for i in range(5)]
    assert not _forked.can_fork(1, 100) and not _forked.can_fork(4, 1)


@linux
def test_a_killed_worker_loses_no_piece():
    parent = os.getpid()

    def job(i: int) -> int:
        if os.getpid() != parent and i == 3:
            os.kill(os.getpid(), signal.SIGKILL)
        return i + 100

    with pytest.warns(RuntimeWarning, match=r"worker process died; the \d+ remaining tests run in this process"):
        got = _forked.map_pieces(job, 12, 2, what="tests")
    assert got == [i + 100 for i in range(12)]


@linux
def test_an_exception_in_a_worker_reaches_the_caller():
    def job(i: int) -> int:
        if i == 2:
            raise PihimInputError("piece 2 refused")
        return i

    with pytest.raises(PihimInputError, match="piece 2 refused"):
        _forked.map_pieces(job, 6, 2)


@linux
def test_started_pieces_run_while_the_caller_works(tmp_path):
    """start() returns at once; the workers work on while this process does something else; results() gives
    the serial values in order and stops them."""
    import time

    gate = tmp_path / "go"

    def job(i: int) -> tuple[int, int]:
        while not gate.exists():  # only once the caller has moved on
            time.sleep(0.01)
        return i, os.getpid()

    started = _forked.start(job, 8, 1)  # one worker is worth forking here: this process has other work
    assert started.running
    gate.touch()  # the caller's own work
    got = started.results()
    assert [i for i, _ in got] == list(range(8)) and all(pid != os.getpid() for _, pid in got)
    assert not started.running


def test_started_without_workers_runs_at_results():
    seen = []
    started = _forked.start(lambda i: seen.append(i) or i * 3, 4, 0)
    assert not started.running and seen == []
    assert started.results() == [0, 3, 6, 9] and seen == [0, 1, 2, 3]
    started.close()  # nothing to stop


@linux
def test_a_killed_started_worker_loses_no_piece():
    parent = os.getpid()

    def job(i: int) -> int:
        if os.getpid() != parent and i == 1:
            os.kill(os.getpid(), signal.SIGKILL)
        return -i

    started = _forked.start(job, 10, 2, what="traces")
    with pytest.raises(PihimInputError, match="background workers"):
        _forked.start(job, 10, -1)
    with pytest.warns(RuntimeWarning, match=r"worker process died; the \d+ remaining traces run in this process"):
        assert started.results() == [-i for i in range(10)]


@linux
def test_closing_started_workers_stops_them():
    import time

    started = _forked.start(lambda i: time.sleep(60) or i, 200, 2)
    pids = [p.pid for p in started._pool._processes.values()]
    time.sleep(0.5)  # the workers are in their first pieces
    t0 = time.perf_counter()
    started.close()  # as a finally does after an error: the pieces begun are interrupted, the others dropped
    assert time.perf_counter() - t0 < 5.0 and not started.running
    for pid in pids:
        with pytest.raises(OSError):
            for _ in range(100):
                os.kill(pid, 0)
                time.sleep(0.01)


@pytest.mark.parametrize("workers", [0, -1, _forked.MAX_WORKERS + 1, 1.5, True, "2"])
def test_bad_worker_counts_are_refused(workers):
    with pytest.raises(PihimInputError, match="workers must be None or an integer"):
        _forked.check_workers(workers)
    with pytest.raises(PihimInputError):
        _forked.map_pieces(lambda i: i, 3, workers)


@linux
def test_an_error_interrupts_the_pieces_being_computed():
    """The error of one piece reaches the caller without waiting for the others begun (a minute each here)."""
    import time

    def job(i: int) -> int:
        if i == 0:
            time.sleep(0.3)
            raise ValueError("piece 0 failed")
        t = time.perf_counter()
        while time.perf_counter() - t < 60:  # Python code: stopped between two instructions
            sum(range(1000))
        return i

    t0 = time.perf_counter()
    with pytest.raises(ValueError, match="piece 0 failed"):
        _forked.map_pieces(job, 4, 2)
    assert time.perf_counter() - t0 < 10.0


_INTERRUPTED_CHILD = """
import sys, time
from pihim import _forked

def job(i):
    if sys.argv[1] == "sleep":
        time.sleep(60)
        return i
    time.sleep(0.02)
    return bytes(20_000_000)  # larger than the pipe: the result is often being sent when Ctrl-C comes

print("start", flush=True)
try:
    for _ in _forked.imap_unordered(job, 40, 2):
        pass
except KeyboardInterrupt:
    print("interrupted", flush=True)
    sys.exit(130)
print("done", flush=True)
"""


@linux
@pytest.mark.parametrize(("kind", "delays"), [("sleep", (1.0,)), ("results", (0.0, 0.05, 0.1, 0.2, 0.3, 0.5))])
@pytest.mark.parametrize("group", [False, True], ids=["parent", "group"])
def test_ctrl_c_stops_the_workers_at_once(kind, delays, group):
    """Ctrl-C to the parent alone or to the whole group (a terminal's): exit within seconds, no traceback, no
    process left, whether the workers were computing (a minute each), starting or sending a result."""
    import subprocess
    import time

    for delay in delays:
        child = subprocess.Popen([sys.executable, "-c", _INTERRUPTED_CHILD, kind], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True, start_new_session=True)
        try:
            assert child.stdout.readline() == "start\n"
            time.sleep(delay)
            t0 = time.perf_counter()
            if group:
                os.killpg(child.pid, signal.SIGINT)
            else:
                child.send_signal(signal.SIGINT)
            out, err = child.communicate(timeout=20)
        finally:
            if child.poll() is None:
                os.killpg(child.pid, signal.SIGKILL)
        assert time.perf_counter() - t0 < 5.0
        assert child.returncode in (0, 130) and out.strip() in ("interrupted", "done") and err == "", (delay, err)
        if kind == "sleep":
            assert child.returncode == 130
        with pytest.raises(ProcessLookupError):  # the workers (in the child's session) are gone
            os.killpg(child.pid, 0)


@linux
def test_a_run_that_ignores_ctrl_c_goes_on():
    """A process started with SIGINT ignored (in the background by a shell) keeps ignoring it in its workers."""
    import subprocess

    child = subprocess.Popen([sys.executable, "-c", _INTERRUPTED_CHILD, "results"], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, start_new_session=True,
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        assert child.stdout.readline() == "start\n"
        for _ in range(5):
            os.killpg(child.pid, signal.SIGINT)
            time.sleep(0.05)
        out, err = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
    assert (child.returncode, out, err) == (0, "done\n", "")


_SCRIPT = """
import signal, sys, time
from pihim import _forked
case = sys.argv[1]

def busy(j):  # calls of about 0.25 s into C, which a signal cannot cut, for good
    import hashlib
    while True:
        hashlib.pbkdf2_hmac("sha256", b"x", b"y", 1_000_000)

def nested(i):  # each piece runs a pool of its own
    return sum(v for _, v in _forked.imap_unordered(busy, 4, 2))

if case == "graceful":  # a program's own Ctrl-C: finish what is being done
    stop = []
    signal.signal(signal.SIGINT, lambda s, f: stop.append(s))
    print("start", flush=True)
    print(_forked.map_pieces(lambda i: time.sleep(1.0) or i, 4, 2), bool(stop), flush=True)
elif case == "nested":
    print("start", flush=True)
    try:
        _forked.map_pieces(nested, 4, 2)
    except KeyboardInterrupt:
        print("interrupted", flush=True)
        sys.exit(130)
elif case == "callbacks":  # pieces that spend their time in Python called back from C (libc's qsort)
    import ctypes, os

    compare_type = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_double), ctypes.POINTER(ctypes.c_double))

    @compare_type
    def compare(a, b):
        time.sleep(0.002)
        return (a[0] > b[0]) - (a[0] < b[0])

    sorting_now = os.pipe()

    def sorting(i):  # a sort of about 0.4 s in the callback, then 0.2 s of Python of its own, for good
        while True:
            values = (ctypes.c_double * 64)(*range(64, 0, -1))
            os.write(sorting_now[1], b"s")
            ctypes.CDLL(None).qsort(values, 64, ctypes.sizeof(ctypes.c_double), compare)
            t = time.perf_counter()
            while time.perf_counter() - t < 0.2:
                pass

    started = _forked.start(sorting, 2, 2)
    os.read(sorting_now[0], 1), os.read(sorting_now[0], 1)  # both sorting: the stop lands in a callback
    t = time.perf_counter()
    started.close()
    print("closed", round(time.perf_counter() - t), flush=True)
elif case == "unclosed":  # a pool its caller never closed (a Ctrl-C cut its close() short)
    started = _forked.start(lambda i: time.sleep(60) or i, 2, 2)
    time.sleep(0.5)
    t = time.perf_counter()
    print("closed", _forked.close_all(), _forked.close_all(), round(time.perf_counter() - t), flush=True)
elif case == "masked":  # a caller that blocks SIGUSR1 (the workers' stop signal)
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGUSR1})
    started = _forked.start(lambda i: time.sleep(60) or i, 4, 2)
    time.sleep(0.5)
    t = time.perf_counter()
    started.close()
    print("closed", round(time.perf_counter() - t), flush=True)
"""


def _run_script(case, signal_group_after=None):
    import subprocess

    child = subprocess.Popen([sys.executable, "-c", _SCRIPT, case], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, start_new_session=True)
    try:
        if signal_group_after is not None:
            assert child.stdout.readline() == "start\n"
            time.sleep(signal_group_after)
            os.killpg(child.pid, signal.SIGINT)
        out, err = child.communicate(timeout=20)
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
    return child.returncode, out, err


@linux
def test_workers_leave_ctrl_c_to_the_caller():
    """A caller whose own SIGINT handler does not raise gets its pieces: the workers ignore Ctrl-C."""
    rc, out, err = _run_script("graceful", signal_group_after=0.3)
    assert (rc, out, err) == (0, "[0, 1, 2, 3] True\n", "")


@linux
def test_ctrl_c_stops_pools_run_by_pieces():
    """Ctrl-C to the group while the workers' pieces run pools of their own: all stop at once."""
    t0 = time.perf_counter()
    rc, out, err = _run_script("nested", signal_group_after=1.0)
    assert (rc, out, err) == (130, "interrupted\n", "")
    assert time.perf_counter() - t0 < 10.0


@linux
def test_a_stop_that_lands_in_a_callback_from_c_is_raised_again():
    """The stop raised in Python called back from C is swallowed there ("Exception ignored in ...", printed by
    the worker) and the piece went on: close() waited for its end (here: for good). It is now raised again
    until it lands outside the callback (in the piece's own Python, within 0.4 s here)."""
    rc, out, err = _run_script("callbacks")
    assert (rc, out, err) == (0, "closed 0\n", "") or (rc, out, err) == (0, "closed 1\n", "")


@linux
def test_close_all_stops_the_pools_left_open():
    rc, out, err = _run_script("unclosed")
    assert (rc, out, err) == (0, "closed 1 0 0\n", "")


@linux
def test_a_caller_blocking_the_stop_signal_still_stops_its_workers():
    rc, out, err = _run_script("masked")
    assert (rc, out, err) == (0, "closed 0\n", "")


def test_signals_deferred_hands_every_signal_over_after_the_block():
    seen = []
    previous = signal.signal(signal.SIGTERM, lambda s, f: seen.append(s))
    try:
        with pytest.raises(KeyboardInterrupt):
            with _forked.signals_deferred():
                os.kill(os.getpid(), signal.SIGINT)
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)
                assert seen == []  # nothing raised or handled inside
        time.sleep(0.01)
        assert seen == [signal.SIGTERM]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_signals_deferred_lets_a_default_sigterm_end_the_process():
    """A program's own Ctrl-C handler that does not raise, then SIGTERM left to its default: the process ends."""
    import subprocess

    script = """
import os, signal, time
from pihim import _forked
got = []
signal.signal(signal.SIGINT, lambda s, f: got.append(s))
with _forked.signals_deferred():
    os.kill(os.getpid(), signal.SIGINT)
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(0.05)
time.sleep(0.5)
print("still running", got)
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=30)
    assert done.returncode == -signal.SIGTERM and done.stdout == "", (done.returncode, done.stdout)


def test_signals_deferred_restores_the_handlers_when_one_raises_on_the_way_out():
    import threading

    def stop(signum, frame):
        raise KeyboardInterrupt

    term = signal.getsignal(signal.SIGTERM)
    previous = signal.signal(signal.SIGUSR1, stop)  # held back in the block too (the workers' stop signal)
    try:
        with pytest.raises(KeyboardInterrupt):
            with _forked.signals_deferred():
                signal.pthread_kill(threading.get_ident(), signal.SIGUSR1)  # pending here until the block ends
                time.sleep(0.05)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        assert signal.getsignal(signal.SIGTERM) is term
    finally:
        signal.signal(signal.SIGUSR1, previous)


def test_signals_deferred_keeps_an_ignored_signal_ignored():
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with _forked.signals_deferred():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
        time.sleep(0.05)
    finally:
        signal.signal(signal.SIGINT, previous)
