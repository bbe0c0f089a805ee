"""Which facets of each assessed HUA show the target's reflection in at least one planned capture.

A facet's canting can be measured only where the target heliostat's
reflection appears in it. For every capture (a ``scan`` waypoint imaging a
HUA-target pair, :attr:`pihim.planning.model.PairPrediction.waypoint_index`)
and every facet of its HUA, :func:`facet_coverage` samples the facet on a
``samples x samples`` grid of points inside its four corners
(:meth:`pihim.field.kinematics.FieldPose.facet_corners`, design canting) and
counts the facet as showing the target when, for at least one sample point
``q``:

* ``q`` is in the camera's field of view at the waypoint's heading and gimbal
  pitch (:func:`pihim.planning.sightlines.in_fov`), seen from the front of
  the facet; and
* the camera ray reflected at ``q`` about the facet normal,
  ``r = d - 2 (d . n) n`` with ``d`` the unit vector from the camera to
  ``q`` (law of reflection), meets the target's mirror rectangle
  (:meth:`~pihim.field.kinematics.FieldPose.mirror_outline`): its back
  structure lies right behind that rectangle.

Occlusion by other heliostats is not tested here (the planner already checks
the HUA's corners and the reflected ray at the HUA centre). The union over a
HUA's captures gives the facets covered; :func:`coverage_summary` gives the
totals reported by ``pihim plan`` (``facet_coverage`` in the summary).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pihim.camera.model import CameraModel
from pihim.errors import PihimInputError
from pihim.planning.model import ScanPass
from pihim.planning.sightlines import in_fov

__all__ = ["FacetCoverage", "coverage_summary", "facet_coverage", "facets_showing_target"]


@dataclass(frozen=True)
class FacetCoverage:
    """Facets of one HUA that show the target's reflection in at least one capture.

    Attributes
    ----------
    hua : str
    n_facets : int
    covered : tuple of int
        Facet indices (row-major, as ``HeliostatSpec.facet_centroids``).
    captures : int
        Captures of this HUA.
    """

    hua: str
    n_facets: int
    covered: tuple[int, ...]
    captures: int

    @property
    def fraction(self) -> float:
        """Share of the HUA's facets covered."""
        return len(self.covered) / self.n_facets if self.n_facets else 0.0

    @property
    def missing(self) -> tuple[int, ...]:
        """Facets not covered."""
        return tuple(sorted(set(range(self.n_facets)) - set(self.covered)))


def _grid(corners: NDArray[np.float64], samples: int) -> NDArray[np.float64]:
    """Sample points inside each quad (..., 4, 3) (TL, TR, BR, BL): shape (..., samples**2, 3)."""
    t = (np.arange(samples) + 0.5) / samples
    u, v = np.meshgrid(t, t, indexing="ij")
    u, v = u.ravel(), v.ravel()
    tl, tr, br, bl = (corners[..., k, None, :] for k in range(4))
    top = tl + u[:, None] * (tr - tl)
    bottom = bl + u[:, None] * (br - bl)
    return top + v[:, None] * (bottom - top)


