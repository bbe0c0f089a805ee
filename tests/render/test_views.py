"""Tests of :mod:`pihim.render.views`: the chosen camera shows, in the render, the scenario it was chosen for.

The sky-vs-sky view is exercised in ``tests/inspection/test_sky_vs_sky.py``;
here the ground-vs-ground view: 8E3's lower edge at 09:30 on 2021-05-13,
the field tracking. The prediction (:func:`pihim.scenarios.ground_vs_ground`)
and the ray tracer are independent paths to the same physics; the render
must show the mirror reflecting ground next to real ground with an axial AoP
difference above the paper's 50 deg and little S0 contrast.
"""

import numpy as np
import pytest

from pihim.camera.model import CameraModel
from pihim.camera.pose import project_points
from pihim.errors import PihimInputError
from pihim.field import UFACET_AIM_POINT, nsttf_like_field, track_field
from pihim.inspection.success import scenario_mask
from pihim.polarimetry.stokes import aop_deg
from pihim.polarimetry.stokes import dolp as dolp_of
from pihim.render.frame import render_frame
from pihim.render.paths import GROUND, MIRROR
from pihim.render.scene import field_scene
from pihim.render.shading import Environment
from pihim.render.views import ground_vs_ground_view, sky_vs_sky_view
from pihim.sky.sun import NSTTF, parse_time, sun_position

CAMERA = CameraModel(width_px=612, height_px=512, focal_length_mm=8.75)


@pytest.fixture(scope="module")
def ground():
    field = nsttf_like_field()
    sun = sun_position(NSTTF, parse_time("2021-05-13T09:30-06:00"))
    env = Environment.clear_sky(sun.vector)
    pose = track_field(field, sun.vector, UFACET_AIM_POINT)
    i = field.index("8E3")
    scene = field_scene(pose)
    view = ground_vs_ground_view(pose, i, env, step_m=3.0, scene=scene)
    assert view is not None
    frame = render_frame(scene, CAMERA, view.camera_pose(), env)
    return {"pose": pose, "i": i, "view": view, "frame": frame}


def test_ground_view_looks_down_at_the_lower_edge(ground):
    view, pose, i = ground["view"], ground["pose"], ground["i"]
    cam = view.camera_pose()
    assert cam.pitch_deg <= -40.0 + 1e-9
    assert view.aop_difference_deg > 50.0 and view.s0_contrast <= 0.1 and view.candidates > 0
    # the point looked at is on the lower edge, and in the middle of the image
    o = pose.mirror_outline()[i]
    e = view.look_at_m - o[3]
    along = e @ (o[2] - o[3]) / np.linalg.norm(o[2] - o[3]) ** 2
    assert 0.15 <= along <= 0.45
    assert np.linalg.norm(e - along * (o[2] - o[3])) < 1e-9
    uv = project_points(CAMERA, cam, view.look_at_m[None])[0]
    np.testing.assert_allclose(uv, [CAMERA.width_px / 2 - 0.5, CAMERA.height_px / 2 - 0.5], atol=1.0)


def test_render_shows_the_predicted_ground_vs_ground_contrast(ground):
    fr, i = ground["frame"], ground["i"]
    lab = fr.labels
    clean = ~fr.supersampled
    h, w = lab.shape[:2]
    near = np.hypot(*(np.indices((h, w))[::-1] - np.array([w / 2, h / 2])[:, None, None])) < 80
    mirror = near & clean & (lab[..., 0] == MIRROR) & (lab[..., 1] == i) & (lab[..., 3] == GROUND)
    real = near & clean & (lab[..., 0] == GROUND)
    assert mirror.sum() > 300 and real.sum() > 300
    a = aop_deg(fr.s1, fr.s2)
    am = np.degrees(0.5 * np.angle(np.mean(np.exp(2j * np.radians(a[mirror])))))
    ag = np.degrees(0.5 * np.angle(np.mean(np.exp(2j * np.radians(a[real])))))
    axial = abs((am - ag + 90.0) % 180.0 - 90.0)
    assert axial > 50.0
    assert axial == pytest.approx(ground["view"].aop_difference_deg, abs=10.0)
    s0m, s0g = fr.s0[mirror].mean(), fr.s0[real].mean()
    assert abs(s0m - s0g) / (s0m + s0g) < 0.15
    d = dolp_of(fr.s0, fr.s1, fr.s2)
    assert np.median(d[mirror]) == pytest.approx(ground["view"].mirror_dolp, abs=0.05)
    # the ground-vs-ground mask covers the lower edge's stretch in view, not the sky reflection
    mask = scenario_mask(lab, i, "ground")
    assert mask[near].any()
    with pytest.raises(PihimInputError, match="background"):
        scenario_mask(lab, i, "water")


def test_views_refuse_and_give_up_cleanly(ground):
    pose, i = ground["pose"], ground["i"]
    env = Environment.clear_sky(sun_position(NSTTF, parse_time("2021-05-13T09:30-06:00")).vector)
    with pytest.raises(PihimInputError):
        sky_vs_sky_view(pose, i, i, env, CAMERA)
    # nothing can satisfy an impossible AoP difference
    assert ground_vs_ground_view(pose, i, env, step_m=6.0, min_aop_difference_deg=91.0) is None
