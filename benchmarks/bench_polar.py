"""Speed benchmark: raw 2448x2048 DoFP frames -> S0, DoLP and AoP, measured as users run it.

Every row goes through the public entry point with its validation
(:func:`pihim.camera.pipeline.polar_image`), on a rotating set of
:data:`N_FRAMES` distinct 12-bit frames (160 MB, five times the 32 MB L3
cache, so no call finds its input in cache), with freshly allocated outputs
(the operating system zeroes new pages) and, where the API offers it, with
preallocated ones (``out=``). Beside each row's wall time: its CPU time
(all threads of the process), the load on the machine, the bytes it must
move (input read plus outputs written), and the floor those bytes set at
the copy bandwidth measured in the same run (:func:`_harness.memory_bandwidth`),
as a ratio. Anchors, like for like: the plain numpy super-pixel route
(float32, same resolution as pihim's super-pixel route) and polanalyser's
bilinear route in float32 (same resolution and dtype as pihim's full
route); polanalyser's float64 default is shown too.

Each row is timed in a process of its own, started for it, which loads the
frames from ``.npy`` files (``numpy.load`` reads into the new array: no
large temporary freed): the state a user's process is in. In one process shared by all rows, a
large block freed before a row (building the frames frees 20 MB arrays;
polanalyser's rows free larger ones) raises glibc's mmap and trim
thresholds, and a row's freed outputs then come back to its next call
without a page fault -- buffer reuse, which a user's process calling
``polar_image`` does not get (measured: 0 page faults per super-pixel
call after a 20 MB array freed, about 2,800 in a fresh process, before
``polar_image`` allocated its outputs as one block). Each row reports its
page faults per call. A user's process may also get its outputs back from
the allocator: ``pihim_superpixel_new_pages`` forces new pages on every
call (the worst case; its median is held to the 10 ms target as well).

First calls are measured in fresh processes: with the numba disk cache as
a user has it after one run (warm) and with an empty cache
(``NUMBA_CACHE_DIR`` set to an empty folder: the compile a first install
pays once).

Run ``python benchmarks/run.py --only bench_polar`` or this file directly;
``--quick`` takes fewer calls and skips the cold compiles.
"""


from __future__ import annotations

import argparse
import importlib.metadata
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numba
import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from pihim._fastmath import atan2_f32
from pihim.camera import _kernels
from pihim.camera.pipeline import PolarImage, polar_image
from pihim.polarimetry.stokes import aop_difference_deg, stokes_from_dolp_aop
from pihim.render.mosaic import mosaic_from_stokes

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness

try:  # optional dependency of the benchmark only (extra "bench")
    import polanalyser as pa
except ImportError:  # pragma: no cover - depends on the environment
    pa = None

#: Sensor size of the Sony IMX250MZR, (rows, columns) = 2048 x 2448 (W x H: 2448 x 2048).
FRAME_SHAPE: tuple[int, int] = (2048, 2448)
BIT_DEPTH = 12
DEFAULT_SEED = 20261122
COUNTS = harness.Counts(repeat=32, warmup=4, quick_repeat=8, quick_warmup=2)
RESULTS_PATH = Path(__file__).resolve().parent / "results" / "polar.json"

ANCHOR = "numpy"
POLANALYSER = "polanalyser"
NOT_AVAILABLE = "n/a (not available)"

#: Largest differences from the numpy anchor allowed for the super-pixel
#: routes, on pixels valid in both (atan2_f32 is accurate to 1e-4 deg).
AGREEMENT_TOLERANCE = {"s0": 1e-3, "dolp": 1e-5, "aop_deg": 1e-2}
#: AoP is compared with the anchor only where the anchor's DoLP reaches this.
AOP_MIN_DOLP = 1e-3
#: Uniform-field check: the field, and the DoLP/AoP errors allowed away from borders.
UNIFORM_FIELD = {"s0": 4000.0, "dolp": 0.4, "aop_deg": (30.0, 120.0)}
UNIFORM_TOLERANCE = {"dolp": 2e-3, "aop_deg": 0.2}
#: Share of the CPUs used by other processes above which a timing counts as
#: disturbed: the report warns, and ``wait_quiet`` retries it.
BUSY_WARNING = harness.BUSY_WARNING

Outputs = tuple[NDArray[Any], NDArray[Any], NDArray[Any]]


# ---------------------------------------------------------------------------
# The test frame
# ---------------------------------------------------------------------------
def _smooth_field(rng: np.random.Generator, shape: tuple[int, int], cells: tuple[int, int]) -> NDArray[np.float64]:
    """Zero-mean, unit-variance random field, smooth on the scale of ``shape / cells``."""
    coarse = rng.standard_normal(cells).astype(np.float32)
    fine = cv2.resize(coarse, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC).astype(np.float64)
    return (fine - fine.mean()) / fine.std()


