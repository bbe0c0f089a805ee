"""Reading the sensor entries of a frame's ``log`` (shared by the estimators and the commands)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pihim.errors import PihimInputError


def sensor_entries(log: Mapping[str, Any]) -> tuple[Mapping[str, Any], Mapping[str, Any]]:
    """``(log["sensor"], log["sensor"]["model"])``, each ``{}`` when absent.

    Raises
    ------
    PihimInputError
        Either is present but not an object.
    """
    sensor = log.get("sensor")
    sensor = {} if sensor is None else sensor
    if not isinstance(sensor, Mapping):
        raise PihimInputError(f"log 'sensor' must be an object, got {type(sensor).__name__}")
    model = sensor.get("model")
    model = {} if model is None else model
    if not isinstance(model, Mapping):
        raise PihimInputError(f"log 'sensor.model' must be an object, got {type(model).__name__}")
    return sensor, model
