"""Exact percentiles of large float32 images without sorting or float64 copies.

:func:`percentiles` returns exactly what ``numpy.percentile(x[where].astype(
np.float64), q)`` returns (numpy's default "linear" method: the same order
statistics and numpy's own interpolation formula), in two passes over the
image instead of a float64 copy and a partition of all of it:

1. a histogram of the upper 16 bits of each value's order key (a float32's
   bit pattern mapped so that unsigned integer order is numeric order),
   which tells in which of 65,536 bins every needed order statistic lies
   and its rank inside the bin;
2. the values of those few bins only are gathered and partitioned.

Both passes are parallel numba kernels. The cost is two reads of the image
plus a partition of the values that share a bin with a needed order
statistic (a bin spans a factor of 1 + 2**-7 in value, so usually a few
per cent of the image; all of it for a constant image, which is still
correct).

References
----------
.. [1] R. J. Hyndman and Y. Fan, "Sample quantiles in statistical packages",
   The American Statistician 50(4), 361-365 (1996): definition 7, numpy's
   default.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

#: Bins of the first pass: the upper 16 bits of the 32-bit order key.
N_BINS = 1 << 16


@njit(inline="always", cache=True)
def order_key(bits):  # pragma: no cover - compiled
    """uint32 key of a float32 bit pattern whose unsigned order is the numeric order (NaN excluded)."""
    if bits & np.uint32(0x80000000):
        return ~bits
    return bits | np.uint32(0x80000000)


@njit(inline="always", cache=True)
def finite_bits(bits):  # pragma: no cover - compiled
    """Whether a float32 bit pattern is a finite number."""
    return (bits & np.uint32(0x7F800000)) != np.uint32(0x7F800000)


@njit(parallel=True, cache=True, nogil=True)
def histogram_keys(x_bits, select, hist):  # pragma: no cover - compiled
    """Histogram of ``order_key(x) >> 16`` over the pixels where ``x`` and ``select`` are finite.

    Parameters
    ----------
    x_bits : (H, W) uint32
        The image's float32 values viewed as uint32.
    select : (H, W) float32
        A pixel counts where this image is finite (pass the image itself to
        count its finite values).
    hist : (n_chunks, N_BINS) int64, zeroed
        One histogram per band of rows; the caller sums them.
    """
    n_rows, n_cols = x_bits.shape
    n_chunks = hist.shape[0]
    for c in prange(n_chunks):
        for i in range(c * n_rows // n_chunks, (c + 1) * n_rows // n_chunks):
            for j in range(n_cols):
                b = x_bits[i, j]
                if math.isfinite(select[i, j]) and finite_bits(b):
                    hist[c, order_key(b) >> 16] += 1


@njit(inline="always", cache=True)
def _gather(bits, c, slot_of_bin, cursor, end, out):  # pragma: no cover - compiled
    """Append the key of one finite float32 bit pattern to band ``c``'s range of its bin's slot, if wanted."""
    if finite_bits(bits):
        key = order_key(bits)
        slot = slot_of_bin[key >> 16]
        if slot >= 0 and cursor[c, slot] < end[c, slot]:
            out[cursor[c, slot]] = key
            cursor[c, slot] += 1


@njit(parallel=True, cache=True, nogil=True)
def gather_bins(x_bits, select, slot_of_bin, cursor, end, out):  # pragma: no cover - compiled
    """Copy the keys of the selected pixels that fall in the wanted bins, grouped by bin.

    Parameters
    ----------
    x_bits, select : see :func:`histogram_keys`
    slot_of_bin : (N_BINS,) int16
        Slot of each wanted bin, -1 for the others.
    cursor : (n_chunks, n_slots) int64
        Where each band of rows writes its next key of each slot (advanced
        in place); the bands' ranges must not overlap.
    end : (n_chunks, n_slots) int64
        End of each range: keys beyond it are dropped (they cannot occur when
        the counts came from :func:`histogram_keys` on the same data).
    out : (n,) uint32
        Destination of the keys.
    """
    n_rows, n_cols = x_bits.shape
    n_chunks = cursor.shape[0]
    for c in prange(n_chunks):
        for i in range(c * n_rows // n_chunks, (c + 1) * n_rows // n_chunks):
            for j in range(n_cols):
                if math.isfinite(select[i, j]):
                    _gather(x_bits[i, j], c, slot_of_bin, cursor, end, out)


@njit(parallel=True, cache=True, nogil=True)
def gather_bins_pair(a_bits, b_bits, select, slot_a, cursor_a, end_a, out_a, slot_b, cursor_b, end_b,
                     out_b):  # pragma: no cover - compiled
    """:func:`gather_bins` for two images of one selection in one pass (``a_bits`` with ``slot_a``, ``cursor_a``,
    ``end_a``, ``out_a``; ``b_bits`` likewise)."""
    n_rows, n_cols = a_bits.shape
    n_chunks = cursor_a.shape[0]
    for c in prange(n_chunks):
        for i in range(c * n_rows // n_chunks, (c + 1) * n_rows // n_chunks):
            for j in range(n_cols):
                if math.isfinite(select[i, j]):
                    _gather(a_bits[i, j], c, slot_a, cursor_a, end_a, out_a)
                    _gather(b_bits[i, j], c, slot_b, cursor_b, end_b, out_b)


def n_chunks_for(n_rows: int) -> int:
    """Bands of rows the kernels split an image into (a few per thread, never more than the rows)."""
    import numba

    return max(1, min(n_rows, 2 * numba.get_num_threads()))


def _key_to_value(key: int) -> float:
    """The float32 value (as a Python float) of an order key."""
    bits = key ^ 0x80000000 if key & 0x80000000 else ~key & 0xFFFFFFFF
    return float(np.array(bits, dtype=np.uint32).view(np.float32))


def linear_positions(n: int, q: Sequence[float]) -> list[tuple[int, int, float]]:
    """numpy's "linear" percentile positions: ``(lower rank, upper rank, weight)`` per ``q`` (percent).

    Follows ``numpy.percentile`` step by step (virtual index ``(n - 1) * q /
    100``, floor, clamping to the sample) so that :func:`interpolate` gives
    bit-identical results.
    """
    positions = []
    for qq in q:
        virtual = (n - 1) * (float(qq) / 100.0)
        if virtual >= n - 1:
            lo = hi = n - 1
            gamma = virtual + 1.0  # numpy's index here is -1; the weight is irrelevant since both values agree
        elif virtual < 0:
            lo = hi = 0
            gamma = virtual - math.floor(virtual)
        else:
            lo = math.floor(virtual)
            hi = lo + 1
            gamma = virtual - lo
        positions.append((int(lo), int(hi), float(gamma)))
    return positions


def interpolate(a: float, b: float, t: float) -> float:
    """numpy's ``_lerp``: ``a + (b - a) t``, computed from ``b`` when ``t >= 0.5``."""
    diff = b - a
    return b - diff * (1.0 - t) if t >= 0.5 else a + diff * t


