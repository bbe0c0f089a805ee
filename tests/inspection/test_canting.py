"""Per-facet canting from the target's reflection, scored against rendered truth.

The frame is rendered by the ray tracer (:mod:`pihim.render`); the estimator
projects the target's outlines mirrored in each facet's plane (an independent
forward model: plane mirroring and ``project_points``, held to OpenCV).
"""

import numpy as np
import pytest

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose, project_points
from pihim.field import UFACET_AIM_POINT, apply_canting_deviation, nsttf_like_field, track_field
from pihim.inspection.canting import PAPER_GRID_STEP_MRAD, estimate_canting, target_outline_segments
from pihim.inspection.features import edge_points
from pihim.planning.pipeline import build_plan
from pihim.render.frame import render_frame
from pihim.render.scene import field_scene
from pihim.render.shading import Environment
from pihim.sky.sun import NSTTF, parse_time, sun_position


@pytest.fixture(scope="module")
def ufacet():
    field = nsttf_like_field()
    t = parse_time("2021-05-13T13:00-06:00")
    sun = sun_position(NSTTF, t).vector
    plan = build_plan(field, t, NSTTF, aim_point=UFACET_AIM_POINT, heliostats=["8E3"], shift=False)
    wp = next(p.waypoints[q.waypoint_index] for p in plan.passes for q in p.predictions
              if (q.hua, q.target) == ("8E3", "7E3"))
    pose = track_field(field, sun, UFACET_AIM_POINT)
    h = field.index("8E3")
    rng = np.random.default_rng(2)
    az, el = rng.normal(0.0, 3.0, 25), rng.normal(0.0, 3.0, 25)
    normals = pose.facet_normals_local.copy()
    normals[h] = apply_canting_deviation(pose.facet_normals_local[h], az, el)
    # the Triton + 35 mm, cropped to the middle 1224 x 1024 px (facets 7-8, 12-13, 17-18 and parts of others)
    cam = CameraModel(width_px=1224, height_px=1024)
    cp = CameraPose.from_waypoint(wp)
    fr = render_frame(field_scene(pose, normals), cam, cp, Environment.clear_sky(sun))
    return field, pose, h, az, el, cam, cp, fr


def test_target_outline_includes_facets_and_members(ufacet):
    field, pose, h, *_ = ufacet
    segs = target_outline_segments(pose, field.index("7E3"))
    # 25 facets x 4 edges, and 4 long edges for each of 1 torque tube + 5 ribs + 5 crossbars
    assert segs.shape == (100 + 4 * 11, 2, 3)
    # the member edges run behind the mirror (on the target's back side)
    t = field.index("7E3")
    depth = (segs[100:].reshape(-1, 3) - pose.mirror_centres[t]) @ pose.normals[t]
    assert np.all(depth < -0.05) and np.all(depth > -0.35)


def test_canting_recovered_to_a_fraction_of_the_paper_grid_step(ufacet):
    field, pose, h, az, el, cam, cp, fr = ufacet
    z = np.zeros_like(fr.s0)
    ep = edge_points(fr.s0, z, z)  # S0 edges (see the module notes of pihim.inspection.canting)
    res = estimate_canting(cam, cp, pose, "8E3", "7E3", ep, min_dolp=None)
    used = [f for f in res.facets if f.used]
    assert len(used) >= 3
    true_az = np.array([az[f.id - 1] for f in used])
    true_el = np.array([el[f.id - 1] for f in used])
    est_az = np.array([f.az_mrad for f in used])
    est_el = np.array([f.el_mrad for f in used])
    # relative to the best-fit orientation (the mean over the facets used), as reported
    err_az = est_az - (true_az - true_az.mean())
    err_el = est_el - (true_el - true_el.mean())
    # measured 0.35 / 0.02 mrad RMS here; the benchmark bound is 0.5 mrad, this fast test a looser 0.6
    assert np.sqrt(np.mean(err_az**2)) < 0.6
    assert np.sqrt(np.mean(err_el**2)) < 0.6
    # the raw best-fit orientation is the mean true canting (exact camera pose, no tracking error)
    assert res.orientation_az_mrad == pytest.approx(true_az.mean(), abs=0.6)
    assert res.orientation_el_mrad == pytest.approx(true_el.mean(), abs=0.6)
    # the paper's grid search is limited by its 1.75 mrad step
    grid_az = np.array([f.grid_az_mrad for f in used])
    assert np.max(np.abs(grid_az - (true_az - true_az.mean()))) < PAPER_GRID_STEP_MRAD
    # every skipped facet says why
    assert all(f.reason for f in res.facets if not f.used)
    assert res.to_dict()["facets"][0]["id"] == 1
