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
        and returned as ``uint8`` (<= 8 bits) or ``uint16``; the Stokes field
        must then be finite. ``None`` returns the float64 mosaic before
        quantisation (noise included if asked for).
    dark_level : float
        Offset added to every pixel, in DN (finite, >= 0).
    read_noise_dn : float
        Standard deviation of additive Gaussian read noise, in DN (finite, >= 0).
    electrons_per_dn : float, optional
        Conversion gain; when given, photon shot noise (Poisson in electrons)
        is applied before the read noise.
    rng : numpy.random.Generator or int, optional
        Random source for the noise (seed for reproducibility).

    Returns
    -------
    numpy.ndarray, shape (H, W)
        The raw mosaic.

    Raises
    ------
    PihimInputError
        A shape no mosaic has, a layout that is not a :class:`MosaicLayout`,
        a bit depth outside 1..16, a negative or non-finite dark level, read
        noise or conversion gain, non-finite Stokes values to be quantised.
    """
    s0, s1, s2 = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (s0, s1, s2)))
    check_mosaic_shape(s0)
    if not isinstance(layout, MosaicLayout):
        raise PihimInputError(f"layout must be a MosaicLayout (MosaicLayout.parse('imx250mzr')), got {layout!r}")
    if bit_depth is not None and (isinstance(bit_depth, bool) or not isinstance(bit_depth, (int, np.integer))):
        raise PihimInputError(f"bit_depth must be an integer in 1..16 or None, got {bit_depth!r}")
    for name, value in (("dark_level", dark_level), ("read_noise_dn", read_noise_dn)):
        if not (np.isfinite(value) and value >= 0):
            raise PihimInputError(f"{name} must be a finite number >= 0 DN, got {value!r}")
    if bit_depth is not None and not all(np.all(np.isfinite(x)) for x in (s0, s1, s2)):
        raise PihimInputError("s0, s1 and s2 must be finite to be quantised (a NaN became a 0 DN pixel); "
                              "bit_depth=None keeps the float mosaic")
    a = (analyser or AnalyserMatrix.ideal()).matrix
    ch = layout.channel_map(s0.shape)
    img = a[ch, 0] * s0 + a[ch, 1] * s1 + a[ch, 2] * s2
    gen = np.random.default_rng(rng)
    if electrons_per_dn is not None:
        if not (np.isfinite(electrons_per_dn) and electrons_per_dn > 0):
            raise PihimInputError(f"electrons_per_dn must be a finite number > 0, got {electrons_per_dn!r}")
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
