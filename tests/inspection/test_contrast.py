"""Tests of :mod:`pihim.inspection.contrast`: Michelson contrast, the paper's 200 x 100 px ROIs, contrast ratio."""

import math

import numpy as np
import pytest

from pihim.errors import PihimInputError
from pihim.inspection.contrast import (
    PAPER_ROI_SIZE,
    RoiPairContrast,
    contrast_ratio,
    michelson_contrast,
    roi_pair_contrast,
)


def test_michelson_of_known_values_and_regions():
    assert michelson_contrast(30.0, 10.0) == pytest.approx(0.5)
    assert michelson_contrast(10.0, 30.0) == pytest.approx(0.5)
    assert michelson_contrast(7.0, 7.0) == 0.0
    # arrays: the (finite) means are compared
    a = np.array([1.0, 3.0, np.nan])
    b = np.array([6.0, 6.0, 6.0])
    assert michelson_contrast(a, b) == pytest.approx((6 - 2) / (6 + 2))
    assert math.isnan(michelson_contrast(0.0, 0.0))
    assert math.isnan(michelson_contrast(np.array([np.nan]), 1.0))


def test_axis_aligned_edge_takes_exactly_two_200x100_regions():
    img = np.full((400, 600), 10.0)
    img[:, 300:] = 30.0  # edge between columns 299 and 300, i.e. at u = 299.5
    r = roi_pair_contrast(img, (299.5, 200.0), (1.0, 0.0))
    assert PAPER_ROI_SIZE == (200, 100)
    assert r.n_a == r.n_b == 200 * 100
    assert (r.mean_a, r.mean_b) == (10.0, 30.0)  # b on the +normal side
    assert r.std_a == r.std_b == 0.0
    assert r.contrast == pytest.approx(0.5) and r.difference == pytest.approx(20.0)
    # the region outlines: 100 px deep on either side, 200 px along the edge
    ua = [c[0] for c in r.corners_a]
    vb = [c[1] for c in r.corners_b]
    assert min(ua) == pytest.approx(199.5) and max(ua) == pytest.approx(299.5)
    assert max(vb) - min(vb) == pytest.approx(200.0)
    # the regions hold exactly the pixels they should: a marked pixel just outside changes nothing
    img2 = img.copy()
    img2[100:300, 199] = 1e6  # column 199 is just beyond region a (columns 200..299)
    img2[99, 250] = 1e6  # row 99 is just above both regions (rows 100..299)
    r2 = roi_pair_contrast(img2, (299.5, 200.0), (1.0, 0.0))
    assert (r2.mean_a, r2.mean_b) == (10.0, 30.0)


def test_roi_statistics_on_noise_and_a_rotated_edge():
    rng = np.random.default_rng(3)
    h, w = 700, 700
    jj, ii = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    angle = math.radians(30.0)
    n = np.array([math.cos(angle), -math.sin(angle)])  # 30 deg counter-clockwise from right, as displayed
    p = np.array([350.0, 350.0])
    side = (jj - p[0]) * n[0] + (ii - p[1]) * n[1]
    img = np.where(side > 0, 0.6, 0.2) + rng.normal(0.0, 0.01, (h, w))
    r = roi_pair_contrast(img, p, 30.0, gap_px=2.0)  # the normal given as an angle
    r_vec = roi_pair_contrast(img, p, n, gap_px=2.0)
    assert r == r_vec
    assert r.mean_a == pytest.approx(0.2, abs=1e-3) and r.mean_b == pytest.approx(0.6, abs=1e-3)
    assert r.std_a == pytest.approx(0.01, rel=0.05) and r.std_b == pytest.approx(0.01, rel=0.05)
    assert r.contrast == pytest.approx(0.4 / 0.8, abs=2e-3)
    assert r.n_a == r.n_b == 20000
    # half of region a outside the image: fewer pixels, same statistics
    edge = roi_pair_contrast(img, (80.0, 350.0), (1.0, 0.0), size=(200, 160))
    assert 0 < edge.n_a < 200 * 160 and edge.n_b == 200 * 160


