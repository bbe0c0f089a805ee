"""Compiled tracing of camera rays through a scene: specular bounces, first diffuse hit, sun visibility.

A camera ray is followed to its first hit. The front of a facet is a mirror:
the ray is reflected specularly and followed again, up to ``max_bounces``
times. The path ends (its *terminal*) at the sky, the sun disc, the ground,
the tower, a back-structure member or the back of a facet; for the last four
and the ground a shadow ray toward the sun says whether the sun lights the
terminal point. A path that would need more mirror bounces than allowed ends
as :data:`LOST` (black).

The kernel records geometry only; :mod:`pihim.render.shading` turns the
recorded paths into Stokes vectors with pihim's sky, ground and mirror
models.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, parallel_chunksize, prange
from numpy.typing import NDArray

from pihim.render.bvh import BLOCK, DYNAMIC_CHUNK, cast_one
from pihim.render.scene import FACET, TOWER, Scene

__all__ = [
    "FACET_BACK",
    "GROUND",
    "KIND_NAMES",
    "LOST",
    "MIRROR",
    "SKY",
    "STRUCTURE_HIT",
    "SUN",
    "TOWER_HIT",
    "Paths",
    "trace_paths",
]

#: What a ray hits (label codes; written into the label images).
SKY, SUN, GROUND, TOWER_HIT, MIRROR, FACET_BACK, STRUCTURE_HIT, LOST = 0, 1, 2, 3, 4, 5, 6, 7
KIND_NAMES = {SKY: "sky", SUN: "sun", GROUND: "ground", TOWER_HIT: "tower", MIRROR: "mirror",
              FACET_BACK: "facet_back", STRUCTURE_HIT: "structure", LOST: "lost"}

_EPS = 1e-7


@dataclass(frozen=True, eq=False)
class Paths:
    """Recorded geometry of traced camera rays (R rays, B = max bounces).

    Attributes
    ----------
    first_kind : (R,) int8
        What the camera ray hits first (a kind code).
    first_prim : (R,) int64
        Its rectangle (-1: sky, sun or ground).
    terminal_kind : (R,) int8
        Where the path ends.
    terminal_prim : (R,) int64
        Terminal rectangle (-1: sky, sun, ground, lost).
    terminal_point : (R, 3)
        Terminal point (NaN for sky, sun, lost), metres.
    terminal_dir : (R, 3)
        Direction of the last ray segment (toward the terminal), unit.
    terminal_normal : (R, 3)
        Surface normal at the terminal, turned toward the arriving ray.
    sun_visible : (R,) bool
        The sun lights the terminal point (lit side, no occluder).
    n_bounces : (R,) int8
        Mirror reflections on the path.
    bounce_normal : (R, B, 3)
        Mirror normals at the bounces (front side).
    bounce_dir : (R, B, 3)
        Ray direction arriving at each bounce (the first is the camera ray).
    bounce_prim : (R, B) int64
        Mirror rectangles of the bounces.
    """

    first_kind: NDArray[np.int8]
    first_prim: NDArray[np.int64]
    terminal_kind: NDArray[np.int8]
    terminal_prim: NDArray[np.int64]
    terminal_point: NDArray[np.float64]
    terminal_dir: NDArray[np.float64]
    terminal_normal: NDArray[np.float64]
    sun_visible: NDArray[np.bool_]
    n_bounces: NDArray[np.int8]
    bounce_normal: NDArray[np.float64]
    bounce_dir: NDArray[np.float64]
    bounce_prim: NDArray[np.int64]


@njit(cache=True)
def _ground_t(ox, oy, oz, dx, dy, dz, ga, gb, gc):  # pragma: no cover - compiled
    # plane z = a + b x + c y  <=>  -b x - c y + z = a; normal (-b, -c, 1)
    den = dz - gb * dx - gc * dy
    if den >= 0.0 or dz >= 0.0:  # moving away from the ground, or level/rising (see render.kernel)
        return np.inf
    t = (ga + gb * ox + gc * oy - oz) / den
    if t <= 0.0:
        return np.inf
    return t


@njit(parallel=True, cache=True)
def _trace(prim, order, box, node_first, node_count, node_right, normal,
           kind, has_ground, ga, gb, gc, sun, cos_sun, ray_o, ray_d, max_bounces,
           first_kind, first_prim, term_kind, term_prim, term_point, term_dir, term_normal, sun_vis,
           n_bounce, b_normal, b_dir, b_prim):  # pragma: no cover - compiled
    gn = np.array([-gb, -gc, 1.0])
    gn = gn / np.sqrt(gn[0] ** 2 + gn[1] ** 2 + gn[2] ** 2)
    n_rays = ray_o.shape[0]
    for blk in prange((n_rays + BLOCK - 1) // BLOCK):
        stack = np.empty(64, np.int64)
        for i in range(blk * BLOCK, min(n_rays, (blk + 1) * BLOCK)):
            ox, oy, oz = ray_o[i, 0], ray_o[i, 1], ray_o[i, 2]
            dx, dy, dz = ray_d[i, 0], ray_d[i, 1], ray_d[i, 2]
            skip = -1
            nb = 0
            tk = LOST
            tp = -1
            px = py = pz = np.nan
            nx = ny = nz = 0.0
            first_kind[i] = LOST
            first_prim[i] = -1
            while True:
                t, p = cast_one(prim, order, box, node_first, node_count, node_right,
                                ox, oy, oz, dx, dy, dz, 0.0, np.inf, skip, False, stack)
                tg = _ground_t(ox, oy, oz, dx, dy, dz, ga, gb, gc) if has_ground else np.inf
                if tg < t:
                    tk = GROUND
                    tp = -1
                    px, py, pz = ox + tg * dx, oy + tg * dy, oz + tg * dz
                    nx, ny, nz = gn[0], gn[1], gn[2]
                elif p >= 0:
                    pn0, pn1, pn2 = normal[p, 0], normal[p, 1], normal[p, 2]
                    facing = dx * pn0 + dy * pn1 + dz * pn2
                    px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
                    k = kind[p]
                    if k == FACET and facing < 0.0:
                        if nb == 0:
                            first_kind[i] = MIRROR
                            first_prim[i] = p
                        if nb >= max_bounces:
                            tk = LOST
                            tp = p
                            px = py = pz = np.nan
                            break
                        b_normal[i, nb, 0] = pn0
                        b_normal[i, nb, 1] = pn1
                        b_normal[i, nb, 2] = pn2
                        b_dir[i, nb, 0] = dx
                        b_dir[i, nb, 1] = dy
                        b_dir[i, nb, 2] = dz
                        b_prim[i, nb] = p
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
                first_kind[i] = tk
                first_prim[i] = tp
            term_kind[i] = tk
            term_prim[i] = tp
            term_point[i, 0], term_point[i, 1], term_point[i, 2] = px, py, pz
            term_dir[i, 0], term_dir[i, 1], term_dir[i, 2] = dx, dy, dz
            term_normal[i, 0], term_normal[i, 1], term_normal[i, 2] = nx, ny, nz
            n_bounce[i] = nb
            vis = False
            if tk == GROUND or tk == TOWER_HIT or tk == STRUCTURE_HIT or tk == FACET_BACK:
                if nx * sun[0] + ny * sun[1] + nz * sun[2] > 0.0:
                    sx, sy, sz = px + _EPS * nx, py + _EPS * ny, pz + _EPS * nz
                    ts, ps = cast_one(prim, order, box, node_first, node_count, node_right,
                                      sx, sy, sz, sun[0], sun[1], sun[2], 0.0, np.inf, tp, True, stack)
                    vis = ps < 0
            sun_vis[i] = vis


def trace_paths(
    scene: Scene,
    origins: NDArray[np.float64],
    directions: NDArray[np.float64],
    sun_dir: NDArray[np.float64],
    *,
    sun_half_angle_deg: float = 0.2666,
    max_bounces: int = 2,
) -> Paths:
    """Trace camera rays through ``scene`` (see the module notes).

    Parameters
    ----------
    scene : Scene
    origins, directions : ndarray, shape (R, 3)
        Ray origins (ENU metres) and unit directions.
    sun_dir : ndarray, shape (3,)
        Unit vector toward the sun.
    sun_half_angle_deg : float
        Angular radius of the sun disc (0.2666 deg: mean solar semi-diameter).
    max_bounces : int
        Mirror reflections followed (>= 0).

    Returns
    -------
    Paths
    """
    o = np.ascontiguousarray(origins, dtype=float).reshape(-1, 3)
    d = np.ascontiguousarray(directions, dtype=float).reshape(-1, 3)
    r = o.shape[0]
    b = max(int(max_bounces), 1)
    out = Paths(
        np.empty(r, np.int8), np.empty(r, np.int64), np.empty(r, np.int8), np.empty(r, np.int64),
        np.empty((r, 3)), np.empty((r, 3)), np.empty((r, 3)), np.empty(r, np.bool_), np.empty(r, np.int8),
        np.zeros((r, b, 3)), np.zeros((r, b, 3)), np.full((r, b), -1, np.int64),
    )
    g = scene.ground
    bvh = scene.bvh
    s = np.asarray(sun_dir, float)
    s = s / np.linalg.norm(s)
    with parallel_chunksize(DYNAMIC_CHUNK):
        _trace(*bvh.arrays(), bvh.normal, scene.kind, g is not None,
               *(g if g is not None else (0.0, 0.0, 0.0)), s, float(np.cos(np.radians(sun_half_angle_deg))),
               o, d, int(max_bounces),
               out.first_kind, out.first_prim, out.terminal_kind, out.terminal_prim, out.terminal_point,
               out.terminal_dir, out.terminal_normal, out.sun_visible, out.n_bounces, out.bounce_normal,
               out.bounce_dir, out.bounce_prim)
    return out
