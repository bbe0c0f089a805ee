"""Frame selection: the HUA-target pairs a frame shows, and whether each is worth the canting estimate.

For one raw frame and its logged pose, :func:`select_pairs`

1. tracks the field for the frame's time from the log alone
   (:func:`pihim.inspection.pipeline.field_pose_from_log`);
2. takes as **HUA candidates** the heliostats whose mirror centre is in front
   of the camera, facing it, and projects inside the frame;
3. finds each candidate's **target**: the camera ray to the HUA's mirror
   centre, reflected about the HUA's normal, meets the nearest other mirror
   rectangle (either face) -- the heliostat seen reflected in the HUA;
4. computes the **polar image** at super-pixel resolution
   (:func:`pihim.camera.polar_image`) and, inside the HUA's projected mirror
   outline, the mean DoLP and the saturated share;
5. applies :class:`SelectionCriteria`, in this order, giving the first failed
   criterion as the skip reason: enough of the HUA in view; a target reflected;
   the mirror large enough in the image; the paper's reflection criterion
   DoLP > 0.2 (section 4.3: images are processed only where the heliostat
   reflection has DoLP > 0.2); few saturated pixels.

The score of a selected pair is its measured reflection DoLP (the demo's
"most polarized reflections first"); the run keeps the best few frames of
each pair for the canting estimate. The paper's sky-vs-sky and
ground-vs-ground predictions are not required by default: at the NSTTF
the planner predicts few images satisfying them (``pihim plan`` prints
the share), and the canting estimator works on the target's outline in S0
(see ``docs/campaign.md``).
"""

from __future__ import annotations

import math
import time as _time
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pihim.errors import PihimInputError

__all__ = ["SKIP_REASONS", "SelectionCriteria", "pair_candidates", "select_pairs"]

#: Skip reasons (the text stored and counted).
SKIP_REASONS = {
    "view": "HUA not enough in view",
    "target": "no target reflected in the HUA",
    "small": "HUA too small in the image",
    "dolp": "reflection DoLP <= criterion",
    "saturated": "HUA reflection saturated",
}


@dataclass(frozen=True)
class SelectionCriteria:
    """Thresholds of the frame selection.

    Attributes
    ----------
    min_in_view : float
        Share of the HUA's facet corners that must project inside the frame.
        Planned captures frame the target's reflection and show 66-80 % of
        the HUA's facet corners on the NSTTF plan at 13:00, hence 0.5.
    min_mirror_px : float
        Smallest projected mirror area, full-resolution pixels.
    min_reflection_dolp : float
        Mean DoLP over the HUA's mirror must exceed this (paper: 0.2).
    max_saturated : float
        Largest share of saturated super-pixels on the HUA's mirror.
    max_range_m : float
        Heliostats farther than this from the camera are not candidates.
    """

    min_in_view: float = 0.5
    min_mirror_px: float = 400.0
    min_reflection_dolp: float = 0.2
    max_saturated: float = 0.02
    max_range_m: float = 120.0

    def __post_init__(self) -> None:
        for k, v in asdict(self).items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise PihimInputError(f"selection criterion {k} must be a finite number >= 0, got {v!r}")
        for k in ("min_in_view", "max_saturated"):
            if getattr(self, k) > 1:
                raise PihimInputError(f"selection criterion {k} is a share, in [0, 1], got {getattr(self, k)!r}")
        if self.min_reflection_dolp >= 1:
            raise PihimInputError("selection criterion min_reflection_dolp must be in [0, 1) (a DoLP is at most 1), "
                                  f"got {self.min_reflection_dolp!r}")


def _project(camera: Any, pose: Any, pts: NDArray) -> tuple[NDArray, NDArray]:
    """Pixels and depths of ENU points (depth <= 0: behind the camera)."""
    from pihim.camera.pose import project_points

    cam = np.asarray(pose.rotation) @ (pts.reshape(-1, 3) - np.asarray(pose.position_m)).T
    depth = cam[2].reshape(pts.shape[:-1])
    uv = project_points(camera, pose, pts.reshape(-1, 3)).reshape(*pts.shape[:-1], 2)
    return uv, depth


