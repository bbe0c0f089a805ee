"""Raw DoFP mosaic -> Stokes, DoLP and AoP images (the live-processing path).

:func:`polar_image` is the entry point. It resolves the bit depth (including
12-bit data stored in 16-bit containers), subtracts the dark level, flags
saturated super-pixels and runs one of the fused numba kernels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from pihim.camera.layout import IMX250MZR, MosaicLayout, check_mosaic_shape
from pihim.errors import PihimInputError
from pihim.polarimetry.analyser import AnalyserMatrix

DemosaicMethod = Literal["superpixel", "full"]
DEMOSAIC_METHODS: tuple[str, ...] = ("superpixel", "full")


@dataclass(frozen=True)
class BitDepth:
    """How raw values map to the ADC range.

    Attributes
    ----------
    bits : int
        ADC resolution (8, 10, 12, 14 or 16).
    shift : int
        Right shift applied to MSB-aligned data (e.g. 4 for 12-bit data
        stored in the high bits of 16-bit words).
    """

    bits: int
    shift: int = 0

    def __post_init__(self) -> None:
        for name, value, lo, hi in (("bits", self.bits, 1, 16), ("shift", self.shift, 0, 15)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
                raise PihimInputError(f"BitDepth.{name} must be an integer in {lo}..{hi}, got {value!r}")
        if self.bits + self.shift > 16:
            raise PihimInputError(f"{self.bits} bits shifted by {self.shift} do not fit a 16-bit word")

    @property
    def full_scale(self) -> int:
        """Largest raw value after the shift, ``2**bits - 1``."""
        return 2**self.bits - 1


def resolve_bit_depth(mosaic: NDArray, bits: int | None = None) -> BitDepth:
    """Decide the ADC bit depth of a raw mosaic.

    Parameters
    ----------
    mosaic : numpy.ndarray
        Unsigned-integer raw mosaic.
    bits : int, optional
        Known ADC resolution. If the data exceed ``2**bits - 1`` but every
        value is a multiple of ``2**(container_bits - bits)``, the data are
        taken as MSB-aligned and shifted down; otherwise an error is raised.
        If omitted: 8 for ``uint8``; for ``uint16``, 12 when all values fit
        in 12 bits or are 12-bit MSB-aligned, else 16.
    """
    if mosaic.dtype == np.uint8:
        container = 8
    elif mosaic.dtype == np.uint16:
        container = 16
    else:
        raise PihimInputError(f"raw mosaic must be uint8 or uint16, got {mosaic.dtype}")
    vmax = int(mosaic.max()) if mosaic.size else 0
    if bits is None:
        if container == 8:
            return BitDepth(8)
        if vmax <= 4095:
            return BitDepth(12)
        if not np.any(mosaic & np.uint16(0x000F)):
            return BitDepth(12, shift=4)
        return BitDepth(16)
    if not 1 <= bits <= container:
        raise PihimInputError(f"bit depth {bits} does not fit a {container}-bit container")
    if vmax <= 2**bits - 1:
        return BitDepth(bits)
    shift = container - bits
    if not np.any(mosaic & np.asarray(2**shift - 1, dtype=mosaic.dtype)):
        return BitDepth(bits, shift=shift)
    raise PihimInputError(
        f"raw values up to {vmax} exceed {bits}-bit full scale and are not MSB-aligned"
    )


@dataclass(frozen=True)
class PolarImage:
    """Polarimetric images computed from one raw frame.

    All images are float32 with the same shape (half the mosaic for the
    super-pixel route). ``dolp`` and ``aop_deg`` are NaN where the input was
    saturated or ``s0 <= 0``. AoP is in degrees in [0, 180), counter-clockwise
    from image right (see ``docs/conventions.md``).
    """

    s0: NDArray[np.float32]
    s1: NDArray[np.float32]
    s2: NDArray[np.float32]
    dolp: NDArray[np.float32]
    aop_deg: NDArray[np.float32]
    saturated: NDArray[np.bool_]
    demosaic: str
    bit_depth: BitDepth | None

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns) of the output images."""
        return self.s0.shape  # type: ignore[return-value]

    def summary(self) -> dict[str, Any]:
        """JSON-ready statistics (see ``schemas/polar-frame.schema.json``).

        Valid pixels are those with a finite DoLP (not saturated, S0 > 0).
        For S0 and DoLP over the valid pixels: ``mean`` is the float64 sum
        divided by their number (summed band by band, so it may differ from
        ``numpy.mean`` in the last digits); ``median``, ``p05`` and ``p95``
        are exactly ``numpy.percentile`` (default linear method) of the
        values. ``aop`` is the circular mean of twice the AoP, halved: the
        direction and length of the mean of the unit vectors ``(S1, S2) /
        |(S1, S2)|``, i.e. of the exact angle ``0.5 atan2(S2, S1)`` of which
        the AoP image is a polynomial approximation (within 1e-4 deg, so the
        two circular means differ by at most 1e-4 deg divided by the
        resultant length); pixels with ``S1 = S2 = 0`` count as angle 0, as
        in the AoP image.
        Computed in two parallel passes over the images
        (:func:`pihim.camera._kernels.frame_moments`,
        :func:`pihim._quantiles.order_statistics_pair`), without float64 copies.
        """
        from pihim import _quantiles
        from pihim.camera import _kernels

        n_pixels = int(self.s0.size)
        base: dict[str, Any] = {
            "height": int(self.shape[0]),
            "width": int(self.shape[1]),
            "demosaic": self.demosaic,
            "bit_depth": None if self.bit_depth is None else self.bit_depth.bits,
            "msb_shift": None if self.bit_depth is None else self.bit_depth.shift,
        }
        empty = {"mean": None, "median": None, "p05": None, "p95": None}
        if n_pixels == 0:
            return {**base, "fraction_saturated": 0.0, "fraction_valid": 0.0, "s0": dict(empty),
                    "dolp": dict(empty), "aop": {"circular_mean_deg": None, "resultant_length": None}}
        images = [np.ascontiguousarray(a) for a in (self.s0, self.s1, self.s2, self.dolp)]
        s0, s1, s2, dolp = (a if a.dtype == np.float32 else a.astype(np.float32) for a in images)
        saturated = np.ascontiguousarray(self.saturated, dtype=np.bool_)
        n_chunks = _quantiles.n_chunks_for(s0.shape[0])
        hist_s0 = np.zeros((n_chunks, _quantiles.N_BINS), dtype=np.int64)
        hist_dolp = np.zeros_like(hist_s0)
        sums = np.zeros((n_chunks, 6))
        _kernels.frame_moments(s0, s1, s2, dolp, saturated, hist_s0, hist_dolp, sums)
        n_valid, n_sat, sum_s0, sum_dolp, sum_c, sum_s = sums.sum(axis=0)
        n_valid = int(n_valid)

        q = (5.0, 50.0, 95.0)
        counts = [int(hist_s0.sum()), int(hist_dolp.sum())]
        ranks = [[r for lo, hi, _ in _quantiles.linear_positions(n, q) for r in (lo, hi)] if n else []
                 for n in counts]
        # the order statistics of both images in one more pass over them
        order = _quantiles.order_statistics_pair((s0, dolp), dolp, (ranks[0], ranks[1]), (hist_s0, hist_dolp))

        def _stats(n: int, order: dict[int, float], total: float) -> dict[str, float | None]:
            if n == 0:
                return dict(empty)
            p05, med, p95 = _quantiles.percentiles_from_statistics(n, q, order)
            return {"mean": float(total / n), "median": med, "p05": p05, "p95": p95}

        if n_valid:
            c, s = sum_c / n_valid, sum_s / n_valid
            aop = {
                "circular_mean_deg": float(np.mod(0.5 * math.degrees(math.atan2(s, c)), 180.0)),
                "resultant_length": float(math.hypot(c, s)),
            }
        else:
            aop = {"circular_mean_deg": None, "resultant_length": None}
        return {
            **base,
            "fraction_saturated": float(n_sat) / n_pixels,
            "fraction_valid": n_valid / n_pixels,
            "s0": _stats(counts[0], order[0], sum_s0),
            "dolp": _stats(counts[1], order[1], sum_dolp),
            "aop": aop,
        }


