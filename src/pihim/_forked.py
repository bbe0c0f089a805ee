"""Independent pieces of work shared among forked copies of this process (Linux), with a serial fallback.

The planner's costly stages (the day sweep's times; in ``pihim plan`` the
lines' settings, the scoring's groups of passes, the facet captures'
candidates, the facet report's chunks of captures and the files) are
independent pieces whose inputs are large (the tracked field, the plan,
closures, compiled kernels). :func:`imap_unordered` hands them to a pool of
processes forked from the caller: the children inherit every input by the
fork itself (nothing is pickled on the way in; only each piece's index is
sent) and send back only the results. What a worker reads of the parent's
Python objects it copies (their reference counts are written), so the
workers' memory grows with what they touch: a ``pihim plan`` of 100,000
heliostats and its two workers held 5.1 GB together at their peak, 2.1 GB in
one process (proportional set sizes, ``BENCHMARKS.md``). With one worker, or off Linux (``fork`` is
unsafe on macOS and absent on Windows), the pieces run in this process, in
order: the results do not depend on the number of workers. :func:`start`
hands pieces to workers that work on while the caller does something else
(``pihim plan`` traces the facet report's captures during the route).
"""

from __future__ import annotations

import contextlib
import gc
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from typing import Any, Generic, TypeVar

from pihim.errors import PihimInputError

T = TypeVar("T")

#: Most worker processes ``workers=None`` starts (each a forked copy of the caller).
DEFAULT_MAX_WORKERS = 8
#: Most worker processes accepted at all.
MAX_WORKERS = 64

#: In a forked worker, the job it serves (handed over by the fork itself: nothing is pickled).
_WORKER_JOB: Callable[[int], Any] | None = None


