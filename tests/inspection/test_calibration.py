"""Camera calibration from synthetic chessboard views with a known camera.

The views are rendered by ``pihim.render.checkerboard`` (every sub-pixel
sample ray back-projected through the true lens onto the board plane), so
the truth is the camera they were rendered with. The independent oracle for
the detected corners is ``project_points`` (held to ``cv2.projectPoints`` in
tests/camera/test_pose.py).

Test camera: 816 x 682 px of 3.45 um behind a 12 mm lens, i.e. the Triton's
pixels and the field of view of the paper's 2448 px + 35 mm set-up (13.4 deg
wide); distortion k1 = -0.12, k2 = 0.05, p1 = 5e-4, p2 = -3e-4, k3 = 0 and
the principal point (411.3, 338.1) px, 3.8 px right of and 2.4 px above the centre. Twelve views
of a 9x6 board (25 mm squares), each as close as the whole board fits:
frontal, +-40 deg yaw, +-35 deg pitch, four 30/30 deg diagonals and three
45 deg obliques. Lens blur sigma 1 px (a realistic PSF; sharp box-filtered
edges make cornerSubPix pixel-lock, see the oracle tests).

Tolerances. With so narrow a field of view a corner error of 0.03 px RMS
(what cornerSubPix reaches here) leaves, by Monte Carlo over this view set,
about 0.02 % on fx, fy, 1 px on cx, cy, and 0.013 on k1 when k1, k2, k3 are
all fitted (they trade off against each other over r < 0.15) but 0.005 with
k3 fixed. Hence fx, fy within 0.5 %, cx, cy within 3 px (3 sigma), k1 within
0.02 with k3 fixed and 0.03 with all five coefficients free; the measured
errors (fx +0.002 %, cx +1.1 px, cy -0.5 px, k1 -0.010 / +0.010 on the
noise-free S0) are noted beside the assertions.
"""

from __future__ import annotations

import json
import math
from importlib import resources

import cv2
import jsonschema
import numpy as np
import pytest

from pihim.camera import CameraModel, CameraPose, polar_image, project_points
from pihim.errors import PihimInputError
from pihim.inspection.calibration import CameraCalibration, calibrate_camera, detect_corners
from pihim.render.checkerboard import board_view_pose, checkerboard_points, render_checkerboard
from pihim.render.sensor import SensorModel

TRUE = CameraModel(width_px=816, height_px=682, pixel_size_um=3.45, focal_length_mm=12.0,
                   principal_point_px=(411.3, 338.1), distortion=(-0.12, 0.05, 5e-4, -3e-4, 0.0),
                   name="test camera")
BOARD = (9, 6)
SQUARE = 0.025
#: (yaw, pitch, roll) deg and distance m of each view (the closest distance at which the whole board fits)
VIEWS = [(0, 0, 0, 1.12), (40, 0, 5, 1.09), (-40, 0, -5, 1.09), (0, 35, 5, 1.22), (0, -35, -5, 1.22),
         (30, 30, 10, 1.11), (-30, 30, -10, 1.13), (30, -30, -10, 1.11), (-30, -30, 10, 1.13),
         (45, 15, 0, 1.21), (-45, -15, 0, 1.19), (15, -45, 0, 1.14)]
SCHEMA = json.loads(resources.files("pihim").joinpath("schemas/camera.schema.json").read_text())


def view_pose(yaw, pitch, roll, distance):
    return board_view_pose(*BOARD, SQUARE, distance_m=distance, yaw_deg=yaw, pitch_deg=pitch, roll_deg=roll)


@pytest.fixture(scope="module")
def frames():
    """The twelve views: noise-free S0 and the Triton's raw mosaic (polarized board, shot and read noise)."""
    out = [render_checkerboard(TRUE, view_pose(*v), *BOARD, SQUARE, supersample=8, blur_sigma_px=1.0,
                               polarized=True, sensor=SensorModel(), rng=k) for k, v in enumerate(VIEWS)]
    assert all(f.board_inside(border_px=5) for f in out)
    return out


