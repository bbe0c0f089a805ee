"""Camera pose refinement on the heliostat under assessment (paper sec. 4.4, step 2).

The logged GPS/IMU pose (about 1-2 m and 1 deg) places the heliostat
hundreds of pixels from where it appears. The pose is refined against the
outlines of the HUA's facets, which the field model gives exactly in the
heliostat frame:

1. **Coarse**: the projected facet outlines, rasterised at a quarter of the
   resolution, are cross-correlated (FFT) with a proximity map of the
   image's edge points, ``exp(-DT^2 / 2 s^2)`` of their distance transform;
   the best image shift is turned into a small pan and tilt of the camera.
   The mirror's outer outline breaks the periodicity of the facet grid, so
   a shift by one facet pitch scores lower than the true one when the outer
   edges are in view.
2. **Fine**: Levenberg-Marquardt on the six pose parameters (rotation vector
   and position increments) minimising the point-to-line distances between
   the image's sub-pixel edge points and the nearest projected model edge,
   re-matched between solves with a shrinking gate (an ICP with the
   point-to-line metric), with a soft-L1 loss against outliers (reflected
   features near a facet edge).

The result is the pose of the camera **relative to the HUA as the field
model places it from its logged drive angles**: a tracking error of the HUA
is absorbed into the pose (it cannot be told apart from a camera pose error
with the HUA alone).

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone", sec. 4.4 (pose from the heliostat's corners, LM, < 0.2 deg).
.. [2] Y. Chen, G. Medioni, "Object modelling by registration of multiple
   range images", Image Vis. Comput. 10(3), 145-155 (1992),
   doi:10.1016/0262-8856(92)90066-C (point-to-plane/line ICP).
.. [3] H. G. Barrow et al., "Parametric correspondence and chamfer matching",
   IJCAI 1977 (distance-transform matching).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose, project_points
from pihim.errors import PihimInputError
from pihim.inspection.features import EdgePoints

__all__ = ["PoseFit", "facet_outline_segments", "line_normals", "match_edge_points", "refine_pose", "sample_segments"]


@dataclass(frozen=True, eq=False)
class PoseFit:
    """A refined camera pose.

    Attributes
    ----------
    pose : CameraPose
        The refined pose.
    prior : CameraPose
        The logged pose it started from.
    rms_px : float
        RMS point-to-line residual of the matched edge points, pixels.
    n_points : int
        Edge points matched in the last iteration.
    coarse_shift_px : (float, float)
        How far the refinement moved the image of the model's first point, pixels.
    position_correction_m : ndarray, shape (3,)
        ``pose - prior`` position, metres (ENU).
    rotation_correction_deg : float
        Angle of the rotation between prior and refined attitude, degrees.
    """

    pose: CameraPose
    prior: CameraPose
    rms_px: float
    n_points: int
    coarse_shift_px: tuple[float, float]
    position_correction_m: NDArray[np.float64]
    rotation_correction_deg: float

    def describe(self) -> dict[str, object]:
        return {
            "pose": self.pose.to_dict(),
            "rms_px": float(self.rms_px),
            "matched_points": int(self.n_points),
            "coarse_shift_px": [float(v) for v in self.coarse_shift_px],
            "position_correction_m": [float(v) for v in self.position_correction_m],
            "rotation_correction_deg": float(self.rotation_correction_deg),
        }


def facet_outline_segments(corners: ArrayLike) -> NDArray[np.float64]:
    """The edges of facets as 3-D segments, shape (F * 4, 2, 3), from corners (F, 4, 3)."""
    c = np.asarray(corners, float)
    if c.ndim != 3 or c.shape[1:] != (4, 3):
        raise PihimInputError(f"facet corners must have shape (F, 4, 3), got {c.shape}")
    return np.stack([c, np.roll(c, -1, axis=1)], axis=2).reshape(-1, 2, 3)


def sample_segments(segments: ArrayLike, spacing_m: float) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Points every ``spacing_m`` along 3-D segments (ends included) and the segment of each point."""
    s = np.asarray(segments, float)
    length = np.linalg.norm(s[:, 1] - s[:, 0], axis=1)
    n = np.maximum(2, np.ceil(length / spacing_m).astype(int) + 1)
    pts = []
    seg = []
    for k in range(len(s)):
        t = np.linspace(0.0, 1.0, n[k])[:, None]
        pts.append(s[k, 0] + t * (s[k, 1] - s[k, 0]))
        seg.append(np.full(n[k], k))
    return np.concatenate(pts), np.concatenate(seg)


