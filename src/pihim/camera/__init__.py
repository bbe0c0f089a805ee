"""Division-of-focal-plane polarization camera: layouts, frames, demosaicing, calibration, camera model and pose."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pihim._lazy import lazy_exports

#: Exported names by submodule; a submodule is imported when one of its names is first used.
_EXPORTS: dict[str, list[str]] = {
    "layout": ["IMX250MZR", "MosaicLayout"],
    "model": ["CameraModel", "camera_for_size"],
    "pipeline": ["BitDepth", "PolarImage", "polar_image"],
    "pose": ["CameraPose", "pixel_rays_world", "project_points"],
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static checkers see the names where they are defined
    from pihim.camera.layout import IMX250MZR, MosaicLayout  # noqa: F401
    from pihim.camera.model import CameraModel, camera_for_size  # noqa: F401
    from pihim.camera.pipeline import BitDepth, PolarImage, polar_image  # noqa: F401
    from pihim.camera.pose import CameraPose, pixel_rays_world, project_points  # noqa: F401
