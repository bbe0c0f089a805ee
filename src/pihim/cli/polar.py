"""``pihim polar``: raw mosaic frames to S0, DoLP and AoP images.

Batch behaviour (``docs/cli.md``):

* every option is checked before the first frame is read;
* a frame that fails -- unreadable, bad data, too large for the memory left,
  outputs that would overwrite an input, a write error -- is reported on one
  stderr line and the batch goes on; the exit status says that some failed;
* a frame's images are written under temporary names and renamed together,
  then its record ``<name>.polar.json`` is written last: a frame with a
  record is complete; a run that is killed leaves at worst a frame without
  a record (redone on the next run) and temporaries that the next run removes;
* a rerun skips the frames whose record matches the input file (size and
  modification time), the options and the outputs on disk (``--overwrite``
  redoes them).

Frames go through a three-stage pipeline: a reader thread reads the next
frames ahead, the main thread computes (the numba kernels release the GIL
and use every core), and a writer thread writes each frame's files and
then its record; records are reported in input order. At most
:data:`READ_AHEAD` frames are read ahead and :data:`WRITES_IN_FLIGHT`
frames wait to be written, and the output arrays are recycled from frame to
frame (``polar_image(out=...)``), so memory stays bounded. An interrupted
run (Ctrl-C, SIGTERM) lets the writer finish or abandon the file it is on,
removes that frame's temporaries and stops.
"""

from __future__ import annotations

import contextlib
import errno
import gc
import hashlib
import json
import math
import os
import queue
import re
import shutil
import sys
import threading
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from pihim._atomic import atomic_group, missing_dirs, remove_empty_dirs, write_json_atomic
from pihim._resources import format_bytes, memory_error_message, require_memory
from pihim.camera.frames import MAX_RAW_VALUE, normalize_pixel_format, read_frame
from pihim.camera.layout import MosaicLayout
from pihim.camera.pipeline import DEMOSAIC_METHODS, PolarImage, polar_image
from pihim.cli._common import emit_json, make_out_dir, parse_layout, progress, report_error, stderr_console
from pihim.errors import PihimInputError
from pihim.polarimetry.analyser import AnalyserMatrix
from pihim.visualize import aop_to_rgb, dolp_to_rgb, polar_figure_png, s0_range, s0_to_gray, write_png

SCHEMA_ID = "pihim.polar-frame/1"
#: Suffix of the per-frame record, written after the frame's images: its completion mark.
RECORD_SUFFIX = ".polar.json"
#: ``schema`` of the FRAME.json that ``pihim simulate`` writes beside its truth images (FRAME.S0.tiff, ...).
SIMULATED_FRAME_SCHEMA = "pihim.simulated-frame/1"
#: Peak bytes per output pixel of a batch run, raw frames read ahead and outputs waiting to be written included:
#: the peak resident size (``VmHWM``: numpy's, OpenCV's, libtiff's and matplotlib's C allocations counted) of
#: ``pihim polar`` over six 1500x1500 frames grew by 69 B per output pixel with full demosaicing, and by 124 B
#: with the PNG previews and the captioned figure (``tests/cli/test_cli_reliability.py`` holds the first
#: figure; ``benchmarks/memory_estimates_quality.py`` measures single frames); with a 15-20 % margin.
BYTES_PER_OUTPUT_PIXEL = 80
BYTES_PER_OUTPUT_PIXEL_PNG = 150
#: With --png, the captioned figure's about constant part (it is decimated to <= 900 px a side).
FIGURE_BYTES = 8_000_000

_IMAGE_KEYS = ("S0", "DoLP", "AoP")
#: Frames read ahead of the one being computed.
READ_AHEAD = 2
#: Computed frames that may wait for (or be in) the writers before the next frame is computed.
WRITES_IN_FLIGHT = 2
#: Writer threads: each writes whole frames (their files atomically as a group); frames are reported in input
#: order whatever order they finish in.
WRITERS = 2


