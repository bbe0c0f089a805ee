"""Render the three scenes of ``docs/rendering.md`` and measure their edge contrast.

Run from the repository root (about 30 s on two cores)::

    python docs/figures/render_scenarios.py

It writes ``docs/figures/render_ufacet.png``, ``render_sky_vs_sky.png`` and
``render_ground_vs_ground.png`` and prints, for every scene, the camera and
the numbers measured from the render. Every scene is the embedded
NSTTF-like field (:func:`pihim.field.nsttf_like_field`) under
:meth:`pihim.render.shading.Environment.clear_sky` at NSTTF on 2021-05-13,
seen by the Triton's field of view at half resolution (1224 x 1024 px,
17.5 mm: a 35 mm lens on the full 2448 x 2048 sensor), rendered by
:func:`pihim.render.frame.render_frame` with the default settings (3 x 3 rays
on edge pixels, two mirror bounces). Nothing is random.

1. **UFACET** (paper Fig. 7a): 13:00, the field tracking
   ``UFACET_AIM_POINT``, the camera at the capture waypoint that
   :func:`pihim.planning.pipeline.build_plan` plans for HUA 8E3 and target
   7E3 (the target's back seen reflected in the HUA).
2. **Sky-vs-sky** (paper Figs. 4a-b, 6a-e): 09:30, front 8E3 and back 9E3
   (adjacent rows, same column). As in the paper's test, the pair is set
   at tracking and every other heliostat face-up. Camera positions south
   of the pair (15-30 m up, within 60 m) are scored with
   :func:`pihim.scenarios.sky_vs_sky`; if no position of that arrangement
   reaches the paper's 0.2 DoLP difference, the back heliostat is set
   face-up too and the search repeated. A position is scored along the
   front's top edge, where the sightline over the edge lands on the back
   mirror; the chosen one maximises the mean predicted DoLP difference
   among those where both reflections show sky at least
   ``SUN_CLEARANCE_DEG`` from the sun, both points are in view and both
   reflections reach the sky past every heliostat (ray casts through the
   scene's BVH, :func:`pihim.render.bvh.cast_rays`), and the front's top
   edge covers the back heliostat over at least ``MIN_OVERLAP_PX`` in the
   image (:func:`pihim.camera.pose.project_points`).
3. **Ground-vs-ground** (paper Figs. 5a-b, 6f-g): 09:30, the field
   tracking, the camera looking down (pitch <= -40 deg) at 8E3's lower
   edge. Positions are scored with :func:`pihim.scenarios.ground_vs_ground`
   at three points of the edge; kept where both the mirror (0.3 and 0.7 m
   inside the edge) and the ground just past it are in view, the mirror
   shows ground that nothing hides, the axial AoP difference exceeds 50 deg,
   the real ground next to the edge and the reflected ground are sunlit
   (nothing of the scene between them and the sun; ray casts as above) and
   the S0 Michelson contrast of the two is at most 0.1; of those, the one
   whose weaker DoLP (mirror or ground) is largest is rendered, so that its
   AoPs are as measurable as possible.

Measurements (scenes 2 and 3) use the paper's regions of interest scaled to
the half-resolution frame: two 100 x 50 px regions (200 x 100 px on the
full sensor), 100 px along the edge and 50 px across it, one on each side,
3 px from the projected edge (:func:`pihim.inspection.contrast.roi_pair_contrast`).
Inside each only the pixels whose labels say what the region is meant to
hold count (scene 2: mirror pixels of the front or of the back heliostat
that reflect sky; scene 3: mirror pixels of the HUA that reflect ground, and
pixels that see the ground directly), and no supersampled (edge) pixel.
S0 and DoLP are region means with their Michelson contrast; AoP is the
axial mean and the axial difference in [0, 90] deg. The edge panels are
:func:`pihim.inspection.edges.gradient_magnitude` (3 x 3 Sobel) of S0 and
DoLP and :func:`pihim.inspection.edges.axial_gradient_magnitude` of AoP (not
DoLP-weighted: the renders are noise-free).
"""

from __future__ import annotations

