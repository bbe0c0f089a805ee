"""Tests of the camera pose: axes and angle signs, OpenCV extrinsics and projection, plan.json poses."""

from __future__ import annotations

import json
import math
from datetime import datetime

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pihim.camera import CameraModel, CameraPose, pixel_rays_world, project_points
from pihim.errors import PihimInputError
from pihim.field.layout import NSTTF_TOWER, Field, nsttf_spec
from pihim.planning.export.plan_json import write_plan_json
from pihim.planning.pipeline import build_plan
from pihim.planning.sightlines import camera_frame, gaze_angles, optical_axis
from pihim.sky.sun import NSTTF

DIST = (-0.2, 0.1, 1e-3, -5e-4, 0.01)
WIDE = CameraModel(focal_length_mm=8.0, distortion=DIST, principal_point_px=(1250.3, 1010.7), pixel_aspect=1.02)
PINHOLE = CameraModel(focal_length_mm=8.0)


def angle_diff_deg(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def random_pose(rng: np.random.Generator) -> CameraPose:
    return CameraPose.from_attitude(rng.uniform(-100, 100, 3), rng.uniform(0, 360), rng.uniform(-89.5, 89.5),
                                    rng.uniform(-179, 179))


def points_in_front(pose: CameraPose, rng: np.random.Generator, n: int = 400) -> np.ndarray:
    """World points inside (and a little beyond) the WIDE camera's field of view, 1 to 80 m ahead."""
    a, b = rng.uniform(-0.6, 0.6, (n, 1)), rng.uniform(-0.5, 0.5, (n, 1))
    s = rng.uniform(1.0, 80.0, (n, 1))
    return pose.position_m + s * (pose.forward + a * pose.right + b * pose.down)


# ------------------------------------------------------------------------------ OpenCV as the oracle


@pytest.mark.parametrize("seed", range(8))
def test_project_points_matches_cv2(seed):
    """Random poses, distortion with tangential terms, off-centre principal point, fy != fx (measured <= 3e-10 px)."""
    rng = np.random.default_rng(seed)
    pose = random_pose(rng)
    pts = points_in_front(pose, rng)
    rvec, tvec = pose.rvec_tvec()
    ref, _ = cv2.projectPoints(pts, rvec, tvec, WIDE.intrinsics(), WIDE.distortion_coefficients())
    mine = project_points(WIDE, pose, pts)
    assert mine.shape == (len(pts), 2)
    np.testing.assert_allclose(mine, ref[:, 0], rtol=0, atol=1e-6)


def test_rodrigues_agrees_with_cv2():
    rng = np.random.default_rng(11)
    for _ in range(20):
        pose = random_pose(rng)
        rvec, tvec = pose.rvec_tvec()
        r_cv, _ = cv2.Rodrigues(rvec)
        np.testing.assert_allclose(r_cv, pose.rotation, atol=1e-13)
        np.testing.assert_allclose(tvec, -pose.rotation @ pose.position_m, atol=1e-12)
        back = CameraPose.from_rvec_tvec(rvec.reshape(3, 1), tvec.reshape(3, 1))
        np.testing.assert_allclose(back.rotation, pose.rotation, atol=1e-13)
        np.testing.assert_allclose(back.position_m, pose.position_m, atol=1e-11)
        # and from cv2's own rvec
        again = CameraPose.from_rvec_tvec(cv2.Rodrigues(pose.rotation)[0], tvec)
        np.testing.assert_allclose(again.rotation, pose.rotation, atol=1e-13)


def test_pixel_rays_world_project_back():
    rng = np.random.default_rng(5)
    pose = random_pose(rng)
    u, v = np.meshgrid(np.linspace(0, 2447, 37), np.linspace(0, 2047, 31))
    origins, dirs = pixel_rays_world(WIDE, pose, u, v)
    assert origins.shape == dirs.shape == u.shape + (3,)
    np.testing.assert_array_equal(origins[3, 4], pose.position_m)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=1e-15)
    uv = project_points(WIDE, pose, origins + 12.0 * dirs)
    np.testing.assert_allclose(uv[..., 0], u, rtol=0, atol=1e-6)
    np.testing.assert_allclose(uv[..., 1], v, rtol=0, atol=1e-6)
    # the principal point's ray is the optical axis
    _, axis = pixel_rays_world(WIDE, pose, WIDE.cx_px, WIDE.cy_px)
    np.testing.assert_allclose(axis, pose.forward, atol=1e-15)


