"""Heliostat field layout: heliostats, their common geometry and the tower.

A :class:`Field` is a set of heliostats of one :class:`HeliostatSpec` (the
same facet grid, pivot geometry and facet size everywhere), their torque-tube
pivots in the field frame and, optionally, the receiver :class:`Tower`. It
knows nothing about the site (latitude, longitude, time); the sun comes in
as an East-North-Up direction when the field is tracked
(:mod:`pihim.field.kinematics`).

Frames and names
----------------
* Field frame: East-North-Up, metres, origin at the base of the tower (the
  NSTTF convention [2]_). Pivots are the torque-tube pivot points, i.e. the
  centre of rotation of the az-el drive, **not** the mirror centre: the mirror
  plane is ``pivot_offset_m`` in front of the pivot along the mirror normal.
* Heliostat frame (:mod:`pihim.field.kinematics`): looking at the mirror face,
  ``x`` right, ``y`` up (toward the top edge), ``z`` the mirror normal out of
  the face; origin at the mirror centre. Facet centroids are given in it.
* Facets are numbered 1..F row by row from the top left as seen from the
  front: for the NSTTF 5 x 5 grid, 1-5 is the top row (left to right), 13 the
  centre, 5/10/15/20/25 the right column.
* Heliostat names follow the NSTTF scheme ``<row><E|W><column>``: ``8E3`` is
  in row 8, the 3rd heliostat East of the North-South centre line. Names are
  parsed case-insensitively and with leading zeros (OpenCSP sometimes writes
  ``5W01``) and stored canonically (``5W1``).

Data files
----------
:func:`load_field` reads the OpenCSP heliostat CSV (columns ``Name, X, Y, Z,
Num. Facets, Num. Rows, Num. Cols, Pivot Height, Pivot Offset, Facet Width,
Facet Height``) and, optionally, the facet-centroid CSV (``Facet id, X, Y,
Z``) [1]_. A UTF-8 byte-order mark is tolerated. Malformed rows raise
:class:`~pihim.errors.PihimInputError` with ``<file>:<line>:`` in front of a
one-line message.

Generated fields
----------------
:func:`nsttf_like_field` builds an NSTTF-like rectangular field from a few
spacing rules (no data file): rows 5-14 north of the tower, 218 heliostats.
:func:`radial_staggered_field` builds large radial-staggered fields (10^4 to
10^5 heliostats and more) in the manner of Collado and Guallar's *campo*
layouts [3]_.

References
----------
.. [1] Sandia National Laboratories, OpenCSP (Apache-2.0),
   https://github.com/sandialabs/OpenCSP: NSTTF heliostat and facet-centroid
   CSV files (``NSTTF_Heliostats_origin_at_torque_tube.csv``,
   ``NSTTF_Facet_Centroids.csv``) and the NSTTF tower figures (height
   63.5508 m, footprint x -5.485..5.485 m, y -9.1186..6.25 m, target
   (0, 6.25, 63.5508) m; BCS stand-by aim point (0, 8.8, 28.9) m; UFACET
   plans aim at (60.0, 8.8, 28.9) m).
.. [2] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone" (pihim paper), section 3 and supplementary Fig. S1.
.. [3] F. J. Collado and J. Guallar, "Campo: Generation of regular heliostat
   fields", Renewable Energy 46, 49-59 (2012),
   doi:10.1016/j.renene.2012.03.011; F. J. Collado and J. Guallar, "A review
   of optimized design layouts for solar power tower plants with campo
   code", Renewable and Sustainable Energy Reviews 20, 142-154 (2013),
   doi:10.1016/j.rser.2012.11.076.
"""

from __future__ import annotations

import csv
import io
import math
import re
import stat
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError

__all__ = [
    "FACET_CSV_COLUMNS",
    "HELIOSTAT_CSV_COLUMNS",
    "INCH_M",
    "NSTTF_BCS_STANDBY",
    "NSTTF_FACET_SIZE_M",
    "NSTTF_PIVOT_HEIGHT_M",
    "NSTTF_PIVOT_OFFSET_M",
    "NSTTF_TOWER",
    "NSTTF_TOWER_TARGET",
    "UFACET_AIM_POINT",
    "Field",
    "Heliostat",
    "HeliostatSpec",
    "Tower",
    "canonical_name",
    "grid_facet_centroids",
    "load_facet_centroids",
    "load_field",
    "nsttf_facet_centroids",
    "nsttf_like_field",
    "nsttf_spec",
    "parse_heliostat_name",
    "radial_staggered_field",
]

#: One inch in metres (NSTTF dimensions are imperial).
INCH_M = 0.0254
_FOOT_M = 12 * INCH_M

#: NSTTF facet width and height, metres (4 ft; OpenCSP heliostat CSV).
NSTTF_FACET_SIZE_M = 1.2192
#: NSTTF pivot height above the ground, metres (OpenCSP heliostat CSV).
NSTTF_PIVOT_HEIGHT_M = 4.02
#: NSTTF distance from the torque-tube pivot to the mirror plane along the
#: normal, metres (7 in; OpenCSP heliostat CSV).
NSTTF_PIVOT_OFFSET_M = 0.1778

#: NSTTF tower target (receiver aim point), field frame, metres (OpenCSP).
NSTTF_TOWER_TARGET = (0.0, 6.25, 63.5508)
#: NSTTF beam characterisation system (BCS) stand-by aim point, metres (OpenCSP).
NSTTF_BCS_STANDBY = (0.0, 8.8, 28.9)
#: Aim point used by OpenCSP's UFACET flight plans, metres.
UFACET_AIM_POINT = (60.0, 8.8, 28.9)

#: Column names of the OpenCSP heliostat CSV, in file order.
HELIOSTAT_CSV_COLUMNS = (
    "Name",
    "X",
    "Y",
    "Z",
    "Num. Facets",
    "Num. Rows",
    "Num. Cols",
    "Pivot Height",
    "Pivot Offset",
    "Facet Width",
    "Facet Height",
)
#: Column names of the OpenCSP facet-centroid CSV.
FACET_CSV_COLUMNS = ("Facet id", "X", "Y", "Z")

_NAME_RE = re.compile(r"^\s*0*([1-9][0-9]*)\s*([EeWw])\s*0*([1-9][0-9]*)\s*$")


