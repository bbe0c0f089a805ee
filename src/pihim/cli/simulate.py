"""``pihim simulate``: one synthetic raw frame of a tracking field, with its log and its ground truth.

A thin layer over :func:`pihim.render.simulate.simulate_frame` and
:func:`pihim.render.simulate.write_simulated_frame`; see ``docs/cli.md``.
"""

from __future__ import annotations

import contextlib
import math
import sys
import time as _time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from pihim._atomic import clean_stale_temporaries
from pihim._inputs import check_regular_file, load_json_file
from pihim._resources import require_memory
from pihim.camera.model import camera_for_size
from pihim.cli._common import check_out_dir, emit_json, load_field_option, output_target, parse_point, stderr_console
from pihim.errors import PihimInputError
from pihim.sky.sun import Site, parse_site, parse_time

if TYPE_CHECKING:
    from pihim.render.simulate import PoseRequest

#: ``RenderSettings().supersample``, the default of ``--supersample`` (a test keeps the two equal): the renderer
#: and its numba kernels are imported only when a frame is rendered, not for ``pihim simulate --help``.
DEFAULT_SUPERSAMPLE = 3

SUMMARY_SCHEMA_ID = "pihim.simulate-summary/1"
#: Peak bytes per pixel of a render and its writing (raw, Stokes and truth images, 7 label planes, the
#: renderer's working arrays) and the about constant part (scene, shading tables): the peak resident size
#: of a whole ``pihim simulate`` run of the NSTTF-like field grows by 120-131 B per pixel plus 75-87 MB
#: (512x512 to 2048x2048, ``benchmarks/memory_estimates_quality.py``); with a 15 % margin.
RENDER_BYTES_PER_PIXEL = 150
RENDER_FIXED_BYTES = 100_000_000


def render_bytes(width: int, height: int) -> int:
    """Estimated peak bytes of rendering and writing a ``width`` x ``height`` frame (NSTTF-like field)."""
    return width * height * RENDER_BYTES_PER_PIXEL + RENDER_FIXED_BYTES


