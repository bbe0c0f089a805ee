"""Speed benchmark: one raw 2448x2048 DoFP frame -> S0, DoLP and AoP images.

Every implementation is timed on the same seeded, 12-bit synthetic frame of
a heliostat field (:func:`synthetic_frame`), one after the other in one run:

``numpy``
    Plain numpy super-pixel route (:func:`numpy_superpixel`), the anchor
    every speed-up is quoted against.
``polanalyser``
    polanalyser's default route: bilinear demosaicing (OpenCV Bayer
    conversion), ``calcStokes``, ``cvtStokesToDoLP`` and ``cvtStokesToAoLP``
    (optional; skipped when polanalyser is not installed).
``pihim_superpixel`` / ``pihim_full``
    :func:`pihim.camera.pipeline.polar_image` with ``demosaic="superpixel"``
    and ``"full"``; the full-resolution route reports "n/a" while its numba
    kernel is not available.
``numba_poly`` / ``numba_libm``
    The same super-pixel numba kernel (:func:`make_superpixel_kernel`) built
    with the polynomial :func:`pihim._fastmath.atan2_f32` and with libm's
    ``math.atan2``: the pair isolates what the polynomial buys.

For each one the report gives the median, p10 and p90 wall time over
``repeat`` calls made after ``warmup`` untimed ones, the first call in the
process (numba JIT compile or on-disk cache load) and, for numba kernels, a
cold compile on a fresh, uncached dispatcher, the speed-up relative to the
numpy anchor and to polanalyser, the tracemalloc peak of one call and the
bytes held by its outputs. Each call takes the raw frame and returns freshly
allocated outputs, so output allocation and first-touch page faults are part
of every figure.

Run ``python benchmarks/run.py`` (all benchmarks) or this file directly.
"""

from __future__ import annotations

import argparse
import gc
import importlib.metadata
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
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
COUNTS = harness.Counts(repeat=30, warmup=3, quick_repeat=5, quick_warmup=1)
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


def polanalyser_bilinear(mosaic: NDArray[np.integer]) -> tuple[NDArray[np.float64], ...]:
    """polanalyser's default route: bilinear demosaic, Stokes, DoLP and AoLP.

    ``pa.demosaicing`` (``COLOR_PolarMono``, i.e. OpenCV's bilinear Bayer
    conversion) returns the 0, 45, 90, 135 deg images at full resolution for
    the IMX250MZR layout; ``pa.calcStokes`` fits the Stokes vector by the
    pseudo-inverse of the polarizer Mueller rows (a ``tensordot``).

    Returns
    -------
    stokes, dolp, aolp : numpy.ndarray, float64
        Stokes channels-last, shape (H, W, 3); DoLP, shape (H, W); AoLP in
        radians in [0, pi), shape (H, W).
    """
    if pa is None:  # pragma: no cover - guarded by the candidate list
        raise RuntimeError("polanalyser is not installed")
    channels = pa.demosaicing(mosaic, pa.COLOR_PolarMono)
    stokes = pa.calcStokes(channels, np.deg2rad([0.0, 45.0, 90.0, 135.0]))
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
# Candidates
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Candidate:
    """One implementation under test.

    Attributes
    ----------
    key : str
        Identifier used in the JSON output.
    label : str
        Row label of the table.
    resolution : {"super-pixel", "full"}
        Output grid: (H/2, W/2) or (H, W).
    run : callable
        ``run(mosaic)``; returns the implementation's own outputs.
    to_common : callable
        Maps those outputs to ``(s0, dolp, aop_deg)`` for the checks.
    dispatchers : callable
        Returns the numba dispatchers the call compiles (resolved lazily,
        so that a kernel still missing only disables its own row).
    note : str
        Caveat printed under the table.
    """

    key: str
    label: str
    resolution: str
    run: Callable[[NDArray[np.integer]], Any]
    to_common: Callable[[Any], Outputs]
    dispatchers: Callable[[], Sequence[Any]] = lambda: ()
    note: str = ""


def _polar_common(result: PolarImage) -> Outputs:
    return result.s0, result.dolp, result.aop_deg


