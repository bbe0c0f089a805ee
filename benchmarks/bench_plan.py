"""Speed and memory benchmark: UFACET flight planning, NSTTF case of the issue and a 10,000-heliostat field.

Rows (each timed ``repeat`` times after ``warmup`` untimed calls, one process):

``NSTTF sun + tracking + canting``
    :func:`pihim.planning.ufacet.track_at`: NREL SPA sun position (pvlib),
    tracking of the 218 NSTTF heliostats toward OpenCSP's UFACET aim point
    (60, 8.8, 28.9) m at 2021-05-13 13:00 MDT, frames and design canting.
    The real field from ``../shared/data/nsttf`` when present, else the
    embedded NSTTF-like field (the report says which).
``NSTTF planning``
    :func:`pihim.planning.ufacet.plan_ufacet` on that pose: targets, lines,
    camera positions on the altitude grid, every sight line, framing, flux,
    pass order and WGS84 waypoints.
``NSTTF full plan``
    Both of the above plus the home point and the split into flights
    (:func:`pihim.planning.endurance.split_flights`). Target: <= 1 s (the
    polarimetric scoring comes on top); planning alone <= 300 ms. Not
    included: the facet captures, route and coverage that
    :func:`pihim.planning.pipeline.build_plan` (and ``pihim plan``) add,
    nor the command's imports, exports and figure (``bench_cli`` times
    ``pihim plan`` as a process).
``radial N full plan``
    A radial-staggered field of N heliostats around a 200 m tower aiming at
    195 m (:func:`pihim.field.layout.radial_staggered_field`), same sun:
    tracking, canting, planning and flights. Target for N = 10,000: <= 30 s.

Figures: median, p10 and p90 wall time; the tracemalloc peak of one call
(numpy allocations included); the share of CPU other processes took. The
NSTTF case summary (passes, waypoints, first pass) is printed below the
table next to OpenCSP's figures from the issue; ``--nsttf-table`` also prints
the per-pass table used in ``docs/opencsp-comparison.md``.

Run ``python benchmarks/run.py --only bench_plan`` or this file directly.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pihim.field.kinematics import track_field
from pihim.field.layout import (
    NSTTF_TOWER,
    UFACET_AIM_POINT,
    Field,
    Tower,
    load_field,
    nsttf_like_field,
    radial_staggered_field,
)
from pihim.planning.endurance import DroneEndurance, split_flights, throughput
from pihim.planning.scoring import score_passes
from pihim.planning.lines import alignment_summary, pass_alignment
from pihim.planning.ufacet import home_waypoint, plan_ufacet, track_at
from pihim.sky.sun import NSTTF, sun_position

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness

COUNTS = harness.Counts(repeat=10, warmup=2, quick_repeat=3, quick_warmup=1, cap_quick=True)
RESULTS_PATH = Path(__file__).resolve().parent / "results" / "plan.json"
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nsttf"
CASE_TIME = "2021-05-13T13:00:00-06:00"
RADIAL_SIZES = (10_000,)
BIG_TOWER = Tower(height_m=200.0, x_min_m=-10.0, x_max_m=10.0, y_min_m=-10.0, y_max_m=10.0, target=(0.0, 0.0, 195.0))
#: OpenCSP's figures for this case, as quoted in the issue.
OPENCSP = {"passes": 26, "waypoints": 53, "first_pass": "5W5 ... 12W14", "pitch_deg": -73.8, "altitude_m": 19.0,
           "heading_deg": 313.6, "time_s": "38-52"}


def nsttf_field() -> tuple[Field, str]:
    """The real NSTTF field from ../shared when present, else the embedded NSTTF-like field."""
    if (SHARED / "heliostats.csv").is_file():
        return load_field(SHARED / "heliostats.csv", SHARED / "facet_centroids.csv", tower=NSTTF_TOWER), \
            "NSTTF survey (../shared/data/nsttf)"
    return nsttf_like_field(), "embedded NSTTF-like field"


def nsttf_full(field: Field) -> tuple[Any, tuple[Any, ...]]:
    """The issue's NSTTF case end to end: sun, tracking, canting, passes, flights."""
    _, pose = track_at(field, CASE_TIME, aim_point=UFACET_AIM_POINT, site=NSTTF)
    res = plan_ufacet(field, pose, aim_point=UFACET_AIM_POINT, origin=NSTTF)
    home = home_waypoint(field, origin=NSTTF)
    return res, split_flights(res.passes, home, origin=NSTTF, tower=field.tower)


