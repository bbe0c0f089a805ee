"""Stokes radiance of traced paths: sky, sun, ground, rough surfaces and mirror bounces.

:class:`Environment` gathers the light and the materials: the sun (direction
and direct normal irradiance), pihim's sky model (:class:`pihim.sky.SkyModel`,
scaled to a diffuse horizontal irradiance), the Torrance-Sparrow ground
(:class:`pihim.surfaces.ground.GroundModel`), the heliostat mirror model
(:mod:`pihim.surfaces.mirror`) and the finishes of the back structure, facet
backs and tower (:class:`SurfaceFinish`).

:func:`shade_paths` evaluates, for every path recorded by
:func:`pihim.render.paths.trace_paths`:

1. the Stokes vector leaving the terminal toward the camera, in a stated
   frame ``(d, e)``:

   * sky: the sky model in the direction of the ray;
   * sun disc: unpolarized, radiance ``E_sun / (pi sin^2 r)``;
   * ground: the ground model for the direction toward the previous vertex,
     its sky part always and its sun part only where the shadow ray reached
     the sun (the heliostats' shadows). The ground model depends on
     direction only, so it is tabulated once per frame on a 1-deg grid of
     view directions and interpolated (:class:`GroundTable`);
   * structure, facet backs, tower (:class:`SurfaceFinish`): a depolarized
     Lambertian part lit by the sun (where visible) and the sky (isotropic,
     with the view factor ``(1 + n_z) / 2``), plus the Torrance-Sparrow
     specular reflection of the sun off a rough dielectric paint, which is
     what makes these surfaces weakly polarizing;

2. every mirror bounce, last first: the Stokes vector is rotated into the
   bounce's s/p basis and multiplied by the mirror model's Mueller matrix
   (tabulated in the incidence cosine, :class:`MirrorTable`);

3. a final rotation into the image frame: ``d`` = the light travelling into
   the camera, ``e`` = the camera's x axis (image right) made perpendicular
   to ``d`` (docs/conventions.md, "Camera and image frames").

Units: radiance in W m^-2 sr^-1 for irradiances in W m^-2.

References
----------
.. [1] R. A. Chipman, W. S. T. Lam, G. Young, *Polarized Light and Optical
   Systems* (2018), ch. 9-10 (polarization ray tracing in local s/p bases).
.. [2] K. E. Torrance, E. M. Sparrow, J. Opt. Soc. Am. 57(9), 1105 (1967),
   doi:10.1364/JOSA.57.001105 (rough-surface specular reflection).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError
from pihim.polarimetry.frames import change_reference, normalize, perpendicular_reference
from pihim.polarimetry.reflection import incidence_basis, reflect_stokes
from pihim.render.paths import FACET_BACK, GROUND, MIRROR, SKY, STRUCTURE_HIT, SUN, TOWER_HIT, Paths
from pihim.sky.model import SkyModel, horizontal_irradiance, with_horizontal_irradiance
from pihim.surfaces.fresnel import fresnel_reflection_mueller
from pihim.surfaces.ground import GroundModel
from pihim.surfaces.mirror import MirrorModel, SecondSurfaceMirror

__all__ = [
    "Environment",
    "GroundTable",
    "MirrorTable",
    "SurfaceFinish",
    "shade_paths",
]

_EAST = np.array([1.0, 0.0, 0.0])
_NORTH = np.array([0.0, 1.0, 0.0])
#: Mean angular radius of the sun disc, deg.
SUN_HALF_ANGLE_DEG = 0.2666


@dataclass(frozen=True)
class SurfaceFinish:
    """A rough, dark, weakly polarizing surface (paint, galvanized steel, concrete).

    Attributes
    ----------
    albedo : float
        Albedo of the depolarized Lambertian part, [0, 1].
    sigma_deg : float
        Facet-slope width of the Torrance-Sparrow specular part, deg.
    refractive_index : float
        Index of the dielectric coating (Fresnel reflection of the specular
        part; this is what polarizes).
    """

    albedo: float = 0.1
    sigma_deg: float = 20.0
    refractive_index: float = 1.5

    def __post_init__(self) -> None:
        if not (isinstance(self.albedo, (int, float)) and 0.0 <= self.albedo <= 1.0):
            raise PihimInputError(f"finish albedo must be in [0, 1], got {self.albedo!r}")
        # the microfacet model validates sigma and the index
        object.__setattr__(self, "_facets", GroundModel(sigma_deg=self.sigma_deg,
                                                       refractive_index=self.refractive_index))

    def describe(self) -> dict[str, float]:
        return {"albedo": float(self.albedo), "sigma_deg": float(self.sigma_deg),
                "refractive_index": float(self.refractive_index)}


@dataclass(frozen=True, eq=False)
class Environment:
    """Light and materials of a rendered scene (see the module notes).

    Build it with :meth:`clear_sky` unless every part is chosen by hand.

    Attributes
    ----------
    sun_dir : ndarray, shape (3,)
        Unit vector toward the sun (ENU).
    sky : SkyModel
        Skylight, in radiance units consistent with ``sun_irradiance_w_m2``.
    ground : GroundModel or None
        Ground reflectance (its ``sun_irradiance`` must equal the sun's).
    mirror : MirrorModel
        Heliostat mirror.
    sun_irradiance_w_m2 : float
        Direct normal irradiance of the sun.
    structure, facet_back, tower : SurfaceFinish
        Finishes of the back structure, the facet backs and the tower.
    sun_half_angle_deg : float
        Angular radius of the sun disc.
    """

    sun_dir: NDArray[np.float64]
    sky: SkyModel
    ground: GroundModel | None
    mirror: MirrorModel
    sun_irradiance_w_m2: float = 1000.0
    structure: SurfaceFinish = SurfaceFinish(albedo=0.20, sigma_deg=20.0)
    facet_back: SurfaceFinish = SurfaceFinish(albedo=0.08, sigma_deg=25.0)
    tower: SurfaceFinish = SurfaceFinish(albedo=0.40, sigma_deg=30.0)
    sun_half_angle_deg: float = SUN_HALF_ANGLE_DEG
    _sky_irradiance: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        s = np.asarray(self.sun_dir, float).reshape(3)
        if not np.all(np.isfinite(s)) or np.linalg.norm(s) == 0:
            raise PihimInputError("sun direction must be a finite non-zero vector")
        s = s / np.linalg.norm(s)
        if s[2] <= 0:
            raise PihimInputError(f"the sun is below the horizon (elevation {math.degrees(math.asin(s[2])):.2f} deg)")
        s.setflags(write=False)
        object.__setattr__(self, "sun_dir", s)
        if not (math.isfinite(self.sun_irradiance_w_m2) and self.sun_irradiance_w_m2 >= 0):
            raise PihimInputError("sun irradiance must be a finite number >= 0 W m^-2")
        if self.ground is not None and not math.isclose(self.ground.sun_irradiance, self.sun_irradiance_w_m2):
            raise PihimInputError("the ground model's sun irradiance must equal the environment's")
        if not 0.0 < self.sun_half_angle_deg < 5.0:
            raise PihimInputError("sun half-angle must be in (0, 5) deg")
        object.__setattr__(self, "_sky_irradiance", horizontal_irradiance(self.sky, s))

    @classmethod
    def clear_sky(
        cls,
        sun_dir: ArrayLike,
        *,
        sky: SkyModel | None = None,
        diffuse_irradiance_w_m2: float = 100.0,
        sun_irradiance_w_m2: float = 1000.0,
        ground: GroundModel | None = None,
        mirror: MirrorModel | None = None,
        **finishes: SurfaceFinish,
    ) -> Environment:
        """A clear day: Rayleigh sky scaled to ``diffuse_irradiance_w_m2``, sun, rough ground, silvered glass.

        Defaults: 1000 W m^-2 direct normal and 100 W m^-2 diffuse
        horizontal irradiance; ground :class:`GroundModel` with sigma 15 deg,
        n = 1.45 (paper) and a diffuse albedo of 0.2; mirror
        :class:`SecondSurfaceMirror`.
        """
        s = normalize(np.asarray(sun_dir, float))
        base = sky or SkyModel()
        if s[2] <= 0:
            raise PihimInputError("the sun is below the horizon")
        sky_scaled = with_horizontal_irradiance(base, s, diffuse_irradiance_w_m2)
        g = ground or GroundModel(diffuse_albedo=0.2, sun_irradiance=sun_irradiance_w_m2)
        return cls(s, sky_scaled, g, mirror or SecondSurfaceMirror(), sun_irradiance_w_m2, **finishes)

    @property
    def sky_irradiance_w_m2(self) -> float:
        """Diffuse horizontal irradiance of the sky model."""
        return float(self._sky_irradiance)

    @property
    def sun_radiance(self) -> float:
        """Radiance of the sun disc, W m^-2 sr^-1 (uniform disc of the given half-angle)."""
        r = math.radians(self.sun_half_angle_deg)
        return self.sun_irradiance_w_m2 / (2.0 * math.pi * (1.0 - math.cos(r)))

    def describe(self) -> dict[str, object]:
        """JSON-friendly record of the light and materials."""
        g = self.ground
        return {
            "sun_dir_enu": [float(x) for x in self.sun_dir],
            "sun_irradiance_w_m2": float(self.sun_irradiance_w_m2),
            "sky": self.sky.describe(),
            "sky_irradiance_w_m2": self.sky_irradiance_w_m2,
            "ground": None if g is None else {"sigma_deg": g.sigma_deg, "refractive_index": g.refractive_index,
                                               "diffuse_albedo": g.diffuse_albedo},
            "mirror": type(self.mirror).__name__,
            "structure": self.structure.describe(),
            "facet_back": self.facet_back.describe(),
            "tower": self.tower.describe(),
        }


def _ground_reference(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Reference axes of ground Stokes: East made perpendicular to ``v`` (North where ``v`` is along East)."""
    return perpendicular_reference(v, _EAST, _NORTH)


class GroundTable:
    """The ground model tabulated over view directions (upper hemisphere; 1 deg in zenith, 2 deg in azimuth).

    Two tables: the part lit by the sun (specular sun term and the sun's share
    of the Lambertian part) and the sky part. Stokes are stored in the frame
    ``(v, e)`` with ``e`` = East made perpendicular to the view direction
    ``v`` (singular only for horizontal views along East/West, where the
    ground sends no light toward the camera anyway).
    """

    def __init__(self, env: Environment, step_deg: float = 1.0, azimuth_step_deg: float = 2.0) -> None:
        if env.ground is None:
            raise PihimInputError("the environment has no ground model")
        self.step_deg = float(step_deg)
        self.azimuth_step_deg = float(azimuth_step_deg)
        self.zen = np.arange(0.0, 90.0 + 0.5 * step_deg, step_deg)
        self.az = np.arange(0.0, 360.0 + 0.5 * azimuth_step_deg, azimuth_step_deg)
        zz, aa = np.meshgrid(np.radians(self.zen), np.radians(self.az), indexing="ij")
        v = np.stack([np.sin(zz) * np.sin(aa), np.sin(zz) * np.cos(aa), np.cos(zz)], axis=-1)
        v[..., 2] = np.maximum(v[..., 2], 1e-9)
        v = normalize(v)
        e = _ground_reference(v)
        sun_part, _ = env.ground.stokes(v, env.sun_dir, None, e)
        everything, _ = env.ground.stokes(v, env.sun_dir, env.sky, e)
        self.sun_part = sun_part
        self.sky_part = everything - sun_part

    def lookup(self, v: NDArray[np.float64], sun_visible: NDArray[np.bool_]) -> tuple[NDArray, NDArray]:
        """Stokes (n, 4) toward unit view directions ``v`` (n, 3) and their reference axes."""
        zen = np.degrees(np.arccos(np.clip(v[:, 2], 0.0, 1.0)))
        az = np.mod(np.degrees(np.arctan2(v[:, 0], v[:, 1])), 360.0)
        fi = np.clip(zen / self.step_deg, 0.0, len(self.zen) - 1.000001)
        fj = np.clip(az / self.azimuth_step_deg, 0.0, len(self.az) - 1.000001)
        i0 = fi.astype(np.int64)
        j0 = fj.astype(np.int64)
        wi = (fi - i0)[:, None]
        wj = (fj - j0)[:, None]

        def bilinear(t: NDArray) -> NDArray:
            return ((1 - wi) * ((1 - wj) * t[i0, j0] + wj * t[i0, j0 + 1])
                    + wi * ((1 - wj) * t[i0 + 1, j0] + wj * t[i0 + 1, j0 + 1]))

        s = bilinear(self.sky_part)
        if np.any(sun_visible):
            s[sun_visible] += bilinear(self.sun_part)[sun_visible]
        s[v[:, 2] <= 0.0] = 0.0
        return s, _ground_reference(v)


class MirrorTable:
    """A mirror model's Mueller matrix tabulated in the incidence cosine.

    The mirror models of :mod:`pihim.surfaces.mirror` have the s/p block form
    ``[[A, B, 0, 0], [B, A, 0, 0], [0, 0, C, D], [0, 0, -D, C]]``; the four
    functions are sampled on ``n`` cosines in [0, 1] and interpolated
    linearly (error below 1e-7 with the default 4097 nodes).
    """

    def __init__(self, mirror: MirrorModel, n: int = 4097) -> None:
        self.cos = np.linspace(0.0, 1.0, n)
        m = mirror.mueller(self.cos)
        block = np.abs(m[:, 0, 2:]).max() + np.abs(m[:, 2:, 0:2]).max() + np.abs(m[:, 0:2, 2:]).max()
        if block > 1e-12 or np.abs(m[:, 0, 0] - m[:, 1, 1]).max() > 1e-12:
            raise PihimInputError("mirror Mueller matrices must have the s/p block form of an isotropic interface")
        self.a, self.b, self.c, self.d = m[:, 0, 0], m[:, 0, 1], m[:, 2, 2], m[:, 2, 3]

    def mueller(self, cos_i: ArrayLike) -> NDArray[np.float64]:
        """Interpolated Mueller matrices ``(..., 4, 4)``."""
        c = np.asarray(cos_i, float)
        a, b, cc, d = (np.interp(c, self.cos, t) for t in (self.a, self.b, self.c, self.d))
        m = np.zeros(c.shape + (4, 4))
        m[..., 0, 0] = m[..., 1, 1] = a
        m[..., 0, 1] = m[..., 1, 0] = b
        m[..., 2, 2] = m[..., 3, 3] = cc
        m[..., 2, 3] = d
        m[..., 3, 2] = -d
        return m

    def reflect(self, s: NDArray, d: NDArray, e: NDArray, normal: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """Reflect Stokes (n, 4) travelling along ``d`` with axes ``e`` off mirrors of ``normal``.

        Same result as :func:`pihim.polarimetry.reflection.reflect_stokes` with
        this table's Mueller matrices, without forming them.
        """
        cos_i = np.abs(np.einsum("ij,ij->i", d, normal))
        s_axis = incidence_basis(d, normal, e)
        s = change_reference(s, d, e, s_axis)
        a, b, c, dd = (np.interp(cos_i, self.cos, t) for t in (self.a, self.b, self.c, self.d))
        out = np.empty_like(s)
        out[:, 0] = a * s[:, 0] + b * s[:, 1]
        out[:, 1] = b * s[:, 0] + a * s[:, 1]
        out[:, 2] = c * s[:, 2] + dd * s[:, 3]
        out[:, 3] = -dd * s[:, 2] + c * s[:, 3]
        d_out = d - 2.0 * np.einsum("ij,ij->i", d, normal)[:, None] * normal
        return out, d_out, s_axis


def finish_stokes(
    finish: SurfaceFinish, env: Environment, v: NDArray, n: NDArray, sun_visible: NDArray[np.bool_]
) -> tuple[NDArray, NDArray]:
    """Stokes leaving a rough surface toward unit view directions ``v`` (n, 3) with unit normals ``n`` (n, 3).

    Lambertian: ``albedo / pi (E_sun max(n.s, 0) [sun visible] + E_sky (1 + n_z) / 2)``, unpolarized.
    Specular sun (Torrance-Sparrow, V-groove shadowing, Fresnel Mueller of
    the coating at the half vector): polarized. Returns Stokes and their
    reference axes (the s axis of the specular reflection).
    """
    s = env.sun_dir
    e_sun = env.sun_irradiance_w_m2
    cos_sn = n @ s
    lit = sun_visible & (cos_sn > 0)
    cos_vn = np.clip(np.einsum("ij,ij->i", v, n), 1e-6, 1.0)
    h = normalize(v + s)
    c = np.clip(h @ s, 0.0, 1.0)  # = v.h
    h_n = np.clip(np.einsum("ij,ij->i", h, n), -1.0, 1.0)
    alpha_deg = np.degrees(np.arccos(h_n))
    facets: GroundModel = finish._facets  # type: ignore[attr-defined]
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.minimum(1.0, np.minimum(2.0 * h_n * cos_vn / c, 2.0 * h_n * np.clip(cos_sn, 0, None) / c))
    g = np.where(c > 0, np.clip(np.nan_to_num(g), 0.0, 1.0), 0.0)
    w = np.where(lit, facets.facet_density(alpha_deg) * g / (4.0 * cos_vn), 0.0)
    s_in = np.zeros((len(v), 4))
    s_in[:, 0] = e_sun
    d_in = np.broadcast_to(-s, v.shape)
    out, _, s_axis = reflect_stokes(s_in, d_in, perpendicular_reference(d_in), h,
                                    lambda ci: fresnel_reflection_mueller(ci, 1.0, finish.refractive_index))
    out *= w[:, None]
    diffuse = finish.albedo / math.pi * (np.where(lit, e_sun * cos_sn, 0.0)
                                         + env.sky_irradiance_w_m2 * 0.5 * (1.0 + n[:, 2]))
    out[:, 0] += diffuse
    return out, s_axis


def shade_paths(
    paths: Paths,
    env: Environment,
    image_right: NDArray[np.float64],
    *,
    ground_table: GroundTable | None = None,
    mirror_table: MirrorTable | None = None,
) -> NDArray[np.float64]:
    """Stokes ``(R, 3)`` = (S0, S1, S2) of traced paths in the image frame.

    Parameters
    ----------
    paths : Paths
        From :func:`pihim.render.paths.trace_paths`.
    env : Environment
    image_right : ndarray, shape (3,) or (R, 3)
        The camera's x axis (image right) in ENU.
    ground_table, mirror_table : optional
        Precomputed tables (built here when omitted).

    Returns
    -------
    ndarray, shape (R, 3)
    """
    r = paths.terminal_kind.shape[0]
    mt = mirror_table or MirrorTable(env.mirror)
    tk = paths.terminal_kind
    td = paths.terminal_dir
    d_light = -td
    stokes = np.zeros((r, 4))
    e = perpendicular_reference(d_light)
    sel = tk == SKY
    if np.any(sel):
        stokes[sel], e[sel] = env.sky.stokes(td[sel], env.sun_dir)
    sel = tk == SUN
    if np.any(sel):
        sky_s, e[sel] = env.sky.stokes(td[sel], env.sun_dir)
        stokes[sel] = sky_s
        stokes[sel, 0] += env.sun_radiance
    sel = tk == GROUND
    if np.any(sel):
        if env.ground is None:
            raise PihimInputError("a ray hit the ground but the environment has no ground model")
        gt = ground_table or GroundTable(env)
        stokes[sel], e[sel] = gt.lookup(d_light[sel], paths.sun_visible[sel])
    for kind, finish in ((STRUCTURE_HIT, env.structure), (FACET_BACK, env.facet_back), (TOWER_HIT, env.tower)):
        sel = tk == kind
        if np.any(sel):
            stokes[sel], e[sel] = finish_stokes(finish, env, d_light[sel], paths.terminal_normal[sel],
                                                paths.sun_visible[sel])
    # mirror bounces, last first
    nb = paths.n_bounces
    d_cur = d_light
    for k in range(paths.bounce_dir.shape[1] - 1, -1, -1):
        sel = nb > k
        if not np.any(sel):
            continue
        s_out, d_out, s_axis = mt.reflect(stokes[sel], d_cur[sel], e[sel], paths.bounce_normal[sel, k])
        stokes[sel] = s_out
        e[sel] = s_axis
        d_cur = d_cur.copy()
        d_cur[sel] = d_out
    # into the image frame: e = image right made perpendicular to the light entering the camera
    right = np.broadcast_to(np.asarray(image_right, float), (r, 3))
    e_img = right - np.einsum("ij,ij->i", right, d_cur)[:, None] * d_cur
    e_img = normalize(e_img)
    stokes = change_reference(stokes, d_cur, e, e_img)
    stokes[(tk == MIRROR) | ~np.isfinite(stokes[:, 0])] = 0.0
    return stokes[:, :3]
