"""Heliostat kinematics: tracking, az-el drive angles, frames, canting and geometry.

Everything is vectorised over heliostats (leading axes broadcast) and uses the
field frame East-North-Up (x East, y North, z Up), metres.

Conventions (``docs/conventions.md``; each pinned by ``tests/field``)
--------------------------------------------------------------------
Tracking
    The mirror normal ``n`` bisects the sun vector ``s`` (scene -> sun) and
    the unit vector ``t`` from the **mirror centre** to the aim point:
    ``n = (s + t) / |s + t|``. The mirror centre is ``pivot +
    pivot_offset * n``, so ``t`` depends on ``n``; :func:`tracking_normals`
    solves this by fixed-point iteration (the map contracts by about
    ``pivot_offset / slant range``, ~1e-3, so three to five iterations reach
    1e-12).
Drive angles
    Azimuth clockwise from North (0 = N, 90 = E), elevation above the
    horizon, of the mirror normal; the back of the mirror points the other
    way (azimuth + 180, -elevation). Same angles as pvlib and
    :mod:`pihim.sky.sun`.
Heliostat frame
    Looking at the mirror face: ``x`` right, ``y`` up (toward the top edge),
    ``z`` the normal out of the face; right-handed; origin at the mirror
    centre. For an az-el drive ``x`` is horizontal: ``x = normalize(Up x
    n)``, ``y = n x x``. A mirror facing South (n = -North, horizontal) is
    seen from the South by an observer looking North, whose right is
    **East**: x = East, y = Up. A face-up mirror (n = Up) is the limit of a
    South-facing mirror tilting up: x = East, y = North (other limits via
    ``vertical_azimuth_deg``).
Facets
    Numbered 1..F row by row from the top left seen from the front (NSTTF:
    1-5 top row, 13 centre, 5/10/15/20/25 the right column).
Design canting (on-axis)
    Facet ``i`` with centroid ``(x_i, y_i)`` (heliostat frame) gets the normal
    of the paraboloid ``z = (x^2 + y^2) / (4 f)`` at ``(x_i, y_i)``:
    ``normalize(-x_i / (2 f), -y_i / (2 f), 1)``. Exactly stated, that normal
    points at ``(0, 0, 2 f + z_p)`` (``z_p`` the paraboloid height at the
    facet), i.e. at the vertex's centre of curvature, not at the focus
    ``(0, 0, f)``; what holds is that a ray parallel to the axis reflected at
    the facet centre passes through the focus (exactly for a centre on the
    paraboloid; for a facet centre at ``z_c`` instead of ``z_p`` the
    reflected ray crosses the axis ``z_p - z_c`` lower, millimetres for
    NSTTF geometry). The conventions' "facet normal points at the focal
    point" is this statement, loosely worded. The focal length is by default
    the slant range from the pivot to the aim point, as OpenCSP does for its
    NSTTF models [1]_; at f = 100 m the NSTTF corner facets are canted by
    about 14 mrad about y and 13 mrad about x (19 mrad in all).
Canting deviation
    Two small rotations of a facet normal relative to its design normal,
    about the fixed heliostat axes, in mrad: **azimuth** about ``y``,
    positive tilting the normal toward ``+x``; **elevation** about ``x``,
    positive tilting the normal toward ``+y`` (a right-hand rotation by
    ``-el`` about ``x``). Elevation is applied first:
    ``n = R_y(az) R_x(-el) n_design``. To first order ``az = dn_x`` and
    ``el = dn_y`` (heliostat frame).

References
----------
.. [1] Sandia National Laboratories, OpenCSP (Apache-2.0),
   https://github.com/sandialabs/OpenCSP: NSTTF heliostat models with
   symmetric-paraboloid canting whose focal length is the slant range to
   the aim point; NSTTF pivot offset 0.1778 m.
.. [2] W. B. Stine and M. Geyer, *Power From The Sun* (2001), ch. 10
   (central receivers: heliostat tracking and canting).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError
from pihim.polarimetry.frames import dot

__all__ = [
    "BackStructure",
    "DriveAngles",
    "FieldPose",
    "apply_canting_deviation",
    "back_structure",
    "canting_angles",
    "canting_deviation",
    "design_facet_normals",
    "drive_angles",
    "facet_centres",
    "facet_corners",
    "facet_rotations",
    "focal_lengths",
    "heliostat_rotation",
    "mirror_outline",
    "normals_from_drive",
    "reflect",
    "rotation_from_drive",
    "to_enu",
    "track_field",
    "tracking_normals",
]

_VERTICAL_EPS = 1e-12


# --------------------------------------------------------------------------- helpers


def _vec3(name: str, a: ArrayLike) -> NDArray[np.float64]:
    v = np.asarray(a, dtype=float)
    if v.ndim == 0 or v.shape[-1] != 3:
        raise PihimInputError(f"{name} must have 3 components on its last axis, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise PihimInputError(f"{name} must be finite")
    return v


def _unit(name: str, a: ArrayLike) -> NDArray[np.float64]:
    """Finite non-zero 3-vectors (last axis), normalised; a zero vector has no direction (it gave NaN)."""
    v = _vec3(name, a)
    length = np.linalg.norm(v, axis=-1, keepdims=True)  # as polarimetry.frames.normalize: the same bits
    if np.any(length == 0.0):
        raise PihimInputError(f"{name} must be non-zero vectors (a zero vector has no direction)")
    return v / length


def _norm(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.sqrt(np.einsum("...i,...i->...", v, v))


def reflect(directions: ArrayLike, normals: ArrayLike) -> NDArray[np.float64]:
    """Specular reflection ``d - 2 (d . n) n`` of propagation directions (``n`` unit).

    Raises
    ------
    PihimInputError
        Vectors without 3 components or not finite, or normals that are not
        unit vectors (within 1e-6): the formula needs them so (a zero normal
        returned the direction unchanged, ``[0, 0, 2]`` tripled it).
    """
    d = _vec3("directions", directions)
    n = _vec3("normals", normals)
    if np.any(np.abs(_norm(n) - 1.0) > 1e-6):
        raise PihimInputError("normals must be unit vectors (normalize them first)")
    return d - 2.0 * dot(d, n)[..., None] * n


# --------------------------------------------------------------------------- tracking


def tracking_normals(
    pivots: ArrayLike,
    sun_dir: ArrayLike,
    aim_point: ArrayLike,
    pivot_offset_m: ArrayLike,
    *,
    tol: float = 1e-12,
    max_iter: int = 30,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Mirror normals and mirror centres of heliostats reflecting the sun onto an aim point.

    Solves ``n = normalize(s + normalize(a - c))`` with ``c = p + d n`` by
    fixed-point iteration, starting from ``c = p``.

    Parameters
    ----------
    pivots : array_like, shape (..., 3)
        Torque-tube pivots ``p``, ENU metres.
    sun_dir : array_like, shape (..., 3)
        Direction from the scene toward the sun ``s`` (normalised here).
    aim_point : array_like, shape (..., 3)
        Aim point(s) ``a``, ENU metres (one for all, or one per heliostat).
    pivot_offset_m : float or array_like, shape (...)
        Pivot-to-mirror-plane distance ``d`` along the normal, metres.
    tol : float
        Stop when no normal component changes by more than ``tol`` between
        iterations (the remaining error is ~1e-3 ``tol``).
    max_iter : int
        Iteration limit.

    Returns
    -------
    normals : ndarray, shape (broadcast, 3)
        Unit mirror normals.
    mirror_centres : ndarray, shape (broadcast, 3)
        ``p + d n``, metres.

    Raises
    ------
    PihimInputError
        Bad shapes, non-finite input, a zero sun vector, an aim point on a
        mirror, a sun exactly behind the aim direction, or no convergence
        (the aim point within about ``d`` of a mirror).

    Notes
    -----
    Reflecting the incoming sunlight (direction ``-s``) off the returned
    normal gives exactly the unit vector from the mirror centre to the aim
    point. For an NSTTF field (218 heliostats) one call takes well under a
    millisecond (``benchmarks/bench_field.py``).
    """
    p = _vec3("pivots", pivots)
    s = _vec3("sun_dir", sun_dir)
    a = _vec3("aim_point", aim_point)
    d = np.asarray(pivot_offset_m, dtype=float)
    if not np.all(np.isfinite(d)):
        raise PihimInputError("pivot_offset_m must be finite")
    s_len = _norm(s)
    if np.any(s_len == 0):
        raise PihimInputError("sun_dir must not be the zero vector")
    s = s / s_len[..., None]
    shape = np.broadcast_shapes(p.shape, s.shape, a.shape, d.shape + (1,))
    # component form (three contiguous arrays) is several times faster than (N, 3) rows for big fields
    px, py, pz = (np.ascontiguousarray(np.broadcast_to(v, shape[:-1])) for v in np.moveaxis(p, -1, 0))
    sx, sy, sz = np.moveaxis(s, -1, 0)
    ax, ay, az = np.moveaxis(a, -1, 0)
    cx, cy, cz = px, py, pz
    nx = ny = nz = None
    converged = False
    with np.errstate(invalid="ignore", divide="ignore"):
        for _ in range(max(1, int(max_iter))):
            tx, ty, tz = ax - cx, ay - cy, az - cz
            inv = 1.0 / np.sqrt(tx * tx + ty * ty + tz * tz)
            mx, my, mz = sx + tx * inv, sy + ty * inv, sz + tz * inv
            inv = 1.0 / np.sqrt(mx * mx + my * my + mz * mz)
            mx *= inv
            my *= inv
            mz *= inv
            cx, cy, cz = px + d * mx, py + d * my, pz + d * mz
            if nx is not None:
                change = max(float(np.max(np.abs(mx - nx), initial=0.0)), float(np.max(np.abs(my - ny), initial=0.0)),
                             float(np.max(np.abs(mz - nz), initial=0.0)))
                if change <= tol:
                    converged = True
            nx, ny, nz = mx, my, mz
            if converged:
                break
    n = np.stack([nx, ny, nz], axis=-1)
    c = np.stack([cx, cy, cz], axis=-1)
    if not np.all(np.isfinite(n)):
        raise PihimInputError(
            "tracking is undefined for some heliostats: aim point on the mirror or sun exactly opposite the aim"
        )
    if not converged:
        raise PihimInputError(f"tracking did not converge in {max_iter} iterations (aim point too close to a mirror?)")
    return n, c


