"""The planner at scale: radial fields of 1,000 to 100,000 heliostats planned, scored and split into flights.

For each size N a fresh process (so that its peak memory is its own):

1. builds a radial-staggered field of N heliostats around a 200 m tower
   aiming at 195 m (:func:`pihim.field.layout.radial_staggered_field`;
   untimed);
2. tracks it for the NSTTF sun of 2021-05-13 13:00 -06:00
   (:func:`pihim.field.kinematics.track_field`);
3. plans the UFACET passes (:func:`pihim.planning.ufacet.plan_ufacet`);
4. scores them with the default contrast-raising shift search
   (:func:`pihim.planning.scoring.score_passes`);
5. splits them into flights (:func:`pihim.planning.endurance.split_flights`;
   from one home point 30 m South of the tower, a 20 min battery less 20 %
   cannot reach the passes at the edge of fields kilometres wide: those are
   counted, ``passes_beyond_battery``, not flown),

the pipeline of ``bench_plan``'s ``radial N full plan + scoring`` rows and
of the issue's figures (1k 1.6-2.9 s, 10k 20-25 s, 20k 57 s, 30k 145-178 s
and 2.1 GB, 100k killed after 300 s at >= 5.4 GB). Each stage's wall and
CPU time (``time.process_time``; numpy may use several threads) and the
process's peak resident memory (``VmHWM``) are recorded with the load
average of the machine, and the passes per heliostat.

Targets: 100,000 heliostats planned and scored in < 5 min and < 8 GB; the
growth from 1k to 100k is fitted on a log-log scale (slope 1 = linear).

What ``pihim plan`` runs
    Since the per-facet captures, the route and the facet report landed,
    ``pihim plan`` does more than the pipeline above: for each size a second
    fresh process times :func:`pihim.planning.pipeline.build_plan` on the
    same field (the command's library call, without the exports), with its
    stages: passes (``plan_ufacet``), scoring, facet captures
    (``plan_facet_captures``), route and flights (``plan_flights``) and the
    traced facet report (``facet_coverage``). Same targets, reported apart
    (``--pipeline-sizes``; default the same sizes).

``pihim plan`` as a whole process
    For the ``--process-sizes`` (default 1,000, 10,000 and 30,000; 100,000
    takes about ten minutes, give it explicitly): the size-N field written
    as an OpenCSP heliostat CSV (untimed), then ``python -m pihim plan
    --field FIELD.csv --time ... --aim 0,0,195 --out DIR --json`` timed as
    a child process, once with ``--workers 1`` (or each ``--process-workers``)
    and once with the command's default (a forked worker per CPU): wall,
    CPU (user + system of the child and its workers, from ``os.wait4``),
    peak resident memory of the largest process, the peak of the summed
    proportional set size of the command and its workers (sampled from
    ``/proc`` four times a second; shared pages counted once), the files
    written and their size, and the command's own split (``seconds`` of its JSON: planning stages,
    and ``total_with_export``; the exports are the difference). The command
    puts the NSTTF tower box at the origin (``--field`` CSVs carry no tower),
    so its plan differs a little from ``build_plan``'s on the same field.

``--figure PATH`` (default ``docs/figures/plan_scale.png``) draws the
log-log figure. Run ``python benchmarks/run.py --only bench_plan_scale`` or
this file directly (``--sizes 1000 10000``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness

RESULTS_PATH = Path(__file__).resolve().parent / "results" / "plan_scale.json"
FIGURE_PATH = Path(__file__).resolve().parents[1] / "docs" / "figures" / "plan_scale.png"
SIZES = (1_000, 3_000, 10_000, 30_000, 100_000)
COUNTS = harness.Counts(repeat=1, warmup=0, quick_repeat=1, quick_warmup=0, cap_quick=True)
CASE_TIME = "2021-05-13T13:00:00-06:00"
STAGES = ("track", "plan", "score", "flights")
#: Stages of build_plan timed in the whole-pipeline rows (functions of pihim.planning.pipeline, and the facet report).
PIPELINE_STAGES = ("plan_ufacet", "score_passes", "plan_facet_captures", "plan_flights", "facet_coverage")


def _peak_rss_mb() -> float:
    with open("/proc/self/status", encoding="utf-8") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")  # pragma: no cover - not Linux


def child(n: int) -> dict[str, Any]:
    """One size, in this process (see the module docstring)."""
    from bench_plan import BIG_TOWER

    from pihim.field.kinematics import track_field
    from pihim.field.layout import radial_staggered_field
    from pihim.planning.endurance import split_flights
    from pihim.planning.scoring import score_passes
    from pihim.planning.ufacet import home_waypoint, plan_ufacet
    from pihim.sky.sun import NSTTF, sun_position

    sun = sun_position(NSTTF, CASE_TIME).vector
    field = radial_staggered_field(n, tower=BIG_TOWER)
    aim = field.default_aim_point
    rss0 = _peak_rss_mb()
    load0 = os.getloadavg()[0]
    wall: dict[str, float] = {}
    cpu: dict[str, float] = {}

    def timed(name: str, fn: Any) -> Any:
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        wall[name], cpu[name] = time.perf_counter() - t0, time.process_time() - c0
        return out

    pose = timed("track", lambda: track_field(field, sun, aim))
    res = timed("plan", lambda: plan_ufacet(field, pose, aim_point=aim, origin=NSTTF))
    scored = timed("score", lambda: score_passes(res.passes, pose, sun, aim_point=aim, origin=NSTTF))
    home = home_waypoint(field, origin=NSTTF)
    far: list[int] = []
    flights = timed("flights", lambda: split_flights(scored, home, origin=NSTTF, tower=field.tower, unflyable=far))
    return {"heliostats": n, "passes": len(res.passes), "passes_per_heliostat": len(res.passes) / n,
            "assessed": len(res.assessed), "captures": res.n_captures, "flights": len(flights),
            "passes_beyond_battery": len(far),
            "wall_s": wall, "cpu_s": cpu, "total_wall_s": sum(wall.values()), "total_cpu_s": sum(cpu.values()),
            "peak_rss_mb": _peak_rss_mb(), "rss_before_mb": rss0,
            "load_avg": round((load0 + os.getloadavg()[0]) / 2.0, 2)}


def child_pipeline(n: int) -> dict[str, Any]:
    """``build_plan`` (``pihim plan``'s library call) on the size-``n`` field, in this process, stages timed."""
    from bench_plan import BIG_TOWER

    import pihim.planning.facets as facets_module
    import pihim.planning.pipeline as pipeline
    from pihim.field.layout import radial_staggered_field
    from pihim.sky.sun import NSTTF, parse_time

    field = radial_staggered_field(n, tower=BIG_TOWER)
    rss0 = _peak_rss_mb()
    load0 = os.getloadavg()[0]
    wall = dict.fromkeys(PIPELINE_STAGES, 0.0)
    cpu = dict.fromkeys(PIPELINE_STAGES, 0.0)

    def timed(module: Any, name: str) -> None:
        fn = getattr(module, name)

        def call(*args: Any, **kwargs: Any) -> Any:
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                wall[name] += time.perf_counter() - t0
                cpu[name] += time.process_time() - c0

        setattr(module, name, call)

    for name in PIPELINE_STAGES[:-1]:
        timed(pipeline, name)
    timed(facets_module, "facet_coverage")  # imported by build_plan when it runs
    t0, c0 = time.perf_counter(), time.process_time()
    plan = pipeline.build_plan(field, parse_time(CASE_TIME), NSTTF)
    total_wall, total_cpu = time.perf_counter() - t0, time.process_time() - c0
    flown = sum(len(f.pass_indices) for f in plan.flights)
    return {"heliostats": n, "passes": len(plan.passes), "passes_flown": flown, "flights": len(plan.flights),
            "captures": sum(w.capture for p in plan.passes for w in p.waypoints),
            "wall_s": wall, "cpu_s": cpu, "total_wall_s": total_wall, "total_cpu_s": total_cpu,
            "peak_rss_mb": _peak_rss_mb(), "rss_before_mb": rss0,
            "load_avg": round((load0 + os.getloadavg()[0]) / 2.0, 2)}


def _write_opencsp_csv(field: Any, path: Path) -> None:
    """The field's heliostats as an OpenCSP heliostat CSV (the layout ``pihim.field.load_field`` reads)."""
    spec = field.spec
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("Name,X,Y,Z,Num. Facets,Num. Rows,Num. Cols,Pivot Height,Pivot Offset,Facet Width,Facet Height\n")
        for name, (x, y, z) in zip(field.names, field.pivots, strict=True):
            fh.write(f"{name},{x:.3f},{y:.3f},{z:.3f},{spec.rows * spec.cols},{spec.rows},{spec.cols},"
                     f"{spec.pivot_height_m},{spec.pivot_offset_m},{spec.facet_width_m},{spec.facet_height_m}\n")


def _tree_memory_mb(pid: int) -> tuple[float, float]:
    """Proportional (PSS: shared pages split among their sharers) and resident set sizes summed over process
    ``pid`` and its descendants (forked workers share the parent's pages: PSS counts them once), MB."""
    pss = rss = 0.0
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            for line in Path(f"/proc/{p}/smaps_rollup").read_text().splitlines():
                if line.startswith("Pss:"):
                    pss += float(line.split()[1]) / 1024.0
                elif line.startswith("Rss:"):
                    rss += float(line.split()[1]) / 1024.0
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError):  # the process ended meanwhile
            continue
    return pss, rss


