"""``pihim sky``: all-sky DoLP and AoP maps for a sun position or a time and site.

Writes, as one group (all or none), into ``--out``:

``sky-dolp.png``, ``sky-aop.png``
    Polar plots like the paper's Fig. 2c-d: North up, azimuth clockwise
    (a map of the sky dome seen from above), radius = zenith angle 0-90 deg;
    the sun is a star, Berry neutral points are crosses. AoP uses the cyclic
    'twilight' colormap.
``sky-maps.npz``
    ``zenith_deg``, ``azimuth_deg`` (cell-centre grids, shape
    ``(90/res, 360/res)``, azimuth clockwise from North), ``s0`` (relative to
    the zenith for the CIE radiance), ``dolp``, ``aop_deg`` (float64), the
    sun's ``sun_zenith_deg`` and ``sun_azimuth_deg``, and ``aop_reference``
    (the frame, in words).

AoP frame: skylight from direction ``v`` travels along ``d = -v``; the AoP is
measured from the local meridian (0 = E-field pointing toward the zenith),
counter-clockwise looking into the beam -- i.e. as an observer on the ground
looking up at that point of the sky sees it: 0 = along the meridian,
90 = horizontal. On the solar meridian the Rayleigh AoP is 90.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from pihim._atomic import write_group
from pihim._resources import require_memory
from pihim.cli._common import check_out_dir, emit_json, output_dir, stderr_console
from pihim.errors import PihimInputError
from pihim.sky.berry import neutral_points
from pihim.sky.model import SkyMap, SkyModel, _grid_size, sky_map
from pihim.visualize import polar_map_png
from pihim.sky.sun import (
    SunPosition,
    angles_from_direction,
    parse_site,
    parse_time,
    require_daylight,
    sun_position,
)

SCHEMA_ID = "pihim.sky/1"
AOP_REFERENCE = (
    "AoP in [0, 180) deg from the local meridian (0 = E-field toward the zenith), counter-clockwise "
    "looking into the beam, i.e. as an observer on the ground looking up at that sky point sees it"
)
#: Peak bytes per sky direction, maps and polar plots: the peak resident size of a whole ``pihim sky`` run
#: grows by 246 B per direction (0.5 and 0.25 deg grids, ``benchmarks/memory_estimates_quality.py``);
#: with a 15 % margin.
SKY_BYTES_PER_DIRECTION = 280
FILES = {"dolp_png": "sky-dolp.png", "aop_png": "sky-aop.png", "npz": "sky-maps.npz"}


def resolve_sun(
    time: str | None, site: str | None, sun_zenith: float | None, sun_azimuth: float | None
) -> tuple[SunPosition, dict[str, Any]]:
    """The sun position from ``--time``/``--site`` or ``--sun-zenith``/``--sun-azimuth``; and a JSON record."""
    angles_given = sun_zenith is not None or sun_azimuth is not None
    if time is not None:
        if angles_given:
            raise PihimInputError("give either --time (with --site) or --sun-zenith and --sun-azimuth, not both")
        where = parse_site(site if site is not None else "nsttf")
        when = parse_time(time)
        pos = sun_position(where, when)
        return pos, {"time": when.isoformat(), "site": where.as_dict(), "refraction": "apparent"}
    if site is not None:
        raise PihimInputError("--site needs --time")
    if sun_zenith is None or sun_azimuth is None:
        raise PihimInputError("give --time (and optionally --site), or both --sun-zenith and --sun-azimuth")
    if not (math.isfinite(sun_zenith) and 0.0 <= sun_zenith <= 90.0):
        raise PihimInputError(f"--sun-zenith must be in [0, 90] deg, got {sun_zenith:g}")
    if not (math.isfinite(sun_azimuth) and -360.0 <= sun_azimuth <= 360.0):  # 1e308 would be reduced to noise
        raise PihimInputError(f"--sun-azimuth must be in [-360, 360] deg, got {sun_azimuth:g}")
    return SunPosition.from_angles(sun_zenith, sun_azimuth), {"time": None, "site": None}


def _summary(result: SkyMap, resolution: float) -> dict[str, Any]:
    """Maximum DoLP and its direction; DoLP statistics on the band 90 deg from the sun."""
    dolp = result.dolp
    i = int(np.nanargmax(dolp))
    iz, ia = np.unravel_index(i, dolp.shape)
    v = np.stack(
        [
            np.sin(np.radians(result.zenith_deg)) * np.sin(np.radians(result.azimuth_deg)),
            np.sin(np.radians(result.zenith_deg)) * np.cos(np.radians(result.azimuth_deg)),
            np.cos(np.radians(result.zenith_deg)),
        ],
        axis=-1,
    )
    scat = np.degrees(np.arccos(np.clip(v @ result.sun_dir, -1.0, 1.0)))
    half = max(1.0, resolution / 2.0)
    band = np.abs(scat - 90.0) <= half
    vals = dolp[band & np.isfinite(dolp)]
    return {
        "dolp_max": {
            "value": float(dolp[iz, ia]),
            "zenith_deg": float(result.zenith_deg[iz, ia]),
            "azimuth_deg": float(result.azimuth_deg[iz, ia]),
            "scattering_angle_deg": float(scat[iz, ia]),
        },
        "band_90deg_from_sun": {
            "half_width_deg": half,
            "cells": int(vals.size),
            "dolp_mean": float(vals.mean()) if vals.size else None,
            "dolp_min": float(vals.min()) if vals.size else None,
            "dolp_max": float(vals.max()) if vals.size else None,
        },
    }


def plot_polar(
    result: SkyMap, quantity: str, path: Path, *, title: str, markers: list[tuple[float, float, str, str]],
    atomic: bool = True,
) -> Path:
    """Write a polar plot (North up, azimuth clockwise, radius = zenith) of ``dolp`` or ``aop_deg``."""
    if quantity == "dolp":
        style, label = "dolp", "DoLP"
    else:
        style, label = "aop", "AoP (deg, from local meridian, seen from the ground)"
    return polar_map_png(getattr(result, quantity), path, style=style, label=label, title=title,
                         markers=tuple(markers), atomic=atomic)


def write_outputs(result: SkyMap, out: Path, *, sun: SunPosition, title: str) -> dict[str, str]:
    """Write the two PNGs and the npz as one group (all or none, :func:`pihim._atomic.write_group`); returns
    the written paths."""
    markers = [(float(sun.azimuth_deg), float(sun.zenith_deg), "*", "sun")]
    if result.model.kind == "berry":
        pts = neutral_points(result.sun_dir, result.model.neutral_point_separation_deg)
        for name in ("babinet", "brewster", "arago", "fourth"):
            zen, az = angles_from_direction(getattr(pts, name))
            markers.append((float(az), float(zen), "X", name))
    written = {k: out / name for k, name in FILES.items()}

    def npz(tmp: Path) -> None:
        np.savez_compressed(
            tmp,
            zenith_deg=result.zenith_deg,
            azimuth_deg=result.azimuth_deg,
            s0=result.s0,
            dolp=result.dolp,
            aop_deg=result.aop_deg,
            sun_zenith_deg=np.float64(sun.zenith_deg),
            sun_azimuth_deg=np.float64(sun.azimuth_deg),
            aop_reference=np.str_(AOP_REFERENCE),
        )

    with output_dir(out):
        write_group({
            written["dolp_png"]: lambda p: plot_polar(result, "dolp", p, title=f"DoLP -- {title}", markers=markers,
                                                      atomic=False),
            written["aop_png"]: lambda p: plot_polar(result, "aop_deg", p, title=f"AoP -- {title}",
                                                     markers=markers, atomic=False),
            written["npz"]: npz,
        })
    return {k: str(v) for k, v in written.items()}


def sky(
    out: Annotated[Path, typer.Option("--out", help="Output directory.")],
    time: Annotated[str | None, typer.Option(help="ISO 8601 time with UTC offset (2024-06-21T10:30-06:00).")] = None,
    site: Annotated[str | None, typer.Option(help="With --time: nsttf (default) or LAT,LON,H (ellipsoidal m).")] = None,
    sun_zenith: Annotated[float | None, typer.Option(help="Sun zenith, deg in [0, 90] (instead of --time).")] = None,
    sun_azimuth: Annotated[float | None, typer.Option(help="Sun azimuth, deg clockwise from North.")] = None,
    model: Annotated[str, typer.Option(help="Sky polarization model: rayleigh or berry.")] = "rayleigh",
    dmax: Annotated[float, typer.Option(help="Maximum DoLP (90 deg from the sun), in [0, 1].")] = 0.8,
    neutral_separation: Annotated[float | None, typer.Option(help="With --model berry: neutral points' distance from the sun, deg (default 15).", show_default=False)] = None,
    radiance: Annotated[str, typer.Option(help="S0 model: cie-clear (CIE type 12) or uniform.")] = "cie-clear",
    resolution: Annotated[float, typer.Option(help="Grid step in zenith and azimuth, deg (must divide 90).")] = 0.5,
    json_out: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
) -> int:
    """All-sky DoLP and AoP maps (PNG polar plots and float arrays in .npz).

    Give the sun as --time (and --site, default NSTTF) or as --sun-zenith and
    --sun-azimuth. AoP is relative to the local meridian as seen from the
    ground (see the .npz's aop_reference).
    """
    separation = 15.0 if neutral_separation is None else neutral_separation
    sky_model = SkyModel(kind=model, dmax=dmax, neutral_point_separation_deg=separation, radiance=radiance)  # type: ignore[arg-type]
    if neutral_separation is not None and sky_model.kind != "berry":
        raise PihimInputError(f"--neutral-separation applies to --model berry (the {sky_model.kind} sky's only "
                              "neutral points are the sun and the antisun)")
    nz = _grid_size(resolution)
    require_memory(4 * nz * nz * SKY_BYTES_PER_DIRECTION, f"--resolution {resolution:g} ({4 * nz * nz:,} directions)")
    sun, when = resolve_sun(time, site, sun_zenith, sun_azimuth)
    require_daylight(sun, what="pihim sky")
    check_out_dir(out)
    result = sky_map(sky_model, sun.vector, resolution)
    title = f"sun zenith {float(sun.zenith_deg):.1f}, azimuth {float(sun.azimuth_deg):.1f} deg, {model}"
    files = write_outputs(result, out, sun=sun, title=title)
    if json_out:
        emit_json(
            {
                "schema": SCHEMA_ID,
                "sun": sun.as_dict(),
                **when,
                "model": sky_model.describe(),
                "resolution_deg": float(90.0 / result.dolp.shape[0]),
                "grid_shape": list(result.dolp.shape),
                **_summary(result, resolution),
                "aop_reference": AOP_REFERENCE,
                "files": files,
            }
        )
    else:
        summ = _summary(result, resolution)
        peak = summ["dolp_max"]
        stderr_console().print(
            f"pihim sky: sun zenith {float(sun.zenith_deg):.1f} deg, azimuth {float(sun.azimuth_deg):.1f} deg, "
            f"{model}; DoLP max {peak['value']:.2f} at zenith {peak['zenith_deg']:.1f} deg, azimuth "
            f"{peak['azimuth_deg']:.1f} deg ({peak['scattering_angle_deg']:.0f} deg from the sun)\n"
            f"wrote {len(files)} files to {out}: {', '.join(Path(v).name for v in files.values())}",
            highlight=False, soft_wrap=True)
    return 0