@dataclass(frozen=True)
class PolarOptions:
    """Everything that determines a frame's outputs besides the frame itself."""

    layout: MosaicLayout
    analyser: AnalyserMatrix | None
    demosaic: str
    dark_level: float
    bit_depth: int | None
    saturation_level: float | None
    width: int | None
    height: int | None
    pixel_format: str | None
    png: bool
    png_level: int = 0  # deflate level of the bare previews: their bytes, not their pixels (not in the fingerprint)

    def fingerprint(self) -> dict[str, Any]:
        """JSON-ready summary compared on resume (a frame made with other options is redone)."""
        return {
            "layout": str(self.layout),
            "analyser_matrix": None if self.analyser is None else self.analyser.matrix.tolist(),
            "demosaic": self.demosaic,
            "dark_level": self.dark_level,
            "bit_depth": self.bit_depth,
            "saturation_level": self.saturation_level,
            "width": self.width,
            "height": self.height,
            "pixel_format": self.pixel_format,
            "png": self.png,
        }


def write_float_tiff(path: Path, image: np.ndarray) -> Path:
    """Write a float32 TIFF (to ``path`` as given: pass a temporary name for atomicity).

    By :func:`pihim._tiff.write_float32_tiff`: one strip after a one-block
    header, written past the page cache where the file system allows (the
    kernel's copy into the cache cost more CPU than computing the images).
    """
    from pihim._tiff import write_float32_tiff

    return write_float32_tiff(path, image)


def output_paths(out_dir: Path, name: str, *, png: bool) -> dict[str, Path]:
    """The files of one frame: ``S0``, ``DoLP``, ``AoP`` TIFFs (with ``png``: the ``*_png`` previews and the
    captioned ``figure_png``, ``<name>.polar.png``); not the record."""
    paths = {k: out_dir / f"{name}.{k}.tiff" for k in _IMAGE_KEYS}
    if png:
        paths.update({f"{k}_png": out_dir / f"{name}.{k}.png" for k in _IMAGE_KEYS})
        paths["figure_png"] = out_dir / f"{name}.polar.png"
    return paths


@dataclass(frozen=True)
class Previews:
    """A frame's PNG previews (:func:`make_previews`)."""

    gray: np.ndarray
    dolp_rgb: np.ndarray
    aop_rgb: np.ndarray
    s0_range: tuple[float, float]


def make_previews(result: PolarImage, out: Previews | None = None, *,
                  s0_bounds: tuple[float, float] | None = None) -> Previews:
    """The three bare previews of a frame and the S0 range of its grey stretch.

    ``out``: previews of an earlier frame of the same size whose arrays are
    written over (no fresh pages to fault in: about 20 ms of CPU per
    super-pixel frame here). ``s0_bounds``: the frame's :func:`s0_range`
    when already known.
    """
    bounds = s0_bounds if s0_bounds is not None else (s0_range(result.s0) or (0.0, 0.0))
    arrays = (None, None, None) if out is None else (out.gray, out.dolp_rgb, out.aop_rgb)
    return Previews(s0_to_gray(result.s0, value_range=bounds, out=arrays[0]),
                    dolp_to_rgb(result.dolp, out=arrays[1]),
                    aop_to_rgb(result.aop_deg, result.dolp, out=arrays[2]), bounds)


class Cancelled(Exception):
    """The run is stopping (Ctrl-C, SIGTERM): the frame being written is abandoned and its temporaries removed."""


