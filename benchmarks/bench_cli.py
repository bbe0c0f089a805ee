"""Command-line benchmark: start-up of every command and ``pihim polar`` over 100 frames, as whole processes.

Everything here runs ``python -m pihim ...`` in a separate process and
records its wall time, its CPU time (user + system, all threads), the
one-minute load average and the share of the CPUs other processes used
meanwhile.

Start-up
    ``pihim --help`` (target <= 0.3 s), and for every command its import
    overhead: the CPU time spent inside every outermost import, timed in the
    process (every module imported during the run, lazily imported ones
    included; the sum of ``python -X importtime``'s top-level entries beside
    it) for ``pihim CMD --help`` and, for the commands that can run in
    seconds, for a real run. Target <= 0.5 s.
``pihim polar`` over 100 frames
    100 distinct 2448x2048 12-bit TIFFs (four synthetic heliostat scenes
    with independent noise; 1 GB) through one process: super-pixel with
    ``--json`` (target <= 66 ms per frame, the camera's 15 fps), super-pixel
    with ``--json --png`` (the previews' cost per frame is the difference of
    these two runs; target <= 60 ms) and full resolution with ``--json``
    (<= 150 ms). Start-up is included (the numba cache is warm, as after a
    first run), and so are the command's defaults (``--png-level 0``: the
    bare previews stored uncompressed). Each run starts after ``sync``. Anchor,
    in the same run: the same frames through a plain script (tifffile read,
    the numpy super-pixel route of ``bench_polar.py``, three float32 TIFFs
    written) in one process. Before each of these runs the frames are
    dropped from the page cache (they are read from the disk, as a user's
    are). Also in the same run: the disk's sustained
    write bandwidth, written as ``pihim polar`` writes (1 GiB with direct
    I/O) and its read bandwidth (the frames read off the disk), and each
    setting's bytes per frame and disk floor (read plus written) per frame.

Beside each real run's import time, its floor: every module the run loaded
except pihim's own, imported in the same order by a bare Python process
right after it, under the collector thresholds the ``pihim`` script starts
with -- what the dependencies (numpy, typer, matplotlib, numba's registries,
...) cost whatever pihim does; the difference is pihim's share.

Run ``python benchmarks/run.py --only bench_cli`` or this file directly
(``--quick``: 20 frames, fewer start-up repetitions; ``--startup-only``: the
start-up rows alone, written to ``results/cli_startup.json``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any


sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness

RESULTS_PATH = Path(__file__).resolve().parent / "results" / "cli.json"
SRC = Path(__file__).resolve().parents[1] / "src"
COMMANDS = ("polar", "calibrate-polarizer", "calibrate-camera", "sky", "ground", "plan", "windows", "demo",
            "simulate", "edges", "canting", "live", "simulate-flight", "campaign")
#: Real runs whose start-up is measured: (label, arguments after ``pihim``; OUT is replaced by a new folder for every run).
REAL_RUNS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("polar (1 frame, --json)", ("polar", "FRAME", "--out", "OUT", "--json")),
    ("sky (--resolution 5)", ("sky", "--sun-zenith", "30", "--sun-azimuth", "235", "--resolution", "5", "--out", "OUT")),
    ("ground (--resolution 5)", ("ground", "--sun-zenith", "30", "--sun-azimuth", "235", "--resolution", "5",
                                 "--out", "OUT")),
    ("plan (NSTTF, 13:00)", ("plan", "--time", "2021-05-13T13:00-06:00", "--out", "OUT", "--json")),
    ("windows (--step-min 60)", ("windows", "--date", "2021-05-13", "--step-min", "60", "--out", "OUT", "--json")),
)
TARGET_HELP_S = 0.3
TARGET_IMPORT_S = 0.5
TARGETS_MS = {"superpixel": 66.0, "full": 150.0, "previews": 60.0}

_ANCHOR_SCRIPT = r"""
import sys, numpy as np, tifffile
sys.path.insert(0, sys.argv[1])
from bench_polar import numpy_superpixel
out = sys.argv[2]
for k, path in enumerate(sys.argv[3:]):
    s0, dolp, aop = numpy_superpixel(tifffile.imread(path))
    for name, image in (("S0", s0), ("DoLP", dolp), ("AoP", aop)):
        tifffile.imwrite(f"{out}/{k:03d}.{name}.tiff", image)
