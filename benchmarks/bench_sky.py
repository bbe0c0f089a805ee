"""Speed benchmark: all-sky skylight maps and sun positions.

Rows (each timed ``repeat`` times after ``warmup`` untimed calls, in one
process, one after the other):

``rayleigh map 0.5 deg``
    :func:`pihim.sky.model.sky_map` with the default ``SkyModel`` (Rayleigh,
    CIE clear-sky S0): 720 azimuths x 180 zeniths = 129,600 directions, S0,
    DoLP and AoP arrays out. The grid directions and their meridian frames
    are cached per resolution (built once per process): a program that
    makes many maps pays for the grid once.
``berry map 0.5 deg``
    The same with the Berry-Dennis-Lee model.
``rayleigh map, cold grid``
    As the first row but with the grid cache cleared before every call
    (directions and frames rebuilt each time): what ``pihim sky``, which
    makes one map per process, pays.
``SkyModel.stokes, 129,600 dirs`` (Rayleigh and Berry)
    The generic interface other modules call: arbitrary directions, default
    frame computed and inputs validated on every call; Stokes (..., 4) out.
``sun_position x1`` / ``x1000``
    pvlib's NREL SPA (numpy) through :func:`pihim.sky.sun.sun_position`.

Figures: median, p10 and p90 wall time, the tracemalloc peak of one call
(Python allocations, numpy included) and the share of CPU used by other
processes during the timing (from ``/proc/stat``; only rows near 0 % are
trustworthy). Target: Rayleigh map <= 20 ms median on the 2-core machine, with the
grid cached and rebuilt.

Run ``python benchmarks/run.py --only bench_sky`` or this file directly.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pihim.sky import model as sky_model_mod
from pihim.sky.model import SkyModel, sky_map
from pihim.sky.sun import NSTTF, direction_from_angles, sun_position

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness

COUNTS = harness.Counts(repeat=30, warmup=3, quick_repeat=5, quick_warmup=1)
RESULTS_PATH = Path(__file__).resolve().parent / "results" / "sky.json"
SUN = direction_from_angles(30.0, 235.0)  # the paper's Fig. 2c-d
TARGETS = (("Rayleigh all-sky map at 0.5 deg (S0+DoLP+AoP), grid cached", "rayleigh_map", 20.0, "ms"),
           ("the same, grid rebuilt: a one-off map, as `pihim sky` makes", "rayleigh_map_cold", 20.0, "ms"))


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
    results = {
        key: {"label": label, "items": n, **harness.measure(fn, repeat, warmup, pause_gc=False)}
        for key, label, n, fn in rows
    }
    return {
        "benchmark": "bench_sky",
        "settings": {"repeat": repeat, "warmup": warmup, "sun_zenith_deg": 30.0, "sun_azimuth_deg": 235.0},
        "results": results,
        "targets": [harness.target(name, results[key]["median_ms"], lim, unit) for name, key, lim, unit in TARGETS],
        "machine": harness.machine_info(),
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
        lines.append(
            f"| {r['label']} | {r['items']} | {harness.ms_cells(r, '.2f')} | {r['peak_mb']:.1f} "
            f"| {harness.other_pct(r['other_cpu'])} |"
        )
    lines += harness.target_table(report["targets"], spec=".2f")
    lines += harness.busy_warning(r["other_cpu"] for r in report["results"].values())
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
    o = harness.options(argv, description="Speed of pihim's sky maps and sun positions.", counts=COUNTS,
                        repeat=repeat, warmup=warmup, quick=quick, json_path=json_path)
    report = run_benchmark(o.repeat, o.warmup)
    return harness.publish(report, markdown_report, o.json_path, echo=echo)


if __name__ == "__main__":
    main(sys.argv[1:] or None)
