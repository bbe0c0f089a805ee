"""Gauss-Legendre nodes and weights by Newton's method on the Legendre recurrence.

``numpy.polynomial.legendre.leggauss`` finds the nodes as eigenvalues of the
companion matrix (LAPACK through OpenBLAS). The ground model takes 256 nodes
when it is built; in a fresh process that first LAPACK call starts
OpenBLAS's threads: 7 ms wall and 10 ms of CPU on the idle 2-core benchmark
machine, but 0.5 s wall and 0.49 s of CPU while another job kept both
cores busy (OpenBLAS's threads waiting for a CPU; 6 ms with
``OPENBLAS_NUM_THREADS=1``), once per ``pihim ground``, ``plan`` or
``windows`` run. Newton's method on ``P_n`` needs numpy arithmetic only: a
few iterations from Tricomi's asymptotic starting values, about 4 ms for
256 nodes, and the same nodes and weights to a few units in the last
place.

References
----------
M. Abramowitz and I. A. Stegun, *Handbook of Mathematical Functions* (1964),
eq. 22.7.10 (the recurrence), 22.8.5 (the derivative) and 25.4.29 (the
weights ``w_i = 2 / ((1 - x_i^2) P_n'(x_i)^2)``).

F. G. Tricomi, "Sugli zeri dei polinomi sferici ed ultrasferici", Annali di
Matematica Pura ed Applicata 31 (1950) 93-97, doi:10.1007/BF02428258 (the
starting values ``cos(pi (4i - 1) / (4n + 2))``).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

#: Newton steps at most; from Tricomi's starting values 3-5 reach the last place for n <= 1000.
_MAX_STEPS = 100


def _legendre_and_derivative(n: int, x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``P_n(x)`` and ``P_n'(x)`` for ``|x| < 1`` (three-term recurrence, A&S 22.7.10 and 22.8.5)."""
    p_prev, p = np.ones_like(x), x.copy()
    for k in range(2, n + 1):
        p_prev, p = p, ((2 * k - 1) * x * p - (k - 1) * p_prev) / k
    return p, n * (x * p - p_prev) / (x * x - 1.0)


@lru_cache(maxsize=16)
def gauss_legendre(n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Nodes (ascending) and weights of the ``n``-point Gauss-Legendre rule on [-1, 1].

    Exact for polynomials of degree ``2 n - 1``; the arrays are cached and
    read-only.

    Parameters
    ----------
    n : int
        Number of nodes, >= 1.

    Returns
    -------
    x, w : numpy.ndarray
        Nodes and weights, shape ``(n,)``.
    """
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
        raise ValueError(f"n must be a whole number >= 1, got {n!r}")
    n = int(n)
    i = np.arange(1, n + 1)
    x = np.cos(np.pi * (4 * i - 1) / (4 * n + 2))  # descending, the largest root first
    for _ in range(_MAX_STEPS):
        p, dp = _legendre_and_derivative(n, x)
        step = p / dp
        x = x - step
        if np.max(np.abs(step)) <= 4 * np.finfo(float).eps:
            break
    _, dp = _legendre_and_derivative(n, x)
    w = 2.0 / ((1.0 - x * x) * dp * dp)
    x, w = x[::-1], w[::-1]
    x, w = 0.5 * (x - x[::-1]), 0.5 * (w + w[::-1])  # the rule's symmetry exact (the middle node 0 for odd n)
    x.flags.writeable = False
    w.flags.writeable = False
    return x, w
