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

import os

from pihim.errors import PihimInputError

# numba's OpenMP threading layer otherwise keeps its worker threads spinning after every parallel
# kernel: on a shared or busy machine (and beside pihim's own reader and writer threads) they burn
# CPU that other work needs, e.g. 7.8 ms of CPU for a 2 ms selection pass. A value set by the user wins;
# it must be set before the first parallel kernel runs, hence here.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"

__all__ = ["PihimInputError", "__version__"]
