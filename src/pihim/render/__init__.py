"""Synthetic polarimetric frames with known ground truth."""

from pihim.render.mosaic import mosaic_from_stokes

__all__ = ["mosaic_from_stokes"]