def oriented(corners, truth):
    """Detected corners in the order of the truth (a 9x6 board may be found from either end)."""
    flip = np.linalg.norm(corners[-1] - truth[0]) < np.linalg.norm(corners[0] - truth[0])
    return corners[::-1] if flip else corners


def check_camera(cam: CameraModel, *, f_rel=5e-3, c_px=3.0, k1_abs=0.02, p_abs=3e-4):
    assert cam.fx_px == pytest.approx(TRUE.fx_px, rel=f_rel)
    assert cam.fy_px == pytest.approx(TRUE.fy_px, rel=f_rel)
    assert abs(cam.cx_px - TRUE.cx_px) < c_px and abs(cam.cy_px - TRUE.cy_px) < c_px
    assert abs(cam.distortion[0] - TRUE.distortion[0]) < k1_abs
    # the tangential terms are well determined even here (measured within 6e-5; 2.5e-4 from super-pixel S0)
    assert np.allclose(cam.distortion[2:4], TRUE.distortion[2:4], rtol=0, atol=p_abs)
    assert (cam.width_px, cam.height_px, cam.pixel_size_um) == (816, 682, 3.45)


# -- renderer ---------------------------------------------------------------------------------


def test_checkerboard_points_are_opencv_object_points():
    p = checkerboard_points(9, 6, 0.03)
    assert p.shape == (54, 3) and np.all(p[:, 2] == 0)
    assert np.allclose(p[:3, :2], [[0, 0], [0.03, 0], [0.06, 0]]) and np.allclose(p[9, :2], [0, 0.03])
    assert np.allclose(p[-1, :2], [0.24, 0.15])


def test_adaptive_rendering_equals_sampling_every_pixel():
    """A wide, strongly distorted lens (62 deg, k1 = -0.2): board, margin and background in view; in the
    second pose the plane's horizon crosses the image (rays above it miss the plane)."""
    cam = CameraModel(width_px=160, height_px=120, pixel_size_um=3.45, focal_length_mm=0.46,
                      principal_point_px=(81.0, 58.5), distortion=(-0.2, 0.08, 1e-3, -5e-4, 0.01))
    poses = [board_view_pose(9, 6, SQUARE, distance_m=0.34, yaw_deg=25, pitch_deg=-15, roll_deg=17),
             board_view_pose(9, 6, SQUARE, distance_m=0.5, yaw_deg=70, pitch_deg=5, roll_deg=-10)]
    for pose in poses:
        a = render_checkerboard(cam, pose, 9, 6, SQUARE, supersample=5, polarized=True)
        b = render_checkerboard(cam, pose, 9, 6, SQUARE, supersample=5, polarized=True, adaptive=False)
        assert a.board_inside()
        assert np.isclose(a.s0.min(), 0.1) and np.isclose(a.s0.max(), 1.0) and np.any(np.isclose(a.s0, 0.3))
        for x, y in ((a.s0, b.s0), (a.s1, b.s1), (a.s2, b.s2)):
            assert np.max(np.abs(x - y)) < 1e-12
        assert np.any(a.s1 != 0) and np.any(a.s2 != 0)
    # the horizon: the rays of the right fifth of the second image run away from the plane
    rays = cam.pixel_rays(np.arange(160.0)[None, :], np.arange(120.0)[:, None]) @ poses[1].rotation
    assert 0.1 < np.mean(-poses[1].position_m[2] / rays[..., 2] < 0) < 0.3


