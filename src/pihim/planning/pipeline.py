"""One call from a field and a time to a scored, flight-split inspection plan.

:func:`build_plan` chains the stages the ``pihim plan`` command runs: sun
position, tracking and canting, UFACET passes, polarimetric scoring with
contrast-raising shifts, the flight split, throughput and a fleet estimate.
"""

from __future__ import annotations

import dataclasses
import math
import time as _time
from collections.abc import Callable, Sequence
from datetime import datetime
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from pihim import _forked
from pihim._forked import check_workers
from pihim.camera.model import CameraModel
from pihim.errors import PihimInputError
from pihim.planning.endurance import (
    DroneEndurance,
    fleet_estimate,
    split_flights,
    throughput,
)
from pihim.planning.attitude import steady_headings
from pihim.planning.lines import alignment_summary
from pihim.planning.model import Plan
from pihim.planning.facet_captures import FacetCaptureSettings, plan_facet_captures
from pihim.planning.route import RouteSettings, plan_flights, turns
from pihim.planning.scoring import ScoringModel, ShiftSearch, build_scene, coverage, score_passes
from pihim.planning.ufacet import MAX_ALTITUDE_LIMIT_M, home_waypoint, plan_ufacet, track_at
from pihim.sky.sun import Site, parse_site, parse_time


def _record(obj: Any) -> dict[str, Any]:
    """Dataclass fields plus its properties, for JSON."""
    d = dataclasses.asdict(obj)
    for name in dir(type(obj)):
        if isinstance(getattr(type(obj), name, None), property):
            d[name] = getattr(obj, name)
    return d