def radial_full(field: Field, sun: np.ndarray, *, scored: bool = False) -> tuple[Any, tuple[Any, ...]]:
    """A large radial field end to end (sun given); optionally with polarimetric scoring and shifts."""
    aim = field.default_aim_point
    pose = track_field(field, sun, aim)
    res = plan_ufacet(field, pose, aim_point=aim, origin=NSTTF)
    passes = res.passes
    if scored:
        passes = score_passes(passes, pose, sun, aim_point=aim, origin=NSTTF)
    home = home_waypoint(field, origin=NSTTF)
    return res, split_flights(passes, home, origin=NSTTF, tower=field.tower)


def nsttf_full_scored(field: Field) -> tuple[Any, ...]:
    """The NSTTF case end to end including polarimetric scoring and contrast-raising shifts."""
    sun, pose = track_at(field, CASE_TIME, aim_point=UFACET_AIM_POINT, site=NSTTF)
    res = plan_ufacet(field, pose, aim_point=UFACET_AIM_POINT, origin=NSTTF)
    passes = score_passes(res.passes, pose, sun.vector, aim_point=UFACET_AIM_POINT, origin=NSTTF)
    home = home_waypoint(field, origin=NSTTF)
    return split_flights(passes, home, origin=NSTTF, tower=field.tower)


def case_summary(res: Any, flights: Sequence[Any]) -> dict[str, Any]:
    """Figures of a plan comparable with OpenCSP's."""
    passes = res.passes
    line = next((p for p in passes if ("6W6", "5W5") in p.pairs), passes[0])
    tp = throughput(flights, DroneEndurance())
    return {
        "passes": len(passes),
        "feasible_passes": sum(p.feasible for p in passes),
        "pass_waypoints": sum(len(p.waypoints) for p in passes),
        "captures": res.n_captures,
        "flight_waypoints": sum(len(f.waypoints) for f in flights),
        "flights": len(flights),
        "flight_minutes": [round(f.duration_s / 60.0, 1) for f in flights],
        "heliostats_assessed": len(res.assessed),
        "heliostats_unassessed": len(res.unassessed),
        "min_altitude_m": res.min_altitude_m,
        "altitudes_m": sorted({round(p.altitude_m, 2) for p in passes}),
        "pitch_range_deg": [min(p.gimbal_pitch_deg for p in passes), max(p.gimbal_pitch_deg for p in passes)],
        "line_5W5": {"huas": [h for h in dict.fromkeys(h for h, _ in line.pairs)], "azimuth_deg": line.azimuth_deg,
                     "altitude_m": line.altitude_m, "pitch_deg": line.gimbal_pitch_deg, "index": line.index},
        "first_pass": {"huas": [h for h in dict.fromkeys(h for h, _ in passes[0].pairs)],
                       "azimuth_deg": passes[0].azimuth_deg, "altitude_m": passes[0].altitude_m,
                       "pitch_deg": passes[0].gimbal_pitch_deg},
        "heliostats_per_hour": tp.heliostats_per_hour,
        "heliostats_per_flight_hour": tp.heliostats_per_flight_hour,
    }


def pass_table(res: Any, field: Field | None = None, pose: Any = None) -> str:
    """Markdown table of every pass (for docs/opencsp-comparison.md).

    With ``field`` and ``pose``, columns give the azimuth of the vertical
    plane of the HUAs' tracking normals (folded to the travel sense), the
    largest angle between the pass and a HUA's plane and the largest
    distance of a capture from its HUA's plane
    (:func:`pihim.planning.lines.pass_alignment`).
    """
    plane = field is not None and pose is not None
    align = {a.index: a for a in pass_alignment(res.passes, field, pose)} if plane else {}
    head = "| # | HUAs (first ... last) | n HUAs | captures | travel az deg |"
    head += " normals' plane az deg | max dev deg | max camera offset m |" if plane else ""
    lines = [head + " altitude m | pitch deg (median) | issues |",
             "|---:|---|---:|---:|---:|" + ("---:|---:|---:|" if plane else "") + "---:|---:|---|"]
    for p in res.passes:
        huas = list(dict.fromkeys(h for h, _ in p.pairs))
        span = f"{huas[0]} ... {huas[-1]}" if huas else "-"
        blocked = sum("blocked" in i for i in p.issues)
        notes = [f"{blocked} blocked pair(s)"] if blocked else []
        notes += [i for i in p.issues if i.startswith("concentrated")]
        cell = ""
        if plane:
            a = align.get(p.index)
            cell = (f" {a.plane_azimuth_deg:.1f} | {a.max_deviation_deg:.1f} | {a.max_camera_offset_m:.1f} |"
                    if a is not None else " - | - | - |")
        lines.append(f"| {p.index} | {span} | {len(huas)} | {len(p.pairs)} | {p.azimuth_deg:.1f} |{cell} "
                     f"{p.altitude_m:.1f} | {p.gimbal_pitch_deg:.1f} | {'; '.join(notes)} |")
    return "\n".join(lines)


