"""``pihim plan``: a UFACET-style polarimetric inspection plan exported to autopilot formats.

A thin layer over :func:`pihim.planning.pipeline.build_plan` and
:func:`pihim.planning.export.export_all`; see ``docs/cli.md``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time as _time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Annotated, Any

import typer

from pihim.cli._common import check_out_dir, emit_json, load_field_option, output_dir, parse_point, stderr_console
from pihim.errors import PihimInputError

SCHEMA_ID = "pihim.plan-summary/1"


def _undulation(value: float | None, site: Any, text: str) -> float:
    """``--geoid-undulation``, checked, or the one pihim knows at ``site``; refused before any planning."""
    from pihim.planning.export._common import known_geoid_undulation

    if value is None:
        known = known_geoid_undulation(site.latitude_deg, site.longitude_deg)
        if known is None:
            raise PihimInputError(f"--site {text.strip()} is not near the NSTTF: give --geoid-undulation (the EGM96 "
                                  f"geoid height there, m), which the mission files' sea-level heights need")
        return known
    if not (math.isfinite(value) and abs(value) <= 120.0):
        raise PihimInputError(f"--geoid-undulation must be a number of metres within +/-120, got {value:g}")
    return float(value)


def plan(
    time: Annotated[str, typer.Option("--time", help="ISO 8601 time with UTC offset, e.g. 2021-05-13T13:00-06:00.")],
    out: Annotated[Path, typer.Option("--out", help="Output directory.")],
    field: Annotated[str, typer.Option("--field", help="nsttf-like (default) or an OpenCSP heliostat CSV.")] = "nsttf-like",
    facets: Annotated[Path | None, typer.Option(help="OpenCSP facet-centroid CSV (with --field CSV).")] = None,
    site: Annotated[str, typer.Option(help="nsttf (default) or LAT,LON,H (deg, deg, ellipsoidal m).")] = "nsttf",
    geoid_undulation: Annotated[float | None, typer.Option(
        "--geoid-undulation", help="EGM96 geoid height above the ellipsoid at the site, m, for the sea-level "
        "heights of the mission files (default -22 near the NSTTF; needed elsewhere).", show_default=False)] = None,
    aim: Annotated[str | None, typer.Option(help="Aim point X,Y,Z (m, ENU); default the field's tower target.")] = None,
    max_altitude: Annotated[float, typer.Option("--max-altitude", help="Highest flight altitude, m above the field origin (at most 1000).")] = 25.0,
    heliostats: Annotated[str | None, typer.Option(help="Comma-separated HUAs to plan for (default: all).")] = None,
    sky_model: Annotated[str, typer.Option(help="Sky polarization model: rayleigh or berry.")] = "rayleigh",
    dmax: Annotated[float, typer.Option(help="Maximum sky DoLP, [0, 1].")] = 0.8,
    mirror: Annotated[str, typer.Option(help="Mirror model: second-surface, ideal or fresnel.")] = "second-surface",
    battery_min: Annotated[float, typer.Option(help="Battery endurance per flight, minutes (at most 1440).")] = 20.0,
    max_mission_items: Annotated[int, typer.Option(
        "--max-mission-items", help="Most mission items per flight the autopilot stores (home included).")] = 700,
    autopilot: Annotated[str, typer.Option(help="Mission files for ardupilot (default) or px4.")] = "ardupilot",
    fleet_hours: Annotated[float, typer.Option(help="Working hours per day for the fleet estimate (at most 24).")] = 8.0,
    no_shift: Annotated[bool, typer.Option("--no-shift", help="Do not shift passes to raise contrast.")] = False,
    facet_target: Annotated[float, typer.Option(
        "--facet-target", help="Share of the imaged HUAs' facets to show a heliostat's back, [0, 1].")] = 0.96,
    single_capture: Annotated[bool, typer.Option(
        "--single-capture", help="One capture per HUA aimed at its centre (no facet captures).")] = False,
    workers: Annotated[int | None, typer.Option("--workers", help="Processes sharing the lines' settings, the scoring, the facet captures, the facet report and the files (default: one per CPU, at most 8; 1: this process only).")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
) -> int:
    """Plan UFACET scan passes scored for polarimetric contrast and export missions."""
    t0 = _time.perf_counter()
    # the planner and its dependencies (scipy, numba, pandas) load only when the command runs, not for --help
    from pihim._forked import MAX_WORKERS
    from pihim.planning.endurance import MAX_BATTERY_MIN, DroneEndurance
    from pihim.planning.facet_captures import FacetCaptureSettings
    from pihim.planning.export import export_all
    from pihim.planning.pipeline import build_plan
    from pihim.planning.scoring import ScoringModel
    from pihim.sky.model import SkyModel
    from pihim.sky.sun import parse_site, parse_time
    from pihim.surfaces.mirror import mirror_model

    when = parse_time(time)
    site_obj = parse_site(site)
    undulation = _undulation(geoid_undulation, site_obj, site)
    aim_point = parse_point(aim, name="--aim")
    check_out_dir(out)
    if not (math.isfinite(battery_min) and 0 < battery_min <= MAX_BATTERY_MIN):
        raise PihimInputError(f"--battery-min must be a positive number of minutes, at most {MAX_BATTERY_MIN:g} "
                              f"(a day), got {battery_min:g}")
    if not (math.isfinite(fleet_hours) and 0 < fleet_hours <= 24):
        raise PihimInputError(f"--fleet-hours must be a positive number of hours per day, at most 24, "
                              f"got {fleet_hours:g}")
    if workers is not None and not 1 <= workers <= MAX_WORKERS:
        raise PihimInputError(f"--workers must be in [1, {MAX_WORKERS}], got {workers}")
    if max_mission_items < 4:
        raise PihimInputError(f"--max-mission-items must be at least 4, got {max_mission_items}")
    if autopilot not in ("ardupilot", "px4"):
        raise PihimInputError(f"--autopilot must be ardupilot or px4, got {autopilot!r}")
    if not (math.isfinite(facet_target) and 0.0 <= facet_target <= 1.0):
        raise PihimInputError(f"--facet-target must be a fraction in [0, 1], got {facet_target:g}")
    fld = load_field_option(field, facets, nsttf_tower=site.strip().lower() == "nsttf")
    names = None if heliostats is None else [h for h in heliostats.split(",") if h.strip()]
    if names == []:
        raise PihimInputError("--heliostats names no heliostat (leave it out to plan for all)")
    scoring = ScoringModel(sky=SkyModel(kind=sky_model, dmax=dmax), mirror=mirror_model(mirror))  # type: ignore[arg-type]
    options = {"autopilot": autopilot}
    with _stage_status(len(fld)) as stage:
        the_plan = build_plan(fld, when, site_obj, aim_point=aim_point, max_altitude_m=max_altitude,
                              heliostats=names, scoring=scoring, shift=not no_shift,
                              endurance=DroneEndurance(battery_min=battery_min), fleet_hours=fleet_hours,
                              max_mission_items=max_mission_items, mission_options=options,
                              facet_captures=(False if single_capture
                                              else FacetCaptureSettings(target_fraction=facet_target)),
                              progress=stage, workers=workers)
        the_plan = dataclasses.replace(the_plan, site={**the_plan.site, "geoid_undulation_m": undulation})
        stage(f"writing plan.json, plan.kml, plan.png and {len(the_plan.flights)} flights' missions")
        with output_dir(out) as out_path:  # interrupted or failed: no empty --out left behind
            files = export_all(the_plan, out_path, field=fld, max_mission_items=max_mission_items,
                               workers=workers, **options)
    summary = the_plan.summary
    summary["seconds"]["total_with_export"] = round(_time.perf_counter() - t0, 4)
    if json_out:
        emit_json({"schema": SCHEMA_ID, "time": the_plan.time_iso, "sun": the_plan.sun,
                   "aim_point": list(the_plan.aim_point), **summary,
                   "files": {k: str(v) for k, v in files.items()}})
    else:
        stderr_console().print(_human_summary(summary, files, out), highlight=False, soft_wrap=True)
    return 0


@contextlib.contextmanager
def _stage_status(n_heliostats: int) -> Iterator[Callable[[str], None]]:
    """A one-line status on stderr naming the stage ``build_plan`` is in (only on a terminal)."""
    if not stderr_console().is_terminal:
        yield lambda _name: None
        return
    from rich.live import Live
    from rich.text import Text

    # redrawn at each stage only: no refresh thread and no stdout / stderr proxies while the planner forks workers
    with Live(Text(f"pihim plan: {n_heliostats:,} heliostats ..."), console=stderr_console(), auto_refresh=False,
              transient=True, redirect_stdout=False, redirect_stderr=False) as live:
        t0 = _time.perf_counter()

        def stage(name: str) -> None:
            live.update(Text(f"pihim plan, {n_heliostats:,} heliostats, {_time.perf_counter() - t0:.0f} s in: "
                             f"{name} ..."), refresh=True)

        yield stage


def _human_summary(summary: dict, files: dict[str, Path], out: Path) -> str:
    """Two lines for the console: what was planned, and what was written where."""
    missions = summary.get("missions", [])
    longest = max((m["duration_s"] for m in missions), default=0.0) / 60.0
    n_flight_files = sum(k.endswith("_plan") and k.startswith("flight_") for k in files)
    from pihim.planning.scoring import images_text

    return (
        f"pihim plan: {summary['passes']} passes, {images_text(summary)}{_facet_text(summary)}; "
        f"{summary['flights']} flights, {summary['distance_m'] / 1000:.2f} km, {summary['turns']} turns, "
        f"longest {longest:.1f} min{_unreachable_text(summary)}\n"
        f"wrote {len(files)} files to {out}: plan.json, plan.kml, plan.png and {n_flight_files} flight missions "
        f"(flight_NN.plan / .waypoints / _litchi*.csv)"
    )


def _unreachable_text(summary: dict) -> str:
    n = len(summary.get("unreachable_passes") or ())
    if not n:
        return ""
    return (f"; {n} passes out of a battery's reach from the take-off point south of the tower, not flown "
            f"(unreachable_passes in plan.json)")


def _facet_text(summary: dict) -> str:
    fc = summary.get("facet_coverage")
    if not fc:
        return ""
    return (f"; {100 * fc['fraction']:.1f} % of the imaged HUAs' facets show a heliostat's back "
            f"({fc['huas_complete']} of {fc['huas']} HUAs complete)")