# --------------------------------------------------------------------------- drive angles


class DriveAngles(NamedTuple):
    """Az-el drive angles of mirror normals, degrees.

    ``azimuth_deg`` is clockwise from North in [0, 360), ``elevation_deg``
    above the horizon in [-90, 90]. The back of the mirror points along
    (``back_azimuth_deg``, ``back_elevation_deg``) = (azimuth + 180,
    -elevation).
    """

    azimuth_deg: NDArray[np.float64]
    elevation_deg: NDArray[np.float64]

    @property
    def back_azimuth_deg(self) -> NDArray[np.float64]:
        """Azimuth of the back of the mirror (``-n``), degrees in [0, 360)."""
        return np.mod(self.azimuth_deg + 180.0, 360.0)

    @property
    def back_elevation_deg(self) -> NDArray[np.float64]:
        """Elevation of the back of the mirror (``-n``), degrees."""
        return -self.elevation_deg


def drive_angles(normals: ArrayLike, *, vertical_azimuth_deg: float = 180.0) -> DriveAngles:
    """Azimuth (clockwise from North) and elevation of mirror normals, degrees.

    Parameters
    ----------
    normals : array_like, shape (..., 3)
        Mirror normals, ENU (normalised here).
    vertical_azimuth_deg : float
        Azimuth reported for (anti)vertical normals, where it is undefined.

    Returns
    -------
    DriveAngles
        ``(azimuth_deg, elevation_deg)`` arrays of shape (...); ``.back_*``
        give the back of the mirror.
    """
    n = _unit("normals", normals)
    horiz = np.hypot(n[..., 0], n[..., 1])
    az = np.mod(np.degrees(np.arctan2(n[..., 0], n[..., 1])), 360.0)
    az = np.where(horiz < _VERTICAL_EPS, float(vertical_azimuth_deg) % 360.0, az)
    el = np.degrees(np.arctan2(n[..., 2], horiz))
    return DriveAngles(az, el)


