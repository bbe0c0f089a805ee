"""Litchi waypoint-mission CSV (``litchi.csv``) for DJI drones.

The metric Litchi CSV [1]_ [2]_ has one row per waypoint under the header
:data:`LITCHI_HEADER`. pihim writes:

* ``latitude``, ``longitude``: WGS84 degrees, 8 decimals (1 mm);
* ``altitude(m)``: height above the **take-off point** (waypoint ellipsoidal
  height - home ellipsoidal height), with ``altitudemode`` = 0 ("Above
  Ground" unchecked: relative to the take-off elevation) -- Litchi's range
  is -200..500 m;
* ``heading(deg)``: the waypoint heading, degrees clockwise from North in
  [0, 360). Litchi uses it only with the mission's Heading Mode set to
  *Custom* (a global setting the CSV cannot carry);
* ``curvesize(m)`` 0 (straight lines through the waypoints, so that actions
  run), ``rotationdir`` 0 (clockwise), ``gimbalmode`` 2 (*interpolate*) and
  ``gimbalpitchangle`` = waypoint gimbal pitch (degrees, negative down);
* actions: at capture waypoints, optionally *stay for* (type 0, milliseconds)
  ``hover_ms``, then *take photo* (type 1, parameter 0); every unused slot
  is ``-1,0`` (no action) up to ``actiontype15``/``actionparam15``;
* ``speed(m/s)``: the waypoint speed (0 = the mission cruising speed);
* no point of interest (``poi_*`` 0), ``photo_timeinterval`` and
  ``photo_distinterval`` -1 (off).

Take-off and landing are Litchi's own; waypoints of kind ``takeoff`` and
``land`` are left out. Global settings (Heading Mode *Custom*, Finish
Action, Path Mode *straight lines*, Cruising Speed) must be set in the
Mission Hub after import. Litchi missions hold at most 99 waypoints (the DJI
waypoint-mission limit); longer ones are refused (``max_waypoints``), and a
plan of several flights is written one flight at a time. A flight longer
than 99 waypoints is cut by :func:`litchi_missions` into missions at pass
boundaries (``pihim plan`` writes ``flight_01_litchi.csv``, or
``flight_01_litchi_1.csv``, ``flight_01_litchi_2.csv`` ... when one flight
needs several; fly them in order on one battery, starting each where the
last ended).

OpenCSP's UFACET planner writes Litchi CSVs the same way (from a template
exported by the Mission Hub, 8-decimal longitude and latitude, altitude,
heading, gimbal pitch) [3]_.

References
----------
.. [1] Litchi Mission Hub, https://flylitchi.com/hub (CSV import/export).
.. [2] W. Barris, "Litchi CSV Format Description", Litchi Utilities,
   https://www.litchiutilities.com/docs/litchiCsv.php.
.. [3] Sandia National Laboratories, OpenCSP,
   ``contrib/app/ufacet-s/flight_planner_ufacet/U_Code/lib/FlightPlan.py``
   (``save_to_litchi_csv``), https://github.com/sandialabs/OpenCSP.
"""

from __future__ import annotations

import csv
import io
import itertools
from pathlib import Path

from pihim.errors import PihimInputError
from pihim.planning.export._common import (
    check_plan,
    mission_waypoints,
    plan_index,
    resolve_flight,
    write_export,
)
from pihim.planning.model import Plan, Waypoint, heading_0_360

__all__ = [
    "LITCHI_ACTION_NONE",
    "LITCHI_ACTION_STAY_MS",
    "LITCHI_ACTION_TAKE_PHOTO",
    "LITCHI_HEADER",
    "LITCHI_MAX_WAYPOINTS",
    "litchi_csv_text",
    "litchi_mission_texts",
    "litchi_missions",
    "litchi_waypoints",
    "write_litchi_csv",
]

