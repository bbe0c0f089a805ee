"""Shared oracles for the planning tests."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest


def _first_mirror(pose, p0: np.ndarray, d: np.ndarray, skip: int) -> tuple[int, float]:
    """First tracked mirror rectangle along p0 + s d (s > 0), testing every heliostat in a plain loop."""
    spec = pose.field.spec
    best, best_s = -1, math.inf
    for k in range(len(pose.normals)):
        if k == skip:
            continue
        n, c, r = pose.normals[k], pose.mirror_centres[k], pose.rotations[k]
        den = float(d @ n)
        if abs(den) < 1e-12:
            continue
        s = float((c - p0) @ n) / den
        q = p0 + s * d - c
        if 1e-9 < s < best_s and abs(q @ r[:, 0]) <= spec.mirror_half_width_m \
                and abs(q @ r[:, 1]) <= spec.mirror_half_height_m:
            best, best_s = k, s
    return best, best_s


@pytest.fixture(scope="session")
def first_mirror() -> Callable[..., tuple[int, float]]:
    """Brute-force ray / mirror oracle: ``first_mirror(pose, p0, d, skip) -> (index or -1, distance)``."""
    return _first_mirror
