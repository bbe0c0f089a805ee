"""Where and at what heading each photo of a written mission is taken, under the autopilots' documented rules.

A small interpreter flies the items of a ``.plan`` file as the ArduPilot and
PX4 documentation describe missions (see ``pihim.planning.export.qgc``,
"Capture timing"):

* one navigation item is flown at a time, in a straight line at the current
  speed (``DO_CHANGE_SPEED`` takes effect at once; acceleration neglected);
  a waypoint with a hold (param 1) stops the vehicle on it for that long;
* the DO/CONDITION items after a navigation item start, in order, when that
  item completes (reached, hold over). ArduPilot: ``CONDITION_YAW`` turns
  at its rate and holds back the DO items after it until the heading is
  within 2 deg; DO items still waiting when the next waypoint completes are
  dropped; a new waypoint leaves the heading where it is
  (``WP_YAW_BEHAVIOR = 0``) unless a ``CONDITION_YAW`` is still turning. PX4:
  the vehicle turns toward the yaw (param 4) of the waypoint it flies to as
  soon as that waypoint is current; ``CONDITION_YAW`` is not a PX4 mission
  command; a waypoint without hold is reached on entering its acceptance
  radius (param 2, else ``NAV_ACC_RAD`` = 2 m);
* the gimbal turns to each commanded pitch at a fixed rate; a capture
  command takes the photo where the vehicle is, at its heading and pitch.

The tests fly the files ``pihim plan`` writes for the NSTTF at 10:00 and
check every photo against its planned capture waypoint (0.5 m, 1 deg), and
show that the interpreter catches the layouts that photograph late or early.
"""

from __future__ import annotations

import json
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import pymap3d
import pytest

from pihim.field import nsttf_like_field
from pihim.planning.export import export_all, flight_file_stem, qgc_plan_document
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
from pihim.planning.pipeline import build_plan
from pihim.sky.sun import NSTTF, parse_time

TIME = "2021-05-13T10:00-06:00"
NAV = {MAV_CMD_NAV_TAKEOFF, MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_LAND, MAV_CMD_NAV_RETURN_TO_LAUNCH}
CAPTURE = {MAV_CMD_IMAGE_START_CAPTURE, MAV_CMD_DO_DIGICAM_CONTROL}


@dataclass
class Photo:
    """One photo: where (ENU around home, m), heading and pitch (deg), and the attitude on reaching its waypoint."""

    enu: np.ndarray
    heading: float
    pitch: float
    arrival_heading: float
    arrival_pitch: float
    t: float


@dataclass
class Flown:
    photos: list[Photo] = field(default_factory=list)
    dropped: list[int] = field(default_factory=list)  # commands of DO items never run
    duration_s: float = 0.0


def _wrap(d: float) -> float:
    return (d + 180.0) % 360.0 - 180.0


def _slew(value: float, target: float, rate: float, dt: float, angular: bool) -> float:
    d = _wrap(target - value) if angular else target - value
    step = rate * dt
    if abs(d) <= step:
        return target % 360.0 if angular else target
    out = value + math.copysign(step, d)
    return out % 360.0 if angular else out


