"""Synthetic flights: frames along the passes at a frame rate, logged poses matched back to the truth."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from pihim.campaign.flight import load_flight, simulate_flight
from pihim.campaign.logs import read_frames_csv
from pihim.errors import PihimInputError


def _angle_deg(a, b) -> float:
    r = np.asarray(a) @ np.asarray(b).T
    return math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(r) - 1) / 2))))


@pytest.mark.parametrize("log", ["dataflash", "ulog"])
def test_fps_flight_poses_match_truth(plan_json, tmp_path, log) -> None:
    pytest.importorskip("pyulog" if log == "ulog" else "pymavlink")
    out = tmp_path / "f"
    s = simulate_flight(plan_json, out, fps=2.0, max_frames=2, size=(64, 54), log=log, seed=2)
    assert s["frames"] == 2
    frames = read_frames_csv(out / "frames.csv")
    assert frames[1].time_utc_s - frames[0].time_utc_s == pytest.approx(0.5, abs=1e-6)
    truth = json.loads((out / "truth" / "flight.json").read_text())["frames"]
    fl = load_flight(out)
    assert fl.log_kind == log and not fl.uncovered
    tol_m, tol_deg = (0.01, 0.01) if log == "dataflash" else (2e-4, 1e-3)
    for m, t in zip(fl.matches, truth, strict=True):
        assert np.linalg.norm(np.subtract(m.pose.position_m, t["pose"]["position_m"])) < tol_m
        assert _angle_deg(m.pose.rotation, t["pose"]["rotation"]) < tol_deg


def test_logged_errors_are_in_the_log_not_in_the_truth(plan_json, tmp_path) -> None:
    out = tmp_path / "f"
    simulate_flight(plan_json, out, max_frames=1, size=(64, 54), log="csv", gps_sigma_m=1.5, seed=4)
    doc = json.loads((out / "truth" / "flight.json").read_text())
    offset = np.array(doc["gps_offset_m"])
    m = load_flight(out).matches[0]
    d = np.subtract(m.pose.position_m, doc["frames"][0]["pose"]["position_m"])
    np.testing.assert_allclose(d, offset, atol=1e-6)  # the constant GPS offset drawn for the flight
    assert np.linalg.norm(offset) > 0


def test_bad_flight_requests(plan_json, tmp_path) -> None:
    with pytest.raises(PihimInputError, match="flights"):
        simulate_flight(plan_json, tmp_path / "x", flight=9, size=(64, 54))
    with pytest.raises(PihimInputError, match="fps"):
        simulate_flight(plan_json, tmp_path / "x", fps=-1.0, size=(64, 54))
    with pytest.raises(PihimInputError, match="no flight.json"):
        load_flight(tmp_path)


def _plan_with(plan_json, tmp_path, edit) -> str:
    doc = json.loads(plan_json.read_text())
    edit(doc)
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(doc))  # json writes NaN as NaN, which Python's reader accepts
    return str(path)


def _nan_capture_x(doc) -> None:
    wps = doc["flights"][0]["waypoints"]
    wps[next(k for k, w in enumerate(wps) if w.get("capture"))]["x_m"] = float("nan")


@pytest.mark.parametrize("edit,msg", [
    (_nan_capture_x, r"flights\[0\]\.waypoints\[\d+\]\.x_m must be finite, got nan"),
    (lambda d: d["passes"][0]["waypoints"][1].update(z_m=float("inf")),
     r"passes\[0\]\.waypoints\[1\]\.z_m must be finite"),
    (lambda d: d.pop("passes"), "the plan has no 'passes' list"),
    (lambda d: d["flights"][0]["waypoints"][0].pop("heading_deg"),
     r"flights\[0\]\.waypoints\[0\] has no 'heading_deg'"),
    # refused by the first frame, after the folders were made: they go again
    (lambda d: d.update(time_iso="2021-05-13T23:00:00-06:00"), "the sun is below the horizon"),
    # the file was not named
    (lambda d: d.update(time_iso="garbage"), r"plan\.json: time_iso: time 'garbage' is not an ISO 8601 date-time"),
    (lambda d: [q.update(target="99E99") for p in d["passes"] for q in p.get("predictions", [])],
     "unknown heliostat '99E99'"),
    # an overflow in the timeline once (an internal error)
    (lambda d: d["flights"][0]["waypoints"][2].update(z_m=1e300),
     r"waypoint 2 of flight 1: the camera at \(.*, 1e\+300\) is more than 10 km"),
])
def test_malformed_plan_one_line_exit_2_nothing_written(plan_json, tmp_path, capsys, edit, msg) -> None:
    """A capture waypoint at x = NaN used to be dropped silently, a plan without passes was a KeyError; a refused
    first frame left empty folders."""
    from pihim.cli import main

    plan = _plan_with(plan_json, tmp_path, edit)
    out = tmp_path / "flight"
    assert main(["simulate-flight", plan, "--out", str(out), "--max-frames", "1", "--size", "64x54"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pihim: error: ") and re.search(msg, err[0]), err
    assert not out.exists()
    with pytest.raises(PihimInputError, match=msg):
        simulate_flight(plan, out, max_frames=1, size=(64, 54))
    assert not out.exists()


@pytest.mark.parametrize("option, api, msg", [
    ("--gps-sigma-m", "gps_sigma_m", r"GPS sigma \(m\) must be a finite number in \[0, 1000\]"),
    ("--attitude-sigma-deg", "attitude_sigma_deg", r"attitude sigma \(deg\) must be a finite number in \[0, 180\]"),
    ("--canting-sigma-mrad", "canting_sigma_mrad", r"canting sigma \(mrad\) must be a finite number in \[0, 1000\]"),
])
def test_huge_noise_is_one_line_exit_2_nothing_written(plan_json, tmp_path, capsys, option, api, msg) -> None:
    """1e308 overflowed the logged poses (numpy warnings, a flight of meaningless positions, exit 0)."""
    from pihim.cli import main

    out = tmp_path / "flight"
    assert main(["simulate-flight", str(plan_json), "--out", str(out), "--max-frames", "1", "--size", "64x54",
                 option, "1e308"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"pihim: error: {option} must be a finite number in [0, "), err
    assert not out.exists()
    with pytest.raises(PihimInputError, match=msg):
        simulate_flight(plan_json, out, max_frames=1, size=(64, 54), **{api: 1e308})
    assert not out.exists()


# --------------------------------------------------------------------------- resuming a killed run

RESUME = {"max_frames": 3, "size": (64, 54), "log": "ulog", "seed": 5}


def _tree(d) -> dict[str, bytes]:
    return {p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def _assert_same_tree(a, b) -> None:
    ta, tb = _tree(a), _tree(b)
    assert sorted(ta) == sorted(tb)
    assert [k for k in ta if ta[k] != tb[k]] == []


def _count_renders(mp) -> list[str]:
    """Record the frame time of every simulate_frame call (the real renderer still runs)."""
    import pihim.render.simulate as sim_mod

    calls: list[str] = []
    real = sim_mod.simulate_frame

    def counted(field, time, **kwargs):
        calls.append(time)
        return real(field, time, **kwargs)

    mp.setattr(sim_mod, "simulate_frame", counted)
    return calls


@pytest.fixture()
def renders(monkeypatch) -> list[str]:
    return _count_renders(monkeypatch)


@pytest.fixture(scope="module")
def fresh_flight(tmp_path_factory, plan_json):
    """A fresh run of RESUME (the reference of every resumed run), its summary and its frame times."""
    with pytest.MonkeyPatch.context() as mp:
        calls = _count_renders(mp)
        out = tmp_path_factory.mktemp("fresh") / "f"
        summary = simulate_flight(plan_json, out, **RESUME)
    assert summary["rendered"] == 3 and summary["reused"] == 0 and len(calls) == 3
    return out, summary, calls


def _summary_counts(s) -> tuple[int, int, int]:
    return s["frames"], s["rendered"], s["reused"]


def test_rerun_of_a_killed_flight_renders_only_the_missing_frames(plan_json, tmp_path, fresh_flight, renders) -> None:
    ref, ref_summary, times = fresh_flight
    out = tmp_path / "f"

    class Killed(BaseException):
        pass

    def kill_at_third(frames_done, total):
        if frames_done == 2:
            raise Killed  # after frame 000001 is on disk: no frames.csv, log, truth/flight.json nor flight.json
    with pytest.raises(Killed):
        simulate_flight(plan_json, out, progress=kill_at_third, **RESUME)
    assert not (out / "flight.json").exists() and len(list((out / "frames").iterdir())) == 2
    renders.clear()
    s = simulate_flight(plan_json, out, **RESUME)
    assert renders == times[2:] and _summary_counts(s) == (3, 1, 2)
    _assert_same_tree(out, ref)
    assert {k: v for k, v in s.items() if k not in ("out", "files", "rendered", "reused")} == \
        {k: v for k, v in ref_summary.items() if k not in ("out", "files", "rendered", "reused")}

    # a complete flight is reused whole; damaged frames are rendered again, byte for byte as before
    renders.clear()
    assert _summary_counts(simulate_flight(plan_json, out, **RESUME)) == (3, 0, 3) and renders == []
    (out / "frames" / "000000.tiff").write_bytes(b"")  # size 0
    doc = json.loads((out / "truth" / "000002.json").read_text())
    (out / "truth" / "000002.json").write_text(json.dumps(doc)[:-200])  # cut short: corrupt JSON
    s = simulate_flight(plan_json, out, **RESUME)
    assert renders == [times[0], times[2]] and _summary_counts(s) == (3, 2, 1)
    _assert_same_tree(out, ref)


def test_rerun_replaces_a_frame_of_another_shape_or_without_truth(plan_json, tmp_path, fresh_flight, renders) -> None:
    import shutil

    import tifffile

    ref, _, times = fresh_flight
    out = tmp_path / "f"
    shutil.copytree(ref, out)
    (out / "flight.json").unlink()
    tifffile.imwrite(out / "frames" / "000001.tiff", np.zeros((54, 66), np.uint16))  # another camera's frame
    (out / "truth" / "000002.json").unlink()  # killed between the TIFF and its truth
    s = simulate_flight(plan_json, out, **RESUME)
    assert renders == times[1:] and _summary_counts(s) == (3, 2, 1)
    _assert_same_tree(out, ref)


def test_shorter_rerun_reuses_its_frames_and_removes_the_rest(plan_json, tmp_path, fresh_flight, renders) -> None:
    import shutil

    ref, _, _ = fresh_flight
    out = tmp_path / "f"
    shutil.copytree(ref, out)
    s = simulate_flight(plan_json, out, **{**RESUME, "max_frames": 2})
    assert renders == [] and _summary_counts(s) == (2, 0, 2)
    fresh = tmp_path / "fresh" / "f"
    simulate_flight(plan_json, fresh, **{**RESUME, "max_frames": 2})
    _assert_same_tree(out, fresh)  # 000002.tiff / .json of the longer run are gone
    assert [r.frame_id for r in read_frames_csv(out / "frames.csv")] == ["000000", "000001"]


def test_frames_of_other_code_are_rendered_again(plan_json, tmp_path, fresh_flight, renders, monkeypatch) -> None:
    import shutil

    import pihim.campaign.flight as flight_mod

    ref, _, _ = fresh_flight
    out = tmp_path / "f"
    shutil.copytree(ref, out)
    assert flight_mod._code_sha256() == flight_mod._code_sha256()  # deterministic
    monkeypatch.setattr(flight_mod, "_code_sha256", lambda: "0" * 64)  # as after an edit of pihim's sources
    s = simulate_flight(plan_json, out, **RESUME)
    assert len(renders) == 3 and _summary_counts(s) == (3, 3, 0)


@pytest.mark.parametrize("change", [{"seed": 6}, {"size": (64, 56)}, {"canting_sigma_mrad": 1.0}])
def test_other_inputs_render_every_frame_again(plan_json, tmp_path, fresh_flight, renders, change) -> None:
    import shutil

    ref, _, _ = fresh_flight
    out = tmp_path / "f"
    shutil.copytree(ref, out)
    s = simulate_flight(plan_json, out, **{**RESUME, **change})
    assert len(renders) == 3 and _summary_counts(s) == (3, 3, 0)
    frame = json.loads((out / "truth" / "000000.json").read_text())
    assert frame["truth"]["simulation"]["inputs_sha256"] != \
        json.loads((ref / "truth" / "000000.json").read_text())["truth"]["simulation"]["inputs_sha256"]


def test_cli_resumes_a_killed_run_and_says_so(plan_json, tmp_path, capsys, renders) -> None:
    from pihim.cli import main

    out = tmp_path / "flight"
    argv = ["simulate-flight", str(plan_json), "--out", str(out), "--max-frames", "2", "--size", "64x54"]
    assert main(argv) == 0
    (out / "flight.json").unlink()  # as if killed before its last write
    renders.clear()
    capsys.readouterr()
    assert main(argv) == 0 and renders == []
    assert "wrote 2 frames (64x54, 2 reused from an earlier run)" in " ".join(capsys.readouterr().err.split())


def test_killed_rerun_over_a_complete_flight_leaves_it_incomplete(plan_json, tmp_path, fresh_flight) -> None:
    import shutil

    ref, _, _ = fresh_flight
    out = tmp_path / "f"
    shutil.copytree(ref, out)

    class Killed(BaseException):
        pass

    def kill(done, total):
        if done == 1:
            raise Killed
    with pytest.raises(Killed):  # another seed over the finished seed-5 flight, killed after one frame
        simulate_flight(plan_json, out, progress=kill, **{**RESUME, "seed": 6})
    # the directory no longer says it is complete, and holds no stale log of the old run
    assert not (out / "flight.json").exists() and not (out / "frames.csv").exists()
    assert not (out / "flight.ulg").exists() and not (out / "truth" / "flight.json").exists()
    assert not (out / ".simulate-flight.lock").exists()


def test_rerun_reuses_frames_whatever_the_plan_path_spelling(plan_json, tmp_path, fresh_flight, renders,
                                                           monkeypatch) -> None:
    import shutil

    ref, _, _ = fresh_flight
    out = tmp_path / "f"
    shutil.copytree(ref, out)
    monkeypatch.chdir(plan_json.parent)
    s = simulate_flight(plan_json.name, out, **RESUME)  # relative, not the absolute path of the first run
    assert renders == [] and _summary_counts(s) == (3, 0, 3)


def test_rerun_with_another_log_kind_and_unrelated_files(plan_json, tmp_path, fresh_flight, renders) -> None:
    import shutil

    ref, _, _ = fresh_flight
    out = tmp_path / "f"
    shutil.copytree(ref, out)
    for name in ("frames/42.tiff", "frames/0000007.tiff", "truth/notes.json"):
        (out / name).write_bytes(b"mine")
    s = simulate_flight(plan_json, out, **{**RESUME, "log": "csv"})
    assert renders == [] and s["log"] == "frames.csv"
    assert not (out / "flight.ulg").exists()  # the ulog of the first run is gone with it
    for name in ("frames/42.tiff", "frames/0000007.tiff", "truth/notes.json"):  # not frame names it writes
        assert (out / name).read_bytes() == b"mine"


def test_one_run_per_directory_at_a_time(plan_json, tmp_path) -> None:
    import fcntl

    out = tmp_path / "f"
    out.mkdir()
    with open(out / ".simulate-flight.lock", "a+b") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)  # as a run in progress holds it
        with pytest.raises(PihimInputError, match="another simulate-flight is writing this directory"):
            simulate_flight(plan_json, out, **RESUME)
    assert not (out / "frames" / "000000.tiff").exists()