#: The metric Litchi CSV header, in column order.
LITCHI_HEADER: tuple[str, ...] = (
    "latitude",
    "longitude",
    "altitude(m)",
    "heading(deg)",
    "curvesize(m)",
    "rotationdir",
    "gimbalmode",
    "gimbalpitchangle",
    *(f"action{kind}{k}" for k in range(1, 16) for kind in ("type", "param")),
    "altitudemode",
    "speed(m/s)",
    "poi_latitude",
    "poi_longitude",
    "poi_altitude(m)",
    "poi_altitudemode",
    "photo_timeinterval",
    "photo_distinterval",
)

LITCHI_ACTION_NONE = -1
LITCHI_ACTION_STAY_MS = 0
LITCHI_ACTION_TAKE_PHOTO = 1
LITCHI_MAX_WAYPOINTS = 99
_GIMBAL_INTERPOLATE = 2
_ALTITUDE_RELATIVE_TO_TAKEOFF = 0
_ALTITUDE_RANGE_M = (-200.0, 500.0)


def litchi_waypoints(plan: Plan, flight: int | None = None) -> tuple[Waypoint, ...]:
    """The waypoints written to the CSV: the mission waypoints without take-off and landing."""
    return tuple(w for w in mission_waypoints(plan, flight) if w.kind not in ("takeoff", "land"))


def _f(v: float, decimals: int) -> str:
    text = f"{v:.{decimals}f}"
    return f"{0.0:.{decimals}f}" if float(text) == 0.0 else text


def litchi_csv_text(
    plan: Plan,
    *,
    flight: int | None = None,
    hover_ms: int = 0,
    max_waypoints: int | None = LITCHI_MAX_WAYPOINTS,
) -> str:
    """The Litchi CSV text (see :func:`write_litchi_csv`)."""
    check_plan(plan)
    wps = litchi_waypoints(plan, resolve_flight(plan, flight))
    if not wps:
        raise PihimInputError("no waypoints to write to the Litchi CSV (only take-off/landing)")
    if max_waypoints is not None and len(wps) > max_waypoints:
        raise PihimInputError(
            f"{len(wps)} waypoints exceed Litchi's limit of {max_waypoints} per mission: "
            "export one flight at a time (flight=...), split with litchi_missions or pass max_waypoints=None"
        )
    return _csv_text(wps, plan.home.height_m, hover_ms)


def litchi_missions(plan: Plan, max_waypoints: int = LITCHI_MAX_WAYPOINTS,
                    flight: int | None = None) -> tuple[tuple[Waypoint, ...], ...]:
    """The plan's flights cut into Litchi missions of at most ``max_waypoints`` waypoints.

    Missions follow the flights in order and never span two flights (two
    batteries). Within a flight a mission ends just before a pass's first
    waypoint (its lead-in, if any) or a transit waypoint, taking as many
    whole passes as fit; only a pass
    longer than ``max_waypoints`` by itself is cut inside (between two of
    its waypoints). Take-off and landing are Litchi's own and left out.

    Parameters
    ----------
    plan : Plan
    max_waypoints : int
        Litchi's limit, 99.
    flight : int, optional
        Only this flight (:attr:`Flight.index`); default every flight.

    Returns
    -------
    tuple of tuple of Waypoint
        The missions, each non-empty; their concatenation is every flight's
        Litchi waypoints in order.
    """
    check_plan(plan)
    if isinstance(max_waypoints, bool) or not isinstance(max_waypoints, int) or max_waypoints < 1:
        raise PihimInputError(f"max_waypoints must be a positive integer, got {max_waypoints!r}")
    missions: list[tuple[Waypoint, ...]] = []
    flights_by_index, by_index = plan_index(plan)
    chosen = plan.flights if flight is None else [f for f in (flights_by_index.get(flight),) if f is not None]
    for f in chosen:
        wps = litchi_waypoints(plan, f.index)
        starts = {(w.x_m, w.y_m, w.z_m, w.kind, w.hua) for w in
                  (by_index[i].waypoints[0] for i in f.pass_indices if i in by_index and by_index[i].waypoints)}
        cuts = [k for k, w in enumerate(wps) if k == 0 or w.kind in ("lead_in", "transit")
                or (w.x_m, w.y_m, w.z_m, w.kind, w.hua) in starts]  # passes without a lead-in start with a capture
        cuts = sorted(set(cuts)) + [len(wps)]
        current: list[Waypoint] = []
        for a, b in itertools.pairwise(cuts):
            segment = list(wps[a:b])
            if current and len(current) + len(segment) > max_waypoints:
                missions.append(tuple(current))
                current = []
            while len(segment) > max_waypoints:  # one pass longer than a mission
                missions.append(tuple(segment[:max_waypoints]))
                segment = segment[max_waypoints:]
            current += segment
        if current:
            missions.append(tuple(current))
    if flight is not None and not missions:
        mission_waypoints(plan, flight)  # raises the "no flight with index" error
    return tuple(missions)


