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
    the stop is raised again 10 ms later (a timer, SIGALRM), and again, until it lands
    (:meth:`swallowed`). Presses of the user's meanwhile follow the rule
    above: one a second after the first ends the process, so that a long
    C call that keeps calling back cannot hold the process for good.
    """

    def __init__(self, clock: Callable[[], float] | None = None,
                 stop: Callable[[int], None] = flush_and_exit) -> None:
        self._clock = time.monotonic if clock is None else clock
        self._stop = stop
        self._held = False  # the next signal was held back (held_back)
        self._raised: BaseException | None = None  # the stop raised, to know it in the hook
        self._owed = False  # that stop was swallowed: the next signal sent by the re-raiser raises it again
        self._resent = False  # the next signal is the timer's (raising a swallowed stop again), not a press
        self._in_hook = False
        self.first: float | None = None

    def held_back(self) -> None:
        """The next signal handled came during a step that must not be cut short, and was held back until now.

        After the first Ctrl-C that step is its clean-up at work (however
        long it took: a press cannot even be noticed during it, let alone
        timed), so the press is the same request.
        """
        self._held = True

    def __call__(self, signum: int, frame: Any) -> None:  # noqa: ARG002
        now, held, resent = self._clock(), self._held, self._resent
        self._held = self._resent = False
        if self._in_hook:  # the hook is noting a swallowed stop: raised again a moment later
            self._again()
            return
        if self.first is None or (resent and self._owed):
            self.first = now if self.first is None else self.first
            self._owed = False
            self._raised = KeyboardInterrupt()
            raise self._raised
        if not resent and not held and now - self.first >= REPEAT_S:
            self._stop(130)

    def swallowed(self) -> None:
        """The stop raised was swallowed: it is raised again :data:`AGAIN_S` later (:meth:`_again`)."""
        self._in_hook = True
        try:
            self._owed = True
            self._again()
        finally:
            self._in_hook = False

    def _again(self) -> None:
        """Send SIGINT to the main thread again in :data:`AGAIN_S`: a one-shot timer (SIGALRM, see
        :meth:`install`), so that nothing here blocks or raises (in the hook, an exception is only printed)."""
        signal.setitimer(signal.ITIMER_REAL, AGAIN_S)

    def _resend(self, signum: int, frame: Any) -> None:  # noqa: ARG002
        """SIGALRM's handler: the timer of :meth:`_again` is up."""
        self._resent = True
        signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)  # type: ignore[arg-type]

    def install(self) -> None:
        """Make this the SIGINT handler, hook ``sys.unraisablehook`` for swallowed stops, and take SIGALRM for
        raising them again (main thread only; the ``pihim`` process uses no other timer)."""
        signal.signal(signal.SIGINT, self)
        signal.signal(signal.SIGALRM, self._resend)
        previous = sys.unraisablehook

        def hook(unraisable: Any) -> None:
            if self._raised is not None and unraisable.exc_value is self._raised:
                self.swallowed()
                return
            previous(unraisable)

        sys.unraisablehook = hook


def exit_on_signals(status: int) -> None:
    """From now on SIGINT and SIGTERM end the process at once with ``status`` (those ignored stay ignored)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, lambda signum, frame: flush_and_exit(status))
