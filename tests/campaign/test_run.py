"""Campaign runs: selection on real frames, canting plumbing with a truth inspector, resume after SIGKILL, bad input."""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")

import pihim  # noqa: E402
from pihim.campaign.logs import FrameRecord, format_utc, read_frames_csv, write_frames_csv  # noqa: E402
from pihim.campaign.run import RunParameters, run_campaign  # noqa: E402
from pihim.cli import main  # noqa: E402
from pihim.errors import PihimInputError  # noqa: E402

#: The folder holding the pihim these tests import (the installed copy or src/): the commands they start run the same
#: code, and use the numba cache that copy's earlier runs filled.
PIHIM_ROOT = str(Path(pihim.__file__).resolve().parents[1])


class TruthInspector:
    """Returns the rendered truth as the canting of each facet (relative to the mean), so the plumbing is scored."""

    def __init__(self, truth: dict) -> None:
        self.facets = {h["name"]: h["facets"] for h in truth["heliostats"]}
        self.calls: list[tuple[str, str]] = []

    def __call__(self, raw, log, field, hua, target):
        from pihim.inspection.canting import CantingResult, FacetCanting
        from pihim.inspection.pipeline import InspectionResult

        self.calls.append((hua, target))
        f = self.facets[hua]
        az = np.array([x["az_mrad"] for x in f])
        el = np.array([x["el_mrad"] for x in f])
        facets = tuple(FacetCanting(x["id"], True, None, float(a - az.mean()), float(e - el.mean()), 0.1, 0.1,
                                    points=50) for x, a, e in zip(f, az, el, strict=True))
        return InspectionResult(hua, target, {}, {}, CantingResult(hua, target, facets, 0.0, 0.0), {})


def _truth(flight: Path) -> dict:
    return json.loads((flight / "truth" / "flight.json").read_text())


def test_selection_finds_the_planned_pairs(flight_copy, tmp_path) -> None:
    s = run_campaign([flight_copy], tmp_path / "c.sqlite", workers=1, processes=False,
                     parameters=RunParameters(stages="select"))
    assert s["counts"]["frames"]["selected"] == 2
    db = sqlite3.connect(tmp_path / "c.sqlite")
    got = sorted(db.execute("SELECT hua, target FROM candidate WHERE selected = 1").fetchall())
    want = sorted((f["hua"], f["target"]) for f in _truth(flight_copy)["frames"])
    assert got == want  # the pair the plan imaged at each capture, found from the raw frame and its log only


def test_canting_stage_combines_per_heliostat_and_reruns_add_nothing(flight_copy, tmp_path) -> None:
    truth = _truth(flight_copy)
    insp = TruthInspector(truth)
    store = tmp_path / "c.sqlite"
    s1 = run_campaign([flight_copy], store, workers=1, processes=False, inspector=insp)
    assert s1["counts"]["observations"] == {"done": 2, "failed": 0}
    assert s1["counts"]["heliostats_measured"] == 2
    db = sqlite3.connect(store)
    for hua in {f["hua"] for f in truth["frames"]}:
        rows = db.execute("SELECT facet, az_mrad, el_mrad, frame_ids, pihim_version, parameters FROM facet_result "
                          "JOIN heliostat ON heliostat.id = facet_result.heliostat_id WHERE heliostat.name = ? "
                          "ORDER BY facet", (hua,)).fetchall()
        f = {h["name"]: h["facets"] for h in truth["heliostats"]}[hua]
        az = np.array([x["az_mrad"] for x in f])
        np.testing.assert_allclose([r[1] for r in rows], az - az.mean(), atol=1e-9)
        assert json.loads(rows[0][3])[0].startswith("f1/") and rows[0][4] and json.loads(rows[0][5])["stages"] == "all"
    n_facets = db.execute("SELECT count(*) FROM facet_result").fetchone()[0]
    calls = len(insp.calls)
    s2 = run_campaign([flight_copy], store, workers=1, processes=False, inspector=insp)
    assert s2["processed_this_run"]["frames_selected"] == 0 and s2["processed_this_run"]["observations"] == 0
    assert len(insp.calls) == calls  # nothing inspected twice
    assert db.execute("SELECT count(*) FROM facet_result").fetchone()[0] == n_facets
    assert db.execute("SELECT count(*) FROM observation").fetchone()[0] == 2


