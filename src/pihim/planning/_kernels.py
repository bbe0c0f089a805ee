"""Compiled inner loops of the planner (numba), imported where used so that the command line starts quickly."""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray


@njit(cache=True, inline="always")
def _seen(points: NDArray, k: int, j: int, cam: NDArray, r: NDArray, dn: NDArray, f: NDArray, p: int, tx: float,
          ty: float) -> bool:  # pragma: no cover - compiled
    """Point ``points[k, j]`` in the view of camera ``p``: the test of :func:`in_fov`."""
    vx = points[k, j, 0] - cam[p, 0]
    vy = points[k, j, 1] - cam[p, 1]
    vz = points[k, j, 2] - cam[p, 2]
    z = vx * f[p, 0] + vy * f[p, 1] + vz * f[p, 2]
    x = vx * r[p, 0] + vy * r[p, 1] + vz * r[p, 2]
    y = vx * dn[p, 0] + vy * dn[p, 1] + vz * dn[p, 2]
    return z > 0.0 and abs(x) <= tx * z and abs(y) <= ty * z


@njit(cache=True)
def in_fov(points: NDArray, cam: NDArray, r: NDArray, dn: NDArray, f: NDArray, tx: float,
           ty: float) -> NDArray:  # pragma: no cover - compiled
    """For points (P, K, 3) seen from cameras (P, 3) with OpenCV axes ``r`` (right), ``dn`` (down) and
    ``f`` (forward), (P, 3) each: in front (``z > 0``) and ``|x| <= tx z``, ``|y| <= ty z``; (P, K) bool
    (False where any coordinate is NaN)."""
    n_p, n_k = points.shape[0], points.shape[1]
    out = np.empty((n_p, n_k), np.bool_)
    for p in range(n_p):
        for j in range(n_k):
            out[p, j] = _seen(points, p, j, cam, r, dn, f, p, tx, ty)
    return out


@njit(cache=True)
def count_in_view(points: NDArray, hua: NDArray, cam: NDArray, r: NDArray, dn: NDArray, f: NDArray, tx: float,
                  ty: float) -> NDArray:  # pragma: no cover - compiled
    """:func:`in_fov` of the points ``points[hua[p]]`` (K each) seen from ``cam[p]`` with axes ``r``, ``dn``,
    ``f`` (P, 3) each, counted per camera: (P,) int64, without the (P, K, 3) gather of the points."""
    n_p, n_k = hua.shape[0], points.shape[1]
    out = np.zeros(n_p, np.int64)
    for p in range(n_p):
        c = 0
        for j in range(n_k):
            if _seen(points, hua[p], j, cam, r, dn, f, p, tx, ty):
                c += 1
        out[p] = c
    return out


@njit(cache=True)
def segments_hit_box(p0: NDArray, p1: NDArray, lo: NDArray, hi: NDArray) -> NDArray:  # pragma: no cover - compiled
    """Segments ``p0 -> p1`` (N, 3) crossing the box ``[lo, hi]``: the slab method of
    :func:`pihim.planning.sightlines.segments_hit_box`, with its handling of parallel and NaN slabs, one pass."""
    n = p0.shape[0]
    out = np.empty(n, np.bool_)
    for i in range(n):
        enter = -np.inf
        leave = np.inf
        bad = False
        for k in range(3):
            dk = p1[i, k] - p0[i, k]
            if dk == 0.0:  # parallel to the slab: inside it or never
                inside = lo[k] <= p0[i, k] <= hi[k]
                t_lo, t_hi = (-np.inf, np.inf) if inside else (np.inf, -np.inf)
            else:
                inv = 1.0 / dk
                t1 = (lo[k] - p0[i, k]) * inv
                t2 = (hi[k] - p0[i, k]) * inv
                n1, n2 = math.isnan(t1), math.isnan(t2)
                t_lo = -np.inf if n1 else (np.nan if n2 else min(t1, t2))
                t_hi = np.inf if n2 else (np.nan if n1 else max(t1, t2))
            if math.isnan(t_lo) or math.isnan(t_hi):
                bad = True
            enter = max(enter, t_lo)
            leave = min(leave, t_hi)
        out[i] = (not bad) and enter <= leave and leave >= 0.0 and enter <= 1.0
    return out


