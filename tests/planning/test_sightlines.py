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
