"""Sight lines over a tracked heliostat field: gaze angles, field of view, ray / mirror and ray / tower tests.

Geometry shared by the UFACET planner (:mod:`pihim.planning.ufacet`,
:mod:`pihim.planning.lines`) and the contrast scoring: every test is
vectorised over many rays, with a grid over the mirror centres so that a ray
is tested only against mirrors near it. Mirrors are the flat tracked
outlines (``mirror_half_width_m`` x ``mirror_half_height_m`` around each
mirror centre, in the mirror plane); the tower is its axis-aligned box.
Headings are degrees clockwise from North, pitch negative below the horizon
(docs/conventions.md, "Flight plans").
"""

from __future__ import annotations

import math
import weakref
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.camera.model import CameraModel
from pihim.errors import PihimInputError
from pihim.field.kinematics import FieldPose

__all__ = [
    "TOWER_HIT",
    "GridCells",
    "MirrorIndex",
    "azimuth_deg",
    "camera_frame",
    "first_mirror_hits",
    "gaze_angles",
    "grid_cells",
    "mirror_index",
    "in_fov",
    "optical_axis",
    "segments_hit_box",
    "tower_box",
]

#: Blocker code for the tower in hit arrays (mirrors are >= 0, nothing is -1).
TOWER_HIT = -2
_EPS_T = 1e-6


def unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def dot(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Dot product along the last axis, broadcasting.

    3-vectors are written out by component: on the planner's broadcast
    shapes (rays against points, (P, K, 3) with (P, 1, 3)) about twice as
    fast as ``np.einsum("...i,...i->...")``, which the day sweep calls
    ~20,000 times.
    """
    if a.shape[-1] == 3 and b.shape[-1] == 3:
        return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]
    return np.einsum("...i,...i->...", a, b)


def azimuth_deg(dx: ArrayLike, dy: ArrayLike) -> NDArray[np.float64]:
    """Azimuth clockwise from North in [0, 360)."""
    a = np.mod(np.degrees(np.arctan2(dx, dy)), 360.0)
    return np.where(a >= 360.0, 0.0, a)


def gaze_angles(camera_enu: ArrayLike, look_at_enu: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Heading and gimbal pitch pointing the optical axis from ``camera_enu`` at ``look_at_enu``.

    Parameters
    ----------
    camera_enu, look_at_enu : array_like, shape (..., 3)
        ENU metres.

    Returns
    -------
    heading_deg : ndarray
        Clockwise from North, [0, 360). For a point straight below it is 0.
    pitch_deg : ndarray
        Above the horizon positive, [-90, 90] (-90 = straight down).
    """
    d = np.asarray(look_at_enu, float) - np.asarray(camera_enu, float)
    horiz = np.hypot(d[..., 0], d[..., 1])
    return azimuth_deg(d[..., 0], d[..., 1]), np.degrees(np.arctan2(d[..., 2], horiz))


def optical_axis(heading_deg: ArrayLike, pitch_deg: ArrayLike) -> NDArray[np.float64]:
    """Unit ENU optical axis for a heading (clockwise from North) and a pitch (negative down), degrees."""
    h = np.radians(np.asarray(heading_deg, float))
    p = np.radians(np.asarray(pitch_deg, float))
    h, p = np.broadcast_arrays(h, p)
    return np.stack([np.cos(p) * np.sin(h), np.cos(p) * np.cos(h), np.sin(p)], axis=-1)


def camera_frame(heading_deg: NDArray[np.float64], pitch_deg: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
    """OpenCV camera axes in ENU (x right, y down, z forward) for zero roll."""
    f = optical_axis(heading_deg, pitch_deg)
    h = np.radians(heading_deg)
    r = np.stack([np.cos(h), -np.sin(h), np.zeros_like(h)], axis=-1)
    return r, np.cross(f, r), f


def in_fov(points: NDArray[np.float64], cam: NDArray[np.float64], heading: NDArray[np.float64],
            pitch: NDArray[np.float64], camera: CameraModel) -> NDArray[np.bool_]:
    """Whether ``points`` (..., K, 3) fall in the camera's field of view; cam/heading/pitch shape (...).

    A point is in view when it is in front of the camera (``z > 0`` in the
    OpenCV frame of :func:`camera_frame`) and within the sensor's half
    angles (``|x| <= z * w / 2f``, ``|y| <= z * h / 2f``; pinhole, no
    distortion). One compiled pass over the points
    (:func:`pihim.planning._kernels.in_fov`): the day sweep tests 400,000
    facet corners at a time.
    """
    from pihim.planning import _kernels

    r, dn, f = camera_frame(np.asarray(heading, float), np.asarray(pitch, float))
    pts = np.asarray(points, float)
    cam = np.asarray(cam, float)
    k = pts.shape[-2]
    lead = np.broadcast_shapes(pts.shape[:-2], cam.shape[:-1], r.shape[:-1])

    def flat(a: NDArray, tail: tuple[int, ...]) -> NDArray:
        out = np.ascontiguousarray(np.broadcast_to(a, (*lead, *tail)).reshape(-1, *tail))
        out.flags.writeable = False  # always read-only (broadcasts are, copies are not): one compiled signature
        return out

    tx = 0.5 * camera.width_px / camera.focal_length_px
    ty = 0.5 * camera.height_px / camera.focal_length_px
    out = _kernels.in_fov(flat(pts, (k, 3)), flat(cam, (3,)), flat(r, (3,)), flat(dn, (3,)), flat(f, (3,)),
                          float(tx), float(ty))
    return out.reshape(*lead, k)


def tower_box(tower: Any, clearance: float = 0.0) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    if tower is None:
        return None
    c = np.asarray(tower.box_corners(), float)
    return c.min(axis=0) - [clearance, clearance, 0.0], c.max(axis=0) + clearance


def segments_hit_box(p0: NDArray[np.float64], p1: NDArray[np.float64], lo: NDArray[np.float64],
                      hi: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Segments p0->p1 (N, 3) crossing the axis-aligned box [lo, hi] (slab method).

    One compiled pass (:func:`pihim.planning._kernels.segments_hit_box`; tested against the same slab test
    written with numpy).
    """
    from pihim.planning import _kernels

    p0 = np.ascontiguousarray(np.asarray(p0, float).reshape(-1, 3))
    p1 = np.ascontiguousarray(np.asarray(p1, float).reshape(-1, 3))
    return _kernels.segments_hit_box(p0, p1, np.ascontiguousarray(lo, float).reshape(3),
                                     np.ascontiguousarray(hi, float).reshape(3))


class GridCells(NamedTuple):
    """Points binned in a uniform grid over x, y (:func:`grid_cells`), as the compiled kernels read them.

    ``n_x`` x ``n_y`` cells of ``cell`` from ``(x0, y0)``; cell ``cx * n_y + cy``
    holds the points ``order[cell_start[c]:cell_start[c + 1]]``.
    """

    x0: float
    y0: float
    cell: float
    n_x: int
    n_y: int
    order: NDArray[np.int64]
    cell_start: NDArray[np.int64]


def grid_cells(xy: NDArray[np.float64], lo: NDArray[np.float64], span: NDArray[np.float64], cell: float) -> GridCells:
    """Bin points ``xy`` (N, 2) in cells of ``cell`` over ``lo`` to ``lo + span``.

    A point beyond the span goes to the nearest edge cell (a search whose cell
    range is clamped into the grid still meets it); a point with a coordinate
    that is not finite is in no cell.
    """
    finite = np.isfinite(xy).all(axis=1)
    n_x, n_y = (int(v) + 1 for v in np.floor(span / cell))
    x0, y0 = float(lo[0]), float(lo[1])
    with np.errstate(invalid="ignore", over="ignore"):
        cx = np.clip(np.floor((xy[:, 0] - x0) / cell), 0, n_x - 1)
        cy = np.clip(np.floor((xy[:, 1] - y0) / cell), 0, n_y - 1)
    key = np.where(finite, np.nan_to_num(cx) * n_y + np.nan_to_num(cy), n_x * n_y).astype(np.int64)
    order = np.argsort(key, kind="stable")
    cell_start = np.searchsorted(key[order], np.arange(n_x * n_y + 1)).astype(np.int64)
    return GridCells(x0, y0, float(cell), n_x, n_y, order, cell_start)


class MirrorIndex:
    """Tracked mirror rectangles of a field with a spatial index for batched ray tests.

    The index is a uniform grid over the mirror centres' x, y: it spans the
    bulk of the field (0.5th to 99.5th percentile of each coordinate; a centre
    beyond it goes to the nearest edge cell, so that one mistyped heliostat far
    away neither inflates the cells nor is lost), with cells about the size of
    a mirror's diagonal, larger in a sparse field so that there are at most
    about ``3 (4 N + 10,000)`` of them. A segment is tested against the mirrors
    of the cells its x, y bounding box, grown by the half-diagonal, meets
    (:func:`pihim.planning._kernels.grid_first_hits`, one compiled pass, no
    candidate lists).
    """

    def __init__(self, pose: FieldPose) -> None:
        spec = pose.field.spec  # type: ignore[attr-defined]
        self.centres = np.ascontiguousarray(pose.mirror_centres, dtype=float)
        self.x = np.ascontiguousarray(pose.rotations[:, :, 0])
        self.y = np.ascontiguousarray(pose.rotations[:, :, 1])
        self.n = np.ascontiguousarray(pose.normals)
        self.hw = float(spec.mirror_half_width_m)
        self.hh = float(spec.mirror_half_height_m)
        self.radius = math.hypot(self.hw, self.hh)
        xy = self.centres[:, :2]
        finite = np.isfinite(xy).all(axis=1)
        lo, hi = np.percentile(xy[finite], [0.5, 99.5], axis=0) if finite.any() else np.zeros((2, 2))
        span = hi - lo
        budget = 4 * len(xy) + 10_000  # cells: about (span_x / cell + 1) (span_y / cell + 1), kept below ~3 budget
        cell = max(2.0 * self.radius, math.sqrt(float(span[0]) * float(span[1]) / budget),
                   float(span[0] + span[1]) / budget, 1e-3)
        if not (math.isfinite(cell) and np.isfinite(lo).all()):  # coordinates near the float limits: one cell
            lo, span, cell = np.zeros(2), np.zeros(2), 1.0
        self.x0, self.y0, self.cell, self.n_x, self.n_y, self.order, self.cell_start = grid_cells(xy, lo, span, cell)

    def first_hits(self, p0: NDArray[np.float64], p1: NDArray[np.float64], exclude: NDArray[np.int64],
                   chunk: int = 50_000) -> NDArray[np.int64]:
        """Index of the first mirror each segment p0->p1 crosses (-1 for none), skipping ``exclude`` (N, E).

        A crossing counts strictly inside the segment; of two mirrors crossed
        at the same point the lower index is reported."""
        n = len(p0)
        out = np.full(n, -1, dtype=np.int64)
        if n == 0:
            return out
        from pihim.planning import _kernels

        ex = np.ascontiguousarray(exclude, np.int64).reshape(n, -1)
        for a in range(0, n, chunk):
            b = min(n, a + chunk)
            out[a:b] = _kernels.grid_first_hits(
                np.ascontiguousarray(p0[a:b], float), np.ascontiguousarray(p1[a:b], float), ex[a:b], self.order,
                self.cell_start, self.x0, self.y0, self.cell, self.n_x, self.n_y, self.centres, self.n, self.x,
                self.y, self.hw, self.hh, self.radius, _EPS_T)
        return out


def first_mirror_hits(pose: FieldPose, p0: ArrayLike, p1: ArrayLike, *,
                      exclude: ArrayLike | None = None) -> NDArray[np.int64]:
    """First tracked mirror rectangle crossed by each segment ``p0 -> p1``, vectorised.

    Parameters
    ----------
    pose : FieldPose
        Tracked field; mirrors are its flat outlines (``mirror_half_width_m``
        x ``mirror_half_height_m`` around each mirror centre, in the mirror
        plane).
    p0, p1 : array_like, shape (N, 3)
        Segment ends, ENU metres.
    exclude : array_like of int, shape (N,) or (N, E), optional
        Heliostat indices ignored per segment (e.g. the HUA and the target);
        -1 entries ignore nothing.

    Returns
    -------
    ndarray of int, shape (N,)
        Index of the first heliostat hit along the segment, -1 if none.
    """
    a = np.atleast_2d(np.asarray(p0, float))
    b = np.atleast_2d(np.asarray(p1, float))
    if a.shape != b.shape or a.shape[-1] != 3:
        raise PihimInputError(f"p0 and p1 must both be (N, 3), got {a.shape} and {b.shape}")
    ex = np.full((len(a), 1), -1, dtype=np.int64) if exclude is None else np.asarray(exclude, dtype=np.int64)
    if ex.ndim == 1:
        ex = ex[:, None]
    return mirror_index(pose).first_hits(a, b, ex)


_INDEXES: weakref.WeakKeyDictionary[Any, MirrorIndex] = weakref.WeakKeyDictionary()


def mirror_index(pose: FieldPose) -> MirrorIndex:
    """The :class:`MirrorIndex` of a pose, built once per pose and kept while the pose lives.

    (Scoring tests sight lines pass by pass; building the index over the
    whole field each time made it quadratic in the field size.)
    """
    try:
        return _INDEXES[pose]
    except (KeyError, TypeError):
        pass
    index = MirrorIndex(pose)
    try:
        _INDEXES[pose] = index
    except TypeError:  # pragma: no cover - a pose that cannot be weakly referenced
        pass
    return index
