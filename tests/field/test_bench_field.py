"""Smoke test of benchmarks/bench_field.py (tiny sizes; the timings themselves are not checked)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_field.py"


def test_bench_field_runs(capsys: pytest.CaptureFixture[str]) -> None:
    if not BENCH.is_file():
        pytest.skip("benchmarks/ not present")
    spec = importlib.util.spec_from_file_location("bench_field_under_test", BENCH)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    report = mod.main(repeat=1, quick=True, warmup=0, radial_sizes=(300,), json_path=None)
    out = capsys.readouterr().out
    assert "| NSTTF tracking + frames + canting" in out and "| radial 300 tracking |" in out
    assert {"nsttf_track", "nsttf_track_cant", "nsttf_geometry", "radial_300_track"} <= set(report["results"])
    assert report["targets"][0]["target"].startswith("NSTTF tracking + canting")
