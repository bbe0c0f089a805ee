"""The 2x2 micro-polarizer mosaic layout of a DoFP sensor.

A layout gives, for each position of the 2x2 super-pixel (row, column), the
nominal transmission-axis angle of the micro-polarizer there, expressed in the
*displayed image* frame: degrees counter-clockwise from image right (toward
image up). The Sony IMX250MZR (Lucid Triton TRI050S-PC) default is::

    row 0:  90  45
    row 1: 135   0

Region-of-interest offsets and reversed read-out change both which angle sits
where and, for reversal, the handedness of the angles (a mirrored image turns
a 45 deg polarizer into a 135 deg one). :meth:`MosaicLayout.from_sensor`
derives the effective layout from the camera settings.

References
----------
.. [1] Sony Semiconductor Solutions, IMX250MZR/MYR polarization image sensor
   product information (2x2 on-chip polarizer arrangement).
.. [2] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone", section 2 and Fig. 1d.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pihim.errors import PihimInputError
from pihim.polarimetry.analyser import NOMINAL_ANGLES_DEG

_VALID = frozenset(int(a) for a in NOMINAL_ANGLES_DEG)
_NAMED = {"imx250mzr": ((90, 45), (135, 0)), "default": ((90, 45), (135, 0))}


def _whole_degrees(a: object) -> int:
    """``a`` as an int if it is a whole number (45, 45.0, numpy ints); ValueError otherwise (0.7, inf, nan)."""
    v = float(a)  # type: ignore[arg-type]
    if not math.isfinite(v) or v != round(v):
        raise ValueError(f"{a!r} is not a whole number of degrees")
    return int(v)


def _mirror_angle(a: int) -> int:
    """Transmission angle after mirroring the image about a vertical or horizontal axis."""
    return (180 - a) % 180


@dataclass(frozen=True)
class MosaicLayout:
    """Nominal polarizer angles (degrees) at the four super-pixel positions.

    Parameters
    ----------
    angles_deg : ((int, int), (int, int))
        ``angles_deg[row][col]`` for row, col in {0, 1}; a permutation of
        0, 45, 90, 135.
    """

    angles_deg: tuple[tuple[int, int], tuple[int, int]] = ((90, 45), (135, 0))

    def __post_init__(self) -> None:
        try:
            grid = tuple(tuple(_whole_degrees(a) for a in row) for row in self.angles_deg)
        except (TypeError, ValueError, OverflowError):
            raise PihimInputError(f"layout must be 2x2 angles, got {self.angles_deg!r}") from None
        flat = [a for row in grid for a in row]
        if len(grid) != 2 or any(len(r) != 2 for r in grid) or sorted(flat) != sorted(_VALID):
            raise PihimInputError(
                f"layout must place 0, 45, 90 and 135 once each in a 2x2 grid, got {self.angles_deg!r}"
            )
        object.__setattr__(self, "angles_deg", grid)

    # -- construction -----------------------------------------------------------
    @classmethod
    def parse(cls, text: str) -> MosaicLayout:
        """Parse ``"imx250mzr"`` or four row-major angles such as ``"90,45,135,0"``."""
        key = text.strip().lower()
        if key in _NAMED:
            return cls(_NAMED[key])
        parts = [p for p in key.replace(";", ",").replace(" ", ",").split(",") if p]
        try:
            nums = [float(p) for p in parts]
        except ValueError:
            nums = []
        if len(nums) != 4:
            raise PihimInputError(
                f"unknown layout {text!r}: give a name ({', '.join(sorted(_NAMED))}) "
                "or four row-major angles like 90,45,135,0"
            )
        if not all(math.isfinite(v) and v == round(v) for v in nums):
            raise PihimInputError(
                f"layout {text!r}: the angles must be the whole degrees 0, 45, 90 and 135 (row-major), "
                "e.g. 90,45,135,0"
            )
        vals = [int(v) for v in nums]
        return cls(((vals[0], vals[1]), (vals[2], vals[3])))

    @classmethod
    def from_sensor(
        cls,
        base: MosaicLayout | None = None,
        *,
        offset_x: int = 0,
        offset_y: int = 0,
        reverse_x: bool = False,
        reverse_y: bool = False,
    ) -> MosaicLayout:
        """Effective layout of an image read with an ROI offset and/or reversed axes.

        The ROI offset (in sensor pixels) is applied first, then the read-out
        reversal, as on Lucid/GenICam cameras (``OffsetX``/``OffsetY``,
        ``ReverseX``/``ReverseY``). Image width and height are assumed even.
        """
        lay = (base or cls()).shifted(offset_y, offset_x)
        if reverse_x:
            lay = lay.reversed_x()
        if reverse_y:
            lay = lay.reversed_y()
        return lay

    def shifted(self, row_offset: int, col_offset: int) -> MosaicLayout:
        """Layout of a crop starting at (``row_offset``, ``col_offset``) of this layout."""
        g = self.angles_deg
        return MosaicLayout(
            tuple(
                tuple(g[(r + row_offset) % 2][(c + col_offset) % 2] for c in range(2))
                for r in range(2)
            )  # type: ignore[arg-type]
        )

    def reversed_x(self) -> MosaicLayout:
        """Layout after mirroring the image left-right (columns reversed)."""
        g = self.angles_deg
        return MosaicLayout(
            tuple(tuple(_mirror_angle(g[r][1 - c]) for c in range(2)) for r in range(2))  # type: ignore[arg-type]
        )

    def reversed_y(self) -> MosaicLayout:
        """Layout after mirroring the image top-bottom (rows reversed)."""
        g = self.angles_deg
        return MosaicLayout(
            tuple(tuple(_mirror_angle(g[1 - r][c]) for c in range(2)) for r in range(2))  # type: ignore[arg-type]
        )

    # -- queries --------------------------------------------------------------------
    @property
    def channel_positions(self) -> tuple[tuple[int, int], ...]:
        """(row, col) in the super-pixel of each channel, channel order 0/45/90/135."""
        where = {a: (r, c) for r, row in enumerate(self.angles_deg) for c, a in enumerate(row)}
        return tuple(where[int(a)] for a in NOMINAL_ANGLES_DEG)

    def angle_map(self, shape: tuple[int, int]) -> NDArray[np.int16]:
        """Full-size map of the nominal angle (degrees) at every pixel."""
        h, w = shape
        tile = np.array(self.angles_deg, dtype=np.int16)
        return np.tile(tile, ((h + 1) // 2, (w + 1) // 2))[:h, :w]

    def channel_map(self, shape: tuple[int, int]) -> NDArray[np.int8]:
        """Full-size map of the channel index (0..3 for 0/45/90/135 deg) at every pixel."""
        return (self.angle_map(shape) // 45).astype(np.int8)

    def split(self, mosaic: NDArray) -> NDArray:
        """Split a raw mosaic into its four channels, shape ``(4, H/2, W/2)``.

        Returned channels are views in order 0, 45, 90, 135 deg.
        """
        check_mosaic_shape(mosaic)
        return np.stack([mosaic[r::2, c::2] for r, c in self.channel_positions])

    def merge(self, channels: NDArray) -> NDArray:
        """Inverse of :meth:`split`: interleave ``(4, h, w)`` channels into an ``(2h, 2w)`` mosaic."""
        channels = np.asarray(channels)
        if channels.ndim != 3 or channels.shape[0] != 4:
            raise PihimInputError(f"expected channels of shape (4, h, w), got {channels.shape}")
        _, h, w = channels.shape
        out = np.empty((2 * h, 2 * w), dtype=channels.dtype)
        for k, (r, c) in enumerate(self.channel_positions):
            out[r::2, c::2] = channels[k]
        return out

    def __str__(self) -> str:
        return ",".join(str(a) for row in self.angles_deg for a in row)


IMX250MZR = MosaicLayout(((90, 45), (135, 0)))


def check_mosaic_shape(mosaic: NDArray) -> None:
    """Raise :class:`PihimInputError` unless ``mosaic`` is 2-D with even, non-zero sides."""
    shape = np.shape(mosaic)
    if len(shape) != 2:
        raise PihimInputError(f"raw mosaic must be a 2-D array, got shape {shape}")
    h, w = shape
    if h < 2 or w < 2 or h % 2 or w % 2:
        raise PihimInputError(f"raw mosaic sides must be even and >= 2, got {w}x{h} (WxH)")