def normals_from_drive(azimuth_deg: ArrayLike, elevation_deg: ArrayLike) -> NDArray[np.float64]:
    """Mirror normals from az-el drive angles: ``(cos el sin az, cos el cos az, sin el)``."""
    az = np.radians(np.asarray(azimuth_deg, dtype=float))
    el = np.radians(np.asarray(elevation_deg, dtype=float))
    az, el = np.broadcast_arrays(az, el)
    ce = np.cos(el)
    return np.stack([ce * np.sin(az), ce * np.cos(az), np.sin(el)], axis=-1)


# --------------------------------------------------------------------------- frames


def heliostat_rotation(normals: ArrayLike, *, vertical_azimuth_deg: float = 180.0) -> NDArray[np.float64]:
    """Heliostat frames of az-el heliostats: columns x, y, z (ENU), shape (..., 3, 3).

    ``z = n``, ``x = normalize(Up x n)`` (horizontal, to the right when
    looking at the face), ``y = z x x`` (toward the top edge). A point with
    heliostat coordinates ``q`` is at ``centre + R @ q`` in ENU.

    Parameters
    ----------
    normals : array_like, shape (..., 3)
        Mirror normals, ENU (normalised here).
    vertical_azimuth_deg : float
        For (anti)vertical normals, where ``Up x n`` vanishes, ``x`` is taken
        as for a normal of that azimuth: ``(-cos A, sin A, 0)``. The default
        180 deg gives ``x`` = East, ``y`` = North for a face-up mirror (the
        limit of a South-facing mirror tilting up).

    Returns
    -------
    ndarray, shape (..., 3, 3)
        Rotation matrices (orthonormal, det +1).
    """
    n = _unit("normals", normals)
    x = np.stack([-n[..., 1], n[..., 0], np.zeros(n.shape[:-1])], axis=-1)
    h = np.hypot(x[..., 0], x[..., 1])
    weak = h < _VERTICAL_EPS
    if np.any(weak):
        a = math.radians(vertical_azimuth_deg)
        x = np.where(weak[..., None], np.array([-math.cos(a), math.sin(a), 0.0]), x)
        h = np.where(weak, 1.0, h)
    x = x / h[..., None]
    y = np.cross(n, x)
    return np.stack([x, y, n], axis=-1)


