"""Edge success on a rendered sky-vs-sky frame: the fast version of ``benchmarks/edge_success_quality.py``.

The benchmark's first candidate arrangement at reduced size: front 8W5
tracking at 16:00 on 2021-05-13, its back neighbour 9W5 and every other
heliostat face-up, the camera where :func:`pihim.render.views.sky_vs_sky_view`
predicts the largest DoLP difference across 8W5's top edge. The Triton's
field of view at 1224 x 1024 pixels, canting 3 mrad, the default sensor's
noise. Looser than the benchmark: one frame at half the sensor's size, full-resolution route,
k = 2 px (4 px of the full sensor).
"""

import numpy as np
import pytest

from pihim.camera import polar_image
from pihim.camera.model import CameraModel
from pihim.camera.pose import project_points
from pihim.errors import PihimInputError
from pihim.field import UFACET_AIM_POINT, nsttf_like_field, track_field
from pihim.inspection.edges import edge_maps
from pihim.inspection.success import FacetOutlines, edge_success, outlines_from_simulation, sky_vs_sky_mask
from pihim.polarimetry.stokes import dolp
from pihim.render.paths import GROUND, MIRROR, SKY
from pihim.render.shading import Environment
from pihim.render.simulate import LookAtPose, simulate_frame
from pihim.render.views import sky_overlap, sky_vs_sky_view
from pihim.sky.sun import NSTTF, parse_time, sun_position

TIME = "2021-05-13T16:00-06:00"
FRONT, BACK = "8W5", "9W5"
CAMERA = CameraModel(width_px=1224, height_px=1024, focal_length_mm=17.5)


@pytest.fixture(scope="module")
def scene():
    field = nsttf_like_field()
    sun = sun_position(NSTTF, parse_time(TIME))
    env = Environment.clear_sky(sun.vector)
    track = track_field(field, sun.vector, UFACET_AIM_POINT)
    i_f, i_b = field.index(FRONT), field.index(BACK)
    az = np.full(len(field.names), 180.0)
    el = np.full(len(field.names), 90.0)
    az[i_f], el[i_f] = track.drive.azimuth_deg[i_f], track.drive.elevation_deg[i_f]
    pose = track.with_drive(az, el)
    view = sky_vs_sky_view(pose, i_f, i_b, env, CAMERA, step_m=3.0, min_overlap_px=150.0)
    assert view is not None
    fixed = {field.names[i]: (180.0, 90.0) for i in range(len(field.names)) if i != i_f}
    sim = simulate_frame(field, TIME, camera=CAMERA, seed=0, canting_sigma_mrad=3.0, drive_deg=fixed,
                         pose_request=LookAtPose(tuple(view.camera_m), tuple(view.look_at_m)))
    return {"field": field, "pose": pose, "view": view, "sim": sim, "i_f": i_f, "i_b": i_b}


def test_the_view_is_the_predicted_sky_vs_sky_scene(scene):
    view, sim, i_f, i_b = scene["view"], scene["sim"], scene["i_f"], scene["i_b"]
    assert view.dolp_difference > 0.2 and view.overlap_px >= 150.0
    # the rendered (noise-free) frame shows what was predicted: both mirrors reflect sky across the top edge,
    # and their DoLP differs by more than 0.2 (the prediction is a mean along the edge, the render a region mean)
    r, lab = sim.rendered, sim.rendered.labels
    sky_mirror = (lab[..., 0] == MIRROR) & (lab[..., 3] == SKY) & ~r.supersampled
    d = dolp(r.s0.astype(float), r.s1, r.s2)
    ov = sky_overlap(scene["pose"], i_f, i_b, CAMERA, view.camera_m, look_at_m=view.look_at_m)
    centre = ov.edge_px[ov.inside].mean(axis=0)
    near = np.hypot(*(np.indices(lab.shape[:2])[::-1] - centre[:, None, None])) < 120
    front = d[sky_mirror & near & (lab[..., 1] == i_f)]
    back = d[sky_mirror & near & (lab[..., 1] == i_b)]
    assert front.size > 500 and back.size > 500
    assert abs(np.median(front) - np.median(back)) > 0.2
    assert abs(np.median(front) - np.median(back)) == pytest.approx(view.dolp_difference, abs=0.1)


def test_the_fixed_drives_are_rendered_and_logged(scene):
    sim, field = scene["sim"], scene["field"]
    logged = {h["name"]: (h["az_deg"], h["el_deg"]) for h in sim.log["heliostats"]}
    assert logged[BACK] == pytest.approx((180.0, 90.0))
    assert logged[FRONT][1] < 80.0  # the front tracks
    assert sim.truth["simulation"]["fixed_drive_deg"][BACK] == [180.0, 90.0]
    np.testing.assert_allclose(sim.true_field.normals[scene["i_b"]], [0.0, 0.0, 1.0], atol=1e-12)
    with pytest.raises(PihimInputError, match="elevation"):
        simulate_frame(field, TIME, camera=CameraModel(width_px=64, height_px=48),
                       pose_request=LookAtPose((0.0, -50.0, 20.0), (0.0, 0.0, 0.0)), drive_deg={BACK: (0.0, 95.0)})
    with pytest.raises(PihimInputError):
        simulate_frame(field, TIME, camera=CameraModel(width_px=64, height_px=48),
                       pose_request=LookAtPose((0.0, -50.0, 20.0), (0.0, 0.0, 0.0)), drive_deg={"99Z9": (0.0, 90.0)})


