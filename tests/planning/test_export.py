"""Mission export: plan.json, QGroundControl .plan, QGC WPL 110, KML, Litchi CSV and the map."""

from __future__ import annotations

import csv
import itertools
import json
import math
import struct
import xml.etree.ElementTree as ET
from dataclasses import replace

import jsonschema
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pihim.errors import PihimInputError
from pihim.field.geodesy import enu_to_geodetic
from pihim.field.layout import NSTTF_TOWER, Field, nsttf_spec
from pihim.planning.export import (
    LITCHI_HEADER,
    OUTPUT_NAMES,
    MissionItemCounter,
    count_mission_items,
    export_all,
    flight_file_stem,
    kml_text,
    litchi_csv_text,
    litchi_mission_texts,
    litchi_missions,
    litchi_waypoints,
    load_plan_schema,
    plan_json_text,
    load_qgc_plan_schema,
    mission_items,
    qgc_plan_document,
    write_kml,
    write_kml_text,
    write_litchi_csv,
    write_plan_figure,
    write_plan_json,
    write_plan_json_text,
    write_qgc_plan,
    write_wpl,
)
from pihim.planning.export.kml import KML_NS
from pihim.planning.export.qgc import (
    MAV_CMD_CONDITION_YAW,
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_DO_DIGICAM_CONTROL,
    MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
    MAV_CMD_DO_MOUNT_CONTROL,
    MAV_CMD_IMAGE_START_CAPTURE,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_NAV_WAYPOINT,
)
from pihim.planning.attitude import leg_speed
from pihim.planning.endurance import DroneEndurance, split_flights
from pihim.planning.model import (
    Flight,
    PairPrediction,
    PassShift,
    Plan,
    ScanPass,
    Waypoint,
)

# NSTTF field origin (OpenCSP lon/lat), ellipsoidal height 1684.88 m (pihim.sky.sun.NSTTF)
ORIGIN = (34.962276, -106.509606, 1684.88)
GEOID_NSTTF = -22.0
LITCHI_HEADER_TEXT = (
    "latitude,longitude,altitude(m),heading(deg),curvesize(m),rotationdir,gimbalmode,gimbalpitchangle,"
    + ",".join(f"actiontype{k},actionparam{k}" for k in range(1, 16))
    + ",altitudemode,speed(m/s),poi_latitude,poi_longitude,poi_altitude(m),poi_altitudemode,"
    "photo_timeinterval,photo_distinterval"
)
CAPTURE_COMMANDS = {MAV_CMD_IMAGE_START_CAPTURE, MAV_CMD_DO_DIGICAM_CONTROL}
NAV = {MAV_CMD_NAV_TAKEOFF, MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_LAND, MAV_CMD_NAV_RETURN_TO_LAUNCH}


# --------------------------------------------------------------------------- a small synthetic plan


def _wp(x, y, z, heading, pitch, speed=2.0, kind="scan", capture=False, hua=None) -> Waypoint:
    lat, lon, h = enu_to_geodetic([x, y, z], ORIGIN)
    return Waypoint(x, y, z, float(lat), float(lon), float(h), heading, pitch, speed, kind, capture, hua)


def _pass(index: int, x: float, altitude: float, northbound: bool, pitch: float, huas, targets) -> ScanPass:
    heading = 0.0 if northbound else 180.0
    ys = [50.0, 60.0, 72.0, 84.0, 96.0]
    if not northbound:
        ys = ys[::-1]
    wps = [_wp(x, ys[0], altitude, heading, pitch, speed=3.0, kind="lead_in")]
    for k, (y, hua) in enumerate(zip(ys[1:4], huas, strict=True)):
        wps.append(_wp(x, y, altitude, heading, pitch + k, speed=2.0, kind="scan", capture=True, hua=hua))
    wps.append(_wp(x, ys[4], altitude, heading, pitch, speed=3.0, kind="run_past"))
    preds = []
    for k, (hua, target) in enumerate(zip(huas, targets, strict=True)):
        preds.append(PairPrediction(
            hua=hua, target=target, waypoint_index=k + 1,
            reflection_dolp=0.15 + 0.1 * k, sky_dolp_difference=0.08 if k else None,
            ground_aop_difference_deg=12.0 + k, ground_aop_raw_difference_deg=168.0 - k,
            reflection_dolp_ok=0.15 + 0.1 * k > 0.2, sky_vs_sky_ok=bool(k), ground_vs_ground_ok=k == 2,
        ))
    return ScanPass(
        index=index, azimuth_deg=heading, altitude_m=altitude, gimbal_pitch_deg=pitch,
        pairs=tuple(zip(huas, targets, strict=True)), waypoints=tuple(wps), predictions=tuple(preds),
        feasible=index != 2, issues=() if index != 2 else ("passes within 12 m of the tower",),
        shift=PassShift(altitude_delta_m=5.0, usable_fraction_before=0.33, usable_fraction_after=0.67) if index == 1
        else None,
    )


def make_plan(*, with_flight: bool = True) -> Plan:
    passes = (
        _pass(0, 25.0, 35.0, True, -28.0, ("5E3", "6E3", "7E3"), ("5E2", "6E2", "7E2")),
        _pass(1, 35.0, 40.0, False, -31.0, ("7E4", "6E4", "5E4"), ("7E3", "6E3", "5E3")),
        _pass(2, 45.0, 45.0, True, -34.0, ("5E5", "6E5", "7E5"), ("5E4", "6E4", "7E4")),
    )
    home = _wp(-30.0, 20.0, 0.0, 0.0, 0.0, speed=0.0, kind="takeoff")
    flights = ()
    if with_flight:
        body = [w for p in passes for w in p.waypoints]
        fw = (
            _wp(-30.0, 20.0, 0.0, 0.0, 0.0, speed=0.0, kind="takeoff"),
            _wp(-30.0, 20.0, 35.0, 45.0, -28.0, speed=5.0, kind="transit"),
            *body,
            _wp(-30.0, 20.0, 45.0, 225.0, 0.0, speed=5.0, kind="return"),
            _wp(-30.0, 20.0, 0.0, 225.0, 0.0, speed=1.0, kind="land"),
        )
        flights = (Flight(index=0, pass_indices=(0, 1, 2), waypoints=fw, duration_s=612.0, distance_m=1450.0,
                          heliostats_assessed=9),)
    site = {"name": "NSTTF", "latitude_deg": ORIGIN[0], "longitude_deg": ORIGIN[1], "height_m": ORIGIN[2],
            "timezone": "America/Denver"}
    return Plan(
        time_iso="2024-06-21T10:30:00-06:00", site=site, sun={"zenith_deg": 25.3, "azimuth_deg": 112.4},
        aim_point=(0.0, 8.8, 28.9), min_altitude_m=20.0, max_altitude_m=120.0,
        camera={"name": "Lucid Triton TRI050S-PC", "focal_length_mm": 35.0}, home=home, passes=passes,
        flights=flights, summary={"heliostats_assessed": 9, "note": "synthetic"},
    )


def make_field() -> Field:
    names, pivots = [], []
    for row, y in ((5, 57.9), (6, 70.1), (7, 82.3)):
        for col in range(1, 6):
            for side, sign in (("E", 1.0), ("W", -1.0)):
                names.append(f"{row}{side}{col}")
                pivots.append((sign * (col - 0.5) * 9.7536, y, 3.8))
    return Field(tuple(names), np.array(pivots), nsttf_spec(), NSTTF_TOWER)


@pytest.fixture(scope="module")
def plan() -> Plan:
    return make_plan()


@pytest.fixture(scope="module")
def field() -> Field:
    return make_field()


def _all_wps(plan: Plan) -> list[Waypoint]:
    return [w for p in plan.passes for w in p.waypoints]


def _flown(plan: Plan) -> list[Waypoint]:
    """The waypoints the mission of the plan's only flight flies between take-off and landing."""
    return list(plan.flights[0].waypoints[1:-1])


def _groups(items: list[dict]) -> list[tuple[dict, list[dict]]]:
    """(navigation item, DO/CONDITION items that follow it) in mission order."""
    groups: list[tuple[dict, list[dict]]] = []
    for it in items:
        if it["command"] in NAV:
            groups.append((it, []))
        else:
            assert groups, "a mission starts with a navigation item"
            groups[-1][1].append(it)
    return groups


# --------------------------------------------------------------------------- plan.json


