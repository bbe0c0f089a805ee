"""Sensor half of the polarimetric renderer: a Stokes image to a raw 12-bit mosaic.

A scene Stokes field in arbitrary radiance units is turned into the raw
division-of-focal-plane mosaic the camera records in three steps:

1. optional Gaussian lens blur of ``S0``, ``S1`` and ``S2`` (linear in the
   Stokes parameters, so it is applied before the polarizers);
2. an exposure: one gain (DN of ``S0`` per scene unit) chosen by
   :func:`choose_exposure` so that a bright percentile of the brightest
   channel lands just under full scale;
3. the mosaic forward model :func:`pihim.render.mosaic.mosaic_from_stokes`
   with the noise figures of :class:`SensorModel` (photon shot noise, read
   noise, dark level, clipping and quantisation).

Noise model. The datasheet figures are read as EMVA 1288 quantities: the
maximum signal-to-noise ratio is that of a pixel at saturation, shot-noise
limited, ``SNR_max = sqrt(N_sat)`` so that ``N_sat = 10**(SNR_dB / 10)``
electrons; the dynamic range is ``N_sat / sigma_read`` so that ``sigma_read
= N_sat / 10**(DR_dB / 20)`` electrons. The saturation capacity is mapped to
full scale minus the dark level. With the defaults (39 dB, 71 dB, 12 bit) that
is 7943 e- of full well, 2.24 e- of read noise and 1.94 e-/DN.

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone", section 2 (Lucid Triton TRI050S-PC, Sony IMX250MZR:
   "dynamic range of 71 dB, a signal-to-noise ratio of 39 dB", 12-bit).
.. [2] LUCID Vision Labs, Triton TRI050S-P polarization camera datasheet
   (IMX250MZR; max. SNR 39 dB, dynamic range 71 dB, 12-bit ADC).
.. [3] European Machine Vision Association, "EMVA Standard 1288: Standard
   for Characterization of Image Sensors and Cameras", release 4.0 (2021):
   saturation capacity, maximum SNR and dynamic range.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import gaussian_filter

from pihim.camera.layout import IMX250MZR, MosaicLayout, check_mosaic_shape
from pihim._inputs import finite_number
from pihim.errors import PihimInputError
from pihim.polarimetry.analyser import AnalyserMatrix
from pihim.render.mosaic import mosaic_from_stokes

__all__ = ["Exposure", "SensorModel", "choose_exposure", "expose", "lens_blur"]


@dataclass(frozen=True)
class SensorModel:
    """Radiometric model of a 12-bit DoFP camera (defaults: Lucid Triton TRI050S-PC).

    Parameters
    ----------
    bit_depth : int
        ADC bits, 1..16 (default 12: full scale 4095 DN).
    snr_db : float
        Maximum signal-to-noise ratio in dB, i.e. that of a pixel at full
        well, shot-noise limited: ``N_sat = 10**(snr_db / 10)`` electrons
        (default 39 dB, paper section 2).
    dynamic_range_db : float
        Full well over read noise in dB, ``20 log10(N_sat / sigma_read)``
        (default 71 dB, paper section 2).
    dark_level_dn : float
        Black-level offset added to every pixel, in DN, ``0 <= dark <
        full scale``; full well maps to full scale minus this offset.
    analyser : AnalyserMatrix, optional
        Per-channel response; the ideal analyser if ``None`` (the attribute
        always holds a matrix after construction).
    layout : MosaicLayout
        Micro-polarizer arrangement (default IMX250MZR).

    Examples
    --------
    >>> s = SensorModel()
    >>> round(s.full_well_e), round(s.read_noise_e, 2), round(s.electrons_per_dn, 3)
    (7943, 2.24, 1.94)
    """

    bit_depth: int = 12
    snr_db: float = 39.0
    dynamic_range_db: float = 71.0
    dark_level_dn: float = 0.0
    analyser: AnalyserMatrix | None = None
    layout: MosaicLayout = IMX250MZR

    def __post_init__(self) -> None:
        bits = self.bit_depth
        if isinstance(bits, bool) or not isinstance(bits, (int, np.integer)) or not 1 <= bits <= 16:
            raise PihimInputError(f"bit_depth must be an integer in 1..16, got {bits!r}")
        snr = finite_number(self.snr_db, "snr_db")
        dr = finite_number(self.dynamic_range_db, "dynamic_range_db")
        dark = finite_number(self.dark_level_dn, "dark_level_dn")
        if snr <= 0:
            raise PihimInputError(f"snr_db must be > 0, got {self.snr_db!r}")
        if dr <= 0:
            raise PihimInputError(f"dynamic_range_db must be > 0, got {self.dynamic_range_db!r}")
        full = 2 ** int(bits) - 1
        if not 0 <= dark < full:
            raise PihimInputError(
                f"dark_level_dn must be in [0, {full}) for {bits} bits, got {self.dark_level_dn!r}"
            )
        analyser = AnalyserMatrix.ideal() if self.analyser is None else self.analyser
        if not isinstance(analyser, AnalyserMatrix):
            raise PihimInputError(f"analyser must be an AnalyserMatrix or None, got {type(analyser).__name__}")
        if not isinstance(self.layout, MosaicLayout):
            raise PihimInputError(f"layout must be a MosaicLayout, got {type(self.layout).__name__}")
        object.__setattr__(self, "bit_depth", int(bits))
        object.__setattr__(self, "snr_db", snr)
        object.__setattr__(self, "dynamic_range_db", dr)
        object.__setattr__(self, "dark_level_dn", dark)
        object.__setattr__(self, "analyser", analyser)

    @property
    def full_scale_dn(self) -> int:
        """Largest raw value, ``2**bit_depth - 1`` DN."""
        return 2**self.bit_depth - 1

    @property
    def full_well_e(self) -> float:
        """Saturation capacity in electrons, ``10**(snr_db / 10)``."""
        return 10.0 ** (self.snr_db / 10.0)

    @property
    def read_noise_e(self) -> float:
        """Temporal dark (read) noise in electrons, ``full_well_e / 10**(dynamic_range_db / 20)``."""
        return self.full_well_e / 10.0 ** (self.dynamic_range_db / 20.0)

    @property
    def electrons_per_dn(self) -> float:
        """Conversion gain in e-/DN: full well spans full scale minus the dark level."""
        return self.full_well_e / (self.full_scale_dn - self.dark_level_dn)

    @property
    def read_noise_dn(self) -> float:
        """Read noise in DN (before quantisation, which adds 1/12 DN^2 of variance)."""
        return self.read_noise_e / self.electrons_per_dn

    def describe(self) -> dict[str, Any]:
        """JSON-ready summary of the parameters and the derived noise figures."""
        assert self.analyser is not None  # set in __post_init__
        return {
            "bit_depth": self.bit_depth,
            "full_scale_dn": self.full_scale_dn,
            "snr_db": self.snr_db,
            "dynamic_range_db": self.dynamic_range_db,
            "dark_level_dn": self.dark_level_dn,
            "full_well_e": self.full_well_e,
            "read_noise_e": self.read_noise_e,
            "electrons_per_dn": self.electrons_per_dn,
            "read_noise_dn": self.read_noise_dn,
            "layout": str(self.layout),
            "analyser": self.analyser.to_dict(),
        }


@dataclass(frozen=True)
class Exposure:
    """A global exposure: scene units to DN.

    Parameters
    ----------
    gain_dn : float
        DN of ``S0`` per scene radiance unit (> 0): unpolarized light of
        scene intensity ``L`` gives ``gain_dn * L / 2`` DN above the dark
        level on an ideal pixel.
    reference : float, optional
        The scene value that was mapped: the chosen percentile of the
        brightest-channel response, in scene units.
    percentile : float, optional
        Percentile (0..100] used for ``reference``.
    headroom : float, optional
        Fraction of (full scale - dark level) that ``reference`` was mapped
        to; above 1 clips on purpose.
    clipped_fraction : float, optional
        Fraction of raw pixels at full scale after this exposure, noise-free.

    The optional fields are ``None`` for an exposure set by hand.
    """

    gain_dn: float
    reference: float | None = None
    percentile: float | None = None
    headroom: float | None = None
    clipped_fraction: float | None = None

    def __post_init__(self) -> None:
        g = finite_number(self.gain_dn, "gain_dn")
        if g <= 0:
            raise PihimInputError(f"gain_dn must be > 0, got {self.gain_dn!r}")
        object.__setattr__(self, "gain_dn", g)
        for name in ("reference", "percentile", "headroom", "clipped_fraction"):
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, finite_number(v, name))
        for name, hi in (("percentile", 100.0), ("clipped_fraction", 1.0)):
            v = getattr(self, name)
            if v is not None and not 0.0 <= v <= hi:
                raise PihimInputError(f"{name} must be in [0, {hi:g}], got {v!r}")

    def describe(self) -> dict[str, Any]:
        """JSON-ready summary."""
        return {
            "gain_dn": self.gain_dn,
            "reference": self.reference,
            "percentile": self.percentile,
            "headroom": self.headroom,
            "clipped_fraction": self.clipped_fraction,
        }


def _stokes_arrays(s0: ArrayLike, s1: ArrayLike, s2: ArrayLike) -> tuple[NDArray, NDArray, NDArray]:
    try:
        arrs = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (s0, s1, s2)))
    except (TypeError, ValueError) as exc:
        raise PihimInputError(f"S0, S1, S2 must be numeric arrays of one shape ({exc})") from None
    check_mosaic_shape(arrs[0])
    return arrs[0], arrs[1], arrs[2]


def _brightest_channel(sensor: SensorModel, s0: NDArray, s1: NDArray, s2: NDArray) -> NDArray:
    """Noise-free ``max_k A_k . (S0, S1, S2)`` per pixel, in the units of S."""
    assert sensor.analyser is not None
    a = sensor.analyser.matrix
    out = a[0, 0] * s0 + a[0, 1] * s1 + a[0, 2] * s2
    for k in range(1, 4):
        np.maximum(out, a[k, 0] * s0 + a[k, 1] * s1 + a[k, 2] * s2, out=out)
    return out


def lens_blur(
    s0: ArrayLike, s1: ArrayLike, s2: ArrayLike, sigma_px: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Gaussian point-spread function applied to each Stokes image.

    Incoherent imaging is linear in intensity and therefore in each Stokes
    parameter, so blurring ``S0``, ``S1`` and ``S2`` separately is exact for
    a polarization-independent lens.

    Parameters
    ----------
    s0, s1, s2 : array_like, shape (H, W)
        Stokes images (finite).
    sigma_px : float
        Standard deviation of the PSF in pixels, >= 0; 0 returns copies.
        Borders are mirrored (the mean of a uniform field is preserved); the
        kernel is truncated at 4 sigma.

    Returns
    -------
    s0, s1, s2 : numpy.ndarray, float64
    """
    sigma = finite_number(sigma_px, "blur_sigma_px")
    if sigma < 0:
        raise PihimInputError(f"blur_sigma_px must be >= 0, got {sigma_px!r}")
    arrs = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (s0, s1, s2)))
    if sigma == 0:
        return arrs[0].copy(), arrs[1].copy(), arrs[2].copy()
    b0, b1, b2 = (gaussian_filter(x, sigma, mode="reflect", truncate=4.0) for x in arrs)
    return b0, b1, b2


