"""Tests of pihim.planning.windows (day sweep) and the ``pihim windows`` command."""

from __future__ import annotations

import csv
import datetime as dt
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pihim.errors import PihimInputError
from pihim.planning.windows import (
    CSV_COLUMNS,
    DaySweep,
    local_timezone,
    paper_agreement,
    parse_date,
    sweep_day,
    write_windows_csv,
    write_windows_png,
)
from pihim.sky.sun import NSTTF, parse_site, sun_position

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "nsttf"


@pytest.fixture(scope="module")
def sweep() -> DaySweep:
    return sweep_day("2021-05-13", step_min=60.0)


def synthetic(fractions, step_min=30.0, start="2021-05-13T07:00", site=NSTTF) -> DaySweep:
    f = np.asarray(fractions, dtype=float)
    times = tuple(pd.date_range(pd.Timestamp(start).tz_localize("America/Denver"), periods=len(f),
                                freq=f"{step_min}min").to_pydatetime())
    z = np.full(len(f), 40.0)
    return DaySweep(date=dt.date(2021, 5, 13), site=site, timezone="America/Denver", times=times, sun_zenith_deg=z,
                    sun_azimuth_deg=z, fraction_planned=np.ones(len(f)), fraction_sky=np.zeros(len(f)),
                    fraction_ground=f, fraction_either=f, n_heliostats=10, step_min=step_min,
                    min_elevation_deg=10.0, n_images=np.zeros(len(f), dtype=np.int64),
                    shifted_passes=np.zeros(len(f), dtype=np.int64))


# --------------------------------------------------------------------------- the sweep


def test_sweep_times_daylight_only(sweep):
    assert len(sweep) > 8
    assert all(isinstance(t, dt.datetime) and str(t.tzinfo) == "America/Denver" for t in sweep.times)
    assert np.all(sweep.sun_elevation_deg >= 10.0)
    assert all(t.date() == dt.date(2021, 5, 13) for t in sweep.times)
    # every excluded hour of the day has the sun below 10 deg (night included)
    hours = pd.date_range(pd.Timestamp("2021-05-13").tz_localize("America/Denver"), periods=24, freq="60min")
    elev = np.asarray(sun_position(NSTTF, hours).elevation_deg)
    assert sorted(hours[elev >= 10.0]) == list(sweep.times)
    assert (elev < 0).any()
    assert {b - a for a, b in zip(sweep.times[:-1], sweep.times[1:])} == {dt.timedelta(minutes=60)}


@pytest.mark.parametrize("day", ["2021-03-14", "2021-05-13", "2021-11-07"])
def test_day_times_follow_elapsed_time_across_dst(day):
    """Oracle: pandas' date_range from local midnight to the next, in elapsed time: the DST days have 23 and 25
    hours (America/Denver), and the times agree instant for instant and in their UTC offsets."""
    from pihim.planning.windows import _day_times

    tz = "America/Denver"
    start = pd.Timestamp(day).tz_localize(tz)
    expect = pd.date_range(start, (pd.Timestamp(day) + pd.Timedelta(days=1)).tz_localize(tz), freq="30min",
                           inclusive="left")
    got = _day_times(dt.date.fromisoformat(day), tz, 30.0)
    assert len(got) == len(expect) == {"2021-03-14": 46, "2021-05-13": 48, "2021-11-07": 50}[day]
    assert [t.isoformat() for t in got] == [t.isoformat() for t in expect]


def test_window_duration_is_elapsed_time_across_dst():
    """01:00 MDT to 01:30 MST on 2021-11-07 is 90 min elapsed, though the wall clocks read 30 min apart."""
    from pihim.planning.windows import Window, _day_times

    times = _day_times(dt.date(2021, 11, 7), "America/Denver", 30.0)
    a, b = times[2], times[5]  # 01:00-06:00 and 01:30-07:00
    assert (a.strftime("%H:%M%z"), b.strftime("%H:%M%z")) == ("01:00-0600", "01:30-0700")
    assert Window(a, b, 1.0, 1.0).duration_min == pytest.approx(90.0)


