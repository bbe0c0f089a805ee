"""The Berry-Dennis-Lee four-neutral-point model of clear-sky polarization.

Single (Rayleigh) scattering gives two unpolarized points, at the sun and
the antisun, each an unstable singularity of index +1. Multiple scattering
splits each into a pair of index +1/2 singularities -- the Babinet point
above the sun and the Brewster point below it, the Arago point above the
antisun and the "fourth" point below it -- which Berry, Dennis and Lee
describe with one complex function on the stereographic projection of the
sky [1]_:

* Sky direction -> complex number by stereographic projection from the
  nadir: zenith at 0, horizon on the unit circle, antipode
  ``-1/conj(zeta)`` [1]_ sec. 2 (written there with the azimuth as the
  argument, ``tan(Z/2) exp(i A)``). pihim writes it in ENU components,
  ``zeta = (x + i y) / (1 + z) = tan(Z/2) exp(i (90 deg - A))`` (real axis
  East, imaginary axis North): a mirror image of the azimuthal form, which
  changes nothing physical because every orientation is mapped back to 3-D
  vectors below rather than read off as an angle.
* The polarization is the complex field ``w = <(E_x + i E_y)^2>`` [1]_
  eq. (2.1): ``arg(w)/2`` is the orientation of the E-field in the
  ``zeta`` plane and ``|w|`` the polarized intensity.
* Splitting: each singularity of a pair lies ``delta/2`` from the sun
  (antisun) along the sun's vertical, ``delta = 4 arctan A`` being Berry's
  pairwise separation [1]_ eqs. (2.4), (2.6). pihim's parameter
  ``separation_deg`` is the angular distance of *each* neutral point from the
  sun (or antisun), i.e. ``delta / 2``.
* The normalized field with the four zeros ``zeta_Ba`` (Babinet),
  ``zeta_Br`` (Brewster) and their antipodes [1]_ eq. (4.2):

  .. math::

      w(\\zeta) = \\frac{-4 (\\zeta - \\zeta_{Br})(\\zeta - \\zeta_{Ba})
          (\\zeta + 1/\\zeta_{Br}^*)(\\zeta + 1/\\zeta_{Ba}^*)}
          {(1 + |\\zeta|^2)^2\\, |\\zeta_{Br} + 1/\\zeta_{Br}^*|\\,
          |\\zeta_{Ba} + 1/\\zeta_{Ba}^*|}.

pihim evaluates eq. (4.2) pair by pair as
``f_n(zeta) = (zeta - zeta_n)(1 + conj(zeta_n) zeta) / (1 + |zeta_n|^2)``,
which equals ``(zeta - zeta_n)(zeta - zeta_n')/(zeta_n - zeta_n')`` for the
antipode ``zeta_n' = -1/conj(zeta_n)``: no pole when a neutral point passes
the zenith, and the pair normalisation is complex rather than a modulus.
That complex normalisation is what makes the pattern turn with the sun
(rotating the scene by ``b`` about the vertical rotates every AoP by ``b``):
with moduli, as printed, ``w`` picks up a spurious ``exp(2 i A_sun)``, which
the OpenSky implementation removes by hand [2]_. Then

* ``|w| = sin(g_Ba) sin(g_Br)`` exactly, ``g_n`` being the angular distance
  of the view direction from neutral point ``n`` (Brewster's 1847 product
  formula quoted in [1]_ sec. 4): 0 at the four neutral points, and
  ``sin^2 g`` of Rayleigh theory when the separation is 0.
* ``DoLP = d_max |w| / (2 - |w|)``: the conversion used by OpenSky [2]_. It
  is exactly Rayleigh's ``sin^2 g / (1 + cos^2 g)`` when the separation is
  0, and it is 0 exactly at the neutral points. (Berry et al. report ``|w|``
  itself, an unnormalised polarized intensity.)
* Known limitation, as in [1]_ sec. 4: eq. (4.2) puts the polarization
  maxima on the horizon; the paper's ad-hoc horizon function is not applied.

The Stokes vectors are formed without trigonometry: with ``P`` the unit
tangent at ``v`` along the image of the real ``zeta`` axis and the frame
``(d = -v, e)``, ``S1 + i S2 = S0 d_max conj(w) pe^2 / (2 - |w|)`` where
``pe = P.e + i P.(d x e)`` (the inverse projection is conformal; the
conjugate appears because ``(e, d x e)`` turns the other way round ``v``
from ``(P, Q)``). Tests check the separation-0 limit against the independent
vector formula of :mod:`pihim.sky.rayleigh`.

References
----------
.. [1] M. V. Berry, M. R. Dennis, R. L. Lee Jr, "Polarization singularities
   in the clear sky", New J. Phys. 6, 162 (2004),
   doi:10.1088/1367-2630/6/1/162.
.. [2] A. Moutenet, L. Poughon, B. Toulon, J. R. Serres, S. Viollet,
   "OpenSky: a modular and open-source simulator of sky polarization
   measurements", IEEE Trans. Instrum. Meas. 73 (2024),
   doi:10.1109/TIM.2024.3374965.
.. [3] G. Horvath, D. Varju, *Polarized Light in Animal Vision*, Springer,
   2004, ch. 4-5: observed Babinet/Brewster/Arago distances of about
   10-25 deg from the sun or antisun.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError
from pihim.sky.rayleigh import pack_stokes, stokes_in_frame

__all__ = ["NeutralPoints", "berry_components", "berry_core", "berry_stokes", "berry_w", "neutral_points"]

_UP = np.array([0.0, 0.0, 1.0])
_NORTH = np.array([0.0, 1.0, 0.0])

#: Largest accepted neutral-point distance from the sun, degrees.
MAX_SEPARATION_DEG = 45.0


@dataclass(frozen=True)
class NeutralPoints:
    """Unit ENU vectors of the four neutral points (arrays broadcast like the sun vector).

    ``babinet`` lies ``separation`` above the sun along its vertical (toward
    the zenith), ``brewster`` the same distance below it; ``arago`` is the
    antipode of ``brewster`` (above the antisun) and ``fourth`` the antipode
    of ``babinet`` (below the antisun).
    """

    babinet: NDArray[np.float64]
    brewster: NDArray[np.float64]
    arago: NDArray[np.float64]
    fourth: NDArray[np.float64]


def _check_separation(separation_deg: float) -> float:
    sep = float(separation_deg)
    if not (np.isfinite(sep) and 0.0 <= sep <= MAX_SEPARATION_DEG):
        raise PihimInputError(
            f"neutral-point separation must be in [0, {MAX_SEPARATION_DEG:g}] deg, got {separation_deg!r}"
        )
    return sep


def neutral_points(sun_dir: ArrayLike, separation_deg: float) -> NeutralPoints:
    """Neutral points ``separation_deg`` above and below the sun (and antisun) on the sun's vertical.

    The sun's vertical is the great circle through the sun and the zenith;
    "above" is toward the zenith, continuing past it when the separation
    exceeds the sun's zenith angle. For a sun exactly at the zenith the
    North-South meridian is used (Babinet toward North).
    """
    sep_rad = np.radians(_check_separation(separation_deg))
    s = np.asarray(sun_dir, dtype=float)
    s = s / np.linalg.norm(s, axis=-1, keepdims=True)
    up = _UP - s[..., 2:3] * s
    norm = np.linalg.norm(up, axis=-1, keepdims=True)
    weak = norm < 1e-12
    up = np.where(weak, _NORTH - s[..., 1:2] * s, up)
    up = up / np.linalg.norm(up, axis=-1, keepdims=True)
    babinet = np.cos(sep_rad) * s + np.sin(sep_rad) * up
    brewster = np.cos(sep_rad) * s - np.sin(sep_rad) * up
    return NeutralPoints(babinet=babinet, brewster=brewster, arago=-brewster, fourth=-babinet)


def _zeta(v: NDArray[np.float64]) -> NDArray[np.complex128]:
    """Stereographic coordinate ``(x + i y)/(1 + z)`` (projection from the nadir)."""
    den = 1.0 + v[..., 2]
    den = np.where(den > 1e-15, den, 1e-15)
    return (v[..., 0] + 1j * v[..., 1]) / den


def _pair_factor(zeta: NDArray[np.complex128], zn: NDArray[np.complex128]) -> NDArray[np.complex128]:
    """``(zeta - zn)(1 + conj(zn) zeta)/(1 + |zn|^2)``: a neutral point and its antipode."""
    return (zeta - zn) * (1.0 + np.conj(zn) * zeta) / (1.0 + (zn * np.conj(zn)).real)


def berry_w(view_dirs: ArrayLike, sun_dir: ArrayLike, separation_deg: float) -> NDArray[np.complex128]:
    """Berry's normalized complex polarization field ``w`` (eq. 4.2) at ENU sky directions.

    ``|w| = sin(g_Ba) sin(g_Br)`` in [0, 1]; ``arg(w)/2`` is the E-field
    orientation in the ``zeta = (x + i y)/(1 + z)`` plane, counted from the
    real (East-at-zenith) axis toward the imaginary (North) axis.
    """
    v = np.asarray(view_dirs, dtype=float)
    npts = neutral_points(sun_dir, separation_deg)
    zeta = _zeta(v)
    one_plus_z = 1.0 + v[..., 2]
    # (1 + |zeta|^2)^2 = 4 / (1 + z)^2, so -4 / (1 + |zeta|^2)^2 = -(1 + z)^2
    return -(one_plus_z**2) * _pair_factor(zeta, _zeta(npts.babinet)) * _pair_factor(zeta, _zeta(npts.brewster))


def berry_stokes(
    view_dirs: ArrayLike,
    sun_dir: ArrayLike,
    e: ArrayLike | None = None,
    *,
    separation_deg: float = 15.0,
    dmax: float = 1.0,
    s0: ArrayLike = 1.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Stokes vectors of skylight arriving from ``view_dirs`` in the Berry-Dennis-Lee model.

    Parameters
    ----------
    view_dirs : array_like, shape (..., 3)
        Unit ENU vectors from the observer toward the sky; the light travels
        along ``d = -view_dirs``.
    sun_dir : array_like, shape (3,) or broadcastable
        Unit ENU vector toward the sun.
    e : array_like, shape (..., 3), optional
        Reference axes (perpendicular to ``view_dirs``); default the local
        meridian "up" (:func:`pihim.sky.rayleigh.prepare_frame`).
    separation_deg : float
        Angular distance of each neutral point from the sun / antisun,
        degrees, in [0, 45]; 0 gives the Rayleigh pattern exactly.
    dmax : float
        Scale of the DoLP, ``DoLP = dmax |w| / (2 - |w|)``.
    s0 : array_like
        Total intensity S0.

    Returns
    -------
    stokes : numpy.ndarray, shape (..., 4)
        ``(S0, S1, S2, 0)`` in the frame ``(d, e)``.
    e : numpy.ndarray, shape (..., 3)
        The reference axes used.

    Notes
    -----
    Valid on the whole sphere except exactly at the nadir;
    :class:`pihim.sky.model.SkyModel` zeroes everything below the horizon.
    """
    _check_separation(separation_deg)
    return stokes_in_frame(berry_components, view_dirs, sun_dir, e, separation_deg, dmax, s0)


