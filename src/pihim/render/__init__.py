"""Synthetic polarimetric frames with known ground truth."""

from pihim.render.mosaic import mosaic_from_stokes
from pihim.render.scenes import edge_scene, uniform_scene

__all__ = ["edge_scene", "mosaic_from_stokes", "uniform_scene"]
