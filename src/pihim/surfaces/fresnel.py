"""Fresnel amplitude coefficients and reflection Mueller matrices.

Refractive indices are complex ``N = n + i k`` with ``k >= 0`` for absorbing
media (the usual tabulated convention, e.g. silver near 550 nm has
``N ~ 0.06 + 3.6i``). Mitsuba writes the same medium as ``eta = n - i k``;
pass ``numpy.conj(N)`` when comparing with it.

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone", eqs. (5)-(7).
.. [2] M. Born, E. Wolf, *Principles of Optics*, 7th ed., Cambridge
   University Press, 1999, sec. 1.5.2 (Fresnel formulae) and 14.2
   (absorbing media).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.polarimetry.reflection import mueller_from_amplitudes


def _cos_transmitted(cos_i: NDArray, n1: NDArray, n2: NDArray) -> NDArray[np.complex128]:
    """Complex cosine of the refraction angle (branch with a decaying transmitted wave)."""
    sin2_t = (n1 / n2) ** 2 * (1.0 - cos_i**2)
    cos_t = np.sqrt(1.0 - sin2_t + 0j)
    # choose the root whose wave decays into medium 2: Im(n2 cos_t) >= 0
    flip = np.imag(n2 * cos_t) < 0
    return np.where(flip, -cos_t, cos_t)


def fresnel_amplitudes(
    cos_i: ArrayLike, n1: ArrayLike = 1.0, n2: ArrayLike = 1.5
) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    """Reflection amplitude coefficients ``(r_s, r_p)`` (paper eqs. 7 and 6).

    ``r_s = (n1 cos_i - n2 cos_t) / (n1 cos_i + n2 cos_t)`` (the paper's R_r),
    ``r_p = (n2 cos_i - n1 cos_t) / (n2 cos_i + n1 cos_t)`` (the paper's R_l),
    so that at normal incidence ``r_p = -r_s`` and a perfect conductor gives
    ``r_s = -1``, ``r_p = +1``.

    Parameters
    ----------
    cos_i : array_like
        Cosine of the angle of incidence, in [0, 1].
    n1, n2 : array_like (complex allowed)
        Refractive index of the incidence medium and of the reflecting medium.
    """
    cos_i = np.clip(np.asarray(cos_i, float), 0.0, 1.0)
    n1 = np.asarray(n1, dtype=complex)
    n2 = np.asarray(n2, dtype=complex)
    cos_t = _cos_transmitted(cos_i, n1, n2)
    r_s = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    r_p = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return r_s, r_p


def fresnel_reflectance(cos_i: ArrayLike, n1: ArrayLike = 1.0, n2: ArrayLike = 1.5) -> tuple[NDArray, NDArray]:
    """Intensity reflectances ``(R_s, R_p) = (|r_s|^2, |r_p|^2)``."""
    r_s, r_p = fresnel_amplitudes(cos_i, n1, n2)
    return np.abs(r_s) ** 2, np.abs(r_p) ** 2


def fresnel_reflection_mueller(cos_i: ArrayLike, n1: ArrayLike = 1.0, n2: ArrayLike = 1.5) -> NDArray[np.float64]:
    """Reflection Mueller matrix ``(..., 4, 4)`` of an n1 | n2 interface, s as the x axis.

    See :func:`pihim.polarimetry.reflection.mueller_from_amplitudes` for the
    matrix layout (paper eq. 5 with s and p swapped).
    """
    return mueller_from_amplitudes(*fresnel_amplitudes(cos_i, n1, n2))


def brewster_angle_deg(n1: float = 1.0, n2: float = 1.5) -> float:
    """Brewster angle ``atan(n2 / n1)`` in degrees (real indices)."""
    return float(np.degrees(np.arctan2(n2, n1)))