def test_plan_json_validates_against_schema(plan, tmp_path):
    path = write_plan_json(plan, tmp_path / "plan.json")
    doc = json.loads(path.read_text())
    schema = load_plan_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    jsonschema.validate(doc, schema, cls=jsonschema.Draft202012Validator)
    assert doc["schema"] == "pihim.plan/1"
    assert doc["export"]["generator"].startswith("pihim ")
    c = doc["export"]["counts"]
    assert (c["passes"], c["waypoints"], c["capture_waypoints"], c["pairs"], c["flights"]) == (3, 15, 9, 9, 1)
    assert c["predictions"] == 9 and 0 <= c["usable_fraction"] <= 1
    # everything from Plan.to_dict() is there unchanged
    ref = json.loads(json.dumps(plan.to_dict()))
    assert {k: doc[k] for k in ref} == ref
    w = doc["passes"][0]["waypoints"][1]
    assert w["capture"] is True and w["hua"] == "5E3" and w["kind"] == "scan"
    assert doc["passes"][0]["predictions"][0]["sky_dolp_difference"] is None
    assert set(doc["passes"][0]["predictions"][0]) >= {"reflection_dolp_ok", "sky_vs_sky_ok", "ground_vs_ground_ok",
                                                      "usable"}


def test_plan_json_is_the_same_text_written_whole_or_in_pieces(plan, tmp_path):
    pieces: list[str] = []
    write_plan_json_text(plan, pieces.append)
    text = plan_json_text(plan)
    assert "".join(pieces) == text and text.endswith("}\n")
    assert write_plan_json(plan, tmp_path / "plan.json").read_text() == text
    with pytest.raises(PihimInputError, match="latitude_deg"):  # checked before the first piece
        write_plan_json_text(_nan_latitude_plan(plan), pieces.append)
    assert "".join(pieces) == text


def test_plan_schema_has_teeth(plan):
    schema = load_plan_schema()
    doc = json.loads(json.dumps(plan.to_dict()))
    doc["passes"][0]["waypoints"][0]["heading_deg"] = 400.0
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(doc, schema, cls=jsonschema.Draft202012Validator)
    doc = json.loads(json.dumps(plan.to_dict()))
    del doc["passes"][1]["predictions"][0]["sky_vs_sky_ok"]
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(doc, schema, cls=jsonschema.Draft202012Validator)


def test_plan_json_non_finite_prediction_becomes_null(plan, tmp_path):
    p0 = plan.passes[0]
    bad = replace(p0, predictions=(replace(p0.predictions[0], reflection_dolp=math.nan), *p0.predictions[1:]))
    doc = json.loads(write_plan_json(replace(plan, passes=(bad, *plan.passes[1:])), tmp_path / "p.json").read_text())
    assert doc["passes"][0]["predictions"][0]["reflection_dolp"] is None
    jsonschema.validate(doc, load_plan_schema(), cls=jsonschema.Draft202012Validator)


def test_plan_to_dict_finite_equals_json_ready_of_to_dict(plan):
    """The one-pass conversion plan.json uses gives what json_ready makes of to_dict: NaN, inf and numpy NaN as
    None, numpy scalars as Python numbers, everything else unchanged."""
    from pihim.planning.export._common import json_ready

    p0 = plan.passes[0]
    bad = replace(p0, predictions=(replace(p0.predictions[0], reflection_dolp=math.nan,
                                           sky_dolp_difference=-math.inf), *p0.predictions[1:]))
    summary = {"a": np.float64(0.25), "b": np.float32(np.nan), "c": [np.int64(3), np.bool_(True), math.inf],
               "d": {"e": (1.5, None, "x")}}
    odd = replace(plan, passes=(bad, *plan.passes[1:]), summary=summary)
    doc = odd.to_dict(finite=True)
    assert doc == json_ready(odd.to_dict())
    assert doc["summary"] == {"a": 0.25, "b": None, "c": [3, True, None], "d": {"e": [1.5, None, "x"]}}
    assert [type(v) for v in doc["summary"]["c"]] == [int, bool, type(None)] and type(doc["summary"]["a"]) is float
    pred = doc["passes"][0]["predictions"][0]
    assert pred["reflection_dolp"] is None and pred["sky_dolp_difference"] is None
    assert math.isnan(odd.to_dict()["passes"][0]["predictions"][0]["reflection_dolp"])  # the default keeps NaN

# --------------------------------------------------------------------------- QGroundControl .plan


def test_qgc_plan_validates_and_has_the_file_constants(plan, tmp_path):
    path = write_qgc_plan(plan, tmp_path / "mission.plan", geofence_margin_m=30.0)
    doc = json.loads(path.read_text())
    schema = load_qgc_plan_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    jsonschema.validate(doc, schema, cls=jsonschema.Draft202012Validator)
    assert (doc["fileType"], doc["version"], doc["groundStation"]) == ("Plan", 1, "QGroundControl")
    m = doc["mission"]
    assert (m["version"], m["firmwareType"], m["vehicleType"], m["globalPlanAltitudeMode"]) == (2, 3, 2, 1)
    home = plan.home
    assert m["plannedHomePosition"] == pytest.approx([home.latitude_deg, home.longitude_deg,
                                                      home.height_m - GEOID_NSTTF], abs=1e-9)
    assert doc["geoFence"]["version"] == 2 and doc["rallyPoints"] == {"points": [], "version": 2}
    circle = doc["geoFence"]["circles"][0]
    assert circle["inclusion"] is True and circle["circle"]["center"] == [home.latitude_deg, home.longitude_deg]
    far = max(math.hypot(w.x_m - home.x_m, w.y_m - home.y_m) for w in plan.flights[0].waypoints)
    assert far + 30.0 - 0.05 <= circle["circle"]["radius"] <= far + 30.0 + 0.05
    for it in m["items"]:
        assert len(it["params"]) == 7 and it["type"] == "SimpleItem" and it["autoContinue"] is True
        if it["command"] in (MAV_CMD_NAV_TAKEOFF, MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_LAND):
            assert it["frame"] == 3 and it["AltitudeMode"] == 1 and it["AMSLAltAboveTerrain"] is None
            assert it["Altitude"] == it["params"][6]
        else:
            assert it["frame"] == 2 and "Altitude" not in it
    assert m["items"][0]["command"] == MAV_CMD_NAV_TAKEOFF
    assert m["items"][-1]["command"] == MAV_CMD_NAV_LAND  # the flight lands at home
    assert m["items"][-1]["params"][4:6] == [home.latitude_deg, home.longitude_deg]
    # reserved parameters of the capture command are 0, not null (issue 11)
    cap = [it for it in m["items"] if it["command"] == MAV_CMD_IMAGE_START_CAPTURE]
    assert cap and all(it["params"][4:7] == [0, 0, 0] for it in cap)


def test_qgc_schema_rejects_what_qgc_rejects(plan):
    schema = load_qgc_plan_schema()
    good = qgc_plan_document(plan)
    for mutate in (
        lambda d: d["mission"]["items"][0]["params"].pop(),  # params must hold 7 values
        lambda d: d["mission"]["items"][0]["params"].__setitem__(0, "15"),  # number or null
        lambda d: d["mission"]["plannedHomePosition"].pop(),  # lat, lon, alt
        lambda d: d.__setitem__("fileType", "Mission"),
        lambda d: d.pop("rallyPoints"),
        lambda d: d["mission"]["items"][0].pop("AltitudeMode"),  # all three altitude keys or none
        lambda d: d["mission"]["items"][1].__setitem__("autoContinue", 1),
    ):
        doc = json.loads(json.dumps(good))
        mutate(doc)
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(doc, schema, cls=jsonschema.Draft202012Validator)


def test_do_jump_ids_unique_and_increasing(plan):
    items = qgc_plan_document(plan)["mission"]["items"]
    ids = [it["doJumpId"] for it in items]
    assert ids == list(range(1, len(items) + 1))


