"""Compiled inner loops of the planner (numba), imported where used so that the command line starts quickly."""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray


@njit(cache=True)
def in_fov(points: NDArray, cam: NDArray, r: NDArray, dn: NDArray, f: NDArray, tx: float,
           ty: float) -> NDArray:  # pragma: no cover - compiled
    """For points (P, K, 3) seen from cameras (P, 3) with OpenCV axes ``r`` (right), ``dn`` (down) and
    ``f`` (forward), (P, 3) each: in front (``z > 0``) and ``|x| <= tx z``, ``|y| <= ty z``; (P, K) bool
    (False where any coordinate is NaN)."""
    n_p, n_k = points.shape[0], points.shape[1]
    out = np.empty((n_p, n_k), np.bool_)
    for p in range(n_p):
        for j in range(n_k):
            vx = points[p, j, 0] - cam[p, 0]
            vy = points[p, j, 1] - cam[p, 1]
            vz = points[p, j, 2] - cam[p, 2]
            z = vx * f[p, 0] + vy * f[p, 1] + vz * f[p, 2]
            x = vx * r[p, 0] + vy * r[p, 1] + vz * r[p, 2]
            y = vx * dn[p, 0] + vy * dn[p, 1] + vz * dn[p, 2]
            out[p, j] = z > 0.0 and abs(x) <= tx * z and abs(y) <= ty * z
    return out