@njit(cache=True, error_model="numpy")
def view_tests(pair: NDArray, ch_all: NDArray, nh_all: NDArray, w_all: NDArray, elev_all: NDArray,
               origin: NDArray, direction: NDArray, altitude: NDArray, nxy_all: NDArray, tc_all: NDArray,
               tn_all: NDArray, tx_all: NDArray, ty_all: NDArray,
               half_w: float, half_h: float, max_range: float, min_elev: float, max_offset: float,
               pitch_min: float, pitch_max: float, keepout: NDArray, use_keepout: bool,
               code_low: int, code_behind: int, code_off_plane: int, code_gimbal: int, code_miss: int,
               code_ok: int) -> tuple:  # pragma: no cover - compiled
    """The geometric tests of :func:`pihim.planning.lines.views_of_pairs` up to the reflected ray's miss
    distance, for the pairs ``pair`` of the pair geometry's arrays (``*_all``), one at a time (same order,
    same codes): camera position (K, 3), code, range, unit sight direction HUA -> camera (K, 3), plane
    offset, miss distance, reflected direction (K, 3) and the hit point on the target's plane (K, 3)."""
    n = pair.shape[0]
    cam = np.empty((n, 3))
    code = np.empty(n, np.int64)
    rng = np.empty(n)
    v = np.empty((n, 3))
    offset = np.empty(n)
    miss = np.full(n, np.inf)
    r = np.full((n, 3), np.nan)
    hit = np.full((n, 3), np.nan)
    to_deg = 180.0 / np.pi
    for i in range(n):
        g = pair[i]
        # rows read as scalars: a 1-D view per row (``ch_all[g]``) made the loop about 30 % slower
        ch0, ch1, ch2 = ch_all[g, 0], ch_all[g, 1], ch_all[g, 2]
        nh0, nh1, nh2 = nh_all[g, 0], nh_all[g, 1], nh_all[g, 2]
        w0, w1, w2 = w_all[g, 0], w_all[g, 1], w_all[g, 2]
        nxy0, nxy1 = nxy_all[g, 0], nxy_all[g, 1]
        c = code_low if elev_all[g] < min_elev else code_ok
        # the camera: where the direction w from the HUA to the camera reaches the pass altitude, on the line
        t = (altitude[i] - ch2) / w2 if w2 != 0.0 else (
            np.inf if altitude[i] - ch2 > 0.0 else (-np.inf if altitude[i] - ch2 < 0.0 else np.nan))
        ex = ch0 + t * w0 - origin[i, 0]
        ey = ch1 + t * w1 - origin[i, 1]
        along = ex * direction[i, 0] + ey * direction[i, 1]
        cam[i, 0] = origin[i, 0] + along * direction[i, 0]
        cam[i, 1] = origin[i, 1] + along * direction[i, 1]
        cam[i, 2] = altitude[i]
        dx, dy, dz = cam[i, 0] - ch0, cam[i, 1] - ch1, cam[i, 2] - ch2
        rg = np.sqrt(dx * dx + dy * dy + dz * dz)
        rng[i] = rg
        s = max(rg, 1e-12)
        v[i, 0], v[i, 1], v[i, 2] = dx / s, dy / s, dz / s
        vn = v[i, 0] * nh0 + v[i, 1] * nh1 + v[i, 2] * nh2
        if c == code_ok and (not np.isfinite(rg) or vn <= 0.0 or rg > max_range):
            c = code_behind
        # distance of the camera from the vertical plane of the HUA's normal
        offset[i] = abs(dx * nxy1 - dy * nxy0)
        if c == code_ok and offset[i] > max_offset:
            c = code_off_plane
        if c == code_ok:  # the gimbal's pitch and the keep-out box (tested only where every test so far passed)
            pitch = np.arctan2(-dz, np.hypot(dx, dy)) * to_deg
            bad = pitch < pitch_min - 1e-9 or pitch > pitch_max + 1e-9
            if use_keepout and (keepout[0, 0] <= cam[i, 0] <= keepout[1, 0]
                                and keepout[0, 1] <= cam[i, 1] <= keepout[1, 1]
                                and keepout[0, 2] <= cam[i, 2] <= keepout[1, 2]):
                bad = True
            if bad:
                c = code_gimbal
        if c == code_ok:  # the ray camera -> HUA centre reflected about the HUA's normal, against the target
            rx = 2.0 * vn * nh0 - v[i, 0]
            ry = 2.0 * vn * nh1 - v[i, 1]
            rz = 2.0 * vn * nh2 - v[i, 2]
            r[i, 0], r[i, 1], r[i, 2] = rx, ry, rz
            denom = rx * tn_all[g, 0] + ry * tn_all[g, 1] + rz * tn_all[g, 2]
            num = (tc_all[g, 0] - ch0) * tn_all[g, 0] + (tc_all[g, 1] - ch1) * tn_all[g, 1] \
                + (tc_all[g, 2] - ch2) * tn_all[g, 2]
            lam = num / denom if denom != 0.0 else np.nan
            hx, hy, hz = ch0 + lam * rx, ch1 + lam * ry, ch2 + lam * rz
            hit[i, 0], hit[i, 1], hit[i, 2] = hx, hy, hz
            qx0, qy0, qz0 = hx - tc_all[g, 0], hy - tc_all[g, 1], hz - tc_all[g, 2]
            qx = abs(qx0 * tx_all[g, 0] + qy0 * tx_all[g, 1] + qz0 * tx_all[g, 2]) - half_w
            qy = abs(qx0 * ty_all[g, 0] + qy0 * ty_all[g, 1] + qz0 * ty_all[g, 2]) - half_h
            if denom > 0.0 and lam > 0.0:
                # np.maximum's NaN propagation: a NaN miss stays NaN (neither missed nor traced)
                miss[i] = np.nan if (qx != qx or qy != qy) else max(max(qx, qy), 0.0)
            else:
                miss[i] = np.inf
            if miss[i] > 0.0:
                c = code_miss
        code[i] = c
    return cam, code, rng, v, offset, miss, r, hit


