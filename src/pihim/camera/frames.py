"""Readers for raw DoFP mosaic frames (TIFF, PNG, Lucid ``.raw`` buffers).

(Stub: being implemented; the interface below is fixed.)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class RawFrame:
    """A raw mosaic read from disk.

    Attributes
    ----------
    data : numpy.ndarray
        2-D ``uint8`` or ``uint16`` mosaic with even sides.
    bit_depth : int or None
        ADC bits when the file format states it (e.g. 12 for
        PolarizeMono12p), else None (let the pipeline decide).
    pixel_format : str
        What was read, e.g. ``"tiff"``, ``"png"``, ``"PolarizeMono12p"``.
    path : pathlib.Path or None
    """

    data: NDArray[np.uint8] | NDArray[np.uint16]
    bit_depth: int | None
    pixel_format: str
    path: Path | None = None


def read_frame(
    path: str | Path,
    *,
    width: int | None = None,
    height: int | None = None,
    pixel_format: str | None = None,
) -> RawFrame:
    """Read one raw mosaic frame; raises PihimInputError on any bad input."""
    raise NotImplementedError
