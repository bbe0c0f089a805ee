"""Tests of :mod:`pihim.render.simulate`: a simulated inspection frame, its log and its ground truth.

Frames are small (the Triton's field of view at a few dozen to a few hundred
pixels) so that every render takes about a second.
"""

import json
import os
from pathlib import Path
from importlib import resources

import jsonschema
import numpy as np
import pytest
import tifffile

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose
from pihim.errors import PihimInputError
from pihim.field import (
    UFACET_AIM_POINT,
    canting_deviation,
    nsttf_like_field,
    rotation_from_drive,
    track_field,
)
from pihim.render.frame import RenderSettings
from pihim.render.paths import GROUND, MIRROR, SUN
from pihim.render.scene import FACET
from pihim.render.simulate import (
    SCHEMA_ID,
    LookAtPose,
    PairPose,
    WaypointPose,
    _logged_pose,
    simulate_frame,
    simulated_frame_paths,
    write_simulated_frame,
)
from pihim.sky.sun import NSTTF, parse_time, sun_position

SCHEMA = json.loads(resources.files("pihim").joinpath("schemas/simulated-frame.schema.json").read_text())
TIME = "2021-05-13T13:00-06:00"
FAST = RenderSettings(supersample=1)


def small_camera(width, height):
    """The Triton + 35 mm field of view with fewer pixels."""
    return CameraModel(width_px=width, height_px=height, focal_length_mm=35.0 * width / 2448)


@pytest.fixture(scope="module")
def field():
    return nsttf_like_field()


@pytest.fixture(scope="module")
def nominal(field):
    """The field as tracked (commanded) at TIME, computed independently of the simulation."""
    sun = sun_position(NSTTF, parse_time(TIME))
    return track_field(field, sun.vector, UFACET_AIM_POINT)


@pytest.fixture(scope="module")
def look_at_8e3(nominal, field):
    """A camera south of 8E3 looking at its mirror centre."""
    return LookAtPose((24.0, 75.0, 20.0), tuple(nominal.mirror_centres[field.index("8E3")]))


@pytest.fixture(scope="module")
def pair(field):
    """HUA 8E3 with 7E3 in its reflection, every error source on."""
    return simulate_frame(field, TIME, camera=small_camera(240, 200), pose_request=PairPose("8E3", "7E3"),
                          canting_sigma_mrad=1.5, tracking_sigma_mrad=1.0, gps_sigma_m=0.4,
                          attitude_sigma_deg=0.3, seed=11, settings=RenderSettings(supersample=2))


@pytest.fixture(scope="module")
def exact(field, look_at_8e3):
    """No error at all."""
    return simulate_frame(field, TIME, camera=small_camera(64, 48), pose_request=look_at_8e3, seed=5, settings=FAST)


# -- the pair: what the planner promises is in the picture ---------------------------


def test_pair_pose_shows_the_hua_with_the_target_in_its_reflection(pair, field):
    lab = pair.rendered.labels
    i_hua, i_tgt = field.index("8E3"), field.index("7E3")
    hua = (lab[..., 0] == MIRROR) & (lab[..., 1] == i_hua)
    assert hua.mean() > 0.3  # the HUA fills much of the frame
    assert (hua & (lab[..., 4] == i_tgt)).sum() > 0.2 * hua.sum()
    assert pair.log["hua"] == "8E3" and pair.log["target"] == "7E3"
    names = [h["name"] for h in pair.log["heliostats"]]
    assert {"8E3", "7E3"} <= set(names)
    assert names == [h["name"] for h in pair.truth["heliostats"]]
    # "in view" is exactly the heliostats the labels refer to
    idx = np.union1d(lab[..., 1].ravel(), lab[..., 4].ravel())
    assert names == [field.names[i] for i in idx if i >= 0]
    assert pair.truth["labels"]["heliostat_index"] == list(field.names)


def test_pair_pose_is_the_planned_capture_waypoint(pair, field):
    from pihim.planning.pipeline import build_plan

    plan = build_plan(field, parse_time(TIME), NSTTF, aim_point=UFACET_AIM_POINT, heliostats=["8E3"], shift=False,
                      facet_captures=False, route=False, facet_report=False)
    wps = [p.waypoints[q.waypoint_index] for p in plan.passes for q in p.predictions
           if (q.hua, q.target) == ("8E3", "7E3")]
    assert CameraPose.from_waypoint(wps[0]) == pair.camera_pose
    assert pair.truth["pose"]["position_m"] == pytest.approx([wps[0].x_m, wps[0].y_m, wps[0].z_m])


