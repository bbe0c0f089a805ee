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
(:class:`pihim.field.kinematics.FieldPose`); steps 1-3 are in
:mod:`pihim.planning.lines`:

1. **Lines in the normals' planes.** Each heliostat links to the heliostat
   of the next row in front of its mirror that lies nearest the vertical
   plane of its tracking normal; the links form disjoint chains (discrete
   streamlines of the normals' horizontal directions, crossing the columns
   of a rectangular field as OpenCSP's 5W5 ... 12W14 line does). Each chain
   gives a straight line along the mean direction of its heliostats'
   normals, through their centroid.
2. **Captures on the line.** The camera ``C`` sees a target's mirror centre
   reflected at the HUA mirror centre when ``C`` lies on the ray
   ``C = H + t w`` with ``w = 2 (u . n_H) n_H - u`` (``u`` the unit vector
   from the HUA to the target mirror centre). At the pass altitude that
   point is projected onto the pass line, and the ray from the projected
   camera through the HUA centre, reflected about ``n_H``, must reach the
   target's mirror rectangle from behind (candidate targets: the
   heliostats in front of the HUA mirror that turn their back to it, within
   :attr:`UfacetSettings.max_off_axis_deg`, ``max_lateral_m`` and
   :attr:`UfacetSettings.max_target_distance_m`). Every capture is on its
   pass's straight line, and within ``max_camera_offset_m`` (default one
   mirror width) of its HUA's normals' plane; each HUA is imaged with up to
   :attr:`UfacetSettings.max_targets` targets, nearest first.
3. **Offset and altitude; moves and extra passes.** Each line is shifted
   sideways (up to ``line_offset_max_m``) and flown at the altitude (1 m
   grid between the minimum safe altitude and ``max_altitude_m``) that
   images the most HUAs, then frames the most of their facet centres, then
   needs the smaller shift and the lower altitude. HUAs not imaged from
   their own line, and the HUAs of lines imaging at most
   ``merge_max_huas``, move to a nearby parallel line that images them;
   HUAs still not imaged get extra lines built the same way among them
   (:attr:`UfacetSettings.extra_passes`), down to a short pass along a
   single HUA's own normals' plane.
4. **Gaze.** Heading and gimbal pitch point the optical axis at the HUA
   mirror centre (heading clockwise from North in [0, 360), pitch negative
   below the horizon). The fraction of the HUA's facet centres inside the
   camera field of view (:class:`pihim.camera.model.CameraModel`, default
   Triton + 35 mm: 13.8 x 11.5 deg) is reported. The camera has no roll.
5. **Visibility (not in OpenCSP).** The sight line camera -> HUA (centre
   and four corners) and the reflected ray HUA -> target are tested against
   the tower box and against the tracked mirror rectangles of every other
   heliostat (vectorised ray / rectangle intersection). For every HUA not
   assessed, the pass's :attr:`ScanPass.issues` says why, for the candidate
   target that came nearest (missed reflection, blocked reflection or
   sight line, range, gimbal); a pass with nothing imageable is marked
   ``feasible=False``.
6. **Altitude.** Minimum safe altitude = highest point of any tracked
   mirror + ``safety_margin_m`` (>= 5 m: the paper's field safety rule,
   section 2); see step 3 for the choice of each pass's altitude.
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
   ideal-gaze curves along the tracking normals, straight sections,
   look-back of 3 targets, lead-in 18 m and run-past 9 m, 5 m/s,
   boustrophedon order.
   See ``docs/opencsp-comparison.md``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from pihim import _forked
from pihim.camera.model import CameraModel
from pihim.errors import PihimInputError
from pihim.field.geodesy import GeodeticOrigin, as_origin, enu_to_geodetic
from pihim.field.kinematics import FieldPose, track_field
from pihim.planning.flux import Beams, beam_concentration
from pihim.planning.lines import (
    VIEW_BEHIND,
    VIEW_CAMERA_BLOCKED,
    VIEW_LOW,
    VIEW_MISS,
    VIEW_OFF_PLANE,
    VIEW_REFLECTION_BLOCKED,
    Candidates,
    PairGeometry,
    ScanLines,
    ViewLimits,
    Views,
    candidate_targets,
    chain_lines,
    horizontal_normals,
    line_offsets,
    link_chains,
    pair_geometry,
    plane_links,
    views_of_pairs,
)
from pihim.planning.model import ScanPass, Waypoint, heading_0_360
from pihim.planning.sightlines import (
    TOWER_HIT,
    MirrorIndex,
    azimuth_deg,
    camera_frame,
    dot,
    first_mirror_hits,
    gaze_angles,
    mirror_index,
    optical_axis,
    segments_hit_box,
    tower_box,
    unit,
)

