"""Camera positions that show the paper's contrast scenarios (sky-vs-sky, ground-vs-ground) in a rendered field.

The paper's sky-vs-sky test (Tian et al., section 4.1, Figs. 4 and 6a-e)
looks at a front heliostat whose top edge lies, in the image, over a back
heliostat; both mirrors reflect sky, so S0 shows little contrast across the
edge, while the DoLP of the two reflections differs (the paper asks for a
difference above 0.2). :func:`sky_vs_sky_view` searches a grid of camera
positions for the one where :func:`pihim.scenarios.sky_vs_sky` predicts the
largest DoLP difference along that edge, with every condition of the
scenario checked in the scene itself (ray casts through its BVH), so that a
render from there shows what the prediction says.

The ground-vs-ground test (section 4.2, Figs. 5 and 6f-g) looks down at a
heliostat's lower edge: the mirror reflects the ground and the real ground
lies beyond the edge, so S0 shows little contrast while the AoP of the two
differs (the paper asks for more than 50 deg). :func:`ground_vs_ground_view`
searches the camera for it the same way, with
:func:`pihim.scenarios.ground_vs_ground`.

This module chooses *where to look from*; it reads the scene's true geometry
and is meant for building test sets of rendered frames, never for the
estimator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose, project_points
from pihim.errors import PihimInputError
from pihim.render.bvh import cast_rays
from pihim.render.scene import Scene, field_scene
from pihim.render.shading import Environment
from pihim.scenarios import GROUND_AOP_DIFFERENCE_MIN_DEG, ground_vs_ground, sky_vs_sky

__all__ = ["GroundVsGroundView", "SkyOverlap", "SkyVsSkyView", "ground_vs_ground_view", "sky_overlap",
           "sky_vs_sky_view"]


def _unit(v: NDArray) -> NDArray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _clear(scene: Scene, origins: NDArray, targets: NDArray, stop: float = 1.0) -> NDArray[np.bool_]:
    """Whether no scene rectangle lies on the segments ``origin -> origin + stop (target - origin)``."""
    o = np.ascontiguousarray(np.broadcast_to(origins, np.shape(targets)), dtype=float)
    _, prim = cast_rays(scene.bvh, o, np.asarray(targets, float) - o, t_max=stop)
    return prim < 0


def _sunlit(scene: Scene, points: NDArray, sun_vec: NDArray) -> NDArray[np.bool_]:
    """Whether the sun (its centre) is seen from ``points``: nothing of the scene toward it."""
    p = np.ascontiguousarray(points, dtype=float)
    _, prim = cast_rays(scene.bvh, p + 1e-6 * sun_vec, np.ascontiguousarray(np.broadcast_to(sun_vec, p.shape)))
    return prim < 0


def _ground_hit(origin: NDArray, d: NDArray, plane: tuple[float, float, float]) -> NDArray:
    """Where rays meet the ground plane ``z = a + b x + c y``."""
    a, b, c = plane
    t = (a + b * origin[..., 0] + c * origin[..., 1] - origin[..., 2]) / (d[..., 2] - b * d[..., 0] - c * d[..., 1])
    return origin + t[..., None] * d


def _grid(centre: NDArray, radius_m: float, heights_m: tuple[float, float], step_m: float) -> NDArray:
    r = np.arange(-radius_m, radius_m + 1e-9, step_m)
    zs = np.arange(heights_m[0], heights_m[1] + 1e-9, 1.0)
    gx, gy, gz = np.meshgrid(centre[0] + r, centre[1] + r, zs, indexing="ij")
    cams = np.stack([gx, gy, gz], axis=-1).reshape(-1, 3)
    return cams[np.linalg.norm(cams[:, :2] - centre[:2], axis=1) <= radius_m]


@dataclass(frozen=True)
class SkyOverlap:
    """Where the front's top edge lies over the back heliostat in the image.

    Attributes
    ----------
    length_px : float
        Length of the top edge, in pixels, whose outside (4 px away from the
        front) falls inside the back heliostat's projected outline.
    centre_m : ndarray, shape (3,)
        Mean ENU point of that stretch of the edge (the front's top-edge
        midpoint when there is none).
    edge_px : ndarray, shape (41, 2)
        The projected top edge, left to right.
    inside : ndarray of bool, shape (41,)
        Which of those points lie over the back heliostat.
    """

    length_px: float
    centre_m: NDArray[np.float64]
    edge_px: NDArray[np.float64]
    inside: NDArray[np.bool_]


def sky_overlap(field_pose, front: int, back: int, camera: CameraModel, camera_m,
                look_at_m=None) -> SkyOverlap:
    """Project the front's top edge and the back's outline with a camera looking at the edge.

    Parameters
    ----------
    field_pose : pihim.field.FieldPose
    front, back : int
        Heliostat indices.
    camera : CameraModel
    camera_m : array_like, shape (3,)
        Camera position, ENU metres.
    look_at_m : array_like, shape (3,), optional
        Where the camera looks (default: the front's top-edge midpoint).
    """
    from matplotlib.path import Path as MplPath

    out = field_pose.mirror_outline()
    fo, bo = out[front], out[back]
    top = 0.5 * (fo[0] + fo[1])
    cp = CameraPose.look_at(np.asarray(camera_m, float), top if look_at_m is None else np.asarray(look_at_m, float))
    s = np.linspace(0.0, 1.0, 41)[:, None]
    edge3 = fo[0] + s * (fo[1] - fo[0])
    edge = project_points(camera, cp, edge3)
    back_px = project_points(camera, cp, bo)
    centre_f = project_points(camera, cp, field_pose.mirror_centres[front][None])[0]
    t = _unit(edge[-1] - edge[0])
    nrm = np.array([-t[1], t[0]])
    if (centre_f - edge[20]) @ nrm > 0:
        nrm = -nrm
    inside = MplPath(back_px).contains_points(edge + 4.0 * nrm)
    step_px = float(np.linalg.norm(edge[-1] - edge[0])) / 40
    mid3 = edge3[inside].mean(axis=0) if inside.any() else top
    return SkyOverlap(float(inside.sum() * step_px), mid3, edge, inside)


@dataclass(frozen=True)
class SkyVsSkyView:
    """A camera position showing a front heliostat's top edge over a back heliostat, both reflecting sky.

    Attributes
    ----------
    front, back : int
        Heliostat indices.
    camera_m, look_at_m : ndarray, shape (3,)
        Camera position and the point it looks at (the middle of the
        overlapping stretch of the front's top edge), ENU metres.
    dolp_difference : float
        Predicted mean |DoLP(front) - DoLP(back)| along the edge.
    front_dolp, back_dolp, front_s0, back_s0 : float
        Predicted means of the two reflections (S0 in the sky model's units).
    s0_contrast : float
        Predicted Michelson contrast of the two S0.
    sun_angles_deg : (float, float)
        Mean angle between each reflection's sky direction and the sun.
    overlap_px : float
        Length of the front's top edge over the back heliostat in the image.
    candidates : int
        Camera positions that met every condition but the overlap and contrast.
    """

    front: int
    back: int
    camera_m: NDArray[np.float64]
    look_at_m: NDArray[np.float64]
    dolp_difference: float
    front_dolp: float
    back_dolp: float
    front_s0: float
    back_s0: float
    s0_contrast: float
    sun_angles_deg: tuple[float, float]
    overlap_px: float
    candidates: int

    def camera_pose(self, roll_deg: float = 0.0) -> CameraPose:
        """The camera pose (looking at :attr:`look_at_m`)."""
        return CameraPose.look_at(self.camera_m, self.look_at_m, roll_deg)


def sky_vs_sky_view(
    field_pose,
    front: int,
    back: int,
    environment: Environment,
    camera: CameraModel,
    *,
    heights_m: tuple[float, float] = (15.0, 30.0),
    radius_m: float = 60.0,
    step_m: float = 1.0,
    edge_samples: int = 11,
    sun_clearance_deg: float = 25.0,
    min_overlap_px: float = 300.0,
    min_dolp_difference: float = 0.2,
    max_s0_contrast: float | None = None,
    scene: Scene | None = None,
) -> SkyVsSkyView | None:
    """The camera position with the largest predicted DoLP difference across the front's top edge.

    The front's top edge is sampled at ``edge_samples`` points; at each, the
    front point is 0.3 m below the edge and the back point is where the
    sightline over the edge meets the back mirror. Camera positions lie on a
    grid of ``step_m`` within ``radius_m`` (horizontally) of the edge's
    midpoint, ``heights_m`` above the ground, on the side of the front away
    from the back. A sample point counts where the sightline lands on the
    back mirror, both mirror points are in view, both reflections reach the
    sky past every object of the scene and lie at least
    ``sun_clearance_deg`` from the sun; a position is scored by the mean over
    its counted points (at least a quarter of them) of
    :func:`pihim.scenarios.sky_vs_sky`'s DoLP difference. The best position
    whose mean difference exceeds ``min_dolp_difference``, whose predicted S0
    Michelson contrast is at most ``max_s0_contrast`` (if given) and whose
    top edge covers the back heliostat over at least ``min_overlap_px`` in
    the image wins.

    Parameters
    ----------
    field_pose : pihim.field.FieldPose
        The heliostats as they stand (the pair and everything that may hide it).
    front, back : int
        Heliostat indices.
    environment : Environment
        Sun, sky and mirror model (:meth:`Environment.clear_sky`).
    camera : CameraModel
        The camera the overlap is measured with.
    scene : Scene, optional
        ``field_scene(field_pose)`` if already built.

    Returns
    -------
    SkyVsSkyView or None
        None when no position meets the conditions.

    References
    ----------
    Tian et al., PIHIM, section 4.1 (sky-vs-sky; DoLP difference > 0.2).
    """
    if front == back:
        raise PihimInputError("the front and back heliostats must differ")
    if not isinstance(camera, CameraModel):
        raise PihimInputError(f"camera must be a CameraModel, got {type(camera).__name__}")
    scene = field_scene(field_pose) if scene is None else scene
    sun_vec = np.asarray(environment.sun_dir, float)
    out = field_pose.mirror_outline()
    fo, bo = out[front], out[back]
    up_f = _unit(fo[0] - fo[3])
    top = 0.5 * (fo[0] + fo[1])
    away = field_pose.mirror_centres[front][:2] - field_pose.mirror_centres[back][:2]
    away = away / (np.linalg.norm(away) or 1.0)
    cams = _grid(top, radius_m, heights_m, step_m)
    cams = cams[(cams[:, :2] - top[:2]) @ away >= 0.0]
    k = int(edge_samples)
    edge = fo[0] + ((np.arange(k) + 0.5) / k)[:, None] * (fo[1] - fo[0])  # (K, 3)
    c = np.broadcast_to(cams[:, None, :], (len(cams), k, 3))
    d = _unit(edge[None] - c)
    n_b, c_b = field_pose.normals[back], field_pose.mirror_centres[back]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_b = ((c_b - c) @ n_b) / (d @ n_b)
    q = c + t_b[..., None] * d
    bx, by = _unit(bo[1] - bo[0]), _unit(bo[0] - bo[3])
    hw, hh = 0.5 * np.linalg.norm(bo[1] - bo[0]), 0.5 * np.linalg.norm(bo[0] - bo[3])
    lx, ly = (q - c_b) @ bx, (q - c_b) @ by
    on_back = (t_b > np.linalg.norm(edge[None] - c, axis=-1)) & (np.abs(lx) < hw - 0.1) & (np.abs(ly) < hh - 0.1)
    p_front = np.broadcast_to(edge - 0.3 * up_f, c.shape)
    q = np.where(on_back[..., None], q, c_b)  # keep the arithmetic finite where the sightline misses
    pred = sky_vs_sky(c, p_front, field_pose.normals[front], q, n_b, sun_vec, environment.sky, environment.mirror)
    ang_f = np.degrees(np.arccos(np.clip(pred.front.source_dir @ sun_vec, -1, 1)))
    ang_b = np.degrees(np.arccos(np.clip(pred.back.source_dir @ sun_vec, -1, 1)))
    ok = on_back & np.isfinite(pred.dolp_difference) & (ang_f >= sun_clearance_deg) & (ang_b >= sun_clearance_deg)
    pf = (p_front + 0.01 * field_pose.normals[front]).reshape(-1, 3)
    pb = (q + 0.01 * n_b).reshape(-1, 3)
    cf = c.reshape(-1, 3)
    clear = (_clear(scene, cf, pf, stop=0.98) & _clear(scene, cf, pb, stop=0.98)
             & _clear(scene, pf, pf + 1e4 * pred.front.source_dir.reshape(-1, 3))
             & _clear(scene, pb, pb + 1e4 * pred.back.source_dir.reshape(-1, 3)))
    ok &= clear.reshape(ok.shape)
    counted = ok.sum(axis=1)
    good = counted >= max(2, k // 4)

    def mean(x: NDArray) -> NDArray:
        return np.where(ok, x, 0.0).sum(axis=1) / np.maximum(counted, 1)

    diff = np.where(good, mean(pred.dolp_difference), -np.inf)
    s0_f, s0_b = mean(pred.front.stokes[..., 0]), mean(pred.back.stokes[..., 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        contrast = np.abs(s0_f - s0_b) / (s0_f + s0_b)
    keep = good & (diff > float(min_dolp_difference))
    if max_s0_contrast is not None:
        keep &= contrast <= float(max_s0_contrast)
    order = np.flatnonzero(keep)[np.argsort(-diff[keep])]
    for j in order:  # best first: the first whose front's top edge covers the back in the image wins
        ov = sky_overlap(field_pose, front, back, camera, cams[j])
        if ov.length_px >= min_overlap_px:
            ov = sky_overlap(field_pose, front, back, camera, cams[j], look_at_m=ov.centre_m)
            if ov.length_px < min_overlap_px:
                continue
            return SkyVsSkyView(
                int(front), int(back), cams[j].copy(), ov.centre_m.copy(), float(diff[j]),
                float(mean(pred.front.dolp)[j]), float(mean(pred.back.dolp)[j]), float(s0_f[j]), float(s0_b[j]),
                float(contrast[j]), (float(mean(ang_f)[j]), float(mean(ang_b)[j])), float(ov.length_px),
                int(good.sum()),
            )
    return None


@dataclass(frozen=True)
class GroundVsGroundView:
    """A camera position looking down at a heliostat's lower edge, mirror-reflected ground against real ground.

    Attributes
    ----------
    heliostat : int
        Heliostat index.
    camera_m, look_at_m : ndarray, shape (3,)
        Camera position and the point of the lower edge it looks at, ENU metres.
    aop_difference_deg : float
        Predicted mean axial AoP difference, mirror vs ground, deg in [0, 90].
    mirror_dolp, ground_dolp : float
        Predicted mean DoLP of the reflected and the real ground.
    s0_contrast : float
        Predicted Michelson contrast of their S0.
    candidates : int
        Camera positions that met every condition.
    """

    heliostat: int
    camera_m: NDArray[np.float64]
    look_at_m: NDArray[np.float64]
    aop_difference_deg: float
    mirror_dolp: float
    ground_dolp: float
    s0_contrast: float
    candidates: int

    def camera_pose(self, roll_deg: float = 0.0) -> CameraPose:
        """The camera pose (looking at :attr:`look_at_m`)."""
        return CameraPose.look_at(self.camera_m, self.look_at_m, roll_deg)


def ground_vs_ground_view(
    field_pose,
    heliostat: int,
    environment: Environment,
    *,
    heights_m: tuple[float, float] = (15.0, 30.0),
    radius_m: float = 40.0,
    step_m: float = 1.0,
    edge_stretch: tuple[float, float] = (0.15, 0.45),
    max_pitch_deg: float = -40.0,
    max_s0_contrast: float = 0.1,
    min_aop_difference_deg: float = GROUND_AOP_DIFFERENCE_MIN_DEG,
    scene: Scene | None = None,
) -> GroundVsGroundView | None:
    """The camera position looking down at the heliostat's lower edge where the AoP tells mirror from ground.

    Three points of the stretch ``edge_stretch`` of the lower edge (0 = left
    end, 1 = right end seen from the front) are evaluated from every position
    of a ``step_m`` grid within ``radius_m`` (horizontally) of the stretch's
    middle, ``heights_m`` up, in front of the mirror and looking down at
    least as steeply as ``max_pitch_deg``. A position is kept where, at every
    point, the real ground just past the edge is in view and sunlit, the
    mirror 0.3 and 0.7 m inside the edge is in view and shows sunlit ground
    that nothing hides, the mean axial AoP difference
    (:func:`pihim.scenarios.ground_vs_ground`) exceeds
    ``min_aop_difference_deg`` and the predicted S0 Michelson contrast is at
    most ``max_s0_contrast``; of those, the one whose weaker DoLP (mirror or
    ground) is largest wins, so that both AoPs are as measurable as possible.

    Returns
    -------
    GroundVsGroundView or None
        None when no position meets the conditions.

    References
    ----------
    Tian et al., PIHIM, section 4.2 and Table 1 (AoP difference > 50 deg).
    """
    scene = field_scene(field_pose) if scene is None else scene
    s = np.asarray(environment.sun_dir, float)
    o = field_pose.mirror_outline()[heliostat]
    up = _unit(o[0] - o[3])
    n = field_pose.normals[heliostat]
    f0, f1 = edge_stretch
    edge = o[3] + np.linspace(f0, f1, 3)[:, None] * (o[2] - o[3])
    aim = o[3] + 0.5 * (f0 + f1) * (o[2] - o[3])
    cams = _grid(aim, radius_m, heights_m, step_m)
    v = aim - cams
    pitch = np.degrees(np.arctan2(v[:, 2], np.linalg.norm(v[:, :2], axis=1)))
    cams = cams[((cams - aim) @ n > 0.5) & (pitch <= max_pitch_deg)]
    if not len(cams):
        return None
    env = environment
    ok = np.ones(len(cams), bool)
    results = []
    for e in edge:
        g = _ground_hit(cams, _unit(e - 0.05 * up - cams), scene.ground)
        ok &= _clear(scene, cams, g) & _sunlit(scene, g, s)
        r = ground_vs_ground(cams, e + 0.3 * up, n, s, env.sky, env.mirror, env.ground, ground_point=g)
        ok &= r.usable
        for h in (0.3, 0.7):
            p = e + h * up + 0.01 * n
            src = r.mirror.source_dir if h == 0.3 else ground_vs_ground(
                cams, e + h * up, n, s, env.sky, env.mirror, env.ground, ground_point=g).mirror.source_dir
            ok &= (src[:, 2] < 0) & _clear(scene, cams, np.broadcast_to(p, cams.shape), stop=0.98)
            g_refl = _ground_hit(np.broadcast_to(p, cams.shape), src, scene.ground)
            ok &= _clear(scene, np.broadcast_to(p, cams.shape), g_refl) & _sunlit(scene, g_refl, s)
        results.append(r)
    axial = np.mean([r.aop_difference_deg for r in results], axis=0)
    s0_m = np.mean([r.mirror.stokes[:, 0] for r in results], axis=0)
    s0_g = np.mean([r.ground_stokes[:, 0] for r in results], axis=0)
    dolp_m = np.mean([r.mirror.dolp for r in results], axis=0)
    dolp_g = np.mean([r.ground_dolp for r in results], axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        contrast = np.abs(s0_m - s0_g) / (s0_m + s0_g)
    ok &= (contrast <= max_s0_contrast) & (axial > min_aop_difference_deg)
    if not ok.any():
        return None
    cand = np.flatnonzero(ok)
    j = cand[np.argmax(np.minimum(dolp_m, dolp_g)[cand])]
    return GroundVsGroundView(int(heliostat), cams[j].copy(), aim.copy(), float(axial[j]), float(dolp_m[j]),
                              float(dolp_g[j]), float(contrast[j]), int(ok.sum()))
