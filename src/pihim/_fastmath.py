"""Small numba-compiled math helpers for the image kernels.

``atan2`` from libm cannot be vectorised by LLVM, which makes it the
bottleneck of a per-pixel AoP kernel: the same super-pixel kernel is about
25x slower with libm ``atan2`` than with the polynomial below on a
1224x1024 output (figures in BENCHMARKS.md).
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Odd polynomial coefficients for atan(t), t in [0, 1]: least-squares fit of
#: t, t^3, ..., t^11 on 4001 Chebyshev nodes (see :func:`fit_atan_coefficients`).
#: Maximum error 1.8e-6 rad (1.0e-4 deg) in float64.
ATAN_COEFFS: tuple[float, ...] = (
    0.9999798315905769,
    -0.33265541945131744,
    0.19366988828003673,
    -0.11664997877294277,
    0.05282219488960116,
    -0.011769974089825996,
)

_C0, _C1, _C2, _C3, _C4, _C5 = (np.float32(c) for c in ATAN_COEFFS)
_HALF_PI = np.float32(np.pi / 2)
_PI = np.float32(np.pi)


def fit_atan_coefficients(n_terms: int = 6, n_nodes: int = 4001) -> np.ndarray:
    """Reproduce :data:`ATAN_COEFFS` (least squares on Chebyshev nodes in [0, 1])."""
    t = 0.5 + 0.5 * np.cos(np.linspace(0.0, np.pi, n_nodes))
    basis = np.stack([t ** (2 * k + 1) for k in range(n_terms)], axis=1)
    return np.linalg.lstsq(basis, np.arctan(t), rcond=None)[0]


@njit(fastmath=True, inline="always", cache=True)
def atan2_f32(y, x):  # pragma: no cover - compiled
    """float32 ``atan2(y, x)`` in radians, (-pi, pi], max error about 1e-6 rad."""
    ax = abs(x)
    ay = abs(y)
    mx = max(ax, ay)
    mn = min(ax, ay)
    t = mn / mx if mx > 0 else np.float32(0.0)
    t2 = t * t
    r = t * (_C0 + t2 * (_C1 + t2 * (_C2 + t2 * (_C3 + t2 * (_C4 + t2 * _C5)))))
    if ay > ax:
        r = _HALF_PI - r
    if x < 0:
        r = _PI - r
    if y < 0:
        r = -r
    return r
