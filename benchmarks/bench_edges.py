"""Speed of the S0 / DoLP / AoP edge maps (:func:`pihim.inspection.edges.edge_maps`) on a full frame.

One rendered 2448x2048 frame of the demo's first pair (8E1 reflecting 7E1
at 13:00 on the embedded NSTTF-like field, the demo's noise and pose
errors), made into full-resolution float32 polar images by
:func:`pihim.camera.polar_image`, as ``pihim demo`` and ``pihim edges`` do.
Rows, each ``repeat`` timed calls after ``warmup`` untimed ones, one process:

``anchor: OpenCV Canny, three 8-bit images``
    What a user of OpenCV would run for the same three maps: S0 scaled to
    its 0.5-99.5 % range, DoLP times 255 and AoP times 255/180 as 8-bit
    images, each through ``cv2.Canny(image, 50, 150, L2gradient=True)``
    (OpenCV's own 3x3 Sobel; no NaN handling, no axial AoP, fixed
    thresholds).
``edge_maps canny`` / ``edge_maps sobel``
    pihim's maps: NaN-aware gradients, the axial AoP gradient weighted by
    DoLP, robust thresholds per map, the combined map.
``edge_maps canny, noise-weighted``
    The same with each gradient divided by its pixel's noise (the demo's and
    ``pihim edges``' default), the noise model's maps included.
``edge_maps canny, float64 images``
    The same on float64 copies of the images (computed in float64).
``EdgeMaps.summary()``
    The statistics ``pihim edges --json`` writes.

Run ``python benchmarks/run.py --only bench_edges`` or this file directly.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness

COUNTS = harness.Counts(repeat=10, warmup=2, quick_repeat=3, quick_warmup=1)
RESULTS_PATH = Path(__file__).resolve().parent / "results" / "edges.json"


def demo_frame() -> tuple[Any, dict[str, Any]]:
    """The full-resolution polar images of the demo's first pair (its seed), and its log's noise model."""
    from pihim.camera import polar_image
    from pihim.demo import DEMO_TIME, DemoSettings
    from pihim.field import nsttf_like_field
    from pihim.inspection.edges import sensor_noise
    from pihim.inspection.pipeline import sensor_settings
    from pihim.planning.pipeline import build_plan
    from pihim.render.simulate import PairPose, simulate_frame
    from pihim.sky.sun import NSTTF, parse_time

    s = DemoSettings()
    field = nsttf_like_field()
    aim = tuple(build_plan(field, parse_time(DEMO_TIME), NSTTF).aim_point)  # the demo's aim point
    sim = simulate_frame(field, DEMO_TIME, aim_point=aim, pose_request=PairPose("8E1", "7E1"),
                         canting_sigma_mrad=s.canting_sigma_mrad, gps_sigma_m=s.gps_sigma_m,
                         attitude_sigma_deg=s.attitude_sigma_deg, seed=s.seed)
    sensor = sensor_settings(sim.log)
    pim = polar_image(sim.raw, layout=sensor["layout"], analyser=sensor["analyser"], demosaic="full",
                      dark_level=sensor["dark_level"], bit_depth=sensor["bit_depth"])
    return pim, sensor_noise(sim.log)


def opencv_canny(s0: np.ndarray, dolp: np.ndarray, aop_deg: np.ndarray) -> list[np.ndarray]:
    """The anchor: ``cv2.Canny`` on the three images as 8-bit (NaN as 0)."""
    import cv2

    lo, hi = np.nanpercentile(s0, [0.5, 99.5])
    images = [np.clip((s0 - lo) * (255.0 / max(hi - lo, 1e-12)), 0, 255), np.nan_to_num(dolp) * 255.0,
              np.nan_to_num(aop_deg) * (255.0 / 180.0)]
    return [cv2.Canny(im.astype(np.uint8), 50, 150, L2gradient=True) for im in images]


def run_benchmark(repeat: int, warmup: int) -> dict[str, Any]:
    """Timings of the rows, JSON-ready."""
    from pihim.inspection.edges import edge_maps, noise_sigmas

    pim, noise_model = demo_frame()
    s0, dolp, aop = pim.s0, pim.dolp, pim.aop_deg
    s0_64, dolp_64, aop_64 = (np.asarray(a, np.float64) for a in (s0, dolp, aop))
    maps = edge_maps(s0, dolp, aop, "canny")
    rows: list[dict[str, Any]] = []

    def add(label: str, fn: Any) -> dict[str, Any]:
        row = {"label": label, **harness.measure(fn, repeat, warmup, trace=False)}
        rows.append(row)
        return row

    anchor = add("anchor: OpenCV Canny, three 8-bit images", lambda: opencv_canny(s0, dolp, aop))
    add("pihim edge_maps canny (float32 images)", lambda: edge_maps(s0, dolp, aop, "canny"))
    add("pihim edge_maps canny, noise-weighted (noise_sigmas included)",
        lambda: edge_maps(s0, dolp, aop, "canny", noise=noise_sigmas(s0, **noise_model)))
    add("pihim edge_maps sobel (float32 images)", lambda: edge_maps(s0, dolp, aop, "sobel"))
    add("pihim edge_maps canny, float64 images", lambda: edge_maps(s0_64, dolp_64, aop_64, "canny"))
    add("pihim EdgeMaps.summary()", maps.summary)
    for row in rows:
        row["vs_anchor"] = row["median_ms"] / anchor["median_ms"]
    return {
        "benchmark": "edges",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "settings": {"repeat": repeat, "warmup": warmup, "frame": f"{s0.shape[1]}x{s0.shape[0]}",
                     "invalid_pixels": int(np.count_nonzero(~np.isfinite(dolp)))},
        "machine": harness.machine_info(),
        "results": rows,
    }


def markdown_report(rep: dict[str, Any]) -> str:
    """The rows as a markdown table."""
    s = rep["settings"]
    lines = [f"Frame {s['frame']} ({s['invalid_pixels']} saturated pixels); {s['repeat']} timed calls after "
             f"{s['warmup']} warm-up.", "",
             "| Row | Median ms | p10 ms | p90 ms | CPU ms | x anchor | Other CPU % | Load |",
             "|---|--:|--:|--:|--:|--:|--:|--:|"]
    for r in rep["results"]:
        lines.append(f"| {r['label']} | {r['median_ms']:.0f} | {r['p10_ms']:.0f} | {r['p90_ms']:.0f} "
                     f"| {r['cpu_ms']:.0f} | {r['vs_anchor']:.2f} | {harness.other_pct(r['other_cpu'])} "
                     f"| {r['load_avg']:.1f} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None, *, repeat: int | None = None, quick: bool = False,
         warmup: int | None = None, json_path: Path | None = RESULTS_PATH, echo: bool = True) -> dict[str, Any]:
    """Run the benchmark, print the markdown table and write the JSON (``--repeat``, ``--warmup``, ``--quick``,
    ``--json PATH``)."""
    o = harness.options(argv, description=__doc__.split("\n\n")[0], counts=COUNTS, repeat=repeat, warmup=warmup,
                        quick=quick, json_path=json_path)
    report = run_benchmark(o.repeat, o.warmup)
    return harness.publish(report, markdown_report, o.json_path, echo=echo)


if __name__ == "__main__":
    main(sys.argv[1:])
