"""``plan.json``: the complete plan as JSON (schema ``pihim.plan/1``).

The document is :meth:`Plan.to_dict() <pihim.planning.model.Plan.to_dict>`
(every pass with its HUA-target pairs, waypoints and predicted contrasts,
the flights and the summary) plus an ``export`` block: the generator, the
frame and unit conventions, and counts. Non-finite numbers (which JSON
cannot hold) become ``null``. The JSON Schema (draft 2020-12) ships as
``pihim/schemas/plan.schema.json`` and is described field by field in
``docs/plan-formats.md``.

References
----------
.. [1] JSON Schema draft 2020-12, https://json-schema.org/draft/2020-12.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any

import pihim
from pihim._atomic import write_atomic
from pihim._jsontext import json_text, write_json_text
from pihim.planning.export._common import (
    check_plan,
    json_ready,
    plan_counts,
)
from pihim.planning.model import PLAN_SCHEMA_ID, Plan

__all__ = ["CONVENTIONS", "load_plan_schema", "plan_document", "plan_json_text", "write_plan_json",
           "write_plan_json_text"]

#: Frames and units, repeated in every ``plan.json`` so the file explains itself.
CONVENTIONS = {
    "field_frame": "East-North-Up, metres, origin at the tower base (x_m East, y_m North, z_m Up)",
    "geodetic": "WGS84 latitude_deg, longitude_deg; height_m is ellipsoidal (not above sea level)",
    "heading_deg": "drone and camera heading, degrees clockwise from North, [0, 360)",
    "gimbal_pitch_deg": "camera pitch, degrees, 0 horizontal, negative below the horizon (-90 straight down)",
    "speed_m_s": "ground speed toward the waypoint, m/s",
    "altitude_m": "pass altitude above the field origin, metres",
    "aop_deg": "AoP differences are axial, degrees in [0, 90]; *_raw_* are raw absolute differences",
}


def load_plan_schema() -> dict[str, Any]:
    """The ``plan.json`` JSON Schema shipped with pihim (``pihim/schemas/plan.schema.json``)."""
    return json.loads(resources.files("pihim").joinpath("schemas/plan.schema.json").read_text(encoding="utf-8"))


def plan_document(plan: Plan) -> dict[str, Any]:
    """The ``plan.json`` content.

    Parameters
    ----------
    plan : Plan

    Returns
    -------
    dict
        ``Plan.to_dict()`` (``schema`` = ``"pihim.plan/1"``) with non-finite
        numbers replaced by ``None``, plus ``export``: ``generator``
        (``"pihim <version>"``), ``conventions`` (:data:`CONVENTIONS`) and
        ``counts`` (passes, flights, waypoints, capture waypoints, pairs,
        heliostats, HUAs, predictions, usable predictions, usable fraction).

    Raises
    ------
    PihimInputError
        Plan without passes or with a non-finite waypoint number.
    """
    check_plan(plan)
    doc = plan.to_dict(finite=True)
    doc["schema"] = PLAN_SCHEMA_ID
    doc["export"] = {
        "generator": f"pihim {pihim.__version__}",
        "conventions": dict(CONVENTIONS),
        "counts": json_ready(plan_counts(plan)),
    }
    return doc


def plan_json_text(plan: Plan) -> str:
    """The ``plan.json`` text: :func:`plan_document` indented by two spaces, one waypoint or prediction per line.

    Members nested four levels deep (a pass's or flight's waypoints and
    predictions, a mission's entries) are each written on one line.
    """
    return json_text(plan_document(plan), indent=2, inline_depth=4) + "\n"


def write_plan_json_text(plan: Plan, write: Callable[[str], Any]) -> None:
    """:func:`plan_json_text` passed to ``write`` (e.g. a text file's) in pieces of a megabyte or two.

    The text of a 100,000-heliostat plan (340 MB) then never lies in memory
    whole. The plan is checked (:func:`plan_document`) before the first piece.
    """
    write_json_text(plan_document(plan), write, indent=2, inline_depth=4)
    write("\n")


def write_plan_json(plan: Plan, path: str | Path) -> Path:
    """Write ``plan.json`` atomically.

    Parameters
    ----------
    plan : Plan
    path : str or path-like
        Output file, conventionally ``plan.json``.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    PihimInputError
        Invalid plan; no file is written.

    Notes
    -----
    The file validates against :func:`load_plan_schema` (tested).
    """
    doc = plan_document(plan)  # checked before a temporary file is made

    def write(tmp: Path) -> None:
        with open(tmp, "w", encoding="utf-8", newline="\n") as fh:
            write_json_text(doc, fh.write, indent=2, inline_depth=4)
            fh.write("\n")

    return write_atomic(path, write)
