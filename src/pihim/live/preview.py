"""Fast preview images of a polar image for the live view: S0 grey, DoLP viridis, AoP cyclic hue, as JPEG.

The colours are those of :mod:`pihim.visualize` (``pihim polar --png``),
evaluated once into look-up tables so that a frame costs a few table reads
per pixel: S0 stretched between its 0.5 and 99.5 percentiles, DoLP on
viridis over ``[0, dolp_max]``, AoP as hue (0 and 180 deg the same colour,
counter-clockwise from image right) with brightness ``DoLP / dolp_max``.
Masked pixels (saturated super-pixels: DoLP and AoP NaN) are black in DoLP
and AoP. Images larger than ``max_side`` are decimated (every k-th pixel,
which keeps DoLP and AoP values unmixed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from pihim.errors import PihimInputError

#: AoP bins of the colour table (1 deg) and DoLP levels of its brightness.
_AOP_BINS = 180
_DOLP_LEVELS = 64


@dataclass(frozen=True)
class PreviewImages:
    """Encoded previews of one frame.

    Attributes
    ----------
    s0, dolp, aop : bytes
        JPEG images of the same size.
    width, height : int
        Preview size in pixels.
    step : int
        Decimation from the polar image (preview pixel ``(i, j)`` is polar
        pixel ``(step * i, step * j)``).
    """

    s0: bytes
    dolp: bytes
    aop: bytes
    width: int
    height: int
    step: int


class PreviewRenderer:
    """Turns S0, DoLP and AoP images into small JPEG previews, fast.

    Parameters
    ----------
    max_side : int
        Largest preview side, pixels (the polar image is decimated by the
        smallest integer step that fits).
    quality : int
        JPEG quality, 1-100.
    dolp_max : float
        DoLP shown at full colour (and full AoP brightness).
    """

    def __init__(self, max_side: int = 640, quality: int = 80, dolp_max: float = 1.0) -> None:
        from pihim.visualize import aop_to_rgb, dolp_to_rgb

        if not 16 <= int(max_side) <= 8192:
            raise PihimInputError(f"preview size must be in 16..8192 px, got {max_side!r}")
        if not 1 <= int(quality) <= 100:
            raise PihimInputError(f"JPEG quality must be in 1..100, got {quality!r}")
        if not (math.isfinite(dolp_max) and 0 < dolp_max <= 1):
            raise PihimInputError(f"dolp_max must be in (0, 1], got {dolp_max!r}")
        self.max_side = int(max_side)
        self.quality = int(quality)
        self.dolp_max = float(dolp_max)
        # DoLP: 256 levels over [0, dolp_max] plus a black entry for NaN; BGR for OpenCV
        levels = np.linspace(0.0, self.dolp_max, 256)
        lut = np.zeros((257, 3), np.uint8)
        lut[:256] = dolp_to_rgb(levels[None, :], vmax=self.dolp_max)[0][:, ::-1]
        self._dolp_lut = lut
        # AoP: hue bin x DoLP level, plus a black entry for NaN
        a = (np.arange(_AOP_BINS) + 0.5) * (180.0 / _AOP_BINS)
        d = np.linspace(0.0, self.dolp_max, _DOLP_LEVELS)
        aa, dd = np.meshgrid(a, d, indexing="ij")
        rgb = aop_to_rgb(aa, dd, dolp_max=self.dolp_max).reshape(-1, 3)
        lut2 = np.zeros((_AOP_BINS * _DOLP_LEVELS + 1, 3), np.uint8)
        lut2[:-1] = rgb[:, ::-1]
        self._aop_lut = lut2
        self._params = [int(cv2.IMWRITE_JPEG_QUALITY), self.quality]

    def step_for(self, shape: tuple[int, int]) -> int:
        """Decimation step for a polar image of ``shape``."""
        return max(1, int(math.ceil(max(shape) / self.max_side)))

    def _encode(self, img: NDArray[np.uint8]) -> bytes:
        ok, buf = cv2.imencode(".jpg", img, self._params)
        if not ok:  # pragma: no cover - OpenCV always encodes uint8 images
            raise RuntimeError("JPEG encoding failed")
        return buf.tobytes()

    def render(self, s0: NDArray, dolp: NDArray, aop_deg: NDArray) -> PreviewImages:
        """JPEG previews of one polar image (float32 arrays of the same 2-D shape).

        One compiled pass (:func:`pihim.live._kernels.colorize`) decimates
        and colours the three images through the tables, then OpenCV encodes
        them.
        """
        from pihim.live import _kernels

        step = self.step_for(s0.shape)
        oh, ow = -(-s0.shape[0] // step), -(-s0.shape[1] // step)
        sub = s0[:: max(1, s0.shape[0] // 200), :: max(1, s0.shape[1] // 200)]
        finite = sub[np.isfinite(sub)]
        lo, hi = np.percentile(finite, (0.5, 99.5)) if finite.size else (0.0, 0.0)
        if not hi > lo:  # nothing to stretch (a frame clipped everywhere): its level against 0, white unless 0
            lo, hi = 0.0, max(float(hi), 0.0)
        scale = 255.0 / (hi - lo) if hi > lo else 0.0
        g = np.empty((oh, ow), np.uint8)
        d = np.empty((oh, ow, 3), np.uint8)
        a = np.empty((oh, ow, 3), np.uint8)
        _kernels.colorize(np.asarray(s0, np.float32), np.asarray(dolp, np.float32), np.asarray(aop_deg, np.float32),
                          step, float(lo), float(scale), 255.0 / self.dolp_max, self._dolp_lut, _AOP_BINS,
                          _DOLP_LEVELS, self._aop_lut, g, d, a)
        return PreviewImages(self._encode(g), self._encode(d), self._encode(a), ow, oh, step)
