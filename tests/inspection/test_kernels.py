"""The compiled inner loops of the pose and canting fits against independent oracles.

OpenCV (``cv2.projectPoints``, ``cv2.Rodrigues``, ``cv2.Sobel``), SciPy
(``map_coordinates``, ``least_squares``, ``fftconvolve``), numpy
(median, percentile) and plain-numpy statements of the same algorithms;
the solvers on synthetic problems with a known answer.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.ndimage import map_coordinates
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from pihim.camera import CameraModel, CameraPose, project_points
from pihim.inspection import _kernels as K
from pihim.inspection.reflection import _facet_masks, _Mask
from pihim.inspection.features import EdgePoints, _median_and_percentile, combined_gradient, edge_points
from pihim.inspection.pose import _CoarseSearch, _line_neighbours, line_normals

DIST = (-0.2, 0.1, 1e-3, -5e-4, 0.01)
WIDE = CameraModel(width_px=640, height_px=480, focal_length_mm=3.0, distortion=DIST,
                   principal_point_px=(331.3, 236.7), pixel_aspect=1.02)
POSE = CameraPose.look_at([1.0, -20.0, 6.0], [0.0, 0.0, 2.0], roll_deg=4.0)


def _perturbed(pose: CameraPose, x: np.ndarray) -> CameraPose:
    """The pose the kernels' parameters describe, built independently (SciPy's rotation vector)."""
    return CameraPose(pose.position_m + x[3:], Rotation.from_rotvec(x[:3]).as_matrix() @ pose.rotation)


def _points(rng: np.random.Generator, n: int = 300) -> np.ndarray:
    return rng.uniform(-4.0, 4.0, (n, 3)) + [0.0, 0.0, 2.0]


# ---------------------------------------------------------------------------------- projection


def test_projection_matches_cv2_and_is_nan_behind_the_camera():
    rng = np.random.default_rng(0)
    pts = _points(rng)
    rvec, tvec = POSE.rvec_tvec()
    ref, _ = cv2.projectPoints(pts, rvec, tvec, WIDE.intrinsics(), WIDE.distortion_coefficients())
    uv = K.project_pose(WIDE, POSE, pts)
    np.testing.assert_allclose(uv, ref[:, 0], rtol=0, atol=1e-7)
    behind = POSE.position_m - 3.0 * POSE.forward
    assert np.all(np.isnan(K.project_pose(WIDE, POSE, behind[None])))


def test_rotation_vector_matches_cv2_rodrigues():
    rng = np.random.default_rng(1)
    for w in [np.zeros(3), np.array([1e-9, -2e-9, 0.0]), *rng.normal(0.0, 1.0, (5, 3)), *rng.normal(0, 1e-5, (3, 3))]:
        np.testing.assert_allclose(K.rotation_from_vector(w), cv2.Rodrigues(w)[0], rtol=0, atol=1e-14)


def test_left_jacobian_moves_the_rotation_vector_to_the_left():
    rng = np.random.default_rng(2)
    for w in [np.zeros(3), rng.normal(0.0, 0.7, 3), rng.normal(0.0, 1e-6, 3)]:
        jl = K.left_jacobian(w)
        for k in range(3):
            h = 1e-6 * np.eye(3)[k]
            # exp(w + h) exp(w)^T = exp(J_l h) to first order
            d = Rotation.from_matrix(K.rotation_from_vector(w + h) @ K.rotation_from_vector(w).T).as_rotvec()
            np.testing.assert_allclose(d, jl @ h, rtol=0, atol=1e-11)


def test_projection_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    pts = _points(rng, 100)
    x = np.array([2e-3, -1e-3, 4e-3, 0.05, -0.1, 0.2])
    uv, jac = K.project_rc_jacobian(np.array(POSE.rotation), np.array(POSE.position_m), x, pts,
                                    K.camera_vector(WIDE))
    np.testing.assert_allclose(uv, project_points(WIDE, _perturbed(POSE, x), pts), rtol=0, atol=1e-8)
    for i in range(6):
        h = np.zeros(6)
        h[i] = 1e-6
        fd = (project_points(WIDE, _perturbed(POSE, x + h), pts)
              - project_points(WIDE, _perturbed(POSE, x - h), pts)) / 2e-6
        np.testing.assert_allclose(jac[:, :, i], fd, rtol=1e-6, atol=1e-4 * np.abs(fd).max())


# ----------------------------------------------------------------------------------- sampling


def test_bilinear_and_sobel_sampling_match_map_coordinates():
    rng = np.random.default_rng(4)
    img = rng.random((30, 40)).astype(np.float32)
    u = np.concatenate([rng.uniform(-2, 42, 3000), [np.nan, 0.0, 39.0, 39.0, 12.5, -1e-9, 39.0 + 1e-9]])
    v = np.concatenate([rng.uniform(-2, 32, 3000), [3.0, 0.0, 29.0, 7.25, 29.0, 5.0, 5.0]])
    np.testing.assert_allclose(K.bilinear(img, u, v), map_coordinates(img, [v, u], order=1, cval=0.0), atol=1e-6)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    g = K.sobel_bilinear(img, u, v)
    np.testing.assert_allclose(g[:, 0], map_coordinates(gx, [v, u], order=1, cval=0.0), atol=1e-6)
    np.testing.assert_allclose(g[:, 1], map_coordinates(gy, [v, u], order=1, cval=0.0), atol=1e-6)


# ------------------------------------------------------------------------------------ solvers


def test_symmetric_eigen_decomposition_matches_numpy():
    rng = np.random.default_rng(12)
    for cond in (1.0, 1e6, 1e12):
        q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
        lam = np.geomspace(1.0, 1.0 / cond, 6) * rng.choice([1.0, 1.0, 0.0], 6)  # some exactly singular
        a = (q * lam) @ q.T
        a = 0.5 * (a + a.T)
        w, v = np.empty(6), np.empty((6, 6))
        K._sym_eig(a, w, v)
        np.testing.assert_allclose(np.sort(w), np.linalg.eigvalsh(a), rtol=0, atol=1e-14)
        np.testing.assert_allclose(v.T @ v, np.eye(6), rtol=0, atol=1e-13)
        np.testing.assert_allclose((v * w) @ v.T, a, rtol=0, atol=1e-14)


def _outline(n_side: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Sample points of four 2 m squares (a small facet grid) and the segment of each point."""
    t = np.linspace(0.0, 1.0, n_side)
    pts, seg = [], []
    for f, (cx, cz) in enumerate([(-1.1, 0.9), (1.1, 0.9), (-1.1, 3.1), (1.1, 3.1)]):
        c = np.array([[cx - 1, 0, cz - 1], [cx + 1, 0, cz - 1], [cx + 1, 0, cz + 1], [cx - 1, 0, cz + 1]], float)
        for j in range(4):
            pts.append(c[j] + t[:, None] * (c[(j + 1) % 4] - c[j]))
            seg.append(np.full(n_side, 4 * f + j))
    return np.concatenate(pts), np.concatenate(seg)