def parse_size(text: str) -> tuple[int, int]:
    """``WxH`` (even, at least 16 x 16) to ``(width, height)``."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise PihimInputError(f"--size must look like 2448x2048, got {text!r}") from None
    if w < 16 or h < 16 or w % 2 or h % 2:
        raise PihimInputError(f"--size must be even and at least 16x16, got {text}")
    require_memory(render_bytes(w, h), f"--size {w}x{h}")
    return w, h


def parse_pose_request(hua: str | None, target: str | None, waypoint: str | None, camera: str | None,
                       look_at: str | None, roll: float | None) -> PoseRequest:
    """Exactly one of ``--hua/--target``, ``--waypoint`` or ``--camera/--look-at [--roll]``."""
    from pihim.render.simulate import LookAtPose, PairPose, WaypointPose

    pair = hua is not None or target is not None
    way = waypoint is not None
    look = camera is not None or look_at is not None or roll is not None
    chosen = sum((pair, way, look))
    if chosen != 1:
        what = "none was given" if chosen == 0 else "several were given"
        raise PihimInputError(
            f"give exactly one camera pose: --hua NAME --target NAME, --waypoint plan.json:INDEX, "
            f"or --camera X,Y,Z --look-at X,Y,Z ({what})"
        )
    if pair:
        if hua is None or target is None:
            raise PihimInputError("--hua and --target go together")
        return PairPose(hua.strip(), target.strip())
    if way:
        assert waypoint is not None
        path, sep, idx = waypoint.rpartition(":")
        if not sep or not path:
            raise PihimInputError(f"--waypoint must be PLAN.json:INDEX, got {waypoint!r}")
        try:
            index = int(idx)
        except ValueError:
            raise PihimInputError(f"--waypoint index must be an integer >= 0, got {idx!r}") from None
        if index < 0:
            raise PihimInputError(f"--waypoint index must be an integer >= 0, got {index}")
        check_regular_file(path, "plan.json file", option="--waypoint")  # its content: _time_for reads it
        return WaypointPose(path, index)
    if camera is None or look_at is None:
        raise PihimInputError("--camera and --look-at go together (--roll needs them)")
    cam = parse_point(camera, name="--camera")
    tgt = parse_point(look_at, name="--look-at")
    assert cam is not None and tgt is not None
    if cam == tgt:
        raise PihimInputError(f"--look-at equals --camera ({camera}): the camera must look somewhere")
    if roll is not None and not (math.isfinite(roll) and -360.0 <= roll <= 360.0):
        raise PihimInputError(f"--roll must be in [-360, 360] deg, got {roll:g}")
    return LookAtPose(tuple(cam), tuple(tgt), 0.0 if roll is None else float(roll))  # type: ignore[arg-type]


@contextlib.contextmanager
def _render_progress(enabled: bool) -> Iterator[Callable[[int, int], Any] | None]:
    """A ``progress(done, total)`` callback drawing a bar on stderr, or None."""
    if not enabled:
        yield None
        return
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                  TimeRemainingColumn(), console=stderr_console(), transient=True) as bar:
        task = bar.add_task("rendering", total=None)

        def update(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        yield update


def _time_for(request: PoseRequest, time: str | None, site: Site) -> str:
    """``--time``, or the time a ``--waypoint`` plan was made for; a note on stderr when they (or the sites) differ.

    Rendering a waypoint at another time is legitimate (how would the same
    flight look an hour later?) but the field then tracks another sun than the
    one the waypoint was planned for, so it is said; so is a ``--site`` other
    than the plan's.
    """
    from pihim.render.simulate import WaypointPose

    planned = None
    if isinstance(request, WaypointPose):  # malformed or too deeply nested: one line now, not a traceback later
        doc = load_json_file(request.plan_path, "plan file")
        doc = doc if isinstance(doc, dict) else {}
        planned = doc.get("time_iso")
        where = doc.get("site") if isinstance(doc.get("site"), dict) else {}
        lat, lon = where.get("latitude_deg"), where.get("longitude_deg")
        if isinstance(lat, (int, float)) and isinstance(lon, (int, float)) \
                and max(abs(lat - site.latitude_deg), abs(lon - site.longitude_deg)) > 1e-6:
            print(f"pihim simulate: note: the plan was made for a site at {lat:g}, {lon:g} deg, not --site "
                  f"({site.latitude_deg:g}, {site.longitude_deg:g} deg)", file=sys.stderr)
        if planned is not None:
            try:
                parse_time(planned)
            except (PihimInputError, TypeError):
                raise PihimInputError(f"{request.plan_path}: time_iso {planned!r} is not an ISO 8601 time with a "
                                      "UTC offset") from None
    if time is None:
        if planned is None:
            raise PihimInputError("--time is required (with --waypoint, the plan's time_iso is the default)")
        return planned
    if planned is not None and parse_time(time) != parse_time(planned):
        print(f"pihim simulate: note: --time {time} is not the time the plan was made for ({planned}); the field "
              "tracks the sun of --time", file=sys.stderr)
    return time


def simulate(
    out: Annotated[Path, typer.Option("--out", help="Raw frame to write, FRAME.tiff (FRAME.json etc. beside it).")],
    time: Annotated[str | None, typer.Option("--time", help="ISO 8601 time with UTC offset, e.g. 2021-05-13T13:00-06:00; with --waypoint default the plan's.", show_default=False)] = None,
    field: Annotated[str, typer.Option("--field", help="nsttf-like (default) or an OpenCSP heliostat CSV.")] = "nsttf-like",
    facets: Annotated[Path | None, typer.Option(help="OpenCSP facet-centroid CSV (with --field CSV).")] = None,
    site: Annotated[str, typer.Option(help="nsttf (default) or LAT,LON,H (deg, deg, ellipsoidal m).")] = "nsttf",
    aim: Annotated[str | None, typer.Option(help="Aim point X,Y,Z (m, ENU); default the --waypoint plan's, else OpenCSP's UFACET aim 60,8.8,28.9.")] = None,
    hua: Annotated[str | None, typer.Option("--hua", help="Heliostat under assessment (with --target).")] = None,
    target: Annotated[str | None, typer.Option("--target", help="Heliostat seen reflected in the HUA.")] = None,
    waypoint: Annotated[str | None, typer.Option("--waypoint", help="PLAN.json:INDEX, a capture waypoint of pihim plan.")] = None,
    camera: Annotated[str | None, typer.Option("--camera", help="Camera position X,Y,Z (m, ENU), with --look-at.")] = None,
    look_at: Annotated[str | None, typer.Option("--look-at", help="Point X,Y,Z (m, ENU) on the optical axis.")] = None,
    roll: Annotated[float | None, typer.Option("--roll", help="Camera roll, deg (with --camera).")] = None,
    canting_sigma_mrad: Annotated[float, typer.Option("--canting-sigma-mrad", help="Facet canting error sigma, mrad.")] = 0.0,
    tracking_sigma_mrad: Annotated[float, typer.Option("--tracking-sigma-mrad", help="Drive-angle error sigma, mrad.")] = 0.0,
    gps_sigma_m: Annotated[float, typer.Option("--gps-sigma-m", help="Logged position error sigma, m.")] = 0.0,
    attitude_sigma_deg: Annotated[float, typer.Option("--attitude-sigma-deg", help="Logged attitude error sigma, deg.")] = 0.0,
    seed: Annotated[int, typer.Option("--seed", help="Seed of every random draw (>= 0).")] = 0,
    size: Annotated[str, typer.Option("--size", help="Frame size WxH (even); the field of view stays the Triton's.")] = "2448x2048",
    supersample: Annotated[int, typer.Option("--supersample", help="Edge pixels get N x N rays (1..16).")] = DEFAULT_SUPERSAMPLE,
    blur_sigma_px: Annotated[float, typer.Option("--blur-sigma-px", help="Gaussian lens blur sigma, pixels.")] = 0.0,
    json_out: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
) -> int:
    """Render a raw polarimetric frame of the tracking field with its log and ground truth."""
    t0 = _time.perf_counter()
    from pihim.render.frame import RenderSettings
    from pihim.render.simulate import simulate_frame, simulated_frame_paths, write_simulated_frame

    # everything is checked before the field is loaded or anything rendered
    paths = simulated_frame_paths(out)
    if out.is_dir():
        raise PihimInputError(f"--out {out}: is a directory; give a FRAME.tiff file name")
    for p in paths.values():  # FRAME.json, FRAME.S0.tiff, ... are written beside it
        if p.is_dir():
            raise PihimInputError(f"--out {out}: {p}, one of the files written beside it, is a directory")
    check_out_dir(out.parent, option="--out")
    for p in (out, *paths.values()):
        output_target(p, option="--out")
    request = parse_pose_request(hua, target, waypoint, camera, look_at, roll)
    width, height = parse_size(size)
    cam = camera_for_size(width, height)
    settings = RenderSettings(supersample=supersample)
    site_obj = parse_site(site)
    time = _time_for(request, time, site_obj)
    aim_point = parse_point(aim, name="--aim")  # None: the --waypoint plan's aim point, else UFACET's
    fld = load_field_option(field, facets, nsttf_tower=site.strip().lower() == "nsttf")
    nsttf_like = field.strip().lower() in ("nsttf-like", "nsttf")
    with _render_progress(sys.stderr.isatty()) as bar:
        sim = simulate_frame(
            fld, time, site=site_obj, aim_point=aim_point, camera=cam, pose_request=request,
            canting_sigma_mrad=canting_sigma_mrad, tracking_sigma_mrad=tracking_sigma_mrad,
            gps_sigma_m=gps_sigma_m, attitude_sigma_deg=attitude_sigma_deg, seed=seed,
            blur_sigma_px=blur_sigma_px, settings=settings, progress=bar,
            field_source="nsttf-like" if nsttf_like else str(field),
            facets_source=None if facets is None else str(facets),
        )
    if out.parent.is_dir():
        clean_stale_temporaries(out.parent)  # of killed runs (their process is gone), see pihim._atomic
    write_simulated_frame(sim, out)
    seconds = _time.perf_counter() - t0
    stats = sim.rendered.stats
    in_view = [h["name"] for h in sim.log["heliostats"]]
    if json_out:
        emit_json({
            "schema": SUMMARY_SCHEMA_ID,
            "files": {k: str(v) for k, v in paths.items()},
            "width_px": width,
            "height_px": height,
            "time": sim.log["time"],
            "hua": sim.log["hua"],
            "target": sim.log["target"],
            "heliostats_in_view": in_view,
            "seed": seed,
            "rays": int(stats.get("rays", 0)),
            "exposure": sim.log["sensor"]["exposure"],
            "seconds": {"render": round(float(stats.get("seconds", float("nan"))), 4),
                        "total": round(seconds, 4)},
        })
    else:
        pair = f"HUA {sim.log['hua']}, target {sim.log['target']}; " if sim.log["hua"] else ""
        clipped = sim.log["sensor"]["exposure"].get("clipped_fraction") or 0.0
        stderr_console().print(
            f"[bold]pihim simulate[/bold]: wrote {out} ({width}x{height} raw) with {paths['json'].name} "
            f"and S0/DoLP/AoP/labels TIFFs", highlight=False, soft_wrap=True,
        )
        stderr_console().print(
            f"  {pair}{len(in_view)} heliostat{'' if len(in_view) == 1 else 's'} in view; {int(stats.get('rays', 0)):,} rays, "
            f"{clipped:.2%} clipped, {seconds:.1f} s", highlight=False, soft_wrap=True,
        )
    return 0
