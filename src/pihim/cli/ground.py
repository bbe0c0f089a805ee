"""``pihim ground``: ground and mirror-reflected-ground polarization from every camera direction.

For each camera direction on the upper hemisphere (zenith x azimuth grid,
from the observed point toward the camera) this computes, in the image frame
of a zero-roll camera looking at the point (AoP counter-clockwise from image
right, as displayed):

* the Stokes vector of the light leaving the rough ground (Torrance-Sparrow
  microfacets lit by the sun and the sky; the paper's Fig. 5c);
* the light from a mirror with the given normal at that point, where it shows
  the ground (the paper's Fig. 5d); NaN where it shows sky or faces away;
* their axial AoP difference, in [0, 90] deg (usable when > 50 deg), and the
  paper's raw difference ``|AoP_mirror - AoP_ground|`` in [0, 180).

Outputs (as one group: all or none) in ``--out``: ``ground-dolp.png``, ``ground-aop.png``,
``mirror-aop.png``, ``aop-difference.png`` (polar plots, North up, azimuth
clockwise, radius = camera zenith) and ``ground-maps.npz`` with the float
arrays; with ``--monte-carlo`` also the paper's Monte Carlo ground map
(``ground-aop-mc.png`` and ``mc_*`` arrays in the npz, Stokes per bin frame).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
import typer

from pihim._atomic import write_group
from pihim._resources import require_memory
from pihim.cli._common import check_out_dir, emit_json, output_dir, stderr_console
from pihim.cli.sky import resolve_sun
from pihim.errors import PihimInputError

if TYPE_CHECKING:
    from pihim.surfaces.ground import GroundModel
from pihim.polarimetry.frames import normalize
from pihim.polarimetry.stokes import aop_difference_deg, aop_raw_difference_deg
from pihim.scenarios import GROUND_AOP_DIFFERENCE_MIN_DEG, image_right, mirror_reflection, to_image_frame
from pihim.sky.model import SkyModel, with_horizontal_irradiance
from pihim.sky.sun import direction_from_angles, require_daylight
from pihim.surfaces.mirror import mirror_model
from pihim.visualize import polar_map_png

SCHEMA_ID = "pihim.ground/1"
#: Peak bytes per map direction, maps and polar plots: the peak resident size of a whole ``pihim ground`` run
#: grows by 877 B per direction (0.5 and 0.25 deg grids, ``benchmarks/memory_estimates_quality.py``);
#: with a 15 % margin.
MAP_BYTES_PER_DIRECTION = 1000
#: Monte Carlo microfacets without ``--facets``.
MC_DEFAULT_FACETS = 100_000
#: Peak bytes per Monte Carlo microfacet: 634 B measured the same way (1e6 and 3e6 facets), with a 15 % margin.
MC_BYTES_PER_FACET = 730
AOP_REFERENCE = (
    "image AoP in [0, 180) deg: counter-clockwise from image right as displayed, for a zero-roll camera "
    "at the map direction looking at the observed point"
)


def _maps(
    ground: GroundModel, sky: SkyModel, mirror: Any, sun: np.ndarray, normal: np.ndarray, resolution: float
) -> dict[str, np.ndarray]:
    from pihim.surfaces.ground import hemisphere_grid  # numba kernels: loaded when a map is made

    grid = hemisphere_grid(resolution)
    v = grid.directions  # from the point toward the camera
    s_g, e_g = ground.stokes(v, sun, sky)
    right = image_right(v, np.zeros(3))
    _, g_dolp, g_aop = to_image_frame(s_g, v, e_g, right)
    refl = mirror_reflection(50.0 * v, np.zeros(3), normal, sun, sky, mirror, ground=ground)
    shows_ground = refl.facing & ~refl.shows_sky
    m_aop = np.where(shows_ground, refl.aop_deg, np.nan)
    m_dolp = np.where(shows_ground, refl.dolp, np.nan)
    return {
        "zenith_deg": grid.zenith_deg,
        "azimuth_deg": grid.azimuth_deg,
        "ground_dolp": g_dolp,
        "ground_aop_deg": g_aop,
        "ground_s0": s_g[..., 0],
        "mirror_dolp": m_dolp,
        "mirror_aop_deg": m_aop,
        "aop_difference_deg": np.where(shows_ground, aop_difference_deg(m_aop, g_aop), np.nan),
        "aop_raw_difference_deg": np.where(shows_ground, aop_raw_difference_deg(m_aop, g_aop), np.nan),
    }


def _summary(maps: dict[str, np.ndarray]) -> dict[str, Any]:
    diff = maps["aop_difference_deg"]
    ok = np.isfinite(diff)
    out: dict[str, Any] = {
        "fraction_mirror_shows_ground": float(ok.mean()),
        "fraction_usable": float((diff[ok] > GROUND_AOP_DIFFERENCE_MIN_DEG).sum() / diff.size),
        "ground_dolp_median": float(np.nanmedian(maps["ground_dolp"])),
    }
    if ok.any():
        i, j = np.unravel_index(np.nanargmax(diff), diff.shape)
        out["max_aop_difference"] = {
            "value_deg": float(diff[i, j]),
            "camera_zenith_deg": float(maps["zenith_deg"][i]),
            "camera_azimuth_deg": float(maps["azimuth_deg"][j]),
        }
    else:
        out["max_aop_difference"] = None
    return out


def ground(
    out: Annotated[Path, typer.Option("--out", help="Output directory.")],
    time: Annotated[str | None, typer.Option(help="ISO 8601 time with UTC offset.")] = None,
    site: Annotated[str | None, typer.Option(help="With --time: nsttf (default) or LAT,LON,H.")] = None,
    sun_zenith: Annotated[float | None, typer.Option(help="Sun zenith, deg in [0, 90].")] = None,
    sun_azimuth: Annotated[float | None, typer.Option(help="Sun azimuth, deg clockwise from North.")] = None,
    model: Annotated[str, typer.Option(help="Sky polarization model: rayleigh or berry.")] = "rayleigh",
    dmax: Annotated[float, typer.Option(help="Maximum sky DoLP, in [0, 1].")] = 0.8,
    sky_irradiance: Annotated[float, typer.Option(help="Diffuse horizontal sky irradiance, W m^-2.")] = 100.0,
    sun_irradiance: Annotated[float, typer.Option(help="Direct normal sun irradiance, W m^-2.")] = 1000.0,
    sigma: Annotated[float, typer.Option(help="Microfacet zenith spread (half-Gaussian width), deg.")] = 15.0,
    refractive_index: Annotated[float, typer.Option(help="Ground refractive index (paper: 1.45).")] = 1.45,
    diffuse_albedo: Annotated[float, typer.Option(help="Albedo of the depolarized Lambertian part, [0, 1].")] = 0.0,
    mirror: Annotated[str, typer.Option(help="Mirror model: second-surface, ideal or fresnel.")] = "second-surface",
    mirror_normal_zenith: Annotated[float, typer.Option(help="Mirror normal zenith, deg.")] = 60.0,
    mirror_normal_azimuth: Annotated[float, typer.Option(help="Mirror normal azimuth, deg clockwise from North.")] = 180.0,
    resolution: Annotated[float, typer.Option(help="Map grid step, deg (must divide 90).")] = 1.0,
    monte_carlo: Annotated[bool, typer.Option("--monte-carlo", help="Also run the paper's Monte Carlo ground map.")] = False,
    facets: Annotated[int | None, typer.Option(help="Monte Carlo microfacets (with --monte-carlo; default 100000).", show_default=False)] = None,
    seed: Annotated[int | None, typer.Option(help="Monte Carlo seed (with --monte-carlo; default 0).", show_default=False)] = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")] = False,
) -> int:
    """Ground and mirror-reflected-ground AoP/DoLP maps over camera directions (paper Fig. 5c-d)."""
    if not (math.isfinite(sigma) and 0 < sigma <= 90):
        raise PihimInputError(f"--sigma must be a number of degrees in (0, 90], got {sigma:g}")
    if not (math.isfinite(mirror_normal_zenith) and 0.0 <= mirror_normal_zenith <= 90.0):
        raise PihimInputError(f"--mirror-normal-zenith must be in [0, 90] deg, got {mirror_normal_zenith:g}")
    if not (math.isfinite(mirror_normal_azimuth) and -360.0 <= mirror_normal_azimuth <= 360.0):
        raise PihimInputError(f"--mirror-normal-azimuth must be in [-360, 360] deg, got {mirror_normal_azimuth:g}")
    normal_azimuth = mirror_normal_azimuth % 360.0
    normal_azimuth = 0.0 if normal_azimuth >= 360.0 else normal_azimuth  # a tiny negative rounds up to 360.0
    if not (math.isfinite(resolution) and resolution > 0 and abs(90.0 / resolution - round(90.0 / resolution)) < 1e-9):
        raise PihimInputError(f"--resolution must divide 90 deg, got {resolution:g}")
    if not monte_carlo and (facets is not None or seed is not None):
        given = " and ".join(o for o, v in (("--facets", facets), ("--seed", seed)) if v is not None)
        raise PihimInputError(f"{given} set the Monte Carlo ground map: add --monte-carlo")
    facets = MC_DEFAULT_FACETS if facets is None else facets
    seed = 0 if seed is None else seed
    if facets < 1:
        raise PihimInputError(f"--facets must be >= 1, got {facets}")
    if seed < 0:
        raise PihimInputError(f"--seed must be a non-negative integer, got {seed}")
    n_dirs = round(90.0 / resolution) * round(360.0 / resolution)
    require_memory(n_dirs * MAP_BYTES_PER_DIRECTION, f"--resolution {resolution:g} ({n_dirs:.3g} directions)")
    if monte_carlo:
        require_memory(facets * MC_BYTES_PER_FACET + n_dirs * MAP_BYTES_PER_DIRECTION,
                       f"--monte-carlo --facets {facets:g}")
    from pihim.surfaces.ground import GroundModel

    try:
        ground_model = GroundModel(sigma_deg=sigma, refractive_index=refractive_index, diffuse_albedo=diffuse_albedo,
                                   sun_irradiance=sun_irradiance)
    except PihimInputError as exc:  # the library's parameter names -> this command's options
        text = str(exc)
        for name in ("refractive_index", "diffuse_albedo", "sun_irradiance"):
            text = text.replace(name, "--" + name.replace("_", "-"))
        raise PihimInputError(text) from None
    mirror_obj = mirror_model(mirror)  # type: ignore[arg-type]
    sun, when = resolve_sun(time, site, sun_zenith, sun_azimuth)
    require_daylight(sun, what="pihim ground")
    sky = with_horizontal_irradiance(SkyModel(kind=model, dmax=dmax), sun.vector, sky_irradiance)  # type: ignore[arg-type]
    check_out_dir(out)
    normal = normalize(direction_from_angles(mirror_normal_zenith, mirror_normal_azimuth))
    with stderr_console().status("pihim ground: computing the ground and mirror maps ..."):
        maps = _maps(ground_model, sky, mirror_obj, sun.vector, normal, resolution)
    # everything is computed (and so validated) before the first file is written
    mc = None
    if monte_carlo:
        with stderr_console().status(f"pihim ground: Monte Carlo over {facets:,} microfacets ..."):
            mc = ground_model.monte_carlo(sun.vector, sky, n_facets=facets, bin_deg=resolution, seed=seed)
    title = f"sun zen {float(sun.zenith_deg):.1f} az {float(sun.azimuth_deg):.1f}, sigma {sigma:g}"
    sun_marker = ((float(sun.azimuth_deg), float(sun.zenith_deg), "*", "sun"),)
    plots = {  # key: (file, values, style, colour-bar label, title)
        "ground_dolp_png": ("ground-dolp.png", maps["ground_dolp"], "dolp", "ground DoLP", "ground DoLP"),
        "ground_aop_png": ("ground-aop.png", maps["ground_aop_deg"], "aop", "ground AoP (deg, image frame)",
                           "ground AoP"),
        "mirror_aop_png": ("mirror-aop.png", maps["mirror_aop_deg"], "aop",
                           "mirror-reflected ground AoP (deg, image frame)", "mirror AoP"),
        "aop_difference_png": ("aop-difference.png", maps["aop_difference_deg"], "aop_difference",
                               "axial AoP difference (deg)", "AoP difference"),
    }
    arrays = dict(maps)
    if mc is not None:
        arrays.update(mc_counts=mc.counts, mc_stokes=mc.stokes, mc_stderr=mc.stderr,
                      mc_dolp=mc.dolp, mc_aop_local_meridian_deg=mc.aop_deg)
        plots["mc_dolp_png"] = ("ground-dolp-mc.png", mc.dolp, "dolp", "ground DoLP (Monte Carlo)", "MC ground DoLP")
    files = {key: out / spec[0] for key, spec in plots.items()}
    files["npz"] = out / "ground-maps.npz"

    def plot(spec: tuple) -> Callable[[Path], Any]:
        _, values, style, label, head = spec
        return lambda p: polar_map_png(values, p, style=style, label=label, title=f"{head} -- {title}",
                                       markers=sun_marker, atomic=False)

    # all files or none (a full disk used to leave the first plots without the rest)
    with output_dir(out):
        write_group({**{files[key]: plot(spec) for key, spec in plots.items()},
                     files["npz"]: lambda p: np.savez_compressed(p, **arrays, aop_reference=np.str_(AOP_REFERENCE))})
    if json_out:
        emit_json({
            "schema": SCHEMA_ID,
            "sun": sun.as_dict(),
            **when,
            "sky": sky.describe(),
            "ground": {"sigma_deg": sigma, "refractive_index": refractive_index, "diffuse_albedo": diffuse_albedo,
                       "sun_irradiance_w_m2": sun_irradiance, "sky_irradiance_w_m2": sky_irradiance},
            "mirror": {"model": mirror.strip().lower(), "normal_zenith_deg": mirror_normal_zenith,
                       "normal_azimuth_deg": normal_azimuth},
            "resolution_deg": resolution,
            "monte_carlo": {"facets": facets, "seed": seed} if monte_carlo else None,
            **_summary(maps),
            "aop_reference": AOP_REFERENCE,
            "files": {k: str(p) for k, p in files.items()},
        })
    else:
        summ = _summary(maps)
        best = summ["max_aop_difference"]
        best_text = "" if best is None else (f", largest AoP difference {best['value_deg']:.0f} deg (camera zenith "
                                             f"{best['camera_zenith_deg']:.0f}, azimuth "
                                             f"{best['camera_azimuth_deg']:.0f} deg)")
        stderr_console().print(
            f"pihim ground: sun zenith {float(sun.zenith_deg):.1f} deg, azimuth {float(sun.azimuth_deg):.1f} deg; "
            f"the mirror shows ground in {100 * summ['fraction_mirror_shows_ground']:.0f} % of camera directions, "
            f"ground-vs-ground usable in {100 * summ['fraction_usable']:.0f} %{best_text}\n"
            f"wrote {len(files)} files to {out}: {', '.join(Path(v).name for v in files.values())}",
            highlight=False, soft_wrap=True)
    return 0
