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
:func:`search_orientation` turns every facet by the same angles over the
paper's +-5 deg in 0.1 deg steps and finds the node where the facets'
reflections of the target best line up with the image's edges. The facets'
own searches below span +-1 deg around the design; when the orientation
search puts the heliostat farther than half a degree from it, the facets are
fitted again around the search's node and that pass is kept if it measures
more facets (the search proposes, the facet fits decide: clutter can raise a
false peak far from the design). So a heliostat whose logged drive angles
are off by more than a facet's grid is still measured.

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
frame pass the quality gates and their deviations are recovered to 0.19 /
0.24 mrad RMS (azimuth / elevation; the best-fit orientation to 0.14 / 0.11
mrad) against 1.67 / 2.08 mrad for the paper's grid search on the same frames;
a median 1.8 s per frame for the whole chain (1.1 s of it this step's CPU,
0.6 s of that the orientation search). Weak: logged drive angles off by
0.1 deg or more (the target's correction recovers some facets at 0.1 deg,
none at 0.5 deg, where the HUA's own turn, absorbed by the camera pose,
displaces the target as a whole; see BENCHMARKS.md). Not yet: polarimetric
edge weighting.

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
           "drive_correction", "estimate_canting", "refine_target_orientation", "search_orientation",
           "target_outline_segments"]

#: Scale of the two canting angles in the refinement, mrad.
_X_SCALE = np.array([0.1, 0.1])

#: The paper's grid step, 0.1 deg, in mrad.
PAPER_GRID_STEP_MRAD = float(np.radians(0.1) * 1e3)


#: Half-range of the paper's heliostat orientation search, +-5 deg, in mrad.
PAPER_ORIENTATION_SPAN_MRAD = float(np.radians(5.0) * 1e3)


@dataclass(frozen=True)
class OrientationSearch:
    """The paper's orientation grid search: one rotation common to every facet of the HUA.

    Paper sec. 4.4: the relative orientation of the HUA and the target is
    corrected over +-5 deg in 0.1 deg steps until the facets' reflections of
    the target line up, before any facet is fitted; a facet's own search then
    spans +-1 deg around it. ``az_mrad`` / ``el_mrad`` are canting-style
    angles in the HUA's frame (:func:`pihim.field.kinematics.apply_canting_deviation`)
    at the best grid node; ``score`` is the mean over the ``facets`` scored
    of the share of each facet's reflected target outline points that fall
    inside the facet within ``tol_px`` of an image edge there.
    """

    az_mrad: float
    el_mrad: float
    score: float
    facets: int
    span_mrad: float
    step_mrad: float
    tol_px: float
    seconds: float

    def to_dict(self) -> dict[str, object]:
        return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in self.__dict__.items()}


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
        The best-fit orientation as a correction of the HUA's logged drive
        angles, (azimuth, elevation) in degrees: the drive angles that turn
        the heliostat's normal as the best-fit orientation does. One frame
        constrains only the orientation of the HUA relative to the target
        (and to the camera pose fitted on the HUA), so the whole correction
        is carried by the HUA.
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

    def subsampled(self, k: int) -> _FacetModel:
        """The same model with every ``k``-th sample point (a cheaper score for the grid search)."""
        return _FacetModel(self.camera, self.pose, self.rot, self.centre, self.normal_local, self.pts[::k],
                           self.seg[::k])

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
        return _FacetModel(self.camera, self.pose, self.rot, self.centre, self.normal_local, self.pts[keep],
                           self.seg[keep])

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