def _line_problem(pose: CameraPose, pts: np.ndarray, seg: np.ndarray, q: np.ndarray, idx: np.ndarray) -> tuple:
    prv, nxt = _line_neighbours(seg)
    sub = np.concatenate([pts[idx], pts[prv[idx]], pts[nxt[idx]]])
    return K.problem(K.POINT_TO_LINE, pose.rotation, pose.position_m, sub, K.camera_vector(WIDE), q=q, gate=3.0)


@pytest.mark.parametrize("kind", ["chamfer", "line", "reflection"])
def test_analytic_jacobians_match_finite_differences(kind):
    rng = np.random.default_rng(5)
    pts, seg = _outline()
    cam = K.camera_vector(WIDE)
    if kind == "chamfer":
        # a plane: its bilinear interpolant and Sobel gradient are exact, so the residual's
        # derivative is the map's gradient times the projection's
        vv, uu = np.mgrid[0:480, 0:640]
        prox = (uu / 1024 + vv / 2048).astype(np.float32)  # exact in single precision
        prob = K.problem(K.CHAMFER, POSE.rotation, POSE.position_m, pts, cam, prox=prox)
        x, m = np.array([1e-3, -2e-3, 1e-3, 0.02, 0.05, -0.03]), len(pts)
        steps = np.array([1e-5] * 3 + [1e-3] * 3)  # the map is single precision
    elif kind == "line":
        idx = np.arange(5, len(pts), 7)
        q = project_points(WIDE, POSE, pts[idx]) + rng.normal(0.0, 1.0, (len(idx), 2))
        prob = _line_problem(POSE, pts, seg, q, idx)
        x, m = np.array([1e-3, -2e-3, 1e-3, 0.02, 0.05, -0.03]), len(idx)
        steps = np.array([1e-7] * 3 + [1e-5] * 3)
    else:
        idx = np.arange(len(pts)) // 2
        q = rng.normal(300.0, 50.0, (len(pts), 4))
        q[:, 2:] /= np.linalg.norm(q[:, 2:], axis=1, keepdims=True)
        aux = np.concatenate([np.eye(3).ravel(), [0.0, 0.5, 2.0], [0.1, -0.99, 0.05]])
        prob = K.problem(K.REFLECTION, POSE.rotation, POSE.position_m, pts, cam, q=q, aux=aux, idx=idx, gate=3.0)
        x, m = np.array([2.0, -3.0]), len(pts)
        steps = np.array([1e-4, 1e-4])
    jac = K.jacobian(prob, x, m)
    f = K.residuals(prob, x, m)
    assert np.abs(jac).max() > 0 and np.ptp(f) > 0
    for i, h in enumerate(steps):
        e = np.zeros(len(x))
        e[i] = h
        fd = (K.residuals(prob, x + e, m) - K.residuals(prob, x - e, m)) / (2 * h)
        np.testing.assert_allclose(jac[:, i], fd, rtol=0, atol=1e-5 * np.abs(fd).max())