def _polanalyser_common(result: tuple[NDArray[np.float64], ...]) -> Outputs:
    stokes, dolp, aolp = result
    return stokes[..., 0], dolp, np.degrees(aolp)


def candidates() -> list[Candidate]:
    """The implementations, in the order they are measured."""
    numba_poly = make_superpixel_kernel(atan2_f32)
    numba_libm = make_superpixel_kernel(math.atan2)
    rows = [
        Candidate(
            ANCHOR,
            "numpy super-pixel, float32 (anchor)",
            "super-pixel",
            numpy_superpixel,
            lambda out: out,
            note="anchor: slicing + eq. (1), float32; returns S0, DoLP, AoP only and flags no saturation",
        ),
    ]
    if pa is not None:
        rows.append(
            Candidate(
                POLANALYSER,
                f"polanalyser {importlib.metadata.version('polanalyser')} bilinear",
                "full",
                polanalyser_bilinear,
                _polanalyser_common,
                note=(
                    "polanalyser: full-resolution bilinear (OpenCV Bayer) demosaic, float64; returns "
                    "channels-last Stokes (H, W, 3), DoLP and AoLP in radians"
                ),
            )
        )
    rows += [
        Candidate(
            "pihim_superpixel",
            'pihim polar_image(demosaic="superpixel")',
            "super-pixel",
            lambda m: polar_image(m, demosaic="superpixel", bit_depth=BIT_DEPTH),
            _polar_common,
            lambda: (_kernels.superpixel_polar,),
        ),
        Candidate(
            "pihim_full",
            'pihim polar_image(demosaic="full")',
            "full",
            lambda m: polar_image(m, demosaic="full", bit_depth=BIT_DEPTH),
            _polar_common,
            lambda: (_kernels.fullres_polar,),
        ),
        Candidate(
            "numba_poly",
            "numba super-pixel kernel, polynomial atan2_f32",
            "super-pixel",
            _kernel_runner(numba_poly),
            _polar_common,
            lambda: (numba_poly,),
            note="numba pair: same benchmark kernel, only atan2 differs; outputs allocated per call",
        ),
        Candidate(
            "numba_libm",
            "numba super-pixel kernel, libm math.atan2",
            "super-pixel",
            _kernel_runner(numba_libm),
            _polar_common,
            lambda: (numba_libm,),
        ),
    ]
    return rows


# ---------------------------------------------------------------------------
# Measurement
# ---------------------------------------------------------------------------
@dataclass
class Measurement:
    """Figures of one candidate (times in ms, memory in bytes)."""

    key: str
    label: str
    resolution: str
    available: bool = True
    reason: str = ""
    first_call_ms: float | None = None
    numba_cache: str | None = None
    jit_compile_ms: float | None = None
    median_ms: float | None = None
    p10_ms: float | None = None
    p90_ms: float | None = None
    mean_ms: float | None = None
    min_ms: float | None = None
    samples_ms: list[float] = field(default_factory=list)
    peak_traced_bytes: int | None = None
    output_bytes: int | None = None
    speedup_vs_numpy: float | None = None
    speedup_vs_polanalyser: float | None = None
    other_cpu_load: float | None = None
    attempts: int = 1
    checks: dict[str, Any] = field(default_factory=dict)


def output_nbytes(result: Any) -> int:
    """Bytes of memory held by the arrays of ``result`` (views count their base once)."""
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


def _cache_counts(dispatchers: Sequence[Any]) -> tuple[int, int]:
    """Total on-disk cache hits and misses of ``dispatchers`` so far."""
    hits = sum(sum(d.stats.cache_hits.values()) for d in dispatchers)
    misses = sum(sum(d.stats.cache_misses.values()) for d in dispatchers)
    return hits, misses


def _cache_status(dispatchers: Sequence[Any], before: tuple[int, int]) -> str:
    """``off`` (no disk cache), ``hit`` (machine code loaded) or ``miss`` (compiled)."""
    if all(d.stats.cache_path is None for d in dispatchers):
        return "off"
    hits, misses = (now - then for now, then in zip(_cache_counts(dispatchers), before, strict=True))
    return "hit" if hits and not misses else "miss"