def pair_candidates(camera: Any, pose: Any, field_pose: Any, criteria: SelectionCriteria = SelectionCriteria()
                    ) -> list[dict[str, Any]]:
    """The geometric part of the selection (steps 2-3 of the module notes), without the image.

    Returns
    -------
    list of dict
        One per HUA candidate: ``hua`` / ``target`` indices (target -1 if
        none), ``in_view`` share, ``mirror_px`` projected area, ``outline_px``
        (4, 2) projected mirror corners, ``reason`` key of :data:`SKIP_REASONS`
        or None.
    """
    fp = field_pose
    spec = fp.field.spec
    c = np.asarray(pose.position_m, float)
    centres = np.asarray(fp.mirror_centres, float)
    normals = np.asarray(fp.normals, float)
    rel = centres - c
    dist = np.linalg.norm(rel, axis=1)
    facing = np.einsum("ij,ij->i", rel, normals) < 0.0
    near = dist <= criteria.max_range_m
    idx = np.flatnonzero(facing & near)
    if idx.size == 0:
        return []
    uv_c, depth_c = _project(camera, pose, centres[idx])
    w, h = camera.width_px, camera.height_px
    inside = (depth_c > 0) & (uv_c[:, 0] >= 0) & (uv_c[:, 0] < w) & (uv_c[:, 1] >= 0) & (uv_c[:, 1] < h)
    idx = idx[inside]
    if idx.size == 0:
        return []
    from pihim.field.kinematics import facet_corners, mirror_outline

    rot_all = np.asarray(fp.rotations, float)
    corners = facet_corners(rot_all[idx], centres[idx], spec.facet_centroids,
                            np.asarray(fp.facet_normals_local)[idx], spec.facet_width_m,
                            spec.facet_height_m)  # (n, F, 4, 3), the candidates only (fields of 100,000)
    uv_f, depth_f = _project(camera, pose, corners)
    ok = (depth_f > 0) & np.all(np.isfinite(uv_f), axis=-1)
    ok &= (uv_f[..., 0] >= 0) & (uv_f[..., 0] < w) & (uv_f[..., 1] >= 0) & (uv_f[..., 1] < h)
    share = ok.reshape(len(idx), -1).mean(axis=1)
    uv_o, _ = _project(camera, pose, mirror_outline(rot_all[idx], centres[idx], spec))  # (n, 4, 2)
    x, y = uv_o[..., 0], uv_o[..., 1]
    area = 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1))
    # targets: the reflected centre ray against every other mirror rectangle
    d = rel[idx] / dist[idx, None]
    n = normals[idx]
    r = d - 2.0 * np.einsum("ij,ij->i", d, n)[:, None] * n
    rot = np.asarray(fp.rotations, float)  # (N, 3, 3), columns x, y, z in ENU
    hw, hh = float(spec.mirror_half_width_m), float(spec.mirror_half_height_m)
    out = []
    for k, i in enumerate(idx):
        denom = normals @ r[k]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.einsum("ij,ij->i", centres - centres[i], normals) / denom
        cand = np.isfinite(t) & (t > 0.5) & (np.abs(denom) > 1e-9)
        cand[i] = False
        target = -1
        if cand.any():
            js = np.flatnonzero(cand)
            hit = centres[i] + t[js, None] * r[k]
            local = np.einsum("nji,nj->ni", rot[js], hit - centres[js])
            on = (np.abs(local[:, 0]) <= hw) & (np.abs(local[:, 1]) <= hh)
            if on.any():
                target = int(js[on][np.argmin(t[js][on])])
        reason = None
        if share[k] < criteria.min_in_view:
            reason = "view"
        elif target < 0:
            reason = "target"
        elif area[k] < criteria.min_mirror_px:
            reason = "small"
        out.append({"hua": int(i), "target": target, "in_view": float(share[k]), "mirror_px": float(area[k]),
                    "range_m": float(dist[i]), "outline_px": uv_o[k], "reason": reason})
    return out