@njit(cache=True)
def grid_first_hits(p0: NDArray, p1: NDArray, exclude: NDArray, order: NDArray, cell_start: NDArray, x0: float,
                    y0: float, cell: float, n_x: int, n_y: int, centres: NDArray, normals: NDArray, x: NDArray,
                    y: NDArray, hw: float, hh: float, reach: float, eps: float) -> NDArray:  # pragma: no cover
    """The first mirror each segment p0 -> p1 crosses strictly inside (``eps < t < 1 - eps``) within its
    half-width ``hw`` and half-height ``hh`` (-1 for none), skipping the mirrors in ``exclude[i]``.

    Candidates come from a uniform grid over the mirror centres' x, y (``n_x`` x ``n_y`` cells of ``cell``
    metres from ``(x0, y0)``; cell ``cx * n_y + cy`` holds ``order[cell_start[c]:cell_start[c + 1]]``, a centre
    beyond the grid in the edge cell nearest it): the cells meeting the segment's x, y bounding box grown by
    ``reach``, the mirrors' half-diagonal, with the box's cell range clamped into the grid. A mirror the segment
    crosses has its centre within ``reach`` of the crossing point, and clamping keeps a centre's cell inside a
    box's range, so no hit is missed. Equal ``t`` keeps the lower mirror index. A segment with a coordinate that
    is not finite meets nothing."""
    n = p0.shape[0]
    out = np.full(n, -1, np.int64)
    for i in range(n):
        ax, ay, az = p0[i, 0], p0[i, 1], p0[i, 2]
        dx, dy, dz = p1[i, 0] - ax, p1[i, 1] - ay, p1[i, 2] - az
        if not (np.isfinite(ax) and np.isfinite(ay) and np.isfinite(az) and np.isfinite(dx) and np.isfinite(dy)
                and np.isfinite(dz)):
            continue
        lo_x = (min(ax, ax + dx) - reach - x0) / cell
        hi_x = (max(ax, ax + dx) + reach - x0) / cell
        lo_y = (min(ay, ay + dy) - reach - y0) / cell
        hi_y = (max(ay, ay + dy) + reach - y0) / cell
        # clamped into the grid (before the conversion: no overflow): a box beyond an edge scans the edge cells,
        # which hold the centres beyond the grid
        cx0, cx1 = int(min(max(lo_x, 0.0), n_x - 1.0)), int(min(max(hi_x, 0.0), n_x - 1.0))
        cy0, cy1 = int(min(max(lo_y, 0.0), n_y - 1.0)), int(min(max(hi_y, 0.0), n_y - 1.0))
        best, bj = np.inf, -1
        for cx in range(cx0, cx1 + 1):
            for cy in range(cy0, cy1 + 1):
                c = cx * n_y + cy
                for k in range(cell_start[c], cell_start[c + 1]):
                    j = order[k]
                    skip = False
                    for e in range(exclude.shape[1]):
                        if exclude[i, e] == j:
                            skip = True
                    if skip:
                        continue
                    denom = dx * normals[j, 0] + dy * normals[j, 1] + dz * normals[j, 2]
                    if denom == 0.0:
                        continue
                    t = ((centres[j, 0] - ax) * normals[j, 0] + (centres[j, 1] - ay) * normals[j, 1]
                         + (centres[j, 2] - az) * normals[j, 2]) / denom
                    if not (np.isfinite(t) and t > eps and t < 1.0 - eps) or t > best or (t == best and j > bj):
                        continue
                    qx = ax + t * dx - centres[j, 0]
                    qy = ay + t * dy - centres[j, 1]
                    qz = az + t * dz - centres[j, 2]
                    if abs(qx * x[j, 0] + qy * x[j, 1] + qz * x[j, 2]) <= hw and abs(qx * y[j, 0] + qy * y[j, 1]
                                                                                     + qz * y[j, 2]) <= hh:
                        best, bj = t, j
        out[i] = bj
    return out


@njit(cache=True)
def cone_intervals(q: NDArray, a: NDArray, e: NDArray, p_terms: NDArray, d_terms: NDArray, centroid: NDArray,
                   winding: NDArray, idx: NDArray, s_first: NDArray, s_last: NDArray,
                   negative: bool) -> tuple:  # pragma: no cover - compiled
    """The parameters ``s`` for which ``a + s e`` lies in the cone from apex ``q`` over a convex polygon, for
    every (apex, polygon) pair of a batch: the closed-form test of
    :func:`pihim.planning.facet_captures.cone_interval`, one pass with no temporaries.

    ``q``, ``a``, ``e`` (B, I, 3): apexes and their lines; ``p_terms``, ``d_terms`` (B, J, K, 3): per polygon
    edge ``P_k = X_k x X_k+1`` and ``D_k = X_k+1 - X_k``; ``centroid``, ``winding`` (B, J, 3); ``idx`` (B, J):
    the polygon's heliostat, -1 for padding. With ``m_k = (X_k - q) x (X_k+1 - q) = P_k - q x D_k``, each edge
    gives ``alpha_k + s beta_k >= 0`` with ``alpha_k = (a - q) . m_k`` and ``beta_k = e . m_k`` (``<= 0`` on the
    opposite nappe, ``negative``), oriented by the side of the polygon's plane the apex is on. Returns ``lo``,
    ``hi`` (B, I, J): ``(inf, -inf)`` where the line misses the cone, the polygon is padding, or the interval
    misses ``[s_first[b], s_last[b]]``."""
    n_b, n_i, n_j, n_k = q.shape[0], q.shape[1], p_terms.shape[1], p_terms.shape[2]
    lo_out = np.empty((n_b, n_i, n_j))
    hi_out = np.empty((n_b, n_i, n_j))
    for b in range(n_b):
        for i in range(n_i):
            qx, qy, qz = q[b, i, 0], q[b, i, 1], q[b, i, 2]
            ax, ay, az = a[b, i, 0] - qx, a[b, i, 1] - qy, a[b, i, 2] - qz
            ex, ey, ez = e[b, i, 0], e[b, i, 1], e[b, i, 2]
            # a x q and e x q (the D_k terms of alpha and beta)
            cax, cay, caz = a[b, i, 1] * qz - a[b, i, 2] * qy, a[b, i, 2] * qx - a[b, i, 0] * qz, \
                a[b, i, 0] * qy - a[b, i, 1] * qx
            cex, cey, cez = ey * qz - ez * qy, ez * qx - ex * qz, ex * qy - ey * qx
            for j in range(n_j):
                if idx[b, j] < 0:
                    lo_out[b, i, j] = np.inf
                    hi_out[b, i, j] = -np.inf
                    continue
                side = (qx * winding[b, j, 0] + qy * winding[b, j, 1] + qz * winding[b, j, 2]) - (
                    centroid[b, j, 0] * winding[b, j, 0] + centroid[b, j, 1] * winding[b, j, 1]
                    + centroid[b, j, 2] * winding[b, j, 2])
                flip = (side > 0.0) != negative  # the oriented normals are -m_k
                lo, hi, empty = -np.inf, np.inf, False
                for k in range(n_k):
                    px, py, pz = p_terms[b, j, k, 0], p_terms[b, j, k, 1], p_terms[b, j, k, 2]
                    dx, dy, dz = d_terms[b, j, k, 0], d_terms[b, j, k, 1], d_terms[b, j, k, 2]
                    alpha = (ax * px + ay * py + az * pz) - (cax * dx + cay * dy + caz * dz)
                    beta = (ex * px + ey * py + ez * pz) - (cex * dx + cey * dy + cez * dz)
                    if beta == 0.0:
                        if alpha != 0.0 and (alpha < 0.0) != flip:
                            empty = True
                        continue
                    bound = -alpha / beta
                    if (beta > 0.0) != flip:
                        lo = max(lo, bound)
                    else:
                        hi = min(hi, bound)
                if empty or lo > s_last[b] or hi < s_first[b]:
                    lo, hi = np.inf, -np.inf
                lo_out[b, i, j] = lo
                hi_out[b, i, j] = hi
    return lo_out, hi_out


