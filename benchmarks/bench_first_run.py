"""The first run: ``pihim demo`` with numba's kernel cache empty, then again with it filled.

pihim's compiled kernels are cached on disk (``cache=True``), so only the
first run on a machine (or after an upgrade) compiles them; that first run
is the README's first command. This benchmark runs ``pihim demo`` as a whole
process three times: **cold** with ``--no-compile-helper`` (every kernel
compiled in the demo's process, ``NUMBA_CACHE_DIR`` and ``MPLCONFIGDIR``
new empty folders),
**cold** as the README runs it (a helper process compiles the renderer's and
the solver's kernels while the demo plans, :mod:`pihim._warmup`; another new
empty folder) and **warm** (every kernel loaded from the second folder, what
every later run pays: the anchor, in the same run). The differences are the
first run's cost without and with the helper. Inside the demo's process a
listener on numba's compile events (``numba.core.event``, ``numba:compile``)
adds up the outermost compilations, so the table also gives the compile time
in that process (not the helper's), the number of kernels it compiled and the
five that took longest.

Each row gives wall and CPU time (the process, its threads and the helper it
reaped, from ``getrusage(RUSAGE_CHILDREN)``), the share of the CPUs other
processes used meanwhile and the load average.

Run ``python benchmarks/run.py --only bench_first_run`` or this file
directly (``--quick``: ``--size 612x512 --pairs 1``; the kernels compiled
are the same at every size, the work is smaller).
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness

RESULTS_PATH = Path(__file__).resolve().parent / "results" / "first_run.json"
#: The runs, in the order they are made: the first run without and with the compiling helper, then a later run.
ROWS = (("cold_no_helper", "cold, `--no-compile-helper`"), ("cold", "cold (default: compiling helper)"),
        ("warm", "warm"))
COUNTS = harness.Counts(repeat=1, warmup=0, quick_repeat=1, quick_warmup=0, cap_quick=True)

#: Runs ``pihim demo`` in this process with a listener on numba's compile events; writes a JSON record.
_DRIVER = r"""
import json, sys, time
from numba.core import event

top = []
starts = []  # compile events nest: a stack of their start times

class Compiles(event.Listener):
    def on_start(self, ev):
        starts.append(time.perf_counter())

    def on_end(self, ev):
        t = time.perf_counter() - starts.pop()
        if not starts:  # an outermost compilation (the kernels it calls are inside it)
            f = ev.data["dispatcher"].py_func
            top.append((t, f"{f.__module__}.{f.__qualname__}"))

event.register("numba:compile", Compiles())
from pihim.cli import main

rc = main(["demo", *sys.argv[2:]])
json.dump({"rc": rc, "compile_s": sum(t for t, _ in top), "kernels": len(top),
           "slowest": sorted(top, reverse=True)[:5]}, open(sys.argv[1], "w"))
"""


def run_demo(cache_dir: Path, out_dir: Path, demo_args: Sequence[str]) -> dict[str, Any]:
    """One ``pihim demo`` process with ``NUMBA_CACHE_DIR=cache_dir``: wall, CPU, load and its compile record.

    matplotlib's configuration and font cache live in ``cache_dir/matplotlib``
    too (``MPLCONFIGDIR``), so a cold run also builds the font cache, as the
    first run on a new machine does.
    """
    record = out_dir.with_suffix(".json")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir), "MPLCONFIGDIR": str(cache_dir / "matplotlib")}
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    s0, load0 = harness.cpu_times(), harness.load_average()
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _DRIVER, str(record), "--out", str(out_dir), *demo_args],
                          env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    s1 = harness.cpu_times()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0 or not record.is_file():
        raise RuntimeError(f"pihim demo failed ({proc.returncode}): {proc.stderr.strip()[-500:]}")
    row = json.loads(record.read_text())
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    other = None
    if s0 is not None and s1 is not None:  # the machine's busy time less this process's and the demo's
        other = max((s1[1] - s0[1]) - (s1[2] - s0[2]) - cpu, 0.0) / (wall * (os.cpu_count() or 1))
    row.update(wall_s=round(wall, 2), cpu_s=round(cpu, 2), other_cpu=other, load_avg=load0)
    return row


def markdown_report(report: dict[str, Any]) -> str:
    """The table for BENCHMARKS.md."""
    s = report["settings"]
    lines = [f"`pihim demo {' '.join(s['demo_args'])}` as a whole process, numba {s['numba']}, "
             f"{report['machine']['cpu_count']} CPUs.", "",
             "| run | wall s | CPU s | compiled kernels | compile s | other CPU % | load |",
             "|---|--:|--:|--:|--:|--:|--:|"]
    for name, label in ROWS:
        if name not in report:
            continue
        r = report[name]
        other = "-" if r["other_cpu"] is None else f"{100 * r['other_cpu']:.0f}"
        lines.append(f"| {label} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['kernels']} | {r['compile_s']:.1f} | "
                     f"{other} | {r['load_avg']:.1f} |")
    w = report["warm"]
    for name in ("cold", "cold_no_helper"):
        if name in report:
            c = report[name]
            lines += ["", f"First run's cost, {dict(ROWS)[name]}: {c['wall_s'] - w['wall_s']:.1f} s wall, "
                      f"{c['cpu_s'] - w['cpu_s']:.1f} s CPU ({c['wall_s'] / w['wall_s']:.2f}x the warm run). "
                      "Slowest compilations in the demo's process: "
                      + ", ".join(f"{n.rsplit('.', 1)[-1]} {t:.1f} s" for t, n in c["slowest"]) + "."]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None, *, quick: bool = False, json_path: Path | None = RESULTS_PATH,
         echo: bool = True) -> dict[str, Any]:
    """Run cold without and with the helper, then warm; print the table and write the JSON report."""
    import numba

    o = harness.options(argv, description="pihim demo's first run (numba compiling) against a later one.",
                        counts=COUNTS, repeat=None, warmup=None, quick=quick, json_path=json_path)
    demo_args = ["--size", "612x512", "--pairs", "1"] if o.quick else []
    report: dict[str, Any] = {"benchmark": "bench_first_run",
                              "settings": {"demo_args": demo_args, "numba": numba.__version__}}
    with tempfile.TemporaryDirectory(prefix="pihim-first-run-") as tmp:
        bare = Path(tmp) / "numba-cache-no-helper"
        bare.mkdir()
        report["cold_no_helper"] = run_demo(bare, Path(tmp) / "cold-no-helper", [*demo_args, "--no-compile-helper"])
        cache = Path(tmp) / "numba-cache"
        cache.mkdir()
        report["cold"] = run_demo(cache, Path(tmp) / "cold", demo_args)
        report["warm"] = run_demo(cache, Path(tmp) / "warm", demo_args)
    report["machine"] = harness.machine_info()
    return harness.publish(report, markdown_report, o.json_path, echo=echo)


if __name__ == "__main__":
    main(sys.argv[1:] or None)
