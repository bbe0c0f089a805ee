"""Data model of a polarimetric inspection flight plan.

A :class:`Plan` holds scan passes (straight lines flown at constant altitude
and heading), each imaging a sequence of heliostat-under-assessment (HUA) /
target pairs from planned waypoints, and the flights the passes are split
into by battery endurance. Positions are field ENU metres and WGS84
(latitude, longitude, ellipsoidal height); headings are degrees clockwise
from North; gimbal pitch is degrees, negative below the horizon.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal

WaypointKind = Literal["takeoff", "transit", "lead_in", "scan", "run_past", "return", "land"]
PLAN_SCHEMA_ID = "pihim.plan/1"

# Plan.to_dict: values copied as they are, and the field names of each dataclass met (dataclasses.fields is slow)
_PLAIN_SCALARS = frozenset({str, int, float, bool, type(None)})
_FIELD_NAMES: dict[type, tuple[str, ...]] = {}


def heading_0_360(deg: float) -> float:
    """A heading folded into [0, 360) degrees (``x % 360.0`` alone gives 360.0 for ``x = -1e-14``)."""
    h = float(deg) % 360.0
    return 0.0 if h >= 360.0 else h


def replace_fields(record: Any, **changes: Any) -> Any:
    """``dataclasses.replace(record, **changes)`` for the records of this module, without running ``__init__``.

    None of them validates in ``__init__`` (they are plain frozen records), so
    the copy is the same; it is about ten times faster, which counts where the
    route re-times every candidate flight (a new :class:`Waypoint` per slowed
    leg). ``changes`` must name fields (not checked: internal use).
    """
    new = object.__new__(type(record))
    new.__dict__.update(record.__dict__, **changes)
    return new


@dataclass(frozen=True)
class Waypoint:
    """One planned drone position and camera attitude.

    Attributes
    ----------
    x_m, y_m, z_m : float
        Field ENU position, metres (z above the field origin).
    latitude_deg, longitude_deg, height_m : float
        WGS84 geodetic position; ``height_m`` is ellipsoidal.
    heading_deg : float
        Drone (and camera) heading, deg clockwise from North, in [0, 360).
    gimbal_pitch_deg : float
        Camera pitch, deg; 0 = horizontal, -90 = straight down.
    speed_m_s : float
        Ground speed toward this waypoint.
    kind : str
        Role in the flight (``scan`` waypoints image a HUA).
    capture : bool
        Take an image here.
    hua : str or None
        The heliostat under assessment imaged here (scan waypoints).
    """

    x_m: float
    y_m: float
    z_m: float
    latitude_deg: float
    longitude_deg: float
    height_m: float
    heading_deg: float
    gimbal_pitch_deg: float
    speed_m_s: float
    kind: WaypointKind = "scan"
    capture: bool = False
    hua: str | None = None


@dataclass(frozen=True)
class PairPrediction:
    """Predicted polarimetric contrast of one planned image of a HUA-target pair.

    ``None`` values mean the scenario does not arise for this image (for
    example the HUA shows no ground, so there is no ground-vs-ground edge).
    """

    hua: str
    target: str
    waypoint_index: int
    reflection_dolp: float | None
    sky_dolp_difference: float | None
    ground_aop_difference_deg: float | None
    ground_aop_raw_difference_deg: float | None
    reflection_dolp_ok: bool
    sky_vs_sky_ok: bool
    ground_vs_ground_ok: bool

    @property
    def usable(self) -> bool:
        """The paper's criteria: reflection DoLP > 0.2 and at least one scenario usable."""
        return self.reflection_dolp_ok and (self.sky_vs_sky_ok or self.ground_vs_ground_ok)


@dataclass(frozen=True)
class PassShift:
    """How a pass was moved from its nominal geometry to raise contrast, and the gain."""

    altitude_delta_m: float = 0.0
    lateral_offset_m: float = 0.0
    gaze_delta_deg: float = 0.0
    usable_fraction_before: float = 0.0
    usable_fraction_after: float = 0.0


