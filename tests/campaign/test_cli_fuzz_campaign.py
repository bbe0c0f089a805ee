"""Fuzz the options of simulate-flight and campaign run: exit 0 or 2 with one error line, never a traceback.

The computations are stubbed where they would start (``typer.Exit(0)``): the
fuzz covers option parsing and validation, as tests/cli/test_cli_fuzz.py
does for ``canting``.
"""

from __future__ import annotations

import itertools

import pytest
import typer
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pihim.cli import main

WEIRD = ["nan", "inf", "-inf", "1e308", "-1e308", "0", "-0", "-1", "1e9", "999999999999", "abc", "", "1.5", "0x10"]
FUZZ = settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True,
                database=None)
_n = itertools.count()


def values(valid: list[str]) -> st.SearchStrategy[str]:
    return st.one_of(st.sampled_from(WEIRD), st.sampled_from(valid), st.floats().map(repr),
                     st.integers(-(2**70), 2**70).map(str))


def check(rc: int, err: str) -> None:
    assert "Traceback" not in err, err
    assert rc in (0, 2), (rc, err)
    if rc == 2:
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len([ln for ln in lines if ln.startswith("pihim: error:")]) == 1, err
        assert all(ln.startswith(("pihim: error:", "pihim: warning:")) for ln in lines), err


def mutated(data, base, options):
    chosen = data.draw(st.lists(st.sampled_from(sorted(options)), min_size=1, max_size=3, unique=True))
    argv = list(base)
    for name in chosen:
        argv += [name, data.draw(options[name], label=name)]
    return argv


def _stop(*args, **kwargs):
    raise typer.Exit(0)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    d = tmp_path_factory.mktemp("fz")
    (d / "plan.json").write_text("{}")
    return d


@FUZZ
@given(data=st.data())
def test_simulate_flight_options(root, capsys, monkeypatch, data):
    import pihim.campaign.flight as flight

    monkeypatch.setattr(flight, "simulate_flight", _stop)
    opts = {
        "--flight": values(["1", "2"]), "--fps": values(["15", "60", "61"]), "--max-frames": values(["1", "0"]),
        "--size": st.sampled_from(["16x16", "15x16", "100000x100000", "axb", ""]),
        "--log": st.sampled_from(["csv", "ulog", "dataflash", "x"]),
        "--canting-sigma-mrad": values(["0", "3"]), "--gps-sigma-m": values(["0", "1.5"]),
        "--attitude-sigma-deg": values(["0", "1"]), "--seed": values(["0", "-1"]),
    }
    argv = mutated(data, ["simulate-flight", str(root / "plan.json"), "--out", str(root / f"o{next(_n)}")], opts)
    check(main(argv), capsys.readouterr().err)


@FUZZ
@given(data=st.data())
def test_campaign_run_options(root, capsys, monkeypatch, data):
    import pihim.campaign.run as run

    monkeypatch.setattr(run, "run_campaign", _stop)
    opts = {
        "--workers": values(["1", "2", "0"]), "--stages": st.sampled_from(["select", "all", "edges", ""]),
        "--frames-per-pair": values(["1", "3", "0"]), "--min-dolp": values(["0.2", "0"]),
        "--field": st.sampled_from(["nsttf-like", "/nonexistent.csv", ""]),
        "--scheduler": st.sampled_from(["tcp://127.0.0.1:1", "nonsense"]),
    }
    argv = mutated(data, ["campaign", "run", str(root), "--store", str(root / f"s{next(_n)}.sqlite")], opts)
    check(main(argv), capsys.readouterr().err)
