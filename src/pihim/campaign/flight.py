"""A flight directory, and the synthetic flight of a plan.

A **flight directory** holds what one flight of the drone recorded::

    FLIGHT/
      flight.json     settings (schema pihim.flight/1, below)
      frames.csv      frame id, file, UTC mid-exposure time [, pose columns]
      flight.ulg | flight.bin   optional autopilot log (when frames.csv has no poses)
      frames/*.tiff   the raw DoFP mosaics

``flight.json`` (``schema: "pihim.flight/1"``):

* ``frames`` -- the frames list (default ``frames.csv``);
* ``log`` -- the pose source: ``frames.csv`` (its pose columns) or a
  ``.ulg`` / ``.bin`` file in the directory;
* ``gimbal_mode`` -- how ``frames.csv`` gimbal angles are referenced
  (:data:`pihim.campaign.logs.GIMBAL_MODES`, default ``body``); logs say it
  themselves;
* ``fixed_gimbal_deg`` -- ``[pitch, yaw, roll]`` of a fixed camera mount,
  for logs without a gimbal stream;
* ``geoid_undulation_m`` -- for logs whose heights are above mean sea level;
* ``max_gap_s`` -- the largest gap in a log stream a frame may fall into;
* ``site`` -- the field origin (latitude, longitude, ellipsoidal height: a
  :class:`pihim.sky.sun.Site` dictionary);
* ``aim_point_m`` -- the aim point the field tracked (ENU m);
* ``heliostats`` -- commanded drive angles of heliostats that did not track
  (``[{name, az_deg, el_deg}]``, usually empty);
* ``camera`` -- the camera model (:meth:`pihim.camera.CameraModel.to_dict`);
* ``sensor`` -- ``{"model": ..., "layout": ...}`` as the simulated frames'
  logs (dark level, bit depth, analyser).

:func:`simulate_flight` writes such a directory for a flight of a
``plan.json``, with ``truth/`` beside it: one ``FRAME.json`` per frame (the
frame's log and its ground truth, as ``pihim simulate`` writes, with the
digests of the frame's inputs and TIFF in ``truth.simulation``, so that a rerun
reuses it) and ``truth/flight.json`` (true poses, the field's true canting).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pihim.campaign.logs import (
    DEFAULT_MAX_GAP_S,
    GIMBAL_MODES,
    FrameMatch,
    FrameRecord,
    format_utc,
    log_kind,
    match_frames,
    read_frames_csv,
    read_log,
)
from pihim.errors import PihimInputError

__all__ = ["FLIGHT_SCHEMA_ID", "SIGMA_LIMITS", "Flight", "check_frame_files", "check_sigmas", "frame_log",
           "load_flight", "load_plan", "simulate_flight"]

FLIGHT_SCHEMA_ID = "pihim.flight/1"


@dataclass(frozen=True, eq=False)
class Flight:
    """A loaded flight directory: settings, frames and each frame's matched pose."""

    directory: Path
    name: str
    settings: dict[str, Any]
    log_kind: str
    matches: tuple[FrameMatch, ...]

    @property
    def uncovered(self) -> list[FrameMatch]:
        """Frames without a pose (outside the log, in a gap)."""
        return [m for m in self.matches if not m.ok]

    def frame_path(self, frame: FrameRecord) -> Path:
        return self.directory / frame.file


def _site(settings: Mapping[str, Any], where: Path) -> Any:
    from pihim.sky.sun import Site

    s = settings.get("site")
    if not isinstance(s, Mapping):
        raise PihimInputError(f"{where}: 'site' must be an object with latitude_deg, longitude_deg, height_m")
    try:
        return Site(name=str(s.get("name", "site")), latitude_deg=s["latitude_deg"], longitude_deg=s["longitude_deg"],
                    height_m=s["height_m"], timezone=str(s.get("timezone", "UTC")))
    except KeyError as exc:
        raise PihimInputError(f"{where}: 'site' has no {exc.args[0]!r}") from None