def write_polar_outputs(
    result: PolarImage, out_dir: Path, stem: str, *, png: bool, previews: Previews | None = None,
    cancel: threading.Event | None = None, png_level: int | None = None,
) -> dict[str, str]:
    """Write ``<stem>.S0/DoLP/AoP.tiff`` (and the PNG previews and figure) together; return the written paths.

    All files are written under temporary names first and renamed only when
    every one is complete; on failure none is left. ``previews`` (else made
    here) are the frame's :func:`make_previews`; when ``cancel`` is set
    before the group is complete, :class:`Cancelled` is raised and nothing is
    left. ``png_level``: deflate level of the three bare previews (0 stores
    them; default :data:`pihim._png.DEFAULT_LEVEL`); the figure is always
    compressed.
    """
    paths = output_paths(out_dir, stem, png=png)
    images = {"S0": result.s0, "DoLP": result.dolp, "AoP": result.aop_deg}
    keys = list(paths)

    def go_on() -> None:
        if cancel is not None and cancel.is_set():
            raise Cancelled(stem)

    with atomic_group([paths[k] for k in keys]) as tmps:
        tmp = dict(zip(keys, tmps, strict=True))
        for k in _IMAGE_KEYS:
            go_on()
            write_float_tiff(tmp[k], images[k])
        if png:
            pv = previews if previews is not None else make_previews(result)
            for key, image in (("S0_png", pv.gray), ("DoLP_png", pv.dolp_rgb), ("AoP_png", pv.aop_rgb)):
                go_on()
                write_png(tmp[key], image, atomic=False, level=png_level)
            go_on()
            polar_figure_png(result.s0, result.dolp, result.aop_deg, tmp["figure_png"],
                             title=f"{stem}: S0, DoLP and AoP", atomic=False,
                             previews=(pv.gray, pv.dolp_rgb, pv.aop_rgb, pv.s0_range))
        go_on()
    return {k: str(v) for k, v in paths.items()}


# -- batch planning ------------------------------------------------------------------------


def output_names(frames: Sequence[Path]) -> dict[Path, str]:
    """Output base name of each frame: its stem, or ``<stem>-<hash>`` when several frames share a stem.

    Stems are compared case-insensitively (outputs must not collide on
    case-insensitive file systems); the hash (8 hex digits of the absolute
    path) keeps the names distinct and the same from one run to the next.
    """
    groups: dict[str, list[Path]] = {}
    for p in frames:
        groups.setdefault(p.stem.casefold(), []).append(p)
    names: dict[Path, str] = {}
    for p in frames:
        if len(groups[p.stem.casefold()]) == 1:
            names[p] = p.stem
        else:
            digest = hashlib.sha1(os.fsencode(os.path.abspath(p))).hexdigest()[:8]
            names[p] = f"{p.stem}-{digest}"
    return names


def _file_id(path: Path) -> tuple[int, int] | None:
    """(device, inode) of an existing file, else None."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


def check_not_an_input(path: Path, outputs: Sequence[Path], inputs: dict[tuple[int, int], Path]) -> None:
    """Refuse (for this frame) outputs that are one of the batch's input files."""
    for o in outputs:
        fid = _file_id(o)
        if fid is not None and fid in inputs:
            raise PihimInputError(f"{path}: its output {o} would overwrite the input {inputs[fid]}; choose another --out")


def check_not_simulated_truth(path: Path, outputs: Sequence[Path], frame_json: Path) -> None:
    """Refuse (for this frame) outputs that are the rendered truth images ``pihim simulate`` wrote beside
    ``frame_json`` (``FRAME.S0.tiff``, ...: the same names): ``--out`` the folder of simulated frames would replace
    the truth with measurements."""
    existing = [o for o in outputs if o.is_file()]
    if not existing or not frame_json.is_file():
        return
    try:
        schema = json.loads(frame_json.read_text(encoding="utf-8")).get("schema")
    except (OSError, ValueError, AttributeError):
        return
    if schema == SIMULATED_FRAME_SCHEMA:
        raise PihimInputError(f"{path}: its output {existing[0]} is the rendered truth of {frame_json} "
                              f"(pihim simulate); choose another --out")


