"""``pihim demo``: the main job on the embedded default, end to end, no data needed.

Plans a UFACET inspection of the embedded NSTTF-like field, renders the
frames of a few HUA-target pairs from the plan as the drone would record
them (canting, GPS/IMU and sensor noise), inspects them from the raw frame
and the log only (pose, per-facet canting) and scores every number against
the rendered truth: ``DIR/report.html`` and ``DIR/demo.json``
(:func:`pihim.demo.run_demo`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pihim.cli._common import emit_json, progress, stderr_console
from pihim.errors import PihimInputError


def demo(
    out: Annotated[Path, typer.Option("--out", help="Output directory.")] = Path("pihim-demo"),
    pairs: Annotated[int, typer.Option(help="HUA-target pairs to render and inspect.")] = 2,
    seed: Annotated[int, typer.Option(help="Seed of the first pair's frame (canting, pose and sensor noise).")] = 2025,
    size: Annotated[str, typer.Option(help="Frame size WxH (even; a centre crop of the Triton's 2448x2048).")]
    = "2448x2048",
    json_out: Annotated[bool, typer.Option("--json", help="Print demo.json on stdout.")] = False,
) -> int:
    """Plan, render, inspect and score a polarimetric inspection; write DIR/report.html."""
    from pihim.demo import DEMO_TIME, DemoSettings, run_demo

    try:
        w, h = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise PihimInputError(f"--size must look like 2448x2048, got {size!r}") from None
    settings = DemoSettings(time=DEMO_TIME, pairs=pairs, seed=seed, width_px=w, height_px=h)
    if out.exists() and not out.is_dir():
        raise PihimInputError(f"--out {out} exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PihimInputError(f"--out {out}: cannot create the directory ({exc.strerror or exc})") from None
    stderr_console.print(f"[bold]pihim demo[/bold]: planning the NSTTF-like field at {DEMO_TIME} ...")
    doc = run_demo(out, settings, steps=lambda items, desc: progress(items, desc, min_items=1))
    if json_out:
        emit_json(doc)
    else:
        sm, plan = doc["summary"], doc["plan"]
        stderr_console.print(
            f"[bold]pihim demo[/bold]: {plan['passes']} passes, {plan['usable_images']}/{plan['images']} captures "
            f"predicted usable, {plan['flights']} flights -> {out / 'plan'}")
        for p in doc["pairs"]:
            if "score" not in p:
                stderr_console.print(f"  {p['hua']}/{p['target']}: not inspected: {p.get('error')}")
                continue
            s = p["score"]
            pose = s["pose"]

            def f(v: float | None, spec: str = ".2f") -> str:
                return "-" if v is None else format(v, spec)

            stderr_console.print(
                f"  {p['hua']}/{p['target']}: pose {f(pose['prior_corner_error_px'], '.0f')} -> "
                f"{f(pose['refined_corner_error_px'])} px; {s['facets_used']} facets, canting RMS error "
                f"az {f(s['rms_az_mrad'])} / el {f(s['rms_el_mrad'])} mrad (paper grid "
                f"{f(s['grid_rms_az_mrad'])} / {f(s['grid_rms_el_mrad'])}); {p['seconds']['total']:.1f} s")
        stderr_console.print(f"  report: {out / 'report.html'}  ({sm['seconds']:.0f} s in all)")
    return 0