def _many_frames(flight: Path, n: int) -> None:
    """Rewrite frames.csv with ``n`` frames 0.1 s apart, cycling through the rendered files and their poses."""
    base = read_frames_csv(flight / "frames.csv")
    t0 = base[0].time_utc_s
    frames = [FrameRecord(f"{k:06d}", base[k % len(base)].file, t0 + 0.1 * k, base[k % len(base)].pose)
              for k in range(n)]
    write_frames_csv(flight / "frames.csv", frames)


def _cli(*args: str, **kw) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": PIHIM_ROOT}
    return subprocess.Popen([sys.executable, "-m", "pihim", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True, **kw)


def test_sigkill_mid_run_then_rerun_loses_and_duplicates_nothing(flight_copy, tmp_path) -> None:
    n = 160
    _many_frames(flight_copy, n)
    store = tmp_path / "c.sqlite"
    proc = _cli("campaign", "run", str(flight_copy), "--store", str(store), "--stages", "select", "--workers", "1")
    _kill_when(proc, store, "SELECT count(*) FROM frame WHERE stage != 'pending'", 20, timeout_s=120)
    db = sqlite3.connect(store)
    finished_first = dict(db.execute("SELECT frame_key, run_id FROM frame WHERE stage != 'pending'").fetchall())
    assert 20 <= len(finished_first) < n
    cand_first = db.execute("SELECT count(*) FROM candidate").fetchone()[0]
    assert cand_first == len(finished_first)  # each frame's selection was written whole, with its frame
    db.close()

    again = _cli("campaign", "run", str(flight_copy), "--store", str(store), "--stages", "select", "--workers", "1",
                 "--json")
    out, err = again.communicate(timeout=180)
    assert again.returncode == 0, err.decode()
    summary = json.loads(out)
    db = sqlite3.connect(store)
    assert db.execute("SELECT count(*) FROM frame WHERE stage = 'pending'").fetchone()[0] == 0
    assert summary["processed_this_run"]["frames_selected"] == n - len(finished_first)  # finished frames not redone
    runs = dict(db.execute("SELECT frame_key, run_id FROM frame").fetchall())
    assert all(runs[k] == r for k, r in finished_first.items())
    # no lost, no duplicated result: one candidate per frame, the pair its file shows
    truth = {f"frames/{f['frame_id']}.tiff": (f["hua"], f["target"]) for f in _truth(flight_copy)["frames"]}
    rows = db.execute("SELECT frame.frame_key, frame.file, candidate.hua, candidate.target FROM candidate JOIN frame "
                      "ON frame.id = candidate.frame_id").fetchall()
    assert len(rows) == n and len({r[0] for r in rows}) == n
    assert all((h, t) == truth[f] for _, f, h, t in rows)
    assert db.execute("SELECT count(*) FROM run").fetchone()[0] == 2


def test_sigkill_in_the_canting_stage_then_rerun_redoes_no_observation(flight_copy, tmp_path) -> None:
    """The whole chain (polar, selection, the real inspector on the 3 chosen frames of each pair) killed with SIGKILL
    once some observations are written; the rerun inspects only the rest, keeps the first run's rows and writes no
    duplicate."""
    n = 24
    _many_frames(flight_copy, n)
    store = tmp_path / "c.sqlite"
    proc = _cli("campaign", "run", str(flight_copy), "--store", str(store), "--workers", "1")
    _kill_when(proc, store, "SELECT count(*) FROM observation", 2, timeout_s=180)
    db = sqlite3.connect(store)
    first = {r[0]: r[1:] for r in db.execute("SELECT frame_id, id, status, reason, result FROM observation")}
    chosen = 3 * len({(f["hua"], f["target"]) for f in _truth(flight_copy)["frames"]})  # frames_per_pair 3
    assert 2 <= len(first) < chosen
    db.close()

    again = _cli("campaign", "run", str(flight_copy), "--store", str(store), "--workers", "1", "--json")
    out, err = again.communicate(timeout=300)
    assert again.returncode == 0, err.decode()
    summary = json.loads(out)
    db = sqlite3.connect(store)
    rows = db.execute("SELECT frame_id, id, status, reason, result FROM observation").fetchall()
    assert db.execute("SELECT count(*) FROM candidate WHERE chosen = 1").fetchone()[0] == chosen
    assert len(rows) == chosen and len({r[0] for r in rows}) == len(rows)  # one observation per chosen frame
    assert summary["processed_this_run"]["observations"] == len(rows) - len(first)  # finished ones not redone
    now = {r[0]: r[1:] for r in rows}
    assert all(now[k] == v for k, v in first.items())  # the first run's rows kept as written
    n_res, n_keys = db.execute("SELECT count(*), count(DISTINCT heliostat_id || '/' || facet) "
                               "FROM facet_result").fetchone()
    assert n_res == n_keys  # one combined result per heliostat and facet
    assert db.execute("SELECT count(*) FROM run").fetchone()[0] == 2


def _kill_when(proc: subprocess.Popen, store: Path, count_sql: str, at_least: int, *, timeout_s: float) -> None:
    """SIGKILL the run (and its cluster's process group) once ``count_sql`` counts ``at_least`` rows in its store."""
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if store.exists():
                try:
                    with sqlite3.connect(store, timeout=1) as db:
                        n = db.execute(count_sql).fetchone()[0]
                except sqlite3.OperationalError:
                    n = 0
                if n >= at_least:
                    os.kill(proc.pid, signal.SIGKILL)
                    break
            time.sleep(0.02)
    finally:
        proc.wait(timeout=30)
        if _group_alive(proc.pid):  # the local cluster's worker processes
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == -signal.SIGKILL, "the run finished before it could be killed"


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


# --------------------------------------------------------------------------- bad input, through the CLI


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _prime_store(flight: Path, store: Path) -> str:
    """A store with the flight's selection (in-process cluster: no worker start-up); its digest."""
    run_campaign([flight], store, workers=1, processes=False, parameters=RunParameters(stages="select"))
    return _sha(store)


def test_log_not_covering_the_frames_exit_2(flight_copy, tmp_path, capsys) -> None:
    store = tmp_path / "c.sqlite"
    before = _prime_store(flight_copy, store)
    settings = json.loads((flight_copy / "flight.json").read_text())
    # a ULog that ends before the second frame
    from pihim.campaign.logs import write_ulog
    from pihim.field.geodesy import enu_to_geodetic

    frames = read_frames_csv(flight_copy / "frames.csv")
    t = np.linspace(frames[0].time_utc_s - 1, frames[0].time_utc_s + 1, 21)
    site = settings["site"]
    lat, lon, h = enu_to_geodetic(np.zeros((21, 3)) + [0, 0, 25.0],
                                  (site["latitude_deg"], site["longitude_deg"], site["height_m"]))
    write_ulog(flight_copy / "flight.ulg", boot_utc_s=t[0] - 5, attitude={"t": t, "quat": np.tile([0, 0, 0, 1.0], (21, 1))},
               position={"t": t, "latitude_deg": lat, "longitude_deg": lon, "height_m": h})
    write_frames_csv(flight_copy / "frames.csv", [FrameRecord(f.frame_id, f.file, f.time_utc_s) for f in frames])
    settings["log"] = "flight.ulg"
    (flight_copy / "flight.json").write_text(json.dumps(settings))
    capsys.readouterr()
    assert main(["campaign", "run", str(flight_copy), "--store", str(store), "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not covered by the log" in err[0] and "after the last position sample" in err[0]
    assert _sha(store) == before


def test_corrupt_log_exit_2(flight_copy, tmp_path, capsys) -> None:
    settings = json.loads((flight_copy / "flight.json").read_text())
    (flight_copy / "flight.bin").write_bytes(b"\xa3\x95\x80" + b"\x01" * 40)
    settings["log"] = "flight.bin"
    settings["geoid_undulation_m"] = -22.0
    (flight_copy / "flight.json").write_text(json.dumps(settings))
    assert main(["campaign", "run", str(flight_copy), "--store", str(tmp_path / "c.sqlite")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "DataFlash" in err[0]
    assert not (tmp_path / "c.sqlite").exists()


@pytest.mark.parametrize("change, msg", [
    (dict(heliostats=[{"name": "5E3", "az_deg": 180.0, "el_deg": 40.0}, {"name": "5e3", "az_deg": 183.0,
                                                                         "el_deg": 40.0}]), "5E3 is listed twice"),
    (dict(aim_point_m=[60.0, 8.8, -5.0]), "'aim_point_m' must be above the ground"),
])
def test_flight_log_refused_once_before_the_store(flight_copy, tmp_path, capsys, change, msg) -> None:
    """A flight's aim point and drive angles are checked when it loads: one line, no store, not every frame
    counted as unreadable on every run."""
    settings = json.loads((flight_copy / "flight.json").read_text())
    (flight_copy / "flight.json").write_text(json.dumps({**settings, **change}))
    assert main(["campaign", "run", str(flight_copy), "--store", str(tmp_path / "c.sqlite")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(flight_copy) in err[0] and msg in err[0], err
    assert not (tmp_path / "c.sqlite").exists()


def test_frame_of_another_camera_exit_2(flight_copy, tmp_path, capsys) -> None:
    import tifffile

    store = tmp_path / "c.sqlite"
    before = _prime_store(flight_copy, store)
    first = read_frames_csv(flight_copy / "frames.csv")[0]
    tifffile.imwrite(flight_copy / first.file, np.zeros((200, 240), np.uint16))
    capsys.readouterr()
    assert main(["campaign", "run", str(flight_copy), "--store", str(store)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another camera" in err[0]
    assert _sha(store) == before


def test_newer_store_exit_2_unchanged(flight_copy, tmp_path, capsys) -> None:
    store = tmp_path / "c.sqlite"
    _prime_store(flight_copy, store)
    with sqlite3.connect(store) as db:
        db.execute("PRAGMA user_version = 99")
    before = _sha(store)
    capsys.readouterr()
    for argv in (["campaign", "run", str(flight_copy), "--store", str(store)],
                 ["campaign", "report", str(store), "--out", str(tmp_path / "r")],
                 ["campaign", "export", str(store), "--out", str(tmp_path / "e")]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "newer than this pihim" in err[0]
    assert _sha(store) == before


def test_unreachable_scheduler_exit_2(flight_copy, tmp_path, capsys) -> None:
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    assert main(["campaign", "run", str(flight_copy), "--store", str(tmp_path / "c.sqlite"),
                 "--scheduler", f"tcp://127.0.0.1:{port}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no dask scheduler answers" in err[0]
    assert not (tmp_path / "c.sqlite").exists()


def test_existing_scheduler_is_used(flight_copy, tmp_path) -> None:
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster:
        s = run_campaign([flight_copy], tmp_path / "c.sqlite", scheduler=cluster.scheduler_address,
                         parameters=RunParameters(stages="select"))
    assert s["scheduler"] == cluster.scheduler_address and s["counts"]["frames"]["selected"] == 2


def test_export_cli(flight_copy, tmp_path) -> None:
    store = tmp_path / "c.sqlite"
    _prime_store(flight_copy, store)
    assert main(["campaign", "export", str(store), "--out", str(tmp_path / "e")]) == 0
    with open(tmp_path / "e" / "candidates.csv", newline="") as fh:
        assert len(list(csv.DictReader(fh))) == 2



def test_export_without_pyarrow_leaves_no_folder(flight_copy, tmp_path, capsys, monkeypatch) -> None:
    store = tmp_path / "c.sqlite"
    _prime_store(flight_copy, store)
    monkeypatch.setitem(sys.modules, "pyarrow", None)  # import pyarrow raises ImportError
    out = tmp_path / "e" / "parquet"
    assert main(["campaign", "export", str(store), "--out", str(out), "--format", "parquet"]) == 2
    assert "Parquet export needs pyarrow" in capsys.readouterr().err
    assert not (tmp_path / "e").exists()


def test_frames_csv_times_are_utc(flight_copy) -> None:
    frames = read_frames_csv(flight_copy / "frames.csv")
    assert format_utc(frames[0].time_utc_s).startswith("2021-05-13T19:00")  # 13:00 MDT = 19:00 UTC


def test_canting_rms_needs_two_facets() -> None:
    from pihim.campaign.run import canting_rms_mrad

    f = [{"used": True, "az_mrad": 1.0, "el_mrad": 0.0}, {"used": True, "az_mrad": -1.0, "el_mrad": 0.0},
         {"used": False, "az_mrad": None, "el_mrad": None}]
    assert canting_rms_mrad(f) == pytest.approx(math.sqrt(0.5))  # sqrt(mean(az^2 + el^2) / 2)
    assert canting_rms_mrad(f[:1]) is None  # one facet is its own reference


@pytest.mark.parametrize("option,value,msg", [
    ("--workers", "99999999999999999999", "--workers 99999999999999999999: at most"),
    ("--workers", "0", "--workers must be an integer >= 1"),
    ("--frames-per-pair", "99999999999999999999", "--frames-per-pair must be in [1, 1000000]"),
    ("--frames-per-pair", "0", "--frames-per-pair must be in [1, 1000000]"),
    ("--min-dolp", "1.5", "--min-dolp must be in [0, 1)"),
    ("--min-dolp", "1", "--min-dolp must be in [0, 1)"),
    ("--min-dolp", "nan", "--min-dolp must be in [0, 1)"),
    ("--min-dolp", "-0.1", "--min-dolp must be in [0, 1)"),
    ("--scheduler", "foo", "not a dask scheduler address tcp://HOST:PORT"),
    ("--scheduler", "tcp://127.0.0.1:99999", "not a dask scheduler address"),
])
def test_out_of_range_run_options_exit_2_before_the_store(flight_copy, tmp_path, capsys, option, value, msg) -> None:
    """Checked up front: no cluster of 10^20 workers, no OverflowError from SQLite, no store file made."""
    store = tmp_path / "c.sqlite"
    assert main(["campaign", "run", str(flight_copy), "--store", str(store), option, value]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pihim: error: ") and msg in err[0], err
    assert not store.exists()


def test_workers_bounded_by_four_per_cpu(flight_copy, tmp_path, capsys, monkeypatch) -> None:
    from pihim.campaign.run import RunParameters, connect, max_local_workers

    monkeypatch.setattr(os, "cpu_count", lambda: 3)
    assert max_local_workers() == 12
    assert main(["campaign", "run", str(flight_copy), "--store", str(tmp_path / "c.sqlite"), "--workers", "13"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "at most 12 local workers (4 x the 3 CPUs" in err[0]
    with pytest.raises(PihimInputError, match="at most 12"):
        connect(None, 13, processes=False)
    with pytest.raises(PihimInputError, match=r"\[1, 1000000\]"):
        RunParameters(frames_per_pair=1_000_001)


def test_scheduler_address_checked_before_connecting() -> None:
    from pihim.campaign.run import check_scheduler_address

    assert check_scheduler_address("tcp://10.0.0.2:8786") == "tcp://10.0.0.2:8786"
    assert check_scheduler_address("10.0.0.2:8786") == "tcp://10.0.0.2:8786"
    assert check_scheduler_address("tls://[::1]:8786") == "tls://[::1]:8786"
    for other in ("ws://proxy.example:8786", "wss://proxy.example:443", "ucx://10.0.0.2:8786"):  # dask comms too
        assert check_scheduler_address(other) == other
    for bad in ("foo", "tcp://host", "tcp://host:0", "tcp://host:65536", "udp://host:8786", "tcp://:8786",
                "tcp://host:8786/x", "tcp://::1:8786"):
        with pytest.raises(PihimInputError, match="not a dask scheduler address"):
            check_scheduler_address(bad)


def test_malformed_scheduler_is_one_line_and_quick(flight_copy, tmp_path) -> None:
    """``--scheduler foo`` used to print a Client.__del__ traceback after its line, 10 s later."""
    t0 = time.monotonic()
    proc = _cli("campaign", "run", str(flight_copy), "--store", str(tmp_path / "c.sqlite"), "--scheduler", "foo")
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    lines = err.decode().strip().splitlines()
    assert len(lines) == 1 and "--scheduler 'foo': not a dask scheduler address" in lines[0], lines
    assert time.monotonic() - t0 < 9  # the old failure waited 10 s for the half-made client
    assert not (tmp_path / "c.sqlite").exists()


def test_an_empty_frame_is_skipped_like_a_truncated_one(flight_copy, tmp_path, capsys) -> None:
    """A zero-byte frame (its header unreadable) is the batch's bad item too: skipped, the other frame processed."""
    frames = read_frames_csv(flight_copy / "frames.csv")
    (flight_copy / frames[1].file).write_bytes(b"")
    store = tmp_path / "c.sqlite"
    assert main(["campaign", "run", str(flight_copy), "--store", str(store), "--stages", "select", "--workers", "1",
                 "--json"]) == 2
    out, err = capsys.readouterr()
    assert json.loads(out)["counts"]["frames"] == {"pending": 0, "selected": 1, "done": 0, "skipped": 1}
    assert err.strip().startswith("pihim: error: 1 of 2 frames could not be read") and len(err.splitlines()) == 1


@pytest.mark.parametrize(("sensor", "needle"), [({"layout": "1,2,3,4", "model": {}}, "layout must place"),
                                                ([1], "'sensor' must be an object, got list"),
                                                ({"model": {"analyser": "x"}}, "analyser must be an object")])
def test_a_bad_sensor_in_flight_json_is_refused_before_the_store(flight_copy, tmp_path, capsys, sensor, needle):
    doc = json.loads((flight_copy / "flight.json").read_text())
    doc["sensor"] = sensor
    _refused_before_the_store(flight_copy, doc, tmp_path, capsys, needle)


def test_a_bad_camera_in_flight_json_names_the_file(flight_copy, tmp_path, capsys):
    """'a camera description must be a mapping, got str' did not say which file."""
    doc = json.loads((flight_copy / "flight.json").read_text())
    doc["camera"] = "triton"
    _refused_before_the_store(flight_copy, doc, tmp_path, capsys, "a camera description must be a mapping, got str")


def _refused_before_the_store(flight_copy, doc, tmp_path, capsys, needle):
    (flight_copy / "flight.json").write_text(json.dumps(doc))
    store = tmp_path / "c.sqlite"
    assert main(["campaign", "run", str(flight_copy), "--store", str(store), "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pihim: error: ") and "flight.json" in err[0] and needle in err[0]
    assert not store.exists()


def test_unreadable_frame_exit_2_others_kept_and_retried(flight_copy, tmp_path, capsys) -> None:
    """A truncated frame is recorded as skipped, the other frame's results are kept, the run says so and exits 2;
    the next run reads the frame again (here repaired) and exits 0."""
    frames = read_frames_csv(flight_copy / "frames.csv")
    bad = flight_copy / frames[1].file
    whole = bad.read_bytes()
    bad.write_bytes(whole[: len(whole) // 2])
    store = tmp_path / "c.sqlite"
    argv = ["campaign", "run", str(flight_copy), "--store", str(store), "--stages", "select", "--workers", "1",
            "--json"]
    assert main(argv) == 2
    out, err = capsys.readouterr()
    summary = json.loads(out)  # the summary is still printed
    assert summary["counts"]["frames"] == {"pending": 0, "selected": 1, "done": 0, "skipped": 1}
    err = err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pihim: error: 1 of 2 frames could not be read") \
        and f"f1/{frames[1].frame_id}" in err[0] and str(store) in err[0], err
    db = sqlite3.connect(store)
    rows = dict(db.execute("SELECT frame_key, stage || ': ' || coalesce(reason, '') FROM frame").fetchall())
    assert rows[frames[0].frame_id].startswith("selected")
    assert rows[frames[1].frame_id].startswith("skipped: unreadable")
    assert db.execute("SELECT count(*) FROM candidate WHERE selected = 1").fetchone()[0] == 1  # the good frame's pair
    db.close()

    bad.write_bytes(whole)  # repaired: the rerun reads it and finishes the campaign
    assert main(argv) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["processed_this_run"]["frames_selected"] == 1
    assert again["counts"]["frames"] == {"pending": 0, "selected": 2, "done": 0, "skipped": 0}


def test_frame_unreadable_at_canting_is_said_as_such(flight_copy, tmp_path) -> None:
    """A frame read at selection and truncated before canting: its pair is stored as failed (not retried), and the
    run's error line says that, not "a rerun tries it again"."""
    from pihim.cli.campaign import _unreadable_status

    store = tmp_path / "c.sqlite"
    run_campaign([flight_copy], store, workers=1, processes=False, parameters=RunParameters(stages="select"))
    frames = read_frames_csv(flight_copy / "frames.csv")
    bad = flight_copy / frames[1].file
    bad.write_bytes(bad.read_bytes()[:1000])
    seen = []
    s = run_campaign([flight_copy], store, workers=1, processes=False, inspector=TruthInspector(_truth(flight_copy)),
                     on_unreadable=lambda *args: seen.append(args))
    assert [(f, stage) for f, _, stage in seen] == [(f"f1/{frames[1].frame_id}", "canting")]
    assert s["counts"]["observations"] == {"done": 1, "failed": 1}
    assert _unreadable_status(seen, 2, store) == 2


def test_unreadable_status_line_names_each_stage(tmp_path, capsys) -> None:
    from pihim.cli.campaign import _unreadable_status

    assert _unreadable_status([], 5, tmp_path / "s") == 0
    got = [("f/1", "cannot read TIFF", "select"), ("f/2", "cannot read TIFF", "select"),
           ("f/3", "no such file", "canting")]
    assert _unreadable_status(got, 5, tmp_path / "s") == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("pihim: error: 3 of 5 frames could not be read (2 at selection, recorded as skipped "
                           "(a rerun tries them again); 1 at canting, its pairs recorded as failed)")
    assert line.endswith("first: f/1: cannot read TIFF")
    assert _unreadable_status([("f/1", "internal error: KeyError: x", "select")], 5, tmp_path / "s") == 1


def test_quiet_interrupt_silences_dask_then_puts_everything_back() -> None:
    """While a run is on, Ctrl-C raises KeyboardInterrupt with dask's loggers at CRITICAL (its shutdown would log
    tracebacks); once the run has closed its cluster, the handler and the loggers' levels are what they were."""
    import logging

    from pihim.campaign.run import _quiet_interrupt

    logging.getLogger("distributed.client").setLevel(logging.WARNING)
    undo = _quiet_interrupt()
    try:
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)
        assert logging.getLogger("distributed.client").level == logging.CRITICAL
        assert logging.getLogger("distributed").level == logging.CRITICAL
    finally:
        undo()
    assert logging.getLogger("distributed.client").level == logging.WARNING
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_quiet_interrupt_sits_over_the_command_lines_handler() -> None:
    """Under the pihim process's handler (pihim._interrupts.Interrupts, also when run as ``python -m pihim``) the
    dask loggers are silenced too, the press goes on to that handler, and undo puts it back."""
    import logging

    from pihim._interrupts import Interrupts
    from pihim.campaign.run import _quiet_interrupt

    presses = Interrupts(stop=lambda status: None)
    previous = signal.signal(signal.SIGINT, presses)
    try:
        logging.getLogger("distributed.client").setLevel(logging.WARNING)
        undo = _quiet_interrupt()
        try:
            assert signal.getsignal(signal.SIGINT) is not presses
            with pytest.raises(KeyboardInterrupt):
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(1)
            assert presses.first is not None  # the press reached the command line's handler
            assert logging.getLogger("distributed.client").level == logging.CRITICAL
        finally:
            undo()
        assert signal.getsignal(signal.SIGINT) is presses
        assert logging.getLogger("distributed.client").level == logging.WARNING
    finally:
        signal.signal(signal.SIGINT, previous)


def test_ctrl_c_stops_the_run_quietly_exit_130(flight_copy, tmp_path) -> None:
    """SIGINT to the whole process group, as a terminal's Ctrl-C: the workers ignore it, the client stops the run
    and closes the cluster; no worker or dask shutdown traceback (there used to be 60-120 lines)."""
    _many_frames(flight_copy, 160)
    store = tmp_path / "c.sqlite"
    proc = _cli("campaign", "run", str(flight_copy), "--store", str(store), "--stages", "select", "--workers", "2")
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                with sqlite3.connect(store, timeout=1) as db:
                    if db.execute("SELECT count(*) FROM frame WHERE stage != 'pending'").fetchone()[0] >= 5:
                        break
            except sqlite3.OperationalError:
                pass
            time.sleep(0.05)
        assert proc.poll() is None, "the run finished before it could be interrupted"
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        if _group_alive(proc.pid):
            os.killpg(proc.pid, signal.SIGKILL)
    text = err.decode()
    assert proc.returncode == 130, text
    assert "Traceback" not in text and len(text.strip().splitlines()) <= 1, text


def test_a_truncated_frame_read_by_a_worker_process_is_one_line(flight_copy, tmp_path) -> None:
    """tifffile logged four lines of its own in the worker processes (the command line silences it in its own)."""
    frames = read_frames_csv(flight_copy / "frames.csv")
    path = flight_copy / frames[1].file
    path.write_bytes(path.read_bytes()[:200])  # a header cut short
    proc = _cli("campaign", "run", str(flight_copy), "--store", str(tmp_path / "c.sqlite"), "--stages", "select",
                "--workers", "1", "--json")
    out, err = proc.communicate(timeout=180)
    assert proc.returncode == 2
    assert json.loads(out)["counts"]["frames"]["skipped"] == 1
    lines = err.decode().strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pihim: error: 1 of 2 frames could not be read"), lines
