"""``QGC WPL 110`` plain-text mission files (``mission.waypoints``).

The de-facto plain-text mission format read by QGroundControl, Mission
Planner, MAVProxy and pymavlink [1]_: a first line ``QGC WPL 110``, then one
tab-separated line per mission item::

    INDEX  CURRENT  FRAME  COMMAND  P1  P2  P3  P4  LAT  LON  ALT  AUTOCONTINUE

Index 0 is the home position (``MAV_CMD_NAV_WAYPOINT`` in ``MAV_FRAME_GLOBAL``
with its altitude above mean sea level, ``CURRENT`` = 1): QGroundControl reads
row 0 of a version-110 file as the planned home position and ArduPilot keeps
home in mission slot 0. Rows 1.. are exactly the items of the ``.plan`` file
(:func:`pihim.planning.export.qgc.mission_items`, same options, same frames
and altitudes).

Numbers: latitude and longitude of coordinate commands with 10 decimals
(0.1 mm), other values with 8. The text format has no way to say "unset":
parameters that are NaN in the ``.plan`` file (``null`` there: the reserved
parameters 5-7 of ``MAV_CMD_IMAGE_START_CAPTURE`` and the pitch/yaw rates of
``MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW``) are written as ``0``, which every
reader parses; ArduPilot and PX4 act on the gimbal angles when they are
given, so a zero rate there does not change what the mission does.

References
----------
.. [1] MAVLink Developer Guide, "File Formats: Mission Plain-Text File
   Format", https://mavlink.io/en/file_formats/; QGroundControl
   ``MissionController::_loadTextMissionFile`` and ``MissionItem::load``
   (12 tab-separated fields per row; version 110 carries home in row 0).
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

from pihim.planning.export._common import write_export
from pihim.planning.export.qgc import (
    MAV_CMD_NAV_WAYPOINT,
    MAV_FRAME_GLOBAL,
    Mission,
    MissionItem,
    mission_items,
)
from pihim.planning.model import Plan

__all__ = ["WPL_HEADER", "wpl_text", "write_wpl"]

#: First line of the file.
WPL_HEADER = "QGC WPL 110"


#: A parameter cell that printed as zero ("0.00000000", "-0.0000000000"): the file writes it "0".
_ZERO_CELL = re.compile(r"(?<=\t)-?0\.0+(?=\t)")
_CELLS = {xy: ("{:.8f}\t{:.8f}\t{:.8f}\t{:.8f}\t{:.%df}\t{:.%df}\t{:.8f}" % (xy, xy)).format for xy in (8, 10)}


def _row(index: int, current: int, item: MissionItem) -> str:
    """One line: index, current, frame, command, the seven parameters (NaN as 0; 10 decimals for latitude and
    longitude of items with a position, else 8) and autocontinue; zero cells are fixed by :data:`_ZERO_CELL`."""
    p = item.params if all(map(math.isfinite, item.params)) else tuple(
        v if math.isfinite(v) else 0.0 for v in item.params)
    cells = _CELLS[10 if item.specifies_coordinate else 8](*p)
    return f"{index}\t{current}\t{item.frame}\t{item.command}\t{cells}\t{1 if item.autocontinue else 0}"


def wpl_text(plan: Plan, **mission_options: Any) -> str:
    """The ``QGC WPL 110`` file text (see :func:`write_wpl`)."""
    return wpl_mission_text(mission_items(plan, **mission_options))


def wpl_mission_text(mission: Mission) -> str:
    """The ``QGC WPL 110`` text of ``mission`` (see :func:`write_wpl`)."""
    lat, lon, amsl = mission.home
    home = MissionItem(MAV_CMD_NAV_WAYPOINT, MAV_FRAME_GLOBAL, (0.0, 0.0, 0.0, 0.0, lat, lon, amsl))
    lines = [WPL_HEADER, _row(0, 1, home)]
    lines += [_row(k, 0, it) for k, it in enumerate(mission.items, start=1)]
    return _ZERO_CELL.sub("0", "\n".join(lines) + "\n")


def write_wpl(plan: Plan, path: str | Path, **mission_options: Any) -> Path:
    """Write a ``QGC WPL 110`` mission file atomically.

    Parameters
    ----------
    plan : Plan
    path : str or path-like
        Output file, conventionally ``mission.waypoints``.
    **mission_options
        Passed to :func:`pihim.planning.export.qgc.mission_items`
        (``flight``, ``autopilot``, ``altitude_frame``, ``camera``, ...).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    PihimInputError
        Invalid plan or option; no file is written.
    """
    text = wpl_text(plan, **mission_options)
    return write_export(path, text, newline="\n")
