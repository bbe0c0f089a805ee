"""Which facets of each assessed HUA show a heliostat's back in at least one planned capture.

A facet's canting can be measured only where the back of a heliostat (the
target) appears reflected in it (:mod:`pihim.inspection.canting`). For every
capture (a ``scan`` waypoint with ``capture=True`` naming its HUA) and every
facet of its HUA, :func:`facet_targets` samples the facet on a
``samples x samples`` grid of points ``q`` inside its four corners
(:meth:`pihim.field.kinematics.FieldPose.facet_corners`, design canting) and
traces, for each point:

* ``q`` in the camera's field of view at the waypoint's heading and gimbal
  pitch (:func:`pihim.planning.sightlines.in_fov`), seen from the front of
  the facet;
* the sight line camera -> ``q`` crossing no other tracked mirror rectangle
  and not the tower box;
* the camera ray reflected at ``q`` about the facet normal,
  ``r = d - 2 (d . n) n`` with ``d`` the unit vector from the camera to
  ``q`` (law of reflection), meeting first (nearest along ``r``, within
  :data:`REACH_M`, 60 m) the mirror rectangle of another heliostat
  (:meth:`~pihim.field.kinematics.FieldPose.mirror_outline`), *from behind*
  (``r . n_T > 0``), with the tower box not in between: the facet shows that
  heliostat's back, whose structure lies right behind its rectangle.

A facet shows the heliostat that most of its qualifying points show. The
union over a HUA's captures gives the facets covered, each with the first
capture that shows it and the heliostat seen (``shown_by``: the pair to
give :func:`pihim.inspection.pipeline` for that facet);
:func:`coverage_summary` gives the totals reported by ``pihim plan``
(``facet_coverage`` in the summary). :func:`facets_showing_target` is the
single-target test without occlusion (one capture, one named target).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from pihim import _forked
from pihim.camera.model import CameraModel
from pihim.errors import PihimInputError
from pihim.field.kinematics import facet_corners
from pihim.planning.model import ScanPass, Waypoint
from pihim.planning.sightlines import in_fov, segments_hit_box, tower_box

__all__ = ["FacetCoverage", "PendingTrace", "capture_key", "coverage_summary", "facet_coverage", "facet_targets",
           "facets_showing_target", "trace_captures"]


@dataclass(frozen=True)
class FacetCoverage:
    """Facets of one HUA that show a heliostat's back in at least one capture.

    Attributes
    ----------
    hua : str
    n_facets : int
    covered : tuple of int
        Facet indices (row-major, as ``HeliostatSpec.facet_centroids``).
    captures : int
        Captures of this HUA.
    shown_by : tuple of (int, (int, int, str))
        Per covered facet: (pass index, waypoint index, heliostat whose back
        it shows), the first capture that shows it.
    """

    hua: str
    n_facets: int
    covered: tuple[int, ...]
    captures: int
    shown_by: tuple[tuple[int, tuple[int, int, str]], ...] = ()

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


def _check_samples(samples: Any) -> None:
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise PihimInputError(f"samples must be a positive integer, got {samples!r}")


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
    _check_samples(samples)
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


def _first_hits_among(p0: NDArray[np.float64], d: NDArray[np.float64], table: NDArray[np.int64],
                      row: NDArray[np.int64], skip: NDArray[np.int64], pose: Any,
                      t_max: NDArray[np.float64] | float) -> NDArray[np.int64]:
    """First mirror rectangle met by each ray ``p0 + t d``, ``0 < t < t_max``, skipping ``skip``; -1 for none.

    Ray ``i`` is tested against the mirrors ``table[row[i]]`` (-1 padded), in one compiled pass
    (:func:`pihim.planning._kernels.first_hits_in_rows`); equal ``t``: the least mirror index.
    """
    from pihim.planning import _kernels

    spec = pose.field.spec
    n_r = len(p0)
    t_lim = np.ascontiguousarray(np.broadcast_to(np.asarray(t_max, float), (n_r,)))
    t_lim.flags.writeable = False  # read-only whether broadcast or copied: one compiled signature of the kernel
    rot = pose.rotations
    return _kernels.first_hits_in_rows(
        np.ascontiguousarray(p0, float), np.ascontiguousarray(d, float), np.ascontiguousarray(table, np.int64),
        np.ascontiguousarray(row, np.int64), np.ascontiguousarray(skip, np.int64), t_lim,
        np.ascontiguousarray(pose.normals, float), np.ascontiguousarray(pose.mirror_centres, float),
        np.ascontiguousarray(rot[:, :, 0], float), np.ascontiguousarray(rot[:, :, 1], float),
        float(spec.mirror_half_width_m), float(spec.mirror_half_height_m))


def _near(tree: cKDTree, xy: NDArray[np.float64], radius: NDArray[np.float64], skip: NDArray[np.int64]
          ) -> NDArray[np.int64]:
    """Heliostats within ``radius`` (horizontal) of each point, except ``skip``: (N, J) -1 padded."""
    lists = tree.query_ball_point(xy, radius, return_sorted=False)
    lens = np.fromiter(map(len, lists), dtype=np.int64, count=len(xy))
    out = np.full((len(xy), max(int(lens.max(initial=0)), 1)), -1, dtype=np.int64)
    flat = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(lens.sum()))
    row = np.repeat(np.arange(len(xy)), lens)
    keep = flat != np.asarray(skip)[row]
    flat, row = flat[keep], row[keep]
    out[row, np.arange(len(row)) - np.searchsorted(row, np.arange(len(xy)))[row]] = flat  # in the tree's order
    return out


#: Captures traced at once by :func:`facet_targets` (its temporaries are about 50 kB per capture: all the
#: captures of a 30,000-heliostat field at once peaked at 4.8 GB).
_CHUNK = 4096

#: How far reflected rays are followed by default, metres (:func:`facet_targets`, :func:`trace_captures`).
REACH_M = 60.0


class _Scene(NamedTuple):
    """What :func:`facet_targets` reads of the tracked field for every chunk of captures, worked out once."""

    radius: float  # a mirror's half-diagonal, metres
    box: Any  # the tower box (lo, hi) or None
    top: float  # the highest mirror point of the field, metres
    tree: cKDTree  # the mirror centres' x, y


def _scene(pose: Any, tower: Any) -> _Scene:
    spec = pose.field.spec
    return _Scene(float(np.hypot(spec.mirror_half_width_m, spec.mirror_half_height_m)), tower_box(tower),
                  float(pose.mirror_outline()[..., 2].max()), cKDTree(pose.mirror_centres[:, :2]))


def _chunk_job(pose: Any, h: NDArray[np.int64], cam: NDArray[np.float64], head: NDArray[np.float64],
               pitch: NDArray[np.float64], camera: CameraModel, samples: int, tower: Any,
               reach_m: float) -> Callable[[int], NDArray[np.int64]]:
    """:func:`facet_targets` of the ``i``-th chunk of :data:`_CHUNK` captures, as a job for :mod:`pihim._forked`
    (the field's k-d tree and extremes built once for all chunks: 0.07 s a chunk at 100,000 heliostats)."""
    scene = _scene(pose, tower)

    def chunk(i: int) -> NDArray[np.int64]:
        sl = slice(i * _CHUNK, (i + 1) * _CHUNK)
        return _targets(pose, scene, h[sl], cam[sl], head[sl], pitch[sl], camera, samples, reach_m)
    return chunk


def facet_targets(pose: Any, hua: Sequence[int], camera_xyz: ArrayLike, heading_deg: ArrayLike,
                  pitch_deg: ArrayLike, *, camera: CameraModel | None = None, samples: int = 3,
                  tower: Any = None, reach_m: float = REACH_M, workers: int | None = 1) -> NDArray[np.int64]:
    """The heliostat whose back each facet shows, per capture, traced ray by ray (module docstring).

    Parameters
    ----------
    pose : FieldPose
    hua : sequence of int, length C
        The HUA of each capture.
    camera_xyz : array_like, shape (C, 3)
        Camera positions, ENU metres.
    heading_deg, pitch_deg : array_like, shape (C,)
        Camera heading (clockwise from North) and pitch (negative down).
    camera : CameraModel, optional
        Field of view; default Triton + 35 mm.
    samples : int
        Sample points per facet side.
    tower : Tower, optional
        Its box blocks sight lines and reflected rays.
    reach_m : float
        Reflected rays are followed this far, metres.
    workers : int or None
        Processes tracing chunks of captures side by side (forked on Linux,
        :func:`pihim._forked.imap_unordered`; None: one per CPU). The result
        does not depend on it.

    Returns
    -------
    ndarray of int, shape (C, F)
        Heliostat index per facet, -1 where none shows a heliostat back: the
        one the facet's middle sample point shows (odd ``samples``), else
        the one most of its qualifying points show.

    Notes
    -----
    A mirror can hide a sight line only where the line is below the
    highest mirror point of the field, so the blockers tested for a capture
    are the mirrors within that stretch (plus a mirror half-diagonal) of the
    HUA: no blocker is missed. Likewise a reflected ray, which starts on a
    facet, can meet within ``reach_m`` only mirrors whose centres lie within
    ``reach_m`` plus two mirror half-diagonals of the HUA's centre; each ray
    is tested against those of its own capture that are not wholly behind
    the HUA's mirror plane. The other points of a facet are traced only
    where its middle point shows no heliostat back.
    """
    camera = camera or CameraModel()
    _check_samples(samples)
    h = np.asarray(hua, dtype=np.int64).reshape(-1)
    cam = np.asarray(camera_xyz, dtype=float).reshape(-1, 3)
    head = np.broadcast_to(np.asarray(heading_deg, float), h.shape)
    pitch = np.broadcast_to(np.asarray(pitch_deg, float), h.shape)
    n_f = pose.facet_centres.shape[1]
    out = np.full((len(h), n_f), -1, dtype=np.int64)
    if len(h) == 0:
        return out
    if len(h) > _CHUNK:  # captures are traced independently: in chunks, so that memory stays bounded
        chunk = _chunk_job(pose, h, cam, head, pitch, camera, samples, tower, reach_m)
        for i, part in _forked.imap_unordered(chunk, -(-len(h) // _CHUNK), workers, what="chunks of captures"):
            out[i * _CHUNK:(i + 1) * _CHUNK] = part
        return out
    return _targets(pose, _scene(pose, tower), h, cam, head, pitch, camera, samples, reach_m)


def _targets(pose: Any, scene: _Scene, h: NDArray[np.int64], cam: NDArray[np.float64], head: NDArray[np.float64],
             pitch: NDArray[np.float64], camera: CameraModel, samples: int, reach_m: float) -> NDArray[np.int64]:
    """:func:`facet_targets` of up to :data:`_CHUNK` captures, at least one."""
    spec = pose.field.spec
    n_f = pose.facet_centres.shape[1]
    radius, box, top, tree = scene
    corners = facet_corners(pose.rotations[h], pose.mirror_centres[h], spec.facet_centroids,
                            pose.facet_normals_local[h], spec.facet_width_m, spec.facet_height_m)  # (C, F, 4, 3)
    q = _grid(corners, samples)  # (C, F, S, 3)
    n_s = q.shape[2]
    d = q - cam[:, None, None, :]
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    n = np.broadcast_to(pose.facet_normals[h][:, :, None, :], q.shape)
    dn = np.sum(d * n, axis=-1)
    seen = in_fov(q.reshape(len(h), -1, 3), cam, head, pitch, camera).reshape(dn.shape)
    cand = (dn < 0.0) & seen  # (C, F, S)
    z0 = q[..., 2].min(axis=(1, 2))
    horiz = np.linalg.norm(cam[:, :2] - pose.mirror_centres[h, :2], axis=1) + radius
    frac = np.where(cam[:, 2] > top, np.clip((top - z0) / np.maximum(cam[:, 2] - z0, 1e-9), 0.0, 1.0), 1.0)
    blk = _near(tree, pose.mirror_centres[h, :2], horiz * frac + 2.0 * radius, h)
    h_xy = pose.mirror_centres[h, :2]
    fwd = pose.normals[h]
    # a reflected ray starts on a facet (within ``radius`` of the HUA's centre) and meets a mirror within
    # ``radius`` of that mirror's centre: every mirror it can meet within ``reach_m`` is in this row, less those
    # wholly behind the HUA's mirror plane (dropped just below; a grazing reflection off a canted facet could
    # in principle reach one)
    tg = _near(tree, h_xy, np.full(len(h), float(reach_m) + 2.0 * radius), h)
    behind = np.einsum("cjd,cd->cj", pose.mirror_centres[np.maximum(tg, 0)] - pose.mirror_centres[h][:, None, :],
                       fwd) < -radius  # wholly behind the HUA's mirror plane: out of a reflected ray's reach
    tg = np.where(behind, -1, tg)

    def trace(live: NDArray[np.int64]) -> NDArray[np.int64]:
        """Heliostat whose back the sample ``live`` (flat index into (C, F, S)) shows; -1 none."""
        out_ = np.full(len(live), -1, dtype=np.int64)
        if len(live) == 0:
            return out_
        order = np.argsort(h[live // (n_f * n_s)], kind="stable")  # grouped by HUA: neighbouring rays, rows
        live = live[order]
        ci = live // (n_f * n_s)
        qq, dd, nn = q.reshape(-1, 3)[live], d.reshape(-1, 3)[live], n.reshape(-1, 3)[live]
        dist = np.linalg.norm(cam[ci] - qq, axis=1)
        blocked = _first_hits_among(qq - 1e-6 * dd, -dd, blk, ci, h[ci], pose, dist - 1e-6) >= 0
        if box is not None:
            blocked |= segments_hit_box(cam[ci], qq - 1e-6 * dd, *box)
        r = dd - 2.0 * np.sum(dd * nn, axis=-1, keepdims=True) * nn
        hit = np.full(len(live), -1, dtype=np.int64)
        k = np.flatnonzero(~blocked)
        hit[k] = _first_hits_among(qq[k] + 1e-6 * r[k], r[k], tg, ci[k], h[ci[k]], pose, float(reach_m))
        ok = hit >= 0
        ok[ok] &= np.sum(r[ok] * pose.normals[hit[ok]], axis=-1) > 0.0
        if box is not None and np.any(ok):
            k = np.flatnonzero(ok)
            hc, hn = pose.mirror_centres[hit[k]], pose.normals[hit[k]]
            t = np.sum((hc - qq[k]) * hn, axis=-1) / np.sum(r[k] * hn, axis=-1)
            ok[k] &= ~segments_hit_box(qq[k] + 1e-6 * r[k], qq[k] + t[:, None] * r[k], *box)
        out_[order] = np.where(ok, hit, -1)
        return out_

    # the middle sample of each facet first; the others only where it shows nothing
    which = np.full(cand.shape, -1, dtype=np.int64)
    mid = (n_s - 1) // 2 if samples % 2 else None
    if mid is not None:
        first = cand.copy()
        first[..., [j for j in range(n_s) if j != mid]] = False
        sel = np.flatnonzero(first.ravel())
        which.reshape(-1)[sel] = trace(sel)
        rest = cand & ~first & ~(which[..., mid] >= 0)[..., None]
    else:
        rest = cand
    sel = np.flatnonzero(rest.ravel())
    which.reshape(-1)[sel] = trace(sel)
    out = (np.where(which[..., mid] >= 0, which[..., mid], -1) if mid is not None
           else np.full((len(h), n_f), -1, dtype=np.int64))
    todo = np.flatnonzero(((out < 0) & (which >= 0).any(axis=-1)).ravel())
    if len(todo):  # the heliostat most of the facet's other points show (the least index among equals)
        from pihim.planning import _kernels

        out.reshape(-1)[todo] = _kernels.row_modes(np.ascontiguousarray(which.reshape(-1, n_s)[todo]))
    return out


CaptureKey = tuple[str, float, float, float, float, float]


def capture_key(w: Waypoint) -> CaptureKey:
    """What :func:`facet_targets` traces of a capture: its HUA, camera position, heading and pitch."""
    return (str(w.hua), w.x_m, w.y_m, w.z_m, w.heading_deg, w.gimbal_pitch_deg)


def _captures(passes: Sequence[ScanPass], names: dict[str, int]) -> list[tuple[int, int, Waypoint]]:
    """(pass index, waypoint index, waypoint) of every capture naming its HUA, in plan order."""
    refs: list[tuple[int, int, Waypoint]] = []
    for p in passes:
        for j, w in enumerate(p.waypoints):
            if not w.capture or w.hua is None:
                continue
            if w.hua not in names:
                raise PihimInputError(f"pass {p.index}: unknown heliostat {w.hua!r}")
            refs.append((p.index, j, w))
    return refs


class PendingTrace:
    """The tracing of captures started by :func:`trace_captures`: :meth:`result` (``{capture_key: row of
    facet_targets}``) or :meth:`close` (in a ``finally``)."""

    def __init__(self, keys: list[CaptureKey], started: _forked.Started[NDArray[np.int64]]) -> None:
        self._keys, self._started = keys, started

    def result(self) -> dict[CaptureKey, NDArray[np.int64]]:
        parts = self._started.results()
        rows = np.concatenate(parts) if parts else np.zeros((0, 0), np.int64)
        return dict(zip(self._keys, rows, strict=True))

    @property
    def running(self) -> bool:
        """Whether workers trace (else :meth:`result` traces, in this process)."""
        return self._started.running

    def close(self) -> None:
        self._started.close()


def trace_captures(passes: Sequence[ScanPass], pose: Any, *, camera: CameraModel | None = None, samples: int = 3,
                   tower: Any = None, background: int = 0) -> PendingTrace:
    """Start tracing every capture of ``passes`` (:func:`facet_targets`) in forked workers and return at once.

    ``pihim plan`` starts the facet report's tracing before the route: the
    captures' positions and attitudes do not change when the route orders,
    reverses or cuts the passes (only their indices do), so ``background``
    workers trace while the route is worked out
    (:func:`pihim._forked.start`), and :func:`facet_coverage` takes the rows
    from ``result()``. With ``background=0`` the tracing runs in
    ``result()``, in this process.
    """
    camera = camera or CameraModel()
    _check_samples(samples)
    names = {nm: k for k, nm in enumerate(pose.field.names)}
    ws = [w for _, _, w in _captures(passes, names)]
    h = np.array([names[str(w.hua)] for w in ws], dtype=np.int64)
    cam = np.array([(w.x_m, w.y_m, w.z_m) for w in ws], dtype=float).reshape(-1, 3)
    head = np.array([w.heading_deg for w in ws], dtype=float)
    pitch = np.array([w.gimbal_pitch_deg for w in ws], dtype=float)
    job = _chunk_job(pose, h, cam, head, pitch, camera, samples, tower, REACH_M)
    return PendingTrace([capture_key(w) for w in ws],
                        _forked.start(job, -(-len(h) // _CHUNK), background, what="chunks of captures"))


def facet_coverage(passes: Sequence[ScanPass], pose: Any, *, camera: CameraModel | None = None,
                   samples: int = 3, tower: Any = None, workers: int | None = 1,
                   traced: dict[CaptureKey, NDArray[np.int64]] | None = None) -> dict[str, FacetCoverage]:
    """Facets of every imaged HUA that show a heliostat back in at least one capture (traced).

    Parameters
    ----------
    passes : sequence of ScanPass
        Passes whose capture waypoints name their HUA (``hua``).
    pose : FieldPose
        The tracked field the passes were planned for.
    camera : CameraModel, optional
    samples : int
        Sample points per facet side.
    tower : Tower, optional
        Blocks sight lines and reflected rays.
    workers : int or None
        Processes tracing side by side (:func:`facet_targets`).
    traced : dict, optional
        Rows of :func:`facet_targets` already traced, by :func:`capture_key`
        (:func:`trace_captures` with the same camera, samples and tower);
        captures not in it are traced here.

    Returns
    -------
    dict of str to FacetCoverage
        One entry per HUA with at least one capture, in first-capture order;
        ``shown_by`` says, per covered facet, which capture (pass index,
        waypoint index) and which heliostat's back (the first capture that
        shows it).
    """
    names = {nm: k for k, nm in enumerate(pose.field.names)}
    n_facets = pose.facet_centres.shape[1]
    refs = _captures(passes, names)
    known = traced or {}
    todo = [k for k, (_, _, w) in enumerate(refs) if capture_key(w) not in known]
    ws = [refs[k][2] for k in todo]
    new = facet_targets(pose, [names[str(w.hua)] for w in ws], np.array([(w.x_m, w.y_m, w.z_m) for w in ws]),
                        [w.heading_deg for w in ws], [w.gimbal_pitch_deg for w in ws], camera=camera,
                        samples=samples, tower=tower, workers=workers)
    rows = np.empty((len(refs), n_facets), np.int64)  # facet_targets' row of every capture
    rows[todo] = new
    fresh = set(todo)
    for k, (_, _, w) in enumerate(refs):
        if k not in fresh:
            rows[k] = known[capture_key(w)]
    # each HUA numbered in first-capture order; the first capture showing each (HUA, facet): the first
    # occurrence of its key among the covered (capture, facet) cells, which np.nonzero gives capture by capture
    huas = list(dict.fromkeys(str(w.hua) for _, _, w in refs))
    hid = {h: i for i, h in enumerate(huas)}
    which = np.array([hid[str(w.hua)] for _, _, w in refs], np.int64)
    kk, ff = np.nonzero(rows >= 0)
    keys, first = np.unique(which[kk] * n_facets + ff, return_index=True)  # sorted: by HUA, then facet
    cap, fac = kk[first], ff[first]
    names_of = np.asarray(pose.field.names, dtype=object)[rows[cap, fac]].tolist()
    refs_pi = np.array([pi for pi, _, _ in refs], np.int64)[cap].tolist()
    refs_j = np.array([j for _, j, _ in refs], np.int64)[cap].tolist()
    shown = list(zip(fac.tolist(), zip(refs_pi, refs_j, names_of, strict=True), strict=True))
    bounds = np.searchsorted(keys // n_facets, np.arange(len(huas) + 1)).tolist()
    count = np.bincount(which, minlength=len(huas)).tolist()
    out = {}
    for i, h in enumerate(huas):
        got = tuple(shown[bounds[i]:bounds[i + 1]])
        out[h] = FacetCoverage(h, n_facets, tuple(f for f, _ in got), count[i], got)
    return out


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
        "definition": "facets of the imaged HUAs that show a heliostat's back in at least one capture (facet "
                      "sampled 3x3: a point in the field of view, seen from the front with the sight line clear, "
                      "whose reflected camera ray meets another heliostat's mirror rectangle first and from behind; "
                      "mirrors are flat tracked rectangles, the tower a box)",
    }
