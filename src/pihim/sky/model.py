"""The skylight model other parts of pihim use: :class:`SkyModel`, and all-sky maps.

``SkyModel.stokes(view_dirs, sun_dir, e=None) -> (stokes, e)`` gives the
Stokes vector of the skylight arriving from each sky direction, in a stated
3-D frame; the ground model integrates it over microfacets and the mirror
model reflects it. :func:`sky_map` evaluates a model on an
azimuth x zenith grid of the visible sky for maps and plots.

Frames (see :mod:`pihim.polarimetry.frames`): light from sky direction ``v``
travels along ``d = -v``; the default reference axis ``e`` is the local
meridian "up" (``perpendicular_reference(d)``: toward the zenith as an
observer looking at that patch of sky sees it; East for ``v`` at the
zenith). The AoP in that frame is counted from "toward the zenith",
counter-clockwise looking into the beam, i.e. as an observer on the ground
looking up at the sky sees it: 0 = field along the meridian, 90 = field
horizontal.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim._quadrature import gauss_legendre
from pihim.errors import PihimInputError
from pihim.polarimetry.stokes import aop_deg, dolp
from pihim.sky.berry import MAX_SEPARATION_DEG, berry_components
from pihim.sky.radiance import CLEAR_SKY_TYPE, cie_relative_radiance
from pihim.sky.rayleigh import rayleigh_components, stokes_in_frame
from pihim.sky.sun import require_daylight

__all__ = ["RadianceKind", "SkyKind", "SkyMap", "SkyModel", "sky_grid", "sky_map"]

SkyKind = Literal["rayleigh", "berry"]
RadianceKind = Literal["cie-clear", "uniform"]
SKY_KINDS: tuple[str, ...] = get_args(SkyKind)
RADIANCE_KINDS: tuple[str, ...] = get_args(RadianceKind)


@dataclass(frozen=True)
class SkyModel:
    """Clear-sky polarized radiance model.

    Attributes
    ----------
    kind : {"rayleigh", "berry"}
        Single-scattering Rayleigh pattern (:mod:`pihim.sky.rayleigh`, the
        paper's model) or the Berry-Dennis-Lee four-neutral-point pattern
        (:mod:`pihim.sky.berry`).
    dmax : float
        Maximum DoLP (at 90 deg from the sun), in [0, 1]. Default 0.8, a
        typical clear-sky maximum in the visible; the paper's measured
        skylight DoLP is below its pure Rayleigh simulation (section 4.1).
    neutral_point_separation_deg : float
        Berry only: distance of each neutral point (Babinet, Brewster, Arago,
        fourth) from the sun or antisun along the sun's vertical, degrees,
        in [0, 45]; default 15 (observed: about 10-25 deg).
    radiance : {"cie-clear", "uniform"}
        S0 distribution: CIE standard clear sky type 12 relative to the
        zenith (:mod:`pihim.sky.radiance`), or 1 everywhere.
    scale : float
        S0 of the zenith sky (``"cie-clear"``) or of every direction
        (``"uniform"``), in the caller's intensity unit. Default 1.
    """

    kind: SkyKind = "rayleigh"
    dmax: float = 0.8
    neutral_point_separation_deg: float = 15.0
    radiance: RadianceKind = "cie-clear"
    scale: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in SKY_KINDS:
            raise PihimInputError(f"unknown sky model {self.kind!r}; choose one of {', '.join(SKY_KINDS)}")
        if self.radiance not in RADIANCE_KINDS:
            raise PihimInputError(f"unknown sky radiance {self.radiance!r}; choose one of {', '.join(RADIANCE_KINDS)}")
        if not _finite(self.dmax) or not 0.0 <= float(self.dmax) <= 1.0:
            raise PihimInputError(f"dmax must be in [0, 1], got {self.dmax!r}")
        sep = self.neutral_point_separation_deg
        if not _finite(sep) or not 0.0 <= float(sep) <= MAX_SEPARATION_DEG:
            raise PihimInputError(
                f"neutral-point separation must be in [0, {MAX_SEPARATION_DEG:g}] deg, got {sep!r}"
            )
        if not _finite(self.scale) or float(self.scale) <= 0.0:
            raise PihimInputError(f"sky radiance scale must be a positive number, got {self.scale!r}")

    def s0(self, view_dirs: ArrayLike, sun_dir: ArrayLike) -> NDArray[np.float64]:
        """Total skylight intensity S0 from each direction (0 below the horizon)."""
        v = np.asarray(view_dirs, dtype=float)
        if self.radiance == "uniform":
            return np.where(v[..., 2] >= 0.0, float(self.scale), 0.0)
        return float(self.scale) * cie_relative_radiance(v, sun_dir, CLEAR_SKY_TYPE)

    def stokes(
        self, view_dirs: ArrayLike, sun_dir: ArrayLike, e: ArrayLike | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Stokes vectors of the skylight arriving from ``view_dirs``.

        Parameters
        ----------
        view_dirs : array_like, shape (..., 3)
            Unit ENU vectors from the observer toward the sky. The light
            propagates along ``d = -view_dirs``.
        sun_dir : array_like, shape (3,) or broadcastable (..., 3)
            Unit ENU vector toward the sun; it must not be below the horizon.
        e : array_like, shape (..., 3), optional
            Reference axes for the result, perpendicular to ``view_dirs``.
            Default: the local meridian "up", ``perpendicular_reference(-view_dirs)``.

        Returns
        -------
        stokes : numpy.ndarray, shape (..., 4)
            ``(S0, S1, S2, S3)`` in the frame ``(d, e)``; all zero for
            directions below the horizon (``view z < 0``); ``S3 = 0``.
        e : numpy.ndarray, shape (..., 3)
            The reference axes used.

        Raises
        ------
        PihimInputError
            Sun below the horizon, malformed or zero vectors, or ``e`` not
            perpendicular to the view directions.
        """
        return stokes_in_frame(self._components, view_dirs, sun_dir, e)

    def _components(
        self, v: NDArray[np.float64], s: NDArray[np.float64], e: NDArray[np.float64], f: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """``(S0, S1, S2)`` on validated unit vectors and frames (``f = d x e``); zero below the horizon."""
        require_daylight(s, what="the sky model")
        s0 = self.s0(v, s)
        if self.kind == "rayleigh":
            s0, s1, s2 = rayleigh_components(v, s, e, f, float(self.dmax), s0)
        else:
            s0, s1, s2 = berry_components(v, s, e, f, float(self.neutral_point_separation_deg), float(self.dmax), s0)
        below = v[..., 2] < 0.0
        if np.any(below):
            s0, s1, s2 = (np.where(below, 0.0, c) for c in (s0, s1, s2))
        return s0, s1, s2

    def describe(self) -> dict[str, object]:
        """JSON-friendly record of the parameters."""
        out: dict[str, object] = {"kind": self.kind, "dmax": float(self.dmax), "radiance": self.radiance}
        if self.kind == "berry":
            out["neutral_point_separation_deg"] = float(self.neutral_point_separation_deg)
        out["scale"] = float(self.scale)
        return out


def _finite(x: object) -> bool:
    if isinstance(x, bool):
        return False
    try:
        return bool(np.isfinite(float(x)))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return False


def _grid_size(resolution_deg: float) -> int:
    res = float(resolution_deg)
    n = 90.0 / res if np.isfinite(res) and res > 0 else float("nan")
    if not (0.05 <= res <= 10.0) or not np.isfinite(n) or abs(n - round(n)) > 1e-9:
        raise PihimInputError(
            f"resolution must be between 0.05 and 10 deg and divide 90 evenly, got {resolution_deg!r}"
        )
    return round(n)


def sky_grid(resolution_deg: float = 0.5) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Cell-centre zenith and azimuth grids (deg) covering the visible sky.

    Returns ``(zenith_deg, azimuth_deg)`` of shape ``(n_zenith, n_azimuth)``
    with ``n_zenith = 90 / resolution`` and ``n_azimuth = 360 / resolution``
    (0.5 deg: 180 x 720 = 129,600 directions). ``resolution_deg`` must divide
    90 into a whole number of cells, between 0.05 and 10 deg.
    """
    nz = _grid_size(resolution_deg)
    res = 90.0 / nz
    zen = (np.arange(nz) + 0.5) * res
    az = (np.arange(4 * nz) + 0.5) * res
    zz, aa = np.meshgrid(zen, az, indexing="ij")
    return zz, aa


@lru_cache(maxsize=4)
def _grid_geometry(nz: int) -> tuple[NDArray[np.float64], ...]:
    """Read-only zenith, azimuth, directions and meridian frames of the grid (cached per size).

    The (..., 3) vectors are stored component-major (each component one
    contiguous block), which speeds up the per-component arithmetic. On the
    grid every factor is a function of the zenith row or of the azimuth
    column alone, so the sines and cosines are taken of the n_zenith row
    and 4 n_zenith column angles only, and the vectors are outer products: with ``v = (sin Z sin A, sin Z cos A,
    cos Z)`` (:func:`~pihim.sky.sun.direction_from_angles`), the meridian
    frame of :func:`~pihim.sky.rayleigh.meridian_frame` is ``e = (-cos Z sin
    A, -cos Z cos A, sin Z)`` and ``d x e = (-cos A, sin A, 0)`` (``sin Z >
    0`` at every cell centre).
    """
    zz, aa = sky_grid(90.0 / nz)
    z, a = np.radians(zz[:, :1]), np.radians(aa[:1, :])
    sz, cz, sa, ca = np.sin(z), np.cos(z), np.sin(a), np.cos(a)
    comp = np.empty((3, 3, *zz.shape))  # (vector, component, zenith, azimuth)
    for k, parts in enumerate(((sz * sa, sz * ca, cz), (-cz * sa, -cz * ca, sz), (-ca, sa, 0.0))):
        for j, part in enumerate(parts):
            comp[k, j] = part
    v, e, f = (np.moveaxis(c, 0, -1) for c in comp)
    arrays = (zz, aa, v, e, f)
    for a in arrays:
        a.flags.writeable = False
    return arrays


@dataclass(frozen=True)
class SkyMap:
    """A model evaluated on the visible sky.

    Arrays have shape ``(n_zenith, n_azimuth)`` (rows: zenith angle, columns:
    azimuth clockwise from North), cell centres in degrees. ``aop_deg`` is
    in [0, 180), relative to the local meridian (0 = field pointing toward
    the zenith), counter-clockwise looking into the beam, i.e. as seen by an
    observer on the ground looking up at that point of the sky.
    ``zenith_deg`` and ``azimuth_deg`` are shared, read-only cached grids.
    """

    zenith_deg: NDArray[np.float64]
    azimuth_deg: NDArray[np.float64]
    s0: NDArray[np.float64]
    dolp: NDArray[np.float64]
    aop_deg: NDArray[np.float64]
    sun_dir: NDArray[np.float64]
    model: SkyModel


def sky_map(model: SkyModel, sun_dir: ArrayLike, resolution_deg: float = 0.5) -> SkyMap:
    """Evaluate ``model`` on :func:`sky_grid` for one sun direction (ENU unit vector).

    The grid directions and their meridian frames are computed once per
    resolution and cached (read-only); each call evaluates S0, DoLP and AoP.
    """
    zz, aa, v, e, f = _grid_geometry(_grid_size(resolution_deg))
    s = np.asarray(sun_dir, dtype=float)
    if s.shape != (3,) or not np.all(np.isfinite(s)) or not np.any(s):
        raise PihimInputError(f"sun direction must be one finite non-zero 3-vector, got {sun_dir!r}")
    s = s / np.linalg.norm(s)
    s0, s1, s2 = model._components(v, s, e, f)
    return SkyMap(
        zenith_deg=zz,
        azimuth_deg=aa,
        s0=np.array(s0),
        dolp=dolp(s0, s1, s2),
        aop_deg=aop_deg(s1, s2),
        sun_dir=s,
        model=model,
    )


def horizontal_irradiance(sky: object, sun_dir: ArrayLike, n_mu: int = 24, n_phi: int = 48) -> float:
    """Diffuse irradiance of a sky on a horizontal plane, ``integral S0(l) l_z d omega``.

    Works for any object with a ``stokes(view_dirs, sun_dir)`` method
    (S0 in radiance units gives W m^-2). Gauss-Legendre in ``cos(zenith)``
    times the midpoint rule in azimuth: exact (``pi L``) for a uniform sky.
    """
    x, w = gauss_legendre(n_mu)
    mu, w_mu = 0.5 * (x + 1.0), 0.5 * w
    phi = (np.arange(n_phi) + 0.5) * (2.0 * np.pi / n_phi)
    mm, pp = np.meshgrid(mu, phi, indexing="ij")
    sin_z = np.sqrt(1.0 - mm**2)
    dirs = np.stack([sin_z * np.sin(pp), sin_z * np.cos(pp), mm], axis=-1)
    s, _ = sky.stokes(dirs, np.asarray(sun_dir, float))  # type: ignore[attr-defined]
    return float(np.sum(np.asarray(s)[..., 0] * mm * w_mu[:, None]) * 2.0 * np.pi / n_phi)


def with_horizontal_irradiance(model: SkyModel, sun_dir: ArrayLike, irradiance_w_m2: float) -> SkyModel:
    """The same sky scaled so that its diffuse horizontal irradiance is ``irradiance_w_m2``.

    Clear skies give roughly 60-150 W m^-2 of diffuse horizontal irradiance
    beside about 900-1000 W m^-2 of direct normal sun, which sets how much the
    sky and the sun each contribute to the light leaving the ground.
    """
    if not _finite(irradiance_w_m2) or float(irradiance_w_m2) <= 0.0:
        raise PihimInputError(f"sky irradiance must be a positive number of W m^-2, got {irradiance_w_m2!r}")
    unit = dataclasses.replace(model, scale=1.0)
    return dataclasses.replace(model, scale=float(irradiance_w_m2) / horizontal_irradiance(unit, sun_dir))
