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

from pihim.errors import PihimInputError
from pihim.polarimetry.reflection import mueller_from_amplitudes


def _as_cos(cos_i: ArrayLike) -> NDArray[np.float64]:
    """``cos_i`` as a float array in [0, 1] (NaN kept; clearly out-of-range values refused).

    Rounding may put a cosine computed from unit vectors a hair outside
    [0, 1]; it is clipped. A value beyond 1e-9 of the range is a mistake (an
    angle in degrees, a cosine of the wrong sign) and is refused.
    """
    c = np.asarray(cos_i, dtype=float)
    bad = np.isfinite(c) & ((c < -1e-9) | (c > 1.0 + 1e-9))
    if np.any(bad):
        raise PihimInputError(f"cos_i must lie in [0, 1], got values such as {c[bad].ravel()[0]:g}")
    return np.clip(c, 0.0, 1.0)


def _cos_transmitted(cos_i: NDArray, n1: NDArray, n2: NDArray) -> NDArray[np.complex128]:
    """Complex cosine of the refraction angle (branch with a decaying transmitted wave)."""
    ratio2 = (n1 / n2) ** 2
    # 1 - ratio2 * sin^2_i, arranged to avoid cancellation near grazing incidence when n1 ~ n2
    cos_t = np.sqrt((1.0 - ratio2) + ratio2 * cos_i**2 + 0j)
    # choose the root whose wave decays into medium 2: Im(n2 cos_t) >= 0
    flip = np.imag(n2 * cos_t) < 0
    return np.where(flip, -cos_t, cos_t)


