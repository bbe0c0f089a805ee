"""Sun position in the East-North-Up field frame, sites and time parsing.

Conventions (``docs/conventions.md``; each one is pinned by a test in
``tests/sky/test_sun.py``):

* Field frame East-North-Up: ``x`` East, ``y`` North, ``z`` Up.
* Directions are unit vectors. Azimuth is measured **clockwise from North**
  (0 = N, 90 = E, 180 = S, 270 = W), zenith from ``+z``, elevation =
  90 - zenith -- the same angles as pvlib. A direction with zenith ``Z`` and
  azimuth ``A`` is ``(sin Z sin A, sin Z cos A, cos Z)``.
* The sun vector points **from the scene toward the sun**.
* Times must be timezone-aware; a naive time is refused with a
  :class:`~pihim.errors.PihimInputError`.

The sun position comes from pvlib's implementation of the NREL Solar Position
Algorithm (SPA, ``pvlib.spa``, the module behind
``pvlib.solarposition.spa_python``, quoted uncertainty +/-0.0003 deg over
-2000..6000) [1]_, called as ``spa_python`` calls it (numpy mode, pressure in
millibars, refraction 0.5667 deg at the horizon, pvlib's Delta T estimate) and
held to ``spa_python`` by a test; the module is loaded on its own because
importing the ``pvlib`` package costs about half a second of CPU (its other
submodules, scipy) that a command computing a sun position need not pay. By default the **apparent** (refraction
corrected) position is returned, because that is the direction from which
sunlight -- and the sky polarization pattern centred on it -- actually
arrives at the site; pass ``refraction=False`` for the true (geometric)
topocentric position.

References
----------
.. [1] I. Reda and A. Andreas, "Solar position algorithm for solar radiation
   applications", Solar Energy 76(5), 577-589 (2004),
   doi:10.1016/j.solener.2003.12.003; corrigendum Solar Energy 81(6), 838
   (2007), doi:10.1016/j.solener.2007.01.003.
.. [2] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone" (pihim paper), section 3: NSTTF field frame, x East,
   y North, z up, origin at the base of the tower.
"""

from __future__ import annotations

import functools
import importlib.util
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError

__all__ = [
    "NSTTF",
    "NSTTF_GEOID_UNDULATION_M",
    "NSTTF_ORTHOMETRIC_HEIGHT_M",
    "Site",
    "SunPosition",
    "angles_from_direction",
    "direction_from_angles",
    "parse_site",
    "parse_time",
    "require_daylight",
    "standard_pressure_pa",
    "sun_position",
]


def _is_real(x: Any) -> bool:
    """True for a finite real number (bools excluded)."""
    if isinstance(x, bool):
        return False
    try:
        return math.isfinite(float(x))
    except (TypeError, ValueError):
        return False


#: Ellipsoidal site heights accepted, metres: below the Dead Sea shore to above any airfield
#: (the standard atmosphere used for refraction ends at 44 km).
SITE_HEIGHT_RANGE_M = (-1000.0, 10000.0)

#: Calendar years accepted for times and dates (the range of :class:`pandas.Timestamp`).
YEAR_RANGE = (1678, 2261)


def check_year(year: int, text: object) -> None:
    """Refuse a time or date outside :data:`YEAR_RANGE` with one line naming ``text``."""
    lo, hi = YEAR_RANGE
    if not lo <= year <= hi:
        raise PihimInputError(f"{text!r}: year {year} is outside the years pihim handles, {lo}..{hi}")


