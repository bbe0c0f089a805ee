"""One raw frame to facet canting: polar image, edge points, camera pose, canting (paper sec. 4.4).

:func:`inspect_frame` chains the estimators for a frame whose metadata
``log`` says where the drone was, when, and which heliostats it saw:

1. :func:`pihim.camera.polar_image` with full-resolution demosaicing (the
   sensor's layout, analyser, dark level and bit depth from ``log["sensor"]``
   when present);
2. sub-pixel edge points of **S0 only**
   (``edge_points(s0)``): the DoLP of the dark target back is
   too noisy at the sensor's 39 dB to add its edges unweighted (see
   :mod:`pihim.inspection.canting`);
3. :func:`pihim.inspection.pose.refine_pose` of the logged camera pose on the
   outlines of the HUA's facets: starting positions about one GPS sigma
   apart around the logged one, an FFT image-shift search, chamfer alignment
   on ever sharper proximity maps and a point-to-line ICP (see its module
   notes). On 20 rendered frames from the issue's priors (GPS 1.5 m,
   attitude 1 deg; the facet corners a median 1,127 px off) it converged on
   every frame, to 0.31 px median (``benchmarks/canting_quality.py``);
4. :func:`pihim.inspection.canting.estimate_canting` (DoLP and saturation
   masks passed for its skip tests).

The field pose the estimators see is rebuilt from the log alone -- the sun
from ``log["time"]`` and ``log["site"]``, the field tracking
``log["aim_point_m"]``, and the logged drive angles of the heliostats in
``log["heliostats"]`` -- never from a simulation's ``truth``.

:func:`combine_results` merges several frames of the same HUA per facet.
"""

from __future__ import annotations

import math
import time as _time
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field as _dc_field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pihim.camera.frames import MAX_RAW_VALUE
from pihim.camera.layout import IMX250MZR, MosaicLayout
from pihim.camera.model import CameraModel
from pihim.camera.pipeline import DEMOSAIC_METHODS, polar_image
from pihim.camera.pose import CameraPose, project_points
from pihim.errors import PihimInputError
from pihim.field.kinematics import FieldPose, drive_angles, track_field
from pihim.inspection._log import sensor_entries
from pihim.inspection.canting import CantingResult, FacetCanting, estimate_canting
from pihim.inspection.features import edge_points
from pihim.inspection.pose import facet_outline_segments, refine_pose
from pihim.polarimetry.analyser import AnalyserMatrix
from pihim.sky.sun import Site, sun_position

__all__ = ["InspectionResult", "SIGMA_FLOOR_MRAD", "combine_results",
           "field_pose_from_log", "inspect_frame", "logged_aim_and_drives"]

#: Floor of the per-facet standard errors used as inverse-variance weights, mrad.
SIGMA_FLOOR_MRAD = 0.05


@dataclass(frozen=True, eq=False)
class InspectionResult:
    """The canting of one HUA from one frame, with what it was measured from.

    Attributes
    ----------
    hua, target : str
    image : dict
        Polar image summary: ``width``, ``height``, ``demosaic``,
        ``bit_depth``, ``fraction_saturated``, ``edge_points``.
    pose : dict
        :meth:`pihim.inspection.pose.PoseFit.describe` plus ``prior`` (the
        logged pose, :meth:`CameraPose.to_dict`).
    canting : CantingResult
    seconds : dict
        Wall time per step: ``polar``, ``edges``, ``pose``, ``canting``, ``total``.
    """

    hua: str
    target: str
    image: dict[str, Any]
    pose: dict[str, Any]
    canting: CantingResult
    seconds: dict[str, float] = _dc_field(default_factory=dict)


def _need(log: Mapping[str, Any], key: str) -> Any:
    if key not in log or log[key] is None:
        raise PihimInputError(f"the log has no '{key}'")
    return log[key]


def _site(log: Mapping[str, Any]) -> Site:
    s = _need(log, "site")
    if not isinstance(s, Mapping):
        raise PihimInputError("log 'site' must be an object with latitude_deg, longitude_deg, height_m")
    try:
        return Site(name=str(s.get("name", "log")), latitude_deg=s["latitude_deg"], longitude_deg=s["longitude_deg"],
                    height_m=s["height_m"], timezone=str(s.get("timezone", "UTC")))
    except KeyError as exc:
        raise PihimInputError(f"log 'site' has no {exc.args[0]!r}") from None


