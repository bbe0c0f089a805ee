"""UFACET-style scan passes for polarimetric drone inspection of a tracking heliostat field.

Method (UFACET, paper section 3 and Fig. 2a; Sandia's OpenCSP planner
``contrib/app/ufacet-s/flight_planner_ufacet`` [2]_, read for the method
only): a camera looks at a heliostat under assessment (HUA) from the point
where the HUA mirror shows the **back of a target heliostat** nearer the
tower. The target's back structure, reflected in the HUA facets, reveals the
facet canting. Because HUA and target both track, the camera, the HUA
centre and the target's mirror image lie in the vertical plane of the HUA's
tracking normal; the heliostats along such a plane form a line running
roughly radially from the tower, and one straight pass at constant altitude
images them one after the other.

What this module computes, for a field tracked at one instant
(:class:`pihim.field.kinematics.FieldPose`):

1. **Targets.** For each heliostat ``H`` the candidate targets are the
   heliostats ``T`` in front of its mirror (``u . n_H > 0`` with ``u`` the
   unit vector from the HUA mirror centre to the target mirror centre) that
   turn their back to it (``u . n_T > 0``), within
   :attr:`UfacetSettings.max_off_axis_deg` of the horizontal direction of
   ``n_H``, ``max_lateral_m`` of its vertical plane and
   :attr:`UfacetSettings.max_target_distance_m`; of candidates abreast
   (forward distances within ``abreast_m``) only the nearest is kept; then
   the nearest :attr:`UfacetSettings.max_targets` (3, OpenCSP's look-back)
   in order of distance.
2. **Lines.** Each heliostat points to its nearest target; where several
   heliostats point to the same one, the link that continues the target's
   own link most straightly is kept. The kept links form disjoint chains of
   heliostats, one scan pass each (no seed points, no manual section
   margins, every heliostat in exactly one chain); chains of at most
   ``merge_max_huas`` HUAs join a nearby parallel pass.
3. **Camera positions.** The camera ``C`` sees the target's mirror-centre
   reflected at the HUA mirror centre when ``C`` lies on the ray
   ``C = H + t w`` with ``w = 2 (u . n_H) n_H - u`` (the mirror image of
   ``u``; equivalently ``C`` is on the line through ``H`` and the target's
   mirror image ``T'`` = ``T`` reflected through the HUA mirror plane, on the
   side opposite ``T'``). At the pass altitude ``z``, ``t = (z - H_z) / w_z``.
   By construction the ray from ``C`` to ``H`` reflected about ``n_H``
   points exactly at ``T``.
4. **Gaze.** Heading and gimbal pitch point the optical axis at the HUA
   mirror centre (heading clockwise from North in [0, 360), pitch negative
   below the horizon). The fraction of the HUA's facet centres inside the
   camera field of view (:class:`pihim.camera.model.CameraModel`, default
   Triton + 35 mm: 13.8 x 11.5 deg) is reported. The camera has no roll.
5. **Visibility (not in OpenCSP).** The sight line camera -> HUA (centre
   and four corners) and the reflected ray HUA -> target are tested against
   the tower box and against the tracked mirror rectangles of every other
   heliostat (vectorised ray / rectangle intersection). Blocked pairs are
   reported per pass in :attr:`ScanPass.issues`; a pass with nothing
   imageable is marked ``feasible=False``.
6. **Altitude.** Minimum safe altitude = highest point of any tracked
   mirror + ``safety_margin_m`` (>= 5 m: the paper's field safety rule,
   section 2). Each pass is flown at the altitude, on a 1 m grid between
   that and ``max_altitude_m``, that images the most HUAs, then shows the
   most of their facet centres in the field of view, then is lowest. The
   gimbal pitch at a capture does not depend on the altitude (``C - H`` is
   parallel to ``w``); the range and the framing do.
7. **Flux (not in OpenCSP).** The sunlight the tracked heliostats
   concentrate toward the aim point is estimated along each pass
   (:func:`beam_concentration`); points above
   :attr:`UfacetSettings.flux_limit_suns` are reported (the paper lists
   the focusing region as a safety factor, section 3).
8. **Order.** Passes are sorted by their azimuth around the tower, starting
   after the largest empty sector, and flown boustrophedon: even passes
   travel away from the tower (along the mirrors' back direction), odd ones
   toward it, with ``lead_in_m`` before the first and ``run_past_m`` after
   the last capture.

Waypoints carry field ENU and exact WGS84 coordinates
(:func:`pihim.field.geodesy.enu_to_geodetic`).

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone" (pihim paper), sections 2-3 (UFACET pairs, 5 m clearance
   above the highest heliostat point, focusing point as a safety factor)
   and 4.4 (HUA 8E3 with target 7E3).
.. [2] Sandia National Laboratories, OpenCSP (Apache-2.0),
   https://github.com/sandialabs/OpenCSP,
   ``contrib/app/ufacet-s/flight_planner_ufacet/U_Code/lib/``
   (``plan_scan_ufacet_xy_analysis.py``, ``plan_scan_ufacet_section_*.py``,
   ``plan_scan_parameters.py``) and ``opencsp/common/lib/uas/ScanPass.py``:
   ideal-gaze curves along the tracking normals, sections, look-back of 3
   targets, lead-in 18 m and run-past 9 m, 5 m/s, boustrophedon order.
   See ``docs/opencsp-comparison.md``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from pihim.camera.model import CameraModel
from pihim.errors import PihimInputError
from pihim.field.geodesy import GeodeticOrigin, as_origin, enu_to_geodetic
from pihim.field.kinematics import FieldPose, track_field
from pihim.planning.model import ScanPass, Waypoint

__all__ = [
    "DEFAULT_CAMERA",
    "OPENCSP_LEAD_IN_M",
    "OPENCSP_RUN_PAST_M",
    "OPENCSP_SPEED_M_S",
    "PAPER_MIN_CLEARANCE_M",
    "UfacetPlan",
    "UfacetSettings",
    "beam_concentration",
    "first_mirror_hits",
    "gaze_angles",
    "home_waypoint",
    "minimum_safe_altitude",
    "optical_axis",
    "plan_passes",
    "plan_ufacet",
    "sun_from_pose",
    "track_at",
]

#: Lead-in before the first capture of a pass, metres (OpenCSP NSTTF value).
OPENCSP_LEAD_IN_M = 18.0
#: Run-past after the last capture of a pass, metres (OpenCSP NSTTF value).
OPENCSP_RUN_PAST_M = 9.0
#: Scan ground speed, m/s (OpenCSP NSTTF UFACET value).
OPENCSP_SPEED_M_S = 5.0
#: Minimum clearance above the highest heliostat point, metres (paper section 2).
PAPER_MIN_CLEARANCE_M = 5.0
#: The paper's camera: Lucid Triton TRI050S-PC with a 35 mm lens (13.8 x 11.5 deg).
DEFAULT_CAMERA = CameraModel()

_TOWER_HIT = -2  # blocker code for the tower in the hit arrays
_EPS_T = 1e-6


# --------------------------------------------------------------------------- settings and result


@dataclass(frozen=True)
class UfacetSettings:
    """Tuning of the UFACET geometry; the defaults suit NSTTF-like heliostats.

    Attributes
    ----------
    max_targets : int
        Targets looked for in front of each HUA (OpenCSP's look-back, 3).
    max_target_distance_m : float
        Horizontal search radius for targets, metres.
    max_off_axis_deg : float
        Largest horizontal angle between the HUA's normal and the direction
        to a target, degrees.
    max_lateral_m : float or None
        Largest horizontal distance of a target's mirror centre from the
        vertical plane of the HUA's normal, metres. Default: the mirror
        width (a target farther aside shifts the camera off the pass line by
        about as much).
    merge_max_huas : int
        Lines of at most this many HUAs join a nearby parallel pass (0: never).
    merge_lateral_m : float or None
        Largest lateral distance of a merged line's camera points from the
        host pass's line, metres. Default: 1.5 mirror widths.
    abreast_m : float or None
        Candidates whose forward distances differ by less than this are
        abreast (the same row); only the nearest is kept. Default: 1.5
        mirror heights (9.1 m for NSTTF heliostats, close to OpenCSP's 9 m
        ``discard_threshold_p``).
    altitude_step_m : float
        Altitude grid of the per-pass altitude search, metres.
    max_range_m : float
        Largest camera-to-HUA distance accepted, metres.
    min_reflection_elevation_deg : float
        Smallest elevation of the camera direction ``w`` seen from the HUA;
        below it the camera would be far and low.
    gimbal_pitch_min_deg, gimbal_pitch_max_deg : float
        Gimbal pitch range, degrees (DJI-style -90..+30).
    corner_inset : float
        Sight lines to HUA corners aim this fraction of the half-size inside
        the rectangle (they must not graze the HUA's own edge).
    tower_clearance_m : float
        Keep-out around the tower box for camera positions, metres.
    flux_check : bool
        Estimate concentrated sunlight along the passes.
    flux_limit_suns : float
        Report pass points where the estimate exceeds this, suns.
    beam_divergence_mrad : float
        Half-angle of a reflected beam at its focus (sun 4.65 mrad plus
        mirror errors), mrad.
    flux_sample_m : float
        Spacing of the flux samples along a pass, metres.
    """

    max_targets: int = 3
    max_target_distance_m: float = 50.0
    max_off_axis_deg: float = 20.0
    max_lateral_m: float | None = None
    merge_max_huas: int = 2
    merge_lateral_m: float | None = None
    abreast_m: float | None = None
    altitude_step_m: float = 1.0
    max_range_m: float = 60.0
    min_reflection_elevation_deg: float = 5.0
    gimbal_pitch_min_deg: float = -90.0
    gimbal_pitch_max_deg: float = 30.0
    corner_inset: float = 0.05
    tower_clearance_m: float = 5.0
    flux_check: bool = True
    flux_limit_suns: float = 3.0
    beam_divergence_mrad: float = 7.0
    flux_sample_m: float = 2.0

    def __post_init__(self) -> None:
        if isinstance(self.max_targets, bool) or not isinstance(self.max_targets, int) or self.max_targets < 1:
            raise PihimInputError(f"max_targets must be a positive integer, got {self.max_targets!r}")
        positive = ("max_target_distance_m", "altitude_step_m", "max_range_m", "flux_limit_suns",
                    "beam_divergence_mrad", "flux_sample_m")
        for label in positive:
            v = getattr(self, label)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise PihimInputError(f"UfacetSettings.{label} must be a positive number, got {v!r}")
        if not 0 < self.max_off_axis_deg < 90:
            raise PihimInputError(f"max_off_axis_deg must be in (0, 90), got {self.max_off_axis_deg!r}")
        if isinstance(self.merge_max_huas, bool) or not isinstance(self.merge_max_huas, int) \
                or self.merge_max_huas < 0:
            raise PihimInputError(f"merge_max_huas must be an integer >= 0, got {self.merge_max_huas!r}")
        for label in ("abreast_m", "max_lateral_m", "merge_lateral_m"):
            v = getattr(self, label)
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise PihimInputError(f"UfacetSettings.{label} must be None or a number >= 0, got {v!r}")
        if not -90.0 <= self.gimbal_pitch_min_deg < self.gimbal_pitch_max_deg <= 90.0:
            raise PihimInputError("gimbal pitch limits must satisfy -90 <= min < max <= 90 deg")
        if not 0 <= self.corner_inset < 1 or self.tower_clearance_m < 0:
            raise PihimInputError("corner_inset must be in [0, 1) and tower_clearance_m >= 0")


@dataclass(frozen=True)
class UfacetPlan:
    """Scan passes and what the planner learnt on the way.

    Attributes
    ----------
    passes : tuple of ScanPass
        Boustrophedon order; waypoints with ENU and WGS84 filled.
    min_altitude_m, max_altitude_m : float
        Altitude limits used, metres above the field origin.
    highest_mirror_point_m : float
        Highest point of any tracked mirror, metres.
    sun_vector : ndarray, shape (3,)
        Sun direction implied by the pose and the aim point (ENU).
    assessed : tuple of str
        HUAs imaged with at least one target.
    unassessed : tuple of (str, str)
        Requested heliostats not imaged, with the reason.
    """

    passes: tuple[ScanPass, ...]
    min_altitude_m: float
    max_altitude_m: float
    highest_mirror_point_m: float
    sun_vector: NDArray[np.float64]
    assessed: tuple[str, ...]
    unassessed: tuple[tuple[str, str], ...]

    @property
    def n_captures(self) -> int:
        """Capturing waypoints over all passes."""
        return sum(w.capture for p in self.passes for w in p.waypoints)


# --------------------------------------------------------------------------- small geometry helpers


def _unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _dot(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.einsum("...i,...i->...", a, b)


def _azimuth_deg(dx: ArrayLike, dy: ArrayLike) -> NDArray[np.float64]:
    """Azimuth clockwise from North in [0, 360)."""
    a = np.mod(np.degrees(np.arctan2(dx, dy)), 360.0)
    return np.where(a >= 360.0, 0.0, a)


def gaze_angles(camera_enu: ArrayLike, look_at_enu: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Heading and gimbal pitch pointing the optical axis from ``camera_enu`` at ``look_at_enu``.

    Parameters
    ----------
    camera_enu, look_at_enu : array_like, shape (..., 3)
        ENU metres.

    Returns
    -------
    heading_deg : ndarray
        Clockwise from North, [0, 360). For a point straight below it is 0.
    pitch_deg : ndarray
        Above the horizon positive, [-90, 90] (-90 = straight down).
    """
    d = np.asarray(look_at_enu, float) - np.asarray(camera_enu, float)
    horiz = np.hypot(d[..., 0], d[..., 1])
    return _azimuth_deg(d[..., 0], d[..., 1]), np.degrees(np.arctan2(d[..., 2], horiz))


def optical_axis(heading_deg: ArrayLike, pitch_deg: ArrayLike) -> NDArray[np.float64]:
    """Unit ENU optical axis for a heading (clockwise from North) and a pitch (negative down), degrees."""
    h = np.radians(np.asarray(heading_deg, float))
    p = np.radians(np.asarray(pitch_deg, float))
    h, p = np.broadcast_arrays(h, p)
    return np.stack([np.cos(p) * np.sin(h), np.cos(p) * np.cos(h), np.sin(p)], axis=-1)


def _camera_frame(heading_deg: NDArray[np.float64], pitch_deg: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
    """OpenCV camera axes in ENU (x right, y down, z forward) for zero roll."""
    f = optical_axis(heading_deg, pitch_deg)
    h = np.radians(heading_deg)
    r = np.stack([np.cos(h), -np.sin(h), np.zeros_like(h)], axis=-1)
    return r, np.cross(f, r), f


def _in_fov(points: NDArray[np.float64], cam: NDArray[np.float64], heading: NDArray[np.float64],
            pitch: NDArray[np.float64], camera: CameraModel) -> NDArray[np.bool_]:
    """Whether ``points`` (..., K, 3) fall in the camera's field of view; cam/heading/pitch shape (...)."""
    r, dn, f = _camera_frame(heading, pitch)
    v = points - cam[..., None, :]
    zc = _dot(v, f[..., None, :])
    tx = 0.5 * camera.width_px / camera.focal_length_px
    ty = 0.5 * camera.height_px / camera.focal_length_px
    with np.errstate(divide="ignore", invalid="ignore"):
        return (zc > 0) & (np.abs(_dot(v, r[..., None, :])) <= tx * zc) & (np.abs(_dot(v, dn[..., None, :])) <= ty * zc)


# --------------------------------------------------------------------------- public helpers


def minimum_safe_altitude(pose: FieldPose, safety_margin_m: float = PAPER_MIN_CLEARANCE_M) -> tuple[float, float]:
    """Minimum safe flight altitude over a tracked field, metres above the field origin.

    Parameters
    ----------
    pose : FieldPose
        The tracked field.
    safety_margin_m : float
        Clearance above the highest mirror point, metres; at least
        :data:`PAPER_MIN_CLEARANCE_M` (5 m, the paper's field safety rule,
        section 2).

    Returns
    -------
    min_altitude_m : float
        ``highest + safety_margin_m``.
    highest_m : float
        Highest corner of any tracked mirror rectangle (flat outline; design
        canting moves facet corners by less than a centimetre).

    Raises
    ------
    PihimInputError
        If the margin is below 5 m or not finite.
    """
    if not (isinstance(safety_margin_m, (int, float)) and math.isfinite(safety_margin_m)) \
            or safety_margin_m < PAPER_MIN_CLEARANCE_M:
        raise PihimInputError(
            f"safety_margin_m must be at least {PAPER_MIN_CLEARANCE_M:g} m above the highest heliostat point "
            f"(paper section 2), got {safety_margin_m!r}"
        )
    highest = float(np.max(pose.mirror_outline()[..., 2]))
    return highest + float(safety_margin_m), highest


def sun_from_pose(pose: FieldPose, aim_point: ArrayLike, *, tol_mrad: float = 0.1) -> NDArray[np.float64]:
    """The sun direction a tracked field implies for an aim point (law of reflection, inverted).

    Each heliostat reflects the sun ``s`` onto the aim point: ``s = 2 (n . t)
    n - t`` with ``t`` the unit vector from its mirror centre to the aim
    point.

    Raises
    ------
    PihimInputError
        If the heliostats disagree by more than ``tol_mrad`` (the pose was
        tracked toward another aim point).
    """
    a = np.asarray(aim_point, float)
    t = _unit(a - pose.mirror_centres)
    n = pose.normals
    s = 2.0 * _dot(n, t)[:, None] * n - t
    mean = _unit(s.mean(axis=0))
    spread = float(np.max(np.linalg.norm(s - mean, axis=1))) if len(s) else 0.0
    if spread > tol_mrad * 1e-3:
        raise PihimInputError(
            f"the pose does not track toward aim point {tuple(np.round(a, 3).tolist())} (implied sun directions "
            f"differ by up to {spread * 1e3:.1f} mrad); track the field with the same aim point"
        )
    return mean


def track_at(field: Any, time: Any, *, aim_point: ArrayLike, site: Any = None) -> tuple[Any, FieldPose]:
    """Sun position and tracked field for one timezone-aware time.

    Parameters
    ----------
    field : Field
        Heliostat field.
    time : str or datetime
        ISO 8601 with a UTC offset (e.g. ``"2021-05-13T13:00:00-06:00"``).
    aim_point : array_like, shape (3,)
        Where the field reflects the sun, ENU metres.
    site : Site or str, optional
        Default :data:`pihim.sky.sun.NSTTF`.

    Returns
    -------
    sun : SunPosition
    pose : FieldPose

    Raises
    ------
    PihimInputError
        Naive time, sun below the horizon, aim point at or below the ground.
    """
    from pihim.sky.sun import NSTTF, parse_time, sun_position

    ts = parse_time(time)
    aim = _check_aim(aim_point)
    sun = sun_position(NSTTF if site is None else site, ts)
    if sun.elevation_deg <= 0.0:
        raise PihimInputError(
            f"the sun is below the horizon at {ts.isoformat()} (elevation {sun.elevation_deg:.2f} deg); "
            "UFACET planning needs the field tracking the sun"
        )
    return sun, track_field(field, sun.vector, aim)


def _check_aim(aim_point: ArrayLike) -> NDArray[np.float64]:
    a = np.asarray(aim_point, dtype=float)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise PihimInputError(f"aim_point must be three finite ENU coordinates, got {aim_point!r}")
    if a[2] <= 0.0:
        raise PihimInputError(f"aim point {tuple(a.tolist())} is inside the ground (z = {a[2]:g} m <= 0)")
    return a


def _tower_box(tower: Any, clearance: float = 0.0) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    if tower is None:
        return None
    c = np.asarray(tower.box_corners(), float)
    return c.min(axis=0) - [clearance, clearance, 0.0], c.max(axis=0) + clearance


def _segments_hit_box(p0: NDArray[np.float64], p1: NDArray[np.float64], lo: NDArray[np.float64],
                      hi: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Segments p0->p1 (N, 3) crossing the axis-aligned box [lo, hi] (slab method)."""
    d = p1 - p0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - p0) * inv
        t2 = (hi - p0) * inv
    tmin = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
    tmax = np.where(np.isnan(t2), np.inf, np.maximum(t1, t2))
    # parallel components: inside the slab or not
    par = d == 0
    inside_slab = (p0 >= lo) & (p0 <= hi)
    tmin = np.where(par, np.where(inside_slab, -np.inf, np.inf), tmin)
    tmax = np.where(par, np.where(inside_slab, np.inf, -np.inf), tmax)
    enter = tmin.max(axis=1)
    leave = tmax.min(axis=1)
    return (enter <= leave) & (leave >= 0.0) & (enter <= 1.0)


class _Mirrors:
    """Tracked mirror rectangles of a field with a spatial index (internal)."""

    def __init__(self, pose: FieldPose) -> None:
        spec = pose.field.spec  # type: ignore[attr-defined]
        self.centres = np.ascontiguousarray(pose.mirror_centres, dtype=float)
        self.x = np.ascontiguousarray(pose.rotations[:, :, 0])
        self.y = np.ascontiguousarray(pose.rotations[:, :, 1])
        self.n = np.ascontiguousarray(pose.normals)
        self.hw = float(spec.mirror_half_width_m)
        self.hh = float(spec.mirror_half_height_m)
        self.radius = math.hypot(self.hw, self.hh)
        self.tree = cKDTree(self.centres)

    def first_hits(self, p0: NDArray[np.float64], p1: NDArray[np.float64], exclude: NDArray[np.int64],
                   chunk: int = 50_000) -> NDArray[np.int64]:
        """Index of the first mirror each segment p0->p1 crosses (-1 for none), skipping ``exclude`` (N, E)."""
        n = len(p0)
        out = np.full(n, -1, dtype=np.int64)
        for a in range(0, n, chunk):
            b = min(n, a + chunk)
            out[a:b] = self._first_hits(p0[a:b], p1[a:b], exclude[a:b])
        return out

    def _first_hits(self, p0: NDArray[np.float64], p1: NDArray[np.float64],
                    exclude: NDArray[np.int64]) -> NDArray[np.int64]:
        n = len(p0)
        out = np.full(n, -1, dtype=np.int64)
        if n == 0:
            return out
        mid = 0.5 * (p0 + p1)
        r = 0.5 * np.linalg.norm(p1 - p0, axis=1) + self.radius
        lists = self.tree.query_ball_point(mid, r, return_sorted=False)
        lens = np.fromiter((len(x) for x in lists), dtype=np.int64, count=n)
        if lens.sum() == 0:
            return out
        ray = np.repeat(np.arange(n), lens)
        rect = np.fromiter((k for x in lists for k in x), dtype=np.int64, count=int(lens.sum()))
        keep = np.all(rect[:, None] != exclude[ray], axis=1)
        ray, rect = ray[keep], rect[keep]
        d = p1[ray] - p0[ray]
        nn = self.n[rect]
        denom = _dot(d, nn)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = _dot(self.centres[rect] - p0[ray], nn) / denom
        ok = np.isfinite(t) & (t > _EPS_T) & (t < 1.0 - _EPS_T)
        ray, rect, t, d = ray[ok], rect[ok], t[ok], d[ok]
        q = p0[ray] + t[:, None] * d - self.centres[rect]
        inside = (np.abs(_dot(q, self.x[rect])) <= self.hw) & (np.abs(_dot(q, self.y[rect])) <= self.hh)
        ray, rect, t = ray[inside], rect[inside], t[inside]
        if len(ray):
            order = np.lexsort((t, ray))
            ray, rect = ray[order], rect[order]
            first = np.r_[True, ray[1:] != ray[:-1]]
            out[ray[first]] = rect[first]
        return out


def first_mirror_hits(pose: FieldPose, p0: ArrayLike, p1: ArrayLike, *,
                      exclude: ArrayLike | None = None) -> NDArray[np.int64]:
    """First tracked mirror rectangle crossed by each segment ``p0 -> p1``, vectorised.

    Parameters
    ----------
    pose : FieldPose
        Tracked field; mirrors are its flat outlines (``mirror_half_width_m``
        x ``mirror_half_height_m`` around each mirror centre, in the mirror
        plane).
    p0, p1 : array_like, shape (N, 3)
        Segment ends, ENU metres.
    exclude : array_like of int, shape (N,) or (N, E), optional
        Heliostat indices ignored per segment (e.g. the HUA and the target);
        -1 entries ignore nothing.

    Returns
    -------
    ndarray of int, shape (N,)
        Index of the first heliostat hit along the segment, -1 if none.
    """
    a = np.atleast_2d(np.asarray(p0, float))
    b = np.atleast_2d(np.asarray(p1, float))
    if a.shape != b.shape or a.shape[-1] != 3:
        raise PihimInputError(f"p0 and p1 must both be (N, 3), got {a.shape} and {b.shape}")
    ex = np.full((len(a), 1), -1, dtype=np.int64) if exclude is None else np.asarray(exclude, dtype=np.int64)
    if ex.ndim == 1:
        ex = ex[:, None]
    return _Mirrors(pose).first_hits(a, b, ex)


def beam_concentration(points: ArrayLike, pose: FieldPose, aim_point: ArrayLike, *,
                       divergence_mrad: float = 7.0) -> NDArray[np.float64]:
    """Rough concentration of reflected sunlight at points, in suns.

    Each tracked heliostat sends a beam from its mirror centre to the aim
    point. Modelled as a cone of circular cross-section, its radius shrinks
    linearly from ``r0 = sqrt(A / pi)`` (``A`` the mirror area) at the mirror
    to ``L * divergence`` at the aim point (``L`` the slant range; the
    design canting focuses it there); beyond the focus it is ignored (the
    flights stay below the aim points of interest). A beam contributes
    ``(r0 / r)^2`` suns inside its cone. Cosine losses, shading, blocking and
    astigmatism are ignored: this flags the focusing region (paper section
    3 lists it as a flight safety factor); it is not a flux map.

    Parameters
    ----------
    points : array_like, shape (M, 3)
        ENU metres.
    pose : FieldPose
        Tracked field.
    aim_point : array_like, shape (3,)
        Aim point of the tracking, ENU metres.
    divergence_mrad : float
        Beam half-angle at the focus, mrad.

    Returns
    -------
    ndarray, shape (M,)
        Suns (1 is direct sunlight; 0 outside every beam).
    """
    pts = np.atleast_2d(np.asarray(points, float))
    a = np.asarray(aim_point, float)
    spec = pose.field.spec  # type: ignore[attr-defined]
    r0 = math.sqrt(4.0 * spec.mirror_half_width_m * spec.mirror_half_height_m / math.pi)
    theta = divergence_mrad * 1e-3
    c = pose.mirror_centres
    axis = a - c
    length = np.linalg.norm(axis, axis=1)
    dirs = -axis / length[:, None]  # unit vectors from the aim point toward the mirrors
    tree = cKDTree(dirs)
    out = np.zeros(len(pts))
    rmax = max(r0, float(length.max()) * theta)  # no beam is wider between its mirror and its focus
    for s0 in range(0, len(pts), 20_000):
        p = pts[s0:s0 + 20_000]
        v = p - a
        dist = np.linalg.norm(v, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            q = v / dist[:, None]
            half = np.where(dist > rmax, np.arcsin(np.minimum(1.0, rmax / dist)), np.pi)
        q = np.where(np.isfinite(q), q, 0.0)
        lists = tree.query_ball_point(q, np.minimum(2.0, 2.0 * np.sin(np.minimum(half, np.pi / 2)) + 1e-12),
                                      return_sorted=False)
        lens = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(p))
        if lens.sum() == 0:
            continue
        pi = np.repeat(np.arange(len(p)), lens)
        hi = np.fromiter((k for x in lists for k in x), dtype=np.int64, count=int(lens.sum()))
        w = p[pi] - c[hi]
        e = axis[hi] / length[hi, None]
        along = _dot(w, e)
        f = along / length[hi]
        perp = np.linalg.norm(w - along[:, None] * e, axis=1)
        radius = (1.0 - f) * r0 + f * length[hi] * theta
        inside = (f > 0) & (f <= 1.0) & (perp <= radius)
        np.add.at(out, s0 + pi[inside], (r0 / np.maximum(radius[inside], 1e-9)) ** 2)
    return out


def home_waypoint(field: Any, *, origin: GeodeticOrigin | Any, point: ArrayLike | None = None,
                  south_of_tower_m: float = 30.0, heading_deg: float = 0.0) -> Waypoint:
    """Take-off and landing point, on the ground.

    Parameters
    ----------
    field : Field
        The field (its tower places the default point).
    origin : GeodeticOrigin or Site
        Field origin on WGS84 (ellipsoidal height).
    point : array_like, shape (2,) or (3,), optional
        ENU metres; a 2-vector is put on the ground (z = 0). Default:
        ``south_of_tower_m`` South of the tower's southern face on its
        centre line (without a tower: South of the southernmost heliostat).
    south_of_tower_m : float
        Distance for the default point, metres.
    heading_deg : float
        Drone heading on the ground, degrees clockwise from North.

    Returns
    -------
    Waypoint
        ``kind="takeoff"``, no capture.
    """
    if point is None:
        tower = getattr(field, "tower", None)
        if tower is not None:
            xyz = np.array([0.5 * (tower.x_min_m + tower.x_max_m), tower.y_min_m - south_of_tower_m, 0.0])
        else:
            p = np.asarray(field.pivots)
            xyz = np.array([float(np.median(p[:, 0])), float(p[:, 1].min()) - south_of_tower_m, 0.0])
    else:
        v = np.asarray(point, float)
        if v.shape not in ((2,), (3,)) or not np.all(np.isfinite(v)):
            raise PihimInputError(f"home point must be 2 or 3 finite ENU coordinates, got {point!r}")
        xyz = np.r_[v, 0.0] if v.shape == (2,) else v
    lat, lon, h = enu_to_geodetic(xyz, as_origin(origin))
    return Waypoint(float(xyz[0]), float(xyz[1]), float(xyz[2]), float(lat), float(lon), float(h),
                    float(heading_deg) % 360.0, 0.0, 0.0, kind="takeoff", capture=False, hua=None)


# --------------------------------------------------------------------------- the planner


@dataclass
class _Pairs:
    """Candidate HUA/target pairs (internal, arrays of length P)."""

    hua: NDArray[np.int64]
    tgt: NDArray[np.int64]
    rank: NDArray[np.int64]


def _candidate_targets(pose: FieldPose, st: UfacetSettings, abreast_m: float,
                       max_lateral_m: float) -> tuple[_Pairs, NDArray[np.float64]]:
    """Up to ``max_targets`` targets per heliostat, nearest first; and the horizontal normal directions."""
    c = pose.mirror_centres
    n = pose.normals
    nb = np.hypot(n[:, 0], n[:, 1])
    b = np.where(nb[:, None] > 1e-9, n[:, :2] / np.maximum(nb, 1e-12)[:, None], 0.0)
    tree = cKDTree(c[:, :2])
    pr = tree.query_pairs(st.max_target_distance_m, output_type="ndarray")
    if len(pr) == 0:
        e = np.zeros(0, dtype=np.int64)
        return _Pairs(e, e, e), b
    i = np.concatenate([pr[:, 0], pr[:, 1]])
    j = np.concatenate([pr[:, 1], pr[:, 0]])
    dxy = c[j, :2] - c[i, :2]
    s = _dot(dxy, b[i])
    lat = dxy[:, 0] * b[i, 1] - dxy[:, 1] * b[i, 0]
    u = _unit(c[j] - c[i])
    off = np.degrees(np.arctan2(np.abs(lat), s))
    ok = (s > 0) & (off <= st.max_off_axis_deg) & (_dot(u, n[i]) > 0) & (_dot(u, n[j]) > 0) & (nb[i] > 1e-9)
    ok &= np.abs(lat) <= max_lateral_m
    i, j, s, lat = i[ok], j[ok], s[ok], np.abs(lat[ok])
    # abreast rejection: within each HUA, walk candidates nearest first (then nearest the normal's vertical
    # plane); drop those abreast of a kept one
    order = np.lexsort((lat, s, i))
    i, j, s = i[order], j[order], s[order]
    starts = np.r_[0, np.flatnonzero(np.diff(i)) + 1, len(i)]
    keep = np.zeros(len(i), dtype=bool)
    for a, z in itertools.pairwise(starts):
        kept: list[float] = []
        for k in range(a, z):
            if all(abs(s[k] - q) >= abreast_m for q in kept):
                kept.append(s[k])
                keep[k] = True
    i, j, s = i[keep], j[keep], s[keep]
    order = np.lexsort((s, i))
    i, j = i[order], j[order]
    first = np.r_[0, np.flatnonzero(np.diff(i)) + 1]
    rank = np.arange(len(i)) - np.repeat(first, np.diff(np.r_[first, len(i)]))
    sel = rank < st.max_targets
    return _Pairs(i[sel].astype(np.int64), j[sel].astype(np.int64), rank[sel].astype(np.int64)), b


def _chains(n_helio: int, pairs: _Pairs, centres: NDArray[np.float64]) -> NDArray[np.int64]:
    """Chain id of every heliostat; the links are each heliostat's nearest target, straightest kept."""
    nxt = np.full(n_helio, -1, dtype=np.int64)
    r0 = pairs.rank == 0
    nxt[pairs.hua[r0]] = pairs.tgt[r0]
    src = np.flatnonzero(nxt >= 0)
    dst = nxt[src]
    # straightness: angle between the link src->dst and dst's own link (dst->nxt[dst]); no onward link: 0
    v1 = _unit(centres[dst, :2] - centres[src, :2])
    onward = nxt[dst]
    has = onward >= 0
    v2 = np.zeros_like(v1)
    v2[has] = _unit(centres[onward[has], :2] - centres[dst[has], :2])
    bend = np.where(has, 1.0 - _dot(v1, v2), 0.0)
    length = np.linalg.norm(centres[dst, :2] - centres[src, :2], axis=1)
    order = np.lexsort((length, bend, dst))
    src, dst = src[order], dst[order]
    first = np.r_[True, dst[1:] != dst[:-1]] if len(dst) else np.zeros(0, bool)
    pred = np.full(n_helio, -1, dtype=np.int64)
    pred[dst[first]] = src[first]
    succ = np.full(n_helio, -1, dtype=np.int64)
    succ[pred[pred >= 0]] = np.flatnonzero(pred >= 0)
    chain = np.full(n_helio, -1, dtype=np.int64)
    cid = 0
    for start in np.flatnonzero(succ < 0):  # innermost node of every chain
        k = int(start)
        while k >= 0 and chain[k] < 0:
            chain[k] = cid
            k = int(pred[k])
        cid += 1
    # cycles cannot occur (links go strictly forward along each normal) but be safe
    rest = np.flatnonzero(chain < 0)
    chain[rest] = cid + np.arange(len(rest))
    return chain


def _merge_fragments(chain: NDArray[np.int64], hua: NDArray[np.int64], rank: NDArray[np.int64],
                     cam_xy: NDArray[np.float64], back: NDArray[np.float64], st: UfacetSettings,
                     mirror_width_m: float) -> NDArray[np.int64]:
    """Group id per chain id: chains of at most ``merge_max_huas`` HUAs join a nearby, parallel, longer line.

    A short chain (typically a leftover where two lines compete for the same
    target) joins the longer pass whose straight line (least squares through
    its nearest-target camera points) passes within ``merge_lateral_m`` of
    all its camera points, within ``max_target_distance_m`` of that pass's
    ends and with mirrors facing within 20 deg of the same way. A separate
    pass would cost a lead-in, a run-past and a transit; the merged pass
    bends by at most the lateral limit.
    """
    n_chain = int(chain.max()) + 1 if len(chain) else 0
    group = np.arange(n_chain)
    if st.merge_max_huas <= 0 or len(hua) == 0:
        return group
    lateral = 1.5 * mirror_width_m if st.merge_lateral_m is None else st.merge_lateral_m
    r0 = rank == 0
    h0 = hua[r0]
    ch0 = chain[h0]
    xy0 = cam_xy[r0]
    ok = np.all(np.isfinite(xy0), axis=1)
    h0, ch0, xy0 = h0[ok], ch0[ok], xy0[ok]
    size = np.bincount(ch0, minlength=n_chain)
    small = np.flatnonzero((size > 0) & (size <= st.merge_max_huas))
    big = size > st.merge_max_huas
    if len(small) == 0 or not np.any(big):
        return group
    # least-squares line of every long chain: centroid, direction (principal axis), extent along it
    order = np.argsort(ch0, kind="stable")
    h0, ch0, xy0 = h0[order], ch0[order], xy0[order]
    starts = np.r_[0, np.flatnonzero(np.diff(ch0)) + 1, len(ch0)]
    lines: dict[int, tuple[NDArray, NDArray, float, float, NDArray]] = {}
    members: dict[int, NDArray] = {}
    for a, z in itertools.pairwise(starts):
        k = int(ch0[a])
        members[k] = np.arange(a, z)
        if not big[k]:
            continue
        p = xy0[a:z]
        m = p.mean(axis=0)
        _, _, vt = np.linalg.svd(p - m, full_matrices=False)
        d = vt[0]
        t = (p - m) @ d
        facing = back[h0[a:z]].sum(axis=0)
        lines[k] = (m, d, float(t.min()), float(t.max()), facing / max(np.linalg.norm(facing), 1e-12))
    tree = cKDTree(xy0)
    cos_lim = math.cos(math.radians(20.0))
    for k in small.tolist():
        idx = members[int(k)]
        p = xy0[idx]
        facing = back[h0[idx]].sum(axis=0)
        facing = facing / max(np.linalg.norm(facing), 1e-12)
        near = tree.query_ball_point(p, lateral + st.max_target_distance_m)
        hosts = {int(ch0[q]) for lst in near for q in lst} & set(lines)
        best, best_lat = -1, math.inf
        for g in hosts:
            m, d, t0, t1, f = lines[g]
            if float(facing @ f) < cos_lim:
                continue
            q = p - m
            t = q @ d
            lat = float(np.max(np.abs(q[:, 0] * d[1] - q[:, 1] * d[0])))
            if lat <= lateral and t.min() >= t0 - st.max_target_distance_m \
                    and t.max() <= t1 + st.max_target_distance_m and lat < best_lat:
                best, best_lat = g, lat
        if best >= 0:
            group[k] = group[best]
    return group


def _altitude_grid(lo: float, hi: float, step: float) -> NDArray[np.float64]:
    z = np.arange(lo, hi + 1e-9, step)
    if len(z) == 0 or z[-1] < hi - 1e-9:
        z = np.r_[z, hi]
    return z


def plan_ufacet(
    field: Any,
    pose: FieldPose,
    *,
    aim_point: ArrayLike,
    origin: GeodeticOrigin | Any,
    camera: CameraModel = DEFAULT_CAMERA,
    max_altitude_m: float = 25.0,
    safety_margin_m: float = PAPER_MIN_CLEARANCE_M,
    lead_in_m: float = OPENCSP_LEAD_IN_M,
    run_past_m: float = OPENCSP_RUN_PAST_M,
    speed_m_s: float = OPENCSP_SPEED_M_S,
    heliostats: Iterable[str] | None = None,
    settings: UfacetSettings = UfacetSettings(),
) -> UfacetPlan:
    """UFACET scan passes for a tracked field, with diagnostics. See :func:`plan_passes`."""
    # ---------------------------------------------------------------- inputs
    if len(pose.normals) != len(field.names):
        raise PihimInputError(
            f"pose has {len(pose.normals)} heliostats but the field {len(field.names)}: track this field"
        )
    aim = _check_aim(aim_point)
    org = as_origin(origin)
    for label, v, strict in (("max_altitude_m", max_altitude_m, True), ("lead_in_m", lead_in_m, False),
                             ("run_past_m", run_past_m, False), ("speed_m_s", speed_m_s, True)):
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v)) \
                or (v <= 0 if strict else v < 0):
            raise PihimInputError(f"{label} must be a finite number {'>' if strict else '>='} 0, got {v!r}")
    if not isinstance(camera, CameraModel):
        raise PihimInputError(f"camera must be a CameraModel, got {type(camera).__name__}")
    sun = sun_from_pose(pose, aim)
    if sun[2] <= 0.0:
        elev = math.degrees(math.asin(max(-1.0, min(1.0, float(sun[2])))))
        raise PihimInputError(
            f"the sun is below the horizon (elevation {elev:.2f} deg implied by the pose); UFACET needs daylight"
        )
    min_alt, highest = minimum_safe_altitude(pose, safety_margin_m)
    if min_alt > max_altitude_m:
        raise PihimInputError(
            f"no feasible pass: minimum safe altitude {min_alt:.2f} m (highest mirror point {highest:.2f} m + "
            f"{safety_margin_m:g} m) exceeds the maximum altitude {max_altitude_m:g} m"
        )
    n_h = len(field.names)
    names = field.names
    if heliostats is None:
        wanted = np.ones(n_h, dtype=bool)
    else:
        req = list(heliostats)
        if not req:
            raise PihimInputError("heliostats is empty: give at least one heliostat name (or None for all)")
        wanted = np.zeros(n_h, dtype=bool)
        wanted[field.indices(req)] = True
    spec = field.spec
    abreast = 1.5 * spec.mirror_height_m if settings.abreast_m is None else settings.abreast_m
    mirrors = _Mirrors(pose)
    tower_box = _tower_box(getattr(field, "tower", None))
    keepout = _tower_box(getattr(field, "tower", None), settings.tower_clearance_m)

    # ---------------------------------------------------------------- targets and lines
    lateral = spec.mirror_width_m if settings.max_lateral_m is None else settings.max_lateral_m
    cand, b = _candidate_targets(pose, settings, abreast, lateral)
    chain = _chains(n_h, cand, pose.mirror_centres)
    sel = wanted[cand.hua]
    pairs = _Pairs(cand.hua[sel], cand.tgt[sel], cand.rank[sel])
    has_cand = np.zeros(n_h, dtype=bool)
    has_cand[cand.hua] = True

    c = pose.mirror_centres
    n = pose.normals
    hu, tg = pairs.hua, pairs.tgt
    u = _unit(c[tg] - c[hu])
    w = 2.0 * _dot(u, n[hu])[:, None] * n[hu] - u
    w_elev = np.degrees(np.arcsin(np.clip(w[:, 2], -1.0, 1.0)))
    steep_ok = w_elev >= settings.min_reflection_elevation_deg

    # reflected ray HUA -> target
    refl_hit = mirrors.first_hits(c[hu] + 1e-6 * u, c[tg], np.stack([hu, tg], axis=1))
    if tower_box is not None:
        refl_hit = np.where((refl_hit < 0) & _segments_hit_box(c[hu], c[tg], *tower_box), _TOWER_HIT, refl_hit)
    refl_ok = refl_hit == -1

    # ---------------------------------------------------------------- camera positions on the altitude grid
    zs = _altitude_grid(min_alt, max_altitude_m, settings.altitude_step_m)
    nz = len(zs)
    with np.errstate(divide="ignore", invalid="ignore"):
        rng = (zs[None, :] - c[hu, 2][:, None]) / w[:, 2][:, None]  # (P, Z) range t = |C - H|
    cam = c[hu][:, None, :] + rng[..., None] * w[:, None, :]
    head, pitch = gaze_angles(cam, c[hu][:, None, :])
    geo_ok = (steep_ok[:, None] & (rng > 0) & (rng <= settings.max_range_m)
              & (pitch >= settings.gimbal_pitch_min_deg - 1e-9) & (pitch <= settings.gimbal_pitch_max_deg + 1e-9))
    if keepout is not None:
        lo, hi = keepout
        in_tower = np.all((cam >= lo) & (cam <= hi), axis=-1)
        geo_ok &= ~in_tower
    test = refl_ok[:, None] & geo_ok
    cam_hit = np.full((len(hu), nz), -1, dtype=np.int64)
    pi_, zi_ = np.nonzero(test)
    if len(pi_):
        p0 = cam[pi_, zi_]
        p1 = c[hu[pi_]] + 1e-6 * w[pi_]
        hits = mirrors.first_hits(p0, p1, hu[pi_, None])
        if tower_box is not None:
            hits = np.where((hits < 0) & _segments_hit_box(p0, p1, *tower_box), _TOWER_HIT, hits)
        cam_hit[pi_, zi_] = hits
    imageable = test & (cam_hit == -1)

    # facet centres in the field of view when the HUA is centred (only where the pair is imageable somewhere)
    fc = pose.facet_centres
    n_facets = fc.shape[1]
    in_view = np.zeros((len(hu), nz), dtype=np.int64)
    rows = np.flatnonzero(imageable.any(axis=1))
    step = max(1, 400_000 // max(1, nz * n_facets))
    for a in range(0, len(rows), step):
        r_ = rows[a:a + step]
        in_view[r_] = _in_fov(fc[hu[r_]][:, None, :, :], cam[r_], head[r_], pitch[r_], camera).sum(axis=-1)
    in_view = np.where(imageable, in_view, -1)

    # ---------------------------------------------------------------- per-pass altitude choice
    low_xy = np.where((rng[:, :1] > 0) & steep_ok[:, None], cam[:, 0, :2], np.nan) if len(hu) else cam[:, 0, :2]
    group = _merge_fragments(chain, hu, pairs.rank, low_xy, b, settings, spec.mirror_width_m)
    pass_of_pair = group[chain[hu]]
    chains_used, pass_idx = np.unique(pass_of_pair, return_inverse=True)
    n_pass = len(chains_used)
    # per HUA and altitude: imaged at all, and the most facet centres in view over its imageable pairs
    score_img = np.zeros((n_pass, nz))
    score_frm = np.zeros((n_pass, nz))
    if len(hu):
        best = np.full((n_h, nz), -1, dtype=np.int64)
        np.maximum.at(best, hu, in_view)
        hua_pass = np.full(n_h, -1, dtype=np.int64)
        hua_pass[hu] = pass_idx
        hs = np.unique(hu)
        np.add.at(score_img, hua_pass[hs], (best[hs] >= 0).astype(float))
        np.add.at(score_frm, hua_pass[hs], np.maximum(best[hs], 0).astype(float))
    zsel = np.zeros(n_pass, dtype=np.int64)
    for k in range(n_pass):
        order = np.lexsort((zs, -score_frm[k], -score_img[k]))
        zsel[k] = order[0]
    zpair = zsel[pass_idx]
    prow = np.arange(len(hu))
    p_cam = cam[prow, zpair] if len(hu) else np.zeros((0, 3))
    p_head = head[prow, zpair] if len(hu) else np.zeros(0)
    p_pitch = pitch[prow, zpair] if len(hu) else np.zeros(0)
    p_img = imageable[prow, zpair] if len(hu) else np.zeros(0, bool)
    p_camhit = cam_hit[prow, zpair] if len(hu) else np.zeros(0, np.int64)
    p_geo = geo_ok[prow, zpair] if len(hu) else np.zeros(0, bool)
    p_rng = rng[prow, zpair] if len(hu) else np.zeros(0)

    # corners of the HUA seen from the chosen camera positions
    outline = pose.mirror_outline()
    inset = 1.0 - settings.corner_inset
    ctr = c[hu]
    corners = ctr[:, None, :] + inset * (outline[hu] - ctr[:, None, :])
    corner_blocked = np.zeros(len(hu), dtype=np.int64)
    ci = np.flatnonzero(p_img)
    if len(ci):
        q0 = np.repeat(p_cam[ci], 4, axis=0)
        q1 = corners[ci].reshape(-1, 3)
        q1 = q1 + 1e-6 * _unit(q0 - q1)
        hits = mirrors.first_hits(q0, q1, np.repeat(hu[ci], 4)[:, None])
        if tower_box is not None:
            hits = np.where((hits < 0) & _segments_hit_box(q0, q1, *tower_box), _TOWER_HIT, hits)
        corner_blocked[ci] = (hits.reshape(-1, 4) != -1).sum(axis=1)
    in_frame = in_view[prow, zpair] if len(hu) else np.zeros(0, np.int64)

    # ---------------------------------------------------------------- build passes
    def nm(k: int) -> str:
        return names[k] if k >= 0 else "the tower"

    rank_of = {(int(h), int(t)): int(r) for h, t, r in zip(hu, tg, pairs.rank)}
    drafts = []
    assessed: set[int] = set()
    by_pass = np.argsort(pass_idx, kind="stable")
    bounds = np.searchsorted(pass_idx[by_pass], np.arange(n_pass + 1))
    for k in range(n_pass):
        idx = by_pass[bounds[k]:bounds[k + 1]]
        issues: list[str] = []
        hidden_behind = 0
        cap = idx[p_img[idx]]
        assessed.update(int(h) for h in hu[cap])
        for p in idx:
            h, t = int(hu[p]), int(tg[p])
            label = f"{names[h]}-{names[t]}"
            if not refl_ok[p]:
                blk = int(refl_hit[p])
                if rank_of.get((h, blk), 1 << 30) < int(pairs.rank[p]):  # behind a nearer target of this HUA
                    hidden_behind += 1
                    continue
                issues.append(f"{label}: reflected ray HUA->target blocked by {nm(blk)}")
            elif not steep_ok[p]:
                issues.append(f"{label}: camera direction only {w_elev[p]:.1f} deg above the horizon")
            elif not p_geo[p]:
                if p_rng[p] > settings.max_range_m:
                    issues.append(f"{label}: camera {p_rng[p]:.0f} m from the HUA (> {settings.max_range_m:g} m)")
                else:
                    issues.append(f"{label}: camera position outside the gimbal range or in the tower keep-out")
            elif not p_img[p]:
                issues.append(f"{label}: camera view of {names[h]} blocked by {nm(int(p_camhit[p]))}")
            elif corner_blocked[p]:
                issues.append(f"{label}: {int(corner_blocked[p])} of 4 corners of {names[h]} hidden from the camera")
        if hidden_behind:
            issues.append(f"{hidden_behind} farther candidate target(s) hidden behind the nearest one (not imaged)")
        huas_here = sorted({int(h) for h in hu[idx]}, key=lambda h: c[h, 1])
        for h in huas_here:
            if h not in assessed:
                issues.append(f"{names[h]}: not assessed (no imageable target)")
        if len(cap):
            frac = in_frame[cap] / n_facets
            if np.any(frac < 1.0):
                issues.append(
                    f"HUA not framed whole: {np.mean(in_frame[cap]):.1f} of {n_facets} facet centres in the "
                    f"{camera.horizontal_fov_deg:.1f} x {camera.vertical_fov_deg:.1f} deg field of view on average "
                    f"(camera {p_rng[cap].min():.1f}-{p_rng[cap].max():.1f} m from the HUA)"
                )
        drafts.append((k, idx, cap, issues))

    # HUAs with no candidate target at all: report in the pass of their chain
    chain_to_pass = {int(ch): k for k, ch in enumerate(chains_used)}
    no_target = np.flatnonzero(wanted & ~has_cand)
    chain = group[chain]
    extra: dict[int, list[str]] = {}
    unassessed: list[tuple[str, str]] = []
    for h in no_target.tolist():
        reason = "no target heliostat in front of its mirror (nearest the tower in its line, or isolated)"
        unassessed.append((names[h], reason))
        k = chain_to_pass.get(int(chain[h]))
        if k is not None:
            extra.setdefault(k, []).append(f"{names[h]}: not assessed ({reason})")
    for h in np.unique(hu).tolist():
        if h not in assessed:
            unassessed.append((names[h], "every candidate target blocked or out of reach"))

    # order: azimuth of the pass around the tower, starting after the largest empty sector
    tower = getattr(field, "tower", None)
    centre_xy = np.zeros(2) if tower is None else np.array([0.5 * (tower.x_min_m + tower.x_max_m),
                                                            0.5 * (tower.y_min_m + tower.y_max_m)])
    az = np.zeros(n_pass)
    out_dir = np.zeros((n_pass, 2))
    for k, idx, _, _ in drafts:
        hh = np.unique(hu[idx])
        m = c[hh, :2].mean(axis=0) - centre_xy
        az[k] = _azimuth_deg(m[0], m[1])
        d = -b[hh].sum(axis=0)
        nd = np.linalg.norm(d)
        out_dir[k] = d / nd if nd > 1e-12 else m / max(np.linalg.norm(m), 1e-12)
    order = np.argsort(az, kind="stable")
    if n_pass > 1:
        a_sorted = az[order]
        gaps = np.diff(np.r_[a_sorted, a_sorted[0] + 360.0])
        start = (int(np.argmax(gaps)) + 1) % n_pass
        order = np.r_[order[start:], order[:start]]

    passes_enu = []
    for rank_, k in enumerate(order):
        _, idx, cap, issues = drafts[k]
        issues = issues + extra.get(int(k), [])
        feasible = len(cap) > 0
        use = cap if feasible else idx[(pairs.rank[idx] == 0) & (p_rng[idx] > 0)]
        e = out_dir[k] if rank_ % 2 == 0 else -out_dir[k]
        proj = p_cam[use, :2] @ e
        use = use[np.lexsort((pairs.rank[use], proj))]
        z = float(zs[zsel[k]])
        pts = [p_cam[p] for p in use]
        if pts:
            first, last = pts[0].copy(), pts[-1].copy()
        else:  # nothing to show: a nominal line over the HUAs at the pass altitude
            hh = np.unique(hu[idx])
            proj_h = c[hh, :2] @ e
            first = np.r_[c[hh[np.argmin(proj_h)], :2], z]
            last = np.r_[c[hh[np.argmax(proj_h)], :2], z]
        first[2] = last[2] = z
        span = last[:2] - first[:2]
        if np.linalg.norm(span) > 1.0:  # fly straight from lead-in to run-past through the first and last capture
            e = span / np.linalg.norm(span)
        lead = first - lead_in_m * np.r_[e, 0.0]
        run = last + run_past_m * np.r_[e, 0.0]
        wps: list[tuple[NDArray[np.float64], float, float, str, bool, str | None]] = []
        h0 = float(p_head[use[0]]) if len(use) else float(_azimuth_deg(-e[0], -e[1]))
        g0 = float(p_pitch[use[0]]) if len(use) else -90.0
        wps.append((lead, h0, g0, "lead_in", False, None))
        for p in use:
            wps.append((p_cam[p], float(p_head[p]), float(p_pitch[p]), "scan", bool(feasible), names[int(hu[p])]))
        h1 = float(p_head[use[-1]]) if len(use) else h0
        g1 = float(p_pitch[use[-1]]) if len(use) else g0
        wps.append((run, h1, g1, "run_past", False, None))
        pr = tuple((names[int(hu[p])], names[int(tg[p])]) for p in use) if feasible else ()
        nominal_pitch = float(np.median(p_pitch[use])) if len(use) else g0
        passes_enu.append((rank_, float(_azimuth_deg(e[0], e[1])), z, nominal_pitch, pr, wps, feasible, issues))

    # flux along the passes
    if settings.flux_check and passes_enu:
        samples, owner = [], []
        for k, (_, _, _, _, _, wps, _, _) in enumerate(passes_enu):
            xyz = np.array([w_[0] for w_ in wps])
            seg = np.diff(xyz, axis=0)
            lens = np.linalg.norm(seg, axis=1)
            for a_, d_, l_ in zip(xyz[:-1], seg, lens):
                m_ = max(1, math.ceil(l_ / settings.flux_sample_m))
                samples.append(a_ + np.outer(np.arange(m_) / m_, d_))
                owner.append(np.full(m_, k))
            samples.append(xyz[-1:])
            owner.append(np.array([k]))
        sp = np.concatenate(samples)
        ow = np.concatenate(owner)
        suns = beam_concentration(sp, pose, aim, divergence_mrad=settings.beam_divergence_mrad)
        for k in np.unique(ow[suns > settings.flux_limit_suns]).tolist():
            m_ = (ow == k) & (suns > settings.flux_limit_suns)
            passes_enu[k][7].append(
                f"concentrated sunlight up to {suns[m_].max():.1f} suns (limit {settings.flux_limit_suns:g}) at "
                f"{int(m_.sum())} of {int((ow == k).sum())} points along the pass"
            )

    # WGS84 for every waypoint at once
    all_xyz = np.array([w_[0] for p_ in passes_enu for w_ in p_[5]]) if passes_enu else np.zeros((0, 3))
    lat, lon, hgt = enu_to_geodetic(all_xyz, org) if len(all_xyz) else (np.zeros(0),) * 3
    passes: list[ScanPass] = []
    q = 0
    for rank_, azi, z, gp, pr, wps, feasible, issues in passes_enu:
        wl = []
        for xyz, hd, gpw, kind, capture, hua in wps:
            hd = float(hd) % 360.0
            wl.append(Waypoint(float(xyz[0]), float(xyz[1]), float(xyz[2]), float(lat[q]), float(lon[q]),
                               float(hgt[q]), 0.0 if hd >= 360.0 else hd, float(gpw), float(speed_m_s),
                               kind=kind, capture=capture, hua=hua))  # type: ignore[arg-type]
            q += 1
        passes.append(ScanPass(index=rank_, azimuth_deg=azi, altitude_m=z, gimbal_pitch_deg=gp, pairs=pr,
                               waypoints=tuple(wl), feasible=feasible, issues=tuple(issues)))
    return UfacetPlan(
        passes=tuple(passes),
        min_altitude_m=float(min_alt),
        max_altitude_m=float(max_altitude_m),
        highest_mirror_point_m=float(highest),
        sun_vector=sun,
        assessed=tuple(names[h] for h in sorted(assessed)),
        unassessed=tuple(sorted(unassessed)),
    )


def plan_passes(
    field: Any,
    pose: FieldPose,
    *,
    aim_point: ArrayLike,
    origin: GeodeticOrigin | Any,
    camera: CameraModel = DEFAULT_CAMERA,
    max_altitude_m: float = 25.0,
    safety_margin_m: float = PAPER_MIN_CLEARANCE_M,
    lead_in_m: float = OPENCSP_LEAD_IN_M,
    run_past_m: float = OPENCSP_RUN_PAST_M,
    speed_m_s: float = OPENCSP_SPEED_M_S,
    heliostats: Iterable[str] | None = None,
    settings: UfacetSettings = UfacetSettings(),
) -> tuple[ScanPass, ...]:
    """UFACET scan passes over a tracked heliostat field.

    Parameters
    ----------
    field : Field
        The heliostats (and tower, used for sight lines and the pass order).
    pose : FieldPose
        The field tracked at the planning instant toward ``aim_point``
        (:func:`pihim.field.kinematics.track_field` or :func:`track_at`).
    aim_point : array_like, shape (3,)
        Where the field reflects the sun, ENU metres (OpenCSP's NSTTF plans:
        (60, 8.8, 28.9)). Must be above the ground.
    origin : GeodeticOrigin or Site
        Field origin on WGS84 (ellipsoidal height), for the waypoints'
        geodetic coordinates (e.g. :data:`pihim.sky.sun.NSTTF`). Required:
        no silent default.
    camera : CameraModel
        Field of view for the framing report (default Triton + 35 mm,
        13.8 x 11.5 deg).
    max_altitude_m : float
        Highest allowed flight altitude, metres above the field origin
        (25 m: OpenCSP's NSTTF case).
    safety_margin_m : float
        Clearance above the highest tracked mirror point, metres (>= 5).
    lead_in_m, run_past_m : float
        Straight flight before the first and after the last capture of each
        pass, metres (OpenCSP: 18 and 9).
    speed_m_s : float
        Ground speed along the passes (OpenCSP: 5 m/s).
    heliostats : iterable of str, optional
        HUAs to assess (default: every heliostat). Targets may be any
        heliostat.
    settings : UfacetSettings
        Geometry tuning.

    Returns
    -------
    tuple of ScanPass
        In flight (boustrophedon) order. In each pass, the ``k``-th capturing
        ``scan`` waypoint images ``pairs[k]``; ``lead_in`` and ``run_past``
        waypoints bracket them. Scan waypoints have ``hua`` set and point the
        optical axis at the HUA mirror centre. An infeasible pass
        (``feasible=False``: nothing imageable) keeps the nominal camera
        positions of its HUAs' nearest targets with ``capture=False`` and says
        why in ``issues``.

    Raises
    ------
    PihimInputError
        Sun below the horizon (implied by the pose), aim point at or below
        the ground, minimum safe altitude above ``max_altitude_m``, unknown
        heliostat names, a pose not tracking toward ``aim_point``, bad
        numbers.

    Notes
    -----
    The method and what differs from OpenCSP are in the module docstring
    and ``docs/opencsp-comparison.md``. Use :func:`plan_ufacet` for the
    altitude limits and the list of heliostats that could not be assessed.
    """
    return plan_ufacet(field, pose, aim_point=aim_point, origin=origin, camera=camera,
                       max_altitude_m=max_altitude_m, safety_margin_m=safety_margin_m, lead_in_m=lead_in_m,
                       run_past_m=run_past_m, speed_m_s=speed_m_s, heliostats=heliostats,
                       settings=settings).passes
