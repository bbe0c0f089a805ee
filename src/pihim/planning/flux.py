"""Concentrated sunlight near a tracking heliostat field (flight safety flag, paper section 3)."""

from __future__ import annotations

import itertools
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from pihim.field.kinematics import FieldPose
from pihim.planning.sightlines import dot

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
        self.centres = pose.mirror_centres
        self.axis = self.aim - self.centres
        self.length = np.linalg.norm(self.axis, axis=1)
        self.tree = cKDTree(-self.axis / self.length[:, None])  # unit vectors from the aim point toward the mirrors
        self.lmax = float(self.length.max())
        self.rmax = max(self.r0, self.lmax * self.theta)  # no beam is wider between its mirror and its focus
        self.z_lo, self.z_hi = float(self.centres[:, 2].min()), float(self.centres[:, 2].max())

    def concentration(self, points: ArrayLike) -> NDArray[np.float64]:
        """Suns at ``points`` (M, 3), ENU metres: shape (M,)."""
        pts = np.atleast_2d(np.asarray(points, float))
        a, r0, theta, c, axis, length, tree = (self.aim, self.r0, self.theta, self.centres, self.axis, self.length,
                                               self.tree)
        out = np.zeros(len(pts))
        rmax, lmax, z_lo, z_hi = self.rmax, self.lmax, self.z_lo, self.z_hi
        for s0 in range(0, len(pts), 20_000):
            p = pts[s0:s0 + 20_000]
            v = p - a
            dist = np.linalg.norm(v, axis=1)
            # a beam holding a point at height z is at most f_max of its way to the aim point there (its axis is
            # within the beam radius r of z), and r <= r0 + f_max L theta there: a narrower cone to search than rmax
            # for points low above the field (the flights). Fixed point of the two bounds, from rmax down.
            rad = np.full(len(p), rmax)
            if a[2] > z_hi:
                for _ in range(3):
                    f_max = np.clip((p[:, 2] + rad - z_lo) / (a[2] - z_hi), 0.0, 1.0)
                    rad = np.minimum(rmax, np.maximum(r0, r0 + f_max * lmax * theta))
            with np.errstate(divide="ignore", invalid="ignore"):
                q = v / dist[:, None]
                half = np.where(dist > rad, np.arcsin(np.minimum(1.0, rad / dist)), np.pi)
            q = np.where(np.isfinite(q), q, 0.0)
            lists = tree.query_ball_point(q, np.minimum(2.0, 2.0 * np.sin(np.minimum(half, np.pi / 2)) + 1e-12),
                                          return_sorted=False)
            lens = np.fromiter(map(len, lists), dtype=np.int64, count=len(p))
            if lens.sum() == 0:
                continue
            pi = np.repeat(np.arange(len(p)), lens)
            hi = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(lens.sum()))
            w = p[pi] - c[hi]
            e = axis[hi] / length[hi, None]
            along = dot(w, e)
            f = along / length[hi]
            perp = np.linalg.norm(w - along[:, None] * e, axis=1)
            radius = (1.0 - f) * r0 + f * length[hi] * theta
            inside = (f > 0) & (f <= 1.0) & (perp <= radius)
            np.add.at(out, s0 + pi[inside], (r0 / np.maximum(radius[inside], 1e-9)) ** 2)
        return out