def logged_aim_and_drives(field: Any, log: Mapping[str, Any]) -> tuple[NDArray[np.float64], dict[int, tuple[float, float]]]:
    """The log's aim point and the drive angles it gives (``{heliostat index: (az_deg, el_deg)}``), checked.

    What does not depend on the frame's time, so that a campaign can refuse a flight's log once, before any
    frame is read.

    Raises
    ------
    PihimInputError
        An aim point that is not 3 finite numbers above the ground; a ``heliostats`` entry that is not
        ``{name, az_deg, el_deg}`` with finite angles, names an unknown heliostat, or repeats one.
    """
    try:
        aim = np.asarray(_need(log, "aim_point_m"), dtype=float)
    except (TypeError, ValueError):
        aim = np.zeros(0)
    if aim.shape != (3,) or not np.all(np.isfinite(aim)):
        raise PihimInputError(f"log 'aim_point_m' must be 3 finite numbers, got {log['aim_point_m']!r}")
    if aim[2] <= 0:  # as pihim plan and pihim windows: a field aims above the ground (the tower's target)
        raise PihimInputError(f"log 'aim_point_m' must be above the ground (z > 0), got z = {aim[2]:g} m")
    helio = _need(log, "heliostats")
    if not isinstance(helio, Sequence) or isinstance(helio, str):
        raise PihimInputError("log 'heliostats' must be a list of {name, az_deg, el_deg}")
    # an empty list is fine: no heliostat off its tracking, every one tracks the aim point (docs/campaign.md)
    drives: dict[int, tuple[float, float]] = {}
    seen: dict[int, str] = {}
    for entry in helio:
        try:
            name = str(entry["name"])
            a, e = float(entry["az_deg"]), float(entry["el_deg"])
        except (KeyError, TypeError, ValueError):
            raise PihimInputError(f"log 'heliostats': bad entry {entry!r} (need name, az_deg, el_deg)") from None
        try:
            i = field.index(name)
        except PihimInputError as exc:  # a heliostat the field does not have (another --field than the log's?)
            raise PihimInputError(f"log 'heliostats': {exc}") from None
        if not (math.isfinite(a) and math.isfinite(e)):
            raise PihimInputError(f"log 'heliostats': non-finite drive angles for {entry['name']}")
        if i in seen:  # two sets of drive angles for one heliostat: which one it had is unknown
            again = "" if seen[i] == str(entry["name"]) else f" (as {entry['name']!r})"
            raise PihimInputError(f"log 'heliostats': {seen[i]} is listed twice{again}; give each heliostat once")
        seen[i] = str(entry["name"])
        drives[i] = (a, e)
    return aim, drives


def field_pose_from_log(field: Any, log: Mapping[str, Any]) -> FieldPose:
    """The field as logged: tracking ``log["aim_point_m"]`` at ``log["time"]``, logged drive angles applied."""
    site = _site(log)
    sun = sun_position(site, _need(log, "time"))
    if not float(sun.elevation_deg) > 0.0:
        raise PihimInputError(f"the sun is below the horizon at {log['time']}: the field does not track")
    aim, drives = logged_aim_and_drives(field, log)
    pose = track_field(field, sun.vector, aim)
    da = drive_angles(pose.normals)
    az = np.array(da.azimuth_deg, float)
    el = np.array(da.elevation_deg, float)
    for i, (a, e) in drives.items():
        az[i], el[i] = a, e
    return pose.with_drive(az, el)


def sensor_settings(log: Mapping[str, Any]) -> dict[str, Any]:
    """The :func:`pihim.camera.polar_image` settings a frame's ``log["sensor"]`` records.

    Returns ``{"layout", "analyser", "dark_level", "bit_depth"}`` (IMX250MZR,
    ideal analyser, 0 DN and the frame's own range where the log is silent);
    a malformed entry is a :class:`PihimInputError`.
    """
    sensor, model = sensor_entries(log)
    layout_text = sensor.get("layout", model.get("layout"))
    layout = IMX250MZR if layout_text is None else MosaicLayout.parse(str(layout_text))
    analyser = None
    if "analyser" in model:
        if not isinstance(model["analyser"], Mapping):
            raise PihimInputError(f"log sensor.model.analyser must be an object with a 'matrix', "
                                  f"got {type(model['analyser']).__name__}")
        try:
            analyser = AnalyserMatrix.from_dict(dict(model["analyser"]))
        except PihimInputError as exc:
            raise PihimInputError(f"log sensor.model.analyser: {exc}") from None
    dark = model.get("dark_level_dn", 0.0)
    bits = model.get("bit_depth")
    if isinstance(dark, bool) or not isinstance(dark, (int, float)) \
            or not (math.isfinite(dark) and 0 <= dark <= MAX_RAW_VALUE):
        raise PihimInputError(f"log sensor dark_level_dn must be a raw level in [0, {MAX_RAW_VALUE}], got {dark!r}")
    if bits is not None and (isinstance(bits, bool) or not isinstance(bits, int) or not 1 <= bits <= 16):
        raise PihimInputError(f"log sensor bit_depth must be an integer from 1 to 16, got {bits!r}")
    return {"layout": layout, "analyser": analyser, "dark_level": float(dark), "bit_depth": bits}


