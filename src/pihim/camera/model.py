"""Pinhole camera model of the inspection camera (intrinsics and field of view)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pihim.errors import PihimInputError


@dataclass(frozen=True)
class CameraModel:
    """A pinhole camera: sensor size, pixel pitch and lens focal length.

    Defaults: Lucid Triton TRI050S-PC (Sony IMX250MZR, 2448 x 2048 px,
    3.45 um pixels) with the paper's 35 mm Kowa lens (paper section 2).
    Camera axes follow OpenCV: x right, y down, z forward.
    """

    width_px: int = 2448
    height_px: int = 2048
    pixel_size_um: float = 3.45
    focal_length_mm: float = 35.0
    name: str = "Lucid Triton TRI050S-PC + 35 mm"

    def __post_init__(self) -> None:
        if self.width_px < 2 or self.height_px < 2:
            raise PihimInputError("camera sensor must be at least 2x2 pixels")
        if not (self.pixel_size_um > 0 and self.focal_length_mm > 0):
            raise PihimInputError("pixel size and focal length must be positive")

    @property
    def focal_length_px(self) -> float:
        """Focal length in pixels."""
        return self.focal_length_mm * 1000.0 / self.pixel_size_um

    @property
    def horizontal_fov_deg(self) -> float:
        """Full horizontal field of view, deg."""
        return math.degrees(2.0 * math.atan(0.5 * self.width_px / self.focal_length_px))

    @property
    def vertical_fov_deg(self) -> float:
        """Full vertical field of view, deg."""
        return math.degrees(2.0 * math.atan(0.5 * self.height_px / self.focal_length_px))

    def intrinsics(self) -> NDArray[np.float64]:
        """OpenCV camera matrix K (principal point at the sensor centre)."""
        f = self.focal_length_px
        return np.array([[f, 0.0, (self.width_px - 1) / 2.0], [0.0, f, (self.height_px - 1) / 2.0], [0.0, 0.0, 1.0]])

    def ground_sample_distance_m(self, range_m: float) -> float:
        """Size of one pixel at ``range_m`` metres, m."""
        return range_m * self.pixel_size_um * 1e-6 / (self.focal_length_mm * 1e-3)