def test_one_navigation_waypoint_per_flight_waypoint_with_relative_altitudes(plan):
    items = qgc_plan_document(plan)["mission"]["items"]
    navs = [it for it in items if it["command"] == MAV_CMD_NAV_WAYPOINT]
    wps = _flown(plan)
    assert len(navs) == len(wps)
    for it, w in zip(navs, wps, strict=True):
        assert it["params"][4:6] == [w.latitude_deg, w.longitude_deg]
        assert it["params"][6] == pytest.approx(w.height_m - plan.home.height_m, abs=1e-9)
        assert it["params"][6] == pytest.approx(w.z_m - plan.home.z_m, abs=0.01)  # flat-earth sanity check
        assert it["params"][3] == w.heading_deg  # PX4 flies the waypoint yaw
    takeoff = items[0]
    start = plan.flights[0].waypoints[0]
    assert takeoff["params"][4:7] == [start.latitude_deg, start.longitude_deg,
                                      pytest.approx(wps[0].height_m - plan.home.height_m)]
    assert takeoff["params"][3] == wps[0].heading_deg  # face the first waypoint's heading


def test_attitude_is_commanded_on_the_leg_before_and_the_photo_first_after_its_waypoint(plan):
    items = qgc_plan_document(plan)["mission"]["items"]
    groups = _groups(items)  # [(TAKEOFF, leg to wp 1), (wp 1, leg to wp 2), ...]
    wps = _flown(plan)
    assert [g[0]["command"] for g in groups] == [MAV_CMD_NAV_TAKEOFF] + [MAV_CMD_NAV_WAYPOINT] * len(wps) \
        + [MAV_CMD_NAV_LAND]
    seq = 0
    pitch = None
    for k, w in enumerate(wps):
        before = groups[k][1]  # the DO items after the previous navigation item: they prepare the leg to w
        cmds = [d["command"] for d in before]
        # the heading of w is commanded last on the leg to w (CONDITION_YAW holds back what follows it)
        assert cmds[-1] == MAV_CMD_CONDITION_YAW and before[-1]["params"][:4] == [w.heading_deg, 30, 0, 0]
        gimbal = [d for d in before if d["command"] == MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW]
        if pitch is None or w.gimbal_pitch_deg != pitch:
            assert len(gimbal) == 1 and gimbal[0]["params"][0] == w.gimbal_pitch_deg
            assert gimbal[0]["params"][1] == 0 and gimbal[0]["params"][2:4] == [None, None]
            assert gimbal[0]["params"][4] == 12  # ROLL_LOCK | PITCH_LOCK: pitch relative to the horizon
        else:
            assert not gimbal  # the gimbal holds its pitch
        pitch = w.gimbal_pitch_deg
        after = groups[k + 1]
        captures = [d for d in after[1] if d["command"] in CAPTURE_COMMANDS]
        assert len(captures) == (1 if w.capture else 0)
        if w.capture:
            seq += 1
            assert after[1][0]["command"] == MAV_CMD_IMAGE_START_CAPTURE  # first: nothing can hold it back
            assert captures[0]["params"] == [0, 0, 1, seq, 0, 0, 0]  # all cameras, one image, sequence, reserved 0
            assert after[0]["params"][0] == 2.0  # a 2 s hold stops the drone on the point
        else:
            assert after[0]["params"][0] == 0
    # speed changes come before the waypoint they apply to, in the group that prepares its leg
    speeds = [(k, it["params"][1]) for k, it in enumerate(items) if it["command"] == MAV_CMD_DO_CHANGE_SPEED]
    assert speeds and all(items[k - 1]["command"] in NAV | CAPTURE_COMMANDS for k, _ in speeds)


def test_mission_options(plan):
    px4 = qgc_plan_document(plan, autopilot="px4", mount_control=True, camera="digicam", capture_hold_s=1.5,
                            altitude_frame="amsl", end="land")
    jsonschema.validate(px4, load_qgc_plan_schema(), cls=jsonschema.Draft202012Validator)
    m = px4["mission"]
    assert m["firmwareType"] == 12 and m["globalPlanAltitudeMode"] == 2
    cmds = [it["command"] for it in m["items"]]
    assert MAV_CMD_CONDITION_YAW not in cmds and MAV_CMD_IMAGE_START_CAPTURE not in cmds
    assert cmds.count(MAV_CMD_DO_DIGICAM_CONTROL) == 9
    assert cmds.count(MAV_CMD_DO_MOUNT_CONTROL) == cmds.count(MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW)
    assert cmds[-1] == MAV_CMD_NAV_LAND
    mounts = [it for it in m["items"] if it["command"] == MAV_CMD_DO_MOUNT_CONTROL]
    gimbals = [it for it in m["items"] if it["command"] == MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW]
    assert [it["params"][0] for it in mounts] == [it["params"][0] for it in gimbals]
    assert all(it["params"][6] == 2 for it in mounts)  # MAV_MOUNT_MODE_MAVLINK_TARGETING
    for it, w in zip([it for it in m["items"] if it["command"] == MAV_CMD_NAV_WAYPOINT], _flown(plan), strict=True):
        assert it["frame"] == 0 and it["AltitudeMode"] == 2
        assert it["params"][6] == pytest.approx(w.height_m - GEOID_NSTTF)  # metres above mean sea level
        assert it["params"][0] == (1.5 if w.capture else 0)
    digicam = next(it for it in m["items"] if it["command"] == MAV_CMD_DO_DIGICAM_CONTROL)
    assert digicam["params"][4] == 1  # shoot
    with pytest.raises(PihimInputError, match="yaw_rate_deg_s"):
        qgc_plan_document(plan, yaw_rate_deg_s=0)


def test_legs_are_slowed_where_the_turn_needs_it(plan):
    # a 90 deg turn over 10 m at 5 m/s (2 s) needs 3 s + 0.5 s settle at 30 deg/s: 10 / 3.5 m/s
    a = _wp(0.0, 0.0, 30.0, 0.0, -30.0, speed=5.0)
    b = _wp(0.0, 10.0, 30.0, 90.0, -30.0, speed=5.0, capture=True)
    assert leg_speed(a, b) == pytest.approx(10.0 / 3.5)
    assert leg_speed(a, replace(b, heading_deg=5.0)) == 5.0  # 0.67 s needed, 2 s available
    assert leg_speed(a, replace(b, heading_deg=350.0, gimbal_pitch_deg=-90.0)) == pytest.approx(10.0 / 2.5)
    assert leg_speed(a, b, yaw_rate_deg_s=90.0) == 5.0


def test_flight_export_uses_the_flight_waypoints(plan):
    items = qgc_plan_document(plan, flight=0)["mission"]["items"]
    assert items == qgc_plan_document(plan)["mission"]["items"]  # the plan's only flight is the default
    f = plan.flights[0]
    assert items[0]["command"] == MAV_CMD_NAV_TAKEOFF and items[-1]["command"] == MAV_CMD_NAV_LAND
    assert items[0]["params"][4:6] == [f.waypoints[0].latitude_deg, f.waypoints[0].longitude_deg]
    assert items[0]["params"][6] == pytest.approx(35.0, abs=0.01)  # climbs to the first transit waypoint
    assert items[0]["params"][3] == 45.0  # facing the first transit heading
    assert sum(it["command"] == MAV_CMD_NAV_WAYPOINT for it in items) == len(f.waypoints) - 2
    assert MAV_CMD_NAV_RETURN_TO_LAUNCH not in [it["command"] for it in items]
    with pytest.raises(PihimInputError, match="no flight with index 3"):
        mission_items(plan, flight=3)


# --------------------------------------------------------------------------- QGC WPL 110


def _parse_wpl(text: str) -> list[dict]:
    lines = text.split("\n")
    assert lines[0] == "QGC WPL 110" and lines[-1] == ""
    rows = []
    for line in lines[1:-1]:
        cells = line.split("\t")
        assert len(cells) == 12, line
        rows.append({"index": int(cells[0]), "current": int(cells[1]), "frame": int(cells[2]),
                     "command": int(cells[3]), "params": [float(c) for c in cells[4:11]],
                     "autocontinue": int(cells[11]), "text": cells})
    return rows


