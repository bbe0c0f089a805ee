"""Compile the demo's slowest kernels in a helper process while the demo plans (a first run only).

pihim's kernels are compiled by numba on their first call and cached on disk
(``cache=True``). A first ``pihim demo`` on a machine spent about 58 s of its
92 s compiling 28 kernels, one after the other on one core (BENCHMARKS.md,
"The first run"). :func:`start` spawns ``python -m pihim._warmup``, which
compiles -- and so caches -- the renderer's kernel (about 15 s) while the
demo plans on the other core, then the least-squares solver of the pose and
canting fits (about 11 s) while the demo renders and makes its polar images,
then the rest of the inspection and the previews on a small frame; it
reports each stage on its standard output. When the demo reaches a kernel
the helper has cached, numba loads it instead of compiling it. Before its
first frame and its first inspection the demo waits for the helper's report
of the renderer and of the solver (:func:`wait_for`: the helper started on
them earlier, so its rest is shorter than the demo's own compilation); any
other kernel the demo reaches first it compiles itself, as without the
helper. The helper ends when the demo does (:func:`stop`), and at once
when the demo's process is gone however it ended, killed included: it
watches the pipe the demo holds open on its standard input, and leaves when
that pipe reaches its end (numba writes each cache file whole, to a
temporary name it then renames, so a kernel is cached or not, never half).

Nothing is started when the two slowest kernels are in numba's cache already
(every later run: numba's own index, which it invalidates when the source or
numba changes), when numba cannot write their cache or its JIT is disabled,
on a single CPU (the helper's work would only add to the demo's), or when the
memory available cannot hold the helper (:data:`HELPER_BYTES`; ``pihim
demo`` asks for it beside the demo's own).
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["HELPER_BYTES", "KERNELS", "Helper", "cached", "compile_kernels", "start", "stop", "wait_for",
           "writable"]

#: Peak resident size of the helper with an empty cache: 558 MB measured (``/usr/bin/time -v python -m
#: pihim._warmup``, 2026-11-26), with a 25 % margin.
HELPER_BYTES = 700_000_000

#: The kernels the demo waits for, in the helper's order: the renderer's and the least-squares solver's
#: (module, name); the helper prints each key once that kernel is compiled (and cached).
KERNELS = {"render": ("pihim.render.kernel", "_kernel"), "solve": ("pihim.inspection._kernels", "solve")}


@dataclass(eq=False)
class Helper:
    """A running helper: its process and, per key of :data:`KERNELS`, whether it has reported it.

    A thread reads the helper's output from the start (:meth:`listen`).
    """

    proc: subprocess.Popen
    reported: dict[str, threading.Event] = field(default_factory=lambda: {k: threading.Event() for k in KERNELS})
    listener: threading.Thread | None = None

    def __post_init__(self) -> None:
        self.listener = threading.Thread(target=self.listen, name="pihim-warmup-listener", daemon=True)
        self.listener.start()

    def listen(self) -> None:
        """Read the helper's reports until its output ends; then nothing more is waited for."""
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            event = self.reported.get(line.strip())
            if event is not None:
                event.set()
        for event in self.reported.values():  # ended (done, failed or killed)
            event.set()


def _cache(what: str) -> Any:
    """numba's on-disk cache of kernel ``what`` (a key of :data:`KERNELS`), or None without one."""
    import importlib

    module, name = KERNELS[what]
    return getattr(getattr(importlib.import_module(module), name), "_cache", None)


def cached(what: str) -> bool:
    """Whether kernel ``what`` has a valid entry in numba's cache.

    numba's index (which it empties when the kernel's source file or numba's
    version changed) lists at least one entry whose data file exists.
    """
    cache = _cache(what)
    try:
        index = cache._cache_file._load_index()
        folder = Path(cache._cache_path)
    except (AttributeError, OSError):  # no cache, or numba's cache internals moved: take it for uncached
        return False
    return any((folder / name).is_file() for name in index.values())


