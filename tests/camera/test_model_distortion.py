"""Tests of the camera model's intrinsics, Brown-Conrady distortion and projection, with OpenCV as the oracle."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pihim.camera import CameraModel
from pihim.camera.model import camera_for_size
from pihim.errors import PihimInputError

# the brief's "real lens" distortion, tangential terms included
DIST = (-0.2, 0.1, 1e-3, -5e-4, 0.01)
# the default sensor behind a short lens (half-diagonal ~0.69 in normalized units) with an
# off-centre principal point and non-square pixels: distortion matters across the image
WIDE = CameraModel(focal_length_mm=8.0, distortion=DIST, principal_point_px=(1250.3, 1010.7), pixel_aspect=1.02)
TRITON = CameraModel(distortion=DIST)
CV_TIGHT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)


def sensor_grid(cam: CameraModel, nu: int = 123, nv: int = 103) -> tuple[np.ndarray, np.ndarray]:
    """Pixel grid from corner to corner of the sensor (its edges and corners included)."""
    return np.meshgrid(np.linspace(0.0, cam.width_px - 1.0, nu), np.linspace(0.0, cam.height_px - 1.0, nv))


# ------------------------------------------------------------------------------ defaults and intrinsics


def test_defaults_unchanged():
    cam = CameraModel()
    f = 35.0 * 1000.0 / 3.45
    assert cam.focal_length_px == cam.fx_px == cam.fy_px == pytest.approx(f, rel=1e-15)
    assert (cam.cx_px, cam.cy_px) == (1223.5, 1023.5)
    np.testing.assert_array_equal(cam.intrinsics(), [[f, 0, 1223.5], [0, f, 1023.5], [0, 0, 1]])
    np.testing.assert_array_equal(cam.distortion_coefficients(), np.zeros(5))
    assert cam.horizontal_fov_deg == pytest.approx(math.degrees(2 * math.atan(1224 / f)))
    assert cam.vertical_fov_deg == pytest.approx(math.degrees(2 * math.atan(1024 / f)))
    assert cam.ground_sample_distance_m(100.0) == pytest.approx(100 * 3.45e-6 / 35e-3)
    assert hash(cam) == hash(CameraModel())  # still a hashable frozen dataclass


def test_intrinsics_with_principal_point_and_aspect():
    k = WIDE.intrinsics()
    fx = 8.0 * 1000 / 3.45
    np.testing.assert_allclose(k, [[fx, 0, 1250.3], [0, 1.02 * fx, 1010.7], [0, 0, 1]], rtol=1e-15)
    assert WIDE.vertical_fov_deg == pytest.approx(math.degrees(2 * math.atan(1024 / (1.02 * fx))))
    np.testing.assert_array_equal(WIDE.distortion_coefficients(), DIST)


@pytest.mark.parametrize(
    "kwargs, needle",
    [
        ({"distortion": (0.1, 0.0, 0.0, 0.0)}, "5 coefficients"),
        ({"distortion": (0.1,) * 8}, "5 coefficients"),
        ({"distortion": 0.1}, "5 coefficients"),
        ({"distortion": (math.nan, 0, 0, 0, 0)}, "k1"),
        ({"distortion": (0, 0, 0, math.inf, 0)}, "p2"),
        ({"pixel_aspect": 0.0}, "aspect"),
        ({"pixel_aspect": -1.0}, "aspect"),
        ({"pixel_aspect": math.nan}, "aspect"),
        ({"principal_point_px": (1.0, math.nan)}, "cy"),
        ({"principal_point_px": (1.0, 2.0, 3.0)}, "principal point"),
        ({"focal_length_mm": math.inf}, "focal length"),
        ({"focal_length_mm": -1.0}, "positive"),
    ],
)
def test_bad_parameters_raise_one_line_errors(kwargs, needle):
    with pytest.raises(PihimInputError) as err:
        CameraModel(**kwargs)
    msg = str(err.value)
    assert needle in msg and "\n" not in msg


# ------------------------------------------------------------------------------ distortion


def test_distort_matches_cv2_project_points():
    """distort_normalized is OpenCV's model: projectPoints of (x, y, 1) with K = I."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.7, 0.7, (2000, 2))
    pts = np.column_stack([xy, np.ones(len(xy))])
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), np.array(DIST))
    xd, yd = WIDE.distort_normalized(xy[:, 0], xy[:, 1])
    np.testing.assert_allclose(np.column_stack([xd, yd]), ref[:, 0], rtol=0, atol=1e-14)


