"""Ctrl-C in the ``pihim`` process: one clean stop however many times it is pressed, and a way out of a stuck one.

Installed by :func:`pihim.__main__.run` (the process only: :func:`pihim.cli.main`
called in another program keeps that program's handler). Standard library only:
it is loaded before any command.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

#: Ctrl-C pressed again within this many seconds of the first one is taken for the same request.
REPEAT_S = 1.0
#: A stop swallowed where Python could not raise it is raised again this many seconds later.
AGAIN_S = 0.01


def flush_and_exit(status: int) -> None:
    """End the process at once with ``status``: what was printed is flushed, and a terminal's cursor (hidden by
    a progress bar) shown again."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # noqa: BLE001, S110 - a closed pipe, or a write this interrupted: nothing more to say
            pass
    try:
        if os.isatty(2):
            os.write(2, b"\x1b[?25h")
    except OSError:
        pass
    os._exit(status)


class Interrupts:
    """The ``pihim`` process's Ctrl-C (SIGINT) handler.

    The first Ctrl-C raises KeyboardInterrupt, as Python's own handler does:
    the command stops its workers, removes its temporaries and the folders
    it made, and exits with status 130. People press it two or three times;
    with Python's handler each later press interrupted that clean-up --
    "Exception ignored" tracebacks under the one-line message, temporaries
    left, and in 2 of 90 runs of a stress test a process that waited for
    good on workers no longer told to stop. Here, presses that come within
    :data:`REPEAT_S` of the first are the same request, and so are those
    held back by :func:`pihim._forked.signals_deferred` while the clean-up
    stopped workers or removed files (:meth:`held_back`); a press after that
    ends the process at once (status 130; its workers die with it,
    ``PR_SET_PDEATHSIG``; the temporaries it was writing are removed by the
    next run writing there).

    A KeyboardInterrupt raised while a compiled library calls back into
    Python is swallowed there (printed as "Exception ignored ...") and the
    command went on; :meth:`install` hooks ``sys.unraisablehook`` so that
    it is raised again instead (:meth:`swallowed`).
    """

    def __init__(self, clock: Callable[[], float] | None = None,
                 stop: Callable[[int], None] = flush_and_exit) -> None:
        self._clock = time.monotonic if clock is None else clock
        self._stop = stop
        self._held = False
        self.first: float | None = None

    def held_back(self) -> None:
        """The next signal handled came during a step that must not be cut short, and was held back until now.

        After the first Ctrl-C that step is its clean-up at work (however
        long it took: a press cannot even be noticed during it, let alone
        timed), so the press is the same request.
        """
        self._held = True

    def __call__(self, signum: int, frame: Any) -> None:  # noqa: ARG002
        now, held, self._held = self._clock(), self._held, False
        if self.first is None:
            self.first = now
            raise KeyboardInterrupt
        if not held and now - self.first >= REPEAT_S:
            self._stop(130)

    def swallowed(self) -> None:
        """The KeyboardInterrupt raised was swallowed: raise it again at the next signal, sent in a moment."""
        self.first = None
        main = threading.main_thread().ident
        if main is not None:
            timer = threading.Timer(AGAIN_S, signal.pthread_kill, (main, signal.SIGINT))
            timer.daemon = True
            timer.start()

    def install(self) -> None:
        """Make this the SIGINT handler (main thread) and hook ``sys.unraisablehook`` for swallowed stops."""
        signal.signal(signal.SIGINT, self)
        previous = sys.unraisablehook

        def hook(unraisable: Any) -> None:
            if (isinstance(unraisable.exc_value, KeyboardInterrupt) and self.first is not None
                    and signal.getsignal(signal.SIGINT) is self):
                self.swallowed()
                return
            previous(unraisable)

        sys.unraisablehook = hook


def exit_on_signals(status: int) -> None:
    """From now on SIGINT and SIGTERM end the process at once with ``status`` (those ignored stay ignored)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, lambda signum, frame: flush_and_exit(status))