def load_flight(directory: str | os.PathLike[str], *, name: str | None = None) -> Flight:
    """Read a flight directory: ``flight.json``, the frames and the log; match every frame.

    Raises
    ------
    PihimInputError
        A missing or malformed ``flight.json`` or ``frames.csv``, an
        unreadable, corrupt or truncated log. Frames outside the log are
        **not** an error here: see :attr:`Flight.uncovered`.
    """
    from pihim._inputs import load_json_file
    from pihim.camera.model import CameraModel

    d = Path(directory)
    if not d.is_dir():
        raise PihimInputError(f"{d}: not a flight directory")
    meta = d / "flight.json"
    if not meta.is_file():
        raise PihimInputError(f"{d}: no flight.json (see docs/campaign.md)")
    settings = load_json_file(meta, "flight.json")
    if not isinstance(settings, dict) or settings.get("schema") != FLIGHT_SCHEMA_ID:
        raise PihimInputError(f"{meta}: not a {FLIGHT_SCHEMA_ID} document")
    from pihim.inspection.pipeline import sensor_settings

    try:  # the camera and the sensor now, not frame by frame after the store is written
        CameraModel.from_dict(settings.get("camera") or {})
        sensor_settings({"sensor": settings.get("sensor")})
    except PihimInputError as exc:
        raise PihimInputError(f"{meta}: {exc}") from None
    site = _site(settings, meta)
    frames = read_frames_csv(d / str(settings.get("frames", "frames.csv")))
    max_gap = float(settings.get("max_gap_s", DEFAULT_MAX_GAP_S))
    log_name = str(settings.get("log", "frames.csv"))
    mode = str(settings.get("gimbal_mode", "body"))
    if mode not in GIMBAL_MODES:
        raise PihimInputError(f"{meta}: gimbal_mode must be one of {', '.join(GIMBAL_MODES)}, got {mode!r}")
    if log_name.lower().endswith(".csv"):
        kind, track = "csv", None
        if any(f.pose is None for f in frames):
            raise PihimInputError(f"{meta}: the log is {log_name} but it has no pose columns; name a .ulg or .bin")
    else:
        log_path = d / log_name
        kind = log_kind(log_path)
        fixed = tuple(float(v) for v in settings.get("fixed_gimbal_deg", (0.0, 0.0, 0.0)))
        und = settings.get("geoid_undulation_m")
        track = read_log(log_path, geoid_undulation_m=None if und is None else float(und),
                         fixed_gimbal_deg=fixed)  # type: ignore[arg-type]
    matches = match_frames(frames, track, site, gimbal_mode=mode, max_gap_s=max_gap)
    return Flight(d, name or str(settings.get("name") or d.name), settings, kind, tuple(matches))


def check_frame_files(flight: Flight) -> None:
    """Every frame file exists and has the camera's size (headers only; one-line error naming the first bad one).

    A frame whose header cannot be read is left to the run, which records it as skipped (unreadable) and goes on.
    """
    import tifffile

    from pihim.camera.model import CameraModel

    cam = CameraModel.from_dict(flight.settings["camera"])
    for m in flight.matches:
        p = flight.frame_path(m.frame)
        if not p.is_file():
            raise PihimInputError(f"{p}: frame {m.frame.frame_id} of flight {flight.name}: no such file")
        if p.suffix.lower() in (".tif", ".tiff"):
            try:
                with tifffile.TiffFile(p) as tf:
                    shape = tf.pages[0].shape
            except Exception:  # noqa: BLE001 - a corrupt frame (even empty) is the batch's bad item, skipped then
                continue
            if tuple(shape[:2]) != (cam.height_px, cam.width_px):
                raise PihimInputError(
                    f"{p}: a {shape[1]}x{shape[0]} frame, but flight {flight.name}'s camera is "
                    f"{cam.width_px}x{cam.height_px} (a frame of another camera?)")


def frame_log(flight: Flight, match: FrameMatch) -> dict[str, Any]:
    """The per-frame ``log`` that :func:`pihim.inspection.pipeline.inspect_frame` reads."""
    if match.pose is None:
        raise PihimInputError(f"frame {match.frame.frame_id} has no pose ({match.reason})")
    s = flight.settings
    return {
        "time": format_utc(match.frame.time_utc_s),
        "site": s["site"],
        "camera": s["camera"],
        "pose": match.pose.to_dict(),
        "sensor": s.get("sensor") or {},
        "aim_point_m": s.get("aim_point_m"),
        "heliostats": list(s.get("heliostats") or []),
    }


# --------------------------------------------------------------------------- synthetic flight


