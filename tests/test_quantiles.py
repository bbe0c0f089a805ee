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


def test_order_statistics_pair_equals_the_sorted_samples():
    """Two images of one selection in one pass: each rank's value is the sorted sample's, NaN and inf left out."""
    from pihim._quantiles import histogram_keys, n_chunks_for, order_statistics_pair

    rng = np.random.default_rng(5)
    a = rng.normal(1000, 100, (120, 90)).astype(np.float32)
    b = rng.uniform(0, 1, a.shape).astype(np.float32)
    b[rng.random(a.shape) < 0.2] = np.nan  # the selection: where b is finite
    a[rng.random(a.shape) < 0.05] = np.inf  # not in a's sample
    a[:3, :3] = 1000.0  # ties in a bin
    hists = []
    for im in (a, b):
        h = np.zeros((n_chunks_for(a.shape[0]), N_BINS), np.int64)
        histogram_keys(im.view(np.uint32), b, h)
        hists.append(h)
    samples = [np.sort(a[np.isfinite(a) & np.isfinite(b)]), np.sort(b[np.isfinite(b)])]
    ranks = [[0, 7, len(samples[0]) // 2, len(samples[0]) - 1], [1, len(samples[1]) // 3, len(samples[1]) - 1]]
    got = order_statistics_pair((a, b), b, (ranks[0], ranks[1]), (hists[0], hists[1]))
    for g, sample, rk in zip(got, samples, ranks, strict=True):
        assert [g[r] for r in rk] == [float(sample[r]) for r in rk]
    assert got == (order_statistics(a, b, ranks[0], hist=hists[0]), order_statistics(b, b, ranks[1], hist=hists[1]))
    with pytest.raises(ValueError, match="share a shape"):
        order_statistics_pair((a, b[:5]), b, (ranks[0], ranks[1]), (hists[0], hists[1]))