def default_workers() -> int:
    """One worker per CPU this process may run on, at most :data:`DEFAULT_MAX_WORKERS`."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cpus, DEFAULT_MAX_WORKERS))


def worker_count(workers: int | None) -> int:
    """The processes ``workers`` asks for: itself, or :func:`default_workers` for None."""
    return default_workers() if workers is None else workers


def check_workers(workers: Any, name: str = "workers") -> None:
    """Refuse anything but None or an integer in [1, :data:`MAX_WORKERS`] (one-line :class:`PihimInputError`)."""
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int)
                                or not 1 <= workers <= MAX_WORKERS):
        raise PihimInputError(f"{name} must be None or an integer in [1, {MAX_WORKERS}], got {workers!r}")


def can_fork(workers: int | None, n: int) -> bool:
    """Whether :func:`imap_unordered` would fork for ``n`` pieces and ``workers``."""
    return min(worker_count(workers), n) > 1 and sys.platform.startswith("linux")


def _worker_setup(job: Callable[[int], Any], parent_pid: int, stop_fd: int, mask: set[int]) -> None:
    """Start a forked worker.

    It keeps ``job``; runs compiled kernels without threads (GNU OpenMP does
    not survive ``fork``); leaves Ctrl-C to the parent, which stops the pool,
    and stops the piece it is on when the parent writes a byte to ``stop_fd``
    (:meth:`Started.close`; see :func:`_on_stop`); dies outright on SIGTERM
    (the parent then takes over its pieces); dies with the parent (Linux
    ``PR_SET_PDEATHSIG``), so that a killed run leaves no orphan; writes to
    the real stdout and stderr, not to a progress display's proxies copied
    by the fork; and then takes the parent's signal ``mask`` back (the
    signals were held back since the fork, see :func:`signals_deferred`).
    """
    global _WORKER_JOB, _IN_PIECE, _STOPPED, _RAISED, _AGAIN
    _IN_PIECE = _STOPPED = _RAISED = False  # a worker forked by a worker's piece starts afresh
    _AGAIN = threading.Event()  # not the parent's: another thread may have held its lock at the fork
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(_STOP_SIGNAL, _on_stop)
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass
    if os.getppid() != parent_pid:  # the parent died before the line above took effect
        os._exit(1)
    sys.stdout, sys.stderr = sys.__stdout__, sys.__stderr__
    _WORKER_JOB = job
    from pihim.surfaces import ground

    ground.use_serial_kernels(True)

    def watch() -> None:  # one byte from the parent (this worker holds a write end too: no end of file)
        try:
            os.read(stop_fd, 1)
        except OSError:  # pragma: no cover - the descriptor is this worker's own
            pass
        while True:
            signal.pthread_kill(main, _STOP_SIGNAL)  # a real signal: it also ends a blocking call
            _AGAIN.wait()  # set when the stop was swallowed (_swallowed_stop): signal once more
            _AGAIN.clear()
            time.sleep(_AGAIN_DELAY_S)

    main = threading.main_thread().ident
    sys.unraisablehook = _swallowed_stop
    threading.Thread(target=watch, name="pihim-stop", daemon=True).start()
    signal.pthread_sigmask(signal.SIG_SETMASK, set(mask) - {_STOP_SIGNAL})


#: The signal a worker's own thread sends it when the parent stops the pool.
_STOP_SIGNAL: int = getattr(signal, "SIGUSR1", 10)
#: In a forked worker: whether a piece is being computed, whether the parent stopped the pool, and whether the
#: stop was raised in the piece.
_IN_PIECE = False
_STOPPED = False
_RAISED = False
#: In a forked worker: set when the stop raised in the piece was swallowed; the watcher thread then signals again
#: after :data:`_AGAIN_DELAY_S`.
_AGAIN = threading.Event()
_AGAIN_DELAY_S = 0.01


def _on_stop(signum: int, frame: Any) -> None:  # noqa: ARG001
    """A worker's handler of the parent's stop: end the piece being computed (in KeyboardInterrupt, which goes
    back to the parent as its result) and refuse every later one.

    Outside a piece (waiting for one, or sending a result back through the pool's pipe) it only takes note:
    raising there could leave half a message in the pipe, on which the parent would wait for good. It raises
    once: a second exception could cut short the clean-up of the first (a pool that the piece itself runs) --
    unless the first was swallowed (:func:`_swallowed_stop`).
    """
    global _STOPPED, _RAISED
    _STOPPED = True
    if _IN_PIECE and not _RAISED:
        _RAISED = True
        raise KeyboardInterrupt


def _swallowed_stop(unraisable: Any) -> None:
    """A worker's ``sys.unraisablehook``: the stop raised where Python cannot pass it on is raised again.

    The signal can come while a compiled library calls back into Python
    (numba's cache through llvmlite's ``ctypes`` callbacks); the
    KeyboardInterrupt raised there is only printed ("Exception ignored in
    ...", a traceback beside the parent's one-line message) and the piece
    went on to its end. It is now dropped silently and raised again at the
    next signal, which the watcher thread sends a moment later.
    """
    global _RAISED
    if _STOPPED and isinstance(unraisable.exc_value, KeyboardInterrupt):
        _RAISED = False
        _AGAIN.set()
        return
    sys.__unraisablehook__(unraisable)


@contextlib.contextmanager
def signals_deferred() -> Iterator[set[int]]:
    """Hold Ctrl-C (SIGINT) and SIGTERM back during the block; those that came are then handled as usual.

    Yields the calling thread's signal mask from before the block.

    For steps that must not be cut short: forking workers (a KeyboardInterrupt
    inside ``fork`` or in a worker before its setup breaks the pool or hangs
    the exit), stopping them and removing temporary files. In the main thread
    the Python handlers are swapped for one that takes note (a signal may go
    to any thread); the calling thread's mask holds both signals, so that
    processes forked in the block start with them blocked. An ignored signal
    stays ignored. Elsewhere than in the main thread only the mask applies.
    """
    held = {signal.SIGINT, signal.SIGTERM}
    came: list[int] = []

    def note(signum: int, frame: Any) -> None:  # noqa: ARG001
        came.append(signum)

    previous: dict[int, Any] = {}
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, held | {_STOP_SIGNAL})
    try:
        if threading.current_thread() is threading.main_thread():
            for sig in held:
                handler = signal.getsignal(sig)
                if handler is not signal.SIG_IGN and handler is not None:
                    previous[sig] = signal.signal(sig, note)
        yield set(mask)
    finally:
        # Those still with the kernel came while every thread held them back (threads started in the block
        # inherit the mask); they are handled when the mask goes below.
        pending = signal.sigpending() & held if hasattr(signal, "sigpending") else set()
        for sig, handler in previous.items():  # while the signals are still held back here
            signal.signal(sig, handler)
        for sig in dict.fromkeys([*came, *pending]):
            held_back = getattr(signal.getsignal(sig), "held_back", None)
            if held_back is not None:  # a handler that counts presses (pihim._interrupts.Interrupts)
                held_back()
            if sig not in pending:
                signal.pthread_kill(threading.get_ident(), sig)  # sent again, to this thread
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # each is now handled by its own handler, default or not


def _run_piece(i: int) -> tuple[int, Any]:
    """Piece ``i`` of the worker's job, with its index (results arrive in order of completion)."""
    global _IN_PIECE
    if _WORKER_JOB is None:
        raise RuntimeError("a forked worker started without its job")
    try:
        _IN_PIECE = True
        if _STOPPED:  # a piece queued before the stop: not begun
            raise KeyboardInterrupt
        return i, _WORKER_JOB(i)
    finally:
        _IN_PIECE = False


def imap_unordered(job: Callable[[int], T], n: int, workers: int | None, *,
                   what: str = "pieces") -> Iterator[tuple[int, T]]:
    """``(i, job(i))`` for ``i`` in ``range(n)``, in order of completion.

    Parameters
    ----------
    job : callable
        ``job(i)`` computes piece ``i``; it must not depend on the other
        pieces having run in the same process (each worker runs some of them).
        Its results are pickled back from the workers.
    n : int
        Number of pieces.
    workers : int or None
        Processes; None: one per CPU (at most :data:`DEFAULT_MAX_WORKERS`);
        1 (or fewer than two pieces, or not Linux): this process, in order.
    what : str
        What the pieces are, for the warning below.

    Notes
    -----
    The pieces go to the pool one at a time (their costs may differ). If a
    worker dies (out of memory, a signal), the pieces not done run in this
    process, with a ``RuntimeWarning``: nothing is lost. If the caller
    stops early (an exception, Ctrl-C, SIGTERM turned into an exception, the
    iterator closed), the workers are stopped as :meth:`Started.close` does:
    the pieces they are computing are interrupted. Call it from a
    process whose other threads hold no lock the workers need (numba
    compiling, logging, a progress display refreshing on its own thread):
    ``fork`` copies only the calling thread.
    """
    check_workers(workers)
    if not can_fork(workers, n):
        for i in range(n):
            yield i, job(i)
        return
    yield from Started(job, n, min(worker_count(workers), n), what).as_completed()


def imap(job: Callable[[int], T], n: int, workers: int | None, *, what: str = "pieces") -> Iterator[T]:
    """``job(0), ..., job(n - 1)`` in order, computed as :func:`imap_unordered` does (results that arrive
    early wait here for those before them)."""
    early: dict[int, Any] = {}
    nxt = 0
    for i, result in imap_unordered(job, n, workers, what=what):
        early[i] = result
        while nxt in early:
            yield early.pop(nxt)
            nxt += 1


class Started(Generic[T]):
    """Pieces started in forked workers that work on while this process does something else (:func:`start`).

    :meth:`results` waits for them (a dead worker's pieces then run here,
    with the warning of :func:`imap_unordered`); :meth:`close` stops the
    workers (the pieces being computed are interrupted, those not begun
    dropped). Without workers nothing runs
    until :meth:`results`, which then runs the pieces here, in order.
    """

    def __init__(self, job: Callable[[int], T], n: int, background: int, what: str) -> None:
        if isinstance(background, bool) or not isinstance(background, int) or not 0 <= background <= MAX_WORKERS:
            raise PihimInputError(f"background workers must be an integer in [0, {MAX_WORKERS}], got {background!r}")
        self._job, self._n, self._what = job, n, what
        self._pool: Any = None
        self._futures: list[Any] = []
        self._stop: tuple[int, int] | None = None  # a pipe: a byte written stops the piece a worker is on
        self._workers = 0
        if background == 0 or n == 0 or not sys.platform.startswith("linux"):
            return
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self._stop = os.pipe()
        self._workers = min(background, n)
        _OPEN.add(self)
        gc.freeze()  # as in imap_unordered: the parent's objects out of the collector's sight while workers live
        try:
            with signals_deferred() as mask:  # the workers are forked at the first submit
                self._pool = ProcessPoolExecutor(self._workers, mp_context=multiprocessing.get_context("fork"),
                                                 initializer=_worker_setup,
                                                 initargs=(job, os.getpid(), self._stop[0], mask))
                self._futures = [self._pool.submit(_run_piece, i) for i in range(n)]
        except BaseException:
            self.close()
            raise

    @property
    def running(self) -> bool:
        """Whether workers were started and not yet stopped."""
        return self._pool is not None

    def as_completed(self) -> Iterator[tuple[int, T]]:
        """``(i, job(i))`` in order of completion, then the pieces a dead worker left (run here, with a
        warning); the workers are stopped when it ends (or is closed early)."""
        import queue
        from concurrent.futures.process import BrokenProcessPool

        done: set[int] = set()
        if self._pool is not None:
            try:  # at once: a Ctrl-C before the try left the pool running (then only close_all() stops it)
                # Each future puts itself in a queue when done (in the pool's thread); waiting on the queue holds
                # no lock that Ctrl-C could leave taken (as concurrent.futures.as_completed's clean-up could).
                finished: queue.SimpleQueue[Any] = queue.SimpleQueue()
                for fut in self._futures:
                    fut.add_done_callback(finished.put)
                for _ in range(self._n):
                    i, result = finished.get().result()
                    done.add(i)
                    yield i, result
            except BrokenProcessPool:
                warnings.warn(f"a worker process died; the {self._n - len(done)} remaining {self._what} run in "
                              "this process", RuntimeWarning, stacklevel=3)
            finally:
                self.close()
        for i in range(self._n):
            if i not in done:
                yield i, self._job(i)

    def results(self) -> list[T]:
        """``[job(0), ..., job(n - 1)]``; the workers are stopped when it returns."""
        out: list[Any] = [None] * self._n
        for i, result in self.as_completed():
            out[i] = result
        return out

    def close(self) -> None:
        """Stop the workers: pieces not begun are dropped, and those being computed are interrupted (a worker
        stops between two Python instructions, so a compiled kernel runs to its end); nothing if none were
        started. Ctrl-C and SIGTERM wait until the workers are gone (:func:`signals_deferred`)."""
        with signals_deferred():  # from here on: a Ctrl-C at the wrong moment left the pool running, unclosed
            if self._stop is None:
                return
            pool, self._pool = self._pool, None
            stop, self._stop = self._stop, None
            _OPEN.discard(self)
            try:
                for fut in self._futures:
                    fut.cancel()
                if pool is not None and not all(fut.done() for fut in self._futures):
                    os.write(stop[1], b"x" * self._workers)  # one byte per worker; the pipe holds 64 KiB
                if pool is not None:
                    pool.shutdown(wait=True)
            finally:
                os.close(stop[0])
                os.close(stop[1])
                gc.unfreeze()


#: The pools started and not yet closed (held here until they are: one dropped unclosed still has workers).
_OPEN: set[Started[Any]] = set()


def close_all() -> int:
    """Stop every pool of workers still open (:meth:`Started.close`); returns how many there were.

    For the end of a command: a Ctrl-C that comes while a pool is being
    closed can cut its :meth:`~Started.close` short before the signals are
    held back, leaving workers that compute on (and that the interpreter's
    exit then waits for).
    """
    pools = list(_OPEN)
    for started in pools:
        started.close()
    return len(pools)


def start(job: Callable[[int], T], n: int, background: int, *, what: str = "pieces") -> Started[T]:
    """Start ``job(0), ..., job(n - 1)`` in ``background`` forked workers and return at once (:class:`Started`).

    For work that can go on while this process does something else (the
    facet report's tracing during the route in ``pihim plan``): give it the
    CPUs this process leaves free (one worker, even, is worth forking here;
    0: the pieces run in :meth:`Started.results`, here). Close it in a
    ``finally`` (or collect it) before starting other workers: each worker
    holds a copy of what it touched.
    """
    return Started(job, n, background, what)


def map_pieces(job: Callable[[int], T], n: int, workers: int | None, *, what: str = "pieces") -> list[T]:
    """``[job(0), ..., job(n - 1)]``, computed as :func:`imap_unordered` does."""
    out: list[Any] = [None] * n
    for i, result in imap_unordered(job, n, workers, what=what):
        out[i] = result
    return out