def test_exposure_is_chosen_over_every_pixel_not_seeing_the_sun(pair):
    lab = pair.rendered.labels
    assert pair.truth["simulation"]["exposure_pixels"] == "not-sun"
    exp = pair.log["sensor"]["exposure"]
    assert exp["percentile"] == 99.9 and exp["gain_dn"] > 0
    not_sun = (lab[..., 0] != SUN) & (lab[..., 3] != SUN)
    mirror = (lab[..., 0] == MIRROR) & (lab[..., 3] != SUN)
    raw = pair.raw.astype(float)
    assert pair.raw.dtype == np.uint16 and pair.raw.shape == (200, 240)
    # the bright end of the frame sits just under full scale (headroom 0.9): neither the sunlit
    # ground nor the brightest mirror region clips
    assert 0.6 * 4095 < np.percentile(raw[not_sun], 99.9) <= 4095
    assert np.percentile(raw[mirror], 99.9) < 4095
    assert np.mean(pair.raw == 4095) < 0.002


def test_exposure_pixels_option_sets_the_reference_region(field):
    kw = dict(camera=small_camera(240, 200), pose_request=PairPose("8E3", "7E3"), seed=3, settings=FAST)
    mirrors = simulate_frame(field, TIME, exposure_pixels="mirror-not-sun", **kw)
    every = simulate_frame(field, TIME, **kw)
    assert mirrors.truth["simulation"]["exposure_pixels"] == "mirror-not-sun"
    # each exposure puts the 99.9th percentile of its own pixels at 0.9 of full scale (noise-free)
    for sim, sel in ((mirrors, lambda lab: (lab[..., 0] == MIRROR) & (lab[..., 3] != SUN)),
                     (every, lambda lab: (lab[..., 0] != SUN) & (lab[..., 3] != SUN))):
        exp = sim.log["sensor"]["exposure"]
        m = sel(sim.rendered.labels)
        r = sim.rendered
        # the brightest of the four ideal micro-polarizers (0, 45, 90, 135 deg): 0.5 (S0 + S1 cos 2t + S2 sin 2t)
        brightest = 0.5 * np.max([r.s0 + r.s1, r.s0 + r.s2, r.s0 - r.s1, r.s0 - r.s2], axis=0)[m]
        assert exp["gain_dn"] * np.percentile(brightest, 99.9) == pytest.approx(0.9 * 4095, rel=0.02)
    ground = every.rendered.labels[..., 0] == GROUND
    assert np.all(every.raw[ground] < 4095)


# -- the log and the truth ----------------------------------------------------------


def test_zero_sigmas_log_equals_truth(exact):
    assert exact.logged_pose == exact.camera_pose
    assert exact.log["pose"] == exact.truth["pose"]
    for lh, th in zip(exact.log["heliostats"], exact.truth["heliostats"], strict=True):
        assert (lh["az_deg"], lh["el_deg"]) == (th["az_deg"], th["el_deg"])
        assert th["tracking_error_mrad"] == {"az": 0.0, "el": 0.0}
        assert all(f["az_mrad"] == 0.0 and f["el_mrad"] == 0.0 for f in th["facets"])


def test_logged_pose_differs_from_truth_within_the_sigmas(pair):
    log, true = pair.log["pose"], pair.truth["pose"]
    d = np.subtract(log["position_m"], true["position_m"])
    assert np.all(d != 0) and np.all(np.abs(d) < 5 * 0.4)
    for k in ("heading_deg", "pitch_deg", "roll_deg"):
        diff = (log[k] - true[k] + 180.0) % 360.0 - 180.0
        assert 0 < abs(diff) < 5 * 0.3
    assert log["pitch_deg"] == pair.log["gimbal"]["pitch_deg"]
    assert pair.log["gps_sigma_m"] == 0.4 and pair.log["attitude_sigma_deg"] == 0.3
    # the logged rotation is the logged angles' rotation
    rot = CameraPose.from_attitude(log["position_m"], log["heading_deg"], log["pitch_deg"], log["roll_deg"]).rotation
    np.testing.assert_allclose(log["rotation"], rot, atol=1e-12)


