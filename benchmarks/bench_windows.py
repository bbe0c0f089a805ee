"""Speed benchmark: polarimetric scoring of an NSTTF plan and the day sweep.

Rows (each timed ``repeat`` times after ``warmup`` untimed calls, in one
process, one after the other; NSTTF-like field, 218 heliostats, tracking the
tower target (the sweep's default aim point), 2021-05-13 10:30 MDT unless
stated):

``track + plan``
    :func:`pihim.field.track_field` and :func:`pihim.planning.ufacet.plan_passes`
    (the planner's share, for reference).
``scene``
    :func:`pihim.planning.scoring.build_scene`: sky scaling and the ground
    radiance table for the sun of the instant.
``score (as planned)``
    ``build_scene`` + :func:`pihim.planning.scoring.score_passes` without
    shifts: every planned image scored.
``score + shifts``
    The same with the default :class:`~pihim.planning.scoring.ShiftSearch`
    (35 candidate shifts per pass, all passes at once).
``full plan``
    Tracking, canting, planning, scoring and shifts for one instant: the
    issue's target, <= 1 s.
``day sweep``
    :func:`pihim.planning.windows.sweep_day` for 2021-05-13 every 10 min with
    the sun above 10 deg (73 instants), in this process: target <= 10 s.
    Timed ``min(repeat, 3)`` times (1 with ``quick``).
``day sweep, forked workers``
    The same with ``workers=2`` (the times shared among two forked copies
    of this process); its CPU time includes the workers'.
``pihim windows`` as a process
    ``python -m pihim windows --date 2021-05-13 --out DIR --json``, with
    ``--workers 1`` and with the default (one worker per CPU): what a user
    runs, imports, first calls and figure included; wall and CPU time
    (``getrusage`` of the finished process and its workers), as often as
    the sweep.

Figures: median, p10 and p90 wall time; the tracemalloc peak of one call;
the share of CPU other processes used during the timing (``/proc/stat``).

Run ``python benchmarks/run.py --only bench_windows`` or this file directly.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pihim.field import nsttf_like_field, track_field
from pihim.planning.scoring import ShiftSearch, build_scene, score_passes
from pihim.planning.ufacet import plan_passes
from pihim.planning.windows import DEFAULT_MAX_ALTITUDE_M, sweep_day
from pihim.sky.sun import NSTTF, sun_position

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness

COUNTS = harness.Counts(repeat=10, warmup=2, quick_repeat=3, quick_warmup=1, cap_quick=True)
SWEEP_REPEAT = 3
RESULTS_PATH = Path(__file__).resolve().parent / "results" / "windows.json"
TIME = "2021-05-13T10:30:00-06:00"
DATE = "2021-05-13"
WORKERS = 2
TARGETS = (
    ("NSTTF full plan incl. tracking, canting and scoring, one instant", "full_plan", 1000.0, "ms"),
    ("NSTTF day sweep, 10-min steps", "day_sweep", 10000.0, "ms"),
)
#: Wall-time targets of the parallel rows (their CPU time is the one-process figure's and more).
WALL_TARGETS = (
    (f"NSTTF day sweep, 10-min steps, {WORKERS} forked workers", "day_sweep_forked", 10000.0, "ms"),
    ("`pihim windows` for that day as a process, default workers", "process_default", 10000.0, "ms"),
)


def run_benchmark(repeat: int, warmup: int, sweep_repeat: int) -> dict[str, Any]:
    """Time every row; return the JSON-ready report."""
    fld = nsttf_like_field()
    aim = fld.default_aim_point
    sun = sun_position(NSTTF, TIME).vector
    search = ShiftSearch(max_altitude_m=DEFAULT_MAX_ALTITUDE_M)

    def track_plan() -> Any:
        pose = track_field(fld, sun, aim)
        return pose, plan_passes(fld, pose, aim_point=aim, origin=NSTTF, max_altitude_m=DEFAULT_MAX_ALTITUDE_M)

    pose, passes = track_plan()
    n_images = sum(w.capture for p in passes for w in p.waypoints)

    def score(search_: ShiftSearch | None) -> Any:
        return score_passes(passes, pose, sun, scene=build_scene(pose, sun), search=search_, aim_point=aim,
                            origin=NSTTF)

    def full() -> Any:
        p, ps = track_plan()
        return score_passes(ps, p, sun, search=search, aim_point=aim, origin=NSTTF)

    rows: list[tuple[str, str, Callable[[], Any], int, bool]] = [
        ("track_plan", "track + plan (planner, reference)", track_plan, repeat, True),
        ("scene", "scene: sky scaling + ground table", lambda: build_scene(pose, sun), repeat, True),
        ("score", f"score as planned ({n_images} images)", lambda: score(None), repeat, True),
        ("score_shift", f"score + shift search ({len(search.candidates())} candidates/pass)", lambda: score(search),
         repeat, True),
        ("full_plan", "full plan: tracking, canting, planning, scoring, shifts", full, repeat, True),
        ("day_sweep", f"day sweep {DATE}, 10-min steps, sun > 10 deg, one process", lambda: sweep_day(DATE),
         sweep_repeat, False),
        ("day_sweep_forked", f"the same sweep in {WORKERS} forked worker processes (`workers={WORKERS}`)",
         lambda: sweep_day(DATE, workers=WORKERS), sweep_repeat, False),
    ]
    results = {
        key: {"label": label,
              **harness.measure(fn, reps, min(warmup, reps) if not key.startswith("day_sweep") else 0, trace=trace)}
        for key, label, fn, reps, trace in rows
    }
    results.update(_process_rows(sweep_repeat))
    n_times = len(sweep_day(DATE, step_min=10.0, search=None, planner=lambda *a, **k: ()))
    results["day_sweep"]["instants"] = n_times
    return {
        "benchmark": "bench_windows",
        "settings": {"repeat": repeat, "warmup": warmup, "sweep_repeat": sweep_repeat, "time": TIME, "date": DATE,
                     "aim_point_m": aim.tolist(), "heliostats": len(fld), "passes": len(passes),
                     "images": n_images, "sweep_instants": n_times},
        "results": results,
        "targets": [harness.target(name, results[key]["median_ms"], lim, unit) for name, key, lim, unit in TARGETS]
        + [harness.target(f"{name}, CPU time (all threads)", results[key]["cpu_ms"], lim, unit)
           for name, key, lim, unit in TARGETS]
        + [harness.target(f"{name}, wall time", results[key]["median_ms"], lim, unit)
           for name, key, lim, unit in WALL_TARGETS],
        "machine": harness.machine_info(),
    }


def _process_rows(repeat: int) -> dict[str, dict[str, Any]]:
    """``pihim windows`` for the day as whole processes, one worker and the default: rows like ``measure``'s."""
    import os
    import statistics
    import tempfile

    rows = {}
    for key, extra, label in (("process_one", ["--workers", "1"], "`pihim windows` as a process, `--workers 1`"),
                              ("process_default", [], "`pihim windows` as a process, default (one worker per CPU)")):
        runs = []
        with tempfile.TemporaryDirectory() as tmp:
            for k in range(repeat):
                argv = [sys.executable, "-m", "pihim", "windows", "--date", DATE, "--out", f"{tmp}/w{k}", "--json",
                        *extra]
                env = {k_: v for k_, v in os.environ.items() if k_ != "PYTHONDONTWRITEBYTECODE"}
                run = harness.process_run(argv, env=env)
                if run["returncode"] != 0:
                    raise RuntimeError(f"pihim windows failed: {run['stderr'].strip()[-300:]}")
                runs.append(run)
        walls = [1e3 * r["wall_s"] for r in runs]
        others = [r["other_cpu"] for r in runs if r["other_cpu"] is not None]
        p10, p90 = (float(v) for v in np.percentile(walls, [10, 90]))
        rows[key] = {"label": label, "median_ms": statistics.median(walls), "p10_ms": p10,
                     "p90_ms": p90, "cpu_ms": statistics.median(1e3 * r["cpu_s"] for r in runs),
                     "peak_mb": None, "other_cpu": max(others) if others else None,
                     "load_avg": harness.load_average(), "repeat": repeat}
    return rows