def _csv_text(wps: tuple[Waypoint, ...], home_h: float, hover_ms: int) -> str:
    if isinstance(hover_ms, bool) or not isinstance(hover_ms, int) or hover_ms < 0:
        raise PihimInputError(f"hover_ms must be a whole number of milliseconds >= 0, got {hover_ms!r}")
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(LITCHI_HEADER)
    for j, w in enumerate(wps):
        altitude = w.height_m - home_h
        if not _ALTITUDE_RANGE_M[0] <= altitude <= _ALTITUDE_RANGE_M[1]:
            raise PihimInputError(
                f"waypoint {j}: altitude {altitude:.1f} m above take-off is outside Litchi's range -200..500 m"
            )
        actions: list[tuple[int, int]] = []
        if w.capture:
            if hover_ms:
                actions.append((LITCHI_ACTION_STAY_MS, hover_ms))
            actions.append((LITCHI_ACTION_TAKE_PHOTO, 0))
        actions += [(LITCHI_ACTION_NONE, 0)] * (15 - len(actions))
        writer.writerow([
            _f(w.latitude_deg, 8),
            _f(w.longitude_deg, 8),
            _f(altitude, 3),
            _f(heading_0_360(w.heading_deg), 3),
            0,
            0,
            _GIMBAL_INTERPOLATE,
            _f(w.gimbal_pitch_deg, 3),
            *(v for a in actions for v in a),
            _ALTITUDE_RELATIVE_TO_TAKEOFF,
            _f(w.speed_m_s, 2),
            0,
            0,
            0,
            0,
            -1,
            -1,
        ])
    return buf.getvalue()


def write_litchi_csv(
    plan: Plan,
    path: str | Path,
    *,
    flight: int | None = None,
    hover_ms: int = 0,
    max_waypoints: int | None = LITCHI_MAX_WAYPOINTS,
) -> Path:
    """Write a Litchi mission CSV atomically.

    Parameters
    ----------
    plan : Plan
    path : str or path-like
        Output file, conventionally ``litchi.csv``.
    flight : int, optional
        Export one flight (:attr:`Flight.index`); default all passes.
    hover_ms : int
        Hover before each photo ("stay for" action), milliseconds; 0 for
        none.
    max_waypoints : int or None
        Refuse more waypoints than this (Litchi's limit, 99); None writes
        any number.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    PihimInputError
        Invalid plan or option, too many waypoints, or an altitude outside
        Litchi's -200..500 m; no file is written.
    """
    text = litchi_csv_text(plan, flight=flight, hover_ms=hover_ms, max_waypoints=max_waypoints)
    return write_export(path, text, newline="\n")


def litchi_mission_texts(plan: Plan, *, hover_ms: int = 0, max_waypoints: int = LITCHI_MAX_WAYPOINTS,
                         flight: int | None = None) -> tuple[str, ...]:
    """Litchi CSV texts of :func:`litchi_missions`, one per mission."""
    return tuple(_csv_text(m, plan.home.height_m, hover_ms) for m in litchi_missions(plan, max_waypoints, flight))