def test_logged_pose_noise_has_the_requested_spread():
    true = CameraPose.from_attitude((10.0, 50.0, 25.0), 200.0, -60.0, 3.0)
    rng = np.random.default_rng(0)
    pos, att = [], []
    for _ in range(2000):
        p, a = _logged_pose(true, 0.5, 0.2, rng)
        pos.append(p.position_m - true.position_m)
        att.append([a["heading_deg"] - 200.0, a["pitch_deg"] + 60.0, a["roll_deg"] - 3.0])
    assert np.std(pos, axis=0) == pytest.approx([0.5] * 3, rel=0.1)
    assert np.abs(np.mean(pos, axis=0)).max() < 0.05
    assert np.std(att, axis=0) == pytest.approx([0.2] * 3, rel=0.1)


def test_tracking_errors_are_true_minus_commanded(pair, nominal, field):
    errs = []
    for lh, th in zip(pair.log["heliostats"], pair.truth["heliostats"], strict=True):
        i = field.index(lh["name"])
        # the log holds the commanded angles: the nominal tracking
        assert lh["az_deg"] == pytest.approx(float(nominal.drive.azimuth_deg[i]), abs=1e-9)
        assert lh["el_deg"] == pytest.approx(float(nominal.drive.elevation_deg[i]), abs=1e-9)
        e = th["tracking_error_mrad"]
        d_az = (th["az_deg"] - lh["az_deg"] + 180.0) % 360.0 - 180.0
        assert np.radians(d_az) * 1e3 == pytest.approx(e["az"], abs=1e-6)
        assert np.radians(th["el_deg"] - lh["el_deg"]) * 1e3 == pytest.approx(e["el"], abs=1e-6)
        errs += [e["az"], e["el"]]
    assert np.all(np.abs(errs) < 5 * 1.0) and np.std(errs) > 0.2


def _scene_canting(sim, nominal, field):
    """Canting deviations recovered from the rendered scene's facet rectangles (independent of the draws).

    The true heliostat frames come from the true drive angles in ``truth``;
    each facet rectangle's normal is taken into that frame and compared with
    the design normal of the nominal tracking.
    """
    scene = sim.scene
    facet = np.asarray(scene.kind) == FACET
    normals = np.asarray(scene.bvh.normal)[facet]
    owner = np.asarray(scene.heliostat)[facet]
    number = np.asarray(scene.facet)[facet]
    out = {}
    for th in sim.truth["heliostats"]:
        i = field.index(th["name"])
        rot = rotation_from_drive(th["az_deg"], th["el_deg"])  # columns x, y, z in ENU
        sel = owner == i
        local = normals[sel] @ rot  # ENU -> heliostat frame
        order = np.argsort(number[sel])
        az, el = canting_deviation(nominal.facet_normals_local[i], local[order])
        out[th["name"]] = (az, el, th)
    return out


def test_truth_canting_is_what_the_scene_holds(pair, nominal, field):
    rec = _scene_canting(pair, nominal, field)
    assert len(rec) >= 2
    drawn = []
    for az, el, th in rec.values():
        assert [f["id"] for f in th["facets"]] == list(range(1, 26))
        np.testing.assert_allclose(az, [f["az_mrad"] for f in th["facets"]], atol=1e-5)
        np.testing.assert_allclose(el, [f["el_mrad"] for f in th["facets"]], atol=1e-5)
        drawn += [f["az_mrad"] for f in th["facets"]] + [f["el_mrad"] for f in th["facets"]]
    assert np.std(drawn) == pytest.approx(1.5, rel=0.35)


def test_zero_canting_sigma_gives_design_canting(exact, nominal, field):
    rec = _scene_canting(exact, nominal, field)
    assert rec
    for az, el, _ in rec.values():
        np.testing.assert_allclose(az, 0.0, atol=1e-6)
        np.testing.assert_allclose(el, 0.0, atol=1e-6)


# -- reproducibility ------------------------------------------------------------------


def test_same_seed_same_bytes_other_seed_other_noise(field, look_at_8e3, exact, tmp_path):
    kw = dict(camera=small_camera(64, 48), pose_request=look_at_8e3, canting_sigma_mrad=2.0,
              tracking_sigma_mrad=1.0, gps_sigma_m=0.5, attitude_sigma_deg=0.5, settings=FAST)
    a = simulate_frame(field, TIME, seed=3, **kw)
    b = simulate_frame(field, TIME, seed=3, **kw)
    c = simulate_frame(field, TIME, seed=4, **kw)
    assert a.raw.tobytes() == b.raw.tobytes()
    assert json.dumps(a.document()) == json.dumps(b.document())
    pa = write_simulated_frame(a, tmp_path / "a" / "frame.tiff")
    pb = write_simulated_frame(b, tmp_path / "b" / "frame.tiff")
    for key in pa:
        assert pa[key].read_bytes() == pb[key].read_bytes(), key
    assert a.raw.tobytes() != c.raw.tobytes()
    assert a.log["pose"] != c.log["pose"]
    assert a.truth["heliostats"][0]["facets"] != c.truth["heliostats"][0]["facets"]


