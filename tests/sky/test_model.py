"""SkyModel: the interface used by the reflection models; validation, horizon, frames, maps."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pihim.errors import PihimInputError
from pihim.polarimetry.frames import (
    aop4_deg,
    change_reference,
    dolp4,
    perpendicular_reference,
)
from pihim.sky.model import SkyModel, sky_grid, sky_map
from pihim.sky.radiance import cie_relative_radiance
from pihim.sky.rayleigh import rayleigh_stokes
from pihim.sky.sun import direction_from_angles

SUN = direction_from_angles(30.0, 235.0)


def test_defaults_and_frozen():
    m = SkyModel()
    got = (m.kind, m.dmax, m.neutral_point_separation_deg, m.radiance, m.scale)
    assert got == ("rayleigh", 0.8, 15.0, "cie-clear", 1.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.dmax = 0.5  # type: ignore[misc]


@pytest.mark.parametrize(
    "kwargs, needle",
    [
        ({"kind": "mie"}, "unknown sky model"),
        ({"dmax": 1.2}, "dmax"),
        ({"dmax": -0.1}, "dmax"),
        ({"dmax": float("nan")}, "dmax"),
        ({"radiance": "perez"}, "radiance"),
        ({"neutral_point_separation_deg": 50.0}, "separation"),
        ({"neutral_point_separation_deg": -1.0}, "separation"),
        ({"scale": 0.0}, "scale"),
    ],
)
def test_parameters_are_validated(kwargs, needle):
    with pytest.raises(PihimInputError, match=needle):
        SkyModel(**kwargs)


def test_below_horizon_directions_get_zero_stokes():
    views = direction_from_angles([10.0, 89.9, 90.0, 90.5, 135.0, 180.0], [0.0, 100.0, 200.0, 300.0, 40.0, 0.0])
    for kind in ("rayleigh", "berry"):
        st, e = SkyModel(kind=kind).stokes(views, SUN)
        assert st.shape == (6, 4) and e.shape == (6, 3)
        assert np.all(st[3:] == 0.0)
        assert np.all(st[:3, 0] > 0.0)


def test_sun_below_horizon_is_refused():
    with pytest.raises(PihimInputError, match="below the horizon"):
        SkyModel().stokes(direction_from_angles(20.0, 0.0), direction_from_angles(95.0, 90.0))


def test_s0_from_radiance_and_scale():
    views = direction_from_angles([0.0, 40.0, 80.0], [0.0, 235.0, 90.0])
    st, _ = SkyModel(radiance="uniform", scale=3.0).stokes(views, SUN)
    assert np.allclose(st[:, 0], 3.0)
    st, _ = SkyModel(radiance="cie-clear", scale=2.0).stokes(views, SUN)
    assert st[0, 0] == pytest.approx(2.0)  # zenith = scale
    assert np.allclose(st[:, 0], 2.0 * cie_relative_radiance(views, SUN))
    r, _ = rayleigh_stokes(views, SUN, dmax=0.8)
    assert np.allclose(st[:, 1:], r[:, 1:] * st[:, :1])  # DoLP/AoP do not depend on S0


def test_broadcasting_and_given_frame():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(4, 5, 3))
    v[..., 2] = np.abs(v[..., 2])
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    m = SkyModel(kind="berry")
    st, e = m.stokes(v, SUN)
    assert st.shape == (4, 5, 4) and e.shape == (4, 5, 3)
    assert np.allclose(e, perpendicular_reference(-v), atol=1e-12)
    other = perpendicular_reference(-v, hint=[1.0, 0.0, 0.0])
    st2, e2 = m.stokes(v, SUN, other)
    assert np.allclose(e2, other)
    assert np.allclose(change_reference(st, -v, e, e2), st2, atol=1e-12)
    with pytest.raises(PihimInputError, match="perpendicular"):
        m.stokes(v, SUN, np.broadcast_to([0.0, 0.0, 1.0], v.shape))


def test_sky_grid():
    zz, aa = sky_grid(0.5)
    assert zz.shape == aa.shape == (180, 720)
    assert zz.size == 129_600
    assert (zz[0, 0], zz[-1, 0], aa[0, 0], aa[0, -1]) == (0.25, 89.75, 0.25, 359.75)
    for bad in (0.7, 0.0, -1.0, 20.0, float("nan")):
        with pytest.raises(PihimInputError, match="resolution"):
            sky_grid(bad)


@pytest.mark.parametrize("resolution", [0.5, 3.0])
def test_sky_map_grid_frames_match_the_generic_route(resolution):
    """sky_map's cached directions and meridian frames (outer products) = direction_from_angles + meridian_frame."""
    from pihim.sky.model import _grid_geometry, _grid_size
    from pihim.sky.rayleigh import meridian_frame
    from pihim.sky.sun import direction_from_angles

    zz, aa, v, e, f = _grid_geometry(_grid_size(resolution))
    v_ref = direction_from_angles(*sky_grid(resolution))
    e_ref, f_ref = meridian_frame(v_ref)
    for got, ref in ((v, v_ref), (e, e_ref), (f, f_ref)):
        assert got.shape == ref.shape
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-15)
        assert not got.flags.writeable
    res = sky_map(SkyModel(), SUN, resolution)
    s, _ = SkyModel().stokes(v_ref, SUN)
    np.testing.assert_allclose(res.s0, s[..., 0], rtol=1e-13)
    np.testing.assert_allclose(res.dolp, np.hypot(s[..., 1], s[..., 2]) / s[..., 0], rtol=0, atol=1e-13)


def test_sky_map_rayleigh_pattern():
    res = sky_map(SkyModel(dmax=0.8), SUN, resolution_deg=2.0)
    assert res.dolp.shape == (45, 180)
    scat = np.degrees(np.arccos(np.clip(direction_from_angles(res.zenith_deg, res.azimuth_deg) @ SUN, -1, 1)))
    assert np.nanmax(res.dolp) == pytest.approx(0.8, abs=1e-3)
    assert np.all(res.dolp[np.abs(scat - 90.0) < 1.0] > 0.79)
    assert np.all(res.dolp[scat < 5.0] < 0.01)
    # solar meridian (azimuth 235 and 55): field horizontal, AoP 90 in the meridian frame
    col = int(np.argmin(np.abs(res.azimuth_deg[0] - 235.0)))
    assert np.allclose(res.aop_deg[:, col], 90.0, atol=1.5)
    assert np.all((res.aop_deg >= 0) & (res.aop_deg < 180))
    st, _ = SkyModel(dmax=0.8).stokes(direction_from_angles(res.zenith_deg, res.azimuth_deg), SUN)
    assert np.allclose(res.dolp, dolp4(st)) and np.allclose(res.aop_deg, aop4_deg(st))