"""


#: Runs ``pihim ARGS`` in this process, through the ``pihim`` script's entry point, and prints, at the end, the
#: CPU and wall time spent importing: every outermost ``import`` statement and ``importlib.import_module`` call
#: (lazy ones and numba's own included) is timed with ``time.process_time`` (the whole process: a thread
#: computing meanwhile is counted too).
_IMPORT_TIMER = r"""
import builtins, importlib, sys, threading, time
_depth = threading.local()
_total = [0.0, 0.0]
_loaded_before = set(sys.modules)
def _timed(f):
    def call(*a, **k):
        if getattr(_depth, "n", 0):
            return f(*a, **k)
        _depth.n = 1
        c, t = time.process_time(), time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            _depth.n = 0
            _total[0] += time.process_time() - c
            _total[1] += time.perf_counter() - t
    return call
builtins.__import__ = _timed(builtins.__import__)
importlib.import_module = _timed(importlib.import_module)
try:
    from pihim.__main__ import run  # what the pihim script runs (it sets up the environment, then loads the CLI)
    sys.argv = ["pihim", *sys.argv[1:]]
    rc = run()
finally:
    sys.stderr.write(f"\nPIHIM_IMPORTS cpu={_total[0]:.6f} wall={_total[1]:.6f}\n")
    sys.stderr.write("PIHIM_MODULES " + " ".join(m for m in list(sys.modules) if m not in _loaded_before
                                                   and m != "__main__" and m.partition(".")[0] != "pihim") + "\n")
sys.exit(rc)
"""

#: Imports, in a bare Python process, the modules named in the file ``sys.argv[1]`` in that order (every module but
#: pihim's own that a timed run loaded, in the order it loaded them) and prints the CPU and wall time it took: the
#: floor that pihim's dependencies and the standard library set for that run, whatever pihim does. The pihim script
#: runs OpenBLAS single-threaded and starts with the collector's thresholds raised (:mod:`pihim._collector`; given
#: as ``sys.argv[2]``), so this process does too.
_FLOOR_SCRIPT = r"""
import gc, importlib, os, sys, time
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
gc.set_threshold(*map(int, sys.argv[2].split(",")))
with open(sys.argv[1]) as f:
    names = f.read().split()
c, t, failed = time.process_time(), time.perf_counter(), 0
for name in names:
    if name not in sys.modules:
        try:
            importlib.import_module(name)
        except Exception:  # a module that only its parent can create (none seen so far): counted, not fatal
            failed += 1
print(f"PIHIM_FLOOR cpu={time.process_time() - c:.6f} wall={time.perf_counter() - t:.6f} modules={len(names)} "
      f"failed={failed}")