def _polygon_mask(shape: tuple[int, int], outline_px: NDArray, scale: float) -> NDArray[np.bool_]:
    import cv2

    mask = np.zeros(shape, np.uint8)
    pts = np.round(np.asarray(outline_px, float) * scale * 16.0).astype(np.int32)  # 4 fractional bits
    cv2.fillPoly(mask, [pts.reshape(-1, 1, 2)], 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def _sensor_settings(log: Mapping[str, Any]) -> dict[str, Any]:
    """Layout, analyser, dark level and bit depth from ``log["sensor"]``
    (:func:`pihim.inspection.pipeline.sensor_settings`)."""
    from pihim.inspection.pipeline import sensor_settings

    return sensor_settings(log)


def select_pairs(raw: NDArray, log: Mapping[str, Any], field: Any,
                 criteria: SelectionCriteria = SelectionCriteria(), *, field_pose: Any = None) -> dict[str, Any]:
    """Select the HUA-target pairs of one frame (module notes).

    Parameters
    ----------
    raw : ndarray, shape (H, W)
        The raw DoFP mosaic.
    log : mapping
        The frame's log (:func:`pihim.campaign.flight.frame_log`: ``time``,
        ``site``, ``camera``, ``pose``, ``sensor``, ``aim_point_m``, ``heliostats``).
    field : pihim.field.Field
    criteria : SelectionCriteria
    field_pose : FieldPose, optional
        The field as logged at the frame's time, if already computed (a run
        tracks once per second of flight); default computed from ``log``.

    Returns
    -------
    dict
        ``candidates``: list of ``{hua, target, selected, reason, score,
        metrics}`` (names; target ``""`` when none); ``seconds``: ``polar``,
        ``geometry``, ``total``.
    """
    from pihim.camera.model import CameraModel
    from pihim.camera.pipeline import polar_image
    from pihim.camera.pose import CameraPose
    from pihim.inspection.pipeline import field_pose_from_log

    t0 = _time.perf_counter()
    camera = CameraModel.from_dict(log["camera"])
    arr = np.asarray(raw)
    if arr.ndim != 2 or (arr.shape[1], arr.shape[0]) != (camera.width_px, camera.height_px):
        raise PihimInputError(f"the frame is {arr.shape[::-1]} but the camera is {camera.width_px}x{camera.height_px}")
    pose = CameraPose.from_dict(log["pose"])
    fp = field_pose_from_log(field, log) if field_pose is None else field_pose
    geo = pair_candidates(camera, pose, fp, criteria)
    t1 = _time.perf_counter()
    names = fp.field.names
    need_image = [g for g in geo if g["reason"] is None]
    t2 = t1
    if need_image:
        s = _sensor_settings(log)
        pol = polar_image(arr, layout=s["layout"], analyser=s["analyser"], demosaic="superpixel",
                          dark_level=s["dark_level"], bit_depth=s["bit_depth"])
        t2 = _time.perf_counter()
        scale = pol.dolp.shape[1] / camera.width_px
        for g in need_image:
            mask = _polygon_mask(pol.dolp.shape, g["outline_px"], scale)
            if not mask.any():
                g["reason"] = "small"
                continue
            vals = pol.dolp[mask]
            g["dolp"] = float(np.nanmean(vals)) if np.isfinite(vals).any() else 0.0
            g["saturated"] = float(np.asarray(pol.saturated)[mask].mean())
            if not g["dolp"] > criteria.min_reflection_dolp:
                g["reason"] = "dolp"
            elif g["saturated"] > criteria.max_saturated:
                g["reason"] = "saturated"
    cands = []
    for g in geo:
        metrics = {k: round(float(g[k]), 4) for k in ("in_view", "mirror_px", "range_m", "dolp", "saturated") if k in g}
        sel = g["reason"] is None
        cands.append({"hua": names[g["hua"]], "target": names[g["target"]] if g["target"] >= 0 else "",
                      "selected": sel, "reason": None if sel else SKIP_REASONS[g["reason"]],
                      "score": g.get("dolp") if sel else None, "metrics": metrics})
    t3 = _time.perf_counter()
    return {"candidates": cands,
            "seconds": {"geometry": round(t1 - t0, 4), "polar": round(t2 - t1, 4), "total": round(t3 - t0, 4)}}