def test_rendered_dark_area_is_exact():
    """Sub-pixel exact coverage: the summed dark fraction equals the area of the dark squares in pixels."""
    cam = CameraModel(width_px=400, height_px=300, pixel_size_um=3.45, focal_length_mm=12.0)
    d = 2.6  # 33 px squares: the board (334 x 234 px) fits
    pose = CameraPose(position_m=[4 * SQUARE + 0.00123, 2.5 * SQUARE - 0.00071, -d], rotation=np.eye(3))
    frame = render_checkerboard(cam, pose, 9, 6, SQUARE, contrast=1.0, background=1.0, supersample=4)
    assert frame.board_inside()
    side_px = SQUARE / d * cam.fx_px  # frontal pinhole: every square is side_px x side_px
    dark_squares = 35  # 10 x 7 squares, half of them dark
    assert np.sum(1.0 - frame.s0) == pytest.approx(dark_squares * side_px**2, rel=2e-5)
    # the dark square holding the board corner (-1, -1) (in squares) and parity
    u, v = project_points(cam, pose, [[-0.5 * SQUARE, -0.5 * SQUARE, 0.0], [0.5 * SQUARE, -0.5 * SQUARE, 0.0]]).T
    assert frame.s0[round(v[0]), round(u[0])] == 0.0 and frame.s0[round(v[1]), round(u[1])] == 1.0


def test_raw_frame_through_the_sensor(frames):
    f = frames[0]
    assert f.raw.dtype == np.uint16 and f.raw.shape == (682, 816) and f.raw.max() <= 4095
    assert f.exposure.headroom == 0.8 and f.exposure.clipped_fraction == 0.0
    s0 = polar_image(f.raw, demosaic="full").s0
    assert np.corrcoef(s0.ravel(), f.s0.ravel())[0, 1] > 0.99


# -- corner detection: the independent oracle ---------------------------------------------------


def test_detected_corners_match_true_projections(frames):
    """Noise-free S0: every detected corner within 0.2 px of project_points (measured max 0.08 px)."""
    errors = []
    for f in frames:
        corners, reason = detect_corners(f.s0, BOARD)
        assert reason is None
        errors.append(oriented(corners, f.corners_px) - f.corners_px)
    e = np.linalg.norm(np.concatenate(errors), axis=1)
    assert e.max() < 0.2 and math.sqrt(np.mean(e**2)) < 0.05


def test_detected_corners_on_sharp_images():
    """Without lens blur cornerSubPix pixel-locks a little on box-filtered edges; still < 0.2 px (max ~0.1)."""
    errors = []
    for v in VIEWS[:6]:
        f = render_checkerboard(TRUE, view_pose(*v), *BOARD, SQUARE, supersample=8)
        corners, _ = detect_corners(f.s0, BOARD)
        errors.append(oriented(corners, f.corners_px) - f.corners_px)
    assert np.linalg.norm(np.concatenate(errors), axis=1).max() < 0.2


def test_detected_corners_on_raw_frames(frames):
    """S0 of the noisy raw mosaic (full-resolution route): within 0.3 px (measured max 0.10 px)."""
    for f in frames:
        corners, _ = detect_corners(polar_image(f.raw, demosaic="full").s0, BOARD)
        assert np.linalg.norm(oriented(corners, f.corners_px) - f.corners_px, axis=1).max() < 0.3


# -- calibration ---------------------------------------------------------------------------------


