"""Camera pose refinement on the heliostat under assessment (paper sec. 4.4, step 2).

The logged GPS/IMU pose (about 1-2 m and 1 deg) places the heliostat
hundreds of pixels from where it appears. The pose is refined against the
outlines of the HUA's facets, which the field model gives exactly in the
heliostat frame:

1. **Search**: starting positions around the logged one (about a GPS
   sigma apart, nearest first, a second ring only when the first fails);
   at each, the projected facet outlines, rasterised at 1/16 resolution,
   are cross-correlated (FFT) with a proximity map ``exp(-DT^2 / 2 s^2)``
   of the image's edge points, and the best image shifts (by two scores:
   mean proximity of the points in frame, and share of the whole model) are
   turned into a pan and tilt of the camera.
2. **Alignment**: the six pose parameters maximise the summed proximity on
   ever sharper maps (s = 48 to 3 px, trust-region least squares); a wide
   map merges the two edges of each facet gap, so the basin spans a good
   part of a facet. The first start whose aligned outline has 80 % of its
   in-frame points within 1.5 px of an edge wins (else the best).
3. **Fine**: Levenberg-Marquardt on the point-to-line distances between the
   image's sub-pixel edge points and the nearest projected model edge,
   re-matched between solves with a shrinking gate (an ICP with the
   point-to-line metric), with a soft-L1 loss against outliers.

The result is the pose of the camera **relative to the HUA as the field
model places it from its logged drive angles**: a tracking error of the HUA
is absorbed into the pose (it cannot be told apart from a camera pose error
with the HUA alone).

The inner loops (projection, the chamfer and point-to-line solves with
analytic Jacobians, the edge-point matching) are compiled
(:mod:`pihim.inspection._kernels`).

Status (20 rendered NSTTF UFACET frames, ``benchmarks/canting_quality.py``)
----------------------------------------------------------------------------
From the issue's GPS 1.5 m / attitude 1 deg priors (facet corners a median
1,127 px off), no pose failure: the worst facet corner lands a median
0.31 px from the truth (at most 0.98 px). The refinement takes a median
0.33 s of CPU per full frame (0.26-1.23 s over 3-51 aligned starts, 2.3 s
for a 4 m-off prior that needs 170; 0.8 s median wall on a heavily loaded
2-core machine).

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

import contextlib
from collections.abc import Callable, Iterator
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
    support : float
        Share of the model's in-frame sample points within 1.5 px of an edge
        point at the refined pose (about 0.9 on a good fit; well below 0.5
        the fit is unlikely to be right).
    starts : int
        Aligned starting poses the search tried.
    """

    pose: CameraPose
    prior: CameraPose
    rms_px: float
    n_points: int
    coarse_shift_px: tuple[float, float]
    position_correction_m: NDArray[np.float64]
    rotation_correction_deg: float
    support: float = float("nan")
    starts: int = 0

    def describe(self) -> dict[str, object]:
        return {
            "pose": self.pose.to_dict(),
            "rms_px": float(self.rms_px),
            "matched_points": int(self.n_points),
            "coarse_shift_px": [float(v) for v in self.coarse_shift_px],
            "position_correction_m": [float(v) for v in self.position_correction_m],
            "rotation_correction_deg": float(self.rotation_correction_deg),
            "support": float(self.support),
            "starts": int(self.starts),
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
    from pihim.inspection import _kernels

    return _kernels.line_normals(np.ascontiguousarray(uv, dtype=float), np.ascontiguousarray(seg, dtype=np.int64))


def match_edge_points(uv: NDArray, usable: NDArray[np.bool_], obs: NDArray, gate: float, min_hits: int,
                      what: str, normals: NDArray | None = None) -> tuple[NDArray[np.int64], NDArray]:
    """Pair image edge points with their nearest usable model sample within ``gate`` pixels.

    Returns the model sample index of each matched edge point and the matched
    points; raises :class:`PihimInputError` (naming ``what``) when fewer than
    ``min_hits`` match. Of equally near samples (a corner, which ends one
    side and starts the next) the one whose line -- through it with its unit
    normal of ``normals`` (N, 2), as :func:`line_normals` gives them -- passes
    nearest the edge point is taken (the point-to-line residual the fits
    minimise), without ``normals`` the first.
    """
    from pihim.inspection import _kernels

    nrm = np.zeros((0, 2)) if normals is None else np.ascontiguousarray(normals[usable], dtype=float)
    # the kernel passes over the edge points outside the model's bounding box grown by the gate
    j, _ = _kernels.nearest_within(np.ascontiguousarray(uv[usable], dtype=float),
                                   np.ascontiguousarray(obs, dtype=float), float(gate), nrm)
    hit = np.flatnonzero(j >= 0)
    if len(hit) < min_hits:
        raise PihimInputError(f"{what} matches only {len(hit)} edge points")
    j = j[hit]
    return np.flatnonzero(usable)[j], obs[hit]


def _rotation_from_vector(r: NDArray) -> NDArray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(r).as_matrix()


def _perturbed(pose: CameraPose, params: NDArray) -> CameraPose:
    """Pose with a small rotation (rotation vector in the camera frame, rad) and a position offset (m)."""
    r = _rotation_from_vector(params[:3])
    return CameraPose(pose.position_m + params[3:], r @ pose.rotation)


class _CoarseSearch:
    """Image-shift scores of projected model points against the edge points at ``1/scale`` resolution.

    The score of a shift ``s`` is the mean proximity ``exp(-DT^2 / 2 sigma^2)`` (at
    ``1/scale`` resolution) over the model points that land in the frame; shifts that bring
    fewer than half as many points into the frame as the best-covered shift are not
    considered (a handful of points would score by chance). The edges' proximity map and
    its transform are computed once; each pose then costs one forward and two inverse FFTs
    (the correlation of the rasterised model with the proximity map and with the frame).
    """

    def __init__(self, camera: CameraModel, edges: EdgePoints, max_shift_px: float, scale: int = 4,
                 sigma_px: float = 2.0):
        import cv2
        from scipy import fft

        h, w = camera.height_px, camera.width_px
        hs, ws = int(np.ceil(h / scale)), int(np.ceil(w / scale))
        obs = np.zeros((hs, ws), np.uint8)
        q = np.rint(edges.xy / scale).astype(int)
        ok = (q[:, 0] >= 0) & (q[:, 0] < ws) & (q[:, 1] >= 0) & (q[:, 1] < hs)
        obs[q[ok, 1], q[ok, 0]] = 1
        dt = cv2.distanceTransform((1 - obs).astype(np.uint8), cv2.DIST_L2, 5)
        prox = np.exp(-0.5 * (dt / sigma_px) ** 2)
        m = int(np.ceil(max_shift_px / scale))
        # the model raster lives on the frame padded by the search range m; a transform size
        # of at least (padded size + m) keeps the circular correlation free of wrap-around
        self.scale, self.m, self.hs, self.ws = scale, m, hs, ws
        self.shape = (fft.next_fast_len(hs + 3 * m, real=True), fft.next_fast_len(ws + 3 * m, real=True))
        self.prox_f = fft.rfft2(np.pad(prox.astype(float), m), self.shape)
        self.ones_f = fft.rfft2(np.pad(np.ones_like(prox), m), self.shape)

    def scores(self, camera: CameraModel, pose: CameraPose, pts: NDArray) -> tuple[NDArray, NDArray]:
        """Score maps over shifts ``(dy, dx)`` in ``[-m, m]^2`` (index ``k`` is shift ``k - m``):
        the mean proximity over the points in frame (``-inf`` where too few are) and the summed
        proximity as a share of all the model's points."""
        from scipy import fft

        from pihim.inspection import _kernels

        m, hs, ws = self.m, self.hs, self.ws
        uv = _kernels.project_pose(camera, pose, pts) / self.scale
        uv = uv[np.all(np.isfinite(uv), axis=1)]
        canvas = np.zeros((hs + 2 * m, ws + 2 * m))
        mi = np.rint(uv).astype(int) + m
        okm = (mi[:, 0] >= 0) & (mi[:, 0] < ws + 2 * m) & (mi[:, 1] >= 0) & (mi[:, 1] < hs + 2 * m)
        np.add.at(canvas, (mi[okm, 1], mi[okm, 0]), 1.0)
        # correlation: total(d) = sum over model points of prox(model + d), count(d) = points in frame
        cf = np.conj(fft.rfft2(canvas, self.shape))
        total = fft.irfft2(cf * self.prox_f, self.shape)
        count = np.rint(fft.irfft2(cf * self.ones_f, self.shape))  # integer counts
        d = np.arange(-m, m + 1)
        sel = np.ix_(d % self.shape[0], d % self.shape[1])
        total, count = total[sel], count[sel]
        win = np.where(count >= 0.5 * count.max(), total / np.maximum(count, 1.0), -np.inf)
        return win, total / max(float(okm.sum()), 1.0)


def _coarse_shift(camera: CameraModel, pose: CameraPose, pts: NDArray, edges: EdgePoints,
                  max_shift_px: float, scale: int = 4, sigma_px: float = 2.0) -> tuple[float, float]:
    """Best image shift ``(dx, dy)`` of the projected points onto the edges (see :class:`_CoarseSearch`)."""
    search = _CoarseSearch(camera, edges, max_shift_px, scale, sigma_px)
    win, _ = search.scores(camera, pose, pts)
    k = np.unravel_index(int(np.argmax(win)), win.shape)
    dy, dx = (k[0] - search.m), (k[1] - search.m)
    # sign convention pinned by tests/inspection/test_pose.py (a known shift is found back)
    return float(dx * scale), float(dy * scale)


def _coarse_peaks(camera: CameraModel, pose: CameraPose, pts: NDArray, search: _CoarseSearch,
                  n_peaks: int) -> list[tuple[float, float, float]]:
    """The ``n_peaks`` best separated image shifts ``(dx, dy, score)`` of each of two scores.

    The mean proximity over the points in frame finds the right shift when the prior is
    close and most of the model is out of the frame; the proximity summed over all points
    (a share of the whole model) when the prior is far and a shift brings more of the
    model into view. Both lists are returned, the first score's peaks first.
    """
    norm, share = search.scores(camera, pose, pts)
    m, scale = search.m, search.scale
    sep = max(3, int(round(25 / scale)))
    out: list[tuple[float, float, float]] = []
    for win in (norm, share):
        w = win.copy()
        for _ in range(n_peaks):
            k = np.unravel_index(int(np.argmax(w)), w.shape)
            if not np.isfinite(w[k]) or w[k] <= 0:
                break
            dx, dy = float((k[1] - m) * scale), float((k[0] - m) * scale)
            w[max(0, k[0] - sep):k[0] + sep + 1, max(0, k[1] - sep):k[1] + sep + 1] = -np.inf
            if all(abs(dx - a) > sep * scale or abs(dy - b) > sep * scale for a, b, _ in out):
                out.append((dx, dy, float(w.dtype.type(win[k]))))
    return out


def _pan_tilt(camera: CameraModel, pose: CameraPose, dx: float, dy: float) -> CameraPose:
    """Turn the camera so that the image content moves by (dx, dy) pixels near the centre."""
    # content moves right (dx > 0) when the camera turns left, i.e. by a positive rotation
    # vector about camera y (x_cam' = R x_cam with R = rotvec(ay e_y)) -- pinned by a test
    ay = np.arctan2(dx, camera.fx_px)
    ax = -np.arctan2(dy, camera.fy_px)
    return _perturbed(pose, np.array([ax, ay, 0.0, 0.0, 0.0, 0.0]))


class _EdgeMaps:
    """Distance transform of the edge points and Gaussian proximity maps ``exp(-DT^2 / 2 s^2)`` (float32).

    The fits take the maps' gradients (Sobel, 3 x 3, divided by 8) where they sample them
    (:mod:`pihim.inspection._kernels`) rather than as whole images.
    """

    def __init__(self, edges: EdgePoints, shape: tuple[int, int], sigmas_px: tuple[float, ...]):
        import cv2

        h, w = shape
        img = np.ones((h, w), np.uint8)
        q = np.rint(edges.xy).astype(int)
        ok = (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)
        img[q[ok, 1], q[ok, 0]] = 0
        self.dt = cv2.distanceTransform(img, cv2.DIST_L2, 5)
        d2 = self.dt * self.dt
        self.levels = [cv2.exp(d2 * np.float32(-0.5 / s**2)) for s in sigmas_px]

    def support(self, uv: NDArray, tol_px: float = 1.5) -> float:
        """Share of the in-frame points ``uv`` within ``tol_px`` of an edge point (0 if fewer than 30 in frame)."""
        h, w = self.dt.shape
        ok = np.all(np.isfinite(uv), axis=1)
        q = np.rint(uv[ok]).astype(int)
        q = q[(q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)]
        return float(np.mean(self.dt[q[:, 1], q[:, 0]] <= tol_px)) if len(q) >= 30 else 0.0


@contextlib.contextmanager
def _aligner(camera: CameraModel, pts: NDArray, maps: _EdgeMaps) -> Iterator[Callable[[list], list]]:
    """``align(poses) -> [_chamfer_align(pose) ...]``, in order, on threads.

    As many threads as numba may use (``NUMBA_NUM_THREADS``: one per CPU, or
    what the caller set, e.g. 1 in a campaign's workers), at most four (a
    start has at most ``2 n_peaks`` alignments); the compiled fits release the
    GIL, and each alignment is computed as on one thread (identical poses).
    """
    from pihim.inspection._threads import ordered_map

    with ordered_map(4) as run:
        yield lambda poses: run(lambda p: _chamfer_align(camera, p, pts, maps), poses)


def _chamfer_align(camera: CameraModel, pose: CameraPose, pts: NDArray, maps: _EdgeMaps) -> CameraPose:
    """Pull the projected points onto the edges through ever sharper proximity maps (coarse to fine).

    Each level maximises the summed proximity ``sum exp(-DT^2 / 2 s^2)`` over the six pose
    parameters (a rotation vector in the camera frame and a position offset): trust-region
    least squares on ``1 - proximity`` with the analytic Jacobian (image gradient of the map
    times the projection Jacobian), compiled (:func:`pihim.inspection._kernels.solve`).
    A wide ``s`` merges the two edges of a facet gap, and the model's two lines alike, so the
    basin spans a good part of a facet instead of the half gap width that nearest-point
    matching (ICP) allows.
    """
    from pihim.inspection import _kernels

    cam = _kernels.camera_vector(camera)
    rot = np.array(pose.rotation)
    centre = np.array(pose.position_m)
    pts = np.ascontiguousarray(pts, dtype=float)
    for prox in maps.levels:
        prob = _kernels.problem(_kernels.CHAMFER, rot, centre, pts, cam, prox=prox)
        x = _kernels.solve(prob, np.zeros(6), len(pts), _X_SCALE, 30, False, 1.0)[0]
        rot = _kernels.rotation_from_vector(x[:3]) @ rot
        centre = centre + x[3:]
    return CameraPose(centre, rot)


#: Scale of the six pose parameters in the fits: rotation vector (rad) and position (m).
_X_SCALE = np.array([1e-3, 1e-3, 1e-3, 0.1, 0.1, 0.1])


def _start_offsets(search_m: tuple[float, float, float], rings: int = 1) -> list[NDArray]:
    """Camera-frame position offsets ``k s``, ``|k| <= rings``, per axis: the prior first, then by distance."""
    ks = np.arange(-rings, rings + 1, dtype=float)
    grids = [tuple(ks * s) if s > 0 else (0.0,) for s in search_m]
    offs = {(a, b, c) for a in grids[0] for b in grids[1] for c in grids[2]}
    return [np.array(o) for o in sorted(offs, key=lambda o: (float(np.linalg.norm(o)), o))]


def refine_pose(
    camera: CameraModel,
    prior: CameraPose,
    segments: ArrayLike,
    edges: EdgePoints,
    *,
    search_m: tuple[float, float, float] = (1.5, 1.5, 2.0),
    search_rings: int = 2,
    max_shift_px: float = 1400.0,
    accept_support: float = 0.9,
    n_peaks: int = 2,
    spacing_m: float = 0.02,
    sigmas_px: tuple[float, ...] = (48.0, 24.0, 12.0, 6.0, 3.0),
    gates_px: tuple[float, ...] = (6.0, 3.0, 3.0),
) -> PoseFit:
    """Refine a camera pose so that projected 3-D segments fall on image edge points.

    Parameters
    ----------
    camera : CameraModel
    prior : CameraPose
        Starting pose (the logged one).
    segments : array_like, shape (S, 2, 3)
        Model edges in ENU (e.g. :func:`facet_outline_segments` of the HUA's
        facets).
    edges : EdgePoints
        Sub-pixel edge points of the image (:func:`pihim.inspection.features.edge_points`).
    search_m : (float, float, float)
        Starting positions: the prior's position moved by ``{-s, 0, s}`` along
        the camera's x (right), y (down) and z (forward) axes, metres (about
        one GPS sigma), nearest first.
    search_rings : int
        Starting positions go out to ``search_rings`` steps per axis (2: up
        to 3 m sideways and 4 m along the view, 125 starts at most; the
        search stops at the first good start, so a prior within about 2 m
        needs only the first few).
    max_shift_px : float
        Half-size of each start's image-shift search, pixels.
    accept_support : float
        The search stops at the first start whose aligned model has this
        share of its in-frame points within 1.5 px of an edge point;
        otherwise the best of all starts is kept. 0.9 (it was 0.8: a frame
        whose GPS prior was 4.3 m off locked onto a neighbouring heliostat at
        support 0.85; the search then went on and found the right pose at
        0.98, 194 starts, 2.3 s).
    n_peaks : int
        Image-shift peaks aligned per start and per coarse score (two scores).
    spacing_m : float
        Sampling of the model edges, metres.
    sigmas_px : tuple of float
        Widths of the coarse-to-fine proximity maps, pixels.
    gates_px : tuple of float
        Matching distance of each final ICP round, pixels.

    Notes
    -----
    A GPS error of 1.5 m at 20 m both moves the heliostat in the image
    (searched as an image shift) and changes its perspective (not a shift:
    the coarse-to-fine alignment absorbs about 1 m of it), hence the
    starting positions. The aligned pose with the largest support wins: a
    start that locks onto the wrong features leaves most of the model off
    the edges (support 0.1-0.6, and 0.85 once, against 0.87-0.98 for the
    right pose on the rendered UFACET frames of
    ``benchmarks/canting_quality.py``, which measures the whole search from
    the issue's priors). The alignments of one start run on threads (as
    many as ``NUMBA_NUM_THREADS``, at most four) and are compared in order,
    so the result is the one-thread result.

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
    from pihim.inspection import _kernels

    pts, seg = sample_segments(segments, spacing_m)
    maps = _EdgeMaps(edges, (camera.height_px, camera.width_px), sigmas_px)
    sparse = pts[:: max(1, int(round(0.12 / spacing_m)))]
    best: tuple[float, CameraPose] | None = None
    tried = 0
    search = _CoarseSearch(camera, edges, max_shift_px, scale=16)
    with _aligner(camera, sparse, maps) as align:
        for off in _start_offsets(search_m, search_rings):
            start = CameraPose(prior.position_m + prior.rotation.T @ off, prior.rotation)
            peaks = _coarse_peaks(camera, start, pts, search, n_peaks)
            # a start's alignments side by side (the compiled fits release the GIL); compared in order
            for aligned in align([_pan_tilt(camera, start, dx, dy) for dx, dy, _ in peaks]):
                tried += 1
                support = maps.support(_kernels.project_pose(camera, aligned, pts))
                if best is None or support > best[0]:
                    best = (support, aligned)
            if best is not None and best[0] >= accept_support:
                break
    if best is None:
        raise PihimInputError("the heliostat's outline matches no edges: pose prior too far off?")
    pose, rms, n_used = _icp(camera, best[1], pts, seg, edges.xy, gates_px)
    support = maps.support(_kernels.project_pose(camera, pose, pts))
    shift = project_points(camera, pose, pts[:1])[0] - project_points(camera, prior, pts[:1])[0]
    dx, dy = float(shift[0]), float(shift[1])
    rel = pose.rotation @ prior.rotation.T
    ang = float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1.0, 1.0))))
    return PoseFit(pose, prior, rms, n_used, (dx, dy), pose.position_m - prior.position_m, ang, support, tried)


def _line_neighbours(seg: NDArray) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Indices of each sample's previous and next sample on the same segment (itself at the ends).

    ``line_normals(uv, seg)[i]`` is the normal of ``uv[nxt[i]] - uv[prv[i]]``.
    """
    i = np.arange(len(seg))
    same_next = np.append(seg[1:] == seg[:-1], False)
    same_prev = np.insert(seg[1:] == seg[:-1], 0, False)
    return np.where(same_prev, i - 1, i), np.where(same_next, i + 1, i)


def _icp(camera: CameraModel, start: CameraPose, pts: NDArray, seg: NDArray, obs: NDArray,
         gates_px: tuple[float, ...]) -> tuple[CameraPose, float, int]:
    """Point-to-line ICP from ``start``; returns (pose, rms px, matched points of the last round).

    Each round re-matches, then solves the six pose parameters by trust-region least squares
    with a soft-L1 loss (scale 1 px) on the distances of the matched edge points from the
    projected outline's lines (:func:`pihim.inspection._kernels.solve`, analytic
    Jacobian including the turn of the line); only the matched model points and their two
    neighbours on the outline (the line's central difference, as :func:`line_normals`) are
    projected.
    """
    from pihim.inspection import _kernels

    cam = _kernels.camera_vector(camera)
    pts = np.ascontiguousarray(pts, dtype=float)
    prv, nxt = _line_neighbours(seg)
    rot = np.array(start.rotation)
    centre = np.array(start.position_m)
    rms = np.inf
    n_used = 0
    for gate in gates_px:
        uv = _kernels.project_rc(rot, centre, pts, cam)
        nrm = line_normals(uv, seg)
        good = np.all(np.isfinite(uv), axis=1) & np.all(np.isfinite(nrm), axis=1)
        inside = good & (uv[:, 0] > -gate) & (uv[:, 0] < camera.width_px + gate) \
            & (uv[:, 1] > -gate) & (uv[:, 1] < camera.height_px + gate)
        if inside.sum() < 30:
            raise PihimInputError("the heliostat is not in view")
        idx, q = match_edge_points(uv, inside, obs, gate, 30, "the heliostat's outline", nrm)
        m = len(idx)
        sub = np.concatenate([pts[idx], pts[prv[idx]], pts[nxt[idx]]])
        prob = _kernels.problem(_kernels.POINT_TO_LINE, rot, centre, sub, cam, q=q, gate=gate)
        x, r, _ = _kernels.solve(prob, np.zeros(6), m, _X_SCALE, 50, True, 1.0)
        rot = _kernels.rotation_from_vector(x[:3]) @ rot
        centre = centre + x[3:]
        rms = float(np.sqrt(np.mean(r**2)))
        n_used = m
    return CameraPose(centre, rot), rms, n_used
