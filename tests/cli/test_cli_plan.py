"""End-to-end tests of ``pihim plan`` on the embedded NSTTF-like field."""

import csv
import json
from importlib import resources
from pathlib import Path

import jsonschema
import pytest

from pihim.cli import main

PLAN_SCHEMA = json.loads(resources.files("pihim").joinpath("schemas/plan.schema.json").read_text())
QGC_SCHEMA = json.loads(resources.files("pihim").joinpath("schemas/qgc-plan.schema.json").read_text())
TIME = "2021-05-13T13:00-06:00"


def test_plan_writes_every_format(tmp_path, capsys):
    out = tmp_path / "plan"
    rc = main(["plan", "--time", TIME, "--aim", "60,8.8,28.9", "--max-altitude", "25", "--out", str(out), "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    names = {"plan.json", "mission.plan", "mission.waypoints", "plan.kml", "litchi.csv", "plan.png"}
    written = {p.name for p in out.iterdir()}
    assert names <= written
    # the whole-plan litchi.csv exceeds Litchi's 99 waypoints: the flights are also written as missions
    parts = sorted(n for n in written - names)
    whole = list(csv.DictReader((out / "litchi.csv").read_text().splitlines()))
    assert len(whole) > 99 and parts and parts[0] == "litchi_01.csv"
    rows = [list(csv.DictReader((out / n).read_text().splitlines())) for n in parts]
    assert all(0 < len(r) <= 99 for r in rows)
    assert sum(len(r) for r in rows) >= len(whole)  # the flights add transits and returns
    plan = json.loads((out / "plan.json").read_text())
    jsonschema.validate(plan, PLAN_SCHEMA)
    jsonschema.validate(json.loads((out / "mission.plan").read_text()), QGC_SCHEMA)
    assert summary["passes"] == len(plan["passes"]) > 10
    assert 0.0 <= summary["coverage"]["either"] <= 1.0
    for p in plan["passes"]:
        assert plan["min_altitude_m"] <= p["altitude_m"] <= 25.0 + 1e-9
        for w in p["waypoints"]:
            assert 0.0 <= w["heading_deg"] < 360.0 and -90.0 <= w["gimbal_pitch_deg"] <= 0.0
    flights = plan["flights"]
    covered = sorted(i for f in flights for i in f["pass_indices"])
    assert covered == sorted(p["index"] for p in plan["passes"] if p["feasible"])


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--time", "2021-05-13T23:00-06:00"], "below the horizon"),
        (["--time", "2021-05-13T13:00"], "utc offset"),
        (["--time", TIME, "--aim", "0,0,-1"], "above the ground"),
        (["--time", TIME, "--heliostats", "8E3,99W1"], "unknown heliostat"),
        (["--time", TIME, "--max-altitude", "8"], "no feasible pass"),
        (["--time", TIME, "--heliostats", "5W1,5E2"], "no scan pass to fly: 5e2: no target heliostat in front"),
    ],
)
def test_impossible_requests(tmp_path, capsys, args, needle):
    out = tmp_path / "p"
    assert main(["plan", *args, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err.lower()
    assert not out.exists()


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs a /proc file system")
def test_out_that_cannot_be_created_is_one_line(capsys):
    # issue 10: 'pihim plan --out /proc/x' was a FileNotFoundError traceback after planning
    assert main(["plan", "--time", TIME, "--heliostats", "8E3", "--out", "/proc/x"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pihim: error: --out /proc/x: cannot create")