# -- other pose requests --------------------------------------------------------------


def test_waypoint_pose_reads_a_plan_json(field, pair, tmp_path):
    t = pair.truth["pose"]
    wp = {"x_m": t["position_m"][0], "y_m": t["position_m"][1], "z_m": t["position_m"][2],
          "heading_deg": t["heading_deg"], "gimbal_pitch_deg": t["pitch_deg"], "capture": True, "hua": "8E3"}
    plan = {"schema": "pihim.plan/1",
            "passes": [{"waypoints": [dict(wp, capture=False), {**wp, "capture": True, "hua": "9E3"}],
                        "predictions": [{"hua": "9E3", "target": "8E3", "waypoint_index": 1}]},
                       {"waypoints": [{**wp, "capture": False, "hua": None}, wp],
                        "predictions": [{"hua": "8E3", "target": "7E3", "waypoint_index": 1}]}]}
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(plan))
    sim = simulate_frame(field, TIME, camera=small_camera(64, 54), pose_request=WaypointPose(path, 1), settings=FAST)
    assert sim.log["hua"] == "8E3" and sim.log["target"] == "7E3"
    np.testing.assert_allclose(sim.camera_pose.rotation, pair.camera_pose.rotation, atol=1e-9)
    np.testing.assert_allclose(sim.camera_pose.position_m, pair.camera_pose.position_m, atol=1e-12)
    with pytest.raises(PihimInputError, match="out of range"):
        simulate_frame(field, TIME, camera=small_camera(64, 54), pose_request=WaypointPose(path, 2))
    for key, name in (("hua", "99E99"), ("target", "8W99")):  # a plan for another field: refused, not logged
        other = json.loads(json.dumps(plan))
        if key == "hua":
            other["passes"][1]["waypoints"][1]["hua"] = other["passes"][1]["predictions"][0]["hua"] = name
        else:
            other["passes"][1]["predictions"][0]["target"] = name
        path.write_text(json.dumps(other))
        with pytest.raises(PihimInputError, match=f"waypoint 1 of .*plan.json: unknown heliostat '{name}'"):
            simulate_frame(field, TIME, camera=small_camera(64, 54), pose_request=WaypointPose(path, 1))


def test_pair_pose_falls_back_to_the_whole_field_plan(field):
    """9W7 alone gets a line of its own that shows another target; in the whole field's one-capture-per-HUA plan
    (tower aim) it shows 8W6 from a neighbour's line: that pair renders from that plan's capture point."""
    from pihim.planning.pipeline import build_plan
    from pihim.sky.sun import NSTTF, parse_time

    aim = field.default_aim_point
    kw = dict(aim_point=aim, shift=False, facet_captures=False, route=False, facet_report=False)
    alone = build_plan(field, parse_time(TIME), NSTTF, heliostats=["9W7"], **kw)
    assert ("9W7", "8W6") not in {(q.hua, q.target) for p in alone.passes for q in p.predictions}
    whole = build_plan(field, parse_time(TIME), NSTTF, **kw)
    (w,) = [p.waypoints[q.waypoint_index] for p in whole.passes if p.feasible for q in p.predictions
            if (q.hua, q.target) == ("9W7", "8W6")]
    sim = simulate_frame(field, TIME, aim_point=aim, camera=small_camera(64, 54),
                         pose_request=PairPose("9W7", "8W6"), settings=FAST)
    np.testing.assert_allclose(sim.camera_pose.position_m, (w.x_m, w.y_m, w.z_m), atol=1e-9)
    assert sim.log["hua"] == "9W7" and sim.log["target"] == "8W6"


