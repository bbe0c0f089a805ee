"""End-to-end tests of ``pihim canting`` on a rendered UFACET frame (8E3 reflecting 7E3, 35 mm, centre crop)."""

import io
import json
import shutil
import sys
from importlib import resources

import jsonschema
import numpy as np
import pytest

from pihim.camera.model import CameraModel
from pihim.cli import main
from pihim.field import nsttf_like_field
from pihim.inspection.canting import CantingResult, FacetCanting
from pihim.inspection.pipeline import combine_results
from pihim.render.simulate import PairPose, simulate_frame, write_simulated_frame

SCHEMA = json.loads(resources.files("pihim").joinpath("schemas/canting.schema.json").read_text())


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    """FRAME.tiff + FRAME.json: the Triton + 35 mm cropped to the middle 1224 x 1024 px."""
    sim = simulate_frame(nsttf_like_field(), "2021-05-13T13:00-06:00", camera=CameraModel(width_px=1224, height_px=1024),
                         pose_request=PairPose("8E3", "7E3"), canting_sigma_mrad=3, gps_sigma_m=0.1,
                         attitude_sigma_deg=0.1, seed=2)
    path = tmp_path_factory.mktemp("canting") / "frame.tiff"
    write_simulated_frame(sim, path)
    return path


@pytest.fixture(scope="module")
def run(frame, tmp_path_factory):
    """One ``pihim canting --json`` run: (exit status, stdout record, canting.json, out dir, stderr)."""
    out = tmp_path_factory.mktemp("out") / "DIR"
    cap = pytest.MonkeyPatch()
    so, se = io.StringIO(), io.StringIO()
    cap.setattr(sys, "stdout", so)
    cap.setattr(sys, "stderr", se)
    try:
        rc = main(["canting", str(frame), "--out", str(out), "--json"])
    finally:
        cap.undo()
    record = json.loads(so.getvalue()) if rc == 0 else None
    on_disk = json.loads((out / "canting.json").read_text()) if rc == 0 else None
    return rc, record, on_disk, out, se.getvalue()


def _truth_errors(frame, record):
    truth = json.loads(frame.with_suffix(".json").read_text())["truth"]
    true = {f["id"]: f for h in truth["heliostats"] if h["name"] == "8E3" for f in h["facets"]}
    used = [f for f in record["facets"] if f["used"]]
    ta = np.array([true[f["id"]]["az_mrad"] for f in used])
    te = np.array([true[f["id"]]["el_mrad"] for f in used])
    ea = np.array([f["az_mrad"] for f in used])
    ee = np.array([f["el_mrad"] for f in used])
    # relative to the mean over the same used facets, as reported
    return ea - (ta - ta.mean()), ee - (te - te.mean())