def test_distort_formula_terms():
    """Each coefficient's term, written out (radial k1/k2/k3, tangential p1/p2)."""
    x, y = 0.3, -0.2
    r2 = x * x + y * y
    for i, (tx, ty) in enumerate([(x * r2, y * r2), (x * r2**2, y * r2**2), (2 * x * y, r2 + 2 * y * y),
                                  (r2 + 2 * x * x, 2 * x * y), (x * r2**3, y * r2**3)]):
        coeffs = [0.0] * 5
        coeffs[i] = 0.1
        xd, yd = CameraModel(distortion=tuple(coeffs)).distort_normalized(x, y)
        assert xd == pytest.approx(x + 0.1 * tx, abs=1e-16) and yd == pytest.approx(y + 0.1 * ty, abs=1e-16)


@pytest.mark.parametrize("cam", [TRITON, WIDE], ids=["35mm", "8mm"])
def test_undistort_inverts_distort_over_the_whole_sensor(cam):
    u, v = sensor_grid(cam)
    xd, yd = (u - cam.cx_px) / cam.fx_px, (v - cam.cy_px) / cam.fy_px
    x, y = cam.undistort_normalized(xd, yd)
    assert np.all(np.isfinite(x)) and np.all(np.isfinite(y))
    bx, by = cam.distort_normalized(x, y)
    assert max(np.abs(bx - xd).max(), np.abs(by - yd).max()) < 1e-10  # normalized units
    assert max(np.abs(bx - xd).max() * cam.fx_px, np.abs(by - yd).max() * cam.fy_px) < 1e-9  # pixels
    assert np.abs(x - xd).max() > 1e-3 if cam is WIDE else True  # the distortion is not negligible


@pytest.mark.parametrize("cam", [TRITON, WIDE], ids=["35mm", "8mm"])
def test_undistort_matches_cv2_undistort_points(cam):
    """cv2.undistortPoints as the oracle.

    OpenCV inverts by fixed-point iteration. With converged criteria (up to 100
    iterations, eps 1e-15) both agree to 1e-13 in normalized coordinates
    (measured ~4e-16). With OpenCV's default criteria (a few iterations) its own
    result is only good to ~5e-7 for the 8 mm lens (~1e-13 for the 35 mm lens),
    so that comparison is held to 2e-6.
    """
    u, v = sensor_grid(cam)
    src = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
    k, d = cam.intrinsics(), cam.distortion_coefficients()
    x, y = cam.undistort_normalized((u - cam.cx_px) / cam.fx_px, (v - cam.cy_px) / cam.fy_px)
    mine = np.stack([x, y], axis=-1).reshape(-1, 2)
    tight = cv2.undistortPoints(src, k, d, None, None, None, CV_TIGHT)[:, 0]
    np.testing.assert_allclose(mine, tight, rtol=0, atol=1e-13)
    default = cv2.undistortPoints(src, k, d)[:, 0]
    np.testing.assert_allclose(mine, default, rtol=0, atol=2e-6)


@settings(max_examples=60, deadline=None)
@given(k1=st.floats(-0.4, 0.4), k2=st.floats(-0.2, 0.2), p1=st.floats(-2e-3, 2e-3), p2=st.floats(-2e-3, 2e-3),
       k3=st.floats(-0.05, 0.05), x=st.floats(-0.6, 0.6), y=st.floats(-0.5, 0.5))
