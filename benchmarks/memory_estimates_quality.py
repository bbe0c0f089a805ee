"""Accuracy study: the memory estimates the commands refuse requests by, against the real peak.

``pihim polar``, ``sky``, ``ground``, ``simulate`` and ``demo`` estimate the memory a
request needs before allocating it and refuse, with the figure, what does not
fit (:func:`pihim._resources.require_memory`). An estimate that is too low
lets a request run into a ``MemoryError`` (or the OOM killer); one that is
too high refuses requests the machine could serve. This study runs each
request in a fresh process and compares the estimate with the growth of the
process's **peak resident set size** (``VmHWM`` in ``/proc/self/status``,
reset through ``/proc/self/clear_refs`` just before the request), which
counts every allocation -- numpy's, and the C allocations of OpenCV,
libtiff, zlib and matplotlib's Agg that ``tracemalloc`` does not see -- and
the growth of the peak virtual size (``VmPeak``, what ``ulimit -v`` limits).

Each process first runs the same command on a tiny request (imports, numba
caches, fonts), so the figures are those of the request itself. For
``polar`` the estimate is consulted after the raw frame is read, so the raw
frame's bytes are subtracted from the measured growth (column *need*).

Run ``python benchmarks/memory_estimates_quality.py [--quick]`` or
``python benchmarks/run.py --quality --only memory_estimates_quality``.
Prints a markdown table and writes ``benchmarks/results/memory_estimates_quality.json``.
Linux only (``/proc``).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

RESULTS_PATH = Path(__file__).resolve().parent / "results" / "memory_estimates_quality.json"
TIME = "2021-05-13T13:00-06:00"
SUN = ["--sun-zenith", "30", "--sun-azimuth", "0"]

#: Case name -> whether it runs with --quick; the requests themselves are built in :func:`_request`.
CASES: dict[str, bool] = {
    "polar superpixel 4000x4000": False,
    "polar full 4000x4000": False,
    "polar superpixel 2000x2000": True,
    "polar full 2000x2000": True,
    "polar superpixel --png 2000x2000": True,
    "polar full --png 2000x2000": False,
    "sky --resolution 0.5": True,
    "sky --resolution 0.25": False,
    "ground --resolution 0.5": True,
    "ground --resolution 0.25": False,
    "ground --monte-carlo --facets 1000000": True,
    "simulate --size 512x512": True,
    "simulate --size 1024x1024": False,
    "demo --size 612x512": False,
    "demo --size 1224x1024": False,
    "demo --size 2448x2048": False,  # the README's first command
}


def _status(key: str) -> int:
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1]) * 1024
    raise KeyError(key)


def _frame(directory: Path, h: int, w: int) -> Path:
    import numpy as np
    import tifffile

    path = directory / f"frame_{h}x{w}.tiff"
    tifffile.imwrite(path, np.random.default_rng(0).integers(0, 4000, (h, w), dtype=np.uint16))
    return path


def _request(name: str, work: Path) -> tuple[list[str], list[str], float, int]:
    """(warm-up argv, argv, estimate in bytes, bytes held before the estimate is consulted)."""
    words = name.split()
    cmd = words[0]
    if cmd == "polar":
        import pihim.cli.polar as polar_cli

        h, w = (int(v) for v in words[-1].split("x"))
        demosaic, png = words[1], "--png" in words
        opts = ["--demosaic", demosaic, *(["--png"] if png else [])]
        tiny = _frame(work, 64, 64)
        frame = _frame(work, h, w)
        est = polar_cli.estimate_frame_bytes(h, w, demosaic=demosaic, png=png)
        return (["polar", str(tiny), "--out", str(work / "o0"), *opts],
                ["polar", str(frame), "--out", str(work / "o1"), *opts], est, 2 * h * w)
    if cmd == "sky":
        from pihim.cli.sky import SKY_BYTES_PER_DIRECTION

        res = float(words[-1])
        nz = round(90 / res)
        return (["sky", *SUN, "--resolution", "5", "--out", str(work / "o0")],
                ["sky", *SUN, "--resolution", words[-1], "--out", str(work / "o1")],
                4 * nz * nz * SKY_BYTES_PER_DIRECTION, 0)
    if cmd == "ground":
        from pihim.cli.ground import MAP_BYTES_PER_DIRECTION, MC_BYTES_PER_FACET

        warm = ["ground", *SUN, "--resolution", "5", "--out", str(work / "o0")]
        if "--monte-carlo" in words:
            facets = int(words[-1])
            return (warm, ["ground", *SUN, "--monte-carlo", "--facets", words[-1], "--out", str(work / "o1")],
                    facets * MC_BYTES_PER_FACET + 90 * 360 * MAP_BYTES_PER_DIRECTION, 0)
        res = float(words[-1])
        n = round(90 / res) * round(360 / res)
        return (warm, ["ground", *SUN, "--resolution", words[-1], "--out", str(work / "o1")],
                n * MAP_BYTES_PER_DIRECTION, 0)
    if cmd == "simulate":
        from pihim.cli.simulate import render_bytes

        w, h = (int(v) for v in words[-1].split("x"))
        pose = ["--hua", "8E3", "--target", "7E3"]
        return (["simulate", "--time", TIME, *pose, "--size", "64x64", "--out", str(work / "o0" / "f.tiff")],
                ["simulate", "--time", TIME, *pose, "--size", words[-1], "--out", str(work / "o1" / "f.tiff")],
                render_bytes(w, h), 0)
    if cmd == "demo":
        from pihim.cli.demo import DEMO_BYTES_PER_PIXEL, DEMO_FIXED_BYTES

        w, h = (int(v) for v in words[-1].split("x"))
        return (["sky", *SUN, "--resolution", "10", "--out", str(work / "o0")],  # imports only: a demo takes minutes
                ["demo", "--pairs", "1", "--size", words[-1], "--out", str(work / "o1")],
                w * h * DEMO_BYTES_PER_PIXEL + DEMO_FIXED_BYTES, 0)
    raise KeyError(name)


def measure(name: str) -> dict[str, Any]:
    """Run case ``name`` in this process (a fresh one: see :func:`main`) and return the figures."""
    from pihim.cli import main as cli

    with tempfile.TemporaryDirectory(prefix="pihim-mem-") as tmp:
        warm, argv, est, held = _request(name, Path(tmp))
        if cli(warm) != 0:
            raise RuntimeError(f"warm-up of {name!r} failed")
        gc.collect()
        rss0, vm0 = _status("VmRSS:"), _status("VmSize:")
        with open("/proc/self/clear_refs", "w", encoding="ascii") as f:
            f.write("5")  # VmHWM := VmRSS
        t0 = time.perf_counter()
        rc = cli(argv)
        seconds = time.perf_counter() - t0
        peak_rss, peak_vm = _status("VmHWM:"), _status("VmPeak:")
    if rc != 0:
        raise RuntimeError(f"{name!r} exited {rc}")
    need = peak_rss - rss0 - held
    return {"case": name, "estimate_bytes": int(est), "peak_rss_growth_bytes": peak_rss - rss0,
            "peak_vm_growth_bytes": max(0, peak_vm - vm0), "held_before_estimate_bytes": held,
            "need_bytes": need, "estimate_over_need": round(est / need, 3), "seconds": round(seconds, 2)}


def markdown(rows: Sequence[dict[str, Any]]) -> str:
    """The results as a markdown table (MB = 1e6 bytes)."""
    out = ["| request | estimate MB | peak RSS growth MB | peak VM growth MB | need MB | estimate / need | s |",
           "|---|--:|--:|--:|--:|--:|--:|"]
    for r in rows:
        out.append(f"| `{r['case']}` | {r['estimate_bytes'] / 1e6:.1f} | {r['peak_rss_growth_bytes'] / 1e6:.1f} | "
                   f"{r['peak_vm_growth_bytes'] / 1e6:.1f} | {r['need_bytes'] / 1e6:.1f} | "
                   f"{r['estimate_over_need']:.2f} | {r['seconds']:.1f} |")
    return "\n".join(out)


def main(argv: Sequence[str] | None = None, *, quick: bool | None = None) -> dict[str, Any]:
    """Run every case in its own process, print the table, write the JSON; return the results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the smaller requests only")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=RESULTS_PATH, help="JSON output path")
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.child)))
        return {}
    quick = bool(quick or args.quick)
    rows = []
    load = []
    t0, c0 = time.perf_counter(), time.process_time()
    for name, small in CASES.items():
        if quick and not small:
            continue
        proc = subprocess.run([sys.executable, __file__, "--child", name], capture_output=True, text=True,
                              env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
        if proc.returncode != 0:
            raise RuntimeError(f"{name}: {proc.stderr.strip().splitlines()[-1:]}")
        rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        load.append(os.getloadavg()[0])
        print(f"  {name}: estimate / need {rows[-1]['estimate_over_need']:.2f}", file=sys.stderr)
    children = os.times()
    report = {
        "benchmark": "memory_estimates_quality",
        "rows": rows,
        "wall_s": round(time.perf_counter() - t0, 1),
        "cpu_s_children": round(children.children_user + children.children_system, 1),
        "cpu_s_self": round(time.process_time() - c0, 1),
        "load_average_1min": [round(v, 2) for v in load],
    }
    print(markdown(rows))
    print(f"\nwall {report['wall_s']} s, CPU {report['cpu_s_children']} s (children), "
          f"1-min load average {min(load, default=0):.1f}-{max(load, default=0):.1f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return report


if __name__ == "__main__":
    main(sys.argv[1:])
