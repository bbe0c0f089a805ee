"""Compiled pixel loops of :mod:`pihim.visualize` (grey stretch, DoLP colour map, AoP hue).

Each kernel evaluates, pixel by pixel and in float64, the same expressions
as the numpy formulation documented in :mod:`pihim.visualize` (with numpy's
``mod`` and round-half-to-even ``rint`` semantics), so the images are
identical to it, without its float64 temporaries (about 20 full-size arrays
for an AoP image). Imported on first use: loading numba costs time that only
callers of these functions should pay.

The kernels run on the calling thread only (no ``prange``): ``pihim polar``
colours frames on its writer threads, several at once, and numba's
parallel launches are not safe from several threads under its fallback
(``workqueue``) threading layer. A super-pixel frame's three colourings
take about 8 ms of one core here.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(inline="always", cache=True)
def _mod1(h):  # pragma: no cover - compiled
    """``numpy.mod(h, 1.0)`` of a finite float.

    numpy computes ``fmod(h, 1)`` (exact) and adds 1 when it is negative:
    one rounding of the real number ``h - floor(h)``, which is what this
    computes, without the slow libm ``fmod``.
    """
    return h - np.floor(h)


@njit(inline="always", cache=True)
def _to_u8(x):  # pragma: no cover - compiled
    """``clip(rint(x * 255), 0, 255)`` as uint8 (NaN is not expected here)."""
    v = np.rint(x * 255.0)
    if v < 0.0:
        v = 0.0
    if v > 255.0:
        v = 255.0
    return np.uint8(v)


@njit(cache=True, nogil=True)
def gray_stretch(x, lo, hi, out):  # pragma: no cover - compiled
    """``out = u8(clip(nan_to_num((x - lo) / (hi - lo)), 0, 1))``, all 0 unless ``hi > lo``."""
    n_rows, n_cols = x.shape
    span = hi - lo
    for i in range(n_rows):
        for j in range(n_cols):
            s = 0.0
            if hi > lo:
                s = (np.float64(x[i, j]) - lo) / span
                if s != s:
                    s = 0.0
            s = min(max(s, 0.0), 1.0)
            out[i, j] = _to_u8(s)


@njit(cache=True, nogil=True)
def lut_colour(d, vmax, lut_u8, out):  # pragma: no cover - compiled
    """``out = lut_u8[clip(rint(d / vmax * 255), 0, 255)]``, black where ``d`` is not finite."""
    n_rows, n_cols = d.shape
    for i in range(n_rows):
        for j in range(n_cols):
            v = np.float64(d[i, j])
            if not math.isfinite(v):
                out[i, j, 0] = 0
                out[i, j, 1] = 0
                out[i, j, 2] = 0
                continue
            k = np.rint(v / vmax * 255.0)
            k = min(max(k, 0.0), 255.0)
            idx = int(k)
            out[i, j, 0] = lut_u8[idx, 0]
            out[i, j, 1] = lut_u8[idx, 1]
            out[i, j, 2] = lut_u8[idx, 2]


@njit(cache=True, nogil=True)
def hue_colour(aop, dolp, use_dolp, dolp_max, out):  # pragma: no cover - compiled
    """AoP as HSV hue (saturation 1), value 1 or ``clip(dolp / dolp_max, 0, 1)``; black where not finite.

    ``dolp`` is read only when ``use_dolp``. The branch-free sextant formulas
    of :func:`pihim.visualize._hsv_to_rgb`, operation for operation. A pixel
    that is not finite is computed as AoP 0 at value 0 (black) instead of
    being skipped, and each row's levels go through a small buffer before
    the interleaved RGB stores: the loop has no branch and vectorises (about
    3x faster than pixel by pixel with a branch, same pixels).
    """
    n_rows, n_cols = aop.shape
    for i in range(n_rows):
        levels = np.empty((3, n_cols))
        for j in range(n_cols):
            a = np.float64(aop[i, j])
            valid = math.isfinite(a)
            v = 1.0
            if use_dolp:
                d = np.float64(dolp[i, j])
                valid = valid & math.isfinite(d)
                v = min(max(d / dolp_max, 0.0), 1.0)
            v = v if valid else 0.0
            h6 = _mod1((a if valid else 0.0) / 180.0) * 6.0
            # v and the sextant terms lie in [0, 1]: rint(255 x) needs no clip (_to_u8)
            levels[0, j] = np.rint(v * min(max(abs(h6 - 3.0) - 1.0, 0.0), 1.0) * 255.0)
            levels[1, j] = np.rint(v * min(max(2.0 - abs(h6 - 2.0), 0.0), 1.0) * 255.0)
            levels[2, j] = np.rint(v * min(max(2.0 - abs(h6 - 4.0), 0.0), 1.0) * 255.0)
        for j in range(n_cols):
            out[i, j, 0] = np.uint8(levels[0, j])
            out[i, j, 1] = np.uint8(levels[1, j])
            out[i, j, 2] = np.uint8(levels[2, j])