def synthetic_scene(
    shape: tuple[int, int] = FRAME_SHAPE, seed: int = DEFAULT_SEED
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Stokes field (S0, S1, S2, in DN) of a heliostat field seen from a drone.

    Weakly polarized textured ground (DoLP 0-0.15) carries rows of
    rectangular heliostats that reflect the sky (DoLP 0.25-0.55, smooth AoP
    with a per-mirror canting error of a few degrees), each made of four
    facets separated by dark gaps and drawn larger toward the bottom of the
    image (perspective). One mirror carries a sun glint that saturates the
    sensor.

    Parameters
    ----------
    shape : (int, int)
        (rows, columns) at full sensor resolution; both even.
    seed : int
        Seed of every random choice (scene and canting errors).

    Returns
    -------
    s0, s1, s2 : numpy.ndarray
        Full-resolution Stokes images in digital numbers (an unpolarized
        ``S0`` gives ``S0 / 2`` DN per ideal pixel).
    """
    rng = np.random.default_rng(seed)
    h, w = shape
    yn = np.linspace(0.0, 1.0, h)[:, None]
    xn = np.linspace(0.0, 1.0, w)[None, :]

    s0 = 1500.0 + 350.0 * _smooth_field(rng, shape, (12, 14)) + 120.0 * _smooth_field(rng, shape, (160, 190))
    s0 = np.clip(s0 + 400.0 * yn, 200.0, None)
    dolp = np.clip(0.06 + 0.03 * _smooth_field(rng, shape, (20, 24)), 0.0, 0.15)
    aop = 90.0 + 25.0 * _smooth_field(rng, shape, (8, 10))

    n_rows, n_cols = 6, 9
    for r in range(n_rows):
        depth = (r + 0.5) / n_rows  # 0 far (top) ... 1 near (bottom)
        cy = int(h * (0.08 + 0.86 * depth))
        half_h = int(h * (0.025 + 0.035 * depth))
        half_w = int(w * (0.018 + 0.022 * depth))
        for c in range(n_cols):
            cx = int(w * (c + 0.5) / n_cols + w * 0.02 * (depth - 0.5) * (c - n_cols / 2))
            rows = slice(max(cy - half_h, 0), min(cy + half_h, h))
            cols = slice(max(cx - half_w, 0), min(cx + half_w, w))
            ly, lx = yn[rows] - yn[cy], xn[:, cols] - xn[:, cx]
            canting = rng.normal(0.0, 3.0)
            s0[rows, cols] = 4300.0 + 900.0 * ly - 500.0 * lx
            sky_band = 0.15 * np.sin(2.0 * np.pi * (xn[:, cols] + 0.3 * depth))
            dolp[rows, cols] = np.clip(0.40 + sky_band + 2.0 * ly, 0.25, 0.55)
            aop[rows, cols] = 35.0 + 20.0 * xn[:, cols] + 40.0 * ly + canting
            gap = max(half_w // 40, 2)  # dark cross between the 2x2 facets
            s0[rows, cx - gap : cx + gap] = 350.0
            s0[cy - gap : cy + gap, cols] = 350.0
            dolp[rows, cx - gap : cx + gap] = 0.05
            dolp[cy - gap : cy + gap, cols] = 0.05

    # sun glint on one near mirror: a Gaussian spot well beyond full scale
    gy, gx = int(0.80 * h), int(0.61 * w)
    spot = np.exp(-(((np.arange(h)[:, None] - gy) / 40.0) ** 2 + ((np.arange(w)[None, :] - gx) / 55.0) ** 2))
    s0 += 30000.0 * spot
    return stokes_from_dolp_aop(s0, dolp, aop)


def synthetic_frame(shape: tuple[int, int] = FRAME_SHAPE, seed: int = DEFAULT_SEED) -> NDArray[np.uint16]:
    """The benchmark frame: :func:`synthetic_scene` seen by a 12-bit IMX250MZR.

    Shot noise (2.5 e-/DN) and read noise (1.2 DN) are applied by
    :func:`pihim.render.mosaic.mosaic_from_stokes`; the result is ``uint16``
    holding 12-bit values (0-4095), shape ``shape``.
    """
    s0, s1, s2 = synthetic_scene(shape, seed)
    return mosaic_from_stokes(s0, s1, s2, bit_depth=BIT_DEPTH, read_noise_dn=1.2, electrons_per_dn=2.5, rng=seed + 1)


# ---------------------------------------------------------------------------
# The implementations
# ---------------------------------------------------------------------------
def numpy_superpixel(mosaic: NDArray[np.integer]) -> Outputs:
    """Super-pixel S0, DoLP and AoP with plain numpy (the anchor).

    What a numpy user would write for an IMX250MZR frame (90, 45 / 135, 0):
    strided channel views cast to float32, paper eq. (1) and (2)-(3).

    Parameters
    ----------
    mosaic : numpy.ndarray, shape (H, W)
        Raw mosaic.

    Returns
    -------
    s0, dolp, aop_deg : numpy.ndarray, shape (H/2, W/2), float32
        Intensity, degree of linear polarization and angle of polarization in
        degrees in [0, 180). Saturation is not flagged.
    """
    i90 = mosaic[0::2, 0::2].astype(np.float32)
    i45 = mosaic[0::2, 1::2].astype(np.float32)
    i135 = mosaic[1::2, 0::2].astype(np.float32)
    i0 = mosaic[1::2, 1::2].astype(np.float32)
    s0 = (i0 + i45 + i90 + i135) / 2
    s1 = i0 - i90
    s2 = i45 - i135
    with np.errstate(divide="ignore", invalid="ignore"):
        dolp = np.sqrt(s1**2 + s2**2) / s0
    aop_deg = np.mod(0.5 * np.degrees(np.arctan2(s2, s1)), 180.0)
    return s0, dolp, aop_deg


def polanalyser_bilinear(mosaic: NDArray[np.integer], dtype: type = np.float64) -> tuple[NDArray[Any], ...]:
    """polanalyser's route: bilinear demosaic, Stokes, DoLP and AoLP.

    ``pa.demosaicing`` (``COLOR_PolarMono``, i.e. OpenCV's bilinear Bayer
    conversion) returns the 0, 45, 90, 135 deg images at full resolution for
    the IMX250MZR layout; ``pa.calcStokes`` fits the Stokes vector by the
    pseudo-inverse of the polarizer Mueller rows (a ``tensordot``). With
    ``dtype=np.float32`` the channels and the polarizer Mueller matrices are
    float32, so the whole route runs in float32 like pihim's (polanalyser's
    default, the angles only, gives float64).

    Returns
    -------
    stokes, dolp, aolp : numpy.ndarray
        Stokes channels-last, shape (H, W, 3); DoLP, shape (H, W); AoLP in
        radians in [0, pi), shape (H, W).
    """
    if pa is None:  # pragma: no cover - guarded by the candidate list
        raise RuntimeError("polanalyser is not installed")
    channels = pa.demosaicing(mosaic, pa.COLOR_PolarMono)
    angles = np.deg2rad([0.0, 45.0, 90.0, 135.0])
    if dtype == np.float64:
        stokes = pa.calcStokes(channels, angles)
    else:
        muellers = np.array([pa.polarizer(a)[:3, :3] for a in angles], dtype=dtype)
        stokes = pa.calcStokes(np.array(channels, dtype=dtype), muellers)
    return stokes, pa.cvtStokesToDoLP(stokes), pa.cvtStokesToAoLP(stokes)


def make_superpixel_kernel(atan2: Callable[[float, float], float]) -> Any:
    """Build a parallel super-pixel numba kernel around a given ``atan2``.

    The kernel has the contract of :func:`pihim.camera._kernels.superpixel_polar`
    (same arguments, outputs and fast-math flags; written independently) so
    that two builds differing only in ``atan2`` time only that function.

    Parameters
    ----------
    atan2 : callable
        ``atan2(y, x)`` usable in nopython mode: ``math.atan2`` (libm) or
        :func:`pihim._fastmath.atan2_f32`.

    Returns
    -------
    numba.core.registry.CPUDispatcher
        Lazily compiled kernel ``kernel(raw, w_pos, dark, sat_level, s0, s1,
        s2, dolp, aop, saturated)``; not cached on disk, so its first call
        compiles.
    """
    deg_per_half_rad = np.float32(90.0 / math.pi)
    half_turn = np.float32(180.0)
    nan = np.float32(np.nan)

    @njit(parallel=True, fastmath=_kernels.FASTMATH)
    def kernel(raw, w_pos, dark, sat_level, s0, s1, s2, dolp, aop, saturated):  # pragma: no cover
        n_rows, n_cols = s0.shape
        for i in prange(n_rows):
            for j in range(n_cols):
                acc0 = np.float32(0.0)
                acc1 = np.float32(0.0)
                acc2 = np.float32(0.0)
                hit = False
                for pos in range(4):  # super-pixel position 2 * row + col
                    value = np.float32(raw[2 * i + pos // 2, 2 * j + pos % 2])
                    hit = hit or value >= sat_level
                    value = value - dark
                    acc0 += w_pos[0, pos] * value
                    acc1 += w_pos[1, pos] * value
                    acc2 += w_pos[2, pos] * value
                s0[i, j] = acc0
                s1[i, j] = acc1
                s2[i, j] = acc2
                saturated[i, j] = hit
                if hit or not acc0 > 0:
                    dolp[i, j] = nan
                    aop[i, j] = nan
                    continue
                dolp[i, j] = np.sqrt(acc1 * acc1 + acc2 * acc2) / acc0
                angle = deg_per_half_rad * atan2(acc2, acc1)
                if angle < 0:
                    angle += half_turn
                if angle >= half_turn:
                    angle -= half_turn
                aop[i, j] = angle

    return kernel


#: Ideal analyser pinv by super-pixel position (90, 45, 135, 0): paper eq. (1).
_W_POS_IMX250MZR = np.array([[0.5, 0.5, 0.5, 0.5], [-1.0, 0.0, 0.0, 1.0], [0.0, 1.0, -1.0, 0.0]], dtype=np.float32)


def _kernel_runner(kernel: Any) -> Callable[[NDArray[np.integer]], PolarImage]:
    """Wrap a kernel of the ``superpixel_polar`` contract as ``frame -> PolarImage``.

    Outputs are allocated per call, as :func:`polar_image` does; no input
    validation, bit-depth detection or dark level (the frame is known 12-bit).
    """
    sat_level = np.float32(2**BIT_DEPTH - 1)

    def run(mosaic: NDArray[np.integer]) -> PolarImage:
        shape = (mosaic.shape[0] // 2, mosaic.shape[1] // 2)
        s0, s1, s2, dolp, aop = (np.empty(shape, dtype=np.float32) for _ in range(5))
        saturated = np.empty(shape, dtype=np.bool_)
        kernel(mosaic, _W_POS_IMX250MZR, np.float32(0.0), sat_level, s0, s1, s2, dolp, aop, saturated)
        return PolarImage(s0, s1, s2, dolp, aop, saturated, "superpixel", None)

    return run


# ---------------------------------------------------------------------------
# Rows
# ---------------------------------------------------------------------------
#: Distinct frames the timed calls rotate through (10 MB each).
N_FRAMES = 16


@dataclass(frozen=True)
class Row:
    """One implementation under test.

    Attributes
    ----------
    key, label : str
        JSON identifier and table label.
    resolution : {"super-pixel", "full"}
    make : callable
        ``make(frames) -> run(k)``: prepares (e.g. preallocates) and returns
        the call on frame ``k % len(frames)``.
    anchor : str or None
        Key of the row this one is compared with (same resolution).
    new_pages : bool
        Every call's outputs on new pages: the row's process fixes glibc's
        mmap and trim thresholds at their initial 128 KiB
        (:func:`pihim._malloc.keep_freed_memory`, ``mallopt``), so that every
        large block is mapped when allocated and unmapped when freed,
        however large the blocks freed before.
    to_common : callable
        Maps the outputs to ``(s0, dolp, aop_deg)`` for the checks.
    note : str
    """

    key: str
    label: str
    resolution: str
    make: Callable[[Sequence[NDArray[np.uint16]]], Callable[[int], Any]]
    anchor: str | None = None
    to_common: Callable[[Any], Outputs] = lambda r: (r.s0, r.dolp, r.aop_deg)
    note: str = ""
    new_pages: bool = False


def _rotating(fn: Callable[[NDArray[np.uint16]], Any]) -> Callable[[Sequence[NDArray[np.uint16]]], Callable[[int], Any]]:
    return lambda frames: (lambda k: fn(frames[k % len(frames)]))


def _preallocated(demosaic: str, with_summary: bool = False) -> Callable[[Sequence[NDArray[np.uint16]]], Callable[[int], Any]]:
    def make(frames: Sequence[NDArray[np.uint16]]) -> Callable[[int], Any]:
        buf = polar_image(frames[0], demosaic=demosaic, bit_depth=BIT_DEPTH)

        def run(k: int) -> Any:
            out = polar_image(frames[k % len(frames)], demosaic=demosaic, bit_depth=BIT_DEPTH, out=buf)
            return out.summary() if with_summary else out

        return run

    return make


def _polanalyser_common(result: tuple[NDArray[Any], ...]) -> Outputs:
    stokes, dolp, aolp = result
    return stokes[..., 0], dolp, np.degrees(aolp)


def rows() -> list[Row]:
    """The implementations, in the order they are measured."""
    out = [
        Row("numpy", "numpy super-pixel, float32 (anchor)", "super-pixel", _rotating(numpy_superpixel),
            to_common=lambda r: r, note="numpy anchor: strided views, eq. (1), sqrt, arctan2; S0, DoLP, AoP only"),
        Row("pihim_superpixel", 'pihim `polar_image(demosaic="superpixel")`, fresh outputs', "super-pixel",
            _rotating(lambda m: polar_image(m, demosaic="superpixel", bit_depth=BIT_DEPTH)), anchor="numpy"),
        Row("pihim_superpixel_new_pages", 'pihim `polar_image(demosaic="superpixel")`, fresh outputs on new pages',
            "super-pixel", _rotating(lambda m: polar_image(m, demosaic="superpixel", bit_depth=BIT_DEPTH)),
            anchor="numpy", new_pages=True,
            note="new pages: the row's process maps every large block anew (glibc's mmap threshold fixed at "
                 "128 KiB), so no call gets pages the one before freed"),
        Row("pihim_superpixel_out", 'pihim `polar_image(demosaic="superpixel", out=...)`', "super-pixel",
            _preallocated("superpixel"), anchor="numpy"),
        Row("pihim_superpixel_summary", "pihim super-pixel `out=...` + `PolarImage.summary()`", "super-pixel",
            _preallocated("superpixel", with_summary=True), anchor="numpy",
            note="summary: what `pihim polar --json` adds per frame (exact percentiles, means, circular mean)"),
    ]
    if pa is not None:
        version = importlib.metadata.version("polanalyser")
        out += [
            Row("polanalyser_f32", f"polanalyser {version} bilinear, float32 (anchor)", "full",
                _rotating(lambda m: polanalyser_bilinear(m, np.float32)), to_common=_polanalyser_common),
            Row("polanalyser_f64", f"polanalyser {version} bilinear, float64 (its default)", "full",
                _rotating(polanalyser_bilinear), anchor="polanalyser_f32", to_common=_polanalyser_common),
        ]
    full_anchor = "polanalyser_f32" if pa is not None else None
    out += [
        Row("pihim_full", 'pihim `polar_image(demosaic="full")`, fresh outputs', "full",
            _rotating(lambda m: polar_image(m, demosaic="full", bit_depth=BIT_DEPTH)), anchor=full_anchor),
        Row("pihim_full_out", 'pihim `polar_image(demosaic="full", out=...)`', "full", _preallocated("full"),
            anchor=full_anchor),
        Row("pihim_full_summary", "pihim full `out=...` + `PolarImage.summary()`", "full",
            _preallocated("full", with_summary=True), anchor=full_anchor),
        Row("numba_poly", "numba kernel alone, polynomial `atan2_f32` (no validation)", "super-pixel",
            lambda frames: (lambda k, run=_kernel_runner(make_superpixel_kernel(atan2_f32)):
                            run(frames[k % len(frames)])), anchor="numpy",
            note="numba pair: the same kernel built twice, only atan2 differs; no input validation or "
                 "bit-depth check, fresh outputs"),
        Row("numba_libm", "numba kernel alone, libm `math.atan2` (no validation)", "super-pixel",
            lambda frames: (lambda k, run=_kernel_runner(make_superpixel_kernel(math.atan2)):
                            run(frames[k % len(frames)])), anchor="numpy"),
    ]
    return out


def output_nbytes(result: Any) -> int:
    """Bytes held by the arrays of ``result`` (views count their base once)."""
    found: dict[int, int] = {}

    def visit(obj: Any) -> None:
        if isinstance(obj, np.ndarray):
            root = obj
            while isinstance(root.base, np.ndarray):
                root = root.base
            found[id(root)] = root.nbytes
        elif isinstance(obj, (tuple, list)):
            for item in obj:
                visit(item)
        elif isinstance(obj, PolarImage):
            visit([obj.s0, obj.s1, obj.s2, obj.dolp, obj.aop_deg, obj.saturated])

    visit(result)
    return sum(found.values())


def measure_row(row: Row, frames: Sequence[NDArray[np.uint16]], repeat: int, warmup: int,
                bandwidth_gb_s: float, wait_quiet_s: float) -> dict[str, Any]:
    """Time one row on the rotating frames (after ``warmup`` calls); bytes moved and the bandwidth floor."""
    run = row.make(frames)
    first = run(0)
    moved = frames[0].nbytes + (output_nbytes(first) if not isinstance(first, dict) else
                               output_nbytes(polar_image(frames[0], demosaic="full" if row.resolution == "full"
                                                         else "superpixel", bit_depth=BIT_DEPTH)))
    del first
    for k in range(warmup):
        run(k)
    best: dict[str, Any] | None = None
    deadline = time.monotonic() + wait_quiet_s
    while True:
        if wait_quiet_s > 0:
            harness.wait_for_quiet(max(deadline - time.monotonic(), 0.0))
        timing = harness.time_calls_cpu(lambda k: run(k + warmup), repeat)
        if best is None or (timing["other_cpu"] or 0) < (best["other_cpu"] or 0):
            best = timing
        if (best["other_cpu"] or 0) <= harness.BUSY_WARNING or time.monotonic() >= deadline:
            break
    floor_ms = 1e3 * moved / (bandwidth_gb_s * 1e9)
    samples = best.pop("samples_ms")
    return {"key": row.key, "label": row.label, "resolution": row.resolution, "anchor": row.anchor,
            **best, "samples_ms": [round(float(v), 3) for v in samples], "bytes_moved": moved,
            "floor_ms": floor_ms, "ratio_to_floor": best["median_ms"] / floor_ms}


#: First argument of this file's command line in a row's own process (see :func:`measure_rows`).
_ROW_CHILD = "--measure-row"


def measure_rows(frames: Sequence[NDArray[np.uint16]], repeat: int, warmup: int, bandwidth_gb_s: float,
                 wait_quiet_s: float) -> list[dict[str, Any]]:
    """:func:`measure_row` for every row, each in a new process of its own (see the module notes)."""
    import json
    import subprocess
    import tempfile

    out = []
    with tempfile.TemporaryDirectory(prefix="pihim-bench-polar-") as tmp:
        for k, frame in enumerate(frames):
            np.save(Path(tmp) / f"frame_{k:03d}.npy", frame)
        for row in rows():
            res = subprocess.run([sys.executable, str(Path(__file__).resolve()), _ROW_CHILD, row.key, tmp,
                                  str(repeat), str(warmup), repr(bandwidth_gb_s), repr(wait_quiet_s)],
                                 capture_output=True, text=True, check=False)
            if res.returncode != 0:
                raise RuntimeError(f"row {row.key} failed: {res.stderr.strip().splitlines()[-1:]}")
            out.append(json.loads(res.stdout.strip().splitlines()[-1]))
    return out


def _measure_row_child(key: str, folder: str, repeat: str, warmup: str, bandwidth_gb_s: str,
                       wait_quiet_s: str) -> None:
    """The row's own process: load the frames, time the row, print its result as one JSON line."""
    import json

    from pihim._malloc import keep_freed_memory

    row = next(r for r in rows() if r.key == key)
    # glibc's default thresholds, fixed: no longer raised by the blocks freed
    if row.new_pages and not keep_freed_memory(128 * 1024, 128 * 1024):
        raise RuntimeError("could not fix glibc's mmap threshold (not glibc, or set in the environment)")
    frames = [np.load(p) for p in sorted(Path(folder).glob("frame_*.npy"))]
    print(json.dumps(measure_row(row, frames, int(repeat), int(warmup), float(bandwidth_gb_s),
                                 float(wait_quiet_s))))