def test_sweep_fractions(sweep):
    for key in ("planned", "sky", "ground", "either"):
        f = sweep.fractions(key)
        assert f.shape == (len(sweep),) and np.all((f >= 0.0) & (f <= 1.0))
    assert np.all(sweep.fraction_either >= np.maximum(sweep.fraction_sky, sweep.fraction_ground) - 1e-12)
    assert np.all(sweep.fraction_either <= sweep.fraction_planned + 1e-12)
    assert sweep.fraction_planned.max() > 0.5 and sweep.n_images.min() > 0
    # the paper's structure: a minimum near solar noon between better morning and afternoon values
    noon = int(np.argmin(sweep.sun_zenith_deg))
    f = sweep.fraction_either
    assert f[noon] < f[:noon].max() and f[noon] < f[noon + 1:].max()
    with pytest.raises(PihimInputError):
        sweep.fractions("clouds")


def test_polar_night_gives_an_empty_sweep(tmp_path):
    site = parse_site("78.2,15.6,10")
    calls = []
    sw = sweep_day("2021-12-21", site=site, planner=lambda *a, **k: calls.append(1) or ())
    assert len(sw) == 0 and not calls and sw.windows(0.1) == ()
    write_windows_csv(sw, tmp_path / "w.csv")
    assert (tmp_path / "w.csv").read_text().strip() == ",".join(CSV_COLUMNS)
    write_windows_png(sw, tmp_path / "w.png")
    assert (tmp_path / "w.png").stat().st_size > 0
    assert sw.summary()["best"] is None


def test_custom_site_uses_solar_offset():
    site = parse_site("35,-106.5,1700")
    tz = local_timezone(site)
    assert tz.utcoffset(None) == dt.timedelta(hours=-7)
    assert local_timezone(NSTTF) == "America/Denver"
    assert local_timezone(parse_site("51.5,0.1,50")) == "UTC"


@pytest.mark.parametrize("kwargs, needle", [
    ({"date": "2021-13-40"}, "date"),
    ({"date": "13/05/2021"}, "date"),
    ({"date": "2021-05-13", "site": "mars"}, "site"),
    ({"date": "2021-05-13", "step_min": 0.1}, "step"),
    ({"date": "2021-05-13", "min_elevation_deg": 95.0}, "elevation"),
    ({"date": "2021-05-13", "aim_point": (1.0, 2.0)}, "aim"),
    ({"date": "2021-05-13", "aim_point": (0.0, 0.0, -1.0)}, "aim"),
])
def test_sweep_bad_input(kwargs, needle):
    date = kwargs.pop("date")
    with pytest.raises(PihimInputError, match=needle):
        sweep_day(date, **kwargs)


def test_parse_date():
    assert parse_date("2021-03-20") == dt.date(2021, 3, 20)
    assert parse_date(dt.date(2021, 3, 20)) == dt.date(2021, 3, 20)
    for bad in ("2021-3-20", "20210320", "", "2021-02-30"):
        with pytest.raises(PihimInputError):
            parse_date(bad)
    # issue 10: 'pihim windows --date 9999-12-31' was a NotImplementedError from pandas
    for bad in ("9999-12-31", dt.date(9999, 12, 31), "0001-01-01"):
        with pytest.raises(PihimInputError, match="outside the years pihim handles"):
            parse_date(bad)
    assert parse_date("2261-12-31") == dt.date(2261, 12, 31)


# --------------------------------------------------------------------------- windows helper


def test_windows_are_contiguous_runs():
    sw = synthetic([0.1, 0.6, 0.7, 0.4, 0.5, 0.5, 0.55, 0.2, 0.9])
    w = sw.windows(0.5)
    assert [(x.start.strftime("%H:%M"), x.end.strftime("%H:%M")) for x in w] == [
        ("07:30", "08:00"), ("09:00", "10:00"), ("11:00", "11:00")]
    assert w[0].peak_fraction == pytest.approx(0.7) and w[0].mean_fraction == pytest.approx(0.65)
    assert w[1].duration_min == 60.0 and w[2].duration_min == 0.0
    assert len(sw.windows(0.5, min_duration_min=30.0)) == 2
    assert sw.windows(0.95) == ()
    assert sw.windows(0.5, "sky") == ()
    with pytest.raises(PihimInputError):
        sw.windows(1.5)


