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
SUMMARY_SCHEMA = json.loads(resources.files("pihim").joinpath("schemas/plan-summary.schema.json").read_text())
TIME = "2021-05-13T13:00-06:00"


def test_plan_writes_one_flyable_mission_per_flight(tmp_path, capsys):
    out = tmp_path / "plan"
    rc = main(["plan", "--time", TIME, "--aim", "60,8.8,28.9", "--max-altitude", "25", "--out", str(out), "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    jsonschema.validate(summary, SUMMARY_SCHEMA)
    assert SUMMARY_SCHEMA["$defs"]["facet_coverage"] == PLAN_SCHEMA["$defs"]["facet_coverage"]  # one definition
    fc = summary["facet_coverage"]
    assert fc["fraction"] >= 0.95 and summary["coverage"]["planned"] >= 0.9  # every facet imaged (issue 11)
    assert summary["distance_m"] == pytest.approx(sum(m["distance_m"] for m in summary["missions"]), abs=1.0)
    written = {p.name for p in out.iterdir()}
    assert {"plan.json", "plan.kml", "plan.png"} <= written
    n = summary["flights"]
    assert n >= 2
    # the plan needs several batteries: no whole-field mission, one mission per flight
    assert not {"mission.plan", "mission.waypoints", "litchi.csv"} & written
    assert {f"flight_{k:02d}.plan" for k in range(1, n + 1)} | {f"flight_{k:02d}.waypoints" for k in range(1, n + 1)} \
        <= written
    plan = json.loads((out / "plan.json").read_text())
    jsonschema.validate(plan, PLAN_SCHEMA)
    assert plan["summary"]["facet_coverage"] == fc
    home = plan["home"]
    for k, f in enumerate(plan["flights"], start=1):
        doc = json.loads((out / f"flight_{k:02d}.plan").read_text())
        jsonschema.validate(doc, QGC_SCHEMA)
        items = doc["mission"]["items"]
        assert len(items) + 1 <= 700 == summary["max_mission_items"]  # home slot included
        assert summary["missions"][k - 1]["mission_items"] == len(items) + 1
        assert items[0]["command"] == 22 and items[-1]["command"] == 21  # take off, land
        assert items[-1]["params"][4:6] == [home["latitude_deg"], home["longitude_deg"]]
        assert f["duration_s"] <= 20 * 60 * 0.8  # within the battery less its reserve
        litchi = sorted(out.glob(f"flight_{k:02d}_litchi*.csv"))
        rows = [list(csv.DictReader(p.read_text().splitlines())) for p in litchi]
        assert litchi and all(0 < len(r) <= 99 for r in rows)  # never a file Litchi refuses
        assert sum(len(r) for r in rows) == len(f["waypoints"]) - 2  # the whole flight but take-off and landing
    assert summary["passes"] == len(plan["passes"]) > 10
    assert 0.0 <= summary["coverage"]["either"] <= 1.0
    for p in plan["passes"]:
        assert plan["min_altitude_m"] <= p["altitude_m"] <= 25.0 + 1e-9
        for w in p["waypoints"]:
            assert 0.0 <= w["heading_deg"] < 360.0 and -90.0 <= w["gimbal_pitch_deg"] <= 0.0
    covered = sorted(i for f in plan["flights"] for i in f["pass_indices"])
    assert covered == sorted(p["index"] for p in plan["passes"] if p["feasible"])


def test_plan_files_read_by_third_party_readers(tmp_path, capsys):
    mavwp = pytest.importorskip("pymavlink.mavwp")
    out = tmp_path / "plan"
    assert main(["plan", "--time", TIME, "--out", str(out)]) == 0
    err = capsys.readouterr().err
    cov = json.loads((out / "plan.json").read_text())["summary"]["coverage"]
    assert (f"heliostats of the field imaged {100 * cov['planned']:.0f} %, with the reflection "
            f"{100 * cov['reflection']:.0f} %, with a contrast edge {100 * cov['either']:.0f} %") in " ".join(err.split())
    assert f"to {out}" in err and len(err.strip().splitlines()) == 2
    for path in sorted(out.glob("flight_*.waypoints")):
        loader = mavwp.MAVWPLoader()
        n = loader.load(str(path))
        items = json.loads(path.with_suffix(".plan").read_text())["mission"]["items"]
        assert n == len(items) + 1 and [loader.wp(k).command for k in range(1, n)] == [it["command"] for it in items]
    fastkml = pytest.importorskip("fastkml.validator")
    etree = pytest.importorskip("lxml.etree")
    assert fastkml.get_schema_parser().validate(etree.parse(str(out / "plan.kml")))


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--time", "2021-05-13T23:00-06:00"], "below the horizon"),
        (["--time", "2021-05-13T13:00"], "utc offset"),
        (["--time", TIME, "--aim", "0,0,-1"], "above the ground"),
        (["--time", TIME, "--heliostats", "8E3,99W1"], "unknown heliostat"),
        (["--time", TIME, "--facet-target", "1.5"], "--facet-target"),
        (["--time", TIME, "--max-altitude", "8"], "no feasible pass"),
        (["--time", TIME, "--heliostats", "5W1,5E2"], "no scan pass to fly: 5e2: no target heliostat in front"),
        (["--time", TIME, "--battery-min", "-5"], "--battery-min must be a positive number of minutes"),
        (["--time", TIME, "--battery-min", "1e308"], "--battery-min must be a positive number of minutes, at most 1440"),
        (["--time", TIME, "--fleet-hours", "25"], "--fleet-hours must be a positive number of hours per day"),
        (["--time", TIME, "--fleet-hours", "0"], "--fleet-hours must be a positive number of hours per day"),
        (["--time", TIME, "--max-mission-items", "12"], "single capture, more than 12"),
        (["--time", TIME, "--autopilot", "inav"], "--autopilot must be ardupilot or px4"),
        (["--time", "2021-05-13T10:00+01:00", "--site", "37.09,-2.36,500"],
         "--site 37.09,-2.36,500 is not near the nsttf: give --geoid-undulation"),
        (["--time", TIME, "--geoid-undulation", "nan"], "--geoid-undulation must be a number of metres"),
        (["--time", TIME, "--heliostats", " , "], "--heliostats names no heliostat"),
        (["--time", TIME, "--geoid-undulation", "500"], "--geoid-undulation must be a number of metres within +/-120"),
        (["--time", TIME, "--workers", "0"], "--workers must be in [1, 64], got 0"),
        (["--time", TIME, "--workers", "65"], "--workers must be in [1, 64], got 65"),
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


def test_a_site_away_from_the_nsttf_with_its_geoid_undulation(tmp_path, capsys):
    """Plataforma Solar de Almeria (EGM96 geoid about +51.5 m): the plan carries the undulation given, and the QGC
    home is at the sea-level height it gives (ellipsoidal height - undulation)."""
    out = tmp_path / "psa"
    assert main(["plan", "--time", "2021-05-13T10:00+01:00", "--site", "37.09,-2.36,500", "--geoid-undulation",
                 "51.5", "--heliostats", "8E3", "--out", str(out)]) == 0
    capsys.readouterr()
    doc = json.loads((out / "plan.json").read_text())
    assert doc["site"]["geoid_undulation_m"] == 51.5 and doc["site"]["latitude_deg"] == 37.09
    home = json.loads(sorted(out.glob("flight_*.plan"))[0].read_text())["mission"]["plannedHomePosition"]
    assert home[2] == pytest.approx(doc["home"]["height_m"] - 51.5)


def test_plan_scores_with_the_second_surface_mirror_by_default(tmp_path, capsys):
    """Pinned convention: without --mirror, the predicted reflections are those of second-surface silvered glass."""

    def predictions(name, *extra):
        out = tmp_path / name
        assert main(["plan", "--time", "2021-05-13T13:00-06:00", "--heliostats", "8E3", "--out", str(out), *extra]) == 0
        capsys.readouterr()
        doc = json.loads((out / "plan.json").read_text())
        return [q for p in doc["passes"] for q in p["predictions"]]

    default = predictions("default")
    assert default and default == predictions("explicit", "--mirror", "second-surface")
    fresnel = predictions("fresnel", "--mirror", "fresnel")
    assert [q["reflection_dolp"] for q in fresnel] != [q["reflection_dolp"] for q in default]


def test_no_mission_file_when_no_pass_is_within_a_battery(tmp_path, capsys):
    """Every pass beyond a battery's reach: the plan is written, no mission file (there is nothing to fly)."""
    out = tmp_path / "o"
    assert main(["plan", "--time", "2021-05-13T10:00-06:00", "--heliostats", "8E3,9E3", "--battery-min", "0.001",
                 "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["flights"] == 0 and summary["unreachable_passes"]
    names = sorted(p.name for p in out.iterdir())
    assert names == ["plan.json", "plan.kml", "plan.png"]