def _flight_waypoints(doc: Mapping[str, Any], flight_index: int) -> tuple[list[dict[str, Any]], list[int | None]]:
    """The flight's waypoints and, for each, its capture index in plan order (None if not a capture)."""
    flights = doc.get("flights") or []
    if not 0 <= flight_index < len(flights):
        raise PihimInputError(f"the plan has {len(flights)} flights; --flight {flight_index + 1} is not one of them")
    fl = flights[flight_index]
    capture_ids: dict[tuple[float, float, float, str | None], int] = {}
    k = 0
    for q in doc["passes"]:
        for w in q["waypoints"]:
            if w.get("capture") is True:
                capture_ids.setdefault((round(w["x_m"], 6), round(w["y_m"], 6), round(w["z_m"], 6), w.get("hua")), k)
                k += 1
    wps = list(fl["waypoints"])
    caps = [capture_ids.get((round(w["x_m"], 6), round(w["y_m"], 6), round(w["z_m"], 6), w.get("hua")))
            if w.get("capture") else None for w in wps]
    return wps, caps


def _check_waypoints(wps: Any, where: str, keys: Sequence[str]) -> None:
    """Refuse ``where`` unless it is a list of waypoint objects whose ``keys`` are finite numbers."""
    from pihim._inputs import finite_number

    if not isinstance(wps, list):
        raise PihimInputError(f"{where} must be a list of waypoints")
    for i, w in enumerate(wps):
        if not isinstance(w, Mapping):
            raise PihimInputError(f"{where}[{i}] must be a waypoint object")
        for k in keys:
            if k not in w:
                raise PihimInputError(f"{where}[{i}] has no {k!r}")
            finite_number(w[k], f"{where}[{i}].{k}")
        if w.get("speed_m_s") is not None:
            finite_number(w["speed_m_s"], f"{where}[{i}].speed_m_s")


def load_plan(plan_path: str | os.PathLike[str], flight: int = 1) -> dict[str, Any]:
    """Read a ``pihim plan`` ``plan.json`` and check what :func:`simulate_flight` uses of it.

    Parameters
    ----------
    plan_path : path-like
    flight : int
        1-based flight of the plan that will be flown.

    Returns
    -------
    dict
        The plan document.

    Raises
    ------
    PihimInputError
        Not a ``pihim.plan/1`` document, no ``passes`` or ``flights`` list,
        no such flight, a waypoint of the flight or of a pass whose
        coordinates (or the flight's headings, gimbal pitches, speeds) are
        missing or not finite (named, e.g. ``passes[3].waypoints[2].x_m``),
        a missing time or aim point.
    """
    from pihim._inputs import finite_number, load_json_file

    plan = Path(plan_path)
    doc = load_json_file(plan, "plan file")
    if not isinstance(doc, dict) or doc.get("schema") != "pihim.plan/1" or "flights" not in doc:
        raise PihimInputError(f"{plan}: not a pihim plan.json (schema pihim.plan/1 with flights)")
    for key in ("passes", "flights"):
        if not isinstance(doc.get(key), list):
            raise PihimInputError(f"{plan}: the plan has no {key!r} list")
    if not isinstance(doc.get("time_iso"), str):
        raise PihimInputError(f"{plan}: the plan has no 'time_iso'")
    from pihim.sky.sun import parse_time

    try:
        parse_time(doc["time_iso"])
    except PihimInputError as exc:
        raise PihimInputError(f"{plan}: time_iso: {exc}") from None
    aim = doc.get("aim_point")
    if not isinstance(aim, list) or len(aim) != 3:
        raise PihimInputError(f"{plan}: 'aim_point' must be a list of 3 numbers (ENU m)")
    for i, v in enumerate(aim):
        finite_number(v, f"{plan}: aim_point[{i}]")
    flights = doc["flights"]
    if not 1 <= flight <= len(flights):
        raise PihimInputError(f"the plan has {len(flights)} flights; --flight {flight} is not one of them")
    for k, q in enumerate(doc["passes"]):
        if not isinstance(q, Mapping):
            raise PihimInputError(f"{plan}: passes[{k}] must be an object")
        _check_waypoints(q.get("waypoints"), f"{plan}: passes[{k}].waypoints", ("x_m", "y_m", "z_m"))
    fl = flights[flight - 1]
    if not isinstance(fl, Mapping):
        raise PihimInputError(f"{plan}: flights[{flight - 1}] must be an object")
    _check_waypoints(fl.get("waypoints"), f"{plan}: flights[{flight - 1}].waypoints",
                     ("x_m", "y_m", "z_m", "heading_deg", "gimbal_pitch_deg"))
    if len(fl["waypoints"]) < 2:
        raise PihimInputError(f"{plan}: flights[{flight - 1}] has fewer than 2 waypoints")
    return doc


