"""Speed benchmark of the polarimetric renderer (issue 8), with Mitsuba 3 side by side.

Part (a), the issue's frame: the UFACET view of heliostat 8E3 with its target
7E3 at NSTTF, 2021-05-13T13:00-06:00, aim point ``UFACET_AIM_POINT``: the
plan of :func:`pihim.planning.pipeline.build_plan` (HUA 8E3 only, no
contrast shift) gives the scan waypoint of the (8E3, 7E3) image, whose
:meth:`CameraPose.from_waypoint` is the camera; the scene is the whole
tracked NSTTF-like field (:func:`field_scene`: 218 heliostats' facets, back
structure, tower, ground plane), the light :meth:`Environment.clear_sky` (sun,
Rayleigh sky, rough ground, second-surface silvered glass); the camera is the
default :class:`CameraModel` (Triton 2448 x 2048, 35 mm) and
``RenderSettings()`` (the defaults: 3 x 3 rays at edge pixels, 2 bounces).

* **first frame**: the first :func:`render_frame` call in the process,
  which includes numba's JIT compile or its load from numba's on-disk cache
  (``hit``/``miss``, counted over every numba dispatcher of ``pihim.render``);
* **frame**: median, p10 and p90 over ``repeat`` further calls (after
  ``warmup`` untimed calls, the first one included);
* **rays/s**: ``stats["rays"]`` (camera rays: one per pixel plus ``n^2``
  per edge pixel; mirror bounces and shadow rays are not counted) divided by
  the median frame time;
* **peak RSS**: the process's resident-set high-water mark (``VmHWM``, reset
  through ``/proc/self/clear_refs`` before each timed frame), the largest
  over the timed frames: everything the process holds (interpreter, numba,
  scene, numpy and numba scratch). **Traced peak**: ``tracemalloc`` peak
  above the start of one extra call (Python and numpy allocations only, see
  :func:`_harness.traced_peak`; not with ``--quick``).

Targets (issue 8): <= 5 s per frame, <= 4 GB.

Part (b), side by side with Mitsuba 3 on a scene both render: the 25 facets
of 8E3 as tracked at the same instant (design canting), alone, as 25 mirror
rectangles of plain glass (Fresnel n = 1.5) under a uniform unpolarized sky
of radiance 1 above the horizon, nothing else, seen by a 256 x 256 pinhole
camera (26 deg field of view) 16 m from the mirror centre at 50 deg
incidence, off the mirror's vertical plane, no roll.

* pihim: ``render_frame`` with ``Environment(sky=SkyModel(dmax=0,
  radiance="uniform"), ground=None, mirror=FresnelMirror(n=1.5),
  sun_irradiance_w_m2=0)``, ``RenderSettings()`` (the defaults: 3 x 3 rays at edge pixels, 2 bounces).
  pihim's sky is zero below the horizon.
* Mitsuba (``scalar_spectral_polarized``): ``stokes`` around ``path``
  (``max_depth = 2``), ``constant`` emitter (flat spectrum 1), the 25 facets
  as ``rectangle`` shapes with a ``conductor`` BSDF ``eta = 1.5, k = 0``
  (only reflects: the dielectric interface's reflection), and a black
  ``conductor`` (``specular_reflectance = 0``) plane 200 km wide at the
  ground standing in for pihim's zero radiance below the horizon;
  ``perspective`` sensor with the same field of view and orientation,
  ``independent`` sampler, box filter. Timed at 16 and 256 samples per
  pixel (``--quick``: 16 only; 256 is then extrapolated x16 and marked so).
* Rays: pihim's ``stats["rays"]`` as in (a). Mitsuba's *camera samples*
  are ``pixels x spp`` (exact); its *ray casts* are estimated as
  ``pixels x spp x (1 + f)``, ``f`` the fraction of pixels whose camera ray
  hits a facet (from pihim's label image of the same view): every sample
  casts its camera ray, a sample that hits a facet casts the reflected ray,
  and nothing else is cast (the BSDFs are smooth, so there is no emitter
  sampling; the ground's zero throughput ends its paths). pihim's ray casts
  are estimated the same way (camera rays x (1 + mean mirror bounces)).
* Agreement: Mitsuba's Stokes images are mapped into pihim's image frame
  (``tests/render/test_mitsuba_oracle.py``: Mitsuba's reference axis is
  ``normalize(ray x camera up)``, its S2 handedness is pihim's; one small
  per-pixel rotation of the reference axis). Compared on facet-interior pixels (pihim
  sees a facet reflecting the sky, no supersampling, both S0 > 0): DoLP,
  axial AoP difference, and reflectance (Mitsuba's S0 divided by the mean
  S0 of the bare sky rendered with the same sensor: the G channel of a flat
  spectrum is not exactly 1).

Run ``python benchmarks/run.py --only bench_render`` or this file directly
(``--no-mitsuba`` skips Mitsuba; ``--mitsuba-spp 16,64,256`` sets its runs).
"""