def _position_ordered_pinv(analyser: AnalyserMatrix, layout: MosaicLayout) -> NDArray[np.float32]:
    """Columns of ``pinv(A)`` reordered to super-pixel positions ``2*row + col``."""
    w = np.empty((3, 4), dtype=np.float32)
    for k, (r, c) in enumerate(layout.channel_positions):
        w[:, 2 * r + c] = analyser.pinv[:, k]
    return w


#: Outputs of at least this many bytes are one block aligned to :data:`_HUGE_PAGE` (see :func:`_new_outputs`).
_BLOCK_MIN_BYTES = 4 << 20
#: Size of a transparent huge page on x86-64 and arm64 Linux (4 KiB base pages).
_HUGE_PAGE = 2 << 20


def _new_outputs(shape: tuple[int, int]) -> tuple[NDArray, ...]:
    """Five float32 images and a bool mask of ``shape``, for one call's results.

    Large ones are views of a single block starting on a 2 MiB boundary:
    numpy asks Linux for transparent huge pages on allocations of 4 MB and
    more, and the block's fresh pages are then mapped and zeroed 2 MiB at a
    time -- 14 page faults for a super-pixel frame's 26 MB, against about
    2,800 for six separate arrays. With new pages every call, medians of
    2.6-3.0 ms per call in three runs (6.8 ms in a fourth, short one)
    against 4.2-8.0 ms for the same kernel writing six separate new arrays
    (``benchmarks/bench_polar.py`` on the idle 2-core benchmark machine,
    2026-11-28: how fast the kernel hands out pages varies from run to
    run).
    """
    n = shape[0] * shape[1]
    total = 5 * 4 * n + n
    if total < _BLOCK_MIN_BYTES:
        return (*(np.empty(shape, dtype=np.float32) for _ in range(5)), np.empty(shape, dtype=np.bool_))
    block = np.empty(total + _HUGE_PAGE, dtype=np.uint8)
    start = -block.ctypes.data % _HUGE_PAGE
    block = block[start:start + total]
    images = tuple(block[k * 4 * n:(k + 1) * 4 * n].view(np.float32).reshape(shape) for k in range(5))
    return (*images, block[5 * 4 * n:].view(np.bool_).reshape(shape))