@njit(cache=True)
def facet_grid(s: NDArray, valid: NDArray, r_lo: NDArray, r_hi: NDArray, back: NDArray, tgt: NDArray,
               b_lo: NDArray, b_hi: NDArray, f_lo: NDArray, f_hi: NDArray, q: NDArray, cam: NDArray,
               fwd: NDArray, right: NDArray, down: NDArray, n_facets: int, tx: float,
               ty: float) -> tuple:  # pragma: no cover - compiled
    """For every candidate capture (camera position ``g`` on the line, aim ``a``) of every HUA ``b``: which
    facets it covers and the heliostat whose back each shows (:func:`pihim.planning.facet_captures._evaluate`).

    A sample point ``i`` (the HUA's facets' samples, ``n_facets`` x S of them, facet-major) shows a target
    from position ``s[b, g]`` when the first (nearest) target interval ``[r_lo, r_hi]`` (B, I, J) containing
    ``s`` is one whose plane it lies behind (``back``), no blocker interval ``[b_lo, b_hi]`` (B, I, Jb)
    contains ``s``, the camera is in front of the facet (``f_lo < s < f_hi``, (B, I)) and the position is
    allowed (``valid``, (B, G)). It is framed by aim ``a`` when its direction from ``cam[b, g]`` has, in the
    camera axes ``fwd``, ``right``, ``down`` (B, G, A, 3), ``z > 0``, ``|x| <= tx z``, ``|y| <= ty z``.
    Returns ``good`` (B, G, A, F): some sample of the facet shows a target and is framed; ``target``
    (B, G, A, F): the target its first such sample shows, -1 where not good."""
    n_b, n_g, n_a = fwd.shape[0], fwd.shape[1], fwd.shape[2]
    n_i, n_j, n_jb = q.shape[1], r_lo.shape[2], b_lo.shape[2]
    n_s = n_i // n_facets
    good = np.zeros((n_b, n_g, n_a, n_facets), np.bool_)
    target = np.full((n_b, n_g, n_a, n_facets), -1, np.int64)
    vis = np.empty(n_i, np.int64)
    for b in range(n_b):
        for g in range(n_g):
            sg = s[b, g]
            any_vis = False
            for i in range(n_i):
                vis[i] = -1
                if not valid[b, g] or not (f_lo[b, i] < sg < f_hi[b, i]):
                    continue
                first = -1
                for j in range(n_j):
                    if r_lo[b, i, j] <= sg <= r_hi[b, i, j]:
                        first = j
                        break
                if first < 0 or not back[b, i, first]:
                    continue
                blocked = False
                for j in range(n_jb):
                    if b_lo[b, i, j] <= sg <= b_hi[b, i, j]:
                        blocked = True
                        break
                if not blocked:
                    vis[i] = tgt[b, first]
                    any_vis = True
            if not any_vis:
                continue
            cx, cy, cz = cam[b, g, 0], cam[b, g, 1], cam[b, g, 2]
            for a in range(n_a):
                for f in range(n_facets):
                    for k in range(n_s):
                        i = f * n_s + k
                        if vis[i] < 0:
                            continue
                        vx, vy, vz = q[b, i, 0] - cx, q[b, i, 1] - cy, q[b, i, 2] - cz
                        z = fwd[b, g, a, 0] * vx + fwd[b, g, a, 1] * vy + fwd[b, g, a, 2] * vz
                        x = right[b, g, a, 0] * vx + right[b, g, a, 1] * vy + right[b, g, a, 2] * vz
                        y = down[b, g, a, 0] * vx + down[b, g, a, 1] * vy + down[b, g, a, 2] * vz
                        if z > 0.0 and abs(x) <= tx * z and abs(y) <= ty * z:
                            good[b, g, a, f] = True
                            target[b, g, a, f] = vis[i]
                            break
    return good, target


@njit(cache=True)
def first_hits_in_rows(p0: NDArray, d: NDArray, table: NDArray, row: NDArray, skip: NDArray, t_max: NDArray,
                       normals: NDArray, centres: NDArray, x: NDArray, y: NDArray, hw: float,
                       hh: float) -> NDArray:  # pragma: no cover - compiled
    """First mirror met by each ray ``p0 + t d`` (R, 3), ``1e-9 < t < t_max``, among its own row of mirrors
    ``table[row[r]]`` (-1 padded), skipping mirror ``skip[r]``; -1 for none. A mirror ``m`` is the rectangle
    of half-width ``hw`` along ``x[m]`` and half-height ``hh`` along ``y[m]`` about ``centres[m]`` in the plane
    of ``normals[m]`` (field-wide (N, 3) arrays). Equal ``t`` keeps the least mirror index, whatever the row's
    order (:func:`pihim.planning.facets._first_hits_among`)."""
    n_r, n_j = p0.shape[0], table.shape[1]
    out = np.full(n_r, -1, np.int64)
    for r in range(n_r):
        best = np.inf
        px0, py0, pz0 = p0[r, 0], p0[r, 1], p0[r, 2]
        dx, dy, dz = d[r, 0], d[r, 1], d[r, 2]
        k = row[r]
        for j in range(n_j):
            m = table[k, j]
            if m < 0 or m == skip[r]:
                continue
            den = dx * normals[m, 0] + dy * normals[m, 1] + dz * normals[m, 2]
            if den == 0.0:  # parallel to the plane (numpy's inf or nan t: no hit either)
                continue
            cn = centres[m, 0] * normals[m, 0] + centres[m, 1] * normals[m, 1] + centres[m, 2] * normals[m, 2]
            t = (cn - (px0 * normals[m, 0] + py0 * normals[m, 1] + pz0 * normals[m, 2])) / den
            if not (t > 1e-9 and t < t_max[r] and (t < best or (t == best and m < out[r]))):
                continue
            cx = centres[m, 0] * x[m, 0] + centres[m, 1] * x[m, 1] + centres[m, 2] * x[m, 2]
            cy = centres[m, 0] * y[m, 0] + centres[m, 1] * y[m, 1] + centres[m, 2] * y[m, 2]
            u = (px0 * x[m, 0] + py0 * x[m, 1] + pz0 * x[m, 2]) + t * (dx * x[m, 0] + dy * x[m, 1] + dz * x[m, 2]) \
                - cx
            v = (px0 * y[m, 0] + py0 * y[m, 1] + pz0 * y[m, 2]) + t * (dx * y[m, 0] + dy * y[m, 1] + dz * y[m, 2]) \
                - cy
            if abs(u) <= hw and abs(v) <= hh:
                best = t
                out[r] = m
    return out