from __future__ import annotations

import math
import os
import platform
import resource
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _harness as harness

COUNTS = harness.Counts(repeat=3, warmup=1, quick_repeat=1, quick_warmup=1, cap_quick=True)
RESULTS_PATH = Path(__file__).resolve().parent / "results" / "render.json"
TIME_ISO = "2021-05-13T13:00-06:00"
HUA, TARGET = "8E3", "7E3"
TARGET_FRAME_S = 5.0
TARGET_PEAK_GB = 4.0
SIDE_PX = 256
SIDE_FOV_DEG = 26.0
SIDE_DISTANCE_M = 16.0
SIDE_INCIDENCE_DEG = 50.0
SIDE_OFF_PLANE_DEG = 40.0  # direction of the camera in the mirror plane, from the heliostat x axis toward y
SIDE_INDEX = 1.5
SIDE_REPEAT = 5
MITSUBA_SPP = (16, 256)
MITSUBA_VARIANT = "scalar_spectral_polarized"
GROUND_HALF_WIDTH_M = 1.0e5


# ---------------------------------------------------------------------------
# Memory and numba helpers
# ---------------------------------------------------------------------------
def _status_kb(key: str) -> int | None:
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return None


def _reset_peak_rss() -> bool:
    """Reset the process's RSS high-water mark (Linux >= 4.0); False if not possible."""
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _peak_rss_mb() -> float:
    """``VmHWM`` (since the last reset) in MB, else the process-lifetime ``ru_maxrss``."""
    hwm = _status_kb("VmHWM")
    if hwm is None:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3
    return hwm / 1e3


def _render_dispatchers() -> list[Any]:
    """Every numba dispatcher defined at module level in ``pihim.render`` (robust to renamed kernels)."""
    from numba.core.dispatcher import Dispatcher

    found: dict[int, Any] = {}
    for name, mod in list(sys.modules.items()):
        if name.startswith("pihim.render") and mod is not None:
            for obj in vars(mod).values():
                if isinstance(obj, Dispatcher):
                    found[id(obj)] = obj
    return list(found.values())


def _cache_counts(dispatchers: Sequence[Any]) -> tuple[int, int]:
    hits = sum(sum(d.stats.cache_hits.values()) for d in dispatchers)
    misses = sum(sum(d.stats.cache_misses.values()) for d in dispatchers)
    return hits, misses


def _cache_status(dispatchers: Sequence[Any], before: tuple[int, int]) -> str:
    if not dispatchers or all(d.stats.cache_path is None for d in dispatchers):
        return "off"
    hits, misses = (now - then for now, then in zip(_cache_counts(dispatchers), before, strict=True))
    if not hits and not misses:
        return "already loaded"
    return "hit" if not misses else ("miss" if not hits else "partial miss")


def _quiet(wait_quiet_s: float) -> None:
    if wait_quiet_s > 0:
        harness.wait_for_quiet(wait_quiet_s)