def _checked_outputs(out: PolarImage, shape: tuple[int, int]) -> tuple[NDArray, ...]:
    """The arrays of ``out`` if they can receive a ``shape`` result, else a one-line error."""
    arrays = (out.s0, out.s1, out.s2, out.dolp, out.aop_deg, out.saturated)
    dtypes = (np.float32,) * 5 + (np.bool_,)
    for name, a, dt in zip(("s0", "s1", "s2", "dolp", "aop_deg", "saturated"), arrays, dtypes, strict=True):
        if not (isinstance(a, np.ndarray) and a.shape == shape and a.dtype == dt and a.flags.c_contiguous
                and a.flags.writeable):
            raise PihimInputError(
                f"out.{name} must be a writeable C-contiguous {np.dtype(dt).name} array of shape {shape}, got "
                f"{getattr(a, 'dtype', type(a).__name__)} of shape {getattr(a, 'shape', None)}"
            )
    return arrays


def polar_image(
    mosaic: NDArray,
    *,
    layout: MosaicLayout = IMX250MZR,
    analyser: AnalyserMatrix | None = None,
    demosaic: DemosaicMethod = "superpixel",
    dark_level: float = 0.0,
    bit_depth: int | None = None,
    saturation_level: float | None = None,
    out: PolarImage | None = None,
) -> PolarImage:
    """Compute S0, S1, S2, DoLP and AoP images from a raw DoFP mosaic.

    Parameters
    ----------
    mosaic : numpy.ndarray, shape (H, W), or RawFrame
        Raw mosaic, ``uint8`` or ``uint16`` (float arrays are accepted for
        synthetic data; they are not range-checked and saturate only at
        ``saturation_level``). H and W must be even. The
        :class:`~pihim.camera.frames.RawFrame` of
        :func:`~pihim.camera.frames.read_frame` is accepted as it is (its
        ``.data``, and its ``bit_depth`` unless ``bit_depth`` is given).
    layout : MosaicLayout
        Micro-polarizer arrangement; default IMX250MZR (90, 45 / 135, 0).
    analyser : AnalyserMatrix, optional
        Calibrated analyser; the ideal one (paper eq. 1) if omitted.
    demosaic : {"superpixel", "full"}
        ``superpixel`` gives (H/2, W/2) images; ``full`` gives (H, W).
    dark_level : float
        Dark level in raw units (after any MSB shift), subtracted first;
        >= 0.
    bit_depth : int, optional
        ADC bits; see :func:`resolve_bit_depth` for the automatic choice.
    saturation_level : float, optional
        Raw value at or above which a pixel counts as saturated; default the
        full scale ``2**bits - 1``. A super-pixel (or, for ``full``, an output
        pixel whose interpolation support) containing one is flagged and its
        DoLP and AoP are NaN.
    out : PolarImage, optional
        Preallocated outputs to write into (e.g. the result of an earlier
        call on a frame of the same size and ``demosaic``): its six arrays
        must have the output shape, be C-contiguous and of the dtypes
        ``polar_image`` returns. Saves allocating (and the operating system
        zeroing) about 26 MB per super-pixel frame and 105 MB per
        full-resolution frame. The arrays are overwritten.

    Returns
    -------
    PolarImage
        With ``out``, a new record holding ``out``'s arrays. Without it,
        the six arrays of a frame-sized result are views of one block of
        memory (fewer, larger pages to map): keeping one of them keeps the
        block (26 MB for a super-pixel frame), so copy an image you keep
        alone for long.
    """
    data = getattr(mosaic, "data", None)
    if isinstance(data, np.ndarray) and not isinstance(mosaic, np.ndarray):  # a RawFrame from read_frame
        if bit_depth is None:
            bit_depth = getattr(mosaic, "bit_depth", None)
        mosaic = data
    raw = np.asarray(mosaic)
    if raw.ndim != 2:
        raise PihimInputError(
            f"raw mosaic must be a 2-D array (or the RawFrame read_frame returns; its array is .data), "
            f"got {type(mosaic).__name__} of shape {raw.shape}"
        )
    check_mosaic_shape(raw)
    if demosaic not in DEMOSAIC_METHODS:
        raise PihimInputError(f"unknown demosaic method {demosaic!r}; choose one of {', '.join(DEMOSAIC_METHODS)}")
    if not isinstance(layout, MosaicLayout):
        raise PihimInputError(f"layout must be a MosaicLayout (MosaicLayout.parse('imx250mzr')), got {layout!r}")
    if analyser is not None and not isinstance(analyser, AnalyserMatrix):
        raise PihimInputError(f"analyser must be an AnalyserMatrix (AnalyserMatrix(matrix) for a 4x3 array), "
                              f"got {type(analyser).__name__}")
    for name, value in (("dark_level", dark_level), ("bit_depth", bit_depth), ("saturation_level", saturation_level)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float, np.integer,
                                                                                     np.floating))):
            raise PihimInputError(f"{name} must be a number, got {value!r}")
    if bit_depth is not None and not isinstance(bit_depth, (int, np.integer)):
        if not float(bit_depth).is_integer():
            raise PihimInputError(f"bit_depth must be a whole number of bits, got {bit_depth!r}")
        bit_depth = int(bit_depth)  # 12.0 (from a JSON file, say) is 12 bits
    if raw.dtype.kind == "f":
        depth = None
        sat = np.inf if saturation_level is None else float(saturation_level)
    else:
        depth = resolve_bit_depth(raw, bit_depth)
        if depth.shift:
            raw = raw >> depth.shift
        sat = float(depth.full_scale if saturation_level is None else saturation_level)
    f32_max = float(np.finfo(np.float32).max)  # the kernels work in float32
    if not math.isfinite(dark_level) or dark_level < 0:
        raise PihimInputError(f"dark level must be a finite number of raw units >= 0, got {dark_level:g}")
    if dark_level > f32_max:
        raise PihimInputError(f"dark level must be at most {f32_max:.4g} (float32), got {dark_level:g}")
    if not (sat > dark_level and (sat == np.inf or sat <= f32_max)):
        raise PihimInputError(f"saturation level must be above the dark level ({dark_level:g}) and at most "
                              f"{f32_max:.4g} (float32), got {sat:g}")
    w_pos = _position_ordered_pinv(analyser or AnalyserMatrix.ideal(), layout)
    h, w = raw.shape
    shape = (h // 2, w // 2) if demosaic == "superpixel" else (h, w)
    if out is None:
        s0, s1, s2, dolp, aop, saturated = _new_outputs(shape)
    else:
        s0, s1, s2, dolp, aop, saturated = _checked_outputs(out, shape)
    from pihim.camera import _kernels  # numba: imported on first use (keeps importing this module quick)

    kernel = _kernels.superpixel_polar if demosaic == "superpixel" else _kernels.fullres_polar
    kernel(raw, w_pos, np.float32(dark_level), np.float32(sat), s0, s1, s2, dolp, aop, saturated)
    return PolarImage(s0, s1, s2, dolp, aop, saturated, demosaic, depth)
