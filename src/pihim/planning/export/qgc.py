"""QGroundControl ``.plan`` mission files (and the MAVLink mission items they hold).

:func:`mission_items` turns a :class:`~pihim.planning.model.Plan` into a list
of MAVLink mission items [2]_; :func:`write_qgc_plan` wraps them in a
QGroundControl plan file [1]_ and :func:`pihim.planning.export.wpl.write_wpl`
writes the same items as a ``QGC WPL 110`` text file.

Mission layout
--------------
1. ``MAV_CMD_NAV_TAKEOFF`` (22): at the first waypoint if its kind is
   ``takeoff`` (climbing to the higher of its altitude and the next
   waypoint's, since a take-off waypoint may sit on the ground), otherwise at
   the plan's home position, climbing to the first waypoint's altitude; yaw
   (param4) = heading of the first waypoint flown.
2. For every other waypoint, in order:

   * ``MAV_CMD_DO_CHANGE_SPEED`` (178: ground speed, m/s, throttle -1,
     absolute) *before* the waypoint whenever its speed differs from the
     previous one (``speed_commands=True``); the speed is the ground speed
     toward this waypoint;
   * ``MAV_CMD_NAV_WAYPOINT`` (16): hold (``capture_hold_s`` at capture
     waypoints, else 0), acceptance radius, pass radius 0, **yaw = the
     waypoint heading** (deg clockwise from North; PX4 flies it);
   * ``MAV_CMD_CONDITION_YAW`` (115): angle = heading, rate
     ``yaw_rate_deg_s`` (0: the autopilot default), direction 0 (shortest),
     absolute (param4 = 0) -- ArduPilot ignores the waypoint yaw, so this
     is what turns an ArduPilot copter (default for ``autopilot="ardupilot"``,
     off for PX4);
   * ``MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW`` (1000): pitch = waypoint gimbal
     pitch (deg, negative down), yaw 0 (camera along the vehicle heading),
     rates NaN (unset), flags ``ROLL_LOCK | PITCH_LOCK`` = 12 (pitch relative
     to the horizon), gimbal device 0 (primary); optionally also the older
     ``MAV_CMD_DO_MOUNT_CONTROL`` (205: pitch, roll 0, yaw 0, mode
     ``MAV_MOUNT_MODE_MAVLINK_TARGETING`` = 2) with ``mount_control=True``;
   * at capture waypoints only: ``MAV_CMD_IMAGE_START_CAPTURE`` (2000:
     camera 0 = all, interval 0, count 1, capture sequence number 1, 2, ...)
     or, with ``camera="digicam"``, ``MAV_CMD_DO_DIGICAM_CONTROL`` (203:
     shoot = 1).

   A waypoint of kind ``land`` becomes ``MAV_CMD_NAV_LAND`` (21: abort
   altitude 0, land mode 0, yaw = last heading) and ends the mission.
3. ``MAV_CMD_NAV_RETURN_TO_LAUNCH`` (20) (``end="rtl"``, default) or
   ``MAV_CMD_NAV_LAND`` at home (``end="land"``), unless a ``land``
   waypoint already ended the mission.

Both ArduPilot and PX4 run the DO/CONDITION items that follow a navigation
item once that waypoint is reached, so yaw, gimbal and camera commands act
*at* their waypoint.

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
.. [3] ArduPilot, "Mission Commands",
   https://ardupilot.org/copter/docs/common-mavlink-mission-command-messages-mav_cmd.html.
"""

from __future__ import annotations

import json
import math
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pihim.errors import PihimInputError
from pihim.planning.export._common import (
    check_plan,
    geoid_undulation,
    heading_0_360,
    json_ready,
    mission_waypoints,
    write_export,
)
from pihim.planning.model import Plan, Waypoint

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


