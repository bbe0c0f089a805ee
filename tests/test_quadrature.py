"""Gauss-Legendre rule by Newton's method (:mod:`pihim._quadrature`)."""

import numpy as np
import pytest
from numpy.polynomial import legendre

from pihim._quadrature import gauss_legendre


@pytest.mark.parametrize("n", [1, 2, 3, 5, 16, 24, 32, 64, 256])
def test_matches_numpy_leggauss(n):
    """Same nodes and weights as numpy's eigenvalue route (an independent method)."""
    x, w = gauss_legendre(n)
    x_ref, w_ref = legendre.leggauss(n)
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-15)
    np.testing.assert_allclose(w, w_ref, rtol=1e-10, atol=0)


@pytest.mark.parametrize("n", [1, 4, 7, 24, 256])
def test_exact_for_degree_2n_minus_1(n):
    """integral of P_k over [-1, 1] is 2 for k = 0 and 0 for 1 <= k <= 2n - 1."""
    x, w = gauss_legendre(n)
    for k in range(2 * n):
        exact = 2.0 if k == 0 else 0.0
        assert abs(np.sum(w * legendre.legval(x, [0] * k + [1])) - exact) < 1e-14, k
    # and not beyond: P_2n is not integrated exactly
    assert abs(np.sum(w * legendre.legval(x, [0] * (2 * n) + [1]))) > 1e-3


def test_symmetric_ascending_and_read_only():
    x, w = gauss_legendre(7)
    assert np.all(np.diff(x) > 0)
    np.testing.assert_array_equal(x, -x[::-1])
    np.testing.assert_array_equal(w, w[::-1])
    assert x[3] == 0.0
    with pytest.raises(ValueError):
        x[0] = 0.0


@pytest.mark.parametrize("n", [0, -1, 2.5, True, "3"])
def test_rejects_bad_counts(n):
    with pytest.raises(ValueError, match="n must be"):
        gauss_legendre(n)
