"""Sun position, sites and times: ENU and azimuth conventions pinned against independent oracles."""

from __future__ import annotations

from datetime import datetime

import numpy as np
import pandas as pd
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pihim.errors import PihimInputError
from pihim.sky.sun import (
    NSTTF,
    NSTTF_GEOID_UNDULATION_M,
    NSTTF_ORTHOMETRIC_HEIGHT_M,
    Site,
    SunPosition,
    angles_from_direction,
    direction_from_angles,
    parse_site,
    parse_time,
    require_daylight,
    standard_pressure_pa,
    sun_position,
)


@pytest.mark.parametrize(
    "zenith, azimuth, expected",
    [
        (90.0, 0.0, (0.0, 1.0, 0.0)),  # North is +y
        (90.0, 90.0, (1.0, 0.0, 0.0)),  # East is +x: azimuth clockwise from North
        (90.0, 180.0, (0.0, -1.0, 0.0)),
        (90.0, 270.0, (-1.0, 0.0, 0.0)),
        (0.0, 123.0, (0.0, 0.0, 1.0)),  # zenith is +z
        (60.0, 90.0, (np.sin(np.radians(60)), 0.0, 0.5)),
    ],
)
def test_direction_from_angles_enu_axes(zenith, azimuth, expected):
    assert np.allclose(direction_from_angles(zenith, azimuth), expected, atol=1e-15)


@given(st.floats(0.01, 179.99), st.floats(0.0, 359.99))
def test_angles_direction_roundtrip(zenith, azimuth):
    v = direction_from_angles(zenith, azimuth)
    assert np.linalg.norm(v) == pytest.approx(1.0)
    z, a = angles_from_direction(v)
    assert z == pytest.approx(zenith, abs=1e-9)
    assert (a - azimuth + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=1e-7)


def test_nrel_spa_reference_value():
    """Reda & Andreas (2004) test case, as in NREL's SPA and pvlib's tests."""
    site = Site("SPA test", 39.742476, -105.1786, 1830.14)
    pos = sun_position(site, "2003-10-17T12:30:30-07:00", pressure_pa=82000.0, temperature_c=11.0, delta_t_s=67.0)
    assert pos.zenith_deg == pytest.approx(50.11162, abs=2e-5)
    assert pos.azimuth_deg == pytest.approx(194.34024, abs=2e-5)
    assert pos.elevation_deg == pytest.approx(90.0 - 50.11162, abs=2e-5)


def test_sun_position_is_pvlib_spa_python_exactly():
    """pvlib's SPA module loaded on its own and called as spa_python calls it: the same numbers, to the bit."""
    pvlib = pytest.importorskip("pvlib")
    rng = np.random.default_rng(0)
    seconds = pd.to_timedelta(np.round(rng.uniform(0, 3 * 365 * 86400, 200), 3), unit="s")  # to the millisecond
    times = pd.DatetimeIndex(pd.Timestamp("2020-01-01", tz="UTC") + seconds)
    for site in (NSTTF, Site("Almeria", 37.09, -2.36, 550.0), Site("Alice Springs", -23.7, 133.87, 600.0)):
        pressure = pvlib.atmosphere.alt2pres(site.height_m)
        assert standard_pressure_pa(site.height_m) == pressure
        for dt in (None, 69.2):
            ref = pvlib.solarposition.spa_python(times, site.latitude_deg, site.longitude_deg, altitude=site.height_m,
                                                 pressure=pressure, temperature=12.0, delta_t=dt, how="numpy")
            got = sun_position(site, times, delta_t_s=dt)
            assert np.array_equal(got.zenith_deg, ref["apparent_zenith"].to_numpy())
            assert np.array_equal(got.azimuth_deg, ref["azimuth"].to_numpy())
            true = sun_position(site, times, delta_t_s=dt, refraction=False)
            assert np.array_equal(true.zenith_deg, ref["zenith"].to_numpy())
    # strings and datetimes (no pandas on that path) give the same bits as the DatetimeIndex
    local = [t.tz_convert("America/Denver") for t in times[:20]]
    by_text = sun_position(NSTTF, [t.isoformat() for t in local])
    by_index = sun_position(NSTTF, times[:20])
    assert np.array_equal(by_text.zenith_deg, by_index.zenith_deg)
    assert np.array_equal(by_text.azimuth_deg, by_index.azimuth_deg)
    one = sun_position(NSTTF, local[3].to_pydatetime())
    assert (one.zenith_deg, one.azimuth_deg) == (by_index.zenith_deg[3], by_index.azimuth_deg[3])


