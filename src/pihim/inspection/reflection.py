"""The target's reflection in a HUA facet, as the canting estimator models it.

A facet is a small plane mirror: the camera sees the target through it as
the target's mirror image in the facet's plane. This module holds that
forward model, independent of the renderer's ray tracer that makes the test
frames: the target's outline (:func:`target_outline_segments`), the facets'
image masks, the projection of the mirrored outline for candidate canting
angles (``_FacetModel``, projections held to ``cv2.projectPoints`` through
:mod:`pihim.inspection._kernels`) or for candidate drive-angle errors of the
HUA (``_TurnModel``), and how a HUA turned from its logged drive angles
sees the world through a camera pose fitted on it (:func:`hua_turn_transform`).
Used by :mod:`pihim.inspection.canting` and :mod:`pihim.inspection.orientation`.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose
from pihim.field.kinematics import FieldPose, apply_canting_deviation
from pihim.inspection.pose import facet_outline_segments
from pihim.render.scene import StructureSizes

__all__ = ["facet_in_view", "hua_turn_transform", "target_outline_segments"]


def target_outline_segments(field_pose: FieldPose, index: int, sizes: StructureSizes = StructureSizes()) -> NDArray:
    """What the target's back shows a HUA: its facet outlines and the long edges of its back-structure members.

    The members (:func:`pihim.field.kinematics.back_structure`, widths
    :class:`pihim.render.scene.StructureSizes`) stand between the target's
    facets and the HUA, so their edges are as much part of the reflected
    picture as the facets'. Each member contributes the four long edges of its
    square section (two of them hidden from any one view; the robust fit
    ignores those).
    """
    corners = field_pose.facet_corners()[index]
    segs = [facet_outline_segments(corners)]
    back = field_pose.back_structure()
    rot = field_pose.rotations[index]
    for k, kind in enumerate(back.kinds):
        if kind == "pedestal":
            continue
        p0, p1 = back.segments[index, k]
        a = (p1 - p0) / np.linalg.norm(p1 - p0)
        b = rot[:, 2] - np.dot(rot[:, 2], a) * a  # across the member, along the mirror normal
        b /= np.linalg.norm(b)
        c = np.cross(a, b)
        half = 0.5 * sizes.width(kind)
        for sb in (-1.0, 1.0):
            for sc in (-1.0, 1.0):
                off = half * (sb * b + sc * c)
                segs.append(np.array([[p0 + off, p1 + off]]))
    return np.concatenate(segs)


class _Mask:
    """A boolean image mask stored as its bounding box: ``sub`` at rows ``r0..``, columns ``c0..``
    of an image of ``shape``; everything outside the box is False."""

    def __init__(self, shape: tuple[int, int], r0: int = 0, c0: int = 0, sub: NDArray | None = None):
        self.shape = shape
        self.r0, self.c0 = int(r0), int(c0)
        self.sub = np.zeros((0, 0), bool) if sub is None else sub

    def full(self) -> NDArray[np.bool_]:
        """The mask as a whole image."""
        m = np.zeros(self.shape, bool)
        hh, ww = self.sub.shape
        m[self.r0:self.r0 + hh, self.c0:self.c0 + ww] = self.sub
        return m

    def area(self) -> int:
        return int(self.sub.sum())

    def values(self, img: NDArray) -> NDArray:
        """``img[mask]`` (same order)."""
        hh, ww = self.sub.shape
        return img[self.r0:self.r0 + hh, self.c0:self.c0 + ww][self.sub]

    def extent(self) -> tuple[int, int, int, int] | None:
        """First and last row and column that hold a True pixel (None if none)."""
        rows = np.flatnonzero(self.sub.any(axis=1))
        cols = np.flatnonzero(self.sub.any(axis=0))
        if rows.size == 0:
            return None
        return self.r0 + rows[0], self.r0 + rows[-1], self.c0 + cols[0], self.c0 + cols[-1]

    def inside(self, uv: NDArray) -> NDArray[np.bool_]:
        """Whether each pixel position ``uv`` (N, 2), rounded to the nearest pixel, is in the mask."""
        hh, ww = self.sub.shape
        out = np.zeros(len(uv), bool)
        with np.errstate(invalid="ignore"):
            box = (uv[:, 0] > self.c0 - 0.5 - 1) & (uv[:, 0] < self.c0 + ww + 0.5) \
                & (uv[:, 1] > self.r0 - 0.5 - 1) & (uv[:, 1] < self.r0 + hh + 0.5)
        k = np.flatnonzero(box)
        i = np.rint(uv[k, 1]).astype(int) - self.r0
        j = np.rint(uv[k, 0]).astype(int) - self.c0
        ok = (i >= 0) & (i < hh) & (j >= 0) & (j < ww)
        out[k[ok]] = self.sub[i[ok], j[ok]]
        return out


def _outline_rings(corners: NDArray, per_side: int = 24) -> NDArray[np.float64]:
    """Points along each facet's outline, ``per_side`` a side from each corner on: shape (F, 4 * per_side, 3)."""
    c = np.asarray(corners, dtype=float)
    t = np.linspace(0.0, 1.0, per_side, endpoint=False)[None, None, :, None]
    start, end = c[:, :, None, :], np.roll(c, -1, axis=1)[:, :, None, :]
    return (start + t * (end - start)).reshape(c.shape[0], 4 * per_side, 3)


