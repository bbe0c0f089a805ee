"""``pihim live``: the live operator view, served to a browser (see ``docs/live.md``).

Only typer is imported here; the server, numba kernels and sources are
imported when the command runs, so ``pihim --help`` stays quick.
"""

from __future__ import annotations

import math
import os
import secrets
import signal
import sys
from pathlib import Path
from typing import Annotated

import typer

from pihim.errors import PihimInputError

SESSION_SCHEMA_ID = "pihim.live-session/1"

#: Longest exposure accepted by ``--exposure-us`` and ``--max-exposure-us``, microseconds (10 s: beyond the
#: range of the machine-vision cameras pihim drives, and far beyond any use over moving heliostat mirrors).
MAX_EXPOSURE_US = 10_000_000.0
#: Highest gain accepted by ``--max-gain-db``, dB (machine-vision sensors offer a few tens of dB).
MAX_GAIN_DB = 100.0


def _parse_size(text: str | None) -> tuple[int, int] | None:
    """``WxH`` to (rows, columns)."""
    if text is None:
        return None
    try:
        w, h = (int(p) for p in text.lower().split("x"))
    except ValueError:
        raise PihimInputError(f"--size must look like 2448x2048, got {text!r}") from None
    if w < 16 or h < 16 or w % 2 or h % 2 or w * h > 64_000_000:
        raise PihimInputError(f"--size must be even, at least 16x16 and at most 64 MP, got {text}")
    return h, w


def _positive(name: str, value: float | None, *, allow_zero: bool = False) -> None:
    if value is None:
        return
    if not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise PihimInputError(f"{name} must be a finite number {'>=' if allow_zero else '>'} 0, got {value:g}")


def _token(option: str | None) -> tuple[str | None, bool]:
    """The token from ``--token`` or ``PIHIM_LIVE_TOKEN``; ``auto`` makes one. Returns (token, generated)."""
    text = option if option is not None else os.environ.get("PIHIM_LIVE_TOKEN") or None
    if text is not None and text.strip().lower() == "auto":
        return secrets.token_urlsafe(24), True
    return text, False