def run_benchmark(repeat: int, warmup: int, radial_sizes: Sequence[int] = RADIAL_SIZES) -> dict[str, Any]:
    """Time every row; return the JSON-ready report."""
    field, source = nsttf_field()
    track_at(field, CASE_TIME, aim_point=UFACET_AIM_POINT, site=NSTTF)  # imports pvlib once, outside the timing
    _, pose = track_at(field, CASE_TIME, aim_point=UFACET_AIM_POINT, site=NSTTF)
    sun = sun_position(NSTTF, CASE_TIME).vector
    rows: list[tuple[str, str, int, Callable[[], Any], int]] = [
        ("nsttf_track", "NSTTF sun + tracking + canting", len(field),
         lambda: track_at(field, CASE_TIME, aim_point=UFACET_AIM_POINT, site=NSTTF), repeat),
        ("nsttf_plan", "NSTTF planning (plan_ufacet)", len(field),
         lambda: plan_ufacet(field, pose, aim_point=UFACET_AIM_POINT, origin=NSTTF), repeat),
        ("nsttf_full", "NSTTF full plan (sun, tracking, canting, passes, flights)", len(field),
         lambda: nsttf_full(field), repeat),
        ("nsttf_full_scored", "NSTTF full plan + polarimetric scoring and shifts", len(field),
         lambda: nsttf_full_scored(field), repeat),
    ]
    radial_fields = {}
    for n in radial_sizes:
        fld = radial_staggered_field(n, tower=BIG_TOWER)
        radial_fields[n] = fld
        rows.append((f"radial_{n}_full", f"radial {n:,} full plan (tracking, canting, passes, flights)", n,
                     (lambda f=fld: radial_full(f, sun)), max(1, min(repeat, 3))))
        rows.append((f"radial_{n}_scored", f"radial {n:,} full plan + polarimetric scoring and shifts", n,
                     (lambda f=fld: radial_full(f, sun, scored=True)), max(1, min(repeat, 3))))
    results = {
        key: {"label": label, "heliostats": n,
              **harness.measure(fn, reps, min(warmup, reps if key.startswith("nsttf") else 1), pause_gc=False)}
        for key, label, n, fn, reps in rows
    }
    res, flights = nsttf_full(field)
    summary = case_summary(res, flights)
    summary["alignment"] = alignment_summary(res.passes, field, pose)
    radial_summary = {}
    for n, fld in radial_fields.items():
        rres, rfl = radial_full(fld, sun)
        radial_summary[str(n)] = {"passes": len(rres.passes), "assessed": len(rres.assessed),
                                  "captures": rres.n_captures, "flights": len(rfl),
                                  "heliostats_per_hour": throughput(rfl).heliostats_per_hour}
    targets = [
        harness.target("NSTTF full plan incl. tracking, canting and polarimetric scoring",
                       results["nsttf_full_scored"]["median_ms"], 1000.0, "ms"),
        harness.target("NSTTF planning alone", results["nsttf_plan"]["median_ms"], 300.0, "ms"),
    ]
    if 10_000 in radial_sizes:
        targets.append(harness.target("10,000-heliostat radial field, full plan incl. scoring",
                                      results["radial_10000_scored"]["median_ms"], 30_000.0, "ms"))
    return {
        "benchmark": "bench_plan",
        "settings": {"repeat": repeat, "warmup": warmup, "time": CASE_TIME, "aim_point": list(UFACET_AIM_POINT),
                     "nsttf_source": source, "radial_sizes": list(radial_sizes),
                     "radial_tower_height_m": BIG_TOWER.height_m},
        "results": results,
        "nsttf_case": summary,
        "radial_case": radial_summary,
        "opencsp": OPENCSP,
        "targets": targets,
        "machine": harness.machine_info(),
        "_plan": (res, field, pose),
    }