def test_chamfer_jacobian_is_the_sobel_gradient_times_the_projection_jacobian():
    rng = np.random.default_rng(10)
    pts, _ = _outline()
    prox = cv2.GaussianBlur(rng.random((480, 640)).astype(np.float32), (0, 0), 3.0)
    x = np.array([1e-3, -2e-3, 1e-3, 0.02, 0.05, -0.03])
    prob = K.problem(K.CHAMFER, POSE.rotation, POSE.position_m, pts, K.camera_vector(WIDE), prox=prox)
    uv, duv = K.project_rc_jacobian(np.array(POSE.rotation), np.array(POSE.position_m), x, pts,
                                    K.camera_vector(WIDE))
    g = K.sobel_bilinear(prox, uv[:, 0], uv[:, 1])
    np.testing.assert_allclose(K.residuals(prob, x, len(pts)), 1.0 - K.bilinear(prox, uv[:, 0], uv[:, 1]), atol=1e-7)
    np.testing.assert_allclose(K.jacobian(prob, x, len(pts)), -np.einsum("nk,nkc->nc", g, duv), atol=1e-9)


def test_point_to_line_solve_recovers_a_known_pose_and_matches_scipy():
    rng = np.random.default_rng(6)
    pts, seg = _outline()
    true_x = np.array([2e-3, -1.5e-3, 3e-3, 0.15, -0.1, 0.2])
    truth = _perturbed(POSE, true_x)
    idx = np.arange(len(pts))
    keep = (idx % 40 > 0) & (idx % 40 < 39)  # not the corners: each point's line is its segment
    idx = idx[keep]
    # edge points on the true lines, slid along them, plus 10 % gross outliers
    uv, nrm = project_points(WIDE, truth, pts), line_normals(project_points(WIDE, truth, pts), seg)
    tang = np.column_stack([nrm[:, 1], -nrm[:, 0]])
    q = uv[idx] + rng.uniform(-0.3, 0.3, (len(idx), 1)) * tang[idx]
    scale = np.array([1e-3] * 3 + [0.1] * 3)
    c = np.array([-1.1, 0.0, 0.9])
    # exact edge points: the pose itself
    prob = _line_problem(POSE, pts, seg, q, idx)
    x = K.solve(prob, np.zeros(6), len(idx), scale, 100, True, 1.0)[0]
    moved = project_points(WIDE, _perturbed(POSE, x), pts) - project_points(WIDE, truth, pts)
    assert np.abs(moved).max() < 1e-4  # pixels
    # with 10 % gross outliers: the robust solution, which scipy finds too
    bad = rng.random(len(idx)) < 0.1
    q[bad] += rng.normal(0.0, 8.0, (bad.sum(), 2))
    prob = _line_problem(POSE, pts, seg, q, idx)
    x, fun, jac = K.solve(prob, np.zeros(6), len(idx), scale, 100, True, 1.0)
    ref = least_squares(lambda p: K.residuals(prob, p, len(idx)), np.zeros(6), loss="soft_l1", f_scale=1.0,
                        x_scale=scale, max_nfev=100)
    moved = project_points(WIDE, _perturbed(POSE, x), c[None]) - project_points(WIDE, truth, c[None])
    assert np.abs(moved).max() < 0.1
    pix = project_points(WIDE, _perturbed(POSE, x), pts) - project_points(WIDE, _perturbed(POSE, ref.x), pts)
    assert np.abs(pix).max() < 1e-3
    # the residuals at the solution, and the Jacobian scaled for the loss as scipy returns it
    np.testing.assert_array_equal(fun, K.residuals(prob, x, len(idx)))
    np.testing.assert_allclose(fun, ref.fun, rtol=0, atol=1e-3)
    np.testing.assert_allclose(jac, ref.jac, rtol=1e-3, atol=1e-3 * np.abs(ref.jac).max())


def test_chamfer_solve_pulls_the_outline_onto_its_edges():
    pts, seg = _outline(120)
    truth = POSE
    start = _perturbed(POSE, np.array([4e-3, -3e-3, 0.0, 0.1, 0.0, -0.1]))
    uv = project_points(WIDE, truth, pts)
    img = np.ones((480, 640), np.uint8)
    q = np.rint(uv).astype(int)
    img[q[:, 1], q[:, 0]] = 0
    dt = cv2.distanceTransform(img, cv2.DIST_L2, 5)
    prox = np.exp(-0.5 * (dt / 6.0) ** 2).astype(np.float32)
    prob = K.problem(K.CHAMFER, start.rotation, start.position_m, pts, K.camera_vector(WIDE), prox=prox)
    before = np.abs(project_points(WIDE, start, pts) - uv).max()
    x = K.solve(prob, np.zeros(6), len(pts), np.array([1e-3] * 3 + [0.1] * 3), 50, False, 1.0)[0]
    after = np.abs(project_points(WIDE, _perturbed(start, x), pts) - uv).max()
    assert before > 5.0 and after < 0.5


