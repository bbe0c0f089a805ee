"""Berry-Dennis-Lee sky: neutral points where documented, DoLP 0 there, Rayleigh limit, rotation covariance."""

from __future__ import annotations

import numpy as np
import pytest

from pihim.errors import PihimInputError
from pihim.polarimetry.frames import aop4_deg, dolp4
from pihim.polarimetry.stokes import aop_difference_deg
from pihim.sky.berry import berry_stokes, berry_w, neutral_points
from pihim.sky.rayleigh import rayleigh_stokes
from pihim.sky.sun import angles_from_direction, direction_from_angles


def _upper_dirs(n, seed=0):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _angles(v):
    z, a = angles_from_direction(v)
    return float(z), float(a)


def test_neutral_points_above_and_below_sun_on_its_vertical():
    pts = neutral_points(direction_from_angles(40.0, 235.0), 20.0)
    assert _angles(pts.babinet) == pytest.approx((20.0, 235.0))  # above the sun
    assert _angles(pts.brewster) == pytest.approx((60.0, 235.0))  # below the sun
    assert _angles(pts.arago) == pytest.approx((120.0, 55.0))  # antipode of Brewster: above the antisun
    assert _angles(pts.fourth) == pytest.approx((160.0, 55.0))  # antipode of Babinet: below the antisun


def test_babinet_passes_the_zenith_for_a_high_sun():
    pts = neutral_points(direction_from_angles(8.0, 235.0), 20.0)
    assert _angles(pts.babinet) == pytest.approx((12.0, 55.0))
    assert _angles(pts.brewster) == pytest.approx((28.0, 235.0))


@pytest.mark.parametrize("sun_zenith, sep", [(40.0, 20.0), (8.0, 20.0), (80.0, 15.0), (60.0, 25.0)])
def test_dolp_is_exactly_zero_at_the_neutral_points(sun_zenith, sep):
    sun = direction_from_angles(sun_zenith, 235.0)
    pts = neutral_points(sun, sep)
    where = np.stack([pts.babinet, pts.brewster, pts.arago, pts.fourth])
    st, _ = berry_stokes(where, sun, separation_deg=sep, dmax=0.8)
    assert np.all(np.hypot(st[:, 1], st[:, 2]) < 1e-12)
    assert np.all(dolp4(st) < 1e-12)
    # ... and clearly polarized 3 deg away from each of them
    side = np.cross(where, sun)
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    off = np.cos(np.radians(3.0)) * where + np.sin(np.radians(3.0)) * side
    st_off, _ = berry_stokes(off, sun, separation_deg=sep, dmax=0.8)
    assert np.all(dolp4(st_off) > 1e-3)


def test_low_sun_shows_the_arago_point_above_the_horizon():
    sun = direction_from_angles(80.0, 100.0)
    pts = neutral_points(sun, 15.0)
    z, a = _angles(pts.arago)
    assert z == pytest.approx(85.0) and a == pytest.approx(280.0)
    st, _ = berry_stokes(pts.arago, sun, separation_deg=15.0)
    assert dolp4(st) < 1e-12


def test_modulus_is_brewsters_product_of_sines():
    sun = direction_from_angles(50.0, 200.0)
    v = _upper_dirs(2000, seed=1)
    pts = neutral_points(sun, 18.0)
    w = berry_w(v, sun, 18.0)
    g_ba = np.arccos(np.clip(v @ pts.babinet, -1, 1))
    g_br = np.arccos(np.clip(v @ pts.brewster, -1, 1))
    assert np.allclose(np.abs(w), np.sin(g_ba) * np.sin(g_br), atol=1e-12)
    assert np.max(np.abs(w)) <= 1.0 + 1e-12


@pytest.mark.parametrize("sun_zenith", [0.0, 5.0, 30.0, 75.0, 90.0])
def test_zero_separation_is_exactly_rayleigh(sun_zenith):
    sun = direction_from_angles(sun_zenith, 310.0)
    v = _upper_dirs(1500, seed=2)
    b, e_b = berry_stokes(v, sun, separation_deg=0.0, dmax=0.7, s0=3.0)
    r, e_r = rayleigh_stokes(v, sun, dmax=0.7, s0=3.0)
    assert np.allclose(e_b, e_r)
    assert np.allclose(b, r, atol=1e-12)


def test_close_to_rayleigh_far_from_the_neutral_points():
    sun = direction_from_angles(35.0, 235.0)
    v = _upper_dirs(4000, seed=3)
    r, _ = rayleigh_stokes(v, sun, dmax=0.8)
    errs = []
    for sep in (15.0, 5.0):
        pts = neutral_points(sun, sep)
        near = np.degrees(np.arccos(np.clip(v @ np.stack([pts.babinet, pts.brewster, pts.arago, pts.fourth]).T, -1, 1)))
        far = near.min(axis=1) > 60.0
        b, _ = berry_stokes(v, sun, separation_deg=sep, dmax=0.8)
        d_aop = aop_difference_deg(aop4_deg(b), aop4_deg(r))[far]
        d_dolp = np.abs(dolp4(b) - dolp4(r))[far]
        errs.append((d_aop.max(), d_dolp.max()))
    (aop15, dolp15), (aop5, dolp5) = errs
    assert aop15 < 1.0 and dolp15 < 0.11
    assert aop5 < aop15 / 5 and dolp5 < dolp15 / 5  # converges to Rayleigh as the pairs merge


def test_pattern_turns_with_the_sun():
    """Rotating sun and sky about the vertical leaves DoLP and meridian-frame AoP unchanged."""
    v = _upper_dirs(1000, seed=4)
    sun = direction_from_angles(40.0, 20.0)
    b0, _ = berry_stokes(v, sun, separation_deg=20.0)
    for beta in (37.0, 123.0, 270.0):
        c, s = np.cos(np.radians(beta)), np.sin(np.radians(beta))
        rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # clockwise seen from above
        b1, _ = berry_stokes(v @ rot.T, rot @ sun, separation_deg=20.0)
        assert np.allclose(dolp4(b1), dolp4(b0), atol=1e-12)
        assert np.max(aop_difference_deg(aop4_deg(b1), aop4_deg(b0))) < 1e-7


def test_separation_is_validated():
    with pytest.raises(PihimInputError):
        neutral_points(direction_from_angles(30.0, 0.0), 60.0)
    with pytest.raises(PihimInputError):
        berry_stokes(_upper_dirs(3), direction_from_angles(30.0, 0.0), separation_deg=-1.0)