@dataclass(frozen=True)
class Site:
    """A place on the WGS84 ellipsoid.

    Attributes
    ----------
    name : str
        Short label.
    latitude_deg : float
        Geodetic latitude, degrees, positive North.
    longitude_deg : float
        Longitude, degrees, positive East.
    height_m : float
        **Ellipsoidal** height above WGS84, metres (not height above sea
        level: ellipsoidal = orthometric + geoid undulation).
    timezone : str
        IANA time zone name for local-time displays (e.g. ``America/Denver``).
        Computations never depend on it: times carry their own offsets.
    """

    name: str
    latitude_deg: float
    longitude_deg: float
    height_m: float
    timezone: str = "UTC"

    def __post_init__(self) -> None:
        for label, value, lim in (("latitude", self.latitude_deg, 90.0), ("longitude", self.longitude_deg, 180.0)):
            if not (_is_real(value) and -lim <= float(value) <= lim):
                raise PihimInputError(f"site {label} must be a number in [-{lim:g}, {lim:g}] deg, got {value!r}")
        lo, hi = SITE_HEIGHT_RANGE_M
        if not (_is_real(self.height_m) and lo <= float(self.height_m) <= hi):
            raise PihimInputError(
                f"site height must be a number of metres in [{lo:g}, {hi:g}] (ellipsoidal), got {self.height_m!r}"
            )

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly record of the site."""
        return {
            "name": self.name,
            "latitude_deg": self.latitude_deg,
            "longitude_deg": self.longitude_deg,
            "height_m": self.height_m,
            "timezone": self.timezone,
        }


#: Orthometric height (above mean sea level) of the NSTTF heliostat field,
#: metres. 1706.88 m = 5600 ft, the elevation Sandia's OpenCSP scripts give
#: for heliostat 5E9 near the tower (they put the tower's balcony at
#: 1755.648 m = 5760 ft). It is a rounded figure, not a survey of the tower
#: base: treat it as +/-10 m.
NSTTF_ORTHOMETRIC_HEIGHT_M = 1706.88

#: Geoid undulation (EGM96 geoid above the WGS84 ellipsoid) at the NSTTF,
#: metres. Central New Mexico lies about 21-23 m below the ellipsoid; -22 m
#: is an estimate that could not be checked against a geoid grid from this
#: project (to be replaced by a GEOID18/EGM96 lookup if it ever matters).
NSTTF_GEOID_UNDULATION_M = -22.0

#: The NSTTF field origin (base of the tower): lon -106.509606,
#: lat 34.962276 (OpenCSP's ``NSTTF_ORIGIN``), ellipsoidal height
#: ``NSTTF_ORTHOMETRIC_HEIGHT_M + NSTTF_GEOID_UNDULATION_M`` = 1684.88 m
#: (uncertain by ~10 m; see the two constants above). Local time:
#: America/Denver. A 10 m height error moves the sun by less than 1e-6 deg
#: (topocentric parallax) and the refraction correction by less than 1e-4 deg.
NSTTF = Site(
    name="NSTTF",
    latitude_deg=34.962276,
    longitude_deg=-106.509606,
    height_m=NSTTF_ORTHOMETRIC_HEIGHT_M + NSTTF_GEOID_UNDULATION_M,
    timezone="America/Denver",
)

_KNOWN_SITES = {"nsttf": NSTTF}


def parse_site(text: str | Site) -> Site:
    """A site from ``"nsttf"`` (case-insensitive) or ``"LAT,LON,H"``.

    Parameters
    ----------
    text : str or Site
        A known site name, or latitude (deg, +N), longitude (deg, +E) and
        ellipsoidal height (m) separated by commas. A :class:`Site` is
        returned unchanged.

    Raises
    ------
    PihimInputError
        Unknown name, wrong number of fields or values out of range.
    """
    if isinstance(text, Site):
        return text
    key = str(text).strip()
    if key.lower() in _KNOWN_SITES:
        return _KNOWN_SITES[key.lower()]
    parts = [p.strip() for p in key.split(",")]
    if len(parts) != 3:
        raise PihimInputError(
            f"site {text!r}: expected a known name ({', '.join(_KNOWN_SITES)}) or LAT,LON,H "
            "(degrees, degrees, ellipsoidal metres)"
        )
    try:
        lat, lon, h = (float(p) for p in parts)
    except ValueError:
        raise PihimInputError(f"site {text!r}: LAT,LON,H must be numbers") from None
    return Site(name="custom", latitude_deg=lat, longitude_deg=lon, height_m=h, timezone="UTC")


def parse_time(time: str | datetime) -> datetime:
    """A timezone-aware :class:`datetime.datetime` from an ISO 8601 string or a datetime.

    Parameters
    ----------
    time : str or datetime.datetime
        E.g. ``"2024-06-21T10:30:00-06:00"`` or ``"2024-06-21T16:30Z"``; a
        :class:`pandas.Timestamp` (a datetime) is taken to the microsecond.

    Returns
    -------
    datetime.datetime
        With its UTC offset (``tzinfo``) as given. pandas is not needed, so
        commands that only parse a time do not pay for importing it.

    Raises
    ------
    PihimInputError
        Malformed text, a year outside :data:`YEAR_RANGE`, or a time without
        a UTC offset (naive): pihim never guesses a time zone.
    """
    if isinstance(time, str):
        try:
            ts = datetime.fromisoformat(time.strip())
        except ValueError:
            raise PihimInputError(
                f"time {time!r} is not an ISO 8601 date-time (e.g. 2024-06-21T10:30:00-06:00)"
            ) from None
        check_year(ts.year, time)
    elif isinstance(time, datetime):
        check_year(time.year, str(time))
        ts = time
        if type(ts) is not datetime:  # a pandas.Timestamp or another subclass: the plain datetime it stands for
            ts = datetime(ts.year, ts.month, ts.day, ts.hour, ts.minute, ts.second, ts.microsecond, ts.tzinfo,
                          fold=ts.fold)
    else:
        raise PihimInputError(f"time must be an ISO 8601 string or a datetime, got {type(time).__name__}")
    if ts.tzinfo is None or ts.utcoffset() is None:
        raise PihimInputError(
            f"time {str(time)!r} has no UTC offset; give one, e.g. 2024-06-21T10:30:00-06:00 or ...Z"
        )
    return ts


def direction_from_angles(zenith_deg: ArrayLike, azimuth_deg: ArrayLike) -> NDArray[np.float64]:
    """Unit ENU vectors ``(..., 3)`` from zenith and azimuth (deg, azimuth clockwise from North).

    ``x = sin Z sin A`` (East), ``y = sin Z cos A`` (North), ``z = cos Z`` (Up).
    The zenith angle must lie in [0, 180] deg (any azimuth is taken modulo
    360): outside it, :func:`angles_from_direction` would not give it back.
    """
    zen = np.asarray(zenith_deg, dtype=float)
    out = (zen < 0.0) | (zen > 180.0)
    if np.any(out):
        raise PihimInputError(f"zenith_deg must lie in [0, 180], got values such as {zen[out].ravel()[0]:g}")
    z_rad = np.radians(zen)
    a_rad = np.radians(np.asarray(azimuth_deg, dtype=float))
    z_rad, a_rad = np.broadcast_arrays(z_rad, a_rad)
    sz = np.sin(z_rad)
    return np.stack([sz * np.sin(a_rad), sz * np.cos(a_rad), np.cos(z_rad)], axis=-1)


def angles_from_direction(v: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Zenith and azimuth (deg) of ENU directions ``(..., 3)``; the inverse of :func:`direction_from_angles`.

    Vectors need not be normalised. Azimuth is in [0, 360), clockwise from
    North; it is 0 for directions along the vertical.
    """
    v = np.asarray(v, dtype=float)
    if v.shape[-1:] != (3,):
        raise PihimInputError(f"directions need 3 components on the last axis, got shape {v.shape}")
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    if np.any((x == 0) & (y == 0) & (z == 0)):
        raise PihimInputError("a zero vector has no direction (angles_from_direction)")
    zen = np.degrees(np.arctan2(np.hypot(x, y), z))
    az = np.mod(np.degrees(np.arctan2(x, y)), 360.0)
    az = np.where(az >= 360.0, 0.0, az)
    return zen, az