def test_waypoint_pose_tracks_the_aim_point_its_plan_was_made_for(field, pair, tmp_path):
    t = pair.truth["pose"]
    wp = {"x_m": t["position_m"][0], "y_m": t["position_m"][1], "z_m": t["position_m"][2],
          "heading_deg": t["heading_deg"], "gimbal_pitch_deg": t["pitch_deg"], "capture": True, "hua": "8E3"}
    tower_aim = [0.0, 6.25, 63.55]
    path = tmp_path / "plan.json"
    path.write_text(json.dumps({"schema": "pihim.plan/1", "aim_point": tower_aim, "passes": [{"waypoints": [wp]}]}))
    sim = simulate_frame(field, TIME, camera=small_camera(64, 54), pose_request=WaypointPose(path, 0), settings=FAST)
    assert sim.log["aim_point_m"] == tower_aim  # the field tracks as the plan assumed
    drives = {h["name"]: h for h in sim.log["heliostats"]}
    default = {h["name"]: h for h in pair.log["heliostats"]}  # the pair was rendered at UFACET's aim point
    common = set(drives) & set(default)
    assert common and all(drives[n] != default[n] for n in common)
    given = simulate_frame(field, TIME, aim_point=UFACET_AIM_POINT, camera=small_camera(64, 54),
                           pose_request=WaypointPose(path, 0), settings=FAST)
    assert given.log["aim_point_m"] == list(UFACET_AIM_POINT)  # an explicit aim point wins
    path.write_text(json.dumps({"schema": "pihim.plan/1", "passes": [{"waypoints": [wp]}]}))
    old = simulate_frame(field, TIME, camera=small_camera(64, 54), pose_request=WaypointPose(path, 0), settings=FAST)
    assert old.log["aim_point_m"] == list(UFACET_AIM_POINT)  # a plan that does not say: UFACET's
    for bad in ([float("nan"), 1, 1], [1], "tower"):  # a plan that says it wrongly: refused, not UFACET's
        path.write_text(json.dumps({"schema": "pihim.plan/1", "aim_point": bad, "passes": [{"waypoints": [wp]}]}))
        with pytest.raises(PihimInputError, match="aim_point must be three finite numbers"):
            simulate_frame(field, TIME, camera=small_camera(64, 54), pose_request=WaypointPose(path, 0))


# -- refusals (all before rendering) ----------------------------------------------


@pytest.fixture(scope="module")
def inside_points(nominal, field):
    i = field.index("8E3")
    c, r = nominal.mirror_centres[i], nominal.rotations[i]
    return {
        "near the centre": c + 0.2 * r[:, 2],
        "in the mirror box": c + 2.0 * r[:, 0] + 1.5 * r[:, 1] + 0.05 * r[:, 2],
        "behind the mirror": c + 1.0 * r[:, 0] - 0.1 * r[:, 2],
    }


@pytest.mark.parametrize("where", ["near the centre", "in the mirror box", "behind the mirror"])
def test_camera_inside_a_heliostat_is_refused(field, inside_points, where):
    p = inside_points[where]
    with pytest.raises(PihimInputError, match="inside heliostat 8E3"):
        simulate_frame(field, TIME, camera=small_camera(64, 48), pose_request=LookAtPose(tuple(p), (0, 0, 0)))


@pytest.mark.parametrize(
    "kwargs, needle",
    [
        ({"pose_request": LookAtPose((24, 75, -3), (24, 94, 4))}, "below the ground"),
        ({"pose_request": LookAtPose((24, 75, 1e300), (24, 94, 4))}, "(24, 75, 1e+300) is more than 10 km"),
        ({"pose_request": LookAtPose((10_001, 0, 20), (24, 94, 4))}, "more than 10 km from the field origin"),
        ({"pose_request": LookAtPose((0, 0, 30), (0, 20, 30))}, "inside the tower"),
        ({"pose_request": LookAtPose((24, 75, 20), (24, 75, 20))}, "equals the camera position"),
        ({"pose_request": PairPose("8E3", "99W1")}, "unknown heliostat"),
        ({"pose_request": PairPose("8E3", "8E3")}, "must differ"),
        ({"pose_request": PairPose("8E3", "14W6")}, "target 14W6 is not visible in HUA 8E3 from any feasible pose"),
        ({"time": "2021-05-13T02:00-06:00"}, "below the horizon"),
        ({"time": "2021-05-13T13:00"}, "UTC offset"),
        ({"canting_sigma_mrad": -1.0}, "canting sigma"),
        ({"tracking_sigma_mrad": float("nan")}, "tracking sigma"),
        ({"gps_sigma_m": -0.1}, "GPS sigma"),
        ({"attitude_sigma_deg": float("inf")}, "attitude sigma"),
        ({"blur_sigma_px": -1}, "blur sigma"),
        ({"seed": -1}, "seed"),
        ({"seed": 1.5}, "seed"),
        ({"camera": small_camera(63, 48)}, "even"),
        ({"aim_point": (60, 8.8, -1)}, "above the ground"),
        ({"pose_request": "8E3"}, "pose_request"),
    ],
)
def test_bad_requests_are_one_line_errors(field, look_at_8e3, kwargs, needle):
    args = {"time": TIME, "camera": small_camera(64, 48), "pose_request": look_at_8e3, **kwargs}
    with pytest.raises(PihimInputError) as info:
        simulate_frame(field, args.pop("time"), **args)
    msg = str(info.value)
    assert needle.lower() in msg.lower() and "\n" not in msg


