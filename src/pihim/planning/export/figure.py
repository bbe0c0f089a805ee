"""Map of a plan in the field frame (``plan.png``).

A top view in field East-North-Up metres: heliostat pivots as grey dots and
the tower footprint (when a :class:`~pihim.field.layout.Field` is given),
each flight as a dashed line (one colour per flight: take-off, transits
between passes, return), each scan pass on top as a line through its
waypoints ending in an arrow, coloured by its predicted usable fraction
(colour bar; infeasible passes dashed), capture waypoints as small open
circles, pass numbers in boxes placed next to the pass starts so that none
overlap (with a leader line), the home position, and a title with the time,
the counts and the coverage as ``pihim plan`` states it (heliostats of the
field imaged, with the target's reflection at DoLP > 0.2, with a usable
contrast edge). Drawn with
matplotlib's object-oriented API on an Agg canvas: no ``pyplot``, no global
state, safe in threads and servers [1]_.

Large plans stay legible: above :data:`MAX_LABELLED_PASSES` passes the pass
numbers, arrowheads and capture marks are left out (the title says so;
``plan.json`` and the KML hold every pass and image), and above
:data:`MAX_LEGEND_FLIGHTS` flights the legend gives the flights' count and
totals in one entry instead of one entry each (their colours repeat every
ten flights).

References
----------
.. [1] matplotlib, "Embedding Matplotlib in graphical user interfaces" and
   ``matplotlib.figure.Figure``, https://matplotlib.org/stable/api/figure_api.html.
"""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pihim.errors import PihimInputError
from pihim.planning.export._common import check_plan, plan_counts, write_export
from pihim.planning.model import Plan

__all__ = ["MAX_LABELLED_PASSES", "MAX_LEGEND_FLIGHTS", "plan_figure", "plan_png_bytes", "write_plan_figure"]

#: Most passes whose numbers, arrowheads and capture marks are drawn (a 1,000-heliostat radial field has about
#: 190 passes; the 1,400 of a 10,000-heliostat field would bury a 1200 x 960 pixel map under their labels).
MAX_LABELLED_PASSES = 200
#: Most flights listed one by one in the legend (``tab10`` has ten colours).
MAX_LEGEND_FLIGHTS = 10
#: The arrowhead at each pass end, points, drawn as matplotlib draws a ``-|>`` arrow of ``mutation_scale=14`` and
#: line width 1.5: head length 0.4 and half-width 0.2 of the scale; its tip held back 2 points (``shrinkB``) plus
#: half the line width over the sine of the head's half-angle (the stroke's mitred tip then ends 2 points short).
_ARROW_LINE_WIDTH_PT = 1.5
_ARROW_LENGTH_PT, _ARROW_HALF_WIDTH_PT = 5.6, 2.8
_ARROW_SHRINK_PT = 2.0 + 0.5 * _ARROW_LINE_WIDTH_PT / math.sin(math.atan2(_ARROW_HALF_WIDTH_PT, _ARROW_LENGTH_PT))


def _check_size(figsize: tuple[float, float], dpi: float) -> None:
    try:
        w, h = (float(v) for v in figsize)
        d = float(dpi)
    except (TypeError, ValueError):
        raise PihimInputError(
            f"figsize must be (width, height) in inches and dpi a number; got {figsize!r}, {dpi!r}"
        ) from None
    if not all(math.isfinite(v) and v > 0 for v in (w, h, d)) or w * d > 20000 or h * d > 20000:
        raise PihimInputError(
            f"figure size {figsize!r} at {dpi!r} dpi must be positive and at most 20000 pixels a side"
        )


