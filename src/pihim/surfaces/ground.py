"""Polarized reflection from rough ground: a Torrance-Sparrow microfacet model.

The ground is a rough dielectric (refractive index 1.45, paper sec. 3) made of
small flat mirrors -- *microfacets* -- plus an optional depolarized
Lambertian (diffuse) part. It is lit by the sun (a directional, unpolarized
source) and, optionally, by a sky whose Stokes radiance comes from any object
with a ``stokes(view_dirs, sun_dir, e=None)`` method (:class:`SkyRadiance`,
the protocol of :class:`pihim.sky.model.SkyModel`). The result is the Stokes
radiance ``(..., 4)`` leaving the ground toward given viewer directions.

Two evaluations of the same model are provided:

* :meth:`GroundModel.monte_carlo` -- the paper's Monte Carlo (sec. 3 and
  4.2): ``n_facets`` microfacets (100,000 in the paper) are drawn from the
  facet distribution, each reflects the sunlight (and one sampled sky ray)
  into its mirror direction, and the reflected Stokes vectors are rotated
  into a common per-bin frame and accumulated into angular bins of the view
  hemisphere (0.5 deg in the paper).
* :meth:`GroundModel.stokes` -- a deterministic evaluation at arbitrary view
  directions: the sun term in closed form (only the facet whose normal
  bisects sun and view directions contributes) and the sky term as a fixed
  quadrature over facet normals.

Frames and units
----------------
East-North-Up (x East, y North, z up); all directions are unit vectors; the
sun vector points from the ground toward the sun; azimuth is clockwise from
North (``x = sin(zen) sin(az)``, ``y = sin(zen) cos(az)``); angles at the API
are degrees. Output Stokes vectors travel along the view direction
``d = v`` (from the ground toward the camera) with reference axis
``e = perpendicular_reference(v)`` (the local meridian, pointing toward the
zenith side) unless the caller passes ``e``. ``S1 > 0`` is a field along
``e``, ``S2 > 0`` a field 45 deg counter-clockwise from ``e`` looking into
the beam (:mod:`pihim.polarimetry.frames`). Each reflection is evaluated in
its own s/p basis with s as the Mueller x axis
(:mod:`pihim.polarimetry.reflection`). ``sun_irradiance`` is the direct
irradiance on a plane normal to the sun beam (W m^-2); sky radiance must be
in the matching radiance unit (W m^-2 sr^-1); S0 of the output is a radiance
in that unit.

Model
-----
Facet normals ``h`` have zenith angle ``alpha`` in [0, 90 deg] and a uniform
azimuth. Two readings of the paper's "half-Gaussian distribution of the
zenith angle" are offered (``density``):

``"solid_angle"`` (default, as in Torrance & Sparrow 1967 [2]_)
    the number of facets (by area) per unit *solid angle* of normal
    directions is proportional to ``exp(-alpha^2 / (2 sigma^2))``; the
    density per unit ``alpha`` is then ``~ sin(alpha) exp(...)``, zero at
    ``alpha = 0``.
``"zenith"`` (the paper's Fig. 3b, "most likely for zenith angle to be 0")
    the probability per unit *alpha* is ``~ exp(-alpha^2 / (2 sigma^2))``;
    per unit solid angle it is ``~ exp(...) / sin(alpha)``, which makes the
    radiance diverge (integrably) at the specular direction of the mean
    surface.

Let ``D(h)`` be the facet area per unit *horizontal* ground area per unit
solid angle of normals, normalised so that the facets' projected area
equals the ground area, ``integral D(h) cos(alpha) d omega_h = 1``. Sunlight
of irradiance ``E`` from direction ``l`` falls on the facets around ``h``
with irradiance ``E (h . l)`` per facet area; the mirror map ``h -> v`` has
the Jacobian ``d omega_v = 4 (v . h) d omega_h`` (``v . h = l . h``); the
ground seen from ``v`` has projected area ``cos(theta_v) = n . v``. Hence the
radiance reflected toward ``v`` is::

    L(v) = E * D(h) * (h . l) / (4 (v . h)) / (n . v) * G * M_F(h . l) [1, 0, 0, 0]
         = E * D(h) * G / (4 (n . v)) * M_F(v . h) [1, 0, 0, 0],  h = normalize(l + v),

with ``M_F`` the Fresnel Mueller matrix in the facet's s/p basis and ``G`` the
shadowing-masking factor. For sky light of Stokes radiance ``L_sky(l)`` the
same bookkeeping with ``d omega_l = 4 (v . h) d omega_h`` gives::

    L(v) = integral D(h) G (v . h) / (n . v) * R_out M_F(v . h) R_in L_sky(l(h)) d omega_h,
    l(h) = 2 (v . h) h - v,

evaluated with Gauss-Legendre nodes in ``alpha`` (on [0, min(90 deg,
6 sigma)]) times the midpoint rule in azimuth; ``R_in`` and ``R_out`` rotate
into and out of the facet's s/p basis. ``G`` (``include_shadowing``) is the
V-groove shadowing-masking factor of Torrance & Sparrow [2]_ in the compact
form of Blinn [3]_ and Cook & Torrance [4]_,
``G = min(1, 2 (n.h)(n.v)/(v.h), 2 (n.h)(n.l)/(v.h))``; without it, facets
are neither shadowed nor masked (the paper's assumptions). The diffuse part
is Lambertian and depolarized, ``S0 += albedo / pi * (E cos(theta_sun) +
E_sky)``, added on top of the specular part (it is not energy-coupled to the
Fresnel transmission); ``E_sky`` is the sky irradiance on the horizontal
ground. Only single reflections are modelled; light reflected below the
horizon is lost.

The paper does not state ``sigma``; the default of 15 deg is a guess for
rough paved ground and a free parameter. :meth:`GroundModel.paper` returns
the configuration closest to the paper's description.

Accuracy and speed
------------------
The Monte Carlo bins agree with the deterministic bin averages
(:meth:`GroundModel.bin_average`) within the Monte Carlo's own standard
errors (chi-square per degree of freedom about 1 for S0, S1 and S2; see
``tests/surfaces/test_ground.py``). The deterministic map's error is set by
the facet-normal quadrature (16 x 32 nodes: about 2e-3 RMS relative in the
sky term against 64 x 128 nodes) and, for ``sky_method="table"``, by the
sky interpolation (about 2e-5 for a smooth sky); raise ``quadrature`` for
grazing views, where the horizon cut makes the integrand discontinuous. A
1-deg hemisphere map (32,400 directions) with sun and sky takes about
0.2 s on two cores; ``benchmarks/bench_ground.py`` has the figures.

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone", sec. 3 (Torrance-Sparrow ground, n = 1.45, 100,000
   microfacets, 0.5 deg sampling), eqs. (4)-(7), sec. 4.2, Table 1, Fig. 5.
.. [2] K. E. Torrance, E. M. Sparrow, "Theory for off-specular reflection
   from roughened surfaces", J. Opt. Soc. Am. 57(9), 1105-1114 (1967),
   doi:10.1364/JOSA.57.001105.
.. [3] J. F. Blinn, "Models of light reflection for computer synthesized
   pictures", SIGGRAPH 1977, 192-198, doi:10.1145/563858.563893.
.. [4] R. L. Cook, K. E. Torrance, "A reflectance model for computer
   graphics", ACM Trans. Graph. 1(1), 7-24 (1982), doi:10.1145/357290.357293.
"""

