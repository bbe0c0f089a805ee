"""Polarimetry: Stokes parameters, DoLP, AoP, analyser matrices and frames.

Conventions (see ``docs/conventions.md``): angles in degrees at the API,
AoP in [0, 180), S1 > 0 means the electric field lies along the reference
axis, S2 > 0 means it lies 45 deg counter-clockwise from it when looking into
the beam.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pihim._lazy import lazy_exports

#: Exported names by submodule; a submodule is imported when one of its names is first used.
_EXPORTS: dict[str, list[str]] = {
    "analyser": ["AnalyserMatrix"],
    "stokes": [
        "aop_deg", "aop_difference_deg", "aop_raw_difference_deg", "dolp", "rotate_reference_deg",
        "stokes_from_dolp_aop",
    ],
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static checkers see the names where they are defined
    from pihim.polarimetry.analyser import AnalyserMatrix  # noqa: F401
    from pihim.polarimetry.stokes import (  # noqa: F401
        aop_deg, aop_difference_deg, aop_raw_difference_deg, dolp, rotate_reference_deg, stokes_from_dolp_aop,
    )
