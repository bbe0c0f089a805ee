"""Adaptive exposure for a polarization camera over heliostat mirrors (paper section 2).

The paper's drone runs "an adaptive exposure algorithm ... in real time to
ensure the captured images are not overexposed in different angles and
lighting conditions". A saturated pixel has no polarization (pihim masks it:
:func:`pihim.camera.polar_image`), so the controller here puts a **hard upper
constraint** on the bright end of the histogram and only a soft wish on the
middle:

1. **Statistics** (:func:`region_stats`): the histogram of the raw values of
   the region of interest (the mirror pixels when they are known, else the
   whole frame), dark level subtracted and normalised by the full scale:
   ``p_hi``, the 99.9th percentile; the median; the fraction of pixels at
   the saturation level.
2. **Decision** (:func:`next_exposure`), a pure function of the statistics,
   the current settings, the parameters and a small state:

   * while the last command has not reached the sensor yet
     (``latency_frames``: a GenICam camera applies a new ``ExposureTime``
     one or two frames later), hold: frames still taken with the old settings
     say nothing about the new ones. This is the simplest dead-time
     compensation, acting only on measurements of the commanded settings
     (compare the Smith predictor [3]_, which predicts instead);
   * **clipped** (the percentile at the saturation level: its true value is
     unknown): divide by ``clipped_step`` when the median is clipped too, else
     bring the median to the target, at least halving;
   * **over the limit** (``p_hi > limit``, 0.85 of full scale by default):
     scale down so that ``p_hi`` lands on ``aim`` (0.75), in one step;
   * otherwise scale up toward the smaller of ``aim / p_hi`` (the constraint
     with its margin) and ``median_target / median`` (the soft target),
     **damped in log space**: only ``damping`` of the log error is corrected
     per step, so noise in the statistics does not make the loop ring;
   * an increase smaller than ``deadband`` (10 %) is not made, and nothing
     is done while ``p_hi`` lies between ``aim`` and ``limit``: together a
     hysteresis band, so that a converged loop does not hunt on noise.
3. **Actuation, exposure before gain**: the wanted brightness (exposure time
   times linear gain) is met with exposure time up to its cap, and only the
   rest with analog gain, because gain amplifies the read noise with the
   signal while a longer exposure collects more photo-electrons (EMVA 1288
   noise model [1]_). The cap is the smaller of the camera's maximum and the
   motion-blur limit at the drone's speed (:func:`motion_blur_exposure_cap_us`,
   after [2]_).

Log-domain exposure control with a histogram target follows the automatic
exposure literature for machine vision ([4]_, [5]_); the saturation-first
rule is what polarimetry needs (a clipped channel biases DoLP and AoP).

References
----------
.. [1] EMVA Standard 1288, "Standard for Characterization of Image Sensors
   and Cameras", release 4.0 (2021): the linear camera model, read noise
   referred to the input scaled by the system gain.
.. [2] J. O'Connor, M. J. Smith, M. R. James, "Cameras and settings for aerial
   surveys in the geosciences: optimising image data", Progress in Physical
   Geography 41(3), 325-344 (2017): motion blur of a moving camera, ground
   speed times exposure over the ground sample distance.
.. [3] O. J. M. Smith, "Closer control of loops with dead time", Chemical
   Engineering Progress 53(5), 217-219 (1957).
.. [4] T. Kuno, H. Sugiura, N. Matoba, "A new automatic exposure system for
   digital still cameras", IEEE Trans. Consumer Electronics 44(1), 192-199
   (1998).
.. [5] Z. Zhang, C. Forster, D. Scaramuzza, "Active exposure control for
   robust visual odometry in HDR environments", IEEE ICRA 2017, 3894-3901.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pihim._inputs import finite_number
from pihim.errors import PihimInputError

__all__ = [
    "ExposureDecision",
    "ExposureParams",
    "ExposureSettings",
    "ExposureState",
    "RegionStats",
    "motion_blur_exposure_cap_us",
    "next_exposure",
    "region_stats",
]


@dataclass(frozen=True)
class ExposureSettings:
    """Exposure time and analog gain of a camera.

    Attributes
    ----------
    exposure_us : float
        Exposure time, microseconds (> 0).
    gain_db : float
        Analog gain, dB (>= 0); the signal is multiplied by ``10**(gain_db / 20)``.
    """

    exposure_us: float
    gain_db: float = 0.0

    def __post_init__(self) -> None:
        t = finite_number(self.exposure_us, "exposure time")
        g = finite_number(self.gain_db, "gain")
        if t <= 0:
            raise PihimInputError(f"exposure time must be > 0 us, got {self.exposure_us!r}")
        if g < 0:
            raise PihimInputError(f"gain must be >= 0 dB, got {self.gain_db!r}")
        object.__setattr__(self, "exposure_us", t)
        object.__setattr__(self, "gain_db", g)

    @property
    def gain_linear(self) -> float:
        """Signal multiplier of the gain, ``10**(gain_db / 20)``."""
        return 10.0 ** (self.gain_db / 20.0)

    @property
    def brightness(self) -> float:
        """Exposure time times linear gain, microseconds: what the raw signal is proportional to."""
        return self.exposure_us * self.gain_linear

    def to_dict(self) -> dict[str, float]:
        """``{"exposure_us", "gain_db"}``."""
        return {"exposure_us": self.exposure_us, "gain_db": self.gain_db}


@dataclass(frozen=True)
class ExposureParams:
    """Tuning of :func:`next_exposure`.

    Attributes
    ----------
    limit : float
        Hard constraint: the ``percentile`` of the region must stay at or below
        this fraction of full scale (the issue's 0.85).
    aim : float
        Where ``p_hi`` is put after a correction from the bright side, fraction
        of full scale (< ``limit``; the gap is the hysteresis band).
    percentile : float
        Percentile of the region held under ``limit`` (99.9: at most 0.1 % of
        the region may be brighter than ``limit``).
    median_target : float
        Soft target of the region's median, fraction of full scale; yields to
        the constraint.
    damping : float
        Fraction (0, 1] of the log error corrected by an upward step.
    deadband : float
        The frame is left alone while the brightness it asks for is less
        than ``1 + deadband`` times the current one (the soft side; > 0).
    clipped_step : float
        Factor the brightness is divided by when the median itself is clipped.
    latency_frames : int
        Frames between a command and the first frame taken with it (>= 1;
        set it to at least the camera's actuation latency).
    exposure_min_us, exposure_max_us : float
        Exposure range of the camera; ``exposure_max_us`` is also where the
        motion-blur cap goes (:func:`motion_blur_exposure_cap_us`).
    gain_max_db : float
        Largest analog gain the controller may use (0 disables gain).
    """

    limit: float = 0.85
    aim: float = 0.75
    percentile: float = 99.9
    median_target: float = 0.35
    damping: float = 0.7
    deadband: float = 0.10
    clipped_step: float = 8.0
    latency_frames: int = 2
    exposure_min_us: float = 20.0
    exposure_max_us: float = 20_000.0
    gain_max_db: float = 24.0

    def __post_init__(self) -> None:
        for name in ("limit", "aim", "percentile", "median_target", "damping", "deadband", "clipped_step",
                     "exposure_min_us", "exposure_max_us", "gain_max_db"):
            object.__setattr__(self, name, finite_number(getattr(self, name), name))
        if not 0 < self.aim < self.limit <= 1:
            raise PihimInputError(f"need 0 < aim < limit <= 1, got aim {self.aim:g}, limit {self.limit:g}")
        if not 50 <= self.percentile < 100:
            raise PihimInputError(f"percentile must be in [50, 100), got {self.percentile:g}")
        if not 0 < self.median_target < 1:
            raise PihimInputError(f"median_target must be in (0, 1), got {self.median_target:g}")
        if not 0 < self.damping <= 1:
            raise PihimInputError(f"damping must be in (0, 1], got {self.damping:g}")
        if not 0 < self.deadband < 1:
            raise PihimInputError(f"deadband must be in (0, 1), got {self.deadband:g}")
        if self.clipped_step <= 1:
            raise PihimInputError(f"clipped_step must be > 1, got {self.clipped_step:g}")
        lat = self.latency_frames
        if isinstance(lat, bool) or not isinstance(lat, (int, np.integer)) or lat < 1:
            raise PihimInputError(f"latency_frames must be an integer >= 1, got {lat!r}")
        if not 0 < self.exposure_min_us <= self.exposure_max_us:
            raise PihimInputError(f"need 0 < exposure_min_us <= exposure_max_us, got {self.exposure_min_us:g}, "
                                  f"{self.exposure_max_us:g}")
        if self.gain_max_db < 0:
            raise PihimInputError(f"gain_max_db must be >= 0, got {self.gain_max_db:g}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready copy of the parameters."""
        return asdict(self)


# --------------------------------------------------------------------------- statistics


@dataclass(frozen=True)
class RegionStats:
    """Histogram statistics of the region of interest of one raw frame.

    Attributes
    ----------
    count : int
        Raw pixels in the region.
    p_hi_dn, median_dn : float
        The ``percentile`` and the median of the raw values, DN.
    fraction_saturated : float
        Share of the region's pixels at or above ``saturation_level``.
    percentile : float
        Which percentile ``p_hi_dn`` is.
    full_scale, dark_level, saturation_level : float
        DN.
    """

    count: int
    p_hi_dn: float
    median_dn: float
    fraction_saturated: float
    percentile: float
    full_scale: float
    dark_level: float = 0.0
    saturation_level: float | None = None

    def _norm(self, v: float) -> float:
        return (v - self.dark_level) / (self.full_scale - self.dark_level)

    @property
    def p_hi(self) -> float:
        """``p_hi_dn`` above the dark level, as a fraction of the range above it."""
        return self._norm(self.p_hi_dn)

    @property
    def median(self) -> float:
        """The median above the dark level, fraction of the range above it."""
        return self._norm(self.median_dn)

    @property
    def clipped(self) -> bool:
        """Whether ``p_hi`` sits at the saturation level (its true value is unknown)."""
        sat = self.full_scale if self.saturation_level is None else self.saturation_level
        return self.count > 0 and self.p_hi_dn >= sat

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready statistics, raw and normalised."""
        return {
            "count": self.count,
            "percentile": self.percentile,
            "p_hi_dn": self.p_hi_dn,
            "median_dn": self.median_dn,
            "p_hi": self.p_hi if self.count else None,
            "median": self.median if self.count else None,
            "fraction_saturated": self.fraction_saturated,
            "full_scale": self.full_scale,
        }


#: Smallest relative change of brightness that is sent to the camera.
_MIN_CHANGE = 0.01
#: Parallel chunks of the histogram kernel.
_CHUNKS = 8


def _quantile_from_histogram(cum: NDArray[np.int64], q: float) -> float:
    """Smallest bin value ``v`` with at least ``q`` of the counts at or below it (nearest-rank)."""
    total = int(cum[-1])
    rank = max(1, int(math.ceil(q * total)))
    return float(np.searchsorted(cum, rank))


def region_stats(
    raw: NDArray,
    region: NDArray[np.bool_] | None = None,
    *,
    bit_depth: int | None = None,
    dark_level: float = 0.0,
    saturation_level: float | None = None,
    percentile: float = 99.9,
    stride: int = 1,
) -> RegionStats:
    """Histogram statistics of a raw mosaic over a region.

    Parameters
    ----------
    raw : ndarray of uint8 or uint16, shape (H, W)
        Raw DoFP mosaic.
    region : ndarray of bool, shape (H, W) or (H/2, W/2), optional
        Pixels of interest (e.g. the mirrors); a half-size mask is a
        super-pixel mask (each true cell counts its four raw pixels).
        ``None``: the whole frame.
    bit_depth : int, optional
        ADC bits; values above ``2**bit_depth - 1`` are taken as MSB-aligned
        and shifted down. Default: 8 for ``uint8``, 12 for ``uint16``.
    dark_level : float
        Black level, DN (the statistics are normalised above it).
    saturation_level : float, optional
        Raw level counted as saturated; default the full scale.
    percentile : float
        The high percentile to report (99.9 by default).
    stride : int
        Take every ``stride``-th super-pixel row and column (all four raw
        pixels of each; a full-size ``region`` ignores it). 1 counts every
        pixel; 2 a quarter of them, ample for a 5 MP frame.

    Returns
    -------
    RegionStats
        With ``count == 0`` (and zero statistics) for an empty region.
    """
    arr = np.asarray(raw)
    if arr.ndim != 2 or arr.dtype not in (np.uint8, np.uint16):
        raise PihimInputError(f"raw frame must be a 2-D uint8 or uint16 array, got {arr.dtype} {arr.shape}")
    bits = (8 if arr.dtype == np.uint8 else 12) if bit_depth is None else int(bit_depth)
    container = 8 * arr.itemsize
    if not 1 <= bits <= container:
        raise PihimInputError(f"bit depth {bits} does not fit {arr.dtype}")
    full = 2**bits - 1
    shift = 0
    if bits < container and arr.size and int(arr.max()) > full:
        shift = container - bits  # MSB-aligned data
    sat = float(full if saturation_level is None else saturation_level)
    if not 0 <= dark_level < full:
        raise PihimInputError(f"dark level must be in [0, {full}), got {dark_level:g}")
    if not 0.0 <= percentile <= 100.0:  # (NaN fails too) 150 reported a level above full scale
        raise PihimInputError(f"percentile must be in [0, 100], got {percentile!r}")
    from pihim.live import _kernels

    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise PihimInputError(f"stride must be an integer >= 1, got {stride!r}")
    hist = np.zeros(full + 1, dtype=np.int64)
    h, w = arr.shape
    if h % 2 or w % 2:
        raise PihimInputError(f"raw mosaic sides must be even, got {w}x{h}")
    if region is None:
        _kernels.histogram_rows(arr, shift, np.zeros((1, 1), np.bool_), False, int(stride), full + 1, _CHUNKS, hist)
    else:
        mask = np.asarray(region, dtype=np.bool_)
        if mask.shape == (h // 2, w // 2):
            _kernels.histogram_rows(arr, shift, mask, True, int(stride), full + 1, _CHUNKS, hist)
        elif mask.shape == arr.shape:
            _kernels.histogram_masked(arr, shift, mask, 1, full + 1, hist)
        else:
            raise PihimInputError(f"region mask of shape {mask.shape} fits neither the frame {arr.shape} "
                                  f"nor its super-pixels")
    cum = np.cumsum(hist)
    count = int(cum[-1])
    if count == 0:
        return RegionStats(0, 0.0, 0.0, 0.0, percentile, float(full), float(dark_level), sat)
    p_hi = _quantile_from_histogram(cum, percentile / 100.0)
    median = _quantile_from_histogram(cum, 0.5)
    n_sat = int(hist[int(math.ceil(sat)):].sum()) if sat <= full else 0
    return RegionStats(count, p_hi, median, n_sat / count, percentile, float(full), float(dark_level), sat)


# --------------------------------------------------------------------------- decision


@dataclass(frozen=True)
class ExposureState:
    """What :func:`next_exposure` carries from one frame to the next.

    Attributes
    ----------
    hold_frames : int
        Frames still to wait before the last command shows in a frame.
    """

    hold_frames: int = 0


@dataclass(frozen=True)
class ExposureDecision:
    """The outcome of one :func:`next_exposure` call.

    Attributes
    ----------
    settings : ExposureSettings
        Settings to command (equal to the current ones when nothing changes).
    state : ExposureState
        State for the next call.
    changed : bool
        Whether a new command is to be sent.
    reason : str
        ``"hold"``, ``"empty region"``, ``"clipped"``, ``"over limit"``,
        ``"brighten"``, ``"in band"`` or ``"at range limit"``.
    requested_scale : float
        Brightness factor the rule asked for, before the camera's range
        limits (1 when holding).
    """

    settings: ExposureSettings
    state: ExposureState
    changed: bool
    reason: str
    requested_scale: float = 1.0


def _allocate(brightness_us: float, params: ExposureParams, cap_us: float) -> ExposureSettings:
    """Exposure first (up to ``cap_us``), the rest as gain (up to ``gain_max_db``)."""
    t = min(max(brightness_us, params.exposure_min_us), cap_us)
    g_lin = min(max(brightness_us / t, 1.0), 10.0 ** (params.gain_max_db / 20.0))
    g_db = 20.0 * math.log10(g_lin)
    return ExposureSettings(t, 0.0 if g_db < 1e-9 else g_db)


def next_exposure(
    stats: RegionStats,
    current: ExposureSettings,
    params: ExposureParams = ExposureParams(),
    state: ExposureState = ExposureState(),
    *,
    exposure_cap_us: float | None = None,
) -> ExposureDecision:
    """The exposure and gain to command after a frame (see the module notes for the rule).

    Parameters
    ----------
    stats : RegionStats
        Statistics of the frame just taken (:func:`region_stats`).
    current : ExposureSettings
        The settings last commanded (the frame was taken with them unless a
        command is still under way, which ``state`` knows).
    params : ExposureParams
    state : ExposureState
        From the previous call (a fresh state for the first frame).
    exposure_cap_us : float, optional
        Extra cap on the exposure time, e.g. the motion-blur limit
        (:func:`motion_blur_exposure_cap_us`); the smaller of it and
        ``params.exposure_max_us`` applies.

    Returns
    -------
    ExposureDecision
    """
    # (NaN fails too) a cap of -5 us commanded the minimum exposure at full gain
    if exposure_cap_us is not None and not exposure_cap_us > 0:
        raise PihimInputError(f"exposure_cap_us must be a positive number of microseconds, got {exposure_cap_us!r}")
    if state.hold_frames > 0:
        return ExposureDecision(current, ExposureState(state.hold_frames - 1), False, "hold")
    if stats.count == 0:
        return ExposureDecision(current, state, False, "empty region")
    cap = params.exposure_max_us if exposure_cap_us is None else min(params.exposure_max_us, exposure_cap_us)
    cap = max(cap, params.exposure_min_us)
    p_hi, median = stats.p_hi, stats.median
    if stats.clipped:
        sat = stats.full_scale if stats.saturation_level is None else stats.saturation_level
        if stats.median_dn >= sat or median <= 0:
            scale, reason = 1.0 / params.clipped_step, "clipped"
        else:
            scale, reason = min(0.5, params.median_target / median), "clipped"
    elif p_hi > params.limit:
        scale, reason = params.aim / p_hi, "over limit"
    else:
        want = params.aim / p_hi if p_hi > 0 else math.inf
        if median > 0:
            want = min(want, params.median_target / median)
        if not math.isfinite(want):  # a black frame: open up by the largest step
            want = params.clipped_step
        if want <= 1.0 + params.deadband:
            return ExposureDecision(current, state, False, "in band")
        scale, reason = math.exp(params.damping * math.log(want)), "brighten"
    new = _allocate(current.brightness * scale, params, cap)
    if abs(math.log(new.brightness / current.brightness)) < math.log1p(_MIN_CHANGE):
        return ExposureDecision(current, state, False, "at range limit", scale)
    return ExposureDecision(new, ExposureState(params.latency_frames - 1), True, reason, scale)


def motion_blur_exposure_cap_us(
    speed_m_s: float,
    range_m: float,
    *,
    focal_length_mm: float = 35.0,
    pixel_pitch_um: float = 3.45,
    max_blur_px: float = 1.0,
    angular_rate_deg_s: float = 0.0,
) -> float:
    """Longest exposure that keeps the motion blur under ``max_blur_px`` pixels.

    A camera moving at ``speed_m_s`` across a scene at ``range_m`` sweeps the
    image at ``v f / (R p)`` pixels per second, and turning at ``omega`` adds
    ``omega f / p`` (small angles; [2]_ in the module notes). The cap is
    ``max_blur_px`` divided by the sum.

    Parameters
    ----------
    speed_m_s : float
        Speed across the line of sight, m/s (>= 0).
    range_m : float
        Distance to the mirrors, m (> 0).
    focal_length_mm, pixel_pitch_um : float
        Lens and sensor (defaults: the paper's 35 mm Kowa on the Triton, 3.45 um).
    max_blur_px : float
        Blur allowed, raw pixels (> 0). A DoFP super-pixel is 2 raw pixels wide.
    angular_rate_deg_s : float
        Attitude rate of the gimbal or airframe, deg/s (>= 0).

    Returns
    -------
    float
        Microseconds; ``inf`` for a still camera.

    Examples
    --------
    5 m/s at 30 m with the Triton and a 35 mm lens: the ground sample distance
    is 2.96 mm, so one pixel of blur takes 591 us.

    >>> round(motion_blur_exposure_cap_us(5.0, 30.0))
    591
    """
    v = finite_number(speed_m_s, "speed")
    r = finite_number(range_m, "range")
    f = finite_number(focal_length_mm, "focal length") * 1e-3
    p = finite_number(pixel_pitch_um, "pixel pitch") * 1e-6
    b = finite_number(max_blur_px, "max blur")
    w = math.radians(finite_number(angular_rate_deg_s, "angular rate"))
    if v < 0 or w < 0:
        raise PihimInputError("speed and angular rate must be >= 0")
    if r <= 0 or f <= 0 or p <= 0 or b <= 0:
        raise PihimInputError("range, focal length, pixel pitch and max blur must be > 0")
    px_per_s = v * f / (r * p) + w * f / p
    return math.inf if px_per_s == 0 else 1e6 * b / px_per_s