def test_wpl_round_trip(plan, tmp_path):
    path = write_wpl(plan, tmp_path / "mission.waypoints")
    rows = _parse_wpl(path.read_text())
    items = qgc_plan_document(plan)["mission"]["items"]
    assert len(rows) == len(items) + 1
    assert [r["index"] for r in rows] == list(range(len(rows)))
    home = rows[0]
    assert (home["current"], home["frame"], home["command"]) == (1, 0, MAV_CMD_NAV_WAYPOINT)
    assert home["params"][4] == pytest.approx(plan.home.latitude_deg, abs=1e-8)
    assert home["params"][5] == pytest.approx(plan.home.longitude_deg, abs=1e-8)
    assert home["params"][6] == pytest.approx(plan.home.height_m - GEOID_NSTTF, abs=1e-6)
    for r, it in zip(rows[1:], items, strict=True):
        assert (r["current"], r["frame"], r["command"], r["autocontinue"]) == (0, it["frame"], it["command"], 1)
        expected = [0.0 if v is None else v for v in it["params"]]  # NaN (null) is 0 in the text file
        assert r["params"] == pytest.approx(expected, abs=1e-8)
    navs = [r for r in rows if r["command"] == MAV_CMD_NAV_WAYPOINT and r["index"] > 0]
    for r, w in zip(navs, _flown(plan), strict=True):
        assert abs(r["params"][4] - w.latitude_deg) <= 1e-8 and abs(r["params"][5] - w.longitude_deg) <= 1e-8
        assert len(r["text"][8].split(".")[1]) >= 8 and len(r["text"][9].split(".")[1]) >= 8
    assert sum(r["command"] == MAV_CMD_IMAGE_START_CAPTURE for r in rows) == 9


def test_wpl_cells_write_zero_as_0_and_keep_8_or_10_decimals():
    """Zero, negative zero, values that print as zero and NaN are "0"; other numbers keep 8 decimals (10 for the
    latitude and longitude of an item with a position), the sign and the digits."""
    from pihim.planning.export.qgc import MAV_FRAME_GLOBAL_RELATIVE_ALT, Mission, MissionItem
    from pihim.planning.export.wpl import wpl_mission_text

    params = (0.0, -0.0, 4e-9, math.nan, 34.9622760001, -106.50960600004, -3e-9)
    items = (MissionItem(MAV_CMD_NAV_WAYPOINT, MAV_FRAME_GLOBAL_RELATIVE_ALT, params),
             MissionItem(MAV_CMD_CONDITION_YAW, MAV_FRAME_GLOBAL_RELATIVE_ALT, (-90.5, 30.0, -1.0, 0.0, 0.0, 0.0,
                                                                                -0.00000001)))
    mission = Mission(items=items, home=(34.96, -106.5, 1650.0), altitude_frame=MAV_FRAME_GLOBAL_RELATIVE_ALT,
                      firmware_type=3, hover_speed_m_s=2.0, cruise_speed_m_s=5.0, geoid_undulation_m=-21.7)
    rows = _parse_wpl(wpl_mission_text(mission))
    assert rows[1]["text"][4:11] == ["0", "0", "0", "0", "34.9622760001", "-106.5096060000", "0"]
    assert rows[2]["text"][4:11] == ["-90.50000000", "30.00000000", "-1.00000000", "0", "0", "0", "-0.00000001"]
    assert rows[0]["text"][4:11] == ["0", "0", "0", "0", "34.9600000000", "-106.5000000000", "1650.00000000"]


def test_wpl_takes_the_mission_options(plan, tmp_path):
    rows = _parse_wpl(write_wpl(plan, tmp_path / "m.waypoints", autopilot="px4", flight=0).read_text())
    cmds = [r["command"] for r in rows]
    assert MAV_CMD_CONDITION_YAW not in cmds and cmds[1] == MAV_CMD_NAV_TAKEOFF and cmds[-1] == MAV_CMD_NAV_LAND


# --------------------------------------------------------------------------- KML


def _q(tag: str) -> str:
    return f"{{{KML_NS}}}{tag}"


def test_kml_well_formed_with_expected_placemarks(plan, field, tmp_path):
    path = write_kml(plan, tmp_path / "plan.kml", field=field)
    root = ET.parse(path).getroot()
    assert root.tag == _q("kml")
    doc = root.find(_q("Document"))
    folders = doc.findall(_q("Folder"))
    pass_folders = [f for f in folders if f.findtext(_q("name")).startswith("Pass ")]
    assert len(pass_folders) == 3
    n_capture = sum(w.capture for w in _all_wps(plan))
    placemarks = root.findall(f".//{_q('Placemark')}")
    # home + one line per pass + capture waypoints + flights + heliostats + tower
    assert len(placemarks) == 1 + 3 + n_capture + 1 + len(field) + 1
    for folder, p in zip(pass_folders, plan.passes, strict=True):
        line = folder.find(f".//{_q('LineString')}")
        assert line.findtext(_q("altitudeMode")) == "relativeToGround"
        coords = [tuple(map(float, c.split(","))) for c in line.findtext(_q("coordinates")).split()]
        assert len(coords) == len(p.waypoints)
        for (lon, lat, alt), w in zip(coords, p.waypoints, strict=True):
            assert abs(lon - w.longitude_deg) < 1e-8 and abs(lat - w.latitude_deg) < 1e-8
            assert alt == pytest.approx(w.z_m, abs=1e-3)
        points = folder.findall(f"{_q('Placemark')}/{_q('Point')}")
        assert len(points) == sum(w.capture for w in p.waypoints)
    first_capture = pass_folders[0].findall(_q("Placemark"))[1]
    desc = first_capture.findtext(_q("description"))
    assert "heading 0.00 deg" in desc and "gimbal pitch -28.00 deg" in desc and "HUA 5E3" in desc
    names = [pm.findtext(_q("name")) for pm in placemarks]
    assert "5E1" in names and "Tower" in names


def test_kml_absolute_altitudes_use_the_geoid(plan, tmp_path):
    root = ET.parse(write_kml(plan, tmp_path / "a.kml", altitude_mode="absolute", geoid_undulation_m=-21.5)).getroot()
    line = root.find(f".//{_q('LineString')}")
    assert line.findtext(_q("altitudeMode")) == "absolute"
    alt = float(line.findtext(_q("coordinates")).split()[0].split(",")[2])
    assert alt == pytest.approx(plan.passes[0].waypoints[0].height_m + 21.5, abs=1e-3)
    # no field: only home, pass lines, captures and flights
    assert len(root.findall(f".//{_q('Placemark')}")) == 1 + 3 + 9 + 1


def test_kml_stream_writes_what_elementtree_writes_for_the_same_tree():
    """The streaming writer against ElementTree's indent + tostring, the same calls on both: nesting that returns
    to ancestors, elements left empty, empty text, attributes and text with characters to escape, numbers."""
    from pihim.planning.export.kml import _Stream

    def build(sub, root):
        doc = sub(root, "Document", id='a&b<"c">\n\t\r')
        sub(doc, "name", "x & y < z > w \"quoted\" 'single'\nsecond line")
        sub(doc, "open", 1)
        sub(doc, "empty")
        sub(doc, "blank", "")
        folder = sub(doc, "Folder")
        pm = sub(folder, "Placemark")
        sub(sub(sub(pm, "Style"), "IconStyle"), "heading", 12.5)
        pt = sub(pm, "Point")
        sub(pt, "coordinates", "1,2,3 4,5,6")
        sub(folder, "Placemark")  # back up two levels, then an element that stays empty
        sub(doc, "Style", id="tower")

    def et_sub(parent, tag, text=None, **attrib):
        el = ET.SubElement(parent, tag, attrib)
        if text is not None:
            el.text = str(text)
        return el

    root = ET.Element("kml", {"xmlns": KML_NS})
    build(et_sub, root)
    stream = _Stream("kml", {"xmlns": KML_NS})
    build(stream.sub, stream.root)
    assert stream.text() == _elementtree_text(root)
    for chunk_lines in (1, 2, 3, 100):  # the same lines, passed to a sink in pieces
        pieces = []
        sunk = _Stream("kml", {"xmlns": KML_NS}, pieces.append, chunk_lines=chunk_lines)
        build(sunk.sub, sunk.root)
        sunk.finish()
        assert "".join(pieces) == stream.text() and (len(pieces) > 5 or chunk_lines == 100)
    leaf_first = _Stream("kml", {})
    leaf = leaf_first.sub(leaf_first.root, "name", "text")
    with pytest.raises(ValueError, match="closed or holds text"):
        leaf_first.sub(leaf, "child")