# ------------------------------------------------------------------------------ axes and signs


def test_look_at_north_axes_and_image_sides():
    pose = CameraPose.look_at((0.0, 0.0, 10.0), (0.0, 10.0, 10.0))
    np.testing.assert_allclose(pose.forward, (0, 1, 0), atol=1e-15)
    np.testing.assert_allclose(pose.right, (1, 0, 0), atol=1e-15)
    np.testing.assert_allclose(pose.down, (0, 0, -1), atol=1e-15)
    assert (pose.heading_deg, pose.pitch_deg, pose.roll_deg) == (0.0, 0.0, 0.0)
    cx, cy = PINHOLE.cx_px, PINHOLE.cy_px
    east, above = project_points(PINHOLE, pose, [[1.0, 20.0, 10.0], [0.0, 20.0, 11.0]])
    assert east[0] > cx and east[1] == pytest.approx(cy, abs=1e-9)  # East of the axis: image right
    assert above[1] < cy and above[0] == pytest.approx(cx, abs=1e-9)  # above the axis: image top


def test_roll_sign_right_wing_down_turns_the_scene_counter_clockwise():
    """Roll +10 deg: camera x (right) turns toward camera y (down), so the right axis dips below the horizon
    and a point that was on the image's right (+u, v = cy) moves up (v < cy), 10 deg counter-clockwise as
    displayed."""
    c = np.array([0.0, 0.0, 10.0])
    level = CameraPose.from_attitude(c, 0.0, 0.0)
    rolled = CameraPose.from_attitude(c, 0.0, 0.0, roll_deg=10.0)
    np.testing.assert_array_equal(rolled.forward, level.forward)
    assert rolled.right[2] == pytest.approx(-math.sin(math.radians(10.0)), abs=1e-15)  # right wing down
    np.testing.assert_allclose(rolled.right, math.cos(math.radians(10)) * level.right
                               + math.sin(math.radians(10)) * level.down, atol=1e-15)
    point = c + 50.0 * level.forward + 3.0 * level.right
    u0, v0 = project_points(PINHOLE, level, point)
    u1, v1 = project_points(PINHOLE, rolled, point)
    cx, cy = PINHOLE.cx_px, PINHOLE.cy_px
    assert u0 > cx and v0 == pytest.approx(cy, abs=1e-9)
    assert u1 > cx and v1 < cy
    assert math.degrees(math.atan2(cy - v1, u1 - cx)) == pytest.approx(10.0, abs=1e-9)
    assert rolled.roll_deg == pytest.approx(10.0, abs=1e-12)


def test_heading_90_pitch_minus_30_looks_east_and_down():
    pose = CameraPose.from_attitude((0, 0, 50), 90.0, -30.0)
    np.testing.assert_allclose(pose.forward, (math.cos(math.radians(30)), 0.0, -0.5), atol=1e-15)
    np.testing.assert_allclose(pose.right, (0, -1, 0), atol=1e-15)  # looking East, right is South
    assert pose.down[2] < 0 and pose.down[0] < 0  # image down: toward the ground, back toward the camera


def test_from_attitude_zero_roll_is_exactly_sightlines_camera_frame():
    headings = [0.0, 1e-7, 15.0, 37.3, 90.0, 135.0, 180.0, 221.687, 270.0, 359.9]
    pitches = [-90.0, -89.99, -60.0, -30.0, -1.0, 0.0, 12.5, 45.0, 89.9, 90.0]
    for h in headings:
        for p in pitches:
            r, d, f = camera_frame(np.float64(h), np.float64(p))
            pose = CameraPose.from_attitude((1.0, 2.0, 3.0), h, p)
            np.testing.assert_array_equal(pose.rotation, np.array([r, d, f]))
            np.testing.assert_array_equal(pose.forward, optical_axis(h, p))


def test_from_attitude_roll_zero_vectorised_camera_frame_grid():
    """The same with camera_frame evaluated on arrays (the way the planner calls it)."""
    h, p = np.meshgrid(np.arange(0.0, 360.0, 7.5), np.arange(-90.0, 90.1, 7.5))
    r, d, f = camera_frame(h, p)
    for i in range(h.shape[0]):
        for j in range(h.shape[1]):
            pose = CameraPose.from_attitude((0, 0, 0), h[i, j], p[i, j])
            np.testing.assert_array_equal(pose.rotation, np.array([r[i, j], d[i, j], f[i, j]]))