# ---------------------------------------------------------------------------
# First calls, in fresh processes
# ---------------------------------------------------------------------------
_FIRST_CALL = r"""
import json, os, sys, time
t0 = time.perf_counter(); c0 = time.process_time()
import numpy as np
from pihim.camera.pipeline import polar_image
t1 = time.perf_counter(); c1 = time.process_time()
raw = np.load(sys.argv[1])
t2 = time.perf_counter(); c2 = time.process_time()
polar_image(raw, demosaic=sys.argv[2], bit_depth=12)
t3 = time.perf_counter(); c3 = time.process_time()
polar_image(raw, demosaic=sys.argv[2], bit_depth=12)
t4 = time.perf_counter(); c4 = time.process_time()
print(json.dumps({"import_s": t1 - t0, "import_cpu_s": c1 - c0, "first_call_s": t3 - t2,
                  "first_call_cpu_s": c3 - c2, "second_call_s": t4 - t3}))
"""


def first_calls(frame: NDArray[np.uint16], cold: bool) -> list[dict[str, Any]]:
    """Import and first ``polar_image`` call in a fresh process per route: numba cache warm, and empty if ``cold``."""
    import json
    import shutil
    import tempfile

    out = []
    with tempfile.TemporaryDirectory(prefix="pihim-bench-") as tmp:
        path = Path(tmp) / "frame.npy"
        np.save(path, frame)
        env = dict(os.environ)
        src = Path(__file__).resolve().parents[1] / "src"
        env["PYTHONPATH"] = os.pathsep.join([str(src), env.get("PYTHONPATH", "")])
        cases = [("warm", None)] + ([("cold", Path(tmp) / "numba-cache")] if cold else [])
        for demosaic in ("superpixel", "full"):
            for label, cache in cases:
                run_env = dict(env)
                if cache is not None:
                    shutil.rmtree(cache, ignore_errors=True)
                    run_env["NUMBA_CACHE_DIR"] = str(cache)
                else:  # the cache a user has after one run: make sure it is there
                    harness.process_run([sys.executable, "-c", _FIRST_CALL, str(path), demosaic], env=env)
                res = harness.process_run([sys.executable, "-c", _FIRST_CALL, str(path), demosaic], env=run_env)
                row = {"demosaic": demosaic, "cache": label, "process_wall_s": res["wall_s"],
                       "process_cpu_s": res["cpu_s"], "load_avg": res["load_after"], "other_cpu": res["other_cpu"]}
                if res["returncode"] == 0:
                    row.update(json.loads(res["stdout"].strip().splitlines()[-1]))
                else:
                    row["error"] = res["stderr"].strip().splitlines()[-1:]
                out.append(row)
    return out


