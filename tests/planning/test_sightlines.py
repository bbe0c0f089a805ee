"""The planner's field-of-view test, held to OpenCV's projection."""

import numpy as np
import pytest

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose
from pihim.planning.sightlines import in_fov, optical_axis


def test_in_fov_agrees_with_opencv_projection() -> None:
    """A point is in view exactly when cv2.projectPoints puts it on the sensor, in front of the camera
    (pinhole, no distortion; the planner's gimbal does not roll)."""
    cv2 = pytest.importorskip("cv2")
    camera = CameraModel()
    rng = np.random.default_rng(3)
    n_cam, k = 40, 200
    cams = rng.uniform([-20, -20, 5], [20, 20, 30], (n_cam, 3))
    heading = rng.uniform(0.0, 360.0, n_cam)
    pitch = rng.uniform(-85.0, 20.0, n_cam)
    # points around the optical axis 20-60 m out, most of them within the 35 mm lens's narrow view
    dist = rng.uniform(20.0, 60.0, (n_cam, k, 1))
    spread = rng.normal(0.0, 0.08, (n_cam, k, 3)) * dist
    pts = cams[:, None, :] + dist * optical_axis(heading, pitch)[:, None, :] + spread
    got = in_fov(pts, cams, heading, pitch, camera)
    assert got.shape == (n_cam, k)
    kmat = camera.intrinsics()
    # the planner's view: the sensor's half-widths either side of the principal point
    u0, u1 = kmat[0, 2] - 0.5 * camera.width_px, kmat[0, 2] + 0.5 * camera.width_px
    v0, v1 = kmat[1, 2] - 0.5 * camera.height_px, kmat[1, 2] + 0.5 * camera.height_px
    for i in range(n_cam):
        pose = CameraPose.from_attitude(cams[i], heading[i], pitch[i], 0.0)
        rvec, tvec = pose.rvec_tvec()
        uv = cv2.projectPoints(pts[i], rvec, tvec, kmat, None)[0].reshape(-1, 2)
        z = (pts[i] - cams[i]) @ np.asarray(pose.rotation, float)[2]
        want = (z > 0) & (uv[:, 0] >= u0) & (uv[:, 0] <= u1) & (uv[:, 1] >= v0) & (uv[:, 1] <= v1)
        # points within 1e-6 px of the border may fall either side
        border = np.minimum.reduce([np.abs(uv[:, 0] - u0), np.abs(uv[:, 0] - u1), np.abs(uv[:, 1] - v0),
                                    np.abs(uv[:, 1] - v1)]) < 1e-6
        np.testing.assert_array_equal(got[i][~border], want[~border])
    assert 0.2 < got.mean() < 0.9  # the draw exercises both answers (measured 0.69 in view)
    # broadcasting: one camera against a (K, 3) set, as the mission-timing check calls it
    one = in_fov(pts[0], cams[0], np.float64(heading[0]), np.float64(pitch[0]), camera)
    np.testing.assert_array_equal(one, got[0])


def _every_mirror(index, p0, p1, exclude):
    """The first mirror each segment crosses, against every mirror of the field (plain loops)."""
    out = np.full(len(p0), -1)
    for i in range(len(p0)):
        best, d = np.inf, p1[i] - p0[i]
        for j in range(len(index.centres)):
            den = d @ index.n[j]
            if j in exclude[i] or den == 0:
                continue
            t = (index.centres[j] - p0[i]) @ index.n[j] / den
            q = p0[i] + t * d - index.centres[j]
            if 1e-6 < t < 1 - 1e-6 and t < best and abs(q @ index.x[j]) <= index.hw and abs(q @ index.y[j]) <= index.hh:
                best, out[i] = t, j
    return out


def test_mirror_index_finds_the_first_mirror_of_every_sight_line_of_a_tracked_field() -> None:
    """Sight lines from cameras above the NSTTF-like field to random mirror points, and reflected rays, against
    every mirror: the grid's candidates miss no crossing."""
    from pihim.field.kinematics import track_field
    from pihim.field.layout import nsttf_like_field
    from pihim.planning.sightlines import MirrorIndex
    from pihim.sky.sun import direction_from_angles

    pose = track_field(nsttf_like_field(), direction_from_angles(35.0, 120.0), np.array([0.0, 0.0, 60.0]))
    index = MirrorIndex(pose)
    rng = np.random.default_rng(8)
    n = 1500
    target = rng.integers(0, len(index.centres), n)
    on_mirror = index.centres[target] + (rng.uniform(-1, 1, (n, 1)) * index.hw * index.x[target]
                                         + rng.uniform(-1, 1, (n, 1)) * index.hh * index.y[target])
    cams = rng.uniform([-120, -20, 8], [120, 200, 30], (n, 3))
    p0, p1 = cams, on_mirror + 60.0 * (on_mirror - cams) / np.linalg.norm(on_mirror - cams, axis=1)[:, None]
    exclude = np.where(rng.random((n, 1)) < 0.5, target[:, None], -1)
    got = index.first_hits(p0, p1, exclude, chunk=400)
    want = _every_mirror(index, p0, p1, exclude)
    assert (want >= 0).sum() > 500 and (want < 0).sum() > 50
    np.testing.assert_array_equal(got, want)


def test_a_stray_heliostat_far_away_neither_inflates_the_grid_nor_is_lost() -> None:
    """400 mirrors on a 10 m lattice and one mistyped 1,000 km away (then one at 1e308 m): the cells stay the
    size of a mirror, and a ray straight down onto any mirror, the stray one included, finds it."""
    from types import SimpleNamespace

    from pihim.planning.sightlines import MirrorIndex

    spec = SimpleNamespace(mirror_half_width_m=3.0, mirror_half_height_m=3.0)
    gx, gy = np.meshgrid(np.arange(20) * 10.0, np.arange(20) * 10.0)
    for far in (1e6, 1e308):
        centres = np.column_stack([np.r_[gx.ravel(), far], np.r_[gy.ravel(), 50.0], np.full(401, 3.0)])
        pose = SimpleNamespace(field=SimpleNamespace(spec=spec), mirror_centres=centres,
                               rotations=np.tile(np.eye(3), (401, 1, 1)), normals=np.tile([0.0, 0.0, 1.0], (401, 1)))
        index = MirrorIndex(pose)
        if far == 1e6:
            assert index.cell < 20.0 and np.diff(index.cell_start).max() <= 4
        got = index.first_hits(centres + [0.5, 0.5, 10.0], centres + [0.5, 0.5, -10.0], np.full((401, 1), -1))
        np.testing.assert_array_equal(got, np.arange(401))
