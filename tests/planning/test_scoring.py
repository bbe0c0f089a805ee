"""Tests of pihim.planning.scoring: image predictions, paper thresholds and pass shifts.

Passes are built by hand here (UFACET camera positions from the law of
reflection) so that the tests do not depend on the planner's choices.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from pihim.errors import PihimInputError
from pihim.field import (
    UFACET_AIM_POINT,
    heliostat_rotation,
    nsttf_like_field,
    track_field,
)
from pihim.field.geodesy import enu_to_geodetic
from pihim.field.kinematics import facet_centres
from pihim.planning.model import ScanPass, Waypoint
from pihim.planning.scoring import (
    GroundTable,
    ScoringModel,
    ShiftSearch,
    build_scene,
    coverage,
    images_text,
    min_safe_altitude_m,
    predict_images,
    score_passes,
)
from pihim.planning.ufacet import first_mirror_hits
from pihim.polarimetry.frames import change_reference, normalize
from pihim.polarimetry.stokes import aop_deg, dolp
from pihim.scenarios import ground_vs_ground, mirror_reflection, sky_vs_sky
from pihim.sky.model import with_horizontal_irradiance
from pihim.sky.sun import NSTTF, direction_from_angles

SUN = direction_from_angles(40.0, 110.0)  # mid-morning at the NSTTF in May
AIM = np.array(UFACET_AIM_POINT)
PAIRS = (("8E3", "7E3"), ("9E3", "8E3"), ("10E3", "9E3"), ("8E5", "7E5"), ("9E5", "8E5"), ("8W3", "7W3"),
         ("9W3", "8W3"), ("10W3", "9W3"), ("11E2", "10E2"), ("12W6", "11W6"))


@pytest.fixture(scope="module")
def field():
    return nsttf_like_field()


@pytest.fixture(scope="module")
def pose(field):
    return track_field(field, SUN, AIM)


def ufacet_camera(pose, hua: int, target: int, altitude: float) -> np.ndarray:
    """Camera at ``altitude`` on the ray from the HUA centre whose reflection points at the target centre."""
    c_h, n_h = pose.mirror_centres[hua], pose.normals[hua]
    u = normalize(pose.mirror_centres[target] - c_h)
    w = 2.0 * np.dot(u, n_h) * n_h - u
    assert w[2] > 0.05
    return c_h + (altitude - c_h[2]) / w[2] * w


def waypoint(xyz, look_at, hua=None, capture=True, kind="scan") -> Waypoint:
    lat, lon, h = enu_to_geodetic(xyz, NSTTF)
    d = np.asarray(look_at) - xyz
    heading = math.degrees(math.atan2(d[0], d[1])) % 360.0
    pitch = math.degrees(math.atan2(d[2], math.hypot(d[0], d[1])))
    return Waypoint(float(xyz[0]), float(xyz[1]), float(xyz[2]), float(lat), float(lon), float(h), heading, pitch,
                    5.0, kind=kind, capture=capture, hua=hua)


def hand_passes(field, pose, altitude: float = 16.0, pairs=PAIRS, per_pass: int = 3) -> tuple[ScanPass, ...]:
    """One capture per pair, ``per_pass`` pairs per pass, with a lead-in waypoint."""
    passes = []
    for k in range(0, len(pairs), per_pass):
        chunk = pairs[k : k + per_pass]
        wps = []
        for hua, tgt in chunk:
            h, t = field.index(hua), field.index(tgt)
            cam = ufacet_camera(pose, h, t, altitude)
            wps.append(waypoint(cam, pose.mirror_centres[h], hua=hua))
        first = np.array([wps[0].x_m, wps[0].y_m - 10.0, altitude])
        lead = waypoint(first, first + [0.0, 1.0, -1.0], capture=False, kind="lead_in")
        passes.append(ScanPass(index=len(passes), azimuth_deg=0.0, altitude_m=altitude, gimbal_pitch_deg=-45.0,
                               pairs=tuple(chunk), waypoints=(lead, *wps)))
    return tuple(passes)


def with_normal(pose, i: int, normal) -> object:
    """The pose with heliostat ``i`` turned to ``normal`` (e.g. face up, as in the paper's sky-vs-sky test)."""
    n = normalize(np.asarray(normal, float))
    normals = pose.normals.copy()
    normals[i] = n
    spec = pose.field.spec
    centres = pose.field.pivots + spec.pivot_offset_m * normals
    rot = heliostat_rotation(normals)
    return dataclasses.replace(pose, normals=normals, mirror_centres=centres, rotations=rot,
                               facet_normals=pose.facet_normals_local @ np.swapaxes(rot, -1, -2),
                               facet_centres=facet_centres(rot, centres, spec.facet_centroids))


def nearest_facet_normal(pose, i: int, point) -> np.ndarray:
    local = pose.rotations[i].T @ (np.asarray(point) - pose.mirror_centres[i])
    k = np.argmin(np.sum((pose.field.spec.facet_centroids[:, :2] - local[:2]) ** 2, axis=1))
    return pose.facet_normals[i, k]


def images(field, pose, altitude=16.0, pairs=PAIRS):
    cams = np.array([ufacet_camera(pose, field.index(h), field.index(t), altitude) for h, t in pairs])
    return cams, field.indices([h for h, _ in pairs]), field.indices([t for _, t in pairs])


# --------------------------------------------------------------------------- predictions vs scenarios


@pytest.fixture(scope="module")
def direct(field, pose):
    """Predictions with the ground model evaluated directly (no table)."""
    scene = build_scene(pose, SUN, ScoringModel(ground_table_size=None))
    cams, h, t = images(field, pose)
    return scene, cams, h, t, predict_images(scene, cams, h, t)


def test_ground_vs_ground_matches_scenarios(pose, direct):
    scene, cams, h, _, pred = direct
    outline = pose.mirror_outline()
    checked = 0
    for i in range(len(cams)):
        bottom = 0.5 * (outline[h[i], 2] + outline[h[i], 3])
        np.testing.assert_allclose(pred.bottom_point[i], bottom, atol=1e-9)
        if not np.all(np.isfinite(pred.ground_point[i])):
            continue
        # the real ground seen past the lower edge: on the line of sight, on the ground plane under the HUA
        v = normalize(bottom - cams[i])
        gp = pred.ground_point[i]
        assert gp[2] == pytest.approx(pose.field.ground_z[h[i]], abs=1e-9)
        assert np.linalg.norm(np.cross(gp - cams[i], v)) < 1e-6 and np.dot(gp - bottom, v) > 0
        ref = ground_vs_ground(cams[i], bottom, nearest_facet_normal(pose, h[i], bottom), SUN, scene.sky,
                               scene.model.mirror, scene.model.ground, ground_point=gp)
        arises = bool(ref.mirror.facing and not ref.mirror.shows_sky)
        assert pred.ground_arises[i] == arises
        if arises:
            checked += 1
            assert pred.ground_aop_difference_deg[i] == pytest.approx(float(ref.aop_difference_deg), abs=1e-9)
            assert pred.ground_aop_raw_difference_deg[i] == pytest.approx(float(ref.aop_raw_difference_deg), abs=1e-9)
            assert pred.hua_ground_dolp[i] == pytest.approx(float(ref.mirror.dolp), abs=1e-12)
            assert pred.ground_ok[i] == bool(ref.usable)
    assert checked >= 3


def test_sky_vs_sky_matches_scenarios(pose, direct):
    scene, cams, h, _, pred = direct
    have = np.flatnonzero(pred.partner >= 0)
    assert len(have) >= 2
    for i in have:
        p = pred.partner[i]
        ph, pp = pred.hua_point[i], pred.partner_point[i]
        # both points on their mirror planes, inside the outlines, on one line of sight from the camera
        for idx, pt in ((h[i], ph), (p, pp)):
            local = pose.rotations[idx].T @ (pt - pose.mirror_centres[idx])
            assert abs(local[2]) < 1e-9
            assert abs(local[0]) <= pose.field.spec.mirror_half_width_m + 1e-9
            assert abs(local[1]) <= pose.field.spec.mirror_half_height_m + 1e-9
        assert np.linalg.norm(np.cross(ph - cams[i], pp - cams[i])) < 1e-6 * np.linalg.norm(ph - cams[i]) ** 2
        hua_front = np.linalg.norm(ph - cams[i]) <= np.linalg.norm(pp - cams[i])
        assert pred.hua_is_front[i] == hua_front
        f, b = ((ph, h[i]), (pp, p)) if hua_front else ((pp, p), (ph, h[i]))
        ref = sky_vs_sky(cams[i], f[0], nearest_facet_normal(pose, f[1], f[0]), b[0],
                         nearest_facet_normal(pose, b[1], b[0]), SUN, scene.sky, scene.model.mirror)
        if np.isfinite(ref.dolp_difference):
            assert pred.sky_dolp_difference[i] == pytest.approx(float(ref.dolp_difference), abs=1e-12)
            assert pred.sky_front_dolp[i] == pytest.approx(float(ref.front.dolp), abs=1e-12)
            assert pred.sky_back_dolp[i] == pytest.approx(float(ref.back.dolp), abs=1e-12)
        else:
            assert np.isnan(pred.sky_dolp_difference[i])
        assert pred.sky_ok[i] == bool(ref.usable)


def test_centre_dolp_matches_mirror_reflection(pose, direct):
    scene, cams, h, _, pred = direct
    for i in (0, 3, 7):
        c = pose.mirror_centres[h[i]]
        ref = mirror_reflection(cams[i], c, nearest_facet_normal(pose, h[i], c), SUN, scene.sky,
                                scene.model.mirror, ground=scene.model.ground)
        assert pred.centre_dolp[i] == pytest.approx(float(ref.dolp), abs=1e-12)


def test_ufacet_cameras_see_the_target_back(direct):
    *_, pred = direct
    # the camera positions are built so that the HUA centre reflects the target centre
    np.testing.assert_allclose(pred.target_hit_extent, 0.0, atol=1e-6)
    assert pred.target_hit.all()


def test_ground_table_close_to_direct_model(pose):
    scene = build_scene(pose, SUN)
    assert isinstance(scene.ground, GroundTable)
    rng = np.random.default_rng(3)
    v = normalize(rng.normal(size=(3000, 3)) * [1.0, 1.0, 0.5] + [0.0, 0.0, 1.0])
    v = v[v[:, 2] > math.sin(math.radians(10.0))]
    s_t, _ = scene.ground.stokes(v, SUN)
    s_d, _ = scene.model.ground.stokes(v, SUN, scene.sky)
    d_ref = dolp(s_d[:, 0], s_d[:, 1], s_d[:, 2])
    ok = d_ref > 0.05
    da = np.abs((aop_deg(s_t[:, 1], s_t[:, 2]) - aop_deg(s_d[:, 1], s_d[:, 2]) + 90.0) % 180.0 - 90.0)[ok]
    assert np.percentile(da, 99) < 1.0 and da.max() < 3.0
    assert np.max(np.abs(dolp(s_t[:, 0], s_t[:, 1], s_t[:, 2]) - d_ref)) < 0.02
    with pytest.raises(PihimInputError, match="another sun"):
        scene.ground.stokes(v, direction_from_angles(30.0, 200.0))


def test_ground_table_evaluates_the_nodes_queries_need_with_the_values_of_a_full_table(pose):
    scene = build_scene(pose, SUN)
    ground = GroundTable(scene.model.ground, scene.sky, SUN, size=17, sky_table_size=33)
    full = GroundTable(scene.model.ground, scene.sky, SUN, size=17, sky_table_size=33)
    rng = np.random.default_rng(5)
    v = normalize(rng.normal(size=(600, 3)) * [1.0, 1.0, 0.4] + [0.0, 0.0, 0.6])  # some below the horizon
    # a few narrow cones of views, in any order, as a plan's images look
    cones = [normalize(v[:40] * 0.05 + c) for c in ([0.3, -0.5, 0.8], [-0.6, 0.1, 0.5], [0.0, 0.0, 1.0])]
    parts = [ground.stokes(c, SUN)[0] for c in cones]
    assert 0 < ground.evaluated.sum() < 0.5 * ground.evaluated.size
    # the whole hemisphere: every node evaluated, at once
    x = np.linspace(-1.0, 1.0, 101)
    xx, yy = np.meshgrid(x, x)
    inside = xx**2 + yy**2 < 1.0
    hemi = np.stack([xx[inside], yy[inside], np.sqrt(1.0 - xx[inside] ** 2 - yy[inside] ** 2)], axis=-1)
    full.stokes(hemi, SUN)
    assert full.evaluated.sum() > 0.75 * full.evaluated.size  # all but corners no view above the horizon needs
    assert np.all(full.evaluated[ground.evaluated])
    for c, part in zip(cones, parts, strict=True):  # the same values whatever was asked before
        np.testing.assert_array_equal(part, full.stokes(c, SUN)[0])
    np.testing.assert_array_equal(ground.stokes(v, SUN)[0], full.stokes(v, SUN)[0])
    assert np.all(ground.stokes(v[v[:, 2] <= 0.0], SUN)[0] == 0.0)
    # each evaluated node holds the model's value at its direction (Lambert azimuthal node, frame e_T)
    x = np.linspace(-math.sqrt(2.0), math.sqrt(2.0), 17)
    gx, gy = np.meshgrid(x, x, indexing="ij")
    gx, gy = gx[full.evaluated], gy[full.evaluated]
    r2 = np.minimum(gx**2 + gy**2, 2.0)
    vz = np.maximum(1.0 - 0.5 * r2, 1e-3)
    k = np.sqrt((1.0 - vz**2) / np.maximum(r2, 1e-300))
    nodes = normalize(np.stack([gx * k, gy * k, vz], axis=-1))
    s_model, e_model = scene.model.ground.stokes(nodes, SUN, scene.sky, sky_table_size=33)
    f = nodes[:, 0] / (1.0 + nodes[:, 2])
    e_t = np.column_stack([1.0 - f * nodes[:, 0], -f * nodes[:, 1], -f * nodes[:, 2] - f])
    np.testing.assert_allclose(full.table[full.evaluated], change_reference(s_model, nodes, e_model, e_t),
                               rtol=1e-9, atol=1e-12 * np.max(s_model[:, 0]))


def test_table_predictions_close_to_direct(field, pose, direct):
    *_, ref = direct
    cams, h, t = images(field, pose)
    pred = predict_images(build_scene(pose, SUN), cams, h, t)
    both = np.isfinite(ref.ground_aop_difference_deg)
    np.testing.assert_array_equal(np.isfinite(pred.ground_aop_difference_deg), both)
    np.testing.assert_allclose(pred.ground_aop_difference_deg[both], ref.ground_aop_difference_deg[both], atol=2.0)
    np.testing.assert_allclose(pred.sky_dolp_difference, ref.sky_dolp_difference, atol=1e-12)  # no ground involved


# --------------------------------------------------------------------------- paper thresholds


def test_flags_follow_paper_thresholds(field, pose):
    # one neighbour face up (the paper's sky-vs-sky test): large DoLP differences occur
    posed = with_normal(pose, field.index("9E3"), [0.0, 0.0, 1.0])
    scene = build_scene(posed, SUN)
    c = posed.mirror_centres[field.index("8E3")]
    rng = np.random.default_rng(0)
    cams = c + np.column_stack([rng.uniform(-15, 15, 300), rng.uniform(-30, 0, 300), rng.uniform(10, 25, 300)])
    pred = predict_images(scene, cams, np.full(300, field.index("8E3")), np.full(300, field.index("7E3")))
    d = pred.sky_dolp_difference
    fin = np.isfinite(d)
    assert np.array_equal(pred.sky_ok, fin & (np.nan_to_num(d) > 0.2))
    g = pred.ground_aop_difference_deg
    assert np.array_equal(pred.ground_ok, np.isfinite(g) & (np.nan_to_num(g) > 50.0))
    assert np.array_equal(pred.reflection_ok, np.nan_to_num(pred.reflection_dolp) > 0.2)
    assert np.array_equal(pred.usable, pred.reflection_ok & (pred.sky_ok | pred.ground_ok))
    # both outcomes of each test occur here
    assert pred.sky_ok.any() and (fin & ~pred.sky_ok).any()
    assert pred.ground_ok.any() and (np.isfinite(g) & ~pred.ground_ok).any()
    # the reflection DoLP is the HUA's side of a usable edge when there is one
    sky_u = pred.sky_ok & ~pred.ground_ok
    np.testing.assert_allclose(pred.reflection_dolp[sky_u], pred.hua_sky_dolp[sky_u])
    grd_u = pred.ground_ok & ~pred.sky_ok
    np.testing.assert_allclose(pred.reflection_dolp[grd_u], pred.hua_ground_dolp[grd_u])
    none = ~np.isfinite(pred.hua_sky_dolp) & ~np.isfinite(pred.hua_ground_dolp)
    np.testing.assert_allclose(pred.reflection_dolp[none], pred.centre_dolp[none])


def test_pair_predictions_records(field, pose):
    passes = hand_passes(field, pose)
    scored = score_passes(passes, pose, SUN, search=None)
    for sp, orig in zip(scored, passes, strict=True):
        assert sp.waypoints == orig.waypoints and sp.shift is None
        captures = [i for i, w in enumerate(sp.waypoints) if w.capture]
        assert [p.waypoint_index for p in sp.predictions] == captures
        for pr, (hua, tgt) in zip(sp.predictions, sp.pairs, strict=True):
            assert (pr.hua, pr.target) == (hua, tgt)
            assert pr.sky_vs_sky_ok == (pr.sky_dolp_difference is not None and pr.sky_dolp_difference > 0.2)
            assert pr.ground_vs_ground_ok == (pr.ground_aop_difference_deg is not None
                                              and pr.ground_aop_difference_deg > 50.0)
            assert pr.reflection_dolp_ok == (pr.reflection_dolp is not None and pr.reflection_dolp > 0.2)
            if pr.ground_aop_difference_deg is not None:
                assert 0.0 <= pr.ground_aop_difference_deg <= 90.0
                assert 0.0 <= pr.ground_aop_raw_difference_deg < 180.0
        assert 0.0 <= sp.usable_fraction <= 1.0
    cov = coverage(scored, len(field))
    assert cov["planned"] == pytest.approx(len(PAIRS) / len(field))
    assert cov["either"] <= cov["planned"] and max(cov["sky"], cov["ground"]) <= cov["either"]
    with_reflection = {pr.hua for sp in scored for pr in sp.predictions if pr.reflection_dolp_ok}
    assert cov["reflection"] == pytest.approx(len(with_reflection) / len(field))
    assert cov["either"] <= cov["reflection"] <= cov["planned"]


def test_images_text_separates_canting_from_contrast_edges():
    summary = {"images": 534, "reflection_images": 530, "usable_images": 0,
               "coverage": {"planned": 0.9, "reflection": 0.88, "either": 0.0}}
    text = images_text(summary)
    assert "534 captures, 530 showing the target's reflection with DoLP > 0.2" in text
    assert "0 also an outline edge" in text and "none at this hour" in text
    assert "imaged 90 %, with the reflection 88 %, with a contrast edge 0 %" in text
    assert "none at this hour" not in images_text({**summary, "usable_images": 3})


def test_capture_of_unknown_pair_is_refused(field, pose):
    sp = hand_passes(field, pose)[0]
    bad = dataclasses.replace(sp, pairs=sp.pairs[1:])
    with pytest.raises(PihimInputError, match="none of the pass's pairs"):
        score_passes([bad], pose, SUN, search=None)


def test_empty_and_no_capture_passes(field, pose):
    sp = hand_passes(field, pose)[0]
    idle = dataclasses.replace(sp, waypoints=tuple(dataclasses.replace(w, capture=False) for w in sp.waypoints))
    out = score_passes([idle], pose, SUN)
    assert out[0].predictions == () and out[0].usable_fraction == 0.0 and out[0].shift is None
    assert score_passes([], pose, SUN) == ()


# --------------------------------------------------------------------------- shifts


@pytest.fixture(scope="module")
def shifted(field):
    """A mid-afternoon pose where some hand-built passes gain from a shift (found once, deterministic)."""
    sun = direction_from_angles(25.0, 200.0)
    posed = track_field(field, sun, AIM)
    pairs = tuple((f"{r}{s}{c}", f"{r - 1}{s}{c}") for r in range(6, 14) for s in "EW" for c in (1, 3, 5, 7))
    passes = hand_passes(field, posed, altitude=17.0, pairs=pairs, per_pass=4)
    search = ShiftSearch(max_altitude_m=30.0)
    return sun, posed, passes, search, score_passes(passes, posed, sun, search=search, aim_point=AIM, origin=NSTTF)


def test_shift_only_when_it_gains_and_stays_safe(shifted):
    sun, posed, passes, search, out = shifted
    nominal = score_passes(passes, posed, sun, search=None)
    lo, hi = min_safe_altitude_m(posed), search.max_altitude_m
    n_shifted = 0
    for sp, nom, orig in zip(out, nominal, passes, strict=True):
        if sp.shift is None:
            assert sp.waypoints == orig.waypoints and sp.predictions == nom.predictions
            continue
        n_shifted += 1
        s = sp.shift
        assert s.usable_fraction_before == pytest.approx(nom.usable_fraction)
        assert s.usable_fraction_after == pytest.approx(sp.usable_fraction)
        assert s.usable_fraction_after > s.usable_fraction_before
        assert all(lo - 1e-9 <= w.z_m <= hi + 1e-9 for w in sp.waypoints)
        assert sp.altitude_m == pytest.approx(orig.altitude_m + s.altitude_delta_m)
        assert s.altitude_delta_m in search.altitude_deltas_m and s.lateral_offset_m in search.lateral_offsets_m
        assert s.gaze_delta_deg in search.gaze_deltas_deg
    assert n_shifted >= 1


def test_scoring_in_batches_gives_the_same_plan(shifted):
    sun, posed, passes, search, out = shifted
    n_images = sum(w.capture for p in passes for w in p.waypoints)
    assert len(passes) > 4 and n_images > 10
    batched = score_passes(passes, posed, sun, search=search, aim_point=AIM, origin=NSTTF, batch_images=5)
    assert batched == out  # passes are independent: the memory bound does not change the result
    with pytest.raises(PihimInputError, match="batch_images"):
        score_passes(passes, posed, sun, batch_images=0)


def test_shifted_predictions_are_recomputed_at_the_new_positions(field, shifted):
    sun, posed, passes, search, out = shifted
    scene = build_scene(posed, sun)
    for sp, orig in zip(out, passes, strict=True):
        if sp.shift is None:
            continue
        caps = [w for w in sp.waypoints if w.capture]
        cams = np.array([(w.x_m, w.y_m, w.z_m) for w in caps])
        h = field.indices([w.hua for w in caps])
        t = field.indices([tg for _, tg in sp.pairs])
        pred = predict_images(scene, cams, h, t)
        assert [p.usable for p in sp.predictions] == pred.usable.tolist()
        assert np.all(pred.target_hit_extent <= search.target_outline_fraction + 1e-9)  # UFACET kept
        # no new blocking of the sight line to the HUA
        cams0 = np.array([(w.x_m, w.y_m, w.z_m) for w in orig.waypoints if w.capture])
        c_h = posed.mirror_centres[h]
        back = 1e-3 * normalize(c_h - cams)
        new_hits = first_mirror_hits(posed, cams, c_h - back, exclude=h)
        old_hits = first_mirror_hits(posed, cams0, c_h - 1e-3 * normalize(c_h - cams0), exclude=h)
        assert np.all((new_hits < 0) | (old_hits >= 0))
        # geometry: lateral offset perpendicular to travel (azimuth 0 -> East), re-aimed at the HUA
        lead, lead0 = sp.waypoints[0], orig.waypoints[0]
        assert lead.x_m - lead0.x_m == pytest.approx(sp.shift.lateral_offset_m, abs=1e-9)
        assert lead.y_m == pytest.approx(lead0.y_m, abs=1e-9)
        assert (lead.heading_deg, lead.gimbal_pitch_deg) == (lead0.heading_deg, lead0.gimbal_pitch_deg)
        for w in caps:
            c = posed.mirror_centres[field.index(w.hua)]
            d = c - np.array([w.x_m, w.y_m, w.z_m])
            assert w.heading_deg == pytest.approx(math.degrees(math.atan2(d[0], d[1])) % 360.0, abs=1e-6)
            assert w.gimbal_pitch_deg == pytest.approx(math.degrees(math.atan2(d[2], math.hypot(d[0], d[1]))),
                                                       abs=1e-6)
            lat, lon, hgt = (float(v) for v in enu_to_geodetic([w.x_m, w.y_m, w.z_m], NSTTF))
            assert (w.latitude_deg, w.longitude_deg, w.height_m) == pytest.approx((lat, lon, hgt), abs=1e-9)


def test_no_shift_outside_altitude_limits(shifted):
    sun, posed, passes, _, _ = shifted
    # only upward moves offered, but the ceiling is the nominal altitude: nothing can move
    search = ShiftSearch(altitude_deltas_m=(0.0, 3.0), lateral_offsets_m=(0.0,), gaze_deltas_deg=(0.0,),
                         max_altitude_m=17.0)
    out = score_passes(passes, posed, sun, search=search)
    assert all(sp.shift is None for sp in out)
    assert all(w.z_m <= 17.0 + 1e-9 for sp in out for w in sp.waypoints)


def test_gaze_slide_changes_the_line_of_sight_elevation(shifted, field):
    sun, posed, passes, _, _ = shifted
    search = ShiftSearch(altitude_deltas_m=(0.0,), lateral_offsets_m=(0.0,), gaze_deltas_deg=(0.0, -4.0),
                         max_altitude_m=30.0, min_framing=0.0)
    out = score_passes(passes, posed, sun, search=search)
    assert any(sp.shift is not None for sp in out)
    for sp, orig in zip(out, passes, strict=True):
        if sp.shift is None:
            continue
        assert sp.shift.gaze_delta_deg == -4.0
        for w, w0 in zip(sp.waypoints, orig.waypoints, strict=True):
            if not w.capture:
                assert (w.x_m, w.y_m, w.z_m) == (w0.x_m, w0.y_m, w0.z_m)
                continue
            c = posed.mirror_centres[field.index(w.hua)]

            def elev(x, y, z, c=c):
                return math.degrees(math.atan2(z - c[2], math.hypot(x - c[0], y - c[1])))

            assert elev(w.x_m, w.y_m, w.z_m) - elev(w0.x_m, w0.y_m, w0.z_m) == pytest.approx(-4.0, abs=1e-6)
            assert w.x_m == pytest.approx(w0.x_m, abs=1e-9) and w.z_m == pytest.approx(w0.z_m)  # along track only


def test_shift_search_validation():
    with pytest.raises(PihimInputError):
        ShiftSearch(altitude_deltas_m=())
    with pytest.raises(PihimInputError):
        ShiftSearch(gaze_deltas_deg=(60.0,))
    with pytest.raises(PihimInputError):
        ShiftSearch(min_altitude_m=30.0, max_altitude_m=20.0)
    assert len(ShiftSearch().candidates()) == 4 * 3 * 3 - 1
    with pytest.raises(PihimInputError):
        ScoringModel(ground_table_size=3)


def test_scene_refuses_night_and_other_pose(field, pose):
    with pytest.raises(PihimInputError, match="below the horizon"):
        build_scene(pose, [0.0, 0.5, -0.5])
    other = track_field(field, direction_from_angles(30.0, 200.0), AIM)
    scene = build_scene(other, direction_from_angles(30.0, 200.0))
    with pytest.raises(PihimInputError, match="another FieldPose"):
        score_passes(hand_passes(field, pose), pose, SUN, scene=scene)


def test_sky_scaled_to_irradiance(pose):
    scene = build_scene(pose, SUN, ScoringModel(sky_irradiance_w_m2=80.0))
    expected = with_horizontal_irradiance(scene.model.sky, SUN, 80.0)
    assert scene.sky.scale == pytest.approx(expected.scale)


def test_planner_passes_are_scored(field, pose):
    from pihim.planning.ufacet import plan_passes

    passes = plan_passes(field, pose, aim_point=AIM, origin=NSTTF)
    out = score_passes(passes, pose, SUN, aim_point=AIM, origin=NSTTF)
    for sp, orig in zip(out, passes, strict=True):
        caps = [i for i, w in enumerate(orig.waypoints) if w.capture and w.hua]
        assert [p.waypoint_index for p in sp.predictions] == caps
        if len(caps) == len(orig.pairs):  # the planner's contract: the k-th capture images pairs[k]
            assert [(p.hua, p.target) for p in sp.predictions] == list(orig.pairs)
        if sp.shift is not None:
            assert sp.shift.usable_fraction_after > sp.shift.usable_fraction_before
    assert sum(len(sp.predictions) for sp in out) > 100


def test_beam_index_keeps_every_clearance_that_matters():
    """The k-d tree over beam directions gives the exact clearance of every beam within its reach (the shift
    test compares clearances with min(nominal, beam_clearance_m) only) and +inf beyond it."""
    from pihim.planning.scoring import _beam_margin, _BeamIndex

    rng = np.random.default_rng(11)
    r = rng.uniform(100.0, 900.0, 3000)
    a = rng.uniform(0.0, 2 * np.pi, 3000)
    centres = np.c_[r * np.sin(a), r * np.cos(a), np.full(3000, 5.0)]
    aim = np.array([0.0, 0.0, 195.0])
    radius, clearance = 3.4, 2.0
    idx = _BeamIndex(centres, aim, radius, clearance + radius)
    pts = np.c_[rng.uniform(-900, 900, (400, 2)), rng.uniform(10.0, 40.0, 400)]
    pts[:50] = centres[:50] + np.array([0.5, -0.3, 2.0])  # right on top of some beams
    exact = _beam_margin(pts, centres, aim, radius)
    fast = idx.margin(pts)
    close = exact < clearance + 1e-9
    assert close.sum() >= 50 and (~close).sum() > 100
    assert np.allclose(fast[close], exact[close])
    assert np.array_equal(np.minimum(fast, clearance), np.minimum(exact, clearance))


def test_scoring_defaults_to_the_second_surface_mirror():
    """Pinned convention: plans are scored with second-surface silvered glass unless told otherwise."""
    from pihim.surfaces.mirror import SecondSurfaceMirror

    mirror = ScoringModel().mirror
    assert isinstance(mirror, SecondSurfaceMirror)
    assert float(mirror.mueller(1.0)[0, 0]) == pytest.approx(0.9680, abs=5e-4)  # glass + silver at 550 nm


def test_min_safe_altitude_is_the_planners_and_refuses_a_margin_under_5_m(pose):
    """A margin of -50 m gave an altitude below the mirrors; ufacet.minimum_safe_altitude refused it."""
    from pihim.planning.ufacet import minimum_safe_altitude

    assert min_safe_altitude_m(pose) == minimum_safe_altitude(pose)[0]
    with pytest.raises(PihimInputError, match="safety_margin_m must be at least 5 m"):
        min_safe_altitude_m(pose, -50.0)


def test_shift_setup_is_built_once_per_scene_and_follows_its_inputs(pose):
    """The shift search's lowest altitude and beam index are kept per scene: the same objects for the same aim
    point and clearance; a new index for another aim point, even one passed in the same (edited) array, whose
    edits never reach the index already kept."""
    from pihim.planning.scoring import _shift_setup

    scene = build_scene(pose, SUN)
    search = ShiftSearch()
    aim = AIM.astype(float)
    alt, a1, b1 = _shift_setup(scene, search, aim)
    assert alt == min_safe_altitude_m(pose) and np.array_equal(a1, AIM)
    assert _shift_setup(scene, search, AIM.copy())[2] is b1  # built once
    aim[2] -= 30.0  # the caller edits its array
    _, a2, b2 = _shift_setup(scene, search, aim)
    assert b2 is not b1 and b2.aim[2] == AIM[2] - 30.0 and b1.aim[2] == AIM[2] and a1[2] == AIM[2]
    assert _shift_setup(scene, dataclasses.replace(search, beam_clearance_m=5.0), AIM)[2] is not b1
    assert _shift_setup(scene, dataclasses.replace(search, min_altitude_m=40.0), None) == (40.0, None, None)
    assert _shift_setup(build_scene(pose, SUN), search, AIM)[2] is not b1  # another scene, its own index