# --------------------------------------------------------------------------- names


def parse_heliostat_name(name: str) -> tuple[int, str, int]:
    """Split an NSTTF heliostat name into (row, side, column).

    Parameters
    ----------
    name : str
        ``<row><E|W><column>``, e.g. ``"8E3"`` (row 8, 3rd East of the
        North-South centre line). Case-insensitive; leading zeros allowed
        (``"5W01"``).

    Returns
    -------
    row : int
        Row number (>= 1).
    side : {"E", "W"}
        Side of the centre line.
    column : int
        Ordinal counted from the centre line (>= 1).

    Raises
    ------
    PihimInputError
        If ``name`` does not have that form.
    """
    m = _NAME_RE.match(name) if isinstance(name, str) else None
    if m is None:
        raise PihimInputError(f"{name!r} is not a heliostat name <row><E|W><column> (e.g. 8E3)")
    return int(m.group(1)), m.group(2).upper(), int(m.group(3))


def canonical_name(name: str) -> str:
    """The canonical spelling of a heliostat name (``"5w01"`` -> ``"5W1"``)."""
    row, side, col = parse_heliostat_name(name)
    return f"{row}{side}{col}"


# --------------------------------------------------------------------------- facets


def grid_facet_centroids(
    rows: int, cols: int, facet_width_m: float, facet_height_m: float, gap_m: float = 0.05
) -> NDArray[np.float64]:
    """Facet centroids of a regular ``rows`` x ``cols`` grid, heliostat frame.

    Facets are numbered row by row from the top left as seen from the front
    (row 1 at ``+y``, column 1 at ``-x``); all centroids lie in the mirror
    plane ``z = 0``; the grid is centred on the mirror centre.

    Parameters
    ----------
    rows, cols : int
        Facet rows and columns.
    facet_width_m, facet_height_m : float
        Facet size, metres.
    gap_m : float
        Gap between neighbouring facets, metres.

    Returns
    -------
    ndarray, shape (rows * cols, 3)

    Raises
    ------
    PihimInputError
        Rows or columns that are not positive integers, a facet size that is
        not positive, a negative gap (overlapping facets).
    """
    for name, n in (("rows", rows), ("cols", cols)):
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise PihimInputError(f"{name} must be a positive integer, got {n!r}")
    for name, v, strict in (("facet_width_m", facet_width_m, True), ("facet_height_m", facet_height_m, True),
                            ("gap_m", gap_m, False)):
        if not (math.isfinite(v) and (v > 0 if strict else v >= 0)):
            raise PihimInputError(f"{name} must be a finite number {'>' if strict else '>='} 0 m, got {v!r}")
    xs = (np.arange(cols) - (cols - 1) / 2.0) * (facet_width_m + gap_m)
    ys = ((rows - 1) / 2.0 - np.arange(rows)) * (facet_height_m + gap_m)
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel(), np.zeros(rows * cols)], axis=-1)


def nsttf_facet_centroids() -> NDArray[np.float64]:
    """The 25 NSTTF facet centroids (heliostat frame, metres), from the NSTTF pitches.

    The NSTTF facets (4 ft square) sit on a grid that is not uniform; in
    inches, measured from the mirror centre:

    * columns at x = 0, +/-50.004 (inner pitch 50.004 in), +/-110.004
      (outer pitch 60 in);
    * rows at y = 0, +/-51 (inner pitch 51 in), +/-101.004 (outer pitch
      50.004 in);
    * the four off-centre rows are set back by 0.456 in (z = -0.456 in); the
      centre row is in the mirror plane.

    These pitches reproduce OpenCSP's ``NSTTF_Facet_Centroids.csv`` [1]_ to
    the micrometre (a test compares them where the file is available).
    Facet 1 is top left (x < 0, y > 0) seen from the front; 13 the centre.

    Returns
    -------
    ndarray, shape (25, 3)
    """
    col_pitch_in = (50.004, 60.0)  # centre -> inner column, inner -> outer column
    row_pitch_in = (51.0, 50.004)  # centre -> inner row, inner -> outer row
    setback_in = 0.456
    half_x = np.cumsum((0.0, *col_pitch_in))  # 0, 50.004, 110.004
    half_y = np.cumsum((0.0, *row_pitch_in))  # 0, 51, 101.004
    xs = np.concatenate([-half_x[:0:-1], half_x]) * INCH_M  # left to right
    ys = np.concatenate([half_y[:0:-1], -half_y]) * INCH_M  # top to bottom
    zs = np.where(np.abs(ys) > 0.0, -setback_in * INCH_M, 0.0)
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    zz = np.broadcast_to(zs[:, None], yy.shape)
    return np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=-1)


# --------------------------------------------------------------------------- spec


def _readonly(a: ArrayLike) -> NDArray[np.float64]:
    out = np.array(a, dtype=float, copy=True)
    out.setflags(write=False)
    return out