def live(
    source: Annotated[str, typer.Option("--source", help="A folder of raw frames, 'synthetic' (synthetic scenes), 'synthetic:DIR' (a flight rendered by pihim simulate) or 'genicam[:SERIAL]'.",
                                        show_default=False)],
    host: Annotated[str, typer.Option(help="Address to listen on; anything but loopback needs --token.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port (0: any free port).")] = 8765,
    token: Annotated[str | None, typer.Option(help="Access token required on every request ('auto' makes one; "
                                                   "default $PIHIM_LIVE_TOKEN).", show_default=False)] = None,
    record: Annotated[Path | None, typer.Option(help="Write every frame (raw TIFF + JSON) into this folder.")] = None,
    captures: Annotated[Path, typer.Option(help="Folder of the capture button's raw frames.")] = Path("captures"),
    fps: Annotated[float, typer.Option(help="Frames per second (replay rate, synthetic rate, camera rate).")] = 15.0,
    size: Annotated[str | None, typer.Option(help="Synthetic frame size WxH (default 2448x2048).")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the synthetic scenes.")] = 0,
    cti: Annotated[Path | None, typer.Option(help="GenTL producer (.cti) of the camera vendor, for genicam.")] = None,
    pixel_format: Annotated[str | None, typer.Option(help="Camera pixel format (genicam) or format of .raw files.")
                            ] = None,
    width: Annotated[int | None, typer.Option(help="Width of .raw frames.")] = None,
    height: Annotated[int | None, typer.Option(help="Height of .raw frames.")] = None,
    bit_depth: Annotated[int | None, typer.Option(help="ADC bits when the frames do not say.")] = None,
    dark_level: Annotated[float, typer.Option(help="Dark level, raw units.")] = 0.0,
    layout: Annotated[str, typer.Option(help="Mosaic layout (name or row-major angles).")] = "imx250mzr",
    auto_exposure: Annotated[bool, typer.Option("--auto-exposure/--no-auto-exposure",
                                                help="Adaptive exposure (commands only cameras that take them).")
                             ] = True,
    exposure_us: Annotated[float, typer.Option(help="Initial exposure, microseconds.")] = 1000.0,
    max_exposure_us: Annotated[float, typer.Option(help="Longest exposure the controller may set, us.")] = 20000.0,
    max_gain_db: Annotated[float, typer.Option(help="Highest gain the controller may set, dB.")] = 24.0,
    speed: Annotated[float | None, typer.Option(help="Drone speed, m/s: caps the exposure against motion blur "
                                                     "(with --range).", show_default=False)] = None,
    range_m: Annotated[float, typer.Option("--range", help="Distance to the mirrors for the blur cap, m.")] = 30.0,
    max_blur_px: Annotated[float, typer.Option(help="Motion blur allowed, raw pixels.")] = 1.0,
    latency_frames: Annotated[int, typer.Option(help="Camera actuation latency the controller waits for, frames.")
                              ] = 2,
    plan: Annotated[Path | None, typer.Option(help="plan.json: draw the heliostat outlines seen from --waypoint.")
                    ] = None,
    waypoint: Annotated[int | None, typer.Option(help="Capture waypoint index of --plan (0-based).")] = None,
    field: Annotated[str, typer.Option(help="Field of the outlines: nsttf-like or an OpenCSP heliostat CSV.")
                     ] = "nsttf-like",
    preview_size: Annotated[int, typer.Option(help="Largest side of the previews, pixels.")] = 640,
    jpeg_quality: Annotated[int, typer.Option(help="JPEG quality of the previews, 1-100.")] = 80,
    duration: Annotated[float | None, typer.Option(help="Stop after this many seconds.", show_default=False)] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print a session summary as JSON on exit.")] = False,
) -> None:
    """Live view in the browser: S0 / DoLP / AoP at 15 fps, adaptive exposure, raw capture."""
    from pihim._inputs import check_regular_file
    from pihim.camera.frames import MAX_RAW_VALUE
    from pihim.cli._common import check_out_dir, emit_json, load_field_option, parse_layout

    # every option is checked before the server or a camera is touched
    tok, generated = _token(token)
    _positive("--fps", fps)
    if fps > 120:
        raise PihimInputError(f"--fps must be at most 120, got {fps:g}")
    for name, value in (("--exposure-us", exposure_us), ("--max-exposure-us", max_exposure_us),
                        ("--range", range_m), ("--max-blur-px", max_blur_px)):
        _positive(name, value)
    for name, value in (("--exposure-us", exposure_us), ("--max-exposure-us", max_exposure_us)):
        if value > MAX_EXPOSURE_US:
            raise PihimInputError(f"{name} must be at most {MAX_EXPOSURE_US:.0f} us (10 s), got {value:g}")
    controlled = source.lower() == "synthetic" or source.lower().startswith(("synthetic:", "genicam"))
    if auto_exposure and controlled and exposure_us > max_exposure_us:  # a folder replay takes no commands
        raise PihimInputError(f"--exposure-us {exposure_us:g} is above --max-exposure-us {max_exposure_us:g}: "
                              f"the first exposure must be one the controller may set")
    _positive("--max-gain-db", max_gain_db, allow_zero=True)
    if max_gain_db > MAX_GAIN_DB:
        raise PihimInputError(f"--max-gain-db must be at most {MAX_GAIN_DB:g} dB, got {max_gain_db:g}")
    _positive("--speed", speed, allow_zero=True)
    _positive("--dark-level", dark_level, allow_zero=True)
    if dark_level > MAX_RAW_VALUE:
        raise PihimInputError(f"--dark-level must be a raw level in [0, {MAX_RAW_VALUE}], got {dark_level:g}")
    if bit_depth is not None and not 1 <= bit_depth <= 16:
        raise PihimInputError(f"--bit-depth must be in 1..16, got {bit_depth}")
    if bit_depth is not None and dark_level >= 2**bit_depth - 1:
        raise PihimInputError(f"--dark-level {dark_level:g} is at or above the {bit_depth}-bit full scale")
    _positive("--duration", duration)
    if not 1 <= latency_frames <= 10:
        raise PihimInputError(f"--latency-frames must be in 1..10, got {latency_frames}")
    if not 0 <= seed < 2**32:
        raise PihimInputError(f"--seed must be an integer in 0..2**32-1, got {seed}")
    if (plan is None) != (waypoint is None):
        raise PihimInputError("--plan and --waypoint go together")
    if plan is not None:
        check_regular_file(plan, "plan.json file", option="--plan")
    syn_size = _parse_size(size)
    from pihim.live.sources import check_source_options

    check_source_options(source, size=syn_size, pixel_format=pixel_format, width=width, height=height,
                         bit_depth=bit_depth)
    mosaic_layout = parse_layout(layout)
    check_out_dir(captures, option="--captures")
    if record is not None:
        check_out_dir(record, option="--record")

    from pihim.live.server import bind_socket, check_bind

    check_bind(host, tok)
    from pihim.live.exposure import ExposureParams, ExposureSettings, motion_blur_exposure_cap_us

    params = None
    if auto_exposure:
        params = ExposureParams(latency_frames=latency_frames, exposure_max_us=max_exposure_us,
                                gain_max_db=max_gain_db, exposure_min_us=min(20.0, max_exposure_us))
    cap = None if speed is None else motion_blur_exposure_cap_us(speed, range_m, max_blur_px=max_blur_px)

    field_obj = None
    overlay = None
    field_used = plan is not None or not (source.lower() == "synthetic" or source.lower().startswith("genicam"))
    if field_used or field.strip().lower() not in ("nsttf-like", "nsttf"):  # a CSV is checked even if unused
        loaded = load_field_option(field, None)
        field_obj = loaded if field_used else None
    if plan is not None:
        from pihim.live.overlay import overlay_from_plan

        overlay = overlay_from_plan(field_obj, plan, int(waypoint))  # type: ignore[arg-type]

    sock = bind_socket(host, port)  # port in use: one line, exit 2, before the (slow) source opens
    try:
        from pihim.cli._common import make_out_dir
        from pihim.live.engine import LiveConfig, LiveEngine
        from pihim.live.sources import open_source

        if captures.is_dir():  # created at the first capture; only clean what killed runs left
            from pihim._atomic import clean_stale_temporaries

            clean_stale_temporaries(captures)
        if record is not None:
            make_out_dir(record, option="--record")
        src = open_source(source, fps=fps, size=syn_size, seed=seed, cti=None if cti is None else str(cti),
                          pixel_format=pixel_format, width=width, height=height, bit_depth=bit_depth)
    except BaseException:
        sock.close()
        raise

    log_overlay = None
    if field_obj is not None:
        import functools

        from pihim.live.overlay import overlay_from_log

        log_overlay = functools.partial(overlay_from_log, field_obj)

    config = LiveConfig(exposure=params, exposure_cap_us=cap, initial_settings=ExposureSettings(exposure_us),
                        preview_max_side=preview_size, jpeg_quality=jpeg_quality, layout=mosaic_layout,
                        dark_level=dark_level, capture_dir=captures, record_dir=record, overlay=overlay,
                        overlay_from_log=log_overlay)
    from pihim.live.preview import PreviewRenderer

    PreviewRenderer(preview_size, jpeg_quality)  # option check before the server starts
    engine = LiveEngine(src, config)
    bound = sock.getsockname()
    shown_host = f"[{bound[0]}]" if ":" in bound[0] else bound[0]
    if bound[0] in ("0.0.0.0", "::"):
        shown_host = "HOST"
    url = f"http://{shown_host}:{bound[1]}/"

    def started() -> None:
        suffix = f"?token={tok}" if tok is not None and generated else ("?token=..." if tok is not None else "")
        desc = src.describe()
        print(f"pihim live: {desc.get('name', desc.get('kind'))} ({desc['width']}x{desc['height']}) at {url}{suffix} "
              f"(Ctrl-C to stop)", file=sys.stderr, flush=True)

    from pihim.live.server import serve

    received = serve(engine, sock, token=tok, duration_s=duration, on_started=started)
    sock.close()
    status = engine.status()
    if json_out:
        emit_json({
            "schema": SESSION_SCHEMA_ID,
            "url": url,
            "source": status["source"],
            "duration_s": status["uptime_s"],
            "frames": status["counters"].get("frames", 0),
            "fps": status["fps"],
            "latency_ms": status["latency_ms"],
            "process_ms": status["process_ms"],
            "process_cpu_ms": status["process_cpu_ms"],
            "source_cpu_ms": status["source_cpu_ms"],
            "captures": status["counters"].get("captures", 0),
            "recorded": status["counters"].get("recorded", 0),
            "record_dropped": status["counters"].get("record_dropped", 0),
            "frames_skipped": status["counters"].get("frames_skipped", 0),
            "source_lost": status["counters"].get("source_lost", 0),
            "exposure_commands": status["counters"].get("exposure_commands", 0),
            "last_error": status["last_error"],
            "stopped_by": {None: "duration", signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}.get(received, "signal"),
        })
    if received is not None:
        # the server caught the signal (to close the connections first): say so as every command does
        print("pihim: terminated" if received == signal.SIGTERM else "pihim: aborted", file=sys.stderr, flush=True)
        raise typer.Exit(128 + int(received))
