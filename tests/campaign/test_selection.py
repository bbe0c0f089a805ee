"""Frame selection: the paper's reflection-DoLP criterion on a logged frame of the synthetic flight."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pihim.camera.layout import IMX250MZR
from pihim.campaign.flight import frame_log, load_flight
from pihim.campaign.selection import SKIP_REASONS, select_pairs
from pihim.field import nsttf_like_field


def _uniform_mosaic(shape: tuple[int, int], s0: float, dolp: float, aop_deg: float) -> np.ndarray:
    """An ideal DoFP mosaic of light with one S0, DoLP and AoP everywhere (Malus's law per micro-polarizer)."""
    theta = np.radians(IMX250MZR.angle_map(shape).astype(float))
    return s0 / 2 * (1 + dolp * np.cos(2 * theta - 2 * np.radians(aop_deg)))


@pytest.fixture(scope="module")
def logged_frame(base_flight):
    """The first frame's log (ideal sensor) and the pair the plan imaged at it."""
    flight = load_flight(base_flight)
    match = flight.matches[0]
    log = {**frame_log(flight, match), "sensor": {}}  # an ideal analyser, no dark level: the mosaic below is exact
    truth = json.loads((base_flight / "truth" / "flight.json").read_text())["frames"][0]
    return log, (truth["hua"], truth["target"])


@pytest.mark.parametrize("dolp, selected", [(0.15, False), (0.19, False), (0.21, True), (0.3, True)])
def test_the_planned_pair_is_selected_only_above_the_papers_dolp(logged_frame, dolp, selected):
    """Pinned convention (paper sec. 4.1): by default a pair is kept only if its HUA's reflection has DoLP > 0.2."""
    log, pair = logged_frame
    shape = (log["camera"]["height_px"], log["camera"]["width_px"])
    raw = _uniform_mosaic(shape, 1000.0, dolp, 30.0)
    out = select_pairs(raw, log, nsttf_like_field())
    cand = next(c for c in out["candidates"] if (c["hua"], c["target"]) == pair)
    assert cand["metrics"]["dolp"] == pytest.approx(dolp, abs=1e-6)
    assert cand["selected"] is selected
    assert cand["reason"] == (None if selected else SKIP_REASONS["dolp"])