@dataclass(frozen=True, eq=False)
class HeliostatSpec:
    """Geometry shared by all heliostats of a field.

    Attributes
    ----------
    rows, cols : int
        Facet rows and columns.
    facet_width_m, facet_height_m : float
        Facet size along the heliostat x and y axes, metres.
    pivot_height_m : float
        Height of the torque-tube pivot above the ground, metres.
    pivot_offset_m : float
        Distance from the pivot to the mirror plane along the mirror normal,
        metres (the mirror is in front of the pivot).
    facet_centroids : ndarray, shape (rows * cols, 3)
        Facet centroids in the heliostat frame (origin at the mirror centre,
        x right, y up, z out of the face), metres, ordered by facet number
        (1 = top left seen from the front, row by row). Read-only.
    """

    rows: int
    cols: int
    facet_width_m: float
    facet_height_m: float
    pivot_height_m: float
    pivot_offset_m: float
    facet_centroids: NDArray[np.float64]

    def __post_init__(self) -> None:
        for label in ("rows", "cols"):
            v = getattr(self, label)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise PihimInputError(f"HeliostatSpec.{label} must be a positive integer, got {v!r}")
            object.__setattr__(self, label, int(v))
        for label in ("facet_width_m", "facet_height_m", "pivot_height_m", "pivot_offset_m"):
            v = getattr(self, label)
            try:
                fv = float(v)
            except (TypeError, ValueError):
                fv = math.nan
            if isinstance(v, bool) or not math.isfinite(fv):
                raise PihimInputError(f"HeliostatSpec.{label} must be a finite number of metres, got {v!r}")
            if label.startswith("facet") and fv <= 0:
                raise PihimInputError(f"HeliostatSpec.{label} must be positive, got {fv:g}")
            object.__setattr__(self, label, fv)
        c = np.asarray(self.facet_centroids, dtype=float)
        if c.shape != (self.rows * self.cols, 3) or not np.all(np.isfinite(c)):
            raise PihimInputError(
                f"HeliostatSpec.facet_centroids must be finite with shape ({self.rows * self.cols}, 3), got {c.shape}"
            )
        close = _closest_pair(c[:, :2], 0.5 * min(self.facet_width_m, self.facet_height_m))
        if close is not None:
            i, j, d = close
            raise PihimInputError(f"HeliostatSpec.facet_centroids: facets {i + 1} and {j + 1} are {d:.3f} m apart, "
                                  f"less than half a facet: they overlap")
        object.__setattr__(self, "facet_centroids", _readonly(c))

    @property
    def n_facets(self) -> int:
        """Number of facets, ``rows * cols``."""
        return self.rows * self.cols

    @property
    def mirror_half_width_m(self) -> float:
        """Half the extent of the facets along the heliostat x axis, metres."""
        return float(np.max(np.abs(self.facet_centroids[:, 0])) + self.facet_width_m / 2.0)

    @property
    def mirror_half_height_m(self) -> float:
        """Half the extent of the facets along the heliostat y axis, metres."""
        return float(np.max(np.abs(self.facet_centroids[:, 1])) + self.facet_height_m / 2.0)

    @property
    def mirror_width_m(self) -> float:
        """Overall mirror width (facet extent along x), metres; 6.807 m for the NSTTF."""
        return 2.0 * self.mirror_half_width_m

    @property
    def mirror_height_m(self) -> float:
        """Overall mirror height (facet extent along y), metres; 6.350 m for the NSTTF."""
        return 2.0 * self.mirror_half_height_m

    @property
    def mirror_area_m2(self) -> float:
        """Reflective area (sum of facet areas), square metres."""
        return self.n_facets * self.facet_width_m * self.facet_height_m

    def _key(self) -> tuple[Any, ...]:
        return (self.rows, self.cols, self.facet_width_m, self.facet_height_m, self.pivot_height_m,
                self.pivot_offset_m, self.facet_centroids.tobytes())

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, HeliostatSpec):
            return NotImplemented
        return self._key() == other._key()

    __hash__ = None  # type: ignore[assignment]


def nsttf_spec() -> HeliostatSpec:
    """The NSTTF heliostat: 5 x 5 facets of 1.2192 m, pivot 4.02 m high, 0.1778 m behind the mirror [1]_."""
    return HeliostatSpec(
        rows=5,
        cols=5,
        facet_width_m=NSTTF_FACET_SIZE_M,
        facet_height_m=NSTTF_FACET_SIZE_M,
        pivot_height_m=NSTTF_PIVOT_HEIGHT_M,
        pivot_offset_m=NSTTF_PIVOT_OFFSET_M,
        facet_centroids=nsttf_facet_centroids(),
    )


# --------------------------------------------------------------------------- tower


@dataclass(frozen=True)
class Tower:
    """A receiver tower: a vertical box on the ground and its target (aim point).

    Defaults are the NSTTF tower [1]_.

    Attributes
    ----------
    height_m : float
        Height of the top of the tower above the field origin, metres.
    x_min_m, x_max_m, y_min_m, y_max_m : float
        Rectangular footprint in the field frame, metres.
    target : tuple of 3 float
        Default aim point (receiver target), field frame, metres.
    """

    height_m: float = 63.5508
    x_min_m: float = -5.485
    x_max_m: float = 5.485
    y_min_m: float = -9.1186
    y_max_m: float = 6.25
    target: tuple[float, float, float] = NSTTF_TOWER_TARGET

    def __post_init__(self) -> None:
        vals = (self.height_m, self.x_min_m, self.x_max_m, self.y_min_m, self.y_max_m)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in vals):
            raise PihimInputError(f"Tower dimensions must be finite numbers of metres, got {vals}")
        if self.height_m <= 0 or self.x_max_m <= self.x_min_m or self.y_max_m <= self.y_min_m:
            raise PihimInputError("Tower needs height > 0 and a footprint with x_max > x_min and y_max > y_min")
        t = tuple(float(v) for v in self.target)
        if len(t) != 3 or not all(math.isfinite(v) for v in t):
            raise PihimInputError(f"Tower.target must be three finite coordinates, got {self.target!r}")
        object.__setattr__(self, "target", t)

    @property
    def footprint_radius_m(self) -> float:
        """Distance from the origin to the farthest footprint corner, metres."""
        return float(max(math.hypot(x, y) for x in (self.x_min_m, self.x_max_m) for y in (self.y_min_m, self.y_max_m)))

    def box_corners(self) -> NDArray[np.float64]:
        """The 8 corners of the tower box, shape (8, 3): bottom 4 (z = 0) then top 4, counter-clockwise from above."""
        xy = [(self.x_min_m, self.y_min_m), (self.x_max_m, self.y_min_m),
              (self.x_max_m, self.y_max_m), (self.x_min_m, self.y_max_m)]
        return np.array([(x, y, 0.0) for x, y in xy] + [(x, y, self.height_m) for x, y in xy])

    def box_edges(self) -> NDArray[np.float64]:
        """The 12 edges of the tower box as segments, shape (12, 2, 3)."""
        c = self.box_corners()
        pairs = [(i, (i + 1) % 4) for i in range(4)] + [(4 + i, 4 + (i + 1) % 4) for i in range(4)]
        pairs += [(i, i + 4) for i in range(4)]
        return np.stack([np.stack([c[a], c[b]]) for a, b in pairs])


#: The NSTTF tower (OpenCSP figures).
NSTTF_TOWER = Tower()


# --------------------------------------------------------------------------- field


