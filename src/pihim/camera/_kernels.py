"""Fused numba kernels: raw mosaic -> S0, S1, S2, DoLP, AoP in one pass.

The kernels are the fast paths of :mod:`pihim.camera.pipeline`; the pure numpy
routes in :mod:`pihim.camera.demosaic` define what they must compute and are
what the tests compare them against.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from pihim._fastmath import atan2_f32

#: LLVM fast-math flags that keep NaN and inf semantics (masked pixels are NaN).
FASTMATH = {"contract", "afn", "reassoc", "arcp", "nsz"}

_RAD2DEG_HALF = np.float32(90.0 / np.pi)  # 0.5 * 180 / pi


@njit(fastmath=FASTMATH, inline="always", cache=True)
def _finish(s0, s1, s2, sat):  # pragma: no cover - compiled
    """DoLP and AoP (deg, [0, 180)) of one pixel; NaN when saturated or S0 <= 0."""
    if sat or not s0 > 0:
        return np.float32(np.nan), np.float32(np.nan)
    p = np.sqrt(s1 * s1 + s2 * s2) / s0
    a = _RAD2DEG_HALF * atan2_f32(s2, s1)
    if a < 0:
        a += np.float32(180.0)
    if a >= np.float32(180.0):
        a -= np.float32(180.0)
    return p, a


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def superpixel_polar(raw, w_pos, dark, sat_level, s0, s1, s2, dolp, aop, saturated):  # pragma: no cover
    """Super-pixel Stokes of a raw mosaic, written into preallocated outputs.

    Parameters
    ----------
    raw : (H, W) integer or float array
    w_pos : (3, 4) float32
        Pseudo-inverse of the analyser matrix with its columns reordered by
        super-pixel position ``2 * row + col``.
    dark : float32
        Dark level subtracted from every pixel.
    sat_level : float32
        Raw values ``>= sat_level`` mark the super-pixel saturated.
    s0, s1, s2, dolp, aop : (H/2, W/2) float32 outputs
    saturated : (H/2, W/2) bool output
    """
    h, w = s0.shape
    for i in prange(h):
        for j in range(w):
            v0 = np.float32(raw[2 * i, 2 * j])
            v1 = np.float32(raw[2 * i, 2 * j + 1])
            v2 = np.float32(raw[2 * i + 1, 2 * j])
            v3 = np.float32(raw[2 * i + 1, 2 * j + 1])
            sat = (v0 >= sat_level) | (v1 >= sat_level) | (v2 >= sat_level) | (v3 >= sat_level)
            v0 -= dark
            v1 -= dark
            v2 -= dark
            v3 -= dark
            a0 = w_pos[0, 0] * v0 + w_pos[0, 1] * v1 + w_pos[0, 2] * v2 + w_pos[0, 3] * v3
            a1 = w_pos[1, 0] * v0 + w_pos[1, 1] * v1 + w_pos[1, 2] * v2 + w_pos[1, 3] * v3
            a2 = w_pos[2, 0] * v0 + w_pos[2, 1] * v1 + w_pos[2, 2] * v2 + w_pos[2, 3] * v3
            s0[i, j] = a0
            s1[i, j] = a1
            s2[i, j] = a2
            p, a = _finish(a0, a1, a2, sat)
            dolp[i, j] = p
            aop[i, j] = a
            saturated[i, j] = sat