"""


def _env() -> dict[str, str]:
    """The environment of the timed processes: this one's, with pihim's source first on the path and Python's
    bytecode cache on (a sandbox that sets ``PYTHONDONTWRITEBYTECODE`` would have every process compile pihim's
    modules afresh, about 0.14 s of CPU a user, whose Python caches bytecode, never pays; the untimed first run
    of each command writes the cache)."""
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(SRC), env.get("PYTHONPATH", "")) if p)
    return env


def dependency_floor(modules: Sequence[str]) -> dict[str, Any]:
    """CPU and wall time a bare Python process takes to import ``modules`` in order (:data:`_FLOOR_SCRIPT`).

    Returns ``floor_cpu_s``, ``floor_wall_s``, ``floor_modules`` and ``floor_failed`` (modules that would not
    import on their own).
    """
    with tempfile.NamedTemporaryFile("w", suffix=".txt", prefix="pihim-modules-") as f:
        f.write("\n".join(modules))
        f.flush()
        from pihim._collector import STARTUP_THRESHOLDS

        res = harness.process_run([sys.executable, "-c", _FLOOR_SCRIPT, f.name, ",".join(map(str, STARTUP_THRESHOLDS))],
                                  env=_env())
    for line in res["stdout"].splitlines():
        if line.startswith("PIHIM_FLOOR "):
            fields = dict(x.split("=") for x in line.split()[1:])
            return {"floor_cpu_s": float(fields["cpu"]), "floor_wall_s": float(fields["wall"]),
                    "floor_modules": int(fields["modules"]), "floor_failed": int(fields["failed"])}
    raise RuntimeError(f"the dependency floor did not run: {res['stderr'].strip()[-300:]}")


def pihim(args: Sequence[str], *, importtime: bool = False, floor: bool = False) -> dict[str, Any]:
    """Run ``python -m pihim ARGS``.

    With ``importtime``: the command runs under :data:`_IMPORT_TIMER` and
    ``-X importtime``, and the result also holds ``import_s`` (sum of the
    top-level ``-X importtime`` entries, wall clock), ``import_cpu_s`` and
    ``import_wall_s`` (the timer's) and ``modules`` (every module but pihim's
    own that the run loaded, in order). With ``floor`` as well: right after the
    run, the :func:`dependency_floor` of those modules (``floor_cpu_s``, ...)
    and ``own_cpu_s``, the import CPU beyond it.
    """
    cmd = [sys.executable, *(["-X", "importtime", "-c", _IMPORT_TIMER] if importtime else ["-m", "pihim"]), *args]
    res = harness.process_run(cmd, env=_env())
    if importtime:
        total, lines = 0, []
        res["import_cpu_s"] = res["import_wall_s"] = None
        res["modules"] = []
        for line in res["stderr"].splitlines():
            if line.startswith("PIHIM_IMPORTS "):
                fields = dict(f.split("=") for f in line.split()[1:])
                res["import_cpu_s"], res["import_wall_s"] = float(fields["cpu"]), float(fields["wall"])
            elif line.startswith("PIHIM_MODULES "):
                res["modules"] = line.split()[1:]
            elif line.startswith("import time:"):
                parts = line.split("|")
                name = parts[2] if len(parts) > 2 else ""
                if name.startswith(" ") and not name.startswith("  ") and parts[1].strip().isdigit():
                    total += int(parts[1])
            else:
                lines.append(line)
        res["import_s"] = total / 1e6
        res["stderr"] = "\n".join(lines)
        if floor:
            res.update(dependency_floor(res["modules"]))
            res["own_cpu_s"] = None if res["import_cpu_s"] is None else res["import_cpu_s"] - res["floor_cpu_s"]
    return res


def _median_run(args: Sequence[str] | Callable[[int], Sequence[str]], n: int, **kw: Any) -> dict[str, Any]:
    """Medians of ``n`` runs of ``pihim ARGS``; ``args`` may be a function of the run's index (a fresh output each)."""
    runs = [pihim(args(k) if callable(args) else args, **kw) for k in range(n)]
    keys = ("wall_s", "cpu_s", "load_before", "load_after", "other_cpu") + (
        ("import_s", "import_cpu_s", "import_wall_s") if kw.get("importtime") else ()) + (
        ("floor_cpu_s", "floor_wall_s", "floor_modules", "floor_failed", "own_cpu_s") if kw.get("floor") else ())
    out = {k: statistics.median(r[k] for r in runs if r[k] is not None) if any(r[k] is not None for r in runs)
           else None for k in keys}
    out["runs"] = n
    out["returncode"] = max(r["returncode"] for r in runs)
    return out


def make_frames(folder: Path, n: int, seed: int = 20261122) -> list[Path]:
    """``n`` distinct 12-bit frames (four scenes, independent noise) as uncompressed TIFFs."""
    import tifffile

    from bench_polar import BIT_DEPTH, FRAME_SHAPE, synthetic_scene
    from pihim.render.mosaic import mosaic_from_stokes

    scenes = [synthetic_scene(FRAME_SHAPE, seed + k) for k in range(4)]
    paths = []
    for k in range(n):
        m = mosaic_from_stokes(*scenes[k % 4], bit_depth=BIT_DEPTH, read_noise_dn=1.2, electrons_per_dn=2.5,
                               rng=seed + 1000 + k)
        path = folder / f"frame_{k:03d}.tiff"
        tifffile.imwrite(path, m)
        paths.append(path)
    return paths