def estimate_frame_bytes(height: int, width: int, *, demosaic: str, png: bool) -> int:
    """Peak bytes of processing and writing one ``width`` x ``height`` mosaic (raw frame excluded)."""
    n_out = height * width if demosaic == "full" else (height // 2) * (width // 2)
    return n_out * (BYTES_PER_OUTPUT_PIXEL_PNG if png else BYTES_PER_OUTPUT_PIXEL) + (FIGURE_BYTES if png else 0)


# -- resume ------------------------------------------------------------------------------------


def input_fingerprint(path: Path) -> dict[str, Any]:
    """Absolute path, size and modification time of an input file."""
    st = os.stat(path)
    return {"path": os.path.abspath(path), "bytes": st.st_size, "mtime_ns": st.st_mtime_ns}


def _tiff_matches(path: Path, height: int, width: int) -> bool:
    """Whether ``path`` is a single float32 TIFF page of the given shape (header only)."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            return len(tif.pages) == 1 and tuple(page.shape) == (height, width) and page.dtype == np.float32
    except Exception:  # noqa: BLE001 - any unreadable file is simply not complete
        return False


def completed_record(record_path: Path, path: Path, options: dict[str, Any]) -> dict[str, Any] | None:
    """The stored record of a frame done earlier with the same input and options, if complete; else None."""
    try:
        with open(record_path, encoding="utf-8") as f:
            rec = json.load(f)
        if not (isinstance(rec, dict) and rec.get("status") == "ok" and rec.get("schema") == SCHEMA_ID):
            return None
        if rec.get("input") != input_fingerprint(path) or rec.get("options") != options:
            return None
        sizes, outputs = rec.get("output_bytes"), rec.get("outputs")
        if not isinstance(sizes, dict) or not isinstance(outputs, dict) or set(sizes) != set(outputs):
            return None
        if set(outputs) != set(output_paths(record_path.parent, "", png=bool(options.get("png")))):
            return None  # made by a version that wrote other files (e.g. no captioned figure yet)
        for key, out in outputs.items():
            here = record_path.parent / Path(out).name  # the record sits beside the outputs
            if os.path.getsize(here) != sizes[key]:
                return None
            if key in _IMAGE_KEYS and not _tiff_matches(here, rec["height"], rec["width"]):
                return None
    except (OSError, ValueError, TypeError, KeyError, RecursionError):
        return None
    return rec


# -- one frame -------------------------------------------------------------------------------------


def _frame_warnings(data: np.ndarray, summary: dict[str, Any], dark_level: float) -> list[str]:
    """Warnings for a frame whose outputs carry no usable DoLP or AoP (``summary``: its statistics)."""
    if summary["fraction_valid"] > 0:
        return []
    vmax = float(data.max()) if data.size else 0.0
    if dark_level >= vmax:
        return [f"no valid pixel: --dark-level {dark_level:g} is at or above every raw value (max {vmax:g})"]
    return ["no valid pixel: every super-pixel is saturated or dark (DoLP and AoP are all NaN)"]


def _write_error(path: Path, exc: OSError, out_dir: Path) -> str:
    """One line for an operating-system error while writing a frame's outputs."""
    text = str(exc)
    if exc.errno == errno.ENOSPC or re.search(r"\d+ requested and \d+ written", text):
        try:
            free = f", {format_bytes(shutil.disk_usage(out_dir).free)} free"
        except OSError:
            free = ""
        return f"{path}: cannot write its outputs in {out_dir}: no space left on the device{free}"
    return f"{path}: cannot write its outputs in {out_dir}: {exc.strerror or ' '.join(text.split())}"


@dataclass
class Computed:
    """A frame between computing and writing."""

    path: Path
    name: str
    pixel_format: str | None  # of the frame read (the raw data itself is not kept)
    source: dict[str, Any]
    result: PolarImage
    summary: dict[str, Any]
    warnings: list[str]
    s0_bounds: tuple[float, float] | None  # with --png: the S0 range of the grey previews
    recycled: Previews | None = None  # an earlier frame's previews, whose arrays this frame's are made in
    previews: Previews | None = None  # made by the writer


def read_one(path: Path, options: PolarOptions) -> tuple[Any, dict[str, Any]]:
    """Read one frame and check that it fits in memory; returns the frame and the input's fingerprint."""
    opts = options
    frame = read_frame(path, width=opts.width, height=opts.height, pixel_format=opts.pixel_format)
    h, w = frame.data.shape
    require_memory(estimate_frame_bytes(h, w, demosaic=opts.demosaic, png=opts.png),
                   f"{path}: a {w}x{h} frame with --demosaic {opts.demosaic}")
    return frame, input_fingerprint(path)


def compute_one(path: Path, name: str, frame: Any, source: dict[str, Any], options: PolarOptions,
                out: PolarImage | None = None, previews_out: Previews | None = None) -> Computed:
    """Stokes images, statistics, warnings and (with ``--png``) the previews' S0 range of a frame read by
    :func:`read_one`.

    ``out`` and ``previews_out``: an earlier frame's arrays of the same size to write over (the previews are
    made by the writer, :func:`write_one`: their compiled kernels run serially, on the writer threads).
    """
    opts = options
    try:
        result = polar_image(
            frame.data,
            layout=opts.layout,
            analyser=opts.analyser,
            demosaic=opts.demosaic,  # type: ignore[arg-type]
            dark_level=opts.dark_level,
            bit_depth=opts.bit_depth if opts.bit_depth is not None else frame.bit_depth,
            saturation_level=opts.saturation_level,
            **({} if out is None else {"out": out}),
        )
    except PihimInputError as exc:
        raise PihimInputError(f"{path}: {exc}") from None
    summary = result.summary()
    warnings = _frame_warnings(frame.data, summary, opts.dark_level)
    s0_bounds = (s0_range(result.s0) or (0.0, 0.0)) if opts.png else None  # parallel: on the computing thread
    return Computed(path, name, frame.pixel_format, source, result, summary, warnings, s0_bounds, previews_out)


def write_one(done: Computed, out_dir: Path, options: PolarOptions, cancel: threading.Event | None = None
              ) -> dict[str, Any]:
    """Write a computed frame's outputs, then its record (the completion mark); returns the record."""
    opts = options
    record_path = out_dir / f"{done.name}{RECORD_SUFFIX}"
    with contextlib.suppress(FileNotFoundError):
        record_path.unlink()  # the frame is not complete again until its new record is written
    if opts.png:
        done.previews = make_previews(done.result, done.recycled, s0_bounds=done.s0_bounds)
    outputs = write_polar_outputs(done.result, out_dir, done.name, png=opts.png, previews=done.previews,
                                  cancel=cancel, png_level=opts.png_level)
    record: dict[str, Any] = {
        "schema": SCHEMA_ID,
        "file": str(done.path),
        "status": "ok",
        "pixel_format": done.pixel_format,
        "layout": str(opts.layout),
        "calibrated": opts.analyser is not None,
        **done.summary,
        "outputs": outputs,
        "warnings": done.warnings,
        "input": done.source,
        "options": opts.fingerprint(),
        "output_bytes": {k: os.path.getsize(v) for k, v in outputs.items()},
    }
    write_json_atomic(record_path, record)
    return record


def process_one(path: Path, out_dir: Path, name: str, options: PolarOptions) -> dict[str, Any]:
    """Read, process and write one frame without the pipeline; returns its JSON record (record file last)."""
    frame, source = read_one(path, options)
    record = write_one(compute_one(path, name, frame, source, options), out_dir, options)
    for text in record["warnings"]:
        print(f"pihim: warning: {path}: {text}", file=sys.stderr)
    return record


def _warn_renamed(batch: Sequence[Path], names: dict[Path, str]) -> None:
    """One warning line per group of frames that share a name and get distinct output names."""
    groups: dict[str, list[Path]] = {}
    for p in batch:
        if names[p] != p.stem:
            groups.setdefault(p.stem.casefold(), []).append(p)
    for group in groups.values():
        listed = ", ".join(f"{p} -> {names[p]}.*" for p in group)
        print(f"pihim: warning: frames share the name {group[0].stem!r}; their outputs are named {listed}",
              file=sys.stderr)


def _error_record(path: Path, message: str) -> dict[str, Any]:
    return {"schema": SCHEMA_ID, "file": str(path), "status": "error", "error": message}


def _summary(processed: Sequence[dict[str, Any]], resumed: int, n_frames: int, out_dir: Path, *, png: bool) -> str:
    """The success line: frames processed by this run, skipped as already complete, and failed.

    Parameters
    ----------
    processed : sequence of dict
        Records of the frames this run processed and wrote.
    resumed : int
        Frames skipped because an earlier run completed them.
    n_frames : int
        Frames in the batch (each file counted once).
    out_dir : Path
        Output directory.
    png : bool
        Whether PNG previews and the captioned figure were asked for.

    Returns
    -------
    str
        One line; the median DoLP range is over the processed frames only.
    """
    failed = n_frames - len(processed) - resumed
    if processed:
        med = [r["dolp"]["median"] for r in processed if r["dolp"]["median"] is not None]
        text = (f"pihim polar: {len(processed)} of {n_frames} frames -> {out_dir}: <stem>.S0/.DoLP/.AoP.tiff "
                f"(float32, AoP in deg)" + (", PNG previews and <stem>.polar.png (captioned)" if png else "")
                + (f"; median DoLP {min(med):.3f}-{max(med):.3f}" if med else ""))
    else:
        text = f"pihim polar: no frame processed in {out_dir}"
    if resumed:
        text += f"; {resumed} of {n_frames} already complete from an earlier run, skipped (--overwrite redoes them)"
    if failed:
        text += f"; {failed} failed"
    return text


# -- options -----------------------------------------------------------------------------------------


def check_options(
    *, demosaic: str, layout: str, calibration: Path | None, dark_level: float, bit_depth: int | None,
    saturation_level: float | None, width: int | None, height: int | None, pixel_format: str | None, png: bool,
    png_level: int = 0,
) -> PolarOptions:
    """Validate every option (one-line :class:`PihimInputError`) before any frame is read."""
    if demosaic not in DEMOSAIC_METHODS:
        raise PihimInputError(f"unknown demosaic method {demosaic!r}; choose one of {', '.join(DEMOSAIC_METHODS)}")
    lay = parse_layout(layout)
    analyser = AnalyserMatrix.load(calibration) if calibration is not None else None
    if not (math.isfinite(dark_level) and 0 <= dark_level <= MAX_RAW_VALUE):
        raise PihimInputError(f"--dark-level must be a raw level in [0, {MAX_RAW_VALUE}], got {dark_level:g}")
    if bit_depth is not None and not 1 <= bit_depth <= 16:
        raise PihimInputError(f"--bit-depth must be in 1..16, got {bit_depth}")
    if saturation_level is not None:
        if not (math.isfinite(saturation_level) and dark_level < saturation_level <= MAX_RAW_VALUE):
            raise PihimInputError(
                f"--saturation-level must be a raw level above --dark-level ({dark_level:g}) and at most "
                f"{MAX_RAW_VALUE}, got {saturation_level:g}"
            )
        if bit_depth is not None and saturation_level > 2**bit_depth - 1:
            raise PihimInputError(
                f"--saturation-level {saturation_level:g} is above the {bit_depth}-bit full scale {2**bit_depth - 1}"
            )
    if bit_depth is not None and dark_level >= 2**bit_depth - 1:
        raise PihimInputError(f"--dark-level {dark_level:g} is at or above the {bit_depth}-bit full scale")
    for label, v in (("--width", width), ("--height", height)):
        if v is not None and v < 1:
            raise PihimInputError(f"{label} must be a positive number of pixels, got {v}")
    if not 0 <= png_level <= 9:
        raise PihimInputError(f"--png-level must be a deflate level 0-9, got {png_level}")
    fmt = None if pixel_format is None else normalize_pixel_format(pixel_format)
    return PolarOptions(lay, analyser, demosaic, float(dark_level), bit_depth,
                        None if saturation_level is None else float(saturation_level), width, height, fmt, png,
                        int(png_level))


def _distinct(frames: Sequence[Path]) -> list[Path]:
    """Frames in order, each file once (the same file named twice is processed once)."""
    seen: set[Any] = set()
    out: list[Path] = []
    for p in frames:
        key = _file_id(p) or os.path.abspath(p)
        if key in seen:
            continue
        seen.add(key)
        out.append(p)
    return out


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
    png: Annotated[bool, typer.Option("--png", help="Also write PNG previews and a captioned figure, <stem>.polar.png.")] = False,
    png_level: Annotated[int, typer.Option(help="Deflate level of the three bare PNG previews: 0 stores them uncompressed (least CPU, keeps up with the camera), 1-9 compress (smaller files; 1-3 fast with Intel ISA-L, installed with pihim on x86-64 and ARM64). The captioned figure is always compressed.")] = 0,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Redo frames already done in --out by an earlier run.")] = False,
    json_out: Annotated[bool, typer.Option("--json", help="Print one JSON object per frame on stdout.")] = False,
) -> int:
    """Turn raw mosaic frames into S0, DoLP and AoP images (float32 TIFF, AoP in degrees).

    Frames that fail are reported (one line each) and skipped; the others are
    still processed. Frames already done in --out with the same input and
    options are skipped (--overwrite redoes them). Exit status 2 if any frame
    was bad input, 1 if only writing failed.
    """
    options = check_options(demosaic=demosaic, layout=layout, calibration=calibration, dark_level=dark_level,
                            bit_depth=bit_depth, saturation_level=saturation_level, width=width, height=height,
                            pixel_format=pixel_format, png=png, png_level=png_level)
    batch = _distinct(frames)
    names = output_names(batch)
    _warn_renamed(batch, names)
    inputs = {fid: p for p in batch if (fid := _file_id(p)) is not None}
    made = missing_dirs(out)
    out_dir = make_out_dir(out)
    fingerprint = json.loads(json.dumps(options.fingerprint()))
    run = _Batch(options, out_dir, json_out=json_out, n_frames=len(batch))

    def decide(path: Path) -> dict[str, Any] | None:
        """The record of a frame that needs no processing (resumed, or refused before reading), else None."""
        name = names[path]
        record_path = out_dir / f"{name}{RECORD_SUFFIX}"
        outputs = [*output_paths(out_dir, name, png=png).values(), record_path]
        check_not_an_input(path, outputs, inputs)
        check_not_simulated_truth(path, outputs, out_dir / f"{name}.json")
        done = None if overwrite else completed_record(record_path, path, fingerprint)
        return None if done is None else {**done, "file": str(path), "resumed": True}

    try:
        run.go(batch, names, decide)
    finally:
        if run.frozen:
            gc.unfreeze()  # a caller in the same process (tests, a notebook) gets its collector back whole
        remove_empty_dirs(made)  # every frame refused: no empty --out left behind
    if json_out:
        if run.resumed:  # the records say the rest (one per frame, "resumed": true for the skipped ones)
            print(f"pihim: {run.resumed} of {len(batch)} frames were already done in {out_dir} and were skipped "
                  "(--overwrite redoes them)", file=sys.stderr)
    elif run.processed or run.resumed:
        stderr_console().print(_summary(run.processed, run.resumed, len(batch), out_dir, png=png),
                               highlight=False, soft_wrap=True)
    return run.status


