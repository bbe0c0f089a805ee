"""Per-facet canting from the target's reflection, scored against rendered truth.

The frame is rendered by the ray tracer (:mod:`pihim.render`, fixture ``ufacet``
in ``conftest.py``); the estimator projects the target's outlines mirrored in
each facet's plane (an independent forward model: plane mirroring and
``project_points``, held to OpenCV). The forward model's parts are tested in
``test_reflection.py``, the orientation searches and solves in
``test_orientation.py``.
"""

import numpy as np
import pytest

from pihim.inspection.canting import PAPER_GRID_STEP_MRAD, estimate_canting
from pihim.inspection.canting_output import reason_code
from pihim.inspection.features import edge_points


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
    # measured 0.002 / 0.008 mrad RMS here over facets 7, 12, 13, 17 and 18 (facet 8 is skipped as ambiguous:
    # two fits 5 mrad apart explain it alike); the benchmark bound is 0.5 mrad, this fast test a looser 0.6
    assert np.sqrt(np.mean(err_az**2)) < 0.6
    assert np.sqrt(np.mean(err_el**2)) < 0.6
    # the raw best-fit orientation is the mean true canting (exact camera pose, no tracking error)
    assert res.orientation_az_mrad == pytest.approx(true_az.mean(), abs=0.6)
    assert res.orientation_el_mrad == pytest.approx(true_el.mean(), abs=0.6)
    # the paper's grid search is limited by its 1.75 mrad step, where its best node is in the true basin; on facet
    # 13 (the target's crossbars) it is not, 3.5 mrad off (the refinement started from the fine grid)
    ids = [f.id for f in used]
    grid_az = np.array([f.grid_az_mrad for f in used])
    others = np.array(ids) != 13
    grid_err = (grid_az - grid_az[others].mean()) - (true_az - true_az[others].mean())  # the others' mean as reference
    assert np.max(np.abs(grid_err[others])) < PAPER_GRID_STEP_MRAD
    assert abs(grid_err[ids.index(13)]) > PAPER_GRID_STEP_MRAD
    # every skipped facet says why; facet 8's reflection fits two ways 5 mrad apart: skipped, not guessed
    assert all(f.reason for f in res.facets if not f.used)
    assert not res.facets[7].used and "alike" in res.facets[7].reason
    assert reason_code(res.facets[7].reason) == "AMBIG"  # not NOREF, whose text it starts with
    assert reason_code("no usable reflection of 7E3: too few edge points inside this facet") == "NOREF"
    assert res.to_dict()["facets"][0]["id"] == 1
    # each facet's share of its outline in the frame, from the pose the fit used, in facet order
    from pihim.inspection.reflection import facet_in_view

    np.testing.assert_array_equal([f.in_view for f in res.facets], facet_in_view(cam, cp, pose.facet_corners()[h]))
    assert all(f.in_view > 0 for f in used)


def test_facets_polarized_at_most_02_are_skipped_by_default(ufacet):
    """Pinned convention (paper sec. 4.1): only reflections with DoLP > 0.2 are processed, unless told otherwise."""
    field, pose, h, az, el, cam, cp, fr = ufacet
    z = np.zeros_like(fr.s0)
    ep = edge_points(fr.s0, z, z)
    res = estimate_canting(cam, cp, pose, "8E3", "7E3", ep, dolp=np.full(fr.s0.shape, 0.19))
    in_view = [f for f in res.facets if f.reason != "facet not in view (or too small)"]
    assert len(in_view) >= 4
    assert all(not f.used and f.reason == "DoLP <= 0.2 on the reflection (paper sec. 4.1)" for f in in_view)


def test_each_facet_gets_its_own_fits_uncertainty_relative_to_the_mean(ufacet, monkeypatch):
    """The jackknife variances (stubbed here: a distinct value per facet, one unknown) reach their own facets,
    taken relative to the mean over the used facets; an unknown one is reported as None (JSON null)."""
    import json

    from pihim.inspection import canting
    from pihim.inspection.uncertainty import relative_variance

    field, pose, h, az, el, cam, cp, fr = ufacet
    z = np.zeros_like(fr.s0)
    ep = edge_points(fr.s0, z, z)
    centres = pose.facet_centres[h]
    unknown = 12

    def stub(model, found, segments, a, e, gate):
        fid = int(np.argmin(np.linalg.norm(centres - model.centre, axis=1))) + 1
        return np.array([np.nan, np.nan]) if fid == unknown else np.array([1e-4 * fid, 4e-4 * fid])

    monkeypatch.setattr(canting, "_jackknife_variance", stub)
    res = estimate_canting(cam, cp, pose, "8E3", "7E3", ep, min_dolp=None)
    used = [f for f in res.facets if f.used]
    assert unknown in [f.id for f in used] and len(used) >= 3
    var = np.array([stub(type("M", (), {"centre": centres[f.id - 1]}), None, None, 0, 0, 0) for f in used])
    want = np.sqrt(relative_variance(var))
    for f, (sa, se) in zip(used, want, strict=True):
        if f.id == unknown:
            assert f.az_sigma_mrad is None and f.el_sigma_mrad is None
        else:
            assert f.az_sigma_mrad == pytest.approx(sa) and f.el_sigma_mrad == pytest.approx(se)
    json.dumps(res.to_dict(), allow_nan=False)


