"""Run the pihim benchmark suite with one command: ``python benchmarks/run.py``.

Every module ``benchmarks/<name>.py`` (except this file and names starting
with ``_``) that defines a ``main()`` returning its results is a benchmark.
Modules named ``*_quality.py`` are accuracy studies: they are slow, measure
no speed and run only with ``--quality``. All others are speed benchmarks and
run by default.

Options are forwarded to a module's ``main`` only when its signature accepts
them (``repeat``, ``warmup``, ``quick``, ``wait_quiet``, or ``**kwargs``); a
``main(argv)`` receives an empty argument list so that it keeps its own
defaults instead of parsing this script's command line.

Exit status: 1 if a benchmark raised (or, with ``--strict``, if a reported
target failed), else 0.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import sys
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

BENCH_DIR = Path(__file__).resolve().parent
QUALITY_SUFFIX = "_quality"


def discover(directory: Path = BENCH_DIR, quality: bool = False) -> list[str]:
    """Names of the benchmark modules in ``directory``, sorted.

    Only file names are looked at, so an accuracy study is not even imported
    unless ``quality`` is true.

    Parameters
    ----------
    directory : pathlib.Path
        Folder holding the benchmark modules.
    quality : bool
        Include the ``*_quality`` accuracy studies.
    """
    names = []
    for path in sorted(directory.glob("*.py")):
        name = path.stem
        if path.resolve() == Path(__file__).resolve() or name.startswith("_"):
            continue
        if name.endswith(QUALITY_SUFFIX) and not quality:
            continue
        names.append(name)
    return names


def call_main(main: Callable[..., Any], options: dict[str, Any]) -> Any:
    """Call a module's ``main`` with the subset of ``options`` it accepts.

    Parameters
    ----------
    main : callable
        The module's entry point.
    options : dict
        Candidate keyword arguments; ``None`` values are dropped so that the
        module's own defaults apply.
    """
    params = inspect.signature(main).parameters
    given = {k: v for k, v in options.items() if v is not None}
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        kwargs = given
    else:
        by_name = (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
        kwargs = {k: v for k, v in given.items() if k in params and params[k].kind in by_name}
    if "argv" in params:
        kwargs["argv"] = []
    return main(**kwargs)


def _targets_summary(results: Any) -> tuple[str, bool]:
    """One-line verdict of a results dict's ``targets``; and whether any failed."""
    targets = results.get("targets") if isinstance(results, dict) else None
    if not targets:
        return "", False
    verdicts = [{True: "PASS", False: "FAIL", None: "n/a"}[t.get("passed")] for t in targets]
    counts = ", ".join(f"{verdicts.count(v)} {v}" for v in ("PASS", "FAIL", "n/a") if v in verdicts)
    return f"targets: {counts}", "FAIL" in verdicts


#: First argument of this file's command line in a benchmark's own process (see :func:`run`).
_CHILD = "--run-one"


def run_one(name: str, options: dict[str, Any]) -> dict[str, Any] | None:
    """Import and run one benchmark module in this process; its outcome, or None if it has no ``main()``."""
    if str(BENCH_DIR) not in sys.path:
        sys.path.insert(0, str(BENCH_DIR))
    try:
        module = importlib.import_module(name)
        entry = getattr(module, "main", None)
        if not callable(entry):
            print(f"(skipped: {name}.py defines no main())")
            return None
        return {"ok": True, "results": call_main(entry, options)}
    except Exception:  # noqa: BLE001 - report and go on with the next benchmark
        traceback.print_exc()
        return {"ok": False, "error": traceback.format_exc(limit=1).strip().splitlines()[-1]}


def run(names: Sequence[str], options: dict[str, Any]) -> dict[str, Any]:
    """Run the named benchmark modules one after the other, each in a new Python process of its own.

    A module's figures then do not depend on the modules run before it in
    the same process (numba's loaded registries, caches, the allocator's
    thresholds raised by their large arrays): each starts as a user's
    process does.

    Returns
    -------
    dict
        ``{name: {"ok": bool, "seconds": float, "results": ..., "error": str}}``.
    """
    import json
    import subprocess
    import tempfile

    outcome: dict[str, Any] = {}
    for name in names:
        print(f"\n## {name}\n", flush=True)
        start = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="pihim-bench-run-") as tmp:
            report = Path(tmp) / "outcome.json"
            proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), _CHILD, name,
                                   json.dumps(options), str(report)], check=False)
            if report.exists():
                res = json.loads(report.read_text())
            else:
                res = {"ok": False, "error": f"its process ended with status {proc.returncode} and no outcome"}
        if res is None:
            continue
        outcome[name] = {**res, "seconds": time.perf_counter() - start}
        sys.stdout.flush()
    return outcome


def _child(name: str, options: str, report: str) -> None:
    """A benchmark's own process: run it and write its outcome (JSON) to ``report``."""
    import json

    res = run_one(name, json.loads(options))
    sys.stdout.flush()
    Path(report).write_text(json.dumps(res, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; returns the exit status."""
    parser = argparse.ArgumentParser(description="Run the pihim benchmarks (speed by default).")
    parser.add_argument("--repeat", type=int, metavar="N", help="timed repetitions per measurement (default 30)")
    parser.add_argument("--warmup", type=int, metavar="N", help="untimed warm-up calls (default 3)")
    parser.add_argument("--quick", action="store_true", help="few repetitions, for a fast look")
    parser.add_argument(
        "--wait-quiet",
        type=float,
        metavar="S",
        help="wait up to S seconds per measurement for other processes to leave the CPUs idle",
    )
    parser.add_argument("--quality", action="store_true", help="also run the *_quality accuracy studies")
    parser.add_argument("--only", action="append", metavar="NAME", help="run only this module (repeatable)")
    parser.add_argument("--strict", action="store_true", help="exit 1 when a reported target fails")
    parser.add_argument("--list", action="store_true", help="list the benchmark modules and exit")
    args = parser.parse_args(argv)

    names = discover(quality=args.quality)
    if args.only:
        known = discover(quality=True)
        unknown = sorted(set(args.only) - set(known))
        if unknown:
            parser.error(f"unknown benchmark(s) {', '.join(unknown)}; available: {', '.join(known)}")
        gated = sorted(set(args.only) - set(names))
        if gated:
            parser.error(f"{', '.join(gated)} is an accuracy study: add --quality to run it")
        names = [n for n in names if n in args.only]
    if args.list:
        print("\n".join(names))
        return 0

    options = {"repeat": args.repeat, "warmup": args.warmup, "quick": args.quick or None, "wait_quiet": args.wait_quiet}
    outcome = run(names, options)

    print("\n## Summary\n")
    status = 0
    for name, res in outcome.items():
        if not res["ok"]:
            print(f"- {name}: ERROR ({res['error']}) after {res['seconds']:.1f} s")
            status = 1
            continue
        verdict, failed = _targets_summary(res["results"])
        where = res["results"].get("json_path") if isinstance(res["results"], dict) else None
        extras = "; ".join(x for x in (verdict, f"JSON: {where}" if where else "") if x)
        print(f"- {name}: done in {res['seconds']:.1f} s" + (f" ({extras})" if extras else ""))
        if failed and args.strict:
            status = 1
    return status


if __name__ == "__main__":
    if sys.argv[1:2] == [_CHILD]:
        _child(*sys.argv[2:5])
    else:
        sys.exit(main())
