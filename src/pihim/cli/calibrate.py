"""``pihim calibrate-polarizer``: fit the analyser matrix from frames behind a rotated polarizer.

A thin layer over :func:`pihim.camera.calibration.calibrate_polarizer`: it
parses the options, reads the frames with :func:`pihim.camera.frames.read_frame`,
writes the calibration JSON atomically and prints a summary. The JSON file
is readable by :meth:`pihim.polarimetry.AnalyserMatrix.load` (``pihim polar
--calibration``).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from pihim._atomic import clean_stale_temporaries, describe_os_error, write_json_atomic
from pihim._inputs import check_distinct
from pihim.camera import calibration
from pihim.camera.frames import MAX_RAW_VALUE, read_frame
from pihim.camera.layout import MosaicLayout
from pihim.cli._common import check_not_an_input, check_out_dir, output_target
from pihim.errors import PihimInputError
from pihim.polarimetry.analyser import NOMINAL_ANGLES_DEG


#: Most angles ``--angles START:STOP:STEP`` may expand to (one frame per angle).
MAX_ANGLES = 10_000
#: Largest polarizer angle magnitude accepted, deg: a multi-turn encoder's cumulative reading (2,777 turns) is fine,
#: a mistyped exponent is refused before the fit (cos 2 theta of 1e308 deg is NaN).
MAX_ANGLE_DEG = 1e6


def parse_angles(text: str, *, max_count: int = MAX_ANGLES) -> list[float]:
    """Parse ``--angles``: comma-separated degrees, or ``START:STOP:STEP`` (STOP exclusive).

    A range is refused before it is expanded when it holds more than
    ``max_count`` angles (``0:1e9:1e-9`` would be 10^18 of them).

    Examples
    --------
    >>> parse_angles("0, 22.5,45")
    [0.0, 22.5, 45.0]
    >>> parse_angles("0:180:45")
    [0.0, 45.0, 90.0, 135.0]
    """
    s = text.strip()
    count: float | None = None
    try:
        if ":" in s:
            parts = [float(p) for p in s.split(":")]
            if len(parts) != 3:
                raise ValueError
            start, stop, step = parts
            if not all(math.isfinite(v) for v in parts) or step <= 0 or stop <= start:
                raise ValueError
            count = (stop - start) / step
            vals = [] if not count - 1e-9 <= max_count else [start + i * step for i in range(math.ceil(count - 1e-9))]
        else:
            vals = [float(p) for p in s.replace(";", ",").split(",") if p.strip()]
    except ValueError:
        raise PihimInputError(
            f"--angles: cannot parse {text!r}; give comma-separated degrees like 0,22.5,45 "
            "or START:STOP:STEP like 0:180:22.5"
        ) from None
    if count is not None and not count - 1e-9 <= max_count:
        raise PihimInputError(f"--angles {text!r} gives {count:.3g} angles; at most {max_count} (one per frame)")
    if not vals:
        raise PihimInputError(f"--angles: no angles in {text!r}")
    bad = next((v for v in vals if not math.isfinite(v)), None)
    if bad is not None:
        raise PihimInputError(f"--angles: {bad!r} in {text!r} is not a finite angle")
    if max(abs(v) for v in vals) > MAX_ANGLE_DEG:
        raise PihimInputError(f"--angles: polarizer angles must be within +-{MAX_ANGLE_DEG:g} deg, got {text!r}")
    return vals


def parse_roi(text: str) -> tuple[int, int, int, int]:
    """Parse ``--roi X,Y,W,H`` (mosaic pixels)."""
    try:
        vals = tuple(int(p) for p in text.replace(" ", "").split(","))
    except ValueError:
        vals = ()
    if len(vals) != 4:
        raise PihimInputError(f"--roi: expected four integers X,Y,WIDTH,HEIGHT, got {text!r}")
    return vals  # type: ignore[return-value]


def _summary(cal: calibration.PolarizerCalibration, out: Path) -> Table:
    x, y, w, h = cal.roi or (0, 0, 0, 0)
    table = Table(
        title=f"Polarizer calibration: {cal.n_frames} frames -> {out}",
        caption=(
            f"ROI {w}x{h} px at ({x}, {y}), {cal.superpixels_used} super-pixels; "
            f"cond(A) = {cal.condition_number:.3f}, angle design cond = {cal.design_condition_number:.2f}"
        ),
    )
    for col in ("channel", "axis", "offset", "trans.", "diatt.", "ext. ratio", "resid. %"):
        table.add_column(col, justify="right")
    for k, nominal in enumerate(NOMINAL_ANGLES_DEG):
        ang = float(cal.angles_deg[k])
        off = (ang - nominal + 90.0) % 180.0 - 90.0
        er = float(cal.extinction_ratio[k])
        table.add_row(
            f"{nominal:g}",
            f"{ang:.2f}°",
            f"{off:+.2f}°",
            f"{cal.transmission[k]:.4f}",
            f"{cal.diattenuation[k]:.4f}",
            "inf" if math.isinf(er) else f"{er:.1f}",
            f"{100 * cal.residual_rms_relative[k]:.3f}",
        )
    return table


def calibrate_polarizer(
    frames: Annotated[
        list[Path],
        typer.Argument(
            metavar="FRAME",
            help="Raw frames (.tif/.tiff, .png, .raw/.bin) of a uniformly lit scene behind the "
            "reference polarizer, one per entry of --angles, in the same order.",
            show_default=False,
        ),
    ],
    angles: Annotated[
        str,
        typer.Option(
            "--angles",
            help="Polarizer angle of each frame in degrees, counter-clockwise from image right: "
            "'0,22.5,45,...' or START:STOP:STEP (e.g. 0:180:22.5). At least 4 distinct angles.",
            show_default=False,
        ),
    ],
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Calibration JSON to write (atomically).", show_default=False)
    ],
    layout: Annotated[
        str, typer.Option("--layout", help="Mosaic layout: imx250mzr or four row-major angles like 90,45,135,0.")
    ] = "imx250mzr",
    dark_level: Annotated[
        float, typer.Option("--dark-level", help="Dark level in DN (after any MSB shift), subtracted.")
    ] = 0.0,
    bit_depth: Annotated[
        int | None, typer.Option("--bit-depth", help="ADC bits; default from the file or the data.")
    ] = None,
    polarizer_dolp: Annotated[
        float, typer.Option("--polarizer-dolp", help="DoLP of the reference polarizer, in (0, 1].")
    ] = 1.0,
    roi: Annotated[
        str | None,
        typer.Option("--roi", help="Region X,Y,WIDTH,HEIGHT in pixels; default the central half of each side."),
    ] = None,
    fit_drift: Annotated[
        bool,
        typer.Option("--fit-drift", help="Also fit a per-frame source intensity drift (needs >= 5 angles)."),
    ] = False,
    width: Annotated[int | None, typer.Option("--width", help="Frame width for .raw buffers.")] = None,
    height: Annotated[int | None, typer.Option("--height", help="Frame height for .raw buffers.")] = None,
    pixel_format: Annotated[
        str | None, typer.Option("--pixel-format", help="Lucid pixel format for .raw buffers, e.g. PolarizeMono12p.")
    ] = None,
    json_output: Annotated[
        bool, typer.Option("--json", help="Print the calibration JSON on stdout (summary goes to stderr).")
    ] = False,
) -> None:
    """Estimate the analyser matrix from frames behind a linear polarizer rotated to known angles."""
    angle_list = parse_angles(angles, max_count=max(len(frames), 1))
    if len(angle_list) != len(frames):
        raise PihimInputError(f"got {len(frames)} frames but {len(angle_list)} angles in --angles")
    mosaic_layout = MosaicLayout.parse(layout)
    roi_box = None if roi is None else parse_roi(roi)
    if bit_depth is not None and not 1 <= bit_depth <= 16:
        raise PihimInputError(f"--bit-depth must be in 1..16, got {bit_depth}")
    if not (math.isfinite(dark_level) and 0 <= dark_level <= MAX_RAW_VALUE):
        raise PihimInputError(f"--dark-level must be a raw level in [0, {MAX_RAW_VALUE}], got {dark_level:g}")
    if not (math.isfinite(polarizer_dolp) and 0 < polarizer_dolp <= 1):
        raise PihimInputError(f"--polarizer-dolp must be in (0, 1], got {polarizer_dolp:g}")
    if out.is_dir():
        raise PihimInputError(f"--out {out}: cannot write the calibration: is a directory; give a JSON file name")
    check_out_dir(out.parent, option="--out")
    output_target(out, option="--out")
    check_not_an_input(out, frames)
    check_distinct(frames, "frame")  # one frame at two polarizer angles is a mistake
    raws = [read_frame(p, width=width, height=height, pixel_format=pixel_format) for p in frames]
    cal = calibration.calibrate_polarizer(
        raws,
        np.asarray(angle_list),
        layout=mosaic_layout,
        dark_level=dark_level,
        bit_depth=bit_depth,
        polarizer_dolp=polarizer_dolp,
        roi=roi_box,
        fit_frame_scale=fit_drift,
    )
    record = cal.to_dict()
    try:
        if out.parent.is_dir():
            clean_stale_temporaries(out.parent)  # left by a killed run
        write_json_atomic(out, record)
    except OSError as exc:  # an operating-system error: exit status 1 (docs/cli.md)
        raise OSError(f"{out}: cannot write the calibration ({describe_os_error(exc)})") from None
    Console(file=sys.stderr).print(_summary(cal, out))  # a human summary: stderr, as every command's
    for w in cal.warnings:
        print(f"pihim: warning: {w}", file=sys.stderr)
    if json_output:
        sys.stdout.write(json.dumps(record, allow_nan=False) + "\n")