import math
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Polygon
from numpy.typing import NDArray

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose, project_points
from pihim.field import UFACET_AIM_POINT, nsttf_like_field, track_field
from pihim.inspection.contrast import PAPER_ROI_SIZE, RoiPairContrast, contrast_ratio, roi_pair_contrast
from pihim.inspection.edges import axial_gradient_magnitude, gradient_magnitude
from pihim.planning.pipeline import build_plan
from pihim.polarimetry.stokes import aop_deg, dolp
from pihim.render.frame import RenderedFrame, render_frame
from pihim.render.paths import FACET_BACK, GROUND, MIRROR, SKY, STRUCTURE_HIT
from pihim.render.scene import field_scene
from pihim.render.shading import Environment
from pihim.render.views import ground_vs_ground_view, sky_overlap, sky_vs_sky_view
from pihim.scenarios import SKY_DOLP_DIFFERENCE_MIN
from pihim.sky.sun import NSTTF, parse_time, sun_position
from pihim.visualize import POLAR_MAP_STYLES

OUT_DIR = Path(__file__).resolve().parent
CAMERA = CameraModel(width_px=1224, height_px=1024, focal_length_mm=17.5)
#: The paper's 200 x 100 px regions of interest on the full sensor, at half resolution; 3 px from the edge.
ROI_SIZE = (PAPER_ROI_SIZE[0] // 2, PAPER_ROI_SIZE[1] // 2)
ROI_GAP_PX = 3.0
#: Sky-vs-sky: reflections at least this far from the sun (no glint, no bright circumsolar sky).
SUN_CLEARANCE_DEG = 25.0
#: Sky-vs-sky: the front's top edge must lie over the back heliostat for at least this long in the image.
MIN_OVERLAP_PX = 150.0
#: Sky-vs-sky: points along the front's top edge at which the prediction is evaluated.
EDGE_SAMPLES = 11
#: Ground-vs-ground: largest S0 Michelson contrast between mirror-reflected and real ground.
GROUND_S0_CONTRAST_MAX = 0.1
#: Ground-vs-ground: the camera looks down at least this steeply, deg.
GROUND_PITCH_MAX_DEG = -40.0
#: Ground-vs-ground: the stretch of the lower edge (0 = left end, 1 = right end seen from the front) scored.
GROUND_EDGE_STRETCH = (0.15, 0.45)
FIG_DPI = 80
ROI_COLOURS = ("#e8202a", "#1f8fff")


# --------------------------------------------------------------------------- small geometry helpers


def _unit(v: NDArray) -> NDArray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# --------------------------------------------------------------------------- regions of interest


@dataclass
class Roi:
    """One region of interest: its outline (pixel corners, for drawing) and its name."""

    outline: NDArray
    name: str


@dataclass
class EdgeMeasurement:
    """The paper's ROI pair across one edge, measured on S0, DoLP and AoP (:mod:`pihim.inspection.contrast`)."""

    s0: RoiPairContrast
    dolp: RoiPairContrast
    aop: RoiPairContrast
    rois: tuple[Roi, Roi]

    @property
    def contrast_ratio(self) -> float:
        return contrast_ratio(self.dolp, self.s0)


def measure_edge(fr: RenderedFrame, edge_point: NDArray, normal: NDArray, valid_a: NDArray[np.bool_],
                 valid_b: NDArray[np.bool_], names: tuple[str, str]) -> EdgeMeasurement:
    """Regions a (the ``-normal`` side) and b (``+normal``) across an edge, each restricted to its own pixels.

    A pixel counts in region a only if ``valid_a`` holds there, in region b only
    if ``valid_b`` does, and never if it was supersampled (an edge pixel);
    all others are NaN for :func:`pihim.inspection.contrast.roi_pair_contrast`.
    """
    h, w = fr.s0.shape
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    side_b = (jj - edge_point[0]) * normal[0] + (ii - edge_point[1]) * normal[1] > 0
    keep = np.where(side_b, valid_b, valid_a) & ~fr.supersampled

    def roi(img: NDArray, axial: bool = False) -> RoiPairContrast:
        return roi_pair_contrast(np.where(keep, img, np.nan), edge_point, normal, ROI_SIZE, gap_px=ROI_GAP_PX,
                                 axial=axial)

    r_s0 = roi(fr.s0)
    r_d = roi(dolp(fr.s0, fr.s1, fr.s2))
    r_a = roi(aop_deg(fr.s1, fr.s2), axial=True)
    rois = (Roi(np.array(r_s0.corners_a), names[0]), Roi(np.array(r_s0.corners_b), names[1]))
    return EdgeMeasurement(r_s0, r_d, r_a, rois)


def _edge_normal(p0: NDArray, p1: NDArray, away_from: NDArray) -> NDArray:
    """Unit normal of the image line ``p0 -> p1`` pointing away from the pixel ``away_from``."""
    t = _unit(np.asarray(p1, float) - np.asarray(p0, float))
    n = np.array([-t[1], t[0]])
    return -n if (np.asarray(away_from, float) - p0) @ n > 0 else n


def in_view(fr: RenderedFrame, names: tuple[str, ...], min_fraction: float = 0.01) -> list[str]:
    """Heliostats seen directly on at least ``min_fraction`` of the frame, largest first."""
    h = fr.labels[..., 1]
    idx, counts = np.unique(h[h >= 0], return_counts=True)
    keep = counts >= min_fraction * h.size
    return [names[i] for i in idx[keep][np.argsort(-counts[keep])]]


def what_mirror_shows(fr: RenderedFrame, heliostat: int) -> dict[str, float]:
    """Fractions of a heliostat's mirror pixels whose reflection ends on the sky, the ground, or a heliostat."""
    lab = fr.labels
    m = (lab[..., 0] == MIRROR) & (lab[..., 1] == heliostat)
    seen = lab[..., 3][m]
    total = max(int(m.sum()), 1)
    return {"sky": float(np.sum(seen == SKY) / total), "ground": float(np.sum(seen == GROUND) / total),
            "heliostats": float(np.sum((seen == FACET_BACK) | (seen == STRUCTURE_HIT)) / total)}


# --------------------------------------------------------------------------- figures


def _normalised(e: NDArray) -> NDArray:
    hi = float(np.nanpercentile(e, 99.5))
    return np.clip(np.nan_to_num(e) / hi, 0.0, 1.0) if hi > 0 else np.zeros_like(e)


def _crop_box(rois: tuple[Roi, ...], shape: tuple[int, int], half: int = 130) -> tuple[int, int, int, int]:
    c = np.mean(np.concatenate([r.outline for r in rois]), axis=0)
    h, w = shape
    j0 = int(np.clip(round(c[0]) - half, 0, w - 2 * half))
    i0 = int(np.clip(round(c[1]) - half, 0, h - 2 * half))
    return i0, i0 + 2 * half, j0, j0 + 2 * half


def figure(fr: RenderedFrame, title: str, caption: str, path: Path, *, rois: tuple[Roi, ...] = (),
           edges: tuple[str, NDArray, str, NDArray] | None = None) -> None:
    """S0 (grey, 0.5-99.5 percentile stretch), DoLP, AoP and optionally a Sobel panel, with title and caption."""
    d = dolp(fr.s0, fr.s1, fr.s2)
    a = aop_deg(fr.s1, fr.s2)
    n_panels = 4 if edges is not None else 3
    if n_panels == 4:
        fig = Figure(figsize=(11.0, 11.0), dpi=FIG_DPI)
        axes = [fig.add_axes(r) for r in ([0.02, 0.545, 0.44, 0.345], [0.51, 0.545, 0.44, 0.345],
                                          [0.02, 0.15, 0.44, 0.345], [0.51, 0.15, 0.44, 0.345])]
    else:
        fig = Figure(figsize=(15.0, 5.6), dpi=FIG_DPI)
        axes = [fig.add_axes([0.01 + 0.33 * k, 0.14, 0.28, 0.66]) for k in range(3)]
    FigureCanvasAgg(fig)
    lo, hi = np.percentile(fr.s0, (0.5, 99.5))
    panels = [
        (fr.s0, "gray", lo, hi, "S0, W m$^{-2}$ sr$^{-1}$ (0.5-99.5 % stretch)"),
        (d, POLAR_MAP_STYLES["dolp"][0], POLAR_MAP_STYLES["dolp"][1], POLAR_MAP_STYLES["dolp"][2], "DoLP"),
        (a, POLAR_MAP_STYLES["aop"][0], POLAR_MAP_STYLES["aop"][1], POLAR_MAP_STYLES["aop"][2],
         "AoP, deg (counter-clockwise from image right)"),
    ]
    for ax, (img, cmap, vmin, vmax, label) in zip(axes, panels):
        im = ax.imshow(img, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="antialiased")
        ax.set_title(label, fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
        cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
        cb.ax.tick_params(labelsize=8)
        if cmap == POLAR_MAP_STYLES["aop"][0]:
            cb.set_ticks([0, 45, 90, 135, 180])
        for r, colour in zip(rois, ROI_COLOURS):
            ax.add_patch(Polygon(r.outline, closed=True, fill=False, edgecolor=colour, linewidth=1.2))
            if ax is axes[0]:
                # the name outside the box, on the far side from the other box
                centre = r.outline.mean(axis=0)
                away = centre - np.mean([q.outline.mean(axis=0) for q in rois], axis=0)
                away = away / (np.linalg.norm(away) or 1.0)
                ax.annotate(r.name, centre + 70.0 * away, color="white", fontsize=9, ha="center", va="center",
                            fontweight="bold", bbox={"facecolor": colour, "edgecolor": "none", "pad": 1.5})
    if edges is not None:
        name_a, e_a, name_b, e_b = edges
        i0, i1, j0, j1 = _crop_box(rois, fr.s0.shape)
        sep = np.ones((i1 - i0, 6))
        crop = np.hstack([_normalised(e_a)[i0:i1, j0:j1], sep, _normalised(e_b)[i0:i1, j0:j1]])
        ax = axes[3]
        ax.imshow(crop, cmap="gray", vmin=0, vmax=1, interpolation="antialiased")
        ax.set_title(f"Sobel magnitude, {i1 - i0} x {j1 - j0} px crop around the ROIs\n"
                     f"left: {name_a}   right: {name_b} (each / its frame's 99.5th percentile)", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        for r, colour in zip(rois, ROI_COLOURS):
            for off in (0, (j1 - j0) + 6):
                ax.add_patch(Polygon(r.outline - [j0 - off, i0], closed=True, fill=False, edgecolor=colour,
                                     linewidth=1.0, alpha=0.8))
        for panel_ax in axes[:3]:
            panel_ax.add_patch(Polygon([[j0, i0], [j1, i0], [j1, i1], [j0, i1]], closed=True, fill=False,
                                       edgecolor="white", linewidth=0.8, linestyle="--"))
    fig.suptitle(title, fontsize=11, y=0.985, va="top")
    chars = int(0.96 * fig.get_figwidth() * 72 / (8.5 * 0.6))
    fig.text(0.01, 0.005, textwrap.fill(caption, chars), fontsize=8.5, va="bottom", ha="left")
    fig.savefig(path, dpi=FIG_DPI)


def _where(pose: CameraPose) -> str:
    x, y, z = pose.position_m
    return (f"camera ({x:.1f}, {y:.1f}, {z:.1f}) m ENU, heading {pose.heading_deg:.1f} deg, "
            f"pitch {pose.pitch_deg:.1f} deg")


# --------------------------------------------------------------------------- scene 1: UFACET


def ufacet(field: object) -> dict:
    t = parse_time("2021-05-13T13:00-06:00")
    sun = sun_position(NSTTF, t)
    pose = track_field(field, sun.vector, UFACET_AIM_POINT)
    plan = build_plan(field, t, NSTTF, aim_point=UFACET_AIM_POINT, heliostats=["8E3"], shift=False)
    wp = next(p.waypoints[q.waypoint_index] for p in plan.passes if p.feasible for q in p.predictions
              if q.hua == "8E3" and q.target == "7E3")
    cam_pose = CameraPose.from_waypoint(wp)
    env = Environment.clear_sky(sun.vector)
    fr = render_frame(field_scene(pose), CAMERA, cam_pose, env)
    lab = fr.labels
    ih, it = field.index("8E3"), field.index("7E3")
    hua = (lab[..., 0] == MIRROR) & (lab[..., 1] == ih)
    shows_target = hua & (lab[..., 4] == it)
    shows_sky = hua & (lab[..., 3] == SKY)
    facets_in_view = sorted(int(f) for f in np.unique(lab[..., 2][hua]) if f > 0)
    facets_target = sorted(int(f) for f in np.unique(lab[..., 2][shows_target]) if f > 0
                           and np.mean(lab[..., 4][hua & (lab[..., 2] == f)] == it) >= 0.25)
    corners = project_points(CAMERA, cam_pose, pose.mirror_outline()[ih])
    sky_dolp = float(np.mean(dolp(fr.s0, fr.s1, fr.s2)[shows_sky & ~fr.supersampled])) if shows_sky.any() else None
    res = {
        "camera": cam_pose, "sun": sun, "frame": fr,
        "range_m": float(np.linalg.norm(pose.mirror_centres[ih] - cam_pose.position_m)),
        "hua_fraction": float(hua.mean()),
        "target_fraction_of_hua": float(shows_target.sum() / max(hua.sum(), 1)),
        "sky_fraction_of_hua": float(shows_sky.sum() / max(hua.sum(), 1)),
        "facets_in_view": facets_in_view, "facets_showing_target": facets_target,
        "hua_corners_px": corners, "hua_sky_dolp": sky_dolp,
    }
    missing = [f for f in range(1, 26) if f not in facets_in_view]
    seen = lab[..., 4][hua]
    idx, counts = np.unique(seen[(seen >= 0) & (seen != it)], return_counts=True)
    others = [field.names[i] for i in idx[np.argsort(-counts)] if counts[list(idx).index(i)] >= 0.005 * hua.sum()]
    res["other_heliostats_seen"] = others
    res["ground_fraction_of_hua"] = what_mirror_shows(fr, ih)["ground"]
    title = (f"UFACET capture of HUA 8E3 / target 7E3, 2021-05-13 13:00 MDT (sun zenith {sun.zenith_deg:.1f} deg, "
             f"azimuth {sun.azimuth_deg:.1f} deg)\n{_where(cam_pose)} (planner's capture waypoint)\n"
             f"8E3 fills {100 * res['hua_fraction']:.0f} % of the frame; {100 * res['target_fraction_of_hua']:.0f} % "
             f"of its mirror pixels show 7E3's back, {100 * res['sky_fraction_of_hua']:.0f} % the sky")
    caption = ("Whole NSTTF-like field tracking the UFACET aim point (60, 8.8, 28.9) m; clear sky (Rayleigh, "
               "CIE clear), second-surface silvered glass, Torrance-Sparrow ground. 1224 x 1024 px = the "
               "Triton + 35 mm field of view at half resolution. The dark, weakly polarized parts of the mirror "
               f"are 7E3's facet backs and back structure (and {', '.join(others) or 'no other heliostat'}) seen "
               "across 8E3; the grey, strongly polarized parts reflect the sky; the white parts at the left "
               f"reflect the distant ground ({100 * res['ground_fraction_of_hua']:.0f} % of 8E3's pixels), next to "
               "real ground at the frame's left edge. Lines are facet gaps. "
               f"8E3 facets not in the frame: {', '.join(map(str, missing)) or 'none'}.")
    figure(fr, title, caption, OUT_DIR / "render_ufacet.png")
    return res


# --------------------------------------------------------------------------- scene 2: sky-vs-sky


def _sky_view(pose, i_front: int, i_back: int, env: Environment, min_dolp_difference: float = 0.2):
    """:func:`pihim.render.views.sky_vs_sky_view` with this figure's camera and settings."""
    return sky_vs_sky_view(pose, i_front, i_back, env, CAMERA, sun_clearance_deg=SUN_CLEARANCE_DEG,
                           min_overlap_px=MIN_OVERLAP_PX, edge_samples=EDGE_SAMPLES,
                           min_dolp_difference=min_dolp_difference)


def sky_scene(field: object) -> dict:
    t = parse_time("2021-05-13T09:30-06:00")
    sun = sun_position(NSTTF, t)
    env = Environment.clear_sky(sun.vector)
    track = track_field(field, sun.vector, UFACET_AIM_POINT)
    i_f, i_b = field.index("8E3"), field.index("9E3")
    n = len(field.names)
    drive = track.drive
    az = np.full(n, 180.0)
    el = np.full(n, 90.0)
    az[[i_f, i_b]] = drive.azimuth_deg[[i_f, i_b]]
    el[[i_f, i_b]] = drive.elevation_deg[[i_f, i_b]]
    paper = _sky_view(track.with_drive(az, el), i_f, i_b, env, min_dolp_difference=0.0)
    normals_deg = math.degrees(math.acos(min(1.0, float(track.normals[i_f] @ track.normals[i_b]))))
    back_face_up = paper is None or not paper.dolp_difference > SKY_DOLP_DIFFERENCE_MIN
    if back_face_up:
        az[i_b], el[i_b] = 180.0, 90.0
    pose = track.with_drive(az, el)
    best = _sky_view(pose, i_f, i_b, env) if back_face_up else paper
    if best is None:
        raise SystemExit("sky-vs-sky: no camera position satisfies the criteria")
    cam_pose = best.camera_pose()
    fr = render_frame(field_scene(pose), CAMERA, cam_pose, env)
    # measure across the front's top edge at the middle of the overlap: a = front, b = back
    ov = sky_overlap(pose, i_f, i_b, CAMERA, best.camera_m, look_at_m=best.look_at_m)
    edge = ov.edge_px
    centre_f = project_points(CAMERA, cam_pose, pose.mirror_centres[i_f][None])[0]
    lab = fr.labels
    sky_mirror = (lab[..., 0] == MIRROR) & (lab[..., 3] == SKY)
    m = measure_edge(fr, edge[ov.inside].mean(axis=0), _edge_normal(edge[0], edge[-1], centre_f),
                     sky_mirror & (lab[..., 1] == i_f), sky_mirror & (lab[..., 1] == i_b), ("F", "B"))
    ddolp = abs(m.dolp.difference)
    res = {"camera": cam_pose, "sun": sun, "frame": fr, "measured": m, "s0_contrast": m.s0.contrast,
           "range_m": float(np.linalg.norm(best.look_at_m - cam_pose.position_m)),
           "dolp_difference": ddolp, "predicted": best, "paper_arrangement": paper, "back_face_up": back_face_up}
    arrangement = ("8E3 tracking, 9E3 and every other heliostat face-up" if back_face_up
                   else "8E3 and 9E3 tracking, every other heliostat face-up")
    title = (f"Sky-vs-sky: front 8E3 over back 9E3, 2021-05-13 09:30 MDT (sun zenith {sun.zenith_deg:.1f} deg, "
             f"azimuth {sun.azimuth_deg:.1f} deg)\n{_where(cam_pose)}\n"
             f"measured across the overlapping edge: S0 Michelson contrast {m.s0.contrast:.3f}, "
             f"DoLP {m.dolp.mean_a:.3f} (front) vs {m.dolp.mean_b:.3f} (back), difference {ddolp:.3f}")
    why = ""
    if back_face_up:
        why = (f"With the pair tracking (the paper's set-up) no camera position reaches the paper's 0.2: the best "
               f"predicted DoLP difference is {(paper.dolp_difference if paper else float('nan')):.3f} (the two normals differ by "
               f"{normals_deg:.1f} deg), "
               "so 9E3 is set face-up here. ")
    caption = (f"{arrangement}. {why}The camera maximises the predicted DoLP difference "
               f"({best.dolp_difference:.3f}: {best.front_dolp:.3f} vs {best.back_dolp:.3f}) over a 1 m grid "
               f"south of the pair, 15-30 m up, within 60 m, with both reflections at least {SUN_CLEARANCE_DEG:.0f} "
               f"deg from the sun and the front's top edge over the back for >= {MIN_OVERLAP_PX:.0f} px. "
               f"ROIs ({ROI_SIZE[0]} x {ROI_SIZE[1]} px, the paper's 200 x 100 px at half resolution): F = front "
               f"mirror reflecting sky ({m.s0.n_a} px), B = back mirror reflecting sky ({m.s0.n_b} px); DoLP "
               f"Michelson contrast {m.dolp.contrast:.3f}, {m.contrast_ratio:.2f} times the S0 contrast. "
               f"Heliostats in view: {', '.join(in_view(fr, field.names))}.")
    edges = ("S0", gradient_magnitude(fr.s0), "DoLP", gradient_magnitude(dolp(fr.s0, fr.s1, fr.s2)))
    figure(fr, title, caption, OUT_DIR / "render_sky_vs_sky.png", rois=m.rois, edges=edges)
    return res


# --------------------------------------------------------------------------- scene 3: ground-vs-ground


def ground_scene(field: object, hua: str = "8E3") -> dict:
    t = parse_time("2021-05-13T09:30-06:00")
    sun = sun_position(NSTTF, t)
    s = sun.vector
    env = Environment.clear_sky(s)
    pose = track_field(field, s, UFACET_AIM_POINT)
    scene = field_scene(pose)
    ih = field.index(hua)
    o = pose.mirror_outline()[ih]
    view = ground_vs_ground_view(pose, ih, env, edge_stretch=GROUND_EDGE_STRETCH, max_pitch_deg=GROUND_PITCH_MAX_DEG,
                                 max_s0_contrast=GROUND_S0_CONTRAST_MAX, scene=scene)
    if view is None:
        raise SystemExit("ground-vs-ground: no camera position satisfies the criteria")
    predicted = {"axial_deg": view.aop_difference_deg, "mirror_dolp": view.mirror_dolp,
                 "ground_dolp": view.ground_dolp, "s0_contrast": view.s0_contrast, "candidates": view.candidates}
    aim = view.look_at_m
    cams = view.camera_m[None]
    j = 0
    cam_pose = CameraPose.look_at(cams[j], aim)
    fr = render_frame(scene, CAMERA, cam_pose, env)
    lab = fr.labels
    px = project_points(CAMERA, cam_pose, np.stack([o[3], o[2], aim, pose.mirror_centres[ih]]))
    # a = the HUA's mirror showing ground, b = the real ground
    m = measure_edge(fr, px[2], _edge_normal(px[0], px[1], px[3]),
                     (lab[..., 0] == MIRROR) & (lab[..., 1] == ih) & (lab[..., 3] == GROUND),
                     lab[..., 0] == GROUND, ("M", "G"))
    res = {"camera": cam_pose, "sun": sun, "frame": fr, "measured": m, "s0_contrast": m.s0.contrast,
           "range_m": float(np.linalg.norm(aim - cam_pose.position_m)),
           "aop_difference_deg": m.aop.difference, "aop_raw_difference_deg": m.aop.raw_difference,
           "predicted": predicted}
    res["in_view"] = in_view(fr, field.names)
    shows = res["mirror_shows"] = what_mirror_shows(fr, ih)
    title = (f"Ground-vs-ground: lower edge of {hua}, 2021-05-13 09:30 MDT (sun zenith {sun.zenith_deg:.1f} deg, "
             f"azimuth {sun.azimuth_deg:.1f} deg)\n{_where(cam_pose)}\n"
             f"measured across the edge: S0 Michelson contrast {m.s0.contrast:.3f}, AoP {m.aop.mean_a:.1f} deg "
             f"(mirror) vs {m.aop.mean_b:.1f} deg (ground), axial difference {m.aop.difference:.1f} deg")
    caption = ("Whole field tracking the UFACET aim point. The camera is the position of a 1 m grid (15-30 m up, "
               f"within 40 m, pitch <= {GROUND_PITCH_MAX_DEG:.0f} deg) where the mirror shows ground (nothing in the "
               "way), the predicted axial AoP difference exceeds 50 deg, the real and the reflected ground are "
               f"sunlit and the S0 contrast is <= {GROUND_S0_CONTRAST_MAX}, whose weaker DoLP is largest "
               f"(predicted: AoP difference {predicted['axial_deg']:.1f} deg, DoLP {predicted['mirror_dolp']:.3f} "
               f"mirror, {predicted['ground_dolp']:.3f} ground, S0 contrast {predicted['s0_contrast']:.3f}). "
               f"ROIs ({ROI_SIZE[0]} x {ROI_SIZE[1]} px): M = {hua}'s mirror reflecting ground ({m.s0.n_a} px, "
               f"DoLP {m.dolp.mean_a:.3f}), G = real ground ({m.s0.n_b} px, DoLP {m.dolp.mean_b:.3f}). "
               f"Heliostats in view: {', '.join(res['in_view'])}. Of {hua}'s mirror pixels "
               f"{100 * shows['ground']:.0f} % show ground, {100 * shows['heliostats']:.0f} % the backs of other "
               f"heliostats (dark), {100 * shows['sky']:.0f} % sky. Dark bands on the ground are heliostat "
               "shadows, striped by sunlight through the facet gaps.")
    edges = ("S0", gradient_magnitude(fr.s0), "AoP (axial: of cos 2AoP, sin 2AoP)",
             axial_gradient_magnitude(aop_deg(fr.s1, fr.s2)))
    figure(fr, title, caption, OUT_DIR / "render_ground_vs_ground.png", rois=m.rois, edges=edges)
    return res


# --------------------------------------------------------------------------- main


def main() -> int:
    t0 = time.perf_counter()
    field = nsttf_like_field()
    u = ufacet(field)
    print(f"UFACET: {_where(u['camera'])}, {u['range_m']:.1f} m from 8E3's mirror centre; "
          f"render {u['frame'].stats['seconds']:.1f} s")
    print(f"  8E3 fills {u['hua_fraction']:.3f} of the frame; of its pixels {u['target_fraction_of_hua']:.3f} show "
          f"7E3, {u['sky_fraction_of_hua']:.3f} sky (DoLP {u['hua_sky_dolp']:.3f}); facets in view "
          f"{u['facets_in_view']}; facets showing 7E3 {u['facets_showing_target']}")
    s = sky_scene(field)
    p, q = s["paper_arrangement"], s["predicted"]
    pd = f"{p.dolp_difference:.3f} at {p.camera_m.round(1)}" if p else "none above 0"
    print(f"sky-vs-sky: paper arrangement best predicted DoLP difference {pd}; back face-up: {s['back_face_up']}")
    print(f"  {_where(s['camera'])}, {s['range_m']:.1f} m from the overlap; predicted {q.dolp_difference:.3f} "
          f"({q.front_dolp:.3f} vs {q.back_dolp:.3f}, S0 {q.front_s0:.1f} vs {q.back_s0:.1f}, {q.candidates} "
          f"candidates, sun angles {q.sun_angles_deg[0]:.1f}/{q.sun_angles_deg[1]:.1f} deg, overlap "
          f"{q.overlap_px:.0f} px)")
    m = s["measured"]
    print(f"  measured: S0 {m.s0.mean_a:.2f} vs {m.s0.mean_b:.2f} -> Michelson {m.s0.contrast:.3f}; "
          f"DoLP {m.dolp.mean_a:.3f} vs {m.dolp.mean_b:.3f} -> difference {s['dolp_difference']:.3f}, Michelson "
          f"{m.dolp.contrast:.3f}, ratio to S0 {m.contrast_ratio:.2f}; AoP {m.aop.mean_a:.1f} vs {m.aop.mean_b:.1f} "
          f"deg, axial difference {m.aop.difference:.1f} deg; ROI pixels {m.s0.n_a}/{m.s0.n_b}")
    g = ground_scene(field)
    pr = g["predicted"]
    print(f"ground-vs-ground: {_where(g['camera'])}, {g['range_m']:.1f} m from the edge; {pr['candidates']} "
          f"candidates; predicted: axial AoP difference {pr['axial_deg']:.1f} deg; DoLP {pr['mirror_dolp']:.3f} vs "
          f"{pr['ground_dolp']:.3f}; S0 contrast {pr['s0_contrast']:.3f}")
    m = g["measured"]
    print(f"  measured: S0 {m.s0.mean_a:.2f} vs {m.s0.mean_b:.2f} -> Michelson {m.s0.contrast:.3f}; "
          f"AoP {m.aop.mean_a:.1f} vs {m.aop.mean_b:.1f} deg -> axial {m.aop.difference:.1f} deg "
          f"(raw {m.aop.raw_difference:.1f}); DoLP {m.dolp.mean_a:.3f} vs {m.dolp.mean_b:.3f}; "
          f"ROI pixels {m.s0.n_a}/{m.s0.n_b}")
    files = ("render_ufacet.png", "render_sky_vs_sky.png", "render_ground_vs_ground.png")
    print(f"wrote {', '.join(str(OUT_DIR / n) for n in files)}"
          f" in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