def _in_view(camera: CameraModel, pose: CameraPose, corners: NDArray) -> float:
    """Share of the HUA's facet outline points that the (logged) pose projects inside the frame."""
    c = corners.reshape(-1, 4, 3)
    t = np.linspace(0.0, 1.0, 8, endpoint=False)[:, None, None]
    ring = np.concatenate([c[:, j][None] + t * (c[:, (j + 1) % 4] - c[:, j])[None] for j in range(4)]).reshape(-1, 3)
    uv = project_points(camera, pose, ring)
    ok = np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] >= 0) & (uv[:, 0] < camera.width_px) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height_px)
    return float(ok.mean())


def inspect_frame(
    raw: NDArray,
    log: Mapping[str, Any],
    field: Any,
    *,
    hua: str | None = None,
    target: str | None = None,
    demosaic: str = "full",
    target_orientation: bool = False,
) -> InspectionResult:
    """Facet canting of ``hua`` from ``target``'s reflection in one raw mosaic frame.

    Parameters
    ----------
    raw : ndarray, shape (H, W)
        The raw DoFP mosaic (``H x W`` must equal ``log["camera"]``).
    log : mapping
        The frame's ``log`` (``pihim simulate``'s ``FRAME.json["log"]``):
        ``camera``, ``pose``, ``time``, ``site``, ``aim_point_m``,
        ``heliostats``, optionally ``sensor``, ``hua``, ``target``.
    field : pihim.field.Field
        The heliostat field the log refers to.
    hua, target : str, optional
        Heliostat under assessment and the target reflected in it; default
        ``log["hua"]`` / ``log["target"]``.
    demosaic : {"full", "superpixel"}
        Demosaicing; the estimators need ``full`` (the pixel grid of the
        camera model).
    target_orientation : bool
        Also correct the target's logged drive angles (see
        :func:`pihim.inspection.canting.estimate_canting`).

    Returns
    -------
    InspectionResult

    Raises
    ------
    PihimInputError
        Missing HUA or target, unknown names, an incomplete log, a frame of
        another size than ``log["camera"]``, the HUA not in view from the
        logged pose, or a pose refinement that finds no match.
    """
    t0 = _time.perf_counter()
    if not isinstance(log, Mapping):
        raise PihimInputError("the log must be a JSON object")
    if demosaic not in DEMOSAIC_METHODS:
        raise PihimInputError(f"unknown demosaic method {demosaic!r}; choose one of {', '.join(DEMOSAIC_METHODS)}")
    if demosaic != "full":
        raise PihimInputError("canting needs full-resolution demosaicing (the camera model's pixel grid)")
    for name, given in (("hua", hua), ("target", target)):
        if given is not None and not str(given).strip():
            raise PihimInputError(f"the {name} name is empty (--{name} NAME)")
    hua = hua if hua is not None else log.get("hua")
    target = target if target is not None else log.get("target")
    if not hua:
        raise PihimInputError("no heliostat under assessment: the log has no 'hua'; give one (--hua NAME)")
    if not target:
        raise PihimInputError("no target heliostat: the log has no 'target'; give one (--target NAME)")
    hua, target = str(hua), str(target)
    if hua == target:
        raise PihimInputError(f"the HUA and the target are the same heliostat ({hua})")
    h = field.index(hua)
    field.index(target)
    camera = CameraModel.from_dict(_need(log, "camera"))
    arr = np.asarray(raw)
    if arr.ndim != 2:
        raise PihimInputError(f"the raw frame must be a 2-D mosaic, got shape {arr.shape}")
    rows, cols = arr.shape
    if (cols, rows) != (camera.width_px, camera.height_px):
        raise PihimInputError(
            f"the log describes a {camera.width_px}x{camera.height_px} frame, but the frame is {cols}x{rows}"
        )
    prior = CameraPose.from_dict(_need(log, "pose"))
    fp = field_pose_from_log(field, log)
    corners = fp.facet_corners()[h]
    share = _in_view(camera, prior, corners)
    if share <= 0.0:
        raise PihimInputError(f"{hua} is not in view: its facets project outside the frame from the logged pose")
    settings = sensor_settings(log)
    t1 = _time.perf_counter()
    pol = polar_image(arr, layout=settings["layout"], analyser=settings["analyser"], demosaic="full",
                      dark_level=settings["dark_level"], bit_depth=settings["bit_depth"])
    t2 = _time.perf_counter()
    ep = edge_points(pol.s0)  # S0 only: see the notes of pihim.inspection.canting
    t3 = _time.perf_counter()
    fit = refine_pose(camera, prior, facet_outline_segments(corners), ep)
    t4 = _time.perf_counter()
    res = estimate_canting(camera, fit.pose, fp, hua, target, ep, dolp=pol.dolp, saturated=pol.saturated,
                           target_orientation=target_orientation)
    t5 = _time.perf_counter()
    sat = np.asarray(pol.saturated, bool)
    image = {
        "width": int(pol.s0.shape[1]),
        "height": int(pol.s0.shape[0]),
        "demosaic": "full",
        "bit_depth": settings["bit_depth"],
        "fraction_saturated": float(sat.mean()) if sat.size else 0.0,
        "edge_points": len(ep),
        "hua_in_view_fraction": share,
    }
    pose = {"prior": prior.to_dict(), **fit.describe()}
    seconds = {"setup": t1 - t0, "polar": t2 - t1, "edges": t3 - t2, "pose": t4 - t3, "canting": t5 - t4,
               "total": t5 - t0}
    return InspectionResult(hua, target, image, pose, res, {k: round(float(v), 4) for k, v in seconds.items()})


