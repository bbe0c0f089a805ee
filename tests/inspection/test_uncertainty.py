"""The delete-one-group jackknife and relative variances, against closed forms."""

import numpy as np
import pytest

from pihim.inspection.uncertainty import jackknife_covariance, relative_variance


def test_jackknife_of_a_mean_is_the_variance_of_the_group_means():
    """For the mean of G equal groups, the grouped jackknife is exactly sum (m_g - m)^2 / (G (G - 1))."""
    rng = np.random.default_rng(0)
    g, per = 7, 40
    labels = np.repeat(np.arange(g), per)
    # correlated inside a group: a shared offset per group plus small independent noise
    x = np.repeat(rng.normal(0, 1.0, g), per)[:, None] * [1.0, -2.0] + rng.normal(0, 0.01, (g * per, 2))
    cov, n = jackknife_covariance(labels, lambda keep: x[keep].mean(axis=0))
    means = x.reshape(g, per, 2).mean(axis=1)
    d = means - means.mean(axis=0)
    assert n == g
    np.testing.assert_allclose(cov, d.T @ d / (g * (g - 1)), rtol=1e-12)
    # the naive standard error takes the 280 points for independent and is far smaller
    naive = x.var(axis=0, ddof=1) / len(x)
    assert np.all(np.diag(cov) > 3 * naive)


def test_jackknife_needs_three_groups_and_finite_estimates():
    labels = np.array([0, 0, 1, 1])
    assert jackknife_covariance(labels, lambda keep: np.ones(2)) == (None, 2)
    labels = np.array([0, 1, 2, 2])
    assert jackknife_covariance(labels, lambda keep: np.array([np.nan]))[0] is None


@pytest.mark.parametrize("n", [2, 3, 5])
def test_relative_variance_is_the_propagated_variance(n):
    """Var(a_i - mean a) from the matrix A = I - 11^T / N: diag(A diag(v) A^T)."""
    v = np.linspace(0.5, 2.0, n)
    a = np.eye(n) - np.full((n, n), 1.0 / n)
    np.testing.assert_allclose(relative_variance(v), np.diag(a @ np.diag(v) @ a.T), rtol=1e-12)
    np.testing.assert_allclose(relative_variance(np.column_stack([v, 2 * v])),
                               np.column_stack([np.diag(a @ np.diag(v) @ a.T), 2 * np.diag(a @ np.diag(v) @ a.T)]))


def test_relative_variance_of_one_estimate_is_zero_and_an_unknown_one_stands_in_at_the_largest():
    assert relative_variance(np.array([4.0])) == pytest.approx([0.0])
    # the unknown variance counts as the largest known one (1.0 here) in the others' sum: 1/3 + 3/9
    out = relative_variance(np.array([1.0, np.nan, 0.5]))
    assert np.isnan(out[1])
    np.testing.assert_allclose(out[[0, 2]], [1.0 / 3 + 2.5 / 9, 0.5 / 3 + 2.5 / 9])
    # two estimates are each other's negatives about their mean: they share one variance, (v1 + v2) / 4
    np.testing.assert_allclose(relative_variance(np.array([2.0, np.nan]))[0], (2.0 + 2.0) / 4)
    assert np.isnan(relative_variance(np.array([np.nan, np.nan]))).all()
