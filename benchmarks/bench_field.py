"""Speed benchmark: heliostat field tracking, canting and geometry.

Rows (each timed ``repeat`` times after ``warmup`` untimed calls, in one
process, one after the other; sun at zenith 30 deg, azimuth 235 deg, the
paper's Fig. 2c-d):

``NSTTF tracking``
    :func:`pihim.field.kinematics.tracking_normals` for the 218 heliostats of
    the embedded NSTTF-like field, aiming at the tower target, pivot offset
    iterated to 1e-12.
``NSTTF tracking + canting``
    :func:`pihim.field.kinematics.track_field`: tracking, heliostat frames,
    on-axis design canting (focal length = slant range) and the 5,450 facet
    normals and centres in ENU -- everything needed for one instant.
``NSTTF geometry``
    Facet corners (218 x 25 x 4 points), mirror outlines and back-structure
    segments of an already tracked field.
``radial N tracking``
    ``tracking_normals`` for radial-staggered fields of 10,000 and 100,000
    heliostats (:func:`pihim.field.layout.radial_staggered_field`, NSTTF
    heliostats around a 200 m tower aiming at 195 m).
``radial N generation``
    Building the 100,000-heliostat field (layout and name parsing).

Figures: median, p10 and p90 wall time; the tracemalloc peak of one call
(numpy allocations included); the bytes of the main outputs; the share of
CPU other processes used during the timing (``/proc/stat``). Target: NSTTF
tracking + canting for one instant well under 10 ms (required: <= 10 ms).

Run ``python benchmarks/run.py --only bench_field`` or this file directly.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pihim.field.kinematics import track_field, tracking_normals
from pihim.field.layout import Tower, nsttf_like_field, radial_staggered_field

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness

COUNTS = harness.Counts(repeat=30, warmup=3, quick_repeat=5, quick_warmup=1, cap_quick=True)
RESULTS_PATH = Path(__file__).resolve().parent / "results" / "field.json"
SUN_ZENITH_DEG, SUN_AZIMUTH_DEG = 30.0, 235.0
RADIAL_SIZES = (10_000, 100_000)
BIG_TOWER = Tower(height_m=200.0, x_min_m=-10.0, x_max_m=10.0, y_min_m=-10.0, y_max_m=10.0, target=(0.0, 0.0, 195.0))
TARGETS = (("NSTTF tracking + canting, one instant (218 heliostats)", "nsttf_track_cant", 10.0, "ms"),)


def _sun() -> np.ndarray:
    z, a = math.radians(SUN_ZENITH_DEG), math.radians(SUN_AZIMUTH_DEG)
    return np.array([math.sin(z) * math.sin(a), math.sin(z) * math.cos(a), math.cos(z)])


def _nbytes(obj: Any) -> int:
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if isinstance(obj, (tuple, list)):
        return sum(_nbytes(o) for o in obj)
    if hasattr(obj, "__dataclass_fields__"):
        return sum(_nbytes(getattr(obj, k)) for k in obj.__dataclass_fields__ if k != "field")
    return 0


def run_benchmark(repeat: int, warmup: int, radial_sizes: Sequence[int] = RADIAL_SIZES) -> dict[str, Any]:
    """Time every row; return the JSON-ready report."""
    sun = _sun()
    nsttf = nsttf_like_field()
    aim = nsttf.default_aim_point
    pose = track_field(nsttf, sun)
    rows: list[tuple[str, str, int, Callable[[], Any], int]] = [
        ("nsttf_track", "NSTTF tracking (normals + mirror centres)", len(nsttf),
         lambda: tracking_normals(nsttf.pivots, sun, aim, nsttf.spec.pivot_offset_m), repeat),
        ("nsttf_track_cant", "NSTTF tracking + frames + canting (facet normals/centres)", len(nsttf),
         lambda: track_field(nsttf, sun), repeat),
        ("nsttf_geometry", "NSTTF facet corners + outlines + back structure", len(nsttf),
         lambda: (pose.facet_corners(), pose.mirror_outline(), pose.back_structure()), repeat),
    ]
    fields = {}
    for n in radial_sizes:
        fld = radial_staggered_field(n, tower=BIG_TOWER)
        fields[n] = fld
        tgt = fld.default_aim_point
        rows.append((f"radial_{n}_track", f"radial {n:,} tracking", n,
                     (lambda f=fld, a=tgt: tracking_normals(f.pivots, sun, a, f.spec.pivot_offset_m)), repeat))
    if radial_sizes:
        n_big = max(radial_sizes)
        rows.append((f"radial_{n_big}_generate", f"radial {n_big:,} field generation", n_big,
                     lambda: radial_staggered_field(n_big, tower=BIG_TOWER), max(1, min(repeat, 5))))
    results = {
        key: {"label": label, "heliostats": n, **harness.measure(fn, reps, min(warmup, reps), nbytes=_nbytes)}
        for key, label, n, fn, reps in rows
    }
    extent = {str(n): float(np.hypot(f.pivots[:, 0], f.pivots[:, 1]).max()) for n, f in fields.items()}
    return {
        "benchmark": "bench_field",
        "settings": {"repeat": repeat, "warmup": warmup, "sun_zenith_deg": SUN_ZENITH_DEG,
                     "sun_azimuth_deg": SUN_AZIMUTH_DEG, "radial_sizes": list(radial_sizes),
                     "radial_tower_height_m": BIG_TOWER.height_m, "radial_field_radius_m": extent},
        "results": results,
        "targets": [harness.target(name, results[key]["median_ms"], lim, unit) for name, key, lim, unit in TARGETS],
        "machine": harness.machine_info(),
    }


def markdown_report(report: dict[str, Any]) -> str:
    """The results as a markdown table plus the targets."""
    s = report["settings"]
    radius = ", ".join(f"{int(k):,}: {v:.0f} m" for k, v in s["radial_field_radius_m"].items())
    lines = [
        (
            f"Field benchmark: sun zenith {s['sun_zenith_deg']:g} deg, azimuth {s['sun_azimuth_deg']:g} deg; "
            f"{s['repeat']} timed calls after {s['warmup']} warm-ups; {report['machine']['cpu_count']} CPUs."
            + (f" Radial fields around a {s['radial_tower_height_m']:g} m tower (radius {radius})." if radius else "")
        ),
        "",
        "| Row | Heliostats | Median ms | p10 ms | p90 ms | Peak MB (tracemalloc) | Output MB | Other CPU % |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in report["results"].values():
        lines.append(
            f"| {r['label']} | {r['heliostats']:,} | {harness.ms_cells(r, '.3f')} "
            f"| {r['peak_mb']:.2f} | {r['output_mb']:.2f} | {harness.other_pct(r['other_cpu'])} |"
        )
    lines += harness.target_table(report["targets"], spec=".3f")
    lines += harness.busy_warning(r["other_cpu"] for r in report["results"].values())
    return "\n".join(lines)


def main(
    argv: Sequence[str] | None = None,
    *,
    repeat: int | None = None,
    quick: bool = False,
    warmup: int | None = None,
    radial_sizes: Sequence[int] = RADIAL_SIZES,
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
        Timed calls per row; default 30, at most 5 with ``quick``.
    quick : bool
        Fewer calls, for a fast look.
    warmup : int, optional
        Untimed calls before timing; default 3, or 1 with ``quick``.
    radial_sizes : sequence of int
        Sizes of the radial-staggered fields to track.
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
    o = harness.options(argv, description="Speed of pihim's heliostat field tracking and canting.", counts=COUNTS,
                        repeat=repeat, warmup=warmup, quick=quick, json_path=json_path)
    report = run_benchmark(o.repeat, o.warmup, tuple(radial_sizes))
    return harness.publish(report, markdown_report, o.json_path, echo=echo)


if __name__ == "__main__":
    main(sys.argv[1:] or None)
