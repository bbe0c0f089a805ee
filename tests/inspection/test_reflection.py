"""The reflection forward model of :mod:`pihim.inspection.reflection`: the target's outline as the HUA mirrors
it, and the view of a HUA turned off its logged drive angles."""

import numpy as np

from pihim.inspection.reflection import hua_turn_transform, target_outline_segments


def test_target_outline_includes_facets_and_members(ufacet):
    field, pose, h, *_ = ufacet
    segs = target_outline_segments(pose, field.index("7E3"))
    # 25 facets x 4 edges, and 4 long edges for each of 1 torque tube + 5 ribs + 5 crossbars
    assert segs.shape == (100 + 4 * 11, 2, 3)
    # the member edges run behind the mirror (on the target's back side)
    t = field.index("7E3")
    depth = (segs[100:].reshape(-1, 3) - pose.mirror_centres[t]) @ pose.normals[t]
    assert np.all(depth < -0.05) and np.all(depth > -0.35)


def test_hua_turn_transform_maps_the_turned_heliostat_onto_the_logged_one(ufacet):
    """A camera pose fitted on the HUA at its logged angles sees a point fixed to the really turned HUA where
    the logged HUA has it: the transform takes the turned HUA's corners (FieldPose.with_drive) onto the
    logged ones, and leaves its pivot in place."""
    _, pose, h, *_ = ufacet
    d = pose.drive
    a, e = np.array(d.azimuth_deg, float), np.array(d.elevation_deg, float)
    a[h] += 0.7
    e[h] -= 0.4
    turned_corners = pose.with_drive(a, e).facet_corners()[h].reshape(-1, 3)
    pivot, m = hua_turn_transform(pose, h, 0.7, -0.4)
    np.testing.assert_allclose(pivot + (turned_corners - pivot) @ m.T, pose.facet_corners()[h].reshape(-1, 3),
                               atol=1e-9)
    np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(hua_turn_transform(pose, h, 0.0, 0.0)[1], np.eye(3), atol=1e-12)


def test_facet_in_view_is_the_share_of_the_outline_on_the_sensor():
    """A camera looking straight down at the ground: a facet under the image centre is wholly in view, the same
    facet centred on the image's right border half in view (its inner side, half of each side across the border),
    and one above the camera (behind it) not at all."""
    from pihim.camera import CameraModel, CameraPose
    from pihim.inspection.pipeline import project_points
    from pihim.inspection.reflection import facet_in_view

    cam = CameraModel()
    pose = CameraPose.look_at([0.0, 0.0, 20.0], [0.0, 0.0, 0.0])
    # on the ground plane, parallel to the sensor, pixels are an affine map of (x, y): find it and its inverse
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    uv = project_points(cam, pose, np.column_stack([xy, np.zeros(3)]))
    jac = np.column_stack([uv[1] - uv[0], uv[2] - uv[0]])  # d(u, v) / d(x, y)

    def ground(u, v):
        return np.append(np.linalg.solve(jac, np.array([u, v]) - uv[0]), 0.0)

    def square(u, v, half_px=100.0):  # a facet whose corners are half_px from (u, v) along the image axes
        return np.array([ground(u + du * half_px, v + dv * half_px) for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1))])

    centre, border = square(cam.width_px / 2, cam.height_px / 2), square(cam.width_px - 0.5, cam.height_px / 2)
    behind = centre + np.array([0.0, 0.0, 40.0])
    share = facet_in_view(cam, pose, np.stack([centre, border, behind]))
    assert share[0] == 1.0 and share[2] == 0.0
    assert abs(share[1] - 0.5) <= 1.5 / 96  # 24 points a side: the side across the border splits 12 / 11-12


def test_one_facet_normal_tilted_as_apply_canting_deviation_does_it():
    """The compiled normal of every canting fit's round: ``apply_canting_deviation`` to the bit in the heliostat
    frame, then turned by the HUA's rotation (to a rounding error of the 3 x 3 product's order)."""
    from scipy.spatial.transform import Rotation

    from pihim.field.kinematics import apply_canting_deviation
    from pihim.inspection._kernels import facet_normal

    rng = np.random.default_rng(5)
    for _ in range(500):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        a, e = rng.uniform(-20.0, 20.0, 2)
        tilted = apply_canting_deviation(n, a, e)
        np.testing.assert_array_equal(facet_normal(np.concatenate([np.eye(3).ravel(), [1.0, 2.0, 3.0], n]), a, e),
                                      tilted)
        rot = Rotation.random(random_state=rng.integers(2**31)).as_matrix()
        np.testing.assert_allclose(facet_normal(np.concatenate([rot.ravel(), [1.0, 2.0, 3.0], n]), a, e),
                                   rot @ tilted, rtol=0, atol=1e-15)