def test_canting_outputs_schema_valid(run):
    rc, record, on_disk, out, err = run
    assert rc == 0, err
    assert sorted(p.name for p in out.iterdir()) == ["canting.json", "canting.png"]
    jsonschema.validate(record, SCHEMA, cls=jsonschema.Draft202012Validator)
    assert on_disk == record
    assert record["hua"] == "8E3" and record["target"] == "7E3" and record["frames"] == 1
    assert [f["id"] for f in record["facets"]] == list(range(1, 26))
    assert record["facets_used"] >= 2
    assert all(f["reason"] and f["reason_code"] for f in record["facets"] if not f["used"])
    pose = record["inputs"][0]["pose"]
    assert pose["rms_px"] < 1.0 and np.linalg.norm(pose["position_correction_m"]) < 0.5
    assert (out / "canting.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "pihim canting" in err and "facets used" in err


def test_canting_agrees_with_truth(frame, run):
    rc, record, *_ = run
    assert rc == 0
    err_az, err_el = _truth_errors(frame, record)
    # measured 0.004 / 0.048 mrad RMS over facets 13, 17 and 18; 0.41 / 1.08 over 4 before the facets' final fits
    # tried the neighbouring basins (facet 18 was 1.9 mrad off in elevation; facet 8 is now left ambiguous)
    assert np.sqrt(np.mean(err_az**2)) < 0.3
    assert np.sqrt(np.mean(err_el**2)) < 0.3


def _bad(tmp_path, capsys, argv):
    out = tmp_path / "DIR"
    rc = main([*argv, "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and err[0].startswith("pihim: error: "), err
    assert not out.exists()
    return err[0]


def test_frame_without_metadata(frame, tmp_path, capsys):
    lone = tmp_path / "lone.tiff"
    shutil.copy(frame, lone)
    assert "no metadata" in _bad(tmp_path, capsys, ["canting", str(lone)])


def test_metadata_for_another_frame_size(frame, tmp_path, capsys):
    doc = json.loads(frame.with_suffix(".json").read_text())
    doc["log"]["camera"] = CameraModel(width_px=2448, height_px=2048).to_dict()
    meta = tmp_path / "other.json"
    meta.write_text(json.dumps({"log": doc["log"]}))
    assert "2448x2048" in _bad(tmp_path, capsys, ["canting", str(frame), "--meta", str(meta)])


def test_hua_not_in_view(frame, tmp_path, capsys):
    assert "not in view" in _bad(tmp_path, capsys, ["canting", str(frame), "--hua", "5E10", "--target", "7E3"])


def test_empty_names_are_named(frame, tmp_path, capsys):
    """``--hua ''`` said the log had no 'hua' (it has one): now the empty option is named."""
    assert "the hua name is empty (--hua NAME)" in _bad(tmp_path, capsys, ["canting", str(frame), "--hua", ""])
    assert "the target name is empty" in _bad(tmp_path, capsys, ["canting", str(frame), "--target", " "])


def test_unreadable_frame(frame, tmp_path, capsys):
    bad = tmp_path / "bad.tiff"
    bad.write_bytes(b"not a tiff at all")
    shutil.copy(frame.with_suffix(".json"), tmp_path / "bad.json")
    _bad(tmp_path, capsys, ["canting", str(bad)])


def test_missing_hua(frame, tmp_path, capsys):
    doc = json.loads(frame.with_suffix(".json").read_text())
    doc["log"]["hua"] = None
    meta = tmp_path / "nohua.json"
    meta.write_text(json.dumps({"log": doc["log"]}))
    assert "--hua" in _bad(tmp_path, capsys, ["canting", str(frame), "--meta", str(meta)])


def _result(vals, sig, orient=(0.0, 0.0)):
    facets = tuple(FacetCanting(i + 1, v is not None, None if v is not None else "facet not in view",
                                *((v[0], v[1], sig, sig, v[0], v[1], 100, 0.1, 0.5) if v is not None else ()))
                   for i, v in enumerate(vals))
    return CantingResult("8E3", "7E3", facets, *orient)


def test_combine_results_weights_and_rereferences():
    true = np.array([[1.0, -2.0], [-1.0, 0.5], [0.0, 1.5]])
    a = _result([tuple(true[0] - 0.0), tuple(true[1]), tuple(true[2])], 0.1)
    # frame 2 sees only facets 1 and 2: its own reference (their mean) differs by a constant
    sub = true[:2] - true[:2].mean(axis=0)
    b = _result([tuple(sub[0]), tuple(sub[1]), None], 0.01, orient=(0.3, -0.2))
    c = combine_results([a, b])
    assert c.frames == 2
    got = np.array([[f.az_mrad, f.el_mrad] for f in c.facets])
    want = true - true.mean(axis=0)
    np.testing.assert_allclose(got, want, atol=1e-6)
    # facet 3 only in frame 1 (sigma 0.1); facets 1, 2 weighted 1 : 4 (frame 2's sigma 0.01 is floored at 0.05
    # in the weights), the frames agreeing: the weighted mean's standard error from their own sigmas
    assert c.facets[2].az_sigma_mrad == pytest.approx(0.1)
    w = np.array([1 / 0.1**2, 1 / 0.05**2])
    assert c.facets[0].az_sigma_mrad == pytest.approx(np.sqrt(np.sum(w**2 * [0.1**2, 0.01**2])) / w.sum(), rel=1e-4)
    assert c.facets[0].points == 200
    with pytest.raises(Exception, match="different HUAs"):
        combine_results([a, CantingResult("9E3", "7E3", a.facets, 0.0, 0.0)])


def test_combined_in_view_is_the_mean_over_the_frames_that_measured_the_facet():
    """Facet 1 measured in both frames (in view 1.0 and 0.5), facet 2 in the first only (its 0.2 in the second,
    where it was skipped, left out), facet 3 in neither (the mean over all frames, to show why)."""
    import dataclasses

    a = _result([(1.0, 0.0), (0.0, 1.0), None], 0.1)
    b = _result([(1.0, 0.0), None, None], 0.1)
    def seen(res, shares):
        return dataclasses.replace(res, facets=tuple(dataclasses.replace(f, in_view=v)
                                                     for f, v in zip(res.facets, shares, strict=True)))

    a, b = seen(a, (1.0, 0.9, 0.0)), seen(b, (0.5, 0.2, 0.1))
    c = combine_results([a, b])
    assert [f.in_view for f in c.facets] == pytest.approx([0.75, 0.9, 0.05])
    assert [f.used for f in c.facets] == [True, True, False]


def test_combined_sigma_from_the_frames_sigmas_and_their_scatter():
    rng = np.random.default_rng(3)
    true = rng.normal(0.0, 3.0, (10, 2))
    true -= true.mean(axis=0)
    # two frames that agree, each with a sigma below the weights' floor: sigma / sqrt(2), not the floor's
    a = _result([tuple(v) for v in true], 0.007)
    c = combine_results([a, a])
    assert all(f.az_sigma_mrad == pytest.approx(0.007 / np.sqrt(2)) for f in c.facets)
    # one facet 1 mrad apart between the frames: its sigma widens to about half of that, the others' barely
    b_vals = true.copy()
    b_vals[4, 0] += 1.0
    b_vals -= b_vals.mean(axis=0)
    c = combine_results([a, _result([tuple(v) for v in b_vals], 0.007)])
    sig = np.array([f.az_sigma_mrad for f in c.facets])
    assert sig[4] > 0.4 and np.all(np.delete(sig, 4) < 0.1)
    assert c.facets[4].el_sigma_mrad == pytest.approx(0.007 / np.sqrt(2), rel=0.05)
    # a frame without a sigma (too few outline elements): from the scatter with two frames, unknown with one
    none = _result([tuple(v) for v in true], None)
    assert combine_results([none, none]).facets[0].az_sigma_mrad == pytest.approx(0.0, abs=1e-9)
    assert combine_results([none, _result([tuple(true[0]), None, *map(tuple, true[2:])], None)]).facets[1] \
        .az_sigma_mrad is None
    json.dumps(combine_results([none, a]).to_dict(), allow_nan=False)


def _meta_with(frame, tmp_path, **changes):
    """A ``--meta`` file: the frame's log with ``changes`` applied (no truth)."""
    doc = json.loads(frame.with_suffix(".json").read_text())
    log = {**doc["log"], **changes}
    meta = tmp_path / "edited.json"
    meta.write_text(json.dumps({"log": log}))
    return log, meta


def test_heliostat_listed_twice_in_the_log(frame, tmp_path, capsys):
    """Two sets of drive angles for 8E3 (az 3 deg apart): which it had is unknown, so the log is refused."""
    helio = json.loads(frame.with_suffix(".json").read_text())["log"]["heliostats"]
    first = next((h for h in helio if h["name"] == "8E3"), {"name": "8E3", "az_deg": 180.0, "el_deg": 45.0})
    twice = [*helio, first, {**first, "az_deg": first["az_deg"] + 3.0}]
    _, meta = _meta_with(frame, tmp_path, heliostats=twice)
    err = _bad(tmp_path, capsys, ["canting", str(frame), "--meta", str(meta)])
    assert "'heliostats'" in err and "8E3 is listed twice" in err
    # another spelling of the same heliostat is the same heliostat
    _, meta = _meta_with(frame, tmp_path, heliostats=[first, {**first, "name": "8e03"}])
    assert "8E3 is listed twice (as '8e03')" in _bad(tmp_path, capsys, ["canting", str(frame), "--meta", str(meta)])


def test_a_frame_given_twice_is_refused(frame, tmp_path, capsys):
    """The same frame twice was combined as '2 frame(s)', its facets counted twice."""
    link = tmp_path / "again.tiff"
    link.symlink_to(frame)
    shutil.copy(frame.with_suffix(".json"), tmp_path / "again.json")
    assert f"{frame}: given twice; give each frame once" in _bad(tmp_path, capsys, ["canting", str(frame), str(frame)])
    assert f"{frame} and {link}: the same file" in _bad(tmp_path, capsys, ["canting", str(frame), str(link)])


def test_a_logged_heliostat_the_field_lacks_is_named(frame, tmp_path, capsys):
    """The log's entry was complete but was called bad, "(need name, az_deg, el_deg)"; the field lacks 99E99."""
    helio = json.loads(frame.with_suffix(".json").read_text())["log"]["heliostats"]
    _, meta = _meta_with(frame, tmp_path, heliostats=[*helio, {"name": "99E99", "az_deg": 180.0, "el_deg": 45.0}])
    err = _bad(tmp_path, capsys, ["canting", str(frame), "--meta", str(meta)])
    assert "log 'heliostats': unknown heliostat '99E99': not among the" in err and "bad entry" not in err
    _, meta = _meta_with(frame, tmp_path, heliostats=[*helio, {"name": "8E3", "az_deg": "south"}])
    assert "bad entry" in _bad(tmp_path, capsys, ["canting", str(frame), "--meta", str(meta)])


@pytest.mark.parametrize("z", [-5.0, 0.0])
def test_aim_point_not_above_ground(frame, tmp_path, capsys, z):
    _, meta = _meta_with(frame, tmp_path, aim_point_m=[60.0, 8.8, z])
    err = _bad(tmp_path, capsys, ["canting", str(frame), "--meta", str(meta)])
    assert f"'aim_point_m' must be above the ground (z > 0), got z = {z:g} m" in err


def test_empty_heliostats_list_means_every_heliostat_tracks(frame, tmp_path):
    """``heliostats: []`` is a log without drive angles off tracking (docs/campaign.md: "usually []"), not an error."""
    from pihim.field import track_field
    from pihim.inspection.pipeline import field_pose_from_log
    from pihim.sky.sun import Site, sun_position

    field = nsttf_like_field()
    log, _ = _meta_with(frame, tmp_path, heliostats=[])
    got = field_pose_from_log(field, log)
    sun = sun_position(Site(name="log", **{k: log["site"][k] for k in ("latitude_deg", "longitude_deg", "height_m")}),
                       log["time"]).vector
    want = track_field(field, sun, np.asarray(log["aim_point_m"], float))
    np.testing.assert_allclose(got.normals, want.normals, atol=1e-12)


def test_the_figure_marks_measured_facets_less_than_half_in_view():
    """canting.png writes "N % in view" under a measured facet with less than half its outline in the frame (both
    panels), and nothing under one at least half in view or a skipped one."""
    from pihim.inspection.canting_output import canting_figure

    facets = [{"id": i + 1, "used": i < 3, "reason": None if i < 3 else "facet not in view",
               "az_mrad": 0.1 * i if i < 3 else None, "el_mrad": -0.1 * i if i < 3 else None,
               "az_sigma_mrad": 0.05 if i < 3 else None, "el_sigma_mrad": 0.05 if i < 3 else None,
               "in_view": (0.3, 0.5, 1.0, 0.1)[min(i, 3)]} for i in range(25)]
    record = {"facet_grid": {"rows": 5, "cols": 5}, "facets": facets, "orientation_mrad": None, "hua": "8E3",
              "target": "7E3", "frames": 1, "facets_used": 3}
    fig = canting_figure(record)
    marks = [t.get_text() for ax in fig.axes for t in ax.texts if t.get_text().endswith("in view")]
    legend = " ".join(t.get_text() for t in fig.texts)  # the suptitle and the legend below the panels
    facets[0]["in_view"] = 0.6  # none under one half: no mark, and the legend leaves its line out
    plain = canting_figure(record)
    import matplotlib.pyplot as plt

    assert not [t for ax in plain.axes for t in ax.texts if t.get_text().endswith("in view")]
    assert "% in view" in legend and "% in view" not in " ".join(t.get_text() for t in plain.texts)
    plt.close(fig)
    plt.close(plain)
    assert marks == ["30 % in view", "30 % in view"]