def disk_write_mb_s(folder: Path, n_bytes: int = 1 << 30) -> float:
    """Sustained write bandwidth of the disk under ``folder``, written as ``pihim polar`` writes its outputs.

    ``n_bytes`` in 16 MiB blocks from a page-aligned buffer with ``O_DIRECT``
    (:mod:`pihim._direct_io`); where the file system refuses direct I/O,
    through the page cache and then fsync.
    """
    import errno
    import mmap
    import time

    block = mmap.mmap(-1, 1 << 24)
    block.write(os.urandom(1 << 24))
    path = folder / "disk-bandwidth.bin"
    os.sync()
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC
    start = time.perf_counter()
    try:
        fd = os.open(path, flags | getattr(os, "O_DIRECT", 0))
    except OSError as exc:
        if exc.errno != errno.EINVAL:
            raise
        fd = os.open(path, flags)
    try:
        for _ in range(n_bytes // len(block)):
            os.write(fd, block)
        os.fsync(fd)
    finally:
        os.close(fd)
    seconds = time.perf_counter() - start
    path.unlink()
    return n_bytes / seconds / 1e6


def disk_read_mb_s(paths: Sequence[str | Path]) -> float:
    """Sequential read bandwidth of the disk holding ``paths``: the files read whole, in 16 MiB blocks, off the disk."""
    import time

    evict_from_page_cache(paths)
    n_bytes, start = 0, time.perf_counter()
    for path in paths:
        with open(path, "rb", buffering=0) as f:
            while block := f.read(1 << 24):
                n_bytes += len(block)
    seconds = time.perf_counter() - start
    evict_from_page_cache(paths)
    return n_bytes / seconds / 1e6


def evict_from_page_cache(paths: Sequence[str | Path]) -> None:
    """Drop the files' pages from the operating system's page cache (``posix_fadvise(DONTNEED)``), after a ``sync``.

    Frames written just before a run would otherwise be read from memory;
    a user's frames come from the disk (or the card) they were copied to.
    """
    os.sync()
    for path in paths:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def _folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.iterdir() if p.is_file())


def polar_runs(n_frames: int) -> dict[str, Any]:
    """``pihim polar`` over ``n_frames`` frames as one process (three settings) and the numpy script anchor."""
    with tempfile.TemporaryDirectory(prefix="pihim-bench-cli-") as tmp:
        root = Path(tmp)
        (root / "in").mkdir()
        frames = [str(p) for p in make_frames(root / "in", n_frames)]
        pihim(["polar", frames[0], "--out", str(root / "warm"), "--png"])  # numba and figure caches as after a run
        pihim(["polar", frames[0], "--out", str(root / "warm2"), "--demosaic", "full"])
        runs: dict[str, Any] = {}
        for key, extra in (("superpixel", ["--json"]), ("superpixel_png", ["--json", "--png"]),
                           ("full", ["--json", "--demosaic", "full"])):
            out = root / f"out-{key}"
            # the previous run's outputs (up to 6 GB) reach the disk before this run, not during it; the frames
            # are read from the disk, not from memory
            evict_from_page_cache(frames)
            res = pihim(["polar", *frames, "--out", str(out), *extra])
            records = res["stdout"].strip().splitlines()
            runs[key] = {k: res[k] for k in ("returncode", "wall_s", "cpu_s", "load_before", "load_after", "other_cpu")}
            runs[key].update(frames=n_frames, records=len(records), ms_per_frame=1e3 * res["wall_s"] / n_frames,
                             cpu_ms_per_frame=1e3 * res["cpu_s"] / n_frames,
                             output_mb_per_frame=_folder_bytes(out) / n_frames / 1e6)
            shutil.rmtree(out, ignore_errors=True)
        out = root / "out-anchor"
        out.mkdir()
        evict_from_page_cache(frames)
        res = harness.process_run([sys.executable, "-c", _ANCHOR_SCRIPT, str(Path(__file__).resolve().parent),
                                   str(out), *frames], env=_env())
        runs["numpy_script"] = {k: res[k] for k in ("returncode", "wall_s", "cpu_s", "load_before", "load_after",
                                                      "other_cpu")}
        runs["numpy_script"].update(frames=n_frames, ms_per_frame=1e3 * res["wall_s"] / n_frames,
                                    cpu_ms_per_frame=1e3 * res["cpu_s"] / n_frames)
        runs["disk_write_mb_s"] = disk_write_mb_s(root)
        runs["disk_read_mb_s"] = disk_read_mb_s(frames)
        input_mb_per_frame = sum(os.path.getsize(f) for f in frames) / n_frames / 1e6
    for key in ("superpixel", "superpixel_png", "full"):
        runs[key]["input_mb_per_frame"] = input_mb_per_frame
        runs[key]["disk_floor_ms_per_frame"] = 1e3 * (runs[key]["output_mb_per_frame"] / runs["disk_write_mb_s"]
                                                      + input_mb_per_frame / runs["disk_read_mb_s"])
    sp, png = runs["superpixel"], runs["superpixel_png"]
    runs["previews"] = {"ms_per_frame": png["ms_per_frame"] - sp["ms_per_frame"],
                        "cpu_ms_per_frame": png["cpu_ms_per_frame"] - sp["cpu_ms_per_frame"]}
    return runs


