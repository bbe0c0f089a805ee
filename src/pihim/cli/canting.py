"""``pihim canting``: facet canting of the heliostat under assessment from one or more raw frames.

A thin layer over :func:`pihim.inspection.pipeline.inspect_frame` and
:func:`pihim.inspection.pipeline.combine_results`; see ``docs/cli.md``. Only
the ``log`` of each metadata file is read, never its ``truth``.
"""

from __future__ import annotations

import json
import time as _time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from pihim._atomic import describe_os_error
from pihim._inputs import check_distinct
from pihim.camera.frames import RAW_SUFFIXES, read_frame
from pihim.camera.model import CameraModel
from pihim.cli._common import check_out_dir, emit_json, load_field_option, report_error, stderr_console
from pihim.cli.edges import _write_all, read_log
from pihim.errors import PihimInputError

if TYPE_CHECKING:  # the inspection imports the renderer's compiled kernels (numba): loaded when the command runs
    from pihim.inspection.pipeline import InspectionResult

def _meta_for(frames: list[Path], meta: list[Path] | None) -> list[Path]:
    if not meta:
        out = []
        for frame in frames:
            m = frame.with_suffix(".json")
            if not m.is_file():
                raise PihimInputError(f"{frame}: no metadata ({m.name} not found beside it); give --meta FRAME.json")
            out.append(m)
        return out
    if len(meta) != len(frames):
        raise PihimInputError(f"{len(meta)} --meta files for {len(frames)} frames: give one per frame, in order")
    return list(meta)


def canting(
    frames: Annotated[list[Path], typer.Argument(help="Raw mosaic frames (.tiff, .png, or .raw sized by the log) of the same HUA.", show_default=False)],
    out: Annotated[Path, typer.Option("--out", help="Output directory (canting.json, canting.png).")],
    meta: Annotated[list[Path] | None, typer.Option("--meta", help="Metadata JSON (its 'log' only), once per frame in order; default FRAME.json beside each frame.")] = None,
    field: Annotated[str, typer.Option("--field", help="nsttf-like or a heliostat CSV.")] = "nsttf-like",
    facets: Annotated[Path | None, typer.Option("--facets", help="Facet CSV for --field CSV.")] = None,
    hua: Annotated[str | None, typer.Option("--hua", help="Heliostat under assessment (default: the log's 'hua').")] = None,
    target: Annotated[str | None, typer.Option("--target", help="Target heliostat reflected in it (default: the log's 'target').")] = None,
    correct_target: Annotated[bool, typer.Option("--correct-target", help="Also correct the target's logged drive angles, with the HUA's, from the target's reflection (about 2 s more CPU per frame; for logs off by 0.1 deg or more).")] = False,
    json_out: Annotated[bool, typer.Option("--json", help="Print canting.json on stdout.")] = False,
) -> int:
    """Facet canting deviations of a heliostat from the target's reflection (canting.json + canting.png).

    Everything is checked and computed before anything is written; both
    outputs appear together or not at all.
    """
    from pihim.inspection.canting_output import canting_png_writer, canting_record
    from pihim.inspection.pipeline import combine_results, inspect_frame

    t0 = _time.perf_counter()
    if not frames:
        raise PihimInputError("give at least one frame")
    check_out_dir(out)
    for frame in frames:
        if not frame.is_file():
            read_frame(frame)  # the reader's own one-line error (missing, a directory, ...)
    check_distinct(frames, "frame")  # a frame given twice would count twice in the combined estimate
    metas = _meta_for(frames, meta)
    fld = load_field_option(field, facets)
    logs = []
    raws = []
    for frame, m in zip(frames, metas, strict=True):
        log = read_log(m)
        try:
            camera = CameraModel.from_dict(log["camera"])
        except PihimInputError as exc:
            raise PihimInputError(f"{m}: {exc}") from None
        if frame.suffix.lower() in RAW_SUFFIXES:
            raw = read_frame(frame, width=camera.width_px, height=camera.height_px)
        else:
            raw = read_frame(frame)
        h, w = raw.data.shape
        if (w, h) != (camera.width_px, camera.height_px):
            raise PihimInputError(f"{m}: describes a {camera.width_px}x{camera.height_px} frame, but {frame} is {w}x{h}")
        logs.append(log)
        raws.append(raw)
    results: list[tuple[Path, Path, InspectionResult]] = []
    for frame, m, log, raw in zip(frames, metas, logs, raws, strict=True):
        sensor = log.get("sensor") if isinstance(log.get("sensor"), dict) else {}
        model = sensor.get("model") if isinstance(sensor.get("model"), dict) else {}
        if model.get("bit_depth") is None and raw.bit_depth:  # the reader's bit depth when the log has none
            log = {**log, "sensor": {**sensor, "model": {**model, "bit_depth": int(raw.bit_depth)}}}
        try:
            r = inspect_frame(raw.data, log, fld, hua=hua, target=target, target_orientation=correct_target)
        except PihimInputError as exc:
            raise PihimInputError(f"{frame}: {exc}") from None
        results.append((frame, m, r))
    combined = combine_results([r for _, _, r in results])
    spec = fld.spec
    paths = {"json": out / "canting.json", "png": out / "canting.png"}
    record = canting_record(combined, results, rows=spec.rows, cols=spec.cols, outputs=paths,
                            seconds=_time.perf_counter() - t0)
    text = json.dumps(record, indent=2, allow_nan=False) + "\n"
    writers: dict[Path, Callable[[Path], None]] = {
        paths["json"]: lambda p: p.write_text(text, encoding="utf-8"),
        paths["png"]: canting_png_writer(record),
    }
    try:
        _write_all(out, writers)
    except OSError as exc:
        report_error(f"{out}: cannot write the outputs: {describe_os_error(exc)}")
        return 1
    if json_out:
        emit_json(record)
    used = [f for f in record["facets"] if f["used"]]
    vals = ", ".join(f"{f['id']}: {f['az_mrad']:+.2f}/{f['el_mrad']:+.2f}" for f in used)
    stderr_console().print(
        f"[bold]pihim canting[/bold]: {record['hua']} (target {record['target']}, {len(frames)} frame(s)): "
        f"{len(used)} of {len(record['facets'])} facets used (az/el mrad relative to the best-fit orientation: "
        f"{vals or 'none'}); wrote {paths['json']} and {paths['png']} in {record['seconds']:.1f} s",
        highlight=False, soft_wrap=True,
    )
    return 0
