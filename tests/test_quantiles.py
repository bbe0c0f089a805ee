"""Exact percentiles by histogram selection (``pihim._quantiles``) against numpy.percentile."""

import numpy as np
import pytest

from pihim._quantiles import N_BINS, order_statistics, percentiles

Q = [0, 0.5, 5, 12.5, 33.3, 50, 95, 99.5, 100]


@pytest.mark.parametrize("kind", ["normal", "integers", "constant", "lognormal", "tiny", "signed zeros"])
def test_identical_to_numpy_percentile(kind):
    rng = np.random.default_rng(abs(hash(kind)) % 2**32)
    for trial in range(40):
        h, w = (int(v) for v in rng.integers(1, 30, 2))
        x = {
            "normal": lambda: rng.normal(0, 1, (h, w)),
            "integers": lambda: rng.integers(-3, 4, (h, w)),
            "constant": lambda: np.full((h, w), 7.25),
            "lognormal": lambda: rng.lognormal(0, 5, (h, w)),
            "tiny": lambda: rng.normal(0, 1e-30, (h, w)),
            "signed zeros": lambda: rng.choice([-0.0, 0.0, 1.0], (h, w)),
        }[kind]().astype(np.float32)
        if trial % 3 == 0:
            x[rng.random((h, w)) < 0.3] = np.nan
        if trial % 5 == 0:
            x[rng.random((h, w)) < 0.1] = np.inf
        where = None
        if trial % 4 == 1:
            where = np.where(rng.random((h, w)) < 0.5, np.float32(1), np.float32(np.nan))
        sample = np.isfinite(x) if where is None else np.isfinite(x) & np.isfinite(where)
        got = percentiles(x, Q, where)
        if not sample.any():
            assert got is None
            continue
        assert np.array_equal(np.asarray(got), np.percentile(x[sample].astype(np.float64), Q)), (kind, trial)


def test_large_image_and_order_statistics():
    rng = np.random.default_rng(1)
    x = rng.normal(1000, 100, (300, 400)).astype(np.float32)
    ranks = [0, 1, 59_999, 119_999]
    got = order_statistics(x, None, ranks)
    ref = np.sort(x, axis=None)
    assert [got[r] for r in ranks] == [float(ref[r]) for r in ranks]
    with pytest.raises(ValueError, match="ranks must lie"):
        order_statistics(x, None, [120_000])
    with pytest.raises(ValueError, match="do not describe"):
        order_statistics(x, None, [5], hist=np.ones((1, N_BINS), np.int64) * 2)
