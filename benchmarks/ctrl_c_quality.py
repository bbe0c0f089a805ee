"""Reliability study: Ctrl-C pressed three times at random moments of ``pihim plan`` and ``pihim windows``.

Each run starts one of the two commands (the embedded NSTTF-like field; ``windows`` at 30-minute steps, so that
it forks workers) in a session of its own, waits 0.3-3 s, and sends SIGINT to the whole process group three
times, 0-300 ms apart, as a terminal does when Ctrl-C is pressed repeatedly. A run is *bad* when it takes more
than 60 s to end (then killed), prints a traceback, or ends with a status other than 0 (it had finished), 130
or -2 (death by SIGINT in the interpreter's last steps, which a shell also shows as 130).

    python benchmarks/ctrl_c_quality.py --runs 90 --seed 7

Run it in the foreground: a process started in the background by a non-interactive shell ignores SIGINT, and
so do the commands it starts. It measures no speed: ``run.py`` runs it with the accuracy studies
(``--quality``). On 2252d9e (before the Ctrl-C work of 2026-11-28) 3 of 60 runs (seed 7) were bad, one hung;
since cd61fe2 none in 20-90 runs per seed. tests/test_main.py holds small deterministic versions.
"""

from __future__ import annotations

import argparse
import collections
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def one_run(kind: str, out: Path, start_s: float, gaps_s: list[float]) -> tuple[int | None, str]:
    """Start ``pihim KIND``, press Ctrl-C after ``start_s`` and then after each gap; (status, stderr)."""
    args = (["plan", "--time", "2021-05-13T13:00-06:00"] if kind == "plan"
            else ["windows", "--date", "2021-05-13", "--step-min", "30"])
    child = subprocess.Popen([sys.executable, "-m", "pihim", *args, "--out", str(out)], stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, text=True, start_new_session=True)
    time.sleep(start_s)
    for gap in gaps_s:
        if child.poll() is None:
            try:
                os.killpg(child.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
        time.sleep(gap)
    try:
        _, err = child.communicate(timeout=60)
        return child.returncode, err
    except subprocess.TimeoutExpired:
        os.killpg(child.pid, signal.SIGKILL)
        _, err = child.communicate()
        return None, err


def main(argv: list[str] | None = None) -> dict[str, object]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=90)
    parser.add_argument("--seed", type=int, default=7)
    a = parser.parse_args(argv)
    rng = random.Random(a.seed)
    statuses: collections.Counter[str] = collections.Counter()
    bad = 0
    with tempfile.TemporaryDirectory(prefix="pihim-ctrl-c-") as tmp:
        for i in range(a.runs):
            kind = rng.choice(["windows", "plan"])
            start_s = rng.uniform(0.3, 3.0)
            gaps_s = [rng.choice([0.0, 0.005, 0.02, 0.1, 0.3]) for _ in range(3)]
            out = Path(tmp) / kind
            shutil.rmtree(out, ignore_errors=True)
            status, err = one_run(kind, out, start_s, gaps_s)
            statuses["hung" if status is None else str(status)] += 1
            wrong = status not in (0, 130, -signal.SIGINT) or "Traceback" in err or "Exception ignored" in err
            bad += wrong
            print(f"{i:3d} {kind:8s} at {start_s:.2f} s, gaps {gaps_s}: status {status}"
                  + (f"  BAD: {err[-300:]!r}" if wrong else ""), flush=True)
    print(f"{a.runs} runs, seed {a.seed}: {bad} bad; statuses {dict(statuses)}")
    return {"runs": a.runs, "seed": a.seed, "bad": bad, "statuses": dict(statuses),
            "targets": [{"target": "no run hung, printed a traceback or ended otherwise", "passed": bad == 0}]}


if __name__ == "__main__":
    sys.exit(1 if main()["bad"] else 0)
