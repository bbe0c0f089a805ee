"""Camera poses from autopilot logs: PX4 ULog, ArduPilot DataFlash and plain ``frames.csv``.

A flight records frames (a frame id, a file and the UTC time of mid-exposure)
and, separately, the vehicle's position and attitude and the gimbal's angles
at their own rates. :func:`match_frames` gives each frame its camera pose:

* **position**: the log's WGS84 fixes (latitude, longitude, *ellipsoidal*
  height) converted exactly to the field frame
  (:func:`pihim.field.geodesy.geodetic_to_enu`) and interpolated linearly in
  time;
* **attitude**: the vehicle's attitude quaternions interpolated by spherical
  linear interpolation (:class:`scipy.spatial.transform.Slerp`);
* **gimbal**: the gimbal's rotation (slerp as well) composed with the
  vehicle's attitude according to how the gimbal reports its angles
  (:data:`GIMBAL_MODES`);
* frames before the first or after the last sample of a stream, or in a gap
  between samples longer than ``max_gap_s``, are **reported** with the
  reason and given no pose: nothing is extrapolated.

Rotations follow the aerospace conventions: the vehicle body frame is FRD
(x forward, y right, z down), the local level frame NED, and the attitude is
the rotation body -> NED, ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (yaw clockwise
from North, pitch nose up, roll right wing down). The camera looks along the
x axis of the gimbal frame with image right along its y axis and image down
along its z axis, so with every angle zero the camera looks forward,
upright. The resulting :class:`~pihim.camera.pose.CameraPose` has exactly the
heading / pitch / roll of ``docs/conventions.md``: a camera rotation
``Rz(h) Ry(p) Rx(r)`` gives ``CameraPose.from_attitude(C, h, p, r)``.

Log formats (what is read):

* **PX4 ULog** (read with pyulog [1]_): ``vehicle_global_position``
  (``lat``, ``lon`` in deg, ``alt_ellipsoid`` or ``alt`` AMSL in m) or
  ``vehicle_gps_position`` / ``sensor_gps`` (``lat``/``lon`` 1e-7 deg and
  ``alt_ellipsoid``/``alt`` mm, or ``latitude_deg``/``longitude_deg`` and
  ``altitude_ellipsoid_m``/``altitude_msl_m``); ``vehicle_attitude.q``
  (Hamilton ``w, x, y, z``, body FRD -> NED); optionally
  ``gimbal_device_attitude_status.q`` with ``device_flags`` (MAVLink gimbal
  protocol v2: roll and pitch relative to the horizon, yaw relative to the
  vehicle unless the yaw-lock / earth-frame flags say otherwise). Log time
  (microseconds since boot) is tied to UTC by the GPS topic's
  ``time_utc_usec``.
* **ArduPilot DataFlash** ``.bin`` (read with pymavlink's ``DFReader`` [2]_):
  ``GPS`` (``GMS``, ``GWk``, ``Lat``, ``Lng``, ``Alt`` above mean sea level),
  ``ATT`` (``Roll``, ``Pitch``, ``Yaw``, deg) and optionally ``MNT``
  (``Roll``, ``Pitch`` earth frame and ``YawB`` relative to the vehicle, or
  ``YawE`` earth frame). GPS week and milliseconds are GPS time, UTC = GPS -
  leap seconds (:func:`gps_to_utc`). The heights are above mean sea level,
  so the geoid undulation must be given (ellipsoidal = AMSL + undulation).
* **frames.csv**: one row per frame, :data:`FRAMES_CSV_COLUMNS`; the pose
  columns may be left out (or empty) when a log gives the poses.

Writers for all three (:func:`write_ulog`, :func:`write_dataflash`,
:func:`write_frames_csv`) follow the published byte layouts (ULog file format
of PX4 [3]_; ArduPilot's DataFlash ``FMT`` records) and are what
``pihim simulate-flight`` writes; the tests read them back with the
libraries' own readers.

References
----------
.. [1] PX4, pyulog: https://github.com/PX4/pyulog
.. [2] ArduPilot, pymavlink ``DFReader``: https://github.com/ArduPilot/pymavlink
.. [3] PX4 User Guide, "ULog File Format" (dev_log/ulog_file_format).
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
import os
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field as _dc_field
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.camera.pose import CameraPose
from pihim.errors import PihimInputError

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

__all__ = [
    "FRAMES_CSV_COLUMNS",
    "GIMBAL_MODES",
    "FrameMatch",
    "FrameRecord",
    "PoseTrack",
    "camera_pose_from_attitude",
    "camera_rotation",
    "gps_to_utc",
    "match_frames",
    "read_dataflash",
    "read_frames_csv",
    "read_log",
    "read_ulog",
    "utc_to_gps",
    "write_dataflash",
    "write_frames_csv",
    "write_ulog",
]

GimbalMode = Literal["body", "stabilized", "earth"]

#: How gimbal angles are referenced:
#: ``body`` -- relative to the airframe; camera rotation = vehicle attitude x gimbal rotation;
#: ``stabilized`` -- roll and pitch relative to the horizon, yaw relative to the vehicle's heading;
#: camera rotation = Rz(vehicle yaw) x gimbal rotation;
#: ``earth`` -- all three relative to the local level frame (yaw from North): camera rotation = gimbal rotation.
GIMBAL_MODES: tuple[str, ...] = ("body", "stabilized", "earth")

#: Columns of ``frames.csv``: the first three are required; the pose columns all or none;
#: ``gimbal_roll_deg`` optional (default 0).
FRAMES_CSV_COLUMNS: tuple[str, ...] = (
    "frame_id", "file", "time_utc",
    "latitude_deg", "longitude_deg", "height_m",
    "roll_deg", "pitch_deg", "yaw_deg",
    "gimbal_pitch_deg", "gimbal_yaw_deg",
)
_POSE_COLUMNS = FRAMES_CSV_COLUMNS[3:]

#: Largest gap between two samples of a stream a frame may fall into, seconds.
DEFAULT_MAX_GAP_S = 1.0

#: GPS - UTC (leap seconds) since the given UTC instants (IERS Bulletin C).
_LEAP_SECONDS: tuple[tuple[float, int], ...] = (
    (datetime(2012, 7, 1, tzinfo=timezone.utc).timestamp(), 16),
    (datetime(2015, 7, 1, tzinfo=timezone.utc).timestamp(), 17),
    (datetime(2017, 1, 1, tzinfo=timezone.utc).timestamp(), 18),
)
_GPS_EPOCH = datetime(1980, 1, 6, tzinfo=timezone.utc).timestamp()
_WEEK_S = 7 * 86400


# --------------------------------------------------------------------------- time


def parse_utc(text: str, *, what: str = "time") -> float:
    """An ISO 8601 date-time with a UTC offset (``Z`` allowed) to seconds since the Unix epoch."""
    s = str(text).strip()
    try:
        dt = datetime.fromisoformat(s)
    except ValueError:
        raise PihimInputError(f"{what} {text!r} is not an ISO 8601 date-time (e.g. 2021-05-13T19:00:00.125Z)") from None
    if dt.tzinfo is None:
        raise PihimInputError(f"{what} {text!r} has no UTC offset; write it as UTC with 'Z' or an offset")
    return dt.timestamp()


def format_utc(t: float) -> str:
    """Seconds since the Unix epoch as ISO 8601 UTC with microseconds (``...Z``)."""
    us = int(round(float(t) * 1e6))
    dt = datetime.fromtimestamp(us // 1_000_000, tz=timezone.utc).replace(microsecond=us % 1_000_000)
    return dt.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _leap(utc_s: float) -> int:
    n = 0
    for since, leap in _LEAP_SECONDS:
        if utc_s >= since:
            n = leap
    if n == 0:
        raise PihimInputError(f"GPS time before 2012-07-01 ({format_utc(utc_s)}) is not supported")
    return n


def gps_to_utc(week: ArrayLike, ms_of_week: ArrayLike) -> NDArray[np.float64]:
    """GPS week and milliseconds of week to UTC seconds since the Unix epoch (leap seconds removed).

    Raises
    ------
    PihimInputError
        A week or millisecond count that is not finite, negative, or (the
        milliseconds) a week or more.
    """
    w, ms = np.asarray(week, float), np.asarray(ms_of_week, float)
    if not (np.all(np.isfinite(w)) and np.all(np.isfinite(ms))):
        raise PihimInputError("GPS week and milliseconds of week must be finite numbers")
    if np.any(w < 0) or np.any(ms < 0) or np.any(ms >= _WEEK_S * 1e3):
        raise PihimInputError(f"GPS week must be >= 0 and milliseconds of week in [0, {_WEEK_S * 1e3:.0f})")
    gps = _GPS_EPOCH + w * _WEEK_S + ms * 1e-3
    approx = np.atleast_1d(gps)
    leaps = np.array([_leap(float(t) - 18.0) for t in approx])
    return (approx - leaps).reshape(np.shape(gps))


def utc_to_gps(utc_s: float) -> tuple[int, int]:
    """UTC seconds since the Unix epoch to ``(GPS week, milliseconds of week)`` (inverse of :func:`gps_to_utc`)."""
    if not math.isfinite(float(utc_s)):
        raise PihimInputError(f"UTC time must be a finite number of seconds, got {utc_s!r}")
    g = float(utc_s) + _leap(float(utc_s)) - _GPS_EPOCH
    week = int(g // _WEEK_S)
    ms = int(round((g - week * _WEEK_S) * 1e3))
    if ms >= int(_WEEK_S * 1000):  # rounded up to the next week's first millisecond
        week, ms = week + 1, ms - int(_WEEK_S * 1000)
    return week, ms


# --------------------------------------------------------------------------- rotations


def _rotation():  # noqa: ANN202 - scipy imported where used
    from scipy.spatial.transform import Rotation

    return Rotation


def _euler(yaw_deg: ArrayLike, pitch_deg: ArrayLike, roll_deg: ArrayLike) -> Rotation:
    """``Rz(yaw) Ry(pitch) Rx(roll)`` (intrinsic Z-Y'-X''), degrees."""
    angles = np.stack(np.broadcast_arrays(*(np.asarray(a, float) for a in (yaw_deg, pitch_deg, roll_deg))), axis=-1)
    return _rotation().from_euler("ZYX", angles, degrees=True)


def camera_rotation(vehicle: Rotation, gimbal: Rotation, mode: str) -> Rotation:
    """The camera's rotation (camera frame -> NED) composed from the vehicle's and the gimbal's.

    Parameters
    ----------
    vehicle : scipy Rotation
        Vehicle attitude, body FRD -> NED.
    gimbal : scipy Rotation
        The gimbal's rotation as it reports it, ``Rz(yaw) Ry(pitch) Rx(roll)``
        of its angles.
    mode : {"body", "stabilized", "earth"}
        See :data:`GIMBAL_MODES`.
    """
    if mode == "body":
        return vehicle * gimbal
    if mode == "stabilized":
        yaw = vehicle.as_euler("ZYX", degrees=True)[..., 0]
        return _euler(yaw, 0.0, 0.0) * gimbal
    if mode == "earth":
        return gimbal
    raise PihimInputError(f"gimbal mode must be one of {', '.join(GIMBAL_MODES)}, got {mode!r}")


def _pose_from_ned(position_enu: NDArray[np.float64], rot: Rotation) -> CameraPose:
    """A :class:`CameraPose` from the camera -> NED rotation (camera x forward, y right, z down)."""
    m = rot.as_matrix()
    ned_to_enu = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    forward, right, down = (ned_to_enu @ m[:, k] for k in range(3))
    # re-orthonormalise the float noise of the matrix product (CameraPose checks to 1e-9)
    u, _, vt = np.linalg.svd(np.array([right, down, forward]))
    return CameraPose(position_enu, u @ vt)


def camera_pose_from_attitude(position_enu: ArrayLike, roll_deg: float, pitch_deg: float, yaw_deg: float,
                              gimbal_pitch_deg: float = 0.0, gimbal_yaw_deg: float = 0.0,
                              gimbal_roll_deg: float = 0.0, mode: str = "body") -> CameraPose:
    """The camera pose of a vehicle attitude and gimbal angles (degrees; see the module notes).

    With ``mode="earth"`` the vehicle's angles do not enter; with
    ``"stabilized"`` only its yaw does.
    """
    angles = (roll_deg, pitch_deg, yaw_deg, gimbal_pitch_deg, gimbal_yaw_deg, gimbal_roll_deg)
    if not all(np.all(np.isfinite(np.asarray(a, float))) for a in angles):  # scipy said "zero norm quaternions"
        raise PihimInputError("attitude and gimbal angles must be finite numbers of degrees")
    rot = camera_rotation(_euler(yaw_deg, pitch_deg, roll_deg), _euler(gimbal_yaw_deg, gimbal_pitch_deg,
                                                                        gimbal_roll_deg), mode)
    return _pose_from_ned(np.asarray(position_enu, float), rot)


# --------------------------------------------------------------------------- frames.csv


@dataclass(frozen=True)
class FrameRecord:
    """One frame of a flight: id, file (relative to the flight directory) and UTC mid-exposure time.

    ``pose`` holds the ``frames.csv`` pose columns (:data:`FRAMES_CSV_COLUMNS`
    3 onward, plus ``gimbal_roll_deg``) when the file has them.
    """

    frame_id: str
    file: str
    time_utc_s: float
    pose: Mapping[str, float] | None = None


def _float_cell(row: Mapping[str, str], key: str, where: str) -> float:
    try:
        v = float(row[key])
    except (TypeError, ValueError):
        raise PihimInputError(f"{where}: column {key} is not a number ({row.get(key)!r})") from None
    if not math.isfinite(v):
        raise PihimInputError(f"{where}: column {key} is not finite")
    return v


def read_frames_csv(path: str | os.PathLike[str]) -> list[FrameRecord]:
    """Read a ``frames.csv`` (:data:`FRAMES_CSV_COLUMNS`), checking every row.

    Raises
    ------
    PihimInputError
        Missing columns, duplicate frame ids, a bad time (no UTC offset),
        non-numeric or non-finite pose cells, pose columns filled in some
        rows and empty in others, times not increasing.
    """
    from pihim._inputs import read_text_file

    p = Path(path)
    text = read_text_file(p, "frames.csv")
    reader = csv.DictReader(io.StringIO(text))
    cols = [c.strip() for c in (reader.fieldnames or [])]
    reader.fieldnames = cols
    missing = [c for c in FRAMES_CSV_COLUMNS[:3] if c not in cols]
    if missing:
        raise PihimInputError(f"{p}: not a frames.csv (no column {', '.join(missing)}; "
                              f"expected {','.join(FRAMES_CSV_COLUMNS)})")
    have_pose = [c for c in _POSE_COLUMNS if c in cols]
    if have_pose and len(have_pose) != len(_POSE_COLUMNS):
        absent = [c for c in _POSE_COLUMNS if c not in cols]
        raise PihimInputError(f"{p}: pose columns must be all present or all absent (missing {', '.join(absent)})")
    out: list[FrameRecord] = []
    seen: set[str] = set()
    with_pose = None
    for k, row in enumerate(reader, start=2):
        where = f"{p}:{k}"
        fid = (row.get("frame_id") or "").strip()
        file = (row.get("file") or "").strip()
        if not fid or not file:
            raise PihimInputError(f"{where}: frame_id and file must not be empty")
        if fid in seen:
            raise PihimInputError(f"{where}: duplicate frame_id {fid!r}")
        seen.add(fid)
        t = parse_utc(row.get("time_utc") or "", what=f"{where}: time_utc")
        pose = None
        if have_pose:
            filled = [bool((row.get(c) or "").strip()) for c in _POSE_COLUMNS]
            if any(filled) and not all(filled):
                raise PihimInputError(f"{where}: pose columns partly empty")
            if all(filled):
                pose = {c: _float_cell(row, c, where) for c in _POSE_COLUMNS}
                if (row.get("gimbal_roll_deg") or "").strip():
                    pose["gimbal_roll_deg"] = _float_cell(row, "gimbal_roll_deg", where)
                if abs(pose["latitude_deg"]) > 90:
                    raise PihimInputError(f"{where}: latitude_deg outside [-90, 90]")
            if with_pose is None:
                with_pose = pose is not None
            elif with_pose != (pose is not None):
                raise PihimInputError(f"{where}: pose columns filled in some rows and empty in others")
        out.append(FrameRecord(fid, file, t, pose))
    if not out:
        raise PihimInputError(f"{p}: no frames")
    return out


def write_frames_csv(path: str | os.PathLike[str], frames: Sequence[FrameRecord]) -> Path:
    """Write ``frames.csv`` atomically (pose columns when every frame has a pose)."""
    from pihim._atomic import write_text_atomic

    with_pose = bool(frames) and all(f.pose is not None for f in frames)
    cols = list(FRAMES_CSV_COLUMNS if with_pose else FRAMES_CSV_COLUMNS[:3])
    if with_pose and any("gimbal_roll_deg" in (f.pose or {}) for f in frames):
        cols.append("gimbal_roll_deg")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for f in frames:
        row: list[Any] = [f.frame_id, f.file, format_utc(f.time_utc_s)]
        if with_pose:
            assert f.pose is not None
            row += [repr(float(f.pose.get(c, 0.0))) for c in cols[3:]]
        w.writerow(row)
    return write_text_atomic(path, buf.getvalue())


# --------------------------------------------------------------------------- tracks


@dataclass(frozen=True, eq=False)
class PoseTrack:
    """Vehicle position, attitude and gimbal as logged, on UTC time axes (seconds since the Unix epoch).

    Attributes
    ----------
    source : str
        ``"ulog"``, ``"dataflash"``.
    position_t : ndarray, shape (N,)
    latitude_deg, longitude_deg, height_m : ndarray, shape (N,)
        WGS84, **ellipsoidal** height.
    attitude_t : ndarray, shape (M,)
    attitude : scipy Rotation of length M
        Vehicle body FRD -> NED.
    gimbal_t : ndarray, shape (K,) or None
    gimbal : scipy Rotation of length K, or None
        The gimbal's reported rotation; None: a fixed mount (``fixed_gimbal_deg``).
    gimbal_mode : str
        See :data:`GIMBAL_MODES`.
    fixed_gimbal_deg : tuple of float
        ``(pitch, yaw, roll)`` of a fixed mount, body mode, used when the log
        has no gimbal stream.
    notes : tuple of str
    """

    source: str
    position_t: NDArray[np.float64]
    latitude_deg: NDArray[np.float64]
    longitude_deg: NDArray[np.float64]
    height_m: NDArray[np.float64]
    attitude_t: NDArray[np.float64]
    attitude: Any
    gimbal_t: NDArray[np.float64] | None = None
    gimbal: Any = None
    gimbal_mode: str = "body"
    fixed_gimbal_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    notes: tuple[str, ...] = _dc_field(default_factory=tuple)

    def span(self) -> tuple[float, float]:
        """The time interval every stream covers (UTC seconds)."""
        starts = [self.position_t[0], self.attitude_t[0]]
        ends = [self.position_t[-1], self.attitude_t[-1]]
        if self.gimbal_t is not None:
            starts.append(self.gimbal_t[0])
            ends.append(self.gimbal_t[-1])
        return float(max(starts)), float(min(ends))


@dataclass(frozen=True)
class FrameMatch:
    """A frame with its camera pose, or the reason it has none (``pose`` None)."""

    frame: FrameRecord
    pose: CameraPose | None
    reason: str | None = None

    @property
    def ok(self) -> bool:
        return self.pose is not None


def _sorted_stream(t: NDArray, what: str, path: Path, *arrays: NDArray) -> tuple[NDArray, ...]:
    """Drop non-finite rows, sort by time and drop repeated times; refuse an empty stream."""
    t = np.asarray(t, float)
    keep = np.isfinite(t)
    for a in arrays:
        a2 = np.asarray(a, float).reshape(len(t), -1)
        keep &= np.all(np.isfinite(a2), axis=1)
    if keep.sum() < 2:
        raise PihimInputError(f"{path}: the log has fewer than two valid {what} samples")
    order = np.argsort(t[keep], kind="stable")
    ts = t[keep][order]
    uniq = np.concatenate([[True], np.diff(ts) > 0])
    return (ts[uniq], *(np.asarray(a)[keep][order][uniq] for a in arrays))


def _quiet() -> contextlib.AbstractContextManager[Any]:
    """Silence readers that print to stdout (stdout is kept for JSON)."""
    return contextlib.redirect_stdout(io.StringIO())


def _need_undulation(geoid_undulation_m: float | None, path: Path, what: str) -> float:
    if geoid_undulation_m is None:
        raise PihimInputError(f"{path}: the log gives {what} heights above mean sea level only; give the geoid "
                              "undulation (flight.json geoid_undulation_m) to make them ellipsoidal")
    u = float(geoid_undulation_m)
    if not math.isfinite(u) or abs(u) > 150:
        raise PihimInputError(f"geoid undulation must be finite and within +-150 m, got {geoid_undulation_m!r}")
    return u


# --------------------------------------------------------------------------- ULog


def read_ulog(path: str | os.PathLike[str], *, geoid_undulation_m: float | None = None,
              fixed_gimbal_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> PoseTrack:
    """Read the pose streams of a PX4 ULog (module notes) with pyulog.

    Raises
    ------
    PihimInputError
        Not a ULog, a corrupt or truncated file, no position, attitude or GPS
        time topic, heights above mean sea level without ``geoid_undulation_m``.
    """
    from pihim._inputs import check_regular_file

    p = Path(path)
    check_regular_file(p, "ULog file")
    try:
        from pyulog import ULog
    except ImportError:  # pragma: no cover - optional extra
        raise PihimInputError("reading a PX4 ULog needs pyulog: pip install 'pihim[campaign]'") from None
    topics = ["vehicle_global_position", "vehicle_gps_position", "sensor_gps", "vehicle_attitude",
              "gimbal_device_attitude_status"]
    try:
        with _quiet():
            ulog = ULog(str(p), topics)
    except Exception as exc:  # noqa: BLE001 - any parser failure is a bad file
        raise PihimInputError(f"{p}: not a readable PX4 ULog ({' '.join(str(exc).split()) or type(exc).__name__})") from None
    if ulog.file_corruption:
        raise PihimInputError(f"{p}: the ULog is corrupt (pyulog found damaged or truncated messages)")
    cut = _ulog_cut(p)
    if cut is not None:
        raise PihimInputError(f"{p}: the ULog is truncated ({cut})")
    data = {d.name: d.data for d in ulog.data_list if d.multi_id == 0}

    gps = data.get("vehicle_gps_position") or data.get("sensor_gps")
    if gps is None or "time_utc_usec" not in gps:
        raise PihimInputError(f"{p}: no GPS topic with time_utc_usec (vehicle_gps_position or sensor_gps): "
                              "cannot tie log time to UTC")
    ok = np.asarray(gps["time_utc_usec"], float) > 0
    if not ok.any():
        raise PihimInputError(f"{p}: the GPS topic never has a UTC time (no fix)")
    offsets = np.asarray(gps["time_utc_usec"], float)[ok] - np.asarray(gps["timestamp"], float)[ok]
    offset_s = float(np.median(offsets)) * 1e-6
    notes = [f"log time tied to UTC by {ok.sum()} GPS samples (spread {np.ptp(offsets) * 1e-3:.3f} ms)"]

    def utc(d: Mapping[str, NDArray]) -> NDArray[np.float64]:
        return np.asarray(d["timestamp"], float) * 1e-6 + offset_s

    gpos = data.get("vehicle_global_position")
    if gpos is not None and "lat" in gpos:
        lat, lon = np.asarray(gpos["lat"], float), np.asarray(gpos["lon"], float)
        if "alt_ellipsoid" in gpos:
            h = np.asarray(gpos["alt_ellipsoid"], float)
        else:
            h = np.asarray(gpos["alt"], float) + _need_undulation(geoid_undulation_m, p, "vehicle_global_position")
        pt = utc(gpos)
        notes.append("position from vehicle_global_position")
    else:
        if "latitude_deg" in gps:
            lat, lon = np.asarray(gps["latitude_deg"], float), np.asarray(gps["longitude_deg"], float)
            h = (np.asarray(gps["altitude_ellipsoid_m"], float) if "altitude_ellipsoid_m" in gps else
                 np.asarray(gps["altitude_msl_m"], float) + _need_undulation(geoid_undulation_m, p, "GPS"))
        elif "lat" in gps:
            lat, lon = np.asarray(gps["lat"], float) * 1e-7, np.asarray(gps["lon"], float) * 1e-7
            h = (np.asarray(gps["alt_ellipsoid"], float) * 1e-3 if "alt_ellipsoid" in gps else
                 np.asarray(gps["alt"], float) * 1e-3 + _need_undulation(geoid_undulation_m, p, "GPS"))
        else:
            raise PihimInputError(f"{p}: the GPS topic has no latitude and longitude fields")
        pt = utc(gps)
        notes.append("position from the GPS topic")
    pt, lat, lon, h = _sorted_stream(pt, "position", p, lat, lon, h)

    att = data.get("vehicle_attitude")
    if att is None or "q[0]" not in att:
        raise PihimInputError(f"{p}: no vehicle_attitude topic with q")
    q = np.stack([np.asarray(att[f"q[{i}]"], float) for i in (1, 2, 3, 0)], axis=1)  # scipy: x, y, z, w
    at, q = _sorted_stream(utc(att), "attitude", p, q)
    if np.any(np.linalg.norm(q, axis=1) < 0.5):
        raise PihimInputError(f"{p}: vehicle_attitude has quaternions far from unit length")
    R = _rotation()
    attitude = R.from_quat(q)

    gim = data.get("gimbal_device_attitude_status")
    gt = gimbal = None
    mode = "body"
    if gim is not None and "q[0]" in gim:
        gq = np.stack([np.asarray(gim[f"q[{i}]"], float) for i in (1, 2, 3, 0)], axis=1)
        gt, gq = _sorted_stream(utc(gim), "gimbal", p, gq)
        gimbal = R.from_quat(gq)
        flags = int(np.asarray(gim.get("device_flags", [0]))[-1])
        earth = bool(flags & (16 | 64)) and not flags & 32  # YAW_LOCK or YAW_IN_EARTH_FRAME, not IN_VEHICLE
        mode = "earth" if earth else "stabilized"
        notes.append(f"gimbal from gimbal_device_attitude_status ({mode} yaw)")
    return PoseTrack("ulog", pt, lat, lon, h, at, attitude, gt, gimbal, mode,
                     tuple(float(v) for v in fixed_gimbal_deg), tuple(notes))  # type: ignore[arg-type]


def _ulog_cut(path: Path) -> str | None:
    """Why the ULog's messages do not end exactly at the end of the file (None if they do).

    Every ULog message starts with its payload size, so a file cut short (a
    log copied while being written, a partial download) ends inside a message;
    pyulog drops such a message silently.
    """
    data = path.read_bytes()
    n = len(data)
    pos = 16
    while pos + 3 <= n:
        size = data[pos] | (data[pos + 1] << 8)
        pos += 3 + size
    if pos != n:
        return f"the last message needs {pos - n} more bytes" if pos > n else f"{n - pos} stray bytes at the end"
    return None


class _ULogWriter:
    """Minimal ULog (version 1) writer: file header, flag bits, formats, info, subscriptions and data."""

    _TYPES = {"uint64_t": "Q", "int64_t": "q", "uint32_t": "I", "int32_t": "i", "uint16_t": "H", "int16_t": "h",
              "uint8_t": "B", "int8_t": "b", "float": "f", "double": "d", "bool": "?"}

    def __init__(self, start_us: int) -> None:
        self.buf = bytearray(b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", start_us))
        self._msg(b"B", bytes(16) + struct.pack("<3Q", 0, 0, 0))
        self.formats: dict[str, list[tuple[str, str, int]]] = {}
        self.ids: dict[str, int] = {}

    def _msg(self, kind: bytes, payload: bytes) -> None:
        if len(payload) > 0xFFFF:
            raise ValueError("ULog message too long")
        self.buf += struct.pack("<HB", len(payload), kind[0]) + payload

    def info(self, key: str, value: str) -> None:
        v = value.encode()
        k = f"char[{len(v)}] {key}".encode()
        self._msg(b"I", bytes([len(k)]) + k + v)

    def fmt(self, name: str, fields: Sequence[tuple[str, str]]) -> None:
        """``fields``: (type, name), arrays as ``float[4]``; the first must be ``uint64_t timestamp``."""
        text = name + ":" + "".join(f"{t} {n};" for t, n in fields)
        self._msg(b"F", text.encode())
        parsed = []
        for t, n in fields:
            base, _, count = t.partition("[")
            parsed.append((base, n, int(count.rstrip("]")) if count else 1))
        self.formats[name] = parsed

    def subscribe(self, name: str) -> int:
        msg_id = len(self.ids)
        self.ids[name] = msg_id
        self._msg(b"A", struct.pack("<BH", 0, msg_id) + name.encode())
        return msg_id

    def data(self, name: str, values: Mapping[str, Any]) -> None:
        payload = bytearray(struct.pack("<H", self.ids[name]))
        for base, n, count in self.formats[name]:
            code = self._TYPES[base]
            v = values[n]
            payload += struct.pack("<" + code * count, *(v if count > 1 else [v]))
        self._msg(b"D", bytes(payload))


def write_ulog(path: str | os.PathLike[str], *, boot_utc_s: float, position: Mapping[str, ArrayLike],
               attitude: Mapping[str, ArrayLike], gimbal: Mapping[str, ArrayLike] | None = None,
               gimbal_earth_yaw: bool = False) -> Path:
    """Write a small PX4-style ULog with the topics :func:`read_ulog` reads (atomically).

    Parameters
    ----------
    path : path-like
    boot_utc_s : float
        UTC of log time zero (seconds since the Unix epoch).
    position : mapping
        ``t`` (UTC s), ``latitude_deg``, ``longitude_deg``, ``height_m``
        (ellipsoidal): written as ``vehicle_global_position`` and as
        ``vehicle_gps_position`` (1e-7 deg, mm, with ``time_utc_usec``).
    attitude : mapping
        ``t`` (UTC s) and ``quat`` (N, 4) scipy order ``x, y, z, w``, body FRD -> NED.
    gimbal : mapping, optional
        ``t`` and ``quat`` (MAVLink gimbal v2 rotation).
    gimbal_earth_yaw : bool
        Set the YAW_IN_EARTH_FRAME flag (else YAW_IN_VEHICLE_FRAME).
    """
    from pihim._atomic import write_atomic

    def us(t: ArrayLike) -> NDArray[np.int64]:
        return np.round((np.asarray(t, float) - boot_utc_s) * 1e6).astype(np.int64)

    w = _ULogWriter(0)
    w.fmt("vehicle_global_position", [("uint64_t", "timestamp"), ("double", "lat"), ("double", "lon"),
                                      ("float", "alt"), ("float", "alt_ellipsoid")])
    w.fmt("vehicle_gps_position", [("uint64_t", "timestamp"), ("uint64_t", "time_utc_usec"), ("int32_t", "lat"),
                                   ("int32_t", "lon"), ("int32_t", "alt"), ("int32_t", "alt_ellipsoid"),
                                   ("uint8_t", "fix_type")])
    w.fmt("vehicle_attitude", [("uint64_t", "timestamp"), ("float[4]", "q")])
    if gimbal is not None:
        w.fmt("gimbal_device_attitude_status", [("uint64_t", "timestamp"), ("uint16_t", "device_flags"),
                                                ("float[4]", "q")])
    w.info("sys_name", "PX4")
    w.info("ver_hw", "PIHIM_SIMULATED")
    for name in w.formats:
        w.subscribe(name)
    items: list[tuple[int, int, str, dict[str, Any]]] = []
    pt = us(position["t"])
    lat, lon, h = (np.asarray(position[k], float) for k in ("latitude_deg", "longitude_deg", "height_m"))
    for k in range(len(pt)):
        items.append((int(pt[k]), 0, "vehicle_global_position",
                      {"timestamp": int(pt[k]), "lat": lat[k], "lon": lon[k], "alt": h[k], "alt_ellipsoid": h[k]}))
        items.append((int(pt[k]), 1, "vehicle_gps_position",
                      {"timestamp": int(pt[k]), "time_utc_usec": int(pt[k]) + int(round(boot_utc_s * 1e6)),
                       "lat": int(round(lat[k] * 1e7)), "lon": int(round(lon[k] * 1e7)),
                       "alt": int(round(h[k] * 1e3)), "alt_ellipsoid": int(round(h[k] * 1e3)), "fix_type": 3}))
    at = us(attitude["t"])
    q = np.asarray(attitude["quat"], float)
    for k in range(len(at)):
        items.append((int(at[k]), 2, "vehicle_attitude",
                      {"timestamp": int(at[k]), "q": [q[k, 3], q[k, 0], q[k, 1], q[k, 2]]}))
    if gimbal is not None:
        gt = us(gimbal["t"])
        gq = np.asarray(gimbal["quat"], float)
        flags = 64 if gimbal_earth_yaw else 32
        for k in range(len(gt)):
            items.append((int(gt[k]), 3, "gimbal_device_attitude_status",
                          {"timestamp": int(gt[k]), "device_flags": flags,
                           "q": [gq[k, 3], gq[k, 0], gq[k, 1], gq[k, 2]]}))
    items.sort(key=lambda it: (it[0], it[1]))
    for _, _, name, values in items:
        w.data(name, values)
    blob = bytes(w.buf)
    return write_atomic(path, lambda tmp: tmp.write_bytes(blob))


# --------------------------------------------------------------------------- DataFlash


def read_dataflash(path: str | os.PathLike[str], *, geoid_undulation_m: float | None,
                   fixed_gimbal_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> PoseTrack:
    """Read the pose streams of an ArduPilot DataFlash ``.bin`` log (module notes) with pymavlink.

    Raises
    ------
    PihimInputError
        Not a DataFlash log, no GPS with a fix or no ATT messages, no geoid
        undulation (GPS heights are above mean sea level).
    """
    from pihim._inputs import check_regular_file

    p = Path(path)
    st = check_regular_file(p, "DataFlash log")
    with open(p, "rb") as fh:
        head = fh.read(3)
    if st.st_size < 3 or head[:2] != b"\xa3\x95":
        raise PihimInputError(f"{p}: not an ArduPilot DataFlash .bin log (no 0xA3 0x95 message header)")
    damage = _dataflash_damage(p)
    if damage is not None:
        raise PihimInputError(f"{p}: the DataFlash log is {damage}")
    try:
        from pymavlink import DFReader
    except ImportError:  # pragma: no cover - optional
        raise PihimInputError("reading a DataFlash log needs pymavlink: pip install pymavlink") from None
    rows: dict[str, list[dict[str, Any]]] = {"GPS": [], "ATT": [], "MNT": []}
    try:
        with _quiet():
            reader = DFReader.DFReader_binary(str(p), zero_time_base=True)
            while True:
                m = reader.recv_match(type=["GPS", "ATT", "MNT"])
                if m is None:
                    break
                rows[m.get_type()].append(m.to_dict())
    except Exception as exc:  # noqa: BLE001 - any parser failure is a bad file
        raise PihimInputError(f"{p}: not a readable DataFlash log ({' '.join(str(exc).split()) or type(exc).__name__})") from None
    gps = [r for r in rows["GPS"] if r.get("Status", 0) >= 3 and r.get("GWk", 0) > 0]
    if not gps:
        raise PihimInputError(f"{p}: no GPS messages with a 3-D fix and GPS time (GPS.Status >= 3, GWk > 0)")
    if not rows["ATT"]:
        raise PihimInputError(f"{p}: no ATT (attitude) messages")
    try:
        g_us = np.array([r["TimeUS"] for r in gps], float)
        g_utc = gps_to_utc([r["GWk"] for r in gps], [r["GMS"] for r in gps])
        lat = np.array([r["Lat"] for r in gps], float)
        lon = np.array([r["Lng"] for r in gps], float)
        alt = np.array([r["Alt"] for r in gps], float)
        a_us = np.array([r["TimeUS"] for r in rows["ATT"]], float)
        att = np.array([[r["Yaw"], r["Pitch"], r["Roll"]] for r in rows["ATT"]], float)
    except KeyError as exc:
        raise PihimInputError(f"{p}: DataFlash GPS/ATT messages lack the field {exc.args[0]}") from None
    except PihimInputError as exc:  # a GPS time out of range: the file is named
        raise PihimInputError(f"{p}: DataFlash GPS message: {exc}") from None
    offsets = g_utc - g_us * 1e-6
    offset_s = float(np.median(offsets))
    h = alt + _need_undulation(geoid_undulation_m, p, "GPS")
    pt, lat, lon, h = _sorted_stream(g_us * 1e-6 + offset_s, "position", p, lat, lon, h)
    at, att = _sorted_stream(a_us * 1e-6 + offset_s, "attitude", p, att)
    attitude = _euler(att[:, 0], att[:, 1], att[:, 2])
    notes = [f"log time tied to UTC by {len(gps)} GPS samples (spread {np.ptp(offsets) * 1e3:.3f} ms)"]
    gt = gimbal = None
    mode = "body"
    mnt = rows["MNT"]
    if mnt:
        try:
            m_us = np.array([r["TimeUS"] for r in mnt], float)
            earth = "YawB" not in mnt[0]
            ykey = "YawE" if earth else "YawB"
            ang = np.array([[r[ykey], r["Pitch"], r["Roll"]] for r in mnt], float)
        except KeyError as exc:
            raise PihimInputError(f"{p}: DataFlash MNT messages lack the field {exc.args[0]}") from None
        gt, ang = _sorted_stream(m_us * 1e-6 + offset_s, "gimbal", p, ang)
        gimbal = _euler(ang[:, 0], ang[:, 1], ang[:, 2])
        mode = "earth" if earth else "stabilized"
        notes.append(f"gimbal from MNT ({ykey})")
    return PoseTrack("dataflash", pt, lat, lon, h, at, attitude, gt, gimbal, mode,
                     tuple(float(v) for v in fixed_gimbal_deg), tuple(notes))  # type: ignore[arg-type]


def _dataflash_damage(path: Path) -> str | None:
    """How a DataFlash log is damaged (None if every message is whole and of a declared type).

    Messages are ``0xA3 0x95 type payload`` with the payload length declared
    by the type's ``FMT`` record (``FMT`` itself is type 0x80, 89 bytes);
    pymavlink skips damaged bytes and a cut-off last message silently.
    """
    data = path.read_bytes()
    n = len(data)
    lengths = {0x80: 89}
    pos = 0
    while pos < n:
        if pos + 3 > n:
            return f"truncated ({n - pos} bytes of a message header at the end)"
        if data[pos] != 0xA3 or data[pos + 1] != 0x95:
            return f"corrupt (no message header at byte {pos})"
        kind = data[pos + 2]
        if kind not in lengths:
            return f"corrupt (message type {kind} at byte {pos} has no FMT record)"
        size = lengths[kind]
        if pos + size > n:
            return f"truncated (the last message needs {pos + size - n} more bytes)"
        if kind == 0x80:
            lengths[data[pos + 3]] = data[pos + 4]
        pos += size
    return None


_DF_STRUCT = {"b": "b", "B": "B", "h": "h", "H": "H", "i": "i", "I": "I", "f": "f", "d": "d", "q": "q", "Q": "Q",
              "n": "4s", "N": "16s", "Z": "64s", "c": "h", "C": "H", "e": "i", "E": "I", "L": "i", "M": "B"}
_DF_SCALE = {"c": 100.0, "C": 100.0, "e": 100.0, "E": 100.0, "L": 1e7}


class _DataFlashWriter:
    """Minimal DataFlash writer: FMT records, then messages ``0xA3 0x95 type payload``."""

    def __init__(self) -> None:
        self.buf = bytearray()
        self.types: dict[str, tuple[int, str, list[str]]] = {}

    def fmt(self, name: str, fmt: str, columns: Sequence[str]) -> None:
        type_id = 0x81 + len(self.types)
        length = 3 + struct.calcsize("<" + "".join(_DF_STRUCT[c] for c in fmt))
        self.types[name] = (type_id, fmt, list(columns))
        self.buf += bytes([0xA3, 0x95, 0x80]) + struct.pack("<BB4s16s64s", type_id, length, name.encode(),
                                                            fmt.encode(), ",".join(columns).encode())

    def msg(self, name: str, values: Mapping[str, Any]) -> None:
        type_id, fmt, cols = self.types[name]
        out = []
        for c, col in zip(fmt, cols, strict=True):
            v = values[col]
            if c in _DF_SCALE:
                v = int(round(float(v) * _DF_SCALE[c]))
            elif c in "bBhHiIqQM":
                v = int(v)
            elif c in "nNZ":
                v = str(v).encode()
            out.append(v)
        self.buf += bytes([0xA3, 0x95, type_id]) + struct.pack("<" + "".join(_DF_STRUCT[c] for c in fmt), *out)


def write_dataflash(path: str | os.PathLike[str], *, boot_utc_s: float, position: Mapping[str, ArrayLike],
                    attitude: Mapping[str, ArrayLike], gimbal: Mapping[str, ArrayLike] | None = None,
                    geoid_undulation_m: float = 0.0) -> Path:
    """Write a small ArduPilot-style DataFlash ``.bin`` with GPS, ATT and MNT messages (atomically).

    ``position``: ``t`` (UTC s), ``latitude_deg``, ``longitude_deg``,
    ``height_m`` (ellipsoidal; written as ``Alt`` = height - undulation).
    ``attitude``: ``t``, ``yaw_deg``, ``pitch_deg``, ``roll_deg`` (ATT, 0.01 deg
    resolution as ArduPilot logs it). ``gimbal``: ``t``, ``yaw_deg``
    (relative to the vehicle), ``pitch_deg``, ``roll_deg`` (MNT, stabilized).
    """
    from pihim._atomic import write_atomic

    w = _DataFlashWriter()
    w.fmt("GPS", "QBIHBLLf", ["TimeUS", "Status", "GMS", "GWk", "NSats", "Lat", "Lng", "Alt"])
    w.fmt("ATT", "QccccCC", ["TimeUS", "DesRoll", "Roll", "DesPitch", "Pitch", "DesYaw", "Yaw"])
    if gimbal is not None:
        w.fmt("MNT", "QBffffffff", ["TimeUS", "I", "DRoll", "DPitch", "DYawB", "DYawE", "Roll", "Pitch", "YawB",
                                    "YawE"])
    items: list[tuple[float, int, str, dict[str, Any]]] = []

    def us(t: float) -> int:
        return int(round((t - boot_utc_s) * 1e6))

    for k, t in enumerate(np.asarray(position["t"], float)):
        wk, ms = utc_to_gps(float(t))
        items.append((t, 0, "GPS", {"TimeUS": us(t), "Status": 3, "GMS": ms, "GWk": wk, "NSats": 14,
                                    "Lat": float(position["latitude_deg"][k]),  # type: ignore[index]
                                    "Lng": float(position["longitude_deg"][k]),  # type: ignore[index]
                                    "Alt": float(position["height_m"][k]) - geoid_undulation_m}))  # type: ignore[index]
    for k, t in enumerate(np.asarray(attitude["t"], float)):
        y = float(attitude["yaw_deg"][k]) % 360.0  # type: ignore[index]
        r, pch = float(attitude["roll_deg"][k]), float(attitude["pitch_deg"][k])  # type: ignore[index]
        items.append((t, 1, "ATT", {"TimeUS": us(t), "DesRoll": r, "Roll": r, "DesPitch": pch, "Pitch": pch,
                                    "DesYaw": y, "Yaw": y}))
    if gimbal is not None:
        for k, t in enumerate(np.asarray(gimbal["t"], float)):
            gy, gp, gr = (float(gimbal[c][k]) for c in ("yaw_deg", "pitch_deg", "roll_deg"))  # type: ignore[index]
            items.append((t, 2, "MNT", {"TimeUS": us(t), "I": 0, "DRoll": gr, "DPitch": gp, "DYawB": gy,
                                        "DYawE": float("nan"), "Roll": gr, "Pitch": gp, "YawB": gy,
                                        "YawE": float("nan")}))
    items.sort(key=lambda it: (it[0], it[1]))
    for _, _, name, values in items:
        w.msg(name, values)
    blob = bytes(w.buf)
    return write_atomic(path, lambda tmp: tmp.write_bytes(blob))


# --------------------------------------------------------------------------- dispatch and matching


def log_kind(path: str | os.PathLike[str]) -> str:
    """``"ulog"``, ``"dataflash"`` or ``"csv"`` from the file's first bytes (one-line error otherwise)."""
    from pihim._inputs import check_regular_file

    p = Path(path)
    check_regular_file(p, "flight log")
    with open(p, "rb") as fh:
        head = fh.read(16)
    if head.startswith(b"ULog\x01\x12\x35"):
        return "ulog"
    if head[:2] == b"\xa3\x95":
        return "dataflash"
    if p.suffix.lower() == ".csv":
        return "csv"
    raise PihimInputError(f"{p}: not a PX4 ULog, an ArduPilot DataFlash .bin or a frames.csv")


def read_log(path: str | os.PathLike[str], *, geoid_undulation_m: float | None = None,
             fixed_gimbal_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> PoseTrack:
    """:func:`read_ulog` or :func:`read_dataflash` by the file's content."""
    kind = log_kind(path)
    if kind == "ulog":
        return read_ulog(path, geoid_undulation_m=geoid_undulation_m, fixed_gimbal_deg=fixed_gimbal_deg)
    if kind == "dataflash":
        return read_dataflash(path, geoid_undulation_m=geoid_undulation_m, fixed_gimbal_deg=fixed_gimbal_deg)
    raise PihimInputError(f"{path}: a frames.csv is not a pose log; give a .ulg or .bin")


def _bracket(t_axis: NDArray[np.float64], t: float, max_gap_s: float, what: str) -> str | None:
    """Why ``t`` cannot be interpolated on ``t_axis`` (None if it can)."""
    if t < t_axis[0]:
        return f"before the first {what} sample ({t_axis[0] - t:.3f} s)"
    if t > t_axis[-1]:
        return f"after the last {what} sample ({t - t_axis[-1]:.3f} s)"
    j = int(np.searchsorted(t_axis, t))
    if j > 0 and t_axis[j] != t and t_axis[j] - t_axis[j - 1] > max_gap_s:
        return f"in a {t_axis[j] - t_axis[j - 1]:.2f} s gap of the {what} samples (> {max_gap_s:g} s)"
    return None


def match_frames(frames: Sequence[FrameRecord], track: PoseTrack | None, origin: Any, *,
                 gimbal_mode: str | None = None, max_gap_s: float = DEFAULT_MAX_GAP_S) -> list[FrameMatch]:
    """Each frame's camera pose from the log at its time (module notes), or the reason it has none.

    Parameters
    ----------
    frames : sequence of FrameRecord
    track : PoseTrack or None
        The log. None: the frames' own ``frames.csv`` pose columns are used
        (each frame must have them).
    origin : GeodeticOrigin, Site or (lat, lon, h)
        The field origin (ellipsoidal height).
    gimbal_mode : str, optional
        For ``frames.csv`` poses (default ``"body"``); a log's own mode otherwise.
    max_gap_s : float
        Largest gap between two samples of a stream a frame may fall into.

    Returns
    -------
    list of FrameMatch
        In the order of ``frames``; ``pose`` None with ``reason`` for frames
        outside the log (before, after, or in a gap).
    """
    from pihim.field.geodesy import geodetic_to_enu

    if not math.isfinite(max_gap_s) or max_gap_s <= 0:
        raise PihimInputError(f"max_gap_s must be > 0, got {max_gap_s!r}")
    if track is None:
        mode = gimbal_mode or "body"
        if mode not in GIMBAL_MODES:
            raise PihimInputError(f"gimbal mode must be one of {', '.join(GIMBAL_MODES)}, got {mode!r}")
        out = []
        for f in frames:
            if f.pose is None:
                out.append(FrameMatch(f, None, "frames.csv has no pose for this frame and there is no log"))
                continue
            q = f.pose
            enu = geodetic_to_enu(q["latitude_deg"], q["longitude_deg"], q["height_m"], origin)
            pose = camera_pose_from_attitude(enu, q["roll_deg"], q["pitch_deg"], q["yaw_deg"],
                                             q["gimbal_pitch_deg"], q["gimbal_yaw_deg"],
                                             q.get("gimbal_roll_deg", 0.0), mode)
            out.append(FrameMatch(f, pose))
        return out

    from scipy.spatial.transform import Slerp

    enu = geodetic_to_enu(track.latitude_deg, track.longitude_deg, track.height_m, origin)
    slerp_att = Slerp(track.attitude_t, track.attitude)
    slerp_gim = Slerp(track.gimbal_t, track.gimbal) if track.gimbal is not None else None
    fixed = _euler(track.fixed_gimbal_deg[1], track.fixed_gimbal_deg[0], track.fixed_gimbal_deg[2])
    times = np.array([f.time_utc_s for f in frames], float)
    reasons: list[str | None] = []
    for t in times:
        why = (_bracket(track.position_t, t, max_gap_s, "position")
               or _bracket(track.attitude_t, t, max_gap_s, "attitude")
               or (None if track.gimbal_t is None else _bracket(track.gimbal_t, t, max_gap_s, "gimbal")))
        reasons.append(why)
    ok = np.array([r is None for r in reasons])
    out_matches: list[FrameMatch] = []
    if ok.any():
        tt = times[ok]
        pos = np.stack([np.interp(tt, track.position_t, enu[:, k]) for k in range(3)], axis=1)
        veh = slerp_att(tt)
        gim = slerp_gim(tt) if slerp_gim is not None else fixed
        mode = track.gimbal_mode if slerp_gim is not None else "body"
        rots = camera_rotation(veh, gim, mode)
        poses = iter(_pose_from_ned(pos[k], rots[k]) for k in range(len(tt)))
    else:
        poses = iter(())
    for f, why in zip(frames, reasons, strict=True):
        out_matches.append(FrameMatch(f, next(poses)) if why is None else FrameMatch(f, None, f"frame {why}"))
    return out_matches