# ---------------------------------------------------------------------------
# Part (a): the issue's NSTTF frame
# ---------------------------------------------------------------------------
def nsttf_setup() -> dict[str, Any]:
    """Plan, camera pose, tracked field scene and clear-sky environment of the UFACET 8E3/7E3 image."""
    from pihim.camera.model import CameraModel
    from pihim.camera.pose import CameraPose
    from pihim.field import UFACET_AIM_POINT, nsttf_like_field, track_field
    from pihim.planning.pipeline import build_plan
    from pihim.render.scene import field_scene
    from pihim.render.shading import Environment
    from pihim.sky.sun import NSTTF, parse_time, sun_position

    t0 = time.perf_counter()
    t = parse_time(TIME_ISO)
    sp = sun_position(NSTTF, t)
    field = nsttf_like_field()
    plan = build_plan(field, t, NSTTF, aim_point=UFACET_AIM_POINT, heliostats=[HUA], shift=False)
    hits = [(p, pr) for p in plan.passes for pr in p.predictions if pr.hua == HUA and pr.target == TARGET]
    if not hits:
        raise RuntimeError(f"the plan has no image of the pair ({HUA}, {TARGET})")
    scan_pass, pred = hits[0]
    wp = scan_pass.waypoints[pred.waypoint_index]
    t_plan = time.perf_counter() - t0
    t1 = time.perf_counter()
    tracked = track_field(field, sp.vector, UFACET_AIM_POINT)
    scene = field_scene(tracked)
    env = Environment.clear_sky(sp.vector)
    t_scene = time.perf_counter() - t1
    return {
        "scene": scene,
        "camera": CameraModel(),
        "pose": CameraPose.from_waypoint(wp),
        "env": env,
        "tracked": tracked,
        "sun": sp.vector,
        "info": {
            "time": TIME_ISO,
            "pair": [HUA, TARGET],
            "waypoint": {"x_m": wp.x_m, "y_m": wp.y_m, "z_m": wp.z_m, "heading_deg": wp.heading_deg,
                         "gimbal_pitch_deg": wp.gimbal_pitch_deg},
            "rectangles": int(scene.n_rectangles),
            "heliostats": len(field.names),
            "plan_s": t_plan,
            "scene_build_s": t_scene,
        },
    }


def bench_nsttf(setup: dict[str, Any], repeat: int, warmup: int, trace: bool, wait_quiet_s: float) -> dict[str, Any]:
    from pihim.render.frame import RenderSettings, render_frame

    settings = RenderSettings()

    def frame():
        return render_frame(setup["scene"], setup["camera"], setup["pose"], setup["env"], settings)

    import pihim.render.frame  # noqa: F401 - make sure every renderer module is imported

    dispatchers = _render_dispatchers()
    before = _cache_counts(dispatchers)
    rss_before = _peak_rss_mb()
    _quiet(wait_quiet_s)
    t0 = time.perf_counter()
    first_fr = frame()
    first_s = time.perf_counter() - t0
    cache = _cache_status(_render_dispatchers(), before)
    for _ in range(max(0, warmup - 1)):
        frame()
    samples, peaks, loads = [], [], []
    last = first_fr
    for _ in range(repeat):
        _quiet(wait_quiet_s)  # before every frame: each one takes seconds
        reset = _reset_peak_rss()
        start = harness.cpu_times()
        t0 = time.perf_counter()
        last = frame()
        samples.append(time.perf_counter() - t0)
        loads.append(harness.other_cpu_load(start, harness.cpu_times()))
        peaks.append(_peak_rss_mb() if reset else None)
    median, p10, p90 = (float(v) for v in np.percentile(samples, [50, 10, 90]))
    traced_mb = None
    if trace:
        peak, _ = harness.traced_peak(frame)
        traced_mb = peak / 1e6
    stats = dict(last.stats)
    labels = last.labels
    bounces = labels[..., 6]
    peak_rss = max((p for p in peaks if p is not None), default=None)
    return {
        "first_call_s": first_s,
        "first_call_cache": cache,
        "first_call_rays_per_second": first_fr.stats["rays"] / first_s,
        "median_s": median,
        "p10_s": p10,
        "p90_s": p90,
        "samples_s": samples,
        "repeat": repeat,
        "warmup": warmup,
        "other_cpu_load": max((v for v in loads if v is not None), default=None),
        "rays": int(stats["rays"]),
        "rays_per_second": stats["rays"] / median,
        "supersampled_pixels": int(stats["supersampled_pixels"]),
        "supersample": int(stats["supersample"]),
        "seconds_primary_last": float(stats.get("seconds_primary", float("nan"))),
        "direct_kind_pixels": stats.get("direct_kind_pixels"),
        "mean_mirror_bounces_per_pixel": float(bounces.mean()),
        "peak_rss_mb": peak_rss if peak_rss is not None else _peak_rss_mb(),
        "peak_rss_kind": "VmHWM per frame" if peak_rss is not None else "process lifetime ru_maxrss",
        "rss_before_mb": rss_before,
        "traced_peak_mb": traced_mb,
        "numba_dispatchers": len(dispatchers),
    }


