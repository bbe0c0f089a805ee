"""Division-of-focal-plane polarization camera: layouts, frames, demosaicing, calibration, camera model and pose."""

from pihim.camera.layout import IMX250MZR, MosaicLayout
from pihim.camera.model import CameraModel
from pihim.camera.pipeline import BitDepth, PolarImage, polar_image
from pihim.camera.pose import CameraPose, pixel_rays_world, project_points

__all__ = [
    "IMX250MZR",
    "BitDepth",
    "CameraModel",
    "CameraPose",
    "MosaicLayout",
    "PolarImage",
    "pixel_rays_world",
    "polar_image",
    "project_points",
]