def rotation_from_drive(azimuth_deg: ArrayLike, elevation_deg: ArrayLike) -> NDArray[np.float64]:
    """Heliostat frames from drive angles (well defined at elevation 90 deg), shape (..., 3, 3).

    ``x = (-cos az, sin az, 0)``, ``z`` = :func:`normals_from_drive`,
    ``y = z x x``; identical to :func:`heliostat_rotation` away from the
    zenith.
    """
    n = normals_from_drive(azimuth_deg, elevation_deg)
    az = np.radians(np.broadcast_to(np.asarray(azimuth_deg, float), n.shape[:-1]))
    x = np.stack([-np.cos(az), np.sin(az), np.zeros(az.shape)], axis=-1)
    return np.stack([x, np.cross(n, x), n], axis=-1)


def to_enu(
    rotations: ArrayLike, origins: ArrayLike, points: ArrayLike, *, per_heliostat: bool = False
) -> NDArray[np.float64]:
    """Heliostat-frame points to ENU: ``origin + R @ q``.

    Parameters
    ----------
    rotations : array_like, shape (N, 3, 3)
        Heliostat frames (columns x, y, z in ENU).
    origins : array_like, shape (N, 3)
        Frame origins (mirror centres), metres.
    points : array_like, shape (P..., 3), or (N, P..., 3) with ``per_heliostat``
        Points in the heliostat frame, metres: the same for every heliostat,
        or one set per heliostat.
    per_heliostat : bool
        Whether ``points`` has a leading heliostat axis.

    Returns
    -------
    ndarray, shape (N, P..., 3)
    """
    r = np.asarray(rotations, dtype=float)
    o = np.asarray(origins, dtype=float)
    q = _vec3("points", points)
    if r.ndim != 3 or r.shape[1:] != (3, 3) or o.shape != (r.shape[0], 3):
        raise PihimInputError(f"rotations must be (N, 3, 3) and origins (N, 3), got {r.shape} and {o.shape}")
    if per_heliostat:
        if q.ndim < 2 or q.shape[0] != r.shape[0]:
            raise PihimInputError(f"per-heliostat points need a leading axis of {r.shape[0]}, got {q.shape}")
        extra = q.ndim - 2
        out = np.einsum("nij,n...j->n...i", r, q)
    else:
        extra = q.ndim - 1
        out = np.einsum("nij,...j->n...i", r, q)
    return o.reshape((o.shape[0],) + (1,) * extra + (3,)) + out


# --------------------------------------------------------------------------- canting


def focal_lengths(pivots: ArrayLike, aim_point: ArrayLike) -> NDArray[np.float64]:
    """Slant range from each pivot to the aim point, metres (the on-axis canting focal length)."""
    return _norm(_vec3("aim_point", aim_point) - _vec3("pivots", pivots))


def design_facet_normals(facet_centroids: ArrayLike, focal_length_m: ArrayLike) -> NDArray[np.float64]:
    """On-axis canted facet normals in the heliostat frame (closed form).

    ``normalize(-x / (2 f), -y / (2 f), 1)``: the normal of the paraboloid
    ``z = (x^2 + y^2) / (4 f)`` above each facet centroid ``(x, y)``. A ray
    arriving along the axis and reflected at the facet centre passes through
    the focus ``(0, 0, f)``; the normal itself points at ``(0, 0, 2 f +
    z_p)``, the vertex's centre of curvature (see the module notes).

    Parameters
    ----------
    facet_centroids : array_like, shape (F, 3)
        Facet centroids, heliostat frame, metres (``z`` is not used).
    focal_length_m : float or array_like, shape (...)
        Focal length(s), metres (``inf``: flat, all normals ``+z``).

    Returns
    -------
    ndarray, shape (..., F, 3)
    """
    c = _vec3("facet_centroids", facet_centroids)
    f = np.asarray(focal_length_m, dtype=float)
    if np.any(~(f > 0)):
        raise PihimInputError("focal_length_m must be positive (inf for flat)")
    inv2f = (0.5 / f)[..., None]
    nx = -c[..., 0] * inv2f
    ny = -c[..., 1] * inv2f
    v = np.stack(np.broadcast_arrays(nx, ny, np.ones_like(nx)), axis=-1)
    return v / _norm(v)[..., None]


