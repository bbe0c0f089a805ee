"""Map of a plan in the field frame (``plan.png``).

A top view in field East-North-Up metres: heliostat pivots as grey dots and
the tower footprint (when a :class:`~pihim.field.layout.Field` is given),
each scan pass as a line through its waypoints ending in an arrow, coloured
by its predicted usable fraction (colour bar; infeasible passes dashed),
capture waypoints as small open circles, pass indices at the pass starts,
the home position, and a title with the time and the counts. Drawn with
matplotlib's object-oriented API on an Agg canvas: no ``pyplot``, no global
state, safe in threads and servers [1]_.

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

from pihim.errors import PihimInputError
from pihim.planning.export._common import check_plan, plan_counts, write_export
from pihim.planning.model import Plan

__all__ = ["plan_figure", "plan_png_bytes", "write_plan_figure"]


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

    for p in plan.passes:
        xy = np.array([(w.x_m, w.y_m) for w in p.waypoints])
        colour = cmap(norm(p.usable_fraction))
        style = "-" if p.feasible else "--"
        ax.plot(xy[:, 0], xy[:, 1], style, color=colour, lw=1.5, zorder=3)
        if len(xy) >= 2 and np.hypot(*(xy[-1] - xy[0])) > 0:
            ax.annotate("", xy=xy[-1], xytext=xy[-2], zorder=4,
                        arrowprops={"arrowstyle": "-|>", "color": colour, "lw": 1.5, "mutation_scale": 14})
        cap = np.array([(w.x_m, w.y_m) for w in p.waypoints if w.capture])
        if len(cap):
            ax.scatter(cap[:, 0], cap[:, 1], s=14, facecolors="white", edgecolors=[colour], linewidths=1.0,
                       marker="o", zorder=4)
        ax.annotate(str(p.index), xy=xy[0], fontsize=7, xytext=(-3, 3), textcoords="offset points", ha="right",
                    zorder=5)
    ax.plot([plan.home.x_m], [plan.home.y_m], marker="*", ms=12, color="crimson", ls="none", label="home", zorder=6)

    counts = plan_counts(plan)
    ax.set_title(f"pihim plan {plan.time_iso}\n{counts['passes']} passes ({counts['feasible_passes']} feasible), "
                 f"{counts['heliostats']} heliostats, {counts['capture_waypoints']} images, "
                 f"{100 * counts['usable_fraction']:.0f} % predicted usable", fontsize=10)
    ax.set_xlabel("East (m)")
    ax.set_ylabel("North (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(loc="lower right", fontsize=8)
    sm = ScalarMappable(norm=norm, cmap=cmap)
    sm.set_array([])
    fig.colorbar(sm, ax=ax, label="predicted usable fraction of the pass's images", shrink=0.8)
    return fig


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