from __future__ import annotations

import math
import types
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Literal, Protocol

import numpy as np
from numba import njit, prange
from numpy.typing import ArrayLike, NDArray

from pihim._quadrature import gauss_legendre
from pihim.errors import PihimInputError
from pihim.sky.model import horizontal_irradiance
from pihim.sky.table import SkyTable as _SkyTable
from pihim.sky.table import sample_table
from pihim.polarimetry.frames import (
    aop4_deg,
    change_reference,
    dolp4,
    dot,
    normalize,
    perpendicular_reference,
)
from pihim.polarimetry.reflection import reflect_stokes
from pihim.surfaces.fresnel import fresnel_reflection_mueller

__all__ = [
    "DEFAULT_SIGMA_DEG",
    "GROUND_REFRACTIVE_INDEX",
    "PAPER_BIN_DEG",
    "PAPER_N_FACETS",
    "GroundModel",
    "HemisphereGrid",
    "MonteCarloResult",
    "SkyRadiance",
    "hemisphere_grid",
    "use_serial_kernels",
]

#: Refractive index of the ground used in the paper (sec. 3, its ref. [28]).
GROUND_REFRACTIVE_INDEX = 1.45
#: Default facet-slope width (deg); not given in the paper, a free parameter.
DEFAULT_SIGMA_DEG = 15.0
#: Number of microfacets of the paper's Monte Carlo (sec. 3).
PAPER_N_FACETS = 100_000
#: Angular sampling of the paper's Monte Carlo (sec. 3), deg.
PAPER_BIN_DEG = 0.5
#: Default direct sun irradiance normal to the beam, W m^-2.
DEFAULT_SUN_IRRADIANCE = 1000.0

Density = Literal["solid_angle", "zenith"]
SkyMethod = Literal["table", "direct"]

_UNIT_TOL = 1e-6
#: Facet zenith angles beyond this many sigma carry < 2e-8 of the density.
_ALPHA_CUT_SIGMAS = 6.0
#: Smallest facet zenith (rad) used to evaluate the "zenith" density, whose
#: per-solid-angle value diverges as 1/sin(alpha) at alpha = 0.
_ALPHA_FLOOR = 1e-6


