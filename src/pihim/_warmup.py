"""Compile the demo's slowest kernels in a helper process while the demo plans (a first run only).

pihim's kernels are compiled by numba on their first call and cached on disk
(``cache=True``). A first ``pihim demo`` on a machine spent about 58 s of its
92 s compiling 28 kernels, one after the other on one core (BENCHMARKS.md,
"The first run"). :func:`start` spawns ``python -m pihim._warmup``, which
compiles -- and so caches -- the renderer's kernel (about 15 s) while the
demo plans on the other core, then the least-squares solver of the pose and
canting fits (about 11 s) while the demo renders and makes its polar images,
then the rest of the inspection and the previews on a small frame. When the
demo reaches a kernel the helper has cached, numba loads it instead of
compiling it. Before its first frame and its first inspection the demo waits
for the helper's renderer and solver (:func:`wait_for`: the helper started on
them earlier, so its rest is shorter than the demo's own compilation); any
other kernel the demo reaches first it compiles itself, as without the
helper. Nothing is started when the two slowest kernels are cached already
(every later run), when numba cannot write their cache, when its JIT is
disabled, or when the memory available cannot hold the helper
(:data:`HELPER_BYTES`; ``pihim demo`` asks for it beside the demo's own).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["HELPER_BYTES", "KERNELS", "cached", "compile_kernels", "start", "stop", "wait_for", "writable"]


#: Peak resident size of the helper with an empty cache: 558 MB measured (``/usr/bin/time -v python -m
#: pihim._warmup``, 2026-11-26), with a 25 % margin.
HELPER_BYTES = 700_000_000

#: The kernels the demo waits for: the renderer's and the least-squares solver's (module, name).
KERNELS = {"render": ("pihim.render.kernel", "_kernel"), "solve": ("pihim.inspection._kernels", "solve")}


def _cache(what: str) -> Any:
    """numba's on-disk cache of kernel ``what`` (a key of :data:`KERNELS`), or None without one."""
    import importlib

    module, name = KERNELS[what]
    return getattr(getattr(importlib.import_module(module), name), "_cache", None)


def cached(what: str) -> bool:
    """Whether kernel ``what`` (a key of :data:`KERNELS`) is in numba's cache: its index and a data file.

    numba writes the index before the data file, each whole (a temporary file renamed).
    """
    try:
        index = Path(_cache(what)._cache_file._index_path)
    except AttributeError:  # no cache, or numba's cache internals moved: take it for uncached
        return False
    return index.is_file() and any(index.parent.glob(index.stem + ".*.nbc"))


def writable(what: str) -> bool:
    """Whether numba can write kernel ``what``'s cache (its folder, chosen by numba as writable, is)."""
    try:
        folder = _cache(what)._cache_path
    except AttributeError:
        return False
    return os.path.isdir(folder) and os.access(folder, os.W_OK)


def start() -> subprocess.Popen | None:
    """Spawn the helper (:func:`compile_kernels` in ``python -m pihim._warmup``), or None when not needed."""
    from numba.core import config

    from pihim._resources import available_memory

    # a helper whose kernels cannot be cached would only make the demo wait for nothing
    if config.DISABLE_JIT or all(cached(k) for k in KERNELS) or not all(writable(k) for k in KERNELS):
        return None
    avail = available_memory()
    if avail is not None and avail < HELPER_BYTES:
        return None
    try:
        return subprocess.Popen([sys.executable, "-m", "pihim._warmup"], stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:
        return None


def wait_for(proc: subprocess.Popen | None, what: str, timeout_s: float = 60.0) -> None:
    """Wait until the helper has cached kernel ``what``, has ended, or ``timeout_s`` passed.

    The helper started on the kernel before the demo needs it, so the rest of
    its compilation is shorter than the demo's own would be.
    """
    if proc is None:
        return
    deadline = time.monotonic() + timeout_s
    while proc.poll() is None and not cached(what) and time.monotonic() < deadline:
        time.sleep(0.1)


def stop(proc: subprocess.Popen | None) -> None:
    """End the helper if it still runs (what it cached stays cached) and reap it."""
    if proc is None:
        return
    if proc.poll() is None:
        proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def compile_kernels(width_px: int = 612, height_px: int = 512) -> None:
    """Call the demo's compiled kernels, slowest and earliest needed first, on small inputs.

    The arguments' types are those of the demo's calls (a small frame of the
    demo's kind), so the specializations compiled and cached are the ones the
    demo loads.
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

    field = nsttf_like_field()
    # 1. the renderer, which the demo needs first, once it has planned: a small frame looking down on a
    #    heliostat (a pair's pose would plan, and compile the planner's kernels before the renderer's)
    centre = np.asarray(field.pivots, float)[field.index("8E3")]
    simulate_frame(field, DEMO_TIME, camera=CameraModel(width_px=64, height_px=48),
                   pose_request=LookAtPose(tuple(centre + [0.0, -8.0, 25.0]), tuple(centre)), seed=0)
    # 2. the solver of the pose and canting fits (one specialization for every kind of problem)
    m = 4
    pts = np.column_stack([np.linspace(-1.0, 1.0, 3 * m), np.zeros(3 * m), np.full(3 * m, 10.0)])
    prob = _kernels.problem(_kernels.POINT_TO_LINE, np.eye(3), np.zeros(3), pts, _kernels.camera_vector(CameraModel()),
                            q=np.zeros((m, 2)), gate=3.0)
    _kernels.solve(prob, np.zeros(6), m, np.ones(6), 2, True, 1.0)
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


if __name__ == "__main__":  # pragma: no cover - the helper process
    compile_kernels()
