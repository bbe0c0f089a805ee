"""Render a full-resolution polarimetric frame with labels: the renderer's top level.

:func:`render_frame` casts one ray through the centre of every pixel
(OpenCV convention: pixel ``(row i, column j)`` is centred on ``(u, v) =
(j, i)`` and covers ``[j - 0.5, j + 0.5) x [i - 0.5, i + 0.5)``), traces
and shades it (:mod:`pihim.render.paths`, :mod:`pihim.render.shading`),
then re-renders every pixel whose path differs from a 4-neighbour's (an
object edge, a facet gap, a shadow border, the sun's limb) with ``n x n``
stratified sub-pixel rays (default 3 x 3, the centre ray reused) and replaces its value by their mean. Edges are
therefore area-weighted to ``1 / n^2`` of a pixel, while the smooth
interiors cost one ray per pixel.

The labels are those of the pixel-centre ray: what it sees directly (kind,
heliostat index, facet number) and, for a mirror pixel, what its reflection
ends on (sky, sun, ground, tower, which heliostat's structure or facet back)
and after how many bounces.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose
from pihim.errors import PihimInputError
from pihim.render.kernel import render_rays
from pihim.render.paths import KIND_NAMES
from pihim.render.scene import Scene
from pihim.render.shading import Environment, GroundTable, MirrorTable
from pihim.sky.table import SkyTable

__all__ = ["LABEL_CHANNELS", "RenderSettings", "RenderedFrame", "camera_arrays", "environment_tables", "render_frame"]

#: Channels of :attr:`RenderedFrame.labels`.
LABEL_CHANNELS = ("direct_kind", "direct_heliostat", "direct_facet", "seen_kind", "seen_heliostat", "seen_facet",
                  "bounces")


@dataclass(frozen=True)
class RenderSettings:
    """Sampling and tracing parameters.

    Attributes
    ----------
    supersample : int
        ``n``: edge pixels get ``n x n`` stratified rays, ``1 / n^2`` of the
        pixel area each (1: no antialiasing). For odd ``n`` the grid contains
        the pixel centre, whose ray is reused. Default 3 (9 rays).
    max_bounces : int
        Mirror reflections followed per path.
    chunk_rays : int
        Rays traced and shaded per batch (bounds the memory).
    sky_table_size : int
        Nodes per axis of the sky table (:class:`pihim.sky.table.SkyTable`;
        513: about 0.3 deg at the zenith, 0.45 deg at the horizon).
    """

    supersample: int = 3
    max_bounces: int = 2
    chunk_rays: int = 1 << 20
    sky_table_size: int = 513

    def __post_init__(self) -> None:
        for name, lo, hi in (("supersample", 1, 16), ("max_bounces", 0, 8), ("chunk_rays", 1024, 1 << 24),
                             ("sky_table_size", 17, 4097)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise PihimInputError(f"{name} must be an integer in [{lo}, {hi}], got {v!r}")


@dataclass(frozen=True, eq=False)
class RenderedFrame:
    """A rendered Stokes image in the image frame, its labels and statistics.

    Attributes
    ----------
    s0, s1, s2 : ndarray of float32, shape (H, W)
        Stokes radiance, W m^-2 sr^-1, reference axis image right (AoP
        counter-clockwise as displayed).
    labels : ndarray of int32, shape (H, W, 7)
        See :data:`LABEL_CHANNELS`; kinds are :data:`pihim.render.paths.KIND_NAMES`
        codes, heliostat -1 / facet 0 for none; ``seen_*`` are -1 except on
        mirror pixels.
    supersampled : ndarray of bool, shape (H, W)
        Pixels rendered with ``n x n`` rays.
    stats : dict
        Rays traced, pixels supersampled, seconds.
    """

    s0: NDArray[np.float32]
    s1: NDArray[np.float32]
    s2: NDArray[np.float32]
    labels: NDArray[np.int32]
    supersampled: NDArray[np.bool_]
    stats: dict[str, Any] = field(default_factory=dict)


def environment_tables(env: Environment, scene: Scene, sky_table_size: int = 513) -> tuple:
    """The light and material tables the compiled kernel reads (see :mod:`pihim.render.kernel`)."""
    sky = SkyTable(env.sky, env.sun_dir, int(sky_table_size))
    if env.ground is not None and scene.ground is not None:
        gt = GroundTable(env)
        g_sky, g_sun, g_step, g_astep = gt.sky_part, gt.sun_part, gt.step_deg, gt.azimuth_step_deg
    else:  # no ground model: the ground is black
        g_sky = g_sun = np.zeros((2, 2, 4))
        g_step = g_astep = 360.0
    mt = MirrorTable(env.mirror)
    finish = np.array([[f.albedo, np.radians(f.sigma_deg), f.refractive_index,
                        1.0 / (2.0 * np.pi * float(f._facets.facet_density(0.0)))]  # type: ignore[attr-defined]
                       for f in (env.structure, env.facet_back, env.tower)])
    return (env.sun_dir, float(np.cos(np.radians(env.sun_half_angle_deg))), env.sun_radiance,
            float(env.sun_irradiance_w_m2), env.sky_irradiance_w_m2,
            sky.table, float(sky.radius), float(sky.step),
            np.ascontiguousarray(g_sky), np.ascontiguousarray(g_sun), float(g_step), float(g_astep),
            len(mt.cos), mt.a, mt.b, mt.c, mt.d, finish)


def camera_arrays(camera: CameraModel, pose: CameraPose) -> tuple:
    """Camera position, world -> camera rotation, intrinsics and distortion for the kernel."""
    return (np.asarray(pose.position_m, float), np.ascontiguousarray(pose.rotation, dtype=float),
            float(camera.fx_px), float(camera.fy_px), float(camera.cx_px), float(camera.cy_px),
            np.asarray(camera.distortion_coefficients(), float))


def render_frame(
    scene: Scene,
    camera: CameraModel,
    pose: CameraPose,
    env: Environment,
    settings: RenderSettings = RenderSettings(),
    *,
    progress: Any = None,
) -> RenderedFrame:
    """Render what ``camera`` at ``pose`` sees of ``scene`` under ``env``.

    Parameters
    ----------
    scene : Scene
        Geometry (:func:`pihim.render.scene.field_scene`).
    camera : CameraModel
        Intrinsics and distortion.
    pose : CameraPose
        Position and orientation.
    env : Environment
        Sun, sky, ground, mirror and finishes.
    settings : RenderSettings
    progress : callable, optional
        ``progress(done_rays, total_rays)`` called after every batch.

    Returns
    -------
    RenderedFrame
    """
    t_start = time.perf_counter()
    h, w = camera.height_px, camera.width_px
    if scene.ground is not None:
        gz = float(scene.ground_height(pose.position_m[0], pose.position_m[1]))
        if pose.position_m[2] <= gz:
            raise PihimInputError(f"the camera is below the ground ({pose.position_m[2]:.2f} m <= {gz:.2f} m)")
    tables = environment_tables(env, scene, settings.sky_table_size)
    cam = camera_arrays(camera, pose)
    chunk = int(settings.chunk_rays)
    n_sub = int(settings.supersample)
    n_ch = len(LABEL_CHANNELS)

    def run(u: NDArray, v: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        s = np.empty((len(u), 3))
        k = np.empty(len(u), np.int64)
        lab = np.empty((len(u), n_ch), np.int32)
        render_rays(scene, tables, cam, np.ascontiguousarray(u), np.ascontiguousarray(v), settings.max_bounces,
                    s, k, lab)
        return s, k, lab

    total = h * w
    stokes = np.empty((total, 3))
    keys = np.empty(total, np.int64)
    labels = np.empty((total, n_ch), np.int32)
    jj = np.tile(np.arange(w, dtype=float), h)
    ii = np.repeat(np.arange(h, dtype=float), w)
    rays = 0
    for a in range(0, total, chunk):
        b = min(a + chunk, total)
        stokes[a:b], keys[a:b], labels[a:b] = run(jj[a:b], ii[a:b])
        rays += b - a
        if progress is not None:
            progress(b, total)
    t_primary = time.perf_counter() - t_start
    key_img = keys.reshape(h, w)
    edge = np.zeros((h, w), bool)
    dh = key_img[:, 1:] != key_img[:, :-1]
    edge[:, 1:] |= dh
    edge[:, :-1] |= dh
    dv = key_img[1:, :] != key_img[:-1, :]
    edge[1:, :] |= dv
    edge[:-1, :] |= dv
    n_edge = int(edge.sum())
    if n_sub > 1 and n_edge:
        offs = (np.arange(n_sub) + 0.5) / n_sub - 0.5
        ou, ov = np.meshgrid(offs, offs)
        ou, ov = ou.ravel(), ov.ravel()
        # an odd grid contains the pixel centre, already traced: reuse it
        reuse = n_sub % 2 == 1
        if reuse:
            keep = (ou != 0.0) | (ov != 0.0)
            ou, ov = ou[keep], ov[keep]
        k_new = len(ou)
        idx = np.flatnonzero(edge.ravel())
        per = max(1, chunk // k_new)
        for a in range(0, len(idx), per):
            sel = idx[a:a + per]
            u = (jj[sel][:, None] + ou[None, :]).ravel()
            v = (ii[sel][:, None] + ov[None, :]).ravel()
            s, _, _ = run(u, v)
            total_s = s.reshape(len(sel), k_new, 3).sum(axis=1)
            if reuse:
                total_s += stokes[sel]
            stokes[sel] = total_s / (n_sub * n_sub)
            rays += len(u)
    elapsed = time.perf_counter() - t_start
    img = stokes.reshape(h, w, 3).astype(np.float32)
    counts = np.bincount(labels[:, 0], minlength=len(KIND_NAMES))
    stats = {
        "width_px": w,
        "height_px": h,
        "rays": int(rays),
        "supersampled_pixels": n_edge,
        "supersample": n_sub,
        "seconds": elapsed,
        "seconds_primary": t_primary,
        "rays_per_second": rays / elapsed if elapsed > 0 else float("nan"),
        "direct_kind_pixels": {KIND_NAMES[k]: int(c) for k, c in enumerate(counts) if k in KIND_NAMES},
    }
    return RenderedFrame(img[..., 0], img[..., 1], img[..., 2], labels.reshape(h, w, -1), edge, stats)