def test_sun_position_imports_neither_pvlib_nor_pandas():
    """Importing pvlib costs about half a second of CPU and pandas most of another: the SPA module alone is
    loaded, and a time given as text or a datetime needs no pandas."""
    import subprocess
    import sys

    code = ("import sys; from pihim.sky.sun import parse_time, sun_position; "
            "t = parse_time('2021-05-13T13:00-06:00'); sun_position('nsttf', t); sun_position('nsttf', [t, t]); "
            "print(type(t).__name__, 'pvlib' in sys.modules, 'pandas' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["datetime", "False", "False"]


def test_equinox_solar_noon_at_nsttf():
    """Independent oracle: at an equinox the noon sun stands 90 - latitude high, due South."""
    times = pd.date_range("2024-03-20T11:30:00-06:00", "2024-03-20T15:30:00-06:00", freq="1min")
    pos = sun_position(NSTTF, times, refraction=False)
    i = int(np.argmax(pos.elevation_deg))
    # declination is about +0.3 deg at local noon on 2024-03-20 (equinox at 03:06 UTC)
    assert pos.elevation_deg[i] == pytest.approx(90.0 - NSTTF.latitude_deg, abs=0.6)
    assert pos.azimuth_deg[i] == pytest.approx(180.0, abs=1.5)
    # solar noon near 13:14 MDT: 106.5 deg W is 7.1 h behind UTC, minus ~7.5 min equation of time
    noon = times[i].tz_convert("America/Denver")
    assert 13 * 60 + 5 <= noon.hour * 60 + noon.minute <= 13 * 60 + 22


def test_morning_sun_is_east_afternoon_sun_is_west():
    pos = sun_position("nsttf", ["2024-06-21T07:00:00-06:00", "2024-06-21T17:30:00-06:00"])
    morning, afternoon = pos.azimuth_deg
    assert 50.0 < morning < 90.0  # ENE in June
    assert 270.0 < afternoon < 310.0  # WNW
    assert pos.vector[0, 0] > 0.5 and pos.vector[1, 0] < -0.5  # x is East
    assert pos.vector[0, 2] > 0.0 and pos.vector[1, 2] > 0.0  # toward the sun: up in daytime
    assert np.allclose(pos.vector, direction_from_angles(pos.zenith_deg, pos.azimuth_deg))
    assert np.allclose(np.linalg.norm(pos.vector, axis=1), 1.0)


def test_vectorised_matches_scalar_calls_and_apparent_is_higher():
    times = ["2024-06-21T08:00:00-06:00", "2024-12-21T12:00:00-07:00", "2024-09-01T18:00:00Z"]
    many = sun_position(NSTTF, times)
    assert many.zenith_deg.shape == (3,) and many.vector.shape == (3, 3)
    for k, t in enumerate(times):
        one = sun_position(NSTTF, t)
        assert isinstance(one.zenith_deg, float) and one.vector.shape == (3,)
        assert one.zenith_deg == pytest.approx(many.zenith_deg[k], abs=1e-9)
        true = sun_position(NSTTF, t, refraction=False)
        assert 0.0 < true.zenith_deg - one.zenith_deg < 0.1  # refraction lifts the sun


def test_parse_time_offsets_and_z():
    a = parse_time("2024-06-21T10:00:00-06:00")
    b = parse_time("2024-06-21T16:00Z")
    assert a == b and a.tzinfo is not None
    assert parse_time(datetime.fromisoformat("2024-06-21T10:00:00+02:00")).utcoffset().total_seconds() == 7200


@pytest.mark.parametrize("naive", ["2024-06-21T10:00:00", "2024-06-21 10:00", datetime(2024, 6, 21, 10)])
def test_naive_time_refused(naive):
    with pytest.raises(PihimInputError, match="no UTC offset"):
        parse_time(naive)
    with pytest.raises(PihimInputError, match="no UTC offset"):
        sun_position(NSTTF, naive)


def test_naive_index_and_malformed_time_refused():
    with pytest.raises(PihimInputError, match="no UTC offset"):
        sun_position(NSTTF, pd.date_range("2024-01-01", periods=3, freq="h"))
    with pytest.raises(PihimInputError, match="ISO 8601"):
        parse_time("yesterday at noon")
    with pytest.raises(PihimInputError):
        sun_position(NSTTF, ["2024-06-21T10:00:00-06:00", "2024-06-21T11:00:00"])


def test_nsttf_site_and_parse_site():
    assert (NSTTF.latitude_deg, NSTTF.longitude_deg) == (34.962276, -106.509606)
    assert NSTTF.timezone == "America/Denver"
    assert NSTTF.height_m == pytest.approx(NSTTF_ORTHOMETRIC_HEIGHT_M + NSTTF_GEOID_UNDULATION_M)
    assert 1600.0 < NSTTF.height_m < 1750.0
    assert parse_site("NSTTF") is NSTTF and parse_site(" nsttf ") is NSTTF
    custom = parse_site("35.1, -106.6, 1650")
    assert (custom.latitude_deg, custom.longitude_deg, custom.height_m) == (35.1, -106.6, 1650.0)


@pytest.mark.parametrize("bad", ["mars", "35,-106", "95,0,0", "10,200,0", "a,b,c", "1,2,nan",
                                 "0,0,1e300", "0,0,-1e6", "0,0,inf"])
def test_parse_site_refuses_bad_text(bad):
    with pytest.raises(PihimInputError):
        parse_site(bad)


def test_require_daylight():
    night = sun_position(NSTTF, "2024-06-21T23:30:00-06:00")
    assert night.elevation_deg < 0 and not night.above_horizon
    with pytest.raises(PihimInputError, match="below the horizon"):
        require_daylight(night)
    with pytest.raises(PihimInputError, match="below the horizon"):
        require_daylight([0.0, 0.6, -0.8])
    require_daylight(SunPosition.from_angles(90.0, 10.0))  # on the horizon is allowed
    require_daylight(direction_from_angles(30.0, 235.0))


def test_out_of_range_years_refused_in_one_line():
    # issue 10: years pandas cannot hold used to fail deep inside pandas
    for text in ("9999-05-13T10:00-06:00", "1000-01-01T00:00Z"):
        with pytest.raises(PihimInputError, match="outside the years pihim handles") as err:
            parse_time(text)
        assert "\n" not in str(err.value)
    assert parse_time("2261-06-01T12:00Z").year == 2261


@pytest.mark.parametrize("azimuth, folded", [(-1e-20, 0.0), (-90.0, 270.0), (360.0, 0.0), (725.0, 5.0)])
def test_from_angles_folds_azimuth_into_0_360(azimuth, folded):
    """[0, 360) as documented: np.mod rounds a tiny negative azimuth up to 360.0 itself."""
    pos = SunPosition.from_angles(30.0, azimuth)
    assert 0.0 <= float(pos.azimuth_deg) < 360.0
    assert float(pos.azimuth_deg) == pytest.approx(folded, abs=1e-12)


def test_direction_angles_out_of_their_domain_are_refused():
    """Zenith 200 was accepted and came back as (160, 180); a zero vector came back as (0, 0)."""
    for zen in (200.0, -1.0, [10.0, 181.0]):
        with pytest.raises(PihimInputError, match=r"zenith_deg must lie in \[0, 180\]"):
            direction_from_angles(zen, 0.0)
    with pytest.raises(PihimInputError, match="a zero vector has no direction"):
        angles_from_direction([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(direction_from_angles(180.0, 0.0), [0.0, 0.0, -1.0], atol=1e-15)  # the nadir is fine