def test_relative_windows():
    sw = synthetic([0.1, 0.3, 0.4, 0.2, 0.38, 0.1])
    assert [(x.start.strftime("%H:%M"), x.end.strftime("%H:%M")) for x in sw.windows(0.9, relative=True)] == [
        ("08:00", "08:00"), ("09:00", "09:00")]
    assert sw.windows(0.5) == ()
    summ = sw.summary(0.9, relative=True)
    assert summ["threshold_fraction"] == pytest.approx(0.36) and len(summ["windows"]) == 2
    assert synthetic([0.0, 0.0]).windows(0.5, relative=True) == ()


def test_planner_refusals_are_recorded():
    from pihim.field import nsttf_like_field

    def refuse(*args, **kwargs):
        raise PihimInputError("no feasible pass")

    sw = sweep_day("2021-05-13", step_min=240.0, planner=refuse, field=nsttf_like_field())
    assert len(sw) >= 2 and np.all(sw.fraction_either == 0.0) and np.all(sw.fraction_planned == 0.0)
    assert len(sw.planner_errors) == len(sw) and sw.planner_errors[0][1] == "no feasible pass"
    assert sw.summary()["planner_errors"][0][0] == sw.times[0].isoformat()


def _arrays(sw: DaySweep) -> dict:
    keys = ("fraction_planned", "fraction_sky", "fraction_ground", "fraction_either", "n_images", "shifted_passes")
    return {k: getattr(sw, k) for k in keys}


def test_forked_workers_give_the_one_process_result(tmp_path, recwarn):
    """Times shared among forked workers: the same sweep to the bit, planner closures and refusals included."""
    import os

    from pihim.planning.ufacet import plan_passes

    pids = tmp_path / "pids"

    def planner(field, pose, **kwargs):  # a closure: not picklable, inherited by the fork
        with pids.open("a") as fh:
            fh.write(f"{os.getpid()}\n")
        if pose.normals[0, 0] > 0.0:  # the first heliostat faces East: in the morning
            raise PihimInputError("refused here")
        return plan_passes(field, pose, **kwargs)

    # one process first: its ground kernel starts OpenMP here, which the forked workers must not touch
    one = sweep_day("2021-05-13", step_min=180.0, planner=planner, workers=1)
    pids.unlink()
    ticks = []
    two = sweep_day("2021-05-13", step_min=180.0, planner=planner, workers=2,
                    progress=lambda done, total: ticks.append((done, total)))
    assert len(one) >= 4 and one.times == two.times
    for k, v in _arrays(one).items():
        np.testing.assert_array_equal(getattr(two, k), v, err_msg=k)
    assert np.any(one.fraction_either > 0.1)
    assert two.planner_errors == one.planner_errors and len(one.planner_errors) >= 1
    assert ticks == [(k, len(two)) for k in range(1, len(two) + 1)]
    workers = {int(v) for v in pids.read_text().split()}
    assert os.getpid() not in workers and 1 <= len(workers) <= 2  # planned in other processes
    assert not [w for w in recwarn if "worker process died" in str(w.message)]


def test_a_killed_worker_loses_no_time():
    """Workers killed mid-sweep: the times they had not returned are planned here, each once, none lost."""
    import os
    import signal

    from pihim.planning.ufacet import plan_passes

    parent = os.getpid()

    def planner(field, pose, **kwargs):
        if os.getpid() != parent and pose.normals[0, 0] < 0.0:  # a worker meets an afternoon time: killed
            os.kill(os.getpid(), signal.SIGKILL)
        if pose.normals[0, 0] > 0.1:  # the first time (7:00-ish) only
            raise PihimInputError("refused here")
        return plan_passes(field, pose, **kwargs)

    ticks = []
    with pytest.warns(RuntimeWarning, match="worker process died"):
        two = sweep_day("2021-05-13", step_min=120.0, planner=planner, workers=2,
                        progress=lambda done, total: ticks.append((done, total)))
    one = sweep_day("2021-05-13", step_min=120.0, planner=planner, workers=1)
    assert len(two) == len(one) >= 5
    for k, v in _arrays(one).items():
        np.testing.assert_array_equal(getattr(two, k), v, err_msg=k)
    assert two.planner_errors == one.planner_errors and len(one.planner_errors) >= 1
    assert ticks == [(k, len(two)) for k in range(1, len(two) + 1)]


