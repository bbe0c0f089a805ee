"""Mission export: a :class:`~pihim.planning.model.Plan` as files for people and drones.

=====================  ==============================  ==================================
file                   writer                          for
=====================  ==============================  ==================================
``plan.json``          :func:`write_plan_json`         the whole plan, schema ``pihim.plan/1``
``mission.plan``       :func:`write_qgc_plan`          QGroundControl (ArduPilot, PX4)
``mission.waypoints``  :func:`write_wpl`               QGC WPL 110 text (Mission Planner, MAVProxy)
``plan.kml``           :func:`write_kml`               Google Earth
``litchi.csv``         :func:`write_litchi_csv`        Litchi (DJI drones)
``plan.png``           :func:`write_plan_figure`       a map of the passes
=====================  ==============================  ==================================

:func:`export_all` writes all six (and, when ``litchi.csv`` is longer than
Litchi's 99 waypoints, the flights as ``litchi_01.csv`` ... missions,
:func:`litchi_missions`). Every writer validates the plan first (a
plan without passes or a waypoint with a non-finite number raises
:class:`~pihim.errors.PihimInputError` with a one-line message) and writes
atomically (temporary sibling, then rename), so a failure never leaves a
partial file. Formats, frames and the ``plan.json`` schema are documented in
``docs/plan-formats.md``.
"""

from __future__ import annotations

import contextlib
import warnings
from pathlib import Path
from typing import Any, Literal

from pihim._atomic import atomic_path
from pihim.errors import PihimInputError
from pihim.planning.export._common import check_plan, write_data
from pihim.planning.export.figure import plan_figure, plan_png_bytes, write_plan_figure
from pihim.planning.export.kml import kml_text, write_kml
from pihim.planning.export.litchi import (
    LITCHI_HEADER,
    LITCHI_MAX_WAYPOINTS,
    litchi_csv_text,
    litchi_mission_texts,
    litchi_missions,
    litchi_waypoints,
    write_litchi_csv,
)
from pihim.planning.export.plan_json import (
    load_plan_schema,
    plan_document,
    plan_json_text,
    write_plan_json,
)
from pihim.planning.export.qgc import (
    Mission,
    MissionItem,
    mission_items,
    qgc_plan_document,
    qgc_plan_text,
    write_qgc_plan,
)
from pihim.planning.export.wpl import wpl_text, write_wpl
from pihim.planning.model import Plan

__all__ = [
    "LITCHI_HEADER",
    "OUTPUT_NAMES",
    "Mission",
    "MissionItem",
    "export_all",
    "kml_text",
    "litchi_csv_text",
    "litchi_mission_texts",
    "litchi_missions",
    "litchi_waypoints",
    "load_plan_schema",
    "load_qgc_plan_schema",
    "mission_items",
    "plan_document",
    "plan_figure",
    "plan_json_text",
    "plan_png_bytes",
    "qgc_plan_document",
    "qgc_plan_text",
    "wpl_text",
    "write_kml",
    "write_litchi_csv",
    "write_plan_figure",
    "write_plan_json",
    "write_qgc_plan",
    "write_wpl",
]

#: Keys of :func:`export_all`'s result and the file names it writes.
OUTPUT_NAMES: dict[str, str] = {
    "plan_json": "plan.json",
    "qgc_plan": "mission.plan",
    "wpl": "mission.waypoints",
    "kml": "plan.kml",
    "litchi": "litchi.csv",
    "figure": "plan.png",
}


def load_qgc_plan_schema() -> dict[str, Any]:
    """The JSON Schema of QGroundControl plan files (``pihim/schemas/qgc-plan.schema.json``)."""
    import json
    from importlib import resources

    return json.loads(resources.files("pihim").joinpath("schemas/qgc-plan.schema.json").read_text(encoding="utf-8"))


