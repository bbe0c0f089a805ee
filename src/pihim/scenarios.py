"""The paper's two contrast scenarios, predicted from physics.

*Sky-vs-sky* (paper section 4.1): two overlapping heliostats both reflect blue
sky; their edge is visible in DoLP when the reflected DoLPs differ by more
than 0.2. *Ground-vs-ground* (section 4.2): a mirror reflecting the ground
lies next to the real ground; the edge is visible in AoP when the two AoPs
differ by more than 50 deg. The paper also processes only images with
DoLP > 0.2 on the heliostat reflection (section 5).

Geometry: the camera at ``camera`` (ENU, m) looks at a mirror point ``P``
with unit normal ``n``. The light reaching the camera travels along
``d_cam = normalize(camera - P)``; before the mirror it travelled along
``d_in = reflect(d_cam, n)``, so the mirror shows the source seen in the
direction ``-d_in`` from ``P``: sky if it points above the horizon, ground
otherwise. The source's Stokes vector is reflected in the mirror's own s/p
basis and then expressed in the camera image frame: reference axis = image
right for a camera with zero roll looking from ``camera`` toward ``gaze``
(OpenCV camera axes), AoP counter-clockwise from image right as displayed
(see docs/conventions.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError
from pihim.polarimetry.frames import change_reference, dot, normalize
from pihim.polarimetry.reflection import reflect_direction, reflect_stokes
from pihim.polarimetry.stokes import aop_deg, aop_difference_deg, aop_raw_difference_deg, dolp

#: Paper thresholds: DoLP difference for sky-vs-sky, AoP difference for
#: ground-vs-ground, minimum DoLP on the heliostat reflection.
SKY_DOLP_DIFFERENCE_MIN = 0.2
GROUND_AOP_DIFFERENCE_MIN_DEG = 50.0
REFLECTION_DOLP_MIN = 0.2


class Sky(Protocol):
    """Anything that gives sky Stokes vectors (see :class:`pihim.sky.model.SkyModel`)."""

    def stokes(
        self, view_dirs: NDArray, sun_dir: NDArray, e: NDArray | None = None
    ) -> tuple[NDArray, NDArray]: ...


class Mirror(Protocol):
    """Anything with a reflection Mueller matrix in the s-as-x basis (see :mod:`pihim.surfaces.mirror`)."""

    def mueller(self, cos_i: NDArray) -> NDArray: ...


class Ground(Protocol):
    """Anything that gives the Stokes vector leaving the ground (see :class:`pihim.surfaces.ground.GroundModel`)."""

    def stokes(
        self, view_dirs: NDArray, sun_dir: NDArray, sky: Sky | None = None, e: NDArray | None = None
    ) -> tuple[NDArray, NDArray]: ...


def image_right(camera: ArrayLike, gaze: ArrayLike) -> NDArray[np.float64]:
    """Image-right axis of a zero-roll camera at ``camera`` looking at ``gaze`` (ENU)."""
    g = normalize(np.asarray(gaze, float) - np.asarray(camera, float))
    right = np.cross(g, [0.0, 0.0, 1.0])
    if np.any(np.linalg.norm(right, axis=-1) < 1e-9):
        raise PihimInputError("camera looks straight up or down: image right is undefined without a heading")
    return normalize(right)


@dataclass(frozen=True)
class Reflection:
    """Light reaching the camera from one mirror point, in the camera image frame.

    Attributes
    ----------
    stokes : (..., 4)
        Stokes vector, reference axis = image right.
    dolp, aop_deg : (...)
        DoLP and image AoP (deg, [0, 180)).
    source_dir : (..., 3)
        Unit vector from the mirror toward what it shows (sky if z > 0).
    shows_sky : (...) bool
    facing : (...) bool
        Camera and source both in front of the mirror (a valid reflection).
    """

    stokes: NDArray[np.float64]
    dolp: NDArray[np.float64]
    aop_deg: NDArray[np.float64]
    source_dir: NDArray[np.float64]
    shows_sky: NDArray[np.bool_]
    facing: NDArray[np.bool_]


def to_image_frame(s: NDArray, d: NDArray, e: NDArray, right: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Stokes (d, e) re-expressed with reference ``right`` (image right); also DoLP and image AoP (deg).

    ``right`` is projected onto the plane perpendicular to ``d`` first.
    """
    r = right - dot(right, d)[..., None] * d
    s_img = change_reference(s, d, e, normalize(r))
    return s_img, dolp(s_img[..., 0], s_img[..., 1], s_img[..., 2]), aop_deg(s_img[..., 1], s_img[..., 2])


