"""``pihim polar``: raw mosaic frames to S0, DoLP and AoP images."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import tifffile
import typer

from pihim._atomic import atomic_path
from pihim.camera.frames import read_frame
from pihim.camera.layout import MosaicLayout
from pihim.camera.pipeline import DEMOSAIC_METHODS, PolarImage, polar_image
from pihim.cli._common import emit_json, parse_layout, progress, report_error, stderr_console, unique_stems
from pihim.errors import PihimInputError
from pihim.polarimetry.analyser import AnalyserMatrix
from pihim.visualize import aop_to_rgb, dolp_to_rgb, polar_figure_png, s0_to_gray, write_png

SCHEMA_ID = "pihim.polar-frame/1"


def write_float_tiff(path: Path, image: np.ndarray) -> Path:
    """Write a float32 TIFF atomically."""
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, np.ascontiguousarray(image, dtype=np.float32))
    return path


def write_polar_outputs(result: PolarImage, out_dir: Path, stem: str, *, png: bool) -> dict[str, str]:
    """Write ``<stem>.S0/DoLP/AoP.tiff`` (and PNG previews); return the written paths."""
    written = {
        "S0": write_float_tiff(out_dir / f"{stem}.S0.tiff", result.s0),
        "DoLP": write_float_tiff(out_dir / f"{stem}.DoLP.tiff", result.dolp),
        "AoP": write_float_tiff(out_dir / f"{stem}.AoP.tiff", result.aop_deg),
    }
    if png:
        written["S0_png"] = write_png(out_dir / f"{stem}.S0.png", s0_to_gray(result.s0))
        written["DoLP_png"] = write_png(out_dir / f"{stem}.DoLP.png", dolp_to_rgb(result.dolp))
        written["AoP_png"] = write_png(out_dir / f"{stem}.AoP.png", aop_to_rgb(result.aop_deg, result.dolp))
        written["figure_png"] = polar_figure_png(result.s0, result.dolp, result.aop_deg,
                                                 out_dir / f"{stem}.polar.png", title=f"{stem}: S0, DoLP and AoP")
    return {k: str(v) for k, v in written.items()}


def process_one(
    path: Path,
    out_dir: Path,
    *,
    layout: MosaicLayout,
    analyser: AnalyserMatrix | None,
    demosaic: str,
    dark_level: float,
    bit_depth: int | None,
    saturation_level: float | None,
    width: int | None,
    height: int | None,
    pixel_format: str | None,
    png: bool,
) -> dict[str, Any]:
    """Read, process and write one frame; returns its JSON record."""
    frame = read_frame(path, width=width, height=height, pixel_format=pixel_format)
    result = polar_image(
        frame.data,
        layout=layout,
        analyser=analyser,
        demosaic=demosaic,  # type: ignore[arg-type]
        dark_level=dark_level,
        bit_depth=bit_depth if bit_depth is not None else frame.bit_depth,
        saturation_level=saturation_level,
    )
    outputs = write_polar_outputs(result, out_dir, path.stem, png=png)
    return {
        "schema": SCHEMA_ID,
        "file": str(path),
        "status": "ok",
        "pixel_format": frame.pixel_format,
        "layout": str(layout),
        "calibrated": analyser is not None,
        **result.summary(),
        "outputs": outputs,
    }


def polar(
    frames: Annotated[list[Path], typer.Argument(help="Raw mosaic frames (.tiff, .png, .raw).", show_default=False)],
    out: Annotated[Path, typer.Option("--out", help="Output directory.")],
    layout: Annotated[str, typer.Option(help="Mosaic layout: a name (imx250mzr) or row-major angles, e.g. 90,45,135,0.")] = "imx250mzr",
    demosaic: Annotated[str, typer.Option(help="superpixel (half resolution) or full.")] = "superpixel",
    calibration: Annotated[Path | None, typer.Option(help="Analyser calibration JSON from 'pihim calibrate-polarizer'.")] = None,
    dark_level: Annotated[float, typer.Option(help="Dark level in raw units, subtracted first.")] = 0.0,
    bit_depth: Annotated[int | None, typer.Option(help="ADC bits (default: from the file format, else inferred).")] = None,
    saturation_level: Annotated[float | None, typer.Option(help="Raw level counted as saturated (default: full scale).")] = None,
    width: Annotated[int | None, typer.Option(help="Width in pixels (.raw only).")] = None,
    height: Annotated[int | None, typer.Option(help="Height in pixels (.raw only).")] = None,
    pixel_format: Annotated[str | None, typer.Option(help="Lucid pixel format (.raw only), e.g. PolarizeMono12p.")] = None,
    png: Annotated[bool, typer.Option("--png", help="Also write PNG previews.")] = False,
    json_out: Annotated[bool, typer.Option("--json", help="Print one JSON object per frame on stdout.")] = False,
) -> int:
    """Turn raw mosaic frames into S0, DoLP and AoP images (float32 TIFF, AoP in degrees).

    Frames that cannot be read are reported (one line each) and skipped; the
    others are still processed. Exit status 2 if any frame was bad input.
    """
    if demosaic not in DEMOSAIC_METHODS:
        raise PihimInputError(f"unknown demosaic method {demosaic!r}; choose one of {', '.join(DEMOSAIC_METHODS)}")
    lay = parse_layout(layout)
    analyser = AnalyserMatrix.load(calibration) if calibration is not None else None
    if dark_level is not None and not (math.isfinite(dark_level) and dark_level >= 0):
        raise PihimInputError(f"--dark-level must be a finite number of raw units >= 0, got {dark_level:g}")
    unique_stems(frames)
    if out.exists() and not out.is_dir():
        raise PihimInputError(f"{out}: exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    status = 0
    done: list[dict[str, Any]] = []
    for path in progress(frames, "polar"):
        try:
            record = process_one(
                path, out, layout=lay, analyser=analyser, demosaic=demosaic, dark_level=dark_level,
                bit_depth=bit_depth, saturation_level=saturation_level, width=width, height=height,
                pixel_format=pixel_format, png=png,
            )
        except PihimInputError as exc:
            report_error(str(exc))
            status = 2
            record = {"schema": SCHEMA_ID, "file": str(path), "status": "error", "error": str(exc)}
        except OSError as exc:
            report_error(f"{path}: {exc}")
            status = max(status, 1)
            record = {"schema": SCHEMA_ID, "file": str(path), "status": "error", "error": str(exc)}
        if json_out:
            emit_json(record)
        elif record["status"] == "ok":
            done.append(record)
    if done:
        med = [r["dolp"]["median"] for r in done if r["dolp"]["median"] is not None]
        stderr_console.print(
            f"pihim polar: {len(done)} of {len(frames)} frames -> {out}: <stem>.S0/.DoLP/.AoP.tiff (float32, AoP in "
            f"deg)" + (", PNG previews and <stem>.polar.png (captioned)" if png else "")
            + (f"; median DoLP {min(med):.3f}-{max(med):.3f}" if med else ""), highlight=False, soft_wrap=True)
    return status
