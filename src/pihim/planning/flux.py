"""Concentrated sunlight near a tracking heliostat field (flight safety flag, paper section 3)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.field.kinematics import FieldPose
from pihim.planning.sightlines import grid_cells

__all__ = ["Beams", "beam_concentration"]


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
    return Beams(pose, aim_point, divergence_mrad=divergence_mrad).concentration(points)


class Beams:
    """The beams of a tracked field toward its aim point, indexed once for many
    :meth:`concentration` calls (:func:`beam_concentration` for the model).

    The index is a uniform grid over the x, y components of the unit vectors
    from the aim point toward the mirror centres (each beam's direction seen
    from its focus). A point whose direction from the aim point is ``q`` can
    lie in a beam only if the beam's direction is within a chord of ``q``
    that the point's height bounds (:meth:`concentration`); the beams of the
    grid cells meeting that chord's square around ``q`` are tested, in one
    compiled pass (:func:`pihim.planning._kernels.beam_suns`).

    Parameters
    ----------
    pose : FieldPose
    aim_point : array_like, shape (3,)
        ENU metres.
    divergence_mrad : float
        Beam half-angle at the focus, mrad.
    """

    def __init__(self, pose: FieldPose, aim_point: ArrayLike, *, divergence_mrad: float = 7.0) -> None:
        self.aim = np.asarray(aim_point, float)
        spec = pose.field.spec  # type: ignore[attr-defined]
        self.r0 = math.sqrt(4.0 * spec.mirror_half_width_m * spec.mirror_half_height_m / math.pi)
        self.theta = divergence_mrad * 1e-3
        self.centres = np.ascontiguousarray(pose.mirror_centres, dtype=float)
        self.axis = self.aim - self.centres
        self.length = np.linalg.norm(self.axis, axis=1)
        self.e = self.axis / self.length[:, None]  # unit beam axes, mirror -> aim point
        self.u = np.ascontiguousarray(-self.e)  # unit vectors from the aim point toward the mirrors
        ok = np.isfinite(self.length)  # a mirror centre that is not finite has no beam (it is in no grid cell)
        self.any_beam = bool(ok.any())
        self.lmax = float(self.length[ok].max(initial=0.0))
        self.rmax = max(self.r0, self.lmax * self.theta)  # no beam is wider between its mirror and its focus
        self.z_lo = float(self.centres[ok, 2].min(initial=np.inf))
        self.z_hi = float(self.centres[ok, 2].max(initial=-np.inf))
        # the grid over u's x, y: cells about the chord a point low above the field searches (2 r0 / L at a
        # typical slant range L), at most about 4 N + 10,000 of them; a beam whose direction is not finite is in
        # no cell (it holds no finite point either)
        uxy = self.u[:, :2]
        finite = np.isfinite(uxy).all(axis=1)
        lo, hi = (uxy[finite].min(axis=0), uxy[finite].max(axis=0)) if finite.any() else (np.zeros(2), np.zeros(2))
        span = hi - lo
        typical = 2.0 * self.r0 / float(np.median(self.length[finite])) if finite.any() else 1.0
        budget = 4 * len(uxy) + 10_000
        cell = max(typical, math.sqrt(float(span[0]) * float(span[1]) / budget), float(span[0] + span[1]) / budget,
                   1e-6)
        self.grid = grid_cells(uxy, lo, span, cell)

    def concentration(self, points: ArrayLike) -> NDArray[np.float64]:
        """Suns at ``points`` (M, 3), ENU metres: shape (M,)."""
        from pihim.planning import _kernels

        p = np.ascontiguousarray(np.atleast_2d(np.asarray(points, float)))
        if not self.any_beam:
            return np.zeros(len(p))
        a, r0, rmax, lmax, z_lo, z_hi = self.aim, self.r0, self.rmax, self.lmax, self.z_lo, self.z_hi
        v = p - a
        dist = np.linalg.norm(v, axis=1)
        # a beam holding a point at height z is at most f_max of its way to the aim point there (its axis is
        # within the beam radius r of z), and r <= r0 + f_max L theta there: a narrower cone to search than rmax
        # for points low above the field (the flights). Fixed point of the two bounds, from rmax down.
        rad = np.full(len(p), rmax)
        if a[2] > z_hi:
            for _ in range(3):
                f_max = np.clip((p[:, 2] + rad - z_lo) / (a[2] - z_hi), 0.0, 1.0)
                rad = np.minimum(rmax, np.maximum(r0, r0 + f_max * lmax * self.theta))
        # the beams holding the point are seen from the aim point within the half-angle of a ball of radius rad
        # around it, i.e. within this chord of its direction q (every beam for a point at the aim point)
        with np.errstate(divide="ignore", invalid="ignore"):
            q = v / dist[:, None]
            half = np.where(dist > rad, np.arcsin(np.minimum(1.0, rad / dist)), np.pi)
        q = np.ascontiguousarray(np.where(np.isfinite(q), q, 0.0))
        chord = np.minimum(2.0, 2.0 * np.sin(np.minimum(half, np.pi / 2)) + 1e-12)
        g = self.grid
        return _kernels.beam_suns(p, q, chord, g.order, g.cell_start, g.x0, g.y0, g.cell, g.n_x, g.n_y, self.u,
                                  self.centres, self.e, self.length, r0, self.theta)