def fly(doc: dict, autopilot: str, *, dt: float = 0.05, gimbal_rate: float = 30.0, px4_yaw_rate: float = 30.0,
        nav_acc_rad: float = 2.0, climb_rate: float = 3.0) -> Flown:
    """Interpret the mission of a QGroundControl plan document (module docstring)."""
    m = doc["mission"]
    lat0, lon0, _ = m["plannedHomePosition"]
    items = [(it["command"], [math.nan if v is None else float(v) for v in it["params"]]) for it in m["items"]]

    def enu(p: list[float]) -> np.ndarray:
        return np.array(pymap3d.geodetic2enu(p[4], p[5], p[6], lat0, lon0, 0.0))

    navs = [k for k, (c, _) in enumerate(items) if c in NAV]
    out = Flown()
    pos = np.zeros(3)
    heading = yaw_target = 0.0
    pitch = pitch_target = 0.0
    yaw_rate = 30.0
    speed = float(m["hoverSpeed"])
    t = 0.0
    pending: deque[tuple[int, list[float]]] = deque()
    yaw_blocking = False
    arrival = (heading, pitch)

    def run_dos() -> None:
        nonlocal speed, pitch_target, yaw_target, yaw_rate, yaw_blocking
        while pending and not yaw_blocking:
            c, p = pending.popleft()
            if c == MAV_CMD_DO_CHANGE_SPEED:
                speed = p[1]
            elif c in (MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, MAV_CMD_DO_MOUNT_CONTROL):
                pitch_target = p[0]
            elif c == MAV_CMD_CONDITION_YAW:
                if autopilot == "ardupilot":
                    yaw_target, yaw_rate, yaw_blocking = p[0] % 360.0, p[1] if p[1] > 0 else 60.0, True
            elif c in CAPTURE:
                out.photos.append(Photo(pos.copy(), heading, pitch, *arrival, t))

    for n, k in enumerate(navs):
        c, p = items[k]
        if c == MAV_CMD_NAV_TAKEOFF:
            t += p[6] / climb_rate
            pos = np.array([0.0, 0.0, p[6]])
        elif c in (MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_LAND):
            target = enu(p)
            if c == MAV_CMD_NAV_LAND:
                target[2] = pos[2]  # over the landing point first; the descent is not timed here
            if autopilot == "px4" and math.isfinite(p[3]):
                yaw_target, yaw_rate = p[3] % 360.0, px4_yaw_rate
            elif autopilot == "ardupilot" and not yaw_blocking:
                yaw_target = heading  # WP_YAW_BEHAVIOR = 0: a new waypoint keeps the heading
            hold = p[0] if c == MAV_CMD_NAV_WAYPOINT else 0.0
            radius = (p[1] if p[1] > 0 else nav_acc_rad) if autopilot == "px4" and hold == 0 else 0.0
            arrived_at = None
            while True:
                run_dos()
                d = target - pos
                dist = float(np.linalg.norm(d))
                if arrived_at is None and dist <= max(radius, 1e-9):
                    arrived_at, arrival = t, (heading, pitch)
                if arrived_at is not None and t - arrived_at >= hold - 1e-9:
                    break
                if dist > 0:
                    step = speed * dt
                    pos = target.copy() if dist <= step else pos + d * (step / dist)
                heading = _slew(heading, yaw_target, yaw_rate, dt, True)
                pitch = _slew(pitch, pitch_target, gimbal_rate, dt, False)
                if yaw_blocking and abs(_wrap(heading - yaw_target)) <= 2.0:
                    yaw_blocking = False
                t += dt
                if dist <= 1e-9 and arrived_at is None:
                    arrived_at, arrival = t, (heading, pitch)
        # this navigation item is complete: DO items still waiting are dropped, the next group starts
        out.dropped += [c_ for c_, _ in pending]
        pending.clear()
        yaw_blocking = False
        nxt = navs[n + 1] if n + 1 < len(navs) else len(items)
        pending.extend(items[k + 1:nxt])
        if autopilot == "px4":  # PX4 runs the DO items between two waypoints one after the other, at once
            run_dos()
        elif pending:  # ArduPilot starts the first one before the next waypoint starts, the others after
            rest = deque(list(pending)[1:])
            del list(pending)[1:]
            pending = deque([pending[0]])
            run_dos()
            pending = rest
    out.duration_s = t
    return out


# --------------------------------------------------------------------------- the NSTTF plan


@pytest.fixture(scope="module")
def nsttf():
    field_ = nsttf_like_field()
    return build_plan(field_, parse_time(TIME), NSTTF), field_