def choose_exposure(
    s0: ArrayLike,
    s1: ArrayLike,
    s2: ArrayLike,
    sensor: SensorModel,
    *,
    mask: ArrayLike | None = None,
    percentile: float = 99.9,
    headroom: float = 0.9,
) -> Exposure:
    """Pick the gain that puts a bright percentile of the scene just under full scale.

    The brightest-channel response of each pixel, ``r = max_k A_k . (S0, S1,
    S2)`` (noise-free, ``A`` the sensor's analyser), is computed; the gain
    maps the ``percentile``-th percentile of ``r`` over the selected pixels to
    ``headroom * (full scale - dark level)`` DN above the dark level. For the
    ideal analyser ``r = (S0 + sqrt(S1**2 + S2**2)) / 2``.

    Parameters
    ----------
    s0, s1, s2 : array_like, shape (H, W)
        Scene Stokes field in scene radiance units (even sides).
    sensor : SensorModel
    mask : array_like of bool, shape (H, W), optional
        Pixels to expose for (e.g. the mirrors); every selected pixel must be
        finite. Default: all finite pixels.
    percentile : float
        In (0, 100]; linear interpolation between order statistics
        (:func:`numpy.percentile`).
    headroom : float
        > 0; values above 1 clip the brightest pixels on purpose.

    Returns
    -------
    Exposure
        With ``clipped_fraction`` the fraction of the (finite) raw pixels
        that sit at full scale, noise-free, without lens blur.

    Raises
    ------
    PihimInputError
        Bad parameters, an empty selection, or one whose percentile response
        is not positive ("nothing bright enough to expose for").
    """
    if not isinstance(sensor, SensorModel):
        raise PihimInputError(f"sensor must be a SensorModel, got {type(sensor).__name__}")
    p = finite_number(percentile, "percentile")
    if not 0 < p <= 100:
        raise PihimInputError(f"percentile must be in (0, 100], got {percentile!r}")
    h = finite_number(headroom, "headroom")
    if h <= 0:
        raise PihimInputError(f"headroom must be > 0, got {headroom!r}")
    s0a, s1a, s2a = _stokes_arrays(s0, s1, s2)
    finite = np.isfinite(s0a) & np.isfinite(s1a) & np.isfinite(s2a)
    if mask is None:
        sel = finite
    else:
        m = np.asarray(mask)
        if m.shape != s0a.shape:
            raise PihimInputError(f"mask shape {m.shape} does not match the Stokes shape {s0a.shape}")
        sel = m.astype(bool)
        if np.any(sel & ~finite):
            raise PihimInputError(f"mask selects {int(np.sum(sel & ~finite))} non-finite Stokes pixels")
    with np.errstate(invalid="ignore"):
        resp = _brightest_channel(sensor, s0a, s1a, s2a)
    if not np.any(sel):
        raise PihimInputError("nothing bright enough to expose for: the selection is empty")
    ref = float(np.percentile(resp[sel], p))
    if not ref > 0:
        raise PihimInputError(
            f"nothing bright enough to expose for: the {p:g}th-percentile channel response is {ref:g}"
        )
    span = sensor.full_scale_dn - sensor.dark_level_dn
    gain = h * span / ref
    # noise-free raw value of every pixel through its own channel
    assert sensor.analyser is not None
    a = sensor.analyser.matrix
    ch = sensor.layout.channel_map(s0a.shape)
    with np.errstate(invalid="ignore"):
        raw = gain * (a[ch, 0] * s0a + a[ch, 1] * s1a + a[ch, 2] * s2a) + sensor.dark_level_dn
        clipped = np.rint(raw[finite]) >= sensor.full_scale_dn
    frac = float(np.mean(clipped)) if clipped.size else 0.0
    return Exposure(gain_dn=gain, reference=ref, percentile=p, headroom=h, clipped_fraction=frac)