def _hits_quad(p: NDArray[np.float64], r: NDArray[np.float64], quad: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether rays ``p + s r`` (s > 0) meet the planar convex quads ``quad`` (..., 4, 3) (broadcast)."""
    a, b, c = quad[..., 0, :], quad[..., 1, :], quad[..., 3, :]
    n = np.cross(b - a, c - a)
    den = np.sum(r * n, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.sum((a - p) * n, axis=-1) / den
    x = p + s[..., None] * r
    inside = np.ones(s.shape, dtype=bool)
    for k in range(4):
        e0, e1 = quad[..., k, :], quad[..., (k + 1) % 4, :]
        inside &= np.sum(np.cross(e1 - e0, x - e0) * n, axis=-1) >= 0.0
    return inside & (s > 1e-9) & np.isfinite(s)


def facets_showing_target(pose: Any, hua: int, target: int, camera_xyz: Sequence[float], heading_deg: float,
                          pitch_deg: float, *, camera: CameraModel | None = None,
                          samples: int = 3) -> NDArray[np.bool_]:
    """Which facets of heliostat ``hua`` show heliostat ``target`` from one camera pose (module docstring).

    Parameters
    ----------
    pose : FieldPose
    hua, target : int
        Heliostat indices.
    camera_xyz : sequence of 3 float
        Camera position, ENU metres.
    heading_deg, pitch_deg : float
        Camera heading (clockwise from North) and pitch (negative down).
    camera : CameraModel, optional
        Field of view; default Triton + 35 mm.
    samples : int
        Sample points per facet side.

    Returns
    -------
    ndarray of bool, shape (F,)
    """
    camera = camera or CameraModel()
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise PihimInputError(f"samples must be a positive integer, got {samples!r}")
    corners = pose.facet_corners()[hua]  # (F, 4, 3)
    q = _grid(corners, samples)  # (F, S, 3)
    cam = np.asarray(camera_xyz, dtype=float)
    d = q - cam
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    n = pose.facet_normals[hua][:, None, :]  # (F, 1, 3)
    front = np.sum(d * n, axis=-1) < 0.0  # the camera sees the mirror side
    r = d - 2.0 * np.sum(d * n, axis=-1, keepdims=True) * n
    hit = _hits_quad(q, r, pose.mirror_outline()[target][None, None])
    seen = in_fov(q.reshape(-1, 3), cam, np.float64(heading_deg), np.float64(pitch_deg), camera).reshape(q.shape[:2])
    return np.any(front & hit & seen, axis=1)


def facet_coverage(passes: Sequence[ScanPass], pose: Any, *, camera: CameraModel | None = None,
                   samples: int = 3) -> dict[str, FacetCoverage]:
    """Facets of every imaged HUA that show its target in at least one capture.

    Parameters
    ----------
    passes : sequence of ScanPass
        Scored passes (their predictions name each capture's HUA, target and
        waypoint).
    pose : FieldPose
        The tracked field the passes were planned for.
    camera : CameraModel, optional
    samples : int
        Sample points per facet side.

    Returns
    -------
    dict of str to FacetCoverage
        One entry per HUA with at least one capture, in first-capture order.
    """
    names = {nm: k for k, nm in enumerate(pose.field.names)}
    n_facets = pose.facet_centres.shape[1]
    covered: dict[str, NDArray[np.bool_]] = {}
    count: dict[str, int] = {}
    for p in passes:
        for pr in p.predictions:
            w = p.waypoints[pr.waypoint_index]
            if pr.hua not in names or pr.target not in names:
                raise PihimInputError(f"pass {p.index}: unknown heliostat {pr.hua!r} or {pr.target!r}")
            seen = facets_showing_target(pose, names[pr.hua], names[pr.target], (w.x_m, w.y_m, w.z_m),
                                         w.heading_deg, w.gimbal_pitch_deg, camera=camera, samples=samples)
            covered[pr.hua] = covered.get(pr.hua, np.zeros(n_facets, dtype=bool)) | seen
            count[pr.hua] = count.get(pr.hua, 0) + 1
    return {h: FacetCoverage(h, n_facets, tuple(np.flatnonzero(m).tolist()), count[h]) for h, m in covered.items()}


def coverage_summary(coverage: dict[str, FacetCoverage]) -> dict[str, Any]:
    """Totals: HUAs, facets, facets covered, their fraction and the HUAs with every facet covered."""
    facets = sum(c.n_facets for c in coverage.values())
    got = sum(len(c.covered) for c in coverage.values())
    return {
        "huas": len(coverage),
        "facets": facets,
        "facets_covered": got,
        "fraction": got / facets if facets else 0.0,
        "huas_complete": sum(len(c.covered) == c.n_facets for c in coverage.values()),
        "definition": "facets of the imaged HUAs in which the target's reflection appears in at least one capture "
                      "(facet sampled 3x3, in the field of view, reflected camera ray meets the target's mirror "
                      "rectangle; occlusion not tested)",
    }
