"""Polarimetric scoring of planned images and contrast-raising pass shifts.

Every capture waypoint of a :class:`~pihim.planning.model.ScanPass` is one
planned image of a heliostat under assessment (HUA) and its UFACET target.
:func:`score_passes` predicts, for all images of a plan at once (one
vectorised evaluation of :mod:`pihim.scenarios`), the paper's two contrast
scenarios and fills the passes' :class:`~pihim.planning.model.PairPrediction`
records; it can then move each pass (altitude, lateral offset, gaze) to raise
its fraction of usable images and records the move as a
:class:`~pihim.planning.model.PassShift`.

What is evaluated for one image
-------------------------------
The camera is at the waypoint position ``C`` (field ENU, metres). Mirrors
are the flat outline rectangles of the tracked heliostats
(:meth:`pihim.field.FieldPose.mirror_outline`); the normal used at a mirror
point is the design normal of the facet nearest to it (canting included).

Sky-vs-sky pair (paper sec. 4.1)
    Candidates are the UFACET target and the ``neighbours`` (default 8)
    heliostats whose pivots are nearest to the HUA's. Each outline is
    projected into a zero-roll pinhole view from ``C`` toward the HUA centre
    (overlap in the image depends only on ``C``, not on the camera
    attitude), and sampled at 12 boundary points (corners and thirds of each
    edge). A candidate **overlaps the HUA** when at least one of its boundary
    samples falls strictly inside the HUA's projected outline or one of the
    HUA's samples inside its outline. The partner is the candidate with the
    most such samples (ties: the target first). Of the pair, the mirror
    nearer to the camera along the line of sight is the *front*, the other
    the *back*. Both are evaluated on one line of sight: through the mean of
    the overlapping samples (a point of the image inside both outlines, on
    the front mirror next to the visible edge); the front point is where it
    meets the front mirror plane, the back point where it meets the back
    mirror plane (hidden there, but the sky it reflects varies slowly across
    the edge). :func:`pihim.scenarios.sky_vs_sky` gives both DoLPs, their
    difference and the paper's criterion (both show sky, difference > 0.2).
    No overlapping candidate: the scenario does not arise (``None``).
Ground-vs-ground edge (paper sec. 4.2)
    The midpoint of the HUA's lower outline edge (heliostat ``-y``). The
    real ground next to it is where the line of sight through that point
    meets the ground plane ``z = ground_z`` under the HUA; the scenario
    arises when the HUA there reflects ground (not sky), faces the camera,
    and no candidate heliostat nearer to the camera covers the point in the
    image. :func:`pihim.scenarios.ground_vs_ground` gives the axial AoP
    difference (in [0, 90] deg; usable when > 50 deg) and the paper's raw
    difference ``|AoP_mirror - AoP_ground|`` in [0, 180).
Reflection DoLP (paper sec. 5: only images with DoLP > 0.2 are processed)
    The DoLP of the light the HUA itself reflects toward the camera at the
    point of the scenario edge: the HUA's point of the sky-vs-sky pair
    and/or its lower-edge point. If one or both scenarios are usable, the
    largest HUA DoLP among the usable ones; else the largest among the
    scenarios that arise; if none arises, the DoLP at the HUA centre (the sky
    or ground the HUA reflects around the target's image; the occlusion by
    the target's back is not modelled). With this choice
    ``PairPrediction.usable`` (reflection DoLP > 0.2 and a usable scenario)
    means "at least one usable edge whose HUA side carries DoLP > 0.2".

The thresholds are :data:`pihim.scenarios.REFLECTION_DOLP_MIN` (0.2),
:data:`~pihim.scenarios.SKY_DOLP_DIFFERENCE_MIN` (0.2) and
:data:`~pihim.scenarios.GROUND_AOP_DIFFERENCE_MIN_DEG` (50 deg).

Speed
-----
The Torrance-Sparrow ground of :class:`pihim.surfaces.ground.GroundModel`
costs a sky tabulation (~25 ms) per call plus ~6 us per view direction. By
default the ground radiance is therefore evaluated once per sun position on
a 49 x 49 Lambert azimuthal grid of view directions (:class:`GroundTable`,
``ScoringModel.ground_table_size``; the model's own sky table at 129 x 129
nodes, ``ground_sky_table_size``) and interpolated bilinearly (Stokes stored
in a reference frame that is smooth over the whole upper hemisphere). The
nodes are evaluated as the queries first need them: a plan's images look at
10-25 % of them (NSTTF day sweep), so a sun position costs the model's sky
table (~10 ms) and those nodes, not all 2,401. Against the model's direct
default evaluation, for view directions above 10 deg elevation and sun zeniths 15-75 deg, the AoP
is within 0.8 deg for 99 % of directions with ground DoLP > 0.05 (2 deg at
worst) and the DoLP within 0.01 (larger AoP errors only where the ground
DoLP is near zero and its AoP undefined). ``ground_table_size=None``
evaluates the model directly. Scoring the NSTTF plan costs a few tens of
milliseconds; see ``benchmarks/bench_windows.py``.

Pass shifts
-----------
A pass can be moved as a whole by ``altitude_delta_m`` (all waypoints),
``lateral_offset_m`` (horizontal, perpendicular to the direction of travel,
positive to the right of it) and ``gaze_delta_deg``: each capture waypoint
slides along the track so that the elevation angle of its line of sight to
the HUA centre (seen from the HUA) changes by that amount (positive: a
steeper, more overhead view; the slide is the closed-form solution on the
shifted track). Capture waypoints are re-aimed at the HUA mirror centre
(heading and gimbal pitch, as the planner does), so the HUA stays centred;
other waypoints keep their attitude. The gaze change is bounded by the grid
(default +/-4 deg). A candidate is admissible only if:

* every waypoint of the pass stays within ``[min_altitude_m,
  max_altitude_m]`` (default minimum: the highest mirror point of the
  tracked field plus 5 m, the paper's safety rule; default maximum 121.9 m,
  400 ft, the usual small-UAS ceiling; the day sweep uses the planner's
  maximum);
* the re-aimed gimbal pitch stays within ``[gimbal_pitch_min_deg,
  gimbal_pitch_max_deg]`` and the HUA stays in the field of view: the
  fraction of its facet centres inside the image
  (:class:`pihim.camera.model.CameraModel`) does not fall below the nominal
  image's (unless it stays at least ``min_framing``);
* the UFACET requirement is kept: the camera ray to the HUA centre,
  reflected by the HUA, still meets the target's mirror outline (scaled by
  ``target_outline_fraction``) -- i.e. the HUA still shows the target's
  back. Shifts that trade the UFACET geometry for contrast are refused;
* no other mirror blocks the sight line to the HUA centre or the reflected
  ray from the HUA centre to the target
  (:func:`pihim.planning.ufacet.first_mirror_hits`);
* the waypoints keep ``tower_clearance_m`` horizontally from the tower
  footprint (unless above the tower) and, when the aim point is known,
  ``beam_clearance_m`` from the beams reflected toward it (each beam a cone
  from the mirror, of the mirror's half diagonal, narrowing to the aim
  point).

The altitude and gimbal limits always hold; the framing, UFACET, blocking,
tower and beam constraints are enforced for the images / waypoints that met them at
the nominal position (a shift never makes them worse, but does not have to
repair a nominal violation; the beam margin may not fall below the smaller
of its nominal value and ``beam_clearance_m``). All candidates of all passes
are scored in one vectorised evaluation; the best admissible one (highest
usable fraction; ties to the smallest move) is applied when it raises the
pass's usable fraction, and the predictions are those recomputed at the
shifted camera positions. Not re-evaluated after a shift: the planner's
``issues`` and ``feasible`` (its flux estimate in particular), and the
order of the capture waypoints along the track (each slides by its own
amount).

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone" (pihim paper), sec. 3 (UFACET geometry, safety altitude
   5 m above the heliostats), sec. 4.1 (sky-vs-sky, DoLP difference > 0.2),
   sec. 4.2 (ground-vs-ground, AoP difference > 50 deg), sec. 5 (DoLP > 0.2
   on the heliostat reflection).
.. [2] Sandia National Laboratories, OpenCSP UFACET flight planning
   (Apache-2.0), https://github.com/sandialabs/OpenCSP.
.. [3] US 14 CFR 107.51(b): small unmanned aircraft at most 400 ft above
   ground level.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.camera.model import CameraModel
from pihim.errors import PihimInputError
from pihim.planning.model import PairPrediction, PassShift, ScanPass, Waypoint
from pihim.polarimetry.frames import (
    change_reference,
    normalize,
    perpendicular_reference,
)
from pihim.scenarios import (
    REFLECTION_DOLP_MIN,
    ground_vs_ground,
    mirror_reflection,
    sky_vs_sky,
)
from pihim.sky.model import SkyModel, with_horizontal_irradiance
from pihim.surfaces.ground import GroundModel
from pihim.surfaces.mirror import MirrorModel, SecondSurfaceMirror

__all__ = [
    "DEFAULT_SHIFT_SEARCH",
    "SAFETY_MARGIN_M",
    "SMALL_UAS_CEILING_M",
    "GroundTable",
    "ImagePredictions",
    "ScoringModel",
    "ScoringScene",
    "ShiftSearch",
    "build_scene",
    "coverage",
    "images_text",
    "min_safe_altitude_m",
    "predict_images",
    "score_passes",
]

#: Minimum height of the drone above the highest heliostat point, metres (paper sec. 2).
SAFETY_MARGIN_M = 5.0
#: 400 ft, the usual ceiling for small unmanned aircraft (14 CFR 107.51), metres.
SMALL_UAS_CEILING_M = 121.92

_SAMPLES_PER_EDGE = 3
_INSIDE_EPS = 1e-9
_EAST = np.array([1.0, 0.0, 0.0])
_UP = np.array([0.0, 0.0, 1.0])


# --------------------------------------------------------------------------- models


@dataclass(frozen=True)
class ScoringModel:
    """The physics used to score images.

    Attributes
    ----------
    sky : SkyModel
        Skylight model; its radiance is rescaled per sun position so that the
        diffuse horizontal irradiance is ``sky_irradiance_w_m2``.
    mirror : MirrorModel
        Heliostat mirror (default second-surface silvered glass).
    ground : GroundModel
        Torrance-Sparrow ground (default sigma 15 deg, n = 1.45, sun
        1000 W m^-2).
    sky_irradiance_w_m2 : float
        Diffuse horizontal sky irradiance, W m^-2 (default 100, clear sky);
        sets the sky's weight against the sun in the ground radiance.
    ground_table_size : int or None
        Nodes per axis of the :class:`GroundTable` (>= 9); ``None`` evaluates
        the ground model directly at every view (exact, slower).
    ground_sky_table_size : int
        ``sky_table_size`` passed to :meth:`GroundModel.stokes` when the
        table is built (its default, 257, costs ~20 ms more per sun).
    """

    sky: SkyModel = field(default_factory=SkyModel)
    mirror: MirrorModel = field(default_factory=SecondSurfaceMirror)
    ground: GroundModel = field(default_factory=GroundModel)
    sky_irradiance_w_m2: float = 100.0
    ground_table_size: int | None = 49
    ground_sky_table_size: int = 129

    def __post_init__(self) -> None:
        s = self.ground_table_size
        if s is not None and (isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 9):
            raise PihimInputError(f"ground_table_size must be an integer >= 9 or None, got {s!r}")
        t = self.ground_sky_table_size
        if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or t < 3:
            raise PihimInputError(f"ground_sky_table_size must be an integer >= 3, got {t!r}")
        e = self.sky_irradiance_w_m2
        if not (isinstance(e, (int, float)) and math.isfinite(e) and e > 0):
            raise PihimInputError(f"sky_irradiance_w_m2 must be a positive number, got {e!r}")


@dataclass(frozen=True)
class ShiftSearch:
    """The grid of pass shifts tried and the constraints they must keep (see the module notes).

    Attributes
    ----------
    altitude_deltas_m, lateral_offsets_m, gaze_deltas_deg : tuple of float
        Values tried (all combinations; the all-zero one is the nominal pass).
    min_altitude_m : float or None
        Lowest admissible waypoint height above the field origin, metres;
        ``None``: :func:`min_safe_altitude_m` of the tracked field.
    max_altitude_m : float
        Highest admissible waypoint height, metres.
    gimbal_pitch_min_deg, gimbal_pitch_max_deg : float
        Gimbal pitch range of the re-aimed camera, degrees (negative down).
    min_framing : float
        Fraction of the HUA's facet centres in the image that is always
        enough; below it a shift must not frame less than the nominal image.
    target_outline_fraction : float
        Scale of the target outline the reflected ray must meet (1 = the whole
        mirror; smaller demands a more central hit).
    tower_clearance_m, beam_clearance_m : float
        Horizontal clearance from the tower footprint, and clearance from the
        reflected beams (only checked when the aim point is known), metres.
    """

    altitude_deltas_m: tuple[float, ...] = (-3.0, 0.0, 3.0, 6.0)
    lateral_offsets_m: tuple[float, ...] = (-3.0, 0.0, 3.0)
    gaze_deltas_deg: tuple[float, ...] = (-4.0, 0.0, 4.0)
    min_altitude_m: float | None = None
    max_altitude_m: float = SMALL_UAS_CEILING_M
    gimbal_pitch_min_deg: float = -90.0
    gimbal_pitch_max_deg: float = 30.0
    min_framing: float = 1.0
    target_outline_fraction: float = 1.0
    tower_clearance_m: float = 10.0
    beam_clearance_m: float = 2.0

    def __post_init__(self) -> None:
        for name in ("altitude_deltas_m", "lateral_offsets_m", "gaze_deltas_deg"):
            vals = tuple(float(v) for v in getattr(self, name))
            if not vals or not all(math.isfinite(v) for v in vals):
                raise PihimInputError(f"ShiftSearch.{name} must be a non-empty tuple of finite numbers")
            object.__setattr__(self, name, vals)
        if any(abs(g) >= 45.0 for g in self.gaze_deltas_deg):
            raise PihimInputError("ShiftSearch.gaze_deltas_deg must be within (-45, 45) deg")
        if not 0.0 <= self.min_framing <= 1.0:
            raise PihimInputError(f"min_framing must be in [0, 1], got {self.min_framing!r}")
        if not -90.0 <= self.gimbal_pitch_min_deg < self.gimbal_pitch_max_deg <= 90.0:
            raise PihimInputError("gimbal pitch limits must satisfy -90 <= min < max <= 90 deg")
        if not self.target_outline_fraction > 0.0:
            raise PihimInputError("target_outline_fraction must be positive")
        if self.min_altitude_m is not None and not self.min_altitude_m < self.max_altitude_m:
            raise PihimInputError(
                f"min altitude {self.min_altitude_m:g} m must be below max altitude {self.max_altitude_m:g} m"
            )

    def candidates(self) -> NDArray[np.float64]:
        """All (altitude, lateral, gaze) combinations except the nominal (0, 0, 0), shape (G, 3)."""
        grid = [c for c in itertools.product(self.altitude_deltas_m, self.lateral_offsets_m, self.gaze_deltas_deg)
                if any(v != 0.0 for v in c)]
        return np.array(grid, dtype=float).reshape(-1, 3)


#: The default shift grid and constraints.
DEFAULT_SHIFT_SEARCH = ShiftSearch()


# --------------------------------------------------------------------------- ground table


def _table_axis(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Reference axis normal to ``v``, smooth over the upper hemisphere: ``x`` carried by the
    smallest rotation taking ``z`` to ``v`` (``x - v_x / (1 + v_z) (v + z)``; singular only at the nadir)."""
    f = v[..., 0] / (1.0 + v[..., 2])
    e = -f[..., None] * v
    e[..., 0] += 1.0
    e[..., 2] -= f
    return e