def test_reflection_solve_recovers_known_canting():
    from pihim.field import apply_canting_deviation

    pts, seg = _outline()
    pts = pts + [0.0, -6.0, 0.0]  # the "target", in front of the facet
    rot_hua = Rotation.from_euler("zx", [20.0, -30.0], degrees=True).as_matrix()
    centre = np.array([0.0, 0.0, 2.0])
    nd = np.array([0.02, 0.03, 1.0]) / np.linalg.norm([0.02, 0.03, 1.0])
    pose = CameraPose.look_at(centre + 15.0 * (rot_hua @ nd) + [0.0, 0.0, 3.0], centre)
    true_az, true_el = 2.5, -1.5

    def mirrored(az, el):
        n = rot_hua @ apply_canting_deviation(nd, az, el)
        return project_points(WIDE, pose, pts - 2.0 * ((pts - centre) @ n)[:, None] * n)

    uv = mirrored(true_az, true_el)
    ok = np.all(np.isfinite(uv), axis=1)
    nrm = line_normals(mirrored(0.0, 0.0), seg)
    idx = np.flatnonzero(ok & np.all(np.isfinite(nrm), axis=1) & (np.arange(len(pts)) % 40 > 2)
                         & (np.arange(len(pts)) % 40 < 37))
    q = np.column_stack([uv[idx], nrm[idx]])
    aux = np.concatenate([rot_hua.ravel(), centre, nd])
    prob = K.problem(K.REFLECTION, pose.rotation, pose.position_m, pts[idx], K.camera_vector(WIDE), q=q, aux=aux,
                     idx=np.arange(len(idx)), gate=3.0)
    x, fun, jac = K.solve(prob, np.array([0.0, 0.0]), len(idx), np.array([0.1, 0.1]), 200, True, 0.5)
    # the held normals are those at zero deviation: the answer is exact only to the outline's turn
    assert x == pytest.approx([true_az, true_el], abs=0.02)
    assert jac.shape == (len(idx), 2)
    # a start a rounding error off zero (a grid node -span + 10 steps) finds the same answer: the first
    # trust radius is at least one scaled unit, not |x0| (1e-14 ended the solve where it began)
    x_tiny = K.solve(prob, np.array([-3.552713678800501e-15, -3.552713678800501e-15]), len(idx),
                     np.array([0.1, 0.1]), 200, True, 0.5)[0]
    assert x_tiny == pytest.approx(x, abs=1e-6)


# ------------------------------------------------------------------------------------- edges


def _edge_points_numpy(s0: np.ndarray, threshold: float | None = None) -> EdgePoints:
    """The edge points of S0 in plain numpy (non-maximum suppression and parabolic peak)."""
    gx, gy, mag = combined_gradient(s0, None, None)
    norm = np.hypot(gx, gy)
    if threshold is None:
        threshold = max(5.0 * float(np.median(mag)), float(np.percentile(mag, 90)))
    h, w = mag.shape
    with np.errstate(invalid="ignore", divide="ignore"):
        nx = np.where(norm > 0, gx / norm, 0.0)
        ny = np.where(norm > 0, gy / norm, 0.0)
    ox, oy = np.rint(nx).astype(int), np.rint(ny).astype(int)
    ii, jj = np.mgrid[1:h - 1, 1:w - 1]
    c, oxi, oyi = mag[1:-1, 1:-1], ox[1:-1, 1:-1], oy[1:-1, 1:-1]
    fwd, bwd = mag[ii + oyi, jj + oxi], mag[ii - oyi, jj - oxi]
    i, j = np.nonzero((c >= threshold) & (c >= fwd) & (c > bwd) & ((oxi != 0) | (oyi != 0)))
    cc, ff, bb = c[i, j], fwd[i, j], bwd[i, j]
    den = ff - 2 * cc + bb
    with np.errstate(invalid="ignore", divide="ignore"):
        off = np.clip(np.where(den < 0, 0.5 * (bb - ff) / den, 0.0), -0.5, 0.5)
    xy = np.column_stack([(j + 1) + off * oxi[i, j], (i + 1) + off * oyi[i, j]])
    return EdgePoints(xy, np.column_stack([nx[i + 1, j + 1], ny[i + 1, j + 1]]), cc)


def test_edge_points_are_those_of_the_numpy_statement():
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:120, 0:160]
    s0 = 1.0 + 2.0 * (np.hypot(xx - 70.3, yy - 55.8) < 33.0) + 1.5 * ((xx + 0.4 * yy) > 120.0)
    s0 = cv2.GaussianBlur(s0, (0, 0), 1.3) + rng.normal(0.0, 0.02, s0.shape)
    s0[10:13, 20:25] = np.nan  # saturated pixels are filled
    ref = _edge_points_numpy(s0)
    got = edge_points(s0)
    assert len(got) > 200
    np.testing.assert_array_equal(got.xy, ref.xy)
    np.testing.assert_array_equal(got.normal, ref.normal)
    np.testing.assert_array_equal(got.strength, ref.strength)
    mask = np.zeros_like(s0, bool)
    mask[:, 80:] = True
    masked = edge_points(s0, mask=mask, threshold=0.05)
    full = _edge_points_numpy(s0, threshold=0.05)
    np.testing.assert_array_equal(masked.xy, full.xy[np.rint(full.xy[:, 0]) >= 80])


