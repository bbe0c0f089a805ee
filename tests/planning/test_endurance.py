"""Flight split by battery endurance, flight time, tower detours, throughput and fleet size."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest

from pihim.errors import PihimInputError
from pihim.field.geodesy import geodetic_to_enu, nsttf_origin
from pihim.field.kinematics import track_field
from pihim.field.layout import NSTTF_TOWER, UFACET_AIM_POINT, nsttf_like_field
from pihim.planning.attitude import leg_speed
from pihim.planning.endurance import (
    PAPER_HELIOSTATS_PER_HOUR,
    DroneEndurance,
    Throughput,
    fleet_estimate,
    flight_time_s,
    split_flights,
    throughput,
)
from pihim.planning.model import Waypoint
from pihim.planning.ufacet import home_waypoint, plan_passes

SUN = np.array([math.sin(math.radians(16.4)) * math.sin(math.radians(178.0)),
                math.sin(math.radians(16.4)) * math.cos(math.radians(178.0)), math.cos(math.radians(16.4))])
FIELD = nsttf_like_field()
POSE = track_field(FIELD, SUN, UFACET_AIM_POINT)
ORIGIN = nsttf_origin(1684.88)


@pytest.fixture(scope="module")
def passes():
    return plan_passes(FIELD, POSE, aim_point=UFACET_AIM_POINT, origin=ORIGIN)


@pytest.fixture(scope="module")
def home():
    return home_waypoint(FIELD, origin=ORIGIN)


def _wp(x: float, y: float, z: float, speed: float = 5.0, kind: str = "transit", capture: bool = False) -> Waypoint:
    return Waypoint(x, y, z, 0.0, 0.0, 0.0, 0.0, 0.0, speed, kind=kind, capture=capture)  # type: ignore[arg-type]


def test_flights_fit_the_battery_and_fly_every_pass_once(passes, home) -> None:
    model = DroneEndurance()
    flights = split_flights(passes, home, origin=ORIGIN, model=model, tower=FIELD.tower)
    assert len(flights) >= 2
    flown = [i for f in flights for i in f.pass_indices]
    assert flown == [p.index for p in passes if p.feasible]  # each once, in plan order
    for k, f in enumerate(flights):
        assert f.index == k
        assert f.duration_s <= model.usable_s == pytest.approx(16 * 60)
        assert f.duration_s == pytest.approx(flight_time_s(f.waypoints, model))
        kinds = [w.kind for w in f.waypoints]
        assert kinds[0] == "takeoff" and kinds[-1] == "land" and kinds[-2] == "return"
        for w in (f.waypoints[0], f.waypoints[-1]):
            assert (w.x_m, w.y_m, w.z_m) == (home.x_m, home.y_m, home.z_m)
        # the pass waypoints are all there, unchanged but for the speed toward the lead-in (transit speed)
        mine = [w for i in f.pass_indices for w in passes[i].waypoints]
        flown_wps = [w for w in f.waypoints if w.kind in ("lead_in", "scan", "run_past")]
        assert [replace(w, speed_m_s=0.0) for w in flown_wps] == [replace(w, speed_m_s=0.0) for w in mine]
        planned = [model.transit_speed_m_s if w.kind == "lead_in" else 5.0 for w in flown_wps]
        assert all(w.speed_m_s <= v for w, v in zip(flown_wps, planned, strict=True))
        # a leg is flown slower only to leave time to turn to the next heading and pitch (leg_speed)
        for prev, w in zip(f.waypoints, f.waypoints[1:]):
            if w in flown_wps and w.speed_m_s < 5.0 and w.kind != "lead_in":
                assert w.speed_m_s == pytest.approx(leg_speed(prev, replace(w, speed_m_s=5.0)))
                assert leg_speed(prev, replace(w, speed_m_s=5.0)) < 5.0
        assert f.heliostats_assessed == len({h for i in f.pass_indices for h, _ in passes[i].pairs})
        # every new waypoint has exact WGS84 coordinates
        enu = geodetic_to_enu([w.latitude_deg for w in f.waypoints], [w.longitude_deg for w in f.waypoints],
                              [w.height_m for w in f.waypoints], ORIGIN)
        assert np.allclose(enu, [[w.x_m, w.y_m, w.z_m] for w in f.waypoints], atol=1e-6)
    # greedy: the next pass would not have fitted
    for f, g in itertools.pairwise(flights):
        trial = split_flights([passes[i] for i in f.pass_indices + (g.pass_indices[0],)], home, origin=ORIGIN,
                              model=model, tower=FIELD.tower)
        assert len(trial) == 2


def test_smaller_battery_more_flights_and_oversized_pass_refused(passes, home) -> None:
    big = split_flights(passes, home, origin=ORIGIN, tower=FIELD.tower)
    small = split_flights(passes, home, origin=ORIGIN, tower=FIELD.tower, model=DroneEndurance(battery_min=8.0))
    assert len(small) > len(big)
    assert sum(f.heliostats_assessed for f in small) == sum(f.heliostats_assessed for f in big)
    with pytest.raises(PihimInputError, match="alone needs") as e:
        split_flights(passes, home, origin=ORIGIN, model=DroneEndurance(battery_min=1.0))
    assert "\n" not in str(e.value)


def test_waypoint_cap_per_flight(passes, home) -> None:
    capped = split_flights(passes, home, origin=ORIGIN, tower=FIELD.tower, max_waypoints=99)
    assert all(len(f.waypoints) <= 99 for f in capped)
    assert [i for f in capped for i in f.pass_indices] == [p.index for p in passes if p.feasible]
    assert len(capped) > len(split_flights(passes, home, origin=ORIGIN, tower=FIELD.tower))
    with pytest.raises(PihimInputError, match="waypoints"):
        split_flights(passes, home, origin=ORIGIN, max_waypoints=5)


def test_transit_legs_go_around_the_tower(passes, home) -> None:
    flights = split_flights(passes, home, origin=ORIGIN, tower=NSTTF_TOWER, model=DroneEndurance())
    lo = np.array([NSTTF_TOWER.x_min_m, NSTTF_TOWER.y_min_m])
    hi = np.array([NSTTF_TOWER.x_max_m, NSTTF_TOWER.y_max_m])
    for f in flights:
        for a, b in itertools.pairwise(f.waypoints):
            if max(a.z_m, b.z_m) >= NSTTF_TOWER.height_m:
                continue
            s = np.linspace(0.0, 1.0, 2001)[:, None]
            xy = (1 - s) * [a.x_m, a.y_m] + s * [b.x_m, b.y_m]
            assert not np.any(np.all((xy > lo) & (xy < hi), axis=1)), (a.kind, b.kind)
    # home is south of the tower and every pass north of it: the first transit needs a detour
    first = flights[0].waypoints
    before = first[:first.index(next(w for w in first if w.kind == "lead_in"))]
    detour = [w for w in before if w.kind == "transit" and (w.x_m, w.y_m) != (home.x_m, home.y_m)]
    assert len(detour) >= 1 and sum(w.kind == "transit" for w in before) >= 2
    # no leg of zero length (a waypoint repeated): the autopilot would have no time to turn on it
    for f in flights:
        for a, b in itertools.pairwise(f.waypoints):
            assert math.dist((a.x_m, a.y_m, a.z_m), (b.x_m, b.y_m, b.z_m)) > 1e-6 or a.kind == "takeoff"


def test_flight_time_of_simple_paths() -> None:
    m = DroneEndurance(capture_s=2.0, turn_s=5.0, takeoff_landing_s=30.0, climb_rate_m_s=2.0,
                       descent_rate_m_s=1.0, transit_speed_m_s=10.0)
    path = [_wp(0, 0, 0, 0.0, "takeoff"), _wp(0, 0, 20, 10.0), _wp(100, 0, 20, 10.0),
            _wp(100, 50, 20, 5.0, "lead_in"), _wp(100, 100, 20, 5.0, "scan", True), _wp(0, 0, 20, 10.0, "return"),
            _wp(0, 0, 0, 0.0, "land")]
    expected = 20 / 2.0 + 100 / 10.0 + 50 / 5.0 + 50 / 5.0 + math.hypot(100, 100) / 10.0 + 20 / 1.0 + 2.0 + 5.0 + 30.0
    assert flight_time_s(path, m) == pytest.approx(expected)
    with pytest.raises(PihimInputError):
        flight_time_s(path[:1], m)


def test_throughput_and_fleet_match_the_paper_figures() -> None:
    # paper section 5: a 20-minute flight imaging six pairs (~12 heliostats) is ~36 heliostats per hour
    paper = Throughput(flights=1, heliostats_assessed=12, flight_time_s=1200.0, elapsed_s=1200.0)
    assert paper.heliostats_per_hour == pytest.approx(PAPER_HELIOSTATS_PER_HOUR)
    # 10,000 heliostats at 50-100 per hour per drone: 100-200 drone-hours; ~10 drones in 10-20 hours
    slow, fast = fleet_estimate(10_000, 50.0, 20.0), fleet_estimate(10_000, 100.0, 10.0)
    assert (slow.drone_hours, fast.drone_hours) == (200.0, 100.0)
    assert slow.drones == fast.drones == 10
    assert fleet_estimate(10_000, 50.0, 10.0).drones == 20
    with pytest.raises(PihimInputError):
        fleet_estimate(100, 0.0, 8.0)
    assert fleet_estimate(100, 50.0, 24.0).drones == 1
    with pytest.raises(PihimInputError, match="at most 24"):
        fleet_estimate(100, 50.0, 24.5)  # working hours are per day


def test_battery_longer_than_a_day_refused() -> None:
    assert DroneEndurance(battery_min=1440.0).usable_s == pytest.approx(1440 * 60 * 0.8)
    with pytest.raises(PihimInputError, match="at most 1440 minutes"):
        DroneEndurance(battery_min=1440.5)


def test_throughput_of_a_plan(passes, home) -> None:
    model = DroneEndurance()
    flights = split_flights(passes, home, origin=ORIGIN, model=model, tower=FIELD.tower)
    tp = throughput(flights, model)
    assert tp.flights == len(flights)
    assert tp.elapsed_s == pytest.approx(tp.flight_time_s + (len(flights) - 1) * model.battery_swap_s)
    assert tp.heliostats_per_flight_hour > tp.heliostats_per_hour > PAPER_HELIOSTATS_PER_HOUR


@pytest.mark.parametrize("kwargs", [{"battery_min": 0.0}, {"reserve_fraction": 1.0}, {"capture_s": -1.0},
                                    {"transit_speed_m_s": float("inf")}])
def test_bad_models_are_refused(kwargs) -> None:
    with pytest.raises(PihimInputError):
        DroneEndurance(**kwargs)


def test_passes_beyond_the_battery_can_be_left_out() -> None:
    passes = plan_passes(FIELD, POSE, aim_point=UFACET_AIM_POINT, origin=ORIGIN)
    home = home_waypoint(FIELD, origin=ORIGIN)
    alone = sorted(split_flights([p], home, origin=ORIGIN)[0].duration_s for p in passes if p.feasible)
    model = DroneEndurance(battery_min=float(np.median(alone)) / 60.0 / 0.8)  # half the passes fit on their own
    with pytest.raises(PihimInputError, match="alone needs"):
        split_flights(passes, home, origin=ORIGIN, model=model)
    far: list[int] = []
    flights = split_flights(passes, home, origin=ORIGIN, model=model, unflyable=far)
    flown = [i for f in flights for i in f.pass_indices]
    assert far and flown and not set(far) & set(flown)
    assert sorted(far + flown) == sorted(p.index for p in passes if p.feasible)
    assert all(f.duration_s <= model.usable_s for f in flights)
