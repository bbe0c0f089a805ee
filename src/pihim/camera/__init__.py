"""Division-of-focal-plane polarization camera: layouts, frames, demosaicing, calibration."""

from pihim.camera.layout import IMX250MZR, MosaicLayout
from pihim.camera.pipeline import BitDepth, PolarImage, polar_image

__all__ = ["IMX250MZR", "BitDepth", "MosaicLayout", "PolarImage", "polar_image"]