def run_benchmark(quick: bool = False, startup_only: bool = False) -> dict[str, Any]:
    """All measurements (with ``startup_only``, the start-up ones alone); the JSON-ready report."""
    n_help = 3 if quick else 7
    report: dict[str, Any] = {"benchmark": "cli", "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                              "machine": harness.machine_info()}
    for c in ("", *COMMANDS):  # untimed: Python's bytecode cache written, as after a first run
        pihim([c, "--help"] if c else ["--help"])
    report["help"] = _median_run(["--help"], n_help, importtime=False)
    report["help_imports"] = _median_run(["--help"], n_help, importtime=True)
    report["command_help"] = {c: _median_run([c, "--help"], 1 if quick else 3, importtime=True) for c in COMMANDS}
    with tempfile.TemporaryDirectory(prefix="pihim-bench-cli-") as tmp:
        frame = make_frames(Path(tmp), 1)[0]
        real = {}
        for i, (label, args) in enumerate(REAL_RUNS):
            def argv(k: int, i: int = i, args: Sequence[str] = args) -> list[str]:
                # a fresh output folder for every run: into a used one, `pihim polar` resumes (skips the frame,
                # loads no kernel) and the run would not be one a user makes
                return [str(frame) if a == "FRAME" else str(Path(tmp) / f"out-{i}-{k}") if a == "OUT" else a
                        for a in args]

            pihim(argv(-1))  # caches (numba) as after a first run
            real[label] = _median_run(argv, 1 if quick else 3, importtime=True, floor=True)
        report["real_runs"] = real
    startup = [report["help_imports"]["import_cpu_s"],
               *(r["import_cpu_s"] for r in report["command_help"].values()),
               *(r["import_cpu_s"] for r in report["real_runs"].values())]
    report["targets"] = [
        harness.target("pihim --help, process wall (median)", report["help"]["wall_s"], TARGET_HELP_S, "s"),
        harness.target("pihim --help, process CPU (median)", report["help"]["cpu_s"], TARGET_HELP_S, "s"),
        harness.target("largest import overhead (CPU) of any command, help or real run", max(startup),
                       TARGET_IMPORT_S, "s"),
    ]
    if startup_only:
        return report
    report["polar"] = polar_runs(20 if quick else 100)
    p = report["polar"]
    report["targets"] += [
        harness.target(f"polar super-pixel --json, {p['superpixel']['frames']} frames, per frame",
                       p["superpixel"]["ms_per_frame"], TARGETS_MS["superpixel"], "ms"),
        harness.target("polar full --json, per frame", p["full"]["ms_per_frame"], TARGETS_MS["full"], "ms"),
        harness.target("polar --png previews, added per frame", p["previews"]["ms_per_frame"], TARGETS_MS["previews"],
                       "ms"),
    ]
    return report


def _f(v: float | None, spec: str = ".2f") -> str:
    return "-" if v is None else f"{v:{spec}}"


def markdown_report(r: dict[str, Any]) -> str:
    """The report as markdown."""
    h = r["help"]
    lines = ["| Process | runs | wall s | CPU s | imports CPU s | imports wall s | -X importtime s "
             "| Other CPU % | Load before / after |",
             "|---|--:|--:|--:|--:|--:|--:|--:|--:|"]
    hi = r["help_imports"]
    lines.append(f"| `pihim --help` | {h['runs']} | {_f(h['wall_s'])} | {_f(h['cpu_s'])} | {_f(hi['import_cpu_s'])} | "
                 f"{_f(hi['import_wall_s'])} | {_f(hi['import_s'])} | {harness.other_pct(h['other_cpu'])} | "
                 f"{_f(h['load_before'], '.1f')} / {_f(h['load_after'], '.1f')} |")
    for label, x in [*((f"`pihim {c} --help`", x) for c, x in r["command_help"].items()),
                     *((f"`pihim {c}` (real run)", x) for c, x in r["real_runs"].items())]:
        lines.append(f"| {label} | {x['runs']} | {_f(x['wall_s'])} | {_f(x['cpu_s'])} | {_f(x['import_cpu_s'])} | "
                     f"{_f(x['import_wall_s'])} | {_f(x['import_s'])} | {harness.other_pct(x['other_cpu'])} | "
                     f"{_f(x['load_before'], '.1f')} / {_f(x['load_after'], '.1f')} |")
    lines += ["", "Import CPU of each real run beside its floor: every module the run loaded except pihim's own "
              "(numpy, typer, matplotlib, numba's registries, the standard library, ...), imported in the same order "
              "by a bare Python process right after the run (median of the runs).", "",
              "| Real run | imports CPU s | dependencies alone, CPU s | pihim's own share, CPU s | modules |",
              "|---|--:|--:|--:|--:|"]
    for c, x in r["real_runs"].items():
        if x.get("floor_cpu_s") is not None:
            lines.append(f"| `pihim {c}` | {_f(x['import_cpu_s'])} | {_f(x['floor_cpu_s'])} | {_f(x['own_cpu_s'])} "
                         f"| {x['floor_modules']:.0f} |")
    if "polar" not in r:
        lines += harness.target_table(r["targets"], spec=".2f", unit_spec={"ms": ".1f"}, column="Result", align="--:")
        return "\n".join(lines)
    p = r["polar"]
    lines += ["", "| `pihim polar` as one process | frames | wall s | CPU s | ms per frame | CPU ms per frame "
              "| Other CPU % | Load before / after |", "|---|--:|--:|--:|--:|--:|--:|--:|"]
    for key, label in (("superpixel", "super-pixel `--json`"), ("full", "full resolution `--json`"),
                       ("superpixel_png", "super-pixel `--json --png`"),
                       ("numpy_script", "anchor: numpy script (read, super-pixel, 3 TIFFs)")):
        x = p[key]
        lines.append(f"| {label} | {x['frames']} | {x['wall_s']:.2f} | {x['cpu_s']:.2f} | {x['ms_per_frame']:.1f} | "
                     f"{x['cpu_ms_per_frame']:.1f} | {harness.other_pct(x['other_cpu'])} | "
                     f"{_f(x['load_before'], '.1f')} / {_f(x['load_after'], '.1f')} |")
    lines.append(f"| previews (`--png` minus super-pixel) | | | | {p['previews']['ms_per_frame']:.1f} | "
                 f"{p['previews']['cpu_ms_per_frame']:.1f} | | |")
    disk = p.get("disk_write_mb_s")
    if disk:
        lines += ["", f"Disk, same run: {disk:.0f} MB/s sustained writes (1 GiB written as `pihim polar` writes, "
                  f"with direct I/O), {p['disk_read_mb_s']:.0f} MB/s reads (the frames, dropped from the page cache "
                  "as before each run). Bytes per frame and the time the disk needs for them, read plus written "
                  "(`pihim polar` reads the frames off the disk and writes past the page cache: a run cannot go "
                  "faster than its disk floor):", "",
                  "| run | MB read per frame | MB written per frame | disk floor, ms per frame "
                  "| measured, ms per frame |", "|---|--:|--:|--:|--:|"]
        for key, label in (("superpixel", "super-pixel `--json`"), ("superpixel_png", "super-pixel `--json --png`"),
                           ("full", "full resolution `--json`")):
            x = p[key]
            lines.append(f"| {label} | {x['input_mb_per_frame']:.1f} | {x['output_mb_per_frame']:.1f} "
                         f"| {x['disk_floor_ms_per_frame']:.1f} | {x['ms_per_frame']:.1f} |")
    lines += harness.target_table(r["targets"], spec=".2f", unit_spec={"ms": ".1f"}, column="Result", align="--:")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None, *, quick: bool = False, json_path: Path | None = RESULTS_PATH,
         echo: bool = True) -> dict[str, Any]:
    """Run the benchmark, print the markdown report and write the JSON.

    Parameters
    ----------
    argv : sequence of str, optional
        ``--quick``, ``--json PATH``, ``--startup-only``.
    quick : bool
        20 frames instead of 100, fewer repetitions.
    json_path : pathlib.Path or None
        Where to write the JSON report.
    echo : bool
        Print the markdown report.
    """
    if argv:
        parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
        parser.add_argument("--quick", action="store_true", help="20 frames, fewer repetitions")
        parser.add_argument("--json", type=Path, default=json_path, metavar="PATH", help="JSON output path")
        parser.add_argument("--startup-only", action="store_true",
                            help="the start-up measurements alone (no `pihim polar` over many frames)")
        args = parser.parse_args(list(argv))
        quick, json_path, startup_only = quick or args.quick, args.json, args.startup_only
    else:
        startup_only = False
    if startup_only and json_path == RESULTS_PATH:
        json_path = RESULTS_PATH.with_name("cli_startup.json")
    report = run_benchmark(quick, startup_only)
    report["quick"] = quick
    report["startup_only"] = startup_only
    return harness.publish(report, markdown_report, json_path, echo=echo)


if __name__ == "__main__":
    main(sys.argv[1:] or None)
