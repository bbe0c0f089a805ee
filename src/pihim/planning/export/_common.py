"""Checks and conversions shared by the mission exporters (private).

Every exporter calls :func:`check_plan` before it creates any file, so bad
input raises :class:`~pihim.errors.PihimInputError` with a one-line message
and leaves nothing behind.
"""

from __future__ import annotations

import math
import os
import weakref
from pathlib import Path
from typing import Any

from pihim._atomic import write_atomic
from pihim.errors import PihimInputError
from pihim.planning.model import Flight, Plan, ScanPass, Waypoint

#: Numeric :class:`~pihim.planning.model.Waypoint` fields that must be finite.
WAYPOINT_NUMBERS = (
    "x_m",
    "y_m",
    "z_m",
    "latitude_deg",
    "longitude_deg",
    "height_m",
    "heading_deg",
    "gimbal_pitch_deg",
    "speed_m_s",
)

# Sites within this many degrees of the NSTTF origin get the NSTTF geoid undulation by default.
_NSTTF_DEFAULT_RADIUS_DEG = 0.5


def _finite(value: Any) -> float | None:
    """``float(value)`` if it is a finite real number (bools excluded), else None."""
    if isinstance(value, bool):
        return None
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def check_waypoint(w: Any, where: str) -> None:
    """Raise a one-line :class:`PihimInputError` unless ``w`` is a usable waypoint.

    Every numeric field must be finite, latitude within +/-90 deg, longitude
    within +/-180 deg, the speed non-negative, the heading in [0, 360] and
    the gimbal pitch in [-90, 90] deg (the ranges of ``plan.schema.json``;
    a heading of exactly 360 is a rounded -0, which the exporters fold).
    """
    if not isinstance(w, Waypoint):
        raise PihimInputError(f"{where}: expected a Waypoint, got {type(w).__name__}")
    for name in WAYPOINT_NUMBERS:
        v = getattr(w, name)
        if _finite(v) is None:
            raise PihimInputError(f"{where}: {name} is {v!r}, not a finite number")
    if not -90.0 <= w.latitude_deg <= 90.0:
        raise PihimInputError(f"{where}: latitude_deg {w.latitude_deg!r} is outside [-90, 90]")
    if not -180.0 <= w.longitude_deg <= 180.0:
        raise PihimInputError(f"{where}: longitude_deg {w.longitude_deg!r} is outside [-180, 180]")
    if w.speed_m_s < 0:
        raise PihimInputError(f"{where}: speed_m_s {w.speed_m_s!r} is negative")
    # [0, 360): plan.schema.json; 360.0 itself passes, as what `x % 360.0` gives for a heading of -1e-14 deg
    if not 0.0 <= w.heading_deg <= 360.0:
        raise PihimInputError(f"{where}: heading_deg {w.heading_deg!r} is outside [0, 360)")
    if not -90.0 <= w.gimbal_pitch_deg <= 90.0:
        raise PihimInputError(f"{where}: gimbal_pitch_deg {w.gimbal_pitch_deg!r} is outside [-90, 90]")


def check_plan(plan: Any) -> Plan:
    """Validate a plan for export: it has passes and every waypoint is finite.

    Returns
    -------
    Plan
        ``plan`` itself.

    Raises
    ------
    PihimInputError
        Not a :class:`Plan`, no passes, a pass without waypoints, or a
        waypoint (home, pass or flight) with a non-finite or out-of-range
        number.
    """
    if not isinstance(plan, Plan):
        raise PihimInputError(f"expected a pihim Plan, got {type(plan).__name__}")
    known = _known(plan)
    if known is not None and known.checked:  # checked before, and immutable: every exporter, every flight asks
        return plan
    if not plan.passes:
        raise PihimInputError("the plan has no scan passes: nothing to export")
    check_waypoint(plan.home, "home")
    for k, p in enumerate(plan.passes):
        if not p.waypoints:
            raise PihimInputError(f"pass {p.index} (#{k}) has no waypoints")
        if not -90.0 <= p.gimbal_pitch_deg <= 90.0:
            raise PihimInputError(
                f"pass {p.index} (#{k}): gimbal_pitch_deg {p.gimbal_pitch_deg!r} is outside [-90, 90]")
        for j, w in enumerate(p.waypoints):
            check_waypoint(w, f"pass {p.index} waypoint {j}")
    for f in plan.flights:
        for j, w in enumerate(f.waypoints):
            check_waypoint(w, f"flight {f.index} waypoint {j}")
    if known is not None:
        known.checked = True
    return plan


class _Known:
    """What the exporters learnt about one plan: checked or not, and its flights and passes by index."""

    __slots__ = ("checked", "index", "ref")

    def __init__(self, ref: weakref.ref) -> None:
        self.ref = ref
        self.checked = False
        self.index: tuple[dict[int, Flight], dict[int, ScanPass]] | None = None


