"""The collector's start-up thresholds of the command line (pihim._collector)."""

from __future__ import annotations

import gc
import subprocess
import sys

import pytest

from pihim._collector import STARTUP_THRESHOLDS, relax_during_startup


@pytest.fixture
def collector_restored():
    """Whatever a test does to the collector's thresholds and callbacks is undone afterwards."""
    thresholds, callbacks = gc.get_threshold(), list(gc.callbacks)
    yield thresholds
    gc.set_threshold(*thresholds)
    gc.callbacks[:] = callbacks


def test_the_thresholds_are_raised_within_the_window(collector_restored):
    relax_during_startup(window_s=3600.0)
    assert gc.get_threshold() == STARTUP_THRESHOLDS != collector_restored
    gc.collect()  # a collection inside the window changes nothing
    assert gc.get_threshold() == STARTUP_THRESHOLDS


def test_the_first_collection_after_the_window_restores_the_thresholds(collector_restored):
    gc.set_threshold(1234, 5, 6)
    callbacks = len(gc.callbacks)
    relax_during_startup(window_s=0.0)
    assert gc.get_threshold() == STARTUP_THRESHOLDS
    gc.collect(0)
    assert gc.get_threshold() == (1234, 5, 6)  # those it found, not CPython's defaults
    assert len(gc.callbacks) == callbacks  # and its hook is gone


def test_the_command_line_starts_with_the_raised_thresholds_and_a_library_user_keeps_his():
    code = ("import atexit, gc, sys; import pihim, pihim.camera; before = gc.get_threshold(); "
            "atexit.register(lambda: print(before, gc.get_threshold())); "
            "from pihim.__main__ import run; sys.argv = ['pihim', '--help']; sys.exit(run())")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-300:]
    library, command_line = done.stdout.strip().splitlines()[-1].split(") (")
    assert library + ")" == str(gc.get_threshold())  # importing pihim changes nothing
    assert "(" + command_line == str(STARTUP_THRESHOLDS)  # `pihim --help` ends well inside the window
