"""Fused numba kernels: raw mosaic -> S0, S1, S2, DoLP, AoP in one pass.

The kernels are the fast paths of :mod:`pihim.camera.pipeline`; the pure numpy
routes in :mod:`pihim.camera.demosaic` define what they must compute and are
what the tests compare them against.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from pihim._fastmath import atan2_f32
from pihim._quantiles import finite_bits, order_key

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


@njit(parallel=True, fastmath=FASTMATH, cache=True, nogil=True)
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


# -- full-resolution route -------------------------------------------------------------

#: Same value as :data:`pihim.camera.demosaic.FULLRES_GRAD_EPS` (the definition).
_FR_EPS = np.float32(1e-2)
#: Output rows per parallel work item of :func:`fullres_polar`. Its scratch
#: (about 36 bytes per output pixel plus halo rows: 1.4 MB for 16 rows of a
#: 2448-px-wide frame) stays within a per-core L2 cache.
_FR_BLOCK_ROWS = 16


@njit(inline="always", cache=True)
def _reflect(k, n):  # pragma: no cover - compiled
    """Index ``k`` mirrored into ``[0, n)`` without repeating the edge (any ``k``, ``n >= 2``)."""
    period = 2 * (n - 1)
    k = k % period
    return period - k if k >= n else k


@njit(parallel=True, fastmath=FASTMATH, cache=True, nogil=True)
def fullres_polar(raw, w_pos, dark, sat_level, s0, s1, s2, dolp, aop, saturated):  # pragma: no cover
    """Full-resolution Stokes of a raw mosaic, written into preallocated outputs.

    Implements :func:`pihim.camera.demosaic.full_resolution` (edge-aware
    interpolation in the channel-difference domain; see its docstring for
    the method and references) in float32, fused with the Stokes
    reconstruction, DoLP and AoP. Work is split into bands of
    :data:`_FR_BLOCK_ROWS` rows; each band mirrors the raw rows it needs
    into a small padded float32 scratch (so borders need no special cases),
    computes the horizontal and vertical neighbour channels with their
    direction weights for its rows plus one halo row, then the diagonal
    channel and the outputs.

    Parameters
    ----------
    raw : (H, W) integer or float array
    w_pos : (3, 4) float32
        Pseudo-inverse of the analyser matrix with its columns reordered by
        super-pixel position ``2 * row + col``. Pixel ``(i, j)`` sits at
        position ``p = 2 * (i % 2) + (j % 2)``; its own, horizontal-,
        vertical- and diagonal-neighbour channels are at positions ``p``,
        ``p ^ 1``, ``p ^ 2`` and ``p ^ 3``, which makes the kernel
        independent of the mosaic layout.
    dark : float32
        Dark level subtracted from every pixel.
    sat_level : float32
        Raw values ``>= sat_level`` are saturated; an output pixel is flagged
        when any raw pixel of its support
        (:func:`pihim.camera.demosaic.full_resolution_support`, mirrored at
        the borders like the data) is.
    s0, s1, s2, dolp, aop : (H, W) float32 outputs
    saturated : (H, W) bool output
    """
    h, w = s0.shape
    eps = _FR_EPS
    half = np.float32(0.5)
    # role coefficients: S[comp] = sum_role coef[p, comp, role] * value[role]
    coef = np.empty((4, 3, 4), dtype=np.float32)
    for p in range(4):
        for comp in range(3):
            for role in range(4):
                coef[p, comp, role] = w_pos[comp, p ^ role]
    nblk = (h + _FR_BLOCK_ROWS - 1) // _FR_BLOCK_ROWS
    for b in prange(nblk):
        r0 = b * _FR_BLOCK_ROWS
        r1 = min(h, r0 + _FR_BLOCK_ROWS)
        nr = r1 - r0
        # x[k, q] = raw[r0 - 4 + k, q - 4] - dark (mirrored); sp likewise, saturated flags
        x = np.empty((nr + 8, w + 8), dtype=np.float32)
        sp = np.empty((nr + 8, w + 8), dtype=np.uint8)
        for k in range(nr + 8):
            ri = _reflect(r0 - 4 + k, h)
            for q in range(4, w + 4):
                v = np.float32(raw[ri, q - 4])
                x[k, q] = v - dark
                sp[k, q] = v >= sat_level
            for q in range(4):
                qa = _reflect(q - 4, w) + 4
                qb = _reflect(w + q, w) + 4
                x[k, q] = x[k, qa]
                sp[k, q] = sp[k, qa]
                x[k, w + 4 + q] = x[k, qb]
                sp[k, w + 4 + q] = sp[k, qb]
        # horizontal saturation bits for image rows r0-3 .. r1+2 (k = row - r0 + 3):
        # bit0 any in j-1..j+1, bit1 any in j-2..j+2, bit2 any in j-3..j+3
        hb = np.empty((nr + 6, w), dtype=np.uint8)
        for k in range(nr + 6):
            for j in range(w):
                q = j + 4
                a1 = sp[k + 1, q - 1] | sp[k + 1, q] | sp[k + 1, q + 1]
                a2 = a1 | sp[k + 1, q - 2] | sp[k + 1, q + 2]
                a3 = a2 | sp[k + 1, q - 3] | sp[k + 1, q + 3]
                hb[k, j] = a1 | (a2 << 1) | (a3 << 2)
        # stage 1 on image rows r0-1 .. r1 and cols -1 .. w (index [k, q], row r0-1+k, col q-1)
        hv = np.empty((nr + 2, w + 2), dtype=np.float32)
        vv = np.empty((nr + 2, w + 2), dtype=np.float32)
        ww = np.empty((nr + 2, w + 2), dtype=np.float32)
        we = np.empty((nr + 2, w + 2), dtype=np.float32)
        wn = np.empty((nr + 2, w + 2), dtype=np.float32)
        ws = np.empty((nr + 2, w + 2), dtype=np.float32)
        for k in range(nr + 2):
            y = k + 3  # row in x
            for q in range(w + 2):
                z = q + 3  # col in x
                c = x[y, z]
                xw1 = x[y, z - 1]
                xw2 = x[y, z - 2]
                xe1 = x[y, z + 1]
                xe2 = x[y, z + 2]
                xn1 = x[y - 1, z]
                xn2 = x[y - 2, z]
                xs1 = x[y + 1, z]
                xs2 = x[y + 2, z]
                g_w = (abs(c - xw2) + half * abs(xw1 - x[y, z - 3])
                       + abs(xn1 - x[y - 1, z - 2]) + abs(xs1 - x[y + 1, z - 2]))
                g_e = (abs(c - xe2) + half * abs(xe1 - x[y, z + 3])
                       + abs(xn1 - x[y - 1, z + 2]) + abs(xs1 - x[y + 1, z + 2]))
                g_n = (abs(c - xn2) + half * abs(xn1 - x[y - 3, z])
                       + abs(xe1 - x[y - 2, z + 1]) + abs(xw1 - x[y - 2, z - 1]))
                g_s = (abs(c - xs2) + half * abs(xs1 - x[y + 3, z])
                       + abs(xe1 - x[y + 2, z + 1]) + abs(xw1 - x[y + 2, z - 1]))
                a_w = np.float32(1.0) / (eps + g_w)
                a_e = np.float32(1.0) / (eps + g_e)
                a_n = np.float32(1.0) / (eps + g_n)
                a_s = np.float32(1.0) / (eps + g_s)
                eh = (a_w * (xw1 + half * (c - xw2)) + a_e * (xe1 + half * (c - xe2))) / (a_w + a_e)
                ev = (a_n * (xn1 + half * (c - xn2)) + a_s * (xs1 + half * (c - xs2))) / (a_n + a_s)
                hv[k, q] = min(max(eh, min(xw1, xe1)), max(xw1, xe1))
                vv[k, q] = min(max(ev, min(xn1, xs1)), max(xn1, xs1))
                ww[k, q] = a_w
                we[k, q] = a_e
                wn[k, q] = a_n
                ws[k, q] = a_s
        # stage 2 (diagonal channel) and outputs for rows r0 .. r1-1
        for i in range(r0, r1):
            k = i - r0 + 1  # row in hv & co
            y = k + 3  # row in x
            t = i - r0 + 3  # row in hb
            ip = 2 * (i % 2)
            c00, c01, c02, c03 = coef[ip, 0, 0], coef[ip, 0, 1], coef[ip, 0, 2], coef[ip, 0, 3]
            c10, c11, c12, c13 = coef[ip, 1, 0], coef[ip, 1, 1], coef[ip, 1, 2], coef[ip, 1, 3]
            c20, c21, c22, c23 = coef[ip, 2, 0], coef[ip, 2, 1], coef[ip, 2, 2], coef[ip, 2, 3]
            d00 = coef[ip + 1, 0, 0] - c00
            d01 = coef[ip + 1, 0, 1] - c01
            d02 = coef[ip + 1, 0, 2] - c02
            d03 = coef[ip + 1, 0, 3] - c03
            d10 = coef[ip + 1, 1, 0] - c10
            d11 = coef[ip + 1, 1, 1] - c11
            d12 = coef[ip + 1, 1, 2] - c12
            d13 = coef[ip + 1, 1, 3] - c13
            d20 = coef[ip + 1, 2, 0] - c20
            d21 = coef[ip + 1, 2, 1] - c21
            d22 = coef[ip + 1, 2, 2] - c22
            d23 = coef[ip + 1, 2, 3] - c23
            for j in range(w):
                q = j + 1  # col in hv & co
                z = j + 4  # col in x
                c = x[y, z]
                h0 = hv[k, q]
                v0 = vv[k, q]
                a_w = ww[k, q]
                a_e = we[k, q]
                a_n = wn[k, q]
                a_s = ws[k, q]
                num = (a_w * (h0 + vv[k, q - 1] - x[y, z - 1]) + a_e * (h0 + vv[k, q + 1] - x[y, z + 1])
                       + a_n * (v0 + hv[k - 1, q] - x[y - 1, z]) + a_s * (v0 + hv[k + 1, q] - x[y + 1, z]))
                dd = num / (a_w + a_e + a_n + a_s)
                x1 = x[y - 1, z - 1]
                x2 = x[y - 1, z + 1]
                x3 = x[y + 1, z - 1]
                x4 = x[y + 1, z + 1]
                lo = min(min(x1, x2), min(x3, x4))
                hi = max(max(x1, x2), max(x3, x4))
                d0 = min(max(dd, lo), hi)
                f = np.float32(j & 1)
                a0 = (c00 + f * d00) * c + (c01 + f * d01) * h0 + (c02 + f * d02) * v0 + (c03 + f * d03) * d0
                a1 = (c10 + f * d10) * c + (c11 + f * d11) * h0 + (c12 + f * d12) * v0 + (c13 + f * d13) * d0
                a2 = (c20 + f * d20) * c + (c21 + f * d21) * h0 + (c22 + f * d22) * v0 + (c23 + f * d23) * d0
                sat = (((hb[t - 3, j] | hb[t + 3, j]) & 1) | ((hb[t - 2, j] | hb[t + 2, j]) & 2)
                       | ((hb[t - 1, j] | hb[t, j] | hb[t + 1, j]) & 4)) != 0
                s0[i, j] = a0
                s1[i, j] = a1
                s2[i, j] = a2
                p, a = _finish(a0, a1, a2, sat)
                dolp[i, j] = p
                aop[i, j] = a
                saturated[i, j] = sat


# -- frame statistics ---------------------------------------------------------------------


@njit(parallel=True, cache=True, nogil=True)
def frame_moments(s0, s1, s2, dolp, saturated, hist_s0, hist_dolp, sums):  # pragma: no cover - compiled
    """One pass over a :class:`~pihim.camera.pipeline.PolarImage` for its summary statistics.

    A pixel is valid where ``dolp`` is finite. Per band of rows ``c``
    (``hist_s0.shape[0]`` bands) it accumulates:

    * ``hist_s0[c]``, ``hist_dolp[c]``: histograms of the upper 16 bits of
      the order keys (:func:`pihim._quantiles.order_key`) of the valid S0
      (where finite, as :func:`pihim._quantiles.gather_bins` selects them)
      and DoLP values, for exact percentiles;
    * ``sums[c]``: valid count, saturated count, sums of the valid S0 and
      DoLP, and sums of ``(S1, S2) / |(S1, S2)|`` (the unit vector of twice
      the exact AoP; ``(1, 0)`` where ``S1 = S2 = 0``, where the AoP image
      is 0 too), all in float64.

    Parameters
    ----------
    s0, s1, s2, dolp : (H, W) float32
    saturated : (H, W) bool
    hist_s0, hist_dolp : (n_chunks, 65536) int64, zeroed
    sums : (n_chunks, 6) float64, zeroed
    """
    n_rows, n_cols = s0.shape
    n_chunks = sums.shape[0]
    s0_bits = s0.view(np.uint32)
    dolp_bits = dolp.view(np.uint32)
    for c in prange(n_chunks):
        n_valid = 0
        n_sat = 0
        sum_s0 = 0.0
        sum_dolp = 0.0
        sum_c = 0.0
        sum_s = 0.0
        for i in range(c * n_rows // n_chunks, (c + 1) * n_rows // n_chunks):
            for j in range(n_cols):
                if saturated[i, j]:
                    n_sat += 1
                d = dolp[i, j]
                if not math.isfinite(d):
                    continue
                n_valid += 1
                b = s0_bits[i, j]
                if finite_bits(b):  # always, unless float input overflowed
                    hist_s0[c, order_key(b) >> 16] += 1
                hist_dolp[c, order_key(dolp_bits[i, j]) >> 16] += 1
                sum_s0 += np.float64(s0[i, j])
                sum_dolp += np.float64(d)
                x = np.float64(s1[i, j])
                y = np.float64(s2[i, j])
                r = math.sqrt(x * x + y * y)
                if r > 0.0:
                    sum_c += x / r
                    sum_s += y / r
                else:
                    sum_c += 1.0
        sums[c, 0] = n_valid
        sums[c, 1] = n_sat
        sums[c, 2] = sum_s0
        sums[c, 3] = sum_dolp
        sums[c, 4] = sum_c
        sums[c, 5] = sum_s