class GroundTable:
    """Ground Stokes radiance tabulated over view directions for one sun position.

    Implements the ``stokes(view_dirs, sun_dir, sky=None, e=None)`` protocol
    of :class:`pihim.surfaces.ground.GroundModel` (the ground is homogeneous,
    so its radiance depends on the view direction only). Nodes form a square
    grid of Lambert azimuthal equal-area coordinates ``(X, Y)`` in
    ``[-sqrt 2, sqrt 2]^2`` (``v_z = 1 - r^2 / 2``); nodes outside the disc
    are clamped just above the horizon. Stokes are stored in the frame
    ``(v, e_T(v))`` with ``e_T`` smooth over the upper hemisphere, and
    interpolated bilinearly.

    The nodes are evaluated when a query first needs them (a plan's images
    look at 10-25 % of the hemisphere), each with the model's own value: the
    results do not depend on the order or grouping of the queries. The
    model's sky table is built once, at the first evaluation. Queries from
    several threads are safe: a node is written before it is marked
    evaluated, with the same value whichever query evaluates it (threads
    querying at once may evaluate the same nodes, and build the sky table,
    more than once).

    Parameters
    ----------
    ground : GroundModel
        The model tabulated (with its default quadrature).
    sky : object with ``stokes`` or None
        Sky lighting the ground.
    sun_dir : array_like, shape (3,)
        Unit vector toward the sun. :meth:`stokes` refuses another sun.
    size : int
        Nodes per axis (49: about 3.3 deg spacing).
    sky_table_size : int
        Passed to :meth:`GroundModel.stokes`.
    """

    def __init__(self, ground: GroundModel, sky: Any, sun_dir: ArrayLike, size: int = 49,
                 sky_table_size: int = 129) -> None:
        self.sun_dir = normalize(np.asarray(sun_dir, dtype=float))
        self.radius = math.sqrt(2.0)
        self.size = int(size)
        self.step = 2.0 * self.radius / (self.size - 1)
        x = np.linspace(-self.radius, self.radius, self.size)
        xx, yy = np.meshgrid(x, x, indexing="ij")
        r2 = np.minimum(xx**2 + yy**2, 2.0)
        vz = np.maximum(1.0 - 0.5 * r2, 1e-3)
        k = np.sqrt(np.maximum(1.0 - vz**2, 0.0) / np.maximum(r2, 1e-300))
        v = np.stack([xx * k, yy * k, vz], axis=-1)
        v[r2 == 0.0] = (0.0, 0.0, 1.0)
        self._nodes = normalize(v)
        self._ground, self._sky, self._sky_table_size = ground, sky, int(sky_table_size)
        self._sky_table: Any = None
        self.table = np.zeros((self.size, self.size, 4))
        self.evaluated = np.zeros((self.size, self.size), dtype=bool)  # nodes whose value is in ``table``

    def _evaluate(self, ix: NDArray[np.intp], iy: NDArray[np.intp]) -> None:
        """Evaluate the corner nodes of the cells ``(ix, iy)`` that are not evaluated yet."""
        need = np.zeros_like(self.evaluated)
        for dx in (0, 1):
            for dy in (0, 1):
                need[ix + dx, iy + dy] = True
        need &= ~self.evaluated
        if not need.any():
            return
        v = self._nodes[need]
        options: dict[str, Any] = {"sky_table_size": self._sky_table_size}
        if self._sky is not None and callable(getattr(self._ground, "sky_table", None)):
            if self._sky_table is None:
                self._sky_table = self._ground.sky_table(self._sky, self.sun_dir, self._sky_table_size)
            options = {"sky_table": self._sky_table}
        s, e = self._ground.stokes(v, self.sun_dir, self._sky, **options)
        self.table[need] = change_reference(s, v, e, _table_axis(v))
        self.evaluated |= need

    def stokes(
        self, view_dirs: ArrayLike, sun_dir: ArrayLike, sky: Any = None, e: ArrayLike | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Interpolated Stokes radiance toward ``view_dirs`` (zero at or below the horizon).

        ``sun_dir`` must be the tabulated sun; ``sky`` is ignored (the table
        was built with its sky). Output frame: ``e``, default
        ``perpendicular_reference(view_dirs)`` as for ``GroundModel``.
        """
        s_dir = normalize(np.asarray(sun_dir, dtype=float))
        if s_dir.shape != (3,) or float(np.max(np.abs(s_dir - self.sun_dir))) > 1e-9:
            raise PihimInputError("GroundTable was built for another sun direction")
        v = normalize(np.asarray(view_dirs, dtype=float))
        vz = np.clip(v[..., 2], -1.0 + 1e-12, 1.0)
        k = np.sqrt(2.0 / (1.0 + vz))
        fx = (v[..., 0] * k + self.radius) / self.step
        fy = (v[..., 1] * k + self.radius) / self.step
        ix = np.clip(fx.astype(np.intp), 0, self.size - 2)
        iy = np.clip(fy.astype(np.intp), 0, self.size - 2)
        up = v[..., 2] > 0.0
        self._evaluate(ix[up], iy[up])  # below the horizon the result is zero whatever the nodes hold
        tx = np.clip(fx - ix, 0.0, 1.0)[..., None]
        ty = np.clip(fy - iy, 0.0, 1.0)[..., None]
        t = self.table
        out = (1 - tx) * (1 - ty) * t[ix, iy] + tx * (1 - ty) * t[ix + 1, iy]
        out = out + (1 - tx) * ty * t[ix, iy + 1] + tx * ty * t[ix + 1, iy + 1]
        out = np.where(up[..., None], out, 0.0)
        e_out = perpendicular_reference(v) if e is None else normalize(np.broadcast_to(np.asarray(e, float), v.shape))
        safe_v = np.where((v[..., 2] > -0.999)[..., None], v, _UP)
        return change_reference(out, v, _table_axis(safe_v), e_out), e_out


# --------------------------------------------------------------------------- scene


@dataclass(frozen=True, eq=False)
class ScoringScene:
    """Everything scoring needs for one instant: tracked geometry and the physics for one sun.

    Build it with :func:`build_scene` (once per instant; it holds the ground
    table). Arrays are indexed like the field's heliostats.
    """

    pose: Any
    sun_dir: NDArray[np.float64]
    model: ScoringModel
    sky: SkyModel
    ground: Any
    centres: NDArray[np.float64]
    normals: NDArray[np.float64]
    rotations: NDArray[np.float64]
    outlines: NDArray[np.float64]
    boundary: NDArray[np.float64]
    facet_xy: NDArray[np.float64]
    facet_normals: NDArray[np.float64]
    ground_z: NDArray[np.float64]
    neighbours: NDArray[np.int64]
    half_size: tuple[float, float]

    @property
    def field(self) -> Any:
        """The tracked field."""
        return self.pose.field


def _neighbour_table(pivots: NDArray[np.float64], k: int) -> NDArray[np.int64]:
    n = len(pivots)
    if k <= 0 or n < 2:
        return np.full((n, 0), -1, dtype=np.int64)
    from scipy.spatial import cKDTree

    kk = min(k + 1, n)
    _, idx = cKDTree(pivots[:, :2]).query(pivots[:, :2], k=kk)
    idx = np.asarray(idx, dtype=np.int64).reshape(n, kk)
    out = np.full((n, k), -1, dtype=np.int64)
    for row in range(n):  # drop self (usually column 0, but not if two pivots coincide)
        others = idx[row][idx[row] != row][:k]
        out[row, : len(others)] = others
    return out


def build_scene(pose: Any, sun_dir: ArrayLike, model: ScoringModel | None = None, *, neighbours: int = 8) -> ScoringScene:
    """Prepare scoring for one tracked field and sun direction.

    Parameters
    ----------
    pose : FieldPose
        The tracked field (:func:`pihim.field.track_field`).
    sun_dir : array_like, shape (3,)
        ENU unit vector toward the sun; it must be above the horizon.
    model : ScoringModel, optional
        Physics (defaults of :class:`ScoringModel`).
    neighbours : int
        How many nearest heliostats (by pivot) are sky-vs-sky candidates
        besides the target.

    Returns
    -------
    ScoringScene
    """
    model = ScoringModel() if model is None else model
    sun = np.asarray(sun_dir, dtype=float)
    if sun.shape != (3,) or not np.all(np.isfinite(sun)) or not np.any(sun):
        raise PihimInputError(f"sun direction must be one finite non-zero 3-vector, got {sun_dir!r}")
    sun = sun / np.linalg.norm(sun)
    if sun[2] <= 0.0:
        raise PihimInputError("the sun is below the horizon: no polarimetric scoring without daylight")
    sky = with_horizontal_irradiance(model.sky, sun, model.sky_irradiance_w_m2)
    if model.ground_table_size is None:
        ground: Any = model.ground
    else:
        ground = GroundTable(model.ground, sky, sun, model.ground_table_size, model.ground_sky_table_size)
    fld = pose.field
    spec = fld.spec
    outlines = np.asarray(pose.mirror_outline(), dtype=float)
    t = np.arange(_SAMPLES_PER_EDGE) / _SAMPLES_PER_EDGE
    a = outlines[:, :, None, :]
    b = np.roll(outlines, -1, axis=1)[:, :, None, :]
    boundary = (a + (b - a) * t[None, None, :, None]).reshape(len(outlines), -1, 3)
    return ScoringScene(
        pose=pose,
        sun_dir=sun,
        model=model,
        sky=sky,
        ground=ground,
        centres=np.asarray(pose.mirror_centres, dtype=float),
        normals=np.asarray(pose.normals, dtype=float),
        rotations=np.asarray(pose.rotations, dtype=float),
        outlines=outlines,
        boundary=boundary,
        facet_xy=np.asarray(spec.facet_centroids, dtype=float)[:, :2],
        facet_normals=np.asarray(pose.facet_normals, dtype=float),
        ground_z=np.asarray(fld.ground_z, dtype=float),
        neighbours=_neighbour_table(np.asarray(fld.pivots, dtype=float), neighbours),
        half_size=(float(spec.mirror_half_width_m), float(spec.mirror_half_height_m)),
    )


def min_safe_altitude_m(pose: Any, margin_m: float = SAFETY_MARGIN_M) -> float:
    """Highest mirror corner of the tracked field plus ``margin_m`` (paper: 5 m), metres above the origin.

    :func:`pihim.planning.ufacet.minimum_safe_altitude`'s first value: a margin
    under 5 m (or negative, which put the camera below the mirrors) is refused.
    """
    from pihim.planning.ufacet import minimum_safe_altitude

    return minimum_safe_altitude(pose, margin_m)[0]


# --------------------------------------------------------------------------- predictions


@dataclass(frozen=True, eq=False)
class ImagePredictions:
    """Vectorised predictions for ``M`` images (arrays of shape (M,)).

    NaN marks a scenario that does not arise for the image. See the module
    notes for the definitions.

    Attributes
    ----------
    partner : int array
        Heliostat index overlapping the HUA in the image (-1: none).
    hua_is_front : bool array
        The HUA is the nearer mirror of the sky-vs-sky pair.
    sky_front_dolp, sky_back_dolp, sky_dolp_difference : float arrays
        DoLPs of the front and back mirrors at the overlap and ``|front - back|``.
    sky_ok : bool array
        Both show sky and the difference exceeds 0.2.
    hua_sky_dolp : float array
        DoLP of the HUA's side of the sky-vs-sky edge.
    ground_arises, ground_occluded : bool arrays
        The HUA's lower edge shows mirror-reflected ground next to visible
        real ground; the lower edge is hidden behind a nearer heliostat.
    ground_aop_difference_deg, ground_aop_raw_difference_deg : float arrays
        Axial ([0, 90]) and raw ([0, 180)) AoP differences, degrees.
    ground_ok : bool array
        Axial difference above 50 deg.
    hua_ground_dolp : float array
        DoLP of the HUA at its lower edge.
    centre_dolp : float array
        DoLP of the HUA's reflection at its centre (sky or ground).
    reflection_dolp : float array
        The HUA reflection DoLP judged against 0.2 (module notes).
    reflection_ok, usable : bool arrays
    target_hit : bool array
        The camera ray to the HUA centre, reflected, meets the target outline.
    target_hit_extent : float array
        Where it meets the target's mirror plane, ``max(|x| / half width,
        |y| / half height)`` in the target's frame (<= 1: on the mirror;
        inf: no hit or no target).
    hua_point, partner_point : float arrays, shape (M, 3)
        The sky-vs-sky evaluation points on the HUA and on the partner (one
        line of sight), ENU metres; NaN without a partner.
    bottom_point, ground_point : float arrays, shape (M, 3)
        The HUA's lower-edge midpoint and the real ground seen next to it;
        ``ground_point`` is NaN where it was not evaluated (occluded edge or
        camera not above the edge).
    """

    partner: NDArray[np.int64]
    hua_is_front: NDArray[np.bool_]
    sky_front_dolp: NDArray[np.float64]
    sky_back_dolp: NDArray[np.float64]
    sky_dolp_difference: NDArray[np.float64]
    sky_ok: NDArray[np.bool_]
    hua_sky_dolp: NDArray[np.float64]
    ground_arises: NDArray[np.bool_]
    ground_occluded: NDArray[np.bool_]
    ground_aop_difference_deg: NDArray[np.float64]
    ground_aop_raw_difference_deg: NDArray[np.float64]
    ground_ok: NDArray[np.bool_]
    hua_ground_dolp: NDArray[np.float64]
    centre_dolp: NDArray[np.float64]
    reflection_dolp: NDArray[np.float64]
    reflection_ok: NDArray[np.bool_]
    usable: NDArray[np.bool_]
    target_hit: NDArray[np.bool_]
    target_hit_extent: NDArray[np.float64]
    hua_point: NDArray[np.float64]
    partner_point: NDArray[np.float64]
    bottom_point: NDArray[np.float64]
    ground_point: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.partner)


def _dot(a: NDArray, b: NDArray) -> NDArray:
    return np.einsum("...i,...i->...", a, b)


def _view_basis(cam: NDArray, look_at: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Zero-roll view axes (gaze g, image right r, image up u) from ``cam`` toward ``look_at`` (M, 3)."""
    g = normalize(look_at - cam)
    r = np.cross(g, _UP)
    weak = np.linalg.norm(r, axis=-1) < 1e-9
    if np.any(weak):
        r[weak] = np.cross(g[weak], np.array([0.0, 1.0, 0.0]))
    r = normalize(r)
    return g, r, np.cross(r, g)


