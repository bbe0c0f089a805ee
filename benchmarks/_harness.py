"""Timing harness shared by the benchmark modules in this folder.

Not a benchmark itself (``run.py`` skips names starting with ``_``). A
benchmark module imports it after putting its own folder on ``sys.path``,
so that it works both as a script and when imported by ``run.py`` or a test::

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import _harness as harness

What it provides:

* load of other processes from ``/proc/stat`` (:func:`cpu_times`,
  :func:`other_cpu_load`, :func:`wait_for_quiet`);
* timing (:func:`time_calls`, :func:`traced_peak` and the row figures of
  :func:`measure`);
* command line and call counts (:class:`Counts`, :func:`options`);
* machine description, targets, markdown pieces and JSON output.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import time
import tracemalloc
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

#: Share of the CPUs used by other processes above which a timing counts as disturbed.
BUSY_WARNING = 0.05
#: Markdown verdict of a target's ``passed`` flag (``None``: figure missing).
VERDICTS: dict[bool | None, str] = {True: "PASS", False: "FAIL", None: "n/a"}

#: ``(wall s, busy CPU s of the machine, CPU s of this process)``, see :func:`cpu_times`.
CpuSample = tuple[float, float, float]


# ---------------------------------------------------------------------------
# Load of other processes
# ---------------------------------------------------------------------------
def cpu_times() -> CpuSample | None:
    """Wall clock, busy CPU time of the machine and CPU time of this process.

    Busy time is read from ``/proc/stat`` (user, nice, system, irq, softirq
    and hypervisor steal, summed over CPUs).

    Returns
    -------
    tuple of float or None
        ``(wall s, busy CPU s, own CPU s)``; ``None`` where ``/proc/stat`` is missing.
    """
    try:
        with open("/proc/stat", encoding="ascii") as fh:
            ticks = [int(v) for v in fh.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    user, nice, system, _idle, _iowait, irq, softirq, steal = ticks + [0] * (8 - len(ticks))
    own = os.times()
    busy = (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")
    return time.perf_counter(), busy, own.user + own.system


def children_cpu_s() -> float:
    """CPU time (user + system, s) of this process's child processes that have ended and been waited for."""
    t = os.times()
    return t.children_user + t.children_system


def other_cpu_load(start: CpuSample | None, end: CpuSample | None) -> float | None:
    """Fraction of the machine's CPU capacity used by *other* processes between two samples.

    Anything well above zero means the timings were taken on a busy machine
    and are inflated (parallel kernels suffer most: a thread that loses its
    core stalls the whole ``prange``). Resolution is one clock tick (10 ms).

    Parameters
    ----------
    start, end : tuple of float or None
        Samples of :func:`cpu_times`.

    Returns
    -------
    float or None
        The fraction (0 = idle machine); ``None`` if a sample is missing.
    """
    if start is None or end is None or end[0] <= start[0]:
        return None
    others = (end[1] - start[1]) - (end[2] - start[2])
    return max(others, 0.0) / ((end[0] - start[0]) * (os.cpu_count() or 1))


