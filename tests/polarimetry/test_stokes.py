"""Tests for pihim.polarimetry.stokes against closed-form values."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pihim.errors import PihimInputError
from pihim.polarimetry import (
    aop_deg,
    aop_difference_deg,
    aop_raw_difference_deg,
    dolp,
    rotate_reference_deg,
    stokes_from_dolp_aop,
)

angles = st.floats(min_value=0.0, max_value=179.999, allow_nan=False)
fractions = st.floats(min_value=0.01, max_value=1.0, allow_nan=False)


def test_dolp_aop_known_values():
    # S1 > 0 only: field along the reference axis -> AoP 0
    assert aop_deg(1.0, 0.0) == 0.0
    # S2 > 0 only: 45 deg counter-clockwise
    assert aop_deg(0.0, 1.0) == pytest.approx(45.0)
    # S1 < 0: perpendicular -> 90
    assert aop_deg(-1.0, 0.0) == pytest.approx(90.0)
    assert aop_deg(0.0, -1.0) == pytest.approx(135.0)
    assert dolp(2.0, 0.6, 0.8) == pytest.approx(0.5)
    assert np.isnan(dolp(0.0, 0.0, 0.0))


def test_aop_range_and_fold():
    a = aop_deg(np.array([1.0, -1.0, 1e-12, 1.0]), np.array([-1e-9, -1e-12, -1.0, 1e-300]))
    assert np.all((a >= 0.0) & (a < 180.0))


@given(s0=st.floats(0.1, 1e4), p=fractions, a=angles)
def test_stokes_roundtrip(s0, p, a):
    s = stokes_from_dolp_aop(s0, p, a)
    assert dolp(*s) == pytest.approx(p, rel=1e-9)
    assert aop_difference_deg(aop_deg(s[1], s[2]), a) == pytest.approx(0.0, abs=1e-7)


def test_rotate_reference_sign():
    # Light at AoP 30 deg; reference axis turned counter-clockwise by 10 deg -> AoP 20 deg.
    s0, s1, s2 = stokes_from_dolp_aop(1.0, 0.7, 30.0)
    r1, r2 = rotate_reference_deg(s1, s2, 10.0)
    assert aop_deg(r1, r2) == pytest.approx(20.0)
    assert dolp(s0, r1, r2) == pytest.approx(0.7)
    # explicit matrix entries (Mueller rotator) for t = 22.5 deg: cos2t = sin2t = 1/sqrt2
    r1, r2 = rotate_reference_deg(1.0, 0.0, 22.5)
    assert (r1, r2) == pytest.approx((np.sqrt(0.5), -np.sqrt(0.5)))


@given(p=fractions, a=angles, t=st.floats(-720, 720))
def test_rotation_preserves_dolp_and_shifts_aop(p, a, t):
    s0, s1, s2 = stokes_from_dolp_aop(1.0, p, a)
    r1, r2 = rotate_reference_deg(s1, s2, t)
    assert dolp(s0, r1, r2) == pytest.approx(p, rel=1e-9)
    assert aop_difference_deg(aop_deg(r1, r2), a - t) == pytest.approx(0.0, abs=1e-6)


def test_aop_difference_axial_vs_raw():
    assert aop_difference_deg(5.0, 175.0) == pytest.approx(10.0)
    assert aop_raw_difference_deg(5.0, 175.0) == pytest.approx(170.0)
    assert aop_difference_deg(0.0, 90.0) == pytest.approx(90.0)
    d = aop_difference_deg(np.linspace(0, 179, 50)[:, None], np.linspace(0, 179, 50)[None, :])
    assert d.min() >= 0.0 and d.max() <= 90.0
    # symmetric
    assert np.allclose(d, d.T)


def test_stokes_from_dolp_aop_refuses_light_that_cannot_be():
    """A DoLP of 1.5 or a negative intensity gave unphysical Stokes vectors without a word."""
    for s0, p in ((1.0, 1.5), (1.0, -0.1), (-1.0, 0.5), ([1.0, 2.0], [0.5, 1.2])):
        with pytest.raises(PihimInputError):
            stokes_from_dolp_aop(s0, p, 30.0)
    s0, s1, s2 = stokes_from_dolp_aop(2.0, 1.0 + 1e-12, 30.0)  # computed DoLPs may round a hair above 1
    assert s0 == 2.0 and np.hypot(s1, s2) == pytest.approx(2.0)


def test_raw_aop_difference_takes_angles_modulo_180():
    """aop_raw_difference_deg(350, 10) returned 340, outside its documented [0, 180)."""
    np.testing.assert_allclose(aop_raw_difference_deg([350.0, -10.0, 170.0, 0.0], [10.0, 10.0, 10.0, 179.0]),
                               [160.0, 160.0, 160.0, 179.0])
    assert aop_raw_difference_deg(-1e-20, 10.0) == 10.0  # np.mod(-1e-20, 180) rounds to 180