class _Selection:
    """Where the wanted order statistics of one image lie, from its histograms: the bins to gather, where each
    band of rows writes its keys of each bin (``cursor`` .. ``end``), and the gathered keys (``keys``)."""

    def __init__(self, hist: NDArray[np.int64], ranks: Sequence[int]) -> None:
        total = hist.sum(axis=0)
        self.total, self.ends = total, np.cumsum(total)
        self.wanted = sorted(set(int(r) for r in ranks))
        n = int(self.ends[-1])
        if self.wanted and (self.wanted[0] < 0 or self.wanted[-1] >= n):
            raise ValueError(f"ranks must lie in [0, {n}), got {self.wanted[0]}..{self.wanted[-1]}")
        self.bins = np.searchsorted(self.ends, np.asarray(self.wanted, dtype=np.int64), side="right")
        self.slots = np.unique(self.bins)
        self.slot_of_bin = np.full(N_BINS, -1, dtype=np.int16)
        self.slot_of_bin[self.slots] = np.arange(self.slots.size)
        per_chunk = hist[:, self.slots]  # (n_chunks, n_slots) counts
        self.sizes = per_chunk.sum(axis=0)
        self.slot_start = np.concatenate(([0], np.cumsum(self.sizes)[:-1])).astype(np.int64)
        cursor = self.slot_start[None, :] + np.concatenate((np.zeros((1, self.slots.size), np.int64),
                                                            np.cumsum(per_chunk, axis=0)[:-1]), axis=0)
        self.cursor = np.ascontiguousarray(cursor, dtype=np.int64)
        self.end = self.cursor + per_chunk
        self.keys = np.empty(int(self.sizes.sum()), dtype=np.uint32)

    def values(self) -> dict[int, float]:
        """Rank -> value, once the keys are gathered."""
        if not np.array_equal(self.cursor, self.end):
            raise ValueError("the histograms do not describe this image and selection")
        out: dict[int, float] = {}
        for s, b in enumerate(self.slots):
            segment = self.keys[self.slot_start[s]: self.slot_start[s] + self.sizes[s]]
            first = int(self.ends[b] - self.total[b])  # rank of the bin's smallest value
            local = [r - first for r, rb in zip(self.wanted, self.bins, strict=True) if rb == b]
            part = np.partition(segment, local)
            for r in local:
                out[r + first] = _key_to_value(int(part[r]))
        return out


