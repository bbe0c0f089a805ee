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
    from pihim._collector import relax_during_startup

    restore = relax_during_startup()  # the libraries' long-lived heap is built without the collector walking it
    try:
        return _load_and_run(limit)
    finally:
        restore()  # for a caller in a process that goes on; the script's process ends here


def _load_and_run(limit: int | None) -> int:
    """:func:`run` once the address-space limit is checked: load the command line, run the command."""
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

    from pihim._interrupts import Interrupts, exit_on_signals

    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not where Ctrl-C is ignored (a background job)
        Interrupts().install()
    try:
        status = main()
    except KeyboardInterrupt:  # the first Ctrl-C, come as the command ended
        print("pihim: aborted", file=sys.stderr)
        status = 130
    # The command's files are in place (or removed). What is left is the interpreter's own exit (joining the worker
    # pools' threads, running finalizers), which a signal would only interrupt, with a traceback: from now on one
    # ends the process at once, with the command's status. A pool still open (its close cut short) is closed.
    exit_on_signals(status)
    forked = sys.modules.get("pihim._forked")
    if forked is not None:
        forked.close_all()
    # The interpreter's exit collects garbage over every object the command made, only for the process to end:
    # 3.9 s of a Ctrl-C'd 100,000-heliostat `pihim plan` (4.38 s from Ctrl-C to exit, 0.49 s frozen). Frozen, the
    # objects are left to the operating system; what the commands write is closed and renamed before they return.
    import gc

    gc.freeze()
    return status


if __name__ == "__main__":
    sys.exit(run())