def _rot_y(v: NDArray[np.float64], ang: NDArray[np.float64]) -> NDArray[np.float64]:
    c, s = np.cos(ang), np.sin(ang)
    return np.stack([c * v[..., 0] + s * v[..., 2], v[..., 1], -s * v[..., 0] + c * v[..., 2]], axis=-1)


def _rot_x_el(v: NDArray[np.float64], el: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation about x tilting +z toward +y by ``el`` (right-hand rotation by ``-el``)."""
    c, s = np.cos(el), np.sin(el)
    return np.stack([v[..., 0], c * v[..., 1] + s * v[..., 2], -s * v[..., 1] + c * v[..., 2]], axis=-1)


def apply_canting_deviation(
    facet_normals: ArrayLike, az_mrad: ArrayLike, el_mrad: ArrayLike
) -> NDArray[np.float64]:
    """Tilt facet normals by canting deviations (heliostat frame).

    ``n = R_y(az) R_x(-el) n_design``: elevation first (about the heliostat
    ``x`` axis, positive toward ``+y``), then azimuth (about ``y``, positive
    toward ``+x``).

    Parameters
    ----------
    facet_normals : array_like, shape (..., 3)
        Design normals, heliostat frame.
    az_mrad, el_mrad : array_like, shape (...)
        Deviations, milliradians.

    Returns
    -------
    ndarray, shape (broadcast, 3)
    """
    n = _vec3("facet_normals", facet_normals)
    az = np.asarray(az_mrad, dtype=float) * 1e-3
    el = np.asarray(el_mrad, dtype=float) * 1e-3
    shape = np.broadcast_shapes(n.shape[:-1], az.shape, el.shape)
    n = np.broadcast_to(n, shape + (3,))
    return _rot_y(_rot_x_el(n, np.broadcast_to(el, shape)), np.broadcast_to(az, shape))


def canting_deviation(
    design_normals: ArrayLike, actual_normals: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Canting deviations (mrad) turning design normals into actual ones; inverse of :func:`apply_canting_deviation`.

    Closed form: with ``phi = atan2(a_x, a_z)`` and ``rho = hypot(a_x,
    a_z)`` of the actual normal ``a``, ``az = phi - asin(d_x / rho)``
    (rotating ``a`` back about ``y`` must restore the design ``x``
    component); then ``el`` is the angle in the y-z plane between the design
    normal and ``R_y(-az) a``.

    Parameters
    ----------
    design_normals, actual_normals : array_like, shape (..., 3)
        Heliostat frame (normalised here).

    Returns
    -------
    az_mrad, el_mrad : ndarray, shape (...)
    """
    d = _unit("design_normals", design_normals)
    a = _unit("actual_normals", actual_normals)
    d, a = np.broadcast_arrays(d, a)
    phi = np.arctan2(a[..., 0], a[..., 2])
    rho = np.hypot(a[..., 0], a[..., 2])
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.clip(d[..., 0] / rho, -1.0, 1.0)
    az = phi - np.arcsin(ratio)
    u = _rot_y(a, -az)
    el = np.arctan2(u[..., 1], u[..., 2]) - np.arctan2(d[..., 1], d[..., 2])
    el = (el + np.pi) % (2.0 * np.pi) - np.pi
    return az * 1e3, el * 1e3


def canting_angles(facet_normals: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Canting of facet normals relative to the heliostat normal ``+z``, mrad (az about y, el about x).

    Equal to ``canting_deviation((0, 0, 1), n)``: ``az = atan2(n_x, n_z)``,
    ``el = asin(n_y)``.
    """
    n = _unit("facet_normals", facet_normals)
    return np.arctan2(n[..., 0], n[..., 2]) * 1e3, np.arctan2(n[..., 1], np.hypot(n[..., 0], n[..., 2])) * 1e3


def facet_rotations(facet_normals: ArrayLike) -> NDArray[np.float64]:
    """Facet frames in the heliostat frame, columns x, y, z, shape (..., 3, 3).

    The heliostat frame turned by the facet's canting angles
    (:func:`canting_angles`): ``R_y(az) R_x(-el)``, so ``z`` = the facet
    normal, ``x = (n_z, 0, -n_x) / hypot(n_x, n_z)`` and ``y = z x x``.
    """
    n = _unit("facet_normals", facet_normals)
    h = np.hypot(n[..., 0], n[..., 2])
    x = np.stack([n[..., 2] / h, np.zeros(h.shape), -n[..., 0] / h], axis=-1)
    return np.stack([x, np.cross(n, x), n], axis=-1)


# --------------------------------------------------------------------------- geometry


def facet_centres(
    rotations: ArrayLike, mirror_centres: ArrayLike, facet_centroids: ArrayLike
) -> NDArray[np.float64]:
    """Facet centroids in ENU, shape (N, F, 3): ``mirror_centre + R @ centroid``.

    The mirror centre already includes the pivot offset (``pivot +
    pivot_offset * n``), so these are points on the mirror surface.
    """
    r = np.asarray(rotations, dtype=float)
    c = np.asarray(mirror_centres, dtype=float)
    q = _vec3("facet_centroids", facet_centroids)
    return c[..., None, :] + q @ np.swapaxes(r, -1, -2)


def facet_corners(
    rotations: ArrayLike,
    mirror_centres: ArrayLike,
    facet_centroids: ArrayLike,
    facet_normals: ArrayLike,
    facet_width_m: float,
    facet_height_m: float,
) -> NDArray[np.float64]:
    """Four corners of every facet in ENU, shape (N, F, 4, 3).

    Corner order as seen from the front: top left, top right, bottom right,
    bottom left (``(-w/2, +h/2)``, ``(+w/2, +h/2)``, ``(+w/2, -h/2)``,
    ``(-w/2, -h/2)`` in the facet frame of :func:`facet_rotations`).

    Parameters
    ----------
    rotations : array_like, shape (N, 3, 3)
        Heliostat frames.
    mirror_centres : array_like, shape (N, 3)
        Heliostat frame origins (pivot + offset * normal), metres.
    facet_centroids : array_like, shape (F, 3)
        Heliostat frame, metres.
    facet_normals : array_like, shape (F, 3) or (N, F, 3)
        Facet normals in the heliostat frame (design or deviated).
    facet_width_m, facet_height_m : float
        Facet size, metres.
    """
    q = _vec3("facet_centroids", facet_centroids)
    fr = facet_rotations(facet_normals)  # (..., F, 3, 3)
    hw, hh = 0.5 * float(facet_width_m), 0.5 * float(facet_height_m)
    local = np.array([[-hw, hh, 0.0], [hw, hh, 0.0], [hw, -hh, 0.0], [-hw, -hh, 0.0]])
    corners_h = q[:, None, :] + local @ np.swapaxes(fr, -1, -2)  # (..., F, 4, 3)
    r = np.asarray(rotations, dtype=float)
    c = np.asarray(mirror_centres, dtype=float)
    if corners_h.ndim not in (3, 4):
        raise PihimInputError(f"facet_normals must be (F, 3) or (N, F, 3), got {np.shape(facet_normals)}")
    enu = corners_h @ np.swapaxes(r, -1, -2)[:, None]  # (N, F, 4, 3)
    return c[:, None, None, :] + enu


def mirror_outline(rotations: ArrayLike, mirror_centres: ArrayLike, spec: object) -> NDArray[np.float64]:
    """Corners of the overall mirror rectangle (flat, in the mirror plane) in ENU, shape (N, 4, 3).

    Order: top left, top right, bottom right, bottom left seen from the
    front; half-sizes ``spec.mirror_half_width_m`` and
    ``spec.mirror_half_height_m`` (a :class:`~pihim.field.layout.HeliostatSpec`).
    """
    hw, hh = float(spec.mirror_half_width_m), float(spec.mirror_half_height_m)  # type: ignore[attr-defined]
    local = np.array([[-hw, hh, 0.0], [hw, hh, 0.0], [hw, -hh, 0.0], [-hw, -hh, 0.0]])
    r = np.asarray(rotations, dtype=float)
    c = np.asarray(mirror_centres, dtype=float)
    return c[:, None, :] + np.einsum("nij,kj->nki", r, local)


@dataclass(frozen=True, eq=False)
class BackStructure:
    """Line segments of a simple heliostat back structure, ENU.

    Attributes
    ----------
    segments : ndarray, shape (N, S, 2, 3)
        Segment end points, metres.
    kinds : tuple of str, length S
        ``"torque_tube"``, ``"rib"``, ``"crossbar"`` or ``"pedestal"`` per
        segment.
    """

    segments: NDArray[np.float64]
    kinds: tuple[str, ...]

    def of_kind(self, kind: str) -> NDArray[np.float64]:
        """Segments of one kind, shape (N, S_kind, 2, 3)."""
        idx = [i for i, k in enumerate(self.kinds) if k == kind]
        return self.segments[:, idx]


def back_structure(
    rotations: ArrayLike, mirror_centres: ArrayLike, spec: object
) -> BackStructure:
    """A simple back structure for tracked heliostats, as segments in ENU.

    In the heliostat frame (origin at the mirror centre, the pivot at
    ``(0, 0, -pivot_offset)``), all members but the pedestal lie in the plane
    through the pivot parallel to the mirror:

    * ``torque_tube``: along ``x`` through the pivot, the mirror width long
      (the elevation axis of an az-el drive);
    * ``rib``: one per facet column, along ``y`` at the column's ``x``, the
      mirror height long;
    * ``crossbar``: one per facet row, along ``x`` at the row's ``y``, the
      mirror width long;
    * ``pedestal``: vertical (ENU), from the ground ``pivot_height`` below the
      pivot up to the pivot.

    Parameters
    ----------
    rotations : array_like, shape (N, 3, 3)
    mirror_centres : array_like, shape (N, 3)
    spec : HeliostatSpec
    """
    hw, hh = float(spec.mirror_half_width_m), float(spec.mirror_half_height_m)  # type: ignore[attr-defined]
    d = float(spec.pivot_offset_m)  # type: ignore[attr-defined]
    cent = np.asarray(spec.facet_centroids, dtype=float)  # type: ignore[attr-defined]
    rows, cols = int(spec.rows), int(spec.cols)  # type: ignore[attr-defined]
    grid = cent.reshape(rows, cols, 3)
    col_x = grid[0, :, 0]
    row_y = grid[:, 0, 1]
    segs = [[(-hw, 0.0, -d), (hw, 0.0, -d)]]
    kinds = ["torque_tube"]
    for x in col_x:
        segs.append([(x, -hh, -d), (x, hh, -d)])
        kinds.append("rib")
    for y in row_y:
        segs.append([(-hw, y, -d), (hw, y, -d)])
        kinds.append("crossbar")
    local = np.array(segs)  # (S, 2, 3)
    r = np.asarray(rotations, dtype=float)
    c = np.asarray(mirror_centres, dtype=float)
    body = c[:, None, None, :] + np.einsum("nij,skj->nski", r, local)
    pivot = c + r[..., 2] * (-d)
    ground = pivot - np.array([0.0, 0.0, float(spec.pivot_height_m)])  # type: ignore[attr-defined]
    pedestal = np.stack([ground, pivot], axis=1)[:, None]
    return BackStructure(np.concatenate([body, pedestal], axis=1), tuple(kinds + ["pedestal"]))


# --------------------------------------------------------------------------- whole field


@dataclass(frozen=True, eq=False)
class FieldPose:
    """A field tracked for one instant, with its design canting.

    Attributes
    ----------
    field : Field
        The field (``pihim.field.layout.Field``).
    normals : ndarray, shape (N, 3)
        Mirror normals, ENU.
    mirror_centres : ndarray, shape (N, 3)
        ``pivot + pivot_offset * normal``, metres.
    rotations : ndarray, shape (N, 3, 3)
        Heliostat frames (columns x, y, z in ENU).
    focal_lengths_m : ndarray, shape (N,)
        Canting focal lengths.
    facet_normals_local : ndarray, shape (N, F, 3)
        Design facet normals, heliostat frame.
    facet_normals : ndarray, shape (N, F, 3)
        Design facet normals, ENU.
    facet_centres : ndarray, shape (N, F, 3)
        Facet centroids, ENU metres.
    """

    field: object
    normals: NDArray[np.float64]
    mirror_centres: NDArray[np.float64]
    rotations: NDArray[np.float64]
    focal_lengths_m: NDArray[np.float64]
    facet_normals_local: NDArray[np.float64]
    facet_normals: NDArray[np.float64]
    facet_centres: NDArray[np.float64]

    @property
    def drive(self) -> DriveAngles:
        """Az-el drive angles of the normals."""
        return drive_angles(self.normals)

    def facet_corners(self, facet_normals_local: ArrayLike | None = None) -> NDArray[np.float64]:
        """Facet corners in ENU, shape (N, F, 4, 3) (design canting unless normals are given)."""
        spec = self.field.spec  # type: ignore[attr-defined]
        n = self.facet_normals_local if facet_normals_local is None else facet_normals_local
        return facet_corners(self.rotations, self.mirror_centres, spec.facet_centroids, n,
                             spec.facet_width_m, spec.facet_height_m)

    def mirror_outline(self) -> NDArray[np.float64]:
        """Mirror rectangle corners in ENU, shape (N, 4, 3)."""
        return mirror_outline(self.rotations, self.mirror_centres, self.field.spec)  # type: ignore[attr-defined]

    def back_structure(self) -> BackStructure:
        """Back-structure segments in ENU."""
        return back_structure(self.rotations, self.mirror_centres, self.field.spec)  # type: ignore[attr-defined]

    def with_drive(self, azimuth_deg: ArrayLike, elevation_deg: ArrayLike) -> FieldPose:
        """The same field with its heliostats driven to other az-el angles (same canting).

        Normals, frames (:func:`rotation_from_drive`), mirror centres (``pivot
        + pivot_offset * normal``) and facet frames follow the new angles;
        the facet normals in the heliostat frame (the canting) are kept. Used
        for tracking errors and for heliostats parked away from tracking.

        Parameters
        ----------
        azimuth_deg, elevation_deg : array_like, shape (N,)
            Drive angles of the mirror normals, degrees.
        """
        spec = self.field.spec  # type: ignore[attr-defined]
        az = np.broadcast_to(np.asarray(azimuth_deg, float), self.normals.shape[:1])
        el = np.broadcast_to(np.asarray(elevation_deg, float), self.normals.shape[:1])
        if not (np.all(np.isfinite(az)) and np.all(np.isfinite(el))):
            raise PihimInputError("drive angles must be finite")
        normals = normals_from_drive(az, el)
        rot = rotation_from_drive(az, el)
        centres = np.asarray(self.field.pivots, float) + float(spec.pivot_offset_m) * normals  # type: ignore[attr-defined]
        enu = self.facet_normals_local @ np.swapaxes(rot, -1, -2)
        fc = facet_centres(rot, centres, spec.facet_centroids)
        return FieldPose(self.field, normals, centres, rot, self.focal_lengths_m, self.facet_normals_local, enu, fc)


def track_field(
    field: object,
    sun_dir: ArrayLike,
    aim_point: ArrayLike | None = None,
    *,
    canting_focal_length_m: ArrayLike | None = None,
    canting_aim_point: ArrayLike | None = None,
) -> FieldPose:
    """Track every heliostat of a field for one sun direction and apply the design canting.

    Parameters
    ----------
    field : Field
        The heliostats (``pihim.field.layout.Field``).
    sun_dir : array_like, shape (3,)
        Direction toward the sun, ENU.
    aim_point : array_like, shape (3,) or (N, 3), optional
        Where the heliostats send the sunlight; default the tower target
        (``field.default_aim_point``).
    canting_focal_length_m : float or array_like, shape (N,), optional
        On-axis canting focal length(s), metres.
    canting_aim_point : array_like, shape (3,), optional
        If no focal length is given, the focal length is the slant range from
        each pivot to this point; default the tracking aim point.

    Returns
    -------
    FieldPose

    Raises
    ------
    PihimInputError
        Not a field; a sun direction that is not one finite 3-vector above
        the horizon; an aim point or focal lengths of the wrong shape.
    """
    if not (hasattr(field, "pivots") and hasattr(field, "spec")):
        raise PihimInputError(f"field must be a pihim.field.Field, got {type(field).__name__}")
    pivots = field.pivots
    spec = field.spec
    sun = _vec3("sun_dir", sun_dir)
    if sun.shape != (3,):
        raise PihimInputError(f"sun_dir must be one direction, shape (3,), got shape {sun.shape}")
    if sun[2] <= 0:  # the mirrors would face the ground (track_at and build_plan refuse such times too)
        raise PihimInputError(f"the sun is not above the horizon (sun_dir z = {sun[2]:g}): heliostats do not track it")
    aim = field.default_aim_point if aim_point is None else _vec3("aim_point", aim_point)
    if aim.ndim == 2 and len(aim) != len(pivots):
        raise PihimInputError(f"aim_point must be one point or one per heliostat ({len(pivots)}), got {len(aim)}")
    normals, centres = tracking_normals(pivots, sun, aim, spec.pivot_offset_m)
    rot = heliostat_rotation(normals)
    if canting_focal_length_m is not None:
        f = np.asarray(canting_focal_length_m, dtype=float)
        if f.ndim > 1 or (f.ndim == 1 and len(f) != len(pivots)):
            raise PihimInputError(f"canting_focal_length_m must be one focal length or one per heliostat "
                                  f"({len(pivots)}), got shape {f.shape}")  # (its values: design_facet_normals)
        f = np.broadcast_to(f, (len(pivots),))
    else:
        f = focal_lengths(pivots, aim if canting_aim_point is None else canting_aim_point)
    local = design_facet_normals(spec.facet_centroids, f)
    enu = local @ np.swapaxes(rot, -1, -2)
    fc = facet_centres(rot, centres, spec.facet_centroids)
    return FieldPose(field, normals, centres, rot, np.asarray(f, dtype=float), local, enu, fc)