def facet_in_view(camera: CameraModel, pose: CameraPose, corners: ArrayLike) -> NDArray[np.float64]:
    """Share of each facet's outline that the camera sees inside its frame.

    Parameters
    ----------
    camera : CameraModel
    pose : CameraPose
    corners : array_like, shape (F, 4, 3)
        Each facet's corners, field ENU metres, in order round the facet.

    Returns
    -------
    ndarray, shape (F,)
        The share, in [0, 1], of 96 points spread evenly along the outline whose projection falls on the
        sensor (pixel centres 0 .. width - 1 and 0 .. height - 1, half a pixel of border included); a point
        behind the camera counts as out of view. Occlusion is not considered.
    """
    from pihim.inspection import _kernels

    rings = _outline_rings(np.asarray(corners, dtype=float))
    uv = _kernels.project_pose(camera, pose, rings.reshape(-1, 3)).reshape(rings.shape[0], rings.shape[1], 2)
    with np.errstate(invalid="ignore"):
        inside = (uv[..., 0] >= -0.5) & (uv[..., 0] < camera.width_px - 0.5) \
            & (uv[..., 1] >= -0.5) & (uv[..., 1] < camera.height_px - 0.5)
    return inside.mean(axis=1)


def _facet_masks(camera: CameraModel, pose: CameraPose, corners: NDArray, margin_px: float) -> list[_Mask]:
    """Masks of each facet's projected outline, eroded by ``margin_px`` (filled and eroded
    on the outline's bounding box grown by the kernel: the same pixels as on the whole image)."""
    import cv2

    from pihim.inspection import _kernels

    shape = (camera.height_px, camera.width_px)
    masks = []
    k = max(1, int(round(2 * margin_px + 1)))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    for ring in _outline_rings(corners):
        uv = _kernels.project_pose(camera, pose, ring)
        if not np.all(np.isfinite(uv)):
            masks.append(_Mask(shape))
            continue
        poly = np.rint(uv).astype(np.int32)
        lo = np.maximum(poly.min(axis=0) - k, 0)
        hi = np.minimum(poly.max(axis=0) + k + 1, [shape[1], shape[0]])
        if np.any(hi <= lo):
            masks.append(_Mask(shape))
            continue
        m = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.uint8)
        cv2.fillPoly(m, [poly - lo.astype(np.int32)], 1)
        masks.append(_Mask(shape, lo[1], lo[0], cv2.erode(m, kernel).astype(bool)))
    return masks


def _quadratic_basis(a: NDArray, e: NDArray) -> NDArray:
    return np.stack([np.ones_like(a), a, e, a * a, e * e, a * e], axis=1)


