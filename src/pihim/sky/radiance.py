"""Relative sky radiance: the CIE standard general sky (CIE S 011/E:2003, ISO 15469:2004).

The standard gives the luminance of a sky element, relative to the zenith,
as the product of a *gradation* function of the element's zenith angle ``Z``
and an *indicatrix* function of its angular distance ``chi`` from the sun:

.. math::

    \\varphi(Z) = 1 + a \\exp\\left(\\frac{b}{\\cos Z}\\right), \\qquad
    \\varphi(\\pi/2) = 1,

    f(\\chi) = 1 + c\\left[\\exp(d\\,\\chi) - \\exp\\left(d\\,\\frac{\\pi}{2}\\right)\\right]
               + e \\cos^2 \\chi,

    \\frac{L(Z, \\chi)}{L_z} = \\frac{f(\\chi)\\, \\varphi(Z)}{f(Z_s)\\, \\varphi(0)},

with ``Z_s`` the solar zenith angle (the zenith's distance from the sun) and
``chi`` in radians inside the exponential. pihim's default is type 12,
"CIE standard clear sky, low luminance turbidity": gradation group V
(``a = -1``, ``b = -0.32``) and indicatrix group 4 (``c = 10``, ``d = -3``,
``e = 0.45``).

The standard describes visible *luminance*; pihim uses it as the relative
broadband radiance (S0) of the skylight. That is an approximation: the real
sky is bluer and relatively darker toward the zenith than the photopic
distribution, but the DoLP and AoP maps do not depend on S0.

References
----------
.. [1] CIE S 011/E:2003 / ISO 15469:2004(E), "Spatial distribution of
   daylight -- CIE standard general sky", CIE Central Bureau, Vienna.
.. [2] R. Kittler, S. Darula, R. Perez, "A set of standard skies
   characterizing daylight conditions for computer and energy conscious
   design", Final report ACE-US Bratislava (1998); S. Darula, R. Kittler,
   "CIE general sky standard defining luminance distributions", Proc. eSim
   2002, Montreal -- the 15 types and their parameter groups.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError

__all__ = [
    "CIE_SKY_TYPES",
    "CLEAR_SKY_TYPE",
    "cie_parameters",
    "cie_relative_radiance",
    "gradation",
    "indicatrix",
]

#: Gradation groups I-VI of CIE S 011: (a, b).
_GRADATION = {1: (4.0, -0.70), 2: (1.1, -0.8), 3: (0.0, -1.0), 4: (-1.0, -0.55), 5: (-1.0, -0.32), 6: (-1.0, -0.15)}
#: Indicatrix groups 1-6 of CIE S 011: (c, d, e).
_INDICATRIX = {
    1: (0.0, -1.0, 0.0),
    2: (2.0, -1.5, 0.15),
    3: (5.0, -2.5, 0.30),
    4: (10.0, -3.0, 0.45),
    5: (16.0, -3.0, 0.30),
    6: (24.0, -2.8, 0.15),
}
#: The 15 standard sky types as (gradation group, indicatrix group).
_TYPES = {
    1: (1, 1), 2: (1, 2), 3: (2, 1), 4: (2, 2), 5: (3, 1), 6: (3, 2), 7: (3, 3), 8: (3, 4),
    9: (4, 2), 10: (4, 3), 11: (4, 4), 12: (5, 4), 13: (5, 5), 14: (6, 5), 15: (6, 6),
}  # fmt: skip

#: ``{type: (a, b, c, d, e)}`` for the 15 CIE standard general skies.
CIE_SKY_TYPES: dict[int, tuple[float, float, float, float, float]] = {
    t: (*_GRADATION[g], *_INDICATRIX[i]) for t, (g, i) in _TYPES.items()
}
#: CIE standard clear sky, low luminance turbidity.
CLEAR_SKY_TYPE = 12


def cie_parameters(sky_type: int) -> tuple[float, float, float, float, float]:
    """``(a, b, c, d, e)`` of CIE standard general sky ``sky_type`` (1-15)."""
    if isinstance(sky_type, bool) or not isinstance(sky_type, (int, np.integer)) or sky_type not in CIE_SKY_TYPES:
        raise PihimInputError(f"CIE sky type must be an integer 1-15, got {sky_type!r}")  # (12.5 was read as 12)
    return CIE_SKY_TYPES[int(sky_type)]


def gradation(zenith_deg: ArrayLike, a: float, b: float) -> NDArray[np.float64]:
    """CIE gradation function ``phi(Z) = 1 + a exp(b / cos Z)``; 1 at and below the horizon.

    Parameters
    ----------
    zenith_deg : array_like
        Zenith angle of the sky element, degrees.
    a, b : float
        Gradation parameters (``b < 0`` for all standard types).
    """
    cos_z = np.cos(np.radians(np.asarray(zenith_deg, dtype=float)))
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        g = 1.0 + a * np.exp(b / cos_z)
    return np.where(cos_z > 0.0, g, 1.0)


def indicatrix(chi_deg: ArrayLike, c: float, d: float, e: float) -> NDArray[np.float64]:
    """CIE scattering indicatrix ``f(chi) = 1 + c [exp(d chi) - exp(d pi/2)] + e cos^2 chi``.

    Parameters
    ----------
    chi_deg : array_like
        Angular distance from the sun, degrees (radians inside the formula).
    c, d, e : float
        Indicatrix parameters.
    """
    chi_rad = np.radians(np.asarray(chi_deg, dtype=float))
    return 1.0 + c * (np.exp(d * chi_rad) - np.exp(d * np.pi / 2.0)) + e * np.cos(chi_rad) ** 2


def cie_relative_radiance(
    view_dirs: ArrayLike, sun_dir: ArrayLike, sky_type: int = CLEAR_SKY_TYPE
) -> NDArray[np.float64]:
    """Sky radiance relative to the zenith, ``L / L_z``, for ENU sky directions.

    Parameters
    ----------
    view_dirs : array_like, shape (..., 3)
        Unit vectors from the observer toward the sky elements.
    sun_dir : array_like, shape (3,) or broadcastable (..., 3)
        Unit vector toward the sun.
    sky_type : int
        CIE standard general sky type, 1-15 (default 12, clear sky).

    Returns
    -------
    numpy.ndarray, shape (...)
        ``f(chi) phi(Z) / (f(Z_s) phi(0))``, dimensionless; 0 for directions
        below the horizon (``z < 0``).
    """
    a, b, c, d, e = cie_parameters(sky_type)
    v = np.asarray(view_dirs, dtype=float)
    s = np.asarray(sun_dir, dtype=float)
    cos_z = v[..., 2]
    cos_chi = np.clip(np.sum(v * s, axis=-1), -1.0, 1.0)
    cos_zs = np.clip(s[..., 2], -1.0, 1.0)
    chi_rad = np.arccos(cos_chi)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        phi = np.where(cos_z > 0.0, 1.0 + a * np.exp(b / cos_z), 1.0)
    f = 1.0 + c * (np.exp(d * chi_rad) - np.exp(d * np.pi / 2.0)) + e * cos_chi**2
    f_zenith = 1.0 + c * (np.exp(d * np.arccos(cos_zs)) - np.exp(d * np.pi / 2.0)) + e * cos_zs**2
    phi_zenith = 1.0 + a * np.exp(b)
    return np.where(cos_z >= 0.0, f * phi / (f_zenith * phi_zenith), 0.0)