def markdown_report(report: dict[str, Any]) -> str:
    """The results as a markdown table plus the targets."""
    s = report["settings"]
    lines = [
        (f"Windows benchmark: NSTTF-like field ({s['heliostats']} heliostats, {s['passes']} passes, {s['images']} "
         f"images at {s['time']}); day sweep {s['date']} ({s['sweep_instants']} instants); {s['repeat']} timed calls "
         f"after {s['warmup']} warm-ups ({s['sweep_repeat']} for the sweep); {report['machine']['cpu_count']} CPUs."),
        "",
        "| Row | Median ms | p10 ms | p90 ms | CPU ms | Peak MB (tracemalloc) | Other CPU % | Load |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in report["results"].values():
        peak = "-" if r["peak_mb"] is None else f"{r['peak_mb']:.1f}"
        lines.append(f"| {r['label']} | {harness.ms_cells(r, '.1f')} | {r['cpu_ms']:.1f} | {peak} "
                     f"| {harness.other_pct(r['other_cpu'])} | {r['load_avg']:.1f} |")
    lines += harness.target_table(report["targets"], spec=".1f")
    lines += harness.busy_warning(r["other_cpu"] for r in report["results"].values())
    return "\n".join(lines)


def main(
    argv: Sequence[str] | None = None,
    *,
    repeat: int | None = None,
    quick: bool = False,
    warmup: int | None = None,
    json_path: Path | None = RESULTS_PATH,
    echo: bool = True,
) -> dict[str, Any]:
    """Run the benchmark, print the markdown table and write the JSON report.

    Parameters
    ----------
    argv : sequence of str, optional
        Command-line arguments (``--repeat N``, ``--warmup N``, ``--quick``,
        ``--json PATH``); ``None`` or empty reads nothing.
    repeat : int, optional
        Timed calls per row; default 10, at most 3 with ``quick``. The day sweep is
        timed ``min(repeat, 3)`` times (once with ``quick``).
    quick : bool
        Fewer calls, for a fast look.
    warmup : int, optional
        Untimed calls before timing (not for the sweep); default 2, or 1 with
        ``quick``.
    json_path : pathlib.Path or None
        Where to write the JSON report (``benchmarks/results/``, git-ignored);
        ``None`` writes nothing.
    echo : bool
        Print the markdown report.

    Returns
    -------
    dict
        The JSON-ready report (``targets`` summarised by ``run.py``).
    """
    o = harness.options(argv, description="Speed of pihim's plan scoring and day sweep.", counts=COUNTS,
                        repeat=repeat, warmup=warmup, quick=quick, json_path=json_path)
    sweep_repeat = 1 if o.quick else min(o.repeat, SWEEP_REPEAT)
    report = run_benchmark(o.repeat, o.warmup, sweep_repeat)
    return harness.publish(report, markdown_report, o.json_path, echo=echo)


if __name__ == "__main__":
    main(sys.argv[1:] or None)
