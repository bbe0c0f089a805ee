"""Straight scan lines in the vertical planes of the tracking normals, and what a camera on them sees.

UFACET (paper section 3, Fig. 2a; OpenCSP's planner [2]_) flies each scan
pass in the vertical plane of the tracking normals of the heliostats under
assessment (HUAs): from there a HUA shows, reflected across its mirror, the
back of a target heliostat nearer the tower. This module builds such lines
for a tracked field and tests, for any camera position on a line, which
target each HUA shows.

Lines
-----
1. **Candidates** (:func:`candidate_targets`). For each heliostat ``H`` the
   heliostats ``T`` in front of its mirror (``u . n_H > 0``, ``u`` the unit
   vector from the HUA mirror centre to the target mirror centre) whose
   back faces it (``u . n_T > 0``), within a search radius, an off-axis
   angle and a lateral distance of the vertical plane of ``n_H``.
2. **Links** (:func:`plane_links`). Each heliostat links to the candidate
   nearest the vertical plane of its normal among those abreast of its
   nearest candidate (forward distances within ``abreast_m``): a discrete
   streamline of the horizontal normal field, which crosses the columns of
   a rectangular field as the normals' planes do (OpenCSP's NSTTF line
   5W5 ... 12W14 steps one column over per row).
3. **Chains** (:func:`link_chains`). Where several heliostats link to the
   same one, the link continuing the target's own link most straightly is
   kept; the kept links form disjoint chains, every heliostat in one. A
   chain whose heliostats stray too far from its line is halved until they
   do not: in a large field a chain runs over the whole radius, along
   normals' planes that curve, and one straight line through it would image
   fewer and fewer of its heliostats as the field grows.
4. **Lines** (:func:`chain_lines`). Each chain gives a straight line whose
   direction is the mean horizontal direction of its heliostats' normals
   (the normals' plane) through the centroid of their mirror centres. The
   planner then shifts each line sideways (a few metres) and picks its
   altitude to image the most HUAs.

Views from a line
-----------------
A camera ``C`` sees the target's mirror centre reflected at the HUA mirror
centre when ``C`` lies on the ray ``H + t w``, ``w = 2 (u . n_H) n_H - u``
(the mirror image of ``u``). At altitude ``z`` that point is generally not on
the line; :func:`views_from_lines` puts the camera at its projection onto
the line (same altitude, nearest point) and traces the ray camera -> HUA
centre reflected about ``n_H``: the pair is imaged when that ray reaches
the target's mirror rectangle from behind, nothing blocks it (mirrors,
tower), nothing blocks the sight line camera -> HUA, and the camera is in
range, within the gimbal limits and outside the tower keep-out. The camera
is then off the HUA's normal plane by the HUA's distance from the line.

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone" (pihim paper), section 3 and Fig. 2a (UFACET geometry).
.. [2] Sandia National Laboratories, OpenCSP (Apache-2.0),
   ``contrib/app/ufacet-s/flight_planner_ufacet`` (ideal-gaze curves along
   the tracking normals, straight scan sections), read for the method only.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from pihim.field.kinematics import FieldPose
from pihim.planning.model import ScanPass, heading_0_360
from pihim.planning.sightlines import (
    TOWER_HIT,
    MirrorIndex,
    dot,
    segments_hit_box,
    unit,
)

__all__ = [
    "VIEW_OK",
    "Candidates",
    "PairGeometry",
    "PassAlignment",
    "ScanLines",
    "ViewLimits",
    "Views",
    "alignment_summary",
    "candidate_targets",
    "chain_lines",
    "horizontal_normals",
    "line_offsets",
    "link_chains",
    "pair_geometry",
    "pass_alignment",
    "plane_links",
    "views_from_lines",
    "views_of_pairs",
]

# Outcome codes of a view, in the order the tests run (a larger code failed later: "nearly imaged").
VIEW_LOW = 1  # camera direction w too close to the horizon
VIEW_BEHIND = 2  # camera behind the HUA mirror plane or farther than the range limit
VIEW_OFF_PLANE = 3  # camera too far aside of the vertical plane of the HUA's normal
VIEW_GIMBAL = 4  # pitch outside the gimbal range, or camera in the tower keep-out
VIEW_MISS = 5  # the reflection at the HUA centre misses the target mirror
VIEW_REFLECTION_BLOCKED = 6  # a mirror or the tower blocks the reflected ray HUA -> target
VIEW_CAMERA_BLOCKED = 7  # a mirror or the tower blocks the sight line camera -> HUA
VIEW_OK = 8


@dataclass(frozen=True)
class Candidates:
    """Candidate (HUA, target) pairs, sorted by HUA then by distance.

    Attributes
    ----------
    hua, target : ndarray of int, shape (P,)
        Heliostat indices.
    forward_m : ndarray, shape (P,)
        Horizontal distance of the target along the HUA's normal direction.
    lateral_m : ndarray, shape (P,)
        Signed horizontal distance of the target from the HUA's normals'
        plane (positive to the right looking along the normal).
    distance_m : ndarray, shape (P,)
        Mirror centre to mirror centre, metres.
    """

    hua: NDArray[np.int64]
    target: NDArray[np.int64]
    forward_m: NDArray[np.float64]
    lateral_m: NDArray[np.float64]
    distance_m: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.hua)

    def take(self, sel: NDArray) -> Candidates:
        """The pairs selected by a boolean mask or an index array."""
        return Candidates(self.hua[sel], self.target[sel], self.forward_m[sel], self.lateral_m[sel],
                          self.distance_m[sel])


@dataclass(frozen=True)
class ScanLines:
    """Straight horizontal lines, one per scan pass candidate.

    Attributes
    ----------
    origin : ndarray, shape (L, 2)
        A point of each line (East, North metres).
    direction : ndarray, shape (L, 2)
        Unit direction, the mean horizontal direction of the normals of the
        line's heliostats (pointing toward the mirror fronts).
    """

    origin: NDArray[np.float64]
    direction: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.origin)

    @functools.cached_property
    def across(self) -> NDArray[np.float64]:
        """Unit horizontal vector to the right of each direction, shape (L, 2) (worked out once: the views
        of every candidate line setting read it, 4 s at 100,000 heliostats when rebuilt per read)."""
        return np.stack([self.direction[:, 1], -self.direction[:, 0]], axis=1)

    def lateral(self, line: NDArray[np.int64], xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Signed distance of points ``xy`` (K, 2) from lines ``line`` (K,), metres."""
        return dot(xy - self.origin[line], self.across[line])

    def along(self, line: NDArray[np.int64], xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Coordinate of points ``xy`` (K, 2) along lines ``line`` (K,), metres."""
        return dot(xy - self.origin[line], self.direction[line])


@dataclass(frozen=True)
class ViewLimits:
    """Limits a camera view must respect (see :class:`pihim.planning.ufacet.UfacetSettings`)."""

    max_range_m: float
    min_reflection_elevation_deg: float
    gimbal_pitch_min_deg: float
    gimbal_pitch_max_deg: float
    tower_box: tuple[NDArray[np.float64], NDArray[np.float64]] | None
    keepout_box: tuple[NDArray[np.float64], NDArray[np.float64]] | None
    max_plane_offset_m: float = math.inf


@dataclass(frozen=True)
class Views:
    """Outcome of camera views of (HUA, target) pairs from lines, arrays of length K.

    Attributes
    ----------
    camera : ndarray, shape (K, 3)
        Camera position on the line, ENU metres.
    code : ndarray of int, shape (K,)
        :data:`VIEW_OK` when imaged, else the first failed test (module
        constants ``VIEW_*``).
    blocker : ndarray of int, shape (K,)
        Heliostat index (or :data:`~pihim.planning.sightlines.TOWER_HIT`)
        blocking the reflected ray or the sight line; -1 otherwise.
    range_m : ndarray, shape (K,)
        Camera to HUA mirror centre.
    elevation_deg : ndarray, shape (K,)
        Elevation of the exact camera direction ``w`` seen from the HUA.
    miss_m : ndarray, shape (K,)
        How far outside the target mirror the reflection at the HUA centre
        lands (0 inside).
    plane_offset_m : ndarray, shape (K,)
        Horizontal distance of the camera from the vertical plane of the
        HUA's tracking normal.
    """

    camera: NDArray[np.float64]
    code: NDArray[np.int64]
    blocker: NDArray[np.int64]
    range_m: NDArray[np.float64]
    elevation_deg: NDArray[np.float64]
    miss_m: NDArray[np.float64]
    plane_offset_m: NDArray[np.float64]

    @property
    def ok(self) -> NDArray[np.bool_]:
        """Imaged: the camera on the line shows the target reflected at the HUA centre."""
        return self.code == VIEW_OK


def horizontal_normals(pose: FieldPose) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Unit horizontal direction of each tracking normal, and whether it is defined (normal not vertical)."""
    n = pose.normals
    nb = np.hypot(n[:, 0], n[:, 1])
    ok = nb > 1e-9
    b = np.where(ok[:, None], n[:, :2] / np.maximum(nb, 1e-12)[:, None], 0.0)
    return b, ok


def candidate_targets(pose: FieldPose, *, max_distance_m: float, max_off_axis_deg: float,
                      max_lateral_m: float) -> Candidates:
    """Heliostats in front of each mirror that turn their back to it (step 1 of the module docstring).

    Parameters
    ----------
    pose : FieldPose
        Tracked field.
    max_distance_m : float
        Horizontal search radius, metres.
    max_off_axis_deg : float
        Largest horizontal angle between the HUA's normal and the direction
        to the target, degrees.
    max_lateral_m : float
        Largest distance of the target's mirror centre from the vertical
        plane of the HUA's normal, metres.

    Returns
    -------
    Candidates
        Sorted by HUA, then distance.
    """
    c = pose.mirror_centres
    n = pose.normals
    b, has_b = horizontal_normals(pose)
    pr = cKDTree(c[:, :2]).query_pairs(max_distance_m, output_type="ndarray")
    if len(pr) == 0:
        e = np.zeros(0, dtype=np.int64)
        z = np.zeros(0)
        return Candidates(e, e, z, z, z)
    i = np.concatenate([pr[:, 0], pr[:, 1]]).astype(np.int64)
    j = np.concatenate([pr[:, 1], pr[:, 0]]).astype(np.int64)
    dxy = c[j, :2] - c[i, :2]
    fwd = dot(dxy, b[i])
    lat = dxy[:, 0] * b[i, 1] - dxy[:, 1] * b[i, 0]
    u = unit(c[j] - c[i])
    off = np.degrees(np.arctan2(np.abs(lat), fwd))
    ok = (fwd > 0) & (off <= max_off_axis_deg) & (np.abs(lat) <= max_lateral_m) & has_b[i]
    ok &= (dot(u, n[i]) > 0) & (dot(u, n[j]) > 0)
    i, j, fwd, lat = i[ok], j[ok], fwd[ok], lat[ok]
    dist = np.linalg.norm(c[j] - c[i], axis=1)
    order = np.lexsort((dist, i))
    return Candidates(i[order], j[order], fwd[order], lat[order], dist[order])


def plane_links(cand: Candidates, n_heliostats: int, abreast_m: float) -> NDArray[np.int64]:
    """Next heliostat toward the tower along each heliostat's normals' plane (step 2), -1 for none.

    Among the candidates whose forward distance is within ``abreast_m`` of
    the nearest one (the next row), the one nearest the vertical plane of
    the heliostat's normal.
    """
    link = np.full(n_heliostats, -1, dtype=np.int64)
    if len(cand) == 0:
        return link
    h = cand.hua
    first = np.r_[True, h[1:] != h[:-1]]
    starts = np.flatnonzero(first)
    nearest = np.minimum.reduceat(cand.forward_m, starts)
    group = np.cumsum(first) - 1
    near_row = cand.forward_m <= nearest[group] + abreast_m
    # within each HUA: the near-row candidate with the smallest |lateral| (then the nearest)
    key_lat = np.where(near_row, np.abs(cand.lateral_m), np.inf)
    order = np.lexsort((cand.forward_m, key_lat, h))
    pick = order[np.r_[True, h[order][1:] != h[order][:-1]]]
    link[h[pick]] = cand.target[pick]
    return link


def link_chains(link: NDArray[np.int64], centres: NDArray[np.float64], max_deviation_m: float = math.inf,
                normals_xy: NDArray[np.float64] | None = None) -> NDArray[np.int64]:
    """Chain id of every heliostat (step 3): where several link to one, the straightest link is kept.

    With ``max_deviation_m`` (and ``normals_xy``, the horizontal normal
    directions), a chain whose members lie farther than that from its line
    (:func:`chain_lines`: mean normal direction through their centroid) is
    cut in two halves, and so on: in a large field a chain spans the whole
    radius along curving normals' planes, which one straight line cannot
    follow.
    """
    n_h = len(link)
    src = np.flatnonzero(link >= 0)
    dst = link[src]
    v1 = unit(centres[dst, :2] - centres[src, :2])
    onward = link[dst]
    has = onward >= 0
    v2 = np.zeros_like(v1)
    v2[has] = unit(centres[onward[has], :2] - centres[dst[has], :2])
    bend = np.where(has, 1.0 - dot(v1, v2), 0.0)
    length = np.linalg.norm(centres[dst, :2] - centres[src, :2], axis=1)
    order = np.lexsort((length, bend, dst))
    src, dst = src[order], dst[order]
    first = np.r_[True, dst[1:] != dst[:-1]] if len(dst) else np.zeros(0, bool)
    pred = np.full(n_h, -1, dtype=np.int64)
    pred[dst[first]] = src[first]
    succ = np.full(n_h, -1, dtype=np.int64)
    succ[pred[pred >= 0]] = np.flatnonzero(pred >= 0)
    chain = np.full(n_h, -1, dtype=np.int64)
    cid = 0
    split = math.isfinite(max_deviation_m) and normals_xy is not None
    for start in np.flatnonzero(succ < 0).tolist():  # the innermost heliostat of every chain
        members = []
        k = start
        while k >= 0 and chain[k] < 0:
            chain[k] = cid
            members.append(k)
            k = int(pred[k])
        if split and len(members) > 2:
            for piece in _straight_pieces(np.asarray(members), centres[:, :2], normals_xy, max_deviation_m):
                chain[piece] = cid
                cid += 1
        else:
            cid += 1
    rest = np.flatnonzero(chain < 0)  # cycles cannot occur (links go forward along each normal); be safe
    chain[rest] = cid + np.arange(len(rest))
    return chain


def _straight_pieces(members: NDArray[np.int64], xy: NDArray[np.float64], normals_xy: NDArray[np.float64],
                     max_deviation_m: float) -> list[NDArray[np.int64]]:
    """Halve a chain (members in order) until every piece's members lie within ``max_deviation_m`` of its line."""
    d = normals_xy[members].sum(axis=0)
    norm = float(np.hypot(*d))
    if len(members) <= 2 or norm < 1e-9:
        return [members]
    d = d / norm
    rel = xy[members] - xy[members].mean(axis=0)
    if float(np.max(np.abs(rel[:, 0] * d[1] - rel[:, 1] * d[0]))) <= max_deviation_m:
        return [members]
    half = len(members) // 2
    return (_straight_pieces(members[:half], xy, normals_xy, max_deviation_m)
            + _straight_pieces(members[half:], xy, normals_xy, max_deviation_m))


def chain_lines(chain: NDArray[np.int64], normals_xy: NDArray[np.float64],
                centres_xy: NDArray[np.float64]) -> ScanLines:
    """One straight line per chain (step 4): mean normals' plane direction, through the centroid."""
    n_lines = int(chain.max()) + 1 if len(chain) else 0
    count = np.bincount(chain, minlength=n_lines).astype(float)
    d = np.zeros((n_lines, 2))
    np.add.at(d, chain, normals_xy)
    norm = np.linalg.norm(d, axis=1)
    origin = np.zeros((n_lines, 2))
    np.add.at(origin, chain, centres_xy)
    origin /= np.maximum(count, 1.0)[:, None]
    # a chain whose normals cancel (cannot happen for a tracking field) keeps the first member's direction
    first = np.full(n_lines, -1, dtype=np.int64)
    first[chain[::-1]] = np.arange(len(chain))[::-1]
    fallback = normals_xy[np.maximum(first, 0)]
    d = np.where(norm[:, None] > 1e-9, d / np.maximum(norm, 1e-12)[:, None], fallback)
    return ScanLines(origin, d)


def line_offsets(max_m: float, step_m: float) -> NDArray[np.float64]:
    """Sideways shifts tried for each line: 0, then +-step, +-2 step ... up to ``max_m``."""
    k = math.floor(max_m / step_m + 1e-9) if step_m > 0 else 0
    return np.r_[0.0, np.ravel(np.column_stack([np.arange(1, k + 1), -np.arange(1, k + 1)])) * step_m]


@dataclass(frozen=True)
class PairGeometry:
    """Per (HUA, target) pair quantities every view of the pair shares (arrays of length P).

    Built by :func:`pair_geometry`; ``w`` is the unit direction from the
    HUA mirror centre toward the cameras that see the target's centre
    reflected there, ``elevation_deg`` its elevation.
    """

    hua: NDArray[np.int64]
    target: NDArray[np.int64]
    hua_centre: NDArray[np.float64]
    hua_normal: NDArray[np.float64]
    hua_plane_normal_xy: NDArray[np.float64]
    target_centre: NDArray[np.float64]
    target_normal: NDArray[np.float64]
    target_x: NDArray[np.float64]
    target_y: NDArray[np.float64]
    w: NDArray[np.float64]
    elevation_deg: NDArray[np.float64]
    half_width_m: float
    half_height_m: float


def pair_geometry(pose: FieldPose, hua: NDArray[np.int64], target: NDArray[np.int64]) -> PairGeometry:
    """Shared geometry of (HUA, target) pairs of a tracked field."""
    c, n = pose.mirror_centres, pose.normals
    ch, nh, ct = c[hua], n[hua], c[target]
    u = unit(ct - ch)
    w = 2.0 * dot(u, nh)[:, None] * nh - u
    nxy = horizontal_normals(pose)[0][hua]
    rot = pose.rotations[target]
    spec = pose.field.spec  # type: ignore[attr-defined]
    return PairGeometry(hua, target, ch, nh, nxy, ct, n[target], np.ascontiguousarray(rot[:, :, 0]),
                        np.ascontiguousarray(rot[:, :, 1]), w,
                        np.degrees(np.arcsin(np.clip(w[:, 2], -1.0, 1.0))),
                        float(spec.mirror_half_width_m), float(spec.mirror_half_height_m))


def views_from_lines(pose: FieldPose, mirrors: MirrorIndex, limits: ViewLimits, hua: NDArray[np.int64],
                     target: NDArray[np.int64], origin: NDArray[np.float64], direction: NDArray[np.float64],
                     altitude: NDArray[np.float64], *, trace: bool = True) -> Views:
    """What a camera on a line at an altitude sees of (HUA, target) pairs, vectorised over K combinations.

    Parameters
    ----------
    pose : FieldPose
        Tracked field.
    mirrors : MirrorIndex
        Mirror rectangles of ``pose`` (for the blocking tests).
    limits : ViewLimits
        Range, elevation, plane offset, gimbal and tower limits.
    hua, target : ndarray of int, shape (K,)
        The pairs.
    origin, direction : ndarray, shape (K, 2)
        Line point and unit direction per combination.
    altitude : ndarray, shape (K,)
        Camera altitude, metres above the field origin.
    trace : bool
        Run the blocking tests (ray / mirror, ray / tower). Without them the
        codes stop at :data:`VIEW_MISS` and passing combinations get
        :data:`VIEW_OK` provisionally.

    Returns
    -------
    Views
    """
    geom = pair_geometry(pose, np.asarray(hua, np.int64), np.asarray(target, np.int64))
    return views_of_pairs(geom, np.arange(len(geom.hua)), mirrors, limits, origin, direction, altitude,
                          trace=trace)


def views_of_pairs(geom: PairGeometry, pair: NDArray[np.int64], mirrors: MirrorIndex, limits: ViewLimits,
                   origin: NDArray[np.float64], direction: NDArray[np.float64], altitude: NDArray[np.float64],
                   *, trace: bool = True) -> Views:
    """:func:`views_from_lines` for pairs ``geom[pair]`` (K,), reusing their precomputed geometry."""
    from pihim.planning import _kernels

    pair = np.ascontiguousarray(pair, dtype=np.int64)
    n = len(pair)

    def f64(a: ArrayLike, shape: tuple[int, ...]) -> NDArray[np.float64]:
        return np.ascontiguousarray(np.broadcast_to(np.asarray(a, float), shape))

    def whole(a: NDArray) -> NDArray[np.float64]:  # the pair geometry's arrays, indexed in the kernel
        return np.ascontiguousarray(a, dtype=float)

    keep = limits.keepout_box
    cam, code, rng, v, plane_offset, miss, r_all, hit_all = _kernels.view_tests(
        pair, whole(geom.hua_centre), whole(geom.hua_normal), whole(geom.w), whole(geom.elevation_deg),
        f64(np.asarray(origin)[..., :2], (n, 2)), f64(np.asarray(direction)[..., :2], (n, 2)), f64(altitude, (n,)),
        whole(geom.hua_plane_normal_xy), whole(geom.target_centre), whole(geom.target_normal),
        whole(geom.target_x), whole(geom.target_y), float(geom.half_width_m),
        float(geom.half_height_m), float(limits.max_range_m), float(limits.min_reflection_elevation_deg),
        float(limits.max_plane_offset_m), float(limits.gimbal_pitch_min_deg), float(limits.gimbal_pitch_max_deg),
        np.zeros((2, 3)) if keep is None else np.array([keep[0], keep[1]], float), keep is not None,
        VIEW_LOW, VIEW_BEHIND, VIEW_OFF_PLANE, VIEW_GIMBAL, VIEW_MISS, VIEW_OK)
    elev = geom.elevation_deg[pair]
    blocker = np.full(n, -1, dtype=np.int64)
    if trace:
        # the reflected ray HUA -> target where it hits the target's mirror (every test so far passed)
        k = np.flatnonzero(miss <= 0)
        r, hit = r_all[k], hit_all[k]
        if len(k):
            pk = pair[k]
            p0, p1 = geom.hua_centre[pk] + 1e-6 * r, hit - 1e-6 * r
            hits = mirrors.first_hits(p0, p1, np.stack([geom.hua[pk], geom.target[pk]], axis=1))
            if limits.tower_box is not None:
                hits = np.where((hits < 0) & segments_hit_box(p0, p1, *limits.tower_box), TOWER_HIT, hits)
            blocked = hits != -1
            code[k[blocked]] = VIEW_REFLECTION_BLOCKED
            blocker[k[blocked]] = hits[blocked]
        k = np.flatnonzero(code == VIEW_OK)
        if len(k):
            pk = pair[k]
            p0, p1 = cam[k], geom.hua_centre[pk] + 1e-6 * v[k]
            hits = mirrors.first_hits(p0, p1, geom.hua[pk, None])
            if limits.tower_box is not None:
                hits = np.where((hits < 0) & segments_hit_box(p0, p1, *limits.tower_box), TOWER_HIT, hits)
            blocked = hits != -1
            code[k[blocked]] = VIEW_CAMERA_BLOCKED
            blocker[k[blocked]] = hits[blocked]
    return Views(cam, code, blocker, rng, elev, miss, plane_offset)


@dataclass(frozen=True)
class PassAlignment:
    """How well one scan pass keeps to the vertical planes of its HUAs' tracking normals.

    Attributes
    ----------
    index : int
        The pass.
    plane_azimuth_deg : float
        Azimuth of the mean horizontal normal direction of the pass's HUAs,
        folded to the direction of travel, degrees clockwise from North.
    median_deviation_deg, max_deviation_deg : float
        Angle between the direction of travel and each imaged HUA's normals'
        plane, degrees (0: the pass lies in the plane's direction).
    median_camera_offset_m, max_camera_offset_m : float
        Horizontal distance of each capture point from the vertical plane of
        its HUA's normal, metres.
    max_off_line_m : float
        Largest horizontal distance of a waypoint from the straight line
        lead-in -> run-past, metres (0 for a straight pass).
    """

    index: int
    plane_azimuth_deg: float
    median_deviation_deg: float
    max_deviation_deg: float
    median_camera_offset_m: float
    max_camera_offset_m: float
    max_off_line_m: float


def _capture_alignment(p: ScanPass, b: NDArray[np.float64], field: Any,
                       pose: FieldPose) -> tuple[NDArray, NDArray, NDArray, float] | None:
    """Per capture of a pass: deviation (deg), camera offset (m), HUA normal directions; and the off-line max."""
    caps = [w for w in p.waypoints if w.capture and w.hua is not None]
    if not caps or len(p.waypoints) < 2:
        return None
    xy = np.array([(w.x_m, w.y_m) for w in p.waypoints])
    e = xy[-1] - xy[0]
    e = e / max(float(np.linalg.norm(e)), 1e-12)
    off_line = float(np.max(np.abs((xy - xy[0]) @ np.array([e[1], -e[0]]))))
    k = field.indices([w.hua for w in caps])
    bk = b[k]
    dev = np.degrees(np.arccos(np.clip(np.abs(bk @ e), 0.0, 1.0)))
    cam_xy = np.array([(w.x_m, w.y_m) for w in caps])
    offset = np.abs(dot(cam_xy - pose.mirror_centres[k, :2], np.stack([bk[:, 1], -bk[:, 0]], axis=1)))
    mean_b = bk.sum(axis=0)
    return dev, offset, mean_b if float(mean_b @ e) >= 0.0 else -mean_b, off_line


def pass_alignment(passes: Sequence[ScanPass], field: Any, pose: FieldPose) -> tuple[PassAlignment, ...]:
    """Alignment of each pass with its HUAs' normals' planes (passes with no capture are skipped).

    Parameters
    ----------
    passes : sequence of ScanPass
        Planned (or scored and shifted) passes.
    field : Field
        The field the names refer to.
    pose : FieldPose
        The tracked field the passes were planned for.

    Returns
    -------
    tuple of PassAlignment
    """
    b, _ = horizontal_normals(pose)
    out = []
    for p in passes:
        got = _capture_alignment(p, b, field, pose)
        if got is None:
            continue
        dev, offset, mean_b, off_line = got
        out.append(PassAlignment(
            index=int(p.index),
            plane_azimuth_deg=heading_0_360(np.degrees(np.arctan2(mean_b[0], mean_b[1]))),
            median_deviation_deg=float(np.median(dev)),
            max_deviation_deg=float(dev.max()),
            median_camera_offset_m=float(np.median(offset)),
            max_camera_offset_m=float(offset.max()),
            max_off_line_m=off_line,
        ))
    return tuple(out)


def alignment_summary(passes: Sequence[ScanPass], field: Any, pose: FieldPose) -> dict[str, float]:
    """Field-wide figures of :func:`pass_alignment`, over every capture (and every pass for the off-line max).

    Returns
    -------
    dict
        ``median_deviation_deg``, ``max_deviation_deg``,
        ``median_camera_offset_m``, ``max_camera_offset_m`` and
        ``max_off_line_m`` (NaN without captures).
    """
    b, _ = horizontal_normals(pose)
    got = [g for g in (_capture_alignment(p, b, field, pose) for p in passes) if g is not None]
    keys = ("median_deviation_deg", "max_deviation_deg", "median_camera_offset_m", "max_camera_offset_m",
            "max_off_line_m")
    if not got:
        return dict.fromkeys(keys, float("nan"))
    d = np.concatenate([g[0] for g in got])
    o = np.concatenate([g[1] for g in got])
    return dict(zip(keys, (float(np.median(d)), float(d.max()), float(np.median(o)), float(o.max()),
                           max(g[3] for g in got)), strict=True))
