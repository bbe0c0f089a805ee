"""Captures that show every facet a heliostat back, the traced facet report, and the flight route.

Oracles: a brute-force membership test for the closed-form cone intervals; plain loops over every
mirror (conftest ``first_mirror``) for the traced report; exhaustive search over directions and cuts
for the route; pihim's renderer (a different ray tracer over the facets, back structure and tower)
for which facets show which heliostat's back.
"""

from __future__ import annotations

import itertools
import math
import sys

import numpy as np
import pytest

from pihim.camera.model import CameraModel
from pihim.errors import PihimInputError
from pihim.field import nsttf_like_field
from pihim.planning.endurance import DroneEndurance, split_flights
from pihim.planning.facet_captures import FacetCaptureSettings, cone_interval
from pihim.planning.facets import facet_targets
from pihim.planning.model import ScanPass, Waypoint
from pihim.planning.pipeline import build_plan
from pihim.planning.route import _Costs, _split, orient_passes, plan_flights, reverse_pass, turns
from pihim.planning.ufacet import home_waypoint, track_at
from pihim.sky.sun import NSTTF, parse_time

TIME = "2021-05-13T10:00-06:00"


@pytest.fixture(scope="module")
def plan10():
    field_ = nsttf_like_field()
    plan = build_plan(field_, parse_time(TIME), NSTTF)
    sun, pose = track_at(field_, parse_time(TIME), aim_point=plan.aim_point, site=NSTTF)
    return plan, field_, pose, sun.vector


# --------------------------------------------------------------------------- closed-form cone intervals


def _in_cone(p, apex, corners, negative):
    """Brute force: does the ray apex -> p (or its opposite) pass through the convex polygon?"""
    d = (p - apex) * (-1.0 if negative else 1.0)
    nrm = np.cross(corners[1] - corners[0], corners[2] - corners[1])
    den = d @ nrm
    if abs(den) < 1e-12:
        return False
    t = ((corners.mean(axis=0) - apex) @ nrm) / den
    if t <= 0:
        return False
    y = apex + t * d
    return all(np.cross(corners[(k + 1) % 4] - corners[k], y - corners[k]) @ nrm >= 0 for k in range(4))


@pytest.mark.parametrize("negative", [False, True])
def test_cone_interval_matches_brute_force(negative):
    rng = np.random.default_rng(7)
    square = np.array([[1.0, 1, 0], [-1, 1, 0], [-1, -1, 0], [1, -1, 0]])
    checked = inside = 0
    for _ in range(60):
        rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        corners = square @ rot.T * rng.uniform(0.5, 3.0) + rng.normal(size=3) * 4
        apex, a, e = rng.normal(size=3) * 3, rng.normal(size=3) * 6, rng.normal(size=3)
        lo, hi = cone_interval(apex, corners, a, e, negative=negative)
        for s in np.linspace(-15, 15, 121):
            if math.isfinite(lo) and min(abs(s - lo), abs(s - hi)) < 1e-6:
                continue  # on the boundary
            want = _in_cone(a + s * e, apex, corners, negative)
            assert (lo <= s <= hi) == want
            checked += 1
            inside += want
    assert inside > 30 and checked - inside > 1000  # both outcomes exercised


# --------------------------------------------------------------------------- the traced report


def _report_oracle(pose, field_, hua, cam, heading, pitch, camera, first_mirror, reach_m=60.0):
    """Plain loops: per facet, the heliostat whose back the middle sample (else most samples) shows."""
    from pihim.planning.sightlines import in_fov, segments_hit_box, tower_box

    box = tower_box(field_.tower)
    corners = pose.facet_corners()[hua]
    out = []
    for f in range(corners.shape[0]):
        tl, tr, br, bl = corners[f]
        n = pose.facet_normals[hua, f]
        shown = []
        for i in range(3):
            for j in range(3):
                u, v = (i + 0.5) / 3, (j + 0.5) / 3
                q = (tl + u * (tr - tl)) + v * ((bl + u * (br - bl)) - (tl + u * (tr - tl)))
                d = (q - cam) / np.linalg.norm(q - cam)
                if d @ n >= 0 or not in_fov(q[None], cam, np.float64(heading), np.float64(pitch), camera)[0]:
                    shown.append(-1)
                    continue
                k, s = first_mirror(pose, q, -d, hua)
                if (k >= 0 and s < np.linalg.norm(cam - q)) or segments_hit_box(cam[None], q[None], *box)[0]:
                    shown.append(-1)  # the sight line is blocked
                    continue
                r = d - 2 * (d @ n) * n
                k, s = first_mirror(pose, q, r, hua)
                ok = k >= 0 and s < reach_m and r @ pose.normals[k] > 0
                if ok and segments_hit_box((q + 1e-6 * r)[None], (q + s * r)[None], *box)[0]:
                    ok = False
                shown.append(k if ok else -1)
        shown = np.array(shown)
        if shown[4] >= 0:
            out.append(int(shown[4]))
        elif (shown >= 0).any():
            vals, counts = np.unique(shown[shown >= 0], return_counts=True)
            out.append(int(vals[np.argmax(counts)]))
        else:
            out.append(-1)
    return out


