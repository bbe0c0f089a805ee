"""Compiled inner loops of the planner (numba), imported where used so that the command line starts quickly."""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray


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
            vx = points[p, j, 0] - cam[p, 0]
            vy = points[p, j, 1] - cam[p, 1]
            vz = points[p, j, 2] - cam[p, 2]
            z = vx * f[p, 0] + vy * f[p, 1] + vz * f[p, 2]
            x = vx * r[p, 0] + vy * r[p, 1] + vz * r[p, 2]
            y = vx * dn[p, 0] + vy * dn[p, 1] + vz * dn[p, 2]
            out[p, j] = z > 0.0 and abs(x) <= tx * z and abs(y) <= ty * z
    return out


@njit(cache=True)
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
        ch, nh, w, nxy = ch_all[g], nh_all[g], w_all[g], nxy_all[g]
        tc, tn, tx, ty = tc_all[g], tn_all[g], tx_all[g], ty_all[g]
        c = code_low if elev_all[g] < min_elev else code_ok
        # the camera: where the direction w from the HUA to the camera reaches the pass altitude, on the line
        t = (altitude[i] - ch[2]) / w[2] if w[2] != 0.0 else (
            np.inf if altitude[i] - ch[2] > 0.0 else (-np.inf if altitude[i] - ch[2] < 0.0 else np.nan))
        ex = ch[0] + t * w[0] - origin[i, 0]
        ey = ch[1] + t * w[1] - origin[i, 1]
        along = ex * direction[i, 0] + ey * direction[i, 1]
        cam[i, 0] = origin[i, 0] + along * direction[i, 0]
        cam[i, 1] = origin[i, 1] + along * direction[i, 1]
        cam[i, 2] = altitude[i]
        dx, dy, dz = cam[i, 0] - ch[0], cam[i, 1] - ch[1], cam[i, 2] - ch[2]
        rg = np.sqrt(dx * dx + dy * dy + dz * dz)
        rng[i] = rg
        s = max(rg, 1e-12)
        v[i, 0], v[i, 1], v[i, 2] = dx / s, dy / s, dz / s
        vn = v[i, 0] * nh[0] + v[i, 1] * nh[1] + v[i, 2] * nh[2]
        if c == code_ok and (not np.isfinite(rg) or vn <= 0.0 or rg > max_range):
            c = code_behind
        # distance of the camera from the vertical plane of the HUA's normal
        offset[i] = abs(dx * nxy[1] - dy * nxy[0])
        if c == code_ok and offset[i] > max_offset:
            c = code_off_plane
        pitch = np.arctan2(-dz, np.hypot(dx, dy)) * to_deg
        bad = pitch < pitch_min - 1e-9 or pitch > pitch_max + 1e-9
        if use_keepout and (keepout[0, 0] <= cam[i, 0] <= keepout[1, 0] and keepout[0, 1] <= cam[i, 1] <= keepout[1, 1]
                            and keepout[0, 2] <= cam[i, 2] <= keepout[1, 2]):
            bad = True
        if c == code_ok and bad:
            c = code_gimbal
        if c == code_ok:  # the ray camera -> HUA centre reflected about the HUA's normal, against the target
            rx = 2.0 * vn * nh[0] - v[i, 0]
            ry = 2.0 * vn * nh[1] - v[i, 1]
            rz = 2.0 * vn * nh[2] - v[i, 2]
            r[i, 0], r[i, 1], r[i, 2] = rx, ry, rz
            denom = rx * tn[0] + ry * tn[1] + rz * tn[2]
            num = (tc[0] - ch[0]) * tn[0] + (tc[1] - ch[1]) * tn[1] \
                + (tc[2] - ch[2]) * tn[2]
            lam = num / denom if denom != 0.0 else np.nan
            hx, hy, hz = ch[0] + lam * rx, ch[1] + lam * ry, ch[2] + lam * rz
            hit[i, 0], hit[i, 1], hit[i, 2] = hx, hy, hz
            qx0, qy0, qz0 = hx - tc[0], hy - tc[1], hz - tc[2]
            qx = abs(qx0 * tx[0] + qy0 * tx[1] + qz0 * tx[2]) - half_w
            qy = abs(qx0 * ty[0] + qy0 * ty[1] + qz0 * ty[2]) - half_h
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
def first_hits(p0: NDArray, p1: NDArray, ray: NDArray, rect: NDArray, exclude: NDArray, centres: NDArray,
               normals: NDArray, x: NDArray, y: NDArray, hw: float, hh: float,
               eps: float) -> NDArray:  # pragma: no cover - compiled
    """For candidate (segment ``ray``, mirror ``rect``) pairs, the first mirror each segment p0 -> p1 crosses
    strictly inside (``eps < t < 1 - eps``) within its half-width ``hw`` and half-height ``hh`` (-1 for
    none), skipping the mirrors in ``exclude[ray]``; equal ``t`` keeps the earlier pair."""
    n = p0.shape[0]
    out = np.full(n, -1, np.int64)
    best = np.full(n, np.inf)
    for m in range(ray.shape[0]):
        i, j = ray[m], rect[m]
        skip = False
        for e in range(exclude.shape[1]):
            if exclude[i, e] == j:
                skip = True
        if skip:
            continue
        dx, dy, dz = p1[i, 0] - p0[i, 0], p1[i, 1] - p0[i, 1], p1[i, 2] - p0[i, 2]
        denom = dx * normals[j, 0] + dy * normals[j, 1] + dz * normals[j, 2]
        num = (centres[j, 0] - p0[i, 0]) * normals[j, 0] + (centres[j, 1] - p0[i, 1]) * normals[j, 1] \
            + (centres[j, 2] - p0[i, 2]) * normals[j, 2]
        if denom == 0.0:
            continue
        t = num / denom
        if not (np.isfinite(t) and t > eps and t < 1.0 - eps) or not t < best[i]:
            continue
        qx = p0[i, 0] + t * dx - centres[j, 0]
        qy = p0[i, 1] + t * dy - centres[j, 1]
        qz = p0[i, 2] + t * dz - centres[j, 2]
        if abs(qx * x[j, 0] + qy * x[j, 1] + qz * x[j, 2]) <= hw and abs(qx * y[j, 0] + qy * y[j, 1]
                                                                         + qz * y[j, 2]) <= hh:
            best[i] = t
            out[i] = j
    return out