__all__ = [
    "DEFAULT_CAMERA",
    "MAX_ALTITUDE_LIMIT_M",
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
#: Largest maximum altitude accepted, metres above the field origin: far above what drone rules allow
#: (120 m in the US and the EU) and where the 35 mm camera's pixel covers 10 cm; the altitude grid between
#: the minimum safe altitude and the maximum would otherwise grow without bound.
MAX_ALTITUDE_LIMIT_M = 1000.0



# --------------------------------------------------------------------------- settings and result


@dataclass(frozen=True)
class UfacetSettings:
    """Tuning of the UFACET geometry; the defaults suit NSTTF-like heliostats.

    Attributes
    ----------
    max_targets : int
        Targets imaged per HUA at most, nearest first (OpenCSP's look-back, 3).
    max_target_distance_m : float
        Horizontal search radius for targets, metres.
    max_off_axis_deg : float
        Largest horizontal angle between the HUA's normal and the direction
        to a target, degrees.
    max_lateral_m : float or None
        Largest horizontal distance of a target's mirror centre from the
        vertical plane of the HUA's normal, metres. Default: the mirror width.
    abreast_m : float or None
        Candidates whose forward distances are within this of the nearest
        one are in the next row; the line links to the one of them nearest
        the normals' plane. Default: 1.5 mirror heights (9.1 m for NSTTF
        heliostats, close to OpenCSP's 9 m ``discard_threshold_p``).
    line_offset_max_m, line_offset_step_m : float
        Sideways shifts of each line tried (0, +-step, ... up to the maximum),
        metres; the shift and the altitude imaging the most HUAs win.
    merge_max_huas : int
        Lines imaging at most this many HUAs are dissolved when every one of
        them is imaged from another line (0: never).
    merge_lateral_m : float or None
        Largest distance of a HUA's mirror centre from another line it moves
        to (not imaged from its own line, or from a dissolved short line),
        metres. Default: 1.5 mirror widths.
    max_plane_deviation_deg : float
        Largest angle between a line and the normals' plane of a HUA moved
        to it, degrees.
    max_line_deviation_m : float
        A chain of links whose heliostats lie farther than this from its
        straight line is halved until they do not, one line per piece
        (:func:`pihim.planning.lines.link_chains`): in a large field a chain
        spans the whole radius along curving normals' planes. NSTTF chains
        stay within 20 m of their lines at every hour of 2021-05-13 and are
        kept whole.
    extra_passes : bool
        HUAs imaged from no line get extra lines, built the same way among
        them only (a HUA alone gets its own normals' plane), when those
        image them.
    max_camera_offset_m : float or None
        Largest horizontal distance of a capture point from the vertical
        plane of its HUA's tracking normal, metres. Default: the mirror
        width.
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
    abreast_m: float | None = None
    line_offset_max_m: float = 3.0
    line_offset_step_m: float = 1.0
    merge_max_huas: int = 2
    merge_lateral_m: float | None = None
    max_plane_deviation_deg: float = 10.0
    max_line_deviation_m: float = 30.0
    extra_passes: bool = True
    max_camera_offset_m: float | None = None
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
        v = self.max_line_deviation_m
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and v > 0):  # math.inf: chains kept whole
            raise PihimInputError(f"UfacetSettings.max_line_deviation_m must be a positive number, got {v!r}")
        if not (isinstance(self.line_offset_max_m, (int, float)) and math.isfinite(self.line_offset_max_m)
                and self.line_offset_max_m >= 0 and isinstance(self.line_offset_step_m, (int, float))
                and math.isfinite(self.line_offset_step_m) and self.line_offset_step_m > 0):
            raise PihimInputError("line_offset_max_m must be >= 0 and line_offset_step_m > 0 (finite numbers)")
        if not 0 <= self.max_plane_deviation_deg < 90:
            raise PihimInputError(f"max_plane_deviation_deg must be in [0, 90), got {self.max_plane_deviation_deg!r}")
        if not 0 < self.max_off_axis_deg < 90:
            raise PihimInputError(f"max_off_axis_deg must be in (0, 90), got {self.max_off_axis_deg!r}")
        if isinstance(self.merge_max_huas, bool) or not isinstance(self.merge_max_huas, int) \
                or self.merge_max_huas < 0:
            raise PihimInputError(f"merge_max_huas must be an integer >= 0, got {self.merge_max_huas!r}")
        for label in ("abreast_m", "max_lateral_m", "merge_lateral_m", "max_camera_offset_m"):
            v = getattr(self, label)
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise PihimInputError(f"UfacetSettings.{label} must be None or a number >= 0, got {v!r}")
        if not -90.0 <= self.gimbal_pitch_min_deg < self.gimbal_pitch_max_deg <= 90.0:
            raise PihimInputError("gimbal pitch limits must satisfy -90 <= min < max <= 90 deg")
        if not 0 <= self.corner_inset < 1 or self.tower_clearance_m < 0:
            raise PihimInputError("corner_inset must be in [0, 1) and tower_clearance_m >= 0")
        for label in ("extra_passes", "flux_check"):  # "no" would be taken for True
            if not isinstance(getattr(self, label), (bool, np.bool_)):
                raise PihimInputError(f"UfacetSettings.{label} must be True or False, got {getattr(self, label)!r}")


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
    t = unit(a - pose.mirror_centres)
    n = pose.normals
    s = 2.0 * dot(n, t)[:, None] * n - t
    mean = unit(s.mean(axis=0))
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
                    heading_0_360(heading_deg), 0.0, 0.0, kind="takeoff", capture=False, hua=None)


# --------------------------------------------------------------------------- the planner


def _altitude_grid(lo: float, hi: float, step: float) -> NDArray[np.float64]:
    z = np.arange(lo, hi + 1e-9, step)
    if len(z) == 0 or z[-1] < hi - 1e-9:
        z = np.r_[z, hi]
    return z


@dataclass(frozen=True)
class _Context:
    """What every view test of one planning run shares (internal): pairs, lines, grids, limits."""

    pose: FieldPose
    mirrors: MirrorIndex
    limits: ViewLimits
    camera: CameraModel
    cand: Candidates
    geom: PairGeometry
    lines: ScanLines
    offsets: NDArray[np.float64]
    altitudes: NDArray[np.float64]
    workers: int | None = 1  # processes evaluating chunks of configurations side by side (pihim._forked)

    def views(self, pair: NDArray[np.int64], line: NDArray[np.int64], offset: NDArray[np.float64],
              altitude: NDArray[np.float64], *, trace: bool = True) -> Views:
        """Views of candidate pairs ``pair`` from lines ``line`` shifted by ``offset`` at ``altitude``."""
        origin = self.lines.origin[line] + offset[:, None] * self.lines.across[line]
        return views_of_pairs(self.geom, pair, self.mirrors, self.limits, origin, self.lines.direction[line],
                              altitude, trace=trace)

    def facets_in_view(self, hua: NDArray[np.int64], cam: NDArray[np.float64]) -> NDArray[np.int64]:
        """Facet centres of each HUA inside the field of view with the HUA centred.

        :func:`gaze_angles` and :func:`camera_frame` on the cameras, then :func:`in_fov` summed in one
        compiled pass (:func:`pihim.planning._kernels.count_in_view`, held to ``in_fov`` by a test).
        """
        from pihim.planning import _kernels

        hua = np.ascontiguousarray(hua, dtype=np.int64)
        cam = np.ascontiguousarray(cam, dtype=float)
        head, pitch = gaze_angles(cam, self.pose.mirror_centres[hua])
        r, dn, f = (np.ascontiguousarray(a, dtype=float) for a in camera_frame(head, pitch))
        c = self.camera
        return _kernels.count_in_view(np.ascontiguousarray(self.pose.facet_centres, dtype=float), hua, cam, r, dn, f,
                                      float(0.5 * c.width_px / c.focal_length_px),
                                      float(0.5 * c.height_px / c.focal_length_px))


def _config_scores(ctx: _Context, pairs: NDArray[np.int64], line_of: NDArray[np.int64], n_h: int, *, trace: bool,
                   allowed: NDArray[np.bool_] | None = None,
                   chunk: int = 400_000) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """HUAs imaged and facet centres framed per (line, offset, altitude) configuration, flattened.

    Configuration ``g = (line * n_offsets + offset) * n_altitudes + altitude``.
    With ``trace=False`` the blocking tests are skipped (an upper bound on
    the HUAs imaged); ``allowed`` restricts the evaluation to some
    configurations; ``pairs`` indexes the context's candidate pairs.
    """
    cand = ctx.cand
    m, nz = len(ctx.offsets), len(ctx.altitudes)
    n_cfg = len(ctx.lines) * m * nz
    combos = len(pairs) * m * nz

    def part(j: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Keys and facet centres framed of the viewing combinations of chunk ``j`` (independent chunks)."""
        k = np.arange(j * chunk, min(combos, (j + 1) * chunk))
        p, mi, zi = pairs[k // (m * nz)], (k // nz) % m, k % nz
        ln = line_of[cand.hua[p]]
        if allowed is not None:
            sel = allowed[(ln * m + mi) * nz + zi]
            p, mi, zi, ln = p[sel], mi[sel], zi[sel], ln[sel]
        h = cand.hua[p]
        v = ctx.views(p, ln, ctx.offsets[mi], ctx.altitudes[zi], trace=trace)  # traces only the geometric survivors
        s = np.flatnonzero(v.ok)
        return ((ln[s] * m + mi[s]) * nz + zi[s]) * n_h + h[s], ctx.facets_in_view(h[s], v.camera[s])

    done = _forked.map_pieces(part, -(-combos // chunk), ctx.workers, what="chunks of line settings")
    key = np.concatenate([kf[0] for kf in done]) if done else np.zeros(0, np.int64)
    frm = np.concatenate([kf[1] for kf in done]) if done else np.zeros(0, np.int64)
    n_img = np.zeros(n_cfg)
    n_frm = np.zeros(n_cfg)
    if len(key):
        order = np.lexsort((-frm, key))
        key, frm = key[order], frm[order]
        first = np.r_[True, key[1:] != key[:-1]]  # best-framed target per (configuration, HUA)
        cfg = key[first] // n_h
        np.add.at(n_img, cfg, 1.0)
        np.add.at(n_frm, cfg, frm[first].astype(float))
    return n_img, n_frm


def _choose_line_settings(ctx: _Context, pairs: NDArray[np.int64], line_of: NDArray[np.int64], n_h: int,
                          shortlist: int = 4) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Per line, the sideways offset and the altitude (indices) imaging the most HUAs.

    Ties: more facet centres framed (summed over the HUAs, best target each),
    then the smaller offset, then the lower altitude. The ray tests (the
    expensive part) run only on each line's ``shortlist`` best
    configurations by geometry alone; blocking can only lower a count.
    """
    n_lines = len(ctx.lines)
    m, nz = len(ctx.offsets), len(ctx.altitudes)
    cfg_line = np.repeat(np.arange(n_lines), m * nz)
    cfg_off = np.tile(np.repeat(np.abs(ctx.offsets), nz), n_lines)
    cfg_z = np.tile(ctx.altitudes, n_lines * m)

    def ranked(n_img: NDArray, n_frm: NDArray) -> NDArray[np.int64]:
        return np.lexsort((cfg_z, cfg_off, -n_frm, -n_img, cfg_line))

    order = ranked(*_config_scores(ctx, pairs, line_of, n_h, trace=False))
    first = np.r_[True, cfg_line[order][1:] != cfg_line[order][:-1]]
    pos = np.arange(len(order)) - np.flatnonzero(first)[np.cumsum(first) - 1]  # rank within its line
    allowed = np.zeros(len(order), dtype=bool)
    allowed[order[pos < shortlist]] = True
    n_img, n_frm = _config_scores(ctx, pairs, line_of, n_h, trace=True, allowed=allowed)
    n_img = np.where(allowed, n_img, -1.0)
    order = ranked(n_img, n_frm)
    best = order[np.r_[True, cfg_line[order][1:] != cfg_line[order][:-1]]]
    return (best // nz) % m, best % nz


def _move_huas(ctx: _Context, cand: Candidates, line_of: NDArray[np.int64], line_off: NDArray[np.float64],
               line_z: NDArray[np.float64], imaged: NDArray[np.bool_], normals_xy: NDArray[np.float64],
               st: UfacetSettings, lateral_limit: float, wanted: NDArray[np.bool_]) -> NDArray[np.int64]:
    """Move HUAs not imaged from their own line, and the HUAs of short lines, to a nearby line that images them.

    A host line must run within ``max_plane_deviation_deg`` of the HUA's
    normals' plane, pass within ``lateral_limit`` of its mirror centre and
    reach within ``max_target_distance_m`` of it along the line; among hosts
    that image it, the nearest line wins. A short line (at most
    ``merge_max_huas`` imaged HUAs) is emptied only if all its imaged HUAs
    find a host (a separate pass would cost a lead-in, a run-past and a
    transit).
    """
    n_lines = len(ctx.lines)
    c_xy = ctx.pose.mirror_centres[:, :2]
    has = np.zeros(len(line_of), bool)
    has[cand.hua] = True
    per_line = np.bincount(line_of[imaged & wanted], minlength=n_lines)
    short = (per_line > 0) & (per_line <= st.merge_max_huas) if st.merge_max_huas > 0 else np.zeros(n_lines, bool)
    movers = np.flatnonzero(has & wanted & (~imaged | short[line_of]))
    hosts = np.flatnonzero((per_line > 0) & ~short)
    if len(movers) == 0 or len(hosts) == 0:
        return line_of
    # extent of each host line along itself (its imaged HUAs)
    mem = np.flatnonzero(imaged & wanted & ~short[line_of])
    s_mem = ctx.lines.along(line_of[mem], c_xy[mem])
    lo = np.full(n_lines, np.inf)
    hi = np.full(n_lines, -np.inf)
    np.minimum.at(lo, line_of[mem], s_mem)
    np.maximum.at(hi, line_of[mem], s_mem)
    # (mover, host) combinations passing the plane, lateral and extent limits; candidates from a k-d tree
    # over points along each host line (every lateral_limit metres over its reach): linear in the field size
    reach_lo = lo[hosts] - st.max_target_distance_m
    reach_hi = hi[hosts] + st.max_target_distance_m
    step = max(lateral_limit, 1.0)
    counts = np.maximum(1, np.ceil((reach_hi - reach_lo) / step).astype(np.int64) + 1)
    owner = np.repeat(np.arange(len(hosts)), counts)
    s_pts = np.repeat(reach_lo, counts) + step * (np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts,
                                                                                          counts))
    hk = hosts[owner]
    pts = (ctx.lines.origin[hk] + line_off[hk, None] * ctx.lines.across[hk]
           + np.minimum(s_pts, reach_hi[owner])[:, None] * ctx.lines.direction[hk])
    near = cKDTree(pts).query_ball_point(c_xy[movers], math.hypot(lateral_limit, 0.5 * step) + 1e-6,
                                         return_sorted=False)
    pairs = {(int(m_), int(hosts[owner[j]])) for m_, lst in zip(movers.tolist(), near, strict=True) for j in lst}
    if not pairs:
        return line_of
    mv, hs = (np.array(v, dtype=np.int64) for v in zip(*sorted(pairs), strict=True))
    keep = hs != line_of[mv]
    keep &= dot(normals_xy[mv], ctx.lines.direction[hs]) >= math.cos(math.radians(st.max_plane_deviation_deg))
    lat = np.abs(ctx.lines.lateral(hs, c_xy[mv]) - line_off[hs])
    keep &= lat <= lateral_limit
    s = ctx.lines.along(hs, c_xy[mv])
    keep &= (s >= lo[hs] - st.max_target_distance_m) & (s <= hi[hs] + st.max_target_distance_m)
    mv, hs, lat = mv[keep], hs[keep], lat[keep]
    if len(mv) == 0:
        return line_of
    # every candidate pair of the mover against the host's chosen offset and altitude
    starts = np.searchsorted(cand.hua, mv)
    counts = np.searchsorted(cand.hua, mv, side="right") - starts
    rows = np.repeat(np.arange(len(mv)), counts)
    p = np.repeat(starts, counts) + (np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts))
    v = ctx.views(p, hs[rows], line_off[hs[rows]], line_z[hs[rows]])
    good_rows = np.unique(rows[v.ok])
    if len(good_rows) == 0:
        return line_of
    order = good_rows[np.lexsort((lat[good_rows], mv[good_rows]))]
    first = order[np.r_[True, mv[order][1:] != mv[order][:-1]]]
    dest = dict(zip(mv[first].tolist(), hs[first].tolist()))
    out = line_of.copy()
    for k in np.flatnonzero(short).tolist():  # all or nothing for the imaged HUAs of a short line
        members = np.flatnonzero((line_of == k) & imaged & wanted)
        if not all(int(h) in dest for h in members):
            for h in members.tolist():
                dest.pop(int(h), None)
    for h, k in dest.items():
        out[h] = k
    return out


def _assign_lines(ctx: _Context, all_cand: Candidates, chain: NDArray[np.int64], b: NDArray[np.float64],
                  st: UfacetSettings, abreast: float, merge_lat: float,
                  wanted: NDArray[np.bool_]) -> tuple[_Context, NDArray[np.int64], NDArray, NDArray, Views]:
    """Line of every HUA, each line's sideways offset and altitude, and the views of every candidate pair.

    Steps 1-3 of the module docstring: the chains' lines get their best
    offset and altitude; HUAs not imaged move to a nearby line; extra lines
    are built for the HUAs left. Returns the context (with the extra lines),
    the line per heliostat, offset and altitude per line and the views.
    """
    cand, c = ctx.cand, ctx.pose.mirror_centres
    n_h = len(chain)
    has_cand = np.zeros(n_h, dtype=bool)
    has_cand[all_cand.hua] = True
    line_of = chain.copy()
    every_pair = np.arange(len(cand))
    mi, zi = _choose_line_settings(ctx, every_pair, line_of, n_h)
    line_off, line_z = ctx.offsets[mi], ctx.altitudes[zi]

    def evaluate(assign: NDArray[np.int64]) -> Views:
        ln = assign[cand.hua]
        return ctx.views(every_pair, ln, line_off[ln], line_z[ln])

    views = evaluate(line_of)
    imaged = np.zeros(n_h, dtype=bool)
    imaged[cand.hua[views.ok]] = True
    moved = _move_huas(ctx, cand, line_of, line_off, line_z, imaged, b, st, merge_lat, wanted)
    if np.any(moved != line_of):
        line_of = moved
        views = evaluate(line_of)
    # HUAs still not imaged: extra lines built the same way among them only, then one line per HUA left
    # (its own normals' plane), each shifted and raised like the others
    for alone in ((False, True) if st.extra_passes else ()):
        imaged[:] = False
        imaged[cand.hua[views.ok]] = True
        left = np.flatnonzero(wanted & has_cand & ~imaged)
        if len(left) == 0:
            break
        if alone:
            sub_id = np.arange(len(left))
        else:
            is_left = np.zeros(n_h, dtype=bool)
            is_left[left] = True
            among = all_cand.take(is_left[all_cand.hua] & is_left[all_cand.target])
            _, sub_id = np.unique(link_chains(plane_links(among, n_h, abreast), c, st.max_line_deviation_m, b)[left],
                                  return_inverse=True)
        extra = chain_lines(sub_id, b[left], c[left, :2])
        n0 = len(ctx.lines)
        ctx = dataclasses.replace(ctx, lines=ScanLines(np.r_[ctx.lines.origin, extra.origin],
                                                       np.r_[ctx.lines.direction, extra.direction]))
        trial = line_of.copy()
        trial[left] = n0 + sub_id
        mi2, zi2 = _choose_line_settings(ctx, np.flatnonzero(np.isin(cand.hua, left)), trial, n_h)
        line_off = np.r_[line_off, ctx.offsets[mi2[n0:]]]
        line_z = np.r_[line_z, ctx.altitudes[zi2[n0:]]]
        v2 = evaluate(trial)
        rescued = np.zeros(n_h, dtype=bool)
        rescued[cand.hua[v2.ok]] = True
        line_of = np.where(rescued & ~imaged, trial, line_of)
        views = evaluate(line_of)
    return ctx, line_of, line_off, line_z, views


def _corners_hidden(ctx: _Context, hua: NDArray[np.int64], cam: NDArray[np.float64],
                    corner_inset: float) -> NDArray[np.int64]:
    """How many of the 4 mirror corners of each HUA a mirror or the tower hides from its camera."""
    if len(hua) == 0:
        return np.zeros(0, dtype=np.int64)
    c = ctx.pose.mirror_centres
    outline = ctx.pose.mirror_outline()
    corners = c[hua][:, None, :] + (1.0 - corner_inset) * (outline[hua] - c[hua][:, None, :])
    q0 = np.repeat(cam, 4, axis=0)
    q1 = corners.reshape(-1, 3)
    q1 = q1 + 1e-6 * unit(q0 - q1)
    hits = ctx.mirrors.first_hits(q0, q1, np.repeat(hua, 4)[:, None])
    if ctx.limits.tower_box is not None:
        hits = np.where((hits < 0) & segments_hit_box(q0, q1, *ctx.limits.tower_box), TOWER_HIT, hits)
    return (hits.reshape(-1, 4) != -1).sum(axis=1)


def _order_around_tower(centres_xy: list[NDArray[np.float64]], tower: Any) -> NDArray[np.int64]:
    """Passes by azimuth of their HUAs' centroid around the tower, starting after the largest empty sector."""
    centre = np.zeros(2) if tower is None else np.array([0.5 * (tower.x_min_m + tower.x_max_m),
                                                         0.5 * (tower.y_min_m + tower.y_max_m)])
    n = len(centres_xy)
    az = np.array([float(azimuth_deg(*(m - centre))) for m in centres_xy]) if n else np.zeros(0)
    order = np.argsort(az, kind="stable")
    if n > 1:
        a_sorted = az[order]
        gaps = np.diff(np.r_[a_sorted, a_sorted[0] + 360.0])
        start = (int(np.argmax(gaps)) + 1) % n
        order = np.r_[order[start:], order[:start]]
    return order


#: Flux samples per piece of work for forked workers (:func:`_flux_issues`; each point is independent).
_FLUX_PIECE = 200_000


def _flux_issues(paths: list[list[NDArray[np.float64]]], pose: FieldPose, aim: NDArray[np.float64],
                 st: UfacetSettings, workers: int | None = 1) -> dict[int, str]:
    """Concentrated-sunlight warnings per pass, sampled every ``flux_sample_m`` along its waypoints
    (:func:`pihim.planning.flux.beam_concentration`; pieces of the samples side by side with ``workers``)."""
    samples, owner = [], []
    for k, pts in enumerate(paths):
        xyz = np.array(pts)
        seg = np.diff(xyz, axis=0)
        for a_, d_, l_ in zip(xyz[:-1], seg, np.linalg.norm(seg, axis=1), strict=True):
            m_ = max(1, math.ceil(l_ / st.flux_sample_m))
            samples.append(a_ + np.outer(np.arange(m_) / m_, d_))
            owner.append(np.full(m_, k))
        samples.append(xyz[-1:])
        owner.append(np.array([k]))
    ow = np.concatenate(owner)
    pts = np.concatenate(samples)
    beams = Beams(pose, aim, divergence_mrad=st.beam_divergence_mrad)
    pieces = _forked.map_pieces(lambda i: beams.concentration(pts[i * _FLUX_PIECE:(i + 1) * _FLUX_PIECE]),
                                -(-len(pts) // _FLUX_PIECE), workers, what="flux samples")
    suns = np.concatenate(pieces)
    out = {}
    for k in np.unique(ow[suns > st.flux_limit_suns]).tolist():
        m_ = (ow == k) & (suns > st.flux_limit_suns)
        out[int(k)] = (f"concentrated sunlight up to {suns[m_].max():.1f} suns (limit {st.flux_limit_suns:g}) at "
                       f"{int(m_.sum())} of {int((ow == k).sum())} points along the pass")
    return out


class _PassDraft(NamedTuple):
    """A pass before geodetic conversion (internal); waypoints are (xyz, heading, pitch, kind, capture, hua)."""

    index: int
    azimuth_deg: float
    altitude_m: float
    pitch_deg: float
    pairs: tuple[tuple[str, str], ...]
    waypoints: list[tuple[NDArray[np.float64], float, float, str, bool, str | None]]
    feasible: bool
    issues: list[str]


def _scan_passes(drafts: list[_PassDraft], origin: GeodeticOrigin, speed_m_s: float) -> list[ScanPass]:
    """ScanPass objects from drafts; geodetic coordinates of every waypoint are converted at once."""
    all_xyz = np.array([w_[0] for d in drafts for w_ in d.waypoints]) if drafts else np.zeros((0, 3))
    lat, lon, hgt = enu_to_geodetic(all_xyz, origin) if len(all_xyz) else (np.zeros(0),) * 3
    passes: list[ScanPass] = []
    q = 0
    for rank_, azi, z, gp, pr, wps, feasible, issues in drafts:
        wl = []
        for xyz, hd, gpw, kind, capture, hua in wps:
            wl.append(Waypoint(float(xyz[0]), float(xyz[1]), float(xyz[2]), float(lat[q]), float(lon[q]),
                               float(hgt[q]), heading_0_360(hd), float(gpw), float(speed_m_s),
                               kind=kind, capture=capture, hua=hua))
            q += 1
        passes.append(ScanPass(index=rank_, azimuth_deg=azi, altitude_m=z, gimbal_pitch_deg=gp, pairs=pr,
                               waypoints=tuple(wl), feasible=feasible, issues=tuple(issues)))
    return passes


def _pair_issue(code: int, label: str, hua: str, target: str, v: Views, i: int, nm: Any,
                st: UfacetSettings, limit_m: float) -> str:
    if code == VIEW_REFLECTION_BLOCKED:
        return f"{label}: reflected ray HUA->target blocked by {nm(int(v.blocker[i]))}"
    if code == VIEW_CAMERA_BLOCKED:
        return f"{label}: camera view of {hua} blocked by {nm(int(v.blocker[i]))}"
    if code == VIEW_MISS:
        return (f"{label}: seen from the pass line, the reflection at the centre of {hua} misses {target} "
                f"by {float(v.miss_m[i]):.1f} m")
    if code == VIEW_OFF_PLANE:
        return (f"{label}: camera {float(v.plane_offset_m[i]):.1f} m aside of the normals' plane of {hua} "
                f"(> {limit_m:.1f} m)")
    if code == VIEW_LOW:
        return f"{label}: camera direction only {float(v.elevation_deg[i]):.1f} deg above the horizon"
    if code == VIEW_BEHIND:
        if np.isfinite(v.range_m[i]) and v.range_m[i] > st.max_range_m:
            return f"{label}: camera {float(v.range_m[i]):.0f} m from the HUA (> {st.max_range_m:g} m)"
        return f"{label}: camera behind the HUA mirror at the pass altitude"
    return f"{label}: camera position outside the gimbal range or in the tower keep-out"


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
    workers: int | None = 1,
) -> UfacetPlan:
    """UFACET scan passes for a tracked field, with diagnostics. See :func:`plan_passes`.

    ``workers``: processes evaluating the lines' offsets and altitudes side by
    side (forked on Linux, :mod:`pihim._forked`; None: one per CPU); the plan
    does not depend on it.
    """
    _forked.check_workers(workers)
    # ---------------------------------------------------------------- inputs
    if len(pose.normals) != len(field.names):
        raise PihimInputError(
            f"pose has {len(pose.normals)} heliostats but the field {len(field.names)}: track this field"
        )
    aim = _check_aim(aim_point)
    org = as_origin(origin)
    for label, val, strict in (("max_altitude_m", max_altitude_m, True), ("lead_in_m", lead_in_m, False),
                               ("run_past_m", run_past_m, False), ("speed_m_s", speed_m_s, True)):
        if isinstance(val, bool) or not (isinstance(val, (int, float)) and math.isfinite(val)) \
                or (val <= 0 if strict else val < 0):
            raise PihimInputError(f"{label} must be a finite number {'>' if strict else '>='} 0, got {val!r}")
    if max_altitude_m > MAX_ALTITUDE_LIMIT_M:
        raise PihimInputError(f"max_altitude_m must be at most {MAX_ALTITUDE_LIMIT_M:g} m, got {max_altitude_m:g}")
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
    st = settings
    tower = getattr(field, "tower", None)
    c = pose.mirror_centres

    # ---------------------------------------------------------------- lines in the normals' planes
    abreast = 1.5 * spec.mirror_height_m if st.abreast_m is None else st.abreast_m
    max_lateral = spec.mirror_width_m if st.max_lateral_m is None else st.max_lateral_m
    all_cand = candidate_targets(pose, max_distance_m=st.max_target_distance_m,
                                 max_off_axis_deg=st.max_off_axis_deg, max_lateral_m=max_lateral)
    b, _ = horizontal_normals(pose)
    chain = link_chains(plane_links(all_cand, n_h, abreast), c, st.max_line_deviation_m, b)
    cand = all_cand.take(wanted[all_cand.hua])
    has_cand = np.zeros(n_h, dtype=bool)
    has_cand[all_cand.hua] = True
    limits = ViewLimits(st.max_range_m, st.min_reflection_elevation_deg, st.gimbal_pitch_min_deg,
                        st.gimbal_pitch_max_deg, tower_box(tower), tower_box(tower, st.tower_clearance_m),
                        spec.mirror_width_m if st.max_camera_offset_m is None else st.max_camera_offset_m)
    merge_lat = 1.5 * spec.mirror_width_m if st.merge_lateral_m is None else st.merge_lateral_m
    ctx = _Context(pose, mirror_index(pose), limits, camera, cand, pair_geometry(pose, cand.hua, cand.target),
                   chain_lines(chain, b, c[:, :2]), line_offsets(st.line_offset_max_m, st.line_offset_step_m),
                   _altitude_grid(min_alt, max_altitude_m, st.altitude_step_m), workers)

    # ---------------------------------------------------------------- offset, altitude and HUAs of each line
    ctx, line_of, line_off, line_z, views = _assign_lines(ctx, all_cand, chain, b, st, abreast, merge_lat, wanted)
    lines = ctx.lines  # with the extra lines

    # ---------------------------------------------------------------- captures: up to max_targets per HUA
    ok = views.ok
    rank = np.zeros(len(cand), dtype=np.int64)
    if np.any(ok):
        k = np.flatnonzero(ok)  # cand is sorted by HUA then distance: rank = position among the HUA's imaged
        first = np.r_[True, cand.hua[k][1:] != cand.hua[k][:-1]]
        grp = np.cumsum(first) - 1
        rank[k] = np.arange(len(k)) - np.flatnonzero(first)[grp]
    capture = ok & (rank < st.max_targets)
    cam = views.camera
    head, pitch = gaze_angles(cam, c[cand.hua])
    in_frame = np.zeros(len(cand), dtype=np.int64)
    cap_idx = np.flatnonzero(capture)
    in_frame[cap_idx] = ctx.facets_in_view(cand.hua[cap_idx], cam[cap_idx])
    n_facets = pose.facet_centres.shape[1]
    corner_blocked = np.zeros(len(cand), dtype=np.int64)
    corner_blocked[cap_idx] = _corners_hidden(ctx, cand.hua[cap_idx], cam[cap_idx], st.corner_inset)

    # ---------------------------------------------------------------- passes: lines with a wanted HUA to assess
    def nm(k: int) -> str:
        return names[k] if k >= 0 else "the tower"

    pair_line = line_of[cand.hua]
    used = np.unique(pair_line)
    assessed = {int(h) for h in cand.hua[capture]}
    drafts = []
    for ln in used.tolist():
        idx = np.flatnonzero(pair_line == ln)
        cap = idx[capture[idx]]
        issues: list[str] = []
        huas_here = sorted({int(h) for h in cand.hua[idx]}, key=lambda h: c[h, 1])
        for h in huas_here:
            if h in assessed:
                continue
            mine = idx[cand.hua[idx] == h]
            best = mine[np.lexsort((cand.distance_m[mine], -views.code[mine]))[0]]  # the pair that came nearest
            label = f"{names[h]}-{names[int(cand.target[best])]}"
            issues.append(_pair_issue(int(views.code[best]), label, names[h], names[int(cand.target[best])],
                                      views, int(best), nm, st, limits.max_plane_offset_m))
            issues.append(f"{names[h]}: not assessed (no imageable target)")
        for p in cap[corner_blocked[cap] > 0]:
            issues.append(f"{names[int(cand.hua[p])]}-{names[int(cand.target[p])]}: {int(corner_blocked[p])} of 4 "
                          f"corners of {names[int(cand.hua[p])]} hidden from the camera")
        if len(cap) and np.any(in_frame[cap] < n_facets):
            issues.append(
                f"HUA not framed whole: {np.mean(in_frame[cap]):.1f} of {n_facets} facet centres in the "
                f"{camera.horizontal_fov_deg:.1f} x {camera.vertical_fov_deg:.1f} deg field of view on average "
                f"(camera {views.range_m[cap].min():.1f}-{views.range_m[cap].max():.1f} m from the HUA)"
            )
        drafts.append((ln, idx, cap, issues))

    # heliostats with no candidate target at all: reported in the pass of their line, if it is flown
    unassessed: list[tuple[str, str]] = []
    extra: dict[int, list[str]] = {}
    reason = "no target heliostat in front of its mirror (nearest the tower in its line, or isolated)"
    for h in np.flatnonzero(wanted & ~has_cand).tolist():
        unassessed.append((names[h], reason))
        extra.setdefault(int(line_of[h]), []).append(f"{names[h]}: not assessed ({reason})")
    for h in np.unique(cand.hua).tolist():
        if h not in assessed:
            unassessed.append((names[h], "every candidate target blocked or out of reach"))

    order = _order_around_tower([c[np.unique(cand.hua[idx]), :2].mean(axis=0) for _, idx, _, _ in drafts], tower)
    passes_enu: list[_PassDraft] = []
    for rank_, k in enumerate(order.tolist()):
        ln, idx, cap, issues = drafts[k]
        issues = issues + extra.get(int(ln), [])
        feasible = len(cap) > 0
        e = -lines.direction[ln] if rank_ % 2 == 0 else lines.direction[ln]  # even passes fly away from the tower
        z = float(line_z[ln])
        p0 = lines.origin[ln] + line_off[ln] * lines.across[ln]
        if feasible:
            use = cap[np.lexsort((cand.distance_m[cap], cam[cap, :2] @ e))]
            s_use = (cam[use, :2] - p0) @ e
        else:  # nothing to image: a nominal line over the HUAs at the pass altitude
            use = idx[:0]
            s_use = (c[np.unique(cand.hua[idx]), :2] - p0) @ e
        first = np.r_[p0 + (s_use.min() - lead_in_m) * e, z]
        last = np.r_[p0 + (s_use.max() + run_past_m) * e, z]
        wps: list[tuple[NDArray[np.float64], float, float, str, bool, str | None]] = []
        h0 = float(head[use[0]]) if feasible else float(azimuth_deg(-e[0], -e[1]))
        g0 = float(pitch[use[0]]) if feasible else -90.0
        wps.append((first, h0, g0, "lead_in", False, None))
        for p in use.tolist():
            wps.append((cam[p], float(head[p]), float(pitch[p]), "scan", True, names[int(cand.hua[p])]))
        if not feasible:  # the nominal ends of the line, no capture
            for s_ in (s_use.min(), s_use.max()):
                wps.append((np.r_[p0 + s_ * e, z], h0, g0, "scan", False, None))
        h1 = float(head[use[-1]]) if feasible else h0
        g1 = float(pitch[use[-1]]) if feasible else g0
        wps.append((last, h1, g1, "run_past", False, None))
        pr = tuple((names[int(cand.hua[p])], names[int(cand.target[p])]) for p in use.tolist())
        nominal_pitch = float(np.median(pitch[use])) if feasible else g0
        passes_enu.append(_PassDraft(rank_, float(azimuth_deg(e[0], e[1])), z, nominal_pitch, pr, wps, feasible,
                                     issues))

    if settings.flux_check and passes_enu:
        for k, text in _flux_issues([[w_[0] for w_ in d.waypoints] for d in passes_enu], pose, aim,
                                    settings, workers).items():
            passes_enu[k].issues.append(text)
    passes = _scan_passes(passes_enu, org, speed_m_s)
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
        optical axis at the HUA mirror centre. All waypoints of a pass lie on
        one straight line. An infeasible pass (``feasible=False``: nothing
        imageable) keeps its line over its HUAs as ``scan`` waypoints with
        ``capture=False`` and says why in ``issues``.

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
