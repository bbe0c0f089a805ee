"""Mission export: a :class:`~pihim.planning.model.Plan` as files for people and drones.

=============================  ==============================  ==================================
file                           writer                          for
=============================  ==============================  ==================================
``plan.json``                  :func:`write_plan_json`         the whole plan, schema ``pihim.plan/1``
``flight_01.plan`` ...         :func:`write_qgc_plan`          QGroundControl (ArduPilot, PX4)
``flight_01.waypoints`` ...    :func:`write_wpl`               QGC WPL 110 text (Mission Planner, MAVProxy)
``flight_01_litchi.csv`` ...   :func:`write_litchi_csv`        Litchi (DJI drones)
``plan.kml``                   :func:`write_kml`               Google Earth
``plan.png``                   :func:`write_plan_figure`       a map of the passes and flights
=============================  ==============================  ==================================

:func:`export_all` writes ``plan.json``, ``plan.kml``, ``plan.png`` and one
mission per flight (one battery): ``flight_NN.plan`` and
``flight_NN.waypoints``, each starting and ending at home and holding at most
``max_mission_items`` mission items (700 by default, what Pixhawk-class
ArduPilot boards store), and the flight as Litchi missions of at most 99
waypoints (``flight_NN_litchi.csv``, or ``flight_NN_litchi_1.csv``, ``_2`` ...
when the flight needs several). The whole-field ``mission.plan``,
``mission.waypoints`` and ``litchi.csv`` are written only when one flight
covers the plan, or for a plan never split into flights (and ``litchi.csv``
only within Litchi's 99 waypoints); a plan split into no flight (every pass
beyond a battery's reach) gets no mission file. Every
writer validates the plan first (a plan without passes or a waypoint with a
non-finite number raises :class:`~pihim.errors.PihimInputError` with a
one-line message) and writes atomically (temporary sibling, then rename), so
a failure never leaves a partial file. Formats, frames and the ``plan.json``
schema are documented in ``docs/plan-formats.md``.
"""

from __future__ import annotations

import contextlib
import functools
import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, Literal

from pihim import _forked
from pihim._atomic import clean_stale_temporaries, missing_dirs, output_target, remove_empty_dirs, temp_sibling
from pihim.errors import PihimInputError
from pihim.planning.export._common import check_plan, mission_waypoints, write_data
from pihim.planning.export.figure import plan_figure, plan_png_bytes, write_plan_figure
from pihim.planning.export.kml import kml_text, write_kml, write_kml_text
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
    write_plan_json_text,
)
from pihim.planning.export.qgc import (
    Mission,
    MissionItem,
    MissionItemCounter,
    count_mission_items,
    mission_items,
    qgc_document_text,
    qgc_mission_document,
    qgc_plan_document,
    qgc_plan_text,
    write_qgc_plan,
)
from pihim.planning.export.wpl import wpl_mission_text, wpl_text, write_wpl
from pihim.planning.model import Plan

__all__ = [
    "DEFAULT_MAX_MISSION_ITEMS",
    "LITCHI_HEADER",
    "OUTPUT_NAMES",
    "Mission",
    "MissionItem",
    "MissionItemCounter",
    "count_mission_items",
    "export_all",
    "flight_file_stem",
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
    "write_kml_text",
    "write_litchi_csv",
    "write_plan_figure",
    "write_plan_json",
    "write_plan_json_text",
    "write_qgc_plan",
    "write_wpl",
]

#: Keys of :func:`export_all`'s result and the file names it writes for the whole plan
#: (``qgc_plan``, ``wpl`` and ``litchi`` only when one flight covers the plan).
OUTPUT_NAMES: dict[str, str] = {
    "plan_json": "plan.json",
    "qgc_plan": "mission.plan",
    "wpl": "mission.waypoints",
    "kml": "plan.kml",
    "litchi": "litchi.csv",
    "figure": "plan.png",
}

#: Default mission-item limit: Pixhawk-class (STM32F4/F7) ArduPilot boards store about 700 items.
DEFAULT_MAX_MISSION_ITEMS = 700


def flight_file_stem(index: int) -> str:
    """File-name stem of a flight's missions: ``flight_01`` for :attr:`Flight.index` 0."""
    return f"flight_{index + 1:02d}"


def load_qgc_plan_schema() -> dict[str, Any]:
    """The JSON Schema of QGroundControl plan files (``pihim/schemas/qgc-plan.schema.json``)."""
    import json
    from importlib import resources

    return json.loads(resources.files("pihim").joinpath("schemas/qgc-plan.schema.json").read_text(encoding="utf-8"))