def order_statistics(
    image: NDArray[np.float32], select: NDArray[np.floating] | None, ranks: Sequence[int],
    hist: NDArray[np.int64] | None = None,
) -> dict[int, float]:
    """The ``ranks``-th smallest (0-based) selected values of a float32 image, exactly.

    Parameters
    ----------
    image : (H, W) float32, C-contiguous
    select : (H, W) float array, optional
        The sample is the pixels where ``image`` and ``select`` are finite (default: where ``image`` is).
    ranks : sequence of int
        Wanted ranks, each in ``[0, n)`` with ``n`` the sample size.
    hist : (n_chunks, N_BINS) int64, optional
        The first pass's histograms if already computed (e.g. by a fused kernel).

    Returns
    -------
    dict
        Rank -> value (Python float).
    """
    x = np.ascontiguousarray(image, dtype=np.float32)
    sel = x if select is None else np.ascontiguousarray(select)
    bits = x.view(np.uint32)
    if hist is None:
        hist = np.zeros((n_chunks_for(x.shape[0]), N_BINS), dtype=np.int64)
        histogram_keys(bits, sel, hist)
    if not len(ranks):
        return {}
    plan = _Selection(hist, ranks)
    gather_bins(bits, sel, plan.slot_of_bin, plan.cursor, plan.end, plan.keys)
    return plan.values()


def order_statistics_pair(
    images: tuple[NDArray[np.float32], NDArray[np.float32]], select: NDArray[np.floating],
    ranks: tuple[Sequence[int], Sequence[int]], hists: tuple[NDArray[np.int64], NDArray[np.int64]],
) -> tuple[dict[int, float], dict[int, float]]:
    """:func:`order_statistics` of two float32 images of one shape and selection, in one pass over them.

    The sample of each image is its finite pixels where ``select`` is
    finite; ``hists`` are their first-pass histograms (required, e.g. from a
    fused kernel). Same results as two calls, one read of the images fewer.
    """
    a, b = (np.ascontiguousarray(im, dtype=np.float32) for im in images)
    sel = np.ascontiguousarray(select)
    if not (a.shape == b.shape == sel.shape):
        raise ValueError(f"images and selection must share a shape, got {a.shape}, {b.shape}, {sel.shape}")
    pa, pb = _Selection(hists[0], ranks[0]), _Selection(hists[1], ranks[1])
    gather_bins_pair(a.view(np.uint32), b.view(np.uint32), sel, pa.slot_of_bin, pa.cursor, pa.end, pa.keys,
                     pb.slot_of_bin, pb.cursor, pb.end, pb.keys)
    return pa.values(), pb.values()


def percentiles_from_statistics(n: int, q: Sequence[float], stats: dict[int, float]) -> list[float]:
    """Percentiles from the order statistics :func:`linear_positions` asks for."""
    return [interpolate(stats[lo], stats[hi], t) for lo, hi, t in linear_positions(n, q)]


def percentiles(
    image: NDArray[np.floating], q: Sequence[float], where: NDArray[np.floating] | None = None
) -> list[float] | None:
    """``numpy.percentile`` of the finite (or ``where``-selected) values of a float32 image, exactly.

    Parameters
    ----------
    image : (H, W) float32 array
        Other float dtypes are converted to float32 first (then the result is
        that of the float32 values).
    q : sequence of float
        Percentiles in [0, 100].
    where : (H, W) float array, optional
        The sample is the finite pixels of ``image`` where ``where`` is also
        finite (default: all finite pixels of ``image``).

    Returns
    -------
    list of float or None
        One value per ``q``, equal to ``numpy.percentile(image[sample].astype(
        np.float64), q)``; ``None`` when the sample is empty.
    """
    x = np.ascontiguousarray(image, dtype=np.float32)
    if x.ndim != 2:
        x = x.reshape(1, -1) if x.size else x.reshape(0, 1)
    sel = None if where is None else np.ascontiguousarray(where).reshape(x.shape)
    hist = np.zeros((n_chunks_for(max(x.shape[0], 1)), N_BINS), dtype=np.int64)
    histogram_keys(x.view(np.uint32), x if sel is None else sel, hist)
    n = int(hist.sum())
    if n == 0:
        return None
    positions = linear_positions(n, q)
    stats = order_statistics(x, sel, [r for lo, hi, _ in positions for r in (lo, hi)], hist=hist)
    return percentiles_from_statistics(n, q, stats)