def test_look_at_agrees_with_gaze_angles():
    rng = np.random.default_rng(2)
    for _ in range(50):
        c, t = rng.uniform(-50, 50, 3), rng.uniform(-50, 50, 3)
        roll = rng.uniform(-179, 179)
        h, p = gaze_angles(c, t)
        pose = CameraPose.look_at(c, t, roll_deg=roll)
        np.testing.assert_allclose(pose.rotation, CameraPose.from_attitude(c, h, p, roll).rotation, atol=1e-12)
        np.testing.assert_allclose(pose.forward, (t - c) / np.linalg.norm(t - c), atol=1e-15)
        if roll == 0:
            assert pose.right[2] == 0.0


def test_look_at_vertical_axis():
    """Straight down: right = East, image top toward North (down = South). Straight up: right = East, down = North."""
    down_pose = CameraPose.look_at((5, 5, 30), (5, 5, 0))
    np.testing.assert_array_equal(down_pose.forward, (0, 0, -1))
    np.testing.assert_allclose(down_pose.right, (1, 0, 0), atol=1e-15)
    np.testing.assert_allclose(down_pose.down, (0, -1, 0), atol=1e-15)
    np.testing.assert_allclose(down_pose.rotation, CameraPose.from_attitude((5, 5, 30), 0, -90).rotation,
                               atol=1e-15)
    assert down_pose.heading_deg == 0.0 and down_pose.pitch_deg == -90.0 and down_pose.roll_deg == 0.0
    north_of_drone = project_points(PINHOLE, down_pose, [5.0, 6.0, 0.0])
    assert north_of_drone[1] < PINHOLE.cy_px  # North is image up
    up_pose = CameraPose.look_at((0, 0, 0), (0, 0, 3))
    np.testing.assert_allclose(up_pose.right, (1, 0, 0), atol=1e-15)
    np.testing.assert_allclose(up_pose.down, (0, 1, 0), atol=1e-15)
    # a rolled vertical pose reports its rotation as heading (roll 0) and rebuilds from it
    spun = CameraPose.look_at((0, 0, 30), (0, 0, 0), roll_deg=30.0)
    rebuilt = CameraPose.from_attitude((0, 0, 30), spun.heading_deg, spun.pitch_deg, spun.roll_deg)
    np.testing.assert_allclose(rebuilt.rotation, spun.rotation, atol=1e-12)


@settings(max_examples=300, deadline=None)
@given(heading=st.floats(0.0, 360.0, exclude_max=True), pitch=st.floats(-89.9, 89.9),
       roll=st.floats(-179.0, 179.0))
def test_attitude_round_trip(heading, pitch, roll):
    pose = CameraPose.from_attitude((1.0, -2.0, 30.0), heading, pitch, roll)
    assert angle_diff_deg(pose.heading_deg, heading) < 1e-8
    assert 0.0 <= pose.heading_deg < 360.0
    assert pose.pitch_deg == pytest.approx(pitch, abs=1e-9)
    assert pose.roll_deg == pytest.approx(roll, abs=1e-8)
    again = CameraPose.from_attitude(pose.position_m, pose.heading_deg, pose.pitch_deg, pose.roll_deg)
    np.testing.assert_allclose(again.rotation, pose.rotation, atol=1e-12)


# ------------------------------------------------------------------------------ transforms, noise, dicts


def test_world_camera_transforms():
    rng = np.random.default_rng(8)
    pose = random_pose(rng)
    pts = rng.uniform(-100, 100, (4, 5, 3))
    cam = pose.world_to_camera(pts)
    assert cam.shape == pts.shape
    np.testing.assert_allclose(pose.camera_to_world(cam), pts, atol=1e-12)
    np.testing.assert_allclose(pose.world_to_camera(pose.position_m + 7.0 * pose.forward), (0, 0, 7), atol=1e-12)
    np.testing.assert_allclose(pose.world_to_camera(pose.position_m + 2.0 * pose.right), (2, 0, 0), atol=1e-12)
    np.testing.assert_allclose(pose.world_to_camera(pose.position_m + 3.0 * pose.down), (0, 3, 0), atol=1e-12)
    behind = project_points(WIDE, pose, pose.position_m - 5.0 * pose.forward)
    assert np.all(np.isnan(behind))