def _failure(path: Path, exc: BaseException, out_dir: Path) -> tuple[int, str]:
    """Exit status and one-line message for a frame that failed with ``exc`` (any stage)."""
    if isinstance(exc, PihimInputError):
        return 2, str(exc)
    if isinstance(exc, MemoryError):
        return 2, memory_error_message(f"{path}: processing the frame")
    if isinstance(exc, OSError):
        return 1, _write_error(path, exc, out_dir)
    return 1, f"{path}: internal error ({type(exc).__name__}: {' '.join(str(exc).split())})"


@dataclass
class _Batch:
    """One ``pihim polar`` run: the pipeline, the exit status and the records reported so far."""

    options: PolarOptions
    out_dir: Path
    json_out: bool
    n_frames: int
    status: int = 0
    resumed: int = 0
    processed: list[dict[str, Any]] = field(default_factory=list)
    cancel: threading.Event = field(default_factory=threading.Event)
    spare: queue.SimpleQueue = field(default_factory=queue.SimpleQueue)  # (PolarImage, Previews | None) to reuse
    frozen: bool = False  # gc.freeze() called by this batch

    def report(self, path: Path, outcome: dict[str, Any] | BaseException) -> None:
        """Report one frame (in input order): its record, or the failure that stopped it."""
        if isinstance(outcome, BaseException):
            code, message = _failure(path, outcome, self.out_dir)
            report_error(message)
            self.status = max(self.status, code)
            record = _error_record(path, message)
        else:
            record = outcome
            if record.get("resumed"):
                self.resumed += 1
            else:
                self.processed.append(record)
                if len(self.processed) == 1:
                    # what lives now lives for the batch (modules, compiled kernels, the laid-out figure): out of
                    # the collector's passes, which otherwise walk it all every few frames (GC 5.4 -> 2 % of the
                    # CPU of a --png run, perf); handed back when the batch ends (polar)
                    gc.freeze()
                    self.frozen = True
                for text in record["warnings"]:
                    print(f"pihim: warning: {path}: {text}", file=sys.stderr)
        if self.json_out:
            emit_json(record)

    def _buffers(self, frame: Any) -> tuple[PolarImage | None, Previews | None]:
        """Output arrays and previews of an earlier frame of the same size to reuse, if any."""
        h, w = frame.data.shape
        shape = (h // 2, w // 2) if self.options.demosaic == "superpixel" else (h, w)
        while True:
            try:
                old, previews = self.spare.get_nowait()
            except queue.Empty:
                return None, None
            if old.shape == shape:
                return old, previews  # arrays of another size are dropped

    def _write(self, done: Computed) -> dict[str, Any]:
        try:
            return write_one(done, self.out_dir, self.options, self.cancel)
        finally:
            self.spare.put((done.result, done.previews or done.recycled))

    def go(self, batch: Sequence[Path], names: dict[Path, str],
           decide: Callable[[Path], dict[str, Any] | None]) -> None:
        """Run the batch: read ahead, compute in this thread, write behind; report every frame in order."""
        # frames to process, in order; the others are final before any work
        finals: dict[int, dict[str, Any] | BaseException] = {}
        todo: list[int] = []
        for k, path in enumerate(batch):
            try:
                known = decide(path)
            except Exception as exc:  # noqa: BLE001 - reported as the frame's failure
                finals[k] = exc
                continue
            if known is None:
                todo.append(k)
            else:
                finals[k] = known
        waiting: deque[tuple[int, Future | dict[str, Any] | BaseException]] = deque()
        reads: deque[tuple[int, Future]] = deque()
        next_read = 0
        with ThreadPoolExecutor(1, thread_name_prefix="pihim-read") as reader, \
                ThreadPoolExecutor(WRITERS, thread_name_prefix="pihim-write") as writer:
            try:
                bar = progress(range(len(batch)), "polar")
                for k in bar:
                    path = batch[k]
                    if k in finals:
                        waiting.append((k, finals[k]))
                    else:
                        while next_read < len(todo) and len(reads) <= READ_AHEAD:
                            j = todo[next_read]
                            reads.append((j, reader.submit(read_one, batch[j], self.options)))
                            next_read += 1
                        j, reading = reads.popleft()
                        assert j == k
                        try:
                            frame, source = reading.result()
                            done = compute_one(path, names[path], frame, source, self.options,
                                               *self._buffers(frame))
                            del frame
                        except Exception as exc:  # noqa: BLE001 - one frame's failure never stops the batch
                            waiting.append((k, exc))
                        else:
                            waiting.append((k, writer.submit(self._write, done)))
                            del done
                    self._flush(batch, waiting, block_beyond=WRITES_IN_FLIGHT)
                self._flush(batch, waiting, block_beyond=0)
            except BaseException:
                self.cancel.set()  # the writer abandons its frame (temporaries removed) and nothing new starts
                for _, item in list(waiting) + list(reads):
                    if isinstance(item, Future):
                        item.cancel()
                raise

    def _flush(self, batch: Sequence[Path], waiting: deque, *, block_beyond: int) -> None:
        """Report the finished frames at the head of ``waiting``; wait while more than ``block_beyond`` are writing."""
        while waiting:
            k, item = waiting[0]
            if isinstance(item, Future):
                pending = sum(isinstance(it, Future) and not it.done() for _, it in waiting)
                if not item.done() and pending <= block_beyond:
                    return
                try:
                    outcome: dict[str, Any] | BaseException = item.result()
                except Exception as exc:  # noqa: BLE001 - the frame's failure
                    outcome = exc
            else:
                outcome = item
            waiting.popleft()
            self.report(batch[k], outcome)