@pytest.mark.parametrize(("share", "want"), [(0.0, 0.0), (0.002, 0.002), (0.25, 0.25), (0.5, 0.5), (0.9, 0.1)])
def test_direction_spread_is_the_share_of_the_weaker_direction(share, want):
    """Normals split between two perpendicular directions (either sign, turned by any angle): the smaller share."""
    from pihim.inspection.canting import _direction_spread

    n_y = int(round(1000 * share))
    t = 0.7  # any turn of the image
    a = np.array([np.cos(t), np.sin(t)])
    b = np.array([-np.sin(t), np.cos(t)])
    normals = np.vstack([np.tile(a, (1000 - n_y, 1)), np.tile(b, (n_y, 1))])
    normals[::2] *= -1  # a line's normal has no sign
    assert _direction_spread(normals) == pytest.approx(want, abs=1e-12)
    fan = np.linspace(0.0, np.pi, 360, endpoint=False)  # every direction alike
    assert _direction_spread(np.column_stack([np.cos(fan), np.sin(fan)])) == pytest.approx(0.5)
    assert _direction_spread(np.zeros((0, 2))) == 0.0


def test_a_facet_whose_matched_edges_run_one_way_is_skipped(ufacet, monkeypatch):
    """The direction spread is taken on each fit's matched unit line normals, and a facet below ``min_spread``
    is skipped as LINE; the gate comes last, so a bound above any spread (0.5) skips exactly the facets used."""
    from pihim.inspection import canting

    field, pose, h, az, el, cam, cp, fr = ufacet
    z = np.zeros_like(fr.s0)
    ep = edge_points(fr.s0, z, z)
    seen = []

    def spy(normals):
        seen.append(np.asarray(normals))
        return spread(normals)

    spread = canting._direction_spread
    monkeypatch.setattr(canting, "_direction_spread", spy)
    res = estimate_canting(cam, cp, pose, "8E3", "7E3", ep, min_dolp=None)
    used = {f.id for f in res.facets if f.used}
    assert len(used) >= 3 and not any(f.reason and "one way" in f.reason for f in res.facets)
    assert seen and all(len(v) >= 300 and np.allclose(np.linalg.norm(v, axis=1), 1.0) for v in seen)
    assert all(spread(v) >= 0.05 for v in seen)  # these facets show edges of both directions
    res = estimate_canting(cam, cp, pose, "8E3", "7E3", ep, min_dolp=None, min_spread=0.51)
    line = {f.id for f in res.facets if not f.used and reason_code(f.reason) == "LINE"}
    assert line == used and not any(f.used for f in res.facets)
    assert "one angle is not measured" in res.facets[min(line) - 1].reason


def test_the_orientation_search_turn_must_measure_two_facets_more_than_the_log_and_fit_no_looser():
    """Without the target's correction the logged drive angles are the prior: one facet more is not enough (a turn
    of the HUA looks almost as a common tilt of its facets), nor two more fitted more loosely on the facets both
    measure (the issue's seed 5: a turn where the truth has none, 7 facets against 5); with it, more facets, then
    more found, then the smaller residual."""
    from pihim.inspection.canting import _keeps_turn

    assert not _keeps_turn((8, 9, 0.1, 0.1), (7, 9, 0.2, 0.2), False)
    assert _keeps_turn((9, 9, 0.2, 0.1), (7, 9, 0.1, 0.1), False)  # the facets the log misses fit more loosely
    assert not _keeps_turn((9, 9, 0.2, 0.25), (7, 9, 0.1, 0.18), False)
    assert not _keeps_turn((0, 5, 0.1, np.inf), (0, 2, 0.2, np.inf), False)
    assert _keeps_turn((2, 5, 0.1, np.inf), (0, 2, np.inf, np.inf), False)  # none in common
    assert _keeps_turn((8, 9, 0.2, 0.3), (7, 9, 0.1, 0.1), True)
    assert not _keeps_turn((7, 9, 0.1, 0.1), (7, 9, 0.1, 0.1), True)
    assert _keeps_turn((7, 10, 0.2, 0.2), (7, 9, 0.1, 0.1), True)
    assert _keeps_turn((7, 9, 0.1, 0.1), (7, 9, 0.2, 0.2), True)
    assert not _keeps_turn((7, 9, 0.2, 0.2), (7, 9, 0.1, 0.1), True)