def test_kml_is_the_same_text_written_whole_or_in_pieces(plan, field, monkeypatch):
    from pihim.planning.export import kml

    text = kml_text(plan, field=field)
    monkeypatch.setattr(kml._Stream.__init__, "__defaults__", (None, 4))  # a piece every 4 lines
    pieces: list[str] = []
    write_kml_text(plan, pieces.append, field=field)
    assert "".join(pieces) == text and len(pieces) > 10 and text.endswith("</kml>\n")
    pieces.clear()
    with pytest.raises(PihimInputError, match="altitude_mode"):  # checked before the first piece
        write_kml_text(plan, pieces.append, altitude_mode="above")
    assert pieces == []


def _elementtree_text(root):
    ET.indent(root, space=" ")
    return ET.tostring(root, encoding="unicode")


# --------------------------------------------------------------------------- Litchi


def test_litchi_csv_header_and_rows(plan, tmp_path):
    path = write_litchi_csv(plan, tmp_path / "litchi.csv")
    text = path.read_text()
    assert text.split("\n")[0] == LITCHI_HEADER_TEXT == ",".join(LITCHI_HEADER)
    rows = list(csv.DictReader(text.splitlines()))
    wps = _flown(plan)  # the plan's only flight, without take-off and landing (Litchi's own)
    assert len(rows) == len(wps)
    for r, w in zip(rows, wps, strict=True):
        assert float(r["latitude"]) == pytest.approx(w.latitude_deg, abs=1e-8)
        assert float(r["longitude"]) == pytest.approx(w.longitude_deg, abs=1e-8)
        assert float(r["altitude(m)"]) == pytest.approx(w.height_m - plan.home.height_m, abs=1e-3)
        assert float(r["heading(deg)"]) == pytest.approx(w.heading_deg, abs=1e-3)
        assert float(r["gimbalpitchangle"]) == pytest.approx(w.gimbal_pitch_deg, abs=1e-3)
        assert (r["gimbalmode"], r["altitudemode"], r["curvesize(m)"]) == ("2", "0", "0")
        assert float(r["speed(m/s)"]) == pytest.approx(w.speed_m_s, abs=0.005)
        assert r["actiontype1"] == ("1" if w.capture else "-1")
        assert all(r[f"actiontype{k}"] == "-1" for k in range(2, 16))
        assert (r["photo_timeinterval"], r["photo_distinterval"]) == ("-1", "-1")


def test_litchi_options_and_limits(plan):
    rows = list(csv.DictReader(litchi_csv_text(plan, hover_ms=800).splitlines()))
    cap = next(r for r in rows if r["actiontype1"] != "-1")
    assert (cap["actiontype1"], cap["actionparam1"], cap["actiontype2"]) == ("0", "800", "1")
    flight_rows = list(csv.DictReader(litchi_csv_text(plan, flight=0).splitlines()))
    assert len(flight_rows) == len(plan.flights[0].waypoints) - 2  # no take-off, no landing
    with pytest.raises(PihimInputError, match="exceed Litchi's limit of 10"):
        litchi_csv_text(plan, max_waypoints=10)


def test_litchi_missions_cut_flights_at_pass_boundaries(plan):
    per_flight = [litchi_waypoints(plan, f.index) for f in plan.flights]
    assert sum(len(w) for w in per_flight) > 12
    for limit in (7, 12, 99):
        missions = litchi_missions(plan, max_waypoints=limit)
        assert all(0 < len(m) <= limit for m in missions)
        # concatenated, the missions are the flights' Litchi waypoints, in order
        assert [w for m in missions for w in m] == [w for f in per_flight for w in f]
        # no mission spans two flights; each starts a flight, a pass's lead-in or a transit
        starts = {id(f[0]) for f in per_flight}
        for m in missions:
            owner = {k for k, f in enumerate(per_flight) for w in m if any(w is x for x in f)}
            assert len(owner) == 1
            longest_pass = max(len(p.waypoints) for p in plan.passes)
            if longest_pass <= limit:
                assert id(m[0]) in starts or m[0].kind in ("lead_in", "transit")
    assert len(litchi_missions(plan, max_waypoints=99)) == len(plan.flights)  # small plan: one per flight
    texts = litchi_mission_texts(plan, max_waypoints=7)
    assert len(texts) == len(litchi_missions(plan, max_waypoints=7))
    assert all(len(list(csv.DictReader(t.splitlines()))) <= 7 for t in texts)
    with pytest.raises(PihimInputError, match="max_waypoints"):
        litchi_missions(plan, max_waypoints=0)


# --------------------------------------------------------------------------- map


def _png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def test_plan_figure_png(plan, field, tmp_path):
    path = write_plan_figure(plan, tmp_path / "plan.png", field=field)
    data = path.read_bytes()
    assert len(data) > 10_000
    assert _png_size(data) == (1200, 960)
    small = write_plan_figure(plan, tmp_path / "small.png", figsize=(4, 3), dpi=50).read_bytes()
    assert _png_size(small) == (200, 150)


def test_plan_figure_pass_labels_never_overlap_when_drawn(monkeypatch):
    """Twelve passes starting 2-4 m apart: each pass number is moved to a free spot. The spots are chosen before
    the figure is drawn (limits and aspect fixed without a draw) at the scale the drawn figure has; the label
    boxes matplotlib draws overlap none of the others, and each stays within 25 m of its pass start."""
    import dataclasses

    import pihim.planning.export.figure as figure_module
    from pihim.planning.export.figure import plan_figure

    def metres_per_pixel(ax):
        inv = ax.transData.inverted()
        return np.abs(inv.transform((1.0, 1.0)) - inv.transform((0.0, 0.0)))

    seen, place = [], figure_module._place_pass_labels

    def spy(fig, ax, starts, *args, **kwargs):
        place(fig, ax, starts, *args, **kwargs)
        seen.append(metres_per_pixel(ax))  # the scale the spots were chosen at (placing does not draw)

    monkeypatch.setattr(figure_module, "_place_pass_labels", spy)

    base = make_plan(with_flight=False)
    passes = tuple(_pass(k, 30.0 + 2.0 * k + (k % 3), 35.0, k % 2 == 0, -30.0, ("5E3", "6E3", "7E3"),
                         ("5E2", "6E2", "7E2")) for k in range(12))
    plan = dataclasses.replace(base, passes=passes)
    fig = plan_figure(plan, field=make_field())
    fig.canvas.draw()
    ax = fig.axes[0]
    np.testing.assert_allclose(seen[0], metres_per_pixel(ax), rtol=1e-9)
    labels = {int(t.get_text()): t for t in ax.texts if (t.get_gid() or "").startswith("pass-label-")}
    assert sorted(labels) == list(range(12))
    renderer = fig.canvas.get_renderer()
    boxes = {k: t.get_bbox_patch().get_window_extent(renderer) for k, t in labels.items()}
    for i, a in boxes.items():
        for j, b in boxes.items():
            assert i == j or not a.overlaps(b), (a, b)
    starts = {p.index: np.array([p.waypoints[0].x_m, p.waypoints[0].y_m]) for p in plan.passes}
    for k, t in labels.items():
        assert np.hypot(*(np.asarray(t.get_position()) - starts[k])) < 25.0
    # each leader runs from a pass start to the edge of that pass's label box (drawn, within 2 pixels)
    (leaders,) = [c for c in ax.collections if c.get_gid() == "pass-leaders"]
    assert len(leaders.get_segments()) >= 6  # most of the twelve labels had to move
    for start, end in leaders.get_segments():
        (k,) = [k for k, s in starts.items() if np.allclose(s, start)]
        box, (x, y) = boxes[k], ax.transData.transform(end)
        outside = max(box.x0 - x, x - box.x1, box.y0 - y, y - box.y1)  # > 0 outside, < 0 inside the box
        assert abs(outside) <= 2.0, (k, outside)