# ---------------------------------------------------------------------------
# Part (b): one heliostat, pihim and Mitsuba
# ---------------------------------------------------------------------------
def side_setup(tracked: Any) -> dict[str, Any]:
    """The 25 facets of the HUA as rectangles, the oblique 256 x 256 view and the uniform-sky environment."""
    from pihim.camera.model import CameraModel
    from pihim.camera.pose import CameraPose
    from pihim.render.scene import FACET, rectangle_scene
    from pihim.render.shading import Environment
    from pihim.sky.model import SkyModel
    from pihim.surfaces.mirror import FresnelMirror

    i = list(tracked.field.names).index(HUA)
    corners = tracked.facet_corners()[i]  # (F, 4, 3): TL, TR, BR, BL seen from the front
    origin = corners[:, 3]
    edge_u = corners[:, 2] - origin
    edge_v = corners[:, 0] - origin
    scene = rectangle_scene(origin, edge_u, edge_v, FACET)
    n = tracked.normals[i]
    frame = tracked.rotations[i]  # columns x, y, z
    c = tracked.mirror_centres[i]
    inc, off = math.radians(SIDE_INCIDENCE_DEG), math.radians(SIDE_OFF_PLANE_DEG)
    toward_camera = math.cos(inc) * n + math.sin(inc) * (math.cos(off) * frame[:, 0] + math.sin(off) * frame[:, 1])
    position = c + SIDE_DISTANCE_M * toward_camera
    focal_mm = SIDE_PX * 3.45e-3 / 2.0 / math.tan(math.radians(SIDE_FOV_DEG / 2.0))
    camera = CameraModel(SIDE_PX, SIDE_PX, pixel_size_um=3.45, focal_length_mm=focal_mm)
    env = Environment(sun_dir=(0.0, 0.0, 1.0), sky=SkyModel(dmax=0.0, radiance="uniform"), ground=None,
                      mirror=FresnelMirror(n=SIDE_INDEX), sun_irradiance_w_m2=0.0)
    gz = np.asarray(getattr(tracked.field, "ground_z", 0.0), float)  # per heliostat, or one level
    ground_z = float(gz[i] if gz.ndim else gz)
    return {"scene": scene, "camera": camera, "pose": CameraPose.look_at(position, c), "env": env,
            "rectangles": (origin, edge_u, edge_v), "ground_z": ground_z,
            "info": {"camera_position_m": position.tolist(), "mirror_centre_m": c.tolist(),
                     "focal_length_mm": focal_mm, "fov_deg": SIDE_FOV_DEG, "pixels": SIDE_PX * SIDE_PX}}


def _mitsuba():
    try:
        import mitsuba as mi
    except ImportError:
        return None, "mitsuba is not installed"
    if MITSUBA_VARIANT not in mi.variants():
        return None, f"Mitsuba has no {MITSUBA_VARIANT} variant (has {', '.join(mi.variants())})"
    mi.set_variant(MITSUBA_VARIANT)
    return mi, ""


def _mitsuba_scene(mi, side: dict[str, Any], *, shapes: bool = True):
    camera, pose = side["camera"], side["pose"]
    right, down, forward = np.asarray(pose.rotation, float)
    c = np.asarray(pose.position_m, float)
    t4 = mi.ScalarTransform4f
    fov_x = 2.0 * math.degrees(math.atan(0.5 * camera.width_px / camera.fx_px))
    desc: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "stokes", "inner": {"type": "path", "max_depth": 2}},
        "sensor": {
            "type": "perspective",
            "fov": fov_x,
            "fov_axis": "x",
            "to_world": t4().look_at(origin=c.tolist(), target=(c + forward).tolist(), up=(-down).tolist()),
            "film": {"type": "hdrfilm", "width": camera.width_px, "height": camera.height_px,
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent"},
        },
        "sky": {"type": "constant", "radiance": {"type": "spectrum", "value": 1.0}},
    }
    if shapes:
        origin, edge_u, edge_v = side["rectangles"]
        for k in range(len(origin)):
            m = np.eye(4)
            nrm = np.cross(edge_u[k], edge_v[k])
            m[:3, 0], m[:3, 1], m[:3, 2] = edge_u[k] / 2, edge_v[k] / 2, nrm / np.linalg.norm(nrm)
            m[:3, 3] = origin[k] + (edge_u[k] + edge_v[k]) / 2
            desc[f"facet_{k:02d}"] = {"type": "rectangle", "to_world": t4(m.tolist()),
                                      "bsdf": {"type": "conductor", "eta": SIDE_INDEX, "k": 0.0}}
        g = np.diag([GROUND_HALF_WIDTH_M, GROUND_HALF_WIDTH_M, 1.0, 1.0])
        g[2, 3] = side["ground_z"]
        desc["black_ground"] = {"type": "rectangle", "to_world": t4(g.tolist()),
                                "bsdf": {"type": "conductor", "specular_reflectance": {"type": "spectrum",
                                                                                       "value": 0.0}}}
    return mi.load_dict(desc)


