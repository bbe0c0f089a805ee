"""``pihim calibrate-camera``: intrinsics and lens distortion from chessboard images.

A thin layer over :func:`pihim.inspection.calibration.calibrate_camera`: it
reads the images (raw DoFP frames, turned into S0 with
:func:`pihim.camera.polar_image`, or ordinary grey images), calibrates,
writes ``camera.json`` atomically (schema ``pihim.camera/1``) and prints a
summary on stderr (with ``--json`` the record on stdout).
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer
from numpy.typing import NDArray
from rich.console import Console
from rich.table import Table

from pihim._atomic import clean_stale_temporaries, describe_os_error, write_json_atomic
from pihim._inputs import check_distinct
from pihim.camera.frames import read_frame
from pihim.camera.layout import MosaicLayout
from pihim.camera.pipeline import DEMOSAIC_METHODS, polar_image
from pihim.cli._common import check_not_an_input, check_out_dir, output_target
from pihim.errors import PihimInputError

if TYPE_CHECKING:  # the calibration module imports the renderer (scipy): loaded when the command runs
    from pihim.inspection.calibration import CameraCalibration

GREY_SUFFIXES = (".png", ".tif", ".tiff")
#: Largest --binning accepted (sensor pixels per image pixel; 2 for pihim's super-pixel images).
MAX_BINNING = 16


def parse_board(text: str) -> tuple[int, int]:
    """Parse ``--board COLSxROWS`` (inner corners), e.g. ``9x6``.

    Examples
    --------
    >>> parse_board("9x6")
    (9, 6)
    """
    parts = text.strip().lower().replace(",", "x").split("x")
    try:
        cols, rows = (int(p) for p in parts)
    except ValueError:
        raise PihimInputError(f"--board: expected inner corners as COLSxROWS like 9x6, got {text!r}") from None
    if cols < 3 or rows < 3:
        raise PihimInputError(f"--board: need at least 3x3 inner corners, got {text!r}")
    if cols > 1000 or rows > 1000:
        raise PihimInputError(f"--board: at most 1000x1000 inner corners, got {text!r}")
    return cols, rows


def read_grey(path: Path) -> NDArray:
    """A single-channel grey image from a PNG (8/16 bit) or TIFF (8/16 bit unsigned or float), any size."""
    label = os.fspath(path)
    suffix = path.suffix.lower()
    if path.is_dir():
        raise PihimInputError(f"{label}: a folder; give the image files (e.g. {label}/*.png)")
    if suffix not in GREY_SUFFIXES:
        raise PihimInputError(f"{label}: unsupported grey image type {suffix or '(no extension)'!r}; "
                              f"expected one of {', '.join(GREY_SUFFIXES)}")
    from pihim._inputs import check_regular_file
    from pihim.camera.frames import stderr_captured

    check_regular_file(path, "grey image")
    import cv2  # imported where used: the command's --help need not load OpenCV
    import tifffile

    captured: list[str] = []
    try:
        if suffix == ".png":
            with stderr_captured(captured):  # libpng prints its own error line
                img = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        else:
            img = tifffile.imread(path)
    except Exception as exc:  # noqa: BLE001 - decoders raise many types on corrupt files
        raise PihimInputError(f"{label}: cannot read image ({type(exc).__name__}: {' '.join(str(exc).split())})") \
            from None
    if img is None:
        detail = "; ".join(line.strip() for line in captured if line.strip())
        raise PihimInputError(f"{label}: cannot decode image ({detail or 'corrupt or unsupported file'})")
    img = np.asarray(img)
    if img.ndim == 3 and img.shape[0] == 1:
        img = img[0]
    if img.ndim != 2:
        raise PihimInputError(f"{label}: expected a single-channel grey image, got shape {img.shape}")
    if img.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        raise PihimInputError(f"{label}: unsupported sample type {img.dtype}; expected 8/16-bit unsigned or float")
    return img


def _summary(cal: CameraCalibration, out: Path) -> Table:
    cam = cal.camera
    k1, k2, p1, p2, k3 = cam.distortion
    table = Table(
        title=f"Camera calibration: {len(cal.views_used)} of {len(cal.views)} views -> {out}",
        caption=(
            f"fx {cam.fx_px:.2f} px ({cam.focal_length_mm:.3f} mm), fy {cam.fy_px:.2f} px, "
            f"cx {cam.cx_px:.2f}, cy {cam.cy_px:.2f} px; k1 {k1:+.5f}, k2 {k2:+.5f}, p1 {p1:+.6f}, p2 {p2:+.6f}, "
            f"k3 {k3:+.5f}; reprojection RMS {cal.rms_px:.3f} px"
        ),
    )
    for col in ("image", "used", "RMS px", "max px", "distance m", "note"):
        table.add_column(col, justify="left" if col in ("image", "note") else "right")
    for v in cal.views:
        dist = None if v.tvec is None else float(np.linalg.norm(v.tvec))
        table.add_row(
            v.name,
            "yes" if v.used else "no",
            "" if v.rms_px is None else f"{v.rms_px:.3f}",
            "" if v.max_error_px is None else f"{v.max_error_px:.3f}",
            "" if dist is None else f"{dist:.3f}",
            v.reason or "",
        )
    return table


def calibrate_camera(
    images: Annotated[
        list[Path],
        typer.Argument(
            metavar="IMAGE",
            help="Chessboard images, all the same size: raw DoFP frames (.tif/.tiff, .png, .raw/.bin; default) "
            "or, with --grey, ordinary grey images (8/16-bit PNG, 8/16-bit or float TIFF).",
            show_default=False,
        ),
    ],
    board: Annotated[
        str,
        typer.Option("--board", help="Inner corners COLSxROWS (OpenCV patternSize; a 9x6 board has 10x7 squares).",
                     show_default=False),
    ],
    square: Annotated[
        float, typer.Option("--square", help="Side of a square, millimetres.", show_default=False)
    ],
    out: Annotated[
        Path, typer.Option("--out", "-o", help="camera.json to write (atomically).", show_default=False)
    ],
    pixel_size_um: Annotated[
        float, typer.Option("--pixel-size-um", help="Sensor pixel pitch, um (to express fx in mm).")
    ] = 3.45,
    grey: Annotated[
        bool,
        typer.Option("--grey", help="The images are grey images, used as they are (not DoFP mosaics)."),
    ] = False,
    demosaic: Annotated[
        str,
        typer.Option(
            "--demosaic",
            help="S0 of DoFP frames: 'full' = full-resolution S0 (pihim.camera.polar_image, demosaic='full'); "
            "'superpixel' = half-resolution S0 of each 2x2 super-pixel, corners mapped back to sensor pixels "
            "(u = 2u' + 0.5). The camera is always given in sensor pixels.",
        ),
    ] = "full",
    layout: Annotated[
        str, typer.Option("--layout", help="Mosaic layout of DoFP frames: imx250mzr or four angles like 90,45,135,0.")
    ] = "imx250mzr",
    binning: Annotated[
        int,
        typer.Option("--binning", help="With --grey: sensor pixels per image pixel (2 for the S0.tiff of "
                     "'pihim polar' with the superpixel route)."),
    ] = 1,
    fix_k3: Annotated[
        bool, typer.Option("--fix-k3", help="Keep k3 = 0 (fit k1, k2, p1, p2 only; advisable for narrow lenses).")
    ] = False,
    max_view_rms: Annotated[
        float | None,
        typer.Option("--max-view-rms", help="Reject views whose reprojection RMS exceeds this many pixels, and refit."),
    ] = None,
    width: Annotated[int | None, typer.Option("--width", help="Frame width for .raw buffers.")] = None,
    height: Annotated[int | None, typer.Option("--height", help="Frame height for .raw buffers.")] = None,
    pixel_format: Annotated[
        str | None, typer.Option("--pixel-format", help="Lucid pixel format for .raw buffers, e.g. PolarizeMono12p.")
    ] = None,
    json_output: Annotated[
        bool, typer.Option("--json", help="Print the camera JSON on stdout (summary goes to stderr).")
    ] = False,
) -> None:
    """Calibrate the camera (fx, fy, cx, cy, k1 k2 p1 p2 k3) from chessboard images with OpenCV."""
    cols, rows = parse_board(board)
    if not (math.isfinite(square) and 0 < square <= 1e6):
        raise PihimInputError(f"--square must be a positive number of millimetres up to 1e6 (1 km), got {square:g}")
    if not (math.isfinite(pixel_size_um) and pixel_size_um > 0):
        raise PihimInputError(f"--pixel-size-um must be positive, got {pixel_size_um:g}")
    if demosaic not in DEMOSAIC_METHODS:
        raise PihimInputError(f"--demosaic must be one of {', '.join(DEMOSAIC_METHODS)}, got {demosaic!r}")
    if not 1 <= binning <= MAX_BINNING:
        raise PihimInputError(f"--binning must be an integer from 1 to {MAX_BINNING} (sensor pixels per image "
                              f"pixel), got {binning}")
    if binning != 1 and not grey:
        raise PihimInputError("--binning applies to --grey images; DoFP frames set it from --demosaic")
    if max_view_rms is not None and not (math.isfinite(max_view_rms) and max_view_rms > 0):
        raise PihimInputError(f"--max-view-rms must be a positive number of pixels, got {max_view_rms:g}")
    if out.is_dir():
        raise PihimInputError(f"--out {out}: is a directory; give the JSON file to write")
    check_out_dir(out.parent, option="--out")
    output_target(out, option="--out")
    check_not_an_input(out, images)
    check_distinct(images, "view")  # one view twice is not two views of the board: it skews the fit
    mosaic_layout = None if grey else MosaicLayout.parse(layout)

    arrays: list[NDArray] = []
    for p in images:
        if grey:
            arrays.append(read_grey(p))
        else:
            frame = read_frame(p, width=width, height=height, pixel_format=pixel_format)
            pol = polar_image(frame.data, layout=mosaic_layout, demosaic=demosaic,  # type: ignore[arg-type]
                              bit_depth=frame.bit_depth)
            arrays.append(pol.s0)
    import cv2

    from pihim.inspection.calibration import calibrate_camera as _calibrate

    image_binning = binning if grey else (2 if demosaic == "superpixel" else 1)
    cal = _calibrate(
        arrays,
        (cols, rows),
        square / 1000.0,
        pixel_size_um=pixel_size_um,
        flags=cv2.CALIB_FIX_K3 if fix_k3 else 0,
        image_binning=image_binning,
        names=[str(p) for p in images],
        max_view_rms_px=max_view_rms,
        name=f"pihim calibrate-camera ({cols}x{rows} board, {square:g} mm squares)",
    )
    record = cal.to_dict()
    record["calibration"]["input"] = {
        "kind": "grey" if grey else "dofp",
        "demosaic": None if grey else demosaic,
        "layout": None if mosaic_layout is None else str(mosaic_layout),
        "files": [str(p) for p in images],
    }
    try:
        if out.parent.is_dir():
            clean_stale_temporaries(out.parent)  # left by a killed run
        write_json_atomic(out, record)
    except OSError as exc:
        raise OSError(f"{out}: cannot write the calibration ({describe_os_error(exc)})") from None
    console = Console(file=sys.stderr, width=160)  # human messages on stderr (docs/cli.md), JSON alone on stdout
    console.print(_summary(cal, out))
    for w in cal.warnings:
        print(f"pihim: warning: {w}", file=sys.stderr)
    if json_output:
        sys.stdout.write(json.dumps(record, allow_nan=False) + "\n")
