"""Captures along each scan pass so that every facet of its HUAs shows a heliostat's back.

A facet's canting is measured where the back of a heliostat (the *target*)
appears reflected in it (paper section 4.4; :mod:`pihim.inspection.canting`).
With the paper's 35 mm lens at <= 25 m one image frames 12-20 of a NSTTF
HUA's 25 facets, and from one camera position the nearest row of
heliostats, reflected, covers only part of the mirror: the gaps between
neighbouring targets show sky or ground in one or two facet columns. This
module plans, for each HUA of each pass, a few captures on the pass line
(stop-and-shoot: the drone stops at each capture point, see
:mod:`pihim.planning.export.qgc`) that together put every facet in view
with a heliostat back reflected in it.

Method
------
For each HUA, its facets are sampled on a ``samples x samples`` grid of
points ``q`` (design canting, :meth:`pihim.field.kinematics.FieldPose.facet_corners`).
The camera moves on the pass line ``C(s) = A + s E`` (``A`` a point of the
line at the pass altitude, ``E`` its horizontal unit direction):

* **What a point reflects.** The camera sees, at ``q``, the mirror image
  of the scene in the facet plane. A mirror rectangle ``M`` (the flat
  tracked outline of another heliostat) appears at ``q`` when ``C`` lies in
  the cone with apex ``q`` spanned by the mirror image of ``M``'s corners
  in the facet plane, on the side opposite to them. The cone is the
  intersection of four half-spaces through ``q`` (one per edge); on the
  line each is a linear inequality in ``s``, so the camera positions form
  an interval ``[lo, hi]``, computed in closed form for every sample point
  and every mirror within ``target_reach_m`` in front of the HUA.
* **Which one.** Where several intervals contain ``s``, the nearest mirror
  (centre distance from the HUA) is the one reflected (it hides the
  others). It counts when the ray meets it from behind (``q`` behind its
  plane): the facet then shows that heliostat's back, its target.
* **Seen.** The camera must be in front of the facet, and the sight line
  ``C -> q`` must miss the mirrors within ``blocker_reach_m`` (the positive
  cone over each rectangle, same closed form).
* **Framed.** For every candidate position (a ``step_m`` grid within
  ``window_m`` of the HUA's planned capture along the line, inside the
  range limit, outside the tower keep-out and the concentrated-sunlight
  region) and every aim point (a grid of offsets in the mirror plane
  around the HUA centre, ``aim_offsets_m``), heading and pitch point the
  optical axis at the aim point and :func:`pihim.planning.sightlines.in_fov`
  says which sample points are in the image.

A facet is covered by a capture when one of its sample points is framed,
seen and shows a heliostat back. Captures are chosen greedily per HUA, the
one adding the most facets first (ties: nearer the planned capture, then
the centre aim), until every facet that any candidate covers is covered,
``max_captures`` is reached or a capture would add fewer than ``min_gain``
facets; one capture per grid point of a pass. Every capture records the
heliostat whose back most of its new facets show (its ``target``) and the
facets it is credited with. HUAs of the plan not imaged by any pass
(requested but left without a target) are tried from the nearest pass
lines within ``rescue_reach_m`` (``rescue``).

The interval test approximates the nearest reflected mirror by centre
distance; :func:`pihim.planning.facets.facet_coverage` then traces the
chosen captures ray by ray (mirrors, tower and field of view) and gives the
coverage that ``pihim plan`` reports.

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone" (pihim paper), sections 3 (UFACET) and 4.4 (canting from
   the target's reflection).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import statistics
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from pihim import _forked
from pihim.camera.model import CameraModel
from pihim.errors import PihimInputError
from pihim.field.geodesy import as_origin, enu_to_geodetic
from pihim.field.kinematics import facet_corners
from pihim.planning.model import ScanPass, Waypoint, heading_0_360
from pihim.planning.sightlines import azimuth_deg, camera_frame, dot, gaze_angles

__all__ = [
    "FacetCapture",
    "FacetCaptureSettings",
    "FacetPlan",
    "cone_interval",
    "plan_facet_captures",
]


@dataclass(frozen=True)
class FacetCaptureSettings:
    """Tuning of :func:`plan_facet_captures` (module docstring).

    Attributes
    ----------
    step_m : float
        Spacing of the candidate camera positions along a pass line, metres
        (also the least distance between two captures of a pass).
    window_m : float
        Candidate positions within this distance (along the line) of the
        HUA's planned capture, metres.
    aim_offsets_m : tuple of float
        Offsets of the aim points from the HUA mirror centre along the
        mirror's width and height axes (every combination), metres.
    max_captures : int
        Captures per HUA at most.
    min_gain : int
        A capture must add at least this many facets.
    target_fraction : float or None
        Once every HUA has its captures, the captures adding the fewest
        facets (the last ones of their HUA) are dropped as long as the
        predicted share of covered facets over all HUAs stays at or above
        this (each HUA keeps its first capture); None keeps them all.
    samples : int
        Sample points per facet side.
    target_reach_m : float
        Mirrors within this horizontal distance in front of the HUA are
        candidate targets (and hide each other), metres.
    blocker_reach_m : float
        Mirrors within this horizontal distance of the HUA are tested as
        blockers of the camera's sight lines, metres.
    max_range_m : float
        Largest camera-to-HUA distance, metres.
    rescue : bool
        Try HUAs not imaged by any pass from the nearest pass lines.
    rescue_reach_m : float
        Largest horizontal distance of such a HUA from a pass line, metres.
    rescue_min_fraction : float
        A rescued HUA must have at least this fraction of its facets covered
        (a HUA imaged in a few facets only would lower the share of facets
        covered; it is left unassessed instead).
    rescue_max_extension_m : float
        A rescue may lengthen its pass by at most this much, metres (the
        pass line that needs the least extension is chosen).
    min_planned_coverage : float
        HUAs that no planned line images even so get short passes of their
        own (:func:`_own_lines`), nearest to the planned captures first, until
        this share of the field's heliostats is imaged (0: never).
    lead_in_m, run_past_m : float
        Straight flight before the first and after the last capture of each
        pass, metres (0: the drone flies straight to the first capture and
        leaves from the last; it stops at every capture anyway).
    speed_m_s : float
        Ground speed of the passes of their own made for rescued HUAs, m/s.
    flux_limit_suns : float
        Candidate positions where the concentrated-sunlight estimate
        (:func:`pihim.planning.flux.beam_concentration`) exceeds this are
        refused (only with an aim point).
    batch : int
        HUAs evaluated together (memory bound; the result does not depend on it).
    """

    step_m: float = 1.0
    window_m: float = 6.0
    aim_offsets_m: tuple[float, ...] = (-0.9, 0.0, 0.9)
    max_captures: int = 4
    min_gain: int = 1
    target_fraction: float | None = 0.96
    samples: int = 3
    target_reach_m: float = 45.0
    blocker_reach_m: float = 14.0
    max_range_m: float = 60.0
    rescue: bool = True
    rescue_reach_m: float = 15.0
    rescue_min_fraction: float = 0.9
    rescue_max_extension_m: float = 15.0
    min_planned_coverage: float = 0.9
    lead_in_m: float = 0.0
    run_past_m: float = 0.0
    speed_m_s: float = 5.0
    flux_limit_suns: float = 3.0
    batch: int = 32

    def __post_init__(self) -> None:
        for label in ("step_m", "window_m", "target_reach_m", "max_range_m", "flux_limit_suns", "speed_m_s"):
            v = getattr(self, label)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise PihimInputError(f"FacetCaptureSettings.{label} must be a positive number, got {v!r}")
        for label in ("blocker_reach_m", "rescue_reach_m", "rescue_max_extension_m", "lead_in_m", "run_past_m"):
            v = getattr(self, label)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise PihimInputError(f"FacetCaptureSettings.{label} must be a number >= 0, got {v!r}")
        for label in ("max_captures", "min_gain", "samples", "batch"):
            v = getattr(self, label)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise PihimInputError(f"FacetCaptureSettings.{label} must be a positive integer, got {v!r}")
        if self.target_fraction is not None and not (isinstance(self.target_fraction, (int, float))
                                                     and 0.0 <= self.target_fraction <= 1.0):
            raise PihimInputError(f"target_fraction must be None or in [0, 1], got {self.target_fraction!r}")
        if not (isinstance(self.min_planned_coverage, (int, float)) and 0.0 <= self.min_planned_coverage <= 1.0):
            raise PihimInputError(f"min_planned_coverage must be in [0, 1], got {self.min_planned_coverage!r}")
        if not (isinstance(self.rescue_min_fraction, (int, float)) and 0.0 <= self.rescue_min_fraction <= 1.0):
            raise PihimInputError(f"rescue_min_fraction must be in [0, 1], got {self.rescue_min_fraction!r}")
        offs = tuple(self.aim_offsets_m)
        if not offs or not all(isinstance(o, (int, float)) and math.isfinite(o) for o in offs):
            raise PihimInputError(f"aim_offsets_m must be finite numbers, got {self.aim_offsets_m!r}")
        object.__setattr__(self, "aim_offsets_m", offs)


@dataclass(frozen=True)
class FacetCapture:
    """One planned capture of a HUA (internal result, also returned for inspection).

    Attributes
    ----------
    pass_index : int
        :attr:`ScanPass.index` of the pass it belongs to.
    hua, target : int
        Heliostat indices (the target: whose back most of the new facets show).
    s_m : float
        Position along the pass line, metres from the line's reference point.
    camera : tuple of float
        ENU position, metres.
    aim : tuple of float
        ENU point the optical axis passes through, metres.
    facets : tuple of int
        Facets this capture was chosen for (predicted).
    """

    pass_index: int
    hua: int
    target: int
    s_m: float
    camera: tuple[float, float, float]
    aim: tuple[float, float, float]
    facets: tuple[int, ...]


@dataclass(frozen=True)
class FacetPlan:
    """Passes with facet captures, and what the planner predicted.

    Attributes
    ----------
    passes : tuple of ScanPass
        Same order and indices; capture waypoints replaced (no predictions:
        score them again).
    captures : tuple of FacetCapture
    predicted : dict of str to tuple of int
        Facets of each HUA predicted covered.
    coverable : dict of str to int
        Facets of each HUA that some candidate capture covers.
    rescued : tuple of str
        HUAs imaged only thanks to the rescue from a nearby pass line.
    """

    passes: tuple[ScanPass, ...]
    captures: tuple[FacetCapture, ...]
    predicted: dict[str, tuple[int, ...]]
    coverable: dict[str, int]
    rescued: tuple[str, ...]


# --------------------------------------------------------------------------- geometry


def cone_interval(apex: NDArray[np.float64], corners: NDArray[np.float64], a: NDArray[np.float64],
                  e: NDArray[np.float64], *, negative: bool) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Parameters ``s`` for which ``a + s e`` lies in the cone from ``apex`` over a convex polygon.

    Parameters
    ----------
    apex : ndarray, shape (..., 3)
    corners : ndarray, shape (..., K, 3)
        Polygon vertices in order (convex, not containing the apex in its plane).
    a, e : ndarray, shape (..., 3)
        Line point and direction.
    negative : bool
        The opposite nappe (points ``apex - t (p - apex)``, ``t > 0``, ``p``
        in the polygon) instead of the cone through the polygon.

    Returns
    -------
    lo, hi : ndarray, shape (...)
        The closed interval; ``lo > hi`` when the line misses the cone.

    Notes
    -----
    Each edge ``(V_k, V_k+1)`` gives the plane through the apex with normal
    ``m_k = (V_k - q) x (V_k+1 - q)``, oriented toward the polygon's
    centroid; the cone is ``{P : (P - q) . m_k >= 0 for all k}`` and the
    opposite nappe the same with ``<= 0``. On the line each condition is
    ``alpha_k + s beta_k >= 0``.
    """
    v = corners - apex[..., None, :]
    m = np.cross(v, np.roll(v, -1, axis=-2))
    orient = np.sign(dot(v.mean(axis=-2)[..., None, :], m))
    m = m * (orient if not negative else -orient)[..., None]
    alpha = dot((a - apex)[..., None, :], m)
    beta = dot(e[..., None, :], m)
    scale = np.linalg.norm(m, axis=-1) * max(float(np.max(np.abs(e))), 1e-300)
    flat = np.abs(beta) <= 1e-12 * np.maximum(scale, 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = -alpha / beta
    lo = np.max(np.where(~flat & (beta > 0), bound, -np.inf), axis=-1)
    hi = np.min(np.where(~flat & (beta < 0), bound, np.inf), axis=-1)
    empty = np.any(flat & (alpha < 0), axis=-1) | np.all(np.abs(m) == 0, axis=(-2, -1))
    lo = np.where(empty, np.inf, lo)
    hi = np.where(empty, -np.inf, hi)
    return lo, hi


def _half_line(q: NDArray[np.float64], n: NDArray[np.float64], a: NDArray[np.float64],
               e: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Interval of ``s`` with ``(a + s e - q) . n > 0`` (camera in front of the plane through q)."""
    alpha = dot(a - q, n)
    beta = dot(e, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = -alpha / beta
    lo = np.where(beta > 0, bound, np.where(beta < 0, -np.inf, np.where(alpha > 0, -np.inf, np.inf)))
    hi = np.where(beta < 0, bound, np.where(beta > 0, np.inf, np.where(alpha > 0, np.inf, -np.inf)))
    return lo, hi


def _polygon_terms(corners: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                                          NDArray[np.float64], NDArray[np.float64]]:
    """Per polygon (..., K, 3): edge terms ``P_k = X_k x X_k+1``, ``D_k = X_k+1 - X_k``, centroid, winding normal."""
    nxt = np.roll(corners, -1, axis=-2)
    return (np.cross(corners, nxt), nxt - corners, corners.mean(axis=-2),
            np.cross(corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 1, :]))


def _cone_intervals(q: NDArray[np.float64], a: NDArray[np.float64], e: NDArray[np.float64],
                    terms: tuple[NDArray, NDArray, NDArray, NDArray], idx: NDArray[np.int64],
                    window: tuple[NDArray[np.float64], NDArray[np.float64]], negative: bool
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`cone_interval` for every (apex, polygon) pair of a batch, compiled
    (:func:`pihim.planning._kernels.cone_intervals`).

    ``q``, ``a``, ``e``: (B, I, 3) apexes and per-apex lines; ``terms`` of :func:`_polygon_terms` for
    polygons (B, J, K, 3); ``idx`` (B, J) their heliostats (-1: padding). Returns ``lo``, ``hi`` (B, I, J),
    ``(inf, -inf)`` for padding and where the interval misses ``[window[0][b], window[1][b]]``.
    """
    from pihim.planning import _kernels

    P, D, cen, wind = (np.ascontiguousarray(t, dtype=np.float64) for t in terms)
    q, a, e = (np.ascontiguousarray(x, dtype=np.float64) for x in (q, a, e))
    return _kernels.cone_intervals(q, a, e, P, D, cen, wind, np.ascontiguousarray(idx, dtype=np.int64),
                                   np.ascontiguousarray(window[0], dtype=np.float64),
                                   np.ascontiguousarray(window[1], dtype=np.float64), bool(negative))


def _grid_points(corners: NDArray[np.float64], samples: int) -> NDArray[np.float64]:
    """Sample points inside quads (..., 4, 3) ordered TL, TR, BR, BL: shape (..., samples**2, 3)."""
    t = (np.arange(samples) + 0.5) / samples
    u, v = np.meshgrid(t, t, indexing="ij")
    u, v = u.ravel(), v.ravel()
    tl, tr, br, bl = (corners[..., k, None, :] for k in range(4))
    top = tl + u[:, None] * (tr - tl)
    bottom = bl + u[:, None] * (br - bl)
    return top + v[:, None] * (bottom - top)


def _neighbours(tree: cKDTree, centres_xy: NDArray[np.float64], huas: NDArray[np.int64], radius: float,
                keep: Any, limit: int) -> NDArray[np.int64]:
    """Up to ``limit`` heliostats within ``radius`` of each HUA (nearest first; equals in the k-d tree's order)
    passing ``keep(huas, candidates) -> bool`` (elementwise); -1 padded."""
    huas = np.asarray(huas, dtype=np.int64)
    lists = tree.query_ball_point(centres_xy[huas], radius, return_sorted=False)
    lens = np.fromiter(map(len, lists), dtype=np.int64, count=len(huas))
    cand = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(lens.sum()))
    row = np.repeat(np.arange(len(huas)), lens)
    ok = cand != huas[row]
    cand, row = cand[ok], row[ok]
    ok = keep(huas[row], cand)
    cand, row = cand[ok], row[ok]
    d = np.linalg.norm(centres_xy[cand] - centres_xy[huas[row]], axis=1)
    order = np.lexsort((d, row))  # by HUA, then distance; stable: equals keep the tree's order
    cand, row = cand[order], row[order]
    start = np.searchsorted(row, np.arange(len(huas)))
    rank = np.arange(len(row)) - start[row]
    out = np.full((len(huas), limit), -1, dtype=np.int64)
    first = rank < limit
    out[row[first], rank[first]] = cand[first]
    return out


# --------------------------------------------------------------------------- evaluation of candidates


@dataclass
class _Instance:
    """A HUA to cover from one pass line (internal)."""

    hua: int
    pass_k: int  # position in the passes tuple
    s0: float  # planned capture (or nearest point) along the line


@dataclass(frozen=True)
class _Line:
    a: NDArray[np.float64]  # point at the pass altitude
    e: NDArray[np.float64]  # horizontal unit direction of travel
    z: float


class _Extents:
    """Planned extent ``(lo, hi)`` of each pass along its line (its captures, metres), by pass position (internal).

    Arrays ``lo`` and ``hi`` (NaN: no extent), read whole by the rescue's admission test, grown when the rescue
    adds passes of its own.
    """

    def __init__(self, n: int) -> None:
        self.lo = np.full(n, np.nan)
        self.hi = np.full(n, np.nan)

    def __contains__(self, k: int) -> bool:
        return k < len(self.lo) and not math.isnan(self.lo[k])

    def __getitem__(self, k: int) -> tuple[float, float]:
        return float(self.lo[k]), float(self.hi[k])

    def __setitem__(self, k: int, lo_hi: tuple[float, float]) -> None:
        if k >= len(self.lo):
            pad = np.full(k + 1 - len(self.lo), np.nan)
            self.lo, self.hi = np.concatenate([self.lo, pad]), np.concatenate([self.hi, pad])
        self.lo[k], self.hi[k] = lo_hi


#: Batches of HUAs one forked worker evaluates in a row (:func:`plan_facet_captures`).
_BATCHES_PER_PIECE = 8


def _evaluate(inst: Sequence[_Instance], lines: Sequence[_Line], pose: Any, camera: CameraModel,
              st: FacetCaptureSettings, ctx: dict[str, Any]) -> dict[str, NDArray]:
    """For each instance: the facets each (position, aim) candidate covers and the target shown.

    Returns arrays ``k`` (B, G) grid indices and ``s`` positions along the
    line, ``cam`` (B, G, 3), ``good`` (B, G, A, F), ``target`` (B, G, A, F)
    (-1 where not good), ``aims`` (B, A, 3), ``head`` and ``pitch`` (B, G, A).
    """
    spec = pose.field.spec
    h = np.array([i.hua for i in inst], dtype=np.int64)
    B = len(h)
    a = np.array([lines[i.pass_k].a for i in inst])
    e3 = np.array([np.r_[lines[i.pass_k].e, 0.0] for i in inst])
    half = int(round(st.window_m / st.step_m))
    k0 = np.round(np.array([i.s0 for i in inst]) / st.step_m).astype(np.int64)
    kk = k0[:, None] + np.arange(-half, half + 1)[None, :]  # (B, G) grid indices along each line
    s = kk * st.step_m
    cam = a[:, None, :] + s[..., None] * e3[:, None, :]  # (B, G, 3)
    ch = pose.mirror_centres[h]
    # camera range and keep-outs (the flux below, where it matters)
    valid = np.linalg.norm(cam - ch[:, None, :], axis=-1) <= st.max_range_m
    if ctx.get("keepout") is not None:
        lo_b, hi_b = ctx["keepout"]
        valid &= ~np.all((cam >= lo_b) & (cam <= hi_b), axis=-1)
    # facet samples of the HUAs
    corners = facet_corners(pose.rotations[h], ch, spec.facet_centroids, pose.facet_normals_local[h],
                            spec.facet_width_m, spec.facet_height_m)  # (B, F, 4, 3)
    n_f = corners.shape[1]
    q = _grid_points(corners, st.samples)  # (B, F, S, 3)
    n_s = q.shape[2]
    q = q.reshape(B, n_f * n_s, 3)
    fn = np.repeat(pose.facet_normals[h], n_s, axis=1)  # (B, I, 3)
    a_i = np.broadcast_to(a[:, None, :], q.shape)
    e_i = np.broadcast_to(e3[:, None, :], q.shape)
    f_lo, f_hi = _half_line(q, fn, a_i, e_i)  # camera in front of each facet
    outline = ctx["outline"]

    def intervals(idx: NDArray[np.int64], pts: NDArray[np.float64], a_: NDArray, e_: NDArray,
                  negative: bool, margin: float = 0.0) -> tuple[NDArray, NDArray]:
        """Intervals (B, I, J) of the polygons ``idx`` seen from ``pts``; empty where they miss the window
        (widened by ``margin`` at both ends)."""
        return _cone_intervals(pts, a_, e_, _polygon_terms(outline[np.maximum(idx, 0)]), idx,
                               (s[:, 0] - margin, s[:, -1] + margin), negative)

    def shortlist(idx: NDArray[np.int64], a_: NDArray, e_: NDArray, negative: bool) -> NDArray[np.int64]:
        """Mirrors whose interval meets the window, widened, for some facet centre (cheap first pass), -1 padded.

        A mirror's image on the HUA is larger than a facet, so where a sample point shows it a facet centre
        nearby does from a camera a little along the line; the window is widened by ``3 step_m`` (at least
        3 m) at both ends.
        """
        pts = pose.facet_centres[h]
        nrm = pose.facet_normals[h]
        if negative:
            a_c = a[:, None, :] - 2.0 * dot(a[:, None, :] - pts, nrm)[..., None] * nrm
            e_c = e3[:, None, :] - 2.0 * dot(e3[:, None, :], nrm)[..., None] * nrm
        else:
            a_c, e_c = np.broadcast_to(a[:, None, :], pts.shape), np.broadcast_to(e3[:, None, :], pts.shape)
        lo, hi = intervals(idx, pts, a_c, e_c, negative, margin=max(3.0 * st.step_m, 3.0))
        meets = (lo <= hi).any(axis=1)  # (B, J): some facet centre's interval meets the widened window
        keep = np.flatnonzero(meets.any(axis=0))
        return np.where(meets[:, keep], idx[:, keep], -1)

    # reflected: the camera line mirrored in each facet plane, in the opposite nappe over each target rectangle
    a_r = a_i - 2.0 * dot(a_i - q, fn)[..., None] * fn
    e_r = e_i - 2.0 * dot(e_i, fn)[..., None] * fn
    tgt = shortlist(ctx["targets"](h), a_r, e_r, True)  # (B, J) nearest first, -1 padded
    r_lo, r_hi = intervals(tgt, q, a_r, e_r, True)  # (B, I, J)
    tj = np.maximum(tgt, 0)
    back = (np.sum(pose.mirror_centres[tj] * pose.normals[tj], axis=-1)[:, None, :]
            - np.matmul(q, pose.normals[tj].transpose(0, 2, 1))) > 0  # q behind the target's plane
    # blockers of the sight line camera -> sample
    blk = shortlist(ctx["blockers"](h), a_i, e_i, False)
    b_lo, b_hi = intervals(blk, q, a_i, e_i, False)
    # aims (the centre aim first: ties prefer it) and their camera axes (zero roll)
    offs = np.array(st.aim_offsets_m, float)
    ox, oy = np.meshgrid(offs, offs, indexing="ij")
    ox, oy = ox.ravel(), oy.ravel()
    order = np.argsort(np.hypot(ox, oy), kind="stable")
    ox, oy = ox[order], oy[order]
    rx, ry = pose.rotations[h][:, :, 0], pose.rotations[h][:, :, 1]
    aims = ch[:, None, :] + ox[None, :, None] * rx[:, None, :] + oy[None, :, None] * ry[:, None, :]  # (B, A, 3)
    head, pitch = gaze_angles(cam[:, :, None, :], aims[:, None, :, :])  # (B, G, A)
    right, down, fwd = camera_frame(head, pitch)  # (B, G, A, 3)
    # on the grid: the nearest containing target, seen from behind, sight line clear, camera in front, framed
    from pihim.planning import _kernels

    good, target = _kernels.facet_grid(
        np.ascontiguousarray(s, dtype=np.float64), np.ascontiguousarray(valid), r_lo, r_hi, np.ascontiguousarray(back),
        np.ascontiguousarray(tgt, dtype=np.int64), b_lo, b_hi, np.ascontiguousarray(f_lo), np.ascontiguousarray(f_hi),
        np.ascontiguousarray(q), np.ascontiguousarray(cam), np.ascontiguousarray(fwd), np.ascontiguousarray(right),
        np.ascontiguousarray(down), n_f, 0.5 * camera.width_px / camera.focal_length_px,
        0.5 * camera.height_px / camera.focal_length_px)
    if ctx.get("flux") is not None:
        # in concentrated sunlight a position covers nothing: asked only where it would cover facets (the same
        # as refusing the position before), once per camera position (pass line, grid index) for every HUA
        known: dict[int, bool] = ctx.setdefault("flux_ok", {})
        vb, vg = np.nonzero(good.any(axis=(2, 3)))
        lk = np.array([i.pass_k for i in inst], dtype=np.int64)
        keys = ((lk[vb] << 32) + (kk[vb, vg] + (1 << 31))).tolist()
        ok = [known.get(key) for key in keys]
        miss = [j for j, v in enumerate(ok) if v is None]
        if miss:
            m = np.array(miss)
            for j, v in zip(miss, (ctx["flux"](cam[vb[m], vg[m]]) <= st.flux_limit_suns).tolist(), strict=True):
                known[keys[j]] = ok[j] = v
        hot = ~np.array(ok, dtype=bool)
        good[vb[hot], vg[hot]] = False
        target[vb[hot], vg[hot]] = -1
    return {"k": kk, "s": s, "cam": cam, "good": good, "target": target, "aims": aims, "head": head,
            "pitch": pitch}


def _greedy(ev: dict[str, NDArray], inst: Sequence[_Instance], used: dict[int, set[int]],
            st: FacetCaptureSettings, commit: bool = True) -> list[list[tuple[int, int, NDArray[np.bool_], int]]]:
    """Greedy captures per instance (:func:`pihim.planning._kernels.greedy_captures`): lists of (grid column,
    aim, new facets mask, target). Grid positions in ``used`` (per pass) are skipped; with ``commit`` the
    picks are added to it."""
    from pihim.planning import _kernels

    good, target, kk = ev["good"], ev["target"], ev["k"]
    B, G, A, F = good.shape
    half = G // 2
    tie = (np.abs(np.arange(G) - half)[:, None] * 1e-3 + np.arange(A)[None, :] * 1e-5)  # nearer, centre aim
    taken = np.zeros((B, G), dtype=bool)
    for b, i in enumerate(inst):
        got = used.get(i.pass_k)
        if got:
            taken[b] = np.isin(kk[b], np.fromiter(got, dtype=np.int64, count=len(got)))
    passes = [i.pass_k for i in inst]
    pass_id = np.unique(np.array(passes, dtype=np.int64), return_inverse=True)[1].astype(np.int64)
    pick_g, pick_a, pick_new, pick_t = _kernels.greedy_captures(
        np.ascontiguousarray(good), np.ascontiguousarray(target, dtype=np.int64),
        np.ascontiguousarray(kk, dtype=np.int64), taken, pass_id, bool(commit), int(st.max_captures),
        float(st.min_gain), tie)
    picks: list[list[tuple[int, int, NDArray[np.bool_], int]]] = []
    for b in range(B):
        mine = [(int(g), int(a_), pick_new[b, r].copy(), int(pick_t[b, r]))
                for r, (g, a_) in enumerate(zip(pick_g[b].tolist(), pick_a[b].tolist(), strict=True)) if g >= 0]
        picks.append(mine)
        if commit:
            for g, _, _, _ in mine:
                used.setdefault(passes[b], set()).add(int(kk[b, g]))
    return picks


# --------------------------------------------------------------------------- the planner


def _pass_line(p: ScanPass) -> _Line | None:
    """Reference point (first waypoint), horizontal direction of travel and altitude of a straight pass."""
    if len(p.waypoints) < 1:
        return None
    w0, w1 = p.waypoints[0], p.waypoints[-1]
    d = np.array([w1.x_m - w0.x_m, w1.y_m - w0.y_m])
    n = float(np.linalg.norm(d))
    if n < 1e-9:
        az = math.radians(p.azimuth_deg)
        d, n = np.array([math.sin(az), math.cos(az)]), 1.0
    return _Line(np.array([w0.x_m, w0.y_m, p.altitude_m]), d / n, float(p.altitude_m))


def plan_facet_captures(
    passes: Sequence[ScanPass],
    pose: Any,
    *,
    origin: Any,
    camera: CameraModel | None = None,
    settings: FacetCaptureSettings | None = None,
    tower: Any = None,
    aim_point: Any = None,
    unassessed: Iterable[str] = (),
    workers: int | None = 1,
) -> FacetPlan:
    """Replace each pass's captures by captures that show every facet of its HUAs a heliostat back.

    Parameters
    ----------
    passes : sequence of ScanPass
        Straight passes with capture waypoints naming their HUA (e.g. scored
        and shifted by :func:`pihim.planning.scoring.score_passes`).
    pose : FieldPose
        The tracked field the passes were planned for.
    origin : GeodeticOrigin or Site
        Field origin on WGS84 (geodetic coordinates of the new waypoints).
    camera : CameraModel, optional
        Default Triton + 35 mm.
    settings : FacetCaptureSettings, optional
    tower : Tower, optional
        Camera positions inside its box grown by 5 m are refused.
    aim_point : array_like, optional
        Aim point of the tracking: positions in concentrated sunlight are refused.
    unassessed : iterable of str
        Requested HUAs no pass images; with ``settings.rescue`` they are tried
        from nearby pass lines.
    workers : int or None
        Processes evaluating the candidates of batches of HUAs side by side
        (forked on Linux, :func:`pihim._forked.imap`; None: one per CPU). The
        plan does not depend on it.

    Returns
    -------
    FacetPlan
        Passes in the same order with the same indices; each capture is a
        ``scan`` waypoint (HUA set, heading and pitch toward its aim point),
        ``pairs`` lists (HUA, target) per capture. Predictions are cleared.
    """
    camera = camera or CameraModel()
    st = settings or FacetCaptureSettings()
    _forked.check_workers(workers)
    if not isinstance(st, FacetCaptureSettings):
        raise PihimInputError(f"settings must be FacetCaptureSettings, got {type(st).__name__}")
    org = as_origin(origin)
    names = list(pose.field.names)
    index = {n: k for k, n in enumerate(names)}
    passes = list(passes)
    lines = [_pass_line(p) for p in passes]
    n_planned = len(passes)
    c = pose.mirror_centres
    cxy = c[:, :2]
    tree = cKDTree(cxy)
    n_f = pose.facet_centres.shape[1]

    def front_of(hh: NDArray[np.int64], cand: NDArray[np.int64]) -> NDArray[np.bool_]:
        return dot(c[cand] - c[hh], pose.normals[hh]) > 0

    j_max = 24
    ctx: dict[str, Any] = {
        "outline": pose.mirror_outline(),
        "targets": lambda hs: _neighbours(tree, cxy, hs, st.target_reach_m, front_of, j_max),
        "blockers": lambda hs: _neighbours(tree, cxy, hs, st.blocker_reach_m, lambda _h, cand: np.ones(len(cand), bool),
                                           12),
        "keepout": None,
        "flux": None,
    }
    if tower is not None:
        from pihim.planning.sightlines import tower_box

        ctx["keepout"] = tower_box(tower, 5.0)
    if aim_point is not None:
        from pihim.planning.flux import Beams

        ctx["flux"] = Beams(pose, np.asarray(aim_point, float)).concentration  # indexed once (one grid of the beams)
    # instances: every HUA captured in a pass, at its first capture
    inst: list[_Instance] = []
    seen_hua: set[int] = set()
    for k, (p, ln) in enumerate(zip(passes, lines, strict=True)):
        if ln is None or not p.feasible:
            continue
        for w in p.waypoints:
            if w.capture and w.hua in index and index[w.hua] not in seen_hua:
                hh = index[w.hua]
                seen_hua.add(hh)
                inst.append(_Instance(hh, k, float(dot(np.array([w.x_m, w.y_m]) - ln.a[:2], ln.e))))
    used: dict[int, set[int]] = {}
    chosen: list[tuple[_Instance, dict[str, NDArray], int, list]] = []
    coverable: dict[str, int] = {}
    parts = [inst[b0:b0 + st.batch] for b0 in range(0, len(inst), st.batch)]
    forked = _forked.can_fork(workers, len(parts))
    run = _BATCHES_PER_PIECE if forked else 1  # consecutive batches to one worker: its flux answers reused

    def evaluate(j: int) -> list[dict[str, NDArray]]:
        evs = [_evaluate(part, lines, pose, camera, st, ctx) for part in parts[j * run:(j + 1) * run]]
        if forked:  # what the greedy choice and the plan read, the targets narrowed for the trip back
            evs = [{k: ev[k] for k in ("k", "good", *_KEPT)} | {"target": ev["target"].astype(np.int32)}
                   for ev in evs]
        return evs

    # the candidates of every batch are independent (evaluated side by side with workers); the choice is not
    evaluated = (ev for evs in _forked.imap(evaluate, -(-len(parts) // run), workers, what="batches of HUAs")
                 for ev in evs)
    for part, ev in zip(parts, evaluated, strict=True):
        picks = _greedy(ev, part, used, st)
        for b, i in enumerate(part):
            coverable[names[i.hua]] = int(ev["good"][b].any(axis=(0, 1)).sum())
            chosen.append((i, _slice(ev, b), b, picks[b]))
    # rescue: requested HUAs no pass images, from the nearest pass lines
    rescued: list[str] = []
    if st.rescue:
        extent = _Extents(len(lines))
        for k, (p, ln) in enumerate(zip(passes, lines, strict=True)):
            if ln is not None and p.feasible:
                s_ = [float(dot(np.array([w.x_m, w.y_m]) - ln.a[:2], ln.e)) for w in p.waypoints if w.capture]
                if s_:
                    extent[k] = (min(s_), max(s_))
        todo = [index[nm] for nm in unassessed if nm in index and index[nm] not in seen_hua]
        left: list[int] = []

        def commit(i: _Instance, ev: dict[str, NDArray], best: int, pk: list) -> None:
            for g, _, _, _ in pk:
                used.setdefault(i.pass_k, set()).add(int(ev["k"][best, g]))
            lo, hi = extent[i.pass_k]
            s_caps = [float(ev["s"][best, g]) for g, _, _, _ in pk]
            extent[i.pass_k] = (min(lo, *s_caps), max(hi, *s_caps))
            coverable[names[i.hua]] = int(ev["good"][best].any(axis=(0, 1)).sum())
            chosen.append((i, _slice(ev, best), 0, pk))
            rescued.append(names[i.hua])

        line_k = np.array([k for k, ln in enumerate(lines) if k in extent and ln is not None], dtype=np.int64)
        line_a = np.array([lines[k].a[:2] for k in line_k]).reshape(-1, 2)
        line_e = np.array([lines[k].e for k in line_k]).reshape(-1, 2)
        from pihim.planning import _kernels

        # every HUA to every flown line in one compiled pass (numpy's (H, L, 2) temporaries took 17 s at 100,000)
        start, j, along = _kernels.lines_near(np.ascontiguousarray(c[np.asarray(todo, dtype=np.int64), :2]),
                                              line_a, line_e, float(st.rescue_reach_m))
        pending = [(hh, line_k[j[start[r]:start[r + 1]]], along[start[r]:start[r + 1]])
                   for r, hh in enumerate(todo)]
        half_w = round(st.window_m / st.step_m) * st.step_m

        def admit(ks: NDArray[np.int64], along: NDArray[np.float64], before: dict[int, int]) -> NDArray[np.bool_]:
            """Lines whose candidate positions (the window around ``along``) can still be within the allowed
            extension of their pass when the HUA's turn comes. The passes' extents grow only by rescues, each by
            at most ``rescue_max_extension_m``, and before this HUA decides only by the HUAs ahead of it in its
            batch: ``before[k]`` of them may extend pass ``k``."""
            mid = np.round(along / st.step_m) * st.step_m
            ahead = np.array([before.get(k, 0) for k in ks.tolist()], dtype=float) if before else 0.0
            reach = (ahead + 1.0) * st.rescue_max_extension_m + 1e-6
            return (mid - half_w <= extent.hi[ks] + reach) & (mid + half_w >= extent.lo[ks] - reach)

        for hh, cand, ev in _evaluated(pending, admit, lines, pose, camera, st, ctx):
            if not cand:
                left.append(hh)
                continue
            picks = _greedy(ev, cand, used, st, commit=False)
            best, key = -1, None
            for b, (i, pk) in enumerate(zip(cand, picks, strict=True)):
                got = sum(int(m.sum()) for _, _, m, _ in pk)
                if got == 0 or got < st.rescue_min_fraction * n_f:
                    continue
                lo, hi = extent[i.pass_k]
                s_caps = [float(ev["s"][b, g]) for g, _, _, _ in pk]
                ext = max(0.0, lo - min(s_caps)) + max(0.0, max(s_caps) - hi)
                if ext > st.rescue_max_extension_m:
                    continue
                if key is None or (ext, -got) < key:
                    best, key = b, (ext, -got)
            if best < 0:
                left.append(hh)
                continue
            commit(cand[best], ev, best, picks[best])
        # HUAs no planned line images: short passes of their own, the nearest to the flown passes first,
        # until the share of the field's heliostats imaged reaches min_planned_coverage
        need = math.ceil(st.min_planned_coverage * len(names) - 1e-9) - len(seen_hua) - len(rescued)
        if need > 0 and left:
            caps_xy = np.array([(w.x_m, w.y_m) for p in passes if p.feasible for w in p.waypoints if w.capture])
            caps_tree = cKDTree(caps_xy) if len(caps_xy) else None
            alts = [p.altitude_m for p, ln in zip(passes, lines, strict=True) if ln is not None and p.feasible]
            own = {"z": float(np.median(alts)) if alts else None,  # the own lines' altitude (their own adds keep it)
                   "index": max(q.index for q in passes) + 1}
            own_pending = []  # every HUA's own lines first (their numbering), then evaluated in batches
            for hh in left:
                ks = _own_lines(hh, pose, passes, lines, ctx, own)
                if ks is not None:
                    own_pending.append((hh, ks, np.zeros(len(ks))))

            def own_offers(j: int) -> list[tuple[float, int, tuple]]:
                """The offers of the HUAs of piece ``j`` (whole batches): each HUA's best own line, its cost."""
                found = []
                for hh, cand_, ev_ in _evaluated(own_pending[cuts[j]:cuts[j + 1]],
                                                 lambda ks, _along, _before: np.ones(len(ks), bool), lines, pose,
                                                 camera, st, ctx):
                    picks_ = _greedy(ev_, cand_, used, st, commit=False)  # used: nothing yet on new lines
                    total = [sum(int(m.sum()) for _, _, m, _ in pk) for pk in picks_]
                    b_ = int(np.argmax(total))
                    if total[b_] == 0 or total[b_] < st.rescue_min_fraction * n_f:
                        continue
                    # the best only, what commit() reads: its facets any position and aim covers (kept 4-D)
                    best_ev = {k: ev_[k][b_:b_ + 1].copy() for k in ("k", *_KEPT)}
                    best_ev["good"] = ev_["good"][b_:b_ + 1].any(axis=(1, 2), keepdims=True)
                    xy = ev_["cam"][b_, [g for g, _, _, _ in picks_[b_]], :2]
                    cost = 0.0
                    if caps_tree is not None:  # distance to the nearest planned capture: among its 8 nearest
                        _, near = caps_tree.query(xy, k=min(8, len(caps_xy)))
                        near = np.unique(np.asarray(near).ravel())
                        cost = float(np.min(np.linalg.norm(caps_xy[near][:, None, :] - xy[None], axis=-1)))
                    found.append((cost, hh, ([cand_[b_]], best_ev, [picks_[b_]], 0)))
                return found

            # the HUAs' own lines are independent (nothing is committed before all are offered): runs of whole
            # batches (as _evaluated forms them, so the same batches whatever the workers) side by side
            starts = _batch_starts([len(ks) for _, ks, _ in own_pending], st.batch)
            cuts = starts[::_BATCHES_PER_PIECE] + [len(own_pending)]
            offers = [o for part in _forked.imap(own_offers, len(cuts) - 1, workers, what="HUAs' own lines")
                      for o in part]
            for cost, hh, (cand_, ev_, picks_, b_) in sorted(offers, key=lambda o: o[:2])[:need]:
                if any(int(ev_["k"][b_, g]) in used.get(cand_[b_].pass_k, set()) for g, _, _, _ in picks_[b_]):
                    continue
                extent[cand_[b_].pass_k] = (0.0, 0.0)
                commit(cand_[b_], ev_, b_, picks_[b_])
    if st.target_fraction is not None:
        _trim(chosen, n_f, st.target_fraction)
    # captures per pass
    caps: list[FacetCapture] = []
    per_pass: dict[int, list[tuple[float, FacetCapture, float, float]]] = {}
    predicted: dict[str, tuple[int, ...]] = {}
    for i, ev, _, pk in chosen:
        mask = np.zeros(n_f, dtype=bool)
        for g, a_, new, tg in pk:
            mask |= new
            cam = ev["cam"][g]
            fc = FacetCapture(passes[i.pass_k].index, i.hua, tg, float(ev["s"][g]), tuple(map(float, cam)),
                              tuple(map(float, ev["aims"][a_])), tuple(np.flatnonzero(new).tolist()))
            caps.append(fc)
            per_pass.setdefault(i.pass_k, []).append((float(ev["s"][g]), fc, float(ev["head"][g, a_]),
                                                      float(ev["pitch"][g, a_])))
        predicted[names[i.hua]] = tuple(np.flatnonzero(mask).tolist())
    out: list[ScanPass | None] = []
    redo: list[tuple[int, ScanPass, _Line | None, _Layout]] = []  # passes rebuilt: their slot in out, layout
    for k, p in enumerate(passes):
        got = per_pass.get(k)
        if k >= n_planned and not got:
            continue  # a rescue line tried but not used
        keep_old = [w for w in p.waypoints if w.capture and w.hua in index
                    and names[index[w.hua]] not in predicted]  # HUAs with nothing coverable keep their capture
        if not got and not keep_old:
            out.append(dataclasses.replace(p, predictions=()))
            continue
        redo.append((len(out), p, lines[k], _layout(lines[k], got or [], keep_old, names, st)))
        out.append(None)
    # the new waypoints' geodetic coordinates at once (a call per pass cost seconds at 100,000 heliostats)
    pts = np.concatenate([lay.pts for *_, lay in redo]) if redo else np.zeros((0, 3))
    lat, lon, hgt = enu_to_geodetic(pts, org) if len(pts) else (np.zeros(0),) * 3
    q = 0
    for slot, p, ln, lay in redo:
        m = len(lay.pts)
        out[slot] = _rebuild(p, ln, lay, lat[q:q + m], lon[q:q + m], hgt[q:q + m], st)
        q += m
    return FacetPlan(tuple(o for o in out if o is not None), tuple(caps), predicted, coverable, tuple(rescued))


def _own_lines(hh: int, pose: Any, passes: list[ScanPass], lines: list[_Line | None], ctx: dict[str, Any],
               own: dict[str, Any]) -> NDArray[np.int64] | None:
    """Lines of its own for a HUA no planned line images: through the point that shows each candidate
    target's centre at the HUA's centre (``H + t w``, ``w`` the mirror image of the direction to the
    target), along the HUA's normals' plane, at the median pass altitude (``own["z"]``). Appends a line and
    a placeholder pass (numbered from ``own["index"]``) per candidate; returns their indices or None."""
    z = own["z"]
    if z is None:
        return None
    c, n = pose.mirror_centres, pose.normals
    tgt = ctx["targets"](np.array([hh]))[0]
    tgt = tgt[tgt >= 0]
    tgt = tgt[dot(c[tgt] - c[hh], n[tgt]) > 0]  # their back faces the HUA
    if len(tgt) == 0:
        return None
    u = c[tgt] - c[hh]
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    w = 2.0 * (u @ n[hh])[:, None] * n[hh] - u
    ok = w[:, 2] > math.sin(math.radians(5.0))
    if not ok.any():
        return None
    w = w[ok]
    cam = c[hh] + ((z - c[hh, 2]) / w[:, 2])[:, None] * w
    b = n[hh, :2] / max(float(np.linalg.norm(n[hh, :2])), 1e-12)
    k0 = len(passes)
    for p0 in cam:
        lines.append(_Line(np.array([p0[0], p0[1], z]), b, z))
        own["index"] += 1
        passes.append(ScanPass(index=own["index"] - 1, azimuth_deg=float(azimuth_deg(b[0], b[1])),
                               altitude_m=z,
                               gimbal_pitch_deg=-90.0, pairs=(), waypoints=(), feasible=True,
                               issues=(f"{pose.field.names[hh]}: imaged from a short pass of its own (no planned "
                                       "line shows its facets a heliostat's back)",)))
    return np.arange(k0, k0 + len(cam), dtype=np.int64)


def _trim(chosen: list[tuple[Any, Any, int, list]], n_f: int, target: float) -> None:
    """Drop the last captures of HUAs, fewest new facets first, while the covered share stays >= target."""
    import heapq

    total = n_f * sum(1 for c in chosen if c[3])
    covered = sum(int(m.sum()) for c in chosen for _, _, m, _ in c[3])
    heap = [(int(c[3][-1][2].sum()), k) for k, c in enumerate(chosen) if len(c[3]) > 1]
    heapq.heapify(heap)
    while heap:
        gain, k = heapq.heappop(heap)
        if total == 0 or (covered - gain) / total < target:
            break
        picks = chosen[k][3]
        picks.pop()
        covered -= gain
        if len(picks) > 1:
            heapq.heappush(heap, (int(picks[-1][2].sum()), k))


def _batch_starts(counts: Sequence[int], size: int) -> list[int]:
    """Where :func:`_evaluated` starts its batches when it admits every candidate: ``counts`` candidates per
    HUA, at most ``size`` per batch (a HUA with more alone)."""
    starts: list[int] = []
    n = 0
    for k, m in enumerate(counts):
        if not starts or n + m > size:
            starts.append(k)
            n = m
        else:
            n += m
    return starts


def _evaluated(pending: Sequence[tuple[int, NDArray[np.int64], NDArray[np.float64]]], admit: Any,
               lines: Sequence[_Line | None], pose: Any, camera: CameraModel, st: FacetCaptureSettings,
               ctx: dict[str, Any]) -> Iterator[tuple[int, list[_Instance], dict[str, NDArray] | None]]:
    """``(hua, candidates, evaluation)`` in order, the candidates of several HUAs evaluated in one batch.

    ``pending`` holds per HUA its candidate pass lines and positions along them; ``admit(lines, positions,
    before)``, asked when a batch is formed (after the decisions on the HUAs of the batches before), says which
    can still be chosen, ``before`` counting per pass line the HUAs ahead in the batch that may extend it.
    An instance's evaluation depends neither on the others in its batch nor on the grid positions already
    used (only :func:`_greedy` does), so a batch of up to ``st.batch`` instances serves several HUAs: a
    100,000-heliostat field has about 25,000 HUAs to rescue, one small evaluation each before.
    """
    k0 = 0
    while k0 < len(pending):
        k1, n = k0, 0
        batch: list[tuple[int, list[_Instance]]] = []
        before: dict[int, int] = {}
        while k1 < len(pending):
            hh, ks, along = pending[k1]
            ok = admit(ks, along, before)
            cand = [_Instance(hh, k, s_) for k, s_ in zip(ks[ok].tolist(), along[ok].tolist(), strict=True)]
            if batch and n + len(cand) > st.batch:
                break
            batch.append((hh, cand))
            for k in {i.pass_k for i in cand}:
                before[k] = before.get(k, 0) + 1
            n += len(cand)
            k1 += 1
        flat = [i for _, cand in batch for i in cand]
        ev = _evaluate(flat, lines, pose, camera, st, ctx) if flat else {}
        off = 0
        for hh, cand in batch:
            yield hh, cand, ({k: v[off:off + len(cand)] for k, v in ev.items()} if cand else None)
            off += len(cand)
        k0 = k1


#: What the captures are built from once chosen (:func:`_slice`).
_KEPT = ("s", "cam", "aims", "head", "pitch")


def _slice(ev: dict[str, NDArray], b: int) -> dict[str, NDArray]:
    """Instance ``b``'s part of an evaluation, copied: a view would keep the batch's (B, G, A, F) arrays alive
    until the end (2 GB at 30,000 heliostats)."""
    return {k: ev[k][b].copy() for k in _KEPT}


class _Layout(NamedTuple):
    """A rebuilt pass's waypoints before geodetic conversion (internal): the captures sorted along the line
    ``(s, xyz, heading, pitch, hua, target)``, the lead-in and run-past ``(xyz, heading, pitch, kind)`` and
    every point in waypoint order, ENU metres (P, 3)."""

    items: list[tuple[float, NDArray[np.float64], float, float, str, str | None]]
    pre: list[tuple[NDArray[np.float64], float, float, str]]
    post: list[tuple[NDArray[np.float64], float, float, str]]
    pts: NDArray[np.float64]


def _layout(ln: _Line | None, got: list[tuple[float, FacetCapture, float, float]], keep_old: list[Waypoint],
            names: list[str], st: FacetCaptureSettings) -> _Layout:
    """The capture waypoints of a pass: ``got`` (plus old captures kept), sorted along the line, with a lead-in
    and a run-past."""
    assert ln is not None
    items: list[tuple[float, NDArray[np.float64], float, float, str, str | None]] = []
    for s_, fc, head, pitch in got:
        items.append((s_, np.array(fc.camera), head, pitch, names[fc.hua], names[fc.target] if fc.target >= 0
                      else None))
    for w in keep_old:
        s_ = float(dot(np.array([w.x_m, w.y_m]) - ln.a[:2], ln.e))
        items.append((s_, np.array([w.x_m, w.y_m, w.z_m]), w.heading_deg, w.gimbal_pitch_deg, w.hua or "", None))
    items.sort(key=lambda t: t[0])
    e3 = np.r_[ln.e, 0.0]
    pre: list[tuple[NDArray[np.float64], float, float, str]] = []
    if st.lead_in_m > 0:
        pre.append((ln.a + (items[0][0] - st.lead_in_m) * e3, items[0][2], items[0][3], "lead_in"))
    post: list[tuple[NDArray[np.float64], float, float, str]] = []
    if st.run_past_m > 0:
        post.append((ln.a + (items[-1][0] + st.run_past_m) * e3, items[-1][2], items[-1][3], "run_past"))
    pts = np.array([t[0] for t in pre] + [t[1] for t in items] + [t[0] for t in post], float)
    return _Layout(items, pre, post, pts)


def _rebuild(p: ScanPass, ln: _Line | None, lay: _Layout, lat: NDArray[np.float64], lon: NDArray[np.float64],
             hgt: NDArray[np.float64], st: FacetCaptureSettings) -> ScanPass:
    """A pass whose capture waypoints are those of ``lay``, at the geodetic coordinates of ``lay.pts``."""
    assert ln is not None
    speed = next((w.speed_m_s for w in p.waypoints if w.kind == "scan"), st.speed_m_s)
    old_pairs = dict(p.pairs)
    wps: list[Waypoint] = []
    q = 0
    for x, hd, gp, kind in lay.pre:
        wps.append(_wp(x, lat[q], lon[q], hgt[q], hd, gp, speed, kind, False, None))
        q += 1
    for _, x, hd, gp, hua, _ in lay.items:
        wps.append(_wp(x, lat[q], lon[q], hgt[q], hd, gp, speed, "scan", True, hua))
        q += 1
    for x, hd, gp, kind in lay.post:
        wps.append(_wp(x, lat[q], lon[q], hgt[q], hd, gp, speed, kind, False, None))
        q += 1
    pairs = tuple((t[4], t[5] if t[5] is not None else old_pairs.get(t[4], t[4])) for t in lay.items)
    issues = tuple(i for i in p.issues if not i.startswith("HUA not framed whole"))
    pitches = [w.gimbal_pitch_deg for w in wps if w.capture]
    return dataclasses.replace(p, pairs=pairs, waypoints=tuple(wps), predictions=(), issues=issues,
                               azimuth_deg=float(azimuth_deg(ln.e[0], ln.e[1])),
                               gimbal_pitch_deg=statistics.median(pitches) if pitches else p.gimbal_pitch_deg)


def _wp(x: NDArray[np.float64], lat: float, lon: float, h: float, heading: float, pitch: float, speed: float,
        kind: str, capture: bool, hua: str | None) -> Waypoint:
    return Waypoint(float(x[0]), float(x[1]), float(x[2]), float(lat), float(lon), float(h), heading_0_360(heading),
                    float(pitch), float(speed), kind=kind, capture=capture, hua=hua)  # type: ignore[arg-type]
