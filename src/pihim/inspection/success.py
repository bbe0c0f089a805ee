"""Scoring edge maps against the ground truth: the paper's edge-detection success (Table 2).

**This module reads ground truth** (true camera pose, true heliostat
geometry, label images) to *score* edge maps. The estimator itself
(:mod:`pihim.inspection.edges`, ``pihim edges``) never does: it sees the raw
frame and the ``log`` of its metadata only. Nothing here feeds back into
edge detection.

The paper (section 4.3) counts a set as successful "where all facet edges
can be identified in the processed polarization images based on the known
heliostat facet shape and location". Made measurable here:

1. the facet outlines of the heliostat are projected into the image with the
   true camera (:func:`facet_outlines_px`), densely sampled along each of the
   four edges of every facet (about one sample per pixel, lens distortion
   included, so curved edges are followed);
2. a sample point is **visible** when it lies inside the image and, in the
   label image, one of the four pixels around it (the 2 x 2 block of pixel
   centres enclosing the point) shows that facet of that heliostat directly
   (``direct_heliostat`` and ``direct_facet``); a facet edge hidden behind
   another heliostat, or outside the frame, is therefore not asked for.
   Without labels, only the image bounds decide;
3. a visible sample point is **found** when an edge pixel lies within
   ``k_px`` of it (Euclidean distance to the edge pixel's centre, in pixels
   of the edge map);
4. an edge is judged when its visible part is at least ``min_visible_px``
   long (sensor pixels); its **coverage** is found / visible points;
5. **success**: at least one edge is judged and every judged edge has
   coverage >= ``min_coverage``.

Edge maps at another resolution than the sensor (the super-pixel route gives
W/2 x H/2) are handled: sensor pixel ``u`` is edge-map pixel
``(u + 0.5) / f - 0.5`` for an integer factor ``f``, inferred from the shapes.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose, project_points
from pihim.errors import PihimInputError

__all__ = [
    "EDGE_NAMES",
    "EdgeSuccess",
    "FacetOutlines",
    "FrameScore",
    "SuccessRate",
    "edge_success",
    "facet_outlines_px",
    "outlines_from_simulation",
    "outlines_from_truth",
    "scenario_mask",
    "score_frame",
    "sky_vs_sky_mask",
    "success_rate",
]

#: Facet edges in corner order (top left, top right, bottom right, bottom left seen from the front):
#: edge k runs from corner k to corner k + 1.
EDGE_NAMES: tuple[str, ...] = ("top", "right", "bottom", "left")
_MAX_SAMPLES = 20000


@dataclass(frozen=True, eq=False)
class FacetOutlines:
    """Projected facet outlines of one heliostat, in sensor pixels ``(u, v)`` = (column, row).

    Attributes
    ----------
    corners_px : ndarray, shape (F, 4, 2)
        Projected corners (NaN at or behind the camera).
    points_px : ndarray, shape (F, 4, S, 2)
        Samples along each edge, corner ``k`` to corner ``k + 1`` inclusive,
        equally spaced in space and projected with distortion.
    step_px : ndarray, shape (F, 4)
        Mean projected spacing of the samples of each edge.
    facet_ids : ndarray of int, shape (F,)
        Facet numbers (1..F unless given).
    image_size : (int, int)
        ``(width, height)`` of the sensor the outlines are expressed in.
    heliostat : int or None
        Label index of the heliostat (``direct_heliostat`` value), if known.
    """

    corners_px: NDArray[np.float64]
    points_px: NDArray[np.float64]
    step_px: NDArray[np.float64]
    facet_ids: NDArray[np.int64]
    image_size: tuple[int, int]
    heliostat: int | None = None


def _corners(corners_enu: ArrayLike) -> NDArray[np.float64]:
    c = np.asarray(corners_enu, dtype=float)
    if c.ndim == 2:
        c = c[None]
    if c.ndim != 3 or c.shape[1:] != (4, 3) or c.shape[0] < 1:
        raise PihimInputError(f"facet corners must have shape (F, 4, 3) (or (4, 3)), got {np.shape(corners_enu)}")
    if not np.all(np.isfinite(c)):
        raise PihimInputError("facet corners must be finite")
    return c


def facet_outlines_px(
    camera: CameraModel,
    pose: CameraPose,
    corners_enu: ArrayLike,
    *,
    spacing_px: float = 1.0,
    facet_ids: ArrayLike | None = None,
    heliostat: int | None = None,
) -> FacetOutlines:
    """Project the facet outlines of one heliostat into the image.

    Parameters
    ----------
    camera : CameraModel
    pose : CameraPose
        The camera pose to project with (for scoring: the **true** pose).
    corners_enu : array_like, shape (F, 4, 3)
        Facet corners, ENU metres, in :func:`pihim.field.facet_corners` order
        (top left, top right, bottom right, bottom left seen from the front),
        e.g. ``FieldPose.facet_corners(normals)[i]``.
    spacing_px : float
        Target spacing of the samples along the longest projected edge.
    facet_ids : array_like of int, optional
        Facet numbers (default 1..F, the label image's ``direct_facet``).
    heliostat : int, optional
        Label index of the heliostat, kept for :func:`edge_success`.

    Returns
    -------
    FacetOutlines
    """
    if not isinstance(camera, CameraModel) or not isinstance(pose, CameraPose):
        raise PihimInputError("facet_outlines_px needs a CameraModel and a CameraPose")
    if isinstance(spacing_px, bool) or not (isinstance(spacing_px, (int, float)) and spacing_px > 0):
        raise PihimInputError(f"spacing_px must be > 0, got {spacing_px!r}")
    corners = _corners(corners_enu)
    n_f = corners.shape[0]
    ids = np.arange(1, n_f + 1) if facet_ids is None else np.asarray(facet_ids, dtype=np.int64).reshape(-1)
    if ids.shape != (n_f,):
        raise PihimInputError(f"facet_ids must have {n_f} entries, got {ids.size}")
    corners_px = project_points(camera, pose, corners)  # (F, 4, 2)
    nxt = np.roll(corners_px, -1, axis=1)
    lengths = np.linalg.norm(nxt - corners_px, axis=-1)
    finite = lengths[np.isfinite(lengths)]
    longest = float(finite.max()) if finite.size else 0.0
    n_s = int(min(_MAX_SAMPLES, max(2, math.ceil(longest / float(spacing_px)) + 1)))
    t = np.linspace(0.0, 1.0, n_s)[None, None, :, None]
    a = corners[:, :, None, :]
    b = np.roll(corners, -1, axis=1)[:, :, None, :]
    points = project_points(camera, pose, a + t * (b - a))  # (F, 4, S, 2)
    seg = np.linalg.norm(np.diff(points, axis=2), axis=-1)
    with np.errstate(invalid="ignore"):
        step = np.nanmean(np.where(np.isfinite(seg), seg, np.nan), axis=2) if n_s > 1 else np.zeros((n_f, 4))
    return FacetOutlines(corners_px, points, np.nan_to_num(step, nan=0.0), ids,
                         (int(camera.width_px), int(camera.height_px)),
                         None if heliostat is None else int(heliostat))


# --------------------------------------------------------------------------- truth -> outlines


def outlines_from_simulation(sim: Any, heliostat: str, *, spacing_px: float = 1.0) -> FacetOutlines:
    """True facet outlines of a heliostat in a :class:`pihim.render.simulate.SimulatedFrame` (reads truth).

    Uses the true heliostat orientation and canting (``sim.true_field``,
    ``sim.facet_normals_local``) and the true camera pose.
    """
    if getattr(sim, "true_field", None) is None or getattr(sim, "camera_pose", None) is None:
        raise PihimInputError("the simulated frame carries no true field or camera pose")
    fld = sim.true_field.field
    i = fld.index(heliostat)
    corners = sim.true_field.facet_corners(sim.facet_normals_local)[i]
    camera = CameraModel.from_dict(sim.log["camera"])
    return facet_outlines_px(camera, sim.camera_pose, corners, spacing_px=spacing_px, heliostat=i)


def outlines_from_truth(document: Mapping[str, Any], heliostat: str, field: Any = None, *,
                        spacing_px: float = 1.0) -> FacetOutlines:
    """True facet outlines of a heliostat from a ``FRAME.json`` document (reads ``truth``).

    The field is rebuilt (the embedded NSTTF-like field unless ``field`` is
    given), tracked with the logged sun and aim point for the design canting,
    driven to the heliostat's true drive angles, and its facets turned by the
    true canting deviations; the true camera pose projects it.
    """
    from pihim.field import apply_canting_deviation, drive_angles, nsttf_like_field, track_field

    try:
        log, truth = document["log"], document["truth"]
        fld = nsttf_like_field() if field is None else field
        i = fld.index(heliostat)
        label_index = list(truth["labels"]["heliostat_index"]).index(fld.names[i])
        entry = next(h for h in truth["heliostats"] if h["name"] == fld.names[i])
        sun = np.asarray(truth["environment"]["sun_dir_enu"], float)
        camera = CameraModel.from_dict(log["camera"])
        pose = CameraPose.from_dict(truth["pose"])
        commanded = track_field(fld, sun, np.asarray(log["aim_point_m"], float))
    except (KeyError, StopIteration, ValueError, TypeError) as exc:
        raise PihimInputError(f"cannot rebuild the true facets of {heliostat!r} from the document: {exc}") from None
    cmd = drive_angles(commanded.normals)
    az = np.array(cmd.azimuth_deg, float)
    el = np.array(cmd.elevation_deg, float)
    az[i], el[i] = float(entry["az_deg"]), float(entry["el_deg"])
    true_pose = commanded.with_drive(az, el)
    facets = sorted(entry["facets"], key=lambda f: int(f["id"]))
    local = np.array(commanded.facet_normals_local, float)
    local[i] = apply_canting_deviation(local[i], np.array([f["az_mrad"] for f in facets], float),
                                       np.array([f["el_mrad"] for f in facets], float))
    corners = true_pose.facet_corners(local)[i]
    return facet_outlines_px(camera, pose, corners, spacing_px=spacing_px, heliostat=label_index)


# --------------------------------------------------------------------------- scoring


@dataclass(frozen=True, eq=False)
class EdgeSuccess:
    """Verdict of :func:`edge_success` for one edge map.

    Attributes
    ----------
    success : bool
        Every judged facet edge reached ``min_coverage`` (and at least one was judged).
    coverage : ndarray, shape (F, 4)
        Fraction of visible sample points with an edge pixel within ``k_px``;
        NaN for edges not judged (edge order :data:`EDGE_NAMES`).
    visible_px : ndarray, shape (F, 4)
        Visible length of each edge, sensor pixels.
    judged : ndarray of bool, shape (F, 4)
    facet_ids : ndarray of int, shape (F,)
    k_px, min_coverage, min_visible_px : float
    """

    success: bool
    coverage: NDArray[np.float64]
    visible_px: NDArray[np.float64]
    judged: NDArray[np.bool_]
    facet_ids: NDArray[np.int64]
    k_px: float
    min_coverage: float
    min_visible_px: float

    @property
    def n_judged(self) -> int:
        """Number of facet edges judged."""
        return int(self.judged.sum())

    @property
    def failed(self) -> list[tuple[int, str]]:
        """``(facet id, edge name)`` of the judged edges below ``min_coverage``."""
        bad = self.judged & ~(self.coverage >= self.min_coverage)
        return [(int(self.facet_ids[f]), EDGE_NAMES[e]) for f, e in zip(*np.nonzero(bad))]

    @property
    def min_edge_coverage(self) -> float:
        """Lowest coverage of a judged edge (NaN if none)."""
        c = self.coverage[self.judged]
        return float(c.min()) if c.size else math.nan

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary."""
        m = self.min_edge_coverage
        return {
            "success": bool(self.success),
            "edges_judged": self.n_judged,
            "edges_failed": [{"facet": f, "edge": e} for f, e in self.failed],
            "min_coverage_found": None if math.isnan(m) else m,
            "k_px": self.k_px,
            "min_coverage": self.min_coverage,
            "min_visible_px": self.min_visible_px,
        }


def _scale_factor(edge_shape: tuple[int, int], image_size: tuple[int, int]) -> int:
    w, h = image_size
    rows, cols = edge_shape
    if (rows, cols) == (h, w):
        return 1
    if rows > 0 and cols > 0 and h % rows == 0 and w % cols == 0 and h // rows == w // cols:
        return h // rows
    raise PihimInputError(
        f"edge map {cols}x{rows} is not the sensor size {w}x{h} divided by an integer factor"
    )


def _visible(points: NDArray[np.float64], outlines: FacetOutlines, labels: NDArray | None,
             heliostat: int | None, mask: NDArray[np.bool_] | None = None) -> NDArray[np.bool_]:
    """Visibility of every sample point (F, 4, S): inside the image, the facet seen directly, in the mask."""
    w, h = outlines.image_size
    u, v = points[..., 0], points[..., 1]
    with np.errstate(invalid="ignore"):
        inside = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    if labels is None and mask is None:
        return inside
    u0 = np.clip(np.floor(np.nan_to_num(u)), 0, w - 1).astype(np.intp)
    v0 = np.clip(np.floor(np.nan_to_num(v)), 0, h - 1).astype(np.intp)
    u1 = np.minimum(u0 + 1, w - 1)
    v1 = np.minimum(v0 + 1, h - 1)
    block = ((v0, u0), (v0, u1), (v1, u0), (v1, u1))
    if labels is not None:
        helio = labels[..., 1]
        facet = labels[..., 2]
        fid = outlines.facet_ids[:, None, None]
        seen = np.zeros(u.shape, dtype=bool)
        for vv, uu in block:
            seen |= (helio[vv, uu] == heliostat) & (facet[vv, uu] == fid)
        inside &= seen
    if mask is not None:
        in_mask = np.zeros(u.shape, dtype=bool)
        for vv, uu in block:
            in_mask |= mask[vv, uu]
        inside &= in_mask
    return inside


def scenario_mask(labels: ArrayLike, heliostat: int, background: str = "sky", *,
                  width_px: int = 6) -> NDArray[np.bool_]:
    """Sensor pixels along a heliostat's sky-vs-sky or ground-vs-ground edges (reads the label image: truth).

    The paper's two scenarios (sections 4.1 and 4.2): the heliostat's mirror
    reflects ``background`` (the sky, or the ground), and across its edge
    lies another surface showing the same kind of thing: another heliostat's
    mirror reflecting it (its own facet gaps included, where they show what
    is behind) or the sky or ground itself. The mask holds the pixels within
    ``width_px`` (Chebyshev distance) of both kinds of pixel, a band around
    exactly those stretches of the outline; pass it to :func:`edge_success`
    (``mask=``) to judge only them.

    Parameters
    ----------
    labels : array_like of int, shape (H, W, >= 4)
        Label image of the frame (channels ``direct_kind``, ``direct_heliostat``,
        ``direct_facet``, ``seen_kind``, ...; :data:`pihim.render.frame.LABEL_CHANNELS`).
    heliostat : int
        Label index of the heliostat.
    background : {"sky", "ground"}
        The scenario: sky-vs-sky or ground-vs-ground.
    width_px : int
        Half-width of the band, pixels (>= 1).

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    from scipy.ndimage import maximum_filter

    from pihim.render.paths import GROUND, MIRROR, SKY

    kinds = {"sky": SKY, "ground": GROUND}
    if background not in kinds:
        raise PihimInputError(f"background must be 'sky' or 'ground', got {background!r}")
    lab = np.asarray(labels)
    if lab.ndim != 3 or lab.shape[2] < 4:
        raise PihimInputError(f"labels must have shape (H, W, >= 4), got {lab.shape}")
    if isinstance(width_px, bool) or not isinstance(width_px, (int, np.integer)) or width_px < 1:
        raise PihimInputError(f"width_px must be an integer >= 1, got {width_px!r}")
    code = kinds[background]
    kind, helio, end = lab[..., 0], lab[..., 1], lab[..., 3]
    mirror_bg = (kind == MIRROR) & (end == code)
    own = mirror_bg & (helio == int(heliostat))
    other = (mirror_bg & (helio != int(heliostat))) | (kind == code)
    size = 2 * int(width_px) + 1
    return (maximum_filter(own.view(np.uint8), size=size) > 0) & (maximum_filter(other.view(np.uint8), size=size) > 0)


def sky_vs_sky_mask(labels: ArrayLike, heliostat: int, *, width_px: int = 6) -> NDArray[np.bool_]:
    """:func:`scenario_mask` for the sky-vs-sky scenario."""
    return scenario_mask(labels, heliostat, "sky", width_px=width_px)


def edge_success(
    edge_map_binary: ArrayLike,
    outlines_px: FacetOutlines,
    k_px: float = 2.0,
    min_coverage: float = 0.9,
    *,
    labels: ArrayLike | None = None,
    heliostat: int | None = None,
    min_visible_px: float = 5.0,
    mask: ArrayLike | None = None,
) -> EdgeSuccess:
    """The paper's edge-detection success: are all visible facet edges of the heliostat found?

    Parameters
    ----------
    edge_map_binary : array_like of bool, shape (H, W) or (H / f, W / f)
        Edge pixels (e.g. ``EdgeMaps["DoLP"].edges``), at the sensor
        resolution or divided by an integer factor (super-pixel route).
    outlines_px : FacetOutlines
        From :func:`facet_outlines_px` (true pose and geometry).
    k_px : float
        Tolerance, pixels of the edge map.
    min_coverage : float
        Fraction of an edge's visible sample points that must be found.
    labels : array_like of int, shape (H, W, >= 3), optional
        Label image of the frame (``FRAME.labels.tiff``); channels 1 and 2
        (``direct_heliostat``, ``direct_facet``) decide visibility. Without it
        every sample inside the image counts as visible.
    heliostat : int, optional
        Label index of the heliostat; default ``outlines_px.heliostat``.
    min_visible_px : float
        Edges with a shorter visible part (sensor pixels) are not judged.
    mask : array_like of bool, shape (H, W), optional
        Sensor pixels where edges are asked for (e.g. :func:`sky_vs_sky_mask`):
        a sample point counts as visible only if one of its four surrounding
        pixels is in the mask.

    Returns
    -------
    EdgeSuccess
    """
    if not isinstance(outlines_px, FacetOutlines):
        raise PihimInputError("outlines_px must be a FacetOutlines (see facet_outlines_px)")
    edges = np.asarray(edge_map_binary)
    if edges.ndim != 2:
        raise PihimInputError(f"the edge map must be a 2-D array, got shape {edges.shape}")
    edges = edges.astype(bool)
    for name, val in (("k_px", k_px), ("min_coverage", min_coverage), ("min_visible_px", min_visible_px)):
        if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val) or val < 0:
            raise PihimInputError(f"{name} must be a finite number >= 0, got {val!r}")
    if min_coverage > 1:
        raise PihimInputError(f"min_coverage must be in [0, 1], got {min_coverage!r}")
    lab = None
    if labels is not None:
        lab = np.asarray(labels)
        w, h = outlines_px.image_size
        if lab.ndim != 3 or lab.shape[:2] != (h, w) or lab.shape[2] < 3:
            raise PihimInputError(f"labels must have shape ({h}, {w}, >= 3), got {lab.shape}")
        if heliostat is None:
            heliostat = outlines_px.heliostat
        if heliostat is None:
            raise PihimInputError("with labels, the heliostat's label index is needed (heliostat=...)")
    msk = None
    if mask is not None:
        msk = np.asarray(mask, dtype=bool)
        w, h = outlines_px.image_size
        if msk.shape != (h, w):
            raise PihimInputError(f"mask must have shape ({h}, {w}), got {msk.shape}")
    factor = _scale_factor(edges.shape, outlines_px.image_size)
    pts = outlines_px.points_px
    visible = _visible(pts, outlines_px, lab, heliostat, msk)
    found = np.zeros(visible.shape, dtype=bool)
    ys, xs = np.nonzero(edges)
    if xs.size and visible.any():
        tree = cKDTree(np.column_stack([xs, ys]).astype(np.float64))
        q = (pts[visible] + 0.5) / factor - 0.5
        dist, _ = tree.query(q, k=1, distance_upper_bound=float(k_px) + 1e-9)
        found[visible] = dist <= float(k_px) + 1e-9
    n_vis = visible.sum(axis=2)
    visible_px = n_vis * outlines_px.step_px
    judged = (n_vis > 0) & (visible_px >= float(min_visible_px))
    with np.errstate(invalid="ignore", divide="ignore"):
        coverage = np.where(judged, found.sum(axis=2) / np.maximum(n_vis, 1), np.nan)
    success = bool(judged.any() and np.all(coverage[judged] >= float(min_coverage)))
    return EdgeSuccess(success, coverage, visible_px.astype(float), judged, outlines_px.facet_ids.copy(),
                       float(k_px), float(min_coverage), float(min_visible_px))


# --------------------------------------------------------------------------- sets of frames


@dataclass(frozen=True, eq=False)
class FrameScore:
    """Edge-success verdicts of one frame, by image type (``"S0"``, ``"DoLP"``, ``"AoP"``, ``"combined"``)."""

    name: str
    results: dict[str, EdgeSuccess]

    def __getitem__(self, image_type: str) -> EdgeSuccess:
        return self.results[_image_type_key(self.results, image_type)]


def _image_type_key(mapping: Mapping[str, Any], image_type: str) -> str:
    want = str(image_type).strip().lower()
    for key in mapping:
        if str(key).lower() == want:
            return key
    raise KeyError(f"no result for image type {image_type!r} (have {', '.join(map(str, mapping))})")


def score_frame(
    maps: Any,
    outlines_px: FacetOutlines,
    *,
    labels: ArrayLike | None = None,
    heliostat: int | None = None,
    k_px: float = 2.0,
    min_coverage: float = 0.9,
    min_visible_px: float = 5.0,
    mask: ArrayLike | None = None,
    name: str = "",
) -> FrameScore:
    """:func:`edge_success` for every image type of an :class:`pihim.inspection.edges.EdgeMaps`."""
    results = {
        image_type: edge_success(m.edges, outlines_px, k_px, min_coverage, labels=labels, heliostat=heliostat,
                                 min_visible_px=min_visible_px, mask=mask)
        for image_type, m in maps.items()
    }
    return FrameScore(str(name), results)


@dataclass(frozen=True)
class SuccessRate:
    """A row of the paper's Table 2."""

    image_type: str
    successful: int
    unsuccessful: int

    @property
    def total(self) -> int:
        """Number of sets."""
        return self.successful + self.unsuccessful

    @property
    def rate(self) -> float:
        """successful / total (NaN for an empty set)."""
        return self.successful / self.total if self.total else math.nan

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready row."""
        return {"image_type": self.image_type, "successful": self.successful, "unsuccessful": self.unsuccessful,
                "total": self.total, "success_rate": None if not self.total else self.rate}


def success_rate(frames: Iterable[FrameScore | Mapping[str, Any]] | Sequence[Any], image_type: str) -> SuccessRate:
    """Successful, unsuccessful and the success rate of one image type over a set of frames (Table 2).

    Parameters
    ----------
    frames : iterable
        :class:`FrameScore` objects, or mappings from image type to an
        :class:`EdgeSuccess` (or a bool verdict).
    image_type : str
        ``"S0"``, ``"DoLP"``, ``"AoP"`` or ``"combined"`` (case-insensitive).

    Raises
    ------
    PihimInputError
        A frame without a result for ``image_type``, or a verdict that is
        neither an :class:`EdgeSuccess` nor a bool.
    """
    ok = bad = 0
    for frame in frames:
        results = frame.results if isinstance(frame, FrameScore) else frame
        if not isinstance(results, Mapping):
            raise PihimInputError(f"frames must be FrameScore objects or mappings, got {type(frame).__name__}")
        try:
            verdict = results[_image_type_key(results, image_type)]
        except KeyError as exc:
            raise PihimInputError(str(exc.args[0])) from None
        if isinstance(verdict, EdgeSuccess):
            passed = verdict.success
        elif isinstance(verdict, (bool, np.bool_)):
            passed = bool(verdict)
        else:  # bool("False") is True: a verdict read from text would count as a success
            raise PihimInputError(f"a verdict must be an EdgeSuccess or a bool, got {verdict!r}")
        ok += int(passed)
        bad += int(not passed)
    return SuccessRate(str(image_type), ok, bad)
