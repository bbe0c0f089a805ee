"""Forward model of a DoFP sensor: a full-resolution Stokes field to a raw mosaic.

Every pixel sees the Stokes vector of the scene at that pixel through the
analyser row of its own micro-polarizer channel; the result is offset by the
dark level, optionally given shot and read noise, clipped to full scale and
quantised. This is the ground-truth generator of the test suite and the demo.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.camera.layout import IMX250MZR, MosaicLayout, check_mosaic_shape
from pihim.errors import PihimInputError
from pihim.polarimetry.analyser import AnalyserMatrix


def mosaic_from_stokes(
    s0: ArrayLike,
    s1: ArrayLike,
    s2: ArrayLike,
    layout: MosaicLayout = IMX250MZR,
    analyser: AnalyserMatrix | None = None,
    *,
    bit_depth: int | None = 12,
    dark_level: float = 0.0,
    read_noise_dn: float = 0.0,
    electrons_per_dn: float | None = None,
    rng: np.random.Generator | int | None = None,
) -> NDArray:
    """Render the raw mosaic a DoFP sensor records for a given Stokes field.

    Parameters
    ----------
    s0, s1, s2 : array_like, shape (H, W)
        Scene Stokes field at full sensor resolution, in digital numbers (DN):
        unpolarized light of ``S0`` gives ``S0 / 2`` DN per ideal pixel.
    layout : MosaicLayout
        Micro-polarizer arrangement (default IMX250MZR).
    analyser : AnalyserMatrix, optional
        Per-channel response; ideal if omitted.
    bit_depth : int or None
        ADC bits. The output is rounded, clipped to ``[0, 2**bit_depth - 1]``
        and returned as ``uint8`` (<= 8 bits) or ``uint16``. ``None`` returns
        the noiseless-quantisation-free float64 mosaic.
    dark_level : float
        Offset added to every pixel, in DN.
    read_noise_dn : float
        Standard deviation of additive Gaussian read noise, in DN.
    electrons_per_dn : float, optional
        Conversion gain; when given, photon shot noise (Poisson in electrons)
        is applied before the read noise.
    rng : numpy.random.Generator or int, optional
        Random source for the noise (seed for reproducibility).

    Returns
    -------
    numpy.ndarray, shape (H, W)
        The raw mosaic.
    """
    s0, s1, s2 = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (s0, s1, s2)))
    check_mosaic_shape(s0)
    a = (analyser or AnalyserMatrix.ideal()).matrix
    ch = layout.channel_map(s0.shape)
    img = a[ch, 0] * s0 + a[ch, 1] * s1 + a[ch, 2] * s2
    gen = np.random.default_rng(rng)
    if electrons_per_dn is not None:
        if electrons_per_dn <= 0:
            raise PihimInputError("electrons_per_dn must be > 0")
        img = gen.poisson(np.clip(img, 0, None) * electrons_per_dn) / electrons_per_dn
    if read_noise_dn > 0:
        img = img + gen.normal(0.0, read_noise_dn, img.shape)
    img = img + dark_level
    if bit_depth is None:
        return img
    if not 1 <= bit_depth <= 16:
        raise PihimInputError(f"bit_depth must be in 1..16, got {bit_depth}")
    full = 2**bit_depth - 1
    dtype = np.uint8 if bit_depth <= 8 else np.uint16
    return np.clip(np.rint(img), 0, full).astype(dtype)