def export_all(
    plan: Plan,
    out_dir: str | Path,
    *,
    field: Any = None,
    flight: int | None = None,
    geoid_undulation_m: float | None = None,
    kml_altitude_mode: Literal["relativeToGround", "absolute"] = "relativeToGround",
    geofence_margin_m: float | None = None,
    litchi_hover_ms: int = 0,
    litchi_max_waypoints: int | None = None,
    figsize: tuple[float, float] = (10.0, 8.0),
    dpi: float = 120.0,
    **mission_options: Any,
) -> dict[str, Path]:
    """Write ``plan.json``, ``mission.plan``, ``mission.waypoints``, ``plan.kml``, ``litchi.csv`` and ``plan.png``.

    All six are rendered in memory first and then renamed into ``out_dir``
    together: invalid input writes nothing, and no file is ever partial.

    Parameters
    ----------
    plan : Plan
    out_dir : str or path-like
        Created if missing; existing files of the same names are replaced.
    field : Field, optional
        Heliostats and tower for the KML and the map.
    flight : int, optional
        Mission files (``.plan``, ``.waypoints``, Litchi) for this flight
        only; default all passes. ``plan.json``, the KML and the map always
        show the whole plan.
    geoid_undulation_m : float, optional
        EGM96 geoid height at the site for the sea-level altitudes (QGC home
        position, ``altitude_frame="amsl"``, absolute KML).
    kml_altitude_mode : {"relativeToGround", "absolute"}
        See :func:`write_kml`.
    geofence_margin_m : float, optional
        Inclusion geofence for the ``.plan`` (see :func:`qgc_plan_document`).
    litchi_hover_ms : int
        Hover before each Litchi photo, milliseconds.
    litchi_max_waypoints : int or None
        Refuse Litchi missions longer than this. Default None: write
        ``litchi.csv`` whole and, when it is longer than Litchi's 99
        waypoints (and ``flight`` is None), also every flight cut into
        missions of at most 99 waypoints at pass boundaries
        (:func:`litchi_missions`) as ``litchi_01.csv``, ``litchi_02.csv``
        ..., in flight order; a :class:`UserWarning` says so.
    figsize, dpi
        Map size (inches) and resolution.
    **mission_options
        Passed to :func:`mission_items` for both mission files
        (``autopilot``, ``altitude_frame``, ``condition_yaw``,
        ``mount_control``, ``camera``, ``capture_hold_s``, ``end``, ...).

    Returns
    -------
    dict of str to Path
        Keys of :data:`OUTPUT_NAMES`, plus ``litchi_01``, ``litchi_02`` ...
        for the Litchi missions when they are written.

    Raises
    ------
    PihimInputError
        Invalid plan or option; nothing is written.
    """
    check_plan(plan)
    opts = dict(mission_options, flight=flight, geoid_undulation_m=geoid_undulation_m)
    contents: dict[str, str | bytes] = {
        "plan_json": plan_json_text(plan),
        "qgc_plan": qgc_plan_text(plan, geofence_margin_m=geofence_margin_m, **opts),
        "wpl": wpl_text(plan, **opts),
        "kml": kml_text(plan, field=field, altitude_mode=kml_altitude_mode, geoid_undulation_m=geoid_undulation_m),
        "litchi": litchi_csv_text(plan, flight=flight, hover_ms=litchi_hover_ms, max_waypoints=litchi_max_waypoints),
        "figure": plan_png_bytes(plan, field=field, figsize=figsize, dpi=dpi),
    }
    n_litchi = len(litchi_waypoints(plan, flight))
    names = dict(OUTPUT_NAMES)
    if litchi_max_waypoints is None and n_litchi > LITCHI_MAX_WAYPOINTS:
        if flight is None and plan.flights:
            parts = litchi_mission_texts(plan, hover_ms=litchi_hover_ms)
            for k, text in enumerate(parts, start=1):
                contents[f"litchi_{k:02d}"] = text
                names[f"litchi_{k:02d}"] = f"litchi_{k:02d}.csv"
            hint = f"the flights are also written as {len(parts)} missions litchi_01.csv ... litchi_{len(parts):02d}.csv"
        else:
            hint = "export one flight at a time"
        warnings.warn(f"litchi.csv has {n_litchi} waypoints; Litchi accepts at most {LITCHI_MAX_WAYPOINTS} per "
                      f"mission: {hint}", UserWarning, stacklevel=2)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise PihimInputError(f"{out} exists and is not a directory")
    paths = {key: out / name for key, name in names.items()}
    with contextlib.ExitStack() as stack:
        for key, data in contents.items():
            write_data(stack.enter_context(atomic_path(paths[key])), data, newline="\n")
    return paths