def child_process(n: int, workers: int | None = None) -> dict[str, Any]:
    """``pihim plan`` on the size-``n`` field from a CSV, as a child process (see the module docstring)."""
    import tempfile
    import threading

    from bench_plan import BIG_TOWER

    from pihim.field.layout import radial_staggered_field

    with tempfile.TemporaryDirectory(prefix="pihim-plan-scale-") as tmp:
        csv = Path(tmp) / "field.csv"
        _write_opencsp_csv(radial_staggered_field(n, tower=BIG_TOWER), csv)
        out = Path(tmp) / "out"
        cmd = [sys.executable, "-m", "pihim", "plan", "--field", str(csv), "--time", CASE_TIME, "--aim", "0,0,195",
               "--out", str(out), "--json", *([] if workers is None else ["--workers", str(workers)])]
        load0 = os.getloadavg()[0]
        peak = [0.0, 0.0]
        stop = threading.Event()
        t0 = time.perf_counter()
        with open(Path(tmp) / "stdout.json", "w+", encoding="utf-8") as stdout:
            proc = subprocess.Popen(cmd, stdout=stdout, stderr=subprocess.PIPE, text=True)

            def sample() -> None:  # the whole tree's memory, the command and its forked workers, 4 times a second
                while not stop.wait(0.25):
                    pss, rss = _tree_memory_mb(proc.pid)
                    peak[0], peak[1] = max(peak[0], pss), max(peak[1], rss)

            sampler = threading.Thread(target=sample, daemon=True)
            sampler.start()
            _, status, usage = os.wait4(proc.pid, 0)
            wall = time.perf_counter() - t0
            stop.set()
            sampler.join()
            proc.returncode = os.waitstatus_to_exitcode(status)
            if proc.returncode != 0:
                raise RuntimeError(f"pihim plan exited with {proc.returncode}: {proc.stderr.read().strip()[-300:]}")
            stdout.seek(0)
            summary = json.load(stdout)
        files = [p for p in out.rglob("*") if p.is_file()]
        return {"heliostats": n, "workers": workers, "passes": summary["passes"], "flights": summary["flights"],
                "wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mb": usage.ru_maxrss / 1024.0,
                "peak_tree_pss_mb": peak[0], "peak_tree_rss_mb": peak[1],
                "command_seconds": summary["seconds"], "files": len(files),
                "files_mb": sum(p.stat().st_size for p in files) / 1e6,
                "load_avg": round((load0 + os.getloadavg()[0]) / 2.0, 2)}


