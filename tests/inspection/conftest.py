"""Shared fixture of the inspection tests: a rendered UFACET frame with known facet canting."""

import numpy as np
import pytest

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose
from pihim.field import UFACET_AIM_POINT, apply_canting_deviation, nsttf_like_field, track_field
from pihim.planning.pipeline import build_plan
from pihim.render.frame import render_frame
from pihim.render.scene import field_scene
from pihim.render.shading import Environment
from pihim.sky.sun import NSTTF, parse_time, sun_position


@pytest.fixture(scope="session")
def ufacet():
    """8E3 seen at its planned UFACET capture of 7E3, 13:00, facets canted N(0, 3 mrad) per axis: field, tracked
    pose, HUA index, true canting az / el (mrad), camera, camera pose, rendered frame."""
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
