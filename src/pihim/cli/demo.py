"""``pihim demo``: the main job on the embedded default, no data needed.

1. Plans a polarimetric inspection of the embedded NSTTF-like field for a
   morning in May (UFACET passes scored for contrast, flights, all mission
   export formats) into ``DIR/plan``.
2. Synthesises a Triton-size raw frame of a heliostat-field-like scene with
   known ground truth (12-bit, shot and read noise), writes it as a TIFF,
   processes it with ``pihim polar`` along both demosaicing routes, and
   reports how close the recovered DoLP and AoP are to the truth.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import tifffile
import typer

from pihim._atomic import atomic_path, write_json_atomic
from pihim.camera.layout import IMX250MZR
from pihim.cli._common import emit_json, stderr_console
from pihim.cli.polar import process_one
from pihim.errors import PihimInputError
from pihim.field import nsttf_like_field
from pihim.planning.export import export_all
from pihim.planning.pipeline import build_plan
from pihim.polarimetry import aop_deg, aop_difference_deg, dolp
from pihim.render.mosaic import mosaic_from_stokes
from pihim.render.scenes import edge_scene
from pihim.sky.sun import NSTTF, parse_time

SCHEMA_ID = "pihim.demo/1"
TRITON_SHAPE = (2048, 2448)  # rows, columns
DEMO_TIME = "2021-05-13T09:30:00-06:00"  # inside the paper's morning window at NSTTF


def _accuracy(recovered_dolp: np.ndarray, recovered_aop: np.ndarray, truth: tuple[np.ndarray, ...]) -> dict[str, float]:
    """DoLP mean absolute error, AoP RMSE and median error (axial, where true DoLP > 0.1).

    The RMSE is dominated by pixels on edges (for the super-pixel route, the
    2x2 cells that straddle an edge); the median shows the error elsewhere.
    """
    t_dolp = dolp(*truth)
    t_aop = aop_deg(truth[1], truth[2])
    ok = np.isfinite(recovered_dolp) & np.isfinite(t_dolp)
    sel = ok & (t_dolp > 0.1)
    err = aop_difference_deg(recovered_aop[sel], t_aop[sel])
    return {
        "dolp_mae": float(np.mean(np.abs(recovered_dolp[ok] - t_dolp[ok]))),
        "aop_rmse_deg": float(np.sqrt(np.mean(err**2))),
        "aop_median_error_deg": float(np.median(err)),
    }


def _block_mean(x: np.ndarray) -> np.ndarray:
    h, w = x.shape
    return x.reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))


def demo(
    out: Annotated[Path, typer.Option("--out", help="Output directory.")] = Path("pihim-demo"),
    seed: Annotated[int, typer.Option(help="Scene and noise seed.")] = 2025,
    size: Annotated[str, typer.Option(help="Frame size WxH (even).")] = "2448x2048",
    png: Annotated[bool, typer.Option("--png/--no-png", help="Write PNG previews.")] = True,
    json_out: Annotated[bool, typer.Option("--json", help="Print the summary as JSON on stdout.")] = False,
) -> int:
    """Synthesise a polarimetric frame with known truth and process it end to end."""
    try:
        w, h = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise PihimInputError(f"--size must look like 2448x2048, got {size!r}") from None
    if w < 16 or h < 16 or w % 2 or h % 2:
        raise PihimInputError(f"--size must be even and at least 16x16, got {size}")
    out.mkdir(parents=True, exist_ok=True)
    t_plan = time.perf_counter()
    field = nsttf_like_field()
    plan = build_plan(field, parse_time(DEMO_TIME), NSTTF)
    plan_files = export_all(plan, out / "plan", field=field)
    plan_record = {"time": DEMO_TIME, "seconds_with_export": round(time.perf_counter() - t_plan, 3),
                   **{k: plan.summary[k] for k in ("passes", "feasible_passes", "waypoints", "images",
                                                   "usable_images", "coverage", "flights")},
                   "files": {k: str(v) for k, v in plan_files.items()}}
    t0 = time.perf_counter()
    truth = edge_scene((h, w), rng=seed)
    raw = mosaic_from_stokes(*truth, IMX250MZR, bit_depth=12, read_noise_dn=2.0, electrons_per_dn=4.0, rng=seed)
    raw_path = out / "demo_raw.tiff"
    with atomic_path(raw_path) as tmp:
        tifffile.imwrite(tmp, raw)
    t_render = time.perf_counter() - t0
    summary: dict[str, Any] = {
        "schema": SCHEMA_ID,
        "raw_frame": str(raw_path),
        "size": {"width": w, "height": h},
        "seed": seed,
        "render_s": round(t_render, 3),
        "plan": plan_record,
        "routes": {},
    }
    truth_sp = tuple(_block_mean(x) for x in truth)
    for route in ("superpixel", "full"):
        sub = out / route
        t1 = time.perf_counter()
        record = process_one(
            raw_path, sub, layout=IMX250MZR, analyser=None, demosaic=route, dark_level=0.0,
            bit_depth=None, saturation_level=None, width=None, height=None, pixel_format=None, png=png,
        )
        elapsed = time.perf_counter() - t1
        rec_dolp = tifffile.imread(record["outputs"]["DoLP"])
        rec_aop = tifffile.imread(record["outputs"]["AoP"])
        acc = _accuracy(rec_dolp, rec_aop, truth_sp if route == "superpixel" else truth)
        summary["routes"][route] = {"seconds_with_io": round(elapsed, 3), **acc, "record": record}
    write_json_atomic(out / "demo.json", summary)
    if json_out:
        emit_json(summary)
    else:
        cov = plan_record["coverage"]
        stderr_console.print(
            f"[bold]pihim demo[/bold]: NSTTF-like field at {DEMO_TIME}: {plan_record['passes']} passes, "
            f"{plan_record['usable_images']}/{plan_record['images']} images predicted usable "
            f"({100 * cov['either']:.0f} % of heliostats), {plan_record['flights']} flights -> {out / 'plan'}"
        )
        stderr_console.print(f"[bold]pihim demo[/bold]: synthetic {w}x{h} 12-bit frame -> {raw_path}")
        for route, r in summary["routes"].items():
            stderr_console.print(
                f"  {route:>10}: DoLP MAE {r['dolp_mae']:.4f}, AoP RMSE {r['aop_rmse_deg']:.2f} deg, "
                f"median {r['aop_median_error_deg']:.2f} deg (true DoLP > 0.1); "
                f"{r['seconds_with_io']:.2f} s incl. I/O -> {out / route}"
            )
        stderr_console.print(f"  summary: {out / 'demo.json'}")
    return 0