def _run_child(flag: str, n: int, *extra: str) -> dict[str, Any]:
    out = subprocess.run([sys.executable, str(Path(__file__).resolve()), flag, str(n), *extra], capture_output=True,
                         text=True, env=dict(os.environ), check=False)
    if out.returncode != 0:
        return {"heliostats": n, "error": out.stderr.strip().splitlines()[-1:] or [f"exit code {out.returncode}"]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def _run_children(flag: str, sizes: Sequence[int], line: Any,
                  extras: Sequence[tuple[str, ...]] = ((),)) -> list[dict[str, Any]]:
    """One child process per size (and per ``extras``, more arguments), each result echoed by ``line(row)``."""
    rows = []
    for n, extra in ((n, e) for n in sizes for e in extras):
        rows.append(_run_child(flag, n, *extra))
        if "error" not in rows[-1]:
            print("  " + line(rows[-1]), flush=True)
    return rows


def run_benchmark(sizes: Sequence[int], pipeline_sizes: Sequence[int] = (),
                  process_sizes: Sequence[int] = (), process_workers: Sequence[int | None] = (1, None)) -> dict[str, Any]:
    rows = _run_children("--child", sizes, lambda r: f"{r['heliostats']:,}: {r['total_wall_s']:.1f} s wall, "
                         f"{r['total_cpu_s']:.1f} s CPU, {r['peak_rss_mb']:.0f} MB")
    pipeline_rows = _run_children("--child-pipeline", pipeline_sizes, lambda r: (
        f"build_plan {r['heliostats']:,}: {r['total_wall_s']:.1f} s wall, {r['total_cpu_s']:.1f} s CPU, "
        f"{r['peak_rss_mb']:.0f} MB"))
    process_rows = _run_children("--child-process", process_sizes, lambda r: (
        f"pihim plan {r['heliostats']:,} --workers {r['workers'] or 'default'}: {r['wall_s']:.1f} s wall, "
        f"{r['cpu_s']:.1f} s CPU, {r['peak_tree_pss_mb']:.0f} MB (PSS, with its workers), {r['files']:,} files"),
        extras=[() if w is None else (str(w),) for w in process_workers])
    ok = [r for r in rows if "error" not in r]
    fit = {}
    if len(ok) >= 2:
        x = np.log([r["heliostats"] for r in ok])
        for key in ("total_wall_s", "total_cpu_s"):
            fit[key] = float(np.polyfit(x, np.log([r[key] for r in ok]), 1)[0])
        fit["passes"] = float(np.polyfit(x, np.log([r["passes"] for r in ok]), 1)[0])
    big = next((r for r in ok if r["heliostats"] == 100_000), None)
    targets = [harness.target("100,000 heliostats planned and scored, wall", big and big["total_wall_s"], 300.0, "s"),
               harness.target("100,000 heliostats, peak memory", big and big["peak_rss_mb"] / 1024.0, 8.0, "GB")]
    ok_p = [r for r in pipeline_rows if "error" not in r]
    if len(ok_p) >= 2:
        x = np.log([r["heliostats"] for r in ok_p])
        fit["pipeline_total_wall_s"] = float(np.polyfit(x, np.log([r["total_wall_s"] for r in ok_p]), 1)[0])
    big_p = next((r for r in ok_p if r["heliostats"] == 100_000), None)
    if 100_000 in pipeline_sizes:
        targets += [harness.target("100,000 heliostats, build_plan (pihim plan's pipeline), wall",
                                   big_p and big_p["total_wall_s"], 300.0, "s"),
                    harness.target("100,000 heliostats, build_plan, peak memory",
                                   big_p and big_p["peak_rss_mb"] / 1024.0, 8.0, "GB")]
    for w in process_workers if 100_000 in process_sizes else ():
        big_c = next((r for r in process_rows if "error" not in r and r["heliostats"] == 100_000
                      and r["workers"] == w), None)
        how = "--workers 1" if w == 1 else "default workers" if w is None else f"--workers {w}"
        targets += [harness.target(f"100,000 heliostats, pihim plan as a process ({how}; plan and all its files), "
                                   "wall", big_c and big_c["wall_s"], 300.0, "s"),
                    harness.target(f"100,000 heliostats, pihim plan as a process ({how}), peak memory of the "
                                   "process and its workers (PSS)", big_c and big_c["peak_tree_pss_mb"] / 1024.0,
                                   8.0, "GB")]
    return {"benchmark": "bench_plan_scale", "sizes": list(sizes), "rows": rows, "pipeline_sizes": list(pipeline_sizes),
            "pipeline_rows": pipeline_rows, "process_sizes": list(process_sizes), "process_rows": process_rows,
            "loglog_slope": fit, "targets": targets, "machine": harness.machine_info()}


def _table(rows: Sequence[dict[str, Any]], header: str, row: Any) -> list[str]:
    """A markdown table: ``header`` (right-aligned columns), then ``row(r)`` per size (or its error)."""
    lines = [header, "|" + "---:|" * (header.count("|") - 1)]
    for r in rows:
        lines.append(f"| {r['heliostats']:,} | failed: {r['error']} |" if "error" in r else row(r))
    return lines


def _pipeline_row(r: dict[str, Any]) -> str:
    return (f"| {r['heliostats']:,} | {r['passes']:,} | {r['flights']:,} | {r['captures']:,} | "
            + " | ".join(f"{r['wall_s'][s]:.1f}" for s in PIPELINE_STAGES)
            + f" | {r['total_wall_s']:.1f} | {r['total_cpu_s']:.1f} | {r['peak_rss_mb']:.0f} | {r['load_avg']:.1f} |")


def _process_row(r: dict[str, Any]) -> str:
    sec = r["command_seconds"]
    planning = sum(v for k, v in sec.items() if k != "total_with_export")
    return (f"| {r['heliostats']:,} | {r.get('workers') or 'default'} | {r['passes']:,} | {r['flights']:,} | "
            f"{planning:.1f} | {sec['total_with_export'] - planning:.1f} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
            f"{r['peak_rss_mb']:.0f} | {r.get('peak_tree_pss_mb', float('nan')):.0f} | {r['files']:,} | "
            f"{r['files_mb']:.0f} | {r['load_avg']:.1f} |")


def markdown_report(report: dict[str, Any]) -> str:
    lines = _table(report["rows"], "| heliostats | passes | passes per heliostat | assessed | flights | passes beyond "
                   "the battery | track s | plan s | score s | flights s | total wall s | total CPU s | peak RSS MB | "
                   "load |", lambda r: (
                       f"| {r['heliostats']:,} | {r['passes']:,} | {r['passes_per_heliostat']:.3f} | "
                       f"{r['assessed']:,} | {r['flights']:,} | {r.get('passes_beyond_battery', 0):,} | "
                       + " | ".join(f"{r['wall_s'][s]:.2f}" for s in STAGES)
                       + f" | {r['total_wall_s']:.1f} | {r['total_cpu_s']:.1f} | {r['peak_rss_mb']:.0f} | "
                       f"{r['load_avg']:.1f} |"))
    f = report["loglog_slope"]
    if "total_wall_s" in f:
        lines += ["", f"Log-log slopes from {min(report['sizes']):,} to {max(report['sizes']):,}: total wall time "
                  f"{f['total_wall_s']:.2f}, total CPU time {f['total_cpu_s']:.2f}, passes {f['passes']:.2f} "
                  "(1 = linear)."]
    if report.get("pipeline_rows"):
        lines += ["", "`build_plan`, what `pihim plan` runs (seconds of wall time per stage):", ""]
        lines += _table(report["pipeline_rows"], "| heliostats | passes | flights | captures | passes s | scoring s | "
                        "facet captures s | route s | facet report s | total wall s | total CPU s | peak RSS MB | "
                        "load |", _pipeline_row)
        if "pipeline_total_wall_s" in f:
            lines += ["", f"Log-log slope of build_plan's wall time: {f['pipeline_total_wall_s']:.2f}."]
    if report.get("process_rows"):
        lines += ["", "`pihim plan` as a whole process on the field from a CSV (plan, plan.json, KML, map and every "
                  "flight's missions):", ""]
        lines += _table(report["process_rows"], "| heliostats | workers | passes | flights | planning s (the "
                        "command's) | exports s | total wall s | total CPU s (with its workers) | peak RSS MB (largest "
                        "process) | peak PSS MB (process and workers) | files | MB written | load |", _process_row)
    lines += harness.target_table(report["targets"], spec=".1f")
    return "\n".join(lines)


def figure(report: dict[str, Any], path: Path) -> None:
    """Log-log figure: time per stage and in total, and passes, against the field size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in report["rows"] if "error" not in r]
    n = np.array([r["heliostats"] for r in ok], float)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 4.2), dpi=110)
    for s, mk in zip(STAGES, "os^v", strict=True):
        ax.loglog(n, [max(r["wall_s"][s], 1e-3) for r in ok], mk + "-", lw=1, ms=4, label=f"{s} (wall)")
    ax.loglog(n, [r["total_wall_s"] for r in ok], "k-", lw=2, label="total wall")
    ax.loglog(n, [r["total_cpu_s"] for r in ok], "k--", lw=1.5, label="total CPU")
    ok_p = [r for r in report.get("pipeline_rows", []) if "error" not in r]
    if ok_p:
        ax.loglog([r["heliostats"] for r in ok_p], [r["total_wall_s"] for r in ok_p], "D-", color="tab:purple",
                  lw=2, ms=4, label="build_plan, what pihim plan runs (wall)")
    ok_c = [r for r in report.get("process_rows", []) if "error" not in r]
    if ok_c:
        ax.loglog([r["heliostats"] for r in ok_c], [r["wall_s"] for r in ok_c], "P-", color="tab:brown", lw=2,
                  ms=5, label="pihim plan as a process, with its files (wall)")
    ref = ok[0]["total_wall_s"] * n / n[0]
    ax.loglog(n, ref, ":", color="0.5", label="slope 1 (linear)")
    ax.axhline(300, color="r", lw=0.8)
    ax.text(n[-1], 330, "5 min", color="r", fontsize=8, ha="right")
    ax.set_xlabel("heliostats")
    ax.set_ylabel("seconds")
    ax.set_title("Plan + score + flights, radial fields")
    ax.legend(fontsize=7, loc="lower right")
    ax.grid(True, which="both", lw=0.3)
    ax2.loglog(n, [r["passes"] for r in ok], "o-", label="passes")
    ax2.loglog(n, [r["peak_rss_mb"] for r in ok], "s-", label="peak RSS, MB")
    if ok_p:
        ax2.loglog([r["heliostats"] for r in ok_p], [r["peak_rss_mb"] for r in ok_p], "D-", color="tab:purple",
                   label="build_plan peak RSS, MB")
    if ok_c:
        ax2.loglog([r["heliostats"] for r in ok_c], [r["peak_rss_mb"] for r in ok_c], "P-", color="tab:brown",
                   label="pihim plan process peak RSS, MB")
    ax2.loglog(n, n * ok[0]["passes"] / n[0], ":", color="0.5", label="slope 1")
    ax2.axhline(8192, color="r", lw=0.8)
    ax2.text(n[-1], 8800, "8 GB", color="r", fontsize=8, ha="right")
    ax2.set_xlabel("heliostats")
    ax2.set_title("Passes and memory")
    ax2.legend(fontsize=7, loc="lower right")
    ax2.grid(True, which="both", lw=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def main(argv: Sequence[str] | None = None, *, quick: bool = False, json_path: Path | None = RESULTS_PATH,
         echo: bool = True) -> dict[str, Any]:
    """Run every size (``--sizes``; ``--quick``: 1k and 10k), print the table, write the JSON and the figure."""
    def configure(parser: Any) -> None:
        parser.add_argument("--sizes", type=int, nargs="*", metavar="N")
        parser.add_argument("--figure", type=Path, default=FIGURE_PATH, metavar="PNG")
        parser.add_argument("--pipeline-sizes", type=int, nargs="*", metavar="N",
                            help="sizes for the build_plan rows (default: the --sizes; none: skip them)")
        parser.add_argument("--process-sizes", type=int, nargs="*", metavar="N",
                            help="sizes for the pihim plan process rows (default: those of the sizes up to 30,000; "
                                 "none: skip them)")
        parser.add_argument("--process-workers", type=int, nargs="*", metavar="W",
                            help="--workers of the process rows, each beside the command's default (one per CPU); "
                                 "default 1")

    o = harness.options(argv, description="The planner at scale (radial fields).", counts=COUNTS, repeat=None,
                        warmup=None, quick=quick, json_path=json_path, configure=configure)
    sizes: Sequence[int] = (1_000, 10_000) if o.quick else SIZES
    fig_path: Path | None = None if o.quick else FIGURE_PATH
    pipeline_sizes: Sequence[int] = sizes
    process_sizes: Sequence[int] | None = None
    if o.args is not None:
        sizes = tuple(o.args.sizes) if o.args.sizes else sizes
        pipeline_sizes = sizes if o.args.pipeline_sizes is None else tuple(o.args.pipeline_sizes)
        process_sizes = None if o.args.process_sizes is None else tuple(o.args.process_sizes)
        fig_path = o.args.figure
    if process_sizes is None:
        process_sizes = tuple(n for n in sizes if n <= 30_000)
    workers: tuple[int | None, ...] = (1, None)
    if o.args is not None and o.args.process_workers is not None:
        workers = (*o.args.process_workers, None)
    report = run_benchmark(sizes, pipeline_sizes, process_sizes, workers)
    if echo:
        print(markdown_report(report))
    if fig_path is not None and sum("error" not in r for r in report["rows"]) >= 2:
        figure(report, fig_path)
        report["figure"] = str(fig_path)
    harness.write_json(report, o.json_path)
    return report


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        print(json.dumps(child(int(sys.argv[2]))))
    elif len(sys.argv) == 3 and sys.argv[1] == "--child-pipeline":
        print(json.dumps(child_pipeline(int(sys.argv[2]))))
    elif len(sys.argv) in (3, 4) and sys.argv[1] == "--child-process":
        print(json.dumps(child_process(int(sys.argv[2]), int(sys.argv[3]) if len(sys.argv) == 4 else None)))
    else:
        main(sys.argv[1:] or None)
