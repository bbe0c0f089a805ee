"""``pihim windows``: when in a day can a heliostat field be inspected with usable polarimetric contrast?

Sweeps one local calendar day (default every 10 minutes while the sun is
more than 10 deg high): at each time the field is tracked, UFACET passes are
planned and every planned image is scored for the paper's sky-vs-sky and
ground-vs-ground contrast, with contrast-raising pass shifts
(:func:`pihim.planning.windows.sweep_day`). Writes atomically into
``--out``:

``windows.csv``
    ``time`` (ISO 8601 with the local offset), ``sun_zenith_deg``,
    ``sun_azimuth_deg``, ``sun_elevation_deg`` and the fractions of the
    field's heliostats with a usable image: ``fraction_planned`` (geometry
    only), ``fraction_sky``, ``fraction_ground``, ``fraction_either``.
``windows.png``
    The fractions against local time, the favourable windows (``either`` at
    or above ``--threshold``, or ``--threshold`` times the day's best with
    ``--relative``) shaded, and at the NSTTF the paper's windows
    (9:30-11:30, 14:00-16:00) hatched.

With ``--json`` a one-line summary goes to stdout: the windows, the best
time, mean fractions and, at the NSTTF, the agreement with the paper's
windows. Without it, a progress bar on stderr follows the sweep and two
lines on stderr give the windows, the best time and the files written.

The times are planned and scored side by side in ``--workers`` forked
processes (default one per CPU, at most 8; the result is identical to one
process's): the NSTTF day at 10-minute steps took 8.4 s on this project's
2-core machine as a process, 12.7 s with ``--workers 1`` (BENCHMARKS.md).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from pihim._atomic import write_group
from pihim.cli._common import check_out_dir, emit_json, load_field_option, output_dir, parse_point, stderr_console
from pihim.errors import PihimInputError

SCHEMA_ID = "pihim.windows/1"


def windows(
    date: Annotated[str, typer.Option("--date", help="Local calendar day, YYYY-MM-DD.")],
    out: Annotated[Path, typer.Option("--out", help="Output directory.")],
    site: Annotated[str, typer.Option(help="nsttf (default) or LAT,LON,H (deg, deg, ellipsoidal m).")] = "nsttf",
    field: Annotated[str, typer.Option("--field", help="nsttf-like (default) or an OpenCSP heliostat CSV.")] = "nsttf-like",
    facets: Annotated[Path | None, typer.Option(help="OpenCSP facet-centroid CSV (with --field CSV).")] = None,
    step_min: Annotated[float, typer.Option("--step-min", help="Sampling step, minutes.")] = 10.0,
    min_elevation: Annotated[float, typer.Option(help="Only times with the sun above this, deg.")] = 10.0,
    aim: Annotated[str | None, typer.Option(help="Aim point X,Y,Z (m, ENU); default the tower target.")] = None,
    max_altitude: Annotated[float, typer.Option("--max-altitude", help="Highest flight altitude, m above the field origin (at most 1000).")] = 25.0,
    threshold: Annotated[float, typer.Option(help="Favourable when this fraction of heliostats is usable, [0, 1].")] = 0.5,
    relative: Annotated[bool, typer.Option("--relative", help="--threshold is a fraction of the day's best instead.")] = False,
    no_shift: Annotated[bool, typer.Option("--no-shift", help="Score the plans without contrast-raising shifts.")] = False,
    workers: Annotated[int | None, typer.Option("--workers", help="Processes planning and scoring times side by side (default: one per CPU, at most 8; 1: this process only).")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
) -> int:
    """Favourable times of day for polarimetric inspection (paper sec. 4.1 windows)."""
    from pihim._malloc import keep_freed_memory
    from pihim.planning.scoring import ShiftSearch
    from pihim.planning.windows import (
        MAX_WORKERS,
        is_nsttf,
        parse_date,
        sweep_day,
        write_windows_csv,
        write_windows_png,
    )
    from pihim.sky.sun import parse_site

    day = parse_date(date)
    site_obj = parse_site(site)
    for label, v, lo, hi in (("--step-min", step_min, 0.5, 240.0), ("--threshold", threshold, 0.0, 1.0)):
        if not (math.isfinite(v) and lo <= v <= hi):
            raise PihimInputError(f"{label} must be in [{lo:g}, {hi:g}], got {v:g}")
    if workers is not None and not 1 <= workers <= MAX_WORKERS:
        raise PihimInputError(f"--workers must be in [1, {MAX_WORKERS}], got {workers}")
    if not (math.isfinite(min_elevation) and 0.0 <= min_elevation < 89.0):
        raise PihimInputError(f"--min-elevation must be in [0, 89) deg, got {min_elevation:g}")
    from pihim.planning.ufacet import MAX_ALTITUDE_LIMIT_M

    if not (math.isfinite(max_altitude) and 0 < max_altitude <= MAX_ALTITUDE_LIMIT_M):
        raise PihimInputError(f"--max-altitude must be in (0, {MAX_ALTITUDE_LIMIT_M:g}] m, got {max_altitude:g}")
    aim_point = None if aim is None else np.array(parse_point(aim, name="--aim"))
    check_out_dir(out)
    fld = load_field_option(field, facets, nsttf_tower=is_nsttf(site_obj))
    keep_freed_memory()  # the sweep's temporaries: freed blocks reused, not faulted in again (pihim._malloc)
    with _progress_bar(f"planning and scoring {day.isoformat()}") as tick:
        sweep = sweep_day(day, site=site_obj, field=fld, aim_point=aim_point, step_min=step_min,
                          min_elevation_deg=min_elevation, max_altitude_m=max_altitude,
                          search=None if no_shift else ShiftSearch(), progress=tick, workers=workers)
    if len(sweep) and len(sweep.planner_errors) == len(sweep):  # nothing planned: no windows to report
        when, why = sweep.planner_errors[0]
        raise PihimInputError(f"the planner refused all {len(sweep)} times of the day; at {when[11:16]}: {why}")
    csv_path, png_path = out / "windows.csv", out / "windows.png"
    with output_dir(out):  # both files or neither, and no empty --out left behind
        write_group({csv_path: lambda p: write_windows_csv(sweep, p),
                     png_path: lambda p: write_windows_png(sweep, p, threshold=threshold, relative=relative)})
    if json_out:
        emit_json({
            "schema": SCHEMA_ID,
            **sweep.summary(threshold, "either", relative=relative),
            "files": {"csv": str(csv_path), "png": str(png_path)},
        })
    else:
        stderr_console().print(_human_summary(sweep.summary(threshold, "either", relative=relative), out),
                               highlight=False, soft_wrap=True)
    return 0


@contextlib.contextmanager
def _progress_bar(description: str) -> Iterator[Callable[[int, int], None]]:
    """A progress bar on stderr fed by ``sweep_day``'s ``progress(done, total)`` callback."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    # no refresh thread and no stdout / stderr proxies: the sweep forks its workers while the bar is up
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  console=stderr_console(), transient=True, disable=not stderr_console().is_terminal,
                  auto_refresh=False, redirect_stdout=False, redirect_stderr=False) as bar:
        task = bar.add_task(description, total=None)

        def tick(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total, refresh=True)

        yield tick


def _hhmm(iso: str) -> str:
    return iso[11:16]


def _human_summary(summary: dict[str, Any], out: Path) -> str:
    """The windows and the best time, the times the planner refused (if any), and what was written where."""
    level = 100 * summary["threshold_fraction"]
    wins = ", ".join(f"{_hhmm(w['start'])}-{_hhmm(w['end'])}" for w in summary["windows"]) or "none"
    best = summary["best"]
    best_text = "" if best is None else f"; best {_hhmm(best['time'])} ({100 * best['fraction']:.0f} %)"
    paper = summary.get("paper_agreement")
    covered = None if not paper else paper.get("paper_covered")
    paper_text = "" if covered is None else f"; {100 * covered:.0f} % of the paper's windows favourable here"
    refused = len(summary.get("planner_errors") or ())
    refused_text = "" if not refused else (f"\nthe planner refused {refused} of the {summary['n_times']} times "
                                           "(counted as nothing coverable; --json lists why)")
    return (f"pihim windows {summary['date']}: {summary['n_times']} times scored; favourable (coverage >= "
            f"{level:.0f} % of {summary['n_heliostats']} heliostats with a usable image): {wins}{best_text}"
            f"{paper_text}{refused_text}\nwrote windows.csv and windows.png to {out}")