def _mitsuba_stokes(mi, scene, img: np.ndarray, side: dict[str, Any]) -> np.ndarray:
    """(H, W, 3) Stokes (G channel) mapped into pihim's image frame."""
    from pihim.polarimetry.frames import change_reference, normalize

    names = list(scene.integrator().aov_names())
    first = img.shape[-1] - len(names)
    s = np.stack([img[..., first + names.index(f"S{k}.G")] for k in range(3)], axis=-1).astype(float)
    camera, pose = side["camera"], side["pose"]
    right, down, _ = np.asarray(pose.rotation, float)
    jj, ii = np.meshgrid(np.arange(camera.width_px, dtype=float), np.arange(camera.height_px, dtype=float))
    d = camera.pixel_rays(jj, ii) @ np.asarray(pose.rotation, float)
    e_mi = normalize(np.cross(d, -down))
    e_pi = normalize(right - (d @ right)[..., None] * d)
    s4 = np.concatenate([s, np.zeros(s.shape[:-1] + (1,))], axis=-1)
    return change_reference(s4, -d, e_mi, e_pi)[..., :3]


def _agreement(fr: Any, s_mi: np.ndarray, sky_level: float) -> dict[str, Any]:
    from pihim.polarimetry import aop_deg, aop_difference_deg, dolp
    from pihim.render.paths import MIRROR, SKY

    s_pi = np.stack([fr.s0, fr.s1, fr.s2], axis=-1).astype(float)
    lab = fr.labels
    interior = ((lab[..., 0] == MIRROR) & (lab[..., 3] == SKY) & ~fr.supersampled & (s_pi[..., 0] > 0)
                & (s_mi[..., 0] > 0))
    p_pi, p_mi = dolp(*np.moveaxis(s_pi, -1, 0)), dolp(*np.moveaxis(s_mi, -1, 0))
    a_pi, a_mi = aop_deg(s_pi[..., 1], s_pi[..., 2]), aop_deg(s_mi[..., 1], s_mi[..., 2])
    da = aop_difference_deg(a_pi, a_mi)[interior]
    dp = np.abs(p_pi - p_mi)[interior]
    refl_mi = s_mi[..., 0] / sky_level
    d_s0 = np.abs(s_pi[..., 0] - refl_mi)
    return {
        "interior_pixels": int(interior.sum()),
        "dolp_mean_pihim": float(p_pi[interior].mean()),
        "dolp_mean_mitsuba": float(p_mi[interior].mean()),
        "dolp_abs_diff_mean": float(dp.mean()),
        "dolp_abs_diff_max": float(dp.max()),
        "aop_mean_pihim_deg": float(a_pi[interior].mean()),
        "aop_axial_diff_mean_deg": float(da.mean()),
        "aop_axial_diff_max_deg": float(da.max()),
        "reflectance_pihim": float(s_pi[..., 0][interior].mean()),
        "reflectance_mitsuba": float(refl_mi[interior].mean()),
        "s0_abs_diff_mean_all_pixels": float(d_s0.mean()),
        "s0_abs_diff_mean_edge_pixels": float(d_s0[fr.supersampled].mean()) if fr.supersampled.any() else None,
        "mitsuba_sky_level_g": sky_level,
    }