def berry_components(
    v: NDArray[np.float64],
    s: NDArray[np.float64],
    e_arr: NDArray[np.float64],
    f: NDArray[np.float64],
    separation_deg: float,
    dmax: float,
    s0: ArrayLike,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Berry ``(S0, S1, S2)`` as separate arrays for prepared unit vectors (no validation)."""
    w = berry_w(v, s, separation_deg)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    den = 1.0 + z
    k = 1.0 / np.where(den > 1e-15, den, 1e-15)
    # unit tangent along the image of the real zeta axis: (1 - x^2 k, -x y k, -x)
    px, py, pz = 1.0 - x * x * k, -x * y * k, -x
    pe = (px * e_arr[..., 0] + py * e_arr[..., 1] + pz * e_arr[..., 2]) + 1j * (
        px * f[..., 0] + py * f[..., 1] + pz * f[..., 2]
    )
    absw = np.abs(w)
    s0 = np.broadcast_to(np.asarray(s0, dtype=float), absw.shape)
    lin = (s0 * dmax / (2.0 - absw)) * (pe * pe * np.conj(w))
    return s0, lin.real, lin.imag


def berry_core(
    v: NDArray[np.float64],
    s: NDArray[np.float64],
    e_arr: NDArray[np.float64],
    f: NDArray[np.float64],
    separation_deg: float,
    dmax: float,
    s0: ArrayLike,
) -> NDArray[np.float64]:
    """Berry Stokes ``(..., 4)`` for prepared unit vectors (no validation; see :func:`berry_stokes`)."""
    return pack_stokes(*berry_components(v, s, e_arr, f, separation_deg, dmax, s0))