def test_plan_figure_arrowheads_point_the_way_each_pass_is_flown(plan, field):
    """One filled triangle per pass, in points at the pass's last waypoint: its tip on the last leg, held back as
    matplotlib holds back a ``-|>`` arrow's, its base behind and symmetric about the leg (a pass flown the other way
    points the other way); the same size in points when the figure is drawn at another size."""
    import dataclasses
    import math

    from pihim.planning.export import figure as figure_module

    flipped = dataclasses.replace(plan, passes=tuple(
        dataclasses.replace(p, waypoints=tuple(reversed(p.waypoints))) for p in plan.passes))
    shrink = 2.0 + 0.75 / math.sin(math.atan(0.5))  # shrinkB plus the mitre of a 1.5-point stroke
    for each, size in ((plan, None), (flipped, None), (plan, (5.0, 4.0))):
        fig = figure_module.plan_figure(each, field=field)
        if size is not None:
            fig.set_size_inches(*size)
        fig.canvas.draw()
        ax = fig.axes[0]
        (heads,) = [c for c in ax.collections if c.get_gid() == "pass-arrowheads"]
        offsets = heads.get_offset_transform().transform(heads.get_offsets())
        triangles = [heads.get_transform().transform(path.vertices[:3]) + offset
                     for path, offset in zip(heads.get_paths(), offsets, strict=True)]
        assert len(triangles) == len(each.passes)
        pt = fig.dpi / 72.0
        for p, tri in zip(each.passes, triangles, strict=True):
            before, end = (ax.transData.transform((w.x_m, w.y_m)) for w in p.waypoints[-2:])
            d = (end - before) / np.linalg.norm(end - before)
            ahead, across = (tri - end) @ d / pt, (tri - end) @ np.array([-d[1], d[0]]) / pt  # points
            np.testing.assert_allclose(ahead, [-shrink, -shrink - 5.6, -shrink - 5.6], atol=0.05)
            np.testing.assert_allclose(np.sort(across), [-2.8, 0.0, 2.8], atol=0.05)
            assert abs(across[0]) < 0.05  # the tip on the leg


def test_plan_figure_of_a_large_plan_leaves_out_numbers_and_lists_flights_in_one_entry(monkeypatch):
    """Above MAX_LABELLED_PASSES passes no pass numbers, arrowheads or image marks are drawn (the title says so),
    and above MAX_LEGEND_FLIGHTS flights the legend holds one entry with their count and totals; at the limits
    (lowered here to 3 passes and 1 flight) the small plan's figure keeps all of them."""
    import pihim.planning.export.figure as figure_module
    from pihim.planning.export.figure import plan_figure

    base = make_plan()
    f0 = base.flights[0]
    two = replace(base, flights=(f0, replace(f0, index=1, duration_s=300.0, distance_m=550.0)))

    def drawn(plan):
        ax = plan_figure(plan, field=make_field()).axes[0]
        numbers = sorted(int(t.get_text()) for t in ax.texts if t.get_text().isdigit())
        arrows = [path for c in ax.collections if c.get_gid() == "pass-arrowheads" for path in c.get_paths()]
        marks = sum(len(c.get_offsets()) for c in ax.collections if c.get_label() != "heliostats"
                    and hasattr(c, "get_sizes") and len(c.get_sizes()) and c.get_sizes()[0] == 14)
        legend = [t.get_text() for t in ax.get_legend().get_texts()]
        return numbers, len(arrows), marks, legend, ax.get_title()

    monkeypatch.setattr(figure_module, "MAX_LABELLED_PASSES", 3)
    monkeypatch.setattr(figure_module, "MAX_LEGEND_FLIGHTS", 2)
    numbers, arrows, marks, legend, title = drawn(two)
    assert numbers == [0, 1, 2] and arrows == 3 and marks == 9
    assert "flight 1: 10.2 min, 1.45 km" in legend and "flight 2: 5.0 min, 0.55 km" in legend
    assert "no pass numbers" not in title
    monkeypatch.setattr(figure_module, "MAX_LABELLED_PASSES", 2)
    monkeypatch.setattr(figure_module, "MAX_LEGEND_FLIGHTS", 1)
    numbers, arrows, marks, legend, title = drawn(two)
    assert numbers == [] and arrows == 0 and marks == 0
    assert "2 flights: 15 min, 2.0 km in all" in legend and not any(t.startswith("flight ") for t in legend)
    assert "over 2 passes: no pass numbers, arrows, image marks" in title


# --------------------------------------------------------------------------- export_all and bad input


def test_export_all_one_flight_writes_the_flight_and_the_whole_field_files(plan, field, tmp_path):
    out = export_all(plan, tmp_path / "out", field=field, geofence_margin_m=20.0)
    per_flight = {"flight_01_plan": "flight_01.plan", "flight_01_waypoints": "flight_01.waypoints",
                  "flight_01_litchi": "flight_01_litchi.csv"}
    assert set(out) == set(OUTPUT_NAMES) | set(per_flight)
    for key, path in out.items():
        assert path == tmp_path / "out" / {**OUTPUT_NAMES, **per_flight}[key] and path.stat().st_size > 0
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(out[k].name for k in out)  # no temporaries
    # one flight covers the plan: the whole-field files are that flight
    assert out["qgc_plan"].read_text() == out["flight_01_plan"].read_text()
    assert out["wpl"].read_text() == out["flight_01_waypoints"].read_text()
    assert out["litchi"].read_text() == out["flight_01_litchi"].read_text()
    jsonschema.validate(json.loads(out["qgc_plan"].read_text()), load_qgc_plan_schema(),
                        cls=jsonschema.Draft202012Validator)
    jsonschema.validate(json.loads(out["plan_json"].read_text()), load_plan_schema(),
                        cls=jsonschema.Draft202012Validator)


def _several_flights(plan: Plan) -> Plan:
    home = plan.home
    flights = split_flights(plan.passes, home, origin=ORIGIN, model=DroneEndurance(battery_min=3.0),
                            include_infeasible=True)
    assert len(flights) == 3
    return replace(plan, flights=flights)


def test_export_all_several_flights_one_mission_each(plan, field, tmp_path):
    multi = _several_flights(plan)
    out = export_all(multi, tmp_path / "out", field=field)
    assert not {"qgc_plan", "wpl", "litchi"} & set(out)  # no whole-field mission a vehicle could not fly
    assert not (tmp_path / "out" / "mission.plan").exists() and not (tmp_path / "out" / "litchi.csv").exists()
    for f in multi.flights:
        stem = flight_file_stem(f.index)
        doc = json.loads(out[f"{stem}_plan"].read_text())
        jsonschema.validate(doc, load_qgc_plan_schema(), cls=jsonschema.Draft202012Validator)
        items = doc["mission"]["items"]
        assert items[0]["command"] == MAV_CMD_NAV_TAKEOFF and items[-1]["command"] == MAV_CMD_NAV_LAND
        assert items[-1]["params"][4:6] == [plan.home.latitude_deg, plan.home.longitude_deg]  # back home
        captures = [it for it in items if it["command"] == MAV_CMD_IMAGE_START_CAPTURE]
        assert len(captures) == sum(w.capture for w in f.waypoints)
        rows = _parse_wpl(out[f"{stem}_waypoints"].read_text())
        assert len(rows) == len(items) + 1
        litchi = list(csv.DictReader(out[f"{stem}_litchi"].read_text().splitlines()))
        assert len(litchi) == len(f.waypoints) - 2
    with pytest.raises(PihimInputError, match="needs 3 flights"):
        qgc_plan_document(multi)
    with pytest.raises(PihimInputError, match="needs 3 flights"):
        litchi_csv_text(multi)
    one = export_all(multi, tmp_path / "one", flight=1)
    assert sorted(k for k in one if k.startswith("flight")) == ["flight_02_litchi", "flight_02_plan",
                                                               "flight_02_waypoints"]


def test_mission_item_limit(plan, tmp_path):
    multi = _several_flights(plan)
    n = max(count_mission_items(f.waypoints) for f in multi.flights)
    assert n == max(len(qgc_plan_document(multi, flight=f.index)["mission"]["items"]) + 1 for f in multi.flights)
    with pytest.raises(PihimInputError, match=f"needs {n} mission items, more than the limit of {n - 1}"):
        export_all(multi, tmp_path / "out", max_mission_items=n - 1)
    assert not (tmp_path / "out").exists()
    # the flight split closes flights before they exceed the limit
    small = split_flights(plan.passes, plan.home, origin=ORIGIN, include_infeasible=True, max_mission_items=40,
                          count_items=count_mission_items)
    assert len(small) > 1 and all(count_mission_items(f.waypoints) <= 40 for f in small)
    with pytest.raises(PihimInputError, match="mission items, more than 10"):
        split_flights(plan.passes, plan.home, origin=ORIGIN, max_mission_items=10, count_items=count_mission_items)


