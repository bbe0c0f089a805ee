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
    the sun above 10 deg (73 instants): target <= 10 s. Timed
    ``min(repeat, 3)`` times (1 with ``quick``).

Figures: median, p10 and p90 wall time; the tracemalloc peak of one call;
the share of CPU other processes used during the timing (``/proc/stat``).

Run ``python benchmarks/run.py --only bench_windows`` or this file directly.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import time
import tracemalloc
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pihim.field import nsttf_like_field, track_field
from pihim.planning.scoring import ShiftSearch, build_scene, score_passes
from pihim.planning.ufacet import plan_passes
from pihim.planning.windows import DEFAULT_MAX_ALTITUDE_M, sweep_day
from pihim.sky.sun import NSTTF, sun_position

DEFAULT_WARMUP = 2
QUICK_REPEAT = 3
QUICK_WARMUP = 1
SWEEP_REPEAT = 3
RESULTS_PATH = Path(__file__).resolve().parent / "results" / "windows.json"
TIME = "2021-05-13T10:30:00-06:00"
DATE = "2021-05-13"
TARGETS = (
    ("NSTTF full plan incl. tracking, canting and scoring, one instant", "full_plan", 1000.0, "ms"),
    ("NSTTF day sweep, 10-min steps", "day_sweep", 10000.0, "ms"),
)


def _cpu_times() -> tuple[float, float, float] | None:
    """(wall, machine busy CPU seconds, own CPU seconds); None without /proc/stat."""
    try:
        with open("/proc/stat", encoding="ascii") as fh:
            ticks = [int(v) for v in fh.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    user, nice, system, _idle, _iowait, irq, softirq, steal = ticks + [0] * (8 - len(ticks))
    own = os.times()
    busy = (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")
    return time.perf_counter(), busy, own.user + own.system


def _other_load(a: tuple[float, float, float] | None, b: tuple[float, float, float] | None) -> float | None:
    if a is None or b is None or b[0] <= a[0]:
        return None
    return max((b[1] - a[1]) - (b[2] - a[2]), 0.0) / ((b[0] - a[0]) * (os.cpu_count() or 1))


def measure(fn: Callable[[], Any], repeat: int, warmup: int, *, trace: bool = True) -> dict[str, Any]:
    """Median/p10/p90 ms over ``repeat`` calls after ``warmup``; tracemalloc peak of one extra call."""
    for _ in range(warmup):
        fn()
    gc.collect()
    gc.disable()
    times = []
    try:
        t0 = _cpu_times()
        for _ in range(repeat):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        t1 = _cpu_times()
    finally:
        gc.enable()
    peak = None
    if trace:
        tracemalloc.start()
        fn()
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    ms = np.array(times) * 1e3
    return {
        "median_ms": float(np.median(ms)),
        "p10_ms": float(np.percentile(ms, 10)),
        "p90_ms": float(np.percentile(ms, 90)),
        "peak_mb": None if peak is None else peak / 1e6,
        "other_cpu": _other_load(t0, t1),
        "repeat": repeat,
    }


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
        ("day_sweep", f"day sweep {DATE}, 10-min steps, sun > 10 deg", lambda: sweep_day(DATE), sweep_repeat, False),
    ]
    results: dict[str, Any] = {}
    for key, label, fn, reps, trace in rows:
        results[key] = {"label": label, **measure(fn, reps, min(warmup, reps) if key != "day_sweep" else 0,
                                                  trace=trace)}
    n_times = len(sweep_day(DATE, step_min=10.0, search=None, planner=lambda *a, **k: ()))
    results["day_sweep"]["instants"] = n_times
    targets = []
    for name, key, limit, unit in TARGETS:
        measured = results[key]["median_ms"]
        targets.append({"target": name, "required": f"<= {limit:g} {unit}", "measured": measured, "unit": unit,
                        "passed": measured <= limit})
    return {
        "benchmark": "bench_windows",
        "settings": {"repeat": repeat, "warmup": warmup, "sweep_repeat": sweep_repeat, "time": TIME, "date": DATE,
                     "aim_point_m": aim.tolist(), "heliostats": len(fld), "passes": len(passes),
                     "images": n_images, "sweep_instants": n_times},
        "results": results,
        "targets": targets,
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                    "python": platform.python_version(), "numpy": np.__version__},
    }


def markdown_report(report: dict[str, Any]) -> str:
    """The results as a markdown table plus the targets."""
    s = report["settings"]
    lines = [
        (f"Windows benchmark: NSTTF-like field ({s['heliostats']} heliostats, {s['passes']} passes, {s['images']} "
         f"images at {s['time']}); day sweep {s['date']} ({s['sweep_instants']} instants); {s['repeat']} timed calls "
         f"after {s['warmup']} warm-ups ({s['sweep_repeat']} for the sweep); {report['machine']['cpu_count']} CPUs."),
        "",
        "| Row | Median ms | p10 ms | p90 ms | Peak MB (tracemalloc) | Other CPU % |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in report["results"].values():
        other = "-" if r["other_cpu"] is None else f"{100 * r['other_cpu']:.0f}"
        peak = "-" if r["peak_mb"] is None else f"{r['peak_mb']:.1f}"
        lines.append(f"| {r['label']} | {r['median_ms']:.1f} | {r['p10_ms']:.1f} | {r['p90_ms']:.1f} | {peak} "
                     f"| {other} |")
    lines += ["", "| Target | Required | Measured | Verdict |", "|---|---|---:|---|"]
    for t in report["targets"]:
        verdict = "PASS" if t["passed"] else "FAIL"
        lines.append(f"| {t['target']} | {t['required']} | {t['measured']:.1f} {t['unit']} | {verdict} |")
    busy = [r for r in report["results"].values() if r["other_cpu"] is not None and r["other_cpu"] > 0.05]
    if busy:
        lines += ["", (f"Warning: other processes used more than 5 % of the CPUs during {len(busy)} row(s); "
                       "those figures are inflated.")]
    return "\n".join(lines)


def main(
    argv: Sequence[str] | None = None,
    *,
    repeat: int = 10,
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
    repeat : int
        Timed calls per row (at most 3 with ``quick``); the day sweep is
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
    if argv:
        p = argparse.ArgumentParser(description="Speed of pihim's plan scoring and day sweep.")
        p.add_argument("--repeat", type=int)
        p.add_argument("--warmup", type=int)
        p.add_argument("--quick", action="store_true")
        p.add_argument("--json", type=Path, default=json_path)
        a = p.parse_args(list(argv))
        repeat = a.repeat if a.repeat is not None else repeat
        warmup = a.warmup if a.warmup is not None else warmup
        quick = quick or a.quick
        json_path = a.json
    if quick:
        repeat = min(repeat, QUICK_REPEAT)
    warmup = warmup if warmup is not None else (QUICK_WARMUP if quick else DEFAULT_WARMUP)
    if repeat < 1 or warmup < 0:
        raise ValueError("repeat must be >= 1 and warmup >= 0")
    sweep_repeat = 1 if quick else min(repeat, SWEEP_REPEAT)
    report = run_benchmark(repeat, warmup, sweep_repeat)
    if echo:
        print(markdown_report(report))
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
        report["json_path"] = str(json_path)
    return report


if __name__ == "__main__":
    import sys

    main(sys.argv[1:] or None)
