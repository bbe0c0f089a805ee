"""Order, orient and group scan passes into flights: less flown distance, fewer turns.

:func:`pihim.planning.endurance.split_flights` flies the passes in the
planner's order (by azimuth around the tower, boustrophedon) and closes a
flight when the next pass would not fit. :func:`plan_flights` chooses the
order, the direction of every pass and where each flight starts and ends in
the sequence, to shorten the whole path (take-off to landing, every flight):

1. **Order.** The passes start in the planner's sweep order. Each pass can
   be flown either way (it is a straight run of stop-and-shoot captures);
   for a given order, the directions minimising the transits are found
   exactly by dynamic programming over the two directions of each pass
   (:func:`orient_passes`). The order is then improved by 2-opt and Or-opt
   moves on the open path (a move is kept when the transits, directions
   re-optimised, get shorter), within a window of positions so that the
   cost stays linear in the number of passes.
2. **Flights.** The ordered passes are cut into flights by dynamic
   programming (:func:`_split`): among all cuts whose flights fit the
   battery (time estimated from the passes' own legs, the transits at the
   transit speed, the climbs and the fixed overheads, with a small margin)
   and the mission-item limit, the one with the shortest total distance
   (climb, transit from home, passes and transits, return, descent), each
   flight's pass directions re-optimised with home at both ends.
3. **Each flight** is built exactly as
   :func:`~pihim.planning.endurance.split_flights` builds it (climb,
   transits around the tower, turn-limited leg speeds, return, landing) and
   checked against the limits; a flight the estimate let through that does
   not fit is split again greedily.

Distances are 3-D path lengths; transits between passes run straight at the
higher of the two pass altitudes, and around the tower where they would
cross it below its top. :func:`turns` counts the changes of horizontal
direction of more than 30 deg along a flight.

**Turns.** Every choice above minimises distance plus
``RouteSettings.turn_cost_m`` (default 10 m) for each turn a transit makes
where it leaves a pass and where it enters the next, which is exactly what
:func:`turns` counts on the flown path (straight passes, no tower detour).
A corner flown from a stop costs about ``v / a`` seconds more than a
straight line (at 8 m/s and ~4 m/s^2 about 2 s, i.e. 16 m of transit), so
10 m is a conservative price. The order is first improved for distance
alone and then for the charged cost, so a turn is given up only where it
saves more than its charge. On the NSTTF day (8:00-16:00, issue 11's case)
this flies 11 % fewer turns (573 against 641 over the nine hours) for 0.8 %
more distance, every hour still within OpenCSP's 5,363 m
(``benchmarks/bench_opencsp.py``).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pihim.errors import PihimInputError
from pihim.field.geodesy import as_origin
from pihim.planning.endurance import (
    DroneEndurance,
    _build,
    _keepout,
    _leg_waypoints,
    _time_and_distance,
    keepout_array,
    split_flights,
)
from pihim.planning.model import Flight, ScanPass, Waypoint

__all__ = ["RouteSettings", "orient_passes", "plan_flights", "reverse_pass", "split_pass", "turns"]


@dataclass(frozen=True)
class RouteSettings:
    """Tuning of :func:`plan_flights`.

    Attributes
    ----------
    window : int
        2-opt and Or-opt moves reach this many positions along the order.
    sweeps : int
        Improvement sweeps at most (each pass over the order).
    time_margin : float
        Fraction of the battery kept free by the flight-split estimate (the
        exact check follows).
    turn_cost_m : float
        Metres of path one turn is worth in the order, direction and split
        choices: every transit between passes (and from or to home) is
        charged this much for each change of horizontal direction of more
        than 30 deg it makes where it leaves a pass and where it enters the
        next (what :func:`turns` counts). 0 minimises the distance alone.
    """

    window: int = 24
    sweeps: int = 6
    time_margin: float = 0.02
    turn_cost_m: float = 10.0

    def __post_init__(self) -> None:
        for label in ("window", "sweeps"):
            v = getattr(self, label)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise PihimInputError(f"RouteSettings.{label} must be an integer >= 0, got {v!r}")
        if not (isinstance(self.time_margin, (int, float)) and 0.0 <= self.time_margin < 0.5):
            raise PihimInputError(f"RouteSettings.time_margin must be in [0, 0.5), got {self.time_margin!r}")
        t = self.turn_cost_m
        if isinstance(t, bool) or not (isinstance(t, (int, float)) and math.isfinite(t) and t >= 0.0):
            raise PihimInputError(f"RouteSettings.turn_cost_m must be a number >= 0, got {t!r}")


# --------------------------------------------------------------------------- passes


def reverse_pass(p: ScanPass) -> ScanPass:
    """The same pass flown the other way: waypoints and pairs reversed, lead-in and run-past swapped.

    Captures keep their position, heading and gimbal pitch (a stop-and-shoot
    capture does not depend on the direction of travel); predictions are
    dropped (their waypoint indices change: score the pass again).
    """
    swap = {"lead_in": "run_past", "run_past": "lead_in"}
    wps = tuple(dataclasses.replace(w, kind=swap[w.kind]) if w.kind in swap else w  # type: ignore[arg-type]
                for w in reversed(p.waypoints))
    return dataclasses.replace(p, waypoints=wps, pairs=tuple(reversed(p.pairs)), predictions=(),
                               azimuth_deg=(p.azimuth_deg + 180.0) % 360.0)


def _ends(passes: Sequence[ScanPass]) -> NDArray[np.float64]:
    """End points of every pass: row ``2k`` its first waypoint, ``2k + 1`` its last, shape (2n, 3)."""
    out = np.zeros((2 * len(passes), 3))
    for k, p in enumerate(passes):
        a, b = p.waypoints[0], p.waypoints[-1]
        out[2 * k] = (a.x_m, a.y_m, a.z_m)
        out[2 * k + 1] = (b.x_m, b.y_m, b.z_m)
    return out


def _outward(passes: Sequence[ScanPass], min_leg_m: float = 0.5) -> NDArray[np.float64]:
    """Unit horizontal direction of travel out of each pass end, rows as :func:`_ends`, shape (2n, 2).

    Row ``2k`` points out of the first waypoint (backward along the pass's
    first horizontal leg of at least ``min_leg_m``), row ``2k + 1`` out of
    the last one (forward along the last such leg); zero when the pass has
    no such leg (a capture point, where the turn is made by the transits).
    """
    out = np.zeros((2 * len(passes), 2))
    for k, p in enumerate(passes):
        xy = np.array([(w.x_m, w.y_m) for w in p.waypoints])
        for row, seq in ((2 * k, xy), (2 * k + 1, xy[::-1])):
            far = np.linalg.norm(seq - seq[0], axis=1) >= min_leg_m
            if far.any():
                v = seq[0] - seq[int(np.argmax(far))]
                out[row] = v / np.linalg.norm(v)
    return out


_COS_TURN = math.cos(math.radians(30.0))  # what turns() counts as a turn


class _Costs:
    """Transit distances between pass ends and from home (internal, cached), around the tower keep-out.

    Pass ``k`` flown in direction ``o`` (0 as planned, 1 reversed) starts at
    end point ``2k + o`` and finishes at ``2k + 1 - o``.
    """

    def __init__(self, passes: Sequence[ScanPass], home: Waypoint, keepout: Any, turn_cost_m: float = 0.0) -> None:
        self.home = np.array([home.x_m, home.y_m, home.z_m])
        self.pts = np.vstack([_ends(passes), self.home, self.home])
        self.out = np.vstack([_outward(passes), np.zeros((2, 2))])
        self.home_pass = len(passes)  # a pseudo-pass at home (both ends), to pin the ends of a flight
        self.turn_cost_m = float(turn_cost_m)
        self.keepout = keepout
        self.keep = keepout_array(keepout)
        self.inner = np.array([_path_length(p.waypoints) for p in passes] + [0.0])
        self._cache: dict[tuple[int, int], float] = {}
        self._home: dict[int, float] = {}

    def with_turn_cost(self, turn_cost_m: float) -> _Costs:
        """The same passes, home and keep-out with another turn cost (the end points, directions and pass
        lengths shared, not worked out again: seconds at 100,000 heliostats; the distances cached anew)."""
        new = copy.copy(self)
        new.turn_cost_m = float(turn_cost_m)
        new._cache, new._home = {}, {}
        return new

    def _straight(self, a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
        from pihim.planning import _kernels

        return _kernels.straight(float(a[0]), float(a[1]), float(a[2]), float(b[0]), float(b[1]), float(b[2]),
                                 self.keep)

    def d(self, e1: int, e2: int) -> float:
        """Transit from end point e1 to end point e2, metres, plus ``turn_cost_m`` per turn it makes
        (:func:`pihim.planning._kernels.transit`)."""
        key = (e1, e2) if e1 <= e2 else (e2, e1)
        v = self._cache.get(key)
        if v is None:
            from pihim.planning import _kernels

            v = _kernels.transit(self.pts, self.out, e1, e2, self.keep, self.turn_cost_m, _COS_TURN)
            self._cache[key] = v
        return v

    def h(self, e: int, z: float) -> float:
        """Home -> end point e (or back): vertical to altitude z at home, then across, metres (turn at e charged)."""
        v = self._home.get(e)
        if v is None:
            p = self.pts[e]
            v = self._straight(np.array([self.home[0], self.home[1], p[2]]), p)
            if self.turn_cost_m:
                leg, b = p - self.home, -self.out[e]
                n = math.hypot(leg[0], leg[1])
                v += self.turn_cost_m * int(n >= 0.5 and bool(b.any()) and float(leg[:2] @ b) / n < _COS_TURN)
            self._home[e] = v
        return v + abs(z - self.home[2])


def _path_length(wps: Sequence[Waypoint]) -> float:
    xyz = np.array([(w.x_m, w.y_m, w.z_m) for w in wps])
    return float(np.linalg.norm(np.diff(xyz, axis=0), axis=1).sum()) if len(xyz) > 1 else 0.0


def orient_passes(order: Sequence[int], costs: _Costs, *, home_z: float | None = None
                  ) -> tuple[float, list[int]]:
    """Directions of passes flown in ``order`` minimising the transits (exact, dynamic programming).

    With ``home_z`` the path starts and ends at home (climb and descent to
    that altitude included). Returns the transit length (without the passes'
    own lengths) and the direction of each pass (0 as planned, 1 reversed).
    """
    n = len(order)
    if n == 0:
        return 0.0, []
    k0 = order[0]
    cost = [costs.h(2 * k0 + o, home_z) if home_z is not None else 0.0 for o in (0, 1)]
    back: list[tuple[int, int]] = [(0, 0)]
    for i in range(1, n):
        kp, k = order[i - 1], order[i]
        new, arg = [0.0, 0.0], [0, 0]
        for o in (0, 1):
            c0 = cost[0] + costs.d(2 * kp + 1, 2 * k + o)
            c1 = cost[1] + costs.d(2 * kp, 2 * k + o)
            new[o], arg[o] = (c0, 0) if c0 <= c1 else (c1, 1)
        cost = new
        back.append((arg[0], arg[1]))
    if home_z is not None:
        kl = order[-1]
        cost = [cost[0] + costs.h(2 * kl + 1, home_z), cost[1] + costs.h(2 * kl, home_z)]
    o = 0 if cost[0] <= cost[1] else 1
    total = cost[o]
    dirs = [0] * n
    for i in range(n - 1, -1, -1):
        dirs[i] = o
        o = back[i][o]
    return total, dirs


def _improve(order: list[int], costs: _Costs, st: RouteSettings, *, pinned: bool = False) -> list[int]:
    """2-opt (segment reversal) and Or-opt (move a run of 1-3 passes, either way) within a window.

    Moves are scored by the change of the transits at the segment ends with
    the directions fixed (a reversed segment flips its passes); the
    directions are re-optimised exactly after every sweep. A search from a
    position whose neighbourhood has not changed since it last found nothing
    is skipped (don't-look marks, :func:`pihim.planning._kernels.improve_sweep`):
    same moves, fewer evaluations. With ``pinned`` the first and last entries
    stay in place (home).
    """
    n = len(order)
    lo_i, hi_i = (1, n - 2) if pinned else (0, n - 1)  # positions that may move
    if hi_i - lo_i < 1 or st.sweeps == 0 or st.window == 0:
        return order
    from pihim.planning import _kernels

    _, dirs = orient_passes(order, costs)
    order_a = np.array(order, dtype=np.int64)
    stamp, seen, clock = np.zeros(n, np.int64), np.zeros((4, n), np.int64), np.ones(1, np.int64)  # don't-look marks
    swept: NDArray[np.int64] | None = None
    for _ in range(st.sweeps):
        dirs_a = np.array(dirs, dtype=np.int64)
        if swept is not None:  # directions the re-optimisation changed: those positions searched again
            stamp[dirs_a != swept] = clock[0]
            clock[0] += 1
        improved = _kernels.improve_sweep(order_a, dirs_a, costs.pts, costs.out, costs.keep, costs.turn_cost_m,
                                          _COS_TURN, lo_i, hi_i, st.window, stamp, seen, clock)
        swept = dirs_a
        _, dirs = orient_passes(order_a.tolist(), costs)
        if not improved:
            break
    return order_a.tolist()


# --------------------------------------------------------------------------- flights


@dataclass(frozen=True)
class _PassCost:
    """Stand-alone figures of one pass (internal): flying time of its own legs and its mission items."""

    time_s: float
    items: int
    alone_s: float = 0.0  # a flight of this pass alone (take-off, transits from and to home, landing): time
    alone_items: int = 0  # and its mission items


def _pass_costs(passes: Sequence[ScanPass], home: Waypoint, model: DroneEndurance,
                count_items: Callable[[Sequence[Waypoint]], int] | None,
                keepout: Any = None) -> tuple[list[_PassCost], int]:
    """Time and items of every pass on its own, and the items of an empty flight (take-off, return, home).

    ``alone_s`` and ``alone_items`` are those of a flight of the pass alone,
    around the tower's ``keepout`` (what :func:`split_flights` checks).
    """
    out = []
    base = 0
    land = dataclasses.replace(home, kind="land")  # type: ignore[arg-type]
    if count_items is not None:
        lift = dataclasses.replace(home, z_m=1.0, kind="transit")  # type: ignore[arg-type]
        base = count_items([home, lift, land])
    empty = count_items([home, land]) if count_items is not None else 0
    for p in passes:
        legs = _build([p], home, keepout, model, None)
        own = [k for k, leg in enumerate(legs) if leg.waypoint is not None]
        inner = legs[own[0]:own[-1] + 1]
        t = model.turn_s + sum(leg.capture for leg in inner) * model.capture_s
        if len(inner) > 1:
            t, _ = _time_and_distance(inner, model)
            t -= model.takeoff_landing_s  # counted once per flight
        items = count_items([home, *p.waypoints, land]) - empty if count_items is not None else 0
        out.append(_PassCost(max(t, 0.0), items, _time_and_distance(legs, model)[0],
                             count_items(_leg_waypoints(legs)) if count_items is not None else 0))
    return out, base


def split_pass(p: ScanPass, pieces: int) -> list[ScanPass]:
    """``p`` cut into ``pieces`` consecutive passes with about as many captures each, cut before a capture.

    For a pass too long for one flight: a radial line in a field of tens of
    thousands of heliostats can hold more stop-and-shoot captures than a
    700-item mission or one battery. The first piece keeps the lead-in, the
    last the run-past; the waypoints keep their order, so the pieces flown
    one after the other are the pass. Each piece images the pairs of the
    HUAs its captures name (all the pass's pairs where captures name none);
    predictions are dropped (score the pieces again, as
    :func:`pihim.planning.pipeline.build_plan` does after the route).

    Parameters
    ----------
    p : ScanPass
    pieces : int
        Number of pieces, at most the pass's number of capture waypoints.

    Returns
    -------
    list of ScanPass
        With ``p.index`` (:func:`plan_flights` renumbers the flown passes).
    """
    caps = [i for i, w in enumerate(p.waypoints) if w.capture]
    if not (isinstance(pieces, int) and 1 <= pieces <= max(len(caps), 1)):
        raise PihimInputError(f"a pass with {len(caps)} captures cannot be cut into {pieces!r} pieces")
    if pieces == 1:
        return [p]
    starts = [0] + [caps[(k * len(caps)) // pieces] for k in range(1, pieces)]
    ends = starts[1:] + [len(p.waypoints)]
    out = []
    for a, b in zip(starts, ends, strict=True):
        wps = p.waypoints[a:b]
        huas = {w.hua for w in wps if w.capture and w.hua is not None}
        pairs = tuple(pr for pr in p.pairs if pr[0] in huas) if huas else p.pairs
        out.append(dataclasses.replace(p, waypoints=wps, pairs=pairs, predictions=()))
    return out


def _fit_passes(fly: list[ScanPass], home: Waypoint, model: DroneEndurance,
                count_items: Callable[[Sequence[Waypoint]], int] | None, max_items: int | None, keepout: Any,
                ) -> tuple[list[ScanPass], list[_PassCost], int]:
    """Passes too long for one flight cut by :func:`split_pass`, with the pieces' costs.

    A pass is cut while a piece needs more mission items than ``max_items``
    or a flight of it alone exceeds the battery though its transits alone
    would not (a pass out of reach stays whole: cutting cannot help it).

    Raises
    ------
    PihimInputError
        A single capture needs more mission items than ``max_items``.
    """
    pc, base = _pass_costs(fly, home, model, count_items, keepout)
    limit = model.usable_s

    def too_long(q: _PassCost) -> bool:
        over_items = max_items is not None and q.alone_items > max_items
        return over_items or (q.alone_s > limit and q.alone_s - q.time_s < limit)

    out: list[ScanPass] = []
    costs: list[_PassCost] = []
    for p, c in zip(fly, pc, strict=True):
        n_caps = sum(w.capture for w in p.waypoints)
        pieces, parts, part_costs = 1, [p], [c]
        while any(too_long(q) for q in part_costs) and pieces < n_caps:
            need = c.items / max(max_items - base, 1) if max_items is not None else 1.0
            if c.alone_s > limit:
                need = max(need, c.time_s / max(limit - (c.alone_s - c.time_s), 1e-9))
            pieces = min(n_caps, max(pieces + 1, math.ceil(1.15 * need)))
            parts = split_pass(p, pieces)
            part_costs, _ = _pass_costs(parts, home, model, count_items, keepout)
        for q in part_costs:
            if max_items is not None and q.alone_items > max_items:
                raise PihimInputError(f"pass {p.index} needs {q.alone_items} mission items for a flight of a single "
                                      f"capture, more than {max_items}")
        out += parts
        costs += part_costs
    return out, costs, base


def _split(order: list[int], costs: _Costs, pc: list[_PassCost], base_items: int, model: DroneEndurance,
           z_of: NDArray[np.float64], item_cap: float, st: RouteSettings) -> list[tuple[int, int]]:
    """Cut ``order`` into flights (position ranges) with the least total distance that fit the estimates.

    Dynamic programming over the cut points; for a flight starting at
    position ``i`` the directions are optimised incrementally as it grows
    (forward costs per direction of its last pass, home appended at the end).
    The flight's altitude for the climb is the highest pass altitude so far.
    """
    from pihim.planning import _kernels

    n = len(order)
    limit = model.usable_s * (1.0 - st.time_margin)
    hz = float(costs.home[2])
    home_leg = np.array([costs.h(e, hz) for e in range(2 * costs.home_pass)], dtype=float)
    cut = _kernels.split_flights_dp(
        np.asarray(order, dtype=np.int64), costs.pts, costs.out, costs.keep, costs.turn_cost_m, _COS_TURN, home_leg,
        np.array([c.time_s for c in pc], dtype=float), np.array([c.items for c in pc], dtype=np.int64),
        np.asarray(costs.inner, dtype=float), np.asarray(z_of, dtype=float), hz, model.transit_speed_m_s,
        model.climb_rate_m_s, model.descent_rate_m_s, model.takeoff_landing_s, limit, float(item_cap),
        int(base_items)).tolist()
    out = []
    j = n
    while j > 0:
        i = cut[j]
        out.append((i, j))
        j = i
    return out[::-1]


def turns(waypoints: Sequence[Waypoint], min_angle_deg: float = 30.0, min_leg_m: float = 0.5) -> int:
    """Changes of horizontal direction of more than ``min_angle_deg`` along a path (vertical legs ignored)."""
    xy = np.array([(w.x_m, w.y_m) for w in waypoints]).reshape(-1, 2)
    d = np.diff(xy, axis=0)
    d = d[np.linalg.norm(d, axis=1) >= min_leg_m]
    if len(d) < 2:
        return 0
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    cos = np.sum(u[1:] * u[:-1], axis=1)
    return int(np.sum(cos < math.cos(math.radians(min_angle_deg))))


def plan_flights(
    passes: Sequence[ScanPass],
    home: Waypoint,
    *,
    origin: Any,
    model: DroneEndurance = DroneEndurance(),
    tower: Any = None,
    max_mission_items: int | None = None,
    count_items: Callable[[Sequence[Waypoint]], int] | None = None,
    include_infeasible: bool = False,
    settings: RouteSettings = RouteSettings(),
    unflyable: list[int] | None = None,
) -> tuple[tuple[ScanPass, ...], tuple[Flight, ...]]:
    """Passes ordered and oriented, and flights cut, for the shortest path (module docstring).

    A pass too long for one flight (mission items or battery, its own legs)
    is first cut into consecutive pieces (:func:`split_pass`).

    Parameters
    ----------
    passes : sequence of ScanPass
        Planned passes (any order).
    home : Waypoint
        Take-off and landing point.
    origin : GeodeticOrigin or Site
        Field origin on WGS84 (transit waypoints).
    model : DroneEndurance
    tower : Tower, optional
        Transits below its top go around it.
    max_mission_items : int, optional
        Most mission items per flight, counted by ``count_items``.
    count_items : callable, optional
        ``count_items(waypoints) -> int`` (required with ``max_mission_items``).
    include_infeasible : bool
        Also fly passes marked infeasible.
    settings : RouteSettings
    unflyable : list, optional
        Given, a pass that a flight from home cannot reach and fly within one
        battery (the edge of a field kilometres wide) is not flown and its
        final index appended here, instead of raising.

    Returns
    -------
    passes : tuple of ScanPass
        Flown passes in flight order, renumbered 0, 1, ... (``index``), some
        reversed (:func:`reverse_pass`, predictions dropped), then the passes
        not flown (infeasible, then unreachable).
    flights : tuple of Flight
        As :func:`~pihim.planning.endurance.split_flights` returns them.

    Raises
    ------
    PihimInputError
        A single capture does not fit one battery or the item limit, a pass
        out of reach without ``unflyable``, or bad input.
    """
    if not isinstance(home, Waypoint):
        raise PihimInputError(f"home must be a Waypoint (see home_waypoint), got {type(home).__name__}")
    if max_mission_items is not None and count_items is None:
        raise PihimInputError("max_mission_items needs count_items (see pihim.planning.export.count_mission_items)")
    org = as_origin(origin)
    fly = [p for p in passes if (p.feasible or include_infeasible) and p.waypoints]
    rest = [p for p in passes if not ((p.feasible or include_infeasible) and p.waypoints)]
    keepout = _keepout(tower, model.tower_clearance_m)
    counter = count_items if max_mission_items is not None else None
    fly, pc, base = _fit_passes(fly, home, model, counter, max_mission_items, keepout)
    beyond: list[ScanPass] = []
    if unflyable is not None:  # out of reach of a battery even alone: not flown
        reach = [c.alone_s <= model.usable_s for c in pc]
        beyond = [p for p, ok in zip(fly, reach, strict=True) if not ok]
        fly = [p for p, ok in zip(fly, reach, strict=True) if ok]
        pc = [c for c, ok in zip(pc, reach, strict=True) if ok]
    if not fly:
        return _with_unflown([], rest, beyond, unflyable), ()
    costs = _Costs(fly, home, keepout, settings.turn_cost_m)
    order = list(range(len(fly)))
    if settings.turn_cost_m:  # the shortest order first; turns are then traded only where they are worth it
        order = _improve(order, costs.with_turn_cost(0.0), settings)
    order = _improve(order, costs, settings)
    z_of = np.array([max(w.z_m for w in p.waypoints) for p in fly])
    item_cap = math.inf if max_mission_items is None else float(max_mission_items)
    time_margin = settings.time_margin
    cap = item_cap
    tours: dict[tuple[int, ...], tuple[list[ScanPass], float, int | None, int]] = {}

    def tour(key: tuple[int, ...]) -> tuple[list[ScanPass], float, int | None, int]:
        """A flight of the passes ``key``: its order improved as a tour from home and back, oriented; its
        passes, time, mission items and the items its passes alone were estimated at. The same block recurs
        from one cut to the next: each is worked out once."""
        if key not in tours:
            hp = costs.home_pass
            block = _improve([hp, *key, hp], costs, settings, pinned=True)[1:-1]
            _, dirs = orient_passes(block, costs, home_z=float(costs.home[2]))
            group = [reverse_pass(fly[k]) if o else fly[k] for k, o in zip(block, dirs, strict=True)]
            legs = _build(group, home, keepout, model, None)
            t, _ = _time_and_distance(legs, model)
            n = count_items(_leg_waypoints(legs)) if max_mission_items is not None and count_items is not None \
                else None
            tours[key] = (group, t, n, base + sum(pc[k].items for k in block))
        return tours[key]

    for _ in range(6):  # the estimates are a little optimistic: tighten them by the error seen and cut again
        blocks = _split(order, costs, pc, base, model, z_of, cap,
                        dataclasses.replace(settings, time_margin=time_margin))
        groups = []
        item_err, time_err, bad = 0, 0.0, False
        for i, j in blocks:
            group, t, n_items, estimate = tour(tuple(order[i:j]))
            groups.append(list(group))
            bad |= t > model.usable_s
            time_err = max(time_err, t / model.usable_s - (1.0 - time_margin))
            if n_items is not None:
                bad |= n_items > max_mission_items
                item_err = max(item_err, n_items - estimate)
        if not bad:
            break
        if max_mission_items is not None:
            cap = min(cap - 1, float(max_mission_items - max(item_err, 0)))
        time_margin = min(0.45, max(time_margin + 0.005, time_margin + time_err))
    flown: list[ScanPass] = []
    flights: list[Flight] = []
    n0 = 0
    for group in groups:  # exact: a group still too long is cut greedily
        renum = _renumber(group, n0)
        left: list[int] | None = None if unflyable is None else []
        sub = split_flights(renum, home, origin=org, model=model, tower=tower, max_mission_items=max_mission_items,
                            count_items=count_items, include_infeasible=True, unflyable=left)
        if left:  # out of reach once the tower's detour counts: not flown, the rest of the group cut again
            gone = set(left)
            beyond += [g for g, r in zip(group, renum, strict=True) if r.index in gone]
            group = [g for g, r in zip(group, renum, strict=True) if r.index not in gone]
            renum = _renumber(group, n0)
            sub = split_flights(renum, home, origin=org, model=model, tower=tower,
                                max_mission_items=max_mission_items, count_items=count_items, include_infeasible=True)
        for f in sub:
            flights.append(dataclasses.replace(f, index=len(flights)))
        flown += renum
        n0 += len(renum)
    return _with_unflown(flown, rest, beyond, unflyable), tuple(flights)


def _with_unflown(flown: list[ScanPass], rest: list[ScanPass], beyond: list[ScanPass],
                  unflyable: list[int] | None) -> tuple[ScanPass, ...]:
    """Flown passes, then the infeasible ones, then those out of reach (their final indices into ``unflyable``)."""
    n0 = len(flown) + len(rest)
    if unflyable is not None:
        unflyable.extend(range(n0, n0 + len(beyond)))
    return tuple(flown) + tuple(_renumber(rest, len(flown))) + tuple(_renumber(beyond, n0))


def _renumber(passes: Sequence[ScanPass], start: int) -> list[ScanPass]:
    return [dataclasses.replace(p, index=start + k) for k, p in enumerate(passes)]