@functools.lru_cache(maxsize=64)
def _quadratic_nodes(s: float) -> tuple[NDArray, NDArray, NDArray]:
    """The nodes ``{-s, 0, s}^2`` (az and el, az major) of a quadratic's fit and the least-squares matrix (6, 9)
    that turns their projections into its coefficients (:meth:`_FacetModel.quadratic_coefficients`)."""
    k = np.array([-s, 0.0, s])
    na, ne = (g.ravel() for g in np.meshgrid(k, k, indexing="ij"))
    return na, ne, np.linalg.pinv(_quadratic_basis(na, ne))


class _FacetModel:
    """The target's outlines reflected in one HUA facet, projected for candidate canting angles."""

    def __init__(self, camera, pose, rot_hua, centre, normal_local, pts, seg):
        from pihim.inspection import _kernels

        self.camera, self.pose, self.rot, self.centre = camera, pose, rot_hua, centre
        self.normal_local, self.pts = normal_local, np.ascontiguousarray(pts, dtype=float)
        self.seg = np.ascontiguousarray(seg, dtype=np.int64)
        self._cam = _kernels.camera_vector(camera)
        self._r = np.array(pose.rotation, float)
        self._c = np.array(pose.position_m, float)
        #: The facet for the ``REFLECTION`` problems (:func:`pihim.inspection._kernels.problem`'s ``aux``).
        self.aux = np.concatenate([np.ravel(rot_hua), centre, normal_local])
        self._motion: float | None = None  # motion_px_per_mrad, once measured

    def _with(self, pts: NDArray, seg: NDArray) -> _FacetModel:
        """The same model on other sample points."""
        return _FacetModel(self.camera, self.pose, self.rot, self.centre, self.normal_local, pts, seg)

    def subsampled(self, k: int) -> _FacetModel:
        """The same model with every ``k``-th sample point (a cheaper score for the grid search)."""
        return self._with(self.pts[::k], self.seg[::k])

    def near(self, mask: _Mask, span_mrad: float, margin_px: float = 20.0,
             centre_mrad: tuple[float, float] = (0.0, 0.0)) -> _FacetModel:
        """The model restricted to the points that can reach the facet's mask within the search span.

        A point is kept if its projection at the search centre ``centre_mrad``
        lies inside the mask's bounding box grown by ``margin_px`` plus the
        largest move of any point between the centre and the corners of the
        ``+-span_mrad`` grid around it (measured on every 16th point; the
        reflection moves almost affinely with the angles).
        """
        ext = mask.extent()
        if ext is None:
            return self
        r_lo, r_hi, c_lo, c_hi = ext
        s = float(span_mrad)
        a0, e0 = (float(v) for v in centre_mrad)
        sub = self.project_many(a0 + np.array([0.0, -s, -s, s, s]), e0 + np.array([0.0, -s, s, -s, s]),
                                self.pts[::16])
        reach = float(np.nanmax(np.linalg.norm(sub[1:] - sub[:1], axis=2), initial=0.0))
        grow = margin_px + reach
        uv = self.project_many(np.array([a0]), np.array([e0]))[0]
        keep = (uv[:, 0] >= c_lo - grow) & (uv[:, 0] <= c_hi + grow) \
            & (uv[:, 1] >= r_lo - grow) & (uv[:, 1] <= r_hi + grow)
        return self._with(self.pts[keep], self.seg[keep])

    def quadratic_coefficients(self, s: float, centre_mrad: tuple[float, float] = (0.0, 0.0)) -> NDArray:
        """Coefficients (6, N, 2) of each point's pixel as a quadratic in the angles (mrad)
        measured from ``centre_mrad``, on the basis ``(1, az, el, az^2, el^2, az el)``.

        Exact projections on the 3 x 3 grid ``centre + {-s, 0, s}^2`` fix the
        quadratic (least squares on the nine nodes); its error is third order,
        far below a pixel over +-17.5 mrad, and it costs nine projections
        instead of one per grid node (the refinement projects exactly:
        :func:`pihim.inspection._kernels.refine_reflection`).
        """
        return self.quadratic_blocks(s, [centre_mrad])[0]

    def quadratic_blocks(self, s: float, centres_mrad: list[tuple[float, float]]) -> NDArray:
        """:meth:`quadratic_coefficients` (B, 6, N, 2) around each of B centres: one projection of all their
        nodes."""
        na, ne, fit = _quadratic_nodes(float(s))
        c = np.asarray(centres_mrad, float).reshape(-1, 2)
        uv = self.project_many((c[:, :1] + na).ravel(), (c[:, 1:] + ne).ravel())  # (9 B, N, 2)
        return (fit @ uv.reshape(len(c), 9, -1)).reshape(len(c), 6, -1, 2)

    def project_quadratic(self, az_mrad: NDArray, el_mrad: NDArray) -> NDArray:
        """Projected points (G, N, 2) for G angle pairs, to second order in the angles
        (:meth:`quadratic_coefficients` with ``s`` the largest ``|angle|`` asked for)."""
        az = np.asarray(az_mrad, float)
        el = np.asarray(el_mrad, float)
        s = max(float(np.max(np.abs(az), initial=0.0)), float(np.max(np.abs(el), initial=0.0)), 1.0)
        coef = self.quadratic_coefficients(s)
        return (_quadratic_basis(az, el) @ coef.reshape(6, -1)).reshape(len(az), -1, 2)

    def project_many(self, az_mrad: NDArray, el_mrad: NDArray, pts: NDArray | None = None) -> NDArray:
        """Projected points (G, N, 2) for G candidate angle pairs at once (no normals)."""
        pts = self.pts if pts is None else pts
        n = apply_canting_deviation(self.normal_local, az_mrad, el_mrad) @ self.rot.T  # (G, 3)
        return self._mirror(pts, n, np.zeros((0, 3, 3)), np.zeros(3))

    def _mirror(self, pts: NDArray, normals: NDArray, turns: NDArray, pivot: NDArray) -> NDArray:
        """:func:`pihim.inspection._kernels.mirror_project` on this model's facet and camera."""
        from pihim.inspection import _kernels

        return _kernels.mirror_project(np.ascontiguousarray(pts, dtype=float),
                                       np.ascontiguousarray(np.reshape(normals, (-1, 3)), dtype=float),
                                       np.asarray(self.centre, float), np.ascontiguousarray(turns, dtype=float),
                                       np.asarray(pivot, float), self._r, self._c, self._cam)

    def motion_px_per_mrad(self) -> float:
        """A bound of how far any point's projection moves per mrad of canting, px: twice the largest, over
        every 16th point, of the norm of its pixel's derivatives by the two angles (differences over 1 mrad
        at the design; the reflection moves almost affinely with the angles)."""
        bound = self._motion
        if bound is None:
            uv = _FacetModel.project_many(self, np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]), self.pts[::16])
            d = np.hypot(np.linalg.norm(uv[1] - uv[0], axis=1), np.linalg.norm(uv[2] - uv[0], axis=1))
            bound = self._motion = 2.0 * float(np.nanmax(d, initial=0.0))
        return bound


