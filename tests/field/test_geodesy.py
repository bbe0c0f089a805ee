"""ENU <-> WGS84: exact round trips, an independent closed-form oracle, and why no flat-earth shortcut."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from pihim.errors import PihimInputError
from pihim.field.geodesy import (
    NSTTF_ORIGIN_LATITUDE_DEG,
    NSTTF_ORIGIN_LONGITUDE_DEG,
    GeodeticOrigin,
    as_origin,
    enu_to_geodetic,
    geodetic_to_enu,
    nsttf_origin,
)

H0 = 1684.88  # ellipsoidal height used by pihim.sky.sun.NSTTF (orthometric 1706.88 m - 22 m geoid)
ORIGIN = nsttf_origin(H0)
A_WGS84 = 6378137.0
F_WGS84 = 1 / 298.257223563


def nsttf_extent_grid() -> np.ndarray:
    """ENU points spanning the NSTTF field (x -140..140 m, y -20..200 m, 0..30 m up)."""
    e, n, u = np.meshgrid(np.linspace(-140, 140, 15), np.linspace(-20, 200, 12), [0.0, 5.0, 30.0], indexing="ij")
    return np.stack([e, n, u], -1).reshape(-1, 3)


def ecef(lat_deg: np.ndarray, lon_deg: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Closed-form geodetic -> ECEF on WGS84 (textbook formula, independent of pymap3d)."""
    e2 = F_WGS84 * (2 - F_WGS84)
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    nu = A_WGS84 / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    return np.stack([(nu + h) * np.cos(lat) * np.cos(lon), (nu + h) * np.cos(lat) * np.sin(lon),
                     (nu * (1 - e2) + h) * np.sin(lat)], -1)


def test_origin_constants() -> None:
    assert (NSTTF_ORIGIN_LATITUDE_DEG, NSTTF_ORIGIN_LONGITUDE_DEG) == (34.962276, -106.509606)
    assert ORIGIN == GeodeticOrigin(34.962276, -106.509606, H0)
    lat, lon, h = enu_to_geodetic([0.0, 0.0, 0.0], ORIGIN)
    assert np.allclose([lat, lon, h], [34.962276, -106.509606, H0], atol=1e-12)


def test_round_trips_below_a_millimetre() -> None:
    p = nsttf_extent_grid()
    lat, lon, h = enu_to_geodetic(p, ORIGIN)
    assert lat.shape == (len(p),)
    back = geodetic_to_enu(lat, lon, h, ORIGIN)
    assert np.max(np.abs(back - p)) < 1e-3 and np.max(np.abs(back - p)) < 1e-6  # in fact micrometres
    lat2, lon2, h2 = enu_to_geodetic(back, ORIGIN)
    assert np.max(np.abs(lat2 - lat)) < 1e-11 and np.max(np.abs(lon2 - lon)) < 1e-11 and np.max(np.abs(h2 - h)) < 1e-6


def test_against_closed_form_oracle() -> None:
    """geodetic_to_enu equals R(lat0, lon0) (ECEF - ECEF0) computed by hand."""
    p = nsttf_extent_grid()
    lat, lon, h = enu_to_geodetic(p, ORIGIN)
    lat0, lon0 = math.radians(ORIGIN.latitude_deg), math.radians(ORIGIN.longitude_deg)
    rot = np.array([
        [-math.sin(lon0), math.cos(lon0), 0.0],
        [-math.sin(lat0) * math.cos(lon0), -math.sin(lat0) * math.sin(lon0), math.cos(lat0)],
        [math.cos(lat0) * math.cos(lon0), math.cos(lat0) * math.sin(lon0), math.sin(lat0)],
    ])
    expected = (ecef(lat, lon, h) - ecef(np.array(ORIGIN.latitude_deg), np.array(ORIGIN.longitude_deg),
                                         np.array(H0))) @ rot.T
    assert np.max(np.abs(geodetic_to_enu(lat, lon, h, ORIGIN) - expected)) < 1e-6
    assert np.max(np.abs(expected - p)) < 1e-6  # so enu_to_geodetic is right too


def test_directions_and_curvature() -> None:
    lat, lon, h = enu_to_geodetic([[0.0, 100.0, 0.0], [100.0, 0.0, 0.0], [0.0, 0.0, 50.0], [2000.0, 0.0, 0.0]],
                                  ORIGIN)
    assert lat[0] > ORIGIN.latitude_deg and math.isclose(lon[0], ORIGIN.longitude_deg, abs_tol=1e-12)
    assert lon[1] > ORIGIN.longitude_deg  # East is increasing longitude
    assert math.isclose(h[2], H0 + 50.0, abs_tol=1e-6)  # Up is the ellipsoid normal
    # a point on the tangent plane 2 km away stands d^2 / (2 R) above the ellipsoid (R ~ 6385 km there)
    assert math.isclose(h[3] - H0, 2000.0**2 / (2 * 6.386e6), rel_tol=0.01)


@pytest.mark.parametrize("metres_per_degree", [111_320.0, 111_111.0])
def test_flat_earth_shortcut_is_decimetres_off_across_nsttf(metres_per_degree: float) -> None:
    """The metres-per-degree shortcut is 0.3-0.8 m off at the field edges: the exact route matters."""
    p = nsttf_extent_grid()
    lat0, lon0 = ORIGIN.latitude_deg, ORIGIN.longitude_deg
    lat = lat0 + p[:, 1] / metres_per_degree
    lon = lon0 + p[:, 0] / (metres_per_degree * math.cos(math.radians(lat0)))
    exact = geodetic_to_enu(lat, lon, H0 + p[:, 2], ORIGIN)
    err = np.hypot(*(exact[:, :2] - p[:, :2]).T)
    assert 0.3 < err.max() < 0.8
    assert err.max() > 1e5 * np.max(np.abs(geodetic_to_enu(*enu_to_geodetic(p, ORIGIN), ORIGIN) - p))


def test_origin_forms_and_errors() -> None:
    site = SimpleNamespace(latitude_deg=34.962276, longitude_deg=-106.509606, height_m=H0, name="NSTTF")
    p = np.array([[10.0, 20.0, 3.0]])
    assert np.allclose(enu_to_geodetic(p, site), enu_to_geodetic(p, (34.962276, -106.509606, H0)))
    assert as_origin(site) == ORIGIN
    with pytest.raises(PihimInputError, match="ellipsoidal height"):
        as_origin((34.96, -106.5))  # the height is never implicit
    with pytest.raises(PihimInputError, match="latitude_deg"):
        GeodeticOrigin(95.0, 0.0, 0.0)
    with pytest.raises(PihimInputError, match="height_m"):
        nsttf_origin(float("nan"))
    with pytest.raises(PihimInputError, match="3 components"):
        enu_to_geodetic([1.0, 2.0], ORIGIN)
    with pytest.raises(PihimInputError, match="latitude"):
        geodetic_to_enu(91.0, 0.0, 0.0, ORIGIN)
    # shapes broadcast
    out = geodetic_to_enu(np.full((2, 3), 34.97), -106.5, H0, ORIGIN)
    assert out.shape == (2, 3, 3)