def expose(
    s0: ArrayLike,
    s1: ArrayLike,
    s2: ArrayLike,
    sensor: SensorModel,
    exposure: Exposure,
    *,
    blur_sigma_px: float = 0.0,
    rng: np.random.Generator | int | None = None,
    noise: bool = True,
) -> NDArray[np.uint16]:
    """Render the raw mosaic the sensor records for a scene Stokes field.

    Parameters
    ----------
    s0, s1, s2 : array_like, shape (H, W)
        Scene Stokes field in scene radiance units, finite, even sides.
    sensor : SensorModel
    exposure : Exposure
        ``gain_dn`` scales scene units to DN of ``S0``.
    blur_sigma_px : float
        Gaussian lens PSF sigma in pixels, applied to S0, S1, S2 before the
        polarizers (see :func:`lens_blur`); 0 means none.
    rng : numpy.random.Generator or int, optional
        Noise source; the same integer seed gives identical bytes.
    noise : bool
        ``False`` renders the noise-free mosaic (still clipped and quantised).

    Returns
    -------
    numpy.ndarray of uint16, shape (H, W)
        Raw DN in ``[0, 2**bit_depth - 1]``; pixels whose channel response is
        negative (non-physical Stokes) read the dark level minus read noise.

    Raises
    ------
    PihimInputError
        Non-finite Stokes values, bad shapes or a negative blur sigma.
    """
    if not isinstance(sensor, SensorModel):
        raise PihimInputError(f"sensor must be a SensorModel, got {type(sensor).__name__}")
    if not isinstance(exposure, Exposure):
        raise PihimInputError(f"exposure must be an Exposure, got {type(exposure).__name__}")
    s0a, s1a, s2a = _stokes_arrays(s0, s1, s2)
    bad = ~(np.isfinite(s0a) & np.isfinite(s1a) & np.isfinite(s2a))
    if np.any(bad):
        raise PihimInputError(f"Stokes field has {int(bad.sum())} non-finite pixels (NaN or inf)")
    b0, b1, b2 = lens_blur(s0a, s1a, s2a, blur_sigma_px)
    g = exposure.gain_dn
    raw = mosaic_from_stokes(
        g * b0,
        g * b1,
        g * b2,
        layout=sensor.layout,
        analyser=sensor.analyser,
        bit_depth=sensor.bit_depth,
        dark_level=sensor.dark_level_dn,
        read_noise_dn=sensor.read_noise_dn if noise else 0.0,
        electrons_per_dn=sensor.electrons_per_dn if noise else None,
        rng=rng,
    )
    return raw.astype(np.uint16, copy=False)