@pytest.mark.parametrize("workers", [0, -1, 65, 1.5, True, "2"])
def test_sweep_refuses_bad_worker_counts(workers):
    with pytest.raises(PihimInputError, match="workers"):
        sweep_day("2021-05-13", workers=workers)


def test_field_without_tower_needs_an_aim_point():
    from pihim.field import nsttf_like_field

    with pytest.raises(PihimInputError, match="aim point"):
        sweep_day("2021-05-13", field=nsttf_like_field(tower=None))


def test_windows_break_at_gaps():
    sw = synthetic([0.8, 0.8, 0.8, 0.8])
    sw = DaySweep(**{**sw.__dict__, "times": (*sw.times[:3], sw.times[3] + dt.timedelta(hours=2))})
    assert len(sw.windows(0.5)) == 2


def test_paper_agreement_on_synthetic_day():
    # 07:00..18:30 every 30 min; favourable exactly in the paper's windows
    times = pd.date_range("2021-05-13T07:00", periods=24, freq="30min")
    inside = [(9.5 <= t.hour + t.minute / 60 <= 11.5) or (14 <= t.hour + t.minute / 60 <= 16) for t in times]
    sw = synthetic(np.where(inside, 0.8, 0.1))
    agree = paper_agreement(sw, 0.5)
    assert agree["paper_covered"] == 1.0 and agree["favourable_inside_paper"] == 1.0 and agree["jaccard"] == 1.0
    assert agree["mean_inside"] == pytest.approx(0.8) and agree["mean_outside"] == pytest.approx(0.1)
    assert "paper_agreement" in sw.summary()
    assert "paper_agreement" not in synthetic([0.5], site=parse_site("10,10,0")).summary()


# --------------------------------------------------------------------------- files


def test_csv_and_png(tmp_path, sweep):
    csv_path = write_windows_csv(sweep, tmp_path / "windows.csv")
    png_path = write_windows_png(sweep, tmp_path / "windows.png", threshold=0.4)
    rows = list(csv.DictReader(csv_path.open()))
    assert tuple(rows[0]) == CSV_COLUMNS and len(rows) == len(sweep)
    for row, t in zip(rows, sweep.times, strict=True):
        ts = pd.Timestamp(row["time"])
        assert ts.tzinfo is not None and ts == t and row["time"].endswith("-06:00")
        assert 0.0 <= float(row["fraction_either"]) <= 1.0
    assert png_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["windows.csv", "windows.png"]