def line_normals(uv: NDArray, seg: NDArray) -> NDArray:
    """Unit 2-D normals of projected polylines at their sample points ``uv`` (N, 2).

    ``seg`` (N,) says which segment each sample belongs to; the tangent is the
    central difference of neighbours on the same segment (one-sided at its
    ends).
    """
    same_next = np.append(seg[1:] == seg[:-1], False)
    same_prev = np.insert(seg[1:] == seg[:-1], 0, False)
    nxt = np.where(same_next[:, None], np.roll(uv, -1, axis=0), uv)
    prv = np.where(same_prev[:, None], np.roll(uv, 1, axis=0), uv)
    tangent = nxt - prv
    ln = np.linalg.norm(tangent, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        tangent = tangent / ln
    return np.column_stack([-tangent[:, 1], tangent[:, 0]])


def match_edge_points(uv: NDArray, usable: NDArray[np.bool_], obs: NDArray, gate: float, min_hits: int,
                      what: str) -> tuple[NDArray[np.int64], NDArray]:
    """Pair image edge points with their nearest usable model sample within ``gate`` pixels.

    Returns the model sample index of each matched edge point and the matched
    points; raises :class:`PihimInputError` (naming ``what``) when fewer than
    ``min_hits`` match.
    """
    from scipy.spatial import cKDTree

    d, j = cKDTree(uv[usable]).query(obs, distance_upper_bound=gate)
    hit = np.isfinite(d)
    if hit.sum() < min_hits:
        raise PihimInputError(f"{what} matches only {int(hit.sum())} edge points")
    return np.flatnonzero(usable)[j[hit]], obs[hit]


def _project_lines(camera: CameraModel, pose: CameraPose, pts: NDArray, seg: NDArray) -> tuple[NDArray, NDArray]:
    """Projected sample points and unit 2-D normals of the projected lines at them."""
    uv = project_points(camera, pose, pts)
    return uv, line_normals(uv, seg)


def _rotation_from_vector(r: NDArray) -> NDArray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(r).as_matrix()


def _perturbed(pose: CameraPose, params: NDArray) -> CameraPose:
    """Pose with a small rotation (rotation vector in the camera frame, rad) and a position offset (m)."""
    r = _rotation_from_vector(params[:3])
    return CameraPose(pose.position_m + params[3:], r @ pose.rotation)


def _coarse_shift(camera: CameraModel, pose: CameraPose, pts: NDArray, edges: EdgePoints,
                  max_shift_px: float, scale: int = 4, sigma_px: float = 2.0,
                  with_score: bool = False) -> tuple[float, ...]:
    import cv2
    from scipy.signal import fftconvolve

    h, w = camera.height_px, camera.width_px
    hs, ws = int(np.ceil(h / scale)), int(np.ceil(w / scale))
    obs = np.zeros((hs, ws), np.uint8)
    q = np.rint(edges.xy / scale).astype(int)
    ok = (q[:, 0] >= 0) & (q[:, 0] < ws) & (q[:, 1] >= 0) & (q[:, 1] < hs)
    obs[q[ok, 1], q[ok, 0]] = 1
    dt = cv2.distanceTransform((1 - obs).astype(np.uint8), cv2.DIST_L2, 5)
    prox = np.exp(-0.5 * (dt / sigma_px) ** 2)
    m = int(np.ceil(max_shift_px / scale))
    uv = project_points(camera, pose, pts) / scale
    fin = np.all(np.isfinite(uv), axis=1)
    uv = uv[fin]
    # model raster on a canvas padded by the search range
    canvas = np.zeros((hs + 2 * m, ws + 2 * m))
    mi = np.rint(uv).astype(int) + m
    okm = (mi[:, 0] >= 0) & (mi[:, 0] < ws + 2 * m) & (mi[:, 1] >= 0) & (mi[:, 1] < hs + 2 * m)
    np.add.at(canvas, (mi[okm, 1], mi[okm, 0]), 1.0)
    # score(s) = sum over model points of prox(model + s), s in [-m, m]^2
    corr = fftconvolve(np.pad(prox, m), canvas[::-1, ::-1], mode="same")
    cy, cx = corr.shape[0] // 2, corr.shape[1] // 2
    win = corr[cy - m:cy + m + 1, cx - m:cx + m + 1]
    k = np.unravel_index(int(np.argmax(win)), win.shape)
    dy, dx = (k[0] - m), (k[1] - m)
    # sign convention pinned by tests/inspection/test_pose.py (a known shift is found back)
    if with_score:
        return win, m, float(max(okm.sum(), 1))
    return float(dx * scale), float(dy * scale)


def _coarse_peaks(camera: CameraModel, pose: CameraPose, pts: NDArray, edges: EdgePoints,
                  max_shift_px: float, n_peaks: int, scale: int = 4) -> list[tuple[float, float, float]]:
    """The ``n_peaks`` best separated image shifts ``(dx, dy, score)``; score = model points on edges / all."""
    win, m, n_pts = _coarse_shift(camera, pose, pts, edges, max_shift_px, scale=scale, with_score=True)
    w = win.copy()
    out = []
    sep = max(3, int(round(25 / scale)))
    for _ in range(n_peaks):
        k = np.unravel_index(int(np.argmax(w)), w.shape)
        if not np.isfinite(w[k]) or w[k] <= 0:
            break
        out.append((float((k[1] - m) * scale), float((k[0] - m) * scale), float(w[k] / n_pts)))
        w[max(0, k[0] - sep):k[0] + sep + 1, max(0, k[1] - sep):k[1] + sep + 1] = -np.inf
    return out


def _coarse_candidates(camera: CameraModel, prior: CameraPose, pts: NDArray, edges: EdgePoints,
                       max_shift_px: float, range_m: float, n_best: int) -> list[tuple[float, CameraPose]]:
    """Starting poses: the best image shifts over camera moves along the optical axis (range error)."""
    found: list[tuple[float, CameraPose]] = []
    steps = np.arange(-range_m, range_m + 1e-9, max(range_m / 8.0, 0.05)) if range_m > 0 else np.zeros(1)
    for step in steps:
        cand = CameraPose(prior.position_m + step * prior.forward, prior.rotation)
        for dx, dy, score in _coarse_peaks(camera, cand, pts, edges, max_shift_px, 3):
            found.append((score, _pan_tilt(camera, cand, dx, dy)))
    found.sort(key=lambda t: -t[0])
    return found[:n_best]


def _pan_tilt(camera: CameraModel, pose: CameraPose, dx: float, dy: float) -> CameraPose:
    """Turn the camera so that the image content moves by (dx, dy) pixels near the centre."""
    # content moves right (dx > 0) when the camera turns left, i.e. by a positive rotation
    # vector about camera y (x_cam' = R x_cam with R = rotvec(ay e_y)) -- pinned by a test
    ay = np.arctan2(dx, camera.fx_px)
    ax = -np.arctan2(dy, camera.fy_px)
    return _perturbed(pose, np.array([ax, ay, 0.0, 0.0, 0.0, 0.0]))


def refine_pose(
    camera: CameraModel,
    prior: CameraPose,
    segments: ArrayLike,
    edges: EdgePoints,
    *,
    max_shift_px: float = 700.0,
    range_m: float = 4.0,
    spacing_m: float = 0.02,
    gates_px: tuple[float, ...] = (40.0, 15.0, 6.0, 3.0, 3.0),
    n_starts: int = 1,
) -> PoseFit:
    """Refine a camera pose so that projected 3-D segments fall on image edge points.

    Parameters
    ----------
    camera : CameraModel
    prior : CameraPose
        Starting pose (the logged one).
    segments : array_like, shape (S, 2, 3)
        Model edges in ENU (e.g. :func:`facet_outline_segments` of the HUA's
        facets and mirror outline).
    edges : EdgePoints
        Sub-pixel edge points of the image (:func:`pihim.inspection.features.edge_points`).
    max_shift_px : float
        Half-size of the coarse search window, pixels.
    range_m : float
        The coarse search also moves the camera along its optical axis by up
        to this much (range / altitude error of the prior), metres.
    spacing_m : float
        Sampling of the model edges, metres.
    gates_px : tuple of float
        Matching distance of each ICP round, pixels.
    n_starts : int
        ICP runs from the best coarse candidates; the one whose final pose
        puts the most edge points within 1.5 px of the model wins.
    Notes
    -----
    Measured on a rendered 2448 x 2048 UFACET frame (20 mm lens, whole HUA in
    view): from priors whose facet corners project within about 100 px of
    the truth the refinement converges to 0.2 px (0.01 deg, 2 mm); from the
    issue's GPS 1.5 m / attitude 1 deg priors (200-600 px) it often stops in
    a wrong minimum of the periodic facet grid (tests/inspection/test_pose.py
    holds the first case; the second is open). Soft priors holding the
    position and attitude near the log, several starting points and the
    neighbouring heliostats' outlines were tried and did not close it.

    Returns
    -------
    PoseFit

    Raises
    ------
    PihimInputError
        No edge points, or too few matched to fix six parameters.
    """
    if len(edges) < 50:
        raise PihimInputError(f"only {len(edges)} edge points in the image: cannot refine the pose")
    pts, seg = sample_segments(segments, spacing_m)
    starts = _coarse_candidates(camera, prior, pts, edges, max_shift_px, range_m, n_starts)
    best = None
    for _, start in starts:
        try:
            fit = _icp(camera, start, pts, seg, edges.xy, gates_px)
        except PihimInputError:
            continue
        if best is None or fit[3] > best[3]:
            best = fit
    if best is None:
        raise PihimInputError("the heliostat's outline matches too few edge points: pose prior too far off?")
    pose, rms, n_used, _support = best
    shift = project_points(camera, pose, pts[:1])[0] - project_points(camera, prior, pts[:1])[0]
    dx, dy = float(shift[0]), float(shift[1])
    rel = pose.rotation @ prior.rotation.T
    ang = float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1.0, 1.0))))
    return PoseFit(pose, prior, rms, n_used, (dx, dy), pose.position_m - prior.position_m, ang)