# ---------------------------------------------------------------------------
# Checks: every route must compute the same quantities
# ---------------------------------------------------------------------------
def uniform_field_check(candidate: Candidate) -> dict[str, Any]:
    """Recover a known uniform DoLP/AoP from a small noiseless mosaic.

    Catches channel-order and sign mistakes in any route, including the
    full-resolution ones (interpolation is exact on a uniform field; 4
    border pixels are ignored).
    """
    worst_dolp = worst_aop = 0.0
    for aop_deg in UNIFORM_FIELD["aop_deg"]:
        s0, s1, s2 = stokes_from_dolp_aop(UNIFORM_FIELD["s0"], UNIFORM_FIELD["dolp"], aop_deg)
        ones = np.ones((32, 32))
        mosaic = mosaic_from_stokes(s0 * ones, s1 * ones, s2 * ones, bit_depth=BIT_DEPTH)
        _, dolp, aop = (np.asarray(a, dtype=np.float64) for a in candidate.to_common(candidate.run(mosaic)))
        border = 4 if candidate.resolution == "full" else 2
        inner = (slice(border, -border), slice(border, -border))
        worst_dolp = max(worst_dolp, float(np.max(np.abs(dolp[inner] - UNIFORM_FIELD["dolp"]))))
        worst_aop = max(worst_aop, float(np.max(aop_difference_deg(aop[inner], aop_deg))))
    return {
        "uniform_max_abs_dolp_error": worst_dolp,
        "uniform_max_aop_error_deg": worst_aop,
        "uniform_ok": worst_dolp <= UNIFORM_TOLERANCE["dolp"] and worst_aop <= UNIFORM_TOLERANCE["aop_deg"],
    }


