"""Sub-pixel edge points and camera pose refinement on the HUA's facet outlines."""

import numpy as np
import pytest

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose, project_points
from pihim.field import nsttf_like_field, track_field
from pihim.inspection.features import EdgePoints, edge_points
from pihim.inspection.pose import _coarse_shift, _pan_tilt, facet_outline_segments, refine_pose, sample_segments
from pihim.polarimetry.frames import normalize
from pihim.render.frame import RenderSettings, render_frame
from pihim.render.scene import field_scene
from pihim.render.shading import Environment
from pihim.polarimetry.stokes import aop_deg, dolp

SUN = normalize(np.array([0.45, -0.35, 0.82]))


def test_edge_points_locate_a_blurred_step_to_a_few_hundredths_of_a_pixel():
    import cv2

    h, w = 64, 64
    for x0 in (30.0, 30.25, 30.5, 30.8):
        # an antialiased vertical step at x = x0 (pixel centres at integers), blurred like a lens
        jj = np.arange(w)[None, :].repeat(h, 0).astype(float)
        cover = np.clip(jj + 0.5 - x0, 0.0, 1.0)
        s0 = cv2.GaussianBlur(1.0 + 3.0 * cover, (0, 0), 1.2)
        ep = edge_points(s0, np.zeros((h, w)), np.zeros((h, w)), smooth_px=0.0)
        mid = (ep.xy[:, 1] > 10) & (ep.xy[:, 1] < h - 10)
        assert mid.sum() > 30
        # the parabola peak of a smooth gradient sits on the step, within 0.05 px
        assert np.median(ep.xy[mid, 0]) == pytest.approx(x0, abs=0.05)
        assert np.all(np.abs(ep.normal[mid, 0]) > 0.99)


def test_axial_aop_makes_no_false_edge_at_the_wrap():
    h, w = 40, 80
    # AoP sweeping smoothly through 180 -> 0 (a continuous orientation field)
    aop = np.mod(170.0 + 0.5 * np.arange(w)[None, :].repeat(h, 0), 180.0)
    ep = edge_points(np.ones((h, w)), np.full((h, w), 0.6), aop, smooth_px=0.0, threshold=0.05)
    assert len(ep) == 0
    # a real 90 deg step is an edge
    step = np.where(np.arange(w)[None, :] < 40, 10.0, 100.0).repeat(h, 0)
    ep = edge_points(np.ones((h, w)), np.full((h, w), 0.6), step, smooth_px=0.0, threshold=0.05)
    assert len(ep) > h - 4


def _view():
    field = nsttf_like_field()
    pose = track_field(field, SUN)
    i = field.index("8E3")
    centre = pose.mirror_centres[i]
    cam = CameraModel(width_px=816, height_px=682, focal_length_mm=5.5)
    true = CameraPose.look_at(centre + 22.0 * normalize(pose.normals[i] + [0.0, 0.0, 0.6]), centre, roll_deg=3.0)
    return field, pose, i, cam, true


def test_coarse_shift_and_pan_tilt_signs():
    field, pose, i, cam, true = _view()
    pts, _ = sample_segments(facet_outline_segments(pose.facet_corners()[i]), 0.02)
    uv = project_points(cam, true, pts)
    ok = np.all(np.isfinite(uv), 1) & (uv[:, 0] > 0) & (uv[:, 0] < cam.width_px) & (uv[:, 1] > 0) \
        & (uv[:, 1] < cam.height_px)
    for sx, sy in [(60, 0), (0, -48), (-100, 36)]:
        ep = EdgePoints(uv[ok] + [sx, sy], np.zeros((ok.sum(), 2)), np.ones(ok.sum()))
        dx, dy = _coarse_shift(cam, true, pts, ep, 300)
        assert (dx, dy) == pytest.approx((sx, sy), abs=4.0)  # a quarter-resolution search
        moved = project_points(cam, _pan_tilt(cam, true, sx, sy), pts[:1]) - project_points(cam, true, pts[:1])
        assert moved[0] == pytest.approx([sx, sy], abs=0.1 * np.hypot(sx, sy) + 1)


def test_refine_pose_converges_from_a_nearby_prior_on_a_rendered_frame():
    field, pose, i, cam, true = _view()
    env = Environment.clear_sky(SUN)
    fr = render_frame(field_scene(pose), cam, true, env, RenderSettings(supersample=3))
    ep = edge_points(fr.s0, dolp(fr.s0, fr.s1, fr.s2), aop_deg(fr.s1, fr.s2))
    corners = pose.facet_corners()[i]
    segs = facet_outline_segments(corners)
    prior = CameraPose(true.position_m + [0.12, -0.08, 0.1],
                       CameraPose.from_attitude(true.position_m, true.heading_deg + 0.4, true.pitch_deg - 0.3,
                                                true.roll_deg).rotation)
    c = corners.reshape(-1, 3)
    before = np.abs(project_points(cam, prior, c) - project_points(cam, true, c)).max()
    fit = refine_pose(cam, prior, segs, ep)
    after = np.abs(project_points(cam, fit.pose, c) - project_points(cam, true, c)).max()
    assert before > 15.0
    assert after < 0.3
    assert fit.rms_px < 0.5


def test_threaded_alignments_give_the_one_thread_pose(monkeypatch):
    """The search's alignments of a start run on threads; the pose is the one a single thread finds, bit for bit."""
    import numba

    field, pose, i, cam, true = _view()
    fr = render_frame(field_scene(pose), cam, true, Environment.clear_sky(SUN), RenderSettings(supersample=2))
    ep = edge_points(fr.s0)
    segs = facet_outline_segments(pose.facet_corners()[i])
    prior = CameraPose(true.position_m + [0.9, -0.6, 0.7], true.rotation)  # a few starts before one is accepted
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 2)
    two = refine_pose(cam, prior, segs, ep)
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 1)
    one = refine_pose(cam, prior, segs, ep)
    assert two.starts == one.starts >= 2
    np.testing.assert_array_equal(two.pose.rotation, one.pose.rotation)
    np.testing.assert_array_equal(two.pose.position_m, one.pose.position_m)
    assert two.rms_px == one.rms_px


def test_search_does_not_stop_at_a_neighbours_outline():
    """Frame 15 of benchmarks/canting_quality.py (12E10 seen showing 11E11 at 10:00, GPS prior 4.3 m off): the
    first start that fits aligns the model onto a neighbouring heliostat at support 0.85. The search must go on
    to the right pose (support 0.98), not accept that one."""
    from pihim.camera import polar_image
    from pihim.inspection.pipeline import field_pose_from_log
    from pihim.render.simulate import PairPose, simulate_frame

    field = nsttf_like_field()
    sim = simulate_frame(field, "2021-05-13T10:00-06:00", camera=CameraModel(), pose_request=PairPose("12E10", "11E11"),
                         canting_sigma_mrad=3.0, gps_sigma_m=1.5, attitude_sigma_deg=1.0, seed=15)
    prior, true = CameraPose.from_dict(sim.log["pose"]), CameraPose.from_dict(sim.truth["pose"])
    assert np.linalg.norm(prior.position_m - true.position_m) > 4.0  # the case: a prior far off
    edges = edge_points(polar_image(sim.raw, demosaic="full", bit_depth=12).s0)
    corners = field_pose_from_log(field, sim.log).facet_corners()[field.index("12E10")]
    fit = refine_pose(CameraModel.from_dict(sim.log["camera"]), prior, facet_outline_segments(corners), edges)
    assert fit.support > 0.95
    assert np.linalg.norm(fit.pose.position_m - true.position_m) < 0.05