def test_perturbed():
    pose = CameraPose.from_attitude((10.0, 20.0, 30.0), 45.0, -40.0, 5.0)
    same = pose.perturbed(0.0, 0.0, np.random.default_rng(0))
    np.testing.assert_allclose(same.rotation, pose.rotation, atol=1e-12)
    np.testing.assert_array_equal(same.position_m, pose.position_m)
    a = pose.perturbed(0.5, 2.0, 42)
    b = pose.perturbed(0.5, 2.0, np.random.default_rng(42))
    assert a == b and a != pose  # seeded: reproducible; and it moved
    rng = np.random.default_rng(1)
    draws = [pose.perturbed(0.5, 2.0, rng) for _ in range(2000)]
    dpos = np.array([d.position_m for d in draws]) - pose.position_m
    datt = np.array([(d.heading_deg - 45.0, d.pitch_deg + 40.0, d.roll_deg - 5.0) for d in draws])
    np.testing.assert_allclose(dpos.std(axis=0), 0.5, rtol=0.1)
    np.testing.assert_allclose(datt.std(axis=0), 2.0, rtol=0.1)
    np.testing.assert_allclose(dpos.mean(axis=0), 0.0, atol=0.05)
    np.testing.assert_allclose(datt.mean(axis=0), 0.0, atol=0.2)
    with pytest.raises(PihimInputError, match=">= 0"):
        pose.perturbed(-1.0, 0.0, rng)


def test_dict_round_trip_and_immutability():
    pose = CameraPose.from_attitude((1.5, -2.25, 30.0), 221.7, -80.6, 3.0)
    d = json.loads(json.dumps(pose.to_dict(), allow_nan=False))
    assert set(d) == {"position_m", "rotation", "heading_deg", "pitch_deg", "roll_deg"}
    assert d["heading_deg"] == pytest.approx(221.7) and d["pitch_deg"] == pytest.approx(-80.6)
    assert d["roll_deg"] == pytest.approx(3.0)
    back = CameraPose.from_dict(d)
    assert back == pose and hash(back) == hash(pose)
    with pytest.raises(ValueError):
        pose.position_m[0] = 0.0
    with pytest.raises(ValueError):
        pose.rotation[0, 0] = 0.0
    src = np.array([1.0, 2.0, 3.0])
    p = CameraPose(position_m=src, rotation=np.eye(3))
    src[0] = 99.0
    assert p.position_m[0] == 1.0  # a copy


# ------------------------------------------------------------------------------ plan.json


def small_field() -> Field:
    names, pivots = [], []
    for row, y in ((5, 57.9), (6, 70.1), (7, 82.3)):
        for col in range(1, 4):
            for side, sign in (("E", 1.0), ("W", -1.0)):
                names.append(f"{row}{side}{col}")
                pivots.append((sign * (col - 0.5) * 9.7536, y, 3.8))
    return Field(tuple(names), np.array(pivots), nsttf_spec(), NSTTF_TOWER)


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    """A plan from the project's own planner (18 heliostats, no contrast shifts: ~1 s) and its plan.json."""
    plan = build_plan(small_field(), datetime.fromisoformat("2021-05-13T13:00-06:00"), NSTTF,
                      aim_point=(0.0, 8.8, 28.9), shift=False)
    path = write_plan_json(plan, tmp_path_factory.mktemp("plan") / "plan.json")
    return plan, path


def test_from_plan_json_matches_the_capture_waypoints(planned):
    plan, path = planned
    captures = [w for p in plan.passes for w in p.waypoints if w.capture]
    doc = json.loads(path.read_text())
    assert len(captures) == doc["export"]["counts"]["capture_waypoints"] >= 4
    for i, w in enumerate(captures):
        pose = CameraPose.from_plan_json(path, i)
        np.testing.assert_allclose(pose.position_m, (w.x_m, w.y_m, w.z_m), rtol=0, atol=1e-12)
        assert angle_diff_deg(pose.heading_deg, w.heading_deg) < 1e-9
        assert pose.pitch_deg == pytest.approx(w.gimbal_pitch_deg, abs=1e-9)
        assert pose.roll_deg == pytest.approx(0.0, abs=1e-12)
        r, d, f = camera_frame(np.float64(w.heading_deg), np.float64(w.gimbal_pitch_deg))
        np.testing.assert_array_equal(pose.rotation, np.array([r, d, f]))
        assert CameraPose.from_waypoint(w) == pose
    # the capture's HUA is in view (the planner aims each capture at its HUA's mirror)
    centres = dict(zip(small_field().names, small_field().pivots, strict=True))
    w = captures[0]
    uv = project_points(CameraModel.from_dict(doc["camera"]), CameraPose.from_plan_json(path, 0), centres[w.hua])
    assert 0 <= uv[0] <= 2447 and 0 <= uv[1] <= 2047