def cold_compile_ms(dispatchers: Sequence[Any]) -> float:
    """Compile time of the signatures seen so far, on fresh uncached dispatchers.

    The production kernels are cached on disk, so their first call in a
    process usually only loads machine code; this recompiles the same Python
    function with the same options (minus ``cache``) to report what a cold
    JIT costs.
    """
    total = 0.0
    for dispatcher in dispatchers:
        options = {k: v for k, v in dispatcher.targetoptions.items() if k not in ("cache", "nopython")}
        for signature in dispatcher.signatures:
            fresh = njit(**options)(dispatcher.py_func)
            start = time.perf_counter()
            fresh.compile(signature)
            total += time.perf_counter() - start
    return 1e3 * total


def _is_missing_kernel(exc: BaseException) -> bool:
    """True for the AttributeError of a numba kernel that has not landed yet."""
    return isinstance(exc, AttributeError) and "pihim.camera._kernels" in str(exc)


def measure(
    candidate: Candidate, mosaic: NDArray[np.integer], repeat: int, warmup: int, compile_time: bool
) -> Measurement:
    """Time one candidate: first call, warm-ups, ``repeat`` timed calls, one traced call."""
    result = Measurement(candidate.key, candidate.label, candidate.resolution)
    gc.collect()
    try:
        dispatchers = tuple(candidate.dispatchers())
        before = _cache_counts(dispatchers)
        start = time.perf_counter()
        out = candidate.run(mosaic)
        result.first_call_ms = 1e3 * (time.perf_counter() - start)
    except Exception as exc:  # noqa: BLE001 - a broken or missing route must not stop the suite
        result.available = False
        result.reason = NOT_AVAILABLE if _is_missing_kernel(exc) else f"n/a ({type(exc).__name__}: {exc})"
        return result
    if dispatchers:
        result.numba_cache = _cache_status(dispatchers, before)
        if compile_time:
            result.jit_compile_ms = cold_compile_ms(dispatchers)
    result.output_bytes = output_nbytes(out)
    del out

    for _ in range(warmup):
        candidate.run(mosaic)
    samples, result.other_cpu_load = harness.time_calls(lambda: candidate.run(mosaic), repeat)
    result.samples_ms = [round(float(s), 4) for s in samples]
    result.median_ms, result.p10_ms, result.p90_ms = (float(v) for v in np.percentile(samples, [50, 10, 90]))
    result.mean_ms, result.min_ms = float(samples.mean()), float(samples.min())

    result.peak_traced_bytes, _ = harness.traced_peak(lambda: candidate.run(mosaic))
    return result


def measure_when_quiet(
    candidate: Candidate,
    mosaic: NDArray[np.integer],
    repeat: int,
    warmup: int,
    compile_time: bool,
    wait_quiet_s: float,
) -> Measurement:
    """:func:`measure`, repeated while other processes disturb it, for up to ``wait_quiet_s`` seconds.

    Before each attempt, wait for the other processes to leave the CPUs
    (nearly) idle; an attempt during which they used more than
    :data:`BUSY_WARNING` of the CPUs is retried until the time is up, and the
    least disturbed attempt is kept. First-call and compile figures always
    come from the first attempt (later ones are warm). ``wait_quiet_s = 0``
    measures once.
    """
    deadline = time.monotonic() + wait_quiet_s

    def attempt(with_compile: bool) -> Measurement:
        if wait_quiet_s > 0:
            harness.wait_for_quiet(max(deadline - time.monotonic(), 0.0), threshold=BUSY_WARNING)
        return measure(candidate, mosaic, repeat, warmup, with_compile)

    first = best = attempt(compile_time)
    while (
        best.available
        and (best.other_cpu_load or 0.0) > BUSY_WARNING
        and wait_quiet_s > 0
        and time.monotonic() < deadline
    ):
        retry = attempt(False)
        retry.attempts = best.attempts + 1
        if (retry.other_cpu_load or 0.0) < (best.other_cpu_load or 0.0):
            retry.first_call_ms, retry.numba_cache = first.first_call_ms, first.numba_cache
            retry.jit_compile_ms = first.jit_compile_ms
            best = retry
        else:
            best.attempts = retry.attempts
    return best


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
#: The project's speed targets: (name, candidate key, figure, limit, unit, limit is a maximum).
TARGETS: tuple[tuple[str, str, str, float, str, bool], ...] = (
    ("super-pixel median time", "pihim_superpixel", "median_ms", 10.0, "ms", True),
    ("super-pixel speed-up vs numpy", "pihim_superpixel", "speedup_vs_numpy", 5.0, "x", False),
    ("super-pixel speed-up vs polanalyser", "pihim_superpixel", "speedup_vs_polanalyser", 50.0, "x", False),
    ("full-resolution median time", "pihim_full", "median_ms", 60.0, "ms", True),
)