# --------------------------------------------------------------------------- transits and the route


@njit(cache=True, inline="always")
def crosses(ax: float, ay: float, bx: float, by: float, keep: NDArray) -> bool:  # pragma: no cover - compiled
    """Whether the 2-D segment a-b passes through the open rectangle ``keep[0:2]`` (low corner) -
    ``keep[2:4]`` (high corner), shrunk by 1e-6 m (Liang-Barsky)."""
    eps = 1e-6
    t0, t1 = 0.0, 1.0
    for k in range(2):
        a, d = (ax, bx - ax) if k == 0 else (ay, by - ay)
        lo, hi = keep[k] + eps, keep[2 + k] - eps
        if abs(d) < 1e-15:
            if a <= lo or a >= hi:
                return False
            continue
        ta, tb = (lo - a) / d, (hi - a) / d
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
        if t0 >= t1:
            return False
    return True


@njit(cache=True)
def detour(ax: float, ay: float, bx: float, by: float, keep: NDArray) -> tuple:  # pragma: no cover - compiled
    """Shortest 2-D path from a to b around the rectangle ``keep`` (:func:`crosses`): Dijkstra over a, b and
    the rectangle's corners, popping the least (distance, node) first as :mod:`heapq` does. Returns the
    intermediate corners (4, 2) and their count (0: the straight segment is clear)."""
    path = np.empty((4, 2))
    if not crosses(ax, ay, bx, by, keep):
        return path, 0
    nx = np.array([ax, bx, keep[0], keep[2], keep[2], keep[0]])
    ny = np.array([ay, by, keep[1], keep[1], keep[3], keep[3]])
    dist = np.full(6, np.inf)
    prev = np.full(6, -1, np.int64)
    dist[0] = 0.0
    heap_d = np.empty(64)  # entries (distance, node); at most 1 + 6 x 5 pushes
    heap_n = np.empty(64, np.int64)
    live = np.zeros(64, np.bool_)
    heap_d[0], heap_n[0], live[0] = 0.0, 0, True
    n_e = 1
    while True:
        k = -1
        for m in range(n_e):
            if live[m] and (k < 0 or heap_d[m] < heap_d[k] or (heap_d[m] == heap_d[k] and heap_n[m] < heap_n[k])):
                k = m
        if k < 0:
            break
        live[k] = False
        dcur, i = heap_d[k], heap_n[k]
        if dcur > dist[i]:
            continue
        for j in range(6):
            if j == i or crosses(nx[i], ny[i], nx[j], ny[j], keep):
                continue
            nd = dcur + math.sqrt((nx[j] - nx[i]) ** 2 + (ny[j] - ny[i]) ** 2)
            if nd < dist[j] - 1e-12:
                dist[j], prev[j] = nd, i
                heap_d[n_e], heap_n[n_e], live[n_e] = nd, j, True
                n_e += 1
    n = 0
    k = prev[1]
    while k > 1:
        path[n, 0], path[n, 1] = nx[k], ny[k]
        n += 1
        k = prev[k]
    return path[:n][::-1].copy(), n


@njit(cache=True, inline="always")
def straight(ax: float, ay: float, az: float, bx: float, by: float, bz: float,
             keep: NDArray) -> float:  # pragma: no cover - compiled
    """Transit a -> b, metres: across (around the keep-out ``keep`` = low x, low y, high x, high y, top z when
    both ends are below its top; ``keep`` empty: none), plus the climb or descent."""
    d = math.hypot(bx - ax, by - ay)
    if keep.shape[0] and max(az, bz) < keep[4] and crosses(ax, ay, bx, by, keep):
        path, n = detour(ax, ay, bx, by, keep)
        px, py = ax, ay
        d = 0.0
        for k in range(n + 1):
            qx, qy = (path[k, 0], path[k, 1]) if k < n else (bx, by)
            d += math.sqrt((qx - px) ** 2 + (qy - py) ** 2)
            px, py = qx, qy
    return d + abs(bz - az)


@njit(cache=True)
def _transit(ax: float, ay: float, az: float, oax: float, oay: float, bx: float, by: float, bz: float, obx: float,
             oby: float, keep: NDArray, turn_cost: float, cos_turn: float) -> float:  # pragma: no cover - compiled
    """:func:`transit` from the ends' coordinates and outward directions (scalars: a cheap call)."""
    v = straight(ax, ay, az, bx, by, bz, keep)
    if turn_cost != 0.0:
        obx, oby = -obx, -oby
        a_any, b_any = oax != 0.0 or oay != 0.0, obx != 0.0 or oby != 0.0
        lx, ly = bx - ax, by - ay
        n = math.hypot(lx, ly)
        turns = 0
        if n < 0.5:  # no horizontal transit: the turn, if any, is from one pass straight into the other
            turns = int(a_any and b_any and oax * obx + oay * oby < cos_turn)
        else:
            ux, uy = lx / n, ly / n
            turns = int(a_any and oax * ux + oay * uy < cos_turn) + int(b_any and ux * obx + uy * oby < cos_turn)
        v += turn_cost * turns
    return v