#: :class:`_Known` by plan identity. A frozen Plan of tuples of frozen passes, flights and waypoints cannot change,
#: and exporting a plan of 4,000 flights asked for all of it for every file of every flight; an entry goes with
#: its plan (weak reference).
_KNOWN: dict[int, _Known] = {}


def _known(plan: Plan) -> _Known | None:
    """The plan's :class:`_Known`, created on first use; None for a plan holding lists (they can change)."""
    if not (isinstance(plan.passes, tuple) and isinstance(plan.flights, tuple)):
        return None
    key = id(plan)
    known = _KNOWN.get(key)
    if known is None or known.ref() is not plan:
        known = _KNOWN[key] = _Known(weakref.ref(plan, lambda _ref, k=key: _KNOWN.pop(k, None)))
    return known


def plan_index(plan: Plan) -> tuple[dict[int, Flight], dict[int, ScanPass]]:
    """The plan's flights and passes by their ``index`` (the first of each index), built once per plan.

    Exporting a plan of 4,000 flights and 34,000 passes looks a flight or a pass up by index for every file of
    every flight; a scan of the plan for each lookup grew as flights x passes.
    """
    known = _known(plan)
    if known is not None and known.index is not None:
        return known.index
    flights: dict[int, Flight] = {}
    for f in plan.flights:
        flights.setdefault(f.index, f)
    passes: dict[int, ScanPass] = {}
    for p in plan.passes:
        passes.setdefault(p.index, p)
    if known is not None:
        known.index = (flights, passes)
    return flights, passes


def mission_waypoints(plan: Plan, flight: int | None = None) -> tuple[Waypoint, ...]:
    """The waypoints one mission file flies.

    Parameters
    ----------
    plan : Plan
    flight : int, optional
        :attr:`Flight.index` of one battery's flight: its waypoints (take-off,
        transits, passes, return, landing) as planned. Default: the waypoints
        of every pass, in plan order, joined by straight legs (no transit
        planning; see ``docs/plan-formats.md``).

    Raises
    ------
    PihimInputError
        Unknown flight index, or a flight without waypoints.
    """
    if flight is None:
        return tuple(w for p in plan.passes for w in p.waypoints)
    if isinstance(flight, bool) or not isinstance(flight, int):
        raise PihimInputError(f"flight must be a flight index (int) or None, got {flight!r}")
    found = plan_index(plan)[0].get(flight)
    if found is None:
        known = ", ".join(str(f.index) for f in plan.flights) or "none"
        raise PihimInputError(f"no flight with index {flight} in the plan (flights: {known})")
    if not found.waypoints:
        raise PihimInputError(f"flight {flight} has no waypoints")
    return tuple(found.waypoints)


def resolve_flight(plan: Plan, flight: int | None) -> int | None:
    """The flight a mission file flies: ``flight``, else the plan's only flight.

    Raises
    ------
    PihimInputError
        ``flight`` is None and the plan has several flights: one mission file
        per battery (``flight=k``).
    """
    if flight is not None:
        return flight
    if len(plan.flights) > 1:
        raise PihimInputError(
            f"the plan needs {len(plan.flights)} flights (batteries): write one mission per flight "
            f"(flight=0 ... {len(plan.flights) - 1})"
        )
    return plan.flights[0].index if plan.flights else None


def known_geoid_undulation(latitude_deg: float, longitude_deg: float) -> float | None:
    """The geoid undulation pihim knows without being told, metres: the NSTTF estimate
    (:data:`pihim.sky.sun.NSTTF_GEOID_UNDULATION_M`) within 0.5 deg of the NSTTF, else None."""
    from pihim.field.geodesy import NSTTF_ORIGIN_LATITUDE_DEG, NSTTF_ORIGIN_LONGITUDE_DEG
    from pihim.sky.sun import NSTTF_GEOID_UNDULATION_M

    if (abs(latitude_deg - NSTTF_ORIGIN_LATITUDE_DEG) <= _NSTTF_DEFAULT_RADIUS_DEG
            and abs(longitude_deg - NSTTF_ORIGIN_LONGITUDE_DEG) <= _NSTTF_DEFAULT_RADIUS_DEG):
        return NSTTF_GEOID_UNDULATION_M
    return None


