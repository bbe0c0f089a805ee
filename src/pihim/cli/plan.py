"""``pihim plan``: a UFACET-style polarimetric inspection plan exported to autopilot formats.

Pipeline: load the field, find the sun for ``--time`` at the site, track and
cant every heliostat, plan UFACET scan passes under the altitude limits,
predict the polarimetric contrast of every planned image (sky-vs-sky DoLP
difference, ground-vs-ground AoP difference, DoLP on the reflection) and
shift passes where that raises it, split the passes into battery-sized
flights, and write ``plan.json``, ``mission.plan``, ``mission.waypoints``,
``plan.kml``, ``litchi.csv`` and ``plan.png`` (see docs/plan-formats.md).
"""

from __future__ import annotations

import math
import time as _time
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from pihim.camera.model import CameraModel
from pihim.cli._common import emit_json, load_field_option, parse_point, stderr_console
from pihim.errors import PihimInputError
from pihim.planning.endurance import DroneEndurance, fleet_estimate, split_flights, throughput
from pihim.planning.export import export_all
from pihim.planning.model import Plan
from pihim.planning.scoring import ScoringModel, ShiftSearch, coverage, score_passes
from pihim.planning.ufacet import home_waypoint, plan_passes, track_at
from pihim.sky.model import SkyModel
from pihim.sky.sun import parse_site, parse_time
from pihim.surfaces.mirror import mirror_model

SCHEMA_ID = "pihim.plan-summary/1"