def test_calibration_recovers_the_camera(frames):
    cal = calibrate_camera([f.s0 for f in frames], BOARD, SQUARE)
    assert isinstance(cal, CameraCalibration) and len(cal.views_used) == 12 and not cal.views_rejected
    check_camera(cal.camera, k1_abs=0.03)  # all five coefficients free: k1 trades with k2, k3 (measured -0.010)
    assert cal.rms_px < 0.4  # the paper's figure
    assert cal.rms_px < 0.05  # measured 0.021
    assert cal.per_view_rms_px.shape == (12,) and cal.per_view_rms_px.max() < 0.1
    # OpenCV's own figure for the same corners and flags
    obj = [checkerboard_points(*BOARD, SQUARE).astype(np.float32)] * 12
    img = [v.corners_px.astype(np.float32) for v in cal.views]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms_cv, k_cv, d_cv, *_ = cv2.calibrateCamera(obj, img, (816, 682), None, None, criteria=criteria)
    assert cal.rms_px == pytest.approx(rms_cv, rel=1e-5)
    assert np.allclose(cal.camera.intrinsics(), k_cv, rtol=1e-7)
    assert np.allclose(cal.camera.distortion, d_cv.ravel(), rtol=1e-6, atol=1e-12)
    # the fitted board poses reproduce the camera positions (board frame) of the views to 2 mm in ~1.1 m
    span = np.array([(BOARD[0] - 1) * SQUARE, (BOARD[1] - 1) * SQUARE])
    for v, f, view in zip(cal.views, frames, VIEWS):
        pos = CameraPose.from_rvec_tvec(v.rvec, v.tvec).position_m
        if np.linalg.norm(v.corners_px[0] - f.corners_px[0]) > 1.0:  # found from the other end: board turned 180 deg
            pos = np.array([span[0] - pos[0], span[1] - pos[1], pos[2]])
        assert np.linalg.norm(pos - view_pose(*view).position_m) < 2e-3


def test_calibration_with_k3_fixed(frames):
    cal = calibrate_camera([f.s0 for f in frames], BOARD, SQUARE, flags=cv2.CALIB_FIX_K3)
    check_camera(cal.camera, k1_abs=0.02)  # measured +0.010
    assert cal.camera.distortion[4] == 0.0 and cal.to_dict()["calibration"]["flags"] == ["CALIB_FIX_K3"]


@pytest.mark.parametrize("flags, k1_abs", [(0, 0.03), (cv2.CALIB_FIX_K3, 0.02)])
def test_calibration_on_noisy_raw_frames(frames, flags, k1_abs):
    """What the Triton records: S0 of the 12-bit mosaic with shot and read noise, full-resolution route."""
    s0 = [polar_image(f.raw, demosaic="full").s0 for f in frames]
    cal = calibrate_camera(s0, BOARD, SQUARE, flags=flags)
    check_camera(cal.camera, k1_abs=k1_abs)  # measured fx +0.000 %, cx +1.4 px, cy -0.2 px, k1 -0.018 / +0.014
    assert cal.rms_px < 0.4 and cal.rms_px < 0.06  # measured 0.026


def test_calibration_on_superpixel_s0_with_binning(frames):
    """Half-resolution S0; corners mapped to sensor pixels by u = 2u' + 0.5."""
    s0 = [polar_image(f.raw, demosaic="superpixel").s0 for f in frames]
    assert s0[0].shape == (341, 408)
    cal = calibrate_camera(s0, BOARD, SQUARE, image_binning=2, flags=cv2.CALIB_FIX_K3)
    # twice the corner noise in sensor pixels (measured cx +0.3 px, cy -2.9 px, k1 -0.009)
    check_camera(cal.camera, c_px=6.0, k1_abs=0.03, p_abs=6e-4)
    assert cal.rms_px < 0.4  # measured 0.063
    e = [np.linalg.norm(oriented(v.corners_px, f.corners_px) - f.corners_px, axis=1).max()
         for v, f in zip(cal.views, frames)]
    assert max(e) < 0.4


def test_record_schema_and_round_trip(frames):
    cal = calibrate_camera([f.s0 for f in frames], BOARD, SQUARE, names=[f"v{k}.png" for k in range(12)])
    doc = json.loads(json.dumps(cal.to_dict(), allow_nan=False))
    jsonschema.validate(doc, SCHEMA, cls=jsonschema.Draft202012Validator)
    assert doc["schema"] == "pihim.camera/1"
    assert CameraModel.from_dict(doc) == cal.camera
    assert doc["camera_matrix"] == cal.camera.intrinsics().tolist()
    c = doc["calibration"]
    assert c["board"] == {"cols": 9, "rows": 6, "square_m": SQUARE} and c["views_used"] == 12
    assert [v["name"] for v in c["views"]] == [f"v{k}.png" for k in range(12)]
    assert c["views"][0]["distance_m"] == pytest.approx(np.linalg.norm(cal.views[0].tvec))
    assert c["rms_px"] == doc["rms_px"] == cal.rms_px
    assert len(c["warnings"]) == 1 and c["warnings"][0].startswith("narrow field of view (image corners at "
                                                                   "normalized radius 0.15): k1, k2 and k3 trade")
    assert calibrate_camera([f.s0 for f in frames], BOARD, SQUARE, flags=cv2.CALIB_FIX_K3).warnings == ()


