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
from typing import Annotated, Any

import numpy as np
import typer

from pihim.camera.frames import RAW_SUFFIXES, read_frame
from pihim.camera.model import CameraModel
from pihim.cli._common import check_out_dir, emit_json, load_field_option, report_error, stderr_console
from pihim.cli.edges import _write_all, read_log
from pihim.errors import PihimInputError
from pihim.inspection.canting import CantingResult
from pihim.inspection.pipeline import InspectionResult, combine_results, inspect_frame

SCHEMA_ID = "pihim.canting/1"

#: Short codes of the skip reasons (figure and ``reason_code``), matched on the reason text.
REASON_CODES: tuple[tuple[str, str, str], ...] = (
    ("not in view", "OUT", "facet not in view"),
    ("saturated", "SAT", "saturated"),
    ("DoLP", "DOLP", "DoLP too low"),
    ("no usable reflection", "NOREF", "no reflection of the target"),
    ("too few matched", "PTS", "too few edge points"),
    ("sub-pixel", "RMS", "residual too large"),
    ("does not look like", "SUPP", "reflection not the target's outline"),
)


def reason_code(reason: str | None) -> str | None:
    """A short code for a skip reason (``OTHER`` when none matches)."""
    if reason is None:
        return None
    for key, code, _ in REASON_CODES:
        if key in reason:
            return code
    return "OTHER"


def canting_record(result: CantingResult, inspections: list[tuple[Path, Path, InspectionResult]], *,
                   rows: int, cols: int, outputs: dict[str, Path], seconds: float) -> dict[str, Any]:
    """The ``pihim.canting/1`` document."""
    doc = result.to_dict()
    facets = []
    for f in doc["facets"]:  # type: ignore[union-attr]
        f = dict(f)
        f["reason_code"] = reason_code(f.get("reason"))
        facets.append(f)
    per_frame = []
    for frame, meta, r in inspections:
        c = r.canting
        per_frame.append({
            "frame": str(frame),
            "meta": str(meta),
            "hua": r.hua,
            "target": r.target,
            "image": r.image,
            "pose": r.pose,
            "facets_used": sum(1 for f in c.facets if f.used),
            "orientation_mrad": None if c.orientation_az_mrad is None else
            {"az": float(c.orientation_az_mrad), "el": float(c.orientation_el_mrad)},
            "seconds": r.seconds,
        })
    return {
        "schema": SCHEMA_ID,
        "hua": doc["hua"],
        "target": doc["target"],
        "frames": doc["frames"],
        "reference": doc["reference"],
        "orientation_mrad": doc["orientation_mrad"],
        "facet_grid": {"rows": int(rows), "cols": int(cols),
                       "numbering": "1..rows*cols row by row from the top left, seen from the front"},
        "facets_used": sum(1 for f in facets if f["used"]),
        "facets": facets,
        "notes": doc["notes"],
        "inputs": per_frame,
        "outputs": {k: str(v) for k, v in outputs.items()},
        "seconds": round(float(seconds), 3),
    }


def _png_writer(record: dict[str, Any]) -> Callable[[Path], None]:
    def write(path: Path) -> None:
        fig = canting_figure(record)
        try:
            fig.savefig(path, format="png", dpi=110)
        finally:
            import matplotlib.pyplot as plt

            plt.close(fig)
    return write


