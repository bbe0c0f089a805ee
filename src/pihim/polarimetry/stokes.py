"""Linear Stokes parameters: DoLP, AoP, construction and frame rotation.

All functions are pure and vectorised: they accept scalars or arrays of any
(broadcast-compatible) shape, one array per Stokes component.

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone", eqs. (1)-(3).
.. [2] D. Goldstein, *Polarized Light*, 3rd ed., CRC Press, 2011, ch. 4-5
   (Stokes parameters and the Mueller rotator).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError


def dolp(s0: ArrayLike, s1: ArrayLike, s2: ArrayLike) -> NDArray[np.floating]:
    """Degree of linear polarization, ``sqrt(S1^2 + S2^2) / S0`` (paper eq. 3).

    Parameters
    ----------
    s0, s1, s2 : array_like
        Stokes components (any consistent intensity unit).

    Returns
    -------
    numpy.ndarray
        DoLP, dimensionless; NaN where ``S0 <= 0``.
    """
    s0 = np.asarray(s0)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.hypot(s1, s2) / s0
    return np.where(s0 > 0, out, np.nan)


def aop_deg(s1: ArrayLike, s2: ArrayLike) -> NDArray[np.floating]:
    """Angle of polarization ``0.5 * atan2(S2, S1)`` in degrees, folded into [0, 180).

    The angle is measured from the frame's reference axis, counter-clockwise
    when looking into the beam (for images: from image right toward image up).
    Paper eq. (2), with the quadrant resolved by ``atan2``.
    """
    a = 0.5 * np.degrees(np.arctan2(s2, s1))
    a = np.mod(a, 180.0)
    # np.mod can return exactly 180.0 for tiny negative inputs
    return np.where(a >= 180.0, 0.0, a)


def stokes_from_dolp_aop(
    s0: ArrayLike, dolp_: ArrayLike, aop_deg_: ArrayLike
) -> tuple[NDArray[np.floating], NDArray[np.floating], NDArray[np.floating]]:
    """Build ``(S0, S1, S2)`` from intensity, DoLP and AoP in degrees.

    Raises
    ------
    PihimInputError
        A negative intensity or a DoLP outside [0, 1] (beyond 1e-9 of it):
        no light has them (NaN passes through, as a missing value).
    """
    s0 = np.asarray(s0, dtype=float)
    p = np.asarray(dolp_, dtype=float)
    if np.any(s0 < 0):
        raise PihimInputError(f"s0 must be >= 0 (an intensity), got values such as {s0[s0 < 0].ravel()[0]:g}")
    bad = (p < -1e-9) | (p > 1.0 + 1e-9)
    if np.any(bad):
        raise PihimInputError(f"dolp must lie in [0, 1], got values such as {p[bad].ravel()[0]:g}")
    two_a = 2.0 * np.radians(aop_deg_)
    s1 = s0 * p * np.cos(two_a)
    s2 = s0 * p * np.sin(two_a)
    s0, s1, s2 = np.broadcast_arrays(s0, s1, s2)
    return s0.copy(), s1.copy(), s2.copy()


def rotate_reference_deg(
    s1: ArrayLike, s2: ArrayLike, angle_deg: ArrayLike
) -> tuple[NDArray[np.floating], NDArray[np.floating]]:
    """Express (S1, S2) in a reference frame whose axis is rotated by ``angle_deg``.

    The new reference axis is the old one rotated counter-clockwise (looking
    into the beam) by ``angle_deg``. The light is unchanged, so its AoP in
    the new frame is ``AoP - angle_deg`` (mod 180) and DoLP is preserved.
    This is the Mueller rotator ``[[c, s], [-s, c]]`` with ``c = cos 2t``,
    ``s = sin 2t`` acting on (S1, S2) [2]_.
    """
    two_t = 2.0 * np.radians(angle_deg)
    c, s = np.cos(two_t), np.sin(two_t)
    s1 = np.asarray(s1, dtype=float)
    s2 = np.asarray(s2, dtype=float)
    return c * s1 + s * s2, -s * s1 + c * s2


def aop_difference_deg(aop_a_deg: ArrayLike, aop_b_deg: ArrayLike) -> NDArray[np.floating]:
    """Axial AoP difference: the smallest angle between two orientations, in [0, 90].

    AoP is an orientation (axial, period 180 deg), so 5 deg and 175 deg differ
    by 10 deg. This is the separability measure used for the ground-vs-ground
    criterion; see :func:`aop_raw_difference_deg` for the paper's Table 1 form.
    """
    d = np.mod(np.asarray(aop_a_deg, dtype=float) - np.asarray(aop_b_deg, dtype=float), 180.0)
    return np.minimum(d, 180.0 - d)


def aop_raw_difference_deg(aop_a_deg: ArrayLike, aop_b_deg: ArrayLike) -> NDArray[np.floating]:
    """Raw absolute AoP difference ``|a - b|`` of angles in [0, 180), in [0, 180).

    This is how the paper's Table 1 reports differences (values above 90 deg
    occur); prefer :func:`aop_difference_deg` for thresholds. Angles outside
    [0, 180) are first taken modulo 180 (AoP's period): 350 deg is 170 deg.
    """
    a = np.mod(np.asarray(aop_a_deg, dtype=float), 180.0)
    b = np.mod(np.asarray(aop_b_deg, dtype=float), 180.0)
    a, b = np.where(a >= 180.0, 0.0, a), np.where(b >= 180.0, 0.0, b)  # np.mod(-1e-20, 180) rounds to 180
    return np.abs(a - b)
