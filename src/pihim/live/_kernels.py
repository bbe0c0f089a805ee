"""Numba kernels of the live view: region histogram and a simulated exposure.

Both run once per frame on 5 MP mosaics, so they are compiled, release the
GIL (the live server's event loop keeps serving while a frame is processed)
and touch every pixel once.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

#: LLVM fast-math flags that keep NaN and inf semantics: masked (saturated) pixels are NaN and
#: must stay detectable (full ``fastmath=True`` would let LLVM drop the ``isfinite`` tests).
_FASTMATH = {"contract", "afn", "reassoc", "arcp", "nsz"}


@njit(nogil=True, cache=True)
def histogram_masked(raw, shift, mask, block, nbins, out):  # pragma: no cover - compiled
    """Add the (right-shifted) values of the pixels whose ``mask[i // block, j // block]`` is true into ``out``.

    Values at or above ``nbins`` count in the last bin.

    ``block`` is 1 for a mask of the mosaic's shape and 2 for a super-pixel
    (half-resolution) mask: a super-pixel counts with its four raw pixels.
    """
    h, w = raw.shape
    top = nbins - 1
    for i in range(h):
        mi = i // block
        for j in range(w):
            if mask[mi, j // block]:
                v = np.int64(raw[i, j]) >> shift
                if v > top:
                    v = top
                out[v] += 1


@njit(nogil=True, parallel=True, cache=True, fastmath=_FASTMATH)
def expose(rate, row0, col0, scale, dark, full_scale, shot_var_per_dn, read_var_dn2,
           gain_lin, table, offset, out):  # pragma: no cover - compiled
    """Linear sensor response with Gaussian-approximated shot and read noise, into ``out`` (uint16).

    Pixel ``(i, j)`` of ``out`` sees ``rate[row0 + i, col0 + j]`` (DN per
    exposure unit at unit gain) and records ``dark + g * (x + n)`` rounded
    and clipped to ``[0, full_scale]``, where ``x = rate * scale / g`` is the
    pre-gain signal, ``n`` is ``sqrt(x * shot_var_per_dn + read_var_dn2)``
    times a standard normal deviate read from ``table`` (cycled from
    ``offset``: a fixed table is far cheaper than drawing 5 million deviates
    per frame, and its period, the table length, is not a multiple of the row
    length, so the pattern does not repeat visibly).
    """
    h, w = out.shape
    n_table = table.shape[0]
    for i in prange(h):
        t = (offset + i * w) % n_table
        for j in range(w):
            x = np.float32(rate[row0 + i, col0 + j] * scale)
            if x < 0.0:
                x = np.float32(0.0)
            sigma = np.sqrt(x * np.float32(shot_var_per_dn) + np.float32(read_var_dn2))
            v = np.float32(dark) + np.float32(gain_lin) * (x + sigma * table[t]) + np.float32(0.5)
            t += 1
            if t == n_table:
                t = 0
            if v < 0.0:
                v = np.float32(0.0)
            if v > full_scale:
                v = np.float32(full_scale)
            out[i, j] = np.uint16(v)


@njit(nogil=True, parallel=True, cache=True)
def histogram_rows(raw, shift, mask, use_mask, stride, nbins, n_chunks, out):  # pragma: no cover - compiled
    """Histogram of a raw mosaic, optionally over a super-pixel mask, in parallel row chunks.

    Every ``stride``-th super-pixel row and column is taken whole (all four
    raw pixels of a taken super-pixel count), so a sub-sample still weighs
    the four polarizer channels equally. ``mask`` is a super-pixel mask
    (H/2, W/2) used when ``use_mask``. Each chunk fills its own row of a
    (n_chunks, nbins) scratch histogram; ``out`` gets their sum.
    """
    h, w = raw.shape
    hs, ws = h // 2, w // 2
    top = nbins - 1
    part = np.zeros((n_chunks, nbins), np.int64)
    rows = (hs + stride - 1) // stride
    per = (rows + n_chunks - 1) // n_chunks
    for c in prange(n_chunks):
        hist = part[c]
        for r in range(c * per, min(rows, (c + 1) * per)):
            si = r * stride
            for sj in range(0, ws, stride):
                if use_mask and not mask[si, sj]:
                    continue
                for di in range(2):
                    for dj in range(2):
                        v = np.int64(raw[2 * si + di, 2 * sj + dj]) >> shift
                        if v > top:
                            v = top
                        hist[v] += 1
    for c in range(n_chunks):
        for k in range(nbins):
            out[k] += part[c, k]


@njit(nogil=True, parallel=True, cache=True, fastmath=_FASTMATH)
def colorize(s0, dolp, aop, step, lo, scale, dolp_scale, dolp_lut, aop_bins, dolp_levels, aop_lut,
             out_s0, out_dolp, out_aop):  # pragma: no cover - compiled
    """Decimate and colour S0 (grey), DoLP (table) and AoP (2-D table) in one pass.

    Output pixel ``(i, j)`` is input pixel ``(step * i, step * j)``. S0 maps
    to ``clip((s0 - lo) * scale, 0, 255)``; DoLP to ``dolp_lut[round(d *
    dolp_scale)]`` (index 256 = NaN, black); AoP to ``aop_lut[bin * levels +
    level]`` with ``bin = floor(aop * aop_bins / 180)``, ``level = round(d /
    dolp_max * (levels - 1))`` and the last entry (black) for NaN.
    """
    oh, ow = out_s0.shape
    nan_aop = aop_bins * dolp_levels
    lev_scale = dolp_scale * (dolp_levels - 1) / 255.0
    for i in prange(oh):
        for j in range(ow):
            y, x = i * step, j * step
            g = (s0[y, x] - lo) * scale
            if not g > 0.0:
                g = 0.0
            if g > 255.0:
                g = 255.0
            out_s0[i, j] = np.uint8(g + 0.5) if g < 254.5 else np.uint8(255)
            d = dolp[y, x]
            a = aop[y, x]
            if np.isfinite(d):
                k = d * dolp_scale + 0.5
                if k < 0.0:
                    k = 0.0
                if k > 255.0:
                    k = 255.0
                kd = int(k)
            else:
                kd = 256
            for c in range(3):
                out_dolp[i, j, c] = dolp_lut[kd, c]
            if np.isfinite(d) and np.isfinite(a):
                b = int(a * aop_bins / 180.0)
                if b < 0:
                    b = 0
                if b >= aop_bins:
                    b = aop_bins - 1
                lv = d * lev_scale + 0.5
                if lv < 0.0:
                    lv = 0.0
                if lv > dolp_levels - 1:
                    lv = dolp_levels - 1
                ka = b * dolp_levels + int(lv)
            else:
                ka = nan_aop
            for c in range(3):
                out_aop[i, j, c] = aop_lut[ka, c]