@dataclass(frozen=True)
class ScanPass:
    """A straight scan line imaging HUA-target pairs.

    Attributes
    ----------
    index : int
        Order within the plan (boustrophedon order).
    azimuth_deg : float
        Direction of travel, deg clockwise from North.
    altitude_m : float
        Flight altitude, metres above the field origin.
    gimbal_pitch_deg : float
        Nominal camera pitch along the pass.
    pairs : tuple of (str, str)
        (HUA, target) pairs imaged, in flight order.
    waypoints : tuple of Waypoint
        Lead-in, scan and run-past waypoints.
    predictions : tuple of PairPrediction
    feasible : bool
        False if any constraint fails; ``issues`` says which.
    issues : tuple of str
        Human-readable constraint violations or warnings for this pass.
    shift : PassShift or None
        Contrast-driven adjustment applied, if any.
    """

    index: int
    azimuth_deg: float
    altitude_m: float
    gimbal_pitch_deg: float
    pairs: tuple[tuple[str, str], ...]
    waypoints: tuple[Waypoint, ...]
    predictions: tuple[PairPrediction, ...] = ()
    feasible: bool = True
    issues: tuple[str, ...] = ()
    shift: PassShift | None = None

    @property
    def heliostats(self) -> tuple[str, ...]:
        """Every heliostat involved (HUAs and targets), first appearance order."""
        seen: dict[str, None] = {}
        for h, t in self.pairs:
            seen.setdefault(h)
            seen.setdefault(t)
        return tuple(seen)

    @property
    def usable_fraction(self) -> float:
        """Fraction of predicted images meeting the paper's criteria."""
        if not self.predictions:
            return 0.0
        return sum(p.usable for p in self.predictions) / len(self.predictions)


@dataclass(frozen=True)
class Flight:
    """One battery's worth of passes, from take-off to landing."""

    index: int
    pass_indices: tuple[int, ...]
    waypoints: tuple[Waypoint, ...]
    duration_s: float
    distance_m: float
    heliostats_assessed: int


@dataclass(frozen=True)
class Plan:
    """A complete inspection plan for one instant."""

    time_iso: str
    site: dict[str, Any]
    sun: dict[str, Any]
    aim_point: tuple[float, float, float]
    min_altitude_m: float
    max_altitude_m: float
    camera: dict[str, Any]
    home: Waypoint
    passes: tuple[ScanPass, ...]
    flights: tuple[Flight, ...] = ()
    summary: dict[str, Any] = field(default_factory=dict)

    def to_dict(self, *, finite: bool = False) -> dict[str, Any]:
        """JSON-ready nested dictionaries (schema ``pihim.plan/1``).

        With ``finite``, non-finite floats become None and numpy scalars
        Python numbers (what ``plan.json`` holds; JSON has no NaN).
        """

        kept = _PLAIN_SCALARS - {float} if finite else _PLAIN_SCALARS  # values copied as they are

        def conv(obj: Any) -> Any:
            kind = type(obj)
            if kind is float and finite:
                return obj if math.isfinite(obj) else None
            if kind in _PLAIN_SCALARS:
                return obj
            if kind is dict:  # the summary: about a million values for a 10,000-heliostat plan's facet report
                return {k: v if type(v) in kept else conv(v) for k, v in obj.items()}
            if kind is list or kind is tuple:
                return [x if type(x) in kept else conv(x) for x in obj]
            names = _FIELD_NAMES.get(kind)
            if names is None and dataclasses.is_dataclass(obj) and not isinstance(obj, type):
                names = _FIELD_NAMES.setdefault(kind, tuple(f.name for f in dataclasses.fields(obj)))
            if names is not None:
                d = {name: v if type(v := getattr(obj, name)) in kept else conv(v) for name in names}
                if kind is Waypoint and d["heading_deg"] == 360.0:  # a heading of a hair below 0 folded by `%`:
                    d["heading_deg"] = 0.0  # written as the schema's [0, 360) wants (the exporters fold it too)
                if isinstance(obj, ScanPass):
                    d["heliostats"] = list(obj.heliostats)
                    d["usable_fraction"] = conv(obj.usable_fraction)
                if isinstance(obj, PairPrediction):
                    d["usable"] = obj.usable
                return d
            if isinstance(obj, (list, tuple)):
                return [conv(x) for x in obj]
            if isinstance(obj, dict):
                return {k: conv(v) for k, v in obj.items()}
            if finite and isinstance(obj, float):
                return float(obj) if math.isfinite(obj) else None
            if finite and hasattr(obj, "item") and callable(obj.item) and getattr(obj, "ndim", None) == 0:
                return conv(obj.item())  # numpy scalar
            return obj

        return {"schema": PLAN_SCHEMA_ID, **conv(self)}