@pytest.mark.parametrize("n", [4, 5, 6, 7, 10, 11, 1000, 1001])
def test_median_and_percentile_are_numpys_bit_for_bit(n):
    rng = np.random.default_rng(n)
    for a in (rng.random(n), np.round(rng.random(n) * 3)):
        assert _median_and_percentile(a, 90) == (float(np.median(a)), float(np.percentile(a, 90)))


# ------------------------------------------------------------------------------- coarse search


def test_coarse_search_scores_equal_the_fftconvolve_statement():
    from scipy.signal import fftconvolve

    rng = np.random.default_rng(8)
    cam = CameraModel(width_px=320, height_px=256, focal_length_mm=4.0)
    pose = CameraPose.look_at([0.0, -12.0, 4.0], [0.0, 0.0, 2.0])
    pts, _ = _outline(30)
    edges = EdgePoints(rng.uniform(0, 300, (400, 2)), np.zeros((400, 2)), np.ones(400))
    scale, m = 4, 10
    search = _CoarseSearch(cam, edges, m * scale, scale=scale)
    win, share = search.scores(cam, pose, pts)
    # the statement: proximity map and model raster convolved ("same") over the padded frame
    hs, ws = 64, 80
    obs = np.zeros((hs, ws), np.uint8)
    qq = np.rint(edges.xy / scale).astype(int)
    ok = (qq[:, 0] < ws) & (qq[:, 1] < hs)
    obs[qq[ok, 1], qq[ok, 0]] = 1
    prox = np.exp(-0.5 * (cv2.distanceTransform(1 - obs, cv2.DIST_L2, 5) / 2.0) ** 2)
    uv = project_points(cam, pose, pts) / scale
    canvas = np.zeros((hs + 2 * m, ws + 2 * m))
    mi = np.rint(uv).astype(int) + m
    okm = (mi[:, 0] >= 0) & (mi[:, 0] < ws + 2 * m) & (mi[:, 1] >= 0) & (mi[:, 1] < hs + 2 * m)
    np.add.at(canvas, (mi[okm, 1], mi[okm, 0]), 1.0)
    total = fftconvolve(np.pad(prox, m), canvas[::-1, ::-1], mode="same")
    count = fftconvolve(np.pad(np.ones_like(prox), m), canvas[::-1, ::-1], mode="same")
    cy, cx = total.shape[0] // 2, total.shape[1] // 2
    sl = (slice(cy - m, cy + m + 1), slice(cx - m, cx + m + 1))
    cnt = np.rint(count[sl])
    ref = np.where(cnt >= 0.5 * cnt.max(), total[sl] / np.maximum(cnt, 1.0), -np.inf)
    assert np.isfinite(ref).sum() > 20
    np.testing.assert_array_equal(np.isfinite(win), np.isfinite(ref))
    # (the statement transforms the single-precision proximity map in single precision)
    np.testing.assert_allclose(win[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=1e-6)
    np.testing.assert_allclose(share, total[sl] / okm.sum(), rtol=0, atol=1e-6)


# ------------------------------------------------------------------------------------ canting


def test_facet_masks_on_bounding_boxes_equal_whole_image_masks():
    cam = CameraModel(width_px=400, height_px=300, focal_length_mm=4.0)
    pose = CameraPose.look_at([0.5, -9.0, 3.0], [0.0, 0.0, 2.0])
    pts, _ = _outline(2)
    corners = pts.reshape(4, 4, 2, 3)[:, :, 0]  # (F, 4, 3) square corners
    corners = np.concatenate([corners, corners + [3.2, 0.0, 0.0]])  # some run off the frame
    masks = _facet_masks(cam, pose, corners, 6.0)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (13, 13))
    t = np.linspace(0.0, 1.0, 24, endpoint=False)[:, None]
    clipped = 0
    for f, mask in enumerate(masks):
        ring = np.concatenate([corners[f, j] + t * (corners[f, (j + 1) % 4] - corners[f, j]) for j in range(4)])
        uv = project_points(cam, pose, ring)
        ref = np.zeros((300, 400), np.uint8)
        cv2.fillPoly(ref, [np.rint(uv).astype(np.int32)], 1)
        ref = cv2.erode(ref, kernel).astype(bool)
        clipped += bool(np.any(uv[:, 0] > 399))
        np.testing.assert_array_equal(mask.full(), ref)
        assert mask.area() == ref.sum()
        probe = np.random.default_rng(f).uniform(-5, 405, (2000, 2))
        i, j = np.rint(probe[:, 1]).astype(int), np.rint(probe[:, 0]).astype(int)
        inside = (i >= 0) & (i < 300) & (j >= 0) & (j < 400)
        expect = np.zeros(2000, bool)
        expect[inside] = ref[i[inside], j[inside]]
        np.testing.assert_array_equal(mask.inside(probe), expect)
    assert clipped >= 2
    assert _Mask((5, 5)).extent() is None