def bench_side(side: dict[str, Any], quick: bool, spp_list: Sequence[int], use_mitsuba: bool,
               wait_quiet_s: float) -> dict[str, Any]:
    from pihim.render.frame import RenderSettings, render_frame
    from pihim.render.paths import MIRROR

    settings = RenderSettings()

    def frame():
        return render_frame(side["scene"], side["camera"], side["pose"], side["env"], settings)

    fr = frame()  # warm-up (the kernels are already compiled by part (a))
    _quiet(wait_quiet_s)
    samples_ms, load = harness.time_calls(frame, 3 if quick else SIDE_REPEAT)
    median = float(np.median(samples_ms)) / 1e3
    labels = fr.labels
    f_mirror = float(np.mean(labels[..., 0] == MIRROR))
    pix = side["camera"].width_px * side["camera"].height_px
    out: dict[str, Any] = {
        "info": side["info"],
        "pihim": {
            "median_s": median,
            "p10_s": float(np.percentile(samples_ms, 10)) / 1e3,
            "p90_s": float(np.percentile(samples_ms, 90)) / 1e3,
            "repeat": len(samples_ms),
            "other_cpu_load": load,
            "rays": int(fr.stats["rays"]),
            "rays_per_second": fr.stats["rays"] / median,
            "ray_casts_estimate": fr.stats["rays"] * (1.0 + float(labels[..., 6].mean())),
            "supersampled_pixels": int(fr.stats["supersampled_pixels"]),
            "supersample": int(fr.stats["supersample"]),
        },
        "facet_pixel_fraction": f_mirror,
        "mitsuba": None,
        "mitsuba_skipped": "",
    }
    out["pihim"]["ray_casts_per_second"] = out["pihim"]["ray_casts_estimate"] / median
    if not use_mitsuba:
        out["mitsuba_skipped"] = "--no-mitsuba"
        return out
    mi, why = _mitsuba()
    if mi is None:
        out["mitsuba_skipped"] = why
        return out
    t0 = time.perf_counter()
    scene = _mitsuba_scene(mi, side)
    load_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    mi.render(scene, spp=1)  # warm-up: first render of the process
    warm_s = time.perf_counter() - t0
    bare = _mitsuba_scene(mi, side, shapes=False)
    bare_img = np.array(mi.render(bare, spp=16), dtype=float)
    names = list(bare.integrator().aov_names())
    sky_level = float(bare_img[..., bare_img.shape[-1] - len(names) + names.index("S0.G")].mean())
    runs = []
    img = None
    for spp in spp_list:
        _quiet(wait_quiet_s)
        start = harness.cpu_times()
        t0 = time.perf_counter()
        img = np.array(mi.render(scene, spp=spp), dtype=float)
        sec = time.perf_counter() - t0
        samples = pix * spp
        casts = samples * (1.0 + f_mirror)
        runs.append({"spp": spp, "seconds": sec, "measured": True, "camera_samples": samples,
                     "samples_per_second": samples / sec, "ray_casts_estimate": casts,
                     "ray_casts_per_second": casts / sec,
                     "other_cpu_load": harness.other_cpu_load(start, harness.cpu_times())})
    if 256 not in spp_list and runs:
        base = runs[0]
        scale = 256 / base["spp"]
        runs.append({"spp": 256, "seconds": base["seconds"] * scale, "measured": False,
                     "camera_samples": base["camera_samples"] * scale,
                     "samples_per_second": base["samples_per_second"],
                     "ray_casts_estimate": base["ray_casts_estimate"] * scale,
                     "ray_casts_per_second": base["ray_casts_per_second"], "other_cpu_load": None,
                     "extrapolated_from_spp": base["spp"]})
    s_mi = _mitsuba_stokes(mi, scene, img, side)
    out["mitsuba"] = {
        "version": mi.__version__,
        "variant": MITSUBA_VARIANT,
        "scene_load_s": load_s,
        "first_render_1spp_s": warm_s,
        "runs": runs,
        "agreement_spp": spp_list[-1],
        "agreement": _agreement(fr, s_mi, sky_level),
    }
    return out