def wait_for_quiet(timeout_s: float, threshold: float = BUSY_WARNING, window_s: float = 2.0) -> float | None:
    """Wait until other processes use less than ``threshold`` of the CPUs over ``window_s``.

    Parameters
    ----------
    timeout_s : float
        Give up after this many seconds.
    threshold : float
        Load (fraction of the CPUs) counted as quiet.
    window_s : float
        Length of each load measurement.

    Returns
    -------
    float or None
        The last measured load; ``None`` where it cannot be measured.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        start = cpu_times()
        time.sleep(window_s)
        load = other_cpu_load(start, cpu_times())
        if load is None or load < threshold or time.monotonic() >= deadline:
            return load


# ---------------------------------------------------------------------------
# Timing
# ---------------------------------------------------------------------------
def time_calls(
    fn: Callable[[], Any], repeat: int, *, pause_gc: bool = True
) -> tuple[NDArray[np.float64], float | None]:
    """Wall time of ``repeat`` calls of ``fn``, one after the other.

    Each call's result is released after its clock stops.

    Parameters
    ----------
    fn : callable
        The call to time, without arguments.
    repeat : int
        Number of timed calls.
    pause_gc : bool
        Disable the garbage collector during the calls.

    Returns
    -------
    samples_ms : numpy.ndarray, shape (repeat,)
        Time of each call in milliseconds.
    other_load : float or None
        :func:`other_cpu_load` over the calls.
    """
    samples = np.empty(repeat)
    gc_was_enabled = gc.isenabled()
    if pause_gc:
        gc.disable()
    start = cpu_times()
    children0 = children_cpu_s()
    try:
        for k in range(repeat):
            t0 = time.perf_counter_ns()
            out = fn()
            samples[k] = (time.perf_counter_ns() - t0) / 1e6
            del out
    finally:
        if gc_was_enabled:
            gc.enable()
    end = cpu_times()
    if end is not None:  # worker processes the calls forked are this run's work, not other load
        end = (end[0], end[1], end[2] + children_cpu_s() - children0)
    return samples, other_cpu_load(start, end)


def traced_peak(fn: Callable[[], Any]) -> tuple[int, Any]:
    """Peak of the memory traced by :mod:`tracemalloc` during one call of ``fn``.

    Only Python allocations are traced (numpy arrays included; scratch memory
    of numba kernels, OpenCV or BLAS is not).

    Returns
    -------
    peak_bytes : int
        Peak traced bytes above the level at the start of the call.
    result : object
        What ``fn`` returned.
    """
    gc.collect()
    tracemalloc.start()
    try:
        baseline = tracemalloc.get_traced_memory()[0]
        out = fn()
        peak = tracemalloc.get_traced_memory()[1] - baseline
    finally:
        tracemalloc.stop()
    return peak, out


def measure(
    fn: Callable[[], Any],
    repeat: int,
    warmup: int,
    *,
    pause_gc: bool = True,
    trace: bool = True,
    nbytes: Callable[[Any], int] | None = None,
) -> dict[str, Any]:
    """The figures of one benchmark row.

    ``warmup`` untimed calls, ``repeat`` timed calls (:func:`time_calls`),
    then one traced call (:func:`traced_peak`).

    Parameters
    ----------
    fn : callable
        The call to time, without arguments.
    repeat, warmup : int
        Timed and untimed calls.
    pause_gc : bool
        Disable the garbage collector during the timed calls.
    trace : bool
        Make the traced call (else ``peak_mb`` is ``None``).
    nbytes : callable, optional
        Bytes held by a result; adds ``output_mb`` (needs ``trace``).

    Returns
    -------
    dict
        ``median_ms``, ``p10_ms``, ``p90_ms``, ``cpu_ms`` (process CPU time,
        all threads, and of the worker processes the calls started and
        waited for, per timed call), ``load_avg`` (one-minute load average
        after the timed calls), ``peak_mb``, [``output_mb``], ``other_cpu``
        (see :func:`other_cpu_load`) and ``repeat``.
    """
    for _ in range(warmup):
        fn()
    gc.collect()
    cpu0 = time.process_time() + children_cpu_s()
    samples, load = time_calls(fn, repeat, pause_gc=pause_gc)
    cpu_ms = 1e3 * (time.process_time() + children_cpu_s() - cpu0) / repeat
    median, p10, p90 = (float(v) for v in np.percentile(samples, [50, 10, 90]))
    row: dict[str, Any] = {"median_ms": median, "p10_ms": p10, "p90_ms": p90, "cpu_ms": cpu_ms,
                           "load_avg": load_average(), "peak_mb": None}
    if trace:
        peak, out = traced_peak(fn)
        row["peak_mb"] = peak / 1e6
        if nbytes is not None:
            row["output_mb"] = nbytes(out) / 1e6
    return {**row, "other_cpu": load, "repeat": repeat}


# ---------------------------------------------------------------------------
# Call counts and command line
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Counts:
    """Default numbers of timed (``repeat``) and untimed (``warmup``) calls per row.

    Attributes
    ----------
    repeat, warmup : int
        Normal run.
    quick_repeat, quick_warmup : int
        With ``--quick``.
    cap_quick : bool
        With ``--quick``, an explicit ``repeat`` is capped at ``quick_repeat``
        (else it is kept).
    """

    repeat: int
    warmup: int
    quick_repeat: int
    quick_warmup: int
    cap_quick: bool = False

    def resolve(self, repeat: int | None, warmup: int | None, quick: bool) -> tuple[int, int]:
        """``(repeat, warmup)`` from the given values (``None``: default).

        Raises
        ------
        ValueError
            If ``repeat < 1`` or ``warmup < 0``.
        """
        if repeat is None:
            repeat = self.quick_repeat if quick else self.repeat
        elif quick and self.cap_quick:
            repeat = min(repeat, self.quick_repeat)
        if warmup is None:
            warmup = self.quick_warmup if quick else self.warmup
        if repeat < 1 or warmup < 0:
            raise ValueError("repeat must be >= 1 and warmup >= 0")
        return repeat, warmup


@dataclass(frozen=True)
class Options:
    """Settings of one run, see :func:`options`.

    Attributes
    ----------
    repeat, warmup : int
        Timed and untimed calls per row.
    quick : bool
        Fast look requested.
    json_path : pathlib.Path or None
        Where to write the JSON report.
    args : argparse.Namespace or None
        The parsed command line (module-specific options included); ``None``
        when there was none.
    """

    repeat: int
    warmup: int
    quick: bool
    json_path: Path | None
    args: argparse.Namespace | None = None


def options(
    argv: Sequence[str] | None,
    *,
    description: str,
    counts: Counts,
    repeat: int | None,
    warmup: int | None,
    quick: bool,
    json_path: Path | None,
    configure: Callable[[argparse.ArgumentParser], None] | None = None,
) -> Options:
    """Merge a module's ``main`` arguments with its command line.

    Parameters
    ----------
    argv : sequence of str or None
        Command-line arguments (``--repeat N``, ``--warmup N``, ``--quick``,
        ``--json PATH`` and what ``configure`` adds); ``None`` or empty reads
        nothing. Given options override the keyword values.
    description : str
        Help text of the parser.
    counts : Counts
        Defaults for ``repeat`` and ``warmup``.
    repeat, warmup : int or None
        Values passed to ``main`` (``None``: default of ``counts``).
    quick : bool
        Fast look requested by the caller.
    json_path : pathlib.Path or None
        Default JSON output path.
    configure : callable, optional
        Adds module-specific options to the parser; read them from
        :attr:`Options.args`.
    """
    args = None
    if argv:
        parser = argparse.ArgumentParser(description=description)
        parser.add_argument("--repeat", type=int, metavar="N", help="timed calls per row")
        parser.add_argument("--warmup", type=int, metavar="N", help="untimed calls before timing")
        parser.add_argument("--quick", action="store_true", help="fewer calls, for a fast look")
        parser.add_argument("--json", type=Path, default=json_path, metavar="PATH", help="JSON output path")
        if configure is not None:
            configure(parser)
        args = parser.parse_args(list(argv))
        repeat = args.repeat if args.repeat is not None else repeat
        warmup = args.warmup if args.warmup is not None else warmup
        quick = quick or args.quick
        json_path = args.json
    repeat, warmup = counts.resolve(repeat, warmup, quick)
    return Options(repeat, warmup, quick, json_path, args)


# ---------------------------------------------------------------------------
# Machine, targets, report
# ---------------------------------------------------------------------------
def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo`` (else what :mod:`platform` knows)."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            model = next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), model)
    except OSError:  # pragma: no cover - not Linux
        pass
    return model


def machine_info() -> dict[str, Any]:
    """CPU count, platform, Python and numpy versions."""
    return {
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
    }


def target(name: str, measured: float | None, limit: float, unit: str, *, at_most: bool = True) -> dict[str, Any]:
    """A target's verdict, as reported in the JSON and summarised by ``run.py``.

    Parameters
    ----------
    name : str
        What the target is.
    measured : float or None
        The figure (``None``: not measured, ``passed`` is ``None``).
    limit : float
        Required value.
    unit : str
        Unit of ``measured`` and ``limit``.
    at_most : bool
        ``limit`` is a maximum (else a minimum).
    """
    passed = None if measured is None else (measured <= limit if at_most else measured >= limit)
    required = f"{'<=' if at_most else '>='} {limit:g} {unit}"
    return {"target": name, "required": required, "measured": measured, "unit": unit, "passed": passed}


def other_pct(load: float | None) -> str:
    """``other_cpu`` as a whole percentage for a table cell ("-" if unknown)."""
    return "-" if load is None else f"{100 * load:.0f}"


def ms_cells(row: Mapping[str, Any], spec: str) -> str:
    """The ``median | p10 | p90`` cells of a row measured by :func:`measure`."""
    return f"{row['median_ms']:{spec}} | {row['p10_ms']:{spec}} | {row['p90_ms']:{spec}}"


def target_table(
    targets: Iterable[Mapping[str, Any]],
    *,
    spec: str = ".2f",
    unit_spec: Mapping[str, str] | None = None,
    column: str = "Verdict",
    align: str = "---:",
) -> list[str]:
    """Markdown lines of the targets table, preceded by a blank line.

    Parameters
    ----------
    targets : iterable of dict
        Made by :func:`target`.
    spec : str
        Format of the measured value.
    unit_spec : mapping, optional
        Format by unit, overriding ``spec``.
    column, align : str
        Header of the verdict column and alignment of the measured one.
    """
    lines = ["", f"| Target | Required | Measured | {column} |", f"|---|---|{align}|---|"]
    for t in targets:
        fmt = (unit_spec or {}).get(t["unit"], spec)
        measured = "-" if t["measured"] is None else f"{t['measured']:{fmt}} {t['unit']}"
        lines.append(f"| {t['target']} | {t['required']} | {measured} | {VERDICTS[t['passed']]} |")
    return lines


def busy_warning(loads: Iterable[float | None]) -> list[str]:
    """Markdown lines warning about rows timed while other processes were busy (none if all were quiet)."""
    busy = sum(load is not None and load > BUSY_WARNING for load in loads)
    if not busy:
        return []
    return [
        "",
        (
            f"Warning: other processes used more than {100 * BUSY_WARNING:g} % of the CPUs during {busy} row(s); "
            "those figures are inflated."
        ),
    ]


def write_json(report: dict[str, Any], path: Path | None, *, announce: bool = False) -> None:
    """Write ``report`` as indented JSON (atomically) and record the path in ``report["json_path"]``.

    Parameters
    ----------
    report : dict
        JSON-ready report.
    path : pathlib.Path or None
        Output file (folders are created); ``None`` writes nothing.
    announce : bool
        Print where the file went.
    """
    if path is None:
        return
    from pihim._atomic import write_text_atomic

    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(report, indent=2) + "\n")  # never a half-written report
    report["json_path"] = str(path)
    if announce:
        print(f"\nJSON written to {path}")


def publish(report: dict[str, Any], markdown: Callable[[dict[str, Any]], str], path: Path | None, *,
            echo: bool = True) -> dict[str, Any]:
    """A benchmark's last step: write its JSON report, then print its markdown table and where the JSON went.

    The JSON goes first, so that a long run is never lost to a table that fails to render.

    Parameters
    ----------
    report : dict
        JSON-ready report.
    markdown : callable
        ``markdown(report)`` -> the report as markdown.
    path : pathlib.Path or None
        JSON output file; ``None`` writes nothing.
    echo : bool
        Print the table (and the JSON's path).

    Returns
    -------
    dict
        ``report``.
    """
    write_json(report, path)
    if echo:
        print(markdown(report))
        if path is not None:
            print(f"\nJSON written to {path}")
    return report


# ---------------------------------------------------------------------------
# CPU time, load average and memory bandwidth (issue 12: figures as users see them)
# ---------------------------------------------------------------------------
def load_average() -> float | None:
    """One-minute load average of the machine (``os.getloadavg``), ``None`` where unknown."""
    try:
        return float(os.getloadavg()[0])
    except (OSError, AttributeError):  # pragma: no cover - not Unix
        return None


def time_calls_cpu(fn: Callable[[int], Any], repeat: int) -> dict[str, Any]:
    """Wall and CPU time of ``repeat`` calls ``fn(k)``, ``k = 0 .. repeat - 1`` (e.g. rotating inputs).

    CPU time is this process's (all threads, :func:`time.process_time`),
    over all the calls, divided by ``repeat``. The garbage collector is
    paused; each result is released after its clock stops.

    Returns
    -------
    dict
        ``samples_ms`` (array), ``median_ms``, ``p10_ms``, ``p90_ms``,
        ``cpu_ms`` (per call), ``other_cpu`` (:func:`other_cpu_load`),
        ``load_avg`` (one-minute load average at the end), ``repeat``,
        ``page_faults`` (this process's minor page faults per call: new
        pages the kernel maps and zeroes; 0 when the allocator hands back
        pages freed by the call before).
    """
    import resource

    samples = np.empty(repeat)
    gc_was_enabled = gc.isenabled()
    gc.disable()
    faults0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    start = cpu_times()
    cpu0 = time.process_time()
    try:
        for k in range(repeat):
            t0 = time.perf_counter_ns()
            out = fn(k)
            samples[k] = (time.perf_counter_ns() - t0) / 1e6
            del out
    finally:
        if gc_was_enabled:
            gc.enable()
    cpu = (time.process_time() - cpu0) / repeat
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0) / repeat
    median, p10, p90 = (float(v) for v in np.percentile(samples, [50, 10, 90]))
    return {"samples_ms": samples, "median_ms": median, "p10_ms": p10, "p90_ms": p90, "cpu_ms": 1e3 * cpu,
            "other_cpu": other_cpu_load(start, cpu_times()), "load_avg": load_average(), "repeat": repeat,
            "page_faults": faults}


def memory_bandwidth(nbytes: int = 256 * 2**20, repeat: int = 7) -> dict[str, float]:
    """The machine's memory bandwidth for a large copy (``numpy.copyto``), best of ``repeat``.

    Both arrays are far larger than any cache and already touched, so this
    is the sustained DRAM rate one thread gets for a streaming read plus
    write: the floor of any pass that reads and writes images. Counted as
    bytes read plus bytes written per second.

    Returns
    -------
    dict
        ``copy_gb_s`` (best), ``copy_gb_s_median`` and ``bytes``.
    """
    n = nbytes // 8
    src = np.ones(n)
    dst = np.empty(n)
    np.copyto(dst, src)
    rates = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        np.copyto(dst, src)
        rates.append(2 * nbytes / (time.perf_counter() - t0) / 1e9)
    return {"copy_gb_s": float(max(rates)), "copy_gb_s_median": float(np.median(rates)), "bytes": float(nbytes)}


def process_run(argv: Sequence[str], *, env: Mapping[str, str] | None = None, cwd: str | None = None,
                timeout: float = 3600.0) -> dict[str, Any]:
    """Run a command as a separate process; its wall time, CPU time (user + system) and the load around it.

    Returns
    -------
    dict
        ``returncode``, ``wall_s``, ``cpu_s``, ``load_before``, ``load_after``,
        ``other_cpu`` (share of the CPUs other processes used meanwhile),
        ``stdout``, ``stderr``.
    """
    import resource
    import subprocess

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load0 = load_average()
    start = cpu_times()
    t0 = time.perf_counter()
    proc = subprocess.run(list(argv), capture_output=True, text=True, env=None if env is None else dict(env),
                          cwd=cwd, timeout=timeout)
    wall = time.perf_counter() - t0
    end = cpu_times()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    others = None
    if start is not None and end is not None:
        busy = end[1] - start[1]
        others = max(busy - cpu, 0.0) / (wall * (os.cpu_count() or 1))
    return {"returncode": proc.returncode, "wall_s": wall, "cpu_s": cpu, "load_before": load0,
            "load_after": load_average(), "other_cpu": others, "stdout": proc.stdout, "stderr": proc.stderr}
