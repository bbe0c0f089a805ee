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

import gc
import os
import sys
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


def _worker_setup(job: Callable[[int], Any], parent_pid: int) -> None:
    """Start a forked worker.

    It keeps ``job``; runs compiled kernels without threads (GNU OpenMP does
    not survive ``fork``); leaves Ctrl-C to the parent, which stops the pool,
    and dies outright on SIGTERM (the parent then takes over its pieces);
    dies with the parent (Linux ``PR_SET_PDEATHSIG``), so that a killed run
    leaves no orphan; and writes to the real stdout and stderr, not to a
    progress display's proxies copied by the fork.
    """
    import signal

    from pihim.surfaces import ground

    global _WORKER_JOB
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass
    if os.getppid() != parent_pid:  # the parent died before the line above took effect
        os._exit(1)
    sys.stdout, sys.stderr = sys.__stdout__, sys.__stderr__
    _WORKER_JOB = job
    ground.use_serial_kernels(True)


def _run_piece(i: int) -> tuple[int, Any]:
    """Piece ``i`` of the worker's job, with its index (results arrive in order of completion)."""
    if _WORKER_JOB is None:
        raise RuntimeError("a forked worker started without its job")
    return i, _WORKER_JOB(i)


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
    process, with a ``RuntimeWarning``: nothing is lost. Call it from a
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
    workers (pieces not begun are dropped). Without workers nothing runs
    until :meth:`results`, which then runs the pieces here, in order.
    """

    def __init__(self, job: Callable[[int], T], n: int, background: int, what: str) -> None:
        if isinstance(background, bool) or not isinstance(background, int) or not 0 <= background <= MAX_WORKERS:
            raise PihimInputError(f"background workers must be an integer in [0, {MAX_WORKERS}], got {background!r}")
        self._job, self._n, self._what = job, n, what
        self._pool: Any = None
        self._futures: list[Any] = []
        if background == 0 or n == 0 or not sys.platform.startswith("linux"):
            return
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        gc.freeze()  # as in imap_unordered: the parent's objects out of the collector's sight while workers live
        try:
            self._pool = ProcessPoolExecutor(min(background, n), mp_context=multiprocessing.get_context("fork"),
                                             initializer=_worker_setup, initargs=(job, os.getpid()))
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
        from concurrent.futures import as_completed
        from concurrent.futures.process import BrokenProcessPool

        done: set[int] = set()
        if self._pool is not None:
            try:
                for fut in as_completed(self._futures):
                    i, result = fut.result()
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
        """Stop the workers (the pieces they began are finished first, those not begun dropped); nothing if
        none were started."""
        if self._pool is None:
            return
        pool, self._pool = self._pool, None
        try:
            for fut in self._futures:
                fut.cancel()
            pool.shutdown(wait=True)
        finally:
            gc.unfreeze()


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