def plan_figure(
    plan: Plan, *, field: Any = None, figsize: tuple[float, float] = (10.0, 8.0), dpi: float = 120.0
) -> Any:
    """Draw the plan map on a new :class:`matplotlib.figure.Figure` (Agg canvas).

    Parameters
    ----------
    plan : Plan
    field : Field, optional
        Heliostat pivots and tower footprint to draw under the passes.
    figsize : (float, float)
        Width and height, inches.
    dpi : float
        Resolution; the PNG is ``round(width * dpi)`` x ``round(height * dpi)``
        pixels.

    Returns
    -------
    matplotlib.figure.Figure
    """
    check_plan(plan)
    _check_size(figsize, dpi)
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.cm import ScalarMappable
    from matplotlib.collections import LineCollection
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    if field is not None:
        from pihim.field.layout import Field

        if not isinstance(field, Field):
            raise PihimInputError(f"field must be a pihim Field, got {type(field).__name__}")

    fig = Figure(figsize=tuple(float(v) for v in figsize), dpi=float(dpi))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    cmap = colormaps["viridis"]
    norm = Normalize(0.0, 1.0)

    if field is not None and len(field):
        piv = np.asarray(field.pivots)
        ax.scatter(piv[:, 0], piv[:, 1], s=6, c="0.6", marker="o", linewidths=0, label="heliostats", zorder=1)
    if field is not None and field.tower is not None:
        t = field.tower
        ax.add_patch(Rectangle((t.x_min_m, t.y_min_m), t.x_max_m - t.x_min_m, t.y_max_m - t.y_min_m,
                               facecolor="0.35", edgecolor="black", label="tower", zorder=2))

    flight_colours = colormaps["tab10"]
    drawn = [f for f in plan.flights if len(f.waypoints) >= 2]
    if len(plan.flights) <= MAX_LEGEND_FLIGHTS:
        for f in drawn:  # under the passes: the whole flight, so the transits between passes show
            fxy = np.array([(w.x_m, w.y_m) for w in f.waypoints])
            ax.plot(fxy[:, 0], fxy[:, 1], ls=(0, (4, 2)), lw=1.1, color=flight_colours(f.index % 10), zorder=2.5,
                    label=f"flight {f.index + 1}: {f.duration_s / 60:.1f} min, {f.distance_m / 1000:.2f} km")
    elif drawn:  # one artist for them all, one legend entry with the totals
        minutes = sum(f.duration_s for f in plan.flights) / 60
        km = sum(f.distance_m for f in plan.flights) / 1000
        ax.add_collection(LineCollection(
            [np.array([(w.x_m, w.y_m) for w in f.waypoints]) for f in drawn],
            colors=[flight_colours(f.index % 10) for f in drawn], linestyles=[(0, (4, 2))], linewidths=1.1,
            zorder=2.5, label=f"{len(plan.flights)} flights: {minutes:.0f} min, {km:.1f} km in all"), autolim=True)

    labelled = len(plan.passes) <= MAX_LABELLED_PASSES
    starts, ends = [], []
    segments, colours, styles, cap_xy, cap_colour = [], [], [], [], []
    # the colour map called once for every pass (34,000 scalar calls took 1.5-2.5 s at 100,000 heliostats)
    pass_colours = cmap(norm(np.array([p.usable_fraction for p in plan.passes], dtype=float)))
    for p, rgba in zip(plan.passes, pass_colours, strict=True):
        xy = np.array([(w.x_m, w.y_m) for w in p.waypoints])
        colour = tuple(rgba)
        segments.append(xy)
        colours.append(colour)
        styles.append("-" if p.feasible else "--")
        moved = np.flatnonzero(np.hypot(*(xy - xy[-1]).T) > 0)  # the last waypoint apart from the end
        if labelled and len(moved):
            ends.append((xy[moved[-1]], xy[-1], colour))
        cap = [(w.x_m, w.y_m) for w in p.waypoints if w.capture]
        cap_xy.extend(cap)
        cap_colour.extend([colour] * len(cap))
        starts.append((p.index, xy))
    # one artist each for all the pass lines and all the capture marks (one per pass drew 2.5x slower)
    ax.add_collection(LineCollection(segments, colors=colours, linestyles=styles, linewidths=1.8, zorder=3),
                      autolim=True)
    if cap_xy and labelled:
        cap_arr = np.array(cap_xy)
        ax.scatter(cap_arr[:, 0], cap_arr[:, 1], s=14, facecolors="white", edgecolors=cap_colour, linewidths=1.0,
                   marker="o", zorder=4)
    ax.plot([plan.home.x_m], [plan.home.y_m], marker="*", ms=12, color="crimson", ls="none", label="home", zorder=6)

    counts = plan_counts(plan)
    unlabelled = "" if labelled else f" (over {MAX_LABELLED_PASSES} passes: no pass numbers, arrows, image marks)"
    ax.set_title(f"pihim plan {plan.time_iso}\n{counts['passes']} passes ({counts['feasible_passes']} feasible), "
                 f"{counts['flights']} flights, {counts['capture_waypoints']} images{unlabelled}\n"
                 f"{_coverage_text(plan)}", fontsize=10)
    ax.set_xlabel("East (m)")
    ax.set_ylabel("North (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(loc="lower right", fontsize=7, framealpha=0.9).set_zorder(8)  # above the pass numbers
    sm = ScalarMappable(norm=norm, cmap=cmap)
    sm.set_array([])
    fig.colorbar(sm, ax=ax, label="share of the pass's images predicted with a usable contrast edge", shrink=0.8)
    if labelled:
        _draw_arrowheads(fig, ax, ends)
        _place_pass_labels(fig, ax, starts)
    return fig


def _data_per_pixel(ax: Any) -> NDArray[np.float64]:
    """Fix the axes' limits and aspect without drawing; the data units per display pixel along x and y."""
    ax.autoscale_view()
    ax.apply_aspect()
    inv = ax.transData.inverted()
    return np.abs(inv.transform((1.0, 1.0)) - inv.transform((0.0, 0.0)))


def _draw_arrowheads(fig: Any, ax: Any, ends: list[tuple[NDArray[np.float64], NDArray[np.float64], Any]]) -> None:
    """A filled triangle at each pass end pointing the way it is flown, all in one collection.

    ``ends`` holds, per pass, a waypoint before the end, the end and the colour. Each triangle is drawn in points
    at its pass end (the collection's offsets, in data coordinates), so it keeps its size whatever the field's
    extent, the figure's size or its resolution; its direction is the last leg's on the axes as laid out (equal
    aspect: the same on any size). One :class:`~matplotlib.collections.PolyCollection` instead of an arrow
    annotation per pass, which matplotlib shortens with Bezier splits at every draw.
    """
    if not ends:
        return
    from matplotlib.collections import PolyCollection
    from matplotlib.transforms import Affine2D

    _data_per_pixel(ax)  # limits and aspect fixed: the legs' directions on the display
    to_display = ax.transData.transform
    triangles = []
    for before, end, _ in ends:
        d = to_display(end) - to_display(before)
        d /= np.linalg.norm(d)
        n = np.array([-d[1], d[0]])
        tip = -_ARROW_SHRINK_PT * d
        base = tip - _ARROW_LENGTH_PT * d
        triangles.append(np.array([tip, base + _ARROW_HALF_WIDTH_PT * n, base - _ARROW_HALF_WIDTH_PT * n]))
    colours = [c for _, _, c in ends]
    heads = PolyCollection(triangles, facecolors=colours, edgecolors=colours, linewidths=_ARROW_LINE_WIDTH_PT,
                           zorder=3.95,  # over the pass lines, under the capture marks
                           offsets=np.array([end for _, end, _ in ends]), offset_transform=ax.transData,
                           transform=Affine2D().scale(1.0 / 72.0) + fig.dpi_scale_trans)
    heads.set_gid("pass-arrowheads")
    ax.add_collection(heads, autolim=False)


def _coverage_text(plan: Plan) -> str:
    """The plan's coverage, with its definition (the same number as ``pihim plan`` prints and ``plan.json`` holds)."""
    cov = plan.summary.get("coverage") if isinstance(plan.summary, dict) else None
    n = plan.summary.get("heliostats_in_field") if isinstance(plan.summary, dict) else None
    if isinstance(cov, dict) and "either" in cov and n:
        refl = f", {100 * cov['reflection']:.0f} % with the target's reflection (DoLP > 0.2)" if "reflection" in cov else ""
        return (f"of {n} heliostats {100 * cov.get('planned', 0.0):.0f} % imaged{refl}, "
                f"{100 * cov['either']:.0f} % with a contrast edge")
    counts = plan_counts(plan)
    return f"{100 * counts['usable_fraction']:.0f} % of the images predicted usable"


def _place_pass_labels(fig: Any, ax: Any, starts: list[tuple[int, NDArray[np.float64]]],
                       fontsize: float = 7.0) -> None:
    """Pass numbers next to the pass starts, each moved to a free spot so that no two labels overlap.

    Candidate spots lie behind the pass start (along the pass) and to either
    side of it, farther and farther; the first whose box (estimated from the
    font size and the axes scale) overlaps no placed label wins; a leader line
    joins a label moved away from its pass.
    """
    per_px = _data_per_pixel(ax)  # the limits and the aspect fixed, hence the metres per pixel, without drawing
    px = fontsize * fig.dpi / 72.0
    # placed boxes in a grid of cells at least as large as any label: a box that overlaps another shares a cell
    # with it, so each spot is checked against a few boxes, not all (a 100,000-heliostat plan has 34,000 labels)
    widest = max((len(str(index)) for index, _ in starts), default=1)
    cell = max((0.62 * px * widest + 4) * per_px[0], (px + 4) * per_px[1])
    grid: dict[tuple[int, int], list[tuple[float, float, float, float]]] = {}
    leaders: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []

    def cells(box: tuple[float, float, float, float]) -> list[tuple[int, int]]:
        i0, i1 = math.floor(box[0] / cell), math.floor(box[2] / cell)
        j0, j1 = math.floor(box[1] / cell), math.floor(box[3] / cell)
        return [(i, j) for i in range(i0, i1 + 1) for j in range(j0, j1 + 1)]

    for index, xy in starts:
        text = str(index)
        w, h = (0.62 * px * len(text) + 4) * per_px[0], (px + 4) * per_px[1]
        start = xy[0]
        d = xy[1] - xy[0] if len(xy) > 1 else np.array([0.0, 1.0])
        d = d / np.linalg.norm(d) if np.linalg.norm(d) > 1e-9 else np.array([0.0, 1.0])
        side = np.array([-d[1], d[0]])
        spot = None
        for r in np.arange(1.0, 12.0, 1.0) * max(w, h):
            for v in (-d, side, -side, -d + side, -d - side):
                c = start + r * v / np.linalg.norm(v)
                box = (c[0] - w / 2, c[1] - h / 2, c[0] + w / 2, c[1] + h / 2)
                if not any(box[0] < b[2] and b[0] < box[2] and box[1] < b[3] and b[1] < box[3]
                           for key in cells(box) for b in grid.get(key, ())):
                    spot = c
                    break
            if spot is not None:
                break
        if spot is None:
            spot = start
        box = (spot[0] - w / 2, spot[1] - h / 2, spot[0] + w / 2, spot[1] + h / 2)
        for key in cells(box):
            grid.setdefault(key, []).append(box)
        label = ax.text(spot[0], spot[1], text, fontsize=fontsize, ha="center", va="center", zorder=7,
                        bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "0.5", "lw": 0.5, "alpha": 0.85})
        label.set_gid(f"pass-label-{index}")
        # the leader runs from the pass start to the edge of the label's box (estimated as above)
        v = start - spot
        reach = min((0.5 * size / abs(c) for size, c in zip((w, h), v, strict=True) if c != 0), default=math.inf)
        if reach < 1.0:
            leaders.append((start, spot + reach * v))
    if leaders:
        from matplotlib.collections import LineCollection

        ax.add_collection(LineCollection(leaders, colors="0.4", linewidths=0.5, zorder=6.5, gid="pass-leaders"),
                          autolim=False)


def plan_png_bytes(plan: Plan, *, field: Any = None, figsize: tuple[float, float] = (10.0, 8.0),
                   dpi: float = 120.0) -> bytes:
    """The map as PNG bytes (see :func:`plan_figure`)."""
    fig = plan_figure(plan, field=field, figsize=figsize, dpi=dpi)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=float(dpi))
    return buf.getvalue()


def write_plan_figure(
    plan: Plan,
    path: str | Path,
    *,
    field: Any = None,
    figsize: tuple[float, float] = (10.0, 8.0),
    dpi: float = 120.0,
) -> Path:
    """Write the plan map as a PNG atomically.

    Parameters
    ----------
    plan : Plan
    path : str or path-like
        Output file, conventionally ``plan.png``.
    field : Field, optional
        Heliostats and tower to draw.
    figsize : (float, float)
        Inches; default 10 x 8.
    dpi : float
        Default 120 (a 1200 x 960 pixel PNG).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    PihimInputError
        Invalid plan, field or size; no file is written.
    """
    data = plan_png_bytes(plan, field=field, figsize=figsize, dpi=dpi)
    return write_export(path, data)
