"""Which facets show a heliostat's back: the planner's traced report against pihim's renderer.

For the NSTTF case (surveyed field from ``../shared/data/nsttf``, else the
embedded NSTTF-like field; aim point (60, 8.8, 28.9); 2021-05-13 at the
given hours), ``build_plan`` plans the facet captures; a random sample of
captures (seeded) is rendered at 1/8 resolution (``step`` pixels apart) with
:func:`pihim.render.paths.trace_paths` over the full scene (every facet with
its canting, the back structure, the tower, the ground) and one mirror
bounce. For every facet of the captured HUA:

* *confirmed*: the report (:func:`pihim.planning.facets.facet_targets`) says
  it shows heliostat T, and some pixel of the facet shows T's back (a facet
  back or a structure member of T) after the bounce;
* *other heliostat*: the report's T is not seen there, another heliostat's
  back is;
* *not seen*: the report names T, the render shows no heliostat back in
  that facet;
* *render only*: the report names none, the render shows a back in some
  pixel of the facet (slivers near the facet edges that the 3 x 3 samples
  miss, or structure members below the mirror rectangle).

An accuracy study (``*_quality``): run with
``python benchmarks/run.py --quality --only facets_render_quality`` or this
file directly (``--hours 10 13 --captures 40``).
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness
from bench_plan import nsttf_field

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose, pixel_rays_world
from pihim.field.layout import UFACET_AIM_POINT
from pihim.planning.facets import facet_targets
from pihim.planning.pipeline import build_plan
from pihim.planning.ufacet import track_at
from pihim.sky.sun import NSTTF, parse_time

RESULTS_PATH = Path(__file__).resolve().parent / "results" / "facets_render.json"
COUNTS = harness.Counts(repeat=1, warmup=0, quick_repeat=1, quick_warmup=0, cap_quick=True)


def check_hour(field: Any, hour: int, n_captures: int, step: int, seed: int) -> dict[str, Any]:
    """Render ``n_captures`` random captures of the plan at ``hour`` and compare facet by facet."""
    from pihim.render.paths import FACET_BACK, MIRROR, STRUCTURE_HIT, trace_paths
    from pihim.render.scene import field_scene

    when = parse_time(f"2021-05-13T{hour:02d}:00:00-06:00")
    plan = build_plan(field, when, NSTTF, aim_point=UFACET_AIM_POINT, facet_report=False)
    sun, pose = track_at(field, when, aim_point=UFACET_AIM_POINT, site=NSTTF)
    scene = field_scene(pose)
    camera = CameraModel()
    names = {n: k for k, n in enumerate(field.names)}
    caps = [w for p in plan.passes for w in p.waypoints if w.capture]
    rng = np.random.default_rng(seed + hour)
    pick = [caps[i] for i in rng.choice(len(caps), min(n_captures, len(caps)), replace=False)]
    report = facet_targets(pose, [names[w.hua] for w in pick], [(w.x_m, w.y_m, w.z_m) for w in pick],
                           [w.heading_deg for w in pick], [w.gimbal_pitch_deg for w in pick], tower=field.tower)
    u, v = np.meshgrid(np.arange(step / 2, camera.width_px, step), np.arange(step / 2, camera.height_px, step))
    counts = {"confirmed": 0, "other_heliostat": 0, "not_seen": 0, "render_only": 0, "neither": 0}
    t0 = time.perf_counter()
    for w, row in zip(pick, report, strict=True):
        h = names[w.hua]
        o, d = pixel_rays_world(camera, CameraPose.from_waypoint(w), u.ravel(), v.ravel())
        paths = trace_paths(scene, o, d, sun.vector, max_bounces=1)
        prim = np.maximum(paths.first_prim, 0)
        on_hua = (paths.first_kind == MIRROR) & (paths.first_prim >= 0) & (scene.heliostat[prim] == h)
        facet = np.where(on_hua, scene.facet[prim] - 1, -1)
        back = np.isin(paths.terminal_kind, (FACET_BACK, STRUCTURE_HIT)) & (paths.terminal_prim >= 0)
        who = np.where(back, scene.heliostat[np.maximum(paths.terminal_prim, 0)], -1)
        for f in range(len(row)):
            seen = set(who[(facet == f) & back].tolist())
            if row[f] >= 0:
                key = "confirmed" if row[f] in seen else ("other_heliostat" if seen else "not_seen")
            else:
                key = "render_only" if seen else "neither"
            counts[key] += 1
    named = counts["confirmed"] + counts["other_heliostat"] + counts["not_seen"]
    return {"hour": hour, "captures": len(pick), "facets": len(pick) * report.shape[1], **counts,
            "confirmed_share": counts["confirmed"] / named if named else None,
            "render_seconds": round(time.perf_counter() - t0, 2)}


def main(argv: Sequence[str] | None = None, *, quick: bool = False, json_path: Path | None = RESULTS_PATH,
         echo: bool = True) -> dict[str, Any]:
    """Run the study, print the table and write the JSON report."""
    def configure(parser: Any) -> None:
        parser.add_argument("--hours", type=int, nargs="*", metavar="H")
        parser.add_argument("--captures", type=int, default=40, metavar="N")
        parser.add_argument("--step", type=int, default=8, metavar="PX")

    o = harness.options(argv, description="Facet report against the renderer.", counts=COUNTS, repeat=None,
                        warmup=None, quick=quick, json_path=json_path, configure=configure)
    hours: Sequence[int] = (10,) if o.quick else (8, 10, 13, 16)
    n, step = (10 if o.quick else 40), 8
    if o.args is not None:
        hours = tuple(o.args.hours) if o.args.hours else hours
        n, step = o.args.captures, o.args.step
    field, source = nsttf_field()
    load0 = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    rows = [check_hour(field, h, n, step, 2026) for h in hours]
    report = {"benchmark": "facets_render_quality", "settings": {"source": source, "hours": list(hours),
                                                                 "captures_per_hour": n, "pixel_step": step},
              "rows": rows, "wall_s": round(time.perf_counter() - t0, 1),
              "cpu_s": round(time.process_time() - c0, 1), "load_avg": round((load0 + os.getloadavg()[0]) / 2, 2),
              "machine": harness.machine_info()}
    if echo:
        print(f"{source}; {n} random captures per hour rendered every {step} px; wall {report['wall_s']} s, "
              f"CPU {report['cpu_s']} s, load {report['load_avg']}\n")
        print("| hour | captures | facets | report names T: confirmed | other heliostat | not seen | "
              "report names none: render shows a back | neither | confirmed share |")
        print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        for r in rows:
            share = "-" if r["confirmed_share"] is None else f"{100 * r['confirmed_share']:.1f} %"
            print(f"| {r['hour']:02d}:00 | {r['captures']} | {r['facets']} | {r['confirmed']} | "
                  f"{r['other_heliostat']} | {r['not_seen']} | {r['render_only']} | {r['neither']} | {share} |")
    harness.write_json(report, o.json_path)
    return report


if __name__ == "__main__":
    main(sys.argv[1:] or None)
