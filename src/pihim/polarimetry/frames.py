"""Stokes reference frames in three dimensions.

A Stokes vector is only meaningful with its frame: the propagation direction
``d`` (unit vector, the way the light travels) and a reference axis ``e``
(unit vector perpendicular to ``d``). ``S1 > 0`` means the field oscillates
along ``e``; ``S2 > 0`` along ``(e + d x e) / sqrt(2)``, 45 deg
counter-clockwise from ``e`` when looking into the beam (toward the source).

Physics functions carry full Stokes vectors ``(..., 4)`` = (S0, S1, S2, S3);
directions are ``(..., 3)`` arrays in any right-handed Cartesian frame (pihim
uses East-North-Up). Everything is vectorised and broadcasts.

References
----------
.. [1] R. A. Chipman, W. S. T. Lam, G. Young, *Polarized Light and Optical
   Systems*, CRC Press, 2018, ch. 6 (Stokes and Mueller calculus) and
   ch. 9-10 (polarization ray tracing, local s/p bases).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.polarimetry.stokes import aop_deg, dolp

_UP = np.array([0.0, 0.0, 1.0])
_EAST = np.array([1.0, 0.0, 0.0])


def normalize(v: ArrayLike) -> NDArray[np.float64]:
    """Unit vectors along the last axis (zero vectors give NaN)."""
    v = np.asarray(v, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)


def dot(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """Dot product along the last axis, broadcasting."""
    return np.sum(np.asarray(a, float) * np.asarray(b, float), axis=-1)


def perpendicular_reference(d: ArrayLike, hint: ArrayLike = _UP, fallback: ArrayLike = _EAST) -> NDArray[np.float64]:
    """A reference axis perpendicular to ``d``: ``hint`` projected onto the plane normal to ``d``.

    Where ``hint`` is (nearly) parallel to ``d`` the ``fallback`` axis is
    projected instead. With the default ``hint`` = up, ``e`` points "up" in
    the plane of polarization, i.e. along the local meridian of ``d``.
    """
    d = normalize(d)
    hint = np.broadcast_to(np.asarray(hint, float), d.shape)
    fallback = np.broadcast_to(np.asarray(fallback, float), d.shape)
    e = hint - dot(hint, d)[..., None] * d
    weak = np.linalg.norm(e, axis=-1) < 1e-6
    if np.any(weak):
        ef = fallback - dot(fallback, d)[..., None] * d
        e = np.where(weak[..., None], ef, e)
    e = normalize(e)
    # one Gram-Schmidt pass more: keeps e perpendicular to round-off for nearly parallel hints
    return normalize(e - dot(e, d)[..., None] * d)


def rotation_angle_deg(d: ArrayLike, e_from: ArrayLike, e_to: ArrayLike) -> NDArray[np.float64]:
    """Signed angle (deg) from ``e_from`` to ``e_to``, counter-clockwise looking into the beam.

    Both axes must be perpendicular to ``d``. Looking into the beam means
    looking along ``-d``; then ``e`` and ``d x e`` appear as "right" and "up",
    so the angle is ``atan2((e_from x e_to) . d, e_from . e_to)``.
    """
    d = np.asarray(d, float)
    return np.degrees(np.arctan2(dot(np.cross(e_from, e_to), d), dot(e_from, e_to)))


def mueller_rotator(angle_deg: ArrayLike) -> NDArray[np.float64]:
    """Mueller matrix ``(..., 4, 4)`` that re-expresses Stokes in a frame whose axis is turned by ``angle_deg``.

    ``S' = R(t) S`` with ``R = [[1,0,0,0],[0,c,s,0],[0,-s,c,0],[0,0,0,1]]``,
    ``c = cos 2t``, ``s = sin 2t``; the AoP drops by ``t``.
    """
    t = 2.0 * np.radians(np.asarray(angle_deg, float))
    c, s = np.cos(t), np.sin(t)
    r = np.zeros((*t.shape, 4, 4))
    r[..., 0, 0] = 1.0
    r[..., 3, 3] = 1.0
    r[..., 1, 1] = c
    r[..., 1, 2] = s
    r[..., 2, 1] = -s
    r[..., 2, 2] = c
    return r


def apply(m: ArrayLike, s: ArrayLike) -> NDArray[np.float64]:
    """Apply Mueller matrices ``(..., 4, 4)`` to Stokes vectors ``(..., 4)``."""
    return np.einsum("...ij,...j->...i", np.asarray(m, float), np.asarray(s, float))


def change_reference(s: ArrayLike, d: ArrayLike, e_from: ArrayLike, e_to: ArrayLike) -> NDArray[np.float64]:
    """Re-express Stokes ``s`` (..., 4), known in frame (``d``, ``e_from``), in frame (``d``, ``e_to``)."""
    return apply(mueller_rotator(rotation_angle_deg(d, e_from, e_to)), s)


def as_stokes4(s: ArrayLike) -> NDArray[np.float64]:
    """Pad (..., 3) linear Stokes with S3 = 0; (..., 4) is returned as float."""
    s = np.asarray(s, float)
    if s.shape[-1] == 4:
        return s
    if s.shape[-1] != 3:
        raise ValueError(f"Stokes vectors need 3 or 4 components on the last axis, got {s.shape}")
    return np.concatenate([s, np.zeros((*s.shape[:-1], 1))], axis=-1)


def dolp4(s: ArrayLike) -> NDArray[np.float64]:
    """DoLP of (..., 4) or (..., 3) Stokes vectors (NaN where S0 <= 0)."""
    s = np.asarray(s, float)
    return dolp(s[..., 0], s[..., 1], s[..., 2])


def aop4_deg(s: ArrayLike) -> NDArray[np.float64]:
    """AoP in [0, 180) deg of (..., 4) or (..., 3) Stokes vectors, relative to their frame's axis."""
    s = np.asarray(s, float)
    return aop_deg(s[..., 1], s[..., 2])


def field_direction(s: ArrayLike, d: ArrayLike, e: ArrayLike) -> NDArray[np.float64]:
    """Unit vector along the oscillation (major) axis of the polarized part of ``s``.

    ``cos(AoP) e + sin(AoP) (d x e)``; defined up to sign (an orientation). This
    turns a Stokes vector back into geometry, which is how the tests pin signs
    independently of the Mueller algebra.
    """
    a = np.radians(aop4_deg(s))[..., None]
    d = np.asarray(d, float)
    e = np.asarray(e, float)
    return np.cos(a) * e + np.sin(a) * np.cross(d, e)