def plan(
    time: Annotated[str, typer.Option("--time", help="ISO 8601 time with UTC offset, e.g. 2021-05-13T13:00-06:00.")],
    out: Annotated[Path, typer.Option("--out", help="Output directory.")],
    field: Annotated[str, typer.Option("--field", help="nsttf-like (default) or an OpenCSP heliostat CSV.")] = "nsttf-like",
    facets: Annotated[Path | None, typer.Option(help="OpenCSP facet-centroid CSV (with --field CSV).")] = None,
    site: Annotated[str, typer.Option(help="nsttf (default) or LAT,LON,H (deg, deg, ellipsoidal m).")] = "nsttf",
    aim: Annotated[str | None, typer.Option(help="Aim point X,Y,Z (m, ENU); default the field's tower target.")] = None,
    max_altitude: Annotated[float, typer.Option("--max-altitude", help="Highest flight altitude, m above the field origin.")] = 25.0,
    heliostats: Annotated[str | None, typer.Option(help="Comma-separated HUAs to plan for (default: all).")] = None,
    sky_model: Annotated[str, typer.Option(help="Sky polarization model: rayleigh or berry.")] = "rayleigh",
    dmax: Annotated[float, typer.Option(help="Maximum sky DoLP, [0, 1].")] = 0.8,
    mirror: Annotated[str, typer.Option(help="Mirror model: second-surface, ideal or fresnel.")] = "second-surface",
    battery_min: Annotated[float, typer.Option(help="Battery endurance per flight, minutes.")] = 20.0,
    fleet_hours: Annotated[float, typer.Option(help="Working hours per day for the fleet estimate.")] = 8.0,
    no_shift: Annotated[bool, typer.Option("--no-shift", help="Do not shift passes to raise contrast.")] = False,
    json_out: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
) -> int:
    """Plan UFACET scan passes scored for polarimetric contrast and export missions."""
    t_start = _time.perf_counter()
    if not (math.isfinite(max_altitude) and max_altitude > 0):
        raise PihimInputError(f"--max-altitude must be a positive number of metres, got {max_altitude:g}")
    if not (math.isfinite(battery_min) and battery_min > 0):
        raise PihimInputError(f"--battery-min must be positive, got {battery_min:g}")
    when = parse_time(time)
    site_obj = parse_site(site)
    aim_point = parse_point(aim, name="--aim")
    if out.exists() and not out.is_dir():
        raise PihimInputError(f"{out}: exists and is not a directory")
    fld = load_field_option(field, facets, nsttf_tower=site.strip().lower() == "nsttf")
    aim_arr = np.asarray(aim_point if aim_point is not None else fld.default_aim_point, dtype=float)
    if aim_arr[2] <= 0:
        raise PihimInputError(f"--aim: the aim point must be above the ground (z > 0), got z = {aim_arr[2]:g}")
    names = None if heliostats is None else [h for h in heliostats.split(",") if h.strip()]
    if names is not None:
        fld.indices(names)  # unknown names -> one-line error
    sky = SkyModel(kind=sky_model, dmax=dmax)  # type: ignore[arg-type]
    scoring = ScoringModel(sky=sky, mirror=mirror_model(mirror))  # type: ignore[arg-type]
    sun, pose = track_at(fld, when, aim_point=aim_arr, site=site_obj)
    camera = CameraModel()
    passes = plan_passes(fld, pose, aim_point=aim_arr, origin=site_obj, camera=camera,
                         max_altitude_m=max_altitude, heliostats=names)
    t_plan = _time.perf_counter()
    scored = score_passes(passes, pose, sun.vector, model=scoring, camera=camera, aim_point=aim_arr,
                          origin=site_obj, search=None if no_shift else ShiftSearch(max_altitude_m=max_altitude))
    t_score = _time.perf_counter()
    endurance = DroneEndurance(battery_min=battery_min)
    home = home_waypoint(fld, origin=site_obj)
    flights = split_flights(scored, home, origin=site_obj, model=endurance, tower=fld.tower)
    rate = throughput(flights, endurance)
    fleet = fleet_estimate(len(fld.names), max(rate.heliostats_per_hour, 1e-9), fleet_hours)
    cover = coverage(scored, len(fld.names))
    summary: dict[str, Any] = {
        "heliostats_in_field": len(fld.names),
        "passes": len(scored),
        "feasible_passes": sum(p.feasible for p in scored),
        "waypoints": sum(len(p.waypoints) for p in scored),
        "images": sum(len(p.predictions) for p in scored),
        "usable_images": sum(sum(q.usable for q in p.predictions) for p in scored),
        "coverage": cover,
        "flights": len(flights),
        "heliostats_per_hour": rate.heliostats_per_hour,
        "heliostats_per_flight_hour": rate.heliostats_per_flight_hour,
        "fleet": {"working_hours": fleet_hours, **_as_dict(fleet)},
        "seconds": {"track_and_plan": round(t_plan - t_start, 4), "scoring": round(t_score - t_plan, 4)},
    }
    the_plan = Plan(
        time_iso=when.isoformat(),
        site=site_obj.as_dict(),
        sun=sun.as_dict(),
        aim_point=tuple(float(v) for v in aim_arr),  # type: ignore[arg-type]
        min_altitude_m=float(min((p.altitude_m for p in scored), default=math.nan)),
        max_altitude_m=float(max_altitude),
        camera=_as_dict(camera),
        home=home,
        passes=scored,
        flights=flights,
        summary=summary,
    )
    files = export_all(the_plan, out, field=fld)
    summary["seconds"]["total_with_export"] = round(_time.perf_counter() - t_start, 4)
    if json_out:
        emit_json({"schema": SCHEMA_ID, "time": when.isoformat(), "sun": sun.as_dict(),
                   "aim_point": list(the_plan.aim_point), **summary,
                   "files": {k: str(v) for k, v in files.items()}})
    else:
        stderr_console.print(
            f"[bold]pihim plan[/bold]: {summary['passes']} passes ({summary['feasible_passes']} feasible), "
            f"{summary['waypoints']} waypoints, {summary['usable_images']}/{summary['images']} images usable, "
            f"{len(flights)} flights, {rate.heliostats_per_hour:.0f} heliostats/h -> {out}"
        )
    return 0


def _as_dict(obj: Any) -> dict[str, Any]:
    import dataclasses

    d = dataclasses.asdict(obj)
    for name in dir(type(obj)):
        if isinstance(getattr(type(obj), name, None), property):
            d[name] = getattr(obj, name)
    return d
