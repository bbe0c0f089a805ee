"""CIE standard clear sky (type 12) relative radiance: a hand-computed value, symmetry, monotonicity."""

from __future__ import annotations

import numpy as np
import pytest

from pihim.errors import PihimInputError
from pihim.sky.radiance import (
    CIE_SKY_TYPES,
    cie_parameters,
    cie_relative_radiance,
    gradation,
    indicatrix,
)
from pihim.sky.sun import direction_from_angles


def test_type_12_and_13_parameters():
    assert cie_parameters(12) == (-1.0, -0.32, 10.0, -3.0, 0.45)
    assert cie_parameters(13) == (-1.0, -0.32, 16.0, -3.0, 0.30)
    assert len(CIE_SKY_TYPES) == 15
    with pytest.raises(PihimInputError):
        cie_parameters(16)


def test_hand_computed_value():
    """Sun at zenith 30 deg, azimuth 180; sky element at zenith 60 deg, azimuth 90.

    cos chi = cos30 cos60 + sin30 sin60 cos90 = 0.433013 -> chi = 1.122964 rad (64.341 deg)
    f(chi)  = 1 + 10 (e^-3.368892 - e^-4.712389) + 0.45 * 0.1875       = 1.338820
    phi(60) = 1 - e^(-0.32 / 0.5)                                        = 0.472708
    f(30)   = 1 + 10 (e^-1.570796 - e^-4.712389) + 0.45 * 0.75          = 3.326463
    phi(0)  = 1 - e^-0.32                                                = 0.273851
    L / Lz  = 1.338820 * 0.472708 / (3.326463 * 0.273851)                = 0.694733
    """
    val = cie_relative_radiance(direction_from_angles(60.0, 90.0), direction_from_angles(30.0, 180.0))
    assert float(val) == pytest.approx(0.694733, abs=2e-6)
    a, b, c, d, e = cie_parameters(12)
    assert float(indicatrix(64.341094, c, d, e)) == pytest.approx(1.338820, abs=2e-6)
    assert float(gradation(60.0, a, b)) == pytest.approx(0.472708, abs=2e-6)


def test_zenith_is_one_and_below_horizon_is_zero():
    for sun_zen in (0.0, 25.0, 70.0):
        sun = direction_from_angles(sun_zen, 140.0)
        assert float(cie_relative_radiance([0.0, 0.0, 1.0], sun)) == pytest.approx(1.0, abs=1e-12)
        assert float(cie_relative_radiance(direction_from_angles(100.0, 0.0), sun)) == 0.0
    assert float(gradation(90.0, -1.0, -0.32)) == 1.0  # phi(horizon) = 1 by definition


def test_symmetric_about_the_solar_meridian():
    sun = direction_from_angles(40.0, 200.0)
    z = np.linspace(1.0, 89.0, 30)
    for off in (10.0, 75.0, 150.0):
        left = cie_relative_radiance(direction_from_angles(z, 200.0 - off), sun)
        right = cie_relative_radiance(direction_from_angles(z, 200.0 + off), sun)
        assert np.allclose(left, right, rtol=1e-12)


def test_monotonic_properties():
    a, b, c, d, e = cie_parameters(12)
    chi = np.linspace(0.0, 90.0, 181)
    assert np.all(np.diff(indicatrix(chi, c, d, e)) < 0)  # darker away from the sun up to 90 deg
    zen = np.linspace(0.0, 89.5, 180)
    assert np.all(np.diff(gradation(zen, a, b)) > 0)  # clear sky brightens toward the horizon
    # brightest near the sun: the circumsolar element beats the zenith and the antisolar sky
    sun = direction_from_angles(45.0, 90.0)
    near = cie_relative_radiance(direction_from_angles(45.0, 95.0), sun)
    anti = cie_relative_radiance(direction_from_angles(45.0, 270.0), sun)
    assert near > 1.0 > anti


@pytest.mark.parametrize("sky_type", [12.5, True, 0, 16, "12"])
def test_a_cie_sky_type_is_one_of_the_fifteen(sky_type):
    """12.5 was read as 12 and True as 1."""
    with pytest.raises(PihimInputError, match="CIE sky type must be an integer 1-15"):
        cie_parameters(sky_type)
    assert cie_parameters(np.int64(12)) == CIE_SKY_TYPES[12]
