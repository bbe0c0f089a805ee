"""Battery endurance: splitting scan passes into flights, flight times, throughput and fleet size.

A drone flies a plan's scan passes (:func:`pihim.planning.ufacet.plan_passes`)
in their (boustrophedon) order, as many per battery as fit: each flight
takes off from the home point, climbs vertically to a transit altitude,
flies the passes, returns and lands vertically. The flight time is estimated
from the path:

* horizontal legs at the waypoint speed (scan passes, e.g. 5 m/s) or at the
  transit speed (take-off, inter-pass and return legs);
* vertical legs at the climb or descent rate, added to the horizontal time
  of the same leg (conservative: no simultaneous climb and cruise);
* a hover/capture time per image and a turn time at the start of every
  pass (decelerate, yaw, settle the gimbal, accelerate);
* a fixed take-off plus landing overhead per flight.

A flight must fit in the battery time minus a reserve fraction. Transit legs
go around the tower (its footprint grown by a clearance) when they would
pass through it below its top.

Heliostats per hour: the paper reports about 36 per hour per drone today (a
typical 20-minute flight imaged six pairs, ~12 heliostats) and hopes for
50-100 per hour with faster acquisition, better planning and longer
endurance; a 10,000-heliostat field would then take 100-200 drone-hours, a
fleet of ~10 drones under a day (paper section 5) [1]_.

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone" (pihim paper), section 5 (throughput and fleet estimate).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from pihim.errors import PihimInputError
from pihim.field.geodesy import GeodeticOrigin, as_origin, enu_to_geodetic
from pihim.planning.attitude import turn_limited_speed
from pihim.planning.model import Flight, ScanPass, Waypoint, heading_0_360, replace_fields

__all__ = [
    "PAPER_HELIOSTATS_PER_HOUR",
    "PAPER_HOPED_HELIOSTATS_PER_HOUR",
    "DroneEndurance",
    "FleetEstimate",
    "Throughput",
    "fleet_estimate",
    "flight_time_s",
    "split_flights",
    "throughput",
]

#: Heliostats per hour per drone reported by the paper's field tests (section 5).
PAPER_HELIOSTATS_PER_HOUR = 36.0
#: Range hoped for with faster acquisition, planning and endurance (paper section 5).
PAPER_HOPED_HELIOSTATS_PER_HOUR = (50.0, 100.0)
#: Longest battery a :class:`DroneEndurance` accepts, minutes: a day (a tethered drone's "battery" included).
MAX_BATTERY_MIN = 24 * 60.0


@dataclass(frozen=True)
class DroneEndurance:
    """Battery and flight-time model of an inspection drone.

    Attributes
    ----------
    battery_min : float
        Flight time of a full battery, minutes (paper: typical 20-minute
        flights); at most :data:`MAX_BATTERY_MIN` (a day).
    reserve_fraction : float
        Fraction of the battery kept in reserve, in [0, 1).
    transit_speed_m_s : float
        Ground speed on take-off, inter-pass and return legs, m/s.
    climb_rate_m_s, descent_rate_m_s : float
        Vertical speeds, m/s.
    capture_s : float
        Hover and capture time per image, seconds.
    turn_s : float
        Time to stop, yaw, settle the gimbal and accelerate at the start of
        each pass, seconds.
    takeoff_landing_s : float
        Arming, take-off and landing overhead per flight, seconds.
    battery_swap_s : float
        Ground time between flights (battery swap, checks), seconds; used for
        throughput per working hour only.
    tower_clearance_m : float
        Horizontal clearance kept around the tower by transit legs, metres.
    yaw_rate_deg_s, gimbal_rate_deg_s : float
        Turn and gimbal-pitch rates, deg/s: a leg is flown slower where the
        drone could not otherwise turn to the next waypoint's heading and
        pitch before reaching it (:func:`pihim.planning.attitude.leg_speed`;
        the mission writers use the same rule).
    settle_s : float
        Margin after such a turn, seconds.
    """

    battery_min: float = 20.0
    reserve_fraction: float = 0.2
    transit_speed_m_s: float = 8.0
    climb_rate_m_s: float = 3.0
    descent_rate_m_s: float = 2.0
    capture_s: float = 2.0
    turn_s: float = 5.0
    takeoff_landing_s: float = 30.0
    battery_swap_s: float = 300.0
    tower_clearance_m: float = 10.0
    yaw_rate_deg_s: float = 30.0
    gimbal_rate_deg_s: float = 30.0
    settle_s: float = 0.5

    def __post_init__(self) -> None:
        for label in ("battery_min", "transit_speed_m_s", "climb_rate_m_s", "descent_rate_m_s", "yaw_rate_deg_s",
                      "gimbal_rate_deg_s"):
            v = getattr(self, label)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise PihimInputError(f"DroneEndurance.{label} must be a positive number, got {v!r}")
        for label in ("capture_s", "turn_s", "takeoff_landing_s", "battery_swap_s", "tower_clearance_m", "settle_s"):
            v = getattr(self, label)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise PihimInputError(f"DroneEndurance.{label} must be a number >= 0, got {v!r}")
        if self.battery_min > MAX_BATTERY_MIN:
            raise PihimInputError(f"DroneEndurance.battery_min must be at most {MAX_BATTERY_MIN:g} minutes (a day), "
                                  f"got {self.battery_min!r}")
        if not (isinstance(self.reserve_fraction, (int, float)) and 0.0 <= self.reserve_fraction < 1.0):
            raise PihimInputError(f"reserve_fraction must be in [0, 1), got {self.reserve_fraction!r}")

    @property
    def usable_s(self) -> float:
        """Flight time available per battery after the reserve, seconds."""
        return 60.0 * self.battery_min * (1.0 - self.reserve_fraction)


@dataclass(frozen=True)
class Throughput:
    """Inspection rate of one drone flying a set of flights back to back.

    Attributes
    ----------
    flights : int
    heliostats_assessed : int
        Distinct HUAs imaged.
    flight_time_s : float
        Sum of the flight durations, seconds.
    elapsed_s : float
        Flights plus a battery swap between consecutive flights, seconds.
    """

    flights: int
    heliostats_assessed: int
    flight_time_s: float
    elapsed_s: float

    @property
    def heliostats_per_flight_hour(self) -> float:
        """Heliostats per hour in the air."""
        return 3600.0 * self.heliostats_assessed / self.flight_time_s if self.flight_time_s > 0 else 0.0

    @property
    def heliostats_per_hour(self) -> float:
        """Heliostats per working hour (battery swaps included)."""
        return 3600.0 * self.heliostats_assessed / self.elapsed_s if self.elapsed_s > 0 else 0.0


@dataclass(frozen=True)
class FleetEstimate:
    """Drones needed to inspect a field within a number of working hours.

    Attributes
    ----------
    n_heliostats : int
    heliostats_per_hour_per_drone : float
    working_hours : float
    drone_hours : float
        ``n_heliostats / heliostats_per_hour_per_drone``.
    drones : int
        ``ceil(drone_hours / working_hours)``.
    """

    n_heliostats: int
    heliostats_per_hour_per_drone: float
    working_hours: float
    drone_hours: float
    drones: int


def fleet_estimate(n_heliostats: int, heliostats_per_hour_per_drone: float, working_hours: float) -> FleetEstimate:
    """Drone-hours and drones to inspect ``n_heliostats`` in ``working_hours`` a day (at most 24).

    Examples
    --------
    The paper's example (section 5): 10,000 heliostats at 50 per hour per
    drone take 200 drone-hours; with 10 working hours, 20 drones.

    >>> fleet_estimate(10_000, 50.0, 10.0).drones
    20
    """
    if isinstance(n_heliostats, bool) or not isinstance(n_heliostats, (int, np.integer)) or n_heliostats < 0:
        raise PihimInputError(f"n_heliostats must be an integer >= 0, got {n_heliostats!r}")
    for label, v in (("heliostats_per_hour_per_drone", heliostats_per_hour_per_drone),
                     ("working_hours", working_hours)):
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise PihimInputError(f"{label} must be a positive number, got {v!r}")
    if working_hours > 24:
        raise PihimInputError(f"working_hours are hours per day, at most 24, got {working_hours!r}")
    hours = n_heliostats / heliostats_per_hour_per_drone
    return FleetEstimate(int(n_heliostats), float(heliostats_per_hour_per_drone), float(working_hours), hours,
                         math.ceil(hours / working_hours - 1e-12))


# --------------------------------------------------------------------------- path helpers


def _keepout(tower: Any, clearance: float) -> tuple[NDArray[np.float64], NDArray[np.float64], float] | None:
    if tower is None:
        return None
    c = np.asarray(tower.box_corners(), float)
    lo = c[:, :2].min(axis=0) - clearance
    hi = c[:, :2].max(axis=0) + clearance
    return lo, hi, float(c[:, 2].max()) + clearance


def keepout_array(keepout: tuple[NDArray[np.float64], NDArray[np.float64], float] | None) -> NDArray[np.float64]:
    """The keep-out as the compiled transits take it (:mod:`pihim.planning._kernels`): low x, low y, high x,
    high y, top z; empty for none."""
    if keepout is None:
        return np.empty(0)
    lo, hi, top = keepout
    return np.array([lo[0], lo[1], hi[0], hi[1], top], dtype=float)


def _detour(a: NDArray[np.float64], b: NDArray[np.float64], keepout: Any) -> list[NDArray[np.float64]]:
    """Intermediate 2-D points of the shortest path from a to b around the keep-out rectangle
    (:func:`pihim.planning._kernels.detour`)."""
    if keepout is None:
        return []
    from pihim.planning import _kernels

    path, n = _kernels.detour(float(a[0]), float(a[1]), float(b[0]), float(b[1]), keepout_array(keepout))
    return [path[k].copy() for k in range(n)]


class _Leg(NamedTuple):
    """A planned position before geodetic conversion (internal; a named tuple: the route builds and rebuilds
    millions of them at 100,000 heliostats, and a tuple is made and changed several times faster than a frozen
    dataclass)."""

    xyz: tuple[float, float, float]
    heading_deg: float
    pitch_deg: float
    speed_m_s: float
    kind: str
    capture: bool = False
    hua: str | None = None
    waypoint: Waypoint | None = None  # already geodetic (pass waypoints)
    pass_start: bool = False  # first waypoint of a scan pass (a turn: model.turn_s)


def _xyz(w: Waypoint) -> tuple[float, float, float]:
    return (w.x_m, w.y_m, w.z_m)


def _heading(a: Sequence[float], b: Sequence[float], default: float) -> float:
    dx, dy = b[0] - a[0], b[1] - a[1]
    if math.hypot(dx, dy) < 1e-9:
        return default
    return heading_0_360(math.degrees(math.atan2(dx, dy)))


def _transit(a: tuple[float, float, float], b: tuple[float, float, float], z: float, keepout: Any,
             model: DroneEndurance, kind: str = "transit", *, start_heading: float = 0.0,
             heading: float | None = None, pitch: float = 0.0, direct: bool = False) -> list[_Leg]:
    """Transit legs from a to above b at altitude z (b itself is not included), around the tower if needed.

    A climb or descent in place keeps ``start_heading``; the horizontal legs
    face ``heading`` (the next pass's, so that the drone turns on the way) or,
    if None, their direction of travel. The gimbal is set to ``pitch``. With
    ``direct`` the last leg is left to the caller, who flies it straight to
    ``b`` (a pass's first waypoint, at or below ``z``): no waypoint above
    ``b``, whose vertical step would be too short to finish a turn on (PX4
    moves on to the next waypoint within its acceptance radius).
    """
    legs: list[_Leg] = []
    pa = np.array(a, float)
    pb = np.array(b, float)
    if abs(a[2] - z) > 1e-9:
        legs.append(_Leg((a[0], a[1], z), start_heading, pitch, model.transit_speed_m_s, kind))
    route = _detour(pa, pb, keepout) if keepout is not None and z < keepout[2] else []
    cur = (a[0], a[1], z)
    for p in route:
        nxt = (float(p[0]), float(p[1]), z)
        legs.append(_Leg(nxt, _heading(cur, nxt, 0.0) if heading is None else heading, pitch,
                         model.transit_speed_m_s, kind))
        cur = nxt
    end = (b[0], b[1], z)
    if not direct and math.dist(end, cur) > 1e-9 and math.dist(end, b) > 1e-9:
        legs.append(_Leg(end, _heading(cur, end, 0.0) if heading is None else heading, pitch,
                         model.transit_speed_m_s, kind))
    return legs


def _build(passes: Sequence[ScanPass], home: Waypoint, keepout: Any, model: DroneEndurance,
           transit_altitude_m: float | None) -> list[_Leg]:
    """Legs of one flight: take-off, climb, passes with transits, return, landing."""
    return _FlightLegs.of(passes, home, keepout, model, transit_altitude_m).legs()


@dataclass(frozen=True)
class _FlightLegs:
    """A flight's legs up to its last pass (internal), to grow pass by pass (:meth:`plus`) and close
    (:meth:`legs`): trying one more pass costs its own legs and the return, not the whole flight again.
    ``body`` as built, ``fast`` the same legs at their turn-limited speeds (:func:`_turn_speeds`: each leg's
    speed depends on it and the leg before only)."""

    body: tuple[_Leg, ...]
    fast: tuple[_Leg, ...]
    z_c: float  # altitude of the climb, the first transit and the return
    home: Waypoint
    keepout: Any
    model: DroneEndurance
    transit_altitude_m: float | None

    @classmethod
    def of(cls, passes: Sequence[ScanPass], home: Waypoint, keepout: Any, model: DroneEndurance,
           transit_altitude_m: float | None) -> _FlightLegs:
        z_c = max(p.altitude_m for p in passes) if transit_altitude_m is None else transit_altitude_m
        body = [_Leg(_xyz(home), home.heading_deg, 0.0, 0.0, "takeoff")]
        for k, p in enumerate(passes):
            body += cls._pass_legs(body[-1], k, p, z_c, keepout, model)
        return cls(tuple(body), tuple(_turn_speeds(body, model)), z_c, home, keepout, model, transit_altitude_m)

    @staticmethod
    def _pass_legs(last: _Leg, k: int, p: ScanPass, z_c: float, keepout: Any, model: DroneEndurance) -> list[_Leg]:
        """The transit from ``last`` (the take-off or the previous pass's end) to pass ``k`` of the flight, and
        the pass."""
        first = p.waypoints[0]
        z = z_c if k == 0 else max(last.xyz[2], first.z_m)
        legs = _transit(last.xyz, _xyz(first), z, keepout, model, start_heading=last.heading_deg,
                        heading=first.heading_deg, pitch=first.gimbal_pitch_deg, direct=True)
        for i, w in enumerate(p.waypoints):
            if i == 0:  # the pass is reached at the transit speed
                w = replace_fields(w, speed_m_s=model.transit_speed_m_s)
            legs.append(_Leg(_xyz(w), w.heading_deg, w.gimbal_pitch_deg, w.speed_m_s, w.kind, w.capture, w.hua, w,
                             pass_start=i == 0))
        return legs

    def plus(self, p: ScanPass, k: int) -> _FlightLegs | None:
        """The flight with pass ``p`` (its ``k``-th) added; None when it must be built again (a higher pass
        raises the climb and the first transit)."""
        z_c = max(self.z_c, p.altitude_m) if self.transit_altitude_m is None else self.transit_altitude_m
        if z_c != self.z_c:
            return None
        new = self._pass_legs(self.body[-1], k, p, z_c, self.keepout, self.model)
        return replace(self, body=self.body + tuple(new),
                       fast=self.fast + tuple(_turn_speeds([self.body[-1], *new], self.model)[1:]))

    def legs(self) -> list[_Leg]:
        """The whole flight at its turn-limited speeds: the body, the return and the landing."""
        h, z_c, last = _xyz(self.home), self.z_c, self.body[-1]
        back = _transit(last.xyz, h, z_c, self.keepout, self.model, start_heading=last.heading_deg)
        if back:
            back[-1] = back[-1]._replace(kind="return")
        if not back or math.dist(back[-1].xyz, (h[0], h[1], z_c)) > 1e-9:  # above home before landing
            back.append(_Leg((h[0], h[1], z_c), last.heading_deg if not back else back[-1].heading_deg, 0.0,
                             self.model.transit_speed_m_s, "return"))
        back.append(_Leg(h, back[-1].heading_deg, 0.0, 0.0, "land"))
        return [*self.fast, *_turn_speeds([last, *back], self.model)[1:]]


def _turn_speeds(legs: list[_Leg], model: DroneEndurance) -> list[_Leg]:
    """Legs flown slower where the drone must turn or re-pitch before their end (see ``leg_speed``)."""
    out = [legs[0]]
    for prev, leg in itertools.pairwise(legs):
        if leg.kind in ("takeoff", "land") or leg.speed_m_s <= 0:
            out.append(leg)
            continue
        turn = abs(leg.heading_deg - prev.heading_deg) % 360.0
        speed = turn_limited_speed(math.dist(prev.xyz, leg.xyz), min(turn, 360.0 - turn),
                                   leg.pitch_deg - prev.pitch_deg, leg.speed_m_s, yaw_rate_deg_s=model.yaw_rate_deg_s,
                                   gimbal_rate_deg_s=model.gimbal_rate_deg_s, settle_s=model.settle_s)
        if speed < leg.speed_m_s:
            wp = None if leg.waypoint is None else replace_fields(leg.waypoint, speed_m_s=speed)
            xyz, heading, pitch, _, kind, capture, hua, _, start = leg
            leg = _Leg(xyz, heading, pitch, speed, kind, capture, hua, wp, start)  # 1.4x faster than _replace
        out.append(leg)
    return out


def _time_and_distance(legs: Sequence[_Leg], model: DroneEndurance) -> tuple[float, float]:
    xyz = np.array([leg.xyz for leg in legs], float)
    d = np.diff(xyz, axis=0)
    horiz = np.hypot(d[:, 0], d[:, 1])
    dz = d[:, 2]
    speed = np.array([leg.speed_m_s if leg.speed_m_s > 0 else model.transit_speed_m_s for leg in legs[1:]])
    t = horiz / speed + np.where(dz > 0, dz / model.climb_rate_m_s, -dz / model.descent_rate_m_s)
    captures = sum(leg.capture for leg in legs)
    turns = sum(leg.pass_start for leg in legs)
    total = float(t.sum()) + captures * model.capture_s + turns * model.turn_s + model.takeoff_landing_s
    return total, float(np.linalg.norm(d, axis=1).sum())


def flight_time_s(waypoints: Sequence[Waypoint], model: DroneEndurance = DroneEndurance()) -> float:
    """Estimated duration of a flight through ``waypoints``, seconds (see the module notes).

    Legs are flown at the destination waypoint's ``speed_m_s`` (the transit
    speed where it is 0); captures, pass starts (``lead_in`` waypoints, and
    ``scan`` waypoints that follow neither a ``lead_in`` nor a ``scan``
    waypoint) and the take-off/landing overhead add fixed times.
    """
    if len(waypoints) < 2:
        raise PihimInputError("a flight needs at least two waypoints")
    legs = [_Leg(_xyz(w), w.heading_deg, w.gimbal_pitch_deg, w.speed_m_s, w.kind, w.capture, w.hua, w,
                 pass_start=w.kind == "lead_in" or (w.kind == "scan" and (k == 0 or waypoints[k - 1].kind
                                                                        not in ("lead_in", "scan"))))
            for k, w in enumerate(waypoints)]
    return _time_and_distance(legs, model)[0]


def _leg_waypoints(legs: Sequence[_Leg]) -> list[Waypoint]:
    """Legs as waypoints for counting mission items (no geodetic conversion: coordinates 0)."""
    return [leg.waypoint if leg.waypoint is not None else
            Waypoint(leg.xyz[0], leg.xyz[1], leg.xyz[2], 0.0, 0.0, 0.0, heading_0_360(leg.heading_deg), leg.pitch_deg,
                     leg.speed_m_s, kind=leg.kind, capture=leg.capture, hua=leg.hua)  # type: ignore[arg-type]
            for leg in legs]


def _finish(index: int, pass_indices: tuple[int, ...], legs: list[_Leg], passes: Sequence[ScanPass],
            origin: GeodeticOrigin, model: DroneEndurance) -> Flight:
    new = [k for k, leg in enumerate(legs) if leg.waypoint is None]
    lat, lon, hgt = enu_to_geodetic(np.array([legs[k].xyz for k in new], float), origin)
    wps: list[Waypoint] = []
    it = iter(range(len(new)))
    for leg in legs:
        if leg.waypoint is not None:
            wps.append(leg.waypoint)
            continue
        q = next(it)
        wps.append(Waypoint(leg.xyz[0], leg.xyz[1], leg.xyz[2], float(lat[q]), float(lon[q]), float(hgt[q]),
                            heading_0_360(leg.heading_deg), leg.pitch_deg, leg.speed_m_s, kind=leg.kind,  # type: ignore[arg-type]
                            capture=leg.capture, hua=leg.hua))
    duration, distance = _time_and_distance(legs, model)
    huas = {h for p in passes for h, _ in p.pairs}
    return Flight(index=index, pass_indices=pass_indices, waypoints=tuple(wps), duration_s=duration,
                  distance_m=distance, heliostats_assessed=len(huas))


def split_flights(
    passes: Sequence[ScanPass],
    home: Waypoint,
    *,
    origin: GeodeticOrigin | Any,
    model: DroneEndurance = DroneEndurance(),
    tower: Any = None,
    transit_altitude_m: float | None = None,
    include_infeasible: bool = False,
    max_waypoints: int | None = None,
    max_mission_items: int | None = None,
    count_items: Callable[[Sequence[Waypoint]], int] | None = None,
    unflyable: list[int] | None = None,
) -> tuple[Flight, ...]:
    """Split scan passes, in order, into flights that each fit one battery.

    Parameters
    ----------
    passes : sequence of ScanPass
        In flight order (e.g. :func:`pihim.planning.ufacet.plan_passes`).
    home : Waypoint
        Take-off and landing point (:func:`pihim.planning.ufacet.home_waypoint`).
    origin : GeodeticOrigin or Site
        Field origin on WGS84, for the transit waypoints.
    model : DroneEndurance
        Battery and speeds.
    tower : Tower, optional
        Transit legs below its top go around it (``field.tower``).
    transit_altitude_m : float, optional
        Altitude of the climb, the first transit and the return. Default: the
        highest pass altitude of the flight (every pass altitude is above the
        minimum safe altitude, so straight legs between passes are too).
    include_infeasible : bool
        Also fly passes marked infeasible (nothing to image). Default: skip.
    max_waypoints : int, optional
        Also close a flight before it exceeds this many waypoints.
    max_mission_items : int, optional
        Also close a flight before its mission exceeds this many items, as
        counted by ``count_items`` (e.g. 700, what Pixhawk-class ArduPilot
        boards store; see :func:`pihim.planning.export.count_mission_items`).
    count_items : callable, optional
        ``count_items(waypoints) -> int``: mission items of a flight's
        waypoints (take-off ... landing). Required with ``max_mission_items``.
        A :class:`pihim.planning.export.MissionItemCounter` counts each
        flight tried on from where the same flight one pass shorter ended
        (the same counts, a few times faster on long flights).
    unflyable : list, optional
        Given, a pass that alone does not fit (too far from home for the
        battery, say, in a field kilometres wide) is left out and its index
        appended here instead of raising.

    Returns
    -------
    tuple of Flight
        Each with its passes' indices (``ScanPass.index``), the full waypoint
        list (``takeoff``, ``transit``, pass waypoints, ``return``, ``land``),
        the estimated duration, the 3-D path length and the number of HUAs
        imaged. Every flown pass appears in exactly one flight, in order.

    Raises
    ------
    PihimInputError
        A single pass does not fit in one battery (or in ``max_waypoints`` or
        ``max_mission_items``), or bad input.
    """
    org = as_origin(origin)
    if not isinstance(home, Waypoint):
        raise PihimInputError(f"home must be a Waypoint (see home_waypoint), got {type(home).__name__}")
    todo = [p for p in passes if (p.feasible or include_infeasible) and p.waypoints]
    keepout = _keepout(tower, model.tower_clearance_m)
    if transit_altitude_m is not None and not (math.isfinite(transit_altitude_m) and transit_altitude_m > 0):
        raise PihimInputError(f"transit_altitude_m must be a positive altitude, got {transit_altitude_m!r}")
    if max_waypoints is not None and (isinstance(max_waypoints, bool) or not isinstance(max_waypoints, int)
                                      or max_waypoints < 4):
        raise PihimInputError(f"max_waypoints must be an integer >= 4, got {max_waypoints!r}")
    if max_mission_items is not None and (isinstance(max_mission_items, bool)
                                          or not isinstance(max_mission_items, int) or max_mission_items < 4):
        raise PihimInputError(f"max_mission_items must be an integer >= 4, got {max_mission_items!r}")
    if max_mission_items is not None and count_items is None:
        raise PihimInputError("max_mission_items needs count_items (see pihim.planning.export.count_mission_items)")
    limit = model.usable_s
    cap = math.inf if max_waypoints is None else max_waypoints
    item_cap = math.inf if max_mission_items is None else max_mission_items

    counting = count_items is not None and max_mission_items is not None
    resume = total = None
    if counting:
        from pihim.planning.export.qgc import MissionItemCounter

        if type(count_items) is MissionItemCounter:  # not a subclass: its __call__ may count otherwise
            resume, total = count_items.resume, count_items.total

    def counter(flight: _FlightLegs, legs: list[_Leg], grown_from: tuple[_FlightLegs, Any] | None,
                found: list[Any]) -> Callable[[], float]:
        """The mission items of ``legs``, ``flight`` closed, counted when asked. With a
        :class:`pihim.planning.export.MissionItemCounter` (``resume``, ``total``) ``flight``'s body is counted on
        from the state after the body it grew from (``grown_from``: that flight and state), and the state after
        its own body is appended to ``found``."""

        def items() -> float:
            if not counting:
                return 0
            if resume is None:
                return count_items(_leg_waypoints(legs))  # type: ignore[misc]
            if grown_from is None:
                state = resume(None, _leg_waypoints(flight.fast))
            else:
                state = resume(grown_from[1], _leg_waypoints(flight.fast[len(grown_from[0].fast):]))
            found.append(state)
            return total(resume(state, _leg_waypoints(legs[len(flight.fast):])))  # type: ignore[misc]

        return items

    def over(legs: list[_Leg], t: float, items: Callable[[], float]) -> str | None:
        if t > limit:
            return (f"{t / 60:.1f} min with take-off and return, more than the {limit / 60:.1f} min a battery "
                    f"allows ({model.battery_min:g} min less {100 * model.reserve_fraction:g} % reserve)")
        if len(legs) > cap:
            return f"{len(legs)} waypoints, more than {max_waypoints}"
        n = items()
        if n > item_cap:
            return f"{n} mission items, more than {max_mission_items}"
        return None

    flights: list[Flight] = []
    current: list[ScanPass] = []
    best_legs: list[_Leg] | None = None
    grown: _FlightLegs | None = None  # the legs of ``current`` up to its last pass
    grown_state: Any = None  # with a resumable counter: its state after ``grown``'s body
    for p in todo:
        trial = current + [p]
        nxt = grown.plus(p, len(current)) if grown is not None else None
        since = None if nxt is None or grown_state is None else (grown, grown_state)
        if nxt is None:
            nxt = _FlightLegs.of(trial, home, keepout, model, transit_altitude_m)
        legs = nxt.legs()
        t, _ = _time_and_distance(legs, model)
        found: list[Any] = []
        why = over(legs, t, counter(nxt, legs, since, found))
        if why is None:
            current, best_legs, grown = trial, legs, nxt
            grown_state = found[0] if found else None
            continue
        if not current:
            if unflyable is None:
                raise PihimInputError(f"pass {p.index} alone needs {why}")
            unflyable.append(p.index)
            continue
        assert best_legs is not None
        flights.append(_finish(len(flights), tuple(q.index for q in current), best_legs, current, org, model))
        current = [p]
        grown = _FlightLegs.of(current, home, keepout, model, transit_altitude_m)
        best_legs = grown.legs()
        t, _ = _time_and_distance(best_legs, model)
        found = []
        why = over(best_legs, t, counter(grown, best_legs, None, found))
        grown_state = found[0] if found else None
        if why is not None:
            if unflyable is None:
                raise PihimInputError(f"pass {p.index} alone needs {why}")
            unflyable.append(p.index)
            current, best_legs, grown, grown_state = [], None, None, None
    if current and best_legs is not None:
        flights.append(_finish(len(flights), tuple(q.index for q in current), best_legs, current, org, model))
    return tuple(flights)


def throughput(flights: Sequence[Flight], model: DroneEndurance = DroneEndurance()) -> Throughput:
    """Heliostats per hour of one drone flying ``flights`` back to back (a battery swap between flights)."""
    n = len(flights)
    huas_total = sum(f.heliostats_assessed for f in flights)
    t = float(sum(f.duration_s for f in flights))
    elapsed = t + max(0, n - 1) * model.battery_swap_s
    return Throughput(n, huas_total, t, elapsed)