def writable(what: str) -> bool:
    """Whether the folder numba chose for kernel ``what``'s cache is (still) writable."""
    try:
        folder = _cache(what)._cache_path
    except AttributeError:
        return False
    return os.path.isdir(folder) and os.access(folder, os.W_OK)


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def start() -> Helper | None:
    """Spawn the helper (:func:`compile_kernels` in ``python -m pihim._warmup``), or None when not needed."""
    from numba.core import config

    from pihim._resources import available_memory

    # a helper whose kernels cannot be cached would only make the demo wait for nothing
    if config.DISABLE_JIT or _cpus() < 2 or all(cached(k) for k in KERNELS) or not all(writable(k) for k in KERNELS):
        return None
    avail = available_memory()
    if avail is not None and avail < HELPER_BYTES:
        return None
    # the helper must import this very pihim (and so compile into this one's cache), whatever its working folder
    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])])}
    try:
        # its standard input: a pipe only this process holds open, whose end tells the helper the demo is gone
        proc = subprocess.Popen([sys.executable, "-m", "pihim._warmup", str(os.getpid())], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
    except OSError:
        return None
    return Helper(proc)


def wait_for(helper: Helper | None, what: str, timeout_s: float = 60.0) -> None:
    """Wait until the helper has reported kernel ``what``, has ended, or ``timeout_s`` passed."""
    if helper is not None:
        helper.reported[what].wait(timeout_s)


def stop(helper: Helper | None) -> None:
    """End the helper if it still runs (what it cached stays cached) and reap it."""
    if helper is None:
        return
    proc = helper.proc
    if proc.stdin is not None:
        proc.stdin.close()  # the helper's watch ends it at the pipe's end; SIGTERM too, should it not be watching
    if proc.poll() is None:
        proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    if helper.listener is not None:
        helper.listener.join(timeout=5)  # its output has ended
    if proc.stdout is not None:
        proc.stdout.close()


def compile_kernels(width_px: int = 612, height_px: int = 512, report: Any = None) -> None:
    """Call the demo's compiled kernels, slowest and earliest needed first, on small inputs.

    The arguments' types are those of the demo's calls (a small frame of the
    demo's kind), so the specializations compiled and cached are the ones the
    demo loads. ``report(stage)`` (optional) is called after each stage:
    the keys of :data:`KERNELS`, then ``"rest"``; it may end the process.
    """
    import tempfile

    import numpy as np

    from pihim.camera import CameraModel, polar_image
    from pihim.demo import DEMO_TIME, _previews
    from pihim.errors import PihimInputError
    from pihim.field import nsttf_like_field
    from pihim.inspection import _kernels
    from pihim.inspection.edges import edge_maps
    from pihim.inspection.pipeline import inspect_frame, sensor_settings
    from pihim.render.simulate import LookAtPose, PairPose, simulate_frame

    say = report or (lambda stage: None)
    field = nsttf_like_field()
    # 1. the renderer, which the demo needs first, once it has planned: a small frame looking down on a
    #    heliostat (a pair's pose would plan, and compile the planner's kernels before the renderer's)
    centre = np.asarray(field.pivots, float)[field.index("8E3")]
    simulate_frame(field, DEMO_TIME, camera=CameraModel(width_px=64, height_px=48),
                   pose_request=LookAtPose(tuple(centre + [0.0, -8.0, 25.0]), tuple(centre)), seed=0)
    say("render")
    # 2. the solver of the pose and canting fits (one specialization for every kind of problem)
    m = 4
    pts = np.column_stack([np.linspace(-1.0, 1.0, 3 * m), np.zeros(3 * m), np.full(3 * m, 10.0)])
    prob = _kernels.problem(_kernels.POINT_TO_LINE, np.eye(3), np.zeros(3), pts, _kernels.camera_vector(CameraModel()),
                            q=np.zeros((m, 2)), gate=3.0)
    _kernels.solve(prob, np.zeros(6), m, np.ones(6), 2, True, 1.0)
    say("solve")
    # 3. the rest of the inspection and the demo's previews, on a frame of a demo pair
    sim = simulate_frame(field, DEMO_TIME, camera=CameraModel(width_px=width_px, height_px=height_px),
                         pose_request=PairPose("8E3", "7E3"), canting_sigma_mrad=3.0, gps_sigma_m=0.1,
                         attitude_sigma_deg=0.1, seed=0)
    try:
        inspect_frame(sim.raw, sim.log, field)
    except PihimInputError:
        pass
    sensor = sensor_settings(sim.log)
    pim = polar_image(sim.raw, layout=sensor["layout"], analyser=sensor["analyser"], demosaic="full",
                      dark_level=sensor["dark_level"], bit_depth=sensor["bit_depth"])
    with tempfile.TemporaryDirectory(prefix="pihim-warmup-") as tmp:
        _previews(Path(tmp), pim, edge_maps(pim.s0, pim.dolp, pim.aop_deg, "canny"))
    say("rest")


def _leave_at_end_of_input() -> None:  # pragma: no cover - the helper process
    """Block until standard input ends (the demo closed it or is gone), then end this process at once."""
    try:
        while sys.stdin.buffer.read(4096):
            pass
    except (OSError, ValueError):
        pass
    os._exit(0)


def _watching_a_pipe() -> bool:
    """Whether standard input is a pipe (as :func:`start` makes it), not a terminal, a file or closed."""
    import stat

    try:
        return stat.S_ISFIFO(os.fstat(0).st_mode) and sys.stdin is not None
    except OSError:
        return False


def _main(argv: list[str]) -> None:  # pragma: no cover - the helper process
    parent = int(argv[0]) if argv else None
    if parent is not None and os.getppid() != parent:  # started by a demo that is gone already
        return
    if parent is not None and _watching_a_pipe():  # the demo's pipe (:func:`start`): leave when it closes
        threading.Thread(target=_leave_at_end_of_input, name="pihim-warmup-watch", daemon=True).start()

    def report(stage: str) -> None:
        print(stage, flush=True)
        if parent is not None and os.getppid() != parent:  # the demo is gone (when not watching its pipe)
            sys.exit(0)

    compile_kernels(report=report)


if __name__ == "__main__":  # pragma: no cover - the helper process
    _main(sys.argv[1:])