def test_grid_scores_equal_the_numpy_statement():
    rng = np.random.default_rng(9)
    coef = rng.normal(0.0, 1.0, (6, 300, 2)) * np.array([20.0, 0.5, 0.5, 0.05, 0.05, 0.05])[:, None, None]
    coef[1:3] += 6.0  # the outline moves 6 px per mrad: the outer nodes leave the mask
    coef[0] += [50.0, 45.0]
    coef[0, 7] = np.nan
    grid = np.linspace(-10.0, 10.0, 9)
    dt = rng.uniform(0, 10, (100, 100)).astype(np.float32)
    full = np.zeros((100, 100), bool)
    full[20:80, 10:90] = rng.random((60, 80)) < 0.8
    mask = _Mask((100, 100), 20, 10, full[20:80, 10:90])
    got = K.grid_scores(coef, grid, grid, mask.sub, mask.r0, mask.c0, np.ascontiguousarray(dt[20:80, 10:90]), 5.0, 10)
    gaz, gel = (g.ravel() for g in np.meshgrid(grid, grid, indexing="ij"))
    basis = np.stack([np.ones_like(gaz), gaz, gel, gaz * gaz, gel * gel, gaz * gel], axis=1)
    uv = (basis @ coef.reshape(6, -1)).reshape(len(gaz), -1, 2)
    fin = np.all(np.isfinite(uv), axis=2)
    ii = np.where(fin, np.rint(np.nan_to_num(uv[..., 1])), -1).astype(int)
    jj = np.where(fin, np.rint(np.nan_to_num(uv[..., 0])), -1).astype(int)
    ok = fin & (ii >= 0) & (ii < 100) & (jj >= 0) & (jj < 100)
    ins = ok & full[np.clip(ii, 0, 99), np.clip(jj, 0, 99)]
    near = ins & (dt[np.clip(ii, 0, 99), np.clip(jj, 0, 99)] <= 5.0)
    n_in = ins.sum(axis=1)
    ref = np.where(n_in >= 10, near.sum(axis=1) / np.maximum(n_in, 1), -1.0)
    assert np.any(ref > 0) and np.any(ref < 0)
    np.testing.assert_array_equal(got, ref)


def test_line_normals_match_the_numpy_statement():
    pts, seg = _outline(25)
    uv = project_points(WIDE, POSE, pts)
    uv[17] = np.nan
    same_next = np.append(seg[1:] == seg[:-1], False)
    same_prev = np.insert(seg[1:] == seg[:-1], 0, False)
    t = np.where(same_next[:, None], np.roll(uv, -1, 0), uv) - np.where(same_prev[:, None], np.roll(uv, 1, 0), uv)
    with np.errstate(invalid="ignore"):
        t = t / np.linalg.norm(t, axis=1, keepdims=True)
    got = line_normals(uv, seg)
    assert np.isnan(got[[16, 18]]).all() and np.isfinite(got[:16]).all() and np.isfinite(got[17]).all()
    np.testing.assert_array_equal(got, np.column_stack([-t[:, 1], t[:, 0]]))


def test_edge_point_matching_is_the_kdtree_s_and_at_a_corner_the_side_whose_line_passes_nearest():
    from scipy.spatial import cKDTree

    from pihim.inspection.pose import match_edge_points

    rng = np.random.default_rng(13)
    pts, seg = _outline(25)  # every corner twice: the end of one side and the start of the next
    uv = project_points(WIDE, POSE, pts)
    nrm = line_normals(uv, seg)
    usable = rng.random(len(uv)) < 0.95
    obs = uv[usable][rng.integers(0, usable.sum(), 3000)] + rng.normal(0.0, 2.0, (3000, 2))
    obs = np.concatenate([obs, uv[:100] + 1e-3, rng.uniform(-50, 700, (500, 2))])
    d, j = cKDTree(uv[usable]).query(obs, distance_upper_bound=3.0)
    hit = np.isfinite(d)
    # the oracle: every usable sample as near as the nearest, by brute force
    d2 = ((obs[:, None, :] - uv[usable][None, :, :]) ** 2).sum(axis=2)
    alike = d2 == d2.min(axis=1, keepdims=True)
    tied = hit & (alike.sum(axis=1) > 1)
    assert tied.sum() > 10  # the coincident corners were met
    line = np.abs(((uv[usable][None, :, :] - obs[:, None, :]) * nrm[usable][None, :, :]).sum(axis=2))
    by_line = np.where(alike, line, np.inf).argmin(axis=1)  # the first of the nearest lines
    first = alike.argmax(axis=1)
    assert np.any(by_line[tied] != first[tied])  # the rule decides somewhere
    for normals, pick in ((nrm, by_line), (None, first)):
        idx, q = match_edge_points(uv, usable, obs, 3.0, 10, "test", normals)
        assert 1000 < len(idx) < len(obs)
        expect = np.where(tied, pick, j)[hit]
        np.testing.assert_array_equal(idx, np.flatnonzero(usable)[expect])
        np.testing.assert_array_equal(q, obs[hit])
    k, tie = K.nearest_within(uv[usable], obs, 3.0, np.zeros((0, 2)))
    np.testing.assert_array_equal(tie, tied)
    np.testing.assert_array_equal(k, np.where(hit, np.where(tied, first, j), -1))
    with pytest.raises(Exception, match="test matches only"):
        match_edge_points(uv, usable, obs + 1e4, 3.0, 10, "test")