def test_undistort_round_trip_property(k1, k2, p1, p2, k3, x, y):
    cam = CameraModel(focal_length_mm=8.0, distortion=(k1, k2, p1, p2, k3))
    xd, yd = cam.distort_normalized(x, y)
    ux, uy = cam.undistort_normalized(xd, yd)
    assert abs(ux - x) < 1e-10 and abs(uy - y) < 1e-10


def test_undistort_without_distortion_is_identity_and_checks_iterations():
    x, y = CameraModel().undistort_normalized([0.1, -0.2], [0.05, 0.3])
    np.testing.assert_array_equal(x, [0.1, -0.2])
    np.testing.assert_array_equal(y, [0.05, 0.3])
    with pytest.raises(PihimInputError, match="iterations"):
        TRITON.undistort_normalized(0.1, 0.1, iterations=0)


def test_undistort_outside_the_invertible_region_is_nan():
    """Strong barrel distortion folds back beyond r ~ 1.3: no inverse there, NaN rather than a wrong ray."""
    cam = CameraModel(distortion=(-0.2, 0.0, 0.0, 0.0, 0.0))
    # xd = x (1 - 0.2 x^2) peaks at x = 1/sqrt(0.6), xd_max ~ 0.861
    x, _ = cam.undistort_normalized([0.5, 0.9], [0.0, 0.0])
    assert x[0] == pytest.approx(0.5 + 0.2 * x[0] ** 3, abs=1e-12) and np.isnan(x[1])


# ------------------------------------------------------------------------------ projection and rays


@pytest.mark.parametrize("cam", [TRITON, WIDE], ids=["35mm", "8mm"])
def test_pixel_rays_then_project_returns_the_pixels(cam):
    u, v = sensor_grid(cam)
    rays = cam.pixel_rays(u, v)
    assert rays.shape == u.shape + (3,)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0, atol=1e-15)
    assert np.all(rays[..., 2] > 0)
    uv = cam.project(rays * 7.5)  # any positive scale
    np.testing.assert_allclose(uv[..., 0], u, rtol=0, atol=1e-6)
    np.testing.assert_allclose(uv[..., 1], v, rtol=0, atol=1e-6)


def test_project_matches_cv2_in_the_camera_frame():
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-0.6, 0.6, 500), rng.uniform(-0.5, 0.5, 500), np.ones(500)])
    pts *= rng.uniform(0.5, 100.0, (500, 1))
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), WIDE.intrinsics(), WIDE.distortion_coefficients())
    np.testing.assert_allclose(WIDE.project(pts), ref[:, 0], rtol=0, atol=1e-9)


def test_principal_point_and_axis_signs():
    """The optical axis hits (cx, cy); +x (right) raises u, +y (down) raises v."""
    uv = WIDE.project([[0.0, 0.0, 5.0], [0.1, 0.0, 5.0], [0.0, 0.1, 5.0]])
    np.testing.assert_allclose(uv[0], (1250.3, 1010.7), atol=1e-12)
    assert uv[1, 0] > 1250.3 and uv[2, 1] > 1010.7


def test_project_behind_or_at_the_camera_is_nan_and_shapes():
    uv = TRITON.project(np.array([[[0.1, 0.1, -1.0], [0.0, 0.0, 0.0], [0.1, 0.1, 1.0]]]))
    assert uv.shape == (1, 3, 2)
    assert np.all(np.isnan(uv[0, :2])) and np.all(np.isfinite(uv[0, 2]))
    with pytest.raises(PihimInputError, match=r"\(\.\.\., 3\)"):
        TRITON.project(np.zeros((4, 2)))


# ------------------------------------------------------------------------------ OpenCV calibration and dicts