def evaluate_targets(by_key: dict[str, Measurement]) -> list[dict[str, Any]]:
    """Compare the figures with :data:`TARGETS`.

    ``passed`` is ``None`` when a figure needed for the target is missing.
    """
    verdicts = []
    for name, key, figure, limit, unit, at_most in TARGETS:
        m = by_key.get(key)
        verdicts.append(harness.target(name, None if m is None else getattr(m, figure), limit, unit, at_most=at_most))
    return verdicts


def machine_info() -> dict[str, Any]:
    """What the figures depend on: CPU, threads and library versions."""
    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel kernel has run yet
        layer = None
    return {
        "cpu_model": harness.cpu_model(),
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "numba_threads": numba.get_num_threads(),
        "numba_threading_layer": layer,
        "opencv": cv2.__version__,
        "opencv_threads": cv2.getNumThreads(),
        "polanalyser": importlib.metadata.version("polanalyser") if pa is not None else None,
        "pihim": importlib.metadata.version("pihim"),
        "openblas_env": {k: v for k, v in os.environ.items() if k.startswith("OPENBLAS_")},
    }


def _fmt(value: float | None, spec: str = ".1f", suffix: str = "") -> str:
    return "-" if value is None else f"{value:{spec}}{suffix}"


def _mb(nbytes: int | None) -> str:
    return "-" if nbytes is None else f"{nbytes / 1e6:.1f}"


