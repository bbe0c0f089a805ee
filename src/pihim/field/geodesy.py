"""Exact conversion between the field frame (local ENU) and WGS84 geodetic coordinates.

The field frame is a local East-North-Up tangent frame at the field origin
(the tower base): ``Up`` is the WGS84 ellipsoid normal at the origin, metres.
Geodetic coordinates are latitude and longitude (degrees) and **ellipsoidal**
height (metres above the WGS84 ellipsoid, not above sea level:
ellipsoidal = orthometric + geoid undulation; about 22 m lower at the NSTTF).

The conversion goes through Earth-centred Earth-fixed coordinates with
pymap3d [1]_ (``enu2geodetic``, ``geodetic2enu``); it is exact to well below
a millimetre over a field. The flat-earth shortcut (a fixed number of metres
per degree of latitude and ``cos(lat)`` times that per degree of longitude)
is 0.5-0.7 m off at the edges of the NSTTF field, which is why pihim does not
use it (tested).

The origin height must be given explicitly: there is no silent default.
:data:`pihim.sky.sun.NSTTF` (a ``Site``) carries the project's documented
NSTTF value and can be passed as the origin.

References
----------
.. [1] M. Hirsch, "pymap3d: Python 3-D coordinate conversions for geospace
   ecef enu eci", Journal of Open Source Software 3(23), 580 (2018),
   doi:10.21105/joss.00580.
.. [2] Sandia National Laboratories, OpenCSP: NSTTF field origin (tower
   base) lon -106.509606 deg, lat 34.962276 deg.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import pymap3d
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError

__all__ = [
    "NSTTF_ORIGIN_LATITUDE_DEG",
    "NSTTF_ORIGIN_LONGITUDE_DEG",
    "GeodeticOrigin",
    "as_origin",
    "enu_to_geodetic",
    "geodetic_to_enu",
    "nsttf_origin",
]

#: Geodetic latitude of the NSTTF field origin (tower base), degrees (OpenCSP).
NSTTF_ORIGIN_LATITUDE_DEG = 34.962276
#: Longitude of the NSTTF field origin (tower base), degrees East (OpenCSP).
NSTTF_ORIGIN_LONGITUDE_DEG = -106.509606


class _SiteLike(Protocol):
    latitude_deg: float
    longitude_deg: float
    height_m: float


@dataclass(frozen=True)
class GeodeticOrigin:
    """Origin of a local ENU field frame on the WGS84 ellipsoid.

    Attributes
    ----------
    latitude_deg : float
        Geodetic latitude, degrees, positive North.
    longitude_deg : float
        Longitude, degrees, positive East.
    height_m : float
        Ellipsoidal height, metres.
    """

    latitude_deg: float
    longitude_deg: float
    height_m: float

    def __post_init__(self) -> None:
        for label, v, lim in (("latitude_deg", self.latitude_deg, 90.0), ("longitude_deg", self.longitude_deg, 180.0),
                              ("height_m", self.height_m, math.inf)):
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(v) \
                    or abs(v) > lim:
                within = "" if math.isinf(lim) else f" within +/-{lim:g}"
                raise PihimInputError(f"GeodeticOrigin.{label} must be a finite number{within}, got {v!r}")
            object.__setattr__(self, label, float(v))


def nsttf_origin(height_m: float) -> GeodeticOrigin:
    """The NSTTF field origin (OpenCSP's lon/lat) at an explicit ellipsoidal height, metres."""
    return GeodeticOrigin(NSTTF_ORIGIN_LATITUDE_DEG, NSTTF_ORIGIN_LONGITUDE_DEG, height_m)


def as_origin(origin: GeodeticOrigin | _SiteLike | Sequence[float]) -> GeodeticOrigin:
    """A :class:`GeodeticOrigin` from itself, a site-like object or ``(lat_deg, lon_deg, height_m)``.

    Site-like: anything with ``latitude_deg``, ``longitude_deg`` and
    ``height_m`` (ellipsoidal) attributes, e.g. :class:`pihim.sky.sun.Site`.
    """
    if isinstance(origin, GeodeticOrigin):
        return origin
    if all(hasattr(origin, a) for a in ("latitude_deg", "longitude_deg", "height_m")):
        o: Any = origin
        return GeodeticOrigin(o.latitude_deg, o.longitude_deg, o.height_m)
    if isinstance(origin, Sequence) and not isinstance(origin, str) and len(origin) == 3:
        return GeodeticOrigin(*origin)
    raise PihimInputError(
        "origin must be a GeodeticOrigin, a Site or (latitude_deg, longitude_deg, ellipsoidal height_m);"
        f" got {origin!r}"
    )


def enu_to_geodetic(
    enu: ArrayLike, origin: GeodeticOrigin | _SiteLike | Sequence[float]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Field-frame points to WGS84 geodetic coordinates (exact, via ECEF).

    Parameters
    ----------
    enu : array_like, shape (..., 3)
        East, North, Up, metres, in the tangent frame at ``origin``.
    origin : GeodeticOrigin, Site or (lat_deg, lon_deg, height_m)
        The field origin; its height is ellipsoidal.

    Returns
    -------
    latitude_deg, longitude_deg, height_m : ndarray, shape (...)
        Geodetic latitude and longitude (degrees) and ellipsoidal height
        (metres).
    """
    o = as_origin(origin)
    p = np.asarray(enu, dtype=float)
    if p.ndim == 0 or p.shape[-1] != 3 or not np.all(np.isfinite(p)):
        raise PihimInputError(f"enu must be finite with 3 components on its last axis, got shape {p.shape}")
    lat, lon, h = pymap3d.enu2geodetic(p[..., 0], p[..., 1], p[..., 2], o.latitude_deg, o.longitude_deg,
                                       o.height_m, deg=True)
    return np.asarray(lat, dtype=float), np.asarray(lon, dtype=float), np.asarray(h, dtype=float)


def geodetic_to_enu(
    latitude_deg: ArrayLike,
    longitude_deg: ArrayLike,
    height_m: ArrayLike,
    origin: GeodeticOrigin | _SiteLike | Sequence[float],
) -> NDArray[np.float64]:
    """WGS84 geodetic coordinates to the field frame (exact, via ECEF).

    Parameters
    ----------
    latitude_deg, longitude_deg : array_like
        Geodetic latitude and longitude, degrees (broadcast together).
    height_m : array_like
        Ellipsoidal height, metres.
    origin : GeodeticOrigin, Site or (lat_deg, lon_deg, height_m)
        The field origin; its height is ellipsoidal.

    Returns
    -------
    ndarray, shape (..., 3)
        East, North, Up, metres.
    """
    o = as_origin(origin)
    lat, lon, h = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (latitude_deg, longitude_deg, height_m)))
    if not (np.all(np.isfinite(lat)) and np.all(np.isfinite(lon)) and np.all(np.isfinite(h))):
        raise PihimInputError("geodetic coordinates must be finite")
    if np.any(np.abs(lat) > 90.0):
        raise PihimInputError("latitude must be within [-90, 90] deg")
    e, n, u = pymap3d.geodetic2enu(lat, lon, h, o.latitude_deg, o.longitude_deg, o.height_m, deg=True)
    return np.stack([np.asarray(e, dtype=float), np.asarray(n, dtype=float), np.asarray(u, dtype=float)], axis=-1)