def test_from_opencv():
    k = np.array([[2300.0, 0.0, 1230.0], [0.0, 2310.0, 1015.0], [0.0, 0.0, 1.0]])
    cam = CameraModel.from_opencv(k, np.array(DIST).reshape(1, 5), (2448, 2048), pixel_size_um=3.45, name="cal")
    np.testing.assert_allclose(cam.intrinsics(), k, rtol=1e-14)
    assert cam.focal_length_mm == pytest.approx(2300.0 * 3.45 / 1000.0, rel=1e-15)
    assert cam.pixel_aspect == pytest.approx(2310.0 / 2300.0, rel=1e-15)
    assert cam.distortion == DIST and cam.name == "cal" and (cam.width_px, cam.height_px) == (2448, 2048)
    four = CameraModel.from_opencv(k, DIST[:4], (2448, 2048))
    assert four.distortion == (*DIST[:4], 0.0)
    eight = CameraModel.from_opencv(k, [*DIST, 0.0, 0.0, 0.0], (2448, 2048))
    assert eight.distortion == DIST
    assert CameraModel.from_opencv(k, None, (2448, 2048)).distortion == (0.0,) * 5


@pytest.mark.parametrize(
    "k, d, needle",
    [
        (np.eye(3) * 100, [*DIST, 0.01, 0.0, 0.0], "must be zero"),
        (np.eye(3) * 100, [0.1, 0.2, 0.3], "4, 5, 8, 12 or 14"),
        ([[100.0, 1.0, 5.0], [0.0, 100.0, 5.0], [0.0, 0.0, 1.0]], DIST, "no skew"),
        (np.eye(2), DIST, "3x3"),
        ([[-100.0, 0.0, 5.0], [0.0, 100.0, 5.0], [0.0, 0.0, 1.0]], DIST, "positive"),
    ],
)
def test_from_opencv_refuses(k, d, needle):
    k = np.array(k, float)
    if k.shape == (3, 3):
        k[2, 2] = 1.0
    with pytest.raises(PihimInputError, match=needle):
        CameraModel.from_opencv(k, d, (100, 100))


@pytest.mark.parametrize("cam", [CameraModel(), WIDE, TRITON], ids=["default", "8mm", "35mm"])
def test_dict_round_trip(cam):
    d = cam.to_dict()
    text = json.dumps(d, allow_nan=False)
    back = CameraModel.from_dict(json.loads(text))
    assert back == cam
    assert set(d) >= {"width_px", "height_px", "pixel_size_um", "focal_length_mm", "fx_px", "fy_px", "cx_px", "cy_px",
                      "distortion", "name"}
    assert d["distortion"] == dict(zip(("k1", "k2", "p1", "p2", "k3"), cam.distortion, strict=True))
    assert (d["fx_px"], d["fy_px"], d["cx_px"], d["cy_px"]) == (cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px)


def test_from_dict_refuses_inconsistent_or_incomplete():
    d = WIDE.to_dict()
    with pytest.raises(PihimInputError, match="fx_px"):
        CameraModel.from_dict({**d, "fx_px": d["fx_px"] * 1.01})
    with pytest.raises(PihimInputError, match="width_px"):
        CameraModel.from_dict({k: v for k, v in d.items() if k != "width_px"})
    with pytest.raises(PihimInputError, match="unknown distortion"):
        CameraModel.from_dict({**d, "distortion": {"k4": 0.1}})
    with pytest.raises(PihimInputError, match="5 coefficients"):
        CameraModel.from_dict({**d, "distortion": [0.1, 0.2]})


@pytest.mark.parametrize("size", [float("nan"), 3.5, "100", True])
def test_the_sensor_size_is_a_whole_number_of_pixels(size):
    """width_px=nan was accepted (cx_px nan, every projection nan), 3.5 too; '100' was a TypeError."""
    with pytest.raises(PihimInputError, match="width_px must be a whole number of pixels"):
        CameraModel(width_px=size)
    with pytest.raises(PihimInputError, match="whole number of pixels"):
        camera_for_size(size, 10)
    cam = CameraModel(width_px=1224.0, height_px=np.int64(1024))  # whole numbers from a JSON file or numpy
    assert type(cam.width_px) is int and type(cam.height_px) is int and cam.width_px == 1224