# -- files ----------------------------------------------------------------------------


def test_written_files_and_schema(pair, tmp_path):
    paths = write_simulated_frame(pair, tmp_path / "out" / "FRAME.tiff")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(
        ["FRAME.tiff", "FRAME.json", "FRAME.S0.tiff", "FRAME.DoLP.tiff", "FRAME.AoP.tiff", "FRAME.labels.tiff"])
    raw = tifffile.imread(paths["raw"])
    assert raw.dtype == np.uint16 and np.array_equal(raw, pair.raw)
    labels = tifffile.imread(paths["labels"])
    assert labels.dtype == np.int32 and np.array_equal(labels, pair.rendered.labels)
    s0 = tifffile.imread(paths["S0"])
    dolp = tifffile.imread(paths["DoLP"])
    aop = tifffile.imread(paths["AoP"])
    assert s0.dtype == dolp.dtype == aop.dtype == np.float32 and s0.shape == (200, 240)
    assert np.array_equal(s0, pair.rendered.s0)
    ok = np.isfinite(aop)
    assert ok.mean() > 0.99 and aop[ok].min() >= 0 and aop[ok].max() < 180
    assert np.nanmax(dolp) <= 1.0 + 1e-5
    doc = json.loads(paths["json"].read_text())
    assert doc["schema"] == SCHEMA_ID
    jsonschema.validate(doc, SCHEMA, cls=jsonschema.Draft202012Validator)
    assert CameraModel.from_dict(doc["log"]["camera"]) == small_camera(240, 200)
    assert doc["log"]["time"] == "2021-05-13T13:00:00-06:00"
    assert "seconds" not in json.dumps(doc["truth"]["render"])


def test_schema_rejects_a_truth_leak_into_the_log(pair):
    doc = json.loads(json.dumps(pair.document()))
    doc["log"]["heliostats"][0]["tracking_error_mrad"] = {"az": 0.0, "el": 0.0}
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(doc, SCHEMA, cls=jsonschema.Draft202012Validator)


def test_a_failed_write_leaves_nothing(pair, tmp_path, monkeypatch):
    import pihim.render.simulate as sim_mod

    real = tifffile.imwrite

    def failing(path, data, **kw):
        if ".labels." in str(path):
            raise OSError(28, "No space left on device")
        return real(path, data, **kw)

    monkeypatch.setattr(sim_mod.tifffile, "imwrite", failing)
    out = tmp_path / "o"
    with pytest.raises(OSError, match="cannot write .*no space left on the device"):
        write_simulated_frame(pair, out / "FRAME.tiff")
    assert list(out.iterdir()) == []


def test_temporaries_name_their_writer(pair, tmp_path, monkeypatch):
    """The frame's temporaries carry the writer's pid, so that a later run removes those a killed run left."""
    import pihim.render.simulate as sim_mod
    from pihim._atomic import is_stale_temporary

    seen = []
    real = tifffile.imwrite

    def spy(path, data, **kw):
        seen.append(Path(path))
        assert is_stale_temporary(Path(path)) is False  # this process is alive
        return real(path, data, **kw)

    monkeypatch.setattr(sim_mod.tifffile, "imwrite", spy)
    write_simulated_frame(pair, tmp_path / "FRAME.tiff")
    assert len(seen) == 5 and all(f"-{os.getpid()}-" in p.name for p in seen)


def test_output_names():
    p = simulated_frame_paths("d/x.tif")
    assert p["json"].as_posix() == "d/x.json" and p["labels"].as_posix() == "d/x.labels.tif"
    with pytest.raises(PihimInputError, match=r"\.tiff"):
        simulated_frame_paths("d/x.png")
