"""A simulated camera: a linear, noisy, clipping sensor with exposure, gain and actuation latency.

It closes the adaptive-exposure loop without hardware (the closed-loop tests
and the synthetic live source): the scene is a per-pixel signal rate in DN
per microsecond of exposure at 0 dB (for a DoFP mosaic, the rate already
includes each pixel's micro-polarizer, e.g. from
:func:`pihim.render.mosaic.mosaic_from_stokes` divided by an exposure). A
frame records

``raw = clip(round(dark + g * (x + n)), 0, full_scale)``, ``x = rate * t * b``

with ``t`` the exposure in microseconds, ``g`` the linear gain, ``b`` the
scene brightness of that frame (a sun behind a cloud, a turn toward the
sun) and ``n`` Gaussian noise with the variance of shot noise (``x /
electrons_per_dn``) plus read noise, the EMVA 1288 linear model with its
noise referred to the input. Settings requested with :meth:`request` reach
the sensor ``latency_frames`` frames later, as on GenICam cameras whose
``ExposureTime`` applies to a frame one or two after the write.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError
from pihim.live.exposure import ExposureSettings

#: Length of the table of standard normal deviates the noise is read from (a prime, so that
#: its period is not a multiple of any frame width).
NOISE_TABLE_SIZE = 1_000_003


@dataclass(frozen=True)
class SensorNoise:
    """Noise and range of the simulated sensor (defaults: the Triton of :class:`pihim.render.sensor.SensorModel`).

    Attributes
    ----------
    bit_depth : int
    dark_level_dn : float
    electrons_per_dn : float
        Conversion gain at 0 dB; shot-noise variance is ``x / electrons_per_dn`` DN^2.
    read_noise_dn : float
        At 0 dB, DN.
    """

    bit_depth: int = 12
    dark_level_dn: float = 0.0
    electrons_per_dn: float = 1.94
    read_noise_dn: float = 1.15

    @property
    def full_scale(self) -> int:
        """``2**bit_depth - 1``."""
        return 2**self.bit_depth - 1


class SimulatedCamera:
    """Linear sensor over a fixed scene with exposure, gain and actuation latency.

    Parameters
    ----------
    rate : array_like, shape (H, W) or larger
        Signal rate, DN per microsecond at 0 dB, per raw pixel. May be larger
        than the frame (``frame_shape``): :meth:`capture` then reads a window
        at an offset, as a moving camera.
    settings : ExposureSettings
        Initial exposure and gain (already applied).
    latency_frames : int
        Frames between :meth:`request` and the first frame taken with the new
        settings (>= 1: the next frame at best).
    noise : SensorNoise
    frame_shape : (int, int), optional
        Even (rows, columns) of a frame; default the shape of ``rate``.
    seed : int
        Seed of the noise table.
    exposure_range_us : (float, float)
        Exposure the camera accepts; requests are clipped to it.
    gain_max_db : float
        Largest gain the camera accepts.
    """

    def __init__(
        self,
        rate: ArrayLike,
        settings: ExposureSettings = ExposureSettings(1000.0),
        *,
        latency_frames: int = 2,
        noise: SensorNoise = SensorNoise(),
        frame_shape: tuple[int, int] | None = None,
        seed: int = 0,
        exposure_range_us: tuple[float, float] = (15.0, 1_000_000.0),
        gain_max_db: float = 48.0,
    ) -> None:
        r = np.ascontiguousarray(rate, dtype=np.float32)
        if r.ndim != 2 or not np.all(np.isfinite(r)) or (r.size and r.min() < 0):
            raise PihimInputError("scene rate must be a finite, non-negative 2-D array")
        shape = r.shape if frame_shape is None else (int(frame_shape[0]), int(frame_shape[1]))
        if shape[0] < 2 or shape[1] < 2 or shape[0] % 2 or shape[1] % 2 or shape[0] > r.shape[0] \
                or shape[1] > r.shape[1]:
            raise PihimInputError(f"frame shape {shape} must be even and fit the scene {r.shape}")
        if isinstance(latency_frames, bool) or int(latency_frames) < 1:
            raise PihimInputError(f"latency_frames must be an integer >= 1, got {latency_frames!r}")
        self.rate = r
        self.frame_shape = shape
        self.noise = noise
        self.latency_frames = int(latency_frames)
        self.exposure_range_us = (float(exposure_range_us[0]), float(exposure_range_us[1]))
        self.gain_max_db = float(gain_max_db)
        self._applied = self._clip(settings)
        self._pending: deque[tuple[int, ExposureSettings]] = deque()
        self._frame = 0
        rng = np.random.default_rng(seed)
        self._table = rng.standard_normal(NOISE_TABLE_SIZE).astype(np.float32)
        self._rng = rng

    def _clip(self, s: ExposureSettings) -> ExposureSettings:
        lo, hi = self.exposure_range_us
        return ExposureSettings(min(max(s.exposure_us, lo), hi), min(s.gain_db, self.gain_max_db))

    @property
    def settings(self) -> ExposureSettings:
        """Settings the next frame will be taken with (unless a request lands first)."""
        return self._applied

    @property
    def frame_index(self) -> int:
        """Number of frames taken so far."""
        return self._frame

    def request(self, settings: ExposureSettings) -> None:
        """Command new settings; they apply from frame ``frame_index + latency_frames - 1`` on.

        With ``latency_frames = 1`` the next frame uses them.
        """
        self._pending.append((self._frame + self.latency_frames - 1, self._clip(settings)))

    def capture(self, brightness: float = 1.0, offset: tuple[int, int] = (0, 0),
                out: NDArray[np.uint16] | None = None) -> tuple[NDArray[np.uint16], ExposureSettings]:
        """Take one frame.

        Parameters
        ----------
        brightness : float
            Scene brightness factor of this frame (> 0).
        offset : (int, int)
            Even (row, column) of the frame's top-left corner in the scene.
        out : ndarray of uint16, optional
            Array to write the frame into (shape ``frame_shape``).

        Returns
        -------
        raw : ndarray of uint16, shape ``frame_shape``
        settings : ExposureSettings
            What this frame was taken with.
        """
        from pihim.live import _kernels

        while self._pending and self._pending[0][0] <= self._frame:
            self._applied = self._pending.popleft()[1]
        r0, c0 = int(offset[0]), int(offset[1])
        h, w = self.frame_shape
        if r0 < 0 or c0 < 0 or r0 + h > self.rate.shape[0] or c0 + w > self.rate.shape[1]:
            raise PihimInputError(f"window at {offset} leaves the scene {self.rate.shape}")
        raw = np.empty((h, w), dtype=np.uint16) if out is None else out
        s = self._applied
        n = self.noise
        _kernels.expose(self.rate, r0, c0, float(s.exposure_us * brightness), float(n.dark_level_dn),
                        float(n.full_scale), 1.0 / n.electrons_per_dn, n.read_noise_dn ** 2, s.gain_linear,
                        self._table, int(self._rng.integers(0, NOISE_TABLE_SIZE)), raw)
        self._frame += 1
        return raw, s
