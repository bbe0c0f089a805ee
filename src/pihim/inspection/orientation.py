"""The HUA's and the target's orientation from the target's reflection (paper sec. 4.4, relative orientation).

:func:`search_orientation` is the paper's grid search (+-5 deg in 0.1 deg
steps) of the HUA's drive-angle errors; :func:`refine_orientations` solves
the target's drive angles, the HUA's turn and every facet's canting together
by robust least squares; :func:`drive_correction` expresses a canting-style
rotation of a whole heliostat as a change of its drive angles. Used by
:func:`pihim.inspection.canting.estimate_canting`.

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone", sec. 4.4 (grid search +-5 deg at 0.1 deg).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose
from pihim.errors import PihimInputError
from pihim.field.kinematics import FieldPose, apply_canting_deviation
from pihim.inspection.reflection import _apply, _FacetModel, _Mask, hua_turn_transform

__all__ = ["OrientationSearch", "PAPER_GRID_STEP_MRAD", "PAPER_ORIENTATION_SPAN_MRAD", "drive_correction",
           "refine_orientations", "search_orientation"]

#: The paper's grid step, 0.1 deg, in mrad.
PAPER_GRID_STEP_MRAD = float(np.radians(0.1) * 1e3)


#: Half-range of the paper's heliostat orientation search, +-5 deg, in mrad.
PAPER_ORIENTATION_SPAN_MRAD = float(np.radians(5.0) * 1e3)


@dataclass(frozen=True)
class OrientationSearch:
    """The paper's orientation grid search: the HUA's drive-angle error.

    Paper sec. 4.4: the relative orientation of the HUA and the target is
    corrected over +-5 deg in 0.1 deg steps until the facets' reflections of
    the target line up, before any facet is fitted; a facet's own search then
    spans +-1 deg around it. ``az_mrad`` / ``el_mrad`` are the HUA's drive
    azimuth and elevation errors (true minus logged, mrad) at the best grid
    node (:func:`hua_turn_transform`); ``score`` is the mean over the
    ``facets`` scored of the share of each facet's reflected target outline
    points that fall inside the facet within ``tol_px`` of an image edge
    there. ``alternatives`` are the next-best distinct peaks, ``(az_mrad,
    el_mrad, score)``, best first (at least half the best score), reported
    so that a user can see how clear the peak was: clutter can raise a false
    peak above the true one (the facet fits then keep the logged angles).
    """

    az_mrad: float
    el_mrad: float
    score: float
    facets: int
    span_mrad: float
    step_mrad: float
    tol_px: float
    seconds: float
    alternatives: tuple[tuple[float, float, float], ...] = ()

    def to_dict(self) -> dict[str, object]:
        out = {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in self.__dict__.items()}
        out["alternatives"] = [{"az_mrad": a, "el_mrad": e, "score": sc} for a, e, sc in self.alternatives]
        return out


def search_orientation(
    facets: list[tuple[_FacetModel, _Mask]],
    dt: NDArray,
    *,
    span_mrad: float = PAPER_ORIENTATION_SPAN_MRAD,
    step_mrad: float = PAPER_GRID_STEP_MRAD,
    tol_px: float = 5.0,
    block: int = 21,
    subsample: int = 96,
    highpass: int = 11,
    n_alternatives: int = 2,
) -> OrientationSearch:
    """The paper's heliostat orientation grid search (sec. 4.4): one pair of angles for every facet.

    Every node of the grid ``{-span, ..., span}^2`` (step ``step_mrad``;
    101 x 101 nodes for the paper's +-5 deg at 0.1 deg) is one pair of angles
    that every facet's model takes: the HUA's drive-angle errors for the
    models :func:`estimate_canting` passes (``_TurnModel``), or a common
    canting tilt for plain facet models; each facet scores the share of its reflected
    target outline points that fall inside its eroded mask within ``tol_px``
    of an image edge, and the node with the largest mean over the facets
    wins. (The share of the points *inside the mask* would not do: a node
    that leaves a few points in a facet, on some edge, would score high.)
    Facet canting errors (a few mrad) move each facet's reflection a little
    differently; the mean over the facets is what a common turn fixes.

    The projections are evaluated on blocks of ``block`` x ``block`` nodes
    from a quadratic through nine exact projections per block (the same
    scheme as a facet's own grid; a block spans 2 deg, where the quadratic is
    well under a pixel), with every ``subsample``-th outline point.

    Parameters
    ----------
    facets : list of (_FacetModel, _Mask)
        The facets to score, each with its target model (design canting) and
        eroded mask.
    dt : ndarray
        Distance transform of the edge-point image, pixels.
    n_alternatives : int
        How many next-best distinct peaks to return beside the best.

    Returns
    -------
    OrientationSearch
    """
    import time

    from scipy import ndimage

    from pihim.inspection import _kernels

    t0 = time.perf_counter()
    m = int(math.floor(span_mrad / step_mrad + 1e-9))
    grid = step_mrad * np.arange(-m, m + 1)  # symmetric, zero (the design) a node
    n = len(grid)
    total = np.zeros((n, n))
    scored = 0
    blocks = [grid[i:i + block] for i in range(0, n, block)]
    for model, mask in facets:
        sub_model = model.subsampled(subsample)
        if len(sub_model.pts) < 10:
            continue
        hh, ww = mask.sub.shape
        dt_crop = np.ascontiguousarray(dt[mask.r0:mask.r0 + hh, mask.c0:mask.c0 + ww])
        near = np.zeros((n, n))
        # every block's quadratic (blocks of one size at once)
        by_size: dict[float, list[tuple[int, int, float, float]]] = {}
        for i, ga in enumerate(blocks):
            for j, ge in enumerate(blocks):
                ca, ce = 0.5 * (ga[0] + ga[-1]), 0.5 * (ge[0] + ge[-1])
                s = max(float(np.max(np.abs(ga - ca))), float(np.max(np.abs(ge - ce))), 1.0)
                by_size.setdefault(s, []).append((i, j, ca, ce))
        for s, group in by_size.items():
            coefs = sub_model.quadratic_blocks(s, [(ca, ce) for _, _, ca, ce in group])
            for (i, j, ca, ce), coef in zip(group, coefs):
                ga, ge = blocks[i], blocks[j]
                _, nn = _kernels.grid_counts(np.ascontiguousarray(coef), ga - ca, ge - ce, mask.sub, mask.r0,
                                             mask.c0, dt_crop, float(tol_px))
                near[i * block:i * block + len(ga), j * block:j * block + len(ge)] = nn.reshape(len(ga), -1)
        if near.max() > 0:
            scored += 1
            # clutter (other heliostats' backs, the ground) raises a facet's counts over broad regions of
            # the grid; the target's reflection is a sharp peak: keep what stands above the local mean,
            # widened by a node either way (facets' own canting spreads their peaks by a few mrad)
            peak = np.clip(near - ndimage.uniform_filter(near, size=highpass, mode="nearest"), 0.0, None)
            total += ndimage.maximum_filter(peak, size=3, mode="nearest") / len(sub_model.pts)
    if scored == 0:
        raise PihimInputError("no facet shows the target's reflection anywhere within the orientation search")
    k = int(np.argmax(total))
    i, j = divmod(k, n)
    # the next-best distinct peaks (local maxima over +-3 nodes, at least half the best score)
    local = (total == ndimage.maximum_filter(total, size=7, mode="nearest")) & (total >= 0.5 * total[i, j])
    local[i, j] = False
    order = np.flatnonzero(local.ravel())
    order = order[np.argsort(-total.ravel()[order], kind="stable")][:max(n_alternatives, 0)]
    alternatives = tuple((float(grid[a]), float(grid[b]), float(total[a, b] / scored))
                         for a, b in (divmod(int(q), n) for q in order))
    return OrientationSearch(float(grid[i]), float(grid[j]), float(total[i, j] / scored), scored, float(span_mrad),
                             float(step_mrad), float(tol_px), time.perf_counter() - t0, alternatives)


def refine_orientations(
    camera: CameraModel,
    pose: CameraPose,
    field_pose: FieldPose,
    hua: int,
    target: int,
    facets: list[tuple[int, float, float, tuple[NDArray, NDArray, NDArray]]],
    *,
    max_deg: float = 5.0,
    hua_turn_deg: tuple[float, float] = (0.0, 0.0),
    solve_hua: bool = True,
    max_points: int = 300,
) -> tuple[tuple[float, float], tuple[float, float]]:
    """Corrections of the target's and the HUA's drive angles that best explain the target's reflections, degrees.

    The paper corrects the logged orientations before measuring canting
    (sec. 4.4). A target at a wrong logged orientation has a distorted
    outline in the model (its points move out of its plane by up to its
    half-width times the error); a HUA at a wrong logged orientation sees,
    through the camera pose fitted on it, the target turned back about the
    HUA's pivot (:func:`hua_turn_transform`): moved, which a common tilt of
    the facets nearly mimics, and turned, which it does not. Either leaves
    every facet's fit a few pixels off. Here the target's two drive angles,
    the HUA's two (``solve_hua``) and every facet's two canting angles are
    solved together by robust least squares (soft-L1, 0.5 px) on the
    point-to-line distances of the facets' last matches
    (:func:`pihim.inspection.canting._settle`'s ``matches``): the target's
    points turn about its pivot with its drive
    angles (mirror centre ``pivot + offset * normal``), then about the
    HUA's pivot with the HUA's turn, and each facet mirrors them in its
    plane. A common tilt of the facets and the HUA's turn differ only by
    that second-order picture, so the HUA's share is weakly determined; the
    facets' deviations relative to their mean are not affected.

    Parameters
    ----------
    facets : list of (facet index, az_mrad, el_mrad, (points, image points, line normals))
        The facets' fits (raw deviations) and their matches, made on the
        target's outline at its logged angles turned by ``hua_turn_deg``.
    max_deg : float
        Largest correction accepted per axis; beyond it the fit is not
        trusted and no correction is returned.
    hua_turn_deg : (float, float)
        The HUA's drive-angle error the matches were made with
        (:func:`hua_turn_transform`), degrees.
    solve_hua : bool
        Also correct the HUA's turn; otherwise it is held. The facets'
        mean canting is then held near zero by a weak penalty (1 px per
        mrad), as the HUA's turn and a common tilt nearly trade off.
    max_points : int
        Matches used per facet, at most (evenly along them).

    Returns
    -------
    ((d_az_target, d_el_target), (d_az_hua, d_el_hua))
        Degrees; the HUA's correction is on top of ``hua_turn_deg``.
    """
    from scipy.optimize import least_squares

    from pihim.field.kinematics import rotation_from_drive
    from pihim.inspection import _kernels

    none = ((0.0, 0.0), (0.0, 0.0))
    if not facets:
        return none
    d = field_pose.drive
    az0, el0 = float(d.azimuth_deg[target]), float(d.elevation_deg[target])
    r0 = field_pose.rotations[target]
    c0 = field_pose.mirror_centres[target]
    pivot = np.asarray(field_pose.field.pivots, float)[target]  # type: ignore[attr-defined]
    offset = float(field_pose.field.spec.pivot_offset_m)  # type: ignore[attr-defined]
    rot_h = field_pose.rotations[hua]
    cam = _kernels.camera_vector(camera)
    rc = np.array(pose.rotation, float)
    cc = np.array(pose.position_m, float)
    h_pivot, m0 = hua_turn_transform(field_pose, hua, *hua_turn_deg)
    h_az, h_el = float(d.azimuth_deg[hua]), float(d.elevation_deg[hua])
    r_log = rotation_from_drive(h_az, h_el)
    # at most ``max_points`` matches per facet, evenly along them: a few hundred fix two angles as well
    facets = [(f, a, e, tuple(np.asarray(v)[::max(1, -(-len(m[1]) // max_points))] for v in m))
              for f, a, e, m in facets]
    local = [(_apply((h_pivot, m0.T), m[0]) - c0) @ r0 for _, _, _, m in facets]  # target frame
    sizes = [len(m[1]) for *_, m in facets]
    starts = np.concatenate([[0], np.cumsum(sizes)])
    centres = [field_pose.facet_centres[hua, f] for f, *_ in facets]
    normals_local = [field_pose.facet_normals_local[hua, f] for f, *_ in facets]
    n_o = 4 if solve_hua else 2
    n_f = len(facets)
    # the facets' mean canting is held near zero (weight ``mean_weight`` px per mrad): with the HUA's turn
    # free, a common tilt of the facets and the turn nearly trade off, and the turn takes the common part
    mean_weight = 1.0 if solve_hua else 0.0

    def block(x_o: NDArray, x_f: NDArray, k: int) -> NDArray:
        """Point-to-line residuals of facet ``k`` at orientation ``x_o`` and its canting ``x_f``."""
        rt = rotation_from_drive(az0 + x_o[0], el0 + x_o[1])
        ct = pivot + offset * rt[:, 2]
        world = (h_pivot, m0) if not solve_hua else \
            (h_pivot, r_log @ rotation_from_drive(h_az + hua_turn_deg[0] + x_o[2], h_el + hua_turn_deg[1] + x_o[3]).T)
        m = facets[k][3]
        p = _apply(world, ct + local[k] @ rt.T)
        n = rot_h @ apply_canting_deviation(normals_local[k], x_f[0], x_f[1])
        virt = p - 2.0 * ((p - centres[k]) @ n)[:, None] * n
        uv = _kernels.project_rc(rc, cc, np.ascontiguousarray(virt), cam)
        return np.nan_to_num(np.sum((uv - m[1]) * m[2], axis=1), nan=10.0)

    def residuals(x: NDArray) -> NDArray:
        out = np.empty(starts[-1] + 2)
        for k in range(n_f):
            out[starts[k]:starts[k + 1]] = block(x[:n_o], x[n_o + 2 * k:n_o + 2 * k + 2], k)
        xf = x[n_o:].reshape(n_f, 2)
        out[starts[-1]:] = mean_weight * xf.mean(axis=0)
        return out

    def jacobian(x: NDArray) -> object:
        # each facet's residuals depend on the orientation angles and its own two: forward differences
        # per facet (n_o + 2 evaluations of that facet's block), the mean rows analytic
        jac = np.zeros((int(starts[-1]) + 2, n_o + 2 * n_f))
        for k in range(n_f):
            xo, xf = x[:n_o].copy(), x[n_o + 2 * k:n_o + 2 * k + 2].copy()
            r0 = block(xo, xf, k)
            idx = np.arange(starts[k], starts[k + 1])
            for j in range(n_o + 2):
                step = (1e-5 if j < n_o else 1e-3)
                xo2, xf2 = xo.copy(), xf.copy()
                if j < n_o:
                    xo2[j] += step
                    col = j
                else:
                    xf2[j - n_o] += step
                    col = n_o + 2 * k + j - n_o
                jac[idx, col] = (block(xo2, xf2, k) - r0) / step
        for a in range(2):
            jac[starts[-1] + a, n_o + 2 * np.arange(n_f) + a] = mean_weight / n_f
        return jac

    n_p = n_o + 2 * n_f
    x0 = np.concatenate([np.zeros(n_o), np.ravel([[a, e] for _, a, e, _ in facets])])
    scale = np.concatenate([np.full(n_o, 0.01), np.full(n_p - n_o, 0.1)])
    fit = least_squares(residuals, x0, jac=jacobian, loss="soft_l1", f_scale=0.5, x_scale=scale, max_nfev=50,
                        tr_solver="exact")
    corr = np.asarray(fit.x[:n_o], float)
    if not np.all(np.abs(corr) <= max_deg):
        return none
    return (float(corr[0]), float(corr[1])), ((float(corr[2]), float(corr[3])) if solve_hua else (0.0, 0.0))


def drive_correction(field_pose: FieldPose, index: int, az_mrad: float, el_mrad: float) -> tuple[float, float]:
    """A canting-style rotation of a whole heliostat as a change of its drive angles, degrees.

    The heliostat's normal (its frame's ``z``) tilted by ``(az_mrad,
    el_mrad)`` (:func:`pihim.field.kinematics.apply_canting_deviation`) has
    drive angles that differ from the logged ones by the returned
    ``(d_azimuth, d_elevation)`` (azimuth wrapped to [-180, 180)).
    """
    from pihim.field.kinematics import drive_angles

    rot = field_pose.rotations[index]
    n0 = rot[:, 2]
    n1 = rot @ apply_canting_deviation(np.array([0.0, 0.0, 1.0]), az_mrad, el_mrad)
    d0, d1 = drive_angles(n0), drive_angles(n1)
    d_az = (float(d1.azimuth_deg) - float(d0.azimuth_deg) + 180.0) % 360.0 - 180.0
    return d_az, float(d1.elevation_deg) - float(d0.elevation_deg)
