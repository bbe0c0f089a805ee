"""The ``canting.json`` document (``pihim.canting/1``) and its figure in the style of the paper's Fig. 8.

Shared by ``pihim canting``, ``pihim demo`` and campaign reports: the document
is :meth:`pihim.inspection.canting.CantingResult.to_dict` with the facet grid,
a short code per skip reason, the per-frame inputs and the outputs; the
figure maps the azimuth and elevation deviations over the facet grid as seen
from the front, skipped facets hatched with their code.

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone", Fig. 8 (facet maps of the canting deviations).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from pihim.inspection.canting import CantingResult
from pihim.inspection.pipeline import InspectionResult

__all__ = ["REASON_CODES", "SCHEMA_ID", "canting_figure", "canting_record", "canting_png_writer", "reason_code"]

SCHEMA_ID = "pihim.canting/1"
#: A measured facet with less of its outline than this inside the frame is marked on the figure with its share in
#: view: on 140 rendered frames such facets were more than 0.5 mrad off six times as often (BENCHMARKS.md, canting).
HALF_IN_VIEW = 0.5

#: Short codes of the skip reasons (figure and ``reason_code``), matched on the reason text.
REASON_CODES: tuple[tuple[str, str, str], ...] = (
    ("not in view", "OUT", "facet not in view"),
    ("saturated", "SAT", "saturated"),
    ("DoLP", "DOLP", "DoLP too low"),
    ("explain it alike", "AMBIG", "two fits explain it alike"),  # before NOREF: its text starts the same
    ("no usable reflection", "NOREF", "no reflection of the target"),
    ("too few matched", "PTS", "too few edge points"),
    ("sub-pixel", "RMS", "residual too large"),
    ("does not look like", "SUPP", "reflection not the target's outline"),
    ("run one way", "LINE", "edges of one direction only"),
)


def reason_code(reason: str | None) -> str | None:
    """A short code for a skip reason (``OTHER`` when none matches)."""
    if reason is None:
        return None
    for key, code, _ in REASON_CODES:
        if key in reason:
            return code
    return "OTHER"


def canting_record(result: CantingResult, inspections: list[tuple[Path, Path, InspectionResult]], *,
                   rows: int, cols: int, outputs: dict[str, Path], seconds: float) -> dict[str, Any]:
    """The ``pihim.canting/1`` document."""
    doc = result.to_dict()
    facets = []
    for f in doc["facets"]:  # type: ignore[union-attr]
        f = dict(f)
        f["reason_code"] = reason_code(f.get("reason"))
        facets.append(f)
    per_frame = []
    for frame, meta, r in inspections:
        c = r.canting
        per_frame.append({
            "frame": str(frame),
            "meta": str(meta),
            "hua": r.hua,
            "target": r.target,
            "image": r.image,
            "pose": r.pose,
            "facets_used": sum(1 for f in c.facets if f.used),
            "orientation_mrad": None if c.orientation_az_mrad is None else
            {"az": float(c.orientation_az_mrad), "el": float(c.orientation_el_mrad)},
            "drive_correction_deg": None if c.drive_correction_deg is None else
            {"az": float(c.drive_correction_deg[0]), "el": float(c.drive_correction_deg[1])},
            "orientation_search": None if c.search is None else c.search.to_dict(),
            "target_correction_deg": None if c.target_correction_deg is None else
            {"az": float(c.target_correction_deg[0]), "el": float(c.target_correction_deg[1])},
            "seconds": r.seconds,
        })
    return {
        "schema": SCHEMA_ID,
        "hua": doc["hua"],
        "target": doc["target"],
        "frames": doc["frames"],
        "reference": doc["reference"],
        "orientation_mrad": doc["orientation_mrad"],
        "drive_correction_deg": doc["drive_correction_deg"],
        "facet_grid": {"rows": int(rows), "cols": int(cols),
                       "numbering": "1..rows*cols row by row from the top left, seen from the front"},
        "facets_used": sum(1 for f in facets if f["used"]),
        "facets": facets,
        "notes": doc["notes"],
        "inputs": per_frame,
        "outputs": {k: str(v) for k, v in outputs.items()},
        "seconds": round(float(seconds), 3),
    }


def canting_png_writer(record: dict[str, Any]) -> Callable[[Path], None]:
    """A writer ``f(path)`` of :func:`canting_figure` as PNG (for an atomic group of outputs)."""
    def write(path: Path) -> None:
        fig = canting_figure(record)
        try:
            fig.savefig(path, format="png", dpi=110)
        finally:
            import matplotlib.pyplot as plt

            plt.close(fig)
    return write


def canting_figure(record: dict[str, Any]) -> Any:
    """Facet maps of the azimuth and elevation deviations (the paper's Fig. 8 style)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm
    from matplotlib.patches import Rectangle

    rows, cols = record["facet_grid"]["rows"], record["facet_grid"]["cols"]
    facets = {f["id"]: f for f in record["facets"]}
    vals = [abs(f[k]) for f in facets.values() if f["used"] for k in ("az_mrad", "el_mrad")]
    vmax = max(1.0, float(np.ceil(max(vals) if vals else 1.0)))
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-vmax, vmax=vmax)
    cmap = plt.get_cmap("RdBu_r")
    fig, axes = plt.subplots(1, 2, figsize=(11.0, 6.0), constrained_layout=True)
    for ax, key, title in zip(axes, ("az", "el"), ("azimuth deviation", "elevation deviation"), strict=True):
        for i in range(rows * cols):
            r, c = divmod(i, cols)
            fid = i + 1
            f = facets.get(fid)
            x, y = c, rows - 1 - r
            if f is not None and f["used"]:
                v = f[f"{key}_mrad"]
                s = f[f"{key}_sigma_mrad"]
                ax.add_patch(Rectangle((x + 0.03, y + 0.03), 0.94, 0.94, facecolor=cmap(norm(v)), edgecolor="k", lw=0.8))
                dark = abs(norm(v) - 0.5) > 0.35
                ax.text(x + 0.5, y + 0.52, f"{v:+.2f}", ha="center", va="center", fontsize=12, weight="bold",
                        color="white" if dark else "black")
                if s is not None:
                    ax.text(x + 0.5, y + 0.25, f"±{s:.2g}", ha="center", va="center", fontsize=8,
                            color="white" if dark else "0.2")
                seen = f.get("in_view")
                if seen is not None and seen < HALF_IN_VIEW:
                    ax.text(x + 0.5, y + 0.07, f"{100 * seen:.0f} % in view", ha="center", va="bottom", fontsize=7,
                            style="italic", color="white" if dark else "0.1")
            else:
                ax.add_patch(Rectangle((x + 0.03, y + 0.03), 0.94, 0.94, facecolor="0.88", edgecolor="0.5", lw=0.8,
                                       hatch="///"))
                code = reason_code(f["reason"]) if f is not None else "N/A"
                ax.text(x + 0.5, y + 0.45, code, ha="center", va="center", fontsize=9, color="0.25",
                        bbox={"facecolor": "0.88", "edgecolor": "none", "pad": 1.0})
            on_dark = f is not None and f["used"] and abs(norm(f[f"{key}_mrad"]) - 0.5) > 0.35
            ax.text(x + 0.08, y + 0.9, str(fid), ha="left", va="top", fontsize=8,
                    color="white" if on_dark else "0.1")
        ax.set_xlim(0, cols)
        ax.set_ylim(0, rows)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"{title} (mrad)", fontsize=12)
        sm = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
        fig.colorbar(sm, ax=ax, orientation="horizontal", fraction=0.05, pad=0.02)
    o = record["orientation_mrad"]
    orient = "none" if o is None else f"az {o['az']:+.2f}, el {o['el']:+.2f} mrad"
    dc = record.get("drive_correction_deg")
    if dc is not None:
        orient += f"; drive correction az {dc['az']:+.3f}, el {dc['el']:+.3f} deg"
    fig.suptitle(f"Facet canting of {record['hua']} (target {record['target']}, {record['frames']} frame(s), "
                 f"{record['facets_used']} facets used), seen from the front\n"
                 f"relative to the best-fit heliostat orientation ({orient})\n"
                 "value ± standard error (a jackknife over the reflected outline's segments; a fit locked onto "
                 "other features is off by more: docs/cli.md)",
                 fontsize=11)
    items = [f"{code}: {text}" for _, code, text in REASON_CODES]
    half = (len(items) + 1) // 2
    partly = any(f["used"] and f.get("in_view") is not None and f["in_view"] < HALF_IN_VIEW for f in facets.values())
    fig.supxlabel("grey hatched = skipped:  " + ";  ".join(items[:half]) + "\n" + ";  ".join(items[half:])
                  + ("\n'N % in view': a measured facet less than half inside the frame (such facets were more "
                     "often wrong on rendered frames)" if partly else ""), fontsize=8.5)
    return fig
