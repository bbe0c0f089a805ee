"""Fused compiled kernel: pixel -> ray -> path -> Stokes in the image frame, with labels.

The same light transport as :func:`pihim.render.paths.trace_paths` followed
by :func:`pihim.render.shading.shade_paths` (the numpy reference, which the
tests hold this kernel to), done per ray in one compiled loop so that no
per-ray arrays travel through memory:

* the pixel's ray is formed in the kernel (OpenCV pinhole with Brown-Conrady
  distortion inverted by Newton's method, as
  :meth:`pihim.camera.model.CameraModel.pixel_rays`);
* the sky comes from :class:`pihim.sky.table.SkyTable` (the sky model
  tabulated on a Lambert azimuthal grid; frame ``e_T``), the ground from
  :class:`pihim.render.shading.GroundTable`, the mirror's Mueller matrix from
  :class:`pihim.render.shading.MirrorTable`;
* rough finishes are evaluated in closed form (diffuse + Torrance-Sparrow
  sun glint with a dielectric Fresnel coating), as
  :func:`pihim.render.shading.finish_stokes`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, parallel_chunksize, prange

from pihim.render.bvh import BLOCK, DYNAMIC_CHUNK, cast_one
from pihim.render.paths import (
    FACET_BACK,
    GROUND,
    LOST,
    MIRROR,
    SKY,
    STRUCTURE_HIT,
    SUN,
    TOWER_HIT,
)
from pihim.render.scene import FACET, TOWER
from pihim.sky.table import sample_table

__all__ = ["render_rays"]

_EPS = 1e-7


@njit(inline="always", cache=True)
def _rotate(s1, s2, dx, dy, dz, ax, ay, az, bx, by, bz):  # pragma: no cover - compiled
    """Stokes S1, S2 re-expressed from axis ``a`` to axis ``b`` (both normal to ``d``)."""
    c = ax * bx + ay * by + az * bz
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    s = cx * dx + cy * dy + cz * dz
    r = c * c + s * s
    if r <= 0.0:
        return s1, s2
    c2 = (c * c - s * s) / r
    s2n = 2.0 * c * s / r
    return c2 * s1 + s2n * s2, -s2n * s1 + c2 * s2


@njit(inline="always", cache=True)
def _perp(dx, dy, dz, hx, hy, hz, fx, fy, fz):  # pragma: no cover - compiled
    """``hint`` made perpendicular to ``d`` (``fallback`` where nearly parallel), unit."""
    k = hx * dx + hy * dy + hz * dz
    ex, ey, ez = hx - k * dx, hy - k * dy, hz - k * dz
    n = math.sqrt(ex * ex + ey * ey + ez * ez)
    if n < 1e-6:
        k = fx * dx + fy * dy + fz * dz
        ex, ey, ez = fx - k * dx, fy - k * dy, fz - k * dz
        n = math.sqrt(ex * ex + ey * ey + ez * ez)
    return ex / n, ey / n, ez / n


@njit(inline="always", cache=True)
def _undistort(xd, yd, k1, k2, p1, p2, k3):  # pragma: no cover - compiled
    if k1 == 0.0 and k2 == 0.0 and p1 == 0.0 and p2 == 0.0 and k3 == 0.0:
        return xd, yd
    x, y = xd, yd
    for _ in range(30):
        r2 = x * x + y * y
        rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        ex = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
        ey = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
        if abs(ex) < 1e-15 and abs(ey) < 1e-15:
            break
        drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d rad / d r2
        jxx = rad + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
        jxy = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
        jyx = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
        jyy = rad + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
        det = jxx * jyy - jxy * jyx
        if det == 0.0:
            return np.nan, np.nan
        x -= (jyy * ex - jxy * ey) / det
        y -= (-jyx * ex + jxx * ey) / det
    return x, y


@njit(parallel=True, cache=True)
def _kernel(prim, order, box, node_first, node_count, node_right, normal,
            kind, prim_heliostat, prim_facet, prim_group, has_ground, ga, gb, gc,
            sun, cos_sun, sun_radiance, sun_irr, sky_irr,
            sky_table, sky_radius, sky_step,
            g_sky, g_sun, g_step, g_astep,
            m_cos_n, m_a, m_b, m_c, m_d,
            finish,
            cam_pos, rot, fx, fy, cx, cy, dist, px_u, px_v, max_bounces,
            out_stokes, out_key, out_labels):  # pragma: no cover - compiled
    n = px_u.shape[0]
    n_blocks = (n + BLOCK - 1) // BLOCK
    nb_max = max(max_bounces, 1)
    gz_n = g_sky.shape[0]
    ga_n = g_sky.shape[1]
    gnx, gny, gnz = -gb, -gc, 1.0
    gl = math.sqrt(gnx * gnx + gny * gny + gnz * gnz)
    gnx, gny, gnz = gnx / gl, gny / gl, gnz / gl
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for blk in prange(n_blocks):
        stack = np.empty(64, np.int64)
        bn = np.empty((nb_max, 3))
        bd = np.empty((nb_max, 3))
        for i in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            # ---- camera ray
            xn, yn = _undistort((px_u[i] - cx) / fx, (px_v[i] - cy) / fy, k1, k2, p1, p2, k3)
            inv = 1.0 / math.sqrt(xn * xn + yn * yn + 1.0)
            xc, yc, zc = xn * inv, yn * inv, inv
            # world = R^T cam (rows of R are the camera axes)
            dx = rot[0, 0] * xc + rot[1, 0] * yc + rot[2, 0] * zc
            dy = rot[0, 1] * xc + rot[1, 1] * yc + rot[2, 1] * zc
            dz = rot[0, 2] * xc + rot[1, 2] * yc + rot[2, 2] * zc
            ox, oy, oz = cam_pos[0], cam_pos[1], cam_pos[2]
            # ---- trace
            skip = -1
            nb = 0
            tk = LOST
            tp = -1
            fk = LOST
            fp = -1
            px = py = pz = 0.0
            nx = ny = nz = 0.0
            valid = not (math.isnan(dx) or math.isnan(dy) or math.isnan(dz))
            while valid:
                t, p = cast_one(prim, order, box, node_first, node_count, node_right,
                                ox, oy, oz, dx, dy, dz, 0.0, np.inf, skip, False, stack)
                tg = np.inf
                if has_ground:
                    den = dz - gb * dx - gc * dy
                    # only rays going down reach the ground: the fitted plane is local to the field, and a
                    # slightly rising ray would otherwise meet it kilometres away where the ground rises
                    if den < 0.0 and dz < 0.0:
                        tt = (ga + gb * ox + gc * oy - oz) / den
                        if tt > 0.0:
                            tg = tt
                if tg < t:
                    tk = GROUND
                    tp = -1
                    px, py, pz = ox + tg * dx, oy + tg * dy, oz + tg * dz
                    nx, ny, nz = gnx, gny, gnz
                elif p >= 0:
                    pn0, pn1, pn2 = normal[p, 0], normal[p, 1], normal[p, 2]
                    facing = dx * pn0 + dy * pn1 + dz * pn2
                    px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
                    k = kind[p]
                    if k == FACET and facing < 0.0:
                        if nb == 0:
                            fk = MIRROR
                            fp = p
                        if nb >= max_bounces:
                            tk = LOST
                            tp = p
                            break
                        bn[nb, 0], bn[nb, 1], bn[nb, 2] = pn0, pn1, pn2
                        bd[nb, 0], bd[nb, 1], bd[nb, 2] = dx, dy, dz
                        nb += 1
                        dx, dy, dz = dx - 2.0 * facing * pn0, dy - 2.0 * facing * pn1, dz - 2.0 * facing * pn2
                        ox, oy, oz = px, py, pz
                        skip = p
                        continue
                    if k == FACET:
                        tk = FACET_BACK
                    elif k == TOWER:
                        tk = TOWER_HIT
                    else:
                        tk = STRUCTURE_HIT
                    tp = p
                    sgn = -1.0 if facing > 0.0 else 1.0
                    nx, ny, nz = sgn * pn0, sgn * pn1, sgn * pn2
                else:
                    tp = -1
                    if dx * sun[0] + dy * sun[1] + dz * sun[2] >= cos_sun:
                        tk = SUN
                    else:
                        tk = SKY
                break
            if nb == 0:
                fk = tk
                fp = tp
            vis = False
            if tk == GROUND or tk == TOWER_HIT or tk == STRUCTURE_HIT or tk == FACET_BACK:
                if nx * sun[0] + ny * sun[1] + nz * sun[2] > 0.0:
                    ts, ps = cast_one(prim, order, box, node_first, node_count, node_right,
                                      px + _EPS * nx, py + _EPS * ny, pz + _EPS * nz,
                                      sun[0], sun[1], sun[2], 0.0, np.inf, tp, True, stack)
                    vis = ps < 0
            # ---- terminal Stokes in frame (d = light direction, e)
            ldx, ldy, ldz = -dx, -dy, -dz
            s0 = s1 = s2 = s3 = 0.0
            ex, ey, ez = _perp(ldx, ldy, ldz, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0)
            if tk == SKY or tk == SUN:
                if dz > 0.0:
                    # sky Stokes in the table's frame e_T(l), l = the ray direction (toward the sky)
                    s0, s1, s2, s3, ex, ey, ez = sample_table(sky_table, sky_radius, sky_step, dx, dy, dz)
                if tk == SUN:
                    s0 += sun_radiance
            elif tk == GROUND:
                vz = min(max(ldz, 0.0), 1.0)
                if vz > 0.0:
                    zen = math.degrees(math.acos(vz))
                    azd = math.degrees(math.atan2(ldx, ldy)) % 360.0
                    fi = min(max(zen / g_step, 0.0), gz_n - 1.000001)
                    fj = min(max(azd / g_astep, 0.0), ga_n - 1.000001)
                    i0 = int(fi)
                    j0 = int(fj)
                    wi = fi - i0
                    wj = fj - j0
                    for c in range(4):
                        val = ((1 - wi) * ((1 - wj) * g_sky[i0, j0, c] + wj * g_sky[i0, j0 + 1, c])
                               + wi * ((1 - wj) * g_sky[i0 + 1, j0, c] + wj * g_sky[i0 + 1, j0 + 1, c]))
                        if vis:
                            val += ((1 - wi) * ((1 - wj) * g_sun[i0, j0, c] + wj * g_sun[i0, j0 + 1, c])
                                    + wi * ((1 - wj) * g_sun[i0 + 1, j0, c] + wj * g_sun[i0 + 1, j0 + 1, c]))
                        if c == 0:
                            s0 = val
                        elif c == 1:
                            s1 = val
                        elif c == 2:
                            s2 = val
                        else:
                            s3 = val
                    ex, ey, ez = _perp(ldx, ldy, ldz, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0)
            elif tk == STRUCTURE_HIT or tk == FACET_BACK or tk == TOWER_HIT:
                fi_ = 0 if tk == STRUCTURE_HIT else (1 if tk == FACET_BACK else 2)
                albedo = finish[fi_, 0]
                sigma = finish[fi_, 1]
                n_idx = finish[fi_, 2]
                knorm = finish[fi_, 3]
                vx, vy, vz = ldx, ldy, ldz
                cos_sn = nx * sun[0] + ny * sun[1] + nz * sun[2]
                lit = vis and cos_sn > 0.0
                cos_vn = min(max(vx * nx + vy * ny + vz * nz, 1e-6), 1.0)
                s0 = albedo / math.pi * ((sun_irr * cos_sn if lit else 0.0) + sky_irr * 0.5 * (1.0 + nz))
                if lit:
                    hx, hy, hz = vx + sun[0], vy + sun[1], vz + sun[2]
                    hl = math.sqrt(hx * hx + hy * hy + hz * hz)
                    if hl > 1e-12:
                        hx, hy, hz = hx / hl, hy / hl, hz / hl
                        cc = min(max(vx * hx + vy * hy + vz * hz, 0.0), 1.0)
                        hn = min(max(hx * nx + hy * ny + hz * nz, -1.0), 1.0)
                        alpha = math.acos(hn)
                        if cc > 0.0 and alpha <= 0.5 * math.pi:
                            dens = math.exp(-0.5 * (alpha / sigma) ** 2) / (2.0 * math.pi * knorm)
                            g = min(1.0, 2.0 * hn * cos_vn / cc, 2.0 * hn * cos_sn / cc)
                            g = min(max(g, 0.0), 1.0)
                            w = dens * g / (4.0 * cos_vn)
                            ct = math.sqrt(max(1.0 - (1.0 - cc * cc) / (n_idx * n_idx), 0.0))
                            rs = (cc - n_idx * ct) / (cc + n_idx * ct)
                            rp = (n_idx * cc - ct) / (n_idx * cc + ct)
                            a_ = 0.5 * (rs * rs + rp * rp)
                            b_ = 0.5 * (rs * rs - rp * rp)
                            s0 += w * sun_irr * a_
                            s1 = w * sun_irr * b_
                            # s axis: (incident light direction -sun) x h
                            qx = -sun[1] * hz + sun[2] * hy
                            qy = -sun[2] * hx + sun[0] * hz
                            qz = -sun[0] * hy + sun[1] * hx
                            ql = math.sqrt(qx * qx + qy * qy + qz * qz)
                            if ql > 1e-12:
                                ex, ey, ez = qx / ql, qy / ql, qz / ql
                            else:
                                s1 = 0.0
            # ---- mirror bounces, last first
            cdx, cdy, cdz = ldx, ldy, ldz  # light propagation direction
            for kb in range(nb - 1, -1, -1):
                mnx, mny, mnz = bn[kb, 0], bn[kb, 1], bn[kb, 2]
                ci = abs(cdx * mnx + cdy * mny + cdz * mnz)
                # s axis = normalize(d x n); fallback: current e at normal incidence
                qx = cdy * mnz - cdz * mny
                qy = cdz * mnx - cdx * mnz
                qz = cdx * mny - cdy * mnx
                ql = math.sqrt(qx * qx + qy * qy + qz * qz)
                if ql > 1e-12:
                    qx, qy, qz = qx / ql, qy / ql, qz / ql
                    s1, s2 = _rotate(s1, s2, cdx, cdy, cdz, ex, ey, ez, qx, qy, qz)
                    ex, ey, ez = qx, qy, qz
                fpos = ci * (m_cos_n - 1)
                j = min(int(fpos), m_cos_n - 2)
                wj = fpos - j
                a_ = (1 - wj) * m_a[j] + wj * m_a[j + 1]
                b_ = (1 - wj) * m_b[j] + wj * m_b[j + 1]
                c_ = (1 - wj) * m_c[j] + wj * m_c[j + 1]
                d_ = (1 - wj) * m_d[j] + wj * m_d[j + 1]
                s0, s1 = a_ * s0 + b_ * s1, b_ * s0 + a_ * s1
                s2, s3 = c_ * s2 + d_ * s3, -d_ * s2 + c_ * s3
                # at normal incidence (ql ~ 0) e stays: it is also normal to the reversed beam
                cdx, cdy, cdz = -bd[kb, 0], -bd[kb, 1], -bd[kb, 2]
            # ---- into the image frame: e_img = camera x made perpendicular to the beam
            rx, ry, rz = rot[0, 0], rot[0, 1], rot[0, 2]
            eix, eiy, eiz = _perp(cdx, cdy, cdz, rx, ry, rz, rot[1, 0], rot[1, 1], rot[1, 2])
            s1, s2 = _rotate(s1, s2, cdx, cdy, cdz, ex, ey, ez, eix, eiy, eiz)
            if tk == LOST or not valid or not math.isfinite(s0):
                s0 = s1 = s2 = 0.0
            out_stokes[i, 0] = s0
            out_stokes[i, 1] = s1
            out_stokes[i, 2] = s2
            # ---- labels and edge key
            fh = prim_heliostat[fp] if fp >= 0 else -1
            ff = prim_facet[fp] if fp >= 0 else 0
            out_labels[i, 0] = fk
            out_labels[i, 1] = fh
            out_labels[i, 2] = ff
            if nb > 0:
                out_labels[i, 3] = tk
                out_labels[i, 4] = prim_heliostat[tp] if tp >= 0 else -1
                out_labels[i, 5] = prim_facet[tp] if tp >= 0 else 0
            else:
                out_labels[i, 3] = -1
                out_labels[i, 4] = -1
                out_labels[i, 5] = -1
            out_labels[i, 6] = nb
            fg = prim_group[fp] + 1 if fp >= 0 else 0
            tg_ = prim_group[tp] + 1 if tp >= 0 else 0
            key = (fg << 30) ^ (tg_ << 6) ^ (fk << 3) ^ tk
            if vis:
                key ^= 1 << 61
            key ^= nb << 62
            out_key[i] = key


def render_rays(scene, tables, camera_arrays, px_u, px_v, max_bounces, out_stokes, out_key, out_labels):
    """Run the fused kernel on pixel coordinates ``px_u``, ``px_v`` (see :func:`pihim.render.frame.render_frame`)."""
    b = scene.bvh
    g = scene.ground if scene.ground is not None else (0.0, 0.0, 0.0)
    # dynamic scheduling: image rows differ in cost, equal static halves leave a thread idle
    with parallel_chunksize(DYNAMIC_CHUNK):
        _kernel(*b.arrays(), b.normal, scene.kind, scene.heliostat, scene.facet, scene.group, scene.ground is not None,
                float(g[0]), float(g[1]), float(g[2]), *tables, *camera_arrays, px_u, px_v, int(max_bounces),
                out_stokes, out_key, out_labels)