@njit(cache=True, inline="always")
def transit(pts: NDArray, out: NDArray, e1: int, e2: int, keep: NDArray, turn_cost: float,
            cos_turn: float) -> float:  # pragma: no cover - compiled
    """Transit from pass end ``e1`` to pass end ``e2`` (rows of ``pts``), plus ``turn_cost`` for each turn
    of more than the angle of ``cos_turn`` out of ``e1`` (along ``out[e1]``) and into ``e2`` (along
    ``-out[e2]``); the same both ways (computed from the lower end)."""
    if e2 < e1:
        e1, e2 = e2, e1
    return _transit(pts[e1, 0], pts[e1, 1], pts[e1, 2], out[e1, 0], out[e1, 1], pts[e2, 0], pts[e2, 1], pts[e2, 2],
                    out[e2, 0], out[e2, 1], keep, turn_cost, cos_turn)


@njit(cache=True, inline="always")
def _unchanged_since(stamp: NDArray, lo: int, hi: int, seen: int) -> bool:  # pragma: no cover - compiled
    """Whether no position ``lo..hi`` (clipped to the order) changed since clock ``seen`` (0: never seen)."""
    if seen == 0:
        return False
    for k in range(max(lo, 0), min(hi, stamp.shape[0] - 1) + 1):
        if stamp[k] >= seen:
            return False
    return True


@njit(cache=True)
def improve_sweep(order: NDArray, dirs: NDArray, pts: NDArray, out: NDArray, keep: NDArray, turn_cost: float,
                  cos_turn: float, lo_i: int, hi_i: int, window: int, stamp: NDArray, seen: NDArray,
                  clock: NDArray) -> bool:  # pragma: no cover - compiled
    """One sweep of :func:`pihim.planning.route._improve` in place: 2-opt (reverse positions i..j), then
    Or-opt (move a run of 1-3 positions between two others, maybe reversed), each within ``window``
    positions, on the positions ``lo_i..hi_i``. Pass ``k`` flown in direction ``o`` runs from end
    ``2k + o`` to end ``2k + 1 - o``; a move is made when it shortens the transits at the segment ends by
    more than 1e-6 m (Or-opt: the best such place). Returns whether any move was made.

    Don't-look marks, kept across sweeps by the caller: ``clock[0]`` counts changes, ``stamp[k]`` is the
    clock at which position ``k`` last changed, ``seen[m, i]`` the clock at which the search from position
    ``i`` (m = 0: 2-opt, 1-3: Or-opt of that many) last found no move. A search whose positions (all it
    reads) have not changed since is skipped: it would find no move again, so the result is the same as
    searching, and the later sweeps, where few positions still move, cost little."""
    n = order.shape[0]
    improved = False

    def s_(i: int) -> int:
        return 2 * order[i] + dirs[i] if 0 <= i < n else -1

    def e_(i: int) -> int:
        return 2 * order[i] + 1 - dirs[i] if 0 <= i < n else -1

    def leg(e1: int, e2: int) -> float:  # the transit between two ends, 0 where either is missing (-1)
        return transit(pts, out, e1, e2, keep, turn_cost, cos_turn) if e1 >= 0 and e2 >= 0 else 0.0

    def mark(a: int, b: int) -> None:  # positions a..b changed
        for k in range(a, b + 1):
            stamp[k] = clock[0]
        clock[0] += 1

    for i in range(lo_i, hi_i):
        j_hi = min(hi_i + 1, i + window + 1)
        if _unchanged_since(stamp, i - 1, j_hi, seen[0, i]):
            continue
        moved = False
        for j in range(i + 1, j_hi):
            old = leg(e_(i - 1), s_(i)) + leg(e_(j), s_(j + 1))
            new = leg(e_(i - 1), e_(j)) + leg(s_(i), s_(j + 1))
            if new < old - 1e-6:  # reverse positions i..j in place, each pass flown the other way
                a, b = i, j
                while a < b:
                    order[a], order[b] = order[b], order[a]
                    dirs[a], dirs[b] = 1 - dirs[b], 1 - dirs[a]
                    a += 1
                    b -= 1
                if a == b:
                    dirs[a] = 1 - dirs[a]
                mark(i, j)
                improved = moved = True
        if not moved:
            seen[0, i] = clock[0]
    for length in range(1, 4):
        i = lo_i
        while i + length - 1 <= hi_i:
            j = i + length - 1
            p_lo, p_hi = max(lo_i, i - window), min(hi_i + 1, j + 1 + window)
            if _unchanged_since(stamp, min(i, p_lo) - 1, max(j + 1, p_hi), seen[length, i]):
                i += 1
                continue
            a, b = s_(i), e_(j)
            before, after = e_(i - 1), s_(j + 1)
            gain = (leg(before, a)
                    + leg(b, after)
                    - leg(before, after))
            best, best_p, best_rev = 1e-6, -1, False
            for p in range(p_lo, p_hi + 1):
                if i <= p <= j + 1:
                    continue
                left, right = e_(p - 1), s_(p)
                base = leg(left, right)
                for rev in (False, True):
                    x, y = (b, a) if rev else (a, b)
                    add = leg(left, x) + leg(y, right)
                    delta = gain - (add - base)
                    if delta > best:
                        best, best_p, best_rev = delta, p, rev
            if best_p >= 0:  # move positions i..j before position best_p, in place (element loops, no slices)
                seg_o = order[i:j + 1].copy()
                seg_d = dirs[i:j + 1].copy()
                if best_p < i:  # positions best_p..i-1 move up by length
                    for k in range(i - 1, best_p - 1, -1):
                        order[k + length] = order[k]
                        dirs[k + length] = dirs[k]
                    q = best_p
                else:  # positions j+1..best_p-1 move down by length
                    for k in range(j + 1, best_p):
                        order[k - length] = order[k]
                        dirs[k - length] = dirs[k]
                    q = best_p - length
                for k in range(length):
                    src = length - 1 - k if best_rev else k
                    order[q + k] = seg_o[src]
                    dirs[q + k] = 1 - seg_d[src] if best_rev else seg_d[src]
                mark(min(best_p, i), max(best_p - 1, j))
                improved = True
            else:
                seen[length, i] = clock[0]
            i += 1
    return improved