def agreement_check(candidate: Candidate, mosaic: NDArray[np.integer], anchor: Outputs) -> dict[str, Any]:
    """Largest differences from the numpy anchor on the benchmark frame.

    Only for super-pixel routes; compared on pixels where both give a
    finite DoLP (the anchor does not mask saturated super-pixels), and AoP
    only where the anchor's DoLP is at least :data:`AOP_MIN_DOLP` (AoP is
    undefined for unpolarized light: with S1 = S2 = 0 exactly, rounding
    residues of order 1e-14 decide the angle).
    """
    s0, dolp, aop = candidate.to_common(candidate.run(mosaic))
    a_s0, a_dolp, a_aop = anchor
    valid = np.isfinite(dolp) & np.isfinite(a_dolp)
    polarized = valid & (a_dolp >= AOP_MIN_DOLP)
    diffs = {
        "s0": float(np.max(np.abs(s0[valid] - a_s0[valid]))),
        "dolp": float(np.max(np.abs(dolp[valid] - a_dolp[valid]))),
        "aop_deg": float(np.max(aop_difference_deg(aop[polarized], a_aop[polarized]))),
    }
    return {
        **{f"max_abs_diff_{k}": v for k, v in diffs.items()},
        "compared_fraction": float(valid.mean()),
        "aop_compared_fraction": float(polarized.mean()),
        "agrees_with_anchor": all(diffs[k] <= AGREEMENT_TOLERANCE[k] for k in diffs),
    }


