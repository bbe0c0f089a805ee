"""Heliostat orientations from the target's reflection (:mod:`pihim.inspection.orientation`): the paper's
+-5 deg search over the HUA's drive angles, the joint solve of the target's and the HUA's angles, and the
drive-angle correction reported for the HUA."""

import numpy as np
import pytest

from pihim.camera.pose import project_points
from pihim.field import apply_canting_deviation
from pihim.inspection.canting import PAPER_GRID_STEP_MRAD, PAPER_ORIENTATION_SPAN_MRAD, estimate_canting
from pihim.inspection.features import edge_points
from pihim.inspection.orientation import drive_correction, refine_orientations
from pihim.inspection.pose import facet_outline_segments, line_normals, refine_pose, sample_segments
from pihim.inspection.reflection import hua_turn_transform, target_outline_segments
from pihim.render.frame import render_frame
from pihim.render.scene import field_scene
from pihim.render.shading import Environment
from pihim.sky.sun import NSTTF, parse_time, sun_position


#: 8E3's true drive angles minus its logged ones, degrees: beyond a facet's own +-1 deg grid
TURN_DEG = (1.4, -1.1)


@pytest.fixture(scope="module")
def turned(ufacet):
    """8E3 really stands 1.4 deg further in azimuth and 1.1 deg lower than the log says; the camera pose is
    refined on its outline at the logged angles, as the pipeline does (so it is right relative to the HUA
    and the target appears turned back about the HUA's pivot)."""
    field, pose, h, az, el, cam, cp, _ = ufacet
    d = pose.drive
    a, e = np.array(d.azimuth_deg, float), np.array(d.elevation_deg, float)
    a[h] += TURN_DEG[0]
    e[h] += TURN_DEG[1]
    true_pose = pose.with_drive(a, e)
    normals = true_pose.facet_normals_local.copy()
    normals[h] = apply_canting_deviation(true_pose.facet_normals_local[h], az, el)
    sun = sun_position(NSTTF, parse_time("2021-05-13T13:00-06:00")).vector
    fr = render_frame(field_scene(true_pose, normals), cam, cp, Environment.clear_sky(sun))
    z = np.zeros_like(fr.s0)
    ep = edge_points(fr.s0, z, z)
    fit = refine_pose(cam, cp, facet_outline_segments(pose.facet_corners()[h]), ep)
    return pose, h, az, el, cam, fit.pose, ep


def test_orientation_search_finds_a_heliostat_turned_beyond_the_facet_grids(turned):
    pose, h, az, el, cam, cp, ep = turned
    # without the search every facet's +-17.5 mrad grid misses its reflection
    alone = estimate_canting(cam, cp, pose, "8E3", "7E3", ep, min_dolp=None, orientation_span_mrad=None)
    assert not any(f.used for f in alone.facets)
    res = estimate_canting(cam, cp, pose, "8E3", "7E3", ep, min_dolp=None, target_orientation=True)
    assert res.search is not None and res.search.step_mrad == pytest.approx(PAPER_GRID_STEP_MRAD)
    assert res.search.span_mrad == pytest.approx(PAPER_ORIENTATION_SPAN_MRAD)
    used = [f for f in res.facets if f.used]
    assert len(used) >= 2  # measured 2 (13, 18); 3 before the final fits tried the neighbouring basins
    ta = np.array([az[f.id - 1] for f in used])
    te = np.array([el[f.id - 1] for f in used])
    # what the HUA's drive-angle correction should be: its true error plus the facets' mean canting as a
    # drive-angle change (a common tilt of the facets is a turn of the HUA)
    want = np.array(TURN_DEG) + np.array(drive_correction(pose, h, ta.mean(), te.mean()))
    # the search's count score finds the turn coarsely (measured 0.09 / 0.49 deg off, 0.22 / 0.37 with the 3
    # facets used before: a common tilt of the facets nearly mimics a turn, the facets' canting blurs the score,
    # and ``want`` holds the mean canting of the facets used) ...
    node = np.degrees(np.array([res.search.az_mrad, res.search.el_mrad]) * 1e-3)
    np.testing.assert_array_less(np.abs(node - want), 0.6)
    # ... the joint least squares of the HUA's turn, the target's angles and the facets' canting to about a
    # tenth of a degree (measured 0.037 / 0.097 deg; 0.007 / 0.101 with the 3 facets used before the final fits
    # tried the neighbouring basins; 0.04 / 0.09 before the facet fits' solver stopped ending where it began on
    # the grid's zero node: the turn and a common tilt of the facets nearly trade off, and the camera pose
    # refined on this crop's partial view of the turned HUA is 2.2 px off at its corners)
    np.testing.assert_allclose(res.drive_correction_deg, want, atol=0.12)
    assert any("HUA's turn" in n for n in res.notes)
    # relative canting as on the logged view (measured 0.024 / 0.041 mrad RMS over 2 facets; 0.37 / 0.10 over 3
    # before the final fits tried the neighbouring basins, 0.02 / 0.05 over 4 before that)
    err_az = np.array([f.az_mrad for f in used]) - (ta - ta.mean())
    err_el = np.array([f.el_mrad for f in used]) - (te - te.mean())
    assert np.sqrt(np.mean(err_az**2)) < 0.6
    assert np.sqrt(np.mean(err_el**2)) < 0.6


