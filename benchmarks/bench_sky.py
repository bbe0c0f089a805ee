"""Speed benchmark: all-sky skylight maps and sun positions.

Rows (each timed ``repeat`` times after ``warmup`` untimed calls, in one
process, one after the other):

``rayleigh map 0.5 deg``
    :func:`pihim.sky.model.sky_map` with the default ``SkyModel`` (Rayleigh,
    CIE clear-sky S0): 720 azimuths x 180 zeniths = 129,600 directions, S0,
    DoLP and AoP arrays out. The grid directions and their meridian frames
    are cached per resolution (built once per process), as the CLI uses it.
``berry map 0.5 deg``
    The same with the Berry-Dennis-Lee model.
``rayleigh map, cold grid``
    As the first row but with the grid cache cleared before every call
    (directions and frames rebuilt each time).
``SkyModel.stokes, 129,600 dirs`` (Rayleigh and Berry)
    The generic interface other modules call: arbitrary directions, default
    frame computed and inputs validated on every call; Stokes (..., 4) out.
``sun_position x1`` / ``x1000``
    pvlib's NREL SPA (numpy) through :func:`pihim.sky.sun.sun_position`.

Figures: median, p10 and p90 wall time, the tracemalloc peak of one call
(Python allocations, numpy included) and the share of CPU used by other
processes during the timing (from ``/proc/stat``; only rows near 0 % are
trustworthy). Target: Rayleigh map <= 20 ms median on the 2-core machine.

Run ``python benchmarks/run.py --only bench_sky`` or this file directly.
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
import pandas as pd

from pihim.sky import model as sky_model_mod
from pihim.sky.model import SkyModel, sky_map
from pihim.sky.sun import NSTTF, direction_from_angles, sun_position

DEFAULT_REPEAT = 30
DEFAULT_WARMUP = 3
QUICK_REPEAT = 5
QUICK_WARMUP = 1
RESULTS_PATH = Path(__file__).resolve().parent / "results" / "sky.json"
SUN = direction_from_angles(30.0, 235.0)  # the paper's Fig. 2c-d
TARGETS = (("Rayleigh all-sky map at 0.5 deg (S0+DoLP+AoP)", "rayleigh_map", 20.0, "ms"),)


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


def measure(fn: Callable[[], Any], repeat: int, warmup: int) -> dict[str, Any]:
    """Median/p10/p90 ms over ``repeat`` calls after ``warmup``; tracemalloc peak of one extra call."""
    for _ in range(warmup):
        fn()
    gc.collect()
    times = []
    t0 = _cpu_times()
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    t1 = _cpu_times()
    tracemalloc.start()
    fn()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    ms = np.array(times) * 1e3
    load = _other_load(t0, t1)
    return {
        "median_ms": float(np.median(ms)),
        "p10_ms": float(np.percentile(ms, 10)),
        "p90_ms": float(np.percentile(ms, 90)),
        "peak_mb": peak / 1e6,
        "other_cpu": load,
        "repeat": repeat,
    }


def _directions(n_zen: int = 180, n_az: int = 720) -> np.ndarray:
    zz, aa = np.meshgrid((np.arange(n_zen) + 0.5) * 90.0 / n_zen, (np.arange(n_az) + 0.5) * 360.0 / n_az, indexing="ij")
    return direction_from_angles(zz, aa)


def run_benchmark(repeat: int, warmup: int) -> dict[str, Any]:
    """Time every row; return the JSON-ready report."""
    rayleigh, berry = SkyModel(), SkyModel(kind="berry")
    dirs = _directions()
    times_1000 = pd.date_range("2024-06-21T06:00:00-06:00", periods=1000, freq="min")

    def cold() -> Any:
        sky_model_mod._grid_geometry.cache_clear()
        return sky_map(rayleigh, SUN, 0.5)

    rows: list[tuple[str, str, str, Callable[[], Any]]] = [
        ("rayleigh_map", "Rayleigh map 0.5 deg (cached grid)", "129,600", lambda: sky_map(rayleigh, SUN, 0.5)),
        ("berry_map", "Berry map 0.5 deg (cached grid)", "129,600", lambda: sky_map(berry, SUN, 0.5)),
        ("rayleigh_map_cold", "Rayleigh map 0.5 deg, grid rebuilt", "129,600", cold),
        ("rayleigh_stokes", "SkyModel.stokes Rayleigh (generic)", "129,600", lambda: rayleigh.stokes(dirs, SUN)),
        ("berry_stokes", "SkyModel.stokes Berry (generic)", "129,600", lambda: berry.stokes(dirs, SUN)),
        ("sun_1", "sun_position, 1 time", "1", lambda: sun_position(NSTTF, "2024-06-21T10:00:00-06:00")),
        ("sun_1000", "sun_position, 1000 times", "1,000", lambda: sun_position(NSTTF, times_1000)),
    ]
    results = {}
    for key, label, n, fn in rows:
        r = measure(fn, repeat, warmup)
        results[key] = {"label": label, "items": n, **r}
    targets = []
    for name, key, limit, unit in TARGETS:
        measured = results[key]["median_ms"]
        targets.append({"target": name, "required": f"<= {limit:g} {unit}", "measured": measured, "unit": unit,
                        "passed": measured <= limit})
    return {
        "benchmark": "bench_sky",
        "settings": {"repeat": repeat, "warmup": warmup, "sun_zenith_deg": 30.0, "sun_azimuth_deg": 235.0},
        "results": results,
        "targets": targets,
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                    "python": platform.python_version(), "numpy": np.__version__},
    }


def markdown_report(report: dict[str, Any]) -> str:
    """The results as a markdown table plus the targets."""
    s = report["settings"]
    lines = [
        (
            f"Sky benchmark: sun zenith {s['sun_zenith_deg']:g} deg, azimuth {s['sun_azimuth_deg']:g} deg; "
            f"{s['repeat']} timed calls after {s['warmup']} warm-ups; {report['machine']['cpu_count']} CPUs."
        ),
        "",
        "| Row | Directions | Median ms | p10 ms | p90 ms | Peak MB (tracemalloc) | Other CPU % |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in report["results"].values():
        other = "-" if r["other_cpu"] is None else f"{100 * r['other_cpu']:.0f}"
        lines.append(
            f"| {r['label']} | {r['items']} | {r['median_ms']:.2f} | {r['p10_ms']:.2f} | {r['p90_ms']:.2f} "
            f"| {r['peak_mb']:.1f} | {other} |"
        )
    lines += ["", "| Target | Required | Measured | Verdict |", "|---|---|---:|---|"]
    for t in report["targets"]:
        verdict = "PASS" if t["passed"] else "FAIL"
        lines.append(f"| {t['target']} | {t['required']} | {t['measured']:.2f} {t['unit']} | {verdict} |")
    busy = [r for r in report["results"].values() if r["other_cpu"] is not None and r["other_cpu"] > 0.05]
    if busy:
        warning = (
            f"Warning: other processes used more than 5 % of the CPUs during {len(busy)} row(s); "
            "those figures are inflated."
        )
        lines += ["", warning]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None, *, repeat: int | None = None, quick: bool = False,
         warmup: int | None = None, json_path: Path | None = RESULTS_PATH, echo: bool = True) -> dict[str, Any]:
    """Run the benchmark, print the markdown table and write the JSON report.

    Parameters
    ----------
    argv : sequence of str, optional
        Command-line arguments (``--repeat N``, ``--warmup N``, ``--quick``,
        ``--json PATH``); ``None`` reads nothing (use the keyword defaults).
    repeat, warmup : int, optional
        Timed and untimed calls per row; default 30 and 3, or 5 and 1 with ``quick``.
    quick : bool
        Fewer calls, for a fast look.
    json_path : pathlib.Path or None
        Where to write the JSON report; ``None`` writes nothing.
    echo : bool
        Print the markdown report.
    """
    if argv:
        p = argparse.ArgumentParser(description="Speed of pihim's sky maps and sun positions.")
        p.add_argument("--repeat", type=int)
        p.add_argument("--warmup", type=int)
        p.add_argument("--quick", action="store_true")
        p.add_argument("--json", type=Path, default=json_path)
        a = p.parse_args(list(argv))
        repeat = a.repeat if a.repeat is not None else repeat
        warmup = a.warmup if a.warmup is not None else warmup
        quick = quick or a.quick
        json_path = a.json
    repeat = repeat if repeat is not None else (QUICK_REPEAT if quick else DEFAULT_REPEAT)
    warmup = warmup if warmup is not None else (QUICK_WARMUP if quick else DEFAULT_WARMUP)
    if repeat < 1 or warmup < 0:
        raise ValueError("repeat must be >= 1 and warmup >= 0")
    report = run_benchmark(repeat, warmup)
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