def mission_items(
    plan: Plan,
    *,
    flight: int | None = None,
    autopilot: Literal["ardupilot", "px4"] = "ardupilot",
    altitude_frame: Literal["relative", "amsl"] = "relative",
    geoid_undulation_m: float | None = None,
    condition_yaw: bool | None = None,
    yaw_rate_deg_s: float = 0.0,
    mount_control: bool = False,
    camera: Literal["image_start_capture", "digicam"] = "image_start_capture",
    capture_hold_s: float = 0.0,
    acceptance_radius_m: float = 0.0,
    speed_commands: bool = True,
    end: Literal["rtl", "land"] = "rtl",
) -> Mission:
    """The MAVLink mission for a plan (see the module docstring for the layout).

    Parameters
    ----------
    plan : Plan
    flight : int, optional
        Export one flight (:attr:`Flight.index`) instead of all passes.
    autopilot : {"ardupilot", "px4"}
        Sets ``firmwareType`` (3 or 12) and the default of ``condition_yaw``.
    altitude_frame : {"relative", "amsl"}
        ``MAV_FRAME_GLOBAL_RELATIVE_ALT`` (metres above home) or
        ``MAV_FRAME_GLOBAL`` (metres above mean sea level).
    geoid_undulation_m : float, optional
        EGM96 geoid height at the site (AMSL = ellipsoidal - undulation);
        default from ``plan.site`` or the NSTTF estimate near the NSTTF.
    condition_yaw : bool, optional
        Add ``MAV_CMD_CONDITION_YAW`` after each waypoint. Default: True for
        ArduPilot, False for PX4 (which flies the waypoint yaw).
    yaw_rate_deg_s : float
        ``CONDITION_YAW`` rate; 0 lets the autopilot use its default.
    mount_control : bool
        Also emit ``MAV_CMD_DO_MOUNT_CONTROL`` (205) for autopilots without
        gimbal protocol v2.
    camera : {"image_start_capture", "digicam"}
        Capture command: ``MAV_CMD_IMAGE_START_CAPTURE`` (2000) or
        ``MAV_CMD_DO_DIGICAM_CONTROL`` (203).
    capture_hold_s : float
        Hold time at capture waypoints (``NAV_WAYPOINT`` param1), seconds.
    acceptance_radius_m : float
        ``NAV_WAYPOINT`` param2; 0 lets the autopilot use its default.
    speed_commands : bool
        Emit ``MAV_CMD_DO_CHANGE_SPEED`` when the waypoint speed changes.
    end : {"rtl", "land"}
        Final command when the waypoints do not end with a landing.

    Returns
    -------
    Mission

    Raises
    ------
    PihimInputError
        Invalid plan (no passes, non-finite waypoint) or option.
    """
    check_plan(plan)
    _option("autopilot", autopilot, ("ardupilot", "px4"))
    _option("altitude_frame", altitude_frame, ("relative", "amsl"))
    _option("camera", camera, ("image_start_capture", "digicam"))
    _option("end", end, ("rtl", "land"))
    for name, flag in (("mount_control", mount_control), ("speed_commands", speed_commands)):
        if not isinstance(flag, bool):
            raise PihimInputError(f"{name} must be True or False, got {flag!r}")
    if condition_yaw is None:
        condition_yaw = autopilot == "ardupilot"
    elif not isinstance(condition_yaw, bool):
        raise PihimInputError(f"condition_yaw must be True, False or None, got {condition_yaw!r}")
    yaw_rate = _nonneg("yaw_rate_deg_s", yaw_rate_deg_s)
    hold = _nonneg("capture_hold_s", capture_hold_s)
    radius = _nonneg("acceptance_radius_m", acceptance_radius_m)
    undulation = geoid_undulation(plan, geoid_undulation_m)
    wps = mission_waypoints(plan, flight)

    home = plan.home
    frame = MAV_FRAME_GLOBAL_RELATIVE_ALT if altitude_frame == "relative" else MAV_FRAME_GLOBAL

    def alt(w: Waypoint) -> float:
        return w.height_m - home.height_m if frame == MAV_FRAME_GLOBAL_RELATIVE_ALT else w.height_m - undulation

    def nav(command: int, w: Waypoint, p1: float, p2: float, p3: float, p4: float,
            target: Waypoint | None, altitude: float | None = None) -> MissionItem:
        z = alt(w) if altitude is None else altitude
        return MissionItem(command, frame, (p1, p2, p3, p4, w.latitude_deg, w.longitude_deg, z), True, target)

    def do(command: int, params: tuple[float, ...], w: Waypoint | None) -> MissionItem:
        return MissionItem(command, MAV_FRAME_MISSION, params, True, w)  # type: ignore[arg-type]

    items: list[MissionItem] = []
    rest: tuple[Waypoint, ...]
    # take-off and landing yaw: the heading of the next / last flown waypoint (not NaN, which the
    # text format cannot carry and PX4 would read as "keep the current heading mode")
    if wps[0].kind == "takeoff":
        rest = wps[1:]
        first_yaw = heading_0_360(rest[0].heading_deg if rest else wps[0].heading_deg)
        climb = max(alt(wps[0]), alt(rest[0])) if rest else alt(wps[0])  # a take-off waypoint may be on the ground
        items.append(nav(MAV_CMD_NAV_TAKEOFF, wps[0], 0.0, 0.0, 0.0, first_yaw, wps[0], altitude=climb))
    else:
        rest = wps
        items.append(nav(MAV_CMD_NAV_TAKEOFF, home, 0.0, 0.0, 0.0, heading_0_360(wps[0].heading_deg), None,
                         altitude=alt(wps[0])))

    speed: float | None = None
    captures = 0
    landed = False
    last_yaw = heading_0_360(wps[0].heading_deg)
    for w in rest:
        if w.kind == "land":
            items.append(nav(MAV_CMD_NAV_LAND, w, 0.0, 0.0, 0.0, last_yaw, w))
            landed = True
            break
        if speed_commands and w.speed_m_s > 0 and w.speed_m_s != speed:
            items.append(do(MAV_CMD_DO_CHANGE_SPEED, (1.0, float(w.speed_m_s), -1.0, 0.0, 0.0, 0.0, 0.0), w))
            speed = w.speed_m_s
        heading = last_yaw = heading_0_360(w.heading_deg)
        items.append(nav(MAV_CMD_NAV_WAYPOINT, w, hold if w.capture else 0.0, radius, 0.0, heading, w))
        if condition_yaw:
            items.append(do(MAV_CMD_CONDITION_YAW, (heading, yaw_rate, 0.0, 0.0, 0.0, 0.0, 0.0), w))
        pitch = float(w.gimbal_pitch_deg)
        flags = float(GIMBAL_MANAGER_FLAGS_ROLL_LOCK | GIMBAL_MANAGER_FLAGS_PITCH_LOCK)
        items.append(do(MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, (pitch, 0.0, _NAN, _NAN, flags, 0.0, 0.0), w))
        if mount_control:
            items.append(do(MAV_CMD_DO_MOUNT_CONTROL,
                            (pitch, 0.0, 0.0, 0.0, 0.0, 0.0, float(MAV_MOUNT_MODE_MAVLINK_TARGETING)), w))
        if w.capture:
            captures += 1
            if camera == "image_start_capture":
                items.append(do(MAV_CMD_IMAGE_START_CAPTURE, (0.0, 0.0, 1.0, float(captures), _NAN, _NAN, _NAN), w))
            else:
                items.append(do(MAV_CMD_DO_DIGICAM_CONTROL, (0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0), w))
    if not landed:
        if end == "rtl":
            items.append(do(MAV_CMD_NAV_RETURN_TO_LAUNCH, (0.0,) * 7, None))
        else:
            items.append(nav(MAV_CMD_NAV_LAND, home, 0.0, 0.0, 0.0, last_yaw, None,
                             altitude=0.0 if frame == MAV_FRAME_GLOBAL_RELATIVE_ALT else alt(home)))

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
        d["Altitude"] = item.params[6]
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
    fence: list[dict[str, Any]] = []
    if geofence_margin_m is not None:
        margin = _nonneg("geofence_margin_m", geofence_margin_m)
        fence.append(_fence_circle(plan, mission_waypoints(plan, mission_options.get("flight")), margin))
    doc = {
        "fileType": "Plan",
        "geoFence": {"circles": fence, "polygons": [], "version": 2},
        "groundStation": "QGroundControl",
        "mission": {
            "cruiseSpeed": mission.cruise_speed_m_s,
            "firmwareType": mission.firmware_type,
            "globalPlanAltitudeMode": _QGC_ALT_MODE[mission.altitude_frame],
            "hoverSpeed": mission.hover_speed_m_s,
            "items": [_json_item(it, k) for k, it in enumerate(mission.items, start=1)],
            "plannedHomePosition": list(mission.home),
            "vehicleType": MAV_TYPE_QUADROTOR,
            "version": 2,
        },
        "rallyPoints": {"points": [], "version": 2},
        "version": 1,
    }
    return json_ready(doc)


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
    indented by four spaces as QGroundControl writes them.
    """
    text = qgc_plan_text(plan, geofence_margin_m=geofence_margin_m, **mission_options)
    return write_export(path, text)


def qgc_plan_text(plan: Plan, *, geofence_margin_m: float | None = None, **mission_options: Any) -> str:
    """The ``.plan`` file text (see :func:`write_qgc_plan`)."""
    doc = qgc_plan_document(plan, geofence_margin_m=geofence_margin_m, **mission_options)
    return json.dumps(doc, indent=4, sort_keys=True, allow_nan=False) + "\n"