@pytest.mark.parametrize(("far_rms", "far_support", "ambiguous"),
                         [(0.10, 0.49, True), (0.20, 0.49, True), (0.25, 0.49, False), (0.25, 0.56, True)])
def test_a_far_rival_that_explains_the_image_as_well_leaves_the_facet_ambiguous(monkeypatch, far_rms, far_support,
                                                                                ambiguous):
    """The final fit's far rivals (1.5 and 2.5 grid steps from the winner): one supported alike that fits the edges
    at least as tightly as the winner (RMS 0.20 px here), or one better supported by the margin, makes the facet
    ambiguous; one supported alike but looser does not count. The refinement is stubbed: two basins, the winner's
    at (0, 0) and one 2.2 grid steps (3.8 mrad) away in azimuth, which the far starts reach and the basin rounds'
    starts (at most a grid step away) do not."""
    from pihim.inspection import canting

    step = PAPER_GRID_STEP_MRAD
    basins = {(0.0, 0.0): (600, 0.20, 0.50), (-2.2 * step, 0.0): (590, far_rms, far_support)}

    def refine(model, mask, ob, dt, gates_px, az, el):
        (a, e), (n, rms, support) = min(basins.items(), key=lambda b: np.hypot(b[0][0] - az, b[0][1] - el))
        return a, e, n, rms, support, "found", "segments", 1000

    monkeypatch.setattr(canting, "_refine_facet", refine)
    first = refine(*[None] * 5, 0.0, 0.0)
    start = canting._Start(0.0, 0.0, None, [first], first)
    gates = canting._Gates(300, 0.3, 0.3)

    def settle(rounds):
        return canting._settle(None, None, start, None, step, (3.0,), [], basin_rounds=rounds, gates=gates)

    assert settle(0)[2:4] == (0.0, 0.0)  # the first fits (no basin rounds) have no far rivals
    if ambiguous:
        with pytest.raises(canting.PihimInputError, match=r"two fits 3\.8 mrad apart explain it alike"):
            settle(2)
    else:
        assert settle(2)[2:4] == (0.0, 0.0)


def test_the_fine_grid_starts_reach_a_basin_the_paper_grid_misses(ufacet, monkeypatch):
    """Facet 13 sees only the target's crossbars: from the paper grid's peaks alone two fits 5 mrad apart explain it
    alike (skipped); the fine grid's best peak starts a fit in its true basin, which is better supported, and the
    facet is measured to a few hundredths of a mrad."""
    from pihim.inspection import canting

    field, pose, h, az, el, cam, cp, fr = ufacet
    z = np.zeros_like(fr.s0)
    ep = edge_points(fr.s0, z, z)

    def facets():
        res = estimate_canting(cam, cp, pose, "8E3", "7E3", ep, min_dolp=None)
        return {f.id: f for f in res.facets}

    with monkeypatch.context() as m:
        m.setattr(canting, "_FINE_PEAKS", 0)
        assert "alike" in facets()[13].reason
    got = facets()
    used = [f for f in got.values() if f.used]
    assert got[13].used
    true_az, true_el = np.array([az[f.id - 1] for f in used]), np.array([el[f.id - 1] for f in used])
    k = [f.id for f in used].index(13)
    assert got[13].az_mrad == pytest.approx(true_az[k] - true_az.mean(), abs=0.05)
    assert got[13].el_mrad == pytest.approx(true_el[k] - true_el.mean(), abs=0.05)


@pytest.mark.parametrize(("rival", "ambiguous"), [((470, 0.28, 0.63, 410), False),   # fewer points, looser: no rival
                                                  ((1000, 0.28, 0.63, 410), True),   # as many points
                                                  ((470, 0.15, 0.63, 410), True),    # tighter
                                                  ((470, 0.28, 0.63, 1400), True)])  # its outline as much inside
def test_a_rival_with_far_fewer_matched_points_fitted_more_loosely_does_not_count(monkeypatch, rival, ambiguous):
    """The support (a share) favours a fit whose outline mostly leaves the facet: on the frame that
    ``benchmarks/canting_quality.py --seed-offset 2000`` renders with seed 2014, facet 17's fit 12 mrad off
    matched 473 edge points at 0.28 px with support 0.63 on 408 outline samples inside the facet, the true one
    1139 points at 0.18 px with support 0.43 on 1539 samples. A rival dominated so (under 1/1.2 of the samples
    inside and of the points, and looser) leaves the winner measured; one that is not makes the facet ambiguous."""
    from pihim.inspection import canting

    step = PAPER_GRID_STEP_MRAD
    win = (0.0, 0.0, 1100, 0.18, 0.43, "found", "segments", 1540)
    far = (-7.0 * step, 0.0, *rival[:3], "found", "segments", rival[3])
    start = canting._Start(0.0, 0.0, None, [win, far], win)
    if ambiguous:
        with pytest.raises(canting.PihimInputError, match="explain it alike"):
            canting._settle(None, None, start, None, step, (3.0,), [])
    else:
        assert canting._settle(None, None, start, None, step, (3.0,), [])[2:4] == (0.0, 0.0)
    monkeypatch.setattr(canting, "_DOMINANCE", None)  # without the rule, every rival supported alike counts
    with pytest.raises(canting.PihimInputError, match="explain it alike"):
        canting._settle(None, None, start, None, step, (3.0,), [])


