"""pihim: Polarimetric Imaging Heliostat Inspection Method toolkit.

Sub-packages follow the physical and pipeline concepts of the method:

``pihim.polarimetry``
    Stokes vectors, DoLP/AoP, analyser matrices, reference-frame rotations.
``pihim.camera``
    Division-of-focal-plane sensor: mosaic layouts, raw frame readers,
    demosaicing, polarizer calibration and the frame-to-Stokes pipeline.
``pihim.render``
    Synthetic polarimetric frames with known ground truth.

Public functions take and return degrees; see ``docs/conventions.md``.
"""

from pihim.errors import PihimInputError

__version__ = "0.1.0"

__all__ = ["PihimInputError", "__version__"]