def test_flight_split_counting_in_pieces_is_counting_whole(plan):
    """split_flights counts a MissionItemCounter's flights on from the flight one pass shorter: the same flights
    as counting each whole, where the flight grows (passes at one altitude), where a higher pass rebuilds it,
    and with a pass out of reach; a subclass that counts otherwise is called whole."""
    def row(altitude):
        return [_pass(k, 20.0 + 4.0 * k, altitude(k), k % 2 == 0, -25.0 - k, (f"{k}A", f"{k}B", f"{k}C"),
                      ("1E1", "1E2", "1E3")) for k in range(12)]

    level = row(lambda k: 40.0 - 0.5 * (k % 3))
    rising = row(lambda k: 30.0 + 2.0 * k if k % 4 else 60.0 - k)
    far = [*level[:5], replace(_pass(5, 6000.0, 40.0, True, -30.0, ("FA", "FB", "FC"), ("1E1", "1E2", "1E3")),
                               feasible=True), *level[6:]]
    for passes, caps in ((level, (60, 95, 200)), (rising, (60, 95, 200)), (far, (95,))):
        for cap in caps:
            kw = dict(origin=ORIGIN, include_infeasible=True, max_mission_items=cap)
            lost: list[int] = []
            whole = split_flights(passes, plan.home, count_items=count_mission_items, unflyable=lost, **kw)
            assert len(whole) > 1 and max(count_mission_items(f.waypoints) for f in whole) > cap - 25  # binds
            lost2: list[int] = []
            assert split_flights(passes, plan.home, count_items=MissionItemCounter(), unflyable=lost2, **kw) == whole
            assert lost2 == lost and lost == ([5] if passes is far else [])
    with pytest.raises(PihimInputError, match="mission items, more than 10"):
        split_flights(plan.passes, plan.home, origin=ORIGIN, max_mission_items=10, count_items=MissionItemCounter())

    class Padded(MissionItemCounter):
        def __call__(self, waypoints):
            return super().__call__(waypoints) + 20

    padded = split_flights(level, plan.home, origin=ORIGIN, include_infeasible=True, max_mission_items=120,
                           count_items=Padded())
    assert max(Padded()(f.waypoints) for f in padded) <= 120 < max(Padded()(f.waypoints) for f in split_flights(
        level, plan.home, origin=ORIGIN, include_infeasible=True, max_mission_items=120, count_items=MissionItemCounter()))


def test_mission_item_counter_options():
    with pytest.raises(PihimInputError, match="autopilot"):
        MissionItemCounter(autopilot="inav")
    with pytest.raises(PihimInputError, match="unknown mission option.*autopilt"):
        MissionItemCounter(autopilt="px4")
    assert repr(MissionItemCounter(autopilot="px4")) == "MissionItemCounter(autopilot='px4')"
    wps = make_plan().flights[0].waypoints
    assert MissionItemCounter(flight=0, altitude_frame="amsl")(wps) == count_mission_items(wps)


_KINDS = ("scan", "lead_in", "run_past", "transit", "return", "takeoff")


@settings(max_examples=300, deadline=None)
@given(steps=st.lists(st.tuples(st.sampled_from([0.0, 0.0, 1e-7, 0.3, 4.0, 25.0]),  # leg length, m
                                st.sampled_from([0.0, 0.0, 1e-10, 5.0, 90.0, 200.0, 359.0]),  # heading change
                                st.sampled_from([0.0, 0.0, 1e-7, 1e-5, 3.0, -40.0]),  # pitch change
                                st.sampled_from([0.0, 0.05, 2.0, 2.0 + 1e-10, 8.0]),  # speed
                                st.sampled_from(_KINDS), st.booleans()),
                      min_size=0, max_size=25),
       takeoff=st.booleans(), land_at=st.none() | st.integers(0, 30), cuts=st.lists(st.integers(1, 26), max_size=4),
       options=st.fixed_dictionaries({}, optional={
           "autopilot": st.sampled_from(["ardupilot", "px4"]), "condition_yaw": st.booleans(),
           "mount_control": st.booleans(), "speed_commands": st.booleans(), "end": st.sampled_from(["rtl", "land"]),
           "camera": st.sampled_from(["image_start_capture", "digicam"]),
           "yaw_rate_deg_s": st.sampled_from([5.0, 30.0]), "settle_s": st.sampled_from([0.0, 0.5])}))
def test_mission_item_count_is_the_built_items(steps, takeoff, land_at, cuts, options):
    """count_mission_items counts without building: it must equal the items mission export builds, for any
    sequence (turns, near-equal speeds and pitches at the tolerances, landings mid-way) and any options; and
    MissionItemCounter counting the same sequence in pieces (cut anywhere) must give the same count."""
    from pihim.planning.export.qgc import MAV_FRAME_GLOBAL_RELATIVE_ALT, _build_items, _options

    x = y = heading = pitch = 0.0
    wps = [Waypoint(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 10.0, 0.0, 0.0, "takeoff" if takeoff else "transit")]
    for k, (leg, turn, dp, speed, kind, capture) in enumerate(steps):
        heading, pitch = (heading + turn) % 360.0, pitch + dp
        x, y = x + leg * math.sin(math.radians(heading)), y + leg * math.cos(math.radians(heading))
        wps.append(Waypoint(x, y, 20.0, 0.0, 0.0, 0.0, heading, pitch, speed, "land" if k == land_at else kind,
                            capture and kind == "scan"))
    built = _build_items(wps, wps[0], lambda w: 0.0, MAV_FRAME_GLOBAL_RELATIVE_ALT, _options(**options))
    assert count_mission_items(wps, **options) == len(built) + 1
    counter = MissionItemCounter(**options)
    assert counter(wps) == len(built) + 1
    bounds = [0, *sorted(c for c in cuts if c <= len(wps)), len(wps)]  # empty pieces too
    state = None
    for a, b in itertools.pairwise(bounds):
        state = counter.resume(state, wps[a:b])
    assert counter.total(state) == len(built) + 1


def test_kml_is_valid_against_the_ogc_schema(plan, field, tmp_path):
    pytest.importorskip("fastkml")
    etree = pytest.importorskip("lxml.etree")
    from fastkml.validator import get_schema_parser

    schema = get_schema_parser()  # the OGC KML 2.2 XSD that fastkml ships
    for kwargs in ({"field": field}, {"altitude_mode": "absolute"}):
        doc = etree.parse(str(write_kml(plan, tmp_path / "plan.kml", **kwargs)))
        assert schema.validate(doc), "\n".join(str(e) for e in list(schema.error_log)[:5])
    # the schema has teeth: the order of the old writer (description after styleUrl) is refused
    bad = (tmp_path / "plan.kml").read_text()
    root = etree.fromstring(bad.encode())
    pm = root.find(f".//{{{KML_NS}}}Placemark")
    desc = pm.find(f"{{{KML_NS}}}description")
    pm.remove(desc)
    pm.append(desc)
    assert not schema.validate(root)


def test_waypoints_files_read_by_pymavlink(plan, tmp_path):
    mavwp = pytest.importorskip("pymavlink.mavwp")
    multi = _several_flights(plan)
    out = export_all(multi, tmp_path / "out")
    for f in multi.flights:
        stem = flight_file_stem(f.index)
        loader = mavwp.MAVWPLoader()
        n = loader.load(str(out[f"{stem}_waypoints"]))
        items = json.loads(out[f"{stem}_plan"].read_text())["mission"]["items"]
        assert n == loader.count() == len(items) + 1
        for k, it in enumerate(items, start=1):
            wp = loader.wp(k)
            assert (wp.seq, wp.command, wp.frame) == (k, it["command"], it["frame"])
            got = [wp.param1, wp.param2, wp.param3, wp.param4, wp.x, wp.y, wp.z]
            assert got == pytest.approx([0.0 if v is None else v for v in it["params"]], abs=1e-6)


def _nan_latitude_plan(plan: Plan, **change) -> Plan:
    p1 = plan.passes[1]
    wps = list(p1.waypoints)
    wps[2] = replace(wps[2], **(change or {"latitude_deg": math.nan}))
    return replace(plan, passes=(plan.passes[0], replace(p1, waypoints=tuple(wps)), plan.passes[2]))


WRITERS = [
    ("plan.json", write_plan_json),
    ("mission.plan", write_qgc_plan),
    ("mission.waypoints", write_wpl),
    ("plan.kml", write_kml),
    ("litchi.csv", write_litchi_csv),
    ("plan.png", write_plan_figure),
]


