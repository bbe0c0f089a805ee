"""Rayleigh skylight: DoLP law, E-field perpendicular to the scattering plane, frames and signs."""

from __future__ import annotations

import numpy as np
import pytest

from pihim.errors import PihimInputError
from pihim.polarimetry.frames import (
    aop4_deg,
    change_reference,
    dolp4,
    field_direction,
    perpendicular_reference,
)
from pihim.sky.rayleigh import meridian_frame, rayleigh_dolp, rayleigh_stokes
from pihim.sky.sun import direction_from_angles

SUN = direction_from_angles(35.0, 235.0)


def _upper_dirs(n, seed=0):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _field(stokes, v, e):
    """Oscillation axis cos(aop) e + sin(aop) (d x e), written out here independently of frames.py."""
    a = np.radians(aop4_deg(stokes))[..., None]
    d = -v
    return np.cos(a) * e + np.sin(a) * np.cross(d, e)


def test_dolp_zero_at_sun_and_antisun_max_at_90():
    perp = np.cross(SUN, [0.0, 0.0, 1.0])
    perp /= np.linalg.norm(perp)
    views = np.stack([SUN, -SUN, perp])
    st, _ = rayleigh_stokes(views, SUN, dmax=0.73)
    assert dolp4(st) == pytest.approx([0.0, 0.0, 0.73], abs=1e-12)


def test_dolp_follows_the_rayleigh_law():
    v = _upper_dirs(500)
    st, _ = rayleigh_stokes(v, SUN, dmax=0.9, s0=2.5)
    g_deg = np.degrees(np.arccos(np.clip(v @ SUN, -1, 1)))
    c2 = np.cos(np.radians(g_deg)) ** 2
    assert np.allclose(dolp4(st), 0.9 * (1 - c2) / (1 + c2), atol=1e-12)
    assert np.allclose(rayleigh_dolp(g_deg, 0.9), dolp4(st), atol=1e-12)
    assert np.allclose(st[:, 0], 2.5) and np.all(st[:, 3] == 0.0)


def test_field_is_perpendicular_to_the_scattering_plane():
    """The E-field implied by Stokes + frame is orthogonal to both the sun and the view direction."""
    rng = np.random.default_rng(7)
    for _ in range(5):
        sun = rng.normal(size=3)
        sun[2] = abs(sun[2])
        sun /= np.linalg.norm(sun)
        v = _upper_dirs(400, seed=int(rng.integers(1 << 30)))
        st, e = rayleigh_stokes(v, sun)
        keep = dolp4(st) > 1e-6
        fld = _field(st, v, e)[keep]
        assert np.allclose(fld @ sun, 0.0, atol=1e-9)
        assert np.allclose(np.sum(fld * v[keep], axis=1), 0.0, atol=1e-9)
        assert np.allclose(field_direction(st, -v, e)[keep], fld, atol=1e-12)


def test_frame_independence():
    """Any reference axis describes the same light: same DoLP, same field line, Stokes related by rotation."""
    v = _upper_dirs(300, seed=3)
    st_m, e_m = rayleigh_stokes(v, SUN, dmax=0.8)
    rng = np.random.default_rng(4)
    other = perpendicular_reference(-v, hint=rng.normal(size=(300, 3)))
    st_o, e_o = rayleigh_stokes(v, SUN, other, dmax=0.8)
    assert np.allclose(e_o, other)
    assert np.allclose(dolp4(st_o), dolp4(st_m), atol=1e-12)
    f_m, f_o = _field(st_m, v, e_m), _field(st_o, v, e_o)
    keep = dolp4(st_m) > 1e-6
    assert np.allclose(np.abs(np.sum(f_m * f_o, axis=1))[keep], 1.0, atol=1e-9)  # same axis (up to sign)
    assert np.allclose(change_reference(st_m, -v, e_m, e_o), st_o, atol=1e-12)


def test_aop_sign_in_the_meridian_frame():
    """Hand-worked case: facing North 45 deg up, sun East 45 deg up.

    The field is along s x v = (-1/2, -1/2, 1/2): in the frame (e = meridian up,
    d x e = West = the observer's left) that is 35.26 deg counter-clockwise from
    up, toward the left. A flipped handedness would give 144.74 deg.
    """
    st, _ = rayleigh_stokes(direction_from_angles(45.0, 0.0), direction_from_angles(45.0, 90.0))
    assert aop4_deg(st) == pytest.approx(np.degrees(np.arctan2(0.5, np.sqrt(0.5))), abs=1e-9)
    assert aop4_deg(st) == pytest.approx(35.264, abs=1e-3)
    # On the solar meridian (and the antisolar one) the field is horizontal: AoP 90.
    # On the horizon 90 deg of azimuth left of the sun (sun 30 deg from the zenith), the sun
    # appears 30 deg right of "up", so the field is 60 deg counter-clockwise from up.
    views = direction_from_angles([10.0, 50.0, 89.0, 90.0], [235.0, 235.0, 55.0, 145.0])
    st2, _ = rayleigh_stokes(views, direction_from_angles(30.0, 235.0))
    assert aop4_deg(st2) == pytest.approx([90.0, 90.0, 90.0, 60.0], abs=1e-9)


def test_meridian_frame_is_perpendicular_reference_and_left_handed_as_seen():
    v = np.vstack([_upper_dirs(200, seed=5), [[0.0, 0.0, 1.0]], -_upper_dirs(5, seed=6)])
    e, f = meridian_frame(v)
    assert np.allclose(e, perpendicular_reference(-v), atol=1e-12)
    assert np.allclose(f, np.cross(-v, e), atol=1e-12)
    e_n, f_n = meridian_frame(direction_from_angles(45.0, 0.0))  # looking North
    assert np.allclose(f_n, [-1.0, 0.0, 0.0])  # d x e is West: the observer's left
    assert e_n[2] > 0 and e_n[1] < 0  # "up" on the sky, tilted toward the observer


def test_bad_inputs():
    v = _upper_dirs(4)
    with pytest.raises(PihimInputError, match="perpendicular"):
        rayleigh_stokes(v, SUN, e=np.tile([0.0, 0.0, 1.0], (4, 1)))
    with pytest.raises(PihimInputError):
        rayleigh_stokes(np.zeros((2, 3)), SUN)
    with pytest.raises(PihimInputError):
        rayleigh_stokes(v[:, :2], SUN)


def test_rayleigh_dolp_refuses_a_maximum_beyond_one():
    """rayleigh_dolp(90, dmax=2) returned 2.0 (SkyModel refused dmax > 1, the function did not)."""
    for dmax in (2.0, -0.1, float("nan")):
        with pytest.raises(PihimInputError, match=r"dmax must lie in \[0, 1\]"):
            rayleigh_dolp(90.0, dmax)
    assert rayleigh_dolp(90.0, 1.0) == pytest.approx(1.0)