def _timeline(wps: Sequence[Mapping[str, Any]]) -> np.ndarray:
    """Arrival time at each waypoint, s from the flight's start (straight legs at the waypoint's speed)."""
    t = [0.0]
    for a, b in zip(wps[:-1], wps[1:], strict=True):
        d = math.dist((a["x_m"], a["y_m"], a["z_m"]), (b["x_m"], b["y_m"], b["z_m"]))
        v = max(float(b.get("speed_m_s") or 0.0), 1.0)
        t.append(t[-1] + d / v)
    return np.array(t)


def _interp_heading(h0: float, h1: float, s: float) -> float:
    d = (h1 - h0 + 180.0) % 360.0 - 180.0
    return (h0 + s * d) % 360.0


#: Largest noise a simulated flight accepts: canting sigma (mrad), GPS sigma (m), attitude sigma (deg) -- far beyond
#: any real error, so that a mistyped exponent is refused instead of overflowing the poses.
SIGMA_LIMITS = {"canting sigma (mrad)": 1000.0, "GPS sigma (m)": 1000.0, "attitude sigma (deg)": 180.0}


def check_sigmas(canting_sigma_mrad: float, gps_sigma_m: float, attitude_sigma_deg: float) -> None:
    """Refuse a noise sigma that is not a finite number in ``[0, SIGMA_LIMITS[...]]`` (one-line PihimInputError)."""
    for (name, top), v in zip(SIGMA_LIMITS.items(), (canting_sigma_mrad, gps_sigma_m, attitude_sigma_deg), strict=True):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and 0 <= v <= top):
            raise PihimInputError(f"{name} must be a finite number in [0, {top:g}], got {v!r}")


def _sha256_file(path: Path) -> str:
    """The sha256 of a file's bytes (hex)."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _code_sha256() -> str:
    """A digest of pihim's own Python sources (relative paths and bytes): any code change makes frames stale."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def _field_sha256(field: Any) -> str:
    """A digest of a field's geometry: names, tower, pivots and heliostat spec (facet centroids included)."""
    h = hashlib.sha256()
    for part in (field.names, field.tower, field.pivots,
                 *(getattr(field.spec, f.name) for f in dataclasses.fields(field.spec))):
        if isinstance(part, np.ndarray):
            h.update(repr(part.shape).encode() + np.ascontiguousarray(part, "<f8").tobytes())
        else:
            h.update(repr(part).encode())
    return h.hexdigest()


