"""Per-facet canting from the target's reflection in the HUA (paper sec. 4.4, steps 3-4).

A facet is a small plane mirror: the camera sees the target heliostat through
it as the **mirror image** of the target in the facet's plane. The target's
facet outlines (known from the field model and its logged drive angles),
reflected in facet ``k``'s plane and projected with the (refined) camera
pose, fall where the image shows the target's edges inside facet ``k``. The
facet's two canting angles move them: a tilt ``d`` turns the reflected rays by
``2 d``, which at the usual UFACET geometry moves the reflection by several
pixels per mrad.

The heliostat's **orientation** (the paper's relative-orientation step):
the camera pose is refined on the HUA's outline at its *logged* drive
angles, so it is right relative to the HUA; a HUA really turned from those
angles sees the target turned back about the HUA's pivot
(:func:`hua_turn_transform`): moved by the turn times the distance (tens of
centimetres per 0.5 deg) *and* turned about itself, which distorts its
reflection by several pixels, more than a facet's canting can absorb.
:func:`search_orientation` turns the HUA's drive angles over the paper's
+-5 deg in 0.1 deg steps and finds the node where the facets' reflections
of the target best line up with the image's edges; the facets are fitted on
the target's outline turned by it, and on the logged outline, and the turn
is kept if it measures at least as many facets (the search proposes, the
facet fits decide: clutter can raise a false peak).

Optionally (``target_orientation=True``) the **target's** logged drive
angles are corrected too, as the paper does: a target off its logged
orientation has a distorted outline in the model, and the facets' fits miss
by a few pixels; :func:`refine_target_orientation` solves the target's two
angles with every facet's canting, and the facets are fitted again on the
corrected outline.

Then for each facet:

1. **Baseline** (the paper's method): a grid search over azimuth and
   elevation deviations with the paper's step, 0.1 deg = 1.745 mrad, scored by
   the share of the projected model points that lie within 5 px of an image
   edge (a truncated chamfer score).
2. **Refinement**: from the best grid node, Levenberg-Marquardt on the
   point-to-line distances between the image's sub-pixel edge points inside
   the facet and the projected reflected outlines, re-matched with a
   shrinking gate; the uncertainty is the standard error from the residuals
   and the Jacobian.

A rotation common to every facet cannot be told from a heliostat pointing
(or camera pose) error, so :class:`CantingResult` reports each facet's
deviation **relative to the best-fit heliostat orientation** (the mean over
the facets used) and that orientation separately.

The estimator reads the frame and the ``log`` only; its forward model is
projection of mirrored points (the compiled projection of
:mod:`pihim.inspection._kernels`, held to ``cv2.projectPoints``), independent
of the renderer's ray tracer that made the test frames.

Status (measured on 20 rendered NSTTF UFACET frames, ``benchmarks/canting_quality.py``)
-----------------------------------------------------------------------------------
From the issue's GPS 1.5 m / attitude 1 deg priors (pose refined to 0.27 px
median at the HUA's corners) and S0 edge points (the DoLP of the dark target
back is too noisy at 39 dB to add its edges unweighted), 0-10 facets per
frame pass the quality gates and their deviations are recovered to 0.18 /
0.30 mrad RMS (azimuth / elevation; the HUA's drive-angle correction to
0.17 / 0.13 mrad) against 1.48 / 2.07 mrad for the paper's grid search on
the same frames; a median 1.8 s per frame for the whole chain (1.1 s of it
this step's CPU). With every heliostat's logged drive angles off by
N(0, 5 mrad), ``target_orientation=True`` measures 40 facets on 10 frames
(44 without the error) to 0.33 / 0.54 mrad at about 2 s more CPU; without
it, 7 (BENCHMARKS.md). Not yet: polarimetric edge weighting.

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone", sec. 4.4 and Fig. 8 (grid search +-5 deg at 0.1 deg,
   facet canting deviations relative to the design).
.. [2] Sandia National Laboratories, OpenCSP UFACET (the reflected-target
   principle of facet canting measurement).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose
from pihim.errors import PihimInputError
from pihim.field.kinematics import FieldPose, apply_canting_deviation
from pihim.inspection.features import EdgePoints
from pihim.inspection.pose import facet_outline_segments, line_normals, match_edge_points, sample_segments
from pihim.render.scene import StructureSizes

__all__ = ["CantingResult", "FacetCanting", "OrientationSearch", "PAPER_GRID_STEP_MRAD", "PAPER_ORIENTATION_SPAN_MRAD",
           "drive_correction", "estimate_canting", "hua_turn_transform", "refine_orientations",
           "refine_target_orientation", "search_orientation", "target_outline_segments"]

#: Scale of the two canting angles in the refinement, mrad.
_X_SCALE = np.array([0.1, 0.1])

#: The paper's grid step, 0.1 deg, in mrad.
PAPER_GRID_STEP_MRAD = float(np.radians(0.1) * 1e3)


#: Half-range of the paper's heliostat orientation search, +-5 deg, in mrad.
PAPER_ORIENTATION_SPAN_MRAD = float(np.radians(5.0) * 1e3)


@dataclass(frozen=True)
class OrientationSearch:
    """The paper's orientation grid search: the HUA's drive-angle error.

    Paper sec. 4.4: the relative orientation of the HUA and the target is
    corrected over +-5 deg in 0.1 deg steps until the facets' reflections of
    the target line up, before any facet is fitted; a facet's own search then
    spans +-1 deg around it. ``az_mrad`` / ``el_mrad`` are the HUA's drive
    azimuth and elevation errors (true minus logged, mrad) at the best grid
    node (:func:`hua_turn_transform`); ``score`` is the mean over the
    ``facets`` scored of the share of each facet's reflected target outline
    points that fall inside the facet within ``tol_px`` of an image edge
    there. ``alternatives`` are the next-best distinct peaks, ``(az_mrad,
    el_mrad, score)``, best first (at least half the best score), reported
    so that a user can see how clear the peak was: clutter can raise a false
    peak above the true one (the facet fits then keep the logged angles).
    """

    az_mrad: float
    el_mrad: float
    score: float
    facets: int
    span_mrad: float
    step_mrad: float
    tol_px: float
    seconds: float
    alternatives: tuple[tuple[float, float, float], ...] = ()

    def to_dict(self) -> dict[str, object]:
        out = {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in self.__dict__.items()}
        out["alternatives"] = [{"az_mrad": a, "el_mrad": e, "score": sc} for a, e, sc in self.alternatives]
        return out


@dataclass(frozen=True)
class FacetCanting:
    """One facet's estimate (mrad, heliostat frame, conventions of :mod:`pihim.field.kinematics`).

    ``az_mrad`` / ``el_mrad`` are relative to the best-fit heliostat
    orientation; ``grid_*`` are the paper's grid-search values (same
    reference); ``used`` is False with ``reason`` for a skipped facet.
    """

    id: int
    used: bool
    reason: str | None = None
    az_mrad: float | None = None
    el_mrad: float | None = None
    az_sigma_mrad: float | None = None
    el_sigma_mrad: float | None = None
    grid_az_mrad: float | None = None
    grid_el_mrad: float | None = None
    points: int = 0
    rms_px: float | None = None
    support: float | None = None

    def to_dict(self) -> dict[str, object]:
        return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class CantingResult:
    """Canting of one HUA from one or more frames.

    Attributes
    ----------
    facets : tuple of FacetCanting
        In facet order 1..F.
    orientation_az_mrad, orientation_el_mrad : float
        Best-fit heliostat orientation: the mean raw facet rotation of the
        used facets (what the relative deviations are relative to).
    search : OrientationSearch or None
        The paper's +-5 deg orientation grid search the facet fits started
        from (None when it was not run).
    drive_correction_deg : (float, float) or None
        Correction of the HUA's logged drive angles, (azimuth, elevation) in
        degrees: the orientation search's turn where the facets were fitted
        on it, plus the drive-angle change that turns the heliostat's normal
        as the best-fit orientation does (a rotation common to the facets
        cannot be told from the HUA's turn, so their mean canting is in it).
    target_correction_deg : (float, float) or None
        Correction of the target's logged drive angles (azimuth, elevation),
        degrees, when the facets were measured on the target's corrected
        outline (:func:`refine_target_orientation`); None when its logged
        angles were kept.
    """

    hua: str
    target: str
    facets: tuple[FacetCanting, ...]
    orientation_az_mrad: float | None
    orientation_el_mrad: float | None
    frames: int = 1
    notes: tuple[str, ...] = field(default_factory=tuple)
    search: OrientationSearch | None = None
    drive_correction_deg: tuple[float, float] | None = None
    target_correction_deg: tuple[float, float] | None = None

    def to_dict(self) -> dict[str, object]:
        return {
            "hua": self.hua,
            "target": self.target,
            "frames": self.frames,
            "reference": "facet deviations relative to the best-fit heliostat orientation (mean over used facets)",
            "orientation_mrad": None if self.orientation_az_mrad is None else
            {"az": float(self.orientation_az_mrad), "el": float(self.orientation_el_mrad)},
            "orientation_search": None if self.search is None else self.search.to_dict(),
            "drive_correction_deg": None if self.drive_correction_deg is None else
            {"az": float(self.drive_correction_deg[0]), "el": float(self.drive_correction_deg[1])},
            "target_correction_deg": None if self.target_correction_deg is None else
            {"az": float(self.target_correction_deg[0]), "el": float(self.target_correction_deg[1])},
            "facets": [f.to_dict() for f in self.facets],
            "notes": list(self.notes),
        }


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


def _facet_masks(camera: CameraModel, pose: CameraPose, corners: NDArray, margin_px: float) -> list[_Mask]:
    """Masks of each facet's projected outline, eroded by ``margin_px`` (filled and eroded
    on the outline's bounding box grown by the kernel: the same pixels as on the whole image)."""
    import cv2

    from pihim.inspection import _kernels

    shape = (camera.height_px, camera.width_px)
    masks = []
    k = max(1, int(round(2 * margin_px + 1)))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    t = np.linspace(0.0, 1.0, 24, endpoint=False)[:, None]
    for f in range(corners.shape[0]):
        ring = np.concatenate([corners[f, j] + t * (corners[f, (j + 1) % 4] - corners[f, j]) for j in range(4)])
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


class _FacetModel:
    """The target's outlines reflected in one HUA facet, projected for candidate canting angles."""

    def __init__(self, camera, pose, rot_hua, centre, normal_local, pts, seg):
        from pihim.inspection import _kernels

        self.camera, self.pose, self.rot, self.centre = camera, pose, rot_hua, centre
        self.normal_local, self.pts, self.seg = normal_local, np.ascontiguousarray(pts, dtype=float), seg
        self._cam = _kernels.camera_vector(camera)
        self._r = np.array(pose.rotation, float)
        self._c = np.array(pose.position_m, float)

    def _project(self, pts: NDArray) -> NDArray:
        from pihim.inspection import _kernels

        return _kernels.project_rc(self._r, self._c, np.ascontiguousarray(pts), self._cam)

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
        instead of one per grid node (the refinement uses :meth:`project`,
        exact).
        """
        k = np.array([-s, 0.0, s])
        na, ne = (g.ravel() for g in np.meshgrid(k, k, indexing="ij"))
        uv = self.project_many(na + centre_mrad[0], ne + centre_mrad[1])  # (9, N, 2)
        return (np.linalg.pinv(_quadratic_basis(na, ne)) @ uv.reshape(9, -1)).reshape(6, -1, 2)

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
        d = (pts - self.centre) @ n.T  # (N, G)
        virt = pts[None, :, :] - 2.0 * d.T[:, :, None] * n[:, None, :]
        return self._project(virt.reshape(-1, 3)).reshape(len(n), -1, 2)

    def project(self, az_mrad: float, el_mrad: float) -> tuple[NDArray, NDArray]:
        n = self.rot @ apply_canting_deviation(self.normal_local, az_mrad, el_mrad)
        virt = self.pts - 2.0 * ((self.pts - self.centre) @ n)[:, None] * n
        uv = self._project(virt)
        return uv, line_normals(uv, self.seg)


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
        world = self.pivot + np.einsum("gij,nj->gni", m, pts - self.pivot)  # (G, N, 3)
        n = self.rot @ self.normal_local
        virt = world - 2.0 * ((world - self.centre) @ n)[:, :, None] * n
        return self._project(virt.reshape(-1, 3)).reshape(len(m), -1, 2)


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


def _fit_facet(model: _FacetModel, mask: _Mask, obs: NDArray, dt: NDArray, span_mrad: float,
               step_mrad: float, gates_px: tuple[float, ...], grid_tol_px: float = 5.0,
               centre_mrad: tuple[float, float] = (0.0, 0.0), prefer_mrad: tuple[float, float] | None = None,
               ambiguity: float = 0.05, matches: list | None = None, max_peaks: int = 3,
               support_margin: float = 0.05) -> tuple:
    """(grid az, grid el, az, el, sigma az, sigma el, points, rms) for one facet (raw, not relative).

    The grid spans ``+-span_mrad`` around ``centre_mrad`` (the heliostat's
    orientation from :func:`search_orientation`, or the design). The grid
    values returned are the paper's (the best node); the refinement starts
    from each of up to ``max_peaks`` local peaks of the grid scoring within
    ``ambiguity`` of the best, nearest ``prefer_mrad`` (default the centre)
    first: the target's back is periodic (facet rows and columns,
    crossbars), so a facet that sees only part of it matches almost as well
    one period away (5-30 mrad at UFACET distances). The refined fit whose
    reflected outline lies best on the image's edges (support, the share
    within 1.5 px) wins; a farther peak must beat a nearer one by
    ``support_margin``. Two fits more than a grid step apart whose supports
    are within ``support_margin`` of each other leave the facet ambiguous:
    it is skipped (raises). Given a list ``matches``, the
    last round's matched model points (world), image points and line normals
    are appended to it as one tuple (for :func:`refine_target_orientation`).

    The refinement rounds solve the two angles by trust-region least squares with a soft-L1
    loss (scale 0.5 px) and the analytic Jacobian of the mirrored projection
    (:func:`pihim.inspection._kernels.solve`).
    """
    from pihim.inspection import _kernels

    # 1. the paper's grid search: every node of the grid, scored by the share of the reflected
    #    outline (inside the facet) within ``grid_tol_px`` of an image edge; the peak is narrow
    #    (a few px per mrad), so no coarser pre-search
    grid = np.arange(-span_mrad, span_mrad + 1e-9, step_mrad)
    gaz, gel = (g.ravel() for g in np.meshgrid(grid, grid, indexing="ij"))
    coarse_model = model.subsampled(6)  # every 6 cm of outline: the score is a share, not a sum
    # every grid node at once, from the quadratic through the nodes {-s, 0, s}^2
    coef = coarse_model.quadratic_coefficients(max(float(np.max(np.abs(grid))), 1.0), centre_mrad)
    hh, ww = mask.sub.shape
    dt_crop = np.ascontiguousarray(dt[mask.r0:mask.r0 + hh, mask.c0:mask.c0 + ww])
    score = _kernels.grid_scores(coef, grid, grid, mask.sub, mask.r0, mask.c0, dt_crop, float(grid_tol_px), 10)
    k = int(np.argmax(score))  # first maximum: the same node the loop over az, then el, kept
    g_best = (float(score[k]), float(gaz[k]) + centre_mrad[0], float(gel[k]) + centre_mrad[1])
    if g_best[0] < 0:
        raise PihimInputError("no reflected target outline falls inside this facet")
    grid_az, grid_el = g_best[1], g_best[2]
    # 2. continuous refinement: point-to-line ICP with LM, from each distinct near-best peak of the grid (the
    #    nearest the preferred angles first); the refined fit whose outline is best supported by the image wins
    pa, pe = centre_mrad if prefer_mrad is None else prefer_mrad
    from scipy import ndimage

    n_g = len(grid)
    sc = score.reshape(n_g, n_g)
    peaks = np.flatnonzero(((sc == ndimage.maximum_filter(sc, size=5, mode="nearest"))
                            & (sc >= (1.0 - ambiguity) * g_best[0])).ravel())
    if peaks.size == 0:
        peaks = np.array([k])
    peaks = peaks[np.argsort((gaz[peaks] + centre_mrad[0] - pa) ** 2 + (gel[peaks] + centre_mrad[1] - pe) ** 2)]
    ob = obs[mask.inside(obs)]
    if len(ob) < 20:
        raise PihimInputError("too few edge points inside this facet")
    fits = []
    error: PihimInputError | None = None
    for k0 in peaks[:max_peaks]:
        try:
            fits.append(_refine_facet(model, mask, ob, dt, gates_px, float(gaz[k0]) + centre_mrad[0],
                                      float(gel[k0]) + centre_mrad[1]))
        except PihimInputError as exc:
            error = exc
    if not fits:
        assert error is not None
        raise error
    best = fits[0]
    for fit in fits[1:]:  # a farther peak must be clearly better supported to displace a nearer one
        if fit[6] > best[6] + support_margin:
            best = fit
    # two distinct fits that the image supports alike: the facet shows too little of the target to tell them
    # apart (a part of its back whose edges repeat), and either would be a made-up number
    for fit in fits:
        apart = math.hypot(fit[0] - best[0], fit[1] - best[1])
        if fit is not best and apart > step_mrad and fit[6] >= best[6] - support_margin:
            raise PihimInputError(f"two fits {apart:.1f} mrad apart explain it alike (support {best[6]:.2f} and "
                                  f"{fit[6]:.2f})")
    az, el, sa, se, n, rms, support, found = best
    if matches is not None:
        matches.append(found)
    return grid_az, grid_el, az, el, sa, se, n, rms, support


def _refine_facet(model: _FacetModel, mask: _Mask, ob: NDArray, dt: NDArray, gates_px: tuple[float, ...],
                  az: float, el: float) -> tuple:
    """Point-to-line ICP with LM from ``(az, el)``: (az, el, sigma az, sigma el, points, rms, support, matches)."""
    from pihim.inspection import _kernels

    aux = np.concatenate([np.ravel(model.rot), model.centre, model.normal_local])
    jac = None
    r = np.zeros(0)
    for gate in gates_px:
        uv, nrm = model.project(az, el)
        ins = mask.inside(uv) & np.all(np.isfinite(nrm), axis=1)
        if ins.sum() < 20:
            raise PihimInputError("the reflected target leaves the facet")
        idx, q = match_edge_points(uv, ins, ob, gate, 15, "the reflected target")
        # only the matched model points move; their line normals are held for the round (the
        # outline barely turns over a round's few mrad) and re-taken at the next re-match
        used_pts, inv = np.unique(idx, return_inverse=True)
        sub, nq = model.pts[used_pts], nrm[idx]

        prob = _kernels.problem(_kernels.REFLECTION, model._r, model._c, sub, model._cam,
                                q=np.column_stack([q, nq]), aux=aux, idx=inv, gate=gate)
        x, r, jac = _kernels.solve(prob, np.array([az, el]), len(q), _X_SCALE, 200, True, 0.5)
        az, el = float(x[0]), float(x[1])
    assert jac is not None
    found = (model.pts[idx], q, nq)
    inl = np.abs(r) < 1.0
    n = int(inl.sum())
    jac = jac[inl] if n > 2 else jac
    s2 = float(np.sum(r[inl] ** 2) / max(n - 2, 1))
    try:
        cov = s2 * np.linalg.inv(jac.T @ jac)
        sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        sig = np.array([np.nan, np.nan])
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) if n else float("nan")
    # support: the share of the reflected outline (inside the facet) that lies on an image edge
    uv, _ = model.project(az, el)
    ins = mask.inside(uv)
    qq = np.rint(uv[ins]).astype(int)
    support = float(np.mean(dt[qq[:, 1], qq[:, 0]] <= 1.5)) if ins.any() else 0.0
    return az, el, float(sig[0]), float(sig[1]), n, rms, support, found


def search_orientation(
    facets: list[tuple[_FacetModel, _Mask]],
    dt: NDArray,
    *,
    span_mrad: float = PAPER_ORIENTATION_SPAN_MRAD,
    step_mrad: float = PAPER_GRID_STEP_MRAD,
    tol_px: float = 5.0,
    block: int = 21,
    subsample: int = 96,
    highpass: int = 11,
    n_alternatives: int = 2,
) -> OrientationSearch:
    """The paper's heliostat orientation grid search (sec. 4.4): one pair of angles for every facet.

    Every node of the grid ``{-span, ..., span}^2`` (step ``step_mrad``;
    101 x 101 nodes for the paper's +-5 deg at 0.1 deg) is one pair of angles
    that every facet's model takes: the HUA's drive-angle errors for the
    models :func:`estimate_canting` passes (``_TurnModel``), or a common
    canting tilt for plain facet models; each facet scores the share of its reflected
    target outline points that fall inside its eroded mask within ``tol_px``
    of an image edge, and the node with the largest mean over the facets
    wins. (The share of the points *inside the mask* would not do: a node
    that leaves a few points in a facet, on some edge, would score high.)
    Facet canting errors (a few mrad) move each facet's reflection a little
    differently; the mean over the facets is what a common turn fixes.

    The projections are evaluated on blocks of ``block`` x ``block`` nodes
    from a quadratic through nine exact projections per block (the same
    scheme as a facet's own grid; a block spans 2 deg, where the quadratic is
    well under a pixel), with every ``subsample``-th outline point.

    Parameters
    ----------
    facets : list of (_FacetModel, _Mask)
        The facets to score, each with its target model (design canting) and
        eroded mask.
    dt : ndarray
        Distance transform of the edge-point image, pixels.
    n_alternatives : int
        How many next-best distinct peaks to return beside the best.

    Returns
    -------
    OrientationSearch
    """
    import time

    from scipy import ndimage

    from pihim.inspection import _kernels

    t0 = time.perf_counter()
    m = int(math.floor(span_mrad / step_mrad + 1e-9))
    grid = step_mrad * np.arange(-m, m + 1)  # symmetric, zero (the design) a node
    n = len(grid)
    total = np.zeros((n, n))
    scored = 0
    blocks = [grid[i:i + block] for i in range(0, n, block)]
    for model, mask in facets:
        sub_model = model.subsampled(subsample)
        if len(sub_model.pts) < 10:
            continue
        hh, ww = mask.sub.shape
        dt_crop = np.ascontiguousarray(dt[mask.r0:mask.r0 + hh, mask.c0:mask.c0 + ww])
        near = np.zeros((n, n))
        for i, ga in enumerate(blocks):
            for j, ge in enumerate(blocks):
                ca, ce = 0.5 * (ga[0] + ga[-1]), 0.5 * (ge[0] + ge[-1])
                s = max(float(np.max(np.abs(ga - ca))), float(np.max(np.abs(ge - ce))), 1.0)
                coef = sub_model.quadratic_coefficients(s, (ca, ce))
                _, nn = _kernels.grid_counts(coef, ga - ca, ge - ce, mask.sub, mask.r0, mask.c0, dt_crop, float(tol_px))
                near[i * block:i * block + len(ga), j * block:j * block + len(ge)] = nn.reshape(len(ga), -1)
        if near.max() > 0:
            scored += 1
            # clutter (other heliostats' backs, the ground) raises a facet's counts over broad regions of
            # the grid; the target's reflection is a sharp peak: keep what stands above the local mean,
            # widened by a node either way (facets' own canting spreads their peaks by a few mrad)
            peak = np.clip(near - ndimage.uniform_filter(near, size=highpass, mode="nearest"), 0.0, None)
            total += ndimage.maximum_filter(peak, size=3, mode="nearest") / len(sub_model.pts)
    if scored == 0:
        raise PihimInputError("no facet shows the target's reflection anywhere within the orientation search")
    k = int(np.argmax(total))
    i, j = divmod(k, n)
    # the next-best distinct peaks (local maxima over +-3 nodes, at least half the best score)
    local = (total == ndimage.maximum_filter(total, size=7, mode="nearest")) & (total >= 0.5 * total[i, j])
    local[i, j] = False
    order = np.flatnonzero(local.ravel())
    order = order[np.argsort(-total.ravel()[order], kind="stable")][:max(n_alternatives, 0)]
    alternatives = tuple((float(grid[a]), float(grid[b]), float(total[a, b] / scored))
                         for a, b in (divmod(int(q), n) for q in order))
    return OrientationSearch(float(grid[i]), float(grid[j]), float(total[i, j] / scored), scored, float(span_mrad),
                             float(step_mrad), float(tol_px), time.perf_counter() - t0, alternatives)


def refine_target_orientation(
    camera: CameraModel,
    pose: CameraPose,
    field_pose: FieldPose,
    hua: int,
    target: int,
    facets: list[tuple[int, float, float, tuple[NDArray, NDArray, NDArray]]],
    *,
    max_deg: float = 5.0,
    hua_turn_deg: tuple[float, float] = (0.0, 0.0),
) -> tuple[float, float]:
    """The target's drive-angle correction that best explains its reflections in the HUA's facets, degrees.

    :func:`refine_orientations` with the HUA's turn held at ``hua_turn_deg``.

    Returns
    -------
    (d_azimuth_deg, d_elevation_deg)
    """
    return refine_orientations(camera, pose, field_pose, hua, target, facets, max_deg=max_deg,
                               hua_turn_deg=hua_turn_deg, solve_hua=False)[0]


def refine_orientations(
    camera: CameraModel,
    pose: CameraPose,
    field_pose: FieldPose,
    hua: int,
    target: int,
    facets: list[tuple[int, float, float, tuple[NDArray, NDArray, NDArray]]],
    *,
    max_deg: float = 5.0,
    hua_turn_deg: tuple[float, float] = (0.0, 0.0),
    solve_hua: bool = True,
    max_points: int = 300,
) -> tuple[tuple[float, float], tuple[float, float]]:
    """Corrections of the target's and the HUA's drive angles that best explain the target's reflections, degrees.

    The paper corrects the logged orientations before measuring canting
    (sec. 4.4). A target at a wrong logged orientation has a distorted
    outline in the model (its points move out of its plane by up to its
    half-width times the error); a HUA at a wrong logged orientation sees,
    through the camera pose fitted on it, the target turned back about the
    HUA's pivot (:func:`hua_turn_transform`): moved, which a common tilt of
    the facets nearly mimics, and turned, which it does not. Either leaves
    every facet's fit a few pixels off. Here the target's two drive angles,
    the HUA's two (``solve_hua``) and every facet's two canting angles are
    solved together by robust least squares (soft-L1, 0.5 px) on the
    point-to-line distances of the facets' last matches (:func:`_fit_facet`'s
    ``matches``): the target's points turn about its pivot with its drive
    angles (mirror centre ``pivot + offset * normal``), then about the
    HUA's pivot with the HUA's turn, and each facet mirrors them in its
    plane. A common tilt of the facets and the HUA's turn differ only by
    that second-order picture, so the HUA's share is weakly determined; the
    facets' deviations relative to their mean are not affected.

    Parameters
    ----------
    facets : list of (facet index, az_mrad, el_mrad, (points, image points, line normals))
        The facets' fits (raw deviations) and their matches, made on the
        target's outline at its logged angles turned by ``hua_turn_deg``.
    max_deg : float
        Largest correction accepted per axis; beyond it the fit is not
        trusted and no correction is returned.
    hua_turn_deg : (float, float)
        The HUA's drive-angle error the matches were made with
        (:func:`hua_turn_transform`), degrees.
    solve_hua : bool
        Also correct the HUA's turn; otherwise it is held. The facets'
        mean canting is then held near zero by a weak penalty (1 px per
        mrad), as the HUA's turn and a common tilt nearly trade off.
    max_points : int
        Matches used per facet, at most (evenly along them).

    Returns
    -------
    ((d_az_target, d_el_target), (d_az_hua, d_el_hua))
        Degrees; the HUA's correction is on top of ``hua_turn_deg``.
    """
    from scipy.optimize import least_squares

    from pihim.field.kinematics import rotation_from_drive
    from pihim.inspection import _kernels

    none = ((0.0, 0.0), (0.0, 0.0))
    if not facets:
        return none
    d = field_pose.drive
    az0, el0 = float(d.azimuth_deg[target]), float(d.elevation_deg[target])
    r0 = field_pose.rotations[target]
    c0 = field_pose.mirror_centres[target]
    pivot = np.asarray(field_pose.field.pivots, float)[target]  # type: ignore[attr-defined]
    offset = float(field_pose.field.spec.pivot_offset_m)  # type: ignore[attr-defined]
    rot_h = field_pose.rotations[hua]
    cam = _kernels.camera_vector(camera)
    rc = np.array(pose.rotation, float)
    cc = np.array(pose.position_m, float)
    h_pivot, m0 = hua_turn_transform(field_pose, hua, *hua_turn_deg)
    h_az, h_el = float(d.azimuth_deg[hua]), float(d.elevation_deg[hua])
    r_log = rotation_from_drive(h_az, h_el)
    # at most ``max_points`` matches per facet, evenly along them: a few hundred fix two angles as well
    facets = [(f, a, e, tuple(np.asarray(v)[::max(1, -(-len(m[1]) // max_points))] for v in m))
              for f, a, e, m in facets]
    local = [(_apply((h_pivot, m0.T), m[0]) - c0) @ r0 for _, _, _, m in facets]  # target frame
    sizes = [len(m[1]) for *_, m in facets]
    starts = np.concatenate([[0], np.cumsum(sizes)])
    centres = [field_pose.facet_centres[hua, f] for f, *_ in facets]
    normals_local = [field_pose.facet_normals_local[hua, f] for f, *_ in facets]
    n_o = 4 if solve_hua else 2
    n_f = len(facets)
    # the facets' mean canting is held near zero (weight ``mean_weight`` px per mrad): with the HUA's turn
    # free, a common tilt of the facets and the turn nearly trade off, and the turn takes the common part
    mean_weight = 1.0 if solve_hua else 0.0

    def block(x_o: NDArray, x_f: NDArray, k: int) -> NDArray:
        """Point-to-line residuals of facet ``k`` at orientation ``x_o`` and its canting ``x_f``."""
        rt = rotation_from_drive(az0 + x_o[0], el0 + x_o[1])
        ct = pivot + offset * rt[:, 2]
        world = (h_pivot, m0) if not solve_hua else \
            (h_pivot, r_log @ rotation_from_drive(h_az + hua_turn_deg[0] + x_o[2], h_el + hua_turn_deg[1] + x_o[3]).T)
        m = facets[k][3]
        p = _apply(world, ct + local[k] @ rt.T)
        n = rot_h @ apply_canting_deviation(normals_local[k], x_f[0], x_f[1])
        virt = p - 2.0 * ((p - centres[k]) @ n)[:, None] * n
        uv = _kernels.project_rc(rc, cc, np.ascontiguousarray(virt), cam)
        return np.nan_to_num(np.sum((uv - m[1]) * m[2], axis=1), nan=10.0)

    def residuals(x: NDArray) -> NDArray:
        out = np.empty(starts[-1] + 2)
        for k in range(n_f):
            out[starts[k]:starts[k + 1]] = block(x[:n_o], x[n_o + 2 * k:n_o + 2 * k + 2], k)
        xf = x[n_o:].reshape(n_f, 2)
        out[starts[-1]:] = mean_weight * xf.mean(axis=0)
        return out

    def jacobian(x: NDArray) -> object:
        # each facet's residuals depend on the orientation angles and its own two: forward differences
        # per facet (n_o + 2 evaluations of that facet's block), the mean rows analytic
        jac = np.zeros((int(starts[-1]) + 2, n_o + 2 * n_f))
        for k in range(n_f):
            xo, xf = x[:n_o].copy(), x[n_o + 2 * k:n_o + 2 * k + 2].copy()
            r0 = block(xo, xf, k)
            idx = np.arange(starts[k], starts[k + 1])
            for j in range(n_o + 2):
                step = (1e-5 if j < n_o else 1e-3)
                xo2, xf2 = xo.copy(), xf.copy()
                if j < n_o:
                    xo2[j] += step
                    col = j
                else:
                    xf2[j - n_o] += step
                    col = n_o + 2 * k + j - n_o
                jac[idx, col] = (block(xo2, xf2, k) - r0) / step
        for a in range(2):
            jac[starts[-1] + a, n_o + 2 * np.arange(n_f) + a] = mean_weight / n_f
        return jac

    n_p = n_o + 2 * n_f
    x0 = np.concatenate([np.zeros(n_o), np.ravel([[a, e] for _, a, e, _ in facets])])
    scale = np.concatenate([np.full(n_o, 0.01), np.full(n_p - n_o, 0.1)])
    fit = least_squares(residuals, x0, jac=jacobian, loss="soft_l1", f_scale=0.5, x_scale=scale, max_nfev=50,
                        tr_solver="exact")
    corr = np.asarray(fit.x[:n_o], float)
    if not np.all(np.abs(corr) <= max_deg):
        return none
    return (float(corr[0]), float(corr[1])), ((float(corr[2]), float(corr[3])) if solve_hua else (0.0, 0.0))


def drive_correction(field_pose: FieldPose, index: int, az_mrad: float, el_mrad: float) -> tuple[float, float]:
    """A canting-style rotation of a whole heliostat as a change of its drive angles, degrees.

    The heliostat's normal (its frame's ``z``) tilted by ``(az_mrad,
    el_mrad)`` (:func:`pihim.field.kinematics.apply_canting_deviation`) has
    drive angles that differ from the logged ones by the returned
    ``(d_azimuth, d_elevation)`` (azimuth wrapped to [-180, 180)).
    """
    from pihim.field.kinematics import drive_angles

    rot = field_pose.rotations[index]
    n0 = rot[:, 2]
    n1 = rot @ apply_canting_deviation(np.array([0.0, 0.0, 1.0]), az_mrad, el_mrad)
    d0, d1 = drive_angles(n0), drive_angles(n1)
    d_az = (float(d1.azimuth_deg) - float(d0.azimuth_deg) + 180.0) % 360.0 - 180.0
    return d_az, float(d1.elevation_deg) - float(d0.elevation_deg)


def estimate_canting(
    camera: CameraModel,
    pose: CameraPose,
    field_pose: FieldPose,
    hua: str,
    target: str,
    edges: EdgePoints,
    *,
    dolp: ArrayLike | None = None,
    saturated: ArrayLike | None = None,
    min_dolp: float | None = 0.2,
    span_mrad: float = 10 * PAPER_GRID_STEP_MRAD,
    step_mrad: float = PAPER_GRID_STEP_MRAD,
    margin_px: float = 6.0,
    gates_px: tuple[float, ...] = (6.0, 3.0, 1.5, 1.5),
    min_points: int = 300,
    min_support: float = 0.3,
    max_rms_px: float = 0.3,
    sizes: StructureSizes = StructureSizes(),
    orientation_span_mrad: float | None = PAPER_ORIENTATION_SPAN_MRAD,
    target_orientation: bool = False,
) -> CantingResult:
    """Estimate every facet's canting of ``hua`` from ``target``'s reflection in one frame.

    Parameters
    ----------
    camera, pose : CameraModel, CameraPose
        Intrinsics and the refined camera pose (:func:`pihim.inspection.pose.refine_pose`).
    field_pose : FieldPose
        The field as logged (drive angles from the plant's log, design canting).
    hua, target : str
        Heliostat names.
    edges : EdgePoints
        Sub-pixel edge points of the frame.
    dolp, saturated : array_like, optional
        DoLP image and saturation mask (same shape) for the skip tests.
    min_dolp : float or None
        A facet is used only if the brighter part of its reflection is
        polarized above this (the 90th percentile of its DoLP; paper: 0.2);
        None disables the test.
    span_mrad, step_mrad : float
        Grid-search half-range and step (paper: +-5 deg in 0.1 deg steps;
        the default half-range here is 1 deg = 17.5 mrad, ten paper steps, as
        the refinement needs only a starting point; pass 87.3 for the
        paper's full range).
    margin_px : float
        Facet outlines are eroded by this much so that the facet's own edges
        (and the gaps) are not taken for reflected features.
    gates_px : tuple of float
        Matching gates of the refinement rounds.
    min_points : int
        Fewest matched edge points for a facet to be used.
    max_rms_px : float
        Largest RMS point-to-line residual of an accepted facet fit, pixels
        (a fit locked to the wrong features leaves larger residuals).
    min_support : float
        Fewest share of the reflected target outline (inside the facet) that
        must lie within 1.5 px of an image edge at the solution; facets whose
        reflection shows something else are skipped, as they would bias the
        best-fit orientation every deviation is relative to.
    orientation_span_mrad : float or None
        Half-range of the orientation search (:func:`search_orientation`,
        step ``step_mrad``) run over the facets that pass the view, saturation
        and DoLP tests before any facet is fitted; each facet's grid then
        spans ``span_mrad`` around its result. Default the paper's +-5 deg;
        None skips it (the facets' grids centred on the design).
    target_orientation : bool
        Correct the target's logged drive angles and the HUA's turn
        together (:func:`refine_orientations`) and fit the facets again on
        the corrected outline, kept if that measures more facets (or as
        many, with smaller residuals). Off by default: it costs about 2 s of
        CPU per frame and helps only when the plant's logged drive angles
        are off by about 0.1 deg or more (BENCHMARKS.md).

    Returns
    -------
    CantingResult
    """
    names = list(field_pose.field.names)  # type: ignore[attr-defined]
    try:
        h = names.index(hua)
        t = names.index(target)
    except ValueError as exc:
        raise PihimInputError(f"unknown heliostat: {exc}") from None
    spec = field_pose.field.spec  # type: ignore[attr-defined]
    corners = field_pose.facet_corners()
    masks = _facet_masks(camera, pose, corners[h], margin_px)
    pts, seg = sample_segments(target_outline_segments(field_pose, t, sizes), 0.01)
    import cv2

    obs_img = np.zeros((camera.height_px, camera.width_px), np.uint8)
    q = np.rint(edges.xy).astype(int)
    ok = (q[:, 0] >= 0) & (q[:, 0] < camera.width_px) & (q[:, 1] >= 0) & (q[:, 1] < camera.height_px)
    obs_img[q[ok, 1], q[ok, 0]] = 1
    dt = cv2.distanceTransform((1 - obs_img).astype(np.uint8), cv2.DIST_L2, 5)
    dolp_img = None if dolp is None else np.asarray(dolp, float)
    sat = None if saturated is None else np.asarray(saturated, bool)
    raw: list[tuple] = []
    candidates: list[tuple[int, _Mask]] = []
    for f in range(spec.n_facets):
        fid = f + 1
        mask = masks[f]
        area = mask.area()
        if area < 200:
            raw.append((fid, "facet not in view (or too small)"))
            continue
        if sat is not None and sat.shape == mask.shape and mask.values(sat).mean() > 0.3:
            raw.append((fid, "saturated"))
            continue
        if min_dolp is not None and dolp_img is not None and dolp_img.shape == mask.shape:
            vals = mask.values(dolp_img)
            p90 = np.nanpercentile(vals, 90) if np.isfinite(vals).any() else 0.0
            if not p90 > min_dolp:
                raw.append((fid, f"DoLP <= {min_dolp:g} on the reflection (paper sec. 4.1)"))
                continue
        raw.append((fid, None))
        candidates.append((f, mask))

    outline = {"pts": pts, "seg": seg}  # the target's outline samples (replaced once its orientation is corrected)

    def facet_model(f: int) -> _FacetModel:
        return _FacetModel(camera, pose, field_pose.rotations[h], field_pose.facet_centres[h, f],
                           field_pose.facet_normals_local[h, f], outline["pts"], outline["seg"])

    def fit_facets(centre: tuple[float, float], prefer: dict[int, tuple[float, float]] | None,
                   collect: list | None = None) -> dict[int, object]:
        fits: dict[int, object] = {}
        for f, mask in candidates:
            model = facet_model(f).near(mask, span_mrad, centre_mrad=centre)
            found: list = []
            try:
                fit = _fit_facet(model, mask, edges.xy, dt, span_mrad, step_mrad, gates_px, centre_mrad=centre,
                                 prefer_mrad=None if prefer is None else prefer.get(f), matches=found)
            except PihimInputError as exc:
                fits[f + 1] = f"no usable reflection of {target}: {exc}"
                continue
            if collect is not None and found and fit[6] >= min_points and fit[8] >= min_support:
                collect.append((f, fit[2], fit[3], found[-1]))  # the residual gate aside: see below
            if fit[6] < min_points:
                fits[f + 1] = f"too few matched edge points ({fit[6]} < {min_points})"
                continue
            if not fit[7] <= max_rms_px:
                fits[f + 1] = (f"the fit is not sub-pixel consistent (residual {fit[7]:.2f} px > {max_rms_px:g} px:"
                               " locked to other features)")
                continue
            if fit[8] < min_support:
                fits[f + 1] = (f"the reflection does not look like {target}'s outline (support {fit[8]:.2f} < "
                               f"{min_support:g}: hidden, or another heliostat)")
                continue
            fits[f + 1] = fit
        return fits

    def n_used(fits: dict[int, object]) -> int:
        return sum(not isinstance(v, str) for v in fits.values())

    def mean_rms(fits: dict[int, object]) -> float:
        v = [r[7] for r in fits.values() if not isinstance(r, str)]
        return float(np.mean(v)) if v else float("inf")

    search = None
    notes = []
    if orientation_span_mrad is not None and candidates:
        drv = field_pose.drive
        drive_h = (float(drv.azimuth_deg[h]), float(drv.elevation_deg[h]))
        pivot_h, _ = hua_turn_transform(field_pose, h, 0.0, 0.0)
        try:
            search = search_orientation([(_TurnModel(facet_model(f), drive_h, pivot_h).near(m, orientation_span_mrad), m)
                                         for f, m in candidates], dt, span_mrad=float(orientation_span_mrad))
        except PihimInputError as exc:
            notes.append(f"orientation search: {exc}")
    # The search's node is the HUA's drive-angle error: beyond two steps, the target's outline is turned as a
    # camera pose fitted on the HUA sees it (hua_turn_transform) and every facet is fitted around its design on
    # that outline. The
    # search proposes, the facet fits decide: the facets are fitted on the logged outline too, and the turn is
    # kept if it measures more facets (or as many, with more facets finding the target's outline -- what the
    # target's correction below starts from -- or as many, closer): clutter -- other heliostats' backs, the
    # ground -- can raise a false peak of the search.
    plain = {"pts": pts, "seg": seg}
    turn_deg = (0.0, 0.0)
    fits: dict[int, object] = {}
    matches: list = []
    world = None
    # a turn of a step or two is what the facets' mean canting alone moves the search's node by; the facet
    # fits absorb it, and fitting twice would only let the two passes' noise choose
    if search is not None and max(abs(search.az_mrad), abs(search.el_mrad)) > 2.5 * step_mrad:
        turn_deg = (math.degrees(search.az_mrad * 1e-3), math.degrees(search.el_mrad * 1e-3))
        world = hua_turn_transform(field_pose, h, *turn_deg)
        outline.update(pts=_apply(world, pts))
        fits = fit_facets((0.0, 0.0), None, matches)
        outline.update(plain)
    # on the logged outline, a facet whose grid has near-equal peaks (the target's back is periodic) starts
    # from the one nearest the tilt that mimics the search's turn
    prefer = None if world is None else {
        f: _equivalent_tilt(facet_model(f).near(m, span_mrad),
                            _TurnModel(facet_model(f), drive_h, pivot_h).near(m, span_mrad),
                            (search.az_mrad, search.el_mrad))
        for f, m in candidates}
    logged_matches: list = []
    logged = fit_facets((0.0, 0.0), prefer, logged_matches)
    if world is not None and (n_used(fits), len(matches), -mean_rms(fits)) > \
            (n_used(logged), len(logged_matches), -mean_rms(logged)):
        notes.append(f"HUA {hua}'s logged drive angles corrected by the orientation search: az {turn_deg[0]:+.2f}, "
                     f"el {turn_deg[1]:+.2f} deg ({n_used(fits)} facets measured, {n_used(logged)} at the logged "
                     "angles)")
        outline.update(pts=_apply(world, pts))
    else:
        if world is not None:
            notes.append(f"the orientation search's node (HUA az {turn_deg[0]:+.2f}, el {turn_deg[1]:+.2f} deg) "
                         f"measured {n_used(fits)} facets, the logged angles {n_used(logged)}: kept the logged angles")
        fits, matches, world, turn_deg = logged, logged_matches, None, (0.0, 0.0)
    # The logged orientations (paper sec. 4.4): the target's drive angles and the HUA's turn solved with every
    # facet that found the target's outline (the residual gate aside: a target off its logged angles fails it
    # everywhere), then the facets fitted again on the corrected outline; kept if it measures more facets (or
    # as many, closer).
    target_corr = None
    if target_orientation and len(matches) >= 2:
        drv = field_pose.drive
        az_t = np.array(drv.azimuth_deg, float)
        el_t = np.array(drv.elevation_deg, float)
        kept = dict(outline)
        total = np.zeros(2)
        turn = np.array(turn_deg, float)
        best = (n_used(fits), -mean_rms(fits))
        found = None  # (fits, target correction, HUA turn, outline) of the best iteration that beats ``best``
        last = (total.copy(), turn.copy())
        for _ in range(3):  # solve, refit on the corrected outline, solve again from the new matches
            fp_t = field_pose.with_drive(np.where(np.arange(len(az_t)) == t, az_t + total[0], az_t),
                                         np.where(np.arange(len(el_t)) == t, el_t + total[1], el_t))
            step_t, step_h = (np.array(v) for v in refine_orientations(camera, pose, fp_t, h, t, matches,
                                                                         hua_turn_deg=(turn[0], turn[1])))
            if not np.any(np.abs(np.concatenate([step_t, step_h])) > 1e-3):
                break
            total += step_t
            turn += step_h
            last = (total.copy(), turn.copy())
            p2, s2 = sample_segments(target_outline_segments(field_pose.with_drive(
                np.where(np.arange(len(az_t)) == t, az_t + total[0], az_t),
                np.where(np.arange(len(el_t)) == t, el_t + total[1], el_t)), t, sizes), 0.01)
            outline.update(pts=_apply(hua_turn_transform(field_pose, h, turn[0], turn[1]), p2), seg=s2)
            matches = []
            tried = fit_facets((0.0, 0.0), None, matches)
            if (n_used(tried), -mean_rms(tried)) > best:
                best = (n_used(tried), -mean_rms(tried))
                found = (tried, total.copy(), turn.copy(), dict(outline))
            if len(matches) < 2 or np.max(np.abs(np.concatenate([step_t, step_h]))) < 0.01:
                break
        if found is not None:
            fits, total, turn, kept_outline = found
            outline.update(kept_outline)
            target_corr = (float(total[0]), float(total[1]))
            notes.append(f"target {target}'s logged orientation corrected by az {total[0]:+.3f}, el {total[1]:+.3f} "
                         f"deg, with the HUA's turn at az {turn[0]:+.3f}, el {turn[1]:+.3f} deg")
            turn_deg = (float(turn[0]), float(turn[1]))
        elif np.any(last[0] != 0.0) or np.any(last[1] != np.array(turn_deg)):
            outline.update(kept)
            notes.append(f"target {target}'s orientation fit (az {last[0][0]:+.3f}, el {last[0][1]:+.3f} deg, the "
                         f"HUA's turn at az {last[1][0]:+.3f}, el {last[1][1]:+.3f} deg) measured no more facets; kept "
                         "the previous angles")
    raw = [(fid, fits[fid] if r is None else r) for fid, r in raw]
    used = [r for r in raw if not isinstance(r[1], str)]
    if used:
        o_az = float(np.mean([r[1][2] for r in used]))
        o_el = float(np.mean([r[1][3] for r in used]))
        g_az = float(np.mean([r[1][0] for r in used]))
        g_el = float(np.mean([r[1][1] for r in used]))
    else:
        o_az = o_el = g_az = g_el = None
        notes.append("no facet could be measured")
    out = []
    for fid, r in raw:
        if isinstance(r, str):
            out.append(FacetCanting(fid, False, r))
        else:
            ga, ge, a, e, sa, se, n, rms, support = r
            out.append(FacetCanting(fid, True, None, a - o_az, e - o_el, sa, se, ga - g_az, ge - g_el, n, rms,
                                    support))
    corr = None
    if o_az is not None:
        rest = drive_correction(field_pose, h, o_az, o_el)
        corr = (turn_deg[0] + rest[0], turn_deg[1] + rest[1])
    return CantingResult(hua, target, tuple(out), o_az, o_el, 1, tuple(notes), search, corr, target_corr)