def geoid_undulation(plan: Plan, value: float | None) -> float:
    """EGM96 geoid height above the WGS84 ellipsoid at the site, metres.

    Orthometric (above mean sea level, "AMSL") height = ellipsoidal height -
    undulation. Resolution order: ``value`` if given; ``plan.site
    ["geoid_undulation_m"]`` if present; the NSTTF estimate
    (:data:`pihim.sky.sun.NSTTF_GEOID_UNDULATION_M`, -22 m) for a site within
    0.5 deg of the NSTTF; otherwise an error, because a wrong value shifts
    every sea-level height by the same error.
    """
    if value is not None:
        f = _finite(value)
        if f is None or abs(f) > 120.0:
            raise PihimInputError(f"geoid_undulation_m must be a finite number of metres within +/-120, got {value!r}")
        return f
    site = plan.site if isinstance(plan.site, dict) else {}
    f = _finite(site.get("geoid_undulation_m"))
    if f is not None:
        return f
    lat, lon = plan.home.latitude_deg, plan.home.longitude_deg
    f = known_geoid_undulation(lat, lon)
    if f is not None:
        return f
    raise PihimInputError(
        f"geoid undulation unknown at lat {lat:.5f}, lon {lon:.5f}: pass geoid_undulation_m= "
        "(EGM96 geoid height above the WGS84 ellipsoid, m) or put it in plan.site"
    )


def site_origin(plan: Plan) -> Any:
    """The field-frame origin (:class:`~pihim.field.geodesy.GeodeticOrigin`) from ``plan.site``.

    ``plan.site`` must hold ``latitude_deg``, ``longitude_deg`` and the
    ellipsoidal ``height_m`` of the field origin (as
    :meth:`pihim.sky.sun.Site.as_dict` writes them).
    """
    from pihim.field.geodesy import GeodeticOrigin

    site = plan.site if isinstance(plan.site, dict) else {}
    vals = [_finite(site.get(k)) for k in ("latitude_deg", "longitude_deg", "height_m")]
    if any(v is None for v in vals):
        raise PihimInputError(
            "plan.site needs finite latitude_deg, longitude_deg and height_m (the field origin) "
            "to place field objects on the map"
        )
    return GeodeticOrigin(*vals)  # type: ignore[arg-type]


_KEPT = frozenset({str, int, bool, type(None)})


def json_ready(obj: Any) -> Any:
    """A copy of nested dicts/lists with non-finite floats replaced by None (JSON has no NaN)."""
    kind = type(obj)
    if kind is float:
        return obj if math.isfinite(obj) else None
    if kind in _KEPT:
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if hasattr(obj, "item") and callable(obj.item) and getattr(obj, "ndim", None) == 0:  # numpy scalar
        return json_ready(obj.item())
    return obj


def plan_counts(plan: Plan) -> dict[str, Any]:
    """Counts used in titles, descriptions and ``plan.json``'s ``export.counts``."""
    waypoints = [w for p in plan.passes for w in p.waypoints]
    heliostats: dict[str, None] = {}
    huas: dict[str, None] = {}
    for p in plan.passes:
        for h, t in p.pairs:
            heliostats.setdefault(h)
            heliostats.setdefault(t)
            huas.setdefault(h)
    predictions = [q for p in plan.passes for q in p.predictions]
    usable = sum(q.usable for q in predictions)
    return {
        "passes": len(plan.passes),
        "feasible_passes": sum(p.feasible for p in plan.passes),
        "flights": len(plan.flights),
        "waypoints": len(waypoints),
        "capture_waypoints": sum(w.capture for w in waypoints),
        "pairs": sum(len(p.pairs) for p in plan.passes),
        "heliostats": len(heliostats),
        "huas": len(huas),
        "predictions": len(predictions),
        "usable_predictions": int(usable),
        "usable_fraction": (usable / len(predictions)) if predictions else 0.0,
    }


def write_data(path: Path, data: str | bytes, *, newline: str | None = None) -> None:
    """Write one rendered export file: bytes as they are, text as UTF-8.

    Parameters
    ----------
    path : Path
        Destination (usually the temporary sibling of :func:`pihim._atomic.atomic_path`).
    data : str or bytes
        The rendered file.
    newline : str, optional
        Passed to :meth:`pathlib.Path.write_text` for text (``"\\n"`` keeps
        Unix line ends on every platform); ignored for bytes.
    """
    if isinstance(data, bytes):
        path.write_bytes(data)
    else:
        path.write_text(data, encoding="utf-8", newline=newline)


def write_export(path: str | os.PathLike[str], data: str | bytes, *, newline: str | None = None) -> Path:
    """Write a rendered (hence already validated) export file atomically.

    Every ``write_xxx(plan, path, ...)`` renders its file in memory first --
    which runs :func:`check_plan` and the option checks -- and then calls
    this, so invalid input never creates a file and a failed write never
    leaves a partial one.

    Parameters
    ----------
    path : str or path-like
        Output file.
    data : str or bytes
        The rendered file (see :func:`write_data`).
    newline : str, optional
        See :func:`write_data`.

    Returns
    -------
    Path
        ``path``.
    """
    return write_atomic(path, lambda p: write_data(p, data, newline=newline))