def test_facet_report_matches_a_brute_force_tracer(plan10, first_mirror):
    plan, field_, pose, sun = plan10
    names = {n: k for k, n in enumerate(field_.names)}
    camera = CameraModel()
    caps = [w for p in plan.passes for w in p.waypoints if w.capture]
    pick = caps[::max(1, len(caps) // 5)][:5]
    got = facet_targets(pose, [names[w.hua] for w in pick], [(w.x_m, w.y_m, w.z_m) for w in pick],
                        [w.heading_deg for w in pick], [w.gimbal_pitch_deg for w in pick], tower=field_.tower)
    for row, w in zip(got, pick, strict=True):
        want = _report_oracle(pose, field_, names[w.hua], np.array([w.x_m, w.y_m, w.z_m]), w.heading_deg,
                              w.gimbal_pitch_deg, camera, first_mirror)
        assert row.tolist() == want
    assert (got >= 0).sum() > 20  # the captures do show heliostat backs


def test_facet_report_in_chunks_is_the_same(plan10, monkeypatch):
    """Captures are traced in chunks (bounded memory at 30,000 heliostats): chunks of 7 give what one batch of
    every capture gives."""
    import pihim.planning.facets as facets_module

    plan, field_, pose, _ = plan10
    names = {n: k for k, n in enumerate(field_.names)}
    caps = [w for p in plan.passes for w in p.waypoints if w.capture][:60]
    args = (pose, [names[w.hua] for w in caps], [(w.x_m, w.y_m, w.z_m) for w in caps],
            [w.heading_deg for w in caps], [w.gimbal_pitch_deg for w in caps])
    whole = facet_targets(*args, tower=field_.tower)
    monkeypatch.setattr(facets_module, "_CHUNK", 7)
    assert np.array_equal(facet_targets(*args, tower=field_.tower), whole)
    assert (whole >= 0).sum() > 100


def test_every_facet_imaged(plan10):
    plan, field_, _, _ = plan10
    fc = plan.summary["facet_coverage"]
    assert fc["fraction"] >= 0.95  # the issue's aim
    assert fc["facets"] == 25 * fc["huas"] and fc["huas"] == len({w.hua for p in plan.passes for w in p.waypoints
                                                                     if w.capture})
    per = fc["per_hua"]
    assert sum(len(v["covered"]) for v in per.values()) == fc["facets_covered"]
    n_field = plan.summary["heliostats_in_field"]
    assert plan.summary["coverage"]["planned"] >= 0.9 and fc["huas"] / n_field >= 0.9
    caps = {(p.index, j): w for p in plan.passes for j, w in enumerate(p.waypoints) if w.capture}
    for hua, v in per.items():
        assert sorted(v["covered"] + v["missing"]) == list(range(25))
        for f, src in v["shown_by"].items():  # each covered facet names a capture of this HUA and a target
            assert int(f) in v["covered"] and caps[(src["pass"], src["waypoint"])].hua == hua
            assert src["target"] in field_.names and src["target"] != hua
    # several captures per HUA, each on its pass's straight line and at least a metre from the others
    assert plan.summary["images"] > 1.5 * fc["huas"]
    for p in plan.passes:
        xy = np.array([(w.x_m, w.y_m) for w in p.waypoints])
        if len(xy) > 2:
            e = (xy[-1] - xy[0]) / np.linalg.norm(xy[-1] - xy[0])
            assert np.abs((xy - xy[0]) @ np.array([e[1], -e[0]])).max() < 1e-6
        cap_xy = np.array([(w.x_m, w.y_m) for w in p.waypoints if w.capture])
        if len(cap_xy) > 1:
            assert np.linalg.norm(np.diff(cap_xy, axis=0), axis=1).min() >= 0.999


def test_the_shortlist_of_targets_and_blockers_looks_over_a_widened_window(plan10, monkeypatch):
    """The cheap first pass (mirrors seen from the facet centres) asks for intervals over the candidate window
    widened by max(3 step_m, 3 m) at both ends; the exact pass over the sample points asks for the window itself."""
    import pihim.planning.facet_captures as fc_module
    from pihim.planning.scoring import score_passes
    from pihim.planning.ufacet import plan_ufacet

    plan, field_, pose, sun = plan10
    calls = []
    inner = fc_module._cone_intervals

    def spy(q, a, e, terms, idx, window, negative):
        calls.append((q.shape[1], np.array(window[0]), np.array(window[1]), negative))
        return inner(q, a, e, terms, idx, window, negative)

    monkeypatch.setattr(fc_module, "_cone_intervals", spy)
    res = plan_ufacet(field_, pose, aim_point=plan.aim_point, origin=NSTTF,
                      heliostats=[n for n in field_.names if n.startswith("10")])
    st = FacetCaptureSettings(target_fraction=None, rescue=False)
    fc_module.plan_facet_captures(score_passes(res.passes, pose, sun, search=None), pose, origin=NSTTF,
                                  tower=field_.tower, aim_point=plan.aim_point, settings=st)
    n_f = len(field_.spec.facet_centroids)
    margin = max(3.0 * st.step_m, 3.0)
    assert len(calls) >= 4 and len(calls) % 4 == 0
    for short, exact in zip(calls[0::2], calls[1::2], strict=True):  # shortlist, then its exact pass
        assert short[0] == n_f and exact[0] == n_f * st.samples**2 and short[3] == exact[3]
        np.testing.assert_allclose(short[1], exact[1] - margin, atol=1e-9)
        np.testing.assert_allclose(short[2], exact[2] + margin, atol=1e-9)
        assert np.all(exact[2] > exact[1])


def test_planner_prediction_agrees_with_the_traced_report(plan10):
    # the closed-form planner and the ray tracer count the same facets within a fraction of a percent
    from pihim.planning.facet_captures import plan_facet_captures
    from pihim.planning.facets import coverage_summary, facet_coverage
    from pihim.planning.scoring import score_passes
    from pihim.planning.ufacet import plan_ufacet

    plan, field_, pose, sun = plan10
    res = plan_ufacet(field_, pose, aim_point=plan.aim_point, origin=NSTTF,
                      heliostats=[n for n in field_.names if n.startswith(("9", "10"))])
    passes = score_passes(res.passes, pose, sun, search=None)
    fp = plan_facet_captures(passes, pose, origin=NSTTF, tower=field_.tower, aim_point=plan.aim_point,
                             settings=FacetCaptureSettings(target_fraction=None, rescue=False))
    traced = coverage_summary(facet_coverage(fp.passes, pose, tower=field_.tower))
    predicted = sum(len(v) for v in fp.predicted.values())
    assert traced["huas"] == len(fp.predicted) > 10
    assert abs(traced["facets_covered"] - predicted) <= 0.01 * traced["facets"]
    assert traced["fraction"] > 0.95


@pytest.mark.parametrize("background", [0, 1, 2])
def test_traced_captures_give_the_same_report(plan10, background, monkeypatch):
    """The report from captures traced beforehand (trace_captures, in workers while the route runs in
    pihim plan) equals the one traced on the spot, reordered and reversed passes included; captures missing
    from the traced rows are traced on the spot."""
    from pihim.planning import facets
    from pihim.planning.route import reverse_pass

    plan, field_, pose, _ = plan10
    monkeypatch.setattr(facets, "_CHUNK", 64)  # several chunks
    passes = [p for p in plan.passes if any(w.capture for w in p.waypoints)]
    pending = facets.trace_captures(passes[::-1], pose, tower=field_.tower, background=background)  # another order
    assert pending.running == (background > 0 and sys.platform.startswith("linux"))
    traced = pending.result()
    assert not pending.running
    flown = [reverse_pass(p) if k % 2 else p for k, p in enumerate(passes)]
    direct = facets.facet_coverage(flown, pose, tower=field_.tower)
    assert facets.facet_coverage(flown, pose, tower=field_.tower, traced=traced) == direct
    some = dict(list(traced.items())[::2])
    assert facets.facet_coverage(flown, pose, tower=field_.tower, traced=some) == direct
    assert sum(len(c.covered) for c in direct.values()) > 100


@pytest.mark.parametrize("samples", [0, True, 2.0])
def test_trace_captures_refuses_a_bad_sample_count(plan10, samples):
    """Checked before any tracing starts, as facet_targets checks it (the chunks trace without checking)."""
    from pihim.planning import facets

    plan, field_, pose, _ = plan10
    with pytest.raises(PihimInputError, match="samples must be a positive integer"):
        facets.trace_captures(plan.passes, pose, samples=samples, tower=field_.tower)


def test_coverage_is_the_first_capture_showing_each_facet(plan10):
    """facet_coverage against its definition, a plain loop over the captures in plan order: per HUA (in
    first-capture order) its captures and the facets some capture shows a heliostat's back in, each with the
    first capture that shows one and the heliostat it shows."""
    from pihim.planning import facets

    plan, field_, pose, _ = plan10
    got = facets.facet_coverage(plan.passes, pose, tower=field_.tower)
    names = list(pose.field.names)
    refs = [(p.index, j, w) for p in plan.passes for j, w in enumerate(p.waypoints) if w.capture and w.hua]
    rows = facets.facet_targets(pose, [names.index(w.hua) for *_, w in refs], [(w.x_m, w.y_m, w.z_m) for *_, w in refs],
                                [w.heading_deg for *_, w in refs], [w.gimbal_pitch_deg for *_, w in refs],
                                tower=field_.tower)
    want: dict[str, tuple[dict, list]] = {}
    for (pi, j, w), row in zip(refs, rows, strict=True):
        shown, n = want.setdefault(w.hua, ({}, [0]))
        n[0] += 1
        for f, t in enumerate(row.tolist()):
            if t >= 0 and f not in shown:
                shown[f] = (pi, j, names[t])
    assert list(got) == list(want)
    for h, (shown, n) in want.items():
        assert got[h] == facets.FacetCoverage(h, rows.shape[1], tuple(sorted(shown)), n[0], tuple(sorted(shown.items())))
    # not a trivial case: HUAs whose facets the first capture leaves uncovered, shown by a later one
    assert sum(len({s[:2] for s in shown.values()}) > 1 for shown, _ in want.values()) > 5


def test_renderer_shows_the_backs_the_report_names(plan10):
    """Render a few captures at 1/8 resolution: every facet the report says shows heliostat T does show T's back
    (facets or structure) in the rendered image, after one mirror bounce."""
    pytest.importorskip("numba")
    from pihim.camera.pose import CameraPose, pixel_rays_world
    from pihim.render.paths import FACET_BACK, MIRROR, STRUCTURE_HIT, trace_paths
    from pihim.render.scene import field_scene

    plan, field_, pose, sun = plan10
    names = {n: k for k, n in enumerate(field_.names)}
    camera = CameraModel()
    scene = field_scene(pose)
    caps = [w for p in plan.passes for w in p.waypoints if w.capture]
    pick = caps[3::max(1, len(caps) // 4)][:4]
    u, v = np.meshgrid(np.arange(4, camera.width_px, 8), np.arange(4, camera.height_px, 8))
    report = facet_targets(pose, [names[w.hua] for w in pick], [(w.x_m, w.y_m, w.z_m) for w in pick],
                           [w.heading_deg for w in pick], [w.gimbal_pitch_deg for w in pick], tower=field_.tower)
    named = 0
    for w, row in zip(pick, report, strict=True):
        h = names[w.hua]
        o, d = pixel_rays_world(camera, CameraPose.from_waypoint(w), u.ravel(), v.ravel())
        paths = trace_paths(scene, o, d, sun, max_bounces=1)
        prim = np.maximum(paths.first_prim, 0)
        on_hua = (paths.first_kind == MIRROR) & (paths.first_prim >= 0) & (scene.heliostat[prim] == h)
        facet = np.where(on_hua, scene.facet[prim] - 1, -1)
        back = np.isin(paths.terminal_kind, (FACET_BACK, STRUCTURE_HIT)) & (paths.terminal_prim >= 0)
        who = np.where(back, scene.heliostat[np.maximum(paths.terminal_prim, 0)], -1)
        for f in np.flatnonzero(row >= 0).tolist():
            assert row[f] in set(who[(facet == f) & back].tolist()), (w.hua, f)
            named += 1
    assert named >= 30


# --------------------------------------------------------------------------- the route


def _pass(index: int, a, b, z=25.0) -> ScanPass:
    wps = tuple(Waypoint(x, y, z, 0.0, 0.0, 0.0, 0.0, -80.0, 5.0, kind="scan", capture=True, hua=f"{index + 6}E1")
                for x, y in (a, b))
    return ScanPass(index=index, azimuth_deg=0.0, altitude_m=z, gimbal_pitch_deg=-80.0,
                    pairs=tuple((w.hua, "5E1") for w in wps), waypoints=wps)


def test_orient_passes_is_exact():
    rng = np.random.default_rng(3)
    passes = [_pass(k, rng.uniform(0, 100, 2), rng.uniform(0, 100, 2)) for k in range(6)]
    home = Waypoint(50, -20, 0, 0, 0, 0, 0, 0, 0, kind="takeoff")
    costs = _Costs(passes, home, None)
    order = [3, 0, 5, 1, 4, 2]
    for hz in (None, 0.0):
        got, dirs = orient_passes(order, costs, home_z=hz)
        best = math.inf
        for ds in itertools.product((0, 1), repeat=len(order)):
            c = sum(costs.d(2 * order[i] + 1 - ds[i], 2 * order[i + 1] + ds[i + 1]) for i in range(len(order) - 1))
            if hz is not None:
                c += costs.h(2 * order[0] + ds[0], 25.0) + costs.h(2 * order[-1] + 1 - ds[-1], 25.0) - 50.0
            best = min(best, c)
        assert got == pytest.approx(best)
        assert len(dirs) == len(order)


def test_split_is_the_shortest_cut():
    rng = np.random.default_rng(5)
    passes = [_pass(k, rng.uniform(0, 200, 2), rng.uniform(0, 200, 2)) for k in range(7)]
    home = Waypoint(100, -30, 0, 0, 0, 0, 0, 0, 0, kind="takeoff")
    costs = _Costs(passes, home, None)
    from pihim.planning.route import RouteSettings, _pass_costs

    model = DroneEndurance(battery_min=4.0)
    pc, base = _pass_costs(passes, home, model, None)
    order = list(range(7))
    z = np.full(7, 25.0)
    got = _split(order, costs, pc, base, model, z, math.inf, RouteSettings())

    def flight(block):  # horizontal transits from home and between passes, climb to 25 m and descent
        transit, _ = orient_passes(block, costs, home_z=0.0)
        t = (sum(pc[k].time_s for k in block) + transit / model.transit_speed_m_s + 25 / 3 + 25 / 2
             + model.takeoff_landing_s)
        return transit + 50.0 + sum(costs.inner[block]), t <= model.usable_s * 0.98

    best = math.inf
    for cuts in itertools.product((0, 1), repeat=6):
        blocks, cur = [], [0]
        for k, c in enumerate(cuts, start=1):
            if c:
                blocks.append(cur)
                cur = []
            cur.append(k)
        blocks.append(cur)
        res = [flight(b) for b in blocks]
        if all(ok for _, ok in res):
            best = min(best, sum(d for d, _ in res))
    total = sum(flight(order[i:j])[0] for i, j in got)
    assert total == pytest.approx(best)
    assert len(got) >= 2  # the battery forces a cut


def test_plan_flights_is_shorter_and_flies_every_pass_once():
    field_ = nsttf_like_field()
    plan = build_plan(field_, parse_time(TIME), NSTTF, route=False, facet_report=False)
    home = home_waypoint(field_, origin=NSTTF)
    greedy = split_flights(plan.passes, home, origin=NSTTF, tower=field_.tower)
    passes, flights = plan_flights(plan.passes, home, origin=NSTTF, tower=field_.tower)
    assert sum(f.distance_m for f in flights) < sum(f.distance_m for f in greedy)
    flown = [i for f in flights for i in f.pass_indices]
    assert flown == list(range(len(flown))) and len(flown) == sum(p.feasible for p in plan.passes)
    caps = sorted((w.x_m, w.y_m, w.z_m) for p in plan.passes for w in p.waypoints if w.capture)
    assert sorted((w.x_m, w.y_m, w.z_m) for f in flights for w in f.waypoints if w.capture) == caps
    assert all(f.duration_s <= DroneEndurance().usable_s for f in flights)


def _long_pass(index: int, n_caps: int, x: float = 0.0, y0: float = 0.0, step: float = 4.0) -> ScanPass:
    """A northbound stop-and-shoot pass: lead-in, ``n_caps`` captures of HUAs ``1E1``, ``2E1`` ..., run-past."""
    wps = [Waypoint(x, y0 - 5.0, 25.0, 0, 0, 0, 0.0, -80.0, 3.0, kind="lead_in")]
    wps += [Waypoint(x, y0 + step * k, 25.0, 0, 0, 0, 0.0, -80.0, 2.0, kind="scan", capture=True, hua=f"{k + 1}E1")
            for k in range(n_caps)]
    wps += [Waypoint(x, y0 + step * n_caps, 25.0, 0, 0, 0, 0.0, -80.0, 3.0, kind="run_past")]
    return ScanPass(index=index, azimuth_deg=0.0, altitude_m=25.0, gimbal_pitch_deg=-80.0,
                    pairs=tuple((f"{k + 1}E1", "0E1") for k in range(n_caps)), waypoints=tuple(wps))


def test_split_pass_keeps_the_waypoints_in_order():
    from pihim.planning.route import split_pass

    p = _long_pass(3, 10)
    for k in (1, 2, 3, 10):
        parts = split_pass(p, k)
        assert len(parts) == k and all(q.index == 3 for q in parts)
        assert tuple(w for q in parts for w in q.waypoints) == p.waypoints
        assert all(q.waypoints[0].capture for q in parts[1:])  # cut before a capture
        caps = [sum(w.capture for w in q.waypoints) for q in parts]
        assert sum(caps) == 10 and max(caps) - min(caps) <= 1
        assert [pr for q in parts for pr in q.pairs] == list(p.pairs)  # each pair in the piece of its capture
    with pytest.raises(PihimInputError, match="cannot be cut"):
        split_pass(p, 11)


def test_plan_flights_cuts_a_pass_too_long_for_one_mission():
    """A 250-capture pass needs about 760 mission items (the 30,000-heliostat radial field's case, which failed
    with "pass alone needs 769 mission items, more than 700"): it is flown in pieces, every capture once, and no
    flight exceeds the limit."""
    from pihim.planning.export.qgc import count_mission_items

    home = Waypoint(0, -40, 0, 0, 0, 0, 0, 0, 0, kind="takeoff")
    p = _long_pass(0, 250, step=1.0)
    passes, flights = plan_flights([p], home, origin=NSTTF, max_mission_items=700, count_items=count_mission_items)
    assert count_mission_items([home, *p.waypoints, home]) > 700
    assert len(flights) >= 2 and all(count_mission_items(f.waypoints) <= 700 for f in flights)
    assert [i for f in flights for i in f.pass_indices] == list(range(len(passes)))
    caps = sorted(w.y_m for w in p.waypoints if w.capture)
    assert sorted(w.y_m for f in flights for w in f.waypoints if w.capture) == caps
    with pytest.raises(PihimInputError, match="single capture, more than 12"):
        plan_flights([p], home, origin=NSTTF, max_mission_items=12, count_items=count_mission_items)


def test_plan_flights_leaves_out_passes_beyond_a_battery():
    """A pass 6 km from home (the edge of a field kilometres wide) cannot be reached and flown on one battery:
    with ``unflyable`` it is planned but not flown and its index reported; without, the route refuses."""
    home = Waypoint(0, -40, 0, 0, 0, 0, 0, 0, 0, kind="takeoff")
    near, far = _long_pass(0, 5), _long_pass(1, 5, x=6000.0)
    out: list[int] = []
    passes, flights = plan_flights([far, near], home, origin=NSTTF, unflyable=out)
    assert out == [1] and len(passes) == 2 and passes[1].waypoints == far.waypoints
    assert [i for f in flights for i in f.pass_indices] == [0]
    assert passes[0].waypoints in (near.waypoints, reverse_pass(near).waypoints)
    with pytest.raises(PihimInputError, match="alone needs"):
        plan_flights([far, near], home, origin=NSTTF)


def test_reverse_pass_and_turns():
    p = _pass(0, (0, 0), (10, 0))
    r = reverse_pass(p)
    assert [w.x_m for w in r.waypoints] == [10, 0] and r.azimuth_deg == pytest.approx((p.azimuth_deg + 180) % 360)
    assert reverse_pass(r).waypoints == p.waypoints
    square = [Waypoint(x, y, 0, 0, 0, 0, 0, 0, 0) for x, y in ((0, 0), (10, 0), (10, 0.2), (10, 10), (0, 10), (-1, 10))]
    assert turns(square) == 2  # the 0.2 m leg is ignored; 90 deg twice; the last leg goes straight on


def test_turn_charges_count_what_turns_counts():
    """Each transit is charged the turns it makes out of one pass and into the next: summed over an order and
    its directions they equal turns() of the path flown (straight passes, no home legs, no tower)."""
    rng = np.random.default_rng(11)
    home = Waypoint(0, -50, 0, 0, 0, 0, 0, 0, 0, kind="takeoff")
    for trial in range(40):
        n = int(rng.integers(2, 7))
        passes = []
        for k in range(n):
            a = rng.uniform(0, 60, 2)
            b = a + rng.uniform(1, 30) * np.array([math.cos(t := rng.uniform(0, 2 * math.pi)), math.sin(t)])
            passes.append(_pass(k, a, b))
        if trial % 4 == 0:  # a pass continuing straight on from the end of another (no transit, no turn)
            w = passes[0].waypoints
            tip = np.array([w[1].x_m, w[1].y_m])
            passes[1] = _pass(1, tip, tip + 2.0 * (tip - np.array([w[0].x_m, w[0].y_m])))
        costs = _Costs(passes, home, None, turn_cost_m=1.0)
        plain = _Costs(passes, home, None)
        order = list(rng.permutation(n))
        dirs = list(rng.integers(0, 2, n))
        path = [w for k, o in zip(order, dirs, strict=True)
                for w in (reverse_pass(passes[k]) if o else passes[k]).waypoints]
        charged = sum(costs.d(2 * order[i] + 1 - dirs[i], 2 * order[i + 1] + dirs[i + 1])
                      - plain.d(2 * order[i] + 1 - dirs[i], 2 * order[i + 1] + dirs[i + 1]) for i in range(n - 1))
        assert charged == pytest.approx(turns(path)), trial


def test_costs_with_another_turn_cost_are_those_built_with_it():
    """The route's two cost tables share the pass geometry (:meth:`_Costs.with_turn_cost`): every transit and
    home leg as a table built with that turn cost, and the first table's cached distances left as they were."""
    rng = np.random.default_rng(23)
    home = Waypoint(0, -50, 0, 0, 0, 0, 0, 0, 0, kind="takeoff")
    passes = [_pass(k, a := rng.uniform(0, 60, 2), a + rng.uniform(-30, 30, 2)) for k in range(7)]
    keepout = (np.array([20.0, 20.0]), np.array([30.0, 30.0]), 40.0)  # low, high corner, top: transits go around
    turned = _Costs(passes, home, keepout, turn_cost_m=10.0)
    ends = range(2 * len(passes))
    before = {(a, b): turned.d(a, b) for a in ends for b in ends}
    home_before = {e: turned.h(e, 25.0) for e in ends}
    plain = turned.with_turn_cost(0.0)
    fresh = _Costs(passes, home, keepout)
    assert plain.turn_cost_m == 0.0 and turned.turn_cost_m == 10.0
    assert all(plain.d(a, b) == fresh.d(a, b) for a in ends for b in ends)
    assert all(plain.h(e, 25.0) == fresh.h(e, 25.0) for e in ends)
    assert any(plain.d(a, b) != before[a, b] for a in ends for b in ends)  # the turn cost does count
    assert all(turned.d(a, b) == before[a, b] for a in ends for b in ends)
    assert all(turned.h(e, 25.0) == home_before[e] for e in ends)
    assert any(plain.h(e, 25.0) != home_before[e] for e in ends)  # the turn at the pass end counts at home too
    assert turned.with_turn_cost(10.0).d(0, 3) == before[0, 3]


def test_turn_cost_trades_distance_for_turns():
    """The route's default charge per turn flies fewer turns than distance alone, for a little more distance."""
    from pihim.planning.route import RouteSettings

    field_ = nsttf_like_field()
    plan = build_plan(field_, parse_time(TIME), NSTTF, route=False, facet_report=False)
    home = home_waypoint(field_, origin=NSTTF)
    runs = {}
    for cost in (0.0, RouteSettings().turn_cost_m):
        _, flights = plan_flights(plan.passes, home, origin=NSTTF, tower=field_.tower,
                                  settings=RouteSettings(turn_cost_m=cost))
        runs[cost] = (sum(turns(f.waypoints) for f in flights), sum(f.distance_m for f in flights))
    (t0, d0), (t1, d1) = runs.values()
    assert RouteSettings().turn_cost_m > 0 and t1 < t0
    assert d1 <= d0 + RouteSettings().turn_cost_m * (t0 - t1)  # each turn saved cost at most its charge
    with pytest.raises(PihimInputError, match="turn_cost_m"):
        RouteSettings(turn_cost_m=-1.0)


def test_facet_capture_settings_are_checked():
    for bad in ({"step_m": 0}, {"max_captures": 0}, {"target_fraction": 1.5}, {"aim_offsets_m": ()},
                {"min_planned_coverage": -0.1}):
        with pytest.raises(PihimInputError):
            FacetCaptureSettings(**bad)


@pytest.fixture(scope="module")
def orphaned(plan10):
    """Half of the flown passes withheld, and the HUAs only they imaged."""
    plan, field_, pose, _ = plan10
    base = build_plan(field_, parse_time(TIME), NSTTF, facet_captures=False, route=False, facet_report=False)
    flown = [p for p in base.passes if p.feasible]
    kept, withheld = flown[1::2], flown[::2]
    orphans = sorted({w.hua for p in withheld for w in p.waypoints if w.capture and w.hua} -
                     {w.hua for p in kept for w in p.waypoints if w.capture and w.hua})
    return kept, orphans


def test_huas_left_without_a_pass_are_rescued_or_given_their_own(plan10, orphaned):
    """Half of the passes withheld: their HUAs are imaged from the nearest remaining lines (rescue) or from
    short passes of their own, each with at least ``rescue_min_fraction`` of its facets predicted, and the
    traced report confirms most of those facets."""
    from pihim.planning.facet_captures import plan_facet_captures
    from pihim.planning.facets import facet_coverage

    plan, field_, pose, _ = plan10
    kept, orphans = orphaned
    st = FacetCaptureSettings()
    fplan = plan_facet_captures(kept, pose, origin=NSTTF, tower=field_.tower, aim_point=plan.aim_point,
                                unassessed=orphans, settings=st)
    n_f = pose.facet_centres.shape[1]
    own = [p for p in fplan.passes if any("short pass of its own" in i for i in p.issues)]
    helped = set(fplan.rescued)
    assert len(orphans) > 20 and len(helped) > 10 and own  # both routes taken
    for h in helped:  # each with enough facets predicted, captured on some pass
        assert len(fplan.predicted[h]) >= st.rescue_min_fraction * n_f
        assert any(w.hua == h and w.capture for p in fplan.passes for w in p.waypoints)
    traced = facet_coverage(fplan.passes, pose, tower=field_.tower)
    got = sum(len(set(traced[h].covered) & set(fplan.predicted[h])) for h in helped)
    assert got >= 0.9 * sum(len(fplan.predicted[h]) for h in helped)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="workers are forked on Linux only")
def test_own_lines_offered_by_workers_change_nothing(plan10, orphaned, monkeypatch):
    """The HUAs' own lines are evaluated side by side in whole batches: with workers (one batch of two HUAs'
    lines per piece) the same captures, rescues and passes as in one process and one piece."""
    from pihim import _forked
    from pihim.planning import facet_captures

    plan, field_, pose, _ = plan10
    kept, orphans = orphaned
    st = FacetCaptureSettings(batch=2)
    args = dict(origin=NSTTF, tower=field_.tower, aim_point=plan.aim_point, unassessed=orphans, settings=st)
    monkeypatch.setattr(facet_captures, "_BATCHES_PER_PIECE", 10**6)
    one = facet_captures.plan_facet_captures(kept, pose, workers=1, **args)  # every HUA's own lines in one piece
    monkeypatch.setattr(facet_captures, "_BATCHES_PER_PIECE", 1)
    pieces = {}
    imap_unordered = _forked.imap_unordered

    def spy(job, n, workers, *, what="pieces"):
        if _forked.can_fork(workers, n):
            pieces[what] = n
        return imap_unordered(job, n, workers, what=what)

    monkeypatch.setattr(_forked, "imap_unordered", spy)
    two = facet_captures.plan_facet_captures(kept, pose, workers=2, **args)
    assert pieces.get("HUAs' own lines", 0) >= 3
    assert any("short pass of its own" in i for p in two.passes for i in p.issues)
    assert (two.passes, two.captures, two.predicted, two.coverable, two.rescued) == \
        (one.passes, one.captures, one.predicted, one.coverable, one.rescued)


def test_build_plan_names_each_stage_as_it_starts(monkeypatch):
    """The progress callback hears the stages in order, only those that run, each before its work."""
    import pihim.planning.pipeline as pipeline

    seen: list[str] = []
    inner = pipeline.plan_facet_captures

    def announced(*args, **kwargs):  # the facet captures run after their stage was named, and only then
        assert seen[-1] == "facet captures"
        return inner(*args, **kwargs)

    monkeypatch.setattr(pipeline, "plan_facet_captures", announced)
    field_ = nsttf_like_field()
    rows = [n for n in field_.names if n.startswith("10")]
    build_plan(field_, parse_time(TIME), NSTTF, heliostats=rows, progress=seen.append)
    assert seen == ["passes", "scoring", "facet captures", "route and flights", "facet report"]
    seen.clear()
    build_plan(field_, parse_time(TIME), NSTTF, heliostats=rows, facet_captures=False, facet_report=False,
               progress=seen.append)
    assert seen == ["passes", "scoring", "route and flights"]


def test_build_plan_refuses_a_bad_fleet_hours_before_planning(monkeypatch) -> None:
    import pihim.planning.pipeline as pipeline

    def no_planning(*args, **kwargs):
        raise AssertionError("planning started")
    monkeypatch.setattr(pipeline, "track_at", no_planning)
    for bad in (25.0, 0.0, float("nan")):
        with pytest.raises(PihimInputError, match="working_hours"):
            build_plan(nsttf_like_field(), parse_time(TIME), NSTTF, fleet_hours=bad)
