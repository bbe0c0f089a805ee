"""The collector's start-up thresholds of the command line (pihim._collector)."""

from __future__ import annotations

import gc
import os
import subprocess
import sys

import pytest

from pihim._collector import STARTUP_THRESHOLDS, relax_during_startup

FOUND = (1234, 5, 6)  # thresholds a test sets first: any process state, CPython's defaults included, is left alone


@pytest.fixture
def collector_restored():
    """The test starts with the thresholds FOUND; whatever it does to them and to the hooks is undone after."""
    thresholds, callbacks = gc.get_threshold(), list(gc.callbacks)
    gc.set_threshold(*FOUND)
    yield
    gc.set_threshold(*thresholds)
    gc.callbacks[:] = callbacks


def test_the_thresholds_are_raised_within_the_window(collector_restored):
    relax_during_startup(window_s=3600.0)
    assert gc.get_threshold() == STARTUP_THRESHOLDS
    gc.collect()  # a collection inside the window changes nothing
    assert gc.get_threshold() == STARTUP_THRESHOLDS


def test_the_first_collection_after_the_window_restores_the_thresholds_once(collector_restored):
    relax_during_startup(window_s=0.0)
    assert gc.get_threshold() == STARTUP_THRESHOLDS
    gc.collect(0)
    assert gc.get_threshold() == FOUND  # those it found, not CPython's defaults
    gc.set_threshold(700, 10, 10)  # set after by the program: later collections leave it
    gc.collect(0)
    assert gc.get_threshold() == (700, 10, 10)


def test_a_hook_after_it_sees_the_whole_collection_that_restores(collector_restored):
    """CPython calls the hooks by index: a hook that removed itself would hide the next one's "stop"."""
    phases = []
    relax_during_startup(window_s=0.0)
    gc.callbacks.append(lambda phase, info: phases.append(phase))
    gc.collect(0)
    assert gc.get_threshold() == FOUND and phases == ["start", "stop"]


def test_restore_puts_the_thresholds_back_at_once_and_only_once(collector_restored):
    callbacks = len(gc.callbacks)
    restore = relax_during_startup(window_s=3600.0)
    assert len(gc.callbacks) == callbacks + 1
    restore()
    assert gc.get_threshold() == FOUND and len(gc.callbacks) == callbacks  # the hook taken out
    gc.set_threshold(700, 10, 10)  # changed after: a second restore leaves it
    restore()
    assert gc.get_threshold() == (700, 10, 10)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork here")
def test_a_forked_worker_gets_the_thresholds_back_at_its_first_collection(collector_restored):
    """A child's CPU clock starts again at zero: it would otherwise keep the raised thresholds for a window of its
    own."""
    relax_during_startup(window_s=3600.0)
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: report its thresholds after one collection, then leave at once
        try:
            before = gc.get_threshold()
            gc.collect(0)
            os.write(write, f"{before} {gc.get_threshold()}".encode())
        finally:
            os._exit(0)
    os.close(write)
    with os.fdopen(read) as pipe:
        report = pipe.read()
    os.waitpid(pid, 0)
    assert report == f"{STARTUP_THRESHOLDS} {FOUND}"
    assert gc.get_threshold() == STARTUP_THRESHOLDS  # the parent's window goes on


def test_a_command_runs_with_the_raised_thresholds_and_its_caller_gets_its_own_back():
    code = ("import gc, sys\n"
            "found = gc.get_threshold()\n"
            "import pihim, pihim.camera, pihim.cli\n"
            "imported = gc.get_threshold()\n"
            "@pihim.cli.app.command('thresholds')\n"
            "def thresholds():\n"
            "    print('command', gc.get_threshold())\n"
            "from pihim.__main__ import run\n"
            "sys.argv = ['pihim', 'thresholds']\n"
            "rc = run()\n"
            "print('found', found, 'imported', imported, 'after', gc.get_threshold(), 'rc', rc)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-300:]
    lines = done.stdout.strip().splitlines()
    assert lines[-2] == f"command {STARTUP_THRESHOLDS}"
    found = lines[-1][len("found "):lines[-1].index(" imported")]
    assert found != str(STARTUP_THRESHOLDS)
    # importing pihim changes nothing, and run() hands the caller its thresholds back
    assert lines[-1] == f"found {found} imported {found} after {found} rc 0"
