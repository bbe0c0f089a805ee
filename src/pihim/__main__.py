"""``python -m pihim`` (and the ``pihim`` script) runs the command line.

The command line needs numpy, SciPy, OpenCV, numba and matplotlib; loading
them can fail before any command runs -- under a small address-space limit
(``ulimit -v``) a shared library does not map ("failed to map segment") or a
thread pool cannot start, and some libraries abort the process outright
(``std::bad_alloc``). :func:`run` therefore refuses a limit below
:data:`START_BYTES` before loading anything, and turns a failure to load into
one line and an exit status instead of a traceback: 2 when an address-space
limit is set (the limit is too small, like a request larger than the
memory), else 1 (a broken installation).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

#: Address space the command line takes once its libraries are loaded (``VmSize`` after ``import pihim.cli``:
#: 1.05 GB on a 2-core Linux machine, thread pools included; with 0.92 GB a library aborted, with 1.02 GB the
#: commands started).
START_BYTES = 1_000_000_000


def _address_space_limit() -> int | None:
    """The soft ``RLIMIT_AS`` in bytes, or None without one."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, OSError, ValueError):
        return None
    return None if soft == resource.RLIM_INFINITY or soft < 0 else int(soft)


def run() -> int:
    """Load the command line and run it; returns the exit status."""
    limit = _address_space_limit()
    if limit is not None and limit < START_BYTES:
        print(f"pihim: error: the address-space limit of {limit / 1e9:.3g} GB (ulimit -v {limit // 1024}) is "
              f"below the {START_BYTES / 1e9:.3g} GB pihim needs to load its libraries", file=sys.stderr)
        return 2
    # numpy's and SciPy's OpenBLAS each start a pool of threads at import that spin before they sleep (0.06 s of
    # CPU each, start-up no command needs: pihim's heavy kernels are numba's and OpenCV's, its matrix products
    # small). A command-line process only; a value set by the user wins.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    try:
        from pihim.cli import main
    except (ImportError, OSError, MemoryError, RecursionError, KeyboardInterrupt) as exc:
        # KeyboardInterrupt: seen under a small limit after OpenBLAS failed to start its threads
        text = " ".join(str(exc).split()) or type(exc).__name__
        if limit is not None:
            print(f"pihim: error: cannot load its libraries under the address-space limit of {limit / 1e9:.3g} GB "
                  f"(ulimit -v {limit // 1024}) ({type(exc).__name__}: {text})", file=sys.stderr)
            return 2
        if isinstance(exc, KeyboardInterrupt):
            print("pihim: aborted", file=sys.stderr)
            return 130
        print(f"pihim: error: cannot load its libraries ({type(exc).__name__}: {text}); reinstall pihim",
              file=sys.stderr)
        return 1
    import signal

    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not where Ctrl-C is ignored (a background job)
        signal.signal(signal.SIGINT, Interrupts())
    try:
        status = main()
    except KeyboardInterrupt:  # the first Ctrl-C, come as the command ended
        print("pihim: aborted", file=sys.stderr)
        status = 130
    _finish(status)
    return status


#: Ctrl-C pressed again within this many seconds of the first one is taken for the same request.
REPEAT_S = 1.0


def _flush_and_exit(status: int) -> None:
    """End the process at once with ``status`` (what was printed is flushed first)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # noqa: BLE001, S110 - a closed pipe, or a write this interrupted: nothing more to say
            pass
    os._exit(status)


class Interrupts:
    """The ``pihim`` process's Ctrl-C (SIGINT) handler.

    The first Ctrl-C raises KeyboardInterrupt, as Python's own handler does:
    the command stops its workers, removes its temporaries and the folders
    it made, and exits with status 130. People press it two or three times;
    before, each later press interrupted that clean-up -- "Exception ignored"
    tracebacks under the one-line message, temporaries left, and in 2 of 90
    runs of a stress test a process that waited for good on workers no
    longer told to stop. Presses within :data:`REPEAT_S` of the first are
    now taken for the same request; one after that ends the process at once
    (status 130; its workers die with it, ``PR_SET_PDEATHSIG``; temporaries
    it was writing are removed by the next run writing there).
    """

    def __init__(self, clock: Callable[[], float] | None = None,
                 stop: Callable[[int], None] = _flush_and_exit) -> None:
        import time

        self._clock = time.monotonic if clock is None else clock
        self._stop = stop
        self.first: float | None = None

    def __call__(self, signum: int, frame: object) -> None:  # noqa: ARG002
        now = self._clock()
        if self.first is None:
            self.first = now
            raise KeyboardInterrupt
        if now - self.first >= REPEAT_S:
            self._stop(130)


def _finish(status: int) -> None:
    """After the command: stop any pool of workers left open; a Ctrl-C or SIGTERM from now on exits at once.

    The command's files are in place (or removed) when it returns; what is
    left is the interpreter's own exit (joining the worker pools' threads,
    running finalizers), which a signal would only interrupt, with a
    traceback. It now ends the process with the command's exit status.
    """
    import signal

    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not signal.SIG_IGN:  # a job started with Ctrl-C ignored keeps ignoring it
            signal.signal(sig, lambda signum, frame: _flush_and_exit(status))
    forked = sys.modules.get("pihim._forked")
    if forked is not None:
        forked.close_all()


if __name__ == "__main__":
    sys.exit(run())