class _TurnModel(_FacetModel):
    """The target reflected in one HUA facet (design canting) when the HUA is turned from its logged drive angles.

    The two angles of :meth:`project_many` (and so of the quadratic and of
    :func:`search_orientation`) are the HUA's drive-angle errors, azimuth and
    elevation in mrad, instead of a facet's canting: the camera pose is
    fitted on the HUA at its logged angles, so a HUA turned by them sees the
    target as the world turned back about its pivot (:func:`hua_turn_transform`).
    """

    def __init__(self, base: _FacetModel, drive_deg: tuple[float, float], pivot: NDArray):
        super().__init__(base.camera, base.pose, base.rot, base.centre, base.normal_local, base.pts, base.seg)
        self.drive_deg, self.pivot = drive_deg, np.asarray(pivot, float)

    def _with(self, pts: NDArray, seg: NDArray) -> _TurnModel:
        return _TurnModel(super()._with(pts, seg), self.drive_deg, self.pivot)

    def project_many(self, az_mrad: NDArray, el_mrad: NDArray, pts: NDArray | None = None) -> NDArray:
        from pihim.field.kinematics import rotation_from_drive

        pts = self.pts if pts is None else pts
        to_deg = 180.0 / math.pi * 1e-3
        az = self.drive_deg[0] + np.asarray(az_mrad, float) * to_deg
        el = self.drive_deg[1] + np.asarray(el_mrad, float) * to_deg
        m = self.rot @ np.swapaxes(rotation_from_drive(az, el), -1, -2)  # (G, 3, 3): logged from true
        n = self.rot @ self.normal_local
        return self._mirror(pts, np.broadcast_to(n, (len(m), 3)), m, self.pivot)