def _inputs_sha256(inputs: Mapping[str, Any]) -> str:
    """sha256 of the canonical JSON (sorted keys, no blanks) of a frame's inputs."""
    text = json.dumps(inputs, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


_FRAME_ID = re.compile(r"[0-9]{6}")


def _request_record(request: Any) -> dict[str, Any]:
    """A pose request as digest input: its type and fields, the plan by its content (digested apart), not its path."""
    fields = dataclasses.asdict(request)
    fields.pop("plan_path", None)
    return {"type": type(request).__name__, **fields}


@contextlib.contextmanager
def _removed_if_empty_on_refusal(made: Sequence[Path]) -> Iterator[None]:
    """On a :class:`PihimInputError` (a frame refused: the sun below the horizon, say), remove the folders this run
    made (``made``, parents first) that are still empty."""
    try:
        yield
    except PihimInputError:
        for d in reversed(made):
            with contextlib.suppress(OSError):
                d.rmdir()  # only an empty folder goes
        raise


@contextlib.contextmanager
def _flight_directory_lock(out: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``out`` (``out/.simulate-flight.lock``) while a run writes it; one line if held."""
    import fcntl

    path = out / ".simulate-flight.lock"
    with open(path, "a+b") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise PihimInputError(f"{out}: another simulate-flight is writing this directory") from None
        try:
            yield
        finally:
            path.unlink(missing_ok=True)  # before the lock is released, so no later run finds a stale file


def _reusable_frame(tiff: Path, truth: Path, inputs_sha256: str) -> dict[str, Any] | None:
    """The frame's ``FRAME.json`` document if it records ``inputs_sha256`` and the TIFF's digest, else None."""
    try:
        doc = json.loads(truth.read_text(encoding="utf-8"))
        sim = doc["truth"]["simulation"]
        if sim["inputs_sha256"] == inputs_sha256 and sim["raw_sha256"] == _sha256_file(tiff):
            return doc
    except (OSError, ValueError, LookupError, TypeError):  # missing, unreadable, corrupt, another document
        pass
    return None


def simulate_flight(plan_path: str | os.PathLike[str], out_dir: str | os.PathLike[str], *, flight: int = 1,
                    fps: float | None = None, max_frames: int | None = None, size: tuple[int, int] = (2448, 2048),
                    log: str = "csv", canting_sigma_mrad: float = 3.0, gps_sigma_m: float = 0.0,
                    attitude_sigma_deg: float = 0.0, vehicle_pitch_deg: float = -4.0, seed: int = 0,
                    field: Any = None, field_source: str = "nsttf-like",
                    progress: Any = None) -> dict[str, Any]:
    """Render the frames a flight of ``plan.json`` would record, with its log and the truth.

    Parameters
    ----------
    plan_path : path-like
        A ``pihim plan`` ``plan.json`` (its time, site and aim point are used).
    out_dir : path-like
        The flight directory to write (module notes) and ``truth/``.
    flight : int
        1-based flight of the plan.
    fps : float, optional
        Record at this rate along the flight's scan passes (lead-in to
        run-past); None: one frame at each capture waypoint (``--captures-only``).
    max_frames : int, optional
        Stop after this many frames.
    size : (int, int)
        Frame size; the Triton's field of view is kept (:func:`pihim.camera.model.camera_for_size`).
    log : {"csv", "ulog", "dataflash"}
        Where the poses go: ``frames.csv`` pose columns, or a ULog / DataFlash
        log sampled at 10 Hz (position) and 50 Hz (attitude, gimbal).
    canting_sigma_mrad : float
        Facet canting deviations (the same field for every frame: one seed).
    gps_sigma_m, attitude_sigma_deg : float
        Logged-pose errors: a constant GPS offset per flight, and attitude
        noise per log sample (so a frame's logged attitude is interpolated
        from noisy samples).
    vehicle_pitch_deg : float
        The airframe's pitch in forward flight (nose down); the camera's true
        pitch is the planned one, the gimbal makes up the difference (body
        mode for ``frames.csv``, stabilized for logs).
    seed : int
    field : pihim.field.Field, optional
        Default the embedded NSTTF-like field.

    Returns
    -------
    dict
        Summary (``pihim.simulate-flight/1``): files, frames (``rendered``
        now, ``reused`` from an earlier run), time span, log kind.

    Raises
    ------
    PihimInputError
        A plan :func:`load_plan` refuses (before anything is written), a
        flight that records no frame, bad options.

    Notes
    -----
    A rerun resumes: frame ``k`` is not rendered again when ``frames/k.tiff``
    and ``truth/k.json`` are there, the JSON's ``truth.simulation`` records
    the same ``inputs_sha256`` (a sha256 of the canonical JSON of what the
    frame is rendered from: pihim version and sources, plan file digest, frame time, pose
    request and true pose, site, aim point, camera, seed, canting sigma,
    field source and geometry digest) and ``raw_sha256`` is the TIFF's
    digest; its truth is read back from the JSON. Anything else (another
    seed, size, sigma or plan, a missing or corrupt file) is rendered again.
    Frames beyond this run's count left by an earlier, longer run are
    removed, and ``flight.json``, ``frames.csv``, the logs and
    ``truth/flight.json`` are removed first and written anew last, so the
    directory is byte for byte the one a fresh run writes, and a killed rerun
    leaves no ``flight.json``. One run writes a directory at a time (a lock
    file; a second run raises :class:`PihimInputError`). The digest also
    covers pihim's own sources, so frames rendered by other code are
    rendered again.
    """
    import pandas as pd
    import tifffile

    from pihim import __version__
    from pihim._atomic import clean_stale_temporaries_tree, write_atomic, write_json_atomic
    from pihim.camera.pose import CameraPose
    from pihim.campaign.logs import write_dataflash, write_frames_csv, write_ulog
    from pihim.camera.model import camera_for_size
    from pihim.field import Field, enu_to_geodetic, nsttf_like_field
    from pihim.render.simulate import LookAtPose, WaypointPose, check_camera_distance, simulate_frame
    from pihim.sky.sun import parse_time

    if log not in ("csv", "ulog", "dataflash"):
        raise PihimInputError(f"log must be csv, ulog or dataflash, got {log!r}")
    if fps is not None and not (math.isfinite(fps) and 0 < fps <= 60):
        raise PihimInputError(f"fps must be in (0, 60], got {fps!r}")
    if max_frames is not None and max_frames < 1:
        raise PihimInputError(f"max_frames must be >= 1, got {max_frames!r}")
    check_sigmas(canting_sigma_mrad, gps_sigma_m, attitude_sigma_deg)
    plan = Path(plan_path)
    doc = load_plan(plan, flight)
    field = field or nsttf_like_field()
    if not isinstance(field, Field):
        raise PihimInputError(f"field must be a pihim.field.Field, got {type(field).__name__}")
    site = _site(doc, plan)
    start = parse_time(doc["time_iso"])
    aim = [float(v) for v in doc["aim_point"]]
    camera = camera_for_size(*size)
    wps, caps = _flight_waypoints(doc, flight - 1)
    for i, w in enumerate(wps):  # a position kilometres away would overflow the timeline before any frame refuses it
        try:
            check_camera_distance([w.get(c) for c in ("x_m", "y_m", "z_m")])
        except (PihimInputError, TypeError, ValueError) as exc:
            raise PihimInputError(f"{plan}: waypoint {i} of flight {flight}: {exc}") from None
    arrive = _timeline(wps)

    # the frames: (time from start, true camera pose, request, capture index)
    shots: list[tuple[float, CameraPose, Any]] = []
    if fps is None:
        for i, c in enumerate(caps):
            if c is not None:
                shots.append((float(arrive[i]), CameraPose.from_waypoint(wps[i]), WaypointPose(str(plan), c)))
    else:
        scan = {"lead_in", "scan", "run_past"}
        for i in range(len(wps) - 1):
            a, b = wps[i], wps[i + 1]
            if a.get("kind") not in scan or b.get("kind") not in scan:
                continue
            t0, t1 = float(arrive[i]), float(arrive[i + 1])
            k0 = math.ceil(t0 * fps - 1e-9)
            for k in range(k0, math.floor(t1 * fps - 1e-9) + 1):
                t = k / fps
                s = (t - t0) / (t1 - t0) if t1 > t0 else 0.0
                pos = [a[c] + s * (b[c] - a[c]) for c in ("x_m", "y_m", "z_m")]
                h = _interp_heading(a["heading_deg"], b["heading_deg"], s)
                p = a["gimbal_pitch_deg"] + s * (b["gimbal_pitch_deg"] - a["gimbal_pitch_deg"])
                pose = CameraPose.from_attitude(pos, h, p)
                shots.append((t, pose, LookAtPose(tuple(pos), tuple(np.add(pos, pose.forward)), 0.0)))
    if max_frames is not None:
        shots = shots[:max_frames]
    if not shots:
        raise PihimInputError(f"flight {flight} of {plan} records no frame (no captures / scan passes)")

    out = Path(out_dir)
    made = [d for d in (*reversed(out.parents), out, out / "frames", out / "truth") if not d.exists()]
    (out / "frames").mkdir(parents=True, exist_ok=True)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    with _removed_if_empty_on_refusal(made), _flight_directory_lock(out):
        # a rerun first withdraws what said the directory was complete: killed, it leaves no flight.json
        for name in ("flight.json", "frames.csv", "flight.ulg", "flight.bin", "truth/flight.json"):
            (out / name).unlink(missing_ok=True)
        clean_stale_temporaries_tree(out, depth=1)  # what a killed run was writing
        t_start = start.timestamp()
        rng = np.random.default_rng(np.random.SeedSequence([seed, 14]))
        gps_offset = rng.standard_normal(3) * gps_sigma_m
        records: list[FrameRecord] = []
        truth_frames: list[dict[str, Any]] = []
        canting: dict[str, list[dict[str, Any]]] = {}
        sensor_log: dict[str, Any] | None = None
        common = {"pihim": __version__, "code_sha256": _code_sha256(), "plan_sha256": _sha256_file(plan), "site": site.as_dict(), "aim_point_m": aim,
                  "camera": camera.to_dict(), "seed": seed, "canting_sigma_mrad": canting_sigma_mrad,
                  "field_source": field_source, "field_sha256": _field_sha256(field)}
        rendered = 0
        for k, (t, pose, request) in enumerate(shots):
            when = start + pd.Timedelta(seconds=t)
            fid = f"{k:06d}"
            rel, truth_path = f"frames/{fid}.tiff", out / "truth" / f"{fid}.json"
            inputs = _inputs_sha256({**common, "time": when.isoformat(), "pose": pose.to_dict(),
                                     "request": _request_record(request)})
            doc = _reusable_frame(out / rel, truth_path, inputs)
            if doc is None:
                sim = simulate_frame(field, when.isoformat(), site=site, aim_point=aim, camera=camera,
                                     pose_request=request, canting_sigma_mrad=canting_sigma_mrad, seed=seed,
                                     field_source=field_source)
                raw = np.ascontiguousarray(sim.raw, dtype=np.uint16)
                write_atomic(out / rel, lambda p, raw=raw: tifffile.imwrite(p, raw))
                doc = sim.document()
                doc["truth"]["simulation"].update(inputs_sha256=inputs, raw_sha256=_sha256_file(out / rel))
                write_json_atomic(truth_path, doc)
                rendered += 1
            flog, ftruth = doc["log"], doc["truth"]
            sensor_log = {"model": flog["sensor"]["model"], "layout": flog["sensor"]["layout"]}
            for h in ftruth["heliostats"]:
                canting.setdefault(h["name"], h["facets"])
            truth_frames.append({"frame_id": fid, "time_utc": format_utc(t_start + t), "hua": flog["hua"],
                                 "target": flog["target"], "pose": ftruth["pose"]})
            records.append(FrameRecord(fid, rel, t_start + t))
            if progress is not None:
                progress(k + 1, len(shots))

        for p in [*(out / "frames").glob("*.tiff"), *(out / "truth").glob("*.json")]:
            if _FRAME_ID.fullmatch(p.stem) and int(p.stem) >= len(shots):
                p.unlink()  # left by an earlier, longer run (only names this function writes: NNNNNN)

        # the logged track: true vehicle (yaw = heading, airframe pitch, no roll) + errors
        t_lo, t_hi = shots[0][0] - 2.0, shots[-1][0] + 2.0

        def truth_at(t: float) -> tuple[np.ndarray, float, float]:
            i = int(np.clip(np.searchsorted(arrive, t) - 1, 0, len(wps) - 2))
            a, b = wps[i], wps[i + 1]
            span = arrive[i + 1] - arrive[i]
            s = float(np.clip((t - arrive[i]) / span, 0.0, 1.0)) if span > 0 else 0.0
            pos = np.array([a[c] + s * (b[c] - a[c]) for c in ("x_m", "y_m", "z_m")])
            return pos, _interp_heading(a["heading_deg"], b["heading_deg"], s), \
                a["gimbal_pitch_deg"] + s * (b["gimbal_pitch_deg"] - a["gimbal_pitch_deg"])
        # frames use their own true pose; the track carries the same pose at the frame times exactly
        shot_t = np.array([s[0] for s in shots])
        tp = np.union1d(np.arange(t_lo, t_hi, 0.1), shot_t)
        ta = np.union1d(np.arange(t_lo, t_hi, 0.02), shot_t)

        def state(t: float) -> tuple[np.ndarray, float, float]:
            j = np.flatnonzero(np.abs(shot_t - t) < 1e-9)
            if j.size:
                pose = shots[int(j[0])][1]
                return np.array(pose.position_m), pose.heading_deg, pose.pitch_deg
            return truth_at(t)

        pos = np.array([state(t)[0] for t in tp]) + gps_offset
        lat, lon, hgt = enu_to_geodetic(pos, site)
        hp = np.array([state(t)[1:] for t in ta])
        yaw = hp[:, 0] + rng.standard_normal(len(ta)) * attitude_sigma_deg
        vpitch = np.full(len(ta), vehicle_pitch_deg) + rng.standard_normal(len(ta)) * attitude_sigma_deg
        vroll = rng.standard_normal(len(ta)) * attitude_sigma_deg
        gpitch = hp[:, 1]
        settings: dict[str, Any] = {
            "schema": FLIGHT_SCHEMA_ID,
            "name": out.name,
            "plan": str(plan),
            "flight": flight,
            "frames": "frames.csv",
            "site": site.as_dict(),
            "aim_point_m": aim,
            "heliostats": [],
            "camera": camera.to_dict(),
            "sensor": sensor_log,
            "max_gap_s": DEFAULT_MAX_GAP_S,
        }
        files = {"flight.json": out / "flight.json", "frames.csv": out / "frames.csv"}
        ta_abs, tp_abs = ta + t_start, tp + t_start
        if log == "csv":
            # body-mounted gimbal: camera = Rz(yaw) Ry(vehicle pitch) Rx(roll) * Ry(gimbal pitch); with the airframe's
            # roll 0 the gimbal pitch making the true camera pitch is the difference (noise stays in the log)
            idx = {round(float(t), 9): k for k, t in enumerate(ta)}
            out_records = []
            for r, t in zip(records, shot_t, strict=True):
                k = idx[round(float(t), 9)]
                j = int(np.searchsorted(tp, t))
                out_records.append(FrameRecord(r.frame_id, r.file, r.time_utc_s, {
                    "latitude_deg": float(lat[j]), "longitude_deg": float(lon[j]), "height_m": float(hgt[j]),
                    "roll_deg": float(vroll[k]), "pitch_deg": float(vpitch[k]), "yaw_deg": float(yaw[k] % 360.0),
                    "gimbal_pitch_deg": float(gpitch[k] - vehicle_pitch_deg), "gimbal_yaw_deg": 0.0}))
            records = out_records
            settings.update({"log": "frames.csv", "gimbal_mode": "body"})
        else:
            from scipy.spatial.transform import Rotation

            position = {"t": tp_abs, "latitude_deg": lat, "longitude_deg": lon, "height_m": hgt}
            zeros = np.zeros(len(ta))
            if log == "ulog":
                att = Rotation.from_euler("ZYX", np.stack([yaw, vpitch, vroll], axis=1), degrees=True).as_quat()
                gim = Rotation.from_euler("ZYX", np.stack([zeros, gpitch, zeros], axis=1), degrees=True).as_quat()
                files["flight.ulg"] = write_ulog(out / "flight.ulg", boot_utc_s=t_start + t_lo - 30.0, position=position,
                                                 attitude={"t": ta_abs, "quat": att}, gimbal={"t": ta_abs, "quat": gim})
                settings["log"] = "flight.ulg"
            else:
                und = -22.0
                files["flight.bin"] = write_dataflash(
                    out / "flight.bin", boot_utc_s=t_start + t_lo - 30.0, position=position, geoid_undulation_m=und,
                    attitude={"t": ta_abs, "yaw_deg": yaw, "pitch_deg": vpitch, "roll_deg": vroll},
                    gimbal={"t": ta_abs, "yaw_deg": zeros, "pitch_deg": gpitch, "roll_deg": zeros})
                settings.update({"log": "flight.bin", "geoid_undulation_m": und})
        write_frames_csv(out / "frames.csv", records)
        true_doc = {
            "schema": "pihim.flight-truth/1",
            "canting_sigma_mrad": canting_sigma_mrad,
            "gps_offset_m": [float(v) for v in gps_offset],
            "attitude_sigma_deg": attitude_sigma_deg,
            "seed": seed,
            "frames": truth_frames,
            "heliostats": [{"name": n, "facets": f} for n, f in sorted(canting.items())],
        }
        files["truth/flight.json"] = write_json_atomic(out / "truth" / "flight.json", true_doc)
        write_json_atomic(out / "flight.json", settings)  # last: a directory with flight.json is complete
        return {
            "schema": "pihim.simulate-flight/1",
            "out": str(out),
            "flight": flight,
            "frames": len(records),
            "rendered": rendered,
            "reused": len(records) - rendered,
            "width_px": camera.width_px,
            "height_px": camera.height_px,
            "log": settings["log"],
            "first_time_utc": format_utc(records[0].time_utc_s),
            "last_time_utc": format_utc(records[-1].time_utc_s),
            "files": {k: str(v) for k, v in files.items()},
        }