def markdown_report(report: dict[str, Any]) -> str:
    """The timings, the targets and the NSTTF case next to OpenCSP's figures, as markdown."""
    s = report["settings"]
    lines = [
        (f"Planning benchmark: {s['time']}, aim point {tuple(s['aim_point'])}; NSTTF source: {s['nsttf_source']}; "
        f"{s['repeat']} timed calls after {s['warmup']} warm-ups (radial rows: at most 3); "
        f"{report['machine']['cpu_count']} CPUs."),
        "",
        "| Row | Heliostats | Median ms | p10 ms | p90 ms | Peak MB (tracemalloc) | Other CPU % |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in report["results"].values():
        lines.append(f"| {r['label']} | {r['heliostats']:,} | {harness.ms_cells(r, '.1f')} | {r['peak_mb']:.1f} "
                     f"| {harness.other_pct(r['other_cpu'])} |")
    lines += harness.target_table(report["targets"], spec=".1f")
    c, o = report["nsttf_case"], report["opencsp"]
    ln = c["line_5W5"]
    lines += [
        "",
        "| NSTTF case | pihim | OpenCSP (issue) |",
        "|---|---|---|",
        f"| Scan passes | {c['passes']} ({c['feasible_passes']} feasible) | {o['passes']} |",
        (f"| Waypoints | {c['pass_waypoints']} in passes ({c['captures']} captures); {c['flight_waypoints']} with "
        f"take-off/transit/return in {c['flights']} flight(s) {c['flight_minutes']} min | {o['waypoints']} |"),
        (f"| Line through 5W5 | HUAs {ln['huas'][0]} ... {ln['huas'][-1]} (5W5 is the target of 6W6), pass "
        f"{ln['index']}, travel {ln['azimuth_deg']:.1f} deg | {o['first_pass']}, heading {o['heading_deg']} deg |"),
        f"| Altitude | {ln['altitude_m']:.1f} m (min safe {c['min_altitude_m']:.1f} m) | about {o['altitude_m']:g} m |",
        (f"| Gimbal pitch | {ln['pitch_deg']:.1f} deg (all passes {c['pitch_range_deg'][0]:.1f} to "
        f"{c['pitch_range_deg'][1]:.1f}) | {o['pitch_deg']} deg |"),
        f"| Heliostats assessed | {c['heliostats_assessed']} ({c['heliostats_unassessed']} without a target) | - |",
        (f"| Passes vs the HUAs' normals' planes | {c['alignment']['median_deviation_deg']:.1f} deg median, "
         f"{c['alignment']['max_deviation_deg']:.1f} max; captures {c['alignment']['median_camera_offset_m']:.1f} m "
         f"median, {c['alignment']['max_camera_offset_m']:.1f} m max from the plane; waypoints "
         f"{c['alignment']['max_off_line_m']:.1e} m off each pass's straight line | straight sections along "
         "the normals' planes |"),
        (f"| Heliostats per hour (one drone, swaps included) | {c['heliostats_per_hour']:.0f} | - "
        "(paper: ~36 today, 50-100 hoped) |"),
        f"| Planning time | {report['results']['nsttf_full']['median_ms']:.0f} ms | {o['time_s']} s |",
    ]
    for n, r in report["radial_case"].items():
        lines.append(f"\nRadial {int(n):,}: {r['passes']} passes, {r['assessed']:,} HUAs assessed, "
                     f"{r['captures']:,} captures, {r['flights']} flights, {r['heliostats_per_hour']:.0f} "
                     "heliostats per hour for one drone.")
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
    nsttf_table: bool = False,
) -> dict[str, Any]:
    """Run the benchmark, print the markdown report and write the JSON report.

    Parameters
    ----------
    argv : sequence of str, optional
        Command-line arguments (``--repeat N``, ``--warmup N``, ``--quick``,
        ``--json PATH``, ``--radial N [N ...]``, ``--nsttf-table``); ``None``
        or empty reads nothing.
    repeat : int, optional
        Timed calls per NSTTF row; default 10, at most 3 with ``quick``
        (radial rows: at most 3).
    quick : bool
        Fewer calls, for a fast look.
    warmup : int, optional
        Untimed calls before timing; default 2, or 1 with ``quick``.
    radial_sizes : sequence of int
        Sizes of the radial fields planned end to end.
    json_path : pathlib.Path or None
        Where to write the JSON report (``benchmarks/results/``, git-ignored);
        ``None`` writes nothing.
    echo : bool
        Print the markdown report.
    nsttf_table : bool
        Also print the per-pass table of the NSTTF case.

    Returns
    -------
    dict
        The JSON-ready report (``targets`` summarised by ``run.py``).
    """
    def configure(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--radial", type=int, nargs="*", metavar="N", help="sizes of the radial fields")
        parser.add_argument("--nsttf-table", action="store_true", help="also print the per-pass NSTTF table")

    o = harness.options(argv, description="Speed of pihim's UFACET planner (NSTTF case and a large field).",
                        counts=COUNTS, repeat=repeat, warmup=warmup, quick=quick, json_path=json_path,
                        configure=configure)
    if o.args is not None:
        radial_sizes = radial_sizes if o.args.radial is None else tuple(o.args.radial)
        nsttf_table = nsttf_table or o.args.nsttf_table
    report = run_benchmark(o.repeat, o.warmup, tuple(radial_sizes))
    res, fld, pose = report.pop("_plan")
    if echo:
        print(markdown_report(report))
        if nsttf_table:
            print()
            print(pass_table(res, fld, pose))
    harness.write_json(report, o.json_path)
    return report


if __name__ == "__main__":
    main(sys.argv[1:] or None)