def _icp(camera: CameraModel, start: CameraPose, pts: NDArray, seg: NDArray, obs: NDArray,
         gates_px: tuple[float, ...]) -> tuple[CameraPose, float, int, int]:
    """Point-to-line ICP from ``start``; returns (pose, rms px, matched points, support within 1.5 px)."""
    from scipy.optimize import least_squares
    from scipy.spatial import cKDTree

    pose = start
    rms = np.inf
    n_used = 0
    for gate in gates_px:
        uv, nrm = _project_lines(camera, pose, pts, seg)
        good = np.all(np.isfinite(uv), axis=1) & np.all(np.isfinite(nrm), axis=1)
        inside = good & (uv[:, 0] > -gate) & (uv[:, 0] < camera.width_px + gate) \
            & (uv[:, 1] > -gate) & (uv[:, 1] < camera.height_px + gate)
        if inside.sum() < 30:
            raise PihimInputError("the heliostat is not in view")
        idx, q = match_edge_points(uv, inside, obs, gate, 30, "the heliostat's outline")

        def residuals(params: NDArray, q=q, idx=idx, pose=pose, gate=gate) -> NDArray:
            uvc, nc = _project_lines(camera, _perturbed(pose, params), pts, seg)
            return np.nan_to_num(np.einsum("ij,ij->i", q - uvc[idx], nc[idx]), nan=gate)

        sol = least_squares(residuals, np.zeros(6), loss="soft_l1", f_scale=1.0,
                            x_scale=np.array([1e-3, 1e-3, 1e-3, 0.1, 0.1, 0.1]), max_nfev=50)
        pose = _perturbed(pose, sol.x)
        r = residuals(np.zeros(6))
        rms = float(np.sqrt(np.mean(r**2)))
        n_used = len(q)
    uv, _ = _project_lines(camera, pose, pts, seg)
    ok = np.all(np.isfinite(uv), axis=1)
    d, _ = cKDTree(uv[ok]).query(obs, distance_upper_bound=1.5)
    return pose, rms, n_used, int(np.isfinite(d).sum())