@dataclass(frozen=True)
class Heliostat:
    """Identity of one heliostat of a field.

    Attributes
    ----------
    name : str
        Canonical NSTTF-style name (``"8E3"``).
    row : int
        Row number.
    side : {"E", "W"}
        Side of the North-South centre line.
    column : int
        Ordinal from the centre line.
    pivot : tuple of 3 float
        Torque-tube pivot, field frame ENU, metres.
    """

    name: str
    row: int
    side: str
    column: int
    pivot: tuple[float, float, float]


#: Two pivots closer than this (metres) are one heliostat given twice (a duplicated row): a field refuses them.
MIN_PIVOT_SPACING_M = 0.5


def _closest_pair(xy: NDArray[np.float64], tol: float) -> tuple[int, int, float] | None:
    """A pair of points (rows of ``xy``, any dimension) closer than ``tol`` (their indices, distance), or None;
    sorted by the first coordinate, each point compared with the next ones while they are within ``tol`` in it."""
    order = np.argsort(xy[:, 0], kind="stable")
    s = xy[order]
    for k in range(1, len(s)):
        dx = s[k:, 0] - s[:-k, 0]
        near = dx < tol
        if not near.any():
            break
        d = np.sqrt(dx**2 + np.sum((s[k:, 1:] - s[:-k, 1:]) ** 2, axis=1))
        hit = np.flatnonzero(near & (d < tol))
        if hit.size:
            a, b = sorted((int(order[hit[0]]), int(order[hit[0] + k])))
            return a, b, float(d[hit[0]])
    return None


@dataclass(frozen=True, eq=False)
class Field:
    """Heliostats of one spec, their pivots and (optionally) the tower.

    Attributes
    ----------
    names : tuple of str
        Canonical heliostat names, unique, in array order.
    pivots : ndarray, shape (N, 3)
        Torque-tube pivots, field frame ENU (origin at the tower base),
        metres. Read-only.
    spec : HeliostatSpec
        Geometry shared by all heliostats.
    tower : Tower or None
        The receiver tower, if known.
    rows, columns : ndarray of int, shape (N,)
        Parsed from the names. Read-only.
    sides : ndarray of str, shape (N,)
        ``"E"`` or ``"W"``. Read-only.

    Notes
    -----
    Site-agnostic: combine with :mod:`pihim.sky.sun` (sun direction) and
    :mod:`pihim.field.geodesy` (WGS84) where needed.
    """

    names: tuple[str, ...]
    pivots: NDArray[np.float64]
    spec: HeliostatSpec
    tower: Tower | None = None
    rows: NDArray[np.int64] = field(init=False, repr=False)
    sides: NDArray[np.str_] = field(init=False, repr=False)
    columns: NDArray[np.int64] = field(init=False, repr=False)
    _index: dict[str, int] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if isinstance(self.names, str) or not isinstance(self.names, Sequence):
            raise PihimInputError("Field.names must be a sequence of heliostat names")
        parsed = [parse_heliostat_name(n) for n in self.names]
        names = tuple(f"{r}{s}{c}" for r, s, c in parsed)
        index: dict[str, int] = {}
        for i, n in enumerate(names):
            if n in index:
                raise PihimInputError(f"duplicate heliostat name {n!r} in Field (positions {index[n]} and {i})")
            index[n] = i
        p = np.asarray(self.pivots, dtype=float)
        if p.ndim != 2 or p.shape != (len(names), 3) or not np.all(np.isfinite(p)):
            raise PihimInputError(f"Field.pivots must be finite with shape ({len(names)}, 3), got {p.shape}")
        if not isinstance(self.spec, HeliostatSpec):
            raise PihimInputError(f"Field.spec must be a HeliostatSpec, got {type(self.spec).__name__}")
        close = _closest_pair(p, MIN_PIVOT_SPACING_M)
        if close is not None:
            i, j, d = close
            raise PihimInputError(f"heliostats {names[i]} and {names[j]} have pivots {d:.2f} m apart, less than "
                                  f"{MIN_PIVOT_SPACING_M:g} m: one heliostat given twice?")
        if self.tower is not None and not isinstance(self.tower, Tower):
            raise PihimInputError(f"Field.tower must be a Tower or None, got {type(self.tower).__name__}")
        rows = np.array([r for r, _, _ in parsed], dtype=np.int64)
        cols = np.array([c for _, _, c in parsed], dtype=np.int64)
        sides = np.array([s for _, s, _ in parsed], dtype="<U1")
        for a in (rows, cols, sides):
            a.setflags(write=False)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "pivots", _readonly(p))
        object.__setattr__(self, "rows", rows)
        object.__setattr__(self, "columns", cols)
        object.__setattr__(self, "sides", sides)
        object.__setattr__(self, "_index", index)

    def __len__(self) -> int:
        return len(self.names)

    def __iter__(self) -> Iterator[Heliostat]:
        for i in range(len(self)):
            yield self._heliostat_at(i)

    def __contains__(self, name: object) -> bool:
        try:
            return isinstance(name, str) and canonical_name(name) in self._index
        except PihimInputError:
            return False

    def __repr__(self) -> str:
        tower = "no tower" if self.tower is None else f"tower {self.tower.height_m:g} m"
        rows = f"rows {int(self.rows.min())}-{int(self.rows.max())}" if len(self) else "empty"
        return f"Field({len(self)} heliostats, {rows}, {self.spec.rows}x{self.spec.cols} facets, {tower})"

    @property
    def name_index(self) -> Mapping[str, int]:
        """Array index of each heliostat by its name as in :attr:`names` (``names[i]`` -> ``i``), read-only.

        Exact names only (:meth:`index` parses other spellings); the mapping
        is the field's own, so looking names up costs no copy.
        """
        return MappingProxyType(self._index)

    def index(self, name: str) -> int:
        """Array index of heliostat ``name`` (any accepted spelling, e.g. ``"8e03"``).

        Raises
        ------
        PihimInputError
            If ``name`` is not a heliostat name or not in this field.
        """
        key = canonical_name(name)
        try:
            return self._index[key]
        except KeyError:
            span = f"rows {int(self.rows.min())}-{int(self.rows.max())}" if len(self) else "no rows"
            raise PihimInputError(
                f"unknown heliostat {name!r}: not among the {len(self)} heliostats of this field ({span})"
            ) from None

    def indices(self, names: Iterable[str]) -> NDArray[np.int64]:
        """Array indices of several heliostats (see :meth:`index`); one name alone is one heliostat.

        (A string is itself iterable: ``"5E1"`` was read as the names
        ``"5"``, ``"E"`` and ``"1"``.)
        """
        if isinstance(names, str):
            names = [names]
        return np.array([self.index(n) for n in names], dtype=np.int64)

    def _heliostat_at(self, i: int) -> Heliostat:
        p = self.pivots[i]
        return Heliostat(self.names[i], int(self.rows[i]), str(self.sides[i]), int(self.columns[i]),
                         (float(p[0]), float(p[1]), float(p[2])))

    def heliostat(self, name: str) -> Heliostat:
        """The :class:`Heliostat` record of ``name``."""
        return self._heliostat_at(self.index(name))

    def pivot(self, name: str) -> NDArray[np.float64]:
        """Pivot of ``name``, shape (3,), metres."""
        return self.pivots[self.index(name)]

    def subset(self, names: Iterable[str]) -> Field:
        """A field with only ``names`` (in that order), same spec and tower."""
        idx = self.indices(names)
        return Field(tuple(self.names[i] for i in idx), self.pivots[idx], self.spec, self.tower)

    @property
    def ground_z(self) -> NDArray[np.float64]:
        """Ground height under each pivot, ``pivot z - pivot_height_m``, metres, shape (N,)."""
        return self.pivots[:, 2] - self.spec.pivot_height_m

    @property
    def default_aim_point(self) -> NDArray[np.float64]:
        """The tower target, shape (3,), metres.

        Raises
        ------
        PihimInputError
            If the field has no tower.
        """
        if self.tower is None:
            raise PihimInputError("this field has no tower: pass an aim point explicitly (or build it with a Tower)")
        return np.array(self.tower.target)