# ---------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------
def machine_info() -> dict[str, Any]:
    import numba

    return {
        "cpu_model": harness.cpu_model(),
        "cpu_count": os.cpu_count(),
        "numba": numba.__version__,
        "numba_threads": numba.get_num_threads(),
        "numba_threading_layer": _threading_layer(),
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


def _threading_layer() -> str:
    import numba

    try:
        return str(numba.threading_layer())
    except ValueError:  # no parallel kernel run yet
        return "-"


def run_benchmark(repeat: int, warmup: int, quick: bool, *, mitsuba: bool = True,
                  mitsuba_spp: Sequence[int] | None = None, wait_quiet_s: float = 0.0) -> dict[str, Any]:
    setup = nsttf_setup()
    nsttf = bench_nsttf(setup, repeat, warmup, trace=not quick, wait_quiet_s=wait_quiet_s)
    side = side_setup(setup["tracked"])
    spp_list = tuple(mitsuba_spp) if mitsuba_spp else ((16,) if quick else MITSUBA_SPP)
    side_res = bench_side(side, quick, spp_list, mitsuba, wait_quiet_s)
    targets = [
        harness.target("NSTTF UFACET frame 2448x2048, median", nsttf["median_s"], TARGET_FRAME_S, "s"),
        harness.target("NSTTF UFACET frame, peak memory (RSS)", nsttf["peak_rss_mb"] / 1e3, TARGET_PEAK_GB, "GB"),
    ]
    return {
        "benchmark": "render",
        "settings": {"repeat": repeat, "warmup": warmup, "quick": quick, "mitsuba_spp": list(spp_list),
                     "wait_quiet_s": wait_quiet_s},
        "machine": machine_info(),
        "nsttf": {**setup["info"], **nsttf},
        "side_by_side": side_res,
        "targets": targets,
    }


def _f(x: Any, spec: str) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return format(x, spec)


def markdown_report(rep: dict[str, Any]) -> str:
    a = rep["nsttf"]
    wp = a["waypoint"]
    lines = [
        (f"(a) NSTTF UFACET view of {a['pair'][0]} (target {a['pair'][1]}), {a['time']}: whole field "
         f"({a['heliostats']} heliostats, {a['rectangles']:,} rectangles), camera at "
         f"({wp['x_m']:.1f}, {wp['y_m']:.1f}, {wp['z_m']:.1f}) m, heading {wp['heading_deg']:.1f} deg, pitch "
         f"{wp['gimbal_pitch_deg']:.1f} deg; 2448 x 2048, {a['supersample']} x {a['supersample']} rays at edge pixels, "
         f"2 bounces; {a['repeat']} timed frames "
         f"after {a['warmup']} warm-up. Plan {a['plan_s']:.2f} s, scene build (tracking + BVH) "
         f"{a['scene_build_s']:.2f} s."),
        "",
        "| Row | Median s | p10 s | p90 s | Camera rays | Rays/s | Peak RSS MB | Traced peak MB | Other CPU % |",
        "|---|--:|--:|--:|--:|--:|--:|--:|--:|",
        (f"| first frame (numba: {a['first_call_cache']}) | {a['first_call_s']:.2f} | | | {a['rays']:,} "
         f"| {a['first_call_rays_per_second']:,.0f} | | | |"),
        (f"| frame | {a['median_s']:.2f} | {a['p10_s']:.2f} | {a['p90_s']:.2f} | {a['rays']:,} "
         f"| {a['rays_per_second']:,.0f} | {a['peak_rss_mb']:,.0f} | {_f(a['traced_peak_mb'], ',.0f')} "
         f"| {harness.other_pct(a['other_cpu_load'])} |"),
        "",
        (f"Pixels by what they see: {a['direct_kind_pixels']}; {a['supersampled_pixels']:,} edge pixels "
         f"supersampled; mean mirror bounces per pixel path {a['mean_mirror_bounces_per_pixel']:.2f}. "
         f"Peak RSS: {a['peak_rss_kind']} (RSS before the first frame {a['rss_before_mb']:,.0f} MB)."),
    ]
    b = rep["side_by_side"]
    p = b["pihim"]
    n = p.get("supersample", 3)
    info = b["info"]
    lines += [
        "",
        (f"(b) {HUA}'s 25 facets alone (glass n = {SIDE_INDEX}), uniform unpolarized sky, {SIDE_PX} x {SIDE_PX}, "
         f"{info['fov_deg']:g} deg field of view, {SIDE_INCIDENCE_DEG:g} deg incidence at {SIDE_DISTANCE_M:g} m; "
         f"{b['facet_pixel_fraction'] * 100:.0f} % of the pixels see a facet."),
        "",
        "| Renderer | spp | Seconds | Camera samples | Samples/s | Ray casts (est.) | Casts/s | Other CPU % |",
        "|---|--:|--:|--:|--:|--:|--:|--:|",
        (f"| pihim `render_frame` ({n}x{n} rays at edge pixels; median of {p['repeat']}) | 1 ({n * n} at edges) "
         f"| {p['median_s']:.3f} | {p['rays']:,} | {p['rays_per_second']:,.0f} | {p['ray_casts_estimate']:,.0f} "
         f"| {p['ray_casts_per_second']:,.0f} | {harness.other_pct(p['other_cpu_load'])} |"),
    ]
    m = b["mitsuba"]
    if m is None:
        lines += ["", f"Mitsuba skipped: {b['mitsuba_skipped']}."]
    else:
        for r in m["runs"]:
            label = f"Mitsuba {m['version']} `{m['variant']}`"
            if not r["measured"]:
                label += f" (extrapolated x{r['spp'] // r['extrapolated_from_spp']} from {r['extrapolated_from_spp']} spp)"
            lines.append(
                f"| {label} | {r['spp']} | {r['seconds']:.2f} | {r['camera_samples']:,.0f} "
                f"| {r['samples_per_second']:,.0f} | {r['ray_casts_estimate']:,.0f} | {r['ray_casts_per_second']:,.0f} "
                f"| {harness.other_pct(r['other_cpu_load'])} |"
            )
        g = m["agreement"]
        lines += [
            "",
            (f"Mitsuba scene load {m['scene_load_s']:.2f} s, first 1-spp render {m['first_render_1spp_s']:.2f} s. "
             f"Agreement with Mitsuba at {m['agreement_spp']} spp on {g['interior_pixels']:,} facet-interior pixels: "
             f"mean DoLP {g['dolp_mean_pihim']:.5f} (pihim) vs {g['dolp_mean_mitsuba']:.5f} (Mitsuba), "
             f"|dDoLP| mean {g['dolp_abs_diff_mean']:.1e}, max {g['dolp_abs_diff_max']:.1e}; axial AoP difference "
             f"mean {g['aop_axial_diff_mean_deg']:.1e} deg, max {g['aop_axial_diff_max_deg']:.1e} deg (mean AoP "
             f"{g['aop_mean_pihim_deg']:.1f} deg); reflectance {g['reflectance_pihim']:.5f} vs "
             f"{g['reflectance_mitsuba']:.5f}. Mean |dS0| (sky radiance 1): all pixels "
             f"{g['s0_abs_diff_mean_all_pixels']:.1e}, edge pixels {_f(g['s0_abs_diff_mean_edge_pixels'], '.1e')}."),
        ]
    lines += harness.target_table(rep["targets"], spec=".2f")
    lines += harness.busy_warning([a["other_cpu_load"], p["other_cpu_load"]])
    mach = rep["machine"]
    lines += [
        "",
        (f"Machine: {mach['cpu_model']}, {mach['cpu_count']} cores, numba {mach['numba']} with "
         f"{mach['numba_threads']} threads ({mach['numba_threading_layer']}), numpy {mach['numpy']}, "
         f"Python {mach['python']}."),
    ]
    return "\n".join(lines)


def _configure(parser: Any) -> None:
    parser.add_argument("--no-mitsuba", action="store_true", help="skip the Mitsuba side of part (b)")
    parser.add_argument("--mitsuba-spp", metavar="N[,N...]", help="Mitsuba samples per pixel to time (default 16,256)")
    parser.add_argument("--wait-quiet", type=float, default=None, metavar="S",
                        help="wait up to S seconds before each measurement for idle CPUs")


def main(
    argv: Sequence[str] | None = None,
    *,
    repeat: int | None = None,
    warmup: int | None = None,
    quick: bool = False,
    wait_quiet: float = 0.0,
    mitsuba: bool = True,
    json_path: Path | None = RESULTS_PATH,
    echo: bool = True,
) -> dict[str, Any]:
    """Run the benchmark, print the markdown report and write the JSON.

    Parameters
    ----------
    argv : sequence of str, optional
        Command-line arguments (``--repeat N``, ``--warmup N``, ``--quick``,
        ``--json PATH``, ``--no-mitsuba``, ``--mitsuba-spp 16,256``,
        ``--wait-quiet S``); ``None`` or empty reads nothing.
    repeat, warmup : int, optional
        Timed and untimed NSTTF frames; default 3 and 1 (``quick``: 1 and 1).
    quick : bool
        One timed NSTTF frame, no traced frame, Mitsuba at 16 spp only (256
        extrapolated).
    wait_quiet : float
        Seconds to wait for idle CPUs before each measurement (0: do not wait).
    mitsuba : bool
        Run the Mitsuba side of part (b).
    json_path : pathlib.Path or None
        Where to write the JSON report; ``None`` writes nothing.
    echo : bool
        Print the markdown report.
    """
    o = harness.options(argv, description=__doc__.split("\n\n")[0], counts=COUNTS, repeat=repeat, warmup=warmup,
                        quick=quick, json_path=json_path, configure=_configure)
    spp = None
    if o.args is not None:
        mitsuba = mitsuba and not o.args.no_mitsuba
        if o.args.mitsuba_spp:
            spp = tuple(int(v) for v in o.args.mitsuba_spp.split(","))
        if o.args.wait_quiet is not None:
            wait_quiet = o.args.wait_quiet
    report = run_benchmark(o.repeat, o.warmup, o.quick, mitsuba=mitsuba, mitsuba_spp=spp, wait_quiet_s=wait_quiet)
    return harness.publish(report, markdown_report, o.json_path, echo=echo)


if __name__ == "__main__":
    main(sys.argv[1:])