def mirror_reflection(
    camera: ArrayLike,
    point: ArrayLike,
    normal: ArrayLike,
    sun_dir: ArrayLike,
    sky: Sky,
    mirror: Mirror,
    *,
    ground: Ground | None = None,
    ground_height_m: float = 0.0,
    gaze: ArrayLike | None = None,
) -> Reflection:
    """Polarization of the light a camera receives from a mirror point.

    The mirror shows sky or ground; ground is modelled only when ``ground``
    is given (else it contributes zero). Vectorised over points/normals.
    """
    camera = np.asarray(camera, float)
    point = np.asarray(point, float)
    n = normalize(normal)
    d_cam = normalize(camera - point)
    d_in = reflect_direction(d_cam, n)
    source = -d_in
    # the normal points out of the mirror face: the camera must be on that side
    # (then the source is too, by the law of reflection)
    facing = dot(n, d_cam) > 1e-9
    shows_sky = source[..., 2] > 0
    s_src, e_src = sky.stokes(source, np.asarray(sun_dir, float))
    if ground is not None:
        # ground point hit by the reversed ray; ground light travels from there toward the mirror
        s_g, e_g = ground.stokes(d_in, np.asarray(sun_dir, float), sky, e_src)
        s_src = np.where(shows_sky[..., None], s_src, s_g)
    s_src = np.where(facing[..., None], s_src, 0.0)
    s_out, d_out, e_out = reflect_stokes(s_src, d_in, e_src, n, mirror.mueller)
    right = image_right(camera, point if gaze is None else gaze)
    s_img, p, a = to_image_frame(s_out, d_out, e_out, right)
    return Reflection(s_img, p, a, source, shows_sky, facing)


@dataclass(frozen=True)
class SkyVsSky:
    """Sky-vs-sky prediction for a front/back heliostat pair (paper section 4.1)."""

    front: Reflection
    back: Reflection
    dolp_difference: NDArray[np.float64]
    usable: NDArray[np.bool_]
    reflection_dolp_ok: NDArray[np.bool_]


def sky_vs_sky(
    camera: ArrayLike,
    front_point: ArrayLike,
    front_normal: ArrayLike,
    back_point: ArrayLike,
    back_normal: ArrayLike,
    sun_dir: ArrayLike,
    sky: Sky,
    mirror: Mirror,
) -> SkyVsSky:
    """DoLP of each reflection and their difference; usable when > 0.2 and both show sky."""
    gaze = 0.5 * (np.asarray(front_point, float) + np.asarray(back_point, float))
    f = mirror_reflection(camera, front_point, front_normal, sun_dir, sky, mirror, gaze=gaze)
    b = mirror_reflection(camera, back_point, back_normal, sun_dir, sky, mirror, gaze=gaze)
    diff = np.abs(f.dolp - b.dolp)
    valid = f.shows_sky & b.shows_sky & f.facing & b.facing
    usable = valid & (diff > SKY_DOLP_DIFFERENCE_MIN)
    refl_ok = valid & (np.maximum(f.dolp, b.dolp) > REFLECTION_DOLP_MIN)
    return SkyVsSky(f, b, np.where(valid, diff, np.nan), usable, refl_ok)


@dataclass(frozen=True)
class GroundVsGround:
    """Ground-vs-ground prediction for one mirror next to real ground (paper section 4.2).

    ``aop_difference_deg`` is axial, in [0, 90]; ``aop_raw_difference_deg`` is
    the paper's Table 1 form ``|AoP_mirror - AoP_ground|`` in [0, 180).
    """

    mirror: Reflection
    ground_stokes: NDArray[np.float64]
    ground_aop_deg: NDArray[np.float64]
    ground_dolp: NDArray[np.float64]
    aop_difference_deg: NDArray[np.float64]
    aop_raw_difference_deg: NDArray[np.float64]
    usable: NDArray[np.bool_]


def ground_vs_ground(
    camera: ArrayLike,
    point: ArrayLike,
    normal: ArrayLike,
    sun_dir: ArrayLike,
    sky: Sky,
    mirror: Mirror,
    ground: Ground,
    *,
    ground_point: ArrayLike | None = None,
) -> GroundVsGround:
    """AoP of the mirror-reflected ground and of the adjacent real ground, and their differences.

    ``ground_point`` is the real ground seen next to the mirror edge; by
    default the point where the camera's line of sight through ``point``
    meets the ground plane z = 0.
    """
    camera = np.asarray(camera, float)
    point = np.asarray(point, float)
    refl = mirror_reflection(camera, point, normal, sun_dir, sky, mirror, ground=ground)
    if ground_point is None:
        v = normalize(point - camera)
        if np.any(v[..., 2] >= 0):
            raise PihimInputError("the camera must look down at the mirror for a ground-vs-ground view")
        t = -point[..., 2] / v[..., 2]
        ground_point = point + t[..., None] * v
    to_cam = normalize(camera - np.asarray(ground_point, float))
    s_g, e_g = ground.stokes(to_cam, np.asarray(sun_dir, float), sky)
    s_img, p_g, a_g = to_image_frame(s_g, to_cam, e_g, image_right(camera, point))
    axial = aop_difference_deg(refl.aop_deg, a_g)
    raw = aop_raw_difference_deg(refl.aop_deg, a_g)
    usable = (~refl.shows_sky) & refl.facing & (axial > GROUND_AOP_DIFFERENCE_MIN_DEG)
    return GroundVsGround(refl, s_img, a_g, p_g, axial, raw, usable)
