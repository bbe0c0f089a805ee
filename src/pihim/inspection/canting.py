"""Per-facet canting from the target's reflection in the HUA (paper sec. 4.4, steps 3-4).

A facet is a small plane mirror: the camera sees the target heliostat through
it as the **mirror image** of the target in the facet's plane. The target's
facet outlines (known from the field model and its logged drive angles),
reflected in facet ``k``'s plane and projected with the (refined) camera
pose, fall where the image shows the target's edges inside facet ``k``. The
facet's two canting angles move them: a tilt ``d`` turns the reflected rays by
``2 d``, which at the usual UFACET geometry moves the reflection by several
pixels per mrad.

The heliostat's **orientation** (the paper's relative-orientation step):
the camera pose is refined on the HUA's outline at its *logged* drive
angles, so it is right relative to the HUA; a HUA really turned from those
angles sees the target turned back about the HUA's pivot
(:func:`hua_turn_transform`): moved by the turn times the distance (tens of
centimetres per 0.5 deg) *and* turned about itself, which distorts its
reflection by several pixels, more than a facet's canting can absorb.
:func:`search_orientation` turns the HUA's drive angles over the paper's
+-5 deg in 0.1 deg steps and finds the node where the facets' reflections
of the target best line up with the image's edges; the facets are fitted on
the target's outline turned by it, and on the logged outline, and the turn
is kept only if it measures at least two facets more and fits the facets
both measure no more loosely (:func:`_keeps_turn`; the search proposes, the
facet fits decide: clutter can raise a false peak).

Optionally (``target_orientation=True``) the **target's** logged drive
angles are corrected too, as the paper does: a target off its logged
orientation has a distorted outline in the model, and the facets' fits miss
by a few pixels; :func:`refine_orientations` solves the target's two
angles with every facet's canting (and the HUA's turn), and the facets are
fitted again on the corrected outline.

Then for each facet:

1. **Baseline** (the paper's method): a grid search over azimuth and
   elevation deviations with the paper's step, 0.1 deg = 1.745 mrad, scored by
   the share of the projected model points that lie within 5 px of an image
   edge (a truncated chamfer score).
2. **Refinement**: from the grid's best nodes and the best peaks of a grid
   four times finer and tighter (2 px; the paper's step is coarse beside a
   fit's basin), Levenberg-Marquardt on the point-to-line distances between
   the image's sub-pixel edge points inside the facet and the projected
   reflected outlines, re-matched with a shrinking gate. A fit whose outline
   mostly leaves the facet, matching far fewer edge points more loosely, is
   no rival of one that matches many (the support, a share, does not see it).
   Once the HUA's turn and the target's correction are chosen, the final fits
   start again half a grid step and a grid step away along each axis from
   every fit that passes the gates, as the outline's parallel edges leave
   local minima half a step to a few steps apart (a clearly better supported
   fit wins; two fits more than half a step apart supported alike leave the
   facet skipped as ambiguous). Eight more start one and a half and two and a
   half grid steps from the final winner, where the target's repeating back
   gives lattice basins: one supported alike that fits the edges at least as
   tightly (RMS residual), or one clearly better supported, also leaves the
   facet ambiguous. The uncertainty is a delete-one-segment jackknife of the
   last round over the target outline's segments the facet shows
   (:mod:`pihim.inspection.uncertainty`).

A rotation common to every facet cannot be told from a heliostat pointing
(or camera pose) error, so :class:`CantingResult` reports each facet's
deviation **relative to the best-fit heliostat orientation** (the mean over
the facets used) and that orientation separately.

The estimator reads the frame and the ``log`` only; its forward model is
projection of mirrored points (:mod:`pihim.inspection.reflection`; the
compiled projection of :mod:`pihim.inspection._kernels`, held to
``cv2.projectPoints``), independent of the renderer's ray tracer that made
the test frames; the orientation steps are in
:mod:`pihim.inspection.orientation` (re-exported here).

Status (measured on rendered NSTTF UFACET frames, ``benchmarks/canting_quality.py``)
------------------------------------------------------------------------------------
From the issue's GPS 1.5 m / attitude 1 deg priors (pose refined to 0.27 px
median at the HUA's corners) and S0 edge points (the DoLP of the dark target
back is too noisy at 39 dB to add its edges unweighted), 0-10 facets per
frame pass the quality gates (77 scored on the issue's 20 frames) and their deviations are
recovered to 0.012 / 0.018 mrad RMS (azimuth / elevation; the largest error
0.08 mrad; the HUA's drive-angle correction to 0.10 / 0.08 mrad) against
0.82 / 0.48 mrad for the paper's grid search on the same facets; about 1.3 s
of CPU per frame for this step (2026-11-28). On the 20 frames after those
(``--frames 40``), which the steps above were not developed on, two more
failures showed, each on one frame, and are now gated (the ``min_spread``
and ``orientation_span_mrad`` parameters): a facet fitted along a single
straight edge, and a turn of the HUA kept for measuring one facet more than
the logged angles; over the 40 frames 117 facets at 0.010 / 0.016 mrad, the
largest error 0.08 mrad (120 at 0.110 / 0.060, largest 1.0 mrad, without the
two gates). Frames 40-59 then had six facets 0.9-4.2 mrad off, locked
(all segments agreeing, so the jackknife sigma is small) in a basin half a
step to 2.5 grid steps from the true one: the final fits now also start
half a step away, and fits half a step apart supported alike make a facet
ambiguous. Over 80 frames (``--frames 80``) 236 facets at 0.058 / 0.018
mrad, the largest error 0.62 mrad; on frames 60-79, rendered after every
choice here was made, 60 facets at 0.010 / 0.015 mrad, largest 0.07 (the
code before these three changes: 63 at 0.46 / 0.04, ten 0.5-3.0 mrad off);
about 1.5 s of CPU per frame for this step. On 80 more frames rendered
after that (100-179), 273 facets: 0.30 / 0.04 mrad on 100-139, where one
frame kept two facets mostly outside the picture 3.2 mrad off (their true
basins, a lattice step away, supported alike and fitted tighter; it moved
its frame's other three facets 1.3 mrad), and 0.029 / 0.047 mrad, largest
0.31, on 140-179. The far rivals (``_FAR_STEPS``) now skip those two as
ambiguous and no other facet of the 180 frames: 570 facets at 0.051 / 0.029
mrad, largest 0.67. **On 120 frames rendered with new seeds** (2000-2119,
``--seed-offset 2000``), unseen by every choice above: 406 facets at 0.75 /
0.23 mrad, over the 0.5 mrad target in azimuth (on their second half 0.72
/ 0.30 with the far rivals, 0.80 / 0.40 without: they skipped four wrong
locks there and nothing else). Four facets were locked on a wrong feature
2.8-12.9 mrad off (absolute; 2.8-8.5 relative to their frame's mean); where
probed, the true fit has more matched points and a tighter residual but
less support (the share of the outline on an edge favours a fit that leaves
little of it inside the facet), and is no peak of the paper's grid.

**Fine-grid starts and dominated rivals** (``_FINE_PEAKS``, ``_DOMINANCE``;
chosen on frames 2000-2043 of those, 2026-11-28): fitted from its true
angles, a facet passed the gates 329 times there, and the estimator had
found that basin only 152 times; a grid four times finer and tighter than
the paper's (over +-5 steps) has it as its best peak 296 times. With both:
the issue's 20 frames 101 facets at 0.024 / 0.028 mrad (77 at 0.012 /
0.018 before), the largest error 0.13; seeds 2000-2119 594 facets at **0.22 / 0.089 mrad**
(406 at 0.75 / 0.23), the largest 2.87 (facets of seeds 2088, 2100 and
2112 2.5-2.9 mrad off relative to their frame's mean; not probed); on 60
frames rendered after the choice (seeds 3000-3059) 281 facets at **0.34 /
0.13 mrad** (185 at 0.041 / 0.014 before), the largest 4.65: frame 3040's
facet 17, whose target reflection lies outside the facet, locked on other
edges 6.6 mrad off its true canting, as before the change, when it was its
frame's only facet (so unscored, but it set the HUA's drive-angle
correction); now two more facets there make it count. The HUA's drive-angle
correction got worse on the issue's frames (0.12 / 0.62 mrad RMS against
0.10 / 0.08): on seed 5 the orientation search's turn (5 mrad in
elevation, none in truth) now measures two facets more than the logged
angles and is kept (2.6 mrad off in elevation); its facets' deviations stay
within 0.15 mrad. About
0.9 s more per frame (1.0 s of CPU; 5.8 s against 4.9 s median on this
day's machine, over the 3 s target either way; BENCHMARKS.md). Then a
fit's rounds were compiled (:func:`pihim.inspection._kernels.reflect_in_mask`,
a window of the outline points near the facet, the matching's cells) and, of two equally near outline
samples (every corner), the one whose line passes nearest the edge point is
matched instead of a k-d tree's pick: 2.8 s median per frame (the canting
step 2.1 s) on a machine that took 4.7 s the same hour; 103 / 598 / 279
facets at 0.024 / 0.028, 0.216 / 0.086 and 0.345 / 0.129 mrad on the
issue's frames, seeds 2000-2119 and 3000-3059 (2026-11-28). A turn of the
HUA must now also fit the facets both outlines measure no more loosely
(``_keeps_turn``): the wrong turns of seeds 5 and 2113 are refused (the
HUA's drive-angle correction 0.10 / 0.07 mrad RMS on the issue's frames
instead of 0.12 / 0.62), 102 / 595 / 279 facets at 0.008 / 0.020, 0.217 /
0.082 and 0.345 / 0.129 mrad; with drive-angle errors of 5 mrad, the same
results as before on 20 frames. Seed 2088 keeps a correction 1.1 mrad off.
A fit is now one compiled call (:func:`pihim.inspection._kernels.refine_reflection`) and a
facet's refinements run on threads: the same fits, 2.2 s median per frame (the canting step
1.55 s) on a machine that took 3.6 s with the code before the same hour.

Before the final fits tried the
neighbouring basins: 87 facets at 0.15 / 0.16 mrad, six of them 0.6-1.15
mrad off, mostly in a basin next to the true one, which also moved the
other facets of their frame (every value is relative to the mean), 1.1 s of
CPU. With every heliostat's logged drive angles off by N(0, 5 mrad),
``target_orientation=True`` measures 32 facets on 10 frames to 0.04 / 0.11
mrad, the largest error 0.27 (37 at 0.35 / 0.33 before the basins) at about
3.5 s more CPU; without it, 2 facets (BENCHMARKS.md). Not yet: polarimetric edge points. Edge
points from a gradient of S0, DoLP and AoP each divided by its pixel's noise
(:func:`pihim.inspection.edges.noise_sigmas`) were tried on 8 of those
frames: 2 facets measured instead of 33, one pose failure, 10.8 s instead of
2.2 s per frame (the target's reflection in DoLP adds points that break the
fits' sub-pixel consistency); the chain stays on S0. Also tried (the 20
frames of ``benchmarks/canting_quality.py``, 2026-11-26): refinements seeded
from the peaks of a grid four times finer than the paper's (tolerance 3 px),
the fit with the most matched points kept: 148 facets measured instead of
87, 3 of them locked 1.7-2.4 mrad off instead of 5 at 0.8-1.3 mrad, but
about 3.8 s of CPU per frame for this step, over the 3 s budget of the whole
chain; not kept. Tried on 2026-11-28 and not kept: the neighbouring basins
in every fit, also those that choose the HUA's turn and the target's
correction (84 facets at 0.028 / 0.029 mrad, but one HUA's drive-angle
correction went 2.6 mrad off in elevation, and with the target's correction
at drive-angle errors of 5 mrad one facet 4.7 mrad off), and from fits that
fail the gates (5 more facets, one of them 0.8 mrad off).

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone", sec. 4.4 and Fig. 8 (grid search +-5 deg at 0.1 deg,
   facet canting deviations relative to the design).
.. [2] Sandia National Laboratories, OpenCSP UFACET (the reflected-target
   principle of facet canting measurement).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose
from pihim.errors import PihimInputError
from pihim.field.kinematics import FieldPose
from pihim.inspection.features import EdgePoints
from pihim.inspection.orientation import (
    PAPER_GRID_STEP_MRAD,
    PAPER_ORIENTATION_SPAN_MRAD,
    OrientationSearch,
    drive_correction,
    refine_orientations,
    search_orientation,
)
from pihim.inspection.reflection import (
    _apply,
    _equivalent_tilt,
    _facet_masks,
    _FacetModel,
    _Mask,
    _TurnModel,
    facet_in_view,
    hua_turn_transform,
    target_outline_segments,
)
from pihim.inspection._threads import ordered_map
from pihim.inspection.pose import sample_segments
from pihim.inspection.uncertainty import jackknife_covariance, relative_variance
from pihim.render.scene import StructureSizes

__all__ = ["CantingResult", "FacetCanting", "OrientationSearch", "PAPER_GRID_STEP_MRAD", "PAPER_ORIENTATION_SPAN_MRAD",
           "drive_correction", "estimate_canting", "hua_turn_transform", "refine_orientations",
           "search_orientation", "target_outline_segments"]

#: Scale of the two canting angles in the refinement, mrad.
_X_SCALE = np.array([0.1, 0.1])
#: ``run(fn, items)``: an ordered map, e.g. on threads (:func:`pihim.inspection._threads.ordered_map`).
_Run = Callable[[Callable[[Any], Any], Iterable[Any]], list]


class _Gates(NamedTuple):
    """What a facet's fit must show to be used (:func:`estimate_canting`'s parameters of the same names)."""

    min_points: int
    max_rms_px: float
    min_support: float

    def passed(self, points: int, rms_px: float, support: float) -> bool:
        return points >= self.min_points and rms_px <= self.max_rms_px and support >= self.min_support


#: Rounds of refinements from the neighbouring basins in the facets' final fits (:func:`_settle`); two
#: measured as good as four on 20 rendered frames (2026-11-28).
_BASIN_ROUNDS = 2
#: Where the refinements of a round start, in grid steps from the winner along each axis (:func:`_settle`), and
#: how far apart, in grid steps, two fits supported alike must be to leave a facet ambiguous. With starts a step
#: away only and fits a step apart, frames 40-79 of ``benchmarks/canting_quality.py`` had seven facets locked
#: 0.5-4.2 mrad off in a basin half a step to 2.5 steps from the true one, some supported within the margin of
#: it. Chosen on frames 40-59 and then checked on 60-79, which it had not seen: there the facets' RMS error went
#: from 0.19 / 0.03 mrad (three locked 0.5-1.6 mrad off) to 0.010 / 0.014 mrad, 63 facets instead of 67 (the
#: estimator alone; the benchmark scores 60, in frames with two or more; 2026-11-28).
_BASIN_STEPS = (0.5, 1.0)
_DISTINCT_STEPS = 0.5
#: Where the far rivals of a facet's final fit start, in grid steps from the settled winner along each axis
#: (:func:`_settle`). The target's back repeats (its facets' sides, the gaps, the crossbars), so a facet that
#: shows only part of it also fits a lattice step away, about 2.5-4.5 mrad at UFACET distances, out of reach of the
#: neighbouring basins: in frame 117 of ``benchmarks/canting_quality.py`` two facets 19 and 30 % in view were
#: measured 3.2 mrad off, their true fits supported alike (0.55 and 0.50 against 0.59 and 0.49) and tighter (RMS
#: residual 0.08 and 0.12 px against 0.10 and 0.21). A far rival counts in the ambiguity test only when it
#: explains the image as well: supported alike and fitting the edges at least as tightly as the winner, or
#: clearly better supported (by ``support_margin``). Counting every far fit supported alike skipped 46 facets of
#: frames 0-179, 44 of them measured right. Chosen on frames 0-179 and on the pairs of frames 0-59 rendered with
#: seeds 1000-1059 (there two facets were 2.7 and 4.5 mrad off, the second's true basin better supported), then
#: checked on the pairs of frames 60-119 with seeds 2060-2119, which it had not seen: four facets 2.9-4.2 mrad
#: off skipped and no other (211 facets -> 207; the others of their frames had moved up to 0.7 mrad with
#: them), about 0.25 s more CPU per frame (2026-11-28, BENCHMARKS.md).
_FAR_STEPS = (1.5, 2.5)
#: The fine grid's starts (:func:`_fine_peaks`): how many of its best peaks (away from the paper grid's) each
#: facet's first fits also start from, its nodes per paper grid step, its half-range in paper grid steps, its
#: tolerance, px, and which of the paper grid's outline samples it scores (every second: every 12 cm). The
#: paper's grid (1.75 mrad, 5 px) is coarse beside a facet fit's basin (a few px per mrad): on 44 rendered frames
#: (``benchmarks/canting_quality.py --seed-offset 2000``, seeds 2000-2043) 329 facets fitted from their true
#: angles pass the gates, but the estimator found that basin for 152 of them (125 ended in another basin, mostly
#: then failing the gates; 52 ambiguous). A grid of quarter steps, 2 px, over +-5 steps had its best peak within
#: 0.75 steps of the true angles for 296 of the 329, its second for 23 more (2026-11-28). Over +-4 steps with
#: every second sample it costs 0.2 s of CPU per frame instead of 0.7, and measured 110 / 321 facets on the
#: issue's frames / seeds 3000-3059 against 112 / 316 (with the first version of ``_DOMINANCE``; BENCHMARKS.md).
_FINE_PEAKS = 2
_FINE_SUB = 4
_FINE_SPAN = 4.0
_FINE_TOL_PX = 2.0
_FINE_STRIDE = 2
#: A fit with fewer than 1/``_DOMINANCE`` of another's outline samples inside the facet, matching fewer than
#: 1/``_DOMINANCE`` of its image edge points and more loosely (larger RMS residual), neither displaces it nor
#: makes the facet ambiguous (:func:`_dominated`). The share of the outline on an edge (support) favours a fit
#: that leaves most of the outline outside the facet: of 584 wrong fits beside a true one on those 44 frames, 48
#: were better supported by the margin, 19 matched 1.2 times as many points and 11 fitted 0.8 times as tightly.
#: Without the condition on the samples inside, the rule let a fit 0.76 mrad off win over its rival 2.5 mrad away
#: (``tests/cli/test_cli_canting.py``'s frame, facet 8).
_DOMINANCE = 1.2
#: How far, px, from a facet's mask (its bounding box) the outline points a fit's rounds project reach
#: (the window of :func:`pihim.inspection._kernels.refine_reflection`).
_WINDOW_PX = 40.0


@dataclass(frozen=True)
class FacetCanting:
    """One facet's estimate (mrad, heliostat frame, conventions of :mod:`pihim.field.kinematics`).

    ``az_mrad`` / ``el_mrad`` are relative to the best-fit heliostat
    orientation; ``grid_*`` are the paper's grid-search values (same
    reference); ``used`` is False with ``reason`` for a skipped facet.
    ``az_sigma_mrad`` / ``el_sigma_mrad`` are standard errors of the relative
    deviations from a delete-one-segment jackknife of the fit
    (:mod:`pihim.inspection.uncertainty`; None with fewer than three target
    outline segments matched); they leave out camera pose errors and a fit
    locked onto other features. ``in_view`` is the share of the facet's
    outline inside the frame from the pose the fit used
    (:func:`pihim.inspection.reflection.facet_in_view`; mean over the frames
    that measured it when combined): on 140 rendered frames a facet less than
    half in view was more than 0.5 mrad off six times as often as one at
    least half in view (BENCHMARKS.md, canting).
    """

    id: int
    used: bool
    reason: str | None = None
    az_mrad: float | None = None
    el_mrad: float | None = None
    az_sigma_mrad: float | None = None
    el_sigma_mrad: float | None = None
    grid_az_mrad: float | None = None
    grid_el_mrad: float | None = None
    points: int = 0
    rms_px: float | None = None
    support: float | None = None
    in_view: float | None = None

    def to_dict(self) -> dict[str, object]:
        return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class CantingResult:
    """Canting of one HUA from one or more frames.

    Attributes
    ----------
    facets : tuple of FacetCanting
        In facet order 1..F.
    orientation_az_mrad, orientation_el_mrad : float
        Best-fit heliostat orientation: the mean raw facet rotation of the
        used facets (what the relative deviations are relative to).
    search : OrientationSearch or None
        The paper's +-5 deg orientation grid search the facet fits started
        from (None when it was not run).
    drive_correction_deg : (float, float) or None
        Correction of the HUA's logged drive angles, (azimuth, elevation) in
        degrees: the orientation search's turn where the facets were fitted
        on it, plus the drive-angle change that turns the heliostat's normal
        as the best-fit orientation does (a rotation common to the facets
        cannot be told from the HUA's turn, so their mean canting is in it).
    target_correction_deg : (float, float) or None
        Correction of the target's logged drive angles (azimuth, elevation),
        degrees, when the facets were measured on the target's corrected
        outline (:func:`refine_orientations`); None when its logged
        angles were kept.
    """

    hua: str
    target: str
    facets: tuple[FacetCanting, ...]
    orientation_az_mrad: float | None
    orientation_el_mrad: float | None
    frames: int = 1
    notes: tuple[str, ...] = field(default_factory=tuple)
    search: OrientationSearch | None = None
    drive_correction_deg: tuple[float, float] | None = None
    target_correction_deg: tuple[float, float] | None = None

    def to_dict(self) -> dict[str, object]:
        return {
            "hua": self.hua,
            "target": self.target,
            "frames": self.frames,
            "reference": "facet deviations relative to the best-fit heliostat orientation (mean over used facets)",
            "orientation_mrad": None if self.orientation_az_mrad is None else
            {"az": float(self.orientation_az_mrad), "el": float(self.orientation_el_mrad)},
            "orientation_search": None if self.search is None else self.search.to_dict(),
            "drive_correction_deg": None if self.drive_correction_deg is None else
            {"az": float(self.drive_correction_deg[0]), "el": float(self.drive_correction_deg[1])},
            "target_correction_deg": None if self.target_correction_deg is None else
            {"az": float(self.target_correction_deg[0]), "el": float(self.target_correction_deg[1])},
            "facets": [f.to_dict() for f in self.facets],
            "notes": list(self.notes),
        }


class _Start(NamedTuple):
    """A facet's grid search and the refinements from its peaks (:func:`_first_fits`)."""

    grid_az: float
    grid_el: float
    ob: NDArray  # the image's edge points inside the facet
    fits: list  # the refined fits from the grid's peaks, nearest the preferred angles first
    best: tuple  # the winner among them


def _first_fits(model: _FacetModel, mask: _Mask, obs: NDArray, dt: NDArray, span_mrad: float, step_mrad: float,
                gates_px: tuple[float, ...], grid_tol_px: float = 5.0, centre_mrad: tuple[float, float] = (0.0, 0.0),
                prefer_mrad: tuple[float, float] | None = None, ambiguity: float = 0.05, max_peaks: int = 3,
                support_margin: float = 0.05, run: _Run | None = None) -> _Start:
    """A facet's grid search and the refinements from its peaks (raw angles); :func:`_settle` finishes the fit.

    The grid spans ``+-span_mrad`` around ``centre_mrad`` (default the
    design; :func:`estimate_canting` turns the target's outline with the
    HUA's orientation instead of moving the grid). The grid values kept are
    the paper's (the best node); the refinement starts from each of up to
    ``max_peaks`` local peaks of the grid scoring within ``ambiguity`` of
    the best, and from the ``_FINE_PEAKS`` best peaks of a grid four times
    finer and tighter (2 px) over +-4 paper steps (:func:`_fine_peaks`),
    nearest ``prefer_mrad`` (default the centre) first: the
    target's back is periodic (facet rows and columns, crossbars), so a
    facet that sees only part of it matches almost as well one period away
    (5-30 mrad at UFACET distances). The refined fit whose reflected outline
    lies best on the image's edges (support, the share within 1.5 px) wins;
    a farther peak must beat a nearer one by ``support_margin``, and not be
    dominated by it (:func:`_dominated`: its outline mostly outside the
    facet, far fewer matched edge points, fitted more loosely).

    The refinement rounds solve the two angles by trust-region least squares
    with a soft-L1 loss (scale 0.5 px) and the analytic Jacobian of the
    mirrored projection (:func:`pihim.inspection._kernels.solve`). Raises
    :class:`~pihim.errors.PihimInputError` when no outline falls inside the
    facet, it holds too few edge points, or no refinement converges.
    """
    from pihim.inspection import _kernels

    # 1. the paper's grid search: every node of the grid, scored by the share of the reflected
    #    outline (inside the facet) within ``grid_tol_px`` of an image edge; the peak is narrow
    #    (a few px per mrad), so no coarser pre-search
    n_half = int(np.floor(span_mrad / step_mrad + 1e-6))
    grid = step_mrad * np.arange(-n_half, n_half + 1)  # symmetric, zero (the design or centre) a node
    gaz, gel = (g.ravel() for g in np.meshgrid(grid, grid, indexing="ij"))
    coarse_model = model.subsampled(6)  # every 6 cm of outline: the score is a share, not a sum
    # every grid node at once, from the quadratic through the nodes {-s, 0, s}^2
    coef = coarse_model.quadratic_coefficients(max(float(np.max(np.abs(grid))), 1.0), centre_mrad)
    hh, ww = mask.sub.shape
    dt_crop = np.ascontiguousarray(dt[mask.r0:mask.r0 + hh, mask.c0:mask.c0 + ww])
    score = _kernels.grid_scores(coef, grid, grid, mask.sub, mask.r0, mask.c0, dt_crop, float(grid_tol_px), 10)
    k = int(np.argmax(score))  # first maximum: the same node the loop over az, then el, kept
    g_best = (float(score[k]), float(gaz[k]) + centre_mrad[0], float(gel[k]) + centre_mrad[1])
    if g_best[0] < 0:
        raise PihimInputError("no reflected target outline falls inside this facet")
    grid_az, grid_el = g_best[1], g_best[2]
    # 2. continuous refinement: point-to-line ICP with LM, from each distinct near-best peak of the grid (the
    #    nearest the preferred angles first); the refined fit whose outline is best supported by the image wins
    pa, pe = centre_mrad if prefer_mrad is None else prefer_mrad
    from scipy import ndimage

    n_g = len(grid)
    sc = score.reshape(n_g, n_g)
    peaks = np.flatnonzero(((sc == ndimage.maximum_filter(sc, size=5, mode="nearest"))
                            & (sc >= (1.0 - ambiguity) * g_best[0])).ravel())
    if peaks.size == 0:
        peaks = np.array([k])
    peaks = peaks[np.argsort((gaz[peaks] + centre_mrad[0] - pa) ** 2 + (gel[peaks] + centre_mrad[1] - pe) ** 2)]
    ob = obs[mask.inside(obs)]
    if len(ob) < 20:
        raise PihimInputError("too few edge points inside this facet")
    starts = [(float(gaz[k0]) + centre_mrad[0], float(gel[k0]) + centre_mrad[1])
              for k0 in peaks[:max_peaks]]
    if _FINE_PEAKS:
        starts += _fine_peaks(coef, mask, dt_crop, step_mrad, centre_mrad, starts)
        starts.sort(key=lambda s: (s[0] - pa) ** 2 + (s[1] - pe) ** 2)
    tried = _refinements(model, mask, ob, dt, gates_px, starts, run)
    fits = [fit for fit in tried if not isinstance(fit, PihimInputError)]
    if not fits:
        raise tried[-1]
    best = fits[0]
    for fit in fits[1:]:  # a farther peak must be clearly better supported to displace a nearer one
        if fit[4] > best[4] + support_margin and not _dominated(fit, best):
            best = fit
    return _Start(grid_az, grid_el, ob, fits, best)


def _dominated(fit: tuple, by: tuple) -> bool:
    """Whether ``fit`` is no rival of ``by``: its reflected outline mostly leaves the facet (fewer than
    1/``_DOMINANCE`` of ``by``'s outline samples inside it), where it matches fewer than 1/``_DOMINANCE`` of
    ``by``'s image edge points (inliers), and more loosely (larger RMS residual). Such a fit keeps a high support
    (a share) on the few samples left inside."""
    d = _DOMINANCE
    return d is not None and fit[7] * d < by[7] and fit[2] * d < by[2] and fit[3] > by[3]


def _fine_peaks(coef: NDArray, mask: _Mask, dt_crop: NDArray, step_mrad: float, centre_mrad: tuple[float, float],
                taken: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Starting angles (raw, mrad) from a grid finer and tighter than the paper's: its best peaks away from ``taken``.

    The same chamfer share as the paper's grid search (:func:`pihim.inspection._kernels.grid_counts`, on every
    ``_FINE_STRIDE``-th point of the paper grid's quadratic model ``coef``), on nodes ``step_mrad / _FINE_SUB``
    apart over ``+-_FINE_SPAN`` paper steps around ``centre_mrad``, a point scoring within ``_FINE_TOL_PX`` of an
    edge; local maxima over +-half a paper step, best first; at most ``_FINE_PEAKS`` of them, each more than
    ``_DISTINCT_STEPS`` paper steps from every start in ``taken`` and from each other.
    """
    from scipy import ndimage

    from pihim.inspection import _kernels

    sub = _FINE_SUB
    n = int(round(_FINE_SPAN * sub))
    grid = step_mrad / sub * np.arange(-n, n + 1)
    coef = np.ascontiguousarray(coef[:, ::_FINE_STRIDE])
    n_in, n_near = _kernels.grid_counts(coef, grid, grid, mask.sub, mask.r0, mask.c0, dt_crop, _FINE_TOL_PX)
    share = np.where(n_in >= 10, n_near / np.maximum(n_in, 1), -1.0).reshape(len(grid), len(grid))
    pk = np.flatnonzero(((share == ndimage.maximum_filter(share, size=sub + 1, mode="nearest")) & (share > 0)).ravel())
    pk = pk[np.argsort(-share.ravel()[pk], kind="stable")]
    out: list[tuple[float, float]] = []
    for k in pk:
        i, j = divmod(int(k), len(grid))
        a, e = float(grid[i]) + centre_mrad[0], float(grid[j]) + centre_mrad[1]
        if all(math.hypot(a - a0, e - e0) > _DISTINCT_STEPS * step_mrad for a0, e0 in taken + out):
            out.append((a, e))
        if len(out) >= _FINE_PEAKS:
            break
    return out


def _settle(model: _FacetModel, mask: _Mask, start: _Start, dt: NDArray, step_mrad: float,
            gates_px: tuple[float, ...], matches: list | None = None, support_margin: float = 0.05,
            basin_rounds: int = 0, gates: _Gates | None = None, run: _Run | None = None) -> tuple:
    """(grid az, grid el, az, el, model, (matches, segments), points, rms, support) for one facet (raw), from ``start``.

    The neighbouring basins: the outline's parallel edges (a target facet's
    two sides, the gaps, the crossbars) give the refinement local minima
    half a grid step to a few steps on either side of the true one, and the
    grid's best node may be a step off; eight refinements started half a
    grid step and a grid step from the winner along each axis
    (``_BASIN_STEPS``) compete with it on support (the best of them wins if
    it beats it by ``support_margin``), again from a new winner,
    ``basin_rounds`` rounds at most. Given ``gates`` (an accepted facet's
    fewest matched points, largest RMS residual and least support), only
    from a winner that passes them, and only a fit that passes them can win
    (all count for the ambiguity test): a fit that has not found the
    target's outline has nothing to improve, and a basin found from it is a
    guess (on 20 rendered frames such rescues added 5 facets, one of them
    0.8 mrad off; 2026-11-28). Two fits more than half a grid step apart
    (``_DISTINCT_STEPS``) whose supports are within ``support_margin`` of
    each other leave the facet ambiguous: it is skipped (raises), unless
    one is dominated by the winner (:func:`_dominated`). With
    ``basin_rounds`` and a winner that passes the gates, so does a far rival
    (``_FAR_STEPS``: refinements started 1.5 and 2.5 grid steps from the
    final winner along each axis) supported alike that fits the image's edges
    at least as tightly as the winner (RMS residual no larger) or is better
    supported by ``support_margin``; a looser one supported alike does not
    count. Given a list ``matches``, the last round's matched model points
    (world), image points and line normals are appended to it as one tuple
    (for :func:`refine_orientations`).
    """
    grid_az, grid_el, ob, fits, best = start
    # 3. the neighbouring basins (see the docstring). Every fit tried is a rival in the ambiguity test, also one
    #    that fails the gates: a basin supported alike is a reason for doubt (counting only those that pass let a
    #    0.55 mrad error through on 20 rendered frames, 2026-11-28)
    def passes(fit: tuple) -> bool:
        return gates is None or gates.passed(fit[2], fit[3], fit[4])

    rivals = list(fits)
    along_az = [(sign * m * step_mrad, 0.0) for m in _BASIN_STEPS for sign in (1, -1)]
    offsets = along_az + [(de, da) for da, de in along_az]
    for _ in range(basin_rounds if passes(best) else 0):
        base = best
        tried = [fit for fit in _refinements(model, mask, ob, dt, gates_px,
                                             [(base[0] + da, base[1] + de) for da, de in offsets], run)
                 if not isinstance(fit, PihimInputError)]
        rivals += tried
        top = max((f for f in tried if passes(f)), key=lambda f: f[4], default=None)
        if top is None or not top[4] > best[4] + support_margin:
            break
        best = top
    # the far rivals (``_FAR_STEPS``): a lattice step away; alike in support but looser, they do not count
    if basin_rounds and passes(best):
        steps = [sign * m * step_mrad for m in _FAR_STEPS for sign in (1, -1)]
        far = [(best[0] + d, best[1]) for d in steps] + [(best[0], best[1] + d) for d in steps]
        for fit in _refinements(model, mask, ob, dt, gates_px, far, run):
            if not isinstance(fit, PihimInputError) and (fit[3] <= best[3] or fit[4] > best[4] + support_margin):
                rivals.append(fit)
    # two distinct fits that the image supports alike: the facet shows too little of the target to tell them
    # apart (a part of its back whose edges repeat), and either would be a made-up number
    for fit in rivals:
        apart = math.hypot(fit[0] - best[0], fit[1] - best[1])
        if (fit is not best and apart > _DISTINCT_STEPS * step_mrad and fit[4] >= best[4] - support_margin
                and not _dominated(fit, best)):
            raise PihimInputError(f"two fits {apart:.1f} mrad apart explain it alike (support {best[4]:.2f} and "
                                  f"{fit[4]:.2f})")
    az, el, n, rms, support, found, segments, _ = best
    if matches is not None:
        matches.append(found)
    # the model and the last round's matches, for the uncertainty of the facets finally used
    return grid_az, grid_el, az, el, model, (found, segments), n, rms, support


def _refinements(model: _FacetModel, mask: _Mask, ob: NDArray, dt: NDArray, gates_px: tuple[float, ...],
                 starts: list[tuple[float, float]], run: _Run | None = None) -> list:
    """:func:`_refine_facet` from each start ``(az, el)``, in order: its fit, or the
    :class:`~pihim.errors.PihimInputError` it raised. On ``run``'s threads
    (:func:`pihim.inspection._threads.ordered_map`; the fit is one compiled call that releases the GIL), else
    one after the other: the same fits."""
    def one(start: tuple[float, float]) -> tuple | PihimInputError:
        try:
            return _refine_facet(model, mask, ob, dt, gates_px, *start)
        except PihimInputError as exc:
            return exc

    return run(one, starts) if run is not None else [one(s) for s in starts]


def _refine_facet(model: _FacetModel, mask: _Mask, ob: NDArray, dt: NDArray, gates_px: tuple[float, ...],
                  az: float, el: float) -> tuple:
    """Point-to-line ICP with LM from ``(az, el)``: (az, el, points, rms, support, matches, segments, inside).

    One compiled call (:func:`pihim.inspection._kernels.refine_reflection`): a round per gate of ``gates_px``,
    each projecting only the outline points within ``_WINDOW_PX`` of the facet's mask while no other can reach
    it (the facet model's motion bound). ``points`` and ``rms`` are the last round's inliers (residual under
    1 px) and their RMS residual; ``matches`` the last round's matched model points (world), image points and
    line normals; ``segments`` the target outline segment of each; ``inside`` how many outline samples fall in
    the facet; ``support`` the share of those on an image edge (within 1.5 px).
    """
    from pihim.inspection import _kernels

    ext = mask.extent()
    box = np.array([1, 0, 0, 0] if ext is None else ext, np.int64)  # first > last: no pixel, no window
    status, count, az, el, r, idx, q, nq, inside, support = _kernels.refine_reflection(
        model.pts, model.seg, model.aux, model._r, model._c, model._cam, mask.sub, mask.r0, mask.c0, box,
        model.motion_px_per_mrad(), _WINDOW_PX, np.ascontiguousarray(ob, dtype=float), dt,
        np.asarray(gates_px, float), float(az), float(el), _X_SCALE, 20, 15, 0.5)
    if status == 1:
        raise PihimInputError("the reflected target leaves the facet")
    if status == 2:
        raise PihimInputError(f"the reflected target matches only {count} edge points")
    found = (model.pts[idx], q, nq)
    inl = np.abs(r) < 1.0
    n = int(inl.sum())
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) if n else float("nan")
    return float(az), float(el), n, rms, float(support), found, model.seg[idx], int(inside)


def _keeps_turn(turned: tuple[int, int, float, float], logged: tuple[int, int, float, float],
                target_orientation: bool) -> bool:
    """Whether the orientation search's turn of the HUA replaces its logged drive angles.

    ``turned`` and ``logged`` are each outline's first fits: (facets measured, facets that found the target's
    outline, mean RMS residual in px, the same over the facets both measured). With the target's correction to
    follow, the turn wins on more facets measured, then on more facets found (what that correction starts from),
    then on a smaller residual. Without it, the log is the prior: the turn must measure at least two facets more
    (``estimate_canting``'s ``orientation_span_mrad``) and fit the facets both measure no more loosely.
    """
    if target_orientation:
        return (turned[0], turned[1], -turned[2]) > (logged[0], logged[1], -logged[2])
    return turned[0] >= logged[0] + 2 and not turned[3] > logged[3]


def _direction_spread(normals: ArrayLike) -> float:
    """How evenly matched edges' directions spread: the smaller eigenvalue of the mean ``n n^T`` of their unit normals.

    The point-to-line residuals of a fit constrain a shift of the
    reflection along their normals only: 0 when every edge runs one way (a
    shift along them changes no residual), 0.5 for normals spread evenly over
    directions; 0 with no normals.
    """
    n = np.asarray(normals, float).reshape(-1, 2)
    if not len(n):
        return 0.0
    return max(0.0, float(np.linalg.eigvalsh(n.T @ n / len(n))[0]))


def _jackknife_variance(model: _FacetModel, found: tuple, segments: NDArray, az: float,
                        el: float, gate: float) -> NDArray[np.float64]:
    """Variances (az, el) of a facet fit, mrad^2: the delete-one-segment jackknife.

    The fit's last round (matches ``found`` on the target outline's ``segments``) is solved again
    from ``(az, el)`` without each segment's points in turn
    (:func:`pihim.inspection.uncertainty.jackknife_covariance`); NaN with fewer than three segments
    matched. Grouped by element instead (a target facet's four sides, a member's four edges), the
    20-frame study left 4 of 82 facets without a sigma and described the errors no better (65 / 62 %
    within two sigma against 70 / 63 %).
    """
    from pihim.inspection import _kernels

    pts_w, q, nq = found
    obs = np.column_stack([q, nq])
    x_fit = np.array([az, el])

    def refit(keep: NDArray[np.bool_]) -> NDArray:
        prob = _kernels.problem(_kernels.REFLECTION, model._r, model._c, pts_w[keep], model._cam, q=obs[keep],
                                aux=model.aux, idx=np.arange(int(keep.sum())), gate=gate)
        return _kernels.solve(prob, x_fit, int(keep.sum()), _X_SCALE, 200, True, 0.5)[0]

    cov, _ = jackknife_covariance(segments, refit)
    return np.full(2, np.nan) if cov is None else np.clip(np.diag(cov), 0.0, None)


def estimate_canting(
    camera: CameraModel,
    pose: CameraPose,
    field_pose: FieldPose,
    hua: str,
    target: str,
    edges: EdgePoints,
    *,
    dolp: ArrayLike | None = None,
    saturated: ArrayLike | None = None,
    min_dolp: float | None = 0.2,
    span_mrad: float = 10 * PAPER_GRID_STEP_MRAD,
    step_mrad: float = PAPER_GRID_STEP_MRAD,
    margin_px: float = 6.0,
    gates_px: tuple[float, ...] = (6.0, 3.0, 1.5, 1.5),
    min_points: int = 300,
    min_support: float = 0.3,
    max_rms_px: float = 0.3,
    min_spread: float = 0.01,
    sizes: StructureSizes = StructureSizes(),
    orientation_span_mrad: float | None = PAPER_ORIENTATION_SPAN_MRAD,
    target_orientation: bool = False,
) -> CantingResult:
    """Estimate every facet's canting of ``hua`` from ``target``'s reflection in one frame.

    Parameters
    ----------
    camera, pose : CameraModel, CameraPose
        Intrinsics and the refined camera pose (:func:`pihim.inspection.pose.refine_pose`).
    field_pose : FieldPose
        The field as logged (drive angles from the plant's log, design canting).
    hua, target : str
        Heliostat names.
    edges : EdgePoints
        Sub-pixel edge points of the frame.
    dolp, saturated : array_like, optional
        DoLP image and saturation mask (same shape) for the skip tests.
    min_dolp : float or None
        A facet is used only if the brighter part of its reflection is
        polarized above this (the 90th percentile of its DoLP; paper: 0.2);
        None disables the test.
    span_mrad, step_mrad : float
        Grid-search half-range and step (paper: +-5 deg in 0.1 deg steps;
        the default half-range here is 1 deg = 17.5 mrad, ten paper steps, as
        the refinement needs only a starting point; pass 87.3 for the
        paper's full range).
    margin_px : float
        Facet outlines are eroded by this much so that the facet's own edges
        (and the gaps) are not taken for reflected features.
    gates_px : tuple of float
        Matching gates of the refinement rounds.
    min_points : int
        Fewest matched edge points for a facet to be used.
    max_rms_px : float
        Largest RMS point-to-line residual of an accepted facet fit, pixels
        (a fit locked to the wrong features leaves larger residuals).
    min_support : float
        Fewest share of the reflected target outline (inside the facet) that
        must lie within 1.5 px of an image edge at the solution; facets whose
        reflection shows something else are skipped, as they would bias the
        best-fit orientation every deviation is relative to.
    min_spread : float
        Least spread of the matched edges' directions: the smaller eigenvalue
        of the mean ``n n^T`` of their unit line normals (0 when they all run
        one way, 0.5 when evenly spread). A fit along a single straight edge
        cannot move along it, so one combination of the two angles stays
        where the grid left it: such a facet is skipped. Rendered frames
        20-39 of ``benchmarks/canting_quality.py`` had one, matched on one
        outline segment, 1.3 mrad off (which moved the other facets of its
        frame by 0.33 mrad); the least spread of a facet used on the 40
        frames is 0.018 (2026-11-28).
    orientation_span_mrad : float or None
        Half-range of the orientation search (:func:`search_orientation`,
        step ``step_mrad``) run over the facets that pass the view, saturation
        and DoLP tests before any facet is fitted. A node more than 2.5 steps
        from the logged angles turns the target's outline as the HUA's turn
        would (:func:`hua_turn_transform`) and every facet is fitted on it and
        on the logged outline. With ``target_orientation``, the turn is kept
        if it measures more facets; on a tie, the outline more facets found
        wins, then the smaller mean residual. Without it, the turn must
        measure at least two facets more than the logged angles (the log is
        the prior): a turn of the HUA looks from the camera almost as a
        common tilt of its facets, and one facet more is within chance (on
        rendered frame 28 of ``benchmarks/canting_quality.py``, no drive-angle
        error, a turn 5 mrad off measured 8 facets against 7 and put them
        0.32 mrad off; 2026-11-28), and it must fit the facets both measure
        no more loosely (mean RMS residual; on frame 5, a turn 5 mrad off in
        elevation measured 7 facets against 5 and set the HUA's drive-angle
        correction 2.6 mrad off). Default the paper's +-5 deg; None skips
        the search.
    target_orientation : bool
        Correct the target's logged drive angles and the HUA's turn
        together (:func:`refine_orientations`) and fit the facets again on
        the corrected outline, kept if that measures more facets (or as
        many, with smaller residuals). Off by default: it costs about 2-4 s of
        CPU per frame and helps only when the plant's logged drive angles
        are off by about 0.1 deg or more (BENCHMARKS.md).

    Returns
    -------
    CantingResult
    """
    names = list(field_pose.field.names)  # type: ignore[attr-defined]
    try:
        h = names.index(hua)
        t = names.index(target)
    except ValueError as exc:
        raise PihimInputError(f"unknown heliostat: {exc}") from None
    spec = field_pose.field.spec  # type: ignore[attr-defined]
    corners = field_pose.facet_corners()
    masks = _facet_masks(camera, pose, corners[h], margin_px)
    in_view = facet_in_view(camera, pose, corners[h])
    pts, seg = sample_segments(target_outline_segments(field_pose, t, sizes), 0.01)
    import cv2

    obs_img = np.zeros((camera.height_px, camera.width_px), np.uint8)
    q = np.rint(edges.xy).astype(int)
    ok = (q[:, 0] >= 0) & (q[:, 0] < camera.width_px) & (q[:, 1] >= 0) & (q[:, 1] < camera.height_px)
    obs_img[q[ok, 1], q[ok, 0]] = 1
    dt = cv2.distanceTransform((1 - obs_img).astype(np.uint8), cv2.DIST_L2, 5)
    dolp_img = None if dolp is None else np.asarray(dolp, float)
    sat = None if saturated is None else np.asarray(saturated, bool)
    raw: list[tuple] = []
    candidates: list[tuple[int, _Mask]] = []
    for f in range(spec.n_facets):
        fid = f + 1
        mask = masks[f]
        area = mask.area()
        if area < 200:
            raw.append((fid, "facet not in view (or too small)"))
            continue
        if sat is not None and sat.shape == mask.shape and mask.values(sat).mean() > 0.3:
            raw.append((fid, "saturated"))
            continue
        if min_dolp is not None and dolp_img is not None and dolp_img.shape == mask.shape:
            vals = mask.values(dolp_img)
            p90 = np.nanpercentile(vals, 90) if np.isfinite(vals).any() else 0.0
            if not p90 > min_dolp:
                raw.append((fid, f"DoLP <= {min_dolp:g} on the reflection (paper sec. 4.1)"))
                continue
        raw.append((fid, None))
        candidates.append((f, mask))

    outline = {"pts": pts, "seg": seg}  # the target's outline samples (replaced once its orientation is corrected)

    def facet_model(f: int) -> _FacetModel:
        return _FacetModel(camera, pose, field_pose.rotations[h], field_pose.facet_centres[h, f],
                           field_pose.facet_normals_local[h, f], outline["pts"], outline["seg"])

    gates = _Gates(min_points, max_rms_px, min_support)
    # each facet's grid search and refinements from its peaks, per outline and preferred angles: the final fits
    # (below) start from those of the outline chosen instead of doing them again
    starts: dict[tuple, tuple] = {}

    def fit_facets(prefer: dict[int, tuple[float, float]] | None, collect: list | None = None,
                   rounds: int = 0) -> dict[int, object]:
        """Every candidate facet fitted on the current outline, its grid around the design; ``rounds`` of
        refinements from the neighbouring basins (:func:`_settle`)."""
        def key(f: int) -> tuple:
            return f, id(outline["pts"]), None if prefer is None else prefer.get(f)

        fits: dict[int, object] = {}
        # the facets to search: their outline models (the points that can reach the facet) first, then each
        # facet's refinements, on threads (the same fits)
        new = [(f, mask) for f, mask in candidates if key(f) not in starts or starts[key(f)][0] is not outline["pts"]]
        with ordered_map() as run:
            near = dict(zip((f for f, _ in new), run(lambda c: facet_model(c[0]).near(c[1], span_mrad), new)))
            for f, mask in candidates:
                prefer_f = None if prefer is None else prefer.get(f)
                if f in near:
                    model = near[f]
                    try:
                        start: _Start | PihimInputError = _first_fits(
                            model, mask, edges.xy, dt, span_mrad, step_mrad, gates_px, prefer_mrad=prefer_f, run=run)
                    except PihimInputError as exc:
                        start = exc
                    starts[key(f)] = (outline["pts"], model, start)  # the outline held: its id stays its own
                _, model, start = starts[key(f)]
                found: list = []
                try:
                    if isinstance(start, PihimInputError):
                        raise start
                    fit = _settle(model, mask, start, dt, step_mrad, gates_px, found, basin_rounds=rounds,
                                  gates=gates, run=run)
                except PihimInputError as exc:
                    fits[f + 1] = f"no usable reflection of {target}: {exc}"
                    continue
                if collect is not None and found and fit[6] >= min_points and fit[8] >= min_support:
                    collect.append((f, fit[2], fit[3], found[-1]))  # the residual gate aside: see below
                if fit[6] < min_points:
                    fits[f + 1] = f"too few matched edge points ({fit[6]} < {min_points})"
                    continue
                if not fit[7] <= max_rms_px:
                    fits[f + 1] = (f"the fit is not sub-pixel consistent (residual {fit[7]:.2f} px > "
                                   f"{max_rms_px:g} px: locked to other features)")
                    continue
                if fit[8] < min_support:
                    fits[f + 1] = (f"the reflection does not look like {target}'s outline (support {fit[8]:.2f} < "
                                   f"{min_support:g}: hidden, or another heliostat)")
                    continue
                spread = _direction_spread(fit[5][0][2])
                if not spread >= min_spread:
                    fits[f + 1] = (f"the matched edges run one way (direction spread {spread:.3f} < "
                                   f"{min_spread:g}): one angle is not measured")
                    continue
                fits[f + 1] = fit
        return fits

    def n_used(fits: dict[int, object]) -> int:
        return sum(not isinstance(v, str) for v in fits.values())

    def mean_rms(fits: dict[int, object], among: dict[int, object] | None = None) -> float:
        """The mean RMS residual of the facets measured (and measured in ``among`` too)."""
        v = [r[7] for f, r in fits.items() if not isinstance(r, str)
             and (among is None or not isinstance(among.get(f, ""), str))]
        return float(np.mean(v)) if v else float("inf")

    search = None
    notes = []
    if orientation_span_mrad is not None and candidates:
        drv = field_pose.drive
        drive_h = (float(drv.azimuth_deg[h]), float(drv.elevation_deg[h]))
        pivot_h, _ = hua_turn_transform(field_pose, h, 0.0, 0.0)
        try:
            turn_models = [(_TurnModel(facet_model(f), drive_h, pivot_h).near(m, orientation_span_mrad), m)
                           for f, m in candidates]
            search = search_orientation(turn_models, dt, span_mrad=float(orientation_span_mrad))
        except PihimInputError as exc:
            notes.append(f"orientation search: {exc}")
    # The search's node is the HUA's drive-angle error: beyond 2.5 steps, the target's outline is turned as a
    # camera pose fitted on the HUA sees it (hua_turn_transform) and every facet is fitted around its design on
    # that outline. The search proposes, the facet fits decide: the facets are fitted on the logged outline too,
    # and the turn is kept by the rule of ``orientation_span_mrad``'s docstring (below): clutter -- other
    # heliostats' backs, the ground -- can raise a false peak of the search.
    plain = {"pts": pts, "seg": seg}
    turn_deg = (0.0, 0.0)
    fits: dict[int, object] = {}
    matches: list = []
    world = None
    # a turn of a step or two is what the facets' mean canting alone moves the search's node by; the facet
    # fits absorb it, and fitting twice would only let the two passes' noise choose
    if search is not None and max(abs(search.az_mrad), abs(search.el_mrad)) > 2.5 * step_mrad:
        turn_deg = (math.degrees(search.az_mrad * 1e-3), math.degrees(search.el_mrad * 1e-3))
        world = hua_turn_transform(field_pose, h, *turn_deg)
        outline.update(pts=_apply(world, pts))
        fits = fit_facets(None, matches)
        outline.update(plain)
    # on the logged outline, a facet whose grid has near-equal peaks (the target's back is periodic) starts
    # from the one nearest the tilt that mimics the search's turn
    def equivalent_tilt(candidate: tuple[int, _Mask]) -> tuple[float, float]:
        f, m = candidate
        return _equivalent_tilt(facet_model(f).near(m, span_mrad),
                                _TurnModel(facet_model(f), drive_h, pivot_h).near(m, span_mrad),
                                (search.az_mrad, search.el_mrad))

    prefer = None
    if world is not None:
        with ordered_map() as run:
            prefer = {f: tilt for (f, _), tilt in zip(candidates, run(equivalent_tilt, candidates))}
    logged_matches: list = []
    logged = fit_facets(prefer, logged_matches)
    final_prefer = None  # the grid peaks' preference of the outline kept (the logged one's, if kept)
    turned_first = (n_used(fits), len(matches), mean_rms(fits), mean_rms(fits, logged))
    logged_first = (n_used(logged), len(logged_matches), mean_rms(logged), mean_rms(logged, fits))
    if world is not None and _keeps_turn(turned_first, logged_first, target_orientation):
        notes.append(f"HUA {hua}'s logged drive angles corrected by the orientation search: az {turn_deg[0]:+.2f}, "
                     f"el {turn_deg[1]:+.2f} deg ({n_used(fits)} facets measured in the first fits, {n_used(logged)} "
                     "at the logged angles)")
        outline.update(pts=_apply(world, pts))
    else:
        if world is not None:
            notes.append(f"the orientation search's node (HUA az {turn_deg[0]:+.2f}, el {turn_deg[1]:+.2f} deg) "
                         f"measured {n_used(fits)} facets in the first fits, the logged angles {n_used(logged)}: "
                         "kept the logged angles")
        fits, matches, world, turn_deg = logged, logged_matches, None, (0.0, 0.0)
        final_prefer = prefer
    # The logged orientations (paper sec. 4.4): the target's drive angles and the HUA's turn solved with every
    # facet that found the target's outline (the residual gate aside: a target off its logged angles fails it
    # everywhere), then the facets fitted again on the corrected outline; kept if it measures more facets (or
    # as many, closer).
    target_corr = None
    if target_orientation and len(matches) >= 2:
        drv = field_pose.drive
        is_t = np.arange(len(drv.azimuth_deg)) == t

        def target_turned(d: NDArray) -> FieldPose:
            """The logged field with the target's drive angles changed by ``d`` (degrees)."""
            return field_pose.with_drive(np.asarray(drv.azimuth_deg, float) + d[0] * is_t,
                                         np.asarray(drv.elevation_deg, float) + d[1] * is_t)

        kept = dict(outline)
        total = np.zeros(2)
        turn = np.array(turn_deg, float)
        best = (n_used(fits), -mean_rms(fits))
        found = None  # (fits, target correction, HUA turn, outline) of the best iteration that beats ``best``
        last = (total.copy(), turn.copy())
        for _ in range(3):  # solve, refit on the corrected outline, solve again from the new matches
            step_t, step_h = (np.array(v) for v in refine_orientations(camera, pose, target_turned(total), h, t,
                                                                         matches, hua_turn_deg=(turn[0], turn[1])))
            if not np.any(np.abs(np.concatenate([step_t, step_h])) > 1e-3):
                break
            total += step_t
            turn += step_h
            last = (total.copy(), turn.copy())
            p2, s2 = sample_segments(target_outline_segments(target_turned(total), t, sizes), 0.01)
            outline.update(pts=_apply(hua_turn_transform(field_pose, h, turn[0], turn[1]), p2), seg=s2)
            matches = []
            tried = fit_facets(None, matches)
            if (n_used(tried), -mean_rms(tried)) > best:
                best = (n_used(tried), -mean_rms(tried))
                found = (tried, total.copy(), turn.copy(), dict(outline))
            if len(matches) < 2 or np.max(np.abs(np.concatenate([step_t, step_h]))) < 0.01:
                break
        if found is not None:
            fits, total, turn, kept_outline = found
            outline.update(kept_outline)
            final_prefer = None
            target_corr = (float(total[0]), float(total[1]))
            notes.append(f"target {target}'s logged orientation corrected by az {total[0]:+.3f}, el {total[1]:+.3f} "
                         f"deg, with the HUA's turn at az {turn[0]:+.3f}, el {turn[1]:+.3f} deg")
            turn_deg = (float(turn[0]), float(turn[1]))
        elif np.any(last[0] != 0.0) or np.any(last[1] != np.array(turn_deg)):
            outline.update(kept)
            notes.append(f"target {target}'s orientation fit (az {last[0][0]:+.3f}, el {last[0][1]:+.3f} deg, the "
                         f"HUA's turn at az {last[1][0]:+.3f}, el {last[1][1]:+.3f} deg) measured no more facets; kept "
                         "the previous angles")
    # The facets' final fits, on the outline chosen above, now also from the neighbouring basins (_settle's
    # ``basin_rounds``). The choices above count the facets each outline measures; fits that may move to a
    # neighbouring basin would blur that count (an outline turned or corrected wrongly gains facets by moving some
    # into a wrong basin: on 20 rendered frames one HUA's drive-angle correction went 2.6 mrad off in elevation, and at
    # drive-angle errors of 5 mrad with the target's correction one facet 4.7 mrad off, 2026-11-28).
    # Every candidate again, not only those measured: a facet whose first fit two grid peaks explained alike can
    # be resolved by a clearly better neighbouring basin (one facet more of 78 on 20 rendered frames, 2026-11-28);
    # the grid searches and peak refinements are those of the first fits (``starts``).
    fits = fit_facets(final_prefer, None, _BASIN_ROUNDS)
    raw = [(fid, fits[fid] if r is None else r) for fid, r in raw]
    used = [r for r in raw if not isinstance(r[1], str)]
    if used:
        o_az = float(np.mean([r[1][2] for r in used]))
        o_el = float(np.mean([r[1][3] for r in used]))
        g_az = float(np.mean([r[1][0] for r in used]))
        g_el = float(np.mean([r[1][1] for r in used]))
    else:
        o_az = o_el = g_az = g_el = None
        notes.append("no facet could be measured")
    # each used fit's standard uncertainty, taken (as the deviations are) relative to the mean over them
    with ordered_map() as run:
        var = np.array(run(lambda r: _jackknife_variance(r[1][4], *r[1][5], r[1][2], r[1][3], gates_px[-1]),
                           used)).reshape(-1, 2)
    sd = np.sqrt(relative_variance(var))
    out = []
    k = 0
    for fid, r in raw:
        if isinstance(r, str):
            out.append(FacetCanting(fid, False, r, in_view=float(in_view[fid - 1])))
        else:
            ga, ge, a, e, _, _, n, rms, support = r
            sa, se = (float(v) if np.isfinite(v) else None for v in sd[k])  # None: too few segments
            out.append(FacetCanting(fid, True, None, a - o_az, e - o_el, sa, se, ga - g_az, ge - g_el, n, rms,
                                    support, float(in_view[fid - 1])))
            k += 1
    corr = None
    if o_az is not None:
        rest = drive_correction(field_pose, h, o_az, o_el)
        corr = (turn_deg[0] + rest[0], turn_deg[1] + rest[1])
    return CantingResult(hua, target, tuple(out), o_az, o_el, 1, tuple(notes), search, corr, target_corr)