def test_refine_orientations_recovers_the_target_and_hua_turns_from_exact_matches(ufacet):
    """Matches made on the logged outline of a view whose target and HUA are both off their logged angles
    (built with FieldPose.with_drive and plane mirroring, not with the solver's own parametrisation):
    the joint solve returns both corrections."""
    field, pose, h, _, _, cam, cp, _ = ufacet
    t = field.index("7E3")
    d = pose.drive
    a, e = np.array(d.azimuth_deg, float), np.array(d.elevation_deg, float)
    a[t] += 0.12
    e[t] -= 0.08
    hua_turn = (0.05, -0.03)
    facets_ = [7, 8, 12, 17, 18]
    rng = np.random.default_rng(5)
    cant = rng.normal(0.0, 2.0, (len(facets_), 2))
    cant -= cant.mean(axis=0)  # the solver holds the facets' mean canting at zero
    pts, seg = sample_segments(target_outline_segments(pose, t), 0.05)
    true_pts, _ = sample_segments(target_outline_segments(pose.with_drive(a, e), t), 0.05)
    pivot, m = hua_turn_transform(pose, h, *hua_turn)
    seen = pivot + (true_pts - pivot) @ m.T
    matches = []
    for (f, (ca, ce)) in zip(facets_, cant, strict=True):
        n = pose.rotations[h] @ apply_canting_deviation(pose.facet_normals_local[h, f - 1], ca, ce)
        c = pose.facet_centres[h, f - 1]
        virt = seen - 2.0 * ((seen - c) @ n)[:, None] * n
        uv = project_points(cam, cp, virt)
        nrm = line_normals(uv, seg)
        ok = np.all(np.isfinite(uv), axis=1) & np.all(np.isfinite(nrm), axis=1)
        matches.append((f - 1, 0.0, 0.0, (pts[ok], uv[ok], nrm[ok])))
    (t_az, t_el), (h_az, h_el) = refine_orientations(cam, cp, pose, h, t, matches)
    assert t_az == pytest.approx(0.12, abs=0.01) and t_el == pytest.approx(-0.08, abs=0.01)
    assert h_az == pytest.approx(hua_turn[0], abs=0.01) and h_el == pytest.approx(hua_turn[1], abs=0.01)


def test_drive_correction_turns_the_normal_like_the_orientation(ufacet):
    _, pose, h, *_ = ufacet
    d = pose.drive
    for a, e in [(25.0, -20.0), (-60.0, 10.0), (0.0, 0.0), (3.0, 80.0)]:
        d_az, d_el = drive_correction(pose, h, a, e)
        az = np.array(d.azimuth_deg, float)
        el = np.array(d.elevation_deg, float)
        az[h] += d_az
        el[h] += d_el
        moved = pose.with_drive(az, el)  # normals from drive angles: independent of drive_correction's inverse
        want = pose.rotations[h] @ apply_canting_deviation(np.array([0.0, 0.0, 1.0]), a, e)
        np.testing.assert_allclose(moved.normals[h], want, atol=1e-12)


def test_target_orientation_is_corrected_from_its_reflection(ufacet):
    """The target 7E3 really stands 0.15 deg further in azimuth and 0.10 deg higher than logged."""
    field, pose, h, az, el, cam, cp, _ = ufacet
    t = field.index("7E3")
    d = pose.drive
    t_az, t_el = np.array(d.azimuth_deg, float), np.array(d.elevation_deg, float)
    t_az[t] -= 0.15
    t_el[t] += 0.10
    normals = pose.facet_normals_local.copy()
    normals[h] = apply_canting_deviation(pose.facet_normals_local[h], az, el)
    sun = sun_position(NSTTF, parse_time("2021-05-13T13:00-06:00")).vector
    fr = render_frame(field_scene(pose.with_drive(t_az, t_el), normals), cam, cp, Environment.clear_sky(sun))
    z = np.zeros_like(fr.s0)
    ep = edge_points(fr.s0, z, z)
    logged = estimate_canting(cam, cp, pose, "8E3", "7E3", ep, min_dolp=None, target_orientation=False)
    res = estimate_canting(cam, cp, pose, "8E3", "7E3", ep, min_dolp=None, target_orientation=True)
    assert res.target_correction_deg is not None
    # measured -0.128 / +0.106 deg
    assert res.target_correction_deg[0] == pytest.approx(-0.15, abs=0.05)
    assert res.target_correction_deg[1] == pytest.approx(0.10, abs=0.05)
    # on the corrected outline more facets pass the residual gate (measured 4 against 3)
    assert sum(f.used for f in res.facets) > sum(f.used for f in logged.facets)
    assert any("corrected" in n for n in res.notes)