# ---------------------------------------------------------------------------
# Targets, machine and report
# ---------------------------------------------------------------------------
#: (name, row key, figure, limit, unit, limit is a maximum).
TARGETS: tuple[tuple[str, str, str, float, str, bool], ...] = (
    ("super-pixel polar_image, fresh outputs on new pages, median", "pihim_superpixel_new_pages", "median_ms", 10.0,
     "ms", True),
    ("super-pixel polar_image, fresh outputs, median", "pihim_superpixel", "median_ms", 10.0, "ms", True),
    ("super-pixel speed-up vs numpy (same resolution, float32)", "pihim_superpixel", "vs_anchor", 5.0, "x", False),
    ("full-resolution polar_image, fresh outputs, median", "pihim_full", "median_ms", 60.0, "ms", True),
)


def machine_info() -> dict[str, Any]:
    """What the figures depend on: CPU, threads and library versions."""
    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel kernel has run yet
        layer = None
    from pihim import _png

    return {
        "cpu_model": harness.cpu_model(),
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "numba_threads": numba.get_num_threads(),
        "numba_threading_layer": layer,
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "opencv": cv2.__version__,
        "polanalyser": importlib.metadata.version("polanalyser") if pa is not None else None,
        "png_deflate": _png.DEFLATE,
    }