@njit(cache=True)
def split_flights_dp(order: NDArray, pts: NDArray, out: NDArray, keep: NDArray, turn_cost: float, cos_turn: float,
                     home_leg: NDArray, time_s: NDArray, items: NDArray, inner: NDArray, z_of: NDArray, home_z: float,
                     transit_speed: float, climb_rate: float, descent_rate: float, overhead_s: float, limit_s: float,
                     item_cap: float, base_items: int) -> NDArray:  # pragma: no cover - compiled
    """The cuts of :func:`pihim.planning.route._split` (its docstring): ``cut[j]`` the start of the flight that
    ends before position ``j`` in the cheapest split of positions ``0..j-1``. ``home_leg[e]`` is the leg
    between home (at its altitude) and pass end ``e``; per pass: ``time_s``, ``items``, ``inner`` (its own
    path length) and ``z_of`` (its highest altitude). The same operations in the same order as the Python
    it replaces (ties kept by the first cut found)."""
    n = order.shape[0]
    best = np.full(n + 1, np.inf)
    cut = np.zeros(n + 1, np.int64)
    best[0] = 0.0
    for i in range(n):
        if not np.isfinite(best[i]):
            continue
        t_passes = 0.0
        inside = 0.0
        n_items = base_items
        k0 = order[i]
        f0, f1 = home_leg[2 * k0], home_leg[2 * k0 + 1]
        z = -np.inf
        for j in range(i, n):
            k = order[j]
            if j > i:
                kp = order[j - 1]
                g0 = min(f0 + transit(pts, out, 2 * kp + 1, 2 * k, keep, turn_cost, cos_turn),
                         f1 + transit(pts, out, 2 * kp, 2 * k, keep, turn_cost, cos_turn))
                g1 = min(f0 + transit(pts, out, 2 * kp + 1, 2 * k + 1, keep, turn_cost, cos_turn),
                         f1 + transit(pts, out, 2 * kp, 2 * k + 1, keep, turn_cost, cos_turn))
                f0, f1 = g0, g1
            t_passes += time_s[k]
            n_items += items[k]
            inside += inner[k]
            z = max(z, z_of[k])
            leg = min(f0 + home_leg[2 * k + 1], f1 + home_leg[2 * k])
            climb = max(z - home_z, 0.0)
            t = t_passes + leg / transit_speed + climb / climb_rate + climb / descent_rate + overhead_s
            if (t > limit_s or n_items > item_cap) and j > i:
                break
            c = best[i] + leg + 2.0 * climb + inside
            if c < best[j + 1]:
                best[j + 1] = c
                cut[j + 1] = i
    return cut


@njit(cache=True)
def _mode(vals: NDArray) -> int:  # pragma: no cover - compiled
    """The most frequent of ``vals`` (the least among equals); -1 for none."""
    if vals.shape[0] == 0:
        return -1
    v = np.sort(vals)
    top, top_n, run = v[0], 0, 0
    for m in range(v.shape[0]):
        run = run + 1 if m > 0 and v[m] == v[m - 1] else 1
        if run > top_n:
            top, top_n = v[m], run
    return top


@njit(cache=True)
def row_modes(rows: NDArray) -> NDArray:  # pragma: no cover - compiled
    """Per row of ``rows`` (R, K): the most frequent value >= 0 (the least among equals), -1 for none."""
    out = np.full(rows.shape[0], -1, np.int64)
    buf = np.empty(rows.shape[1], np.int64)
    for r in range(rows.shape[0]):
        n = 0
        for k in range(rows.shape[1]):
            if rows[r, k] >= 0:
                buf[n] = rows[r, k]
                n += 1
        out[r] = _mode(buf[:n])
    return out


@njit(cache=True)
def greedy_captures(good: NDArray, target: NDArray, kk: NDArray, taken: NDArray, pass_id: NDArray, commit: bool,
                    max_captures: int, min_gain: float, tie: NDArray) -> tuple:  # pragma: no cover - compiled
    """Greedy captures per instance (:func:`pihim.planning.facet_captures._greedy`), in rounds: in each,
    every instance still active, in order, takes the (position, aim) adding the most facets not yet covered
    (``good`` (B, G, A, F); less ``tie`` (G, A) to break ties; the first maximum), skipping grid positions
    already ``taken`` (B, G: by its own picks, and with ``commit`` by any instance of the same pass,
    ``pass_id``, which share the grid indices ``kk``), and stops when the best adds fewer than
    ``min_gain``. Returns per instance and pick: position, aim (-1: none), the new facets and the target most
    of them show (the least heliostat index among equals; -1 none)."""
    n_b, n_g, n_a, n_f = good.shape
    pick_g = np.full((n_b, max_captures), -1, np.int64)
    pick_a = np.full((n_b, max_captures), -1, np.int64)
    pick_new = np.zeros((n_b, max_captures, n_f), np.bool_)
    pick_t = np.full((n_b, max_captures), -1, np.int64)
    cov = np.zeros((n_b, n_f), np.bool_)
    active = np.ones(n_b, np.bool_)
    vals = np.empty(n_f, np.int64)
    for r in range(max_captures):
        if not active.any():
            break
        for b in range(n_b):
            if not active[b]:
                continue
            best, best_g, best_a, best_gain = -np.inf, 0, 0, 0.0
            for g in range(n_g):
                for a in range(n_a):
                    gain = -1.0
                    if not taken[b, g]:
                        cnt = 0
                        for f in range(n_f):
                            if good[b, g, a, f] and not cov[b, f]:
                                cnt += 1
                        gain = float(cnt)
                    score = gain - tie[g, a]
                    if score > best:
                        best, best_g, best_a, best_gain = score, g, a, gain
            if best_gain < min_gain:
                active[b] = False
                continue
            n_v = 0
            for f in range(n_f):
                new = good[b, best_g, best_a, f] and not cov[b, f]
                pick_new[b, r, f] = new
                if new:
                    cov[b, f] = True
                    if target[b, best_g, best_a, f] >= 0:
                        vals[n_v] = target[b, best_g, best_a, f]
                        n_v += 1
            pick_t[b, r] = _mode(vals[:n_v])
            pick_g[b, r], pick_a[b, r] = best_g, best_a
            k = kk[b, best_g]
            for b2 in range(n_b):
                if b2 == b or (commit and pass_id[b2] == pass_id[b]):
                    for g in range(n_g):
                        if kk[b2, g] == k:
                            taken[b2, g] = True
    return pick_g, pick_a, pick_new, pick_t