def test_png_write_is_atomic(tmp_path, monkeypatch, sweep):
    target = tmp_path / "windows.png"
    target.write_bytes(b"old")
    from matplotlib.figure import Figure

    def boom(self, *a, **k):
        Path(a[0]).write_bytes(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(Figure, "savefig", boom)
    with pytest.raises(OSError):
        write_windows_png(sweep, target)
    assert target.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["windows.png"]


# --------------------------------------------------------------------------- CLI


def run_cli(argv):
    from pihim.cli import app, main
    from pihim.cli.windows import windows

    if not any(getattr(c, "name", None) == "windows" for c in app.registered_commands):
        app.command("windows")(windows)  # until the lead registers it
    return main(argv)


def test_cli_writes_outputs(tmp_path, capsys):
    out = tmp_path / "w"
    rc = run_cli(["windows", "--date", "2021-05-13", "--step-min", "120", "--out", str(out), "--json"])
    assert rc == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["schema"] == "pihim.windows/1" and rec["n_times"] == len(list(csv.DictReader((out / "windows.csv").open())))
    assert rec["paper_agreement"]["paper_windows_local"] == [["09:30", "11:30"], ["14:00", "16:00"]]
    assert (out / "windows.png").stat().st_size > 0
    assert Path(rec["files"]["csv"]) == out / "windows.csv"


def test_cli_says_what_it_found_without_json(tmp_path, capsys):
    out = tmp_path / "w"
    assert run_cli(["windows", "--date", "2021-05-13", "--step-min", "120", "--out", str(out)]) == 0
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert cap.out == "" and len(lines) == 2
    assert lines[0].startswith("pihim windows 2021-05-13: ") and "times scored; favourable (coverage >= 50 % of" in lines[0]
    assert "of the paper's windows favourable here" in lines[0]  # NSTTF: compared with the paper
    assert lines[1] == f"wrote windows.csv and windows.png to {out}"


@pytest.mark.parametrize("args, needle", [
    (["--date", "2021-05-32"], "date"),
    (["--date", "yesterday"], "date"),
    (["--date", "2021-05-13", "--site", "atlantis"], "site"),
    (["--date", "2021-05-13", "--site", "91,0,0"], "latitude"),
    (["--date", "2021-05-13", "--step-min", "0"], "step"),
    (["--date", "2021-05-13", "--aim", "1,2"], "aim"),
    (["--date", "2021-05-13", "--field", "no-such-field.csv"], "field"),
    (["--date", "2021-05-13", "--facets", "f.csv"], "facets"),
    (["--date", "2021-05-13", "--threshold", "2"], "threshold"),
    (["--date", "2021-05-13", "--max-altitude", "-5"], "altitude"),
    (["--date", "2021-05-13", "--workers", "0"], "workers"),
    (["--date", "2021-05-13", "--workers", "65"], "workers"),
])
def test_cli_bad_input_one_line_exit_2(tmp_path, capsys, args, needle):
    out = tmp_path / "w"
    assert run_cli(["windows", *args, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err.lower()
    assert not out.exists()


def test_cli_refuses_a_day_the_planner_refused_throughout(tmp_path, capsys):
    """--max-altitude 5 m (below every mirror + 5 m): every time was refused, yet the run said 'none' with exit 0."""
    out = tmp_path / "w"
    assert run_cli(["windows", "--date", "2021-05-13", "--step-min", "120", "--max-altitude", "5",
                    "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "the planner refused all 6 times of the day; at 08:00: no feasible pass" in err
    assert not out.exists()
    # some times refused (the tracking mirrors' tops rise above 9.9 m at those): said, and the rest reported
    assert run_cli(["windows", "--date", "2021-05-13", "--step-min", "120", "--max-altitude", "14.9",
                    "--out", str(out)]) == 0
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 3 and lines[1] == ("the planner refused 4 of the 6 times (counted as nothing coverable; "
                                            "--json lists why)")


def test_cli_out_is_a_file(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    assert run_cli(["windows", "--date", "2021-05-13", "--out", str(f)]) == 2
    assert "not a directory" in capsys.readouterr().err


def test_cli_with_the_shared_nsttf_csv(tmp_path, capsys):
    if not (SHARED / "heliostats.csv").is_file():
        pytest.skip("../shared/data/nsttf is not available (fresh clone)")
    out = tmp_path / "w"
    rc = run_cli(["windows", "--date", "2021-03-20", "--step-min", "180", "--field", str(SHARED / "heliostats.csv"),
                  "--facets", str(SHARED / "facet_centroids.csv"), "--no-shift", "--out", str(out), "--json"])
    assert rc == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["n_heliostats"] == rec["settings"]["field_heliostats"] > 200 and rec["settings"]["shift_search"] is None


def test_windows_module_does_not_import_pandas():
    """pandas (with pyarrow, ~0.45 s of CPU) is not needed for a day's times: ``pihim windows`` starts without it."""
    import subprocess
    import sys

    code = ("import sys, datetime; from pihim.planning.windows import _day_times, sweep_day; "
            "_day_times(datetime.date(2021, 5, 13), 'America/Denver', 60.0); print('pandas' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False"]