@pytest.mark.parametrize(("name", "writer"), WRITERS)
def test_bad_plans_raise_one_line_errors_and_write_nothing(plan, tmp_path, name, writer):
    for bad, pattern in ((replace(plan, passes=()), "no scan passes"),
                         (_nan_latitude_plan(plan), "pass 1 waypoint 2: latitude_deg is nan"),
                         # outside plan.schema.json's ranges: were written (a plan.json its own schema refuses)
                         (_nan_latitude_plan(plan, heading_deg=400.0), r"heading_deg 400.0 is outside \[0, 360\)"),
                         (_nan_latitude_plan(plan, heading_deg=-0.5), r"heading_deg -0.5 is outside \[0, 360\)"),
                         (_nan_latitude_plan(plan, gimbal_pitch_deg=-120.0), r"-120.0 is outside \[-90, 90\]"),
                         (replace(plan, passes=(replace(plan.passes[0], gimbal_pitch_deg=95.0), *plan.passes[1:])),
                          r"pass \d+ \(#0\): gimbal_pitch_deg 95.0 is outside")):
        with pytest.raises(PihimInputError, match=pattern) as exc:
            writer(bad, tmp_path / name)
        assert "\n" not in str(exc.value)
        assert list(tmp_path.iterdir()) == []


def test_a_heading_rounded_to_360_is_exported(plan, tmp_path):
    """(-1e-14) % 360.0 == 360.0: a planner heading of a hair below 0 must not make the plan unexportable."""
    assert -1e-14 % 360.0 == 360.0
    path = write_plan_json(_nan_latitude_plan(plan, heading_deg=360.0), tmp_path / "plan.json")
    doc = json.loads(path.read_text())
    jsonschema.validate(doc, load_plan_schema(), cls=jsonschema.Draft202012Validator)  # exclusiveMaximum 360
    assert 360.0 not in [w["heading_deg"] for p in doc["passes"] for w in p["waypoints"]]


def test_export_all_bad_plan_writes_nothing(plan, tmp_path):
    with pytest.raises(PihimInputError, match="latitude_deg"):
        export_all(_nan_latitude_plan(plan), tmp_path / "out")
    assert not (tmp_path / "out").exists() or list((tmp_path / "out").iterdir()) == []
    flight_wps = list(plan.flights[0].waypoints)
    flight_wps[1] = replace(flight_wps[1], heading_deg=math.inf)
    bad = replace(plan, flights=(replace(plan.flights[0], waypoints=tuple(flight_wps)),))
    with pytest.raises(PihimInputError, match="flight 0 waypoint 1: heading_deg"):
        export_all(bad, tmp_path / "out")


def test_a_checked_plan_is_remembered_by_identity_only(plan):
    from pihim.planning.export._common import _KNOWN, check_plan

    assert check_plan(plan) is plan and _KNOWN[id(plan)].checked  # export_all asks once per file
    bad = _nan_latitude_plan(plan)  # a new plan, equal but for one waypoint: checked in full
    with pytest.raises(PihimInputError, match="latitude_deg is nan"):
        check_plan(bad)
    assert id(bad) not in _KNOWN or not _KNOWN[id(bad)].checked


def test_the_plan_index_is_built_once_per_plan_and_dropped_with_it(plan):
    """Flights and passes by index (the first of each), the same dicts for the same plan object, fresh ones for
    another plan, and no entry left once a plan is gone; a flight lookup by index gives that flight's waypoints."""
    import gc

    from pihim.planning.export._common import _KNOWN, mission_waypoints, plan_index

    flights, passes = plan_index(plan)
    assert flights == {0: plan.flights[0]} and passes == {p.index: p for p in plan.passes}
    assert plan_index(plan)[0] is flights and plan_index(plan)[1] is passes
    twin = replace(plan, passes=(*plan.passes, replace(plan.passes[0], waypoints=plan.passes[1].waypoints)),
                   flights=(*plan.flights, replace(plan.flights[0], index=7, waypoints=plan.passes[2].waypoints)))
    f2, p2 = plan_index(twin)
    assert p2[plan.passes[0].index] is plan.passes[0]  # the first pass of a repeated index
    assert f2[7].waypoints == plan.passes[2].waypoints and mission_waypoints(twin, 7) == plan.passes[2].waypoints
    key = id(twin)
    del twin, f2, p2
    gc.collect()
    assert key not in _KNOWN  # the weak reference's callback removed it

def test_failed_write_keeps_the_previous_file(plan, tmp_path):
    path = write_qgc_plan(plan, tmp_path / "mission.plan")
    before = path.read_bytes()
    with pytest.raises(PihimInputError, match="autopilot"):
        write_qgc_plan(plan, path, autopilot="betaflight")
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["mission.plan"]


def test_geoid_undulation_needed_away_from_the_nsttf(plan, tmp_path):
    shift = 10.0  # degrees of longitude: far from the NSTTF
    moved = replace(plan, home=replace(plan.home, longitude_deg=plan.home.longitude_deg + shift), site={})
    with pytest.raises(PihimInputError, match="geoid_undulation_m"):
        write_qgc_plan(moved, tmp_path / "m.plan")
    doc = qgc_plan_document(moved, geoid_undulation_m=-30.0)
    assert doc["mission"]["plannedHomePosition"][2] == pytest.approx(moved.home.height_m + 30.0)
    with pytest.raises(PihimInputError, match="plan.site needs"):
        write_kml(moved, tmp_path / "m.kml", field=make_field())
    assert list(tmp_path.iterdir()) == []


def test_litchi_files_read_by_litchi_wp(plan, tmp_path, capsys):
    """Every data row of every flight's Litchi mission parses with the litchi-wp reader, with our values."""
    waypoint = pytest.importorskip("litchi_wp.waypoint")
    multi = _several_flights(plan)
    out = export_all(multi, tmp_path / "out")
    paths = sorted(v for k, v in out.items() if "litchi" in k)
    assert paths
    for path in paths:
        rows = list(csv.DictReader(path.read_text().splitlines()))
        parsed = waypoint.Waypoint.from_file(str(path))
        ignored = [ln for ln in capsys.readouterr().out.splitlines()[1:] if not ln.rstrip().endswith(":")]
        assert ignored == [ln for ln in ignored if ln.startswith("0: latitude")]  # only the header line
        assert 1 <= len(parsed) == len(rows) <= 99
        for wp, row in zip(parsed, rows, strict=True):
            assert (wp.lat, wp.lon) == (float(row["latitude"]), float(row["longitude"]))
            assert wp.altitude.value == float(row["altitude(m)"]) and wp.heading == float(row["heading(deg)"])
            assert wp.gimbal.pitchangle == float(row["gimbalpitchangle"])
            photo = any(a.type == waypoint.ActionType.TAKE_PHOTO for a in wp.actions)
            assert photo == any(row[f"actiontype{k}"] == "1" for k in range(1, 16))


def test_qgc_plans_read_by_mavsdk(plan, tmp_path):
    """MAVSDK's QGroundControl importer (MissionRaw.import_qgroundcontrol_mission) reads every flight's .plan
    into the same mission items. It needs a System: a MAVSDK autopilot on a loopback UDP port provides one."""
    pytest.importorskip("mavsdk")
    import socket

    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.mission_raw import MissionRaw

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    autopilot = Mavsdk(Configuration.create_with_component_type(ComponentType.AUTOPILOT))
    station = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    station.add_any_connection(f"udpin://127.0.0.1:{port}")
    autopilot.add_any_connection(f"udpout://127.0.0.1:{port}")
    system = station.first_autopilot(timeout_s=10.0)
    if system is None:
        pytest.skip("no MAVSDK system over loopback UDP within 10 s")
    mission = MissionRaw(system)
    multi = _several_flights(plan)
    out = export_all(multi, tmp_path / "out")
    for f in multi.flights:
        path = out[f"{flight_file_stem(f.index)}_plan"]
        items = json.loads(path.read_text())["mission"]["items"]
        got = mission.import_qgroundcontrol_mission(str(path)).mission_items
        assert [(m.command, m.frame) for m in got] == [(it["command"], it["frame"]) for it in items]
        for m, it in zip(got, items, strict=True):
            lat, lon = it["params"][4:6]
            if m.frame != 2:  # MAV_FRAME_MISSION items carry no position
                assert (m.x, m.y) == (round(lat * 1e7), round(lon * 1e7))
            assert m.z == pytest.approx(it["params"][6], abs=1e-4)