def combine_results(results: Iterable[InspectionResult | CantingResult]) -> CantingResult:
    """Combine several frames' canting of the same HUA, per facet.

    Each facet's relative deviations (azimuth and elevation separately) are
    averaged with weights ``1 / max(sigma, 0.05 mrad)^2`` over the frames that
    used it (a frame without a sigma counts as 0.05 mrad: the floor keeps a
    frame whose fit claims a tiny sigma from outweighing the others, as a fit
    locked onto other features claims one too). The combined sigma is the
    larger of the weighted mean's standard error from the frames' sigmas,
    ``sqrt(sum w^2 sigma^2) / sum w`` (unknown if a frame had none), and, with
    two frames or more, the one from their scatter,
    ``sqrt(sum w r^2 / ((n - 1) sum w))`` with ``r`` the frames' residuals:
    frames that disagree beyond their sigmas widen it.
    Every frame reports deviations relative to the mean over *its own* used
    facets, so when frames use different facet sets their references differ
    by a constant: each frame's offset to the combination is estimated (a
    weighted mean over its facets) and removed, alternating a few times.
    The result is re-referenced to the mean of the combined facets; the
    best-fit orientation is the mean of the frames' orientations (each
    shifted by its offset), the drive correction the mean of the frames'
    (the orientation searches stay with their frames). Grid values are averaged (unweighted) and
    re-referenced likewise; points add up; ``rms_px`` is the point-weighted
    RMS; ``frames`` counts the frames.

    Raises
    ------
    PihimInputError
        No results, or results for different HUAs.
    """
    res = [r.canting if isinstance(r, InspectionResult) else r for r in results]
    if not res:
        raise PihimInputError("no results to combine")
    huas = {r.hua for r in res}
    if len(huas) > 1:
        raise PihimInputError(f"cannot combine frames of different HUAs: {', '.join(sorted(huas))}")
    if len(res) == 1:
        return res[0]
    n_f = max(len(r.facets) for r in res)
    n_k = len(res)
    comps = {}
    for key in ("az", "el"):
        val = np.full((n_k, n_f), np.nan)
        wgt = np.zeros((n_k, n_f))
        given = np.full((n_k, n_f), np.nan)  # the frames' own sigmas (NaN: none)
        for k, r in enumerate(res):
            for f in r.facets:
                if f.used and f.id <= n_f:
                    v = getattr(f, f"{key}_mrad")
                    s = getattr(f, f"{key}_sigma_mrad")
                    if s is not None and np.isfinite(s):
                        given[k, f.id - 1] = float(s)
                    s = SIGMA_FLOOR_MRAD if s is None or not np.isfinite(s) else max(float(s), SIGMA_FLOOR_MRAD)
                    val[k, f.id - 1] = float(v)
                    wgt[k, f.id - 1] = 1.0 / s**2
        used = wgt > 0
        offs = np.zeros(n_k)
        comb = np.full(n_f, np.nan)
        sw = wgt.sum(axis=0)
        have = sw > 0
        for _ in range(20):
            x = np.where(used, val - offs[:, None], 0.0)
            comb = np.where(have, (wgt * x).sum(axis=0) / np.where(have, sw, 1.0), np.nan)
            if have.any():
                comb = comb - np.nanmean(comb)
            rw = wgt.sum(axis=1)
            d = np.where(used, val - comb[None, :], 0.0)
            offs = np.where(rw > 0, (wgt * d).sum(axis=1) / np.where(rw > 0, rw, 1.0), 0.0)
        n_frames = used.sum(axis=0)
        sw1 = np.where(have, sw, 1.0)
        # from the frames' sigmas (NaN where a frame had none) and from the frames' scatter about the combination
        prop = np.sqrt(np.sum(np.where(used, wgt**2 * given**2, 0.0), axis=0)) / sw1
        prop = np.where(have & ~np.any(used & np.isnan(given), axis=0), prop, np.nan)
        resid = np.where(used, val - offs[:, None] - comb[None, :], 0.0)
        scatter = np.sqrt(np.sum(wgt * resid**2, axis=0) / (np.maximum(n_frames - 1, 1) * sw1))
        sig = np.fmax(prop, np.where(n_frames >= 2, scatter, np.nan))
        orient = [getattr(r, f"orientation_{key}_mrad") for r in res]
        o = [o + offs[k] for k, o in enumerate(orient) if o is not None]
        comps[key] = (comb, sig, float(np.mean(o)) if o else None)
    out = []
    n_used = 0
    grid: dict[str, NDArray] = {}
    for key in ("az", "el"):
        g = np.full((n_k, n_f), np.nan)
        for k, r in enumerate(res):
            for f in r.facets:
                gv = getattr(f, f"grid_{key}_mrad")
                if f.used and f.id <= n_f and gv is not None:
                    g[k, f.id - 1] = gv
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # facets no frame used: NaN
            gm = np.nanmean(g, axis=0)
        grid[key] = gm - np.nanmean(gm) if np.isfinite(gm).any() else gm
    for i in range(n_f):
        fid = i + 1
        per = [f for r in res for f in r.facets if f.id == fid]
        use = [f for f in per if f.used]
        if not use:
            reasons = [f.reason for f in per if f.reason]
            seen = [f.in_view for f in per if f.in_view is not None]
            out.append(FacetCanting(fid, False, reasons[0] if reasons else "not measured in any frame",
                                    in_view=float(np.mean(seen)) if seen else None))
            continue
        n_used += 1
        pts = sum(int(f.points) for f in use)
        rms = [(f.rms_px, f.points) for f in use if f.rms_px is not None]
        rms_px = float(np.sqrt(sum(r * r * p for r, p in rms) / max(sum(p for _, p in rms), 1))) if rms else None
        sup_v = [f.support for f in use if f.support is not None]
        seen = [f.in_view for f in use if f.in_view is not None]
        out.append(FacetCanting(
            fid, True, None,
            float(comps["az"][0][i]), float(comps["el"][0][i]),
            *(float(comps[key][1][i]) if np.isfinite(comps[key][1][i]) else None for key in ("az", "el")),
            float(grid["az"][i]), float(grid["el"][i]), pts, rms_px, float(np.mean(sup_v)) if sup_v else None,
            float(np.mean(seen)) if seen else None,
        ))
    targets = sorted({r.target for r in res})
    notes = [f"combined from {n_k} frames ({n_used} facets measured in at least one)"]
    if n_used == 0:
        notes.append("no facet could be measured")
    corr = [r.drive_correction_deg for r in res if r.drive_correction_deg is not None]
    drive = (float(np.mean([c[0] for c in corr])), float(np.mean([c[1] for c in corr]))) if corr else None
    return CantingResult(res[0].hua, "+".join(targets), tuple(out), comps["az"][2], comps["el"][2],
                         sum(r.frames for r in res), tuple(notes), None, drive)