def _fmt(value: float | None, spec: str = ".1f", suffix: str = "") -> str:
    return "-" if value is None else f"{value:{spec}}{suffix}"


def markdown_report(report: dict[str, Any]) -> str:
    """The results as markdown: rows, first calls, targets, checks and machine."""
    s, bw = report["settings"], report["bandwidth"]
    lines = [
        f"{report['frames']['count']} distinct {report['frames']['width']}x{report['frames']['height']} uint16 "
        f"12-bit frames ({report['frames']['count'] * report['frames']['bytes'] / 1e6:.0f} MB) in rotation; "
        f"{s['repeat']} timed calls after {s['warmup']} warm-ups. Copy bandwidth measured in this run: "
        f"{bw['copy_gb_s']:.1f} GB/s (best of 7; median {bw['copy_gb_s_median']:.1f}).",
        "",
        "| Implementation | Output | Median ms | p10 ms | p90 ms | CPU ms | vs anchor | MB moved | floor ms "
        "| x floor | page faults / call | Other CPU % | Load |",
        "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for m in report["results"]:
        lines.append(
            f"| {m['label']} | {m['resolution']} | {m['median_ms']:.1f} | {m['p10_ms']:.1f} | {m['p90_ms']:.1f} "
            f"| {m['cpu_ms']:.1f} | {_fmt(m.get('vs_anchor'), '.2f', 'x')} | {m['bytes_moved'] / 1e6:.1f} "
            f"| {m['floor_ms']:.2f} | {m['ratio_to_floor']:.1f} | {m['page_faults']:.0f} "
            f"| {harness.other_pct(m['other_cpu'])} "
            f"| {_fmt(m['load_avg'], '.1f')} |")
    lines += harness.busy_warning(m["other_cpu"] for m in report["results"])
    if report["first_calls"]:
        lines += ["", "| First call in a fresh process | numba cache | import s (CPU) | first call s (CPU) "
                  "| second call s | process wall s | process CPU s | Load |", "|---|---|--:|--:|--:|--:|--:|--:|"]
        for f in report["first_calls"]:
            if "error" in f:
                lines.append(f"| {f['demosaic']} | {f['cache']} | error: {f['error']} |" + " |" * 5)
                continue
            lines.append(
                f"| {f['demosaic']} | {f['cache']} | {f['import_s']:.2f} ({f['import_cpu_s']:.2f}) "
                f"| {f['first_call_s']:.2f} ({f['first_call_cpu_s']:.2f}) | {f['second_call_s']:.3f} "
                f"| {f['process_wall_s']:.2f} | {f['process_cpu_s']:.2f} | {_fmt(f['load_avg'], '.1f')} |")
    lines += harness.target_table(report["targets"], spec=".2f", unit_spec={"ms": ".1f"}, column="Result",
                                  align="--:")
    lines += ["", "| Check (not timed) | Uniform field: max DoLP / AoP error | vs numpy anchor: max S0 / DoLP / AoP |",
              "|---|---|---|"]
    for key, c in report["checks"].items():
        uniform = (f"{'ok' if c['uniform_ok'] else 'FAIL'}: {c['uniform_max_abs_dolp_error']:.1e} / "
                   f"{c['uniform_max_aop_error_deg']:.1e} deg")
        anchor = "-"
        if "agrees_with_anchor" in c:
            anchor = (f"{'ok' if c['agrees_with_anchor'] else 'DIFFERS'}: {c['max_abs_diff_s0']:.1e} / "
                      f"{c['max_abs_diff_dolp']:.1e} / {c['max_abs_diff_aop_deg']:.1e} deg")
        lines.append(f"| {key} | {uniform} | {anchor} |")
    mach = report["machine"]
    lines += ["", f"Machine: {mach['cpu_model']}, {mach['cpu_count']} cores, numba {mach['numba']} "
              f"({mach['numba_threads']} threads, {mach['numba_threading_layer']}, OMP_WAIT_POLICY="
              f"{mach['omp_wait_policy']}), numpy {mach['numpy']}, OpenCV {mach['opencv']}, polanalyser "
              f"{mach['polanalyser'] or 'not installed'}, Python {mach['python']}."]
    lines += ["", *[f"- {n}" for n in report["notes"]]]
    return "\n".join(lines)


NOTES = (
    "Wall: median/p10/p90 of the timed calls (time.perf_counter_ns, garbage collector paused). CPU: process CPU "
    "time (all threads) over the timed calls, per call; on 2 cores a parallel kernel can show CPU up to twice its "
    "wall time.",
    "MB moved: the input frame read plus the outputs written (the least any implementation must move); floor: those "
    "bytes at the copy bandwidth measured in this run (read + write bytes per second); x floor: median / floor.",
    "vs anchor: the anchor's median divided by the row's (same output resolution): numpy super-pixel for the "
    "super-pixel rows, polanalyser bilinear float32 for the full-resolution rows (float32 channels and Mueller "
    "matrices, so the same dtype as pihim's outputs).",
    "Fresh outputs: every call allocates its outputs (the allocator may hand back the block the call before freed, "
    "as in a user's process; the page faults say so); new pages: every call's outputs are pages the operating "
    "system maps and zeroes anew; out=: the same arrays are written every call. Each row runs in a new process of "
    "its own; page faults / call: that process's minor faults per timed call.",
    "Other CPU %: share of the machine's CPUs used by other processes during the timed calls (/proc/stat); Load: "
    "one-minute load average after them.",
)


def run_benchmark(repeat: int, warmup: int, seed: int = DEFAULT_SEED, cold: bool = True,
                  wait_quiet_s: float = 0.0) -> dict[str, Any]:
    """Measure every row on the rotating frames, the first calls and the bandwidth; the JSON-ready report."""
    scenes = [synthetic_scene(FRAME_SHAPE, seed + k) for k in range(4)]
    frames = [mosaic_from_stokes(*scenes[k % 4], bit_depth=BIT_DEPTH, read_noise_dn=1.2, electrons_per_dn=2.5,
                                 rng=seed + 100 + k) for k in range(N_FRAMES)]
    del scenes
    bandwidth = harness.memory_bandwidth()
    results = measure_rows(frames, repeat, warmup, bandwidth["copy_gb_s"], wait_quiet_s)
    by_key = {m["key"]: m for m in results}
    for m in results:
        ref = by_key.get(m["anchor"]) if m["anchor"] else None
        m["vs_anchor"] = ref["median_ms"] / m["median_ms"] if ref else None
    checks: dict[str, Any] = {}
    anchor_out = numpy_superpixel(frames[0])
    for r in rows():
        if r.key.endswith(("_out", "_summary")):
            continue
        holder = [frames[0]]  # the route is built once (a numba row compiles its kernel then)
        call = r.make(holder)

        def run(m: NDArray[np.integer], holder: list = holder, call: Callable[[int], Any] = call) -> Any:
            holder[0] = m
            return call(0)

        cand = Candidate(r.key, r.label, r.resolution, run, r.to_common)
        checks[r.key] = uniform_field_check(cand)
        if r.resolution == "super-pixel" and r.key != "numpy":
            checks[r.key].update(agreement_check(cand, frames[0], anchor_out))
    targets = [harness.target(name, (by_key.get(key) or {}).get(fig), limit, unit, at_most=at_most)
               for name, key, fig, limit, unit, at_most in TARGETS]
    return {
        "benchmark": "polar",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "frames": {"count": N_FRAMES, "height": FRAME_SHAPE[0], "width": FRAME_SHAPE[1], "bytes": frames[0].nbytes,
                   "seed": seed, "fraction_saturated": float(np.mean(frames[0] >= 2**BIT_DEPTH - 1))},
        "settings": {"repeat": repeat, "warmup": warmup, "cold": cold, "wait_quiet_s": wait_quiet_s},
        "bandwidth": bandwidth,
        "machine": machine_info(),
        "results": results,
        "first_calls": first_calls(frames[0], cold),
        "targets": targets,
        "checks": checks,
        "notes": [r.note for r in rows() if r.note] + list(NOTES),
    }


@dataclass(frozen=True)
class Candidate:
    """A route as the checks see it: ``run(mosaic)`` and the map to ``(s0, dolp, aop_deg)``."""

    key: str
    label: str
    resolution: str
    run: Callable[[NDArray[np.integer]], Any]
    to_common: Callable[[Any], Outputs]


def main(
    argv: Sequence[str] | None = None,
    *,
    repeat: int | None = None,
    warmup: int | None = None,
    quick: bool = False,
    seed: int = DEFAULT_SEED,
    json_path: Path | None = RESULTS_PATH,
    wait_quiet: float = 0.0,
    echo: bool = True,
) -> dict[str, Any]:
    """Run the benchmark, print the markdown report and write the JSON (see the module docstring).

    Parameters
    ----------
    argv : sequence of str, optional
        ``--repeat N``, ``--warmup N``, ``--quick``, ``--json PATH``, ``--seed N``, ``--wait-quiet S``.
    repeat, warmup : int, optional
        Timed and untimed calls per row; default 32 and 4 (8 and 2 with ``quick``).
    quick : bool
        Fewer calls and no cold compiles.
    seed : int
        Seed of the synthetic frames.
    json_path : pathlib.Path or None
        Where to write the JSON report.
    wait_quiet : float
        Seconds each row may wait and retry for other processes to leave the CPUs idle.
    echo : bool
        Print the markdown report.
    """

    def configure(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--seed", type=int, help=f"seed of the synthetic frames (default {DEFAULT_SEED})")
        parser.add_argument("--wait-quiet", type=float, metavar="S", help="wait and retry up to S s per row")

    o = harness.options(argv, description=__doc__.split("\n\n")[0], counts=COUNTS, repeat=repeat, warmup=warmup,
                        quick=quick, json_path=json_path, configure=configure)
    if o.args is not None:
        seed = o.args.seed if o.args.seed is not None else seed
        wait_quiet = o.args.wait_quiet if o.args.wait_quiet is not None else wait_quiet
    report = run_benchmark(o.repeat, o.warmup, seed=seed, cold=not o.quick, wait_quiet_s=wait_quiet)
    report["settings"]["quick"] = o.quick
    return harness.publish(report, markdown_report, o.json_path, echo=echo)


if __name__ == "__main__":
    if sys.argv[1:2] == [_ROW_CHILD]:
        _measure_row_child(*sys.argv[2:])
    else:
        main(sys.argv[1:] or None)