def build_plan(
    field: Any,
    time: datetime | str,
    site: Site | str,
    *,
    aim_point: ArrayLike | None = None,
    max_altitude_m: float = 25.0,
    heliostats: Sequence[str] | None = None,
    scoring: ScoringModel | None = None,
    shift: bool = True,
    camera: CameraModel | None = None,
    endurance: DroneEndurance | None = None,
    fleet_hours: float = 8.0,
    max_mission_items: int | None = 700,
    mission_options: dict[str, Any] | None = None,
    steady_heading: bool = True,
    facet_report: bool = True,
    facet_captures: bool | FacetCaptureSettings = True,
    route: bool | RouteSettings = True,
    progress: Callable[[str], None] | None = None,
    workers: int | None = 1,
) -> Plan:
    """Plan, score and split an inspection of ``field`` at ``time``.

    Parameters
    ----------
    field : pihim.field.Field
    time : datetime or str
        Timezone-aware instant (or ISO 8601 text with a UTC offset).
    site : Site or str
        Where the field's origin is (sun position and WGS84 conversion); a
        string is read by :func:`pihim.sky.sun.parse_site` (``"nsttf"``,
        ``"LAT,LON,H"``).
    aim_point : array_like, optional
        ENU aim point of the tracking heliostats; the field's tower target if omitted.
    max_altitude_m : float
        Highest flight altitude above the field origin, metres.
    heliostats : sequence of str, optional
        HUAs to plan for (default: every heliostat).
    scoring : ScoringModel, optional
        Sky, mirror and ground physics (defaults: Rayleigh sky, second-surface mirror,
        Torrance-Sparrow ground).
    shift : bool
        Shift passes (within the altitude limits) where that raises contrast.
    camera, endurance : optional
        Camera and drone models (Triton + 35 mm; 20 min battery with 20 % reserve).
    fleet_hours : float
        Working hours per day for the fleet estimate.
    max_mission_items : int or None
        Close a flight before its autopilot mission exceeds this many items
        (default 700, what Pixhawk-class ArduPilot boards store; None: no
        limit). Counted as :func:`pihim.planning.export.count_mission_items`
        counts with ``mission_options`` (by a
        :class:`~pihim.planning.export.MissionItemCounter`).
    mission_options : dict, optional
        The options the missions will be written with (``autopilot``,
        ``mount_control``, ...; see :func:`pihim.planning.export.mission_items`).
    steady_heading : bool
        Fly runs of captures at one heading where the field of view allows
        (:func:`pihim.planning.attitude.steady_headings`); only without
        ``facet_captures`` (facet captures aim at chosen points of the HUA).
    facet_report : bool
        Report which facets of each imaged HUA show a heliostat's back in at
        least one capture, and which (``summary["facet_coverage"]``,
        :func:`pihim.planning.facets.facet_coverage`).
    facet_captures : bool or FacetCaptureSettings
        Replace each HUA's single capture by the few captures along its pass
        that show every facet a heliostat's back
        (:func:`pihim.planning.facet_captures.plan_facet_captures`), and try
        requested HUAs left without a target from nearby passes.
    route : bool or RouteSettings
        Order and orient the passes and cut the flights for the shortest
        path (:func:`pihim.planning.route.plan_flights`); False flies them in
        the planner's order, cutting greedily
        (:func:`pihim.planning.endurance.split_flights`).
    progress : callable, optional
        Called with the name of each stage as it starts: ``"passes"``,
        ``"scoring"``, ``"facet captures"`` (with ``facet_captures``),
        ``"route and flights"``, ``"facet report"`` (with ``facet_report``).
        A 100,000-heliostat plan takes minutes.
    workers : int or None
        Processes sharing the choice of the lines' offsets and altitudes, the
        scoring, the facet captures' candidates and the facet report (forked
        copies of this one on Linux, :mod:`pihim._forked`; None: one per
        CPU). The plan does not depend on it. With more than one, call it
        from a process whose other threads hold no lock the workers need
        (numba compiling, logging, a display refreshing on its own thread).

    Returns
    -------
    Plan
        With ``summary`` holding counts, coverage, throughput, the fleet estimate and timings.
    """
    t0 = _time.perf_counter()
    time = parse_time(time)  # an ISO 8601 string too; a naive time is refused
    if isinstance(site, str):  # "nsttf" or "LAT,LON,H", as sun_position takes it
        site = parse_site(site)
    if not isinstance(site, Site):
        raise PihimInputError(f"site must be a pihim.sky.sun.Site, 'nsttf' or 'LAT,LON,H', got {site!r}")
    if not (math.isfinite(max_altitude_m) and 0 < max_altitude_m <= MAX_ALTITUDE_LIMIT_M):
        raise PihimInputError(f"maximum altitude must be in (0, {MAX_ALTITUDE_LIMIT_M:g}] m, got {max_altitude_m:g}")
    aim = np.asarray(field.default_aim_point if aim_point is None else aim_point, dtype=float)
    if aim.shape != (3,) or not np.all(np.isfinite(aim)):
        raise PihimInputError("the aim point must be three finite coordinates X,Y,Z in metres")
    if aim[2] <= 0:
        raise PihimInputError(f"the aim point must be above the ground (z > 0), got z = {aim[2]:g}")
    check_workers(workers)
    if heliostats is not None:
        field.indices(heliostats)  # unknown names -> one-line error
    fleet_estimate(0, 1.0, fleet_hours)  # a bad fleet_hours refused now, not after the planning
    camera = camera or CameraModel()
    endurance = endurance or DroneEndurance()
    scoring = scoring or ScoringModel()
    stage = progress or (lambda _name: None)
    stage("passes")
    sun, pose = track_at(field, time, aim_point=aim, site=site)
    planned = plan_ufacet(field, pose, aim_point=aim, origin=site, camera=camera,
                          max_altitude_m=max_altitude_m, heliostats=heliostats, workers=workers)
    passes = planned.passes
    if not passes:
        first = "; ".join(f"{n}: {why}" for n, why in planned.unassessed[:3])
        more = f" (and {len(planned.unassessed) - 3} more)" if len(planned.unassessed) > 3 else ""
        raise PihimInputError(f"no scan pass to fly: {first}{more}")
    t_plan = _time.perf_counter()
    stage("scoring")
    scene = build_scene(pose, sun.vector, scoring)
    scored = score_passes(passes, pose, sun.vector, scene=scene, camera=camera, aim_point=aim, origin=site,
                          search=ShiftSearch(max_altitude_m=max_altitude_m) if shift else None, workers=workers)
    t_score = _time.perf_counter()
    rescued: tuple[str, ...] = ()
    if facet_captures is not False:
        stage("facet captures")
        fc_settings = facet_captures if isinstance(facet_captures, FacetCaptureSettings) else None
        fplan = plan_facet_captures(scored, pose, origin=site, camera=camera, settings=fc_settings, tower=field.tower,
                                    aim_point=aim, unassessed=[n for n, _ in planned.unassessed], workers=workers)
        scored, rescued = fplan.passes, fplan.rescued
    elif steady_heading:
        scored = steady_headings(scored, pose, camera=camera)
    t_facets = _time.perf_counter()
    stage("route and flights")
    tracing = None
    if facet_report:  # the report's tracing needs the captures, not the route: workers trace during the route,
        from pihim.planning.facets import trace_captures  # on the CPUs the route (serial, here) leaves free

        tracing = trace_captures(scored, pose, camera=camera, tower=field.tower,
                                 background=_forked.worker_count(workers) - 1)
    try:
        home = home_waypoint(field, origin=site)
        counter = None
        if max_mission_items is not None:
            from pihim.planning.export.qgc import MissionItemCounter

            counter = MissionItemCounter(**dict(mission_options or {}))  # bad options -> one-line error here
        unflown: list[int] = []  # passes no flight from home reaches within a battery (a field kilometres wide)
        if route is not False:
            scored, flights = plan_flights(scored, home, origin=site, model=endurance, tower=field.tower,
                                           max_mission_items=max_mission_items, count_items=counter,
                                           settings=route if isinstance(route, RouteSettings) else RouteSettings(),
                                           unflyable=unflown)
        else:
            flights = split_flights(scored, home, origin=site, model=endurance, tower=field.tower,
                                    max_mission_items=max_mission_items, count_items=counter)
        # collected (its workers stopped) before the predictions start theirs; without workers it runs below
        traced = tracing.result() if tracing is not None and tracing.running else None
    finally:
        if tracing is not None:
            tracing.close()
    if facet_captures is not False or route is not False:  # new or reversed captures: predict them
        scored = score_passes(scored, pose, sun.vector, scene=scene, camera=camera, aim_point=aim, origin=site,
                              search=None, workers=workers)
    t_route = _time.perf_counter()
    rate = throughput(flights, endurance)
    fleet = fleet_estimate(len(field.names), max(rate.heliostats_per_hour, 1e-9), fleet_hours)
    summary: dict[str, Any] = {
        "heliostats_in_field": len(field.names),
        "passes": len(scored),
        "feasible_passes": sum(p.feasible for p in scored),
        "waypoints": sum(len(p.waypoints) for p in scored),
        "images": sum(len(p.predictions) for p in scored),
        "reflection_images": sum(sum(q.reflection_dolp_ok for q in p.predictions) for p in scored),
        "usable_images": sum(sum(q.usable for q in p.predictions) for p in scored),
        "coverage": coverage(scored, len(field.names)),
        "alignment": {"planned": alignment_summary(passes, field, pose),
                      "flown": alignment_summary(scored, field, pose)},
        "flights": len(flights),
        "distance_m": round(sum(f.distance_m for f in flights), 1),
        "turns": sum(turns(f.waypoints) for f in flights),
        "rescued_huas": list(rescued),
        "unreachable_passes": sorted(unflown),
        "max_mission_items": max_mission_items,
        "missions": [{"flight": f.index, "mission_items": counter(f.waypoints) if counter else None,
                      "waypoints": len(f.waypoints), "passes": len(f.pass_indices),
                      "captures": sum(w.capture for w in f.waypoints), "duration_s": round(f.duration_s, 1),
                      "distance_m": round(f.distance_m, 1), "turns": turns(f.waypoints)} for f in flights],
        "heliostats_per_hour": rate.heliostats_per_hour,
        "heliostats_per_flight_hour": rate.heliostats_per_flight_hour,
        "fleet": {"working_hours": fleet_hours, **_record(fleet)},
        "seconds": {"track_and_plan": round(t_plan - t0, 4), "scoring": round(t_score - t_plan, 4),
                    "facet_captures": round(t_facets - t_score, 4),
                    "route_and_predictions": round(t_route - t_facets, 4)},
    }
    if facet_report:
        from pihim.planning.facets import coverage_summary, facet_coverage

        stage("facet report")
        t_rep = _time.perf_counter()
        if traced is None and tracing is not None:
            traced = tracing.result()
        per_hua = facet_coverage(scored, pose, camera=camera, tower=field.tower, workers=workers, traced=traced)
        summary["facet_coverage"] = {
            **coverage_summary(per_hua),
            "per_hua": {h: {"covered": list(c.covered), "missing": list(c.missing), "captures": c.captures,
                            "shown_by": {str(f): {"pass": pi, "waypoint": wi, "target": tg}
                                         for f, (pi, wi, tg) in c.shown_by}}
                        for h, c in per_hua.items()}}
        summary["seconds"]["facet_report"] = round(_time.perf_counter() - t_rep, 4)
    return Plan(
        time_iso=time.isoformat(),
        site=site.as_dict(),
        sun=sun.as_dict(),
        aim_point=(float(aim[0]), float(aim[1]), float(aim[2])),
        min_altitude_m=float(min((p.altitude_m for p in scored), default=math.nan)),
        max_altitude_m=float(max_altitude_m),
        camera=_record(camera),
        home=home,
        passes=scored,
        flights=flights,
        summary=summary,
    )