def test_the_window_of_projected_outline_points_and_the_threads_change_no_fit(ufacet, monkeypatch):
    """A fit's rounds project only the outline points near the facet while no other can reach it (the window of
    ``_kernels.refine_reflection``), and a facet's refinements run on threads: the same facets, angles and
    residuals as projecting them all, one refinement after the other."""
    import numba

    from pihim.inspection import canting

    field, pose, h, az, el, cam, cp, fr = ufacet
    z = np.zeros_like(fr.s0)
    ep = edge_points(fr.s0, z, z)

    def result() -> dict:
        out = estimate_canting(cam, cp, pose, "8E3", "7E3", ep, min_dolp=None).to_dict()
        del out["orientation_search"]["seconds"]
        return out

    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 2)
    windowed = result()
    assert sum(f["used"] for f in windowed["facets"]) >= 5
    monkeypatch.setattr(canting, "_WINDOW_PX", 0.0)  # every projection of all points
    monkeypatch.setattr(numba.config, "NUMBA_NUM_THREADS", 1)  # every refinement in this thread
    assert windowed == result()


def test_a_window_holds_every_outline_point_that_can_reach_the_facet(ufacet):
    """Within the angles a window allows, the points in the facet's mask, their pixels and line normals are those
    of all points, even for a window a few pixels wide (points just outside it come in if the bound is wrong);
    beyond them, all points are projected again and the window is set anew."""
    from pihim.inspection import _kernels as K
    from pihim.inspection.pose import sample_segments
    from pihim.inspection.reflection import _facet_masks, _FacetModel, target_outline_segments

    field, pose, h, az, el, cam, cp, fr = ufacet
    pts, seg = sample_segments(target_outline_segments(pose, field.index("7E3")), 0.01)
    masks = _facet_masks(cam, cp, pose.facet_corners()[h], 6.0)
    width = 4.0
    rng = np.random.default_rng(3)
    checked = 0
    for f, mask in enumerate(masks):
        if mask.area() < 200:
            continue
        model = _FacetModel(cam, cp, pose.rotations[h], pose.facet_centres[h, f], pose.facet_normals_local[h, f],
                            pts, seg).near(mask, 17.5)
        rate = model.motion_px_per_mrad()
        box = np.array(mask.extent(), np.int64)
        ref, where, part_pts, part_seg = np.zeros(3), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64)

        def project(a: float, e: float) -> tuple:
            nonlocal where, part_pts, part_seg
            normal = K.facet_normal(model.aux, a, e)
            *out, windowed, where, part_pts, part_seg = K._window_project(
                model.pts, model.seg, np.asarray(model.centre, float), normal, model._r, model._c, model._cam,
                mask.sub, mask.r0, mask.c0, box, width, rate, a, e, ref, where, part_pts, part_seg)
            return (*out, windowed)

        centre = rng.normal(0.0, 3.0, 2)
        assert not project(*centre)[4]  # all points: the window's reference
        assert ref[0] == 1.0 and tuple(ref[1:]) == tuple(centre)
        for _ in range(10):
            d = rng.normal(size=2)
            a, e = centre + d / np.hypot(*d) * rng.uniform(0.5, 0.999) * width / rate  # within the bound
            uv, nrm, ins, usable, windowed = project(a, e)
            assert windowed and len(where) < len(model.pts)
            full = K.reflect_in_mask(model.pts, model.seg, np.asarray(model.centre, float),  # all points
                                     K.facet_normal(model.aux, a, e), model._r, model._c, model._cam, mask.sub,
                                     mask.r0, mask.c0)
            np.testing.assert_array_equal(where[ins], np.flatnonzero(full[2]))
            np.testing.assert_array_equal(where[usable], np.flatnonzero(full[3]))
            np.testing.assert_array_equal(uv[ins], full[0][full[2]])
            np.testing.assert_array_equal(nrm[usable], full[1][full[3]])
            checked += int(full[2].sum() > 0)
        a, e = centre + [1.001 * width / rate, 0.0]  # beyond: all points, and a new reference
        assert not project(a, e)[4] and tuple(ref[1:]) == (a, e)
    assert checked >= 30