def test_the_mask_holds_exactly_the_sky_vs_sky_stretches(scene):
    lab, i_f = scene["sim"].rendered.labels, scene["i_f"]
    mask = sky_vs_sky_mask(lab, i_f, width_px=4)
    assert 0 < mask.sum() < 0.05 * mask.size
    kind, helio, end = lab[..., 0], lab[..., 1], lab[..., 3]
    own = (kind == MIRROR) & (helio == i_f) & (end == SKY)
    # every masked pixel is within 4 px of the front's sky reflection and of another surface showing sky
    ys, xs = np.nonzero(mask)
    pick = np.linspace(0, ys.size - 1, 200).astype(int)
    for y, x in zip(ys[pick], xs[pick]):
        win = (slice(max(y - 4, 0), y + 5), slice(max(x - 4, 0), x + 5))
        assert own[win].any()
        other = ((kind[win] == MIRROR) & (helio[win] != i_f) & (end[win] == SKY)) | (kind[win] == SKY)
        assert other.any()
    # the front's edges against the ground are not in it
    ground = kind == GROUND
    from scipy.ndimage import binary_dilation
    against_ground = binary_dilation(own, iterations=2) & binary_dilation(ground, iterations=2)
    far = against_ground & ~binary_dilation(mask, iterations=6)
    assert far.sum() > 0.9 * against_ground.sum()


def test_dolp_finds_the_sky_vs_sky_edges(scene):
    sim = scene["sim"]
    pim = polar_image(sim.raw, demosaic="full", bit_depth=12)
    maps = edge_maps(pim.s0, pim.dolp, pim.aop_deg, "canny")
    outlines = outlines_from_simulation(sim, FRONT)
    mask = sky_vs_sky_mask(sim.rendered.labels, scene["i_f"])
    lab = sim.rendered.labels
    dolp_res = edge_success(maps["DoLP"].edges, outlines, 2.0, 0.9, labels=lab, mask=mask)
    assert dolp_res.n_judged >= 2 and dolp_res.success, dolp_res.to_dict()
    # an empty edge map finds nothing; edges shifted off the true outline by 10 px fail too
    assert not edge_success(np.zeros_like(maps["DoLP"].edges), outlines, 2.0, 0.9, labels=lab, mask=mask).success
    shifted = np.roll(maps["DoLP"].edges, 10, axis=0)
    assert not edge_success(shifted, outlines, 2.0, 0.9, labels=lab, mask=mask).success


def test_mask_restricts_the_judged_edges(scene):
    sim = scene["sim"]
    outlines = outlines_from_simulation(sim, FRONT)
    lab = sim.rendered.labels
    edges = np.zeros(lab.shape[:2], bool)
    every = edge_success(edges, outlines, 2.0, labels=lab)
    none = edge_success(edges, outlines, 2.0, labels=lab, mask=np.zeros_like(edges))
    some = edge_success(edges, outlines, 2.0, labels=lab, mask=sky_vs_sky_mask(lab, scene["i_f"]))
    assert none.n_judged == 0 and not none.success
    assert 0 < some.n_judged < every.n_judged
    with pytest.raises(PihimInputError, match="mask"):
        edge_success(edges, outlines, 2.0, labels=lab, mask=np.zeros((3, 3), bool))
    assert isinstance(outlines, FacetOutlines)
    # the projected top edge of the front lies in the mask where it is over the back
    ov = sky_overlap(scene["pose"], scene["i_f"], scene["i_b"], CAMERA, scene["view"].camera_m,
                     look_at_m=scene["view"].look_at_m)
    assert np.allclose(ov.edge_px, project_points(CAMERA, sim.camera_pose,
                       scene["pose"].mirror_outline()[scene["i_f"]][0]
                       + np.linspace(0, 1, 41)[:, None] * (scene["pose"].mirror_outline()[scene["i_f"]][1]
                                                           - scene["pose"].mirror_outline()[scene["i_f"]][0])),
                       atol=1e-6)


def test_sky_vs_sky_mask_refuses_bad_input():
    with pytest.raises(PihimInputError):
        sky_vs_sky_mask(np.zeros((4, 4)), 0)
    with pytest.raises(PihimInputError):
        sky_vs_sky_mask(np.zeros((4, 4, 5), int), 0, width_px=0)
