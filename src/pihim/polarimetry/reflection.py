"""Specular reflection of Stokes vectors in 3-D, each in its own s/p basis.

Every reflection is evaluated in the basis of its plane of incidence:
``s = normalize(d_in x n)`` (perpendicular to the plane of incidence) is the
reference axis -- the **x axis of the Mueller matrix** -- for both the
incident and the reflected beam, and ``p = d x s`` completes each frame. In
these frames a perfect conductor has amplitude coefficients ``r_s = -1``,
``r_p = +1``, the Fresnel sign convention of the paper's eqs. (6)-(7).
Incoming Stokes are rotated into that basis, multiplied by the reflection
Mueller matrix, and returned with the basis they are in, so that callers can
rotate them into any other frame with
:func:`pihim.polarimetry.frames.change_reference`.

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone", eqs. (4)-(7).
.. [2] R. A. Chipman, W. S. T. Lam, G. Young, *Polarized Light and Optical
   Systems*, CRC Press, 2018, sec. 8.3 (Mueller matrices for reflection and
   refraction in the s/p basis).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.polarimetry.frames import apply, change_reference, dot, normalize

MuellerFunction = Callable[[NDArray[np.float64]], NDArray[np.float64]]


def mueller_from_amplitudes(r_s: ArrayLike, r_p: ArrayLike) -> NDArray[np.float64]:
    """Mueller matrix ``(..., 4, 4)`` of an interface with complex amplitude coefficients.

    Basis: s is the x axis (``S1 > 0`` = field perpendicular to the plane of
    incidence). With ``A = (|r_s|^2 + |r_p|^2)/2``, ``B = (|r_s|^2 - |r_p|^2)/2``,
    ``C = Re(r_s r_p*)``, ``D = Im(r_s r_p*)``::

        [[A, B, 0, 0],
         [B, A, 0, 0],
         [0, 0, C, D],
         [0, 0, -D, C]]

    This is the paper's eq. (5) re-expressed with s instead of p as the x axis
    (which changes the sign of the off-diagonal ``B`` and of ``D``).
    """
    rs = np.asarray(r_s, dtype=complex)
    rp = np.asarray(r_p, dtype=complex)
    rs, rp = np.broadcast_arrays(rs, rp)
    a2, b2 = np.abs(rs) ** 2, np.abs(rp) ** 2
    x = rs * np.conj(rp)
    m = np.zeros((*rs.shape, 4, 4))
    m[..., 0, 0] = m[..., 1, 1] = 0.5 * (a2 + b2)
    m[..., 0, 1] = m[..., 1, 0] = 0.5 * (a2 - b2)
    m[..., 2, 2] = m[..., 3, 3] = x.real
    m[..., 2, 3] = x.imag
    m[..., 3, 2] = -x.imag
    return m


def reflect_direction(d: ArrayLike, normal: ArrayLike) -> NDArray[np.float64]:
    """Mirror direction ``d - 2 (d . n) n`` (``n`` unit; either side)."""
    d = np.asarray(d, float)
    n = normalize(normal)
    return d - 2.0 * dot(d, n)[..., None] * n


def incidence_basis(d: ArrayLike, normal: ArrayLike, fallback: ArrayLike) -> NDArray[np.float64]:
    """The s axis ``normalize(d x n)``; ``fallback`` (projected) at normal incidence."""
    d = normalize(d)
    s = np.cross(d, normalize(normal))
    weak = np.linalg.norm(s, axis=-1) < 1e-12  # a cross product this small is still accurate
    if np.any(weak):
        fb = np.broadcast_to(np.asarray(fallback, float), s.shape)
        fb = fb - dot(fb, d)[..., None] * d
        s = np.where(weak[..., None], fb, s)
    s = normalize(s)
    return normalize(s - dot(s, d)[..., None] * d)


def reflect_stokes(
    s: ArrayLike,
    d: ArrayLike,
    e: ArrayLike,
    normal: ArrayLike,
    mueller: MuellerFunction,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Reflect Stokes vectors ``s`` (..., 4) travelling along ``d`` with reference ``e`` off a surface.

    Parameters
    ----------
    s : array_like, (..., 4)
        Incident Stokes in frame (``d``, ``e``).
    d, e : array_like, (..., 3)
        Incident propagation direction and reference axis (unit, perpendicular).
    normal : array_like, (..., 3)
        Surface normal (either side; only the line matters).
    mueller : callable
        ``mueller(cos_i)`` -> ``(..., 4, 4)`` reflection Mueller matrix in the
        s-as-x basis for the incidence cosine ``cos_i`` in [0, 1], e.g.
        :func:`pihim.surfaces.fresnel.fresnel_reflection_mueller` partially
        applied.

    Returns
    -------
    s_out : (..., 4)
        Reflected Stokes in frame (``d_out``, ``s_axis``).
    d_out : (..., 3)
        Reflected direction.
    s_axis : (..., 3)
        Reference axis of ``s_out``: the s direction of the plane of incidence.
    """
    d = normalize(d)
    n = normalize(normal)
    cos_i = np.abs(dot(d, n))
    s_axis = incidence_basis(d, n, e)
    s_in = change_reference(s, d, e, s_axis)
    s_out = apply(mueller(cos_i), s_in)
    return s_out, reflect_direction(d, n), s_axis