def _equivalent_tilt(model: _FacetModel, turned: _TurnModel, turn_mrad: tuple[float, float],
                     subsample: int = 8) -> tuple[float, float]:
    """The facet tilt (canting angles, mrad) that moves the facet's reflection of the target as the HUA's turn
    ``turn_mrad`` does: Gauss-Newton on the projected outline points (every ``subsample``-th), from no tilt.

    To first order a turn of the HUA and a common tilt of its facets move the
    target's reflection alike; they differ by the target's distortion (a
    pixel or so per 0.1 deg), which the least squares averages over.
    """
    pts = model.pts[::subsample]
    if len(pts) < 3:
        return 0.0, 0.0
    goal = turned.project_many(np.array([turn_mrad[0]]), np.array([turn_mrad[1]]), pts)[0].ravel()
    x = np.zeros(2)
    h = 0.5
    for _ in range(4):
        uv = model.project_many(x[0] + np.array([0.0, h, 0.0]), x[1] + np.array([0.0, 0.0, h]), pts)
        r = goal - uv[0].ravel()
        jac = np.column_stack([(uv[1] - uv[0]).ravel() / h, (uv[2] - uv[0]).ravel() / h])
        ok = np.isfinite(r) & np.all(np.isfinite(jac), axis=1)
        if ok.sum() < 3:
            return 0.0, 0.0
        dx = np.linalg.lstsq(jac[ok], r[ok], rcond=None)[0]
        x += dx
        if np.max(np.abs(dx)) < 1e-3:
            break
    return float(x[0]), float(x[1])


def hua_turn_transform(field_pose: FieldPose, index: int, d_az_deg: float, d_el_deg: float) -> tuple[NDArray, NDArray]:
    """How the world looks from a camera pose fitted on a heliostat that is turned from its logged drive angles.

    A camera pose refined on the HUA's outline at its logged drive angles
    (:func:`pihim.inspection.pose.refine_pose`) is right *relative to the
    HUA*. If the HUA is really at ``logged + (d_az, d_el)``, every other
    point ``p`` of the world (the target) sits, in that pose's frame, at
    ``pivot + M (p - pivot)`` with ``M = R_logged R_true^T`` (drive frames,
    :func:`pihim.field.kinematics.rotation_from_drive`) and ``pivot`` the
    HUA's torque-tube pivot. Returns ``(pivot, M)``.
    """
    from pihim.field.kinematics import rotation_from_drive

    d = field_pose.drive
    az, el = float(d.azimuth_deg[index]), float(d.elevation_deg[index])
    r_log = rotation_from_drive(az, el)
    r_true = rotation_from_drive(az + d_az_deg, el + d_el_deg)
    offset = float(field_pose.field.spec.pivot_offset_m)  # type: ignore[attr-defined]
    pivot = field_pose.mirror_centres[index] - offset * field_pose.rotations[index][:, 2]
    return pivot, r_log @ r_true.T


def _apply(world: tuple[NDArray, NDArray] | None, pts: NDArray) -> NDArray:
    """``pivot + M (p - pivot)`` for each point (the identity for ``world=None``)."""
    if world is None:
        return pts
    pivot, m = world
    return pivot + (pts - pivot) @ m.T