def test_from_plan_json_errors(planned, tmp_path):
    _, path = planned
    n = json.loads(path.read_text())["export"]["counts"]["capture_waypoints"]
    with pytest.raises(PihimInputError, match=rf"capture index {n} out of range: .* has {n} capture waypoints"):
        CameraPose.from_plan_json(path, n)
    with pytest.raises(PihimInputError, match="out of range"):
        CameraPose.from_plan_json(path, -1)
    with pytest.raises(PihimInputError, match="not found"):
        CameraPose.from_plan_json(tmp_path / "missing.json", 0)
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(PihimInputError, match="not valid JSON") as err:
        CameraPose.from_plan_json(bad, 0)
    assert "\n" not in str(err.value)
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"schema": "something/1", "passes": []}))
    with pytest.raises(PihimInputError, match="not a pihim plan.json"):
        CameraPose.from_plan_json(other, 0)
    with pytest.raises(PihimInputError, match="integer"):
        CameraPose.from_plan_json(path, 0.0)


def test_from_waypoint_mapping():
    w = {"x_m": 1.0, "y_m": 2.0, "z_m": 30.0, "heading_deg": 90.0, "gimbal_pitch_deg": -30.0, "roll_deg": 4.0}
    pose = CameraPose.from_waypoint(w)
    assert pose == CameraPose.from_attitude((1, 2, 30), 90, -30, 4)
    with pytest.raises(PihimInputError, match="gimbal_pitch_deg"):
        CameraPose.from_waypoint({k: v for k, v in w.items() if k != "gimbal_pitch_deg"})
    with pytest.raises(PihimInputError, match="waypoint x_m must be a number of metres, got None"):
        CameraPose.from_waypoint({**w, "x_m": None})
    with pytest.raises(PihimInputError, match="waypoint heading_deg must be a number of degrees, got 'east'"):
        CameraPose.from_waypoint({**w, "heading_deg": "east"})


# ------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    "position, rotation, needle",
    [
        ((0, 0, 0), np.diag([1.0, 1.0, 1.001]), "orthonormal"),
        ((0, 0, 0), [[1.0, 1e-6, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "orthonormal"),
        ((0, 0, 0), np.diag([1.0, 1.0, -1.0]), "determinant"),
        ((0, 0, 0), np.eye(3)[:2], "shape"),
        ((0, 0, 0), np.full((3, 3), np.nan), "finite"),
        ((0, 0, math.nan), np.eye(3), "finite"),
        ((0, 0), np.eye(3), "shape"),
        ("abc", np.eye(3), "3 numbers"),
    ],
)
def test_bad_pose_raises(position, rotation, needle):
    with pytest.raises(PihimInputError, match=needle) as err:
        CameraPose(position_m=position, rotation=rotation)
    assert "\n" not in str(err.value)


def test_bad_constructor_arguments_raise():
    with pytest.raises(PihimInputError, match="equals the camera position"):
        CameraPose.look_at((1, 2, 3), (1, 2, 3))
    with pytest.raises(PihimInputError, match="finite"):
        CameraPose.look_at((1, 2, 3), (1, math.nan, 3))
    with pytest.raises(PihimInputError, match="heading"):
        CameraPose.from_attitude((0, 0, 0), math.nan, 0.0)
    with pytest.raises(PihimInputError, match="roll"):
        CameraPose.from_attitude((0, 0, 0), 0.0, 0.0, math.inf)
    with pytest.raises(PihimInputError, match="rvec"):
        CameraPose.from_rvec_tvec([0.1, 0.2], [0, 0, 0])
    pose = CameraPose.from_attitude((0, 0, 0), 0.0, 0.0)
    with pytest.raises(PihimInputError, match=r"\(\.\.\., 3\)"):
        pose.world_to_camera(np.zeros((5, 2)))
    with pytest.raises(PihimInputError, match=r"\(\.\.\., 3\)"):
        project_points(WIDE, pose, [1.0, 2.0])
    with pytest.raises(PihimInputError, match="rotation"):
        CameraPose.from_dict({"position_m": [0, 0, 0]})