def _check_indices(n1: NDArray[np.complex128], n2: NDArray[np.complex128]) -> None:
    """Refuse indices outside the ``n + i k`` convention (``n >= 0``, ``k >= 0``) with a one-line error."""
    for name, n in (("n1", n1), ("n2", n2)):
        if np.any(n.imag < 0.0):
            bad = complex(n.flat[int(np.argmax(n.imag < 0.0))])
            raise PihimInputError(
                f"{name} = {bad} has k < 0: pihim writes N = n + ik with k >= 0 (silver ~ 0.06+3.6j); "
                "for mitsuba's eta = n - ik pass numpy.conj(eta)"
            )
        if np.any(~(n.real >= 0.0)) or np.any(n == 0):
            raise PihimInputError(f"{name}: a refractive index needs n >= 0 and N != 0, got {n}")


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
        Cosine of the angle of incidence, in [0, 1] (a rounding error's worth
        outside is clipped; more is refused).
    n1, n2 : array_like (complex allowed)
        Refractive index ``n + i k`` of the incidence medium and of the
        reflecting medium: ``n >= 0``, ``k >= 0`` (absorbing media), not 0.

    Raises
    ------
    PihimInputError
        An index with ``k < 0`` (the ``n - i k`` form, e.g. mitsuba's: pass
        its complex conjugate), a negative real part or 0. With ``k < 0`` the
        formulae give a wave growing into the medium and reflectances above 1.
        A ``cos_i`` outside [0, 1] (an angle in degrees passed by mistake).
    """
    cos_i = _as_cos(cos_i)
    n1 = np.asarray(n1, dtype=complex)
    n2 = np.asarray(n2, dtype=complex)
    _check_indices(n1, n2)
    cos_t = _cos_transmitted(cos_i, n1, n2)
    with np.errstate(divide="ignore", invalid="ignore"):
        r_s = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
        r_p = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    # matched indices: no interface, no reflection (also the limit at grazing incidence, where both are 0/0)
    same = np.asarray(n1) == np.asarray(n2)
    return np.where(same, 0.0, r_s), np.where(same, 0.0, r_p)


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


def brewster_angle_deg(n1: float, n2: float) -> float:
    """Brewster angle ``atan(n2 / n1)`` in degrees, for light in medium ``n1`` meeting medium ``n2``.

    Both indices are required, incidence medium first: glass seen from air is
    ``brewster_angle_deg(1.0, 1.5)`` = 56.3 deg (a single index used to be
    taken as ``n1``, silently returning 45 deg for ``brewster_angle_deg(1.5)``).

    Parameters
    ----------
    n1 : float
        Real refractive index of the medium the light comes from (air: 1.0).
    n2 : float
        Real refractive index of the reflecting medium.

    Raises
    ------
    PihimInputError
        An index that is not a finite real number > 0.
    """
    for name, n in (("n1", n1), ("n2", n2)):
        if isinstance(n, (bool, complex)) or not isinstance(n, (int, float, np.integer, np.floating)) \
                or not np.isfinite(n) or n <= 0:
            raise PihimInputError(f"brewster_angle_deg: {name} must be a finite real index > 0, got {n!r}")
    return float(np.degrees(np.arctan2(n2, n1)))


# --------------------------------------------------------------------------
# Transmission (used by the second-surface heliostat mirror)
# --------------------------------------------------------------------------



def fresnel_transmission_amplitudes(
    cos_i: ArrayLike, n1: ArrayLike = 1.0, n2: ArrayLike = 1.5
) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    """Transmission amplitude coefficients ``(t_s, t_p)`` of an n1 | n2 interface.

    Born & Wolf sec. 1.5.2, eqs. (20)::

        t_s = 2 n1 cos_i / (n1 cos_i + n2 cos_t)
        t_p = 2 n1 cos_i / (n2 cos_i + n1 cos_t)

    They pair with :func:`fresnel_amplitudes` (same time convention
    ``exp(-i omega t)``, same branch of ``cos_t``): ``t_s = 1 + r_s`` and
    ``(n2 / n1) t_p = 1 + r_p``. In the s/p frames of
    :mod:`pihim.polarimetry.reflection` (``p = d x s`` for the incident and
    for the refracted direction), ``t_s`` and ``t_p`` are positive for
    dielectrics below the critical angle: refraction does not flip the field.

    Parameters
    ----------
    cos_i : array_like
        Cosine of the angle of incidence in medium 1, in [0, 1] (a rounding error's worth outside is
        clipped; more is refused).
    n1, n2 : array_like (complex allowed)
        Refractive indices of the incidence medium and of the medium entered.
        Beyond the critical angle (``n1 > n2``) the amplitudes describe the
        evanescent wave; no power is transmitted (see
        :func:`fresnel_transmission_mueller`).

    Returns
    -------
    t_s, t_p : complex ndarray
        Ratios of transmitted to incident field amplitude (dimensionless).

    References
    ----------
    .. [1] M. Born, E. Wolf, *Principles of Optics*, 7th ed., 1999,
       sec. 1.5.2, eqs. (20) and (21).
    """
    cos_i = _as_cos(cos_i)
    n1 = np.asarray(n1, dtype=complex)
    n2 = np.asarray(n2, dtype=complex)
    cos_t = _cos_transmitted(cos_i, n1, n2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_s = 2.0 * n1 * cos_i / (n1 * cos_i + n2 * cos_t)
        t_p = 2.0 * n1 * cos_i / (n2 * cos_i + n1 * cos_t)
    same = n1 == n2  # no interface: the field passes unchanged (the limit at grazing incidence too)
    return np.where(same, 1.0 + 0j, t_s), np.where(same, 1.0 + 0j, t_p)


def fresnel_transmission_mueller(cos_i: ArrayLike, n1: ArrayLike = 1.0, n2: ArrayLike = 1.5) -> NDArray[np.float64]:
    """Transmission Mueller matrix ``(..., 4, 4)`` of an n1 | n2 interface, s as the x axis.

    Power (flux) transmission: the amplitude Mueller matrix of ``(t_s, t_p)``
    (layout of :func:`pihim.polarimetry.reflection.mueller_from_amplitudes`)
    times the beam-area and impedance factor ``eta = Re(n2 cos_t) / (n1 cos_i)``
    (Born & Wolf sec. 1.5.3), so that for lossless dielectrics
    ``R_s + T_s = 1`` and ``R_p + T_p = 1`` with ``T_s = M00 + M01`` and
    ``T_p = M00 - M01``. Beyond the critical angle ``cos_t`` is imaginary and
    the matrix is zero (total internal reflection).

    This is a flux ratio, not a radiance ratio: radiance inside medium 2 is
    a further ``(n2 / n1)**2`` higher (solid-angle compression); the factor
    cancels on any path that leaves through the same kind of interface,
    such as the glass of a second-surface mirror.

    Parameters
    ----------
    cos_i : array_like
        Cosine of the angle of incidence in medium 1, in [0, 1] (a rounding error's worth outside is
        clipped; more is refused).
    n1, n2 : array_like
        Real refractive indices (non-absorbing media; absorption in a slab is
        handled separately with Beer-Lambert, see
        :class:`pihim.surfaces.mirror.SecondSurfaceMirror`).

    Raises
    ------
    pihim.errors.PihimInputError
        If an index has a non-zero imaginary part or is not positive: the
        transmitted power into an absorbing medium is not a property of the
        interface alone.

    References
    ----------
    .. [1] M. Born, E. Wolf, *Principles of Optics*, 7th ed., 1999,
       sec. 1.5.3 (reflectivity and transmissivity).
    """
    n1c = np.asarray(n1, dtype=complex)
    n2c = np.asarray(n2, dtype=complex)
    for name, n in (("n1", n1c), ("n2", n2c)):
        if np.any(n.imag != 0.0) or np.any(~(n.real > 0.0)):
            raise PihimInputError(f"fresnel_transmission_mueller needs real positive indices, got {name}={n}")
    cos_i = _as_cos(cos_i)
    cos_t = _cos_transmitted(cos_i, n1c, n2c)
    # sqrt(eta) * t without dividing by cos_i (stable at grazing incidence):
    # sqrt(eta) * 2 n1 cos_i = 2 sqrt(n1 cos_i Re(n2 cos_t))
    num = 2.0 * np.sqrt(n1c.real * cos_i * np.clip(np.real(n2c * cos_t), 0.0, None))
    return mueller_from_amplitudes(num / (n1c * cos_i + n2c * cos_t), num / (n2c * cos_i + n1c * cos_t))