def _project(p: NDArray, cam: NDArray, g: NDArray, r: NDArray, u: NDArray) -> tuple[NDArray, NDArray]:
    """Image-plane coordinates (..., 2) (tangents) and depth (...) of points ``p`` (M, ..., 3)."""
    extra = p.ndim - 2
    shape = (cam.shape[0],) + (1,) * extra + (3,)
    q = p - cam.reshape(shape)
    gg, rr, uu = (a.reshape(shape) for a in (g, r, u))
    depth = _dot(q, gg)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / depth
        xy = np.stack([_dot(q, rr) * inv, _dot(q, uu) * inv], axis=-1)
    return xy, depth


def _inside(pts: NDArray, quads: NDArray) -> NDArray[np.bool_]:
    """Points (..., S, 2) strictly inside convex quads (..., 4, 2) (either winding) -> (..., S)."""
    pos = neg = None
    for i in range(4):
        a = quads[..., i, None, :]
        b = quads[..., (i + 1) % 4, None, :]
        cross = (b[..., 0] - a[..., 0]) * (pts[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (pts[..., 0] - a[..., 0])
        pos = cross > _INSIDE_EPS if pos is None else pos & (cross > _INSIDE_EPS)
        neg = cross < -_INSIDE_EPS if neg is None else neg & (cross < -_INSIDE_EPS)
    return pos | neg  # type: ignore[operator]


def _plane_hit(cam: NDArray, d: NDArray, centre: NDArray, normal: NDArray) -> NDArray:
    """Ray parameter where ``cam + t d`` meets the plane through ``centre`` with ``normal``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return _dot(centre - cam, normal) / _dot(d, normal)


def _facet_normals_at(scene: ScoringScene, idx: NDArray, points: NDArray) -> NDArray:
    """Design normal of the facet nearest to each point (heliostat ``idx``), ENU."""
    local = np.einsum("mji,mj->mi", scene.rotations[idx], points - scene.centres[idx])
    d2 = np.sum((local[:, None, :2] - scene.facet_xy[None]) ** 2, axis=-1)
    return scene.facet_normals[idx, np.argmin(d2, axis=1)]


def _nudge_overhead(cam: NDArray, targets: Sequence[NDArray]) -> NDArray:
    """Move cameras 1 um North where one looks exactly straight down (image right undefined)."""
    bad = np.zeros(len(cam), dtype=bool)
    for t in targets:
        bad |= np.hypot(t[:, 0] - cam[:, 0], t[:, 1] - cam[:, 1]) < 1e-9
    if np.any(bad):
        cam = cam.copy()
        cam[bad, 1] += 1e-6
    return cam


def predict_images(scene: ScoringScene, cameras: ArrayLike, hua: ArrayLike, target: ArrayLike) -> ImagePredictions:
    """Predict the contrast scenarios for ``M`` images at once.

    Parameters
    ----------
    scene : ScoringScene
        Geometry and physics of the instant (:func:`build_scene`).
    cameras : array_like, shape (M, 3)
        Camera positions, field ENU metres.
    hua, target : array_like of int, shape (M,)
        Heliostat indices of each image's HUA and UFACET target (-1: no target).

    Returns
    -------
    ImagePredictions
    """
    cam = np.asarray(cameras, dtype=float).reshape(-1, 3)
    h = np.asarray(hua, dtype=np.int64).reshape(-1)
    tg = np.asarray(target, dtype=np.int64).reshape(-1)
    m = len(cam)
    if not (len(h) == m and len(tg) == m):
        raise PihimInputError("cameras, hua and target must have the same length")
    if m == 0:
        e = np.zeros(0)
        b = np.zeros(0, dtype=bool)
        p3 = np.zeros((0, 3))
        return ImagePredictions(np.zeros(0, dtype=np.int64), b, e, e, e, b, e, b, b, e, e, b, e, e, e, b, b, b, e,
                                p3, p3, p3, p3)
    n_helio = len(scene.centres)
    if np.any((h < 0) | (h >= n_helio)) or np.any(tg >= n_helio):
        raise PihimInputError("heliostat index out of range")
    sun, sky, mirror = scene.sun_dir, scene.sky, scene.model.mirror
    c_h, n_h = scene.centres[h], scene.normals[h]
    cam = _nudge_overhead(cam, [c_h])
    g, r, u = _view_basis(cam, c_h)

    # ---- candidates overlapping the HUA in the image
    cand = np.concatenate([tg[:, None], scene.neighbours[h]], axis=1)  # (M, K)
    dup = np.zeros(cand.shape, dtype=bool)
    for j in range(1, cand.shape[1]):
        dup[:, j] = np.any(cand[:, :j] == cand[:, j : j + 1], axis=1)
    valid = (cand >= 0) & (cand != h[:, None]) & ~dup
    cs = np.where(valid, cand, 0)
    hq, hq_depth = _project(scene.outlines[h], cam, g, r, u)  # (M, 4, 2)
    hs, _ = _project(scene.boundary[h], cam, g, r, u)  # (M, S, 2)
    # bounding circles in the image: only pairs that may overlap are tested in full
    radius = math.hypot(*scene.half_size)
    cc, cc_depth = _project(scene.centres[cs], cam, g, r, u)  # (M, K, 2)
    # a mirror of radius R whose centre is at depth d spans at most R / (d - R) in tangent units near the
    # image centre; 1.5 covers the tangent-plane stretch (sec^2) up to ~35 deg off axis
    hc_r = radius / np.maximum(np.linalg.norm(c_h - cam, axis=-1) - radius, 1e-9)
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = (radius / (cc_depth - radius) + hc_r[:, None]) * 1.5
    valid &= (cc_depth > 1.05 * radius) & np.all(hq_depth > 0, axis=-1)[:, None]
    valid &= np.hypot(cc[..., 0], cc[..., 1]) < reach  # the HUA centre is at the image origin
    pi, pk = np.nonzero(valid)
    pc = cs[pi, pk]
    cq, cq_depth = _project(scene.outlines[pc], cam[pi], g[pi], r[pi], u[pi])  # (P, 4, 2)
    csmp, _ = _project(scene.boundary[pc], cam[pi], g[pi], r[pi], u[pi])  # (P, S, 2)
    ok_p = np.all(cq_depth > 0, axis=-1)
    in_h = _inside(csmp, hq[pi]) & ok_p[:, None]  # candidate samples inside the HUA outline
    h_in = _inside(hs[pi], cq) & ok_p[:, None]  # HUA samples inside candidate outlines
    count = np.zeros(valid.shape, dtype=np.int64)
    count[pi, pk] = in_h.sum(-1) + h_in.sum(-1)
    pair_row = np.full(valid.shape, -1, dtype=np.int64)
    pair_row[pi, pk] = np.arange(len(pi))
    best = np.argmax(count, axis=1)  # ties: the lowest column, i.e. the target first
    rows = np.arange(m)
    has_pair = count[rows, best] > 0
    partner = np.where(has_pair, cs[rows, best], -1)

    out_nan = np.full(m, np.nan)
    sky_f, sky_b, sky_diff, hua_sky = out_nan.copy(), out_nan.copy(), out_nan.copy(), out_nan.copy()
    sky_ok = np.zeros(m, dtype=bool)
    hua_front = np.zeros(m, dtype=bool)
    hua_pt, partner_pt = np.full((m, 3), np.nan), np.full((m, 3), np.nan)
    if np.any(has_pair):
        sel = np.flatnonzero(has_pair)
        k = pair_row[sel, best[sel]]
        w1 = in_h[k].astype(float)[..., None]
        w2 = h_in[k].astype(float)[..., None]
        xy = (np.sum(csmp[k] * w1, axis=1) + np.sum(hs[sel] * w2, axis=1)) / (w1.sum(1) + w2.sum(1))
        d = normalize(g[sel] + xy[:, :1] * r[sel] + xy[:, 1:] * u[sel])
        p = partner[sel]
        t_h = _plane_hit(cam[sel], d, c_h[sel], n_h[sel])
        t_p = _plane_hit(cam[sel], d, scene.centres[p], scene.normals[p])
        pt_h = cam[sel] + t_h[:, None] * d
        pt_p = cam[sel] + t_p[:, None] * d
        hua_pt[sel], partner_pt[sel] = pt_h, pt_p
        front_h = t_h <= t_p
        hf = front_h[:, None]
        f_idx, b_idx = np.where(front_h, h[sel], p), np.where(front_h, p, h[sel])
        f_pt, b_pt = np.where(hf, pt_h, pt_p), np.where(hf, pt_p, pt_h)
        res = sky_vs_sky(cam[sel], f_pt, _facet_normals_at(scene, f_idx, f_pt),
                         b_pt, _facet_normals_at(scene, b_idx, b_pt), sun, sky, mirror)
        sky_f[sel], sky_b[sel] = res.front.dolp, res.back.dolp
        sky_diff[sel] = res.dolp_difference
        sky_ok[sel] = res.usable
        hua_front[sel] = front_h
        hua_sky[sel] = np.where(front_h, res.front.dolp, res.back.dolp)
        # the scenario arises only where both mirrors show sky and face the camera
        sky_f[sel] = np.where(np.isfinite(res.dolp_difference), sky_f[sel], np.nan)
        sky_b[sel] = np.where(np.isfinite(res.dolp_difference), sky_b[sel], np.nan)
        hua_sky[sel] = np.where(np.isfinite(res.dolp_difference), hua_sky[sel], np.nan)

    # ---- ground-vs-ground at the HUA's lower edge
    bottom = 0.5 * (scene.outlines[h, 2] + scene.outlines[h, 3])
    bxy, _ = _project(bottom[:, None], cam, g, r, u)  # (M, 1, 2)
    d_b = normalize(bottom - cam)
    covered = _inside(bxy[pi], cq)[:, 0] & ok_p  # (P,)
    t_c = _plane_hit(cam[pi], d_b[pi], scene.centres[pc], scene.normals[pc])
    dist_b = np.linalg.norm(bottom - cam, axis=-1)
    occluded = np.zeros(m, dtype=bool)
    np.logical_or.at(occluded, pi, covered & (t_c > 0) & (t_c < dist_b[pi] - 1e-6))
    g_axial, g_raw, hua_ground = out_nan.copy(), out_nan.copy(), out_nan.copy()
    g_ok = np.zeros(m, dtype=bool)
    g_arises = np.zeros(m, dtype=bool)
    ground_pt = np.full((m, 3), np.nan)
    look_down = d_b[:, 2] < -1e-9
    sel = np.flatnonzero(~occluded & look_down)
    if len(sel):
        gz = scene.ground_z[h[sel]]
        tg_ground = (gz - bottom[sel, 2]) / d_b[sel, 2]
        gpt = bottom[sel] + np.maximum(tg_ground, 0.0)[:, None] * d_b[sel]
        ground_pt[sel] = gpt
        res_g = ground_vs_ground(cam[sel], bottom[sel], _facet_normals_at(scene, h[sel], bottom[sel]), sun, sky,
                                 mirror, scene.ground, ground_point=gpt)
        arises = res_g.mirror.facing & ~res_g.mirror.shows_sky
        g_arises[sel] = arises
        g_axial[sel] = np.where(arises, res_g.aop_difference_deg, np.nan)
        g_raw[sel] = np.where(arises, res_g.aop_raw_difference_deg, np.nan)
        hua_ground[sel] = np.where(arises, res_g.mirror.dolp, np.nan)
        g_ok[sel] = res_g.usable & arises

    # ---- reflection DoLP at the HUA centre (used when no scenario arises)
    centre = mirror_reflection(cam, c_h, _facet_normals_at(scene, h, c_h), sun, sky, mirror, ground=scene.ground)
    centre_dolp = np.where(centre.facing, centre.dolp, np.nan)

    with np.errstate(invalid="ignore"):
        usable_max = np.fmax(np.where(sky_ok, hua_sky, np.nan), np.where(g_ok, hua_ground, np.nan))
        arising_max = np.fmax(hua_sky, hua_ground)
    refl = np.where(np.isfinite(usable_max), usable_max, np.where(np.isfinite(arising_max), arising_max, centre_dolp))
    refl_ok = np.nan_to_num(refl, nan=0.0) > REFLECTION_DOLP_MIN
    usable = refl_ok & (sky_ok | g_ok)

    # ---- UFACET: does the HUA show the target's back?
    extent = np.full(m, np.inf)
    has_t = tg >= 0
    if np.any(has_t):
        st = np.flatnonzero(has_t)
        d_in = normalize(c_h[st] - cam[st])
        d_out = d_in - 2.0 * _dot(d_in, n_h[st])[:, None] * n_h[st]
        tt = tg[st]
        t_hit = _plane_hit(c_h[st], d_out, scene.centres[tt], scene.normals[tt])
        pt = c_h[st] + np.nan_to_num(t_hit)[:, None] * d_out
        local = np.einsum("mji,mj->mi", scene.rotations[tt], pt - scene.centres[tt])
        hw, hh = scene.half_size
        ext = np.maximum(np.abs(local[:, 0]) / hw, np.abs(local[:, 1]) / hh)
        extent[st] = np.where(t_hit > 0, ext, np.inf)
    return ImagePredictions(
        partner=partner,
        hua_is_front=hua_front,
        sky_front_dolp=sky_f,
        sky_back_dolp=sky_b,
        sky_dolp_difference=sky_diff,
        sky_ok=sky_ok,
        hua_sky_dolp=hua_sky,
        ground_arises=g_arises,
        ground_occluded=occluded,
        ground_aop_difference_deg=g_axial,
        ground_aop_raw_difference_deg=g_raw,
        ground_ok=g_ok,
        hua_ground_dolp=hua_ground,
        centre_dolp=centre_dolp,
        reflection_dolp=refl,
        reflection_ok=refl_ok,
        usable=usable,
        target_hit=extent <= 1.0,
        target_hit_extent=extent,
        hua_point=hua_pt,
        partner_point=partner_pt,
        bottom_point=bottom,
        ground_point=ground_pt,
    )


# --------------------------------------------------------------------------- passes


@dataclass(frozen=True, eq=False)
class _Images:
    """The capture waypoints of a set of passes, flattened."""

    pass_id: NDArray[np.int64]
    waypoint_index: NDArray[np.int64]
    hua: NDArray[np.int64]
    target: NDArray[np.int64]
    cameras: NDArray[np.float64]
    heading_deg: NDArray[np.float64]
    pitch_deg: NDArray[np.float64]
    hua_names: tuple[str, ...]
    target_names: tuple[str, ...]


def _collect_images(passes: Sequence[ScanPass], fld: Any) -> _Images:
    cols: dict[str, list[Any]] = {k: [] for k in ("p", "w", "h", "t", "c", "hd", "pt", "hn", "tn")}
    index = getattr(fld, "name_index", None)  # not rebuilt for each group of passes (19 ms at 100,000)
    if index is None:  # a field-like object without one
        index = {n: i for i, n in enumerate(fld.names)}

    def canon(name: str) -> str:  # exact names are looked up directly; other spellings are parsed
        return name if name in index else fld.names[fld.index(name)]

    for pi, sp in enumerate(passes):
        pairs = [(canon(h), canon(t)) for h, t in sp.pairs]
        targets: dict[str, str] = {}
        for hua_name, target_name in pairs:
            targets.setdefault(hua_name, target_name)
        captures = [(wi, canon(wp.hua)) for wi, wp in enumerate(sp.waypoints) if wp.capture and wp.hua]
        # the planner's contract: the k-th capture images pairs[k]; otherwise the HUA's first pair
        one_to_one = len(captures) == len(pairs) and all(c[1] == pr[0] for c, pr in zip(captures, pairs, strict=False))
        for k, (wi, h_name) in enumerate(captures):
            wp = sp.waypoints[wi]
            if h_name not in targets:
                raise PihimInputError(
                    f"pass {sp.index}: capture waypoint {wi} images {wp.hua!r}, which is in none of the pass's pairs"
                )
            t_name = pairs[k][1] if one_to_one else targets[h_name]
            cols["p"].append(pi)
            cols["w"].append(wi)
            cols["h"].append(index[h_name])
            cols["t"].append(index[t_name])
            cols["c"].append((wp.x_m, wp.y_m, wp.z_m))
            cols["hd"].append(wp.heading_deg)
            cols["pt"].append(wp.gimbal_pitch_deg)
            cols["hn"].append(h_name)
            cols["tn"].append(t_name)
    return _Images(
        pass_id=np.array(cols["p"], dtype=np.int64),
        waypoint_index=np.array(cols["w"], dtype=np.int64),
        hua=np.array(cols["h"], dtype=np.int64),
        target=np.array(cols["t"], dtype=np.int64),
        cameras=np.array(cols["c"], dtype=float).reshape(-1, 3),
        heading_deg=np.array(cols["hd"], dtype=float),
        pitch_deg=np.array(cols["pt"], dtype=float),
        hua_names=tuple(cols["hn"]),
        target_names=tuple(cols["tn"]),
    )


def _opt(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _pair_predictions(imgs: _Images, pred: ImagePredictions, sel: NDArray[np.int64]) -> tuple[PairPrediction, ...]:
    """PairPrediction records of images ``sel`` (indices into ``imgs``), in the given order;
    ``pred`` is aligned with ``sel``."""
    out = []
    for j, i in enumerate(sel):
        out.append(PairPrediction(
            hua=imgs.hua_names[i],
            target=imgs.target_names[i],
            waypoint_index=int(imgs.waypoint_index[i]),
            reflection_dolp=_opt(pred.reflection_dolp[j]),
            sky_dolp_difference=_opt(pred.sky_dolp_difference[j]),
            ground_aop_difference_deg=_opt(pred.ground_aop_difference_deg[j]),
            ground_aop_raw_difference_deg=_opt(pred.ground_aop_raw_difference_deg[j]),
            reflection_dolp_ok=bool(pred.reflection_ok[j]),
            sky_vs_sky_ok=bool(pred.sky_ok[j]),
            ground_vs_ground_ok=bool(pred.ground_ok[j]),
        ))
    return tuple(out)


def _take(pred: ImagePredictions, idx: NDArray[np.int64]) -> ImagePredictions:
    return ImagePredictions(**{f.name: getattr(pred, f.name)[idx] for f in dataclasses.fields(pred)})


def _gaze(cam: NDArray, look_at: NDArray) -> tuple[NDArray, NDArray]:
    """Heading (deg clockwise from North, [0, 360)) and pitch (deg, negative down) from ``cam`` to ``look_at``."""
    d = look_at - cam
    heading = np.mod(np.degrees(np.arctan2(d[..., 0], d[..., 1])), 360.0)
    return np.where(heading >= 360.0, 0.0, heading), np.degrees(np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1])))


def _framing(cam: NDArray, points: NDArray, heading_deg: NDArray, pitch_deg: NDArray,
             camera: CameraModel) -> NDArray[np.float64]:
    """Fraction of ``points`` (..., F, 3) inside the image of cameras (..., 3) with the given attitude
    (:func:`pihim.planning.sightlines.in_fov`)."""
    from pihim.planning.sightlines import in_fov

    return in_fov(points, cam, heading_deg, pitch_deg, camera).mean(axis=-1)


def _tower_ok(points: NDArray, tower: Any, clearance: float) -> NDArray[np.bool_]:
    if tower is None:
        return np.ones(points.shape[:-1], dtype=bool)
    dx = np.maximum.reduce([tower.x_min_m - points[..., 0], np.zeros(points.shape[:-1]), points[..., 0] - tower.x_max_m])
    dy = np.maximum.reduce([tower.y_min_m - points[..., 1], np.zeros(points.shape[:-1]), points[..., 1] - tower.y_max_m])
    return (np.hypot(dx, dy) >= clearance) | (points[..., 2] >= tower.height_m + clearance)


def _beam_margin(points: NDArray, centres: NDArray, aim: NDArray, radius: float,
                 beams: _BeamIndex | None = None) -> NDArray[np.float64]:
    """Smallest clearance of each point (W, 3) from the reflected beams (cones from the mirrors to ``aim``).

    With ``beams`` only the beams within its reach of a point are measured;
    a point farther than the reach from every beam gets +inf.
    """
    if beams is not None:
        return beams.margin(points)
    ab = aim[None, :] - centres  # (N, 3)
    q = points[:, None, :] - centres[None]  # (W, N, 3)
    t = np.clip(np.sum(q * ab[None], axis=-1) / np.sum(ab * ab, axis=-1)[None], 0.0, 1.0)
    dist = np.linalg.norm(q - t[..., None] * ab[None], axis=-1)
    return np.min(dist - (1.0 - t) * radius, axis=1)


class _BeamIndex:
    """The reflected beams (segments mirror centre -> aim point, cones of base ``radius``) indexed by direction.

    A point ``P`` within ``reach`` of the segment from ``c`` to the aim point
    ``a`` sees it within ``asin(reach / |P - a|)`` of the direction ``c - a``
    from ``a`` (law of sines in the triangle a, P, nearest point), so a k-d
    tree over the unit directions from the aim point to the mirrors finds
    every beam that can come that close: the clearance of a shifted pass is
    checked against the beams near it, not against the whole field.
    """

    def __init__(self, centres: NDArray, aim: NDArray, radius: float, reach: float) -> None:
        from scipy.spatial import cKDTree

        self.centres, self.aim, self.radius, self.reach = centres, aim, float(radius), float(reach)
        d = centres - aim[None]
        self.tree = cKDTree(d / np.linalg.norm(d, axis=1, keepdims=True))

    def margin(self, points: NDArray) -> NDArray[np.float64]:
        p = np.atleast_2d(np.asarray(points, float))
        v = p - self.aim[None]
        dist = np.linalg.norm(v, axis=1)
        out = np.full(len(p), np.inf)
        near_aim = dist <= self.reach
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(near_aim[:, None], 0.0, v / dist[:, None])
            ang = np.where(near_aim, np.pi, np.arcsin(np.minimum(1.0, self.reach / dist)))
        chord = np.where(ang >= np.pi / 2, 2.0, 2.0 * np.sin(0.5 * ang)) + 1e-9
        lists = self.tree.query_ball_point(u, chord, return_sorted=False)
        for k, lst in enumerate(lists):
            if near_aim[k]:
                lst = range(len(self.centres))
            if len(lst) == 0:
                continue
            out[k] = _beam_margin(p[k:k + 1], self.centres[np.fromiter(lst, dtype=np.int64)], self.aim,
                                  self.radius)[0]
        return out


def _blocked(scene: ScoringScene, cams: NDArray, hua: NDArray, target: NDArray) -> NDArray[np.bool_]:
    """Whether another tracked mirror blocks the sight line camera -> HUA centre or the reflected
    ray HUA centre -> target plane (:func:`pihim.planning.ufacet.first_mirror_hits`)."""
    from pihim.planning.ufacet import first_mirror_hits

    c_h, n_h = scene.centres[hua], scene.normals[hua]
    sight = first_mirror_hits(scene.pose, cams, c_h - 1e-3 * normalize(c_h - cams), exclude=hua) >= 0
    d_in = normalize(c_h - cams)
    d_out = d_in - 2.0 * _dot(d_in, n_h)[:, None] * n_h
    t = _plane_hit(c_h, d_out, scene.centres[target], scene.normals[target])
    t = np.where(np.isfinite(t) & (t > 0), t, 0.0)
    end = c_h + t[:, None] * d_out
    refl = first_mirror_hits(scene.pose, c_h + 1e-3 * d_out, end, exclude=np.stack([hua, target], axis=1)) >= 0
    return sight | (refl & (t > 0))


def _slide(cam: NDArray, c_h: NDArray, along: NDArray, across: NDArray, gaze_deg: NDArray) -> tuple[NDArray, NDArray]:
    """Slide cameras along the track so the line-of-sight elevation (from the HUA) changes by ``gaze_deg``.

    Returns the new positions and whether the slide exists.
    """
    q = cam - c_h
    hgt = q[:, 2]
    a, b = _dot(q, along), _dot(q, across)
    elev = np.arctan2(hgt, np.hypot(a, b))
    new = elev + np.radians(gaze_deg)
    ok = (hgt > 0) & (new > math.radians(1.0)) & (new < math.radians(89.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        r_new = hgt / np.tan(new)
        rad = r_new**2 - b**2
        ok &= rad >= 0
        a_new = np.where(a >= 0, 1.0, -1.0) * np.sqrt(np.maximum(rad, 0.0))
    s = np.where(ok & (gaze_deg != 0.0), a_new - a, 0.0)
    return cam + s[:, None] * along, ok | (gaze_deg == 0.0)


def _track_axes(azimuth_deg: NDArray) -> tuple[NDArray, NDArray]:
    """Horizontal unit vectors along the direction of travel and to its right."""
    az = np.radians(azimuth_deg)
    along = np.stack([np.sin(az), np.cos(az), np.zeros_like(az)], axis=-1)
    right = np.stack([np.cos(az), -np.sin(az), np.zeros_like(az)], axis=-1)
    return along, right


def _moved_waypoints(sp: ScanPass, new_xyz: NDArray, origin: Any) -> tuple[Waypoint, ...]:
    """Waypoints at new field positions, geodetic coordinates recomputed."""
    import pymap3d

    old = np.array([(w.x_m, w.y_m, w.z_m) for w in sp.waypoints], dtype=float)
    if origin is not None:
        from pihim.field.geodesy import enu_to_geodetic

        lat, lon, hgt = enu_to_geodetic(new_xyz, origin)
    else:  # offset in the tangent frame of each waypoint's own geodetic position (sub-mm for metre shifts)
        d = new_xyz - old
        lat0 = np.array([w.latitude_deg for w in sp.waypoints])
        lon0 = np.array([w.longitude_deg for w in sp.waypoints])
        h0 = np.array([w.height_m for w in sp.waypoints])
        lat, lon, hgt = (np.asarray(v, dtype=float) for v in
                         pymap3d.enu2geodetic(d[:, 0], d[:, 1], d[:, 2], lat0, lon0, h0, deg=True))
    return tuple(
        dataclasses.replace(w, x_m=float(p[0]), y_m=float(p[1]), z_m=float(p[2]), latitude_deg=float(la),
                            longitude_deg=float(lo), height_m=float(hh))
        for w, p, la, lo, hh in zip(sp.waypoints, new_xyz, np.atleast_1d(lat), np.atleast_1d(lon),
                                    np.atleast_1d(hgt), strict=True)
    )


def score_passes(
    passes: Sequence[ScanPass],
    pose: Any,
    sun_dir: ArrayLike,
    *,
    model: ScoringModel | None = None,
    scene: ScoringScene | None = None,
    search: ShiftSearch | None = DEFAULT_SHIFT_SEARCH,
    camera: CameraModel | None = None,
    aim_point: ArrayLike | None = None,
    origin: Any = None,
    batch_images: int = 2000,
    workers: int | None = 1,
) -> tuple[ScanPass, ...]:
    """Predict the contrast of every planned image and, optionally, shift passes to raise it.

    Parameters
    ----------
    passes : sequence of ScanPass
        Planned passes; capture waypoints (``capture=True``) with ``hua`` set
        are the images, and ``pairs`` gives each HUA's target.
    pose : FieldPose
        The tracked field the passes were planned for.
    sun_dir : array_like, shape (3,)
        ENU unit vector toward the sun (above the horizon).
    model : ScoringModel, optional
        Physics; ignored when ``scene`` is given.
    scene : ScoringScene, optional
        A prepared :func:`build_scene` for this pose and sun (reuse it to
        score several plans of one instant).
    search : ShiftSearch or None
        Shift grid and constraints; ``None`` scores the passes as planned.
    camera : CameraModel, optional
        For the framing constraint of shifts (default Triton + 35 mm).
    aim_point : array_like, shape (3,), optional
        Where the heliostats send the sunlight; enables the beam-clearance
        check of shifts.
    origin : Site, GeodeticOrigin or (lat, lon, h), optional
        Field origin for exact geodetic coordinates of shifted waypoints;
        without it each waypoint's own geodetic position is offset locally.
    batch_images : int
        Passes are scored in consecutive groups of about this many images
        (passes are independent; the groups bound the memory of large
        fields, the result does not depend on it).
    workers : int or None
        Processes scoring groups side by side (forked on Linux,
        :func:`pihim._forked.imap_unordered`; None: one per CPU). The result
        does not depend on it.

    Returns
    -------
    tuple of ScanPass
        Copies with ``predictions`` (one per capture waypoint, in waypoint
        order) and, where a shift raised the usable fraction, moved waypoints
        (capture waypoints re-aimed at their HUA), ``altitude_m`` and a
        :class:`PassShift` recording the move and the before/after usable
        fractions; other passes keep ``shift=None``.
    """
    passes = tuple(passes)
    from pihim._forked import check_workers

    check_workers(workers)
    if isinstance(batch_images, bool) or not isinstance(batch_images, int) or batch_images < 1:
        raise PihimInputError(f"batch_images must be a positive integer, got {batch_images!r}")
    if scene is None:
        scene = build_scene(pose, sun_dir, model)
    elif scene.pose is not pose:
        raise PihimInputError("scene was built for another FieldPose")
    counts = [sum(w.capture for w in sp.waypoints) for sp in passes]
    if sum(counts) > batch_images and len(passes) > 1:
        groups: list[list[ScanPass]] = [[]]
        size = 0
        for sp, k in zip(passes, counts, strict=True):
            if groups[-1] and size + k > batch_images:
                groups.append([])
                size = 0
            groups[-1].append(sp)
            size += k
        from pihim import _forked

        if search is not None:
            _shift_setup(scene, search, aim_point)  # built here once, inherited by forked workers

        def group(i: int) -> tuple[ScanPass, ...]:
            return score_passes(groups[i], pose, sun_dir, scene=scene, search=search, camera=camera,
                                aim_point=aim_point, origin=origin, batch_images=batch_images)

        return tuple(sp for g in _forked.map_pieces(group, len(groups), workers, what="groups of passes") for sp in g)
    fld = pose.field
    imgs = _collect_images(passes, fld)
    pred = predict_images(scene, imgs.cameras, imgs.hua, imgs.target)
    n_pass = len(passes)
    n_img = np.bincount(imgs.pass_id, minlength=n_pass)
    nominal = np.bincount(imgs.pass_id, weights=pred.usable.astype(float), minlength=n_pass)
    with np.errstate(invalid="ignore", divide="ignore"):
        nominal = np.where(n_img > 0, nominal / np.maximum(n_img, 1), 0.0)
    order = [np.flatnonzero(imgs.pass_id == p) for p in range(n_pass)]
    result = [
        dataclasses.replace(sp, predictions=_pair_predictions(imgs, _take(pred, order[p]), order[p]))
        for p, sp in enumerate(passes)
    ]
    if search is None or len(imgs.hua) == 0:
        return tuple(result)
    chosen = _search_shifts(passes, imgs, pred, nominal, scene, search, camera or CameraModel(), aim_point)
    for p, (cand, shifted_cams, headings, pitches, shifted_pred) in chosen.items():
        sp = passes[p]
        dz, dl, gaze = (float(v) for v in cand)
        _, right = _track_axes(np.array([sp.azimuth_deg]))
        xyz = np.array([(w.x_m, w.y_m, w.z_m) for w in sp.waypoints], dtype=float)
        xyz = xyz + dl * right[0] + np.array([0.0, 0.0, dz])
        xyz[imgs.waypoint_index[order[p]]] = shifted_cams
        after = float(np.mean(shifted_pred.usable))
        moved = list(_moved_waypoints(sp, xyz, origin))
        for wi, hd, pt in zip(imgs.waypoint_index[order[p]], headings, pitches, strict=True):
            moved[wi] = dataclasses.replace(moved[wi], heading_deg=float(hd), gimbal_pitch_deg=float(pt))
        result[p] = dataclasses.replace(
            result[p],
            altitude_m=sp.altitude_m + dz,
            waypoints=tuple(moved),
            predictions=_pair_predictions(imgs, shifted_pred, order[p]),
            shift=PassShift(altitude_delta_m=dz, lateral_offset_m=dl, gaze_delta_deg=gaze,
                            usable_fraction_before=float(nominal[p]), usable_fraction_after=after),
        )
    return tuple(result)


#: Per scene, what every group of passes would otherwise rebuild (:func:`_shift_setup`): the field's highest
#: mirror point and the beams' direction index, 55 and 40 ms at 100,000 heliostats for each of the ~140 groups of
#: the two scorings of a build_plan.
_SCENE_MEMO: weakref.WeakKeyDictionary[ScoringScene, dict[Any, Any]] = weakref.WeakKeyDictionary()


def _shift_setup(scene: ScoringScene, search: ShiftSearch,
                 aim_point: ArrayLike | None) -> tuple[float, NDArray[np.float64] | None, _BeamIndex | None]:
    """The shift search's lowest altitude, aim point and beam index for ``scene``, built once per scene."""
    memo = _SCENE_MEMO.setdefault(scene, {})
    if search.min_altitude_m is not None:
        min_alt = float(search.min_altitude_m)
    else:
        if "min_alt" not in memo:
            memo["min_alt"] = min_safe_altitude_m(scene.pose)
        min_alt = memo["min_alt"]
    if aim_point is None:
        return min_alt, None, None
    aim = np.array(aim_point, dtype=float).reshape(3)  # a copy: the cached index must not see the caller's edits
    aim.setflags(write=False)
    radius = math.hypot(*scene.half_size)
    key = ("beams", aim.tobytes(), np.float64(search.beam_clearance_m).tobytes())  # bytes: a NaN finds itself
    if key not in memo:
        memo[key] = _BeamIndex(scene.centres, aim, radius, search.beam_clearance_m + radius)
    return min_alt, aim, memo[key]


def _search_shifts(
    passes: Sequence[ScanPass],
    imgs: _Images,
    nominal_pred: ImagePredictions,
    nominal: NDArray[np.float64],
    scene: ScoringScene,
    search: ShiftSearch,
    camera: CameraModel,
    aim_point: ArrayLike | None,
) -> dict[int, tuple[NDArray, NDArray, NDArray, NDArray, ImagePredictions]]:
    """Best admissible shift per pass that raises its usable fraction.

    Returns ``{pass: (candidate, cameras, headings, pitches, predictions)}`` for its capture images.
    """
    cands = search.candidates()
    n_pass, n_cand, m = len(passes), len(cands), len(imgs.hua)
    if n_cand == 0:
        return {}
    fld = scene.field
    tower = getattr(fld, "tower", None)
    min_alt, aim, beams = _shift_setup(scene, search, aim_point)
    max_alt = float(search.max_altitude_m)

    # pass-level checks on all waypoints: altitude limits and tower clearance
    wp_xyz = [np.array([(w.x_m, w.y_m, w.z_m) for w in sp.waypoints], dtype=float).reshape(-1, 3) for sp in passes]
    az = np.array([sp.azimuth_deg for sp in passes], dtype=float)
    along_p, right_p = _track_axes(az)
    pass_ok = np.ones((n_cand, n_pass), dtype=bool)
    for p, xyz in enumerate(wp_xyz):
        if len(xyz) == 0:
            pass_ok[:, p] = False
            continue
        zlo, zhi = xyz[:, 2].min(), xyz[:, 2].max()
        pass_ok[:, p] &= (zlo + cands[:, 0] >= min_alt - 1e-9) & (zhi + cands[:, 0] <= max_alt + 1e-9)
        nom_tower = _tower_ok(xyz, tower, search.tower_clearance_m)
        moved = xyz[None] + cands[:, 1, None, None] * right_p[p] + cands[:, 0, None, None] * _UP
        pass_ok[:, p] &= np.all(_tower_ok(moved, tower, search.tower_clearance_m) | ~nom_tower[None], axis=1)

    # image-level geometry of every candidate
    pid = imgs.pass_id
    c_h = scene.centres[imgs.hua]
    cams = (imgs.cameras[None] + cands[:, 1, None, None] * right_p[pid][None]
            + cands[:, 0, None, None] * _UP)  # (G, M, 3)
    flat = cams.reshape(-1, 3)
    gaze = np.repeat(cands[:, 2], m)
    flat, slide_ok = _slide(flat, np.tile(c_h, (n_cand, 1)), np.tile(along_p[pid], (n_cand, 1)),
                            np.tile(right_p[pid], (n_cand, 1)), gaze)
    cams = flat.reshape(n_cand, m, 3)
    slide_ok = slide_ok.reshape(n_cand, m)
    heading, pitch = _gaze(cams, c_h[None])
    facets = np.asarray(scene.pose.facet_centres, dtype=float)[imgs.hua]
    frame_nom = _framing(imgs.cameras, facets, imgs.heading_deg, imgs.pitch_deg, camera)
    frame_new = _framing(cams, facets[None], heading, pitch, camera)
    framing_ok = frame_new >= np.minimum(frame_nom, search.min_framing)[None] - 1e-9
    pitch_ok = (pitch >= search.gimbal_pitch_min_deg) & (pitch <= search.gimbal_pitch_max_deg)
    tower_nom = _tower_ok(imgs.cameras, tower, search.tower_clearance_m)
    img_ok = slide_ok & framing_ok & pitch_ok & (_tower_ok(cams, tower, search.tower_clearance_m)
                                                 | ~tower_nom[None])
    bad = np.zeros((n_cand, n_pass), dtype=bool)
    np.logical_or.at(bad, (np.repeat(np.arange(n_cand), m), np.tile(pid, n_cand)), ~img_ok.reshape(-1))
    cand_ok = pass_ok & ~bad & (np.bincount(pid, minlength=n_pass) > 0)[None]
    # only passes that can gain
    cand_ok &= (nominal < 1.0)[None]
    run = cand_ok[:, pid]  # (G, M): images to evaluate
    gi, mi = np.nonzero(run)
    if len(gi) == 0:
        return {}
    pred = predict_images(scene, cams[gi, mi], imgs.hua[mi], imgs.target[mi])
    # UFACET requirement kept where it held nominally
    nom_hit = nominal_pred.target_hit_extent <= search.target_outline_fraction
    keep = (pred.target_hit_extent <= search.target_outline_fraction) | ~nom_hit[mi]
    viol = np.zeros((n_cand, n_pass), dtype=bool)
    np.logical_or.at(viol, (gi, pid[mi]), ~keep)
    usable = np.zeros((n_cand, n_pass))
    np.add.at(usable, (gi, pid[mi]), pred.usable.astype(float))
    counts = np.bincount(pid, minlength=n_pass).astype(float)
    frac = np.where(cand_ok & ~viol, usable / np.maximum(counts, 1.0)[None], -1.0)
    scale = np.array([max(max(abs(v) for v in vals), 1e-12) for vals in
                      (search.altitude_deltas_m, search.lateral_offsets_m, search.gaze_deltas_deg)])
    cost = np.sum(np.abs(cands) / scale, axis=1)
    radius = math.hypot(*scene.half_size)
    # row in `pred` of (candidate, image)
    lookup = np.full((n_cand, m), -1, dtype=np.int64)
    lookup[gi, mi] = np.arange(len(gi))
    chosen: dict[int, tuple[NDArray, NDArray, NDArray, NDArray, ImagePredictions]] = {}
    nominal_blocked: NDArray[np.bool_] | None = None
    for p in range(n_pass):
        gains = frac[:, p] - nominal[p]
        ranked = [g for g in np.lexsort((cost, -frac[:, p])) if gains[g] > 1e-12]
        sel = np.flatnonzero(pid == p)
        for g in ranked:
            if aim is not None:
                xyz = wp_xyz[p] + cands[g, 1] * right_p[p] + cands[g, 0] * _UP
                xyz[imgs.waypoint_index[sel]] = cams[g, sel]
                nom_margin = _beam_margin(wp_xyz[p], scene.centres, aim, radius, beams)
                new_margin = _beam_margin(xyz, scene.centres, aim, radius, beams)
                if np.any(new_margin < np.minimum(nom_margin, search.beam_clearance_m) - 1e-9):
                    continue
            if nominal_blocked is None:
                nominal_blocked = _blocked(scene, imgs.cameras, imgs.hua, imgs.target)
            if np.any(_blocked(scene, cams[g, sel], imgs.hua[sel], imgs.target[sel]) & ~nominal_blocked[sel]):
                continue  # the shift would hide the HUA or the target's reflection behind another mirror
            chosen[p] = (cands[g], cams[g, sel], heading[g, sel], pitch[g, sel], _take(pred, lookup[g, sel]))
            break
    return chosen


def images_text(summary: Mapping[str, Any]) -> str:
    """A plan summary's captures and coverage in words, as ``pihim plan``, ``pihim demo`` and the demo report say it.

    Separates what the canting measurement needs (the target's reflection
    with DoLP > 0.2, paper sec. 5) from the paper's edge-contrast scenarios
    (sec. 4.1-4.2), which the paper finds at NSTTF mostly at 9:30-11:30 and
    14:00-16:00: around noon a plan can have none without being useless.
    """
    n, u = int(summary["images"]), int(summary["usable_images"])
    r = summary.get("reflection_images")
    cov = summary.get("coverage", {})
    text = (f"{n} captures, {'?' if r is None else r} showing the target's reflection with DoLP > 0.2 (for canting), "
            f"{u} also an outline edge with the paper's polarimetric contrast (sky-vs-sky or ground-vs-ground)")
    if n and not u:
        text += ": none at this hour (pihim windows lists the hours that have them)"
    if cov:
        text += (f"; heliostats of the field imaged {100 * cov.get('planned', 0.0):.0f} %, with the reflection "
                 f"{100 * cov.get('reflection', 0.0):.0f} %, with a contrast edge {100 * cov.get('either', 0.0):.0f} %")
    return text


def coverage(passes: Sequence[ScanPass], n_heliostats: int) -> dict[str, float]:
    """Fractions of a field's heliostats with at least one planned / usable image.

    Parameters
    ----------
    passes : sequence of ScanPass
        Scored passes.
    n_heliostats : int
        Size of the field (the denominator).

    Returns
    -------
    dict
        ``planned``: HUAs with at least one image; ``reflection``: with an
        image whose target reflection has DoLP > 0.2 (what the canting
        measurement needs, paper sec. 5); ``sky``: with an image whose
        reflection DoLP > 0.2 and sky-vs-sky usable; ``ground``: likewise
        ground-vs-ground; ``either``: with a usable image (either scenario).
    """
    sets: dict[str, set[str]] = {"planned": set(), "reflection": set(), "sky": set(), "ground": set(),
                                 "either": set()}
    for sp in passes:
        for pr in sp.predictions:
            sets["planned"].add(pr.hua)
            if pr.reflection_dolp_ok:
                sets["reflection"].add(pr.hua)
            if pr.reflection_dolp_ok and pr.sky_vs_sky_ok:
                sets["sky"].add(pr.hua)
            if pr.reflection_dolp_ok and pr.ground_vs_ground_ok:
                sets["ground"].add(pr.hua)
            if pr.usable:
                sets["either"].add(pr.hua)
    n = max(int(n_heliostats), 1)
    return {k: len(v) / n for k, v in sets.items()}