def test_a_canting_round_s_pass_equals_the_numpy_statement():
    from pihim.field.kinematics import apply_canting_deviation

    rng = np.random.default_rng(21)
    pts, seg = _outline(40)
    pts = pts + [0.0, 8.0, 0.0]  # the target, 8 m behind the facet's plane
    centre = np.array([0.0, 0.5, 2.0])
    rot = np.eye(3)
    normal = rot @ apply_canting_deviation(np.array([0.0, -1.0, 0.0]), 3.0, -2.0)
    virt = pts - 2.0 * ((pts - centre) @ normal)[:, None] * normal
    uv = project_points(WIDE, POSE, virt)
    assert np.isfinite(uv).all()
    box = np.floor(np.nanpercentile(uv, [20, 80], axis=0)).astype(int)  # a mask over part of the reflection
    (c0, r0), (c1, r1) = box
    sub = rng.random((r1 - r0, c1 - c0)) < 0.9
    mask = _Mask((int(r1) + 50, int(c1) + 50), r0, c0, sub)
    rot, cpos = np.asarray(POSE.rotation, float), np.asarray(POSE.position_m, float)
    got_uv, got_nrm, ins, usable = K.reflect_in_mask(pts, seg.astype(np.int64), centre, normal, rot, cpos,
                                                     K.camera_vector(WIDE), sub, r0, c0)
    np.testing.assert_allclose(got_uv, uv, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(got_nrm, line_normals(got_uv, seg))
    np.testing.assert_array_equal(ins, mask.inside(got_uv))
    np.testing.assert_array_equal(usable, ins & np.isfinite(got_nrm).all(axis=1))
    assert 100 < ins.sum() < len(pts)



def _canting_fit_numpy(pts, seg, aux, mask, obs, dt, gates, az, el):
    """A facet's canting fit in plain numpy: each round mirrors and projects every outline point, pairs the edge
    points with the usable ones (``match_edge_points``), and solves the two angles (``solve``)."""
    from pihim.field.kinematics import apply_canting_deviation
    from pihim.inspection.pose import match_edge_points

    rot_hua, centre, design = aux[:9].reshape(3, 3), aux[9:12], aux[12:]
    rot, cpos, cam = np.asarray(POSE.rotation, float), np.asarray(POSE.position_m, float), K.camera_vector(WIDE)

    def project(a, e):
        n = rot_hua @ apply_canting_deviation(design, a, e)
        uv = project_points(WIDE, POSE, pts - 2.0 * ((pts - centre) @ n)[:, None] * n)
        nrm = line_normals(uv, seg)
        ins = mask.inside(uv)
        return uv, nrm, ins, ins & np.isfinite(nrm).all(axis=1)

    for gate in gates:
        uv, nrm, _, usable = project(az, el)
        k, q = match_edge_points(uv, usable, obs, gate, 15, "the reflection", nrm)
        used, inv = np.unique(k, return_inverse=True)
        prob = K.problem(K.REFLECTION, rot, cpos, pts[used], cam, q=np.column_stack([q, nrm[k]]), aux=aux, idx=inv,
                         gate=gate)
        x, r, _ = K.solve(prob, np.array([az, el]), len(q), np.array([0.1, 0.1]), 200, True, 0.5)
        az, el = x
    uv, _, ins, _ = project(az, el)
    qq = np.rint(uv[ins]).astype(int)
    return az, el, r, k, q, nrm[k], int(ins.sum()), float(np.mean(dt[qq[:, 1], qq[:, 0]] <= 1.5))


def test_a_canting_fit_equals_the_numpy_statement_of_its_rounds():
    """``refine_reflection`` (one compiled call, its window of outline points near the mask, the window off or a
    few pixels wide) against the fit's rounds in plain numpy; it finds the true angles from 1.4 mrad off, and
    reports too few usable or matched points as such."""
    from pihim.field.kinematics import apply_canting_deviation
    from pihim.inspection.reflection import _FacetModel

    rng = np.random.default_rng(24)
    pts, seg = _outline(200)
    pts = pts + [0.0, 8.0, 0.0]  # the target, 8 m behind the facet's plane
    # the facet faces -y: its design normal (heliostat frame z) turned by the HUA's rotation
    centre, design = np.array([0.0, 0.5, 2.0]), np.array([0.0, 0.0, 1.0])
    rot_hua = Rotation.from_euler("x", 90.0, degrees=True).as_matrix()
    aux = np.concatenate([rot_hua.ravel(), centre, design])
    true = (3.0, -2.0)
    n = rot_hua @ apply_canting_deviation(design, *true)
    uv = project_points(WIDE, POSE, pts - 2.0 * ((pts - centre) @ n)[:, None] * n)
    (c0, r0), (c1, r1) = np.floor(np.nanpercentile(uv, [10, 90], axis=0)).astype(int)
    shape = (int(r1) + 60, int(c1) + 60)
    mask = _Mask(shape, r0, c0, rng.random((r1 - r0, c1 - c0)) < 0.95)
    obs = np.concatenate([uv[::2] + rng.normal(0.0, 0.05, uv[::2].shape), rng.uniform([c0, r0], [c1, r1], (40, 2))])
    img = np.ones(shape, np.uint8)
    q = np.rint(obs).astype(int)
    img[q[:, 1], q[:, 0]] = 0
    dt = cv2.distanceTransform(img, cv2.DIST_L2, 5)
    model = _FacetModel(WIDE, POSE, rot_hua, centre, design, pts, seg)
    gates = np.array([6.0, 3.0, 1.5, 1.5])

    def fit(window_px, sub=mask.sub, edges=obs):
        return K.refine_reflection(model.pts, model.seg, aux, model._r, model._c, model._cam, sub, r0, c0,
                                   np.array(mask.extent(), np.int64), model.motion_px_per_mrad(), window_px, edges,
                                   dt, gates, 2.0, -1.0, np.array([0.1, 0.1]), 20, 15, 0.5)

    ref = _canting_fit_numpy(pts, seg, aux, mask, obs, dt, gates, 2.0, -1.0)
    assert ref[0] == pytest.approx(true[0], abs=0.02) and ref[1] == pytest.approx(true[1], abs=0.02)
    for window_px in (0.0, 4.0, 40.0):
        status, count, az, el, r, idx, qm, nq, inside, support = fit(window_px)
        assert (status, count) == (0, 0)
        assert (az, el) == pytest.approx(ref[:2], abs=1e-9)
        np.testing.assert_allclose(r, ref[2], rtol=0, atol=1e-8)
        np.testing.assert_array_equal(idx, ref[3])
        np.testing.assert_array_equal(qm, ref[4])
        np.testing.assert_allclose(nq, ref[5], rtol=0, atol=1e-9)
        assert (inside, support) == (ref[6], pytest.approx(ref[7], abs=1e-12))
        assert support > 0.9 and inside > 500
    assert fit(40.0, sub=np.zeros_like(mask.sub))[:2] == (1, 0)  # nothing in the mask
    assert fit(40.0, edges=obs + 1e4)[:2] == (2, 0)  # no edge point within the gate


def test_mirrored_projections_of_many_angle_pairs_equal_the_numpy_statement():
    from pihim.field.kinematics import apply_canting_deviation

    rng = np.random.default_rng(22)
    pts = _outline(20)[0] + [0.0, 8.0, 0.0]
    centre = np.array([0.0, 0.5, 2.0])
    normals = apply_canting_deviation(np.array([0.0, -1.0, 0.0]), rng.uniform(-15, 15, 5), rng.uniform(-15, 15, 5))
    pivot = np.array([0.3, 7.0, 1.5])
    turns = Rotation.from_rotvec(rng.normal(0.0, 0.01, (5, 3))).as_matrix()
    rot, cpos, cam = np.asarray(POSE.rotation, float), np.asarray(POSE.position_m, float), K.camera_vector(WIDE)
    for m in (None, turns):
        world = np.broadcast_to(pts, (5, *pts.shape)) if m is None else pivot + (pts - pivot) @ np.swapaxes(m, 1, 2)
        d = np.einsum("gnk,gk->gn", world - centre, normals)
        ref = np.stack([project_points(WIDE, POSE, w - 2.0 * d[g][:, None] * normals[g])
                        for g, w in enumerate(world)])
        got = K.mirror_project(pts, normals, centre, np.zeros((0, 3, 3)) if m is None else m, pivot, rot, cpos, cam)
        assert np.isfinite(ref).all() and np.ptp(ref[:, 0, 0]) > 2.0  # the angle pairs move the reflection
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-8)


def test_unique_inverse_equals_numpy_s():
    rng = np.random.default_rng(23)
    for n, m in ((1, 5), (50, 0), (1000, 300), (1000, 5000)):
        idx = rng.integers(0, n, m)
        used, inv = K.unique_inverse(idx, n)
        ref_used, ref_inv = np.unique(idx, return_inverse=True)
        np.testing.assert_array_equal(used, ref_used)
        np.testing.assert_array_equal(inv, ref_inv)