def markdown_report(report: dict[str, Any]) -> str:
    """The results as markdown: figures, targets, checks, machine and notes."""
    frame, settings = report["frame"], report["settings"]
    lines = [
        f"Frame: {frame['width']}x{frame['height']} uint16, {frame['bit_depth']}-bit synthetic heliostat scene "
        f"(seed {frame['seed']}, {100 * frame['fraction_saturated']:.2f} % saturated pixels); "
        f"{settings['repeat']} timed calls after {settings['warmup']} warm-ups.",
        "",
        "| Implementation | Output | Median ms | p10 ms | p90 ms | vs numpy | vs polanalyser "
        "| Peak traced MB | Output MB | First call ms | JIT compile ms | Other CPU % |",
        "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for m in report["results"]:
        if not m["available"]:
            lines.append(f"| {m['label']} | {m['resolution']} | {m['reason']} |" + " |" * 9)
            continue
        first = _fmt(m["first_call_ms"])
        if m["numba_cache"] is not None:
            first += f" (cache {m['numba_cache']})"
        load = None if m["other_cpu_load"] is None else 100 * m["other_cpu_load"]
        lines.append(
            f"| {m['label']} | {m['resolution']} | {_fmt(m['median_ms'])} | {_fmt(m['p10_ms'])} "
            f"| {_fmt(m['p90_ms'])} | {_fmt(m['speedup_vs_numpy'], '.2f', 'x')} "
            f"| {_fmt(m['speedup_vs_polanalyser'], '.1f', 'x')} | {_mb(m['peak_traced_bytes'])} "
            f"| {_mb(m['output_bytes'])} | {first} | {_fmt(m['jit_compile_ms'], '.0f')} | {_fmt(load, '.0f')} |"
        )
    busiest = max((m["other_cpu_load"] or 0.0 for m in report["results"]), default=0.0)
    if busiest > BUSY_WARNING:
        lines += [
            "",
            f"**Warning:** other processes used up to {100 * busiest:.0f} % of the CPUs while timing; "
            "the figures are inflated (rerun on an idle machine, e.g. with --wait-quiet 300).",
        ]

    lines += harness.target_table(report["targets"], spec=".2f", unit_spec={"ms": ".1f"}, column="Result", align="--:")

    lines += [
        "",
        "| Check (not timed) | Uniform field: max DoLP / AoP error | vs numpy anchor: max S0 / DoLP / AoP difference |",
        "|---|---|---|",
    ]
    for m in report["results"]:
        c = m["checks"]
        if not c:
            continue
        uniform = (
            f"{'ok' if c['uniform_ok'] else 'FAIL'}: {c['uniform_max_abs_dolp_error']:.1e} / "
            f"{c['uniform_max_aop_error_deg']:.1e} deg"
        )
        anchor = "-"
        if "agrees_with_anchor" in c:
            anchor = (
                f"{'ok' if c['agrees_with_anchor'] else 'DIFFERS'}: {c['max_abs_diff_s0']:.1e} / "
                f"{c['max_abs_diff_dolp']:.1e} / {c['max_abs_diff_aop_deg']:.1e} deg"
            )
        lines.append(f"| {m['label']} | {uniform} | {anchor} |")

    mach = report["machine"]
    polanalyser_version = mach["polanalyser"] or "not installed"
    lines += [
        "",
        f"Machine: {mach['cpu_model']}, {mach['cpu_count']} cores (os.cpu_count), numba {mach['numba']} "
        f"with {mach['numba_threads']} threads ({mach['numba_threading_layer']}), numpy {mach['numpy']}, "
        f"OpenCV {mach['opencv']} ({mach['opencv_threads']} threads), polanalyser {polanalyser_version}, "
        f"Python {mach['python']}.",
        "",
        *[f"- {note}" for note in report["notes"]],
    ]
    return "\n".join(lines)


NOTES = (
    "Each call takes the raw frame and returns newly allocated outputs; times are wall-clock "
    "(time.perf_counter_ns) with the garbage collector paused.",
    "vs numpy / vs polanalyser: median time of the reference divided by the row's median (higher is faster).",
    "polanalyser works at full resolution (4x the pixels of the super-pixel routes) in float64, so "
    "'super-pixel vs polanalyser' compares different products; pihim full vs polanalyser is like for like. "
    "Its channel list is 0/45/90/135 deg for the IMX250MZR layout, like pihim's, but it stores Stokes "
    "channels-last and AoLP in radians; for timing this does not matter, and the uniform-field check "
    "confirms it recovers the same DoLP and AoP.",
    "Peak traced MB: tracemalloc peak during one call (numpy and OpenCV-returned arrays are traced; "
    "scratch allocated inside numba kernels, OpenCV or OpenBLAS is not). Output MB: bytes held by the "
    "returned arrays.",
    "First call: numba JIT compile or on-disk cache load (cache hit/miss shown) plus one run; "
    "JIT compile: cold compile of the same kernel on a fresh, uncached dispatcher.",
    "Other CPU %: share of the machine's CPU time used by other processes during the timed calls "
    "(from /proc/stat); on 2 cores a parallel kernel whose second thread loses its core waits for a "
    "whole scheduler slice, so only rows near 0 % are trustworthy.",
    "The pixel kernels use no BLAS, so OPENBLAS_CORETYPE/OPENBLAS_L2_SIZE (set on this machine, "
    "left unchanged) do not affect them; only polanalyser's calcStokes (a tensordot, i.e. a 3x4 by "
    "4xN dgemm) and polar_image's 4x3 pinv call OpenBLAS.",
)


def run_benchmark(
    repeat: int = COUNTS.repeat,
    warmup: int = COUNTS.warmup,
    seed: int = DEFAULT_SEED,
    compile_time: bool = True,
    wait_quiet_s: float = 0.0,
) -> dict[str, Any]:
    """Measure every candidate on one frame and return the JSON-ready report.

    With ``wait_quiet_s > 0``, see :func:`measure_when_quiet`.
    """
    mosaic = synthetic_frame(FRAME_SHAPE, seed)
    rows = candidates()
    measurements = [measure_when_quiet(c, mosaic, repeat, warmup, compile_time, wait_quiet_s) for c in rows]
    by_key = {m.key: m for m in measurements}

    anchor = by_key[ANCHOR]
    reference = by_key.get(POLANALYSER)
    for m in measurements:
        if not m.available or m.median_ms is None:
            continue
        m.speedup_vs_numpy = anchor.median_ms / m.median_ms if anchor.median_ms else None
        if reference is not None and reference.median_ms:
            m.speedup_vs_polanalyser = reference.median_ms / m.median_ms

    anchor_out = numpy_superpixel(mosaic)
    for c, m in zip(rows, measurements, strict=True):
        if not m.available:
            continue
        m.checks = uniform_field_check(c)
        if c.resolution == "super-pixel" and c.key != ANCHOR:
            m.checks.update(agreement_check(c, mosaic, anchor_out))

    notes = [c.note for c in rows if c.note] + list(NOTES)
    if pa is None:
        notes.insert(0, "polanalyser is not installed (pip install polanalyser): its row and target are skipped.")
    return {
        "benchmark": "polar",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "frame": {
            "height": int(mosaic.shape[0]),
            "width": int(mosaic.shape[1]),
            "dtype": str(mosaic.dtype),
            "bit_depth": BIT_DEPTH,
            "seed": seed,
            "min": int(mosaic.min()),
            "max": int(mosaic.max()),
            "fraction_saturated": float(np.mean(mosaic >= 2**BIT_DEPTH - 1)),
        },
        "settings": {"repeat": repeat, "warmup": warmup, "compile_time": compile_time, "wait_quiet_s": wait_quiet_s},
        "machine": machine_info(),
        "results": [vars(m) for m in measurements],
        "targets": evaluate_targets(by_key),
        "notes": notes,
    }


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
    """Run the benchmark, print the markdown report and write the JSON.

    Parameters
    ----------
    argv : sequence of str, optional
        Command-line arguments (``--repeat N``, ``--warmup N``, ``--quick``,
        ``--json PATH``, ``--seed N``, ``--wait-quiet S``); ``None`` or empty
        reads nothing.
    repeat, warmup : int, optional
        Timed and untimed calls per implementation; default 30 and 3, or 5
        and 1 with ``quick``.
    quick : bool
        Fewer calls and no cold-compile measurement, for a fast look.
    seed : int
        Seed of the synthetic frame.
    json_path : pathlib.Path or None
        Where to write the JSON report (directories are created); ``None``
        writes nothing.
    wait_quiet : float
        Seconds each implementation may wait for other processes to leave
        the CPUs idle before it is timed (0: do not wait).
    echo : bool
        Print the markdown report.

    Returns
    -------
    dict
        The report (also written to ``json_path``); its ``targets`` entries
        carry ``passed`` flags.
    """

    def configure(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--seed", type=int, help=f"seed of the synthetic frame (default {DEFAULT_SEED})")
        parser.add_argument("--wait-quiet", type=float, metavar="S",
                            help="wait and retry up to S s per implementation for idle CPUs")

    o = harness.options(argv, description=__doc__.split("\n\n")[0], counts=COUNTS, repeat=repeat, warmup=warmup,
                        quick=quick, json_path=json_path, configure=configure)
    if o.args is not None:
        seed = o.args.seed if o.args.seed is not None else seed
        wait_quiet = o.args.wait_quiet if o.args.wait_quiet is not None else wait_quiet
    report = run_benchmark(repeat=o.repeat, warmup=o.warmup, seed=seed, compile_time=not o.quick,
                           wait_quiet_s=wait_quiet)
    report["settings"]["quick"] = o.quick
    if echo:
        print(markdown_report(report))
    harness.write_json(report, o.json_path, announce=echo)
    return report


if __name__ == "__main__":
    main(sys.argv[1:] or None)