# -- rejections and errors -------------------------------------------------------------------------


def test_views_without_a_board_or_off_model_are_rejected(frames):
    blank = np.full((682, 816), 0.5)
    other_lens = CameraModel(width_px=816, height_px=682, pixel_size_um=3.45, focal_length_mm=12.0,
                             principal_point_px=(411.3, 338.1), distortion=(1.0, 0.0, 0.0, 0.0, 0.0))
    odd = render_checkerboard(other_lens, view_pose(30, 20, 5, 1.15), *BOARD, SQUARE, supersample=4,
                              blur_sigma_px=1.0)
    images = [f.s0 for f in frames[:8]] + [blank, odd.s0]
    cal = calibrate_camera(images, BOARD, SQUARE, max_view_rms_px=0.2)  # the odd view: 0.49 px, others < 0.08
    used = [v.used for v in cal.views]
    assert used == [True] * 8 + [False, False]
    assert cal.views[8].reason == "blank image (no contrast)" and cal.views[8].corners_px is None
    assert cal.views[9].reason.startswith("reprojection RMS") and cal.views[9].corners_px is not None
    check_camera(cal.camera, k1_abs=0.05)
    assert cal.rms_px < 0.05
    # without the RMS gate the off-model view spoils the fit
    assert calibrate_camera(images, BOARD, SQUARE).rms_px > 0.1


def test_rejected_reason_when_no_board_found(frames):
    noise = np.random.default_rng(1).uniform(0, 1, (682, 816))
    cal = calibrate_camera([f.s0 for f in frames[:4]] + [noise], BOARD, SQUARE)
    assert cal.views[4].reason == "no 9x6 chessboard found"
    assert len(cal.views_used) == 4 and any("only 4 views" in w for w in cal.warnings)


def test_input_errors(frames):
    blank = np.zeros((682, 816))
    with pytest.raises(PihimInputError, match="no image with a detectable 9x6 chessboard among 2"):
        calibrate_camera([blank, blank], BOARD, SQUARE)
    with pytest.raises(PihimInputError, match=r"only 2 usable view\(s\) .* need at least 3 \(image 2: blank"):
        calibrate_camera([frames[0].s0, frames[1].s0, blank], BOARD, SQUARE)
    with pytest.raises(PihimInputError, match="different sizes: image 0 is 816x682, image 1 is 408x341"):
        calibrate_camera([frames[0].s0, frames[1].s0[::2, ::2], frames[2].s0], BOARD, SQUARE)
    with pytest.raises(PihimInputError, match="board"):
        calibrate_camera([frames[0].s0], (7, 7), SQUARE)
    with pytest.raises(PihimInputError, match="square size"):
        calibrate_camera([frames[0].s0], BOARD, -1.0)
    with pytest.raises(PihimInputError, match="flags"):
        calibrate_camera([frames[0].s0], BOARD, SQUARE, flags=cv2.CALIB_RATIONAL_MODEL)
    with pytest.raises(PihimInputError, match="2-D grey image"):
        calibrate_camera([np.zeros((10, 10, 3))], BOARD, SQUARE)
    with pytest.raises(PihimInputError, match="no images"):
        calibrate_camera([], BOARD, SQUARE)
    for exc_msg in ("only 2 usable", "no image with"):
        try:
            calibrate_camera([frames[0].s0, frames[1].s0, blank] if exc_msg.startswith("only") else [blank],
                             BOARD, SQUARE)
        except PihimInputError as exc:
            assert "\n" not in str(exc)
