"""Camera heading along the scan passes: constant wherever the field of view allows.

The planner points the optical axis of every capture at its HUA's mirror
centre (:func:`pihim.planning.sightlines.gaze_angles`), so the heading
changes from one capture to the next (median 5 deg at NSTTF 10:00). A drone
without a yawing gimbal must then turn between captures, and every turn is a
chance to take a photo before the turn has finished. :func:`steady_headings`
groups consecutive captures of a pass into *runs* flown at one heading,
whenever one heading frames each capture of the run at least as well as
aiming it at its own HUA would:

* the HUA's mirror centre stays within ``max_offset_deg`` (default a quarter
  of the horizontal field of view, 3.45 deg for the Triton + 35 mm) of the
  optical axis, horizontally; and
* each capture frames no fewer of its HUA's facet centres
  (:func:`pihim.planning.sightlines.in_fov`) than aiming it at its own HUA
  would (with a 35 mm lens at <= 25 m a HUA over-fills the frame, so a
  heading that loses a facet column without gaining another is refused).

Runs are grown greedily in flight order; a run's heading is chosen on a
0.05 deg grid spanning its captures' gaze headings: the heading framing the
most facet centres in total, then the one nearest the middle of the span.
Gimbal pitch stays each capture's own (a gimbal re-pitches in a fraction of
a second). Lead-in and run-past waypoints take the heading of the first and
last run, so the drone turns on the transit before the pass, not in it.

Headings change only inside a pass and only between runs; the mission
writers (:mod:`pihim.planning.export.qgc`) turn the drone on the leg *before*
each capture so that it arrives at the planned heading.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pihim.camera.model import CameraModel
from pihim.errors import PihimInputError
from pihim.planning.model import ScanPass, Waypoint, heading_0_360
from pihim.planning.sightlines import gaze_angles, in_fov, optical_axis

__all__ = ["heading_runs", "leg_speed", "steady_headings", "turn_limited_speed"]

_GRID_DEG = 0.05


def _unwrap(headings: Sequence[float]) -> NDArray[np.float64]:
    """Headings made continuous (no 359 -> 0 jump), degrees."""
    return np.degrees(np.unwrap(np.radians(np.asarray(headings, float))))


def _framed(facets: NDArray[np.float64], cams: NDArray[np.float64], headings: NDArray[np.float64],
            pitches: NDArray[np.float64], camera: CameraModel) -> NDArray[np.bool_]:
    """Facet centres (N, K) in view from cameras (N, 3) at headings (M,) and pitches (N,): shape (M, N, K)."""
    m, n = len(headings), len(cams)
    cam = np.broadcast_to(cams, (m, n, 3))
    hd = np.broadcast_to(headings[:, None], (m, n))
    pt = np.broadcast_to(pitches, (m, n))
    return in_fov(np.broadcast_to(facets, (m, *facets.shape)), cam, hd, pt, camera)


def _axis_offsets(cams: NDArray[np.float64], centres: NDArray[np.float64], headings: NDArray[np.float64],
                  pitches: NDArray[np.float64]) -> NDArray[np.float64]:
    """Angle between the optical axis and the direction to each HUA centre, degrees, shape (M, N)."""
    d = centres - cams
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    axis = optical_axis(np.broadcast_to(headings[:, None], (len(headings), len(cams))),
                        np.broadcast_to(pitches, (len(headings), len(cams))))
    return np.degrees(np.arccos(np.clip(np.sum(axis * d[None], axis=-1), -1.0, 1.0)))


def heading_runs(cams: NDArray[np.float64], centres: NDArray[np.float64], facets: NDArray[np.float64],
                 gaze_heading_deg: Sequence[float], pitch_deg: Sequence[float], camera: CameraModel,
                 max_offset_deg: float) -> list[tuple[int, int, float]]:
    """Split captures (in flight order) into runs flown at one heading.

    Parameters
    ----------
    cams : ndarray, shape (N, 3)
        Capture positions, ENU metres.
    centres : ndarray, shape (N, 3)
        Mirror centre of each capture's HUA, ENU metres.
    facets : ndarray, shape (N, K, 3)
        Facet centres of each capture's HUA, ENU metres.
    gaze_heading_deg, pitch_deg : sequence of float, length N
        Heading pointing at each HUA's mirror centre, and gimbal pitch, deg.
    camera : CameraModel
    max_offset_deg : float
        Largest angle between the optical axis and the direction to a HUA's
        centre, degrees (at steep pitch a heading change moves the HUA by
        much less than the heading change: it mostly rotates the image).

    Returns
    -------
    list of (start, stop, heading_deg)
        Runs ``captures[start:stop]`` and their heading in [0, 360).
    """
    n = len(cams)
    if n == 0:
        return []
    gaze = _unwrap(gaze_heading_deg)
    pitch = np.asarray(pitch_deg, float)
    own = in_fov(facets, cams, gaze, pitch, camera)  # (N, K): what each capture frames aimed at its own HUA

    def best_heading(a: int, b: int) -> float | None:
        lo, hi = float(gaze[a:b].min()), float(gaze[a:b].max())
        cand = np.arange(lo, hi + 0.5 * _GRID_DEG, _GRID_DEG) if hi - lo > _GRID_DEG else np.array([0.5 * (lo + hi)])
        cand = cand[(_axis_offsets(cams[a:b], centres[a:b], cand, pitch[a:b]) <= max_offset_deg + 1e-9).all(axis=1)]
        if len(cand) == 0:
            return None
        seen = _framed(facets[a:b], cams[a:b], cand, pitch[a:b], camera)  # (M, n, K)
        keeps = (seen.sum(axis=2) >= own[a:b].sum(axis=1)[None]).all(axis=1)  # no capture frames fewer facets
        if not keeps.any():
            return None
        cand, total = cand[keeps], seen[keeps].sum(axis=(1, 2))
        k = np.lexsort((np.abs(cand - 0.5 * (lo + hi)), -total))[0]
        return float(cand[k])

    runs: list[tuple[int, int, float]] = []
    a = 0
    while a < n:
        b, heading = a + 1, float(gaze[a])
        while b < n:
            h = best_heading(a, b + 1)
            if h is None:
                break
            b, heading = b + 1, h
        runs.append((a, b, heading % 360.0))
        a = b
    return runs


def steady_headings(passes: Sequence[ScanPass], pose: Any, *, camera: CameraModel | None = None,
                    max_offset_deg: float | None = None) -> tuple[ScanPass, ...]:
    """Passes with one heading per run of captures (module docstring).

    Parameters
    ----------
    passes : sequence of ScanPass
        Scored passes whose capture waypoints aim at their HUA (``hua`` set).
    pose : FieldPose
        The tracked field (facet centres of the HUAs).
    camera : CameraModel, optional
        Default Triton + 35 mm.
    max_offset_deg : float, optional
        Largest horizontal offset of a HUA's centre from the optical axis,
        degrees; default a quarter of the horizontal field of view. 0 keeps
        every capture aimed at its own HUA.

    Returns
    -------
    tuple of ScanPass
        Same passes, positions, pitches and speeds; capture headings replaced
        by their run's heading, lead-in and run-past headings by the first and
        last run's.
    """
    camera = camera or CameraModel()
    limit = 0.25 * camera.horizontal_fov_deg if max_offset_deg is None else max_offset_deg
    if isinstance(limit, bool) or not (isinstance(limit, (int, float)) and math.isfinite(limit)) or limit < 0:
        raise PihimInputError(f"max_offset_deg must be a number >= 0, got {max_offset_deg!r}")
    names = {n: k for k, n in enumerate(pose.field.names)}
    out: list[ScanPass] = []
    for p in passes:
        idx = [j for j, w in enumerate(p.waypoints) if w.capture and w.hua in names]
        if not idx or limit == 0:
            out.append(p)
            continue
        hua = np.array([names[p.waypoints[j].hua] for j in idx])  # type: ignore[index]
        cams = np.array([(p.waypoints[j].x_m, p.waypoints[j].y_m, p.waypoints[j].z_m) for j in idx])
        gaze, _ = gaze_angles(cams, pose.mirror_centres[hua])
        pitch = [p.waypoints[j].gimbal_pitch_deg for j in idx]
        runs = heading_runs(cams, pose.mirror_centres[hua], pose.facet_centres[hua], gaze.tolist(), pitch, camera,
                            float(limit))
        wps = list(p.waypoints)
        for a, b, heading in runs:
            for j in idx[a:b]:
                wps[j] = dataclasses.replace(wps[j], heading_deg=heading_0_360(heading))
        first, last = heading_0_360(runs[0][2]), heading_0_360(runs[-1][2])
        wps = [_edge_heading(w, j, idx, first, last) for j, w in enumerate(wps)]
        out.append(dataclasses.replace(p, waypoints=tuple(wps)))
    return tuple(out)


def _edge_heading(w: Waypoint, j: int, idx: list[int], first: float, last: float) -> Waypoint:
    """Lead-in (before the first capture) and run-past (after the last) waypoints face the nearest run."""
    if w.capture:
        return w
    if j < idx[0]:
        return dataclasses.replace(w, heading_deg=first)
    if j > idx[-1]:
        return dataclasses.replace(w, heading_deg=last)
    return w


def _turn(a: float, b: float) -> float:
    """Smallest angle from heading a to heading b, degrees in [0, 180]."""
    d = abs(float(b) - float(a)) % 360.0
    return min(d, 360.0 - d)


def turn_limited_speed(distance_m: float, turn_deg: float, pitch_change_deg: float, speed_m_s: float, *,
                       yaw_rate_deg_s: float = 30.0, gimbal_rate_deg_s: float = 30.0, settle_s: float = 0.5,
                       min_speed_m_s: float = 0.1) -> float:
    """Ground speed on a leg that leaves time to turn and re-pitch before its end.

    Needed: ``max(turn / yaw_rate, pitch change / gimbal_rate) + settle_s``
    seconds (nothing without a turn or pitch change); available:
    ``distance / speed``. Acceleration is neglected: a drone that starts the
    leg from a hover takes longer, which only adds time to turn.

    Parameters
    ----------
    distance_m : float
        Leg length, metres.
    turn_deg, pitch_change_deg : float
        Heading and gimbal-pitch changes over the leg, degrees.
    speed_m_s : float
        Planned speed, m/s (0 = the autopilot's default: kept).
    yaw_rate_deg_s, gimbal_rate_deg_s : float
        Turn and gimbal rates, deg/s.
    settle_s : float
        Margin after the turn, seconds.
    min_speed_m_s : float
        Never slower than this (a leg too short to turn on at this speed
        keeps it; the turn then ends after the waypoint).

    Returns
    -------
    float
        ``speed_m_s`` or a lower speed, m/s.
    """
    if speed_m_s <= 0 or distance_m <= 1e-6 or (turn_deg <= 1e-9 and abs(pitch_change_deg) <= 1e-9):
        return float(speed_m_s)
    need = max(turn_deg / yaw_rate_deg_s, abs(pitch_change_deg) / gimbal_rate_deg_s) + settle_s
    return float(min(speed_m_s, max(distance_m / need, min(min_speed_m_s, speed_m_s))))


def leg_speed(prev: Waypoint, w: Waypoint, *, yaw_rate_deg_s: float = 30.0, gimbal_rate_deg_s: float = 30.0,
              settle_s: float = 0.5) -> float:
    """Speed on the leg ``prev -> w`` that lets the drone arrive at ``w``'s heading and gimbal pitch.

    See :func:`turn_limited_speed`; take-off and landing waypoints keep
    their speed.
    """
    if w.kind in ("takeoff", "land"):
        return float(w.speed_m_s)
    dist = math.dist((prev.x_m, prev.y_m, prev.z_m), (w.x_m, w.y_m, w.z_m))
    return turn_limited_speed(dist, _turn(prev.heading_deg, w.heading_deg), w.gimbal_pitch_deg - prev.gimbal_pitch_deg,
                              float(w.speed_m_s), yaw_rate_deg_s=yaw_rate_deg_s, gimbal_rate_deg_s=gimbal_rate_deg_s,
                              settle_s=settle_s)