class SkyRadiance(Protocol):
    """Anything that gives the sky's Stokes radiance, like :class:`pihim.sky.model.SkyModel`.

    ``stokes(view_dirs, sun_dir, e=None)`` takes unit vectors ``(..., 3)``
    from the observer toward the sky and the sun vector ``(3,)`` and returns
    ``(stokes (..., 4), e (..., 3))``: the radiance arriving from each
    direction, propagating along ``d = -view_dirs``, in the frame with
    reference axis ``e`` (the caller's ``e`` if given). Directions below the
    horizon give zero.
    """

    def stokes(
        self, view_dirs: ArrayLike, sun_dir: ArrayLike, e: ArrayLike | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...  # pragma: no cover - protocol


# ---------------------------------------------------------------------------
# Input checks
# ---------------------------------------------------------------------------
def _unit_vectors(v: ArrayLike, name: str) -> NDArray[np.float64]:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError) as exc:
        raise PihimInputError(f"{name} must be a numeric array of 3-vectors") from exc
    if a.ndim == 0 or a.shape[-1] != 3:
        raise PihimInputError(f"{name} must have 3 components on its last axis, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise PihimInputError(f"{name} contains non-finite values")
    norm = np.linalg.norm(a, axis=-1)
    if a.size and np.max(np.abs(norm - 1.0)) > _UNIT_TOL:
        raise PihimInputError(f"{name} must be unit vectors (largest |norm - 1| = {np.max(np.abs(norm - 1.0)):.3g})")
    return a


def _sun_vector(sun_dir: ArrayLike) -> NDArray[np.float64]:
    s = _unit_vectors(sun_dir, "sun_dir")
    if s.shape != (3,):
        raise PihimInputError(f"sun_dir must have shape (3,), got {s.shape}")
    return s


def _check_sky(sky: object) -> None:
    if sky is not None and not callable(getattr(sky, "stokes", None)):
        raise PihimInputError(f"sky must have a stokes(view_dirs, sun_dir, e=None) method, got {type(sky).__name__}")


def _check_bin(bin_deg: float, name: str = "bin_deg") -> int:
    if isinstance(bin_deg, bool) or not (
        isinstance(bin_deg, (int, float)) and math.isfinite(bin_deg) and 0 < bin_deg <= 90
    ):
        raise PihimInputError(f"{name} must be in (0, 90] deg, got {bin_deg!r}")
    n = round(90.0 / bin_deg)
    if abs(n * bin_deg - 90.0) > 1e-9 * 90.0:
        raise PihimInputError(f"{name} must divide 90 deg evenly, got {bin_deg!r}")
    return n


# ---------------------------------------------------------------------------
# Hemisphere binning
# ---------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class HemisphereGrid:
    """Regular zenith x azimuth bins of the upper hemisphere of view directions.

    Bin ``(i, j)`` covers zenith ``[i, i+1) * step_deg`` and azimuth
    ``[j, j+1) * step_deg`` (clockwise from North); a direction is assigned
    by truncation (``floor``), the scheme of the paper's Monte Carlo (sec. 4.2,
    assumption 4, with 1-deg bins). Build with :func:`hemisphere_grid`.

    Attributes
    ----------
    step_deg : float
        Bin width in zenith and azimuth, deg.
    zenith_deg, azimuth_deg : (nz,), (na,) ndarray
        Bin centres, deg.
    directions : (nz, na, 3) ndarray
        Unit vectors of the bin centres (ENU).
    reference : (nz, na, 3) ndarray
        Stokes reference axis of each bin, ``perpendicular_reference`` of the
        centre direction (the local meridian, toward the zenith side).
    projected_solid_angle : (nz, na) ndarray
        ``integral cos(zen) d omega`` over the bin, sr (sums to pi).
    """

    step_deg: float
    zenith_deg: NDArray[np.float64]
    azimuth_deg: NDArray[np.float64]
    directions: NDArray[np.float64]
    reference: NDArray[np.float64]
    projected_solid_angle: NDArray[np.float64]

    @property
    def shape(self) -> tuple[int, int]:
        """``(nz, na)``."""
        return self.directions.shape[:2]

    def locate(self, dirs: ArrayLike) -> NDArray[np.intp]:
        """Flat bin index ``i * na + j`` of unit vectors ``(..., 3)``; -1 at or below the horizon."""
        d = np.asarray(dirs, float)
        nz, na = self.shape
        zen = np.degrees(np.arccos(np.clip(d[..., 2], -1.0, 1.0)))
        az = np.mod(np.degrees(np.arctan2(d[..., 0], d[..., 1])), 360.0)
        i = np.minimum((zen / self.step_deg).astype(np.intp), nz - 1)
        j = np.minimum((az / self.step_deg).astype(np.intp), na - 1)
        return np.where(d[..., 2] > 0.0, i * na + j, -1)


def _direction(zen_rad: ArrayLike, az_rad: ArrayLike) -> NDArray[np.float64]:
    zen_rad, az_rad = np.broadcast_arrays(np.asarray(zen_rad, float), np.asarray(az_rad, float))
    sz = np.sin(zen_rad)
    return np.stack([sz * np.sin(az_rad), sz * np.cos(az_rad), np.cos(zen_rad)], axis=-1)


def hemisphere_grid(step_deg: float = 1.0) -> HemisphereGrid:
    """Bins of the view hemisphere ``(90 / step_deg) x (360 / step_deg)`` for maps and the Monte Carlo.

    Parameters
    ----------
    step_deg : float
        Bin width, deg; must divide 90 (e.g. 0.5, 1, 2, 5).

    Returns
    -------
    HemisphereGrid
        Centres, directions, per-bin Stokes reference axes and projected
        solid angles. With ``step_deg = 1`` the map has 90 x 360 directions.
    """
    nz = _check_bin(step_deg, "step_deg")
    na = 4 * nz
    step = 90.0 / nz
    zen = (np.arange(nz) + 0.5) * step
    az = (np.arange(na) + 0.5) * step
    zz, aa = np.meshgrid(np.radians(zen), np.radians(az), indexing="ij")
    dirs = _direction(zz, aa)
    edges = np.radians(np.arange(nz + 1) * step)
    ring = 0.5 * (np.sin(edges[1:]) ** 2 - np.sin(edges[:-1]) ** 2) * np.radians(step)
    return HemisphereGrid(
        step_deg=step,
        zenith_deg=zen,
        azimuth_deg=az,
        directions=dirs,
        reference=perpendicular_reference(dirs),
        projected_solid_angle=np.broadcast_to(ring[:, None], (nz, na)).copy(),
    )


@dataclass(frozen=True, eq=False)
class MonteCarloResult:
    """Binned output of :meth:`GroundModel.monte_carlo`.

    Attributes
    ----------
    grid : HemisphereGrid
        The bins; Stokes of bin ``(i, j)`` are in the frame of its centre
        (``grid.directions[i, j]``, ``grid.reference[i, j]``).
    counts : (nz, na) int ndarray
        Reflected rays (sun and sky) that landed in each bin.
    stokes : (nz, na, 4) ndarray
        Bin-averaged Stokes radiance (W m^-2 sr^-1, projected-solid-angle
        average, ``sum of ray fluxes / (ground area * projected solid
        angle)``), diffuse part included.
    stderr : (nz, na, 4) ndarray
        One-sigma sampling error of ``stokes`` (from the per-facet flux
        spread; the diffuse part is exact).
    n_facets, seed : int
        Sample size and seed of the run.
    """

    grid: HemisphereGrid
    counts: NDArray[np.int64]
    stokes: NDArray[np.float64]
    stderr: NDArray[np.float64]
    n_facets: int
    seed: int

    @property
    def dolp(self) -> NDArray[np.float64]:
        """Degree of linear polarization per bin (NaN where S0 = 0)."""
        return dolp4(self.stokes)

    @property
    def aop_deg(self) -> NDArray[np.float64]:
        """AoP per bin, deg in [0, 180), from the bin's reference axis."""
        return aop4_deg(self.stokes)


# ---------------------------------------------------------------------------
# Numba kernel of the sky integral (tabulated sky)
# ---------------------------------------------------------------------------
def _renamed(fn: types.FunctionType, name: str) -> types.FunctionType:
    """A copy of the plain function ``fn`` (same code, globals and defaults) named ``name``."""
    copy = types.FunctionType(fn.__code__, fn.__globals__, name, fn.__defaults__, fn.__closure__)
    copy.__qualname__ = name
    return copy


@njit(parallel=True, fastmath=True, cache=True)
def _sky_kernel(views, e_out, nodes, weights, table, radius, step, n, shadowing, out):  # pragma: no cover - compiled
    """Sky term of :meth:`GroundModel.stokes` for unit views ``(V, 3)``, written into ``out (V, 4)``.

    Same integrand as :func:`_sky_integral_numpy`, with the sky Stokes taken
    by bilinear interpolation from ``table`` (see :class:`_SkyTable`): the
    sky in frame ``(d = -l, e_T(l))``, ``e_T(l) = x - l_x / (1 + l_z) (l + z)``,
    on a square grid of Lambert azimuthal equal-area coordinates.
    """
    n_views = views.shape[0]
    n_nodes = nodes.shape[0]
    inv_n2 = 1.0 / (n * n)
    for i in prange(n_views):
        vx = views[i, 0]
        vy = views[i, 1]
        vz = views[i, 2]
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        a3 = 0.0
        if vz > 0.0:
            ex = e_out[i, 0]
            ey = e_out[i, 1]
            ez = e_out[i, 2]
            for j in range(n_nodes):
                hx = nodes[j, 0]
                hy = nodes[j, 1]
                hz = nodes[j, 2]
                c = vx * hx + vy * hy + vz * hz
                if c <= 0.0:
                    continue
                lx = 2.0 * c * hx - vx
                ly = 2.0 * c * hy - vy
                lz = 2.0 * c * hz - vz
                if lz <= 0.0:
                    continue
                g = 1.0
                if shadowing:
                    g = min(1.0, 2.0 * hz * vz / c, 2.0 * hz * lz / c)
                w = weights[j] * g * c / vz
                # sky Stokes at l and the table's axis e_T(l)
                s0, s1, s2, s3, tex, tey, tez = sample_table(table, radius, step, lx, ly, lz)
                # s axis of the facet's plane of incidence: normalize(d_in x h) = normalize(v x h)
                sx = vy * hz - vz * hy
                sy = vz * hx - vx * hz
                sz = vx * hy - vy * hx
                ns = math.sqrt(sx * sx + sy * sy + sz * sz)
                if ns < 1e-12:  # normal incidence: any axis normal to l serves
                    sx = tex
                    sy = tey
                    sz = tez
                else:
                    sx /= ns
                    sy /= ns
                    sz /= ns
                # rotate (d_in = -l, e_T) -> (d_in, s): cos t = e_T.s, sin t = (e_T x s).d_in
                ct = tex * sx + tey * sy + tez * sz
                st = -((tey * sz - tez * sy) * lx + (tez * sx - tex * sz) * ly + (tex * sy - tey * sx) * lz)
                c2 = ct * ct - st * st
                s2t = 2.0 * st * ct
                q1 = c2 * s1 + s2t * s2
                q2 = -s2t * s1 + c2 * s2
                # Fresnel reflection (real index n > 1, external reflection), s as x axis
                cos_t = math.sqrt(1.0 - (1.0 - c * c) * inv_n2)
                rs = (c - n * cos_t) / (c + n * cos_t)
                rp = (n * c - cos_t) / (n * c + cos_t)
                fa = 0.5 * (rs * rs + rp * rp)
                fb = 0.5 * (rs * rs - rp * rp)
                fc = rs * rp
                r0 = fa * s0 + fb * q1
                r1 = fb * s0 + fa * q1
                r2 = fc * q2
                r3 = fc * s3
                # rotate (v, s) -> (v, e_out): cos u = s.e, sin u = (s x e).v
                cu = sx * ex + sy * ey + sz * ez
                su = (sy * ez - sz * ey) * vx + (sz * ex - sx * ez) * vy + (sx * ey - sy * ex) * vz
                c2u = cu * cu - su * su
                s2u = 2.0 * su * cu
                a0 += w * r0
                a1 += w * (c2u * r1 + s2u * r2)
                a2 += w * (-s2u * r1 + c2u * r2)
                a3 += w * r3
        out[i, 0] = a0
        out[i, 1] = a1
        out[i, 2] = a2
        out[i, 3] = a3


#: The same kernel compiled without threads (``prange`` runs as ``range``; each view's sum is the same loop, and
#: the values are identical on this machine, tested; ``fastmath`` lets LLVM reorder sums, so another CPU could in
#: principle differ in the last bits): used where a process must not start OpenMP threads, in the workers that
#: :func:`pihim.planning.windows.sweep_day` forks (GNU OpenMP does not survive ``fork``). A copy of the Python
#: function under its own name: numba's on-disk cache is keyed by the function's name and line, not by
#: ``parallel``, and would hand this twin the threaded machine code. (With ``NUMBA_DISABLE_JIT=1`` both are
#: the plain function.)
_sky_kernel_serial = njit(fastmath=True, cache=True)(
    _renamed(getattr(_sky_kernel, "py_func", _sky_kernel), "_sky_kernel_serial"))
_serial_kernels = False


def use_serial_kernels(serial: bool = True) -> None:
    """Run this module's compiled kernels without threads in this process, or with them again.

    For processes that must not start OpenMP threads: workers forked from a
    process whose OpenMP runtime has started (GNU OpenMP does not survive
    ``fork``; numba then terminates the child).

    Parameters
    ----------
    serial : bool
        True: the threadless twins from now on; False: the threaded kernels.
    """
    global _serial_kernels
    _serial_kernels = bool(serial)


# ---------------------------------------------------------------------------
# Sky sampling: direct calls or a Lambert azimuthal table (pihim.sky.table)
# ---------------------------------------------------------------------------
def _stokes4(s: ArrayLike) -> NDArray[np.float64]:
    s = np.asarray(s, float)
    if s.shape[-1] == 3:
        s = np.concatenate([s, np.zeros((*s.shape[:-1], 1))], axis=-1)
    return s


def _direct_sampler(sky: SkyRadiance, sun_dir: NDArray[np.float64]) -> SkySampler:
    def sample(l: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        s, e = sky.stokes(l, sun_dir)
        return _stokes4(s), np.asarray(e, float)

    return sample


def _shadowing(h_z: NDArray, v_z: NDArray, l_z: NDArray, c: NDArray) -> NDArray[np.float64]:
    """V-groove shadowing-masking ``min(1, 2 h_z v_z / c, 2 h_z l_z / c)`` clipped at 0 (``c = v.h = l.h``)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.minimum(1.0, np.minimum(2.0 * h_z * v_z / c, 2.0 * h_z * l_z / c))
    return np.where(c > 0, np.clip(g, 0.0, 1.0), 0.0)


SkySampler = Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], NDArray[np.float64]]]


def _sky_integral_numpy(
    views: NDArray[np.float64],
    e_out: NDArray[np.float64],
    nodes: NDArray[np.float64],
    weights: NDArray[np.float64],
    sampler: SkySampler,
    n: float,
    shadowing: bool,
    max_pairs: int = 250_000,
) -> NDArray[np.float64]:
    """Reference (numpy) sky term: the facet-normal quadrature with the project's reflection routines.

    For each view ``v`` and node ``h``: ``l = 2 (v.h) h - v``; the sky Stokes
    from ``sampler(l)`` are reflected with :func:`reflect_stokes` (Fresnel,
    s as x axis), re-expressed in the output frame ``(v, e_out)`` and summed
    with weight ``w_h G (v.h) / v_z``. Pairs with ``v.h <= 0`` or
    ``l_z <= 0`` contribute nothing. Processed in chunks of about
    ``max_pairs`` (view, node) pairs.
    """
    out = np.zeros((views.shape[0], 4))
    mueller = partial(fresnel_reflection_mueller, n1=1.0, n2=n)
    chunk = max(1, max_pairs // max(1, nodes.shape[0]))
    for start in range(0, views.shape[0], chunk):
        v = views[start : start + chunk]
        c = v @ nodes.T
        l = 2.0 * c[..., None] * nodes[None] - v[:, None]
        ok = (c > 0) & (l[..., 2] > 0) & (v[:, None, 2] > 0)
        iv, ih = np.nonzero(ok)
        if iv.size == 0:
            continue
        lv, hv, vv, cv = l[iv, ih], nodes[ih], v[iv], c[iv, ih]
        lv = normalize(lv)
        s_in, e_in = sampler(lv)
        s_ref, _, s_axis = reflect_stokes(s_in, -lv, e_in, hv, mueller)
        s_ref = change_reference(s_ref, vv, s_axis, e_out[start + iv])
        g = _shadowing(hv[:, 2], vv[:, 2], lv[:, 2], cv) if shadowing else 1.0
        w = weights[ih] * g * cv / vv[:, 2]
        for k in range(4):
            out[start : start + chunk, k] += np.bincount(iv, weights=w * s_ref[:, k], minlength=v.shape[0])
    return out


# ---------------------------------------------------------------------------
# The model
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class GroundModel:
    """Rough dielectric ground: specular Torrance-Sparrow microfacets plus a depolarized Lambertian part.

    Parameters
    ----------
    sigma_deg : float
        Width of the half-Gaussian facet-zenith distribution, deg (> 0, <= 90).
        Not given in the paper; 15 deg is a guess for rough paved ground.
    refractive_index : float
        Real refractive index of the ground (> 1); 1.45 in the paper.
    diffuse_albedo : float
        Albedo in [0, 1] of the Lambertian, depolarized part (0: specular
        facets only, the paper's assumption 2).
    sun_irradiance : float
        Direct solar irradiance on a plane normal to the beam, W m^-2 (>= 0).
    include_shadowing : bool
        Apply the Torrance-Sparrow V-groove shadowing-masking factor ``G``.
    density : {"solid_angle", "zenith"}
        Whether ``exp(-alpha^2 / (2 sigma^2))`` is the facet density per unit
        solid angle of normals (Torrance & Sparrow) or per unit zenith angle
        ``alpha`` (the paper's Fig. 3b); see the module notes.

    Notes
    -----
    Both :meth:`stokes` and :meth:`monte_carlo` use the same distribution,
    the same normalisation (facets' projected area = ground area) and the
    same ``G``, so they estimate the same radiance.
    """

    sigma_deg: float = DEFAULT_SIGMA_DEG
    refractive_index: float = GROUND_REFRACTIVE_INDEX
    diffuse_albedo: float = 0.0
    sun_irradiance: float = DEFAULT_SUN_IRRADIANCE
    include_shadowing: bool = True
    density: Density = "solid_angle"
    _norm: float = field(init=False, repr=False, compare=False)
    _mean_cos: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        s = self.sigma_deg
        if isinstance(s, bool) or not (isinstance(s, (int, float)) and math.isfinite(s) and 0.0 < s <= 90.0):
            raise PihimInputError(f"sigma_deg must be in (0, 90] deg, got {s!r}")
        if not isinstance(self.include_shadowing, (bool, np.bool_)):  # "no" would be taken for True
            raise PihimInputError(f"include_shadowing must be True or False, got {self.include_shadowing!r}")
        n = self.refractive_index
        if not (isinstance(n, (int, float)) and math.isfinite(n) and n > 1.0):
            raise PihimInputError(f"refractive_index must be a real number > 1, got {n!r}")
        a = self.diffuse_albedo
        if not (isinstance(a, (int, float)) and 0.0 <= a <= 1.0):
            raise PihimInputError(f"diffuse_albedo must be in [0, 1], got {a!r}")
        e = self.sun_irradiance
        if not (isinstance(e, (int, float)) and math.isfinite(e) and e >= 0.0):
            raise PihimInputError(f"sun_irradiance must be finite and >= 0 W m^-2, got {e!r}")
        if self.density not in ("solid_angle", "zenith"):
            raise PihimInputError(f"density must be 'solid_angle' or 'zenith', got {self.density!r}")
        # K = int_0^{pi/2} exp(-a^2/2s^2) w(a) cos(a) da and Z = int exp w da, w = sin (solid angle) or 1
        x, wq = gauss_legendre(256)
        amax = self._alpha_max(sigma_factor=12.0)
        alpha = 0.5 * amax * (x + 1.0)
        wq = 0.5 * amax * wq
        g = np.exp(-0.5 * (alpha / self.sigma_rad) ** 2) * self._jacobian(alpha)
        k = float(np.sum(wq * g * np.cos(alpha)))
        z = float(np.sum(wq * g))
        object.__setattr__(self, "_norm", k)
        object.__setattr__(self, "_mean_cos", k / z)

    @classmethod
    def paper(cls, sigma_deg: float = DEFAULT_SIGMA_DEG, **kwargs) -> GroundModel:
        """The paper's ground (sec. 3, assumptions of sec. 4.2).

        Half-Gaussian density per unit zenith angle (Fig. 3b), n = 1.45,
        specular facets only (no diffuse part), no shadowing or masking.
        ``sigma_deg`` is not stated in the paper.
        """
        opts = {"diffuse_albedo": 0.0, "include_shadowing": False, "density": "zenith"}
        opts.update(kwargs)
        return cls(sigma_deg=sigma_deg, **opts)

    # -- distribution ------------------------------------------------------
    @property
    def sigma_rad(self) -> float:
        """Facet-slope width in radians."""
        return math.radians(self.sigma_deg)

    @property
    def mean_cos_alpha(self) -> float:
        """``<cos alpha>`` over facet area: projected facet area per unit facet area."""
        return self._mean_cos

    def _alpha_max(self, sigma_factor: float = _ALPHA_CUT_SIGMAS) -> float:
        return min(0.5 * math.pi, sigma_factor * self.sigma_rad)

    def _jacobian(self, alpha: NDArray) -> NDArray:
        return np.sin(alpha) if self.density == "solid_angle" else np.ones_like(alpha)

    def facet_density(self, alpha_deg: ArrayLike) -> NDArray[np.float64]:
        """``D``: facet area per unit ground area per steradian of normals at zenith ``alpha_deg``.

        Normalised so that ``integral D cos(alpha) d omega = 1`` over the
        hemisphere of normals (facets' projected area equals the ground
        area). Zero beyond 90 deg. For ``density="zenith"``, ``alpha`` is
        floored at 1e-6 rad where ``D ~ 1 / sin(alpha)`` diverges.

        Parameters
        ----------
        alpha_deg : array_like
            Facet zenith angle, deg.

        Returns
        -------
        ndarray
            ``D`` in sr^-1.
        """
        alpha = np.radians(np.asarray(alpha_deg, float))
        g = np.exp(-0.5 * (alpha / self.sigma_rad) ** 2) / (2.0 * math.pi * self._norm)
        if self.density == "zenith":
            g = g / np.sin(np.maximum(alpha, _ALPHA_FLOOR))
        return np.where((alpha >= 0) & (alpha <= 0.5 * math.pi), g, 0.0)

    def sample_facets(self, n_facets: int, rng: np.random.Generator) -> NDArray[np.float64]:
        """``n_facets`` facet normals ``(n, 3)`` drawn from the (area-weighted) facet distribution.

        ``"zenith"``: ``alpha = |N(0, sigma)|`` truncated to 90 deg by
        rejection. ``"solid_angle"``: Rayleigh draws (density ``~ alpha
        exp(...)``) accepted with probability ``sin(alpha) / alpha`` and
        ``alpha <= 90 deg``. Azimuth uniform in [0, 360) deg.
        """
        sig = self.sigma_rad
        out = np.empty(0)
        while out.size < n_facets:
            m = int(1.2 * (n_facets - out.size)) + 16
            if self.density == "zenith":
                a = np.abs(rng.normal(0.0, sig, m))
                keep = a <= 0.5 * math.pi
            else:
                a = sig * np.sqrt(-2.0 * np.log1p(-rng.random(m)))
                with np.errstate(invalid="ignore", divide="ignore"):
                    ratio = np.where(a > 0, np.sin(a) / a, 1.0)
                keep = (a <= 0.5 * math.pi) & (rng.random(m) < ratio)
            out = np.concatenate([out, a[keep]])
        alpha = out[:n_facets]
        phi = rng.uniform(0.0, 2.0 * math.pi, n_facets)
        return _direction(alpha, phi)

    def quadrature_nodes(self, n_alpha: int = 16, n_phi: int = 32) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Facet normals and weights for integrals ``integral f(h) D(h) d omega_h``.

        Gauss-Legendre in ``alpha`` on [0, min(90 deg, 6 sigma)] times the
        midpoint rule in azimuth (``n_phi`` equal steps); the weights include
        ``D(alpha) sin(alpha) d alpha d phi``, so ``sum(w * h_z) = 1`` up to the
        2e-8 of the density cut beyond 6 sigma.

        Returns
        -------
        nodes : (n_alpha * n_phi, 3) ndarray
        weights : (n_alpha * n_phi,) ndarray, sr^-1 * sr (dimensionless)
        """
        if n_alpha < 1 or n_phi < 1:
            raise PihimInputError(f"quadrature needs n_alpha >= 1 and n_phi >= 1, got ({n_alpha}, {n_phi})")
        x, wq = gauss_legendre(n_alpha)
        amax = self._alpha_max()
        alpha = 0.5 * amax * (x + 1.0)
        wa = 0.5 * amax * wq * np.exp(-0.5 * (alpha / self.sigma_rad) ** 2) * self._jacobian(alpha)
        wa = wa / (2.0 * math.pi * self._norm)
        phi = (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)
        aa, pp = np.meshgrid(alpha, phi, indexing="ij")
        nodes = _direction(aa, pp).reshape(-1, 3)
        weights = np.broadcast_to((wa * 2.0 * math.pi / n_phi)[:, None], aa.shape).reshape(-1)
        return np.ascontiguousarray(nodes), np.ascontiguousarray(weights)

    # -- pieces ------------------------------------------------------------
    def _mueller(self) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
        return partial(fresnel_reflection_mueller, n1=1.0, n2=self.refractive_index)

    def sky_irradiance(self, sky: SkyRadiance | None, sun_dir: ArrayLike, n_mu: int = 24, n_phi: int = 48) -> float:
        """Sky irradiance on the horizontal ground, W m^-2 (see :func:`pihim.sky.model.horizontal_irradiance`)."""
        if sky is None:
            return 0.0
        return horizontal_irradiance(sky, _sun_vector(sun_dir), n_mu, n_phi)

    def diffuse_radiance(self, sun_dir: ArrayLike, sky: SkyRadiance | None = None) -> float:
        """Radiance of the Lambertian part, ``albedo / pi * (E cos(theta_sun) + E_sky)``, W m^-2 sr^-1."""
        if self.diffuse_albedo == 0.0:
            return 0.0
        sun = _sun_vector(sun_dir)
        e_h = self.sun_irradiance * max(sun[2], 0.0) + self.sky_irradiance(sky, sun)
        return self.diffuse_albedo / math.pi * e_h

    def _sun_term(
        self, v: NDArray[np.float64], e: NDArray[np.float64], sun: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        out = np.zeros((v.shape[0], 4))
        if self.sun_irradiance == 0.0 or sun[2] <= 0.0:
            return out
        ok = v[:, 2] > 0.0
        if not np.any(ok):
            return out
        vv, ee = v[ok], e[ok]
        h = normalize(sun + vv)
        c = dot(vv, h)
        s_in = np.zeros((vv.shape[0], 4))
        s_in[:, 0] = self.sun_irradiance
        d_in = np.broadcast_to(-sun, vv.shape)
        s_ref, _, s_axis = reflect_stokes(s_in, d_in, perpendicular_reference(d_in), h, self._mueller())
        s_ref = change_reference(s_ref, vv, s_axis, ee)
        alpha_deg = np.degrees(np.arccos(np.clip(h[:, 2], -1.0, 1.0)))
        g = _shadowing(h[:, 2], vv[:, 2], np.full(c.shape, sun[2]), c) if self.include_shadowing else 1.0
        w = self.facet_density(alpha_deg) * g / (4.0 * vv[:, 2])
        out[ok] = w[:, None] * s_ref
        return out

    # -- deterministic evaluation -------------------------------------------
    def sky_table(self, sky: SkyRadiance, sun_dir: ArrayLike, size: int = 257) -> _SkyTable:
        """The sky tabulated for :meth:`stokes` (``sky_method="table"``): pass it as ``sky_table=`` to reuse it
        across calls with the same sky and sun (the values are those :meth:`stokes` computes with
        ``sky_table_size=size``)."""
        _check_sky(sky)
        if sky is None:
            raise PihimInputError("sky_table needs a sky")
        if not (isinstance(size, int) and size >= 3):
            raise PihimInputError(f"sky_table_size must be an integer >= 3, got {size!r}")
        return _SkyTable(sky, _sun_vector(sun_dir), size)

    def stokes(
        self,
        view_dirs: ArrayLike,
        sun_dir: ArrayLike,
        sky: SkyRadiance | None = None,
        e: ArrayLike | None = None,
        *,
        sky_method: SkyMethod = "table",
        quadrature: tuple[int, int] = (16, 32),
        sky_table_size: int = 257,
        sky_table: _SkyTable | None = None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Stokes radiance leaving the ground toward ``view_dirs`` (deterministic).

        Parameters
        ----------
        view_dirs : array_like, (..., 3)
            Unit vectors from the ground point toward the camera (ENU).
            Directions at or below the horizon get zero.
        sun_dir : array_like, (3,)
            Unit vector toward the sun. No sun term when it is below the horizon.
        sky : SkyRadiance, optional
            Sky radiance (e.g. :class:`pihim.sky.model.SkyModel`); None: sun only.
        e : array_like, (..., 3), optional
            Output reference axes (unit, normal to ``view_dirs``); default
            ``perpendicular_reference(view_dirs)``.
        sky_method : {"table", "direct"}
            ``"table"``: the sky is evaluated once on a
            ``sky_table_size^2`` Lambert azimuthal grid and interpolated
            inside a compiled (numba) kernel -- fast, with an interpolation
            error set by the sky's smoothness. ``"direct"``: the sky is
            called at every quadrature direction and the integrand is
            evaluated with numpy (slow reference).
        quadrature : (int, int)
            ``(n_alpha, n_phi)`` of :meth:`quadrature_nodes` for the sky term.
        sky_table_size : int
            Table nodes per axis for ``sky_method="table"`` (>= 3).
        sky_table : pihim.sky.table.SkyTable, optional
            With ``sky_method="table"``: the table of ``sky`` for this sun
            (:meth:`sky_table`), built once by the caller and reused across
            calls (it costs ~10-25 ms per call otherwise); ``sky_table_size``
            is then unused. A table of another sun is refused; that it is
            ``sky``'s is the caller's to keep. Unused without a sky or with
            ``sky_method="direct"``.

        Returns
        -------
        stokes : (..., 4) ndarray
            Stokes radiance (W m^-2 sr^-1 for ``sun_irradiance`` in W m^-2),
            propagating along ``view_dirs``, in the frame of ``e``. With
            ``density="zenith"`` the sun term is singular at the mean
            surface's specular direction (finite here only because ``alpha``
            is floored at 1e-6 rad); compare bin averages there.
        e : (..., 3) ndarray
            The reference axes used.
        """
        v = _unit_vectors(view_dirs, "view_dirs")
        sun = _sun_vector(sun_dir)
        _check_sky(sky)
        shape = v.shape[:-1]
        v = v.reshape(-1, 3)
        if e is None:
            ee = perpendicular_reference(v)
        else:
            try:
                e_b = np.broadcast_to(np.asarray(e, float), shape + (3,))
            except ValueError as exc:
                raise PihimInputError(f"e must broadcast to the shape of view_dirs {shape + (3,)}") from exc
            ee = _unit_vectors(e_b, "e").reshape(-1, 3)
            if v.size and np.max(np.abs(dot(ee, v))) > _UNIT_TOL:
                raise PihimInputError("e must be perpendicular to view_dirs")
        out = self._sun_term(v, ee, sun)
        if sky is not None:
            out += self._sky_term(v, ee, sun, sky, sky_method, quadrature, sky_table_size, sky_table)
        diffuse = self.diffuse_radiance(sun, sky)
        if diffuse:
            out[:, 0] += np.where(v[:, 2] > 0.0, diffuse, 0.0)
        return out.reshape(shape + (4,)), ee.reshape(shape + (3,))

    def _sky_term(self, v, ee, sun, sky, sky_method, quadrature, sky_table_size, sky_table=None
                  ) -> NDArray[np.float64]:
        nodes, weights = self.quadrature_nodes(*quadrature)
        if sky_method == "direct":
            return _sky_integral_numpy(
                v, ee, nodes, weights, _direct_sampler(sky, sun), self.refractive_index, self.include_shadowing
            )
        if sky_method != "table":
            raise PihimInputError(f"sky_method must be 'table' or 'direct', got {sky_method!r}")
        if sky_table is not None:
            if not isinstance(sky_table, _SkyTable):
                raise PihimInputError(f"sky_table must be a pihim.sky.table.SkyTable, got {type(sky_table).__name__}")
            if float(np.max(np.abs(sky_table.sun_dir - sun))) > 1e-12:
                raise PihimInputError("sky_table was built for another sun direction")
            table = sky_table
        elif not (isinstance(sky_table_size, int) and sky_table_size >= 3):
            raise PihimInputError(f"sky_table_size must be an integer >= 3, got {sky_table_size!r}")
        else:
            table = _SkyTable(sky, sun, sky_table_size)
        out = np.zeros((v.shape[0], 4))
        # writable C arrays always: a read-only view (a broadcast reference axis) would compile a second specialization
        (_sky_kernel_serial if _serial_kernels else _sky_kernel)(
            np.require(v, np.float64, ["C", "W"]),
            np.require(ee, np.float64, ["C", "W"]),
            nodes,
            weights,
            table.table,
            table.radius,
            table.step,
            float(self.refractive_index),
            bool(self.include_shadowing),
            out,
        )
        return out

    def bin_average(
        self,
        grid: HemisphereGrid,
        sun_dir: ArrayLike,
        sky: SkyRadiance | None = None,
        *,
        sub: int = 4,
        **stokes_options,
    ) -> NDArray[np.float64]:
        """Deterministic bin averages ``(nz, na, 4)`` comparable with :meth:`monte_carlo` bins.

        Each bin is sampled at ``sub x sub`` midpoints in (zenith, azimuth)
        weighted by ``cos(zen) sin(zen)`` (projected solid angle, the
        Monte Carlo's normalisation), with Stokes re-expressed in the bin's
        common frame (reference axis of the bin centre projected onto each
        sample's transverse plane, as the Monte Carlo does for every ray).
        ``stokes_options`` are passed to :meth:`stokes`.
        """
        if not (isinstance(sub, int) and sub >= 1):
            raise PihimInputError(f"sub must be an integer >= 1, got {sub!r}")
        nz, na = grid.shape
        step = math.radians(grid.step_deg)
        off = (np.arange(sub) + 0.5) / sub
        zen = (np.arange(nz)[:, None] + off[None, :]) * step  # (nz, sub)
        az = (np.arange(na)[:, None] + off[None, :]) * step  # (na, sub)
        zz = np.broadcast_to(zen[:, None, :, None], (nz, na, sub, sub))
        aa = np.broadcast_to(az[None, :, None, :], (nz, na, sub, sub))
        d = _direction(zz, aa)
        ec = grid.reference[:, :, None, None, :]
        e = normalize(ec - dot(ec, d)[..., None] * d)
        s, _ = self.stokes(d, sun_dir, sky, e, **stokes_options)
        w = np.cos(zz) * np.sin(zz)
        return np.sum(s * w[..., None], axis=(2, 3)) / np.sum(w, axis=(2, 3))[..., None]

    # -- Monte Carlo ----------------------------------------------------------
    def monte_carlo(
        self,
        sun_dir: ArrayLike,
        sky: SkyRadiance | None = None,
        *,
        n_facets: int = PAPER_N_FACETS,
        bin_deg: float = PAPER_BIN_DEG,
        seed: int = 0,
    ) -> MonteCarloResult:
        """The paper's Monte Carlo: ``n_facets`` microfacets reflect the light into angular bins.

        Each facet ``k`` (normal ``h_k`` from :meth:`sample_facets`, area
        ``a = 1 / (n_facets <cos alpha>)`` per unit ground area, so the
        facets tile the ground) reflects

        * the sunlight, flux ``E (h_k . l) a G`` times the Fresnel Mueller
          matrix applied to unpolarized light, into ``v_k = reflect(-l, h_k)``;
        * if ``sky`` is given, one sky ray from ``l_k`` drawn with density
          ``(h_k . l) / pi`` about ``h_k`` (cosine-weighted), flux
          ``pi a G L_sky(l_k)`` (Fresnel-reflected, polarization included),
          into ``reflect(-l_k, h_k)``.

        Each reflected Stokes vector is rotated from the facet's s/p basis
        into its bin's common frame (the bin centre's reference axis
        projected onto the plane normal to the ray) and summed into the bin
        ``floor(zen / bin_deg), floor(az / bin_deg)``. Radiance per bin =
        summed flux / projected solid angle of the bin (ground area 1 m^2);
        rays reflected below the horizon are lost. The diffuse part is added
        exactly (not sampled).

        Parameters
        ----------
        sun_dir : array_like, (3,)
            Unit vector toward the sun.
        sky : SkyRadiance, optional
            Sky radiance; None: sun only.
        n_facets : int
            Number of microfacets (>= 1); 100,000 in the paper.
        bin_deg : float
            Bin width, deg, dividing 90; 0.5 in the paper.
        seed : int
            Seed of :func:`numpy.random.default_rng`; equal seeds give equal
            results.

        Returns
        -------
        MonteCarloResult
        """
        sun = _sun_vector(sun_dir)
        _check_sky(sky)
        if isinstance(n_facets, bool) or not isinstance(n_facets, (int, np.integer)) or n_facets < 1:
            raise PihimInputError(f"n_facets must be an integer >= 1, got {n_facets!r}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise PihimInputError(f"seed must be a non-negative integer, got {seed!r}")
        _check_bin(bin_deg)
        grid = hemisphere_grid(bin_deg)
        n_facets = int(n_facets)
        rng = np.random.default_rng(int(seed))
        h = self.sample_facets(n_facets, rng)
        area = 1.0 / (n_facets * self._mean_cos)
        mueller = self._mueller()

        rays_idx, rays_flux, rays_facet = [], [], []
        if self.sun_irradiance > 0.0 and sun[2] > 0.0:
            c = h @ sun
            lit = np.nonzero(c > 0.0)[0]
            hl, cl = h[lit], c[lit]
            d_in = np.broadcast_to(-sun, hl.shape)
            s_in = np.zeros((lit.size, 4))
            s_in[:, 0] = self.sun_irradiance
            s_ref, d_ref, s_axis = reflect_stokes(s_in, d_in, perpendicular_reference(d_in), hl, mueller)
            g = _shadowing(hl[:, 2], d_ref[:, 2], np.full(cl.shape, sun[2]), cl) if self.include_shadowing else 1.0
            w = area * cl * g
            idx, flux = self._to_bins(grid, s_ref, d_ref, s_axis, w)
            rays_idx.append(idx)
            rays_flux.append(flux)
            rays_facet.append(lit)
        if sky is not None:
            l = _cosine_hemisphere(h, rng)
            s_sky, e_sky = sky.stokes(l, sun)
            s_ref, d_ref, s_axis = reflect_stokes(_stokes4(s_sky), -l, np.asarray(e_sky, float), h, mueller)
            c = dot(l, h)
            g = _shadowing(h[:, 2], d_ref[:, 2], l[:, 2], c) if self.include_shadowing else 1.0
            w = math.pi * area * g * (l[:, 2] > 0)
            idx, flux = self._to_bins(grid, s_ref, d_ref, s_axis, w)
            rays_idx.append(idx)
            rays_flux.append(flux)
            rays_facet.append(np.arange(n_facets))

        nbins = grid.shape[0] * grid.shape[1]
        total = np.zeros((nbins, 4))
        sumsq = np.zeros((nbins, 4))
        counts = np.zeros(nbins, dtype=np.int64)
        if rays_idx:
            idx = np.concatenate(rays_idx)
            flux = np.concatenate(rays_flux)
            facet = np.concatenate(rays_facet)
            keep = idx >= 0
            idx, flux, facet = idx[keep], flux[keep], facet[keep]
            counts = np.bincount(idx, minlength=nbins).astype(np.int64)
            # per-facet contribution to each bin (a facet's sun and sky rays may share a bin)
            key = facet.astype(np.int64) * nbins + idx
            ukey, inv = np.unique(key, return_inverse=True)
            per = np.zeros((ukey.size, 4))
            for k in range(4):
                per[:, k] = np.bincount(inv, weights=flux[:, k], minlength=ukey.size)
            ubin = ukey % nbins
            for k in range(4):
                total[:, k] = np.bincount(ubin, weights=per[:, k], minlength=nbins)
                sumsq[:, k] = np.bincount(ubin, weights=per[:, k] ** 2, minlength=nbins)
        var = np.maximum(sumsq - total**2 / n_facets, 0.0)
        omega = grid.projected_solid_angle.reshape(-1, 1)
        stokes = total / omega
        stderr = np.sqrt(var) / omega
        diffuse = self.diffuse_radiance(sun, sky)
        stokes[:, 0] += diffuse
        shape = grid.shape
        return MonteCarloResult(
            grid=grid,
            counts=counts.reshape(shape),
            stokes=stokes.reshape(shape + (4,)),
            stderr=stderr.reshape(shape + (4,)),
            n_facets=n_facets,
            seed=int(seed),
        )

    @staticmethod
    def _to_bins(grid, s_ref, d_ref, s_axis, w) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
        """Bin index of each ray and its flux Stokes in the bin's common frame."""
        idx = grid.locate(d_ref)
        up = idx >= 0
        flux = np.zeros_like(s_ref)
        if np.any(up):
            d = d_ref[up]
            ec = grid.reference.reshape(-1, 3)[idx[up]]
            e = normalize(ec - dot(ec, d)[:, None] * d)
            w_up = w[up] if np.ndim(w) else np.full(d.shape[0], w)
            flux[up] = w_up[:, None] * change_reference(s_ref[up], d, s_axis[up], e)
        return idx, flux


def _cosine_hemisphere(h: NDArray[np.float64], rng: np.random.Generator) -> NDArray[np.float64]:
    """One direction per normal ``h`` with density ``(h . l) / pi`` on the hemisphere about ``h``."""
    u1 = rng.random(h.shape[0])
    u2 = rng.random(h.shape[0])
    r = np.sqrt(u1)
    phi = 2.0 * math.pi * u2
    t1 = perpendicular_reference(h)  # any unit axis normal to h
    t2 = np.cross(h, t1)
    local_z = np.sqrt(np.maximum(1.0 - u1, 0.0))
    l = (r * np.cos(phi))[:, None] * t1 + (r * np.sin(phi))[:, None] * t2 + local_z[:, None] * h
    return normalize(l)
