"""The campaign commands' --json outputs against their schemas, end to end on a one-frame ULog flight."""

from __future__ import annotations

import json
from importlib import resources

import pytest

from pihim.cli import main

jsonschema = pytest.importorskip("jsonschema")
pytest.importorskip("distributed")
pytest.importorskip("pyulog")


def _schema(name: str) -> dict:
    return json.loads(resources.files("pihim").joinpath(f"schemas/{name}.schema.json").read_text())


def test_simulate_run_report_export_json(plan_json, tmp_path, capsys) -> None:
    flight = tmp_path / "f"
    assert main(["simulate-flight", str(plan_json), "--out", str(flight), "--max-frames", "1", "--size", "96x80",
                 "--log", "ulog", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    jsonschema.validate(doc, _schema("simulate-flight"))
    assert doc["log"] == "flight.ulg" and (flight / "flight.ulg").is_file() and (flight / "truth" / "000000.json").is_file()
    # a second simulate-flight into the same directory is refused, the flight kept
    assert main(["simulate-flight", str(plan_json), "--out", str(flight), "--max-frames", "1", "--size", "96x80"]) == 2
    capsys.readouterr()

    store = tmp_path / "c.sqlite"
    assert main(["campaign", "run", str(flight), "--store", str(store), "--stages", "select", "--workers", "1",
                 "--campaign", "may", "--json"]) == 0
    run = json.loads(capsys.readouterr().out)
    jsonschema.validate(run, _schema("campaign-run"))
    assert run["campaign"] == "may" and run["flights"][0]["log"] == "ulog"
    assert run["parameters"]["criteria"]["min_reflection_dolp"] == 0.2  # the paper's criterion without --min-dolp

    assert main(["campaign", "report", str(store), "--out", str(tmp_path / "r"), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    jsonschema.validate(rep, _schema("campaign-report"))
    assert rep["heliostats_measured"] == 0 and (tmp_path / "r" / "index.html").is_file()

    assert main(["campaign", "export", str(store), "--out", str(tmp_path / "e"), "--json"]) == 0
    exp = json.loads(capsys.readouterr().out)
    jsonschema.validate(exp, _schema("campaign-export"))
    assert exp["rows"]["frames"] == 1


@pytest.mark.parametrize("argv,msg", [
    (["simulate-flight", "PLAN", "--out", "X", "--fps", "5", "--captures-only"], "exclude each other"),
    (["simulate-flight", "PLAN", "--out", "X", "--fps", "0"], "--fps"),
    (["simulate-flight", "PLAN", "--out", "X", "--log", "mavlink"], "--log"),
    (["simulate-flight", "PLAN", "--out", "X", "--flight", "9"], "flights"),
    (["simulate-flight", "PLANDIR", "--out", "X"], "a folder; give its plan.json"),
    (["campaign", "run", "NOWHERE", "--store", "S"], "not a flight directory"),
    (["campaign", "run", "NOWHERE", "--store", "S", "--stages", "edges"], "stages"),
    (["campaign", "run", "NOWHERE", "--store", "S", "--campaign", " "], "--campaign must be a name"),
    (["campaign", "export", "S", "--out", "E", "--format", "xlsx"], "csv or parquet"),
])
def test_bad_options_one_line_exit_2(plan_json, tmp_path, capsys, argv, msg) -> None:
    argv = [str(plan_json) if a == "PLAN" else str(plan_json.parent) if a == "PLANDIR"
            else str(tmp_path / a) if a in ("X", "S", "E", "NOWHERE") else a for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and msg in err[0]
