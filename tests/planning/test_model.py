"""The plan's records (pihim.planning.model)."""

from __future__ import annotations

import dataclasses
import inspect

import pytest

from pihim.planning import model
from pihim.planning.model import Waypoint, replace_fields

RECORDS = [c for _, c in inspect.getmembers(model, inspect.isclass)
           if dataclasses.is_dataclass(c) and c.__module__ == model.__name__]


def test_replace_fields_is_dataclasses_replace():
    """The route's fast copy equals dataclasses.replace, and leaves the original alone."""
    w = Waypoint(1.0, 2.0, 3.0, 34.9, -106.5, 1700.0, 90.0, -30.0, 2.0, "scan", True, "5E3")
    for changes in ({"speed_m_s": 0.7}, {"kind": "run_past", "heading_deg": 270.0}, {}):
        new = replace_fields(w, **changes)
        assert new == dataclasses.replace(w, **changes) and type(new) is Waypoint
        assert new is not w
    assert w.speed_m_s == 2.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        replace_fields(w, speed_m_s=1.0).speed_m_s = 3.0  # type: ignore[misc]


@pytest.mark.parametrize("record", RECORDS, ids=lambda c: c.__name__)
def test_records_do_not_validate_in_init(record):
    """replace_fields skips __init__: valid only while no record of the module checks its fields there."""
    assert not hasattr(record, "__post_init__")
    assert record.__dataclass_params__.frozen


@pytest.mark.parametrize(("deg", "want"), [(-1e-14, 0.0), (0.0, 0.0), (359.5, 359.5), (360.0, 0.0), (-90.0, 270.0),
                                          (725.0, 5.0)])
def test_heading_0_360_never_gives_360(deg, want):
    """``x % 360.0`` is 360.0 for a heading of -1e-14 deg; the plan's schema wants [0, 360)."""
    assert deg % 360.0 == 360.0 or deg != -1e-14  # the case the helper exists for
    assert model.heading_0_360(deg) == want


def test_a_home_waypoint_a_hair_west_of_north_faces_0_not_360():
    from pihim.field import nsttf_like_field
    from pihim.field.geodesy import NSTTF_ORIGIN_LATITUDE_DEG, NSTTF_ORIGIN_LONGITUDE_DEG
    from pihim.planning.ufacet import home_waypoint

    origin = (NSTTF_ORIGIN_LATITUDE_DEG, NSTTF_ORIGIN_LONGITUDE_DEG, 1700.0)
    w = home_waypoint(nsttf_like_field(), origin=origin, heading_deg=-1e-14)
    assert w.heading_deg == 0.0
