"""``pihim edges``: edge maps of the S0, DoLP and AoP images of one raw frame.

A thin layer over :func:`pihim.camera.polar_image` and
:func:`pihim.inspection.edges.edge_maps`; see ``docs/cli.md``. Only the
``log`` of the metadata file is read (camera size, mosaic layout, analyser,
dark level, bit depth): never its ``truth``.
"""

from __future__ import annotations

import json
import time as _time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from pihim._atomic import describe_os_error, write_group
from pihim.camera.frames import RAW_SUFFIXES, read_frame
from pihim.camera.model import CameraModel
from pihim.camera.pipeline import DEMOSAIC_METHODS, polar_image
from pihim.cli._common import check_out_dir, emit_json, output_dir, report_error, stderr_console
from pihim.errors import PihimInputError
from pihim.inspection._log import sensor_entries
from pihim.inspection.edges import EDGE_METHODS, IMAGE_TYPES, EdgeMaps, edge_maps, noise_sigmas, sensor_noise

SCHEMA_ID = "pihim.edges/1"


def output_paths(out_dir: Path, stem: str) -> dict[str, Path]:
    """Files written for a frame ``stem``: ``<T>_png``, ``<T>_tiff`` per image type and ``summary``."""
    paths: dict[str, Path] = {}
    for t in IMAGE_TYPES:
        paths[f"{t}_png"] = out_dir / f"{stem}.edges.{t}.png"
        paths[f"{t}_tiff"] = out_dir / f"{stem}.gradient.{t}.tiff"
    paths["summary"] = out_dir / f"{stem}.edges.json"
    return paths


def read_log(meta: Path) -> dict[str, Any]:
    """The ``log`` of a metadata file (``{"log": ...}`` as ``pihim simulate`` writes, or a bare log).

    ``truth`` is never looked at.
    """
    from pihim._inputs import load_json_file

    if not meta.exists():
        raise PihimInputError(f"{meta}: metadata file not found")
    doc = load_json_file(meta, "metadata file")
    if not isinstance(doc, Mapping):
        raise PihimInputError(f"{meta}: metadata must be a JSON object")
    log = doc.get("log", doc if "camera" in doc else None)
    if not isinstance(log, Mapping):
        raise PihimInputError(f"{meta}: no 'log' object in the metadata")
    if not isinstance(log.get("camera"), Mapping):
        raise PihimInputError(f"{meta}: the log has no 'camera' description")
    return dict(log)


def sensor_settings(log: Mapping[str, Any], meta: Path) -> dict[str, Any]:
    """Layout, analyser, dark level and bit depth from ``log["sensor"]`` (defaults if absent)."""
    from pihim.inspection.pipeline import sensor_settings as from_log

    try:
        settings = from_log(log)
        sensor, model = sensor_entries(log)
    except PihimInputError as exc:
        raise PihimInputError(f"{meta}: {exc}") from None
    layout_text = sensor.get("layout", model.get("layout"))
    return {**settings, "layout_source": "log" if layout_text is not None else "default"}


def _write_all(out_dir: Path, writers: dict[Path, Callable[[Path], None]]) -> None:
    """Create ``out_dir`` and write every file as one atomic group; on failure remove the folders just made."""
    with output_dir(out_dir):
        write_group(writers)


def _png_writer(mask: np.ndarray) -> Callable[[Path], None]:
    def write(path: Path) -> None:
        import cv2  # imported where used: the command's --help need not load OpenCV

        if not cv2.imwrite(str(path), np.where(mask, 255, 0).astype(np.uint8)):
            raise OSError(f"{path}: could not write PNG")
    return write


def _tiff_writer(image: np.ndarray) -> Callable[[Path], None]:
    def write(path: Path) -> None:
        import tifffile

        tifffile.imwrite(path, np.ascontiguousarray(image, dtype=np.float32))
    return write


def summary_record(frame: Path, meta: Path, maps: EdgeMaps, *, demosaic: str, camera: CameraModel,
                   settings: dict[str, Any], fraction_saturated: float, outputs: dict[str, Path],
                   seconds: float, noise_model: dict[str, Any] | None = None) -> dict[str, Any]:
    """The ``pihim.edges/1`` JSON summary."""
    rows, cols = maps.shape
    return {
        "schema": SCHEMA_ID,
        "frame": str(frame),
        "meta": str(meta),
        "method": maps.method,
        "demosaic": demosaic,
        "sensor": {
            "width_px": int(camera.width_px),
            "height_px": int(camera.height_px),
            "layout": str(settings["layout"]),
            "layout_source": settings["layout_source"],
            "analyser_source": "log" if settings["analyser"] is not None else "default",
            "dark_level_dn": settings["dark_level"],
            "bit_depth": settings["bit_depth"],
        },
        "width": int(cols),
        "height": int(rows),
        "fraction_saturated": float(fraction_saturated),
        "parameters": dict(maps.parameters),
        "noise_model": noise_model,
        "images": maps.summary(),
        "outputs": {k: str(v) for k, v in outputs.items()},
        "seconds": round(float(seconds), 4),
    }


