"""Demosaicing of DoFP mosaics into per-channel intensity images (numpy routes).

Two routes are offered by the pipeline:

``superpixel``
    Each 2x2 super-pixel gives one Stokes sample (half resolution, no
    interpolation, no inter-channel mixing beyond the 2x2 cell).
``full``
    Full-resolution interpolation, see :func:`full_resolution`.

:func:`bilinear` is the classical per-channel bilinear interpolation, kept
as the reference that the full-resolution route is measured against.
The functions here are the readable definitions; the pipeline uses fused
numba kernels that the tests compare with them.

Channel order is always 0, 45, 90, 135 deg.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from pihim.camera.layout import IMX250MZR, MosaicLayout, check_mosaic_shape

_BILINEAR_KERNEL = np.array([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]]) / 4.0


def superpixel(mosaic: NDArray, layout: MosaicLayout = IMX250MZR) -> NDArray[np.float64]:
    """Channel intensities per super-pixel, shape ``(4, H/2, W/2)``."""
    return layout.split(np.asarray(mosaic)).astype(np.float64)


def bilinear(mosaic: NDArray, layout: MosaicLayout = IMX250MZR) -> NDArray[np.float64]:
    """Per-channel bilinear interpolation to full resolution, shape ``(4, H, W)``.

    Each channel is known on a quarter of the pixels (a period-2 lattice); the
    missing values are averages of the 2 or 4 nearest samples of the same
    channel. Borders are mirrored without repeating the edge pixel, which
    keeps the period-2 lattice intact.

    References
    ----------
    .. [1] S. Gao, V. Gruev, "Bilinear and bicubic interpolation methods for
       division of focal plane polarimeters", Opt. Express 19(27), 26161-26173
       (2011), doi:10.1364/OE.19.026161.
    """
    m = np.asarray(mosaic, dtype=np.float64)
    check_mosaic_shape(m)
    out = np.empty((4, *m.shape))
    ch = layout.channel_map(m.shape)
    for k in range(4):
        sparse = np.where(ch == k, m, 0.0)
        out[k] = cv2.filter2D(sparse, -1, _BILINEAR_KERNEL, borderType=cv2.BORDER_REFLECT_101)
    return out