@njit(cache=True)
def lines_near(points: NDArray, a: NDArray, e: NDArray, reach: float) -> tuple:  # pragma: no cover - compiled
    """For points (H, 2): the lines through ``a`` (L, 2) along the unit vectors ``e`` (L, 2) that pass within
    ``reach`` of each (``|(p - a) x e| <= reach``), in line order, and the point's position along each,
    ``(p - a) . e`` (the products and sums of ``np.sum(rel * e, axis=1)``, in its order, from its +0.0 start:
    the same floats, signed zeros included). Returns ``start`` (H + 1,) and the lines ``idx`` and positions
    ``along`` of point ``h`` at ``start[h]:start[h + 1]``: the (H, L) test without its (H, L, 2) temporaries
    (25,000 points by 34,000 lines at 100,000 heliostats)."""
    n_h, n_l = points.shape[0], a.shape[0]
    start = np.zeros(n_h + 1, np.int64)
    idx = np.empty(n_l + 64 * n_h, np.int64)
    along = np.empty(idx.shape[0], np.float64)
    m = 0
    for h in range(n_h):
        if m + n_l > idx.shape[0]:  # room for every line of this point
            idx = np.concatenate((idx, np.empty(idx.shape[0], np.int64)))
            along = np.concatenate((along, np.empty(along.shape[0], np.float64)))
        m = _near_one(points[h, 0], points[h, 1], a, e, reach, idx, along, m)
        start[h + 1] = m
    return start, idx[:m].copy(), along[:m].copy()


@njit(cache=True)
def _near_one(px: float, py: float, a: NDArray, e: NDArray, reach: float, idx: NDArray, along: NDArray,
              m: int) -> int:  # pragma: no cover - compiled
    """:func:`lines_near` of one point, written from ``m`` on; returns the end."""
    for j in range(a.shape[0]):
        rx = px - a[j, 0]
        ry = py - a[j, 1]
        if abs(rx * e[j, 1] - ry * e[j, 0]) <= reach:
            idx[m] = j
            along[m] = 0.0 + rx * e[j, 0] + ry * e[j, 1]  # np.sum's start at +0: -0.0 sums to +0.0 there too
            m += 1
    return m


@njit(cache=True)
def beam_suns(p: NDArray, q: NDArray, chord: NDArray, order: NDArray, cell_start: NDArray, x0: float, y0: float,
              cell: float, n_x: int, n_y: int, u: NDArray, c: NDArray, e: NDArray, length: NDArray, r0: float,
              theta: float) -> NDArray:  # pragma: no cover - compiled
    """Suns at points ``p`` (M, 3) in the beams of :class:`pihim.planning.flux.Beams`: (M,).

    Point ``i`` is tested against the beams whose direction ``u`` (N, 3; from the aim point toward mirror
    centre ``c``) is within ``chord[i]`` of its own direction ``q[i]``; candidates come from the grid over u's
    x, y (``n_x`` x ``n_y`` cells of ``cell`` from ``(x0, y0)``; cell ``cx * n_y + cy`` holds
    ``order[cell_start[c]:cell_start[c + 1]]``, a direction beyond the grid in its nearest edge cell) that meet
    the square of half-side ``chord[i]`` around ``q[i]``'s x, y, clamped into the grid (x, y distances never
    exceed the 3-D one, so no candidate is missed). A beam of axis ``e`` (mirror to aim point, unit) and
    length ``L`` holds the point where it is a fraction ``0 < f <= 1`` of the way and within ``(1 - f) r0 +
    f L theta`` of the axis, and adds ``(r0 / radius)^2``; the arithmetic is that of
    :func:`pihim.planning.sightlines.dot` and :func:`numpy.linalg.norm`, operation for operation. A point with
    a coordinate that is not finite is in no beam."""
    n = p.shape[0]
    out = np.zeros(n)
    for i in range(n):
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):
            continue
        qx, qy, qz, r = q[i, 0], q[i, 1], q[i, 2], chord[i]
        r2 = r * r
        cx0 = int(min(max((qx - r - x0) / cell, 0.0), n_x - 1.0))
        cx1 = int(min(max((qx + r - x0) / cell, 0.0), n_x - 1.0))
        cy0 = int(min(max((qy - r - y0) / cell, 0.0), n_y - 1.0))
        cy1 = int(min(max((qy + r - y0) / cell, 0.0), n_y - 1.0))
        s = 0.0
        for cx in range(cx0, cx1 + 1):
            for cy in range(cy0, cy1 + 1):
                k0 = cx * n_y + cy
                for k in range(cell_start[k0], cell_start[k0 + 1]):
                    h = order[k]
                    dx, dy, dz = u[h, 0] - qx, u[h, 1] - qy, u[h, 2] - qz
                    if dx * dx + dy * dy + dz * dz > r2:
                        continue
                    wx, wy, wz = px - c[h, 0], py - c[h, 1], pz - c[h, 2]
                    along = wx * e[h, 0] + wy * e[h, 1] + wz * e[h, 2]
                    f = along / length[h]
                    if not (f > 0.0 and f <= 1.0):
                        continue
                    ox, oy, oz = wx - along * e[h, 0], wy - along * e[h, 1], wz - along * e[h, 2]
                    radius = (1.0 - f) * r0 + f * length[h] * theta
                    if math.sqrt(ox * ox + oy * oy + oz * oz) <= radius:
                        g = r0 / max(radius, 1e-9)
                        s += g * g
        out[i] = s
    return out