@dataclass(frozen=True)
class SunPosition:
    """Where the sun is, seen from a site.

    Scalars for one time; arrays of shape ``(n,)`` (vector ``(n, 3)``) for
    ``n`` times.

    Attributes
    ----------
    zenith_deg, azimuth_deg, elevation_deg : float or numpy.ndarray
        Degrees; azimuth clockwise from North; elevation = 90 - zenith.
        Apparent (refraction-corrected) unless computed with
        ``refraction=False``.
    vector : numpy.ndarray
        Unit ENU vector(s) from the scene toward the sun, ``(3,)`` or ``(n, 3)``.
    """

    zenith_deg: Any
    azimuth_deg: Any
    elevation_deg: Any
    vector: NDArray[np.float64] = field(repr=False)

    @classmethod
    def from_angles(cls, zenith_deg: ArrayLike, azimuth_deg: ArrayLike) -> SunPosition:
        """A position from zenith and azimuth (deg); azimuth is folded into [0, 360)."""
        zen = np.asarray(zenith_deg, dtype=float)
        az = np.mod(np.asarray(azimuth_deg, dtype=float), 360.0)
        az = np.where(az >= 360.0, 0.0, az)  # a tiny negative azimuth rounds to 360.0 in np.mod
        if not (np.all(np.isfinite(zen)) and np.all(np.isfinite(az))):
            raise PihimInputError("sun zenith and azimuth must be finite numbers")
        if np.any((zen < 0.0) | (zen > 180.0)):
            raise PihimInputError(f"sun zenith must be in [0, 180] deg, got {zenith_deg!r}")
        vec = direction_from_angles(zen, az)
        conv = float if zen.ndim == 0 else np.asarray
        return cls(conv(zen), conv(az), conv(90.0 - zen), vec)

    @property
    def above_horizon(self) -> Any:
        """True where the sun's centre is above the horizon (elevation >= 0)."""
        above = np.asarray(self.elevation_deg) >= 0.0
        return bool(above) if above.ndim == 0 else above

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly record (lists for several times)."""
        def conv(x: Any) -> Any:
            return np.asarray(x).tolist()

        return {
            "zenith_deg": conv(self.zenith_deg),
            "azimuth_deg": conv(self.azimuth_deg),
            "elevation_deg": conv(self.elevation_deg),
            "vector": conv(self.vector),
        }


def _instants(time: Any) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.int64], bool]:
    """Unix times (s), UTC years and UTC months of one or many times, and whether a single time was given.

    pandas objects are handled only when pandas is already loaded (they cannot exist otherwise).
    """
    pd = sys.modules.get("pandas")
    if isinstance(time, str | datetime):
        stamps, single = [parse_time(time)], True
    elif pd is not None and isinstance(time, pd.DatetimeIndex):
        if time.tz is None:
            raise PihimInputError("times have no UTC offset (naive DatetimeIndex); localise them first")
        utc = time.tz_convert("UTC")
        unix = np.asarray((utc - pd.Timestamp("1970-01-01", tz="UTC")) / pd.Timedelta("1s"), dtype=float)
        return unix, utc.year.to_numpy(), utc.month.to_numpy(), False
    elif isinstance(time, Sequence | np.ndarray) or (pd is not None and isinstance(time, pd.Series)):
        stamps, single = [parse_time(t) for t in time], False
        if not stamps:
            raise PihimInputError("no times given")
    else:
        raise PihimInputError(
            f"time must be an ISO 8601 string, a datetime or a sequence of them, got {type(time).__name__}"
        )
    utc = [t.astimezone(timezone.utc) for t in stamps]
    unix = np.array([t.timestamp() for t in stamps], dtype=float)  # exact microseconds / 1e6, correctly rounded
    return unix, np.array([t.year for t in utc]), np.array([t.month for t in utc]), single


def standard_pressure_pa(height_m: ArrayLike) -> Any:
    """Air pressure of the standard atmosphere at a height, Pa.

    ``100 ((44331.514 - h) / 11880.516) ** (1 / 0.1902632)`` with ``h`` in
    metres: the relation pvlib's ``atmosphere.alt2pres`` documents (sea-level
    101,325 Pa and 288.15 K, lapse rate -6.5e-3 K/m, dry air), from
    "A Quick Derivation relating altitude to air pressure", Portland State
    Aerospace Society, version 1.03 (2004).
    """
    return 100.0 * ((44331.514 - np.asarray(height_m, dtype=float)) / 11880.516) ** (1.0 / 0.1902632)


@functools.cache
def _spa() -> ModuleType:
    """pvlib's SPA module, loaded without importing the ``pvlib`` package (it needs numpy only).

    Falls back to ``import pvlib.spa`` if pvlib ever lays the module out
    differently. ``PVLIB_USE_NUMBA`` unset: the numpy implementation, as
    ``spa_python(how="numpy")`` uses.
    """
    try:
        spec = importlib.util.find_spec("pvlib")  # finds the package without running its __init__
        origin = Path(next(iter(spec.submodule_search_locations or []))) / "spa.py"  # type: ignore[union-attr]
        mod_spec = importlib.util.spec_from_file_location("pihim._pvlib_spa", origin)
        module = importlib.util.module_from_spec(mod_spec)  # type: ignore[arg-type]
        mod_spec.loader.exec_module(module)  # type: ignore[union-attr]
        if getattr(module, "USE_NUMBA", False) or not hasattr(module, "solar_position"):
            raise ImportError("unexpected pvlib.spa")
        return module
    except Exception:  # noqa: BLE001 - any surprise: the ordinary, slower import
        from pvlib import spa

        return spa


def sun_position(
    site: Site | str,
    time: Any,
    *,
    refraction: bool = True,
    pressure_pa: float | None = None,
    temperature_c: float = 12.0,
    delta_t_s: float | None = None,
) -> SunPosition:
    """Sun position at ``site`` for one or many timezone-aware times (NREL SPA via pvlib).

    Parameters
    ----------
    site : Site or str
        A :class:`Site` or text accepted by :func:`parse_site` (``"nsttf"``).
    time : str, datetime, sequence of them, or tz-aware DatetimeIndex
        Times with UTC offsets; naive times raise :class:`PihimInputError`.
    refraction : bool
        ``True`` (default): apparent, refraction-corrected zenith (SPA's
        topocentric zenith with the refraction term, which depends on
        ``pressure_pa`` and ``temperature_c``). ``False``: true zenith.
    pressure_pa : float, optional
        Air pressure for the refraction term, Pa. Default: the standard
        atmosphere at the site height (``pvlib.atmosphere.alt2pres``).
    temperature_c : float
        Air temperature for the refraction term, deg C (SPA default 12).
    delta_t_s : float, optional
        TT - UT1 in seconds; default: pvlib's estimate for the year and month.

    Returns
    -------
    SunPosition
        Scalars for a single time, arrays for a sequence.
    """
    site = parse_site(site)
    unixtime, years, months, single = _instants(time)
    if pressure_pa is None:
        pressure_pa = float(standard_pressure_pa(site.height_m))
    if not (math.isfinite(pressure_pa) and pressure_pa > 0 and math.isfinite(temperature_c)):
        raise PihimInputError("pressure must be positive and temperature finite")
    spa = _spa()
    delta_t = spa.calculate_deltat(years, months) if delta_t_s is None else delta_t_s
    # as spa_python calls it: pressure in millibars, 0.5667 deg refraction at the horizon, numpy mode
    app_zenith, zenith, _, _, azimuth, _ = spa.solar_position(
        unixtime, site.latitude_deg, site.longitude_deg, site.height_m, pressure_pa / 100.0, temperature_c,
        delta_t, 0.5667, 4)
    zen = np.asarray(app_zenith if refraction else zenith, dtype=float)
    az = np.asarray(azimuth, dtype=float)
    if single:
        return SunPosition.from_angles(zen[0], az[0])
    return SunPosition.from_angles(zen, az)


def require_daylight(sun: SunPosition | ArrayLike, *, what: str = "a sky model") -> None:
    """Raise :class:`PihimInputError` if the sun (any of several) is below the horizon.

    Parameters
    ----------
    sun : SunPosition or array_like
        A position, or ENU sun vector(s) ``(..., 3)`` (below the horizon
        when ``z < 0``).
    what : str
        What needs daylight, for the message.
    """
    if isinstance(sun, SunPosition):
        elev = np.atleast_1d(np.asarray(sun.elevation_deg, float))
    else:
        v = np.asarray(sun, dtype=float)
        if v.shape[-1:] != (3,):
            raise PihimInputError(f"sun vectors need 3 components on the last axis, got shape {v.shape}")
        n = np.linalg.norm(v, axis=-1)
        if np.any(~np.isfinite(n) | (n == 0)):
            raise PihimInputError("sun direction must be a finite non-zero vector")
        elev = np.atleast_1d(np.degrees(np.arcsin(np.clip(v[..., 2] / n, -1, 1))))
    if np.any(elev < 0.0):
        worst = float(np.min(elev))
        raise PihimInputError(
            f"the sun is below the horizon (elevation {worst:.2f} deg); {what} needs the sun above it"
        )
