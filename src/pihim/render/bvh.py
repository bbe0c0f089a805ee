"""Bounding-volume hierarchy over rectangles, and compiled ray casting.

The renderer's scene is a set of rectangles (heliostat facets, the faces of
the back-structure members and of the tower) above an analytic ground
plane. A binary BVH of axis-aligned boxes, built with the binned surface
area heuristic (16 bins per axis), lets a ray visit only the few
rectangles near it: with the whole NSTTF field in the scene (about 21,000
rectangles) a ray tests a few dozen boxes and a handful of rectangles
instead of all of them.

A rectangle is ``origin + u U + v V`` with ``0 <= u, v <= 1`` and ``U``
perpendicular to ``V``; its plane normal ``N = normalize(U x V)``. Stored
per rectangle: origin, ``U / |U|^2`` and ``V / |V|^2`` (so ``u`` and ``v``
are one dot product each), and ``N``.

References
----------
.. [1] T. Moeller, B. Trumbore, "Fast, minimum storage ray-triangle
   intersection", J. Graphics Tools 2 (1997) (the parametric test used here
   is its two-edge form specialised to rectangles).
.. [2] M. Pharr, W. Jakob, G. Humphreys, *Physically Based Rendering*, 4th
   ed. (2023), sec. 7.3 (BVH construction and compact depth-first layout).
.. [3] A. Williams et al., "An efficient and robust ray-box intersection
   algorithm", J. Graphics Tools 10 (2005) (slab test with reciprocal
   directions).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, parallel_chunksize, prange
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError

__all__ = ["BLOCK", "DYNAMIC_CHUNK", "RectangleBVH", "build_bvh", "cast_one", "cast_rays"]

#: Fast-math flags that keep IEEE infinities and NaNs (the slab test relies on them).
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}
_LEAF_SIZE = 4
_STACK = 64
#: Rays per parallel work item (work arrays are allocated once per block).
BLOCK = 256
#: Blocks handed to a thread at a time (dynamic scheduling; see numba.parallel_chunksize).
DYNAMIC_CHUNK = 4
_INF = np.inf


@dataclass(frozen=True, eq=False)
class RectangleBVH:
    """Rectangles and the flattened hierarchy over them (see the module notes).

    Attributes
    ----------
    origin, u_dual, v_dual, normal : ndarray, shape (P, 3)
        Rectangle corner, ``U / |U|^2``, ``V / |V|^2`` and unit plane normal.
    order : ndarray, shape (P,)
        Primitive indices in leaf order (nodes refer to ranges of it).
    node_lo, node_hi : ndarray, shape (M, 3)
        Node bounding boxes.
    node_first, node_count : ndarray, shape (M,)
        For a leaf, the range ``order[first:first + count]``; for an inner
        node ``count == 0`` and ``first`` is the left child.
    node_right : ndarray, shape (M,)
        Right child of an inner node (unused for leaves).
    """

    origin: NDArray[np.float64]
    u_dual: NDArray[np.float64]
    v_dual: NDArray[np.float64]
    normal: NDArray[np.float64]
    order: NDArray[np.int64]
    node_lo: NDArray[np.float64]
    node_hi: NDArray[np.float64]
    node_first: NDArray[np.int64]
    node_count: NDArray[np.int64]
    node_right: NDArray[np.int64]

    def __post_init__(self) -> None:
        # traversal copies: primitive data in leaf order (contiguous per leaf), node boxes packed
        prim = np.concatenate([self.origin, self.u_dual, self.v_dual, self.normal], axis=1)[self.order]
        object.__setattr__(self, "_prim", np.ascontiguousarray(prim))
        object.__setattr__(self, "_box", np.ascontiguousarray(np.concatenate([self.node_lo, self.node_hi], axis=1)))

    def arrays(self) -> tuple:
        """The arrays :func:`cast_one` takes, in its order."""
        return (self._prim, self.order, self._box, self.node_first, self.node_count,  # type: ignore[attr-defined]
                self.node_right)

    @property
    def n_primitives(self) -> int:
        return int(self.origin.shape[0])

    @property
    def n_nodes(self) -> int:
        return int(self.node_lo.shape[0])


@njit(inline="always", cache=True)
def _area(lo0, lo1, lo2, hi0, hi1, hi2):  # pragma: no cover - compiled
    ex = max(hi0 - lo0, 0.0)
    ey = max(hi1 - lo1, 0.0)
    ez = max(hi2 - lo2, 0.0)
    return ex * ey + ey * ez + ez * ex


@njit(cache=True)
def _build(lo, hi, centroid, leaf_size):  # pragma: no cover - compiled
    """Binned surface-area-heuristic build (16 bins per axis), depth first."""
    n = lo.shape[0]
    n_bins = 16
    cap = max(1, 2 * n)
    node_lo = np.empty((cap, 3))
    node_hi = np.empty((cap, 3))
    node_first = np.zeros(cap, np.int64)
    node_count = np.zeros(cap, np.int64)
    node_right = np.zeros(cap, np.int64)
    order = np.arange(n)
    st_node = np.empty(256, np.int64)
    st_a = np.empty(256, np.int64)
    st_b = np.empty(256, np.int64)
    st_node[0] = 0
    st_a[0] = 0
    st_b[0] = n
    sp = 1
    n_nodes = 1
    bin_cnt = np.zeros(n_bins, np.int64)
    bin_lo = np.empty((n_bins, 3))
    bin_hi = np.empty((n_bins, 3))
    right_area = np.empty(n_bins)
    right_cnt = np.zeros(n_bins, np.int64)
    while sp > 0:
        sp -= 1
        node = st_node[sp]
        a = st_a[sp]
        b = st_b[sp]
        bl = np.full(3, np.inf)
        bh = np.full(3, -np.inf)
        cl = np.full(3, np.inf)
        ch = np.full(3, -np.inf)
        for k in range(a, b):
            p = order[k]
            for j in range(3):
                bl[j] = min(bl[j], lo[p, j])
                bh[j] = max(bh[j], hi[p, j])
                cl[j] = min(cl[j], centroid[p, j])
                ch[j] = max(ch[j], centroid[p, j])
        for j in range(3):  # element copies: a row assignment would compile numba's shape-mismatch error
            node_lo[node, j] = bl[j]
            node_hi[node, j] = bh[j]
        count = b - a
        best_cost = np.inf
        best_axis = -1
        best_split = 0
        if count > leaf_size:
            for axis in range(3):
                ext = ch[axis] - cl[axis]
                if ext <= 0.0:
                    continue
                scale = n_bins / ext
                bin_cnt[:] = 0
                bin_lo[:] = np.inf
                bin_hi[:] = -np.inf
                for k in range(a, b):
                    p = order[k]
                    bi = min(int((centroid[p, axis] - cl[axis]) * scale), n_bins - 1)
                    bin_cnt[bi] += 1
                    for j in range(3):
                        bin_lo[bi, j] = min(bin_lo[bi, j], lo[p, j])
                        bin_hi[bi, j] = max(bin_hi[bi, j], hi[p, j])
                # sweep from the right
                rl0 = rl1 = rl2 = np.inf
                rh0 = rh1 = rh2 = -np.inf
                rc = 0
                for bi in range(n_bins - 1, 0, -1):
                    rc += bin_cnt[bi]
                    if bin_cnt[bi] > 0:
                        rl0 = min(rl0, bin_lo[bi, 0])
                        rl1 = min(rl1, bin_lo[bi, 1])
                        rl2 = min(rl2, bin_lo[bi, 2])
                        rh0 = max(rh0, bin_hi[bi, 0])
                        rh1 = max(rh1, bin_hi[bi, 1])
                        rh2 = max(rh2, bin_hi[bi, 2])
                    right_cnt[bi] = rc
                    right_area[bi] = _area(rl0, rl1, rl2, rh0, rh1, rh2) if rc > 0 else 0.0
                ll0 = ll1 = ll2 = np.inf
                lh0 = lh1 = lh2 = -np.inf
                lc = 0
                for bi in range(0, n_bins - 1):
                    lc += bin_cnt[bi]
                    if bin_cnt[bi] > 0:
                        ll0 = min(ll0, bin_lo[bi, 0])
                        ll1 = min(ll1, bin_lo[bi, 1])
                        ll2 = min(ll2, bin_lo[bi, 2])
                        lh0 = max(lh0, bin_hi[bi, 0])
                        lh1 = max(lh1, bin_hi[bi, 1])
                        lh2 = max(lh2, bin_hi[bi, 2])
                    rcnt = right_cnt[bi + 1]
                    if lc == 0 or rcnt == 0:
                        continue
                    cost = lc * _area(ll0, ll1, ll2, lh0, lh1, lh2) + rcnt * right_area[bi + 1]
                    if cost < best_cost:
                        best_cost = cost
                        best_axis = axis
                        best_split = bi
        parent_area = _area(bl[0], bl[1], bl[2], bh[0], bh[1], bh[2])
        # leaf when small, unsplittable, or when splitting does not pay (traversal cost ~ 1 test)
        if best_axis < 0 or (count <= 2 * leaf_size and best_cost >= (count - 1.0) * parent_area):
            node_first[node] = a
            node_count[node] = count
            continue
        ext = ch[best_axis] - cl[best_axis]
        scale = n_bins / ext
        i = a
        j = b - 1
        while i <= j:
            p = order[i]
            bi = min(int((centroid[p, best_axis] - cl[best_axis]) * scale), n_bins - 1)
            if bi <= best_split:
                i += 1
            else:
                order[i] = order[j]
                order[j] = p
                j -= 1
        mid = i
        if mid == a or mid == b:
            mid = a + count // 2
        left = n_nodes
        right = n_nodes + 1
        n_nodes += 2
        node_first[node] = left
        node_count[node] = 0
        node_right[node] = right
        st_node[sp] = right
        st_a[sp] = mid
        st_b[sp] = b
        sp += 1
        st_node[sp] = left
        st_a[sp] = a
        st_b[sp] = mid
        sp += 1
    return (order, node_lo[:n_nodes].copy(), node_hi[:n_nodes].copy(), node_first[:n_nodes].copy(),
            node_count[:n_nodes].copy(), node_right[:n_nodes].copy())


def build_bvh(origin: ArrayLike, edge_u: ArrayLike, edge_v: ArrayLike) -> RectangleBVH:
    """Build the hierarchy over rectangles ``origin + u edge_u + v edge_v`` (``0 <= u, v <= 1``).

    Parameters
    ----------
    origin, edge_u, edge_v : array_like, shape (P, 3)
        One corner and the two perpendicular edges of each rectangle, metres.

    Returns
    -------
    RectangleBVH

    Raises
    ------
    PihimInputError
        Shapes differ, values are not finite, an edge has zero length or the
        edges of a rectangle are not perpendicular (|cos| > 1e-6).
    """
    o = np.ascontiguousarray(origin, dtype=float)
    u = np.ascontiguousarray(edge_u, dtype=float)
    v = np.ascontiguousarray(edge_v, dtype=float)
    if o.ndim != 2 or o.shape[1] != 3 or u.shape != o.shape or v.shape != o.shape:
        raise PihimInputError(f"rectangles need (P, 3) origins and edges, got {o.shape}, {u.shape}, {v.shape}")
    if not (np.all(np.isfinite(o)) and np.all(np.isfinite(u)) and np.all(np.isfinite(v))):
        raise PihimInputError("rectangle corners and edges must be finite")
    lu = np.einsum("ij,ij->i", u, u)
    lv = np.einsum("ij,ij->i", v, v)
    if np.any(lu <= 0) or np.any(lv <= 0):
        raise PihimInputError("rectangle edges must have non-zero length")
    cos = np.einsum("ij,ij->i", u, v) / np.sqrt(lu * lv)
    if o.shape[0] and np.max(np.abs(cos)) > 1e-6:
        raise PihimInputError("rectangle edges must be perpendicular")
    n = np.cross(u, v)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    corners = np.stack([o, o + u, o + v, o + u + v])
    lo = corners.min(axis=0)
    hi = corners.max(axis=0)
    # flat rectangles have zero-thickness boxes; pad so the slab test never divides 0 by 0 badly
    pad = 1e-9 * (1.0 + np.abs(lo).max(axis=1, keepdims=True))
    lo = lo - pad
    hi = hi + pad
    centroid = 0.5 * (lo + hi)
    if o.shape[0] == 0:
        empty3 = np.zeros((0, 3))
        return RectangleBVH(o, u, v, n, np.zeros(0, np.int64), empty3, empty3, np.zeros(0, np.int64),
                            np.zeros(0, np.int64), np.zeros(0, np.int64))
    order, nlo, nhi, nfirst, ncount, nright = _build(lo, hi, centroid, _LEAF_SIZE)
    return RectangleBVH(o, u / lu[:, None], v / lv[:, None], n, order, nlo, nhi, nfirst, ncount, nright)


@njit(inline="always", cache=True, fastmath=_FAST)
def _box_entry(box, node, ox, oy, oz, ix, iy, iz, tmax):  # pragma: no cover - compiled
    t1 = (box[node, 0] - ox) * ix
    t2 = (box[node, 3] - ox) * ix
    tn = min(t1, t2)
    tf = max(t1, t2)
    t1 = (box[node, 1] - oy) * iy
    t2 = (box[node, 4] - oy) * iy
    tn = max(tn, min(t1, t2))
    tf = min(tf, max(t1, t2))
    t1 = (box[node, 2] - oz) * iz
    t2 = (box[node, 5] - oz) * iz
    tn = max(tn, min(t1, t2))
    tf = min(tf, max(t1, t2))
    if tf >= max(tn, 0.0) and tn <= tmax:
        return tn
    return _INF


@njit(cache=True, fastmath=_FAST)
def cast_one(prim, order, box, node_first, node_count, node_right,
             ox, oy, oz, dx, dy, dz, tmin, tmax, skip, any_hit, stack):  # pragma: no cover - compiled
    """Nearest rectangle hit by one ray in ``(tmin, tmax)``, skipping primitive ``skip``.

    The first six arguments are :meth:`RectangleBVH.arrays`. Returns ``(t,
    primitive)`` with the primitive's index in the caller's order; ``(inf,
    -1)`` when nothing is hit. With ``any_hit`` the first hit found is
    returned (shadow rays). ``stack`` is a caller-owned int64 work array of
    at least 64 entries (allocated once per batch of rays, not per ray).
    """
    best_t = tmax
    best_k = -1
    if box.shape[0] == 0:
        return _INF, -1
    ix = 1.0 / dx if dx != 0.0 else _INF
    iy = 1.0 / dy if dy != 0.0 else _INF
    iz = 1.0 / dz if dz != 0.0 else _INF
    if _box_entry(box, 0, ox, oy, oz, ix, iy, iz, best_t) == _INF:
        return _INF, -1
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        cnt = node_count[node]
        if cnt > 0:
            first = node_first[node]
            for k in range(first, first + cnt):
                nx = prim[k, 9]
                ny = prim[k, 10]
                nz = prim[k, 11]
                den = dx * nx + dy * ny + dz * nz
                if den == 0.0:
                    continue
                wx = prim[k, 0] - ox
                wy = prim[k, 1] - oy
                wz = prim[k, 2] - oz
                t = (wx * nx + wy * ny + wz * nz) / den
                if t <= tmin or t >= best_t:
                    continue
                qx = t * dx - wx
                qy = t * dy - wy
                qz = t * dz - wz
                uu = qx * prim[k, 3] + qy * prim[k, 4] + qz * prim[k, 5]
                if uu < 0.0 or uu > 1.0:
                    continue
                vv = qx * prim[k, 6] + qy * prim[k, 7] + qz * prim[k, 8]
                if vv < 0.0 or vv > 1.0:
                    continue
                if order[k] == skip:
                    continue
                best_t = t
                best_k = k
                if any_hit:
                    return best_t, order[best_k]
            continue
        left = node_first[node]
        right = node_right[node]
        tl = _box_entry(box, left, ox, oy, oz, ix, iy, iz, best_t)
        tr = _box_entry(box, right, ox, oy, oz, ix, iy, iz, best_t)
        if tl != _INF and tr != _INF:
            if tl <= tr:
                stack[sp] = right
                stack[sp + 1] = left
            else:
                stack[sp] = left
                stack[sp + 1] = right
            sp += 2
        elif tl != _INF:
            stack[sp] = left
            sp += 1
        elif tr != _INF:
            stack[sp] = right
            sp += 1
    if best_k < 0:
        return _INF, -1
    return best_t, order[best_k]


@njit(parallel=True, cache=True)
def _cast_many(prim, order, box, node_first, node_count, node_right, ray_o, ray_d, tmax, t_out,
               p_out):  # pragma: no cover - compiled
    n = ray_o.shape[0]
    n_blocks = (n + BLOCK - 1) // BLOCK
    for blk in prange(n_blocks):
        stack = np.empty(_STACK, np.int64)
        for i in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            t, p = cast_one(prim, order, box, node_first, node_count, node_right, ray_o[i, 0], ray_o[i, 1],
                            ray_o[i, 2], ray_d[i, 0], ray_d[i, 1], ray_d[i, 2], 0.0, tmax, -1, False, stack)
            t_out[i] = t
            p_out[i] = p


def cast_rays(
    bvh: RectangleBVH, origins: ArrayLike, directions: ArrayLike, *, t_max: float = np.inf
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Nearest rectangle along each ray.

    Parameters
    ----------
    bvh : RectangleBVH
    origins, directions : array_like, shape (R, 3)
        Ray origins and directions (need not be unit; ``t`` is in units of
        ``|direction|``).
    t_max : float
        Farthest hit considered.

    Returns
    -------
    t : ndarray, shape (R,)
        Ray parameter of the hit, ``inf`` for none.
    primitive : ndarray, shape (R,)
        Rectangle index, ``-1`` for none.
    """
    o = np.ascontiguousarray(origins, dtype=float).reshape(-1, 3)
    d = np.ascontiguousarray(directions, dtype=float).reshape(-1, 3)
    if o.shape != d.shape:
        raise PihimInputError(f"origins and directions must have the same shape, got {o.shape} and {d.shape}")
    t = np.empty(o.shape[0])
    p = np.empty(o.shape[0], np.int64)
    with parallel_chunksize(DYNAMIC_CHUNK):
        _cast_many(*bvh.arrays(), o, d, float(t_max), t, p)
    return t, p