@pytest.fixture(scope="module")
def nsttf_steady():
    """One capture per HUA aimed at its centre (no facet captures): the case steady headings are for."""
    field_ = nsttf_like_field()
    return build_plan(field_, parse_time(TIME), NSTTF, facet_captures=False, facet_report=False), field_


def _captures(flight) -> list:
    return [w for w in flight.waypoints if w.capture]


def _planned_enu(plan, w) -> np.ndarray:
    h = plan.home
    return np.array(pymap3d.geodetic2enu(w.latitude_deg, w.longitude_deg, w.height_m - h.height_m,
                                         h.latitude_deg, h.longitude_deg, 0.0))


def _errors(plan, flight, flown: Flown) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    caps = _captures(flight)
    assert len(flown.photos) == len(caps)
    pos = np.array([np.linalg.norm(ph.enu - _planned_enu(plan, w)) for ph, w in zip(flown.photos, caps, strict=True)])
    hd = np.array([abs(_wrap(ph.heading - w.heading_deg)) for ph, w in zip(flown.photos, caps, strict=True)])
    arr = np.array([abs(_wrap(ph.arrival_heading - w.heading_deg)) for ph, w in zip(flown.photos, caps, strict=True)])
    pt = np.array([max(abs(ph.pitch - w.gimbal_pitch_deg), abs(ph.arrival_pitch - w.gimbal_pitch_deg))
                   for ph, w in zip(flown.photos, caps, strict=True)])
    return pos, hd, arr, pt


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])
def test_every_photo_at_its_planned_point_heading_and_pitch(nsttf, tmp_path, autopilot):
    plan, field_ = nsttf
    assert len(plan.flights) >= 2
    files = export_all(plan, tmp_path, field=field_, autopilot=autopilot)
    limit_s = 60.0 * 20.0 * 0.8  # the default battery less its reserve
    for f in plan.flights:
        doc = json.loads(files[f"{flight_file_stem(f.index)}_plan"].read_text())
        flown = fly(doc, autopilot)
        pos, hd, arr, pt = _errors(plan, f, flown)
        assert pos.max() <= 0.5, f"flight {f.index}: photo up to {pos.max():.2f} m from its point"
        assert hd.max() <= 1.0 and arr.max() <= 1.0, (hd.max(), arr.max())  # at the heading on arrival already
        assert pt.max() <= 1.0
        assert not flown.dropped
        assert flown.duration_s <= limit_s


def test_mission_item_count_of_planned_flights(nsttf):
    """count_mission_items (counting without building, for the route) equals the items the export builds, on
    the planned flights, for every option that changes the layout."""
    from pihim.planning.export.qgc import MAV_FRAME_GLOBAL_RELATIVE_ALT, _build_items, _options, count_mission_items

    plan, _ = nsttf
    for options in ({}, {"autopilot": "px4"}, {"mount_control": True}, {"speed_commands": False, "end": "land"}):
        for f in plan.flights:
            built = _build_items(f.waypoints, f.waypoints[0], lambda w: 0.0, MAV_FRAME_GLOBAL_RELATIVE_ALT,
                                 _options(**options))
            assert count_mission_items(f.waypoints, **options) == len(built) + 1


def test_headings_do_change_between_captures(nsttf):
    # the test above is not trivial: the drone turns by many degrees between captures
    plan, _ = nsttf
    turns = []
    for f in plan.flights:
        caps = _captures(f)
        turns += [abs(_wrap(b.heading_deg - a.heading_deg)) for a, b in zip(caps, caps[1:])]
    assert sum(t > 2.0 for t in turns) > 50 and max(turns) > 45.0