# --------------------------------------------------------------------------- CSV


#: Largest facet count of one heliostat a field file may declare (real heliostats have 1 to ~100).
MAX_FACETS_PER_HELIOSTAT = 10_000


def _open_rows(path: Path, kind: str) -> Iterator[tuple[int, list[str]]]:
    """(line number, cells) for every non-blank row; BOM tolerated."""
    from pihim._inputs import MAX_TEXT_BYTES

    try:
        st = path.stat()
        if not stat.S_ISREG(st.st_mode):
            raise PihimInputError(f"{path}: cannot read {kind}: not a regular file")
        if st.st_size > MAX_TEXT_BYTES:
            raise PihimInputError(f"{path}: cannot read {kind}: {st.st_size} bytes is more than {MAX_TEXT_BYTES}")
        text = path.read_bytes().decode("utf-8-sig")
    except OSError as e:
        raise PihimInputError(f"{path}: cannot read {kind}: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        line = path.read_bytes()[: e.start].count(b"\n") + 1
        raise PihimInputError(f"{path}:{line}: {kind} is not UTF-8 text ({e.reason})") from None
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        for cells in reader:
            if not cells or all(not c.strip() for c in cells):
                continue
            yield reader.line_num, [c.strip() for c in cells]
    except csv.Error as e:
        raise PihimInputError(f"{path}:{reader.line_num}: unreadable {kind} row ({e})") from None


def _check_header(path: Path, lineno: int, cells: list[str], expected: Sequence[str], kind: str) -> None:
    if [c.casefold() for c in cells] != [c.casefold() for c in expected]:
        raise PihimInputError(
            f"{path}:{lineno}: {kind} header must be {','.join(expected)}; got {','.join(cells)}"
        )


#: Largest magnitude of a length in a field CSV, metres (100 km): far beyond any heliostat field, so that a
#: mistyped exponent is refused on its line instead of overflowing the geometry later.
_MAX_CSV_LENGTH_M = 1e5


def _number(path: Path, lineno: int, column: str, text: str) -> float:
    """A length column's value, metres: finite and within +-100 km."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise PihimInputError(f"{path}:{lineno}: column {column!r} must be a finite number, got {text!r}")
    if abs(v) > _MAX_CSV_LENGTH_M:
        raise PihimInputError(f"{path}:{lineno}: column {column!r} must be within +-{_MAX_CSV_LENGTH_M:g} m, "
                              f"got {text!r}")
    return v


def _integer(path: Path, lineno: int, column: str, text: str, minimum: int = 1) -> int:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v) or v != int(v) or v < minimum:
        raise PihimInputError(f"{path}:{lineno}: column {column!r} must be an integer >= {minimum}, got {text!r}")
    return int(v)


def _read_heliostat_csv(path: Path) -> tuple[tuple[str, ...], NDArray[np.float64], dict[str, Any], int]:
    """Names, pivots, spec numbers and the line of the first data row."""
    rows = _open_rows(path, "heliostat CSV")
    first = next(rows, None)
    if first is None:
        raise PihimInputError(f"{path}: empty heliostat CSV (expected the header {','.join(HELIOSTAT_CSV_COLUMNS)})")
    _check_header(path, first[0], first[1], HELIOSTAT_CSV_COLUMNS, "heliostat CSV")
    ncol = len(HELIOSTAT_CSV_COLUMNS)
    names: list[str] = []
    pivots: list[tuple[float, float, float]] = []
    seen: dict[str, int] = {}
    spec: dict[str, Any] | None = None
    spec_line = 0
    for lineno, cells in rows:
        if len(cells) != ncol:
            raise PihimInputError(f"{path}:{lineno}: expected {ncol} columns, got {len(cells)}")
        try:
            r, s, c = parse_heliostat_name(cells[0])
        except PihimInputError:
            raise PihimInputError(
                f"{path}:{lineno}: heliostat name {cells[0]!r} is not <row><E|W><column> (e.g. 8E3)"
            ) from None
        name = f"{r}{s}{c}"
        if name in seen:
            raise PihimInputError(f"{path}:{lineno}: duplicate heliostat name {name!r} (first on line {seen[name]})")
        xyz = tuple(_number(path, lineno, col, cells[k]) for k, col in ((1, "X"), (2, "Y"), (3, "Z")))
        n_facets = _integer(path, lineno, "Num. Facets", cells[4])
        n_rows = _integer(path, lineno, "Num. Rows", cells[5])
        n_cols = _integer(path, lineno, "Num. Cols", cells[6])
        if n_facets != n_rows * n_cols:
            raise PihimInputError(
                f"{path}:{lineno}: Num. Facets = {n_facets} but Num. Rows x Num. Cols = {n_rows} x {n_cols}"
            )
        if n_facets > MAX_FACETS_PER_HELIOSTAT:
            raise PihimInputError(
                f"{path}:{lineno}: Num. Facets = {n_facets} ({n_rows} x {n_cols}) is more than pihim handles, "
                f"at most {MAX_FACETS_PER_HELIOSTAT} facets per heliostat (the facet table alone would take "
                f"{n_facets * 24 / 1e9:.3g} GB)"
            )
        dims = {label: _number(path, lineno, label, cells[k])
                for k, label in ((7, "Pivot Height"), (8, "Pivot Offset"), (9, "Facet Width"), (10, "Facet Height"))}
        for label in ("Facet Width", "Facet Height"):
            if dims[label] <= 0:
                given = cells[HELIOSTAT_CSV_COLUMNS.index(label)]
                raise PihimInputError(f"{path}:{lineno}: column {label!r} must be positive, got {given!r}")
        this = {"Num. Facets": n_facets, "Num. Rows": n_rows, "Num. Cols": n_cols, **dims}
        if spec is None:
            spec, spec_line = this, lineno
        else:
            for label, v in this.items():
                if v != spec[label]:
                    raise PihimInputError(
                        f"{path}:{lineno}: {label} = {v:g} differs from {spec[label]:g} on line {spec_line}"
                        " (a field has one heliostat spec)"
                    )
        seen[name] = lineno
        names.append(name)
        pivots.append(xyz)  # type: ignore[arg-type]
    if spec is None:
        raise PihimInputError(f"{path}: no heliostat rows after the header")
    return tuple(names), np.array(pivots, dtype=float), spec, spec_line


def load_facet_centroids(path: str | Path) -> NDArray[np.float64]:
    """Read an OpenCSP facet-centroid CSV (``Facet id, X, Y, Z``, heliostat frame, metres).

    Parameters
    ----------
    path : str or path-like
        The CSV file. A UTF-8 byte-order mark is tolerated; rows may come in
        any order but the ids must be exactly 1..F.

    Returns
    -------
    ndarray, shape (F, 3)
        Centroids ordered by facet id.

    Raises
    ------
    PihimInputError
        ``<file>:<line>: ...`` for a bad header, column count, non-numeric or
        duplicate id; ``<file>: ...`` for missing ids or no rows.
    """
    path = Path(path)
    rows = _open_rows(path, "facet CSV")
    first = next(rows, None)
    if first is None:
        raise PihimInputError(f"{path}: empty facet CSV (expected the header {','.join(FACET_CSV_COLUMNS)})")
    _check_header(path, first[0], first[1], FACET_CSV_COLUMNS, "facet CSV")
    by_id: dict[int, tuple[int, tuple[float, float, float]]] = {}
    for lineno, cells in rows:
        if len(cells) != len(FACET_CSV_COLUMNS):
            raise PihimInputError(f"{path}:{lineno}: expected {len(FACET_CSV_COLUMNS)} columns, got {len(cells)}")
        fid = _integer(path, lineno, "Facet id", cells[0])
        xyz = tuple(_number(path, lineno, col, cells[k]) for k, col in ((1, "X"), (2, "Y"), (3, "Z")))
        if fid in by_id:
            raise PihimInputError(f"{path}:{lineno}: duplicate facet id {fid} (first on line {by_id[fid][0]})")
        by_id[fid] = (lineno, xyz)  # type: ignore[assignment]
    if not by_id:
        raise PihimInputError(f"{path}: no facet rows after the header")
    missing = sorted(set(range(1, len(by_id) + 1)) - set(by_id))
    if missing:
        raise PihimInputError(f"{path}: facet ids must be 1..{len(by_id)}; missing {missing[:5]}")
    return np.array([by_id[i][1] for i in range(1, len(by_id) + 1)], dtype=float)


def load_field(
    heliostat_csv: str | Path,
    facet_csv: str | Path | None = None,
    *,
    tower: Tower | None = None,
) -> Field:
    """Load a field from OpenCSP CSV files.

    Parameters
    ----------
    heliostat_csv : str or path-like
        OpenCSP heliostat CSV [1]_: ``Name, X, Y, Z`` (torque-tube pivot,
        field frame ENU, metres, origin at the tower base), ``Num. Facets,
        Num. Rows, Num. Cols, Pivot Height, Pivot Offset, Facet Width, Facet
        Height`` (metres). All rows must share the same facet grid and
        dimensions (a :class:`Field` has one :class:`HeliostatSpec`).
    facet_csv : str or path-like, optional
        OpenCSP facet-centroid CSV (heliostat frame). Without it, the NSTTF
        centroids (:func:`nsttf_facet_centroids`) are used for a 5 x 5 grid of
        1.2192 m facets, otherwise a regular grid with 5 cm gaps
        (:func:`grid_facet_centroids`).
    tower : Tower, optional
        Receiver tower of the field (e.g. :data:`NSTTF_TOWER`); the CSV
        does not describe it.

    Returns
    -------
    Field

    Raises
    ------
    PihimInputError
        One-line ``<file>:<line>: ...`` messages for wrong column counts,
        non-numeric values, bad or duplicate names, facet counts that do not
        match rows x columns, rows whose spec differs from the first, and a
        facet file whose facet count differs from ``Num. Facets``.

    Examples
    --------
    >>> field = load_field("heliostats.csv", "facet_centroids.csv", tower=NSTTF_TOWER)  # doctest: +SKIP
    >>> field.heliostat("8E3").row  # doctest: +SKIP
    8
    """
    hpath = Path(heliostat_csv)
    names, pivots, s, _ = _read_heliostat_csv(hpath)
    rows, cols = s["Num. Rows"], s["Num. Cols"]
    w, h = s["Facet Width"], s["Facet Height"]
    if facet_csv is not None:
        fpath = Path(facet_csv)
        centroids = load_facet_centroids(fpath)
        if len(centroids) != s["Num. Facets"]:
            raise PihimInputError(
                f"{fpath}: {len(centroids)} facets but {hpath.name} says Num. Facets = {s['Num. Facets']}"
            )
    elif rows == 5 and cols == 5 and w == NSTTF_FACET_SIZE_M and h == NSTTF_FACET_SIZE_M:
        centroids = nsttf_facet_centroids()
    else:
        centroids = grid_facet_centroids(rows, cols, w, h)
    try:
        spec = HeliostatSpec(rows=rows, cols=cols, facet_width_m=w, facet_height_m=h,
                             pivot_height_m=s["Pivot Height"], pivot_offset_m=s["Pivot Offset"],
                             facet_centroids=centroids)
    except PihimInputError as exc:
        raise PihimInputError(f"{facet_csv if facet_csv is not None else hpath}: {exc}") from None
    try:
        return Field(names, pivots, spec, tower)
    except PihimInputError as exc:
        raise PihimInputError(f"{hpath}: {exc}") from None


# --------------------------------------------------------------------------- NSTTF-like field

#: Heliostats per side of the centre line in NSTTF rows 5..14 (218 in all).
NSTTF_ROW_COUNTS_PER_SIDE = {5: 10, 6: 9, 7: 9, 8: 10, 9: 11, 10: 12, 11: 14, 12: 14, 13: 14, 14: 6}
_NSTTF_FIRST_ROW_Y_FT = 190.0
_NSTTF_MIN_ROW_PITCH_FT = 40.0
_NSTTF_ROW_PITCH_FT = (9.5, 0.105)  # pitch = 9.5 ft + 0.105 * y, at least 40 ft
_NSTTF_COLUMN_PITCH_FT = 32.0
#: Ground plane fitted to the NSTTF pivots (minus the pivot height): z = a + b x + c y, metres.
_NSTTF_GROUND_PLANE = (-0.28, 0.0219, 0.0050)


def nsttf_row_y_m() -> dict[int, float]:
    """North coordinate of NSTTF-like rows 5..14, metres, from the row-pitch rule.

    Row 5 is 190 ft north of the tower; the pitch to the next row is
    ``max(40 ft, 9.5 ft + 0.105 y)``: 40 ft up to row 8, then growing with
    the distance to the tower (fewer blocked reflections farther out). The
    rule reproduces the surveyed NSTTF rows to about 0.4 m.
    """
    y = _NSTTF_FIRST_ROW_Y_FT
    out = {}
    for row in sorted(NSTTF_ROW_COUNTS_PER_SIDE):
        out[row] = y * _FOOT_M
        a, b = _NSTTF_ROW_PITCH_FT
        y += max(_NSTTF_MIN_ROW_PITCH_FT, a + b * y)
    return out


def nsttf_like_field(*, spec: HeliostatSpec | None = None, tower: Tower | None = NSTTF_TOWER) -> Field:
    """An NSTTF-like rectangular field generated from spacing rules (no data file).

    Rows 5-14 north of the tower with 10, 9, 9, 10, 11, 12, 14, 14, 14 and 6
    heliostats on each side of the North-South centre line (218 in all, as
    the NSTTF [1]_). Rules, derived from the published NSTTF layout:

    * columns: ``x = +/-(column - 1/2) * 32 ft`` (9.754 m pitch), rows not
      staggered;
    * rows: see :func:`nsttf_row_y_m` (57.9 m to about 195 m North);
    * ground: the plane ``z = -0.28 + 0.0219 x + 0.0050 y`` m (the site
      rises to the East), pivots ``pivot_height_m`` above it.

    Every heliostat lies within 0.32 m (horizontally) and 0.61 m (vertically,
    0.15 m rms) of its surveyed NSTTF position; use :func:`load_field` for the
    survey itself.

    Parameters
    ----------
    spec : HeliostatSpec, optional
        Defaults to :func:`nsttf_spec`.
    tower : Tower or None
        Defaults to the NSTTF tower.

    Returns
    -------
    Field
        Names ``<row><E|W><column>``, ordered row by row from the East end to
        the West end (as in the OpenCSP file).
    """
    spec = nsttf_spec() if spec is None else spec
    names: list[str] = []
    xy: list[tuple[float, float]] = []
    ys = nsttf_row_y_m()
    for row, per_side in NSTTF_ROW_COUNTS_PER_SIDE.items():
        for side, cols in (("E", range(per_side, 0, -1)), ("W", range(1, per_side + 1))):
            sign = 1.0 if side == "E" else -1.0
            for c in cols:
                names.append(f"{row}{side}{c}")
                xy.append((sign * (c - 0.5) * _NSTTF_COLUMN_PITCH_FT * _FOOT_M, ys[row]))
    p = np.array(xy)
    a, b, c = _NSTTF_GROUND_PLANE
    z = a + b * p[:, 0] + c * p[:, 1] + spec.pivot_height_m
    return Field(tuple(names), np.column_stack([p, z]), spec, tower)


# --------------------------------------------------------------------------- radial stagger


def radial_staggered_field(
    n_heliostats: int,
    *,
    spec: HeliostatSpec | None = None,
    tower: Tower | None = None,
    first_radius_m: float | None = None,
    clearance_m: float = 0.5,
    blocking_factor: float = 1.0,
    azimuth_span_deg: float = 360.0,
    ground_z_m: float = 0.0,
) -> Field:
    """A radial-staggered field of exactly ``n_heliostats`` heliostats around a tower.

    Layout in the manner of Collado and Guallar's *campo* code [3]_:

    * Each heliostat needs a circle of diameter ``DM = sqrt(W^2 + H^2) +
      clearance_m`` (W, H the overall mirror width and height) so that
      neighbours never collide whatever their orientation.
    * Heliostats stand on concentric rings, grouped in **zones**. Within a
      zone every ring has the same angular step ``d_alpha``, so the
      azimuthal spacing ``R d_alpha`` grows with the radius; consecutive rings
      are staggered by ``d_alpha / 2``. In the first ring of a zone the chord
      between neighbours is at least ``DM``.
    * A new zone starts when the chord at the next ring would reach
      ``2 DM``: the angular step is halved (the ring count doubles) and the
      radial gap to the new zone is a full ``DM`` (rings of different zones
      are not staggered against each other).
    * Radial increment between rings: ``max(DM cos 30 deg,
      blocking_factor * H * R / (2 h))`` with ``h`` the height of the tower
      target above the pivots. The first term is the densest collision-free
      staggered packing (neighbours in adjacent rings exactly ``DM`` apart);
      the second keeps heliostats two rings apart (same azimuth) far enough
      that a mirror of height H does not block its rear neighbour's
      reflection toward the target, to first order (a simple geometric rule
      of ours, not campo's optimisation).

    Every pair of heliostats is at least ``DM`` apart (tested). No attempt is
    made at optimising annual efficiency: this is a realistic *shape* for
    scaling studies and benchmarks.

    Parameters
    ----------
    n_heliostats : int
        Number of heliostats (>= 1). The last ring is filled from North
        outwards, so partial rings stay nearly symmetric.
    spec : HeliostatSpec, optional
        Heliostat geometry; default :func:`nsttf_spec`.
    tower : Tower, optional
        Default :data:`NSTTF_TOWER`. Taller towers give denser far fields.
    first_radius_m : float, optional
        Radius of the first ring, metres. Default: the larger of 0.75 x the
        tower height and the tower footprint radius + ``DM``.
    clearance_m : float
        Safety distance added to the mirror diagonal, metres.
    blocking_factor : float
        Scale of the no-blocking radial increment (0 gives the densest
        packing everywhere).
    azimuth_span_deg : float
        Angular width of the field, centred on North, degrees (360: a
        surround field; e.g. 120: a North field from -60 to +60 deg).
    ground_z_m : float
        Flat ground height, metres; pivots are ``pivot_height_m`` above it.

    Returns
    -------
    Field
        Names ``<ring><E|W><k>``: the ring number is the "row", ``k`` counts
        from North along each side (East: azimuth 0..180 deg clockwise from
        North, a heliostat exactly on the centre line counts as East;
        West: 0..-180 deg).
    """
    if isinstance(n_heliostats, bool) or not isinstance(n_heliostats, (int, np.integer)) or n_heliostats < 1:
        raise PihimInputError(f"n_heliostats must be a positive integer, got {n_heliostats!r}")
    spec = nsttf_spec() if spec is None else spec
    tower = NSTTF_TOWER if tower is None else tower
    for label, v, lo in (("clearance_m", clearance_m, 0.0), ("blocking_factor", blocking_factor, 0.0)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= lo):
            raise PihimInputError(f"{label} must be a finite number >= {lo:g}, got {v!r}")
    if not (isinstance(azimuth_span_deg, (int, float)) and 0 < azimuth_span_deg <= 360):
        raise PihimInputError(f"azimuth_span_deg must be in (0, 360], got {azimuth_span_deg!r}")
    dm = math.hypot(spec.mirror_width_m, spec.mirror_height_m) + clearance_m
    pivot_z = ground_z_m + spec.pivot_height_m
    h_aim = tower.target[2] - pivot_z
    if h_aim <= 0:
        raise PihimInputError("the tower target must be above the heliostat pivots")
    r = first_radius_m if first_radius_m is not None else max(0.75 * tower.height_m, tower.footprint_radius_m + dm)
    if not (isinstance(r, (int, float)) and math.isfinite(r) and r > dm / 2):
        raise PihimInputError(f"first_radius_m must be a finite radius > DM/2 = {dm / 2:.3g} m, got {r!r}")
    full = azimuth_span_deg >= 360.0
    half_span = math.radians(azimuth_span_deg) / 2.0
    # angular step of the first zone: chord 2 R sin(step / 2) >= DM; an even count on a full circle
    step = 2.0 * math.asin(min(1.0, dm / (2.0 * r)))
    if full:
        m = max(2, math.floor(2.0 * math.pi / step) // 2 * 2)
        step = 2.0 * math.pi / m
    radial_min = dm * math.cos(math.radians(30.0))

    thetas: list[NDArray[np.float64]] = []
    radii: list[NDArray[np.float64]] = []
    ring_of: list[NDArray[np.int64]] = []
    total, ring, ring_in_zone = 0, 0, 0
    while total < n_heliostats:
        ring += 1
        delta = 0.5 if ring_in_zone % 2 == 0 else 0.0
        if full:
            k = np.arange(round(2.0 * math.pi / step))
            th = (k + delta) * step
            th = np.where(th > math.pi, th - 2.0 * math.pi, th)
        else:
            kmax = math.floor(half_span / step - delta) + 1
            k = np.arange(-kmax - 1, kmax + 1)
            th = (k + delta) * step
            th = th[np.abs(th) <= half_span + 1e-12]
        if total + th.size > n_heliostats:  # last ring: keep the heliostats nearest North
            th = th[np.argsort(np.abs(th), kind="stable")[: n_heliostats - total]]
        thetas.append(th)
        radii.append(np.full(th.size, r))
        ring_of.append(np.full(th.size, ring, dtype=np.int64))
        total += th.size
        # next ring
        dr = max(radial_min, blocking_factor * spec.mirror_height_m * r / (2.0 * h_aim))
        r_next = r + dr
        if 2.0 * r_next * math.sin(step / 4.0) >= dm:  # halving the step keeps the chord >= DM: new zone
            r_next = r + max(dm, dr)
            step /= 2.0
            ring_in_zone = 0
        else:
            ring_in_zone += 1
        r = r_next

    theta = np.concatenate(thetas)
    radius = np.concatenate(radii)
    ring_no = np.concatenate(ring_of)
    east = theta >= 0.0
    # column ordinal: along each side, by angular distance from North
    order = np.lexsort((np.abs(theta), ~east, ring_no))  # ring, East first, then from North
    theta, radius, ring_no, east = theta[order], radius[order], ring_no[order], east[order]
    key = ring_no * 2 + (~east)
    starts = np.r_[0, np.flatnonzero(np.diff(key)) + 1]
    counts = np.diff(np.r_[starts, key.size])
    col = np.arange(key.size) - np.repeat(starts, counts) + 1
    names = tuple(f"{rg}{'E' if e else 'W'}{c}" for rg, e, c in zip(ring_no.tolist(), east.tolist(), col.tolist()))
    pivots = np.column_stack([radius * np.sin(theta), radius * np.cos(theta), np.full(theta.size, pivot_z)])
    return Field(names, pivots, spec, tower)
