"""pihim's flights next to OpenCSP's UFACET mission: NSTTF, 2021-05-13, every hour from 8:00 to 16:00.

For each hour, ``pihim.planning.pipeline.build_plan`` plans the issue's case
(surveyed NSTTF field from ``../shared/data/nsttf``, else the embedded
NSTTF-like field; aim point (60, 8.8, 28.9); at most 25 m) as ``pihim plan``
does, and the table gives what is flown: scan passes, flights (20 min
battery, 20 % reserve, at most 700 mission items each), the 3-D path length
from take-off to landing over all flights, the turns (changes of horizontal
direction of more than 30 deg), the captures, the share of the field's
heliostats imaged (planned coverage) and with a usable image, and the share
of the imaged HUAs' facets that show a heliostat's back (traced,
``pihim.planning.facets``). Three configurations are planned beside it
for reference: the same plan routed for distance alone (no charge per turn,
``RouteSettings(turn_cost_m=0)``), one capture per HUA in the planner's order
(the plan before issue 11's "every facet" and "shorter" parts) and the same
single captures with the route optimiser.

OpenCSP's UFACET mission for this case (13:00 -06:00) flies 5,363 m from
launch to return in 26 passes (the figure the issue quotes; OpenCSP was not
re-run here, and its mission is not known at other hours).

Targets, at every hour: distance <= 5,363 m, planned coverage >= 0.9 and
>= 95 % of the imaged HUAs' facets showing a heliostat's back -- on the
surveyed layout only (OpenCSP's mission flies it); on the embedded field the
rows are printed without a verdict.

Each plan is timed once (wall and CPU time, ``time.process_time``), with the
load average of the machine; the planner is deterministic.

Run ``python benchmarks/run.py --only bench_opencsp`` or this file directly
(``--hours 13`` for one hour).
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness
from bench_plan import nsttf_field

from pihim.field.layout import UFACET_AIM_POINT
from pihim.planning.pipeline import build_plan
from pihim.planning.route import RouteSettings
from pihim.sky.sun import NSTTF, parse_time

COUNTS = harness.Counts(repeat=1, warmup=0, quick_repeat=1, quick_warmup=0, cap_quick=True)
RESULTS_PATH = Path(__file__).resolve().parent / "results" / "opencsp.json"
DATE = "2021-05-13"
HOURS = tuple(range(8, 17))
#: OpenCSP's UFACET mission for the NSTTF case at 13:00 -06:00, as the issue quotes it.
OPENCSP = {"hour": 13, "distance_m": 5363.0, "passes": 26}
CONFIGS = {
    "pihim": {},
    "pihim, distance only (no charge per turn)": {"route": RouteSettings(turn_cost_m=0.0)},
    "single capture, route": {"facet_captures": False},
    "single capture, planner order": {"facet_captures": False, "route": False},
}


def plan_hour(field: Any, hour: int, **kwargs: Any) -> dict[str, Any]:
    """One plan and its figures (see the module docstring)."""
    when = parse_time(f"{DATE}T{hour:02d}:00:00-06:00")
    load0 = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    plan = build_plan(field, when, NSTTF, aim_point=UFACET_AIM_POINT, **kwargs)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    s = plan.summary
    fc = s.get("facet_coverage", {})
    return {
        "hour": hour,
        "passes": s["passes"],
        "flights": s["flights"],
        "distance_m": s["distance_m"],
        "turns": s["turns"],
        "captures": s["images"],
        "planned_coverage": s["coverage"]["planned"],
        "usable_coverage": s["coverage"]["either"],
        "facet_fraction": fc.get("fraction"),
        "huas": fc.get("huas"),
        "huas_complete": fc.get("huas_complete"),
        "flight_minutes": round(sum(m["duration_s"] for m in s["missions"]) / 60.0, 1),
        "longest_flight_min": round(max(m["duration_s"] for m in s["missions"]) / 60.0, 1),
        "max_mission_items": max(m["mission_items"] for m in s["missions"]),
        "rescued": len(s.get("rescued_huas", [])),
        "wall_s": round(wall, 2),
        "cpu_s": round(cpu, 2),
        "load_avg": round((load0 + os.getloadavg()[0]) / 2.0, 2),
        "seconds": s["seconds"],
    }


def field_is_surveyed(source: str) -> bool:
    """Whether :func:`bench_plan.nsttf_field` found the surveyed layout (the targets are for it alone)."""
    return source.startswith("NSTTF survey")


def run_benchmark(hours: Sequence[int] = HOURS, configs: Sequence[str] = tuple(CONFIGS)) -> dict[str, Any]:
    """Every hour, every configuration."""
    field, source = nsttf_field()
    build_plan(field, parse_time(f"{DATE}T13:00:00-06:00"), NSTTF, aim_point=UFACET_AIM_POINT,
               facet_captures=False, route=False, facet_report=False)  # imports and caches, untimed
    rows = {name: [plan_hour(field, h, **CONFIGS[name]) for h in hours] for name in configs}
    mine = rows.get("pihim", [])
    targets = []
    if mine and field_is_surveyed(source):  # OpenCSP's mission flies the surveyed layout: no verdict on another
        targets = [
            harness.target("pihim distance, every hour", max(r["distance_m"] for r in mine), OPENCSP["distance_m"],
                           "m"),
            harness.target("planned coverage, every hour", min(r["planned_coverage"] for r in mine), 0.9, "",
                           at_most=False),
            harness.target("facets showing a heliostat's back, every hour", min(r["facet_fraction"] for r in mine),
                           0.95, "", at_most=False),
        ]
    return {"benchmark": "bench_opencsp", "settings": {"date": DATE, "hours": list(hours), "source": source,
                                                       "aim_point": list(UFACET_AIM_POINT), "max_altitude_m": 25.0},
            "opencsp": OPENCSP, "rows": rows, "targets": targets, "machine": harness.machine_info()}


def markdown_report(report: dict[str, Any]) -> str:
    """The table for BENCHMARKS.md and docs/opencsp-comparison.md."""
    s = report["settings"]
    o = report["opencsp"]
    lines = [f"NSTTF ({s['source']}), {s['date']}, aim point {tuple(s['aim_point'])}, <= {s['max_altitude_m']:g} m; "
             f"{report['machine']['cpu_count']} CPUs. OpenCSP (13:00, as quoted by the issue): "
             f"{o['distance_m']:,.0f} m, {o['passes']} passes.", ""]
    for name, rows in report["rows"].items():
        lines += [f"**{name}**", "",
                  "| hour | distance m | vs OpenCSP | passes | flights | turns | captures | planned | usable | facets "
                  "| HUAs complete | flight min | max items | wall s | CPU s | load |",
                  "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in rows:
            facets = "-" if r["facet_fraction"] is None else f"{100 * r['facet_fraction']:.1f} %"
            complete = "-" if r["huas_complete"] is None else f"{r['huas_complete']}/{r['huas']}"
            lines.append(
                f"| {r['hour']:02d}:00 | {r['distance_m']:,.0f} | {r['distance_m'] / o['distance_m']:.2f} | "
                f"{r['passes']} | {r['flights']} | {r['turns']} | {r['captures']} | "
                f"{100 * r['planned_coverage']:.1f} % | {100 * r['usable_coverage']:.1f} % | {facets} | {complete} | "
                f"{r['flight_minutes']:.1f} | {r['max_mission_items']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
                f"{r['load_avg']:.1f} |")
        lines.append("")
    if report["targets"]:
        lines += harness.target_table(report["targets"], spec=".3f", unit_spec={"m": ",.0f"})
    elif not field_is_surveyed(s["source"]):
        lines.append("No verdict: OpenCSP's mission flies the surveyed NSTTF layout, which this run lacks "
                     "(../shared/data/nsttf); the embedded field's rows are for reference.")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None, *, quick: bool = False, json_path: Path | None = RESULTS_PATH,
         echo: bool = True) -> dict[str, Any]:
    """Run, print the markdown table and write the JSON report (``--hours``, ``--configs``, ``--quick``: 13:00)."""
    def configure(parser: Any) -> None:
        parser.add_argument("--hours", type=int, nargs="*", metavar="H", help="hours of 2021-05-13 (-06:00)")
        parser.add_argument("--configs", nargs="*", choices=list(CONFIGS), help="configurations to plan")

    o = harness.options(argv, description="pihim's flights next to OpenCSP's UFACET mission (NSTTF).",
                        counts=COUNTS, repeat=None, warmup=None, quick=quick, json_path=json_path,
                        configure=configure)
    hours: Sequence[int] = (13,) if o.quick else HOURS
    configs: Sequence[str] = tuple(CONFIGS)
    if o.args is not None:
        hours = tuple(o.args.hours) if o.args.hours else hours
        configs = tuple(o.args.configs) if o.args.configs else configs
    report = run_benchmark(hours, configs)
    return harness.publish(report, markdown_report, o.json_path, echo=echo)


if __name__ == "__main__":
    main(sys.argv[1:] or None)
