"""``pihim calibrate-polarizer`` (stub: being implemented)."""

from __future__ import annotations


def calibrate_polarizer() -> None:
    """Estimate the analyser matrix from frames behind a linear polarizer."""
    raise NotImplementedError