def _fit_facet(model: _FacetModel, mask: _Mask, obs: NDArray, dt: NDArray, span_mrad: float,
               step_mrad: float, gates_px: tuple[float, ...], grid_tol_px: float = 5.0,
               centre_mrad: tuple[float, float] = (0.0, 0.0), prefer_mrad: tuple[float, float] | None = None,
               ambiguity: float = 0.05, matches: list | None = None) -> tuple:
    """(grid az, grid el, az, el, sigma az, sigma el, points, rms) for one facet (raw, not relative).

    The grid spans ``+-span_mrad`` around ``centre_mrad`` (the heliostat's
    orientation from :func:`search_orientation`, or the design). The grid
    values returned are the paper's (the best node); the refinement starts
    from the node nearest ``prefer_mrad`` (default the centre) among those
    scoring within ``ambiguity`` of the best: the target's back is periodic
    (facet rows and columns, crossbars), so a facet that sees only part of it
    matches almost as well one period away (15-30 mrad at UFACET distances),
    and canting errors are small next to that. Given a list ``matches``, the
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
    # 2. continuous refinement: point-to-line ICP with LM, from the near-best node nearest the preferred angles
    pa, pe = centre_mrad if prefer_mrad is None else prefer_mrad
    cand = np.flatnonzero(score >= (1.0 - ambiguity) * g_best[0])
    k0 = int(cand[np.argmin((gaz[cand] + centre_mrad[0] - pa) ** 2 + (gel[cand] + centre_mrad[1] - pe) ** 2)])
    az, el = float(gaz[k0]) + centre_mrad[0], float(gel[k0]) + centre_mrad[1]
    ob = obs[mask.inside(obs)]
    if len(ob) < 20:
        raise PihimInputError("too few edge points inside this facet")
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
    if matches is not None:
        matches.append((model.pts[idx], q, nq))
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
    return grid_az, grid_el, az, el, float(sig[0]), float(sig[1]), n, rms, support


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
) -> OrientationSearch:
    """The paper's heliostat orientation grid search (sec. 4.4): one rotation for every facet.

    Every node of the grid ``{-span, ..., span}^2`` (step ``step_mrad``;
    101 x 101 nodes for the paper's +-5 deg at 0.1 deg) tilts all facet
    normals by the same angles; each facet scores the share of its reflected
    target outline points that fall inside its eroded mask within ``tol_px``
    of an image edge, and the node with the largest mean over the facets
    wins. (The share of the points *inside the mask* would not do: a node
    that leaves a few points in a facet, on some edge, would score high.)
    Facet canting errors (a few mrad) move each facet's reflection a little
    differently; the mean over the facets is what a common rotation fixes.

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
    return OrientationSearch(float(grid[i]), float(grid[j]), float(total[i, j] / scored), scored, float(span_mrad),
                             float(step_mrad), float(tol_px), time.perf_counter() - t0)


def refine_target_orientation(
    camera: CameraModel,
    pose: CameraPose,
    field_pose: FieldPose,
    hua: int,
    target: int,
    facets: list[tuple[int, float, float, tuple[NDArray, NDArray, NDArray]]],
    *,
    max_deg: float = 5.0,
) -> tuple[float, float]:
    """The target's drive-angle correction that best explains its reflections in the HUA's facets, degrees.

    The paper corrects the target's logged orientation before measuring
    canting (sec. 4.4): a target at a wrong logged orientation has a
    distorted outline in the model (its points move out of its plane by up
    to its half-width times the error), and every facet's fit is off by a
    few pixels. Here the target's two drive angles and every facet's two
    canting angles are solved together by robust least squares (soft-L1,
    0.5 px) on the point-to-line distances of the facets' last matches
    (:func:`_fit_facet`'s ``matches``): the target's points turn about its
    pivot with the drive angles (mirror centre ``pivot + offset * normal``),
    each facet mirrors them in its plane.

    Parameters
    ----------
    facets : list of (facet index, az_mrad, el_mrad, (points, image points, line normals))
        The facets' fits (raw deviations) and their matches.
    max_deg : float
        Largest correction accepted per axis; beyond it the fit is not
        trusted and (0, 0) is returned.

    Returns
    -------
    (d_azimuth_deg, d_elevation_deg)
    """
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    from pihim.field.kinematics import rotation_from_drive
    from pihim.inspection import _kernels

    if not facets:
        return 0.0, 0.0
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
    local = [(m[0] - c0) @ r0 for _, _, _, m in facets]  # target frame
    sizes = [len(m[1]) for *_, m in facets]
    starts = np.concatenate([[0], np.cumsum(sizes)])
    centres = [field_pose.facet_centres[hua, f] for f, *_ in facets]
    normals_local = [field_pose.facet_normals_local[hua, f] for f, *_ in facets]

    def residuals(x: NDArray) -> NDArray:
        rt = rotation_from_drive(az0 + x[0], el0 + x[1])
        ct = pivot + offset * rt[:, 2]
        out = np.empty(starts[-1])
        for k, (loc, (_, _, _, m)) in enumerate(zip(local, facets, strict=True)):
            p = ct + loc @ rt.T
            n = rot_h @ apply_canting_deviation(normals_local[k], x[2 + 2 * k], x[3 + 2 * k])
            virt = p - 2.0 * ((p - centres[k]) @ n)[:, None] * n
            uv = _kernels.project_rc(rc, cc, np.ascontiguousarray(virt), cam)
            out[starts[k]:starts[k + 1]] = np.sum((uv - m[1]) * m[2], axis=1)
        return np.nan_to_num(out, nan=10.0)

    n_p = 2 + 2 * len(facets)
    sparsity = lil_matrix((int(starts[-1]), n_p), dtype=int)
    for k in range(len(facets)):
        sparsity[starts[k]:starts[k + 1], [0, 1, 2 + 2 * k, 3 + 2 * k]] = 1
    x0 = np.concatenate([[0.0, 0.0], np.ravel([[a, e] for _, a, e, _ in facets])])
    scale = np.concatenate([[0.01, 0.01], np.full(n_p - 2, 0.1)])
    fit = least_squares(residuals, x0, jac_sparsity=sparsity, loss="soft_l1", f_scale=0.5, x_scale=scale,
                        max_nfev=200)
    d_az, d_el = float(fit.x[0]), float(fit.x[1])
    if not (abs(d_az) <= max_deg and abs(d_el) <= max_deg):
        return 0.0, 0.0
    return d_az, d_el


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
        Correct the target's logged drive angles
        (:func:`refine_target_orientation`) and fit the facets again on its
        corrected outline, kept if that measures more facets (or as many,
        with smaller residuals). Off by default: it costs about 1 s of CPU
        per frame and helps only when the plant's logged drive angles are
        off by about 0.1 deg or more (BENCHMARKS.md).

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

    def fit_facets(centre: tuple[float, float], prefer: tuple[float, float] | None,
                   collect: list | None = None) -> dict[int, object]:
        fits: dict[int, object] = {}
        for f, mask in candidates:
            model = facet_model(f).near(mask, span_mrad, centre_mrad=centre)
            found: list = []
            try:
                fit = _fit_facet(model, mask, edges.xy, dt, span_mrad, step_mrad, gates_px, centre_mrad=centre,
                                 prefer_mrad=prefer, matches=found)
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
        try:
            search = search_orientation([(facet_model(f).near(m, orientation_span_mrad), m) for f, m in candidates],
                                        dt, span_mrad=float(orientation_span_mrad))
        except PihimInputError as exc:
            notes.append(f"orientation search: {exc}")
    # The facets' own grids (+-span_mrad) around the design hold a heliostat within half a span of it;
    # between near-equal peaks of a facet's grid the refinement starts from the one nearest the search's
    # node. Farther, the search proposes and the facet fits decide: the facets are fitted again around the
    # search's node, and that pass is kept if it measures more facets (clutter -- other heliostats' backs,
    # the ground -- can raise a false peak of the search far from the design).
    centre = (0.0, 0.0) if search is None else \
        tuple(v if abs(v) > 0.5 * span_mrad else 0.0 for v in (search.az_mrad, search.el_mrad))
    node = None if search is None else (search.az_mrad, search.el_mrad)
    design_matches: list = []
    fits = fit_facets((0.0, 0.0), node if centre == (0.0, 0.0) else None, design_matches)
    matches = design_matches
    prefer = node if centre == (0.0, 0.0) else None
    if centre != (0.0, 0.0):
        moved_matches: list = []
        moved = fit_facets(centre, node, moved_matches)
        n_moved, n_design = n_used(moved), n_used(fits)
        if n_moved > n_design:
            fits, matches, prefer = moved, moved_matches, node
            notes.append(f"facets fitted around the orientation search's node (az {centre[0]:+.1f}, "
                         f"el {centre[1]:+.1f} mrad): {n_moved} facets measured there, {n_design} around the design")
        else:
            centre = (0.0, 0.0)
            notes.append(f"the orientation search's node (az {search.az_mrad:+.1f}, el {search.el_mrad:+.1f} mrad) "
                         "measured fewer facets than the design; kept the design")
    # The target's logged orientation (paper sec. 4.4): solved with every facet that found the target's
    # outline (the residual gate aside: a target off its logged angles fails it everywhere), then the facets
    # fitted again on the corrected outline; kept if it measures more facets (or as many, closer).
    target_corr = None
    if target_orientation and len(matches) >= 2:
        drv = field_pose.drive
        az_t = np.array(drv.azimuth_deg, float)
        el_t = np.array(drv.elevation_deg, float)
        plain = dict(outline)
        total = np.zeros(2)
        best = (n_used(fits), -mean_rms(fits))
        tried = fits
        for _ in range(4):  # solve, refit on the corrected outline, solve again from the new matches
            fp_t = field_pose.with_drive(np.where(np.arange(len(az_t)) == t, az_t + total[0], az_t),
                                         np.where(np.arange(len(el_t)) == t, el_t + total[1], el_t))
            step = np.array(refine_target_orientation(camera, pose, fp_t, h, t, matches))
            if not np.any(np.abs(step) > 1e-3):
                break
            total += step
            az_n, el_n = az_t.copy(), el_t.copy()
            az_n[t] += total[0]
            el_n[t] += total[1]
            p2, s2 = sample_segments(target_outline_segments(field_pose.with_drive(az_n, el_n), t, sizes), 0.01)
            outline.update(pts=p2, seg=s2)
            matches = []
            tried = fit_facets(centre, prefer, matches)
            if len(matches) < 2 or np.max(np.abs(step)) < 0.005:
                break
        if np.any(total != 0.0) and (n_used(tried), -mean_rms(tried)) > best:
            fits, target_corr = tried, (float(total[0]), float(total[1]))
            notes.append(f"target {target}'s logged orientation corrected by az {total[0]:+.3f}, el {total[1]:+.3f} deg")
        elif np.any(total != 0.0):
            outline.update(plain)
            notes.append(f"target {target}'s orientation fit (az {total[0]:+.3f}, el {total[1]:+.3f} deg) measured no "
                         "more facets; kept its logged angles")
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
    corr = None if o_az is None else drive_correction(field_pose, h, o_az, o_el)
    return CantingResult(hua, target, tuple(out), o_az, o_el, 1, tuple(notes), search, corr, target_corr)
