"""The garbage collector's thresholds while a command-line process starts.

A ``pihim`` command builds, in its first second, a heap of 150,000-220,000
objects the collector tracks (``pihim plan``, ``pihim ground``) that live as
long as the process: the modules of numpy, SciPy,
matplotlib and typer, numba's typing and lowering registries (loaded with
the first compiled kernel), the command's own tables. None of it is garbage,
but with CPython's default thresholds (700, 10, 10) the collector walks the
growing heap in full three times and its young generations some 400 times:
0.17 s of CPU in collections in one ``pihim ground --resolution 5`` run
(``gc.callbacks`` timing, 2026-11-28). With the thresholds below, that
command's imports took 0.68-0.72 s of CPU against 0.91-0.93 s, those of
``pihim polar`` on one frame 0.48-0.50 s against 0.57-0.61 s
(``benchmarks/bench_cli.py --startup-only``, twice each, alternating, same
hour; more than the collections' own time in the one run timed, which
differs by 10-20 % from run to run with the host's speed).

:func:`relax_during_startup` raises the thresholds to (200,000, 30, 30) for a
window of CPU time at the start of the process, then puts back those it
found. The young generation is still collected, every 200,000 allocations
instead of 700, so cycles of garbage are still freed; a command that runs
longer than the window runs under the usual thresholds afterwards. mypy sets
the same thresholds for its whole run ("otherwise we can spend a large
fraction of cpu in gc", ``mypy/build.py``).

The window is checked when a collection ends (a ``gc.callbacks`` hook), so
the thresholds come back at the first collection after it; a worker forked
by the command gets them back at its own first collection. Only the command
line calls this; a program importing pihim keeps its own collector settings.
"""

from __future__ import annotations

import gc
import os
import sys
import time
from collections.abc import Callable
from typing import Any

#: The collector's thresholds during the start-up window (generation 0, 1, 2).
STARTUP_THRESHOLDS = (200_000, 30, 30)
#: CPU seconds of the process after which the thresholds it had are restored (the imports of the slowest command,
#: ``pihim ground``, take 0.7-0.9 s of CPU; its whole run at the default resolution about 2 s).
STARTUP_WINDOW_S = 2.0


def relax_during_startup(window_s: float = STARTUP_WINDOW_S,
                         thresholds: tuple[int, int, int] = STARTUP_THRESHOLDS) -> Callable[[], None]:
    """Raise the collector's thresholds until the process has used ``window_s`` seconds of CPU.

    Parameters
    ----------
    window_s : float
        CPU time of the process (``time.process_time``, all threads), s, from which on the thresholds in force
        before the call are restored, at the end of the next collection. A process forked meanwhile (a pool's
        worker) gets them back at the end of its first collection: its CPU clock starts again at zero.
    thresholds : tuple of int
        The thresholds of generations 0, 1 and 2 meanwhile (:func:`gc.set_threshold`).

    Returns
    -------
    callable
        Restores the thresholds found at once, if the hook has not yet, and takes the hook out of
        :data:`gc.callbacks`; for a caller that returns to a program that goes on (``pihim.__main__.run``). Call
        it outside a collection.

    Notes
    -----
    Nothing is changed on an interpreter other than CPython (whose collector these thresholds describe). The hook
    never removes itself: CPython calls the hooks by their index in :data:`gc.callbacks`, so a hook that removed
    itself during a collection would hide the next hook from that collection's end (a timing hook would see its
    start alone); once due it only restores the thresholds, once, and stays in the list, doing nothing.
    """
    if sys.implementation.name != "cpython":
        return lambda: None
    before = gc.get_threshold()
    deadline = time.process_time() + window_s
    pid = os.getpid()
    done = False

    def restore_when_due(phase: str, info: dict[str, Any]) -> None:
        nonlocal done
        if not done and phase == "stop" and (time.process_time() >= deadline or os.getpid() != pid):
            done = True
            gc.set_threshold(*before)

    def restore() -> None:
        nonlocal done
        if not done:
            done = True
            gc.set_threshold(*before)
        if restore_when_due in gc.callbacks:
            gc.callbacks.remove(restore_when_due)

    gc.set_threshold(*thresholds)
    gc.callbacks.append(restore_when_due)
    return restore