def test_axial_statistics_for_aop():
    img = np.full((300, 400), 175.0)
    img[:, 200:] = 5.0
    img[::7, :200] = 177.0  # a little spread on side a
    r = roi_pair_contrast(img, (199.5, 150.0), (1.0, 0.0), axial=True)
    assert r.axial and math.isnan(r.contrast)
    assert r.mean_a == pytest.approx(175.3, abs=0.1) and r.mean_b == pytest.approx(5.0)
    assert r.difference == pytest.approx(180.0 - r.mean_a + 5.0)  # axial: 175.3 and 5 are 9.7 deg apart
    assert r.difference == pytest.approx(9.7, abs=0.1)
    assert r.raw_difference == pytest.approx(170.3, abs=0.1)  # the paper's Table 1 form
    assert 0.0 < r.std_a < 2.0 and r.std_b == pytest.approx(0.0, abs=1e-5)
    wrap = np.where(np.arange(400)[None, :] % 2 == 0, 179.0, 1.0) * np.ones((300, 1))
    rw = roi_pair_contrast(wrap, (199.5, 150.0), (1.0, 0.0), axial=True)
    assert min(rw.mean_a, 180.0 - rw.mean_a) == pytest.approx(0.0, abs=1e-6)  # not 90
    assert rw.std_a == pytest.approx(1.0, abs=0.01)


def test_contrast_ratio_as_the_paper_reports_it():
    assert contrast_ratio(0.593, 0.1) == pytest.approx(5.93)
    assert contrast_ratio(0.2, 0.0) == math.inf
    assert math.isnan(contrast_ratio(0.0, 0.0)) and math.isnan(contrast_ratio(math.nan, 0.1))
    # on regions: a sky-vs-sky-like edge, hardly visible in S0 but clear in DoLP
    s0 = np.full((300, 500), 40.0)
    s0[:, 250:] = 42.0
    dolp = np.full((300, 500), 0.25)
    dolp[:, 250:] = 0.55
    c_s0 = roi_pair_contrast(s0, (249.5, 150.0), (1.0, 0.0))
    c_dolp = roi_pair_contrast(dolp, (249.5, 150.0), (1.0, 0.0))
    assert isinstance(c_s0, RoiPairContrast)
    expected = (0.30 / 0.80) / (2.0 / 82.0)
    assert contrast_ratio(c_dolp, c_s0) == pytest.approx(expected)
    d = c_dolp.to_dict()
    assert d["a"]["pixels"] == 20000 and d["contrast"] == pytest.approx(0.375)


def test_bad_roi_input():
    img = np.zeros((50, 50))
    with pytest.raises(PihimInputError):
        roi_pair_contrast(img, (10.0, 10.0), (0.0, 0.0))
    with pytest.raises(PihimInputError):
        roi_pair_contrast(img, (10.0, np.nan), (1.0, 0.0))
    with pytest.raises(PihimInputError):
        roi_pair_contrast(img, (10.0, 10.0), (1.0, 0.0), size=(0, 10))
    with pytest.raises(PihimInputError):
        roi_pair_contrast(np.zeros((2, 2, 2)), (1.0, 1.0), (1.0, 0.0))
    empty = roi_pair_contrast(img, (-500.0, -500.0), (1.0, 0.0), size=(10, 10))
    assert empty.n_a == empty.n_b == 0 and math.isnan(empty.mean_a) and math.isnan(empty.contrast)


def test_michelson_of_a_region_at_the_dark_level():
    """A dark region's S0 after dark subtraction averages a little below 0: a contrast a little above 1, no error
    (refusing negative means broke roi_pair_contrast on real polar images)."""
    assert michelson_contrast(-0.334, 599.5) == pytest.approx(599.834 / 599.166)
