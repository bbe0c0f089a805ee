"""Synthetic polarimetric frames with known ground truth."""

from pihim.render.mosaic import mosaic_from_stokes
from pihim.render.scenes import edge_scene, uniform_scene
from pihim.render.sensor import Exposure, SensorModel, choose_exposure, expose

__all__ = [
    "Exposure",
    "SensorModel",
    "choose_exposure",
    "edge_scene",
    "expose",
    "mosaic_from_stokes",
    "uniform_scene",
]