def canting_figure(record: dict[str, Any]) -> Any:
    """Facet maps of the azimuth and elevation deviations (the paper's Fig. 8 style)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm
    from matplotlib.patches import Rectangle

    rows, cols = record["facet_grid"]["rows"], record["facet_grid"]["cols"]
    facets = {f["id"]: f for f in record["facets"]}
    vals = [abs(f[k]) for f in facets.values() if f["used"] for k in ("az_mrad", "el_mrad")]
    vmax = max(1.0, float(np.ceil(max(vals) if vals else 1.0)))
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-vmax, vmax=vmax)
    cmap = plt.get_cmap("RdBu_r")
    fig, axes = plt.subplots(1, 2, figsize=(11.0, 6.0), constrained_layout=True)
    for ax, key, title in zip(axes, ("az", "el"), ("azimuth deviation", "elevation deviation"), strict=True):
        for i in range(rows * cols):
            r, c = divmod(i, cols)
            fid = i + 1
            f = facets.get(fid)
            x, y = c, rows - 1 - r
            if f is not None and f["used"]:
                v = f[f"{key}_mrad"]
                s = f[f"{key}_sigma_mrad"]
                ax.add_patch(Rectangle((x + 0.03, y + 0.03), 0.94, 0.94, facecolor=cmap(norm(v)), edgecolor="k", lw=0.8))
                dark = abs(norm(v) - 0.5) > 0.35
                ax.text(x + 0.5, y + 0.52, f"{v:+.2f}", ha="center", va="center", fontsize=12, weight="bold",
                        color="white" if dark else "black")
                if s is not None:
                    ax.text(x + 0.5, y + 0.25, f"±{s:.2g}", ha="center", va="center", fontsize=8,
                            color="white" if dark else "0.2")
            else:
                ax.add_patch(Rectangle((x + 0.03, y + 0.03), 0.94, 0.94, facecolor="0.88", edgecolor="0.5", lw=0.8,
                                       hatch="///"))
                code = reason_code(f["reason"]) if f is not None else "N/A"
                ax.text(x + 0.5, y + 0.45, code, ha="center", va="center", fontsize=9, color="0.25",
                        bbox={"facecolor": "0.88", "edgecolor": "none", "pad": 1.0})
            on_dark = f is not None and f["used"] and abs(norm(f[f"{key}_mrad"]) - 0.5) > 0.35
            ax.text(x + 0.08, y + 0.9, str(fid), ha="left", va="top", fontsize=8,
                    color="white" if on_dark else "0.1")
        ax.set_xlim(0, cols)
        ax.set_ylim(0, rows)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"{title} (mrad)", fontsize=12)
        sm = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
        fig.colorbar(sm, ax=ax, orientation="horizontal", fraction=0.05, pad=0.02)
    o = record["orientation_mrad"]
    orient = "none" if o is None else f"az {o['az']:+.2f}, el {o['el']:+.2f} mrad"
    fig.suptitle(f"Facet canting of {record['hua']} (target {record['target']}, {record['frames']} frame(s), "
                 f"{record['facets_used']} facets used), seen from the front\n"
                 f"relative to the best-fit heliostat orientation ({orient}); value ± standard error",
                 fontsize=11)
    items = [f"{code}: {text}" for _, code, text in REASON_CODES]
    half = (len(items) + 1) // 2
    fig.supxlabel("grey hatched = skipped:  " + ";  ".join(items[:half]) + "\n" + ";  ".join(items[half:]),
                  fontsize=8.5)
    return fig


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
    json_out: Annotated[bool, typer.Option("--json", help="Print canting.json on stdout.")] = False,
) -> int:
    """Facet canting deviations of a heliostat from the target's reflection (canting.json + canting.png).

    Everything is checked and computed before anything is written; both
    outputs appear together or not at all.
    """
    t0 = _time.perf_counter()
    if not frames:
        raise PihimInputError("give at least one frame")
    check_out_dir(out)
    for frame in frames:
        if not frame.is_file():
            read_frame(frame)  # the reader's own one-line error (missing, a directory, ...)
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
            r = inspect_frame(raw.data, log, fld, hua=hua, target=target)
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
        paths["png"]: _png_writer(record),
    }
    try:
        _write_all(out, writers)
    except OSError as exc:
        report_error(f"{out}: {exc}")
        return 1
    if json_out:
        emit_json(record)
    used = [f for f in record["facets"] if f["used"]]
    vals = ", ".join(f"{f['id']}: {f['az_mrad']:+.2f}/{f['el_mrad']:+.2f}" for f in used)
    stderr_console.print(
        f"[bold]pihim canting[/bold]: {record['hua']} (target {record['target']}, {len(frames)} frame(s)): "
        f"{len(used)} of {len(record['facets'])} facets used (az/el mrad relative to the best-fit orientation: "
        f"{vals or 'none'}); wrote {paths['json']} and {paths['png']} in {record['seconds']:.1f} s",
        highlight=False, soft_wrap=True,
    )
    return 0
