"""A small synthetic flight shared by the campaign tests (rendered once per session)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

PLAN_TIME = "2021-05-13T13:00-06:00"
SIZE = (160, 134)


@pytest.fixture(scope="session")
def plan_json(tmp_path_factory) -> Path:
    from pihim.cli import main

    out = tmp_path_factory.mktemp("plan")
    assert main(["plan", "--time", PLAN_TIME, "--single-capture", "--out", str(out)]) == 0  # one capture per HUA
    return out / "plan.json"


@pytest.fixture(scope="session")
def base_flight(tmp_path_factory, plan_json) -> Path:
    """Two capture frames of flight 1 at 160x134, poses in frames.csv."""
    from pihim.campaign.flight import simulate_flight

    out = tmp_path_factory.mktemp("flights") / "f1"
    simulate_flight(plan_json, out, max_frames=2, size=SIZE, log="csv", canting_sigma_mrad=3.0, seed=3)
    return out


@pytest.fixture()
def flight_copy(tmp_path, base_flight) -> Path:
    dst = tmp_path / "f1"
    shutil.copytree(base_flight, dst)
    return dst