def _old_layout(doc: dict) -> dict:
    """The layout of pihim before issue 11: yaw, gimbal, then capture after each waypoint, no leg timing."""
    items = doc["mission"]["items"]
    navs = [k for k, it in enumerate(items) if it["command"] in NAV]
    out = []
    for n, k in enumerate(navs):
        nav = items[k]
        group = items[k + 1:(navs[n + 1] if n + 1 < len(navs) else len(items))]
        nxt_yaw = [it for it in group if it["command"] == MAV_CMD_CONDITION_YAW]
        gimb = [it for it in group if it["command"] == MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW]
        cap = [it for it in group if it["command"] in CAPTURE]
        out.append(nav)
        if nav["command"] == MAV_CMD_NAV_WAYPOINT:  # this waypoint's own heading and pitch, then the photo
            out.append({**(nxt_yaw[0] if nxt_yaw else {"command": MAV_CMD_CONDITION_YAW}),
                        "params": [nav["params"][3], 0, 0, 0, 0, 0, 0]})
            if gimb:
                out.append(gimb[0])
            out += cap
            nav["params"][0] = 0  # flown through, no hold
    doc = json.loads(json.dumps(doc))
    doc["mission"]["items"] = out
    return doc


def test_interpreter_catches_photos_taken_before_the_turn_ends(nsttf):
    plan, _ = nsttf
    f = plan.flights[0]
    doc = _old_layout(qgc_plan_document(plan, flight=f.index, autopilot="ardupilot"))
    flown = fly(doc, "ardupilot")
    caps = _captures(f)
    missed = len(caps) - len(flown.photos)  # still turning when the next waypoint completed: the photo is dropped
    assert missed >= 0
    if missed:
        assert MAV_CMD_IMAGE_START_CAPTURE in flown.dropped
    late = sum(np.linalg.norm(ph.enu - _planned_enu(plan, w)) > 0.5 or abs(_wrap(ph.heading - w.heading_deg)) > 1.0
               for ph, w in zip(flown.photos, caps, strict=False))
    assert missed + late > 10  # the issue counted 126 of 198 at 10:00


def test_interpreter_catches_px4_photos_in_the_acceptance_radius(nsttf):
    plan, _ = nsttf
    f = plan.flights[0]
    flown = fly(qgc_plan_document(plan, flight=f.index, autopilot="px4", capture_hold_s=0.0), "px4")
    pos, _, _, _ = _errors(plan, f, flown)
    assert np.median(pos) == pytest.approx(2.0, abs=0.3)  # taken on entering NAV_ACC_RAD, before the point


# --------------------------------------------------------------------------- one heading along a run


def test_heading_constant_along_runs_where_the_field_of_view_allows(nsttf_steady):
    from pihim.camera.model import CameraModel
    from pihim.planning.attitude import steady_headings
    from pihim.planning.sightlines import gaze_angles, in_fov, optical_axis
    from pihim.planning.ufacet import track_at

    plan, field_ = nsttf_steady
    _, pose = track_at(field_, parse_time(TIME), aim_point=plan.aim_point, site=NSTTF)
    camera = CameraModel()
    names = {n: k for k, n in enumerate(field_.names)}
    exact = steady_headings(plan.passes, pose, max_offset_deg=0.0)  # every capture aimed at its own HUA: unchanged
    assert exact == plan.passes
    captures = changes = 0
    for p in plan.passes:
        caps = [w for w in p.waypoints if w.capture]
        captures += len(caps)
        changes += sum(abs(_wrap(b.heading_deg - a.heading_deg)) > 1e-6 for a, b in zip(caps, caps[1:]))
        for w in caps:
            h = names[w.hua]
            cam = np.array([w.x_m, w.y_m, w.z_m])
            gaze, _ = gaze_angles(cam, pose.mirror_centres[h])
            d = pose.mirror_centres[h] - cam
            cos = float(optical_axis(w.heading_deg, w.gimbal_pitch_deg) @ d / np.linalg.norm(d))
            off = math.degrees(math.acos(min(1.0, cos)))
            assert off <= 0.25 * camera.horizontal_fov_deg + 0.01  # the HUA stays near the middle of the frame
            flown = in_fov(pose.facet_centres[h], cam, np.float64(w.heading_deg), np.float64(w.gimbal_pitch_deg),
                           camera).sum()
            aimed = in_fov(pose.facet_centres[h], cam, gaze, np.float64(w.gimbal_pitch_deg), camera).sum()
            assert flown >= aimed  # no capture frames fewer facets than aiming it at its HUA would
        first = next(k for k, w in enumerate(p.waypoints) if w.capture)
        assert p.waypoints[0].heading_deg == p.waypoints[first].heading_deg  # the pass is entered facing the run
    n_passes = sum(any(w.capture for w in p.waypoints) for p in plan.passes)
    assert changes < captures - n_passes  # some consecutive captures share a heading


