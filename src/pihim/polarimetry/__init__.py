"""Polarimetry: Stokes parameters, DoLP, AoP, analyser matrices and frames.

Conventions (see ``docs/conventions.md``): angles in degrees at the API,
AoP in [0, 180), S1 > 0 means the electric field lies along the reference
axis, S2 > 0 means it lies 45 deg counter-clockwise from it when looking into
the beam.
"""

from pihim.polarimetry.analyser import AnalyserMatrix
from pihim.polarimetry.stokes import (
    aop_deg,
    aop_difference_deg,
    aop_raw_difference_deg,
    dolp,
    rotate_reference_deg,
    stokes_from_dolp_aop,
)

__all__ = [
    "AnalyserMatrix",
    "aop_deg",
    "aop_difference_deg",
    "aop_raw_difference_deg",
    "dolp",
    "rotate_reference_deg",
    "stokes_from_dolp_aop",
]
