"""Renderable scene: heliostat facets, back structure, tower and ground as rectangles.

Everything the camera can see is a rectangle in the field frame (ENU,
metres) above an analytic ground plane ``z = a + b x + c y``:

* every facet of every heliostat is one rectangle whose plane normal is the
  facet normal (with its own canting deviation); seen from the front it is a
  mirror, seen from the back it is the painted back of the facet. The gaps
  between facets are simply where no rectangle is;
* the back structure of :func:`pihim.field.kinematics.back_structure`
  (torque tube, one rib per facet column, one crossbar per facet row, the
  pedestal) as square-section boxes, six rectangles each;
* the tower as its box (top and four sides).

Each rectangle carries a surface kind (:data:`FACET`, :data:`STRUCTURE`,
:data:`TOWER`), the index of its heliostat (-1 for the tower or other
objects) and its facet number (1..F, 0 for none), which the renderer turns
into label images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError
from pihim.field.kinematics import FieldPose
from pihim.render.bvh import RectangleBVH, build_bvh

__all__ = [
    "FACET",
    "STRUCTURE",
    "TOWER",
    "Scene",
    "StructureSizes",
    "box_rectangles",
    "field_scene",
    "fit_ground_plane",
    "rectangle_scene",
]

#: Surface kinds of scene rectangles.
FACET, STRUCTURE, TOWER = 0, 1, 2


@dataclass(frozen=True)
class StructureSizes:
    """Square cross-section widths of the schematic back-structure members, metres.

    NSTTF heliostats have a torque tube of about 0.25 m and lighter ribs and
    crossbars; the figures are representative, not surveyed.
    """

    torque_tube_m: float = 0.20
    rib_m: float = 0.08
    crossbar_m: float = 0.08
    pedestal_m: float = 0.35

    def width(self, kind: str) -> float:
        return float({"torque_tube": self.torque_tube_m, "rib": self.rib_m, "crossbar": self.crossbar_m,
                      "pedestal": self.pedestal_m}[kind])


@dataclass(frozen=True, eq=False)
class Scene:
    """Rectangles with their labels, the BVH over them, and the ground plane.

    Attributes
    ----------
    bvh : RectangleBVH
        Geometry and acceleration structure.
    kind : ndarray of int8, shape (P,)
        :data:`FACET`, :data:`STRUCTURE` or :data:`TOWER`.
    heliostat : ndarray of int32, shape (P,)
        Heliostat index (-1: none).
    facet : ndarray of int16, shape (P,)
        Facet number 1..F (0: not a facet).
    group : ndarray of int64, shape (P,)
        Surface id for edge detection: rectangles that render as one smooth
        surface share it (the pieces of one face of a structure member), so
        their joints are not taken for edges and supersampled.
    ground : tuple of 3 float or None
        Ground plane ``z = a + b x + c y`` as ``(a, b, c)``; None: no ground
        (rays that miss everything see the sky, also downward).
    heliostat_names : tuple of str
        Names by heliostat index.
    """

    bvh: RectangleBVH
    kind: NDArray[np.int8]
    heliostat: NDArray[np.int32]
    facet: NDArray[np.int16]
    ground: tuple[float, float, float] | None
    heliostat_names: tuple[str, ...] = ()
    group: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        if self.group is None:
            object.__setattr__(self, "group", np.arange(self.kind.shape[0], dtype=np.int64))

    @property
    def n_rectangles(self) -> int:
        return self.bvh.n_primitives

    def ground_height(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
        """Ground height ``z`` at ``(x, y)``, metres (NaN without ground)."""
        if self.ground is None:
            return np.full(np.broadcast_shapes(np.shape(x), np.shape(y)), np.nan)
        a, b, c = self.ground
        return a + b * np.asarray(x, float) + c * np.asarray(y, float)


def box_rectangles(
    p0: ArrayLike, p1: ArrayLike, width: ArrayLike, up_hint: ArrayLike
) -> tuple[NDArray, NDArray, NDArray]:
    """The six faces of square-section boxes around segments, as rectangles.

    Parameters
    ----------
    p0, p1 : array_like, shape (M, 3)
        Segment end points (the box axis), metres.
    width : float or array_like, shape (M,)
        Side of the square cross-section, metres.
    up_hint : array_like, shape (M, 3) or (3,)
        A direction not parallel to the segments; one side of each box is
        perpendicular to it (used to align member boxes with the mirror).

    Returns
    -------
    origin, edge_u, edge_v : ndarray, shape (M * 6, 3)
        Faces with outward normals ``edge_u x edge_v``.
    """
    p0 = np.asarray(p0, float).reshape(-1, 3)
    p1 = np.asarray(p1, float).reshape(-1, 3)
    w = np.broadcast_to(np.asarray(width, float), (p0.shape[0],))
    a = p1 - p0
    length = np.linalg.norm(a, axis=1)
    if np.any(length <= 0):
        raise PihimInputError("structure members must have non-zero length")
    ah = a / length[:, None]
    hint = np.broadcast_to(np.asarray(up_hint, float), p0.shape)
    b = np.cross(hint, ah)
    weak = np.linalg.norm(b, axis=1) < 1e-9
    if np.any(weak):
        b[weak] = np.cross(np.array([1.0, 0.0, 0.0]), ah[weak])
        still = np.linalg.norm(b, axis=1) < 1e-9
        b[still] = np.cross(np.array([0.0, 1.0, 0.0]), ah[still])
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    c = np.cross(ah, b)
    hb = 0.5 * w[:, None] * b
    hc = 0.5 * w[:, None] * c
    corner = p0 - hb - hc  # the (-b, -c) corner at the start
    wb = 2 * hb
    wc = 2 * hc
    # (a, b, c) is right-handed (a x b = c, b x c = a, c x a = b); each face's (u, v) is
    # ordered so that u x v is its outward normal: -c, +c, -b, +b, -a, +a
    faces_o = [corner, corner + wc, corner, corner + wb, corner, corner + a]
    faces_u = [wb, a, a, wc, wc, wb]
    faces_v = [a, wb, wc, a, wb, wc]
    o = np.stack(faces_o, axis=1).reshape(-1, 3)
    u = np.stack(faces_u, axis=1).reshape(-1, 3)
    v = np.stack(faces_v, axis=1).reshape(-1, 3)
    return o, u, v


def rectangle_scene(
    origin: ArrayLike,
    edge_u: ArrayLike,
    edge_v: ArrayLike,
    kind: ArrayLike = FACET,
    *,
    ground: tuple[float, float, float] | None = None,
) -> Scene:
    """A scene of free rectangles (tests, oracles, small set-ups).

    Parameters
    ----------
    origin, edge_u, edge_v : array_like, shape (P, 3)
        Corner and perpendicular edges; the front (mirror side of a
        :data:`FACET`) is the side ``edge_u x edge_v`` points to.
    kind : int or array_like, shape (P,)
        Surface kinds.
    ground : (a, b, c), optional
        Ground plane ``z = a + b x + c y``.

    Returns
    -------
    Scene
        Each rectangle is its own "heliostat" ``i`` with facet number 1.
    """
    bvh = build_bvh(np.atleast_2d(np.asarray(origin, float)), np.atleast_2d(np.asarray(edge_u, float)),
                    np.atleast_2d(np.asarray(edge_v, float)))
    n = bvh.n_primitives
    k = np.broadcast_to(np.asarray(kind, np.int8), (n,)).copy()
    if np.any((k < FACET) | (k > TOWER)):
        raise PihimInputError("rectangle kinds must be FACET, STRUCTURE or TOWER")
    return Scene(bvh, k, np.arange(n, dtype=np.int32), np.ones(n, np.int16), ground,
                 tuple(f"R{i}" for i in range(n)))


def fit_ground_plane(points: ArrayLike) -> tuple[float, float, float]:
    """Least-squares plane ``z = a + b x + c y`` through ground points (e.g. under the pivots).

    A single point (or points on a line) gives a level plane through their
    mean height.
    """
    p = np.asarray(points, float).reshape(-1, 3)
    if p.shape[0] == 0 or not np.all(np.isfinite(p)):
        raise PihimInputError("ground points must be finite and at least one")
    if p.shape[0] < 3:
        return float(p[:, 2].mean()), 0.0, 0.0
    a_mat = np.column_stack([np.ones(len(p)), p[:, 0], p[:, 1]])
    coef, *_ = np.linalg.lstsq(a_mat, p[:, 2], rcond=None)
    if np.linalg.matrix_rank(a_mat) < 3:
        return float(p[:, 2].mean()), 0.0, 0.0
    return float(coef[0]), float(coef[1]), float(coef[2])


def field_scene(
    pose: FieldPose,
    facet_normals_local: ArrayLike | None = None,
    *,
    structure: bool = True,
    tower: bool = True,
    ground: bool = True,
    sizes: StructureSizes = StructureSizes(),
) -> Scene:
    """The scene of a tracked field: facets, back structure, tower and ground.

    Parameters
    ----------
    pose : FieldPose
        The tracked field (:func:`pihim.field.track_field`).
    facet_normals_local : array_like, shape (N, F, 3), optional
        Actual facet normals in each heliostat frame (design canting plus
        deviations, :func:`pihim.field.apply_canting_deviation`); default the
        design normals of ``pose``.
    structure, tower, ground : bool
        Include the back structure, the tower box and the ground plane (fitted
        to the ground under the pivots).
    sizes : StructureSizes
        Member widths.

    Returns
    -------
    Scene
    """
    field = pose.field
    spec = field.spec  # type: ignore[attr-defined]
    n_h = len(pose.normals)
    normals_local = pose.facet_normals_local if facet_normals_local is None else np.asarray(facet_normals_local, float)
    if normals_local.shape != pose.facet_normals_local.shape:
        raise PihimInputError(
            f"facet normals must have shape {pose.facet_normals_local.shape}, got {normals_local.shape}"
        )
    corners = pose.facet_corners(normals_local)  # (N, F, 4, 3): TL, TR, BR, BL from the front
    n_f = corners.shape[1]
    bl = corners[:, :, 3]
    o = [bl.reshape(-1, 3)]
    u = [(corners[:, :, 2] - bl).reshape(-1, 3)]  # toward +x (right)
    v = [(corners[:, :, 0] - bl).reshape(-1, 3)]  # toward +y (up): u x v = facet normal (front)
    kinds = [np.full(n_h * n_f, FACET, np.int8)]
    owner = [np.repeat(np.arange(n_h, dtype=np.int32), n_f)]
    facet_no = [np.tile(np.arange(1, n_f + 1, dtype=np.int16), n_h)]
    groups = [np.arange(n_h * n_f, dtype=np.int64)]
    next_group = n_h * n_f
    if structure and n_h:
        back = pose.back_structure()
        piece_m = min(float(spec.facet_width_m), float(spec.facet_height_m))
        for k, kind in enumerate(back.kinds):
            seg = back.segments[:, k]
            hint = pose.normals if kind != "pedestal" else pose.rotations[:, :, 0]
            # long tilted members are cut into facet-sized pieces: their bounding boxes stay tight,
            # so a ray tests only the pieces near it (the BVH's speed depends on it)
            n_pc = 1 if kind == "pedestal" else max(1, int(round(np.linalg.norm(seg[0, 1] - seg[0, 0]) / piece_m)))
            f = np.linspace(0.0, 1.0, n_pc + 1)
            a0 = seg[:, None, 0] + f[None, :-1, None] * (seg[:, None, 1] - seg[:, None, 0])
            a1 = seg[:, None, 0] + f[None, 1:, None] * (seg[:, None, 1] - seg[:, None, 0])
            bo, bu, bv = box_rectangles(a0.reshape(-1, 3), a1.reshape(-1, 3), sizes.width(kind),
                                        np.repeat(hint, n_pc, axis=0))
            # faces (N, pieces, 6); the end caps between two pieces are inside the member: drop them
            face = np.broadcast_to(np.arange(6), (n_h, n_pc, 6))
            piece = np.broadcast_to(np.arange(n_pc)[:, None], (n_h, n_pc, 6))
            keep = ~(((face == 4) & (piece > 0)) | ((face == 5) & (piece < n_pc - 1)))
            keep = keep.reshape(-1)
            o.append(bo[keep])
            u.append(bu[keep])
            v.append(bv[keep])
            kinds.append(np.full(int(keep.sum()), STRUCTURE, np.int8))
            heliostat_of = np.broadcast_to(np.arange(n_h, dtype=np.int32)[:, None, None], (n_h, n_pc, 6))
            owner.append(heliostat_of.reshape(-1)[keep])
            facet_no.append(np.zeros(int(keep.sum()), np.int16))
            # one group per (heliostat, member, face): the pieces of a face join without an edge
            g = next_group + (np.arange(n_h)[:, None, None] * 6 + np.arange(6)[None, None, :]) * len(back.kinds) + k
            groups.append(np.broadcast_to(g, (n_h, n_pc, 6)).reshape(-1)[keep].astype(np.int64))
        next_group += n_h * 6 * len(back.kinds)
    tw = getattr(field, "tower", None)
    if tower and tw is not None:
        c = tw.box_corners()
        # four sides (outward) and the top
        for i in range(4):
            j = (i + 1) % 4
            o.append(c[i][None])
            u.append((c[j] - c[i])[None])
            v.append((c[i + 4] - c[i])[None])
        o.append(c[4][None])
        u.append((c[5] - c[4])[None])
        v.append((c[7] - c[4])[None])
        kinds.append(np.full(5, TOWER, np.int8))
        owner.append(np.full(5, -1, np.int32))
        facet_no.append(np.zeros(5, np.int16))
        groups.append(next_group + np.arange(5, dtype=np.int64))
    bvh = build_bvh(np.concatenate(o), np.concatenate(u), np.concatenate(v))
    plane = None
    if ground:
        pivots = np.asarray(field.pivots, float)  # type: ignore[attr-defined]
        g = pivots.copy()
        g[:, 2] = field.ground_z  # type: ignore[attr-defined]
        plane = fit_ground_plane(g)
    return Scene(bvh, np.concatenate(kinds), np.concatenate(owner), np.concatenate(facet_no), plane,
                 tuple(field.names), np.concatenate(groups))  # type: ignore[attr-defined]
