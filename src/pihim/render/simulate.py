"""One synthetic inspection image of a heliostat field, with what the drone logs and what is true.

:func:`simulate_frame` chains the renderer's pieces into the frame a
polarimetric drone would take over a field at a given time:

1. the sun at ``time`` from the site (refused below the horizon);
2. the field tracked toward the aim point (:func:`pihim.field.track_field`):
   these drive angles are what the plant's control system **commands and
   logs**;
3. per-facet canting deviations ``N(0, canting_sigma_mrad)`` (azimuth and
   elevation, :func:`pihim.field.apply_canting_deviation`) on the design
   normals of every heliostat, and per-heliostat tracking errors
   ``N(0, tracking_sigma_mrad)`` on the azimuth and elevation drive angles:
   the **true** heliostats, from which the scene is built
   (:func:`pihim.render.scene.field_scene`);
4. the camera placed at a planned capture of a HUA-target pair
   (:class:`PairPose`), at a capture waypoint of a ``plan.json``
   (:class:`WaypointPose`) or looking at a point (:class:`LookAtPose`); this
   is the **true** camera pose;
5. the frame rendered (:func:`pihim.render.frame.render_frame`), exposed as
   an auto-exposure would (every pixel that does not see the sun disc,
   directly or in a mirror; or, with ``exposure_pixels="mirror-not-sun"``,
   the mirrors only, which clips the sunlit ground) and recorded as a noisy
   12-bit raw mosaic
   (:func:`pihim.render.sensor.expose`);
6. the **logged** camera pose: the true pose with GPS noise
   ``N(0, gps_sigma_m)`` on x, y, z and attitude noise
   ``N(0, attitude_sigma_deg)`` on heading, pitch and roll.

The result separates what a user of real data has (:attr:`SimulatedFrame.log`:
time, site, camera intrinsics, the logged pose, the commanded heliostat drive
angles, the sensor and exposure) from what only the simulation knows
(:attr:`SimulatedFrame.truth`: the true pose, true drive angles and tracking
errors, every facet's canting deviation, the environment, label legends).
Later processing steps are meant to run on the raw frame and ``log`` only;
``truth`` scores them.

Randomness. One integer seed drives everything through
:class:`numpy.random.SeedSequence` child streams, one per purpose (canting,
tracking, logged pose, sensor noise), so a seed gives identical raw bytes and
identical JSON, and changing one sigma (or the image size) does not change the
other draws.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
from numpy.typing import ArrayLike, NDArray

from pihim._atomic import atomic_group, describe_os_error
from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose
from pihim.errors import PihimInputError
from pihim.field import (
    UFACET_AIM_POINT,
    FieldPose,
    apply_canting_deviation,
    drive_angles,
    enu_to_geodetic,
    track_field,
)
from pihim.polarimetry.stokes import aop_deg, dolp
from pihim.render.frame import LABEL_CHANNELS, RenderedFrame, RenderSettings, render_frame
from pihim.render.paths import KIND_NAMES, MIRROR, SUN
from pihim.render.scene import Scene, StructureSizes, field_scene
from pihim.render.sensor import Exposure, SensorModel, choose_exposure, expose
from pihim.render.shading import Environment
from pihim.sky.sun import NSTTF, Site, parse_time, sun_position

__all__ = [
    "MAX_CAMERA_DISTANCE_M",
    "SCHEMA_ID",
    "LookAtPose",
    "PairPose",
    "PoseRequest",
    "SimulatedFrame",
    "WaypointPose",
    "check_camera_distance",
    "simulate_frame",
    "simulated_frame_paths",
    "write_simulated_frame",
]

#: ``schema`` of the ``FRAME.json`` written by :func:`write_simulated_frame`.
SCHEMA_ID = "pihim.simulated-frame/1"

#: A camera closer than this to a mirror centre is inside the heliostat, metres.
_MIRROR_CENTRE_CLEARANCE_M = 0.5
#: Margin around the mirror's bounding box (facet canting, structure members), metres.
_MIRROR_BOX_MARGIN_M = 0.15
#: Farthest camera from the field origin, metres: the flat-ground local ENU frame and float precision hold well
#: within it (the widest fields are a few kilometres across).
MAX_CAMERA_DISTANCE_M = 10_000.0


# --------------------------------------------------------------------------- pose requests


@dataclass(frozen=True)
class PairPose:
    """The planned capture of a HUA-target pair: the target seen reflected in the HUA.

    The camera goes where :func:`pihim.planning.pipeline.build_plan` (with
    this HUA only, no contrast shift, one capture per HUA -- no facet
    captures -- and the planner's default camera, the Triton with a 35 mm
    lens) places the imaging waypoint of the pair, in a feasible pass: the
    point of the pass line from which the HUA's centre shows the target.
    When that plan has no such capture (the HUA alone gets a line of its
    own; in the whole field it can be imaged from a neighbour's line, with
    another target), the capture of the pair in the same plan of the whole
    field is used, so every pair of a one-capture-per-HUA plan of the field
    can be rendered. The planner chooses targets for that camera's framing,
    so the pose does not depend on the simulated image size.
    """

    hua: str
    target: str


@dataclass(frozen=True)
class WaypointPose:
    """Capture waypoint ``index`` (0-based, see :meth:`CameraPose.from_plan_json`) of a ``plan.json``."""

    plan_path: str | os.PathLike[str]
    index: int


@dataclass(frozen=True)
class LookAtPose:
    """A camera at ``camera_m`` whose optical axis passes through ``look_at_m`` (ENU metres)."""

    camera_m: tuple[float, float, float]
    look_at_m: tuple[float, float, float]
    roll_deg: float = 0.0


PoseRequest = PairPose | WaypointPose | LookAtPose


# --------------------------------------------------------------------------- result


@dataclass(frozen=True, eq=False)
class SimulatedFrame:
    """A simulated raw frame with its log and its ground truth.

    Attributes
    ----------
    raw : ndarray of uint16, shape (H, W)
        The raw DoFP mosaic the camera records (shot and read noise).
    rendered : RenderedFrame
        Noise-free Stokes images, labels and render statistics.
    log : dict
        What the drone and the plant record (JSON-ready; see the module notes
        and ``schemas/simulated-frame.schema.json``).
    truth : dict
        What only the simulation knows (JSON-ready).
    scene : Scene
        The rendered geometry (true heliostats).
    true_field : FieldPose
        True heliostat orientations (design canting in ``facet_normals_local``;
        the deviated facet normals are :attr:`facet_normals_local`).
    commanded_field : FieldPose
        The field as tracked and logged by the control system.
    facet_normals_local : ndarray, shape (N, F, 3)
        True facet normals in each heliostat frame (design plus deviation).
    camera_pose : CameraPose
        True camera pose.
    logged_pose : CameraPose
        Camera pose as logged (GPS and attitude noise).
    exposure : Exposure
    seconds : float
        Wall time of the whole simulation.
    """

    raw: NDArray[np.uint16]
    rendered: RenderedFrame
    log: dict[str, Any]
    truth: dict[str, Any]
    scene: Scene | None = None
    true_field: FieldPose | None = None
    commanded_field: FieldPose | None = None
    facet_normals_local: NDArray[np.float64] | None = None
    camera_pose: CameraPose | None = None
    logged_pose: CameraPose | None = None
    exposure: Exposure | None = None
    seconds: float = float("nan")

    def document(self) -> dict[str, Any]:
        """The ``FRAME.json`` document: ``{"schema", "log", "truth"}``."""
        return {"schema": SCHEMA_ID, "log": self.log, "truth": self.truth}


# --------------------------------------------------------------------------- validation


def _sigma(name: str, value: Any, maximum: float = math.inf) -> float:
    """``value`` as a float in [0, maximum] (a maximum keeps a mistyped exponent from overflowing the geometry)."""
    if isinstance(value, bool):
        raise PihimInputError(f"{name} must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise PihimInputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v < 0:
        raise PihimInputError(f"{name} must be a finite number >= 0, got {value!r}")
    if v > maximum:
        raise PihimInputError(f"{name} must be at most {maximum:g}, got {value!r}")
    return v


def _seed(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise PihimInputError(f"seed must be an integer >= 0, got {value!r}")
    return int(value)


def _fixed_drives(field: Any, drive_deg: Any) -> dict[int, tuple[float, float]]:
    """``{heliostat index: (az, el)}`` of the heliostats commanded away from tracking (validated)."""
    if drive_deg is None:
        return {}
    if not isinstance(drive_deg, Mapping):
        raise PihimInputError(f"drive_deg must map heliostat names to (azimuth, elevation) deg, got {drive_deg!r}")
    out: dict[int, tuple[float, float]] = {}
    for name, angles in drive_deg.items():
        i = field.index(name)
        try:
            az, el = (float(a) for a in angles)
        except (TypeError, ValueError):
            raise PihimInputError(f"drive angles of {name} must be (azimuth_deg, elevation_deg), got {angles!r}") from None
        if not (math.isfinite(az) and math.isfinite(el) and 0.0 <= el <= 90.0):
            raise PihimInputError(f"drive angles of {name} must be finite with elevation in [0, 90] deg, got {angles!r}")
        out[i] = (az, el)
    return out


def _point(name: str, value: Any) -> NDArray[np.float64]:
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise PihimInputError(f"{name} must be three numbers X,Y,Z in metres, got {value!r}") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise PihimInputError(f"{name} must be three finite numbers X,Y,Z in metres, got {value!r}")
    return a


def _check_request(req: Any) -> None:
    if isinstance(req, PairPose):
        if not isinstance(req.hua, str) or not isinstance(req.target, str):
            raise PihimInputError("a HUA-target pair needs two heliostat names")
    elif isinstance(req, WaypointPose):
        if isinstance(req.index, bool) or not isinstance(req.index, (int, np.integer)) or req.index < 0:
            raise PihimInputError(f"waypoint index must be an integer >= 0, got {req.index!r}")
    elif isinstance(req, LookAtPose):
        cam = _point("camera position", req.camera_m)
        tgt = _point("look-at point", req.look_at_m)
        if np.array_equal(cam, tgt):
            raise PihimInputError(f"the look-at point equals the camera position {cam.tolist()}")
        r = req.roll_deg
        if isinstance(r, bool) or not isinstance(r, (int, float, np.floating, np.integer)) or not math.isfinite(r):
            raise PihimInputError(f"roll must be a finite number of degrees, got {r!r}")
    else:
        raise PihimInputError(
            f"pose_request must be PairPose, WaypointPose or LookAtPose, got {type(req).__name__}"
        )


# --------------------------------------------------------------------------- geometry


def check_camera_distance(position: Any) -> None:
    """Refuse a camera more than :data:`MAX_CAMERA_DISTANCE_M` from the field origin (one line)."""
    x, y, z = (float(v) for v in position)
    if not math.hypot(x, y, z) <= MAX_CAMERA_DISTANCE_M:
        raise PihimInputError(f"the camera at ({x:.6g}, {y:.6g}, {z:.6g}) is more than "
                              f"{MAX_CAMERA_DISTANCE_M / 1000:g} km from the field origin")


def _check_camera_position(position: NDArray, pose: FieldPose, scene: Scene) -> None:
    """Refuse a camera below the ground, inside a heliostat or the tower, or kilometres away (one-line errors)."""
    fld = pose.field
    names = fld.names  # type: ignore[attr-defined]
    spec = fld.spec  # type: ignore[attr-defined]
    check_camera_distance(position)
    x, y, z = (float(v) for v in position)
    where = f"({x:.2f}, {y:.2f}, {z:.2f})"
    if scene.ground is not None:
        gz = float(scene.ground_height(x, y))
        if z <= gz:
            raise PihimInputError(f"the camera at {where} is below the ground (z {z:.2f} m <= {gz:.2f} m)")
    if len(names):
        d = np.linalg.norm(pose.mirror_centres - position, axis=1)
        i = int(np.argmin(d))
        if d[i] < _MIRROR_CENTRE_CLEARANCE_M:
            raise PihimInputError(
                f"the camera at {where} is inside heliostat {names[i]} ({d[i]:.2f} m from its mirror centre)"
            )
        q = np.einsum("nji,nj->ni", pose.rotations, position - pose.mirror_centres)  # heliostat-frame coordinates
        m = _MIRROR_BOX_MARGIN_M
        inside = ((np.abs(q[:, 0]) <= spec.mirror_half_width_m + m)
                  & (np.abs(q[:, 1]) <= spec.mirror_half_height_m + m)
                  & (q[:, 2] <= m) & (q[:, 2] >= -(spec.pivot_offset_m + m)))
        pivots = np.asarray(fld.pivots, float)  # type: ignore[attr-defined]
        ped = ((np.hypot(pivots[:, 0] - x, pivots[:, 1] - y) <= 0.5 * StructureSizes().pedestal_m + 0.05)
               & (z <= pivots[:, 2]) & (z >= pivots[:, 2] - spec.pivot_height_m))
        hit = np.flatnonzero(inside | ped)
        if hit.size:
            raise PihimInputError(f"the camera at {where} is inside heliostat {names[int(hit[0])]}")
    tw = getattr(fld, "tower", None)
    if tw is not None and tw.x_min_m <= x <= tw.x_max_m and tw.y_min_m <= y <= tw.y_max_m and z <= tw.height_m:
        raise PihimInputError(f"the camera at {where} is inside the tower")


def _pair_pose(fld: Any, ts: Any, site: Site, aim: NDArray, req: PairPose) -> tuple[CameraPose, str, str]:
    from pihim.planning.pipeline import build_plan

    hua = fld.names[fld.index(req.hua)]
    target = fld.names[fld.index(req.target)]
    if hua == target:
        raise PihimInputError(f"the target must differ from the HUA (both {hua})")
    refusal = f"target {target} is not visible in HUA {hua} from any feasible pose"
    why = ""
    for only in ([hua], None):  # this HUA alone; else the whole field (where its line can differ)
        try:
            plan = build_plan(fld, ts, site, aim_point=aim, heliostats=only, shift=False, facet_captures=False,
                              route=False, facet_report=False)
        except PihimInputError as exc:
            why = f" ({exc})"
            continue
        for p in plan.passes:
            if not p.feasible:
                continue
            for pred in p.predictions:
                if pred.hua == hua and pred.target == target:
                    return CameraPose.from_waypoint(p.waypoints[pred.waypoint_index]), hua, target
    raise PihimInputError(refusal + why)


def _plan_aim_point(path: Path) -> list[float] | None:
    """The aim point a plan.json was made for, or None when it does not say (then the caller's default).

    An ``aim_point`` that is not three finite numbers is refused (one line), not replaced by the default: the
    field would track toward another point than the plan's.
    """
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None  # the waypoint reader names what is wrong with the file
    if not isinstance(doc, dict) or doc.get("aim_point") is None:
        return None
    aim = doc["aim_point"]
    try:
        out = [float(v) for v in aim]
    except (TypeError, ValueError):
        out = []
    if len(out) != 3 or not all(math.isfinite(v) for v in out):
        raise PihimInputError(f"{path}: aim_point must be three finite numbers X,Y,Z in metres, got {aim!r}")
    return out


def _waypoint_pair(path: Path, index: int) -> tuple[str | None, str | None]:
    """HUA and target of capture waypoint ``index`` of a plan.json, where the plan says (else None)."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        k = 0
        for p in doc["passes"]:
            for wi, w in enumerate(p["waypoints"]):
                if isinstance(w, dict) and w.get("capture") is True:
                    if k == index:
                        hua = w.get("hua")
                        targets = [q.get("target") for q in p.get("predictions", [])
                                   if q.get("waypoint_index") == wi and q.get("hua") == hua]
                        return (hua if isinstance(hua, str) else None,
                                targets[0] if len(targets) == 1 and isinstance(targets[0], str) else None)
                    k += 1
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        pass
    return None, None


def _logged_pose(true_pose: CameraPose, gps_sigma: float, att_sigma: float,
                 rng: np.random.Generator) -> tuple[CameraPose, dict[str, float]]:
    """The pose as the drone logs it; always draws 6 normals so the stream does not depend on the sigmas."""
    dpos = rng.standard_normal(3) * gps_sigma + 0.0
    datt = rng.standard_normal(3) * att_sigma + 0.0
    heading, pitch, roll = true_pose.heading_deg, true_pose.pitch_deg, true_pose.roll_deg
    if att_sigma == 0.0:
        rot = np.array(true_pose.rotation)
        angles = {"heading_deg": heading, "pitch_deg": pitch, "roll_deg": roll}
    else:
        h = _fold360(heading + datt[0])
        p = float(np.clip(pitch + datt[1], -90.0, 90.0))  # a gimbal pitch, not past the vertical
        r = float((roll + datt[2] + 180.0) % 360.0 - 180.0)
        rot = np.array(CameraPose.from_attitude((0.0, 0.0, 0.0), h, p, r).rotation)
        angles = {"heading_deg": h, "pitch_deg": p, "roll_deg": r}
    pos = np.array(true_pose.position_m) + dpos if gps_sigma > 0 else np.array(true_pose.position_m)
    return CameraPose(pos, rot), angles


def _fold360(a: Any) -> Any:
    """Angles folded into [0, 360) (``np.mod`` can round a tiny negative angle up to 360)."""
    x = np.mod(np.asarray(a, float), 360.0)
    x = np.where(x >= 360.0, 0.0, x)
    return float(x) if x.ndim == 0 else x


def _pose_dict(pose: CameraPose, site: Site, angles: dict[str, float] | None = None) -> dict[str, Any]:
    a = angles or {"heading_deg": pose.heading_deg, "pitch_deg": pose.pitch_deg, "roll_deg": pose.roll_deg}
    lat, lon, h = enu_to_geodetic(pose.position_m, site)
    return {
        "position_m": [float(v) for v in pose.position_m],
        "latitude_deg": float(lat),
        "longitude_deg": float(lon),
        "height_m": float(h),
        "heading_deg": float(a["heading_deg"]),
        "pitch_deg": float(a["pitch_deg"]),
        "roll_deg": float(a["roll_deg"]),
        "rotation": [[float(v) for v in row] for row in pose.rotation],
    }


def _jsonable(obj: Any) -> Any:
    """Plain Python numbers, lists and dicts (numpy scalars and arrays converted)."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    return obj


def _default_field_source(fld: Any) -> str:
    from pihim.field import nsttf_like_field

    ref = nsttf_like_field()
    if tuple(fld.names) == ref.names and np.array_equal(np.asarray(fld.pivots), ref.pivots):
        return "nsttf-like"
    return "in-memory field"


# --------------------------------------------------------------------------- main entry


def simulate_frame(
    field: Any,
    time: Any,
    *,
    site: Site = NSTTF,
    aim_point: ArrayLike | None = None,
    camera: CameraModel = CameraModel(),
    pose_request: PoseRequest,
    canting_sigma_mrad: float = 0.0,
    tracking_sigma_mrad: float = 0.0,
    gps_sigma_m: float = 0.0,
    attitude_sigma_deg: float = 0.0,
    seed: int = 0,
    sensor: SensorModel = SensorModel(),
    exposure_percentile: float = 99.9,
    headroom: float = 0.9,
    exposure_pixels: str = "not-sun",
    blur_sigma_px: float = 0.0,
    settings: RenderSettings = RenderSettings(),
    progress: Callable[[int, int], Any] | None = None,
    field_source: str | None = None,
    facets_source: str | None = None,
    drive_deg: Mapping[str, tuple[float, float]] | None = None,
) -> SimulatedFrame:
    """Simulate the raw frame of a drone camera over a tracking field, with its log and ground truth.

    Parameters
    ----------
    field : pihim.field.Field
        The heliostats (with the tower, if any).
    time : str or datetime
        Timezone-aware instant (ISO 8601 with an offset).
    site : Site
        Where the field origin is (sun position, WGS84 of the logged pose).
    aim_point : array_like, shape (3,), optional
        Tracking (and canting) aim point, ENU metres, above the ground.
        Default: with a :class:`WaypointPose`, the aim point the plan was
        made for (``plan.json``'s ``aim_point``, so that the field tracks as
        the plan assumed); otherwise OpenCSP's UFACET aim point.
    camera : CameraModel
        Intrinsics and distortion (even width and height).
    pose_request : PairPose, WaypointPose or LookAtPose
        Where the camera is and where it looks (the true pose).
    canting_sigma_mrad : float
        Standard deviation of every facet's canting deviation, azimuth and
        elevation, mrad, in [0, 1000].
    tracking_sigma_mrad : float
        Standard deviation of every heliostat's drive-angle error, azimuth
        and elevation, mrad, in [0, 1000].
    gps_sigma_m : float
        Standard deviation of the logged position on x, y and z, metres, in [0, 1000].
    attitude_sigma_deg : float
        Standard deviation of the logged heading, pitch and roll, deg, in [0, 180].
    seed : int
        >= 0; the same seed gives identical raw bytes and identical JSON.
    sensor : SensorModel
    exposure_percentile, headroom : float
        See :func:`pihim.render.sensor.choose_exposure`.
    exposure_pixels : {"not-sun", "mirror-not-sun"}
        Pixels the exposure is chosen over: everything but the sun disc and
        its reflections (default; nothing else clips), or the mirror pixels
        that do not reflect the sun (the brightest mirror region just
        unclipped; the sunlit ground then clips).
    blur_sigma_px : float
        Gaussian lens blur, pixels, in [0, 100].
    settings : RenderSettings
    progress : callable, optional
        ``progress(done_rays, total_rays)`` during the render.
    field_source, facets_source : str, optional
        What the field was loaded from, for the log (default ``"nsttf-like"``
        when ``field`` is the embedded field, else ``"in-memory field"``).
    drive_deg : mapping of str to (float, float), optional
        Heliostats commanded to fixed drive angles instead of tracking:
        ``{name: (azimuth_deg, elevation_deg)}`` of the mirror normal (e.g.
        ``(180.0, 90.0)``, face-up stow, as in the paper's sky-vs-sky test
        where only the pair under test tracks). The commanded angles are what
        the log records; the tracking error applies on top as for the others.

    Returns
    -------
    SimulatedFrame

    Raises
    ------
    PihimInputError
        Bad parameters, sun below the horizon, unknown heliostat names, a
        pair whose target is not visible in the HUA from any feasible pose, a
        camera below the ground, inside a heliostat or the tower, a look-at
        point equal to the camera position.
    """
    import time as _time

    t0 = _time.perf_counter()
    # --- validate everything before any expensive step
    canting_sigma = _sigma("canting sigma (mrad)", canting_sigma_mrad, 1000.0)  # 1 rad: beyond any canting error
    tracking_sigma = _sigma("tracking sigma (mrad)", tracking_sigma_mrad, 1000.0)
    gps_sigma = _sigma("GPS sigma (m)", gps_sigma_m, 1000.0)
    att_sigma = _sigma("attitude sigma (deg)", attitude_sigma_deg, 180.0)
    blur = _sigma("blur sigma (px)", blur_sigma_px, 100.0)
    seed_i = _seed(seed)
    if not isinstance(camera, CameraModel):
        raise PihimInputError(f"camera must be a CameraModel, got {type(camera).__name__}")
    if camera.width_px % 2 or camera.height_px % 2:
        raise PihimInputError(
            f"the image size must be even for the 2x2 polarizer mosaic, got {camera.width_px}x{camera.height_px}"
        )
    if not isinstance(sensor, SensorModel):
        raise PihimInputError(f"sensor must be a SensorModel, got {type(sensor).__name__}")
    if not isinstance(settings, RenderSettings):
        raise PihimInputError(f"settings must be RenderSettings, got {type(settings).__name__}")
    pct = _sigma("exposure percentile", exposure_percentile)
    if not 0 < pct <= 100:
        raise PihimInputError(f"exposure percentile must be in (0, 100], got {exposure_percentile!r}")
    head = _sigma("headroom", headroom)
    if exposure_pixels not in ("not-sun", "mirror-not-sun"):
        raise PihimInputError(f"exposure_pixels must be 'not-sun' or 'mirror-not-sun', got {exposure_pixels!r}")
    if head <= 0:
        raise PihimInputError(f"headroom must be > 0, got {headroom!r}")
    if not isinstance(site, Site):
        raise PihimInputError(f"site must be a Site, got {type(site).__name__}")
    _check_request(pose_request)
    if aim_point is None:
        aim_point = _plan_aim_point(Path(pose_request.plan_path)) if isinstance(pose_request, WaypointPose) else None
    aim = _point("aim point", UFACET_AIM_POINT if aim_point is None else aim_point)
    if aim[2] <= 0:
        raise PihimInputError(f"the aim point must be above the ground (z > 0), got z = {aim[2]:g}")
    if not hasattr(field, "names") or not hasattr(field, "pivots") or not hasattr(field, "spec"):
        raise PihimInputError(f"field must be a pihim.field.Field, got {type(field).__name__}")
    if isinstance(pose_request, PairPose):
        field.index(pose_request.hua)  # unknown names -> one-line error, before anything else
        field.index(pose_request.target)
    fixed = _fixed_drives(field, drive_deg)
    ts = parse_time(time)
    sun = sun_position(site, ts)
    if not float(sun.elevation_deg) > 0.0:
        raise PihimInputError(
            f"the sun is below the horizon at {ts.isoformat()} (elevation {float(sun.elevation_deg):.2f} deg); "
            "the field does not track at night"
        )
    env = Environment.clear_sky(sun.vector)

    # --- random streams: canting, tracking, logged pose, sensor noise
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(seed_i).spawn(4)]
    rng_cant, rng_track, rng_pose, rng_noise = streams

    # --- the field: commanded (logged) and true
    commanded = track_field(field, sun.vector, aim)
    n_h, n_f = commanded.facet_normals_local.shape[:2]
    cant_az = rng_cant.standard_normal((n_h, n_f)) * canting_sigma + 0.0
    cant_el = rng_cant.standard_normal((n_h, n_f)) * canting_sigma + 0.0
    facet_local = apply_canting_deviation(commanded.facet_normals_local, cant_az, cant_el)
    cmd = drive_angles(commanded.normals)
    cmd_az = _fold360(np.asarray(cmd.azimuth_deg, float))
    cmd_el = np.asarray(cmd.elevation_deg, float)
    if fixed:
        for i, (az_i, el_i) in fixed.items():
            cmd_az[i], cmd_el[i] = _fold360(az_i), el_i
        commanded = commanded.with_drive(cmd_az, cmd_el)
    err_az = rng_track.standard_normal(n_h) * tracking_sigma + 0.0
    err_el = rng_track.standard_normal(n_h) * tracking_sigma + 0.0
    true_az = _fold360(cmd_az + np.degrees(err_az * 1e-3))
    true_el = cmd_el + np.degrees(err_el * 1e-3)
    truth_field = commanded.with_drive(true_az, true_el)
    scene = field_scene(truth_field, facet_local)

    # --- the camera
    hua: str | None = None
    target: str | None = None
    req = pose_request
    if isinstance(req, PairPose):
        cam_pose, hua, target = _pair_pose(field, ts, site, aim, req)
    elif isinstance(req, WaypointPose):
        cam_pose = CameraPose.from_plan_json(req.plan_path, int(req.index))
        hua, target = _waypoint_pair(Path(req.plan_path), int(req.index))
        for name in (hua, target):  # a plan made for another field would log heliostats this frame does not show
            if name is not None:
                try:
                    field.index(name)
                except PihimInputError as exc:
                    raise PihimInputError(f"waypoint {req.index} of {req.plan_path}: {exc} (a plan for another "
                                          f"field?)") from None
    else:
        check_camera_distance(req.camera_m)  # before the pose's arithmetic overflows
        cam_pose = CameraPose.look_at(req.camera_m, req.look_at_m, float(req.roll_deg))
    _check_camera_position(np.asarray(cam_pose.position_m, float), truth_field, scene)

    # --- render and record
    rendered = render_frame(scene, camera, cam_pose, env, settings, progress=progress)
    labels = rendered.labels
    if exposure_pixels == "mirror-not-sun":
        mask = (labels[..., 0] == MIRROR) & (labels[..., 3] != SUN)
    else:
        mask = (labels[..., 0] != SUN) & (labels[..., 3] != SUN)
    exposure = choose_exposure(rendered.s0, rendered.s1, rendered.s2, sensor,
                               mask=mask if mask.any() else None, percentile=pct, headroom=head)
    raw = expose(rendered.s0, rendered.s1, rendered.s2, sensor, exposure, blur_sigma_px=blur, rng=rng_noise)
    logged, logged_angles = _logged_pose(cam_pose, gps_sigma, att_sigma, rng_pose)

    # --- log and truth
    seen = np.union1d(labels[..., 1].ravel(), labels[..., 4].ravel())
    in_view = [int(i) for i in seen if 0 <= i < n_h]
    names = tuple(field.names)
    log_helio = [{"name": names[i], "az_deg": float(cmd_az[i]), "el_deg": float(cmd_el[i])} for i in in_view]
    truth_helio = [
        {
            "name": names[i],
            "az_deg": float(true_az[i]),
            "el_deg": float(true_el[i]),
            "tracking_error_mrad": {"az": float(err_az[i]), "el": float(err_el[i])},
            "facets": [{"id": f + 1, "az_mrad": float(cant_az[i, f]), "el_mrad": float(cant_el[i, f])}
                       for f in range(n_f)],
        }
        for i in in_view
    ]
    if field_source is None:
        field_source = _default_field_source(field)
    gimbal = {"pitch_deg": logged_angles["pitch_deg"], "roll_deg": logged_angles["roll_deg"]}
    log = {
        "time": ts.isoformat(),
        "site": site.as_dict(),
        "camera": camera.to_dict(),
        "pose": _pose_dict(logged, site, logged_angles),
        "gps_sigma_m": gps_sigma,
        "attitude_sigma_deg": att_sigma,
        "gimbal": gimbal,
        "sensor": {"model": sensor.describe(), "exposure": exposure.describe(), "layout": str(sensor.layout)},
        "aim_point_m": [float(v) for v in aim],
        "field": {"source": field_source, "facets": facets_source, "heliostat_count": len(names)},
        "heliostats": log_helio,
        "hua": hua,
        "target": target,
        "sun": {"zenith_deg": float(sun.zenith_deg), "azimuth_deg": float(sun.azimuth_deg)},
    }
    render_stats = {k: v for k, v in rendered.stats.items() if "second" not in k}
    truth = {
        "pose": _pose_dict(cam_pose, site),
        "heliostats": truth_helio,
        "environment": env.describe(),
        "render": render_stats,
        "labels": {
            "channels": list(LABEL_CHANNELS),
            "kinds": {str(k): v for k, v in sorted(KIND_NAMES.items())},
            "heliostat_index": list(names),
        },
        "simulation": {
            "seed": seed_i,
            "canting_sigma_mrad": canting_sigma,
            "tracking_sigma_mrad": tracking_sigma,
            "gps_sigma_m": gps_sigma,
            "attitude_sigma_deg": att_sigma,
            "blur_sigma_px": blur,
            "exposure_percentile": pct,
            "headroom": head,
            "supersample": int(settings.supersample),
            "max_bounces": int(settings.max_bounces),
            "exposure_pixels": exposure_pixels if mask.any() else "all",
            "fixed_drive_deg": {names[i]: [float(a), float(e)] for i, (a, e) in fixed.items()},
        },
    }
    return SimulatedFrame(
        raw=raw,
        rendered=rendered,
        log=_jsonable(log),
        truth=_jsonable(truth),
        scene=scene,
        true_field=truth_field,
        commanded_field=commanded,
        facet_normals_local=facet_local,
        camera_pose=cam_pose,
        logged_pose=logged,
        exposure=exposure,
        seconds=_time.perf_counter() - t0,
    )


# --------------------------------------------------------------------------- output


def simulated_frame_paths(out_tiff_path: str | os.PathLike[str]) -> dict[str, Path]:
    """The files :func:`write_simulated_frame` writes for ``FRAME.tiff`` (or ``.tif``).

    Keys ``raw``, ``json``, ``S0``, ``DoLP``, ``AoP``, ``labels``.
    """
    out = Path(out_tiff_path)
    if out.suffix.lower() not in (".tif", ".tiff") or not out.stem:
        raise PihimInputError(f"the output must be a .tiff (or .tif) file name, got {str(out)!r}")
    stem = out.parent / out.stem
    return {
        "raw": out,
        "json": Path(f"{stem}.json"),
        "S0": Path(f"{stem}.S0{out.suffix}"),
        "DoLP": Path(f"{stem}.DoLP{out.suffix}"),
        "AoP": Path(f"{stem}.AoP{out.suffix}"),
        "labels": Path(f"{stem}.labels{out.suffix}"),
    }


def write_simulated_frame(sim: SimulatedFrame, out_tiff_path: str | os.PathLike[str]) -> dict[str, Path]:
    """Write a simulated frame: ``FRAME.tiff``, ``FRAME.json`` and the noise-free images beside them.

    * ``FRAME.tiff``: the raw uint16 mosaic (what ``pihim polar`` reads);
    * ``FRAME.json``: ``{"schema": "pihim.simulated-frame/1", "log", "truth"}``;
    * ``FRAME.S0.tiff``, ``FRAME.DoLP.tiff``, ``FRAME.AoP.tiff``: float32
      noise-free full-resolution images (AoP in deg in [0, 180), counter-
      clockwise from image right; DoLP NaN where S0 <= 0);
    * ``FRAME.labels.tiff``: int32 (H, W, 7) labels (channels in
      ``truth.labels.channels``).

    All six are written under temporary names and renamed only when every one
    is complete; if anything fails nothing is left (a file of the same name
    that existed before may then be gone).

    Returns
    -------
    dict of Path
        As :func:`simulated_frame_paths`.

    Raises
    ------
    OSError
        ``"cannot write FRAME.tiff: <reason>"`` when the files cannot be
        written (a full disk named as such); nothing of the frame is left.
    """
    paths = simulated_frame_paths(out_tiff_path)
    r = sim.rendered
    with np.errstate(invalid="ignore", divide="ignore"):
        images: dict[str, NDArray] = {
            "S0": np.asarray(r.s0, np.float32),
            "DoLP": np.asarray(dolp(r.s0.astype(np.float64), r.s1, r.s2), np.float32),
            "AoP": np.asarray(aop_deg(r.s1.astype(np.float64), r.s2), np.float32),
        }
    text = json.dumps(sim.document(), indent=2, allow_nan=False) + "\n"
    keys = list(paths)
    try:
        # pid-named temporaries (pihim._atomic): the next run removes those a killed run left
        with atomic_group([paths[k] for k in keys]) as tmp_list:
            tmps = dict(zip(keys, tmp_list, strict=True))
            tifffile.imwrite(tmps["raw"], np.ascontiguousarray(sim.raw, dtype=np.uint16))
            tmps["json"].write_text(text, encoding="utf-8")
            for key, img in images.items():
                tifffile.imwrite(tmps[key], np.ascontiguousarray(img))
            # labels are piecewise constant: deflate shrinks them ~100x (140 MB -> ~1 MB for a full frame)
            tifffile.imwrite(tmps["labels"], np.ascontiguousarray(r.labels, dtype=np.int32),
                             photometric="minisblack", planarconfig="contig", compression="zlib")
    except OSError as exc:  # an operating-system error, not bad input: the CLI exits 1
        raise OSError(f"cannot write {paths['raw']}: {describe_os_error(exc)}") from None
    return paths
