"""QGroundControl ``.plan`` mission files (and the MAVLink mission items they hold).

:func:`mission_items` turns a :class:`~pihim.planning.model.Plan` into a list
of MAVLink mission items [2]_; :func:`write_qgc_plan` wraps them in a
QGroundControl plan file [1]_ and :func:`pihim.planning.export.wpl.write_wpl`
writes the same items as a ``QGC WPL 110`` text file.

Mission layout
--------------
One mission is one flight (one battery): it starts at home and ends there.

1. ``MAV_CMD_NAV_TAKEOFF`` (22): at the first waypoint if its kind is
   ``takeoff`` (climbing to the higher of its altitude and the next
   waypoint's, since a take-off waypoint may sit on the ground), otherwise at
   the plan's home position, climbing to the first waypoint's altitude; yaw
   (param4) = heading of the first waypoint flown.
2. Then, for every waypoint ``w`` after the take-off, in order:

   * the DO/CONDITION items that prepare the leg *to* ``w`` (they follow the
     previous navigation item, so they run when the drone leaves it):
     ``MAV_CMD_DO_CHANGE_SPEED`` (178: ground speed, m/s, throttle -1) when
     the leg speed changes; ``MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW`` (1000:
     pitch = ``w``'s gimbal pitch, yaw 0 = along the vehicle, rates NaN,
     flags ``ROLL_LOCK | PITCH_LOCK`` = 12, pitch relative to the horizon;
     plus ``MAV_CMD_DO_MOUNT_CONTROL`` (205) with ``mount_control=True``) when
     the pitch changes; and, last (``condition_yaw``, default for ArduPilot),
     ``MAV_CMD_CONDITION_YAW`` (115: angle = ``w``'s heading, rate
     ``yaw_rate_deg_s``, direction 0, absolute);
   * ``MAV_CMD_NAV_WAYPOINT`` (16): hold ``capture_hold_s`` at capture
     waypoints (default 2 s) else 0, acceptance radius, pass radius 0,
     **yaw (param4) = ``w``'s heading** (PX4 flies it on the leg to ``w``);
   * at capture waypoints, *first* after the waypoint:
     ``MAV_CMD_IMAGE_START_CAPTURE`` (2000: camera 0 = all, interval 0,
     count 1, sequence number 1, 2, ..., reserved params 5-7 = 0) or, with
     ``camera="digicam"``, ``MAV_CMD_DO_DIGICAM_CONTROL`` (203: shoot = 1).

   A waypoint of kind ``land`` becomes ``MAV_CMD_NAV_LAND`` (21: yaw = last
   heading) and ends the mission.
3. ``MAV_CMD_NAV_RETURN_TO_LAUNCH`` (20) (``end="rtl"``, default) or
   ``MAV_CMD_NAV_LAND`` at home (``end="land"``), unless a ``land``
   waypoint already ended the mission.

Capture timing
--------------
Both autopilots run a mission as two tracks [3]_ [4]_ [5]_: the navigation
item being flown, and the DO/CONDITION items that follow the last navigation
item reached, started in order once it is reached (after its hold). In
ArduPilot ``CONDITION_YAW`` completes only within 2 deg of its angle and
holds back the DO items after it, but never the navigation: when the next
waypoint is reached, DO items still waiting are dropped [3]_ [6]_. PX4 turns
toward the yaw of the waypoint it is flying to as soon as that waypoint
becomes current [4]_ [7]_. Hence the order above: the capture command comes
first after its waypoint (nothing can hold it back), and the heading and
pitch of waypoint ``w`` are commanded when the drone leaves the waypoint
before it, so they are reached during the leg. The leg is flown slower where
``max(|dheading| / yaw_rate_deg_s, |dpitch| / gimbal_rate_deg_s) +
settle_s`` exceeds the leg time
(:func:`pihim.planning.attitude.leg_speed`), so the drone arrives at every
waypoint already at its heading and pitch. The hold at capture waypoints
stops the drone at the capture point (a rotary-wing vehicle "stays at the
waypoint" for param1 [5]_), so the photo is taken at the point, not within
the acceptance radius before it. ``tests/planning/test_mission_timing.py``
runs the written files through an interpreter of these rules and checks
every photo's position and heading against the plan.

With ArduPilot set ``WP_YAW_BEHAVIOR = 0`` (never change yaw): with the
default (face the next waypoint) the autopilot turns toward the next
waypoint whenever a waypoint starts, until the ``CONDITION_YAW`` after it
runs. With PX4 keep the mission's yaw (``MPC_YAW_MODE`` / ``MIS_YAWMODE``
"as set by the mission" where the firmware has it) and ``MPC_YAWRAUTO_MAX``
>= ``yaw_rate_deg_s``.

Altitudes
---------
``altitude_frame="relative"`` (default): ``MAV_FRAME_GLOBAL_RELATIVE_ALT``
(3), altitude = waypoint ellipsoidal height - home ellipsoidal height, i.e.
metres above the **home (take-off) position**; the autopilot adds its own
home altitude, so the drone must take off from ``plan.home``.
``altitude_frame="amsl"``: ``MAV_FRAME_GLOBAL`` (0), altitude above mean sea
level = ellipsoidal height - geoid undulation (EGM96). The planned home
position is always ``[lat, lon, home AMSL]`` as QGroundControl expects; its
altitude uses the same geoid undulation (see
:func:`pihim.planning.export._common.geoid_undulation`).

References
----------
.. [1] QGroundControl Developer Guide, "Plan File Format",
   https://docs.qgroundcontrol.com/master/en/qgc-dev-guide/file_formats/plan.html;
   loader rules from the QGroundControl source
   (``PlanMasterController::loadFromFile``,
   ``MissionController::_loadJsonMissionFileV2``, ``SimpleMissionItem::load``,
   ``MissionItem::load``, ``JsonHelper::validateKeys``,
   ``MissionCommandTree``), https://github.com/mavlink/qgroundcontrol.
.. [2] MAVLink common message set (``common.xml``), ``MAV_CMD``,
   ``MAV_FRAME``, ``MAV_AUTOPILOT``, ``MAV_TYPE``, ``GIMBAL_MANAGER_FLAGS``,
   https://mavlink.io/en/messages/common.html; mission protocol,
   https://mavlink.io/en/services/mission.html.
.. [3] ArduPilot, "Mission Commands" (Copter: ``NAV_WAYPOINT`` param1 hold,
   ``CONDITION_YAW``, DO commands),
   https://ardupilot.org/copter/docs/common-mavlink-mission-command-messages-mav_cmd.html.
.. [4] PX4 User Guide, "Mission Mode (Multicopter)",
   https://docs.px4.io/main/en/flight_modes_mc/mission.html (mission
   commands, ``NAV_ACC_RAD``, ``MIS_YAW_TMT`` / ``MIS_YAW_ERR``).
.. [5] MAVLink, ``MAV_CMD_NAV_WAYPOINT``: param1 "hold time ... time to stay
   at waypoint for rotary wing", param2 "acceptance radius (if the sphere
   with this radius is hit, the waypoint counts as reached)", param4 "yaw
   angle at waypoint (rotary wing)",
   https://mavlink.io/en/messages/common.html#MAV_CMD_NAV_WAYPOINT.
.. [6] ArduPilot issue 33238, "CONDITION_YAW only gates DO commands - it does
   not prevent NAV command advancement",
   https://github.com/ArduPilot/ardupilot/issues/33238.
.. [7] PX4 (pixhawk.org), "Multirotor Yaw Modes": in the default mode the
   vehicle assumes the yaw of the destination waypoint "as soon as that
   waypoint becomes the current destination",
   http://pixhawk.org/users/multirotor_yaw_modes.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pihim._jsontext import json_text
from pihim.errors import PihimInputError
from pihim.planning.export._common import (
    check_plan,
    geoid_undulation,
    json_ready,
    mission_waypoints,
    resolve_flight,
    write_export,
)
from pihim.planning.attitude import leg_speed
from pihim.planning.model import Plan, Waypoint, heading_0_360

__all__ = [
    "MAV_CMD_CONDITION_YAW",
    "MAV_CMD_DO_CHANGE_SPEED",
    "MAV_CMD_DO_DIGICAM_CONTROL",
    "MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW",
    "MAV_CMD_DO_MOUNT_CONTROL",
    "MAV_CMD_IMAGE_START_CAPTURE",
    "MAV_CMD_NAV_LAND",
    "MAV_CMD_NAV_RETURN_TO_LAUNCH",
    "MAV_CMD_NAV_TAKEOFF",
    "MAV_CMD_NAV_WAYPOINT",
    "MAV_FRAME_GLOBAL",
    "MAV_FRAME_GLOBAL_RELATIVE_ALT",
    "MAV_FRAME_MISSION",
    "Mission",
    "MissionItem",
    "MissionItemCounter",
    "count_mission_items",
    "mission_items",
    "qgc_plan_document",
    "qgc_plan_text",
    "write_qgc_plan",
]

# MAV_CMD values (MAVLink common.xml)
MAV_CMD_NAV_WAYPOINT = 16
MAV_CMD_NAV_RETURN_TO_LAUNCH = 20
MAV_CMD_NAV_LAND = 21
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_CONDITION_YAW = 115
MAV_CMD_DO_CHANGE_SPEED = 178
MAV_CMD_DO_DIGICAM_CONTROL = 203
MAV_CMD_DO_MOUNT_CONTROL = 205
MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW = 1000
MAV_CMD_IMAGE_START_CAPTURE = 2000

# MAV_FRAME values
MAV_FRAME_GLOBAL = 0
MAV_FRAME_MISSION = 2
MAV_FRAME_GLOBAL_RELATIVE_ALT = 3

# MAV_AUTOPILOT / MAV_TYPE values
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
MAV_TYPE_QUADROTOR = 2

GIMBAL_MANAGER_FLAGS_ROLL_LOCK = 4
GIMBAL_MANAGER_FLAGS_PITCH_LOCK = 8
MAV_MOUNT_MODE_MAVLINK_TARGETING = 2

#: Commands that carry a latitude, longitude and altitude (QGC "specifiesCoordinate").
COORDINATE_COMMANDS = frozenset({MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_LAND, MAV_CMD_NAV_TAKEOFF})
#: Navigation commands (everything else is a DO/CONDITION command).
NAV_COMMANDS = COORDINATE_COMMANDS | {MAV_CMD_NAV_RETURN_TO_LAUNCH}

# QGroundControlQmlGlobal::AltMode: Mixed 0, Relative 1, Absolute 2, CalcAboveTerrain 3, TerrainFrame 4, None 5
_QGC_ALT_MODE = {MAV_FRAME_GLOBAL_RELATIVE_ALT: 1, MAV_FRAME_GLOBAL: 2}

_NAN = math.nan


@dataclass(frozen=True)
class MissionItem:
    """One MAVLink mission item (``MISSION_ITEM_INT`` content).

    Attributes
    ----------
    command : int
        ``MAV_CMD`` value.
    frame : int
        ``MAV_FRAME`` value (2 = ``MAV_FRAME_MISSION`` for commands without
        a position, as QGroundControl writes them).
    params : tuple of 7 float
        param1..param4, x (latitude, deg), y (longitude, deg), z (altitude,
        m). NaN means "unset"; QGroundControl writes it as JSON ``null``.
    autocontinue : bool
    waypoint : Waypoint or None
        The plan waypoint this item flies to (navigation items) or acts at
        (DO/CONDITION items); None for synthetic items (take-off at home,
        return to launch).
    """

    command: int
    frame: int
    params: tuple[float, float, float, float, float, float, float]
    autocontinue: bool = True
    waypoint: Waypoint | None = None

    @property
    def is_nav(self) -> bool:
        """True for navigation commands (take-off, waypoint, land, return)."""
        return self.command in NAV_COMMANDS

    @property
    def specifies_coordinate(self) -> bool:
        """True if params 5-7 are latitude, longitude and altitude."""
        return self.command in COORDINATE_COMMANDS


@dataclass(frozen=True)
class Mission:
    """Mission items plus what a ground station needs around them.

    Attributes
    ----------
    items : tuple of MissionItem
        Without the home position (QGroundControl's ``items``; item ``k``
        has mission sequence number ``k + 1``).
    home : tuple of 3 float
        Planned home position: latitude, longitude (deg), altitude above
        mean sea level (m).
    altitude_frame : int
        ``MAV_FRAME_GLOBAL_RELATIVE_ALT`` (3) or ``MAV_FRAME_GLOBAL`` (0).
    firmware_type : int
        ``MAV_AUTOPILOT`` value (3 ArduPilot, 12 PX4).
    hover_speed_m_s, cruise_speed_m_s : float
        Default speeds for QGroundControl's mission settings.
    geoid_undulation_m : float
        Geoid height used for the sea-level altitudes.
    """

    items: tuple[MissionItem, ...]
    home: tuple[float, float, float]
    altitude_frame: int
    firmware_type: int
    hover_speed_m_s: float
    cruise_speed_m_s: float
    geoid_undulation_m: float


def _option(name: str, value: Any, allowed: tuple[Any, ...]) -> None:
    if value not in allowed:
        raise PihimInputError(f"{name} must be one of {', '.join(map(repr, allowed))}; got {value!r}")


def _nonneg(name: str, value: Any) -> float:
    try:
        f = float(value)
    except (TypeError, ValueError):
        f = math.nan
    if isinstance(value, bool) or not math.isfinite(f) or f < 0:
        raise PihimInputError(f"{name} must be a finite number >= 0, got {value!r}")
    return f


@dataclass(frozen=True)
class _Options:
    """Checked mission options (internal)."""

    autopilot: str
    condition_yaw: bool
    yaw_rate_deg_s: float
    gimbal_rate_deg_s: float
    settle_s: float
    mount_control: bool
    camera: str
    capture_hold_s: float
    acceptance_radius_m: float
    speed_commands: bool
    end: str


def _options(autopilot: Any = "ardupilot", condition_yaw: Any = None, yaw_rate_deg_s: Any = 30.0,
             gimbal_rate_deg_s: Any = 30.0, settle_s: Any = 0.5, mount_control: Any = False,
             camera: Any = "image_start_capture", capture_hold_s: Any = 2.0, acceptance_radius_m: Any = 0.0,
             speed_commands: Any = True, end: Any = "rtl") -> _Options:
    _option("autopilot", autopilot, ("ardupilot", "px4"))
    _option("camera", camera, ("image_start_capture", "digicam"))
    _option("end", end, ("rtl", "land"))
    for name, flag in (("mount_control", mount_control), ("speed_commands", speed_commands)):
        if not isinstance(flag, bool):
            raise PihimInputError(f"{name} must be True or False, got {flag!r}")
    if condition_yaw is None:
        condition_yaw = autopilot == "ardupilot"
    elif not isinstance(condition_yaw, bool):
        raise PihimInputError(f"condition_yaw must be True, False or None, got {condition_yaw!r}")
    rates = [_nonneg(n, v) for n, v in (("yaw_rate_deg_s", yaw_rate_deg_s), ("gimbal_rate_deg_s", gimbal_rate_deg_s))]
    for name, r in zip(("yaw_rate_deg_s", "gimbal_rate_deg_s"), rates, strict=True):
        if r <= 0:
            raise PihimInputError(f"{name} must be a finite number > 0, got {r!r}")
    return _Options(autopilot, condition_yaw, rates[0], rates[1], _nonneg("settle_s", settle_s), mount_control,
                    camera, _nonneg("capture_hold_s", capture_hold_s),
                    _nonneg("acceptance_radius_m", acceptance_radius_m), speed_commands, end)


def _build_items(wps: Sequence[Waypoint], home: Waypoint, alt: Any, frame: int, o: _Options) -> list[MissionItem]:
    """Mission items for a waypoint sequence (module docstring, "Mission layout"; :func:`_count_items` counts
    them without building them)."""

    def nav(command: int, w: Waypoint, p1: float, p2: float, p4: float, target: Waypoint | None,
            altitude: float | None = None) -> MissionItem:
        z = alt(w) if altitude is None else altitude
        return MissionItem(command, frame, (p1, p2, 0.0, p4, w.latitude_deg, w.longitude_deg, z), True, target)

    def do(command: int, params: tuple[float, ...], w: Waypoint | None) -> MissionItem:
        return MissionItem(command, MAV_FRAME_MISSION, params, True, w)  # type: ignore[arg-type]

    items: list[MissionItem] = []
    state = {"speed": math.nan, "pitch": math.nan}

    def prepare(prev: Waypoint, w: Waypoint) -> None:
        """DO items run on arrival at ``prev``: speed, gimbal and heading for the leg to ``w``."""
        speed = leg_speed(prev, w, yaw_rate_deg_s=o.yaw_rate_deg_s, gimbal_rate_deg_s=o.gimbal_rate_deg_s,
                          settle_s=o.settle_s)
        if o.speed_commands and speed > 0 and not math.isclose(speed, state["speed"], abs_tol=1e-9):
            items.append(do(MAV_CMD_DO_CHANGE_SPEED, (1.0, speed, -1.0, 0.0, 0.0, 0.0, 0.0), w))
            state["speed"] = speed
        pitch = float(w.gimbal_pitch_deg)
        if not math.isclose(pitch, state["pitch"], abs_tol=1e-6):
            flags = float(GIMBAL_MANAGER_FLAGS_ROLL_LOCK | GIMBAL_MANAGER_FLAGS_PITCH_LOCK)
            items.append(do(MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, (pitch, 0.0, _NAN, _NAN, flags, 0.0, 0.0), w))
            if o.mount_control:
                items.append(do(MAV_CMD_DO_MOUNT_CONTROL,
                                (pitch, 0.0, 0.0, 0.0, 0.0, 0.0, float(MAV_MOUNT_MODE_MAVLINK_TARGETING)), w))
            state["pitch"] = pitch
        if o.condition_yaw:  # last: it holds back the DO items after it until the heading is reached
            items.append(do(MAV_CMD_CONDITION_YAW, (heading_0_360(w.heading_deg), o.yaw_rate_deg_s, 0.0, 0.0,
                                                    0.0, 0.0, 0.0), w))

    rest: Sequence[Waypoint]
    if wps[0].kind == "takeoff":
        start, rest = wps[0], wps[1:]
        first_yaw = heading_0_360(rest[0].heading_deg if rest else start.heading_deg)
        climb = max(alt(start), alt(rest[0])) if rest else alt(start)  # a take-off waypoint may be on the ground
        items.append(nav(MAV_CMD_NAV_TAKEOFF, start, 0.0, 0.0, first_yaw, start, altitude=climb))
    else:
        start, rest = home, wps
        items.append(nav(MAV_CMD_NAV_TAKEOFF, home, 0.0, 0.0, heading_0_360(wps[0].heading_deg), None,
                         altitude=alt(wps[0])))
    captures = 0
    landed = False
    prev = dataclasses.replace(start, heading_deg=rest[0].heading_deg if rest else start.heading_deg,
                               gimbal_pitch_deg=0.0)
    last_yaw = heading_0_360(prev.heading_deg)
    for w in rest:
        if w.kind == "land":
            items.append(nav(MAV_CMD_NAV_LAND, w, 0.0, 0.0, last_yaw, w))
            landed = True
            break
        prepare(prev, w)
        last_yaw = heading_0_360(w.heading_deg)
        items.append(nav(MAV_CMD_NAV_WAYPOINT, w, o.capture_hold_s if w.capture else 0.0, o.acceptance_radius_m,
                         last_yaw, w))
        if w.capture:  # first after its waypoint: runs as soon as the waypoint (and its hold) is done
            captures += 1
            if o.camera == "image_start_capture":
                items.append(do(MAV_CMD_IMAGE_START_CAPTURE, (0.0, 0.0, 1.0, float(captures), 0.0, 0.0, 0.0), w))
            else:
                items.append(do(MAV_CMD_DO_DIGICAM_CONTROL, (0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0), w))
        prev = w
    if not landed:
        if o.end == "rtl":
            items.append(do(MAV_CMD_NAV_RETURN_TO_LAUNCH, (0.0,) * 7, None))
        else:
            items.append(nav(MAV_CMD_NAV_LAND, home, 0.0, 0.0, last_yaw, None,
                             altitude=0.0 if frame == MAV_FRAME_GLOBAL_RELATIVE_ALT else alt(home)))
    return items


def _count_items(wps: Sequence[Waypoint], o: _Options) -> int:
    """``len(_build_items(wps, wps[0], ...))`` without building the items.

    The route counts every flight it tries (tens of thousands at 100,000
    heliostats), so the rules of :func:`_build_items` are applied here to
    plain floats: the leg speed of :func:`~pihim.planning.attitude.leg_speed`
    (the same operations in the same order, so the same speeds to the last
    bit), a speed item where it changes, a pitch item (and a mount item)
    where the pitch changes, the yaw condition, the navigation item, the
    capture. ``tests/planning/test_export.py`` holds it to the built items.
    """
    return _tally(wps, o, None)[0] + 1  # the return, or the landing


# what the items of the next waypoint depend on: the count so far, the speed and pitch of the last speed and pitch
# items, the last waypoint's x, y, z, heading (None before the first after the take-off) and pitch, and whether
# a landing ended the mission
_Tally = tuple[int, float, float, float, float, float, float | None, float, bool]


def _tally(wps: Sequence[Waypoint], o: _Options, state: _Tally | None) -> _Tally:
    """:func:`_count_items` of ``wps`` continued from ``state`` (None: ``wps`` starts the flight), less the
    closing item: counting a flight in pieces gives the count of the whole, to the item."""
    if state is None:
        first = wps[0]
        wps = wps[1:] if first.kind == "takeoff" else wps
        state = (1, _NAN, _NAN, first.x_m, first.y_m, first.z_m, None, 0.0, False)  # 1: the take-off
    n, speed_state, pitch_state, px, py, pz, ph, pp, landed = state
    if landed:
        return state
    yaw_rate, gimbal_rate, settle = o.yaw_rate_deg_s, o.gimbal_rate_deg_s, o.settle_s
    speeds, per_waypoint, per_pitch = o.speed_commands, 1 + o.condition_yaw, 1 + o.mount_control
    for w in wps:
        kind = w.kind
        if kind == "land":
            landed = True
            break  # its landing item ends the mission (counted as the return would be)
        x, y, z, h, pitch = w.x_m, w.y_m, w.z_m, float(w.heading_deg), float(w.gimbal_pitch_deg)
        if ph is None:  # the first waypoint after the take-off: the drone already faces it
            ph = h
        speed = float(w.speed_m_s)
        if kind != "takeoff":  # leg_speed -> turn_limited_speed, inlined
            dist = math.dist((px, py, pz), (x, y, z))
            d = abs(h - ph) % 360.0
            turn = min(d, 360.0 - d)
            dp = pitch - pp
            if not (speed <= 0 or dist <= 1e-6 or (turn <= 1e-9 and abs(dp) <= 1e-9)):
                need = max(turn / yaw_rate, abs(dp) / gimbal_rate) + settle
                speed = float(min(speed, max(dist / need, min(0.1, speed))))
        if speeds and speed > 0 and not math.isclose(speed, speed_state, abs_tol=1e-9):
            n += 1
            speed_state = speed
        if not math.isclose(pitch, pitch_state, abs_tol=1e-6):
            n += per_pitch
            pitch_state = pitch
        n += per_waypoint + bool(w.capture)
        px, py, pz, ph, pp = x, y, z, h, pitch
    return (n, speed_state, pitch_state, px, py, pz, ph, pp, landed)


class MissionItemCounter:
    """:func:`count_mission_items` with its options checked once, able to count a flight in pieces.

    ``counter(waypoints)`` is ``count_mission_items(waypoints, **mission_options)``.
    A flight grown one pass at a time (:func:`pihim.planning.endurance.split_flights`
    tries every prefix of a flight) is counted from where its last piece ended:
    ``state = counter.resume(None, first_piece)``, then
    ``counter.resume(state, next_piece)``, and ``counter.total(state)`` is the
    count of all the pieces one after the other, to the item (tested).

    :func:`~pihim.planning.endurance.split_flights` counts in pieces with
    this class only; a subclass is called on whole flights, as any other
    counting function is.

    Parameters
    ----------
    **mission_options
        As :func:`count_mission_items`.

    Raises
    ------
    PihimInputError
        A bad or unknown option (when made, not at the first count).
    """

    __slots__ = ("_given", "_o")

    def __init__(self, **mission_options: Any) -> None:
        counted = {k: v for k, v in mission_options.items()
                   if k not in ("altitude_frame", "geoid_undulation_m", "flight")}  # no effect on the count
        try:
            self._o = _options(**counted)
        except TypeError:
            import inspect

            known = inspect.signature(_options).parameters
            unknown = ", ".join(sorted(k for k in counted if k not in known))
            if not unknown:
                raise
            raise PihimInputError(f"unknown mission option(s): {unknown} (see mission_items)") from None
        self._given = dict(mission_options)

    def __repr__(self) -> str:
        return f"MissionItemCounter({', '.join(f'{k}={v!r}' for k, v in self._given.items())})"

    def __call__(self, waypoints: Sequence[Waypoint]) -> int:
        if not waypoints:
            raise PihimInputError("no waypoints to count")
        return _count_items(waypoints, self._o) + 1

    def resume(self, state: _Tally | None, waypoints: Sequence[Waypoint]) -> _Tally:
        """The count after ``waypoints``, continued from ``state`` (None: they start the flight)."""
        if state is None and not waypoints:
            raise PihimInputError("no waypoints to count")
        return _tally(waypoints, self._o, state)

    @staticmethod
    def total(state: _Tally) -> int:
        """Mission items of the waypoints counted into ``state``, home slot and closing item included."""
        return state[0] + 2


def count_mission_items(waypoints: Sequence[Waypoint], **mission_options: Any) -> int:
    """Mission items a waypoint sequence becomes, home slot included (what an autopilot stores).

    Parameters
    ----------
    waypoints : sequence of Waypoint
        One flight's waypoints (take-off ... landing), as
        :attr:`pihim.planning.model.Flight.waypoints`.
    **mission_options
        As :func:`mission_items` (``autopilot``, ``condition_yaw``,
        ``mount_control``, ``speed_commands``, rates, ``capture_hold_s``,
        ``end``); altitude options do not change the count.

    Returns
    -------
    int
        ``len(mission_items(...).items) + 1``: ArduPilot keeps home in slot 0
        of its mission storage, and the ``.waypoints`` file has that row too.
    """
    if not waypoints:
        raise PihimInputError("no waypoints to count")
    return MissionItemCounter(**mission_options)(waypoints)


def mission_items(
    plan: Plan,
    *,
    flight: int | None = None,
    autopilot: Literal["ardupilot", "px4"] = "ardupilot",
    altitude_frame: Literal["relative", "amsl"] = "relative",
    geoid_undulation_m: float | None = None,
    condition_yaw: bool | None = None,
    yaw_rate_deg_s: float = 30.0,
    gimbal_rate_deg_s: float = 30.0,
    settle_s: float = 0.5,
    mount_control: bool = False,
    camera: Literal["image_start_capture", "digicam"] = "image_start_capture",
    capture_hold_s: float = 2.0,
    acceptance_radius_m: float = 0.0,
    speed_commands: bool = True,
    end: Literal["rtl", "land"] = "rtl",
) -> Mission:
    """The MAVLink mission of one flight (see the module docstring for the layout and timing).

    Parameters
    ----------
    plan : Plan
    flight : int, optional
        The flight (:attr:`Flight.index`) to fly. Default: the plan's only
        flight; a plan of several flights must be exported one flight at a
        time (one battery, one mission); a plan without flights flies its
        passes joined by straight legs (no battery check).
    autopilot : {"ardupilot", "px4"}
        Sets ``firmwareType`` (3 or 12) and the default of ``condition_yaw``.
    altitude_frame : {"relative", "amsl"}
        ``MAV_FRAME_GLOBAL_RELATIVE_ALT`` (metres above home) or
        ``MAV_FRAME_GLOBAL`` (metres above mean sea level).
    geoid_undulation_m : float, optional
        EGM96 geoid height at the site (AMSL = ellipsoidal - undulation);
        default from ``plan.site`` or the NSTTF estimate near the NSTTF.
    condition_yaw : bool, optional
        Turn with ``MAV_CMD_CONDITION_YAW`` on every leg. Default: True for
        ArduPilot (which ignores the waypoint yaw), False for PX4 (which flies
        the waypoint yaw, param 4).
    yaw_rate_deg_s : float
        Yaw rate, deg/s (> 0): ``CONDITION_YAW`` param 2, and the rate the leg
        timing assumes (for PX4 set ``MPC_YAWRAUTO_MAX`` at least this high).
    gimbal_rate_deg_s : float
        Gimbal pitch rate the leg timing assumes, deg/s (> 0).
    settle_s : float
        Margin after a turn before a photo, seconds.
    mount_control : bool
        Also emit ``MAV_CMD_DO_MOUNT_CONTROL`` (205) for autopilots without
        gimbal protocol v2.
    camera : {"image_start_capture", "digicam"}
        Capture command: ``MAV_CMD_IMAGE_START_CAPTURE`` (2000) or
        ``MAV_CMD_DO_DIGICAM_CONTROL`` (203).
    capture_hold_s : float
        Hold at capture waypoints (``NAV_WAYPOINT`` param 1), seconds: the
        drone stops at the point and the photo is taken when the hold ends.
        Default 2 s, the hover per image of the flight-time model
        (:attr:`pihim.planning.endurance.DroneEndurance.capture_s`).
    acceptance_radius_m : float
        ``NAV_WAYPOINT`` param 2; 0 lets the autopilot use its default.
    speed_commands : bool
        Emit ``MAV_CMD_DO_CHANGE_SPEED`` when the leg speed changes.
    end : {"rtl", "land"}
        Final command when the waypoints do not end with a landing.

    Returns
    -------
    Mission

    Raises
    ------
    PihimInputError
        Invalid plan (no passes, non-finite waypoint) or option, or a plan of
        several flights without ``flight``.
    """
    check_plan(plan)
    _option("altitude_frame", altitude_frame, ("relative", "amsl"))
    o = _options(autopilot, condition_yaw, yaw_rate_deg_s, gimbal_rate_deg_s, settle_s, mount_control, camera,
                 capture_hold_s, acceptance_radius_m, speed_commands, end)
    undulation = geoid_undulation(plan, geoid_undulation_m)
    wps = mission_waypoints(plan, resolve_flight(plan, flight))

    home = plan.home
    frame = MAV_FRAME_GLOBAL_RELATIVE_ALT if altitude_frame == "relative" else MAV_FRAME_GLOBAL

    def alt(w: Waypoint) -> float:
        return w.height_m - home.height_m if frame == MAV_FRAME_GLOBAL_RELATIVE_ALT else w.height_m - undulation

    items = _build_items(wps, home, alt, frame, o)
    speeds = [w.speed_m_s for w in wps if w.speed_m_s > 0]
    hover = float(statistics.median(speeds)) if speeds else 5.0
    cruise = float(max(speeds)) if speeds else hover
    return Mission(
        items=tuple(items),
        home=(home.latitude_deg, home.longitude_deg, home.height_m - undulation),
        altitude_frame=frame,
        firmware_type=MAV_AUTOPILOT_ARDUPILOTMEGA if autopilot == "ardupilot" else MAV_AUTOPILOT_PX4,
        hover_speed_m_s=hover,
        cruise_speed_m_s=cruise,
        geoid_undulation_m=undulation,
    )


def _json_item(item: MissionItem, jump_id: int) -> dict[str, Any]:
    d: dict[str, Any] = {
        "autoContinue": item.autocontinue,
        "command": item.command,
        "doJumpId": jump_id,
        "frame": item.frame,
        "params": [p if math.isfinite(p) else None for p in item.params],
        "type": "SimpleItem",
    }
    if item.specifies_coordinate:  # QGC writes these three only for items with an altitude
        d["AMSLAltAboveTerrain"] = None
        d["Altitude"] = d["params"][6]
        d["AltitudeMode"] = _QGC_ALT_MODE[item.frame]
    return d


def _fence_circle(plan: Plan, waypoints: tuple[Waypoint, ...], margin_m: float) -> dict[str, Any]:
    """An inclusion circle on home enclosing every waypoint plus ``margin_m``."""
    from pihim.field.geodesy import geodetic_to_enu

    h = plan.home
    lat = [w.latitude_deg for w in waypoints]
    lon = [w.longitude_deg for w in waypoints]
    enu = geodetic_to_enu(lat, lon, [h.height_m] * len(lat), (h.latitude_deg, h.longitude_deg, h.height_m))
    radius = max(math.hypot(float(e), float(n)) for e, n in zip(enu[..., 0], enu[..., 1], strict=True))
    return {
        "circle": {"center": [h.latitude_deg, h.longitude_deg], "radius": round(radius + margin_m, 2)},
        "inclusion": True,
        "version": 1,
    }


def qgc_plan_document(
    plan: Plan,
    *,
    geofence_margin_m: float | None = None,
    **mission_options: Any,
) -> dict[str, Any]:
    """The QGroundControl plan file content as a dictionary.

    Parameters
    ----------
    plan : Plan
    geofence_margin_m : float, optional
        If given, add an inclusion geofence circle centred on home whose
        radius is the farthest mission waypoint plus this margin (metres).
        Default: no geofence.
    **mission_options
        Passed to :func:`mission_items` (``flight``, ``autopilot``,
        ``altitude_frame``, ...).

    Returns
    -------
    dict
        ``fileType`` "Plan", ``version`` 1, ``groundStation``
        "QGroundControl", ``mission`` (version 2), ``geoFence`` (version 2)
        and ``rallyPoints`` (version 2); NaN parameters are ``None``.
    """
    mission = mission_items(plan, **mission_options)
    return qgc_mission_document(plan, mission, geofence_margin_m, mission_options.get("flight"))


def qgc_mission_document(plan: Plan, mission: Mission, geofence_margin_m: float | None,
                         flight: int | None) -> dict[str, Any]:
    """:func:`qgc_plan_document` of ``mission``, the mission of ``flight`` of ``plan``."""
    fence: list[dict[str, Any]] = []
    if geofence_margin_m is not None:
        margin = _nonneg("geofence_margin_m", geofence_margin_m)
        fence.append(_fence_circle(plan, mission_waypoints(plan, resolve_flight(plan, flight)), margin))
    doc = {
        "fileType": "Plan",
        "geoFence": {"circles": fence, "polygons": [], "version": 2},
        "groundStation": "QGroundControl",
        "mission": {
            "cruiseSpeed": mission.cruise_speed_m_s,
            "firmwareType": mission.firmware_type,
            "globalPlanAltitudeMode": _QGC_ALT_MODE[mission.altitude_frame],
            "hoverSpeed": mission.hover_speed_m_s,
            "items": [],  # below: _json_item writes them JSON-ready (the bulk of the file, walked once)
            "plannedHomePosition": list(mission.home),
            "vehicleType": MAV_TYPE_QUADROTOR,
            "version": 2,
        },
        "rallyPoints": {"points": [], "version": 2},
        "version": 1,
    }
    doc = json_ready(doc)
    doc["mission"]["items"] = [_json_item(it, k) for k, it in enumerate(mission.items, start=1)]
    return doc


def write_qgc_plan(
    plan: Plan,
    path: str | Path,
    *,
    geofence_margin_m: float | None = None,
    **mission_options: Any,
) -> Path:
    """Write a QGroundControl ``.plan`` file (JSON) atomically.

    Parameters
    ----------
    plan : Plan
    path : str or path-like
        Output file, conventionally ``mission.plan`` (QGroundControl picks
        the loader from the ``.plan`` extension).
    geofence_margin_m : float, optional
        See :func:`qgc_plan_document`.
    **mission_options
        See :func:`mission_items`.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    PihimInputError
        Invalid plan or option; no file is written.

    Notes
    -----
    The file validates against ``pihim/schemas/qgc-plan.schema.json``,
    written from QGroundControl's loader rules [1]_. Keys are sorted and
    indented by four spaces as QGroundControl writes them, each mission item
    on one line (a few times faster to write for long missions).
    """
    text = qgc_plan_text(plan, geofence_margin_m=geofence_margin_m, **mission_options)
    return write_export(path, text)


def qgc_plan_text(plan: Plan, *, geofence_margin_m: float | None = None, **mission_options: Any) -> str:
    """The ``.plan`` file text (see :func:`write_qgc_plan`)."""
    return qgc_document_text(qgc_plan_document(plan, geofence_margin_m=geofence_margin_m, **mission_options))


def qgc_document_text(doc: dict[str, Any]) -> str:
    """The text of a :func:`qgc_plan_document` (keys sorted, indented by four spaces, one mission item per line)."""
    return json_text(doc, indent=4, sort_keys=True, inline_depth=3) + "\n"