def _check_limit(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 4:
        raise PihimInputError(f"max_mission_items must be an integer >= 4, got {value!r}")
    return value


#: A file's text written in pieces to the ``write`` it is given (see ``export_all``).
_Producer = Callable[[Callable[[str], Any]], None]

#: Flights whose mission files one piece of :func:`export_all`'s work renders.
_FLIGHTS_PER_PIECE = 64


def _mission_files(plan: Plan, flight: int | None, stem: str, *, max_items: int, geofence_margin_m: float | None,
                   litchi_hover_ms: int, opts: dict[str, Any]) -> dict[str, tuple[str, str | bytes]]:
    """``{key: (file name, content)}`` of one flight's missions (or of a plan without flights)."""
    mission = mission_items(plan, flight=flight, **opts)  # built once for the .plan and .waypoints files
    n_items = len(mission.items) + 1
    if n_items > max_items:
        which = "the plan" if flight is None else f"flight {flight + 1}"
        raise PihimInputError(
            f"{which} needs {n_items} mission items, more than the limit of {max_items}: plan with "
            f"max_mission_items={max_items} and the same mission options, or raise the limit"
        )
    key = stem.replace(".", "_")
    out: dict[str, tuple[str, str | bytes]] = {
        f"{key}_plan": (f"{stem}.plan", qgc_document_text(qgc_mission_document(plan, mission, geofence_margin_m,
                                                                               flight))),
        f"{key}_waypoints": (f"{stem}.waypoints", wpl_mission_text(mission)),
    }
    if flight is None:  # a plan without flights: its passes, if Litchi takes them
        if len(litchi_waypoints(plan)) <= LITCHI_MAX_WAYPOINTS:
            out[f"{key}_litchi"] = (f"{stem}_litchi.csv", litchi_csv_text(plan, hover_ms=litchi_hover_ms))
        return out
    parts = litchi_mission_texts(plan, hover_ms=litchi_hover_ms, flight=flight)
    for k, text in enumerate(parts, start=1):
        suffix = "" if len(parts) == 1 else f"_{k}"
        out[f"{key}_litchi{suffix}"] = (f"{stem}_litchi{suffix}.csv", text)
    return out


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
    max_mission_items: int = DEFAULT_MAX_MISSION_ITEMS,
    figsize: tuple[float, float] = (10.0, 8.0),
    dpi: float = 120.0,
    workers: int | None = 1,
    **mission_options: Any,
) -> dict[str, Path]:
    """Write ``plan.json``, ``plan.kml``, ``plan.png`` and one set of mission files per flight.

    Each file is written to a temporary next to its final name by the process
    that renders it, and the temporaries are renamed together once all are
    written: invalid input leaves nothing behind (an ``out_dir`` this call
    created is removed again), and no file is ever partial.

    Parameters
    ----------
    plan : Plan
    out_dir : str or path-like
        Created if missing; existing files of the same names are replaced.
    field : Field, optional
        Heliostats and tower for the KML and the map.
    flight : int, optional
        Mission files for this flight (:attr:`Flight.index`) only; default
        every flight. ``plan.json``, the KML and the map always show the
        whole plan.
    geoid_undulation_m : float, optional
        EGM96 geoid height at the site for the sea-level altitudes (QGC home
        position, ``altitude_frame="amsl"``, absolute KML).
    kml_altitude_mode : {"relativeToGround", "absolute"}
        See :func:`write_kml`.
    geofence_margin_m : float, optional
        Inclusion geofence for the ``.plan`` files (see :func:`qgc_plan_document`).
    litchi_hover_ms : int
        Hover before each Litchi photo, milliseconds.
    max_mission_items : int
        Refuse a flight whose mission holds more items than this (home slot
        included; default 700). :func:`pihim.planning.pipeline.build_plan`
        splits flights under the same limit.
    figsize, dpi
        Map size (inches) and resolution.
    workers : int or None
        Processes rendering the files side by side (forked copies of this
        one on Linux, :mod:`pihim._forked`; None: one per CPU); the files do
        not depend on it.
    **mission_options
        Passed to :func:`mission_items` for the mission files (``autopilot``,
        ``altitude_frame``, ``condition_yaw``, ``mount_control``, ``camera``,
        ``capture_hold_s``, ``yaw_rate_deg_s``, ``end``, ...).

    Returns
    -------
    dict of str to Path
        ``plan_json``, ``kml``, ``figure``; per flight ``flight_01_plan``,
        ``flight_01_waypoints`` and ``flight_01_litchi`` (or
        ``flight_01_litchi_1``, ``_2`` ...); ``qgc_plan``, ``wpl`` and
        ``litchi`` (the whole-field files) when one flight covers the plan.

    Raises
    ------
    PihimInputError
        Invalid plan or option, or a flight over ``max_mission_items``;
        nothing is written.
    """
    check_plan(plan)
    limit = _check_limit(max_mission_items)
    _forked.check_workers(workers)
    opts = dict(mission_options, geoid_undulation_m=geoid_undulation_m)
    if flight is not None:
        mission_waypoints(plan, flight)  # unknown index -> one-line error
    flights = [f.index for f in plan.flights if flight is None or f.index == flight]

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise PihimInputError(f"{out} exists and is not a directory")
    created = missing_dirs(out)
    out.mkdir(parents=True, exist_ok=True)

    made: list[Path] = []  # every temporary this process makes (a worker's copy of the list stays in the worker)

    def stage(files: dict[str, tuple[str, str | bytes | _Producer]]) -> dict[str, tuple[Path, Path]]:
        """Write files each to a temporary next to its final path: ``{key: (path, temporary)}``.

        A file is its rendered content, or a function that writes the text in pieces to the ``write`` it is
        given (``plan.json`` and ``plan.kml``: 340 and 210 MB at 100,000 heliostats).
        """
        first = len(made)
        staged: dict[str, tuple[Path, Path]] = {}
        try:
            for key, (name, data) in files.items():
                final = output_target(out / name)  # a link is followed, anything but a regular file refused
                final.parent.mkdir(parents=True, exist_ok=True)
                temp = temp_sibling(final, made)
                if callable(data):
                    with open(temp, "w", encoding="utf-8", newline="\n") as fh:
                        data(fh.write)
                else:
                    write_data(temp, data, newline="\n")
                staged[key] = (out / name, temp)
        except BaseException:
            _unlink(made[first:])
            raise
        return staged

    def missions(ks: list[int]) -> dict[str, tuple[Path, Path]]:
        staged: dict[str, tuple[Path, Path]] = {}
        try:
            for k in ks:
                staged.update(stage(_mission_files(plan, k, flight_file_stem(k), max_items=limit,
                                                   geofence_margin_m=geofence_margin_m,
                                                   litchi_hover_ms=litchi_hover_ms, opts=opts)))
        except BaseException:
            _unlink(temp for _, temp in staged.values())
            raise
        return staged

    # Every file is rendered and written to its temporary by the process that renders it (side by side with
    # workers, the plan-wide files first, the longest): only the names come back, and no file's content waits
    # in memory for the others. The temporaries are renamed together once all are written.
    pieces: list[Callable[[], dict[str, tuple[Path, Path]]]] = [
        lambda: stage({"plan_json": ("plan.json", functools.partial(write_plan_json_text, plan))}),
        lambda: stage({"kml": ("plan.kml", functools.partial(write_kml_text, plan, field=field,
                                                              altitude_mode=kml_altitude_mode,
                                                              geoid_undulation_m=geoid_undulation_m))}),
        lambda: stage({"figure": ("plan.png", plan_png_bytes(plan, field=field, figsize=figsize, dpi=dpi))}),
    ]
    pieces += [functools.partial(missions, flights[i:i + _FLIGHTS_PER_PIECE])
               for i in range(0, len(flights), _FLIGHTS_PER_PIECE)]

    def render(i: int) -> Any:
        try:
            return pieces[i]()
        except PihimInputError as exc:  # raised below in the pieces' order, whichever worker met it first
            return exc

    done: list[Any] = [None] * len(pieces)
    staged: dict[str, tuple[Path, Path]] = {}
    results = _forked.imap_unordered(render, len(pieces), workers, what="files")
    try:
        for i, result in results:
            done[i] = result
        for result in done:
            if isinstance(result, PihimInputError):
                raise result
            staged.update(result)  # in the pieces' order, whatever the order they came in
        # A plan never split into flights is one mission; a plan split into none (every pass beyond a battery's
        # reach from home) has nothing flyable, so no mission files.
        if not plan.flights and "flights" not in plan.summary:
            files = _mission_files(plan, None, "mission", max_items=limit, geofence_margin_m=geofence_margin_m,
                                   litchi_hover_ms=litchi_hover_ms, opts=opts)
            # under the plan-wide keys and names
            keys = {"mission_plan": "qgc_plan", "mission_waypoints": "wpl", "mission_litchi": "litchi"}
            staged.update(stage({keys[key]: (OUTPUT_NAMES[keys[key]], data) for key, (_, data) in files.items()}))
        elif len(plan.flights) == 1 and flight is None:  # one flight covers the plan: the whole-field files too
            stem = flight_file_stem(plan.flights[0].index)
            copies = {"qgc_plan": f"{stem}_plan", "wpl": f"{stem}_waypoints", "litchi": f"{stem}_litchi"}
            staged.update(stage({key: (OUTPUT_NAMES[key], staged[of][1].read_bytes())
                                 for key, of in copies.items() if of in staged}))
        for path, temp in staged.values():
            os.replace(temp, output_target(path))
    except BaseException:
        with _forked.signals_deferred():  # a second Ctrl-C waits until the workers are gone and the folder clean
            try:
                results.close()  # the workers stopped first: what they were writing is then stale (below)
            finally:
                # the temporaries not renamed (a file already renamed stays: it replaced the earlier one for good)
                known = [temp for r in done if isinstance(r, dict) for _, temp in r.values()]  # made by workers
                _unlink([*made, *known])
                clean_stale_temporaries(out)  # those of pieces a stopped worker finished: its process is gone
                remove_empty_dirs(created)
        raise
    clean_stale_temporaries(out)  # a worker that died (its pieces ran again here) left its temporary behind
    return {key: path for key, (path, _) in staged.items()}


def _unlink(paths: Iterable[Path]) -> None:
    for p in paths:
        with contextlib.suppress(OSError):
            p.unlink()