# --------------------------------------------------------------------------- facets showing the target


def _facet_oracle(pose, hua: int, target: int, cam, heading: float, pitch: float, camera) -> list[bool]:
    """Plain loops: a facet shows the target if one of its 3x3 sample points, in view from the front, reflects
    the camera ray onto the target's mirror rectangle (plane intersection, then the point in the rectangle's
    own frame within its half sizes)."""
    spec = pose.field.spec
    corners = pose.facet_corners()[hua]
    n_t, c_t, r_t = pose.normals[target], pose.mirror_centres[target], pose.rotations[target]
    h, p = math.radians(heading), math.radians(pitch)
    axis = np.array([math.cos(p) * math.sin(h), math.cos(p) * math.cos(h), math.sin(p)])
    right = np.array([math.cos(h), -math.sin(h), 0.0])
    up = np.cross(right, axis)
    tx = 0.5 * camera.width_px / camera.focal_length_px
    ty = 0.5 * camera.height_px / camera.focal_length_px
    out = []
    for f in range(corners.shape[0]):
        tl, tr, br, bl = corners[f]
        n = pose.facet_normals[hua, f]
        shows = False
        for i in range(3):
            for j in range(3):
                u, v = (i + 0.5) / 3, (j + 0.5) / 3
                q = (tl + u * (tr - tl)) + v * ((bl + u * (br - bl)) - (tl + u * (tr - tl)))
                d = (q - cam) / np.linalg.norm(q - cam)
                z = float((q - cam) @ axis)
                if d @ n >= 0 or z <= 0 or abs((q - cam) @ right) > tx * z or abs((q - cam) @ up) > ty * z:
                    continue
                r = d - 2 * (d @ n) * n
                den = float(r @ n_t)
                if abs(den) < 1e-12:
                    continue
                s = float((c_t - q) @ n_t) / den
                x = q + s * r - c_t
                if s > 0 and abs(x @ r_t[:, 0]) <= spec.mirror_half_width_m \
                        and abs(x @ r_t[:, 1]) <= spec.mirror_half_height_m:
                    shows = True
        out.append(shows)
    return out


def test_facets_showing_the_target_match_a_brute_force_oracle(nsttf):
    from pihim.camera.model import CameraModel
    from pihim.planning.facets import facets_showing_target
    from pihim.planning.ufacet import track_at

    plan, field_ = nsttf
    _, pose = track_at(field_, parse_time(TIME), aim_point=plan.aim_point, site=NSTTF)
    names = {n: k for k, n in enumerate(field_.names)}
    camera = CameraModel()
    shots = [(p, pr) for p in plan.passes for pr in p.predictions]
    for k, (p, pr) in enumerate(shots):
        w = p.waypoints[pr.waypoint_index]
        cam = np.array([w.x_m, w.y_m, w.z_m])
        got = facets_showing_target(pose, names[pr.hua], names[pr.target], cam, w.heading_deg, w.gimbal_pitch_deg)
        if k % 40 == 0:
            want = _facet_oracle(pose, names[pr.hua], names[pr.target], cam, w.heading_deg, w.gimbal_pitch_deg,
                                 camera)
            assert got.tolist() == want
        assert 0 < got.sum() < 25  # each capture shows its named target in some facets, never all
