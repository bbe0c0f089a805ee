"""``pihim demo``: the whole chain (plan, render, inspect, score, report) on a small centre crop."""

import io
import json
import re
import sys

import numpy as np
import pytest

from pihim.cli import main


def _run(args):
    cap = pytest.MonkeyPatch()
    so, se = io.StringIO(), io.StringIO()
    cap.setattr(sys, "stdout", so)
    cap.setattr(sys, "stderr", se)
    try:
        rc = main(args)
    finally:
        cap.undo()
    return rc, so.getvalue(), se.getvalue()


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "DIR"
    rc, so, se = _run(["demo", "--out", str(out), "--pairs", "1", "--size", "1224x1024", "--json"])
    return rc, json.loads(so) if rc == 0 else None, out, se


def test_demo_writes_a_report_whose_every_link_resolves(demo_run):
    rc, doc, out, err = demo_run
    assert rc == 0, err
    assert json.loads((out / "demo.json").read_text()) == doc
    # with --json too, the summary and per-pair lines go to stderr (stdout holds the JSON alone)
    pair = doc["pairs"][0]
    assert f"{pair['hua']}/{pair['target']}: " in err and f"report: {out / 'report.html'}" in err
    page = (out / "report.html").read_text()
    links = re.findall(r'(?:src|href)="([^"]+)"', page)
    assert any(s.endswith("plan.png") for s in links)
    assert sum(s.endswith(".png") for s in links) >= 8  # plan map, 6 previews and edge maps, canting figure
    for link in links:
        assert (out / link).is_file(), link
    assert not list(out.rglob("*.part*"))  # no temporary file left behind


def test_demo_scores_against_the_truth_it_never_gave_the_estimator(demo_run):
    rc, doc, out, err = demo_run
    assert rc == 0, err
    (pair,) = doc["pairs"]
    truth = json.loads((out / pair["dir"] / "frame.json").read_text())["truth"]
    true_h = next(h for h in truth["heliostats"] if h["name"] == pair["hua"])
    true_f = {f["id"]: f for f in true_h["facets"]}
    rows = pair["score"]["facets"]
    assert [r["id"] for r in rows] == list(range(1, 26))
    for r in rows:  # the table's truth is the frame's truth
        assert r["true_az_mrad"] == true_f[r["id"]]["az_mrad"] and r["true_el_mrad"] == true_f[r["id"]]["el_mrad"]
    used = [r for r in rows if r["used"]]
    if used:  # relative truth: the mean over the facets used is removed
        assert np.mean([r["true_rel_az_mrad"] for r in used]) == pytest.approx(0.0, abs=1e-9)
        for r in used:
            assert r["err_az_mrad"] == pytest.approx(r["est_az_mrad"] - r["true_rel_az_mrad"])
    plan_aim = json.loads((out / "plan" / "plan.json").read_text())["aim_point"]
    frame_aim = json.loads((out / pair["dir"] / "frame.json").read_text())["log"]["aim_point_m"]
    assert frame_aim == pytest.approx(plan_aim)  # the frames track the aim point the plan was made for
    pose = pair["score"]["pose"]
    assert pose["prior_corner_error_px"] > 20  # the logged pose was really off (GPS 1.5 m, attitude 1 deg) ...
    assert pose["refined_corner_error_px"] < 2.0  # ... and the estimator found the true pose from the image
    assert set(pair["score"]["edge_success"]) == {"S0", "DoLP", "AoP"}
    assert doc["summary"]["pairs"] == 1


@pytest.mark.parametrize("args, words", [
    (["--size", "10x10"], "--size"),
    (["--size", "100000x100000"], "--size"),
    (["--size", "big"], "--size"),
    (["--pairs", "0"], "pairs"),
    (["--seed", "-1"], "seed"),
])
def test_demo_bad_input_is_one_line_and_exit_2(tmp_path, args, words):
    rc, so, se = _run(["demo", "--out", str(tmp_path / "o"), *args])
    assert rc == 2
    lines = [ln for ln in se.splitlines() if ln.strip()]
    assert len(lines) == 1 and words in lines[0], se
    assert not (tmp_path / "o").exists()


def test_demo_out_is_a_file(tmp_path):
    f = tmp_path / "afile"
    f.write_text("x")
    rc, so, se = _run(["demo", "--out", str(f)])
    assert rc == 2 and "not a directory" in se


@pytest.mark.parametrize("avail, flag, expected", [
    (None, [], True),  # memory unknown: the helper runs
    ("tight", [], False),  # room for the demo but not beside it for the helper
    ("ample", [], True),
    ("ample", ["--no-compile-helper"], False),
])
def test_demo_starts_the_compiling_helper_only_where_it_fits(tmp_path, monkeypatch, avail, flag, expected):
    import pihim.cli.demo as cli_demo
    import pihim.demo
    from pihim._warmup import HELPER_BYTES
    from pihim.errors import PihimInputError

    need = 612 * 512 * cli_demo.DEMO_BYTES_PER_PIXEL + cli_demo.DEMO_FIXED_BYTES
    value = {None: None, "tight": need + HELPER_BYTES - 1, "ample": need + HELPER_BYTES}[avail]
    monkeypatch.setattr(cli_demo, "available_memory", lambda: value)
    seen = []

    def fake_run_demo(out, settings, **kw):
        seen.append(kw["compile_helper"])
        raise PihimInputError("stop here")

    monkeypatch.setattr(pihim.demo, "run_demo", fake_run_demo)
    rc, so, se = _run(["demo", "--out", str(tmp_path / "o"), "--size", "612x512", *flag])
    assert rc == 2 and "stop here" in se
    assert seen == [expected]