def edges(
    frame: Annotated[Path, typer.Argument(help="Raw mosaic frame (.tiff, .png, or .raw sized by the log).", show_default=False)],
    out: Annotated[Path, typer.Option("--out", help="Output directory.")],
    meta: Annotated[Path | None, typer.Option("--meta", help="Metadata JSON (its 'log' only); default FRAME.json beside the frame.")] = None,
    method: Annotated[str, typer.Option(help="sobel (thresholded magnitude) or canny.")] = "sobel",
    demosaic: Annotated[str, typer.Option(help="superpixel (half resolution) or full.")] = "superpixel",
    noise_weighted: Annotated[bool, typer.Option("--noise-weighted/--no-noise-weighted", help="Divide each gradient by its pixel's noise (S0 and the log's sensor gain and read noise) before the thresholds.")] = True,
    json_out: Annotated[bool, typer.Option("--json", help="Print the JSON summary on stdout.")] = False,
) -> int:
    """Edge maps of the S0, DoLP and AoP images of a raw frame (PNG edges, float32 TIFF gradients, JSON summary).

    Everything is checked before anything is written; all outputs appear
    together or not at all.
    """
    t0 = _time.perf_counter()
    if method not in EDGE_METHODS:
        raise PihimInputError(f"unknown edge method {method!r}; choose one of {', '.join(EDGE_METHODS)}")
    if demosaic not in DEMOSAIC_METHODS:
        raise PihimInputError(f"unknown demosaic method {demosaic!r}; choose one of {', '.join(DEMOSAIC_METHODS)}")
    check_out_dir(out)
    if not frame.is_file():
        read_frame(frame)  # the reader's own one-line error (missing, a directory, ...)
    if meta is None:
        meta = frame.with_suffix(".json")
        if not meta.is_file():
            raise PihimInputError(f"{frame}: no metadata ({meta.name} not found beside it); give --meta FRAME.json")
    log = read_log(meta)
    try:
        camera = CameraModel.from_dict(log["camera"])
    except PihimInputError as exc:
        raise PihimInputError(f"{meta}: {exc}") from None
    settings = sensor_settings(log, meta)
    try:
        noise_model = sensor_noise(log)
    except PihimInputError as exc:
        raise PihimInputError(f"{meta}: {exc}") from None
    if frame.suffix.lower() in RAW_SUFFIXES:  # a headerless Lucid buffer: its size comes from the log
        raw = read_frame(frame, width=camera.width_px, height=camera.height_px)
    else:
        raw = read_frame(frame)
    h, w = raw.data.shape
    if (w, h) != (camera.width_px, camera.height_px):
        raise PihimInputError(
            f"{meta}: describes a {camera.width_px}x{camera.height_px} frame, but {frame} is {w}x{h}"
        )
    pol = polar_image(raw.data, layout=settings["layout"], analyser=settings["analyser"],
                      demosaic=demosaic, dark_level=settings["dark_level"],  # type: ignore[arg-type]
                      bit_depth=settings["bit_depth"] if settings["bit_depth"] is not None else raw.bit_depth)
    noise = noise_sigmas(pol.s0, **noise_model) if noise_weighted else None  # type: ignore[arg-type]
    maps = edge_maps(pol.s0, pol.dolp, pol.aop_deg, method, noise=noise)  # type: ignore[arg-type]
    paths = output_paths(out, frame.stem)
    writers: dict[Path, Callable[[Path], None]] = {}
    for t, m in maps.items():
        writers[paths[f"{t}_png"]] = _png_writer(m.edges)
        writers[paths[f"{t}_tiff"]] = _tiff_writer(m.gradient)
    sat = float(pol.saturated.mean()) if pol.saturated.size else 0.0
    record = summary_record(frame, meta, maps, demosaic=demosaic, camera=camera, settings=settings,
                            fraction_saturated=sat, outputs=paths, seconds=_time.perf_counter() - t0,
                            noise_model=noise_model if noise_weighted else None)
    text = json.dumps(record, indent=2, allow_nan=False) + "\n"
    writers[paths["summary"]] = lambda p: p.write_text(text, encoding="utf-8")
    try:
        _write_all(out, writers)
    except OSError as exc:
        report_error(f"{out}: cannot write the outputs: {describe_os_error(exc)}")
        return 1
    if json_out:
        emit_json(record)
    else:
        frac = ", ".join(f"{t} {st['edge_fraction']:.1%}" for t, st in record["images"].items())
        stderr_console().print(
            f"[bold]pihim edges[/bold]: {frame.name} ({method}, {demosaic}, {maps.shape[1]}x{maps.shape[0]}): "
            f"edge pixels {frac}; wrote {len(writers)} files to {out}", highlight=False, soft_wrap=True,
        )
    return 0
