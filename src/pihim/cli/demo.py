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

from pihim._atomic import clean_stale_temporaries_tree
from pihim._resources import available_memory, require_memory
from pihim.cli._common import emit_json, output_dir, progress, stderr_console
from pihim.errors import PihimInputError

#: Peak bytes of a demo per frame pixel and its about constant part (plan, scene, libraries): the peak resident
#: size of ``pihim demo --pairs 1`` grows by 254-277 B per pixel plus 228-250 MB (612x512 to 2448x2048,
#: ``benchmarks/memory_estimates_quality.py``, 2026-11-26; the plan's facet captures raised the constant part
#: from 150-185 MB); with a 15-25 % margin. Pairs are processed one after the other.
DEMO_BYTES_PER_PIXEL = 300
DEMO_FIXED_BYTES = 280_000_000


def demo(
    out: Annotated[Path, typer.Option("--out", help="Output directory.")] = Path("pihim-demo"),
    pairs: Annotated[int, typer.Option(help="HUA-target pairs to render and inspect.")] = 2,
    seed: Annotated[int, typer.Option(help="Seed of the first pair's frame (canting, pose and sensor noise).")] = 2025,
    size: Annotated[str, typer.Option(help="Frame size WxH (even; a centre crop of the Triton's 2448x2048).")]
    = "2448x2048",
    json_out: Annotated[bool, typer.Option("--json", help="Print demo.json on stdout.")] = False,
    compile_helper: Annotated[bool, typer.Option(
        help="On a first run, compile the renderer's and the solver's kernels in a second process while planning.")]
    = True,
) -> int:
    """Plan, render, inspect and score a polarimetric inspection; write DIR/report.html."""
    from pihim.demo import DEMO_TIME, DemoSettings, run_demo

    try:
        w, h = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise PihimInputError(f"--size must look like 2448x2048, got {size!r}") from None
    if not all(64 <= v <= 2 * 2448 and v % 2 == 0 for v in (w, h)):
        raise PihimInputError(f"--size must be WxH with even sides in 64..4896, got {size}")
    need = w * h * DEMO_BYTES_PER_PIXEL + DEMO_FIXED_BYTES
    require_memory(need, f"pihim demo --size {w}x{h}")
    if compile_helper:  # the helper only where it fits beside the demo
        from pihim._warmup import HELPER_BYTES

        avail = available_memory()
        compile_helper = avail is None or avail >= need + HELPER_BYTES
    settings = DemoSettings(time=DEMO_TIME, pairs=pairs, seed=seed, width_px=w, height_px=h)
    # one line if DIR cannot be made; removes the temporaries killed runs left in it, and DIR itself if made here
    # and the run stops before writing anything
    with output_dir(out):
        clean_stale_temporaries_tree(out, depth=2)  # ... and in DIR/plan, DIR/pairs/NN_HUA-TARGET
        stderr_console().print(f"[bold]pihim demo[/bold]: planning the NSTTF-like field at {DEMO_TIME} ...")
        doc = run_demo(out, settings, steps=lambda items, desc: progress(items, desc, min_items=1),
                       compile_helper=compile_helper)
    sm, plan = doc["summary"], doc["plan"]
    from pihim.planning.scoring import images_text

    stderr_console().print(f"[bold]pihim demo[/bold]: {plan['passes']} passes, {images_text(plan)}; "
                           f"{plan['flights']} flights -> {out / 'plan'}", highlight=False)

    def f(v: float | None, spec: str = ".2f") -> str:
        return "-" if v is None else format(v, spec)

    for p in doc["pairs"]:
        if "score" not in p:
            stderr_console().print(f"  {p['hua']}/{p['target']}: not inspected: {p.get('error')}")
            continue
        s = p["score"]
        pose = s["pose"]
        stderr_console().print(
            f"  {p['hua']}/{p['target']}: pose {f(pose['prior_corner_error_px'], '.0f')} -> "
            f"{f(pose['refined_corner_error_px'])} px; {s['facets_used']} facets, canting RMS error "
            f"az {f(s['rms_az_mrad'])} / el {f(s['rms_el_mrad'])} mrad (paper grid "
            f"{f(s['grid_rms_az_mrad'])} / {f(s['grid_rms_el_mrad'])}); {p['seconds']['total']:.1f} s")
    stderr_console().print(f"  report: {out / 'report.html'}  ({sm['seconds']:.0f} s in all)")
    if json_out:
        emit_json(doc)
    return 0
