"""Frame sources of the live view: one interface for a folder replay, a simulated camera and GenICam cameras.

A source hands out :class:`LiveFrame` objects, one raw DoFP mosaic each, at
its own pace (:meth:`FrameSource.read` blocks until the next frame is due or
has arrived). Sources whose camera takes commands (``controllable``) accept
new exposure and gain settings from the adaptive exposure
(:mod:`pihim.live.exposure`).

Failures come in three kinds:

* :class:`~pihim.errors.PihimInputError` when the source is made: a folder
  without frames, a missing GenTL producer, no camera; the command line turns
  it into one line on stderr and exit status 2;
* :class:`FrameError`: one frame is unusable (corrupt file, a frame of
  another size than the stream's); the live view shows the message and goes
  on with the next frame;
* :class:`SourceLost`: the camera stopped delivering (unplugged, powered
  off); the live view shows the message and calls
  :meth:`FrameSource.reconnect` until it comes back.

Sources
-------
:class:`FolderSource`
    Replays the raw frames of a folder (TIFF, PNG, Lucid ``.raw``) at a
    given rate, looping. A ``NAME.json`` beside ``NAME.tiff`` written by
    ``pihim simulate`` (``pihim.simulated-frame/1``) or by a live capture
    (``pihim.live-capture/1``) travels with the frame: its logged camera
    pose draws the heliostat outlines, its exposure is shown.
:class:`SyntheticSource`
    A :class:`~pihim.live.simcam.SimulatedCamera` over pihim's synthetic
    heliostat scenes (:func:`pihim.render.scenes.edge_scene`) that drifts
    across the scene and changes the scene brightness every few seconds, so
    the adaptive exposure has something to do; the mirror pixels are known.
:class:`RenderedSource`
    The renderer flying a plan: the views ``pihim simulate`` rendered at a
    plan's capture waypoints, re-exposed live by the simulated camera, with
    the mirror pixels from the render's labels and the logged pose.
:class:`GenICamSource`
    A GenICam camera (e.g. the Lucid Triton TRI050S-P) through
    ``harvesters`` and the camera vendor's GenTL producer (``.cti``).
"""

from __future__ import annotations

import json
import math
import os
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from pihim.errors import PihimInputError
from pihim.live.exposure import ExposureSettings

__all__ = [
    "FRAME_SUFFIXES",
    "FolderSource",
    "FrameError",
    "FrameSource",
    "GenICamSource",
    "LiveFrame",
    "RenderedSource",
    "SourceLost",
    "SyntheticSource",
    "check_source_options",
    "open_source",
]

#: File types a folder source replays.
FRAME_SUFFIXES: tuple[str, ...] = (".tif", ".tiff", ".png", ".raw", ".bin")
#: The images pihim writes beside a frame, named ``NAME.TAG[.MORE].ext``: ``pihim simulate``'s truth
#: (``S0 DoLP AoP labels``), ``pihim polar``'s products, previews and figure (``polar``), ``pihim edges``' maps
#: (``edges gradient``). They are not frames, and a folder replay skips them.
DERIVED_IMAGE_TAGS: frozenset[str] = frozenset({"S0", "DoLP", "AoP", "labels", "polar", "edges", "gradient"})


def _is_derived_image(p: Path) -> bool:
    return any(tag in DERIVED_IMAGE_TAGS for tag in p.stem.split(".")[1:])


def _is_frame_candidate(p: Path) -> bool:
    return p.suffix.lower() in FRAME_SUFFIXES and not p.name.startswith(".") and p.is_file()


class FrameError(Exception):
    """One frame could not be used; the stream goes on (the message is one line)."""


class SourceLost(Exception):
    """The camera stopped delivering frames; :meth:`FrameSource.reconnect` may bring it back."""


@dataclass(frozen=True, eq=False)
class LiveFrame:
    """One raw frame from a source.

    Attributes
    ----------
    raw : ndarray of uint8 or uint16, shape (H, W)
        The DoFP mosaic (even sides). Owned by the frame: sources never
        reuse the buffer, so a frame can be kept (captured, recorded) while
        the next one arrives.
    index : int
        Sequence number given by the source (0, 1, 2, ...).
    time_unix : float
        Wall-clock time of the frame, seconds since the epoch.
    t_monotonic : float
        :func:`time.monotonic` when the frame was handed over; latency is
        measured from here.
    bit_depth : int or None
        ADC bits when known.
    pixel_format : str
        E.g. ``"PolarizeMono12p"``, ``"tiff"``, ``"simulated"``.
    settings : ExposureSettings or None
        Exposure and gain the frame was taken with, when known.
    region : ndarray of bool or None
        Mirror pixels, shape (H, W) or the super-pixel shape (H/2, W/2),
        when the source knows them.
    meta : dict
        Source-specific, JSON-ready details (file name, camera serial, the
        ``log`` of a simulated frame).
    """

    raw: NDArray
    index: int
    time_unix: float
    t_monotonic: float
    bit_depth: int | None = None
    pixel_format: str = "unknown"
    settings: ExposureSettings | None = None
    region: NDArray[np.bool_] | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns) of the mosaic."""
        return self.raw.shape  # type: ignore[return-value]


@runtime_checkable
class FrameSource(Protocol):
    """What the live engine needs from a source of raw frames."""

    #: Whether :meth:`set_exposure` reaches a sensor.
    controllable: bool
    #: (rows, columns) of every frame.
    shape: tuple[int, int]

    def describe(self) -> dict[str, Any]:
        """JSON-ready description (kind, name, rate, size)."""
        ...

    def read(self) -> LiveFrame:
        """The next frame; blocks until it is due. Raises :class:`FrameError` or :class:`SourceLost`."""
        ...

    def set_exposure(self, settings: ExposureSettings) -> None:
        """Command new exposure and gain (ignored by sources that are not ``controllable``)."""
        ...

    def reconnect(self) -> None:
        """Try to get the camera back after :class:`SourceLost` (raise :class:`SourceLost` if not yet)."""
        ...

    def close(self) -> None:
        """Release the camera or files."""
        ...


class _Pacer:
    """Sleeps until frame ``k`` of a stream at ``fps`` is due; falls back into step when late."""

    def __init__(self, fps: float) -> None:
        if not (isinstance(fps, (int, float)) and math.isfinite(fps) and 0 < fps <= 1000):
            raise PihimInputError(f"frame rate must be in (0, 1000] frames per second, got {fps!r}")
        self.period = 1.0 / float(fps)
        self._next: float | None = None
        self._stop = threading.Event()

    def wait(self) -> None:
        now = time.monotonic()
        if self._next is None or now - self._next > self.period:  # first frame, or late: restart the clock
            self._next = now
        else:
            self._stop.wait(max(0.0, self._next - now))
        self._next += self.period

    def interrupt(self) -> None:
        self._stop.set()


def _natural_key(path: Path) -> list[Any]:
    """Sort key putting ``f2`` before ``f10``."""
    return [int(t) if t.isdigit() else t.casefold() for t in re.split(r"(\d+)", path.name)]


# --------------------------------------------------------------------------- folder replay


class FolderSource:
    """Replay the raw frames of a folder at ``fps``, looping.

    Parameters
    ----------
    folder : path
        Folder with ``.tif``/``.tiff``, ``.png``, ``.raw``/``.bin`` frames
        (hidden files and pihim's temporaries are skipped, and so are the
        images pihim writes beside frames, see :data:`DERIVED_IMAGE_TAGS`),
        replayed in natural name order.
    fps : float
        Frames per second.
    loop : bool
        Start again after the last frame (else :meth:`read` raises
        :class:`SourceLost` at the end).
    width, height, pixel_format :
        For ``.raw``/``.bin`` buffers (see :func:`pihim.camera.frames.read_frame`).
    bit_depth : int, optional
        ADC bits, when the files do not say.

    Raises
    ------
    PihimInputError
        The folder does not exist, holds no frame files, or none of them can
        be read.
    """

    controllable = False

    def __init__(self, folder: str | os.PathLike[str], fps: float = 15.0, *, loop: bool = True,
                 width: int | None = None, height: int | None = None, pixel_format: str | None = None,
                 bit_depth: int | None = None) -> None:
        from pihim.camera.frames import read_frame

        self.folder = Path(folder)
        if not self.folder.exists():
            raise PihimInputError(f"--source {folder}: no such folder")
        if not self.folder.is_dir():
            raise PihimInputError(f"--source {folder}: not a folder (give a folder of frames, 'synthetic' or "
                                  f"'genicam[:SERIAL]')")
        try:
            candidates = [p for p in self.folder.iterdir() if _is_frame_candidate(p)]
        except OSError as exc:
            raise PihimInputError(f"--source {folder}: cannot list the folder ({exc.strerror or exc})") from None
        files = [p for p in candidates if not _is_derived_image(p)]
        if not files:
            derived = len(candidates)
            raise PihimInputError(f"--source {folder}: no frames in the folder (expected "
                                  f"{', '.join(FRAME_SUFFIXES)} files" + (
                                      f"; {derived} images pihim writes beside frames, NAME.S0.tiff, "
                                      f"NAME.polar.png and the like, were skipped" if derived else "") + ")")
        self.files = sorted(files, key=_natural_key)
        self._read_kw = {"width": width, "height": height, "pixel_format": pixel_format}
        self._read = read_frame
        self._bit_depth = bit_depth
        first_error = None
        for k, path in enumerate(self.files):
            try:
                first = read_frame(path, **self._read_kw)
            except PihimInputError as exc:
                first_error = first_error or str(exc)
                continue
            self.shape: tuple[int, int] = first.data.shape  # type: ignore[assignment]
            self._pos = k
            break
        else:
            raise PihimInputError(f"--source {folder}: none of its {len(self.files)} frame files can be read "
                                  f"(first error: {first_error})")
        self.fps = float(fps)
        self.loop = loop
        self._pacer = _Pacer(fps)
        self._index = 0
        self._sidecars: dict[Path, dict[str, Any] | None] = {}

    def describe(self) -> dict[str, Any]:
        """Kind, folder, number of files, rate and size."""
        return {"kind": "folder", "name": str(self.folder), "files": len(self.files), "fps": self.fps,
                "width": self.shape[1], "height": self.shape[0], "controllable": False}

    def _sidecar(self, path: Path) -> dict[str, Any] | None:
        """The JSON beside a frame (simulated frame or live capture), parsed once; None if absent or foreign."""
        if path not in self._sidecars:
            doc = None
            side = path.with_suffix(".json")
            try:
                if side.is_file() and side.stat().st_size < 16_000_000:
                    loaded = json.loads(side.read_text(encoding="utf-8"))
                    if isinstance(loaded, dict) and str(loaded.get("schema", "")).startswith(
                            ("pihim.simulated-frame/", "pihim.live-capture/")):
                        doc = loaded
            except (OSError, ValueError, RecursionError):
                doc = None
            self._sidecars[path] = doc
        return self._sidecars[path]

    def read(self) -> LiveFrame:
        """The next file's frame, when due; :class:`FrameError` for an unreadable or odd-sized one."""
        if self._pos >= len(self.files):
            if not self.loop:
                raise SourceLost(f"{self.folder}: end of the folder")
            self._pos = 0
        path = self.files[self._pos]
        self._pos += 1
        self._pacer.wait()
        try:
            frame = self._read(path, **self._read_kw)
        except PihimInputError as exc:
            raise FrameError(f"{exc}; skipped") from None
        if frame.data.shape != self.shape:
            h, w = frame.data.shape
            raise FrameError(f"{path}: frame is {w}x{h} (WxH) but the stream is {self.shape[1]}x{self.shape[0]}; "
                             f"skipped")
        meta: dict[str, Any] = {"file": path.name}
        settings = None
        doc = self._sidecar(path)
        if doc is not None:
            log = doc.get("log") if doc.get("schema", "").startswith("pihim.simulated-frame/") else None
            if isinstance(log, dict):
                meta["log"] = log
            exp = doc.get("exposure")
            if isinstance(exp, dict):
                try:
                    settings = ExposureSettings(exp["exposure_us"], exp.get("gain_db", 0.0))
                except (KeyError, PihimInputError, TypeError):
                    settings = None
        idx = self._index
        self._index += 1
        return LiveFrame(frame.data, idx, time.time(), time.monotonic(), frame.bit_depth or self._bit_depth,
                         frame.pixel_format, settings, None, meta)

    def set_exposure(self, settings: ExposureSettings) -> None:  # noqa: ARG002 - recorded frames
        """Recorded frames cannot be re-exposed: ignored."""

    def reconnect(self) -> None:
        """Start again from the first file."""
        self._pos = 0

    def close(self) -> None:
        """Stop waiting."""
        self._pacer.interrupt()


# --------------------------------------------------------------------------- synthetic scenes


def synthetic_scene(shape: tuple[int, int], seed: int, *, reference_us: float = 1000.0,
                    detail_scale: int | None = None) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Signal rate and mirror mask of a synthetic heliostat scene for :class:`SimulatedCamera`.

    The scene is :func:`pihim.render.scenes.edge_scene` (mirrors reflecting
    sky, DoLP 0.15-0.6, on a weakly polarized ground) seen through the
    IMX250MZR mosaic; at ``reference_us`` of exposure and 0 dB its brightest
    pixels are near 4000 DN of 12 bits. Frames larger than 1.3 MP are built
    at a lower resolution (``detail_scale``, default so that the scene has at
    most about 1.3 MP) and enlarged, which keeps start-up near a second.

    Returns
    -------
    rate : ndarray of float32, shape ``shape``
        DN per microsecond at 0 dB.
    mirrors : ndarray of bool, shape ``(H/2, W/2)``
        Super-pixels on a mirror facet.
    """
    import cv2

    from pihim.render.mosaic import mosaic_from_stokes
    from pihim.render.scenes import edge_scene

    h, w = shape
    k = detail_scale or max(1, int(math.ceil(math.sqrt(h * w / 1.3e6))))
    sh, sw = max(16, h // k), max(16, w // k)
    s0, s1, s2 = edge_scene((sh, sw), rng=seed)
    if (sh, sw) != (h, w):
        s0, s1, s2 = (cv2.resize(np.asarray(a, np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
                      for a in (s0, s1, s2))
    dolp = np.hypot(s1, s2) / np.maximum(s0, 1e-6)
    bright = s0 > 1500.0  # facets are 2000-4000 DN, the ground 900-1500 and the frames darker
    mirrors = (dolp > 0.12) & bright
    mosaic = mosaic_from_stokes(s0, s1, s2, bit_depth=None)
    rate = (np.asarray(mosaic, np.float32) / np.float32(reference_us)).astype(np.float32)
    sp = mirrors.reshape(h // 2, 2, w // 2, 2).all(axis=(1, 3))
    return rate, sp


class SyntheticSource:
    """A simulated camera over synthetic heliostat scenes, with a brightness programme.

    Parameters
    ----------
    shape : (int, int)
        Even (rows, columns) of a frame; default the Triton's 2048 x 2448.
    fps : float
        Frames per second.
    seed : int
        Scene and noise seed.
    scenes : int
        Number of different scenes cycled through (one per ``period_s``).
    period_s : float
        Seconds between scene and brightness changes.
    brightness : sequence of float
        Scene brightness factors, one per period, cycled: the default
        ``(1, 10, 1, 0.1)`` makes the adaptive exposure work every few seconds.
    drift_px : int
        Half-amplitude of the slow side-to-side drift of the view, raw pixels
        (even); the scene is made this much wider on each side.
    latency_frames : int
        Actuation latency of the simulated camera.
    settings : ExposureSettings
        Initial exposure and gain.
    """

    controllable = True

    def __init__(self, shape: tuple[int, int] = (2048, 2448), fps: float = 15.0, *, seed: int = 0, scenes: int = 2,
                 period_s: float = 4.0, brightness: tuple[float, ...] = (1.0, 10.0, 1.0, 0.1), drift_px: int = 64,
                 latency_frames: int = 2, settings: ExposureSettings = ExposureSettings(1000.0)) -> None:
        from pihim.live.simcam import SimulatedCamera

        h, w = int(shape[0]), int(shape[1])
        if h < 16 or w < 16 or h % 2 or w % 2:
            raise PihimInputError(f"synthetic frame size must be even and at least 16x16, got {w}x{h}")
        if not 1 <= int(scenes) <= 16:
            raise PihimInputError(f"scenes must be in 1..16, got {scenes!r}")
        if not (math.isfinite(period_s) and period_s > 0):
            raise PihimInputError(f"period must be > 0 s, got {period_s!r}")
        if not brightness or not all(math.isfinite(b) and b > 0 for b in brightness):
            raise PihimInputError("brightness factors must be finite and > 0")
        d = 2 * (max(0, int(drift_px)) // 2)
        self.shape = (h, w)
        self.fps = float(fps)
        self.period_s = float(period_s)
        self.brightness = tuple(float(b) for b in brightness)
        self.drift_px = d
        self._pacer = _Pacer(fps)
        self._rates = []
        self._regions = []
        for k in range(int(scenes)):
            rate, mirrors = synthetic_scene((h + 2 * d, w + 2 * d), seed + k)
            self._rates.append(rate)
            self._regions.append(mirrors)
        self._cam = SimulatedCamera(self._rates[0], settings, latency_frames=latency_frames, frame_shape=(h, w),
                                    seed=seed)
        self._index = 0
        self._t0: float | None = None
        self._lock = threading.Lock()

    def describe(self) -> dict[str, Any]:
        """Kind, size, rate and programme."""
        return {"kind": "synthetic", "name": "synthetic heliostat scenes (simulated camera)", "fps": self.fps,
                "width": self.shape[1], "height": self.shape[0], "scenes": len(self._rates),
                "period_s": self.period_s, "brightness": list(self.brightness), "controllable": True,
                "latency_frames": self._cam.latency_frames}

    def read(self) -> LiveFrame:
        """Take the next frame with the simulated camera of the current scene."""
        self._pacer.wait()
        now = time.monotonic()
        if self._t0 is None:
            self._t0 = now
        period = int((now - self._t0) // self.period_s)
        cam_k = period % len(self._rates)
        b = self.brightness[period % len(self.brightness)]
        # drift: a triangle wave over 20 s, in even pixels (the mosaic phase is kept)
        d = self.drift_px
        phase = ((now - self._t0) / 10.0) % 2.0
        off = int(round(d * (phase if phase < 1.0 else 2.0 - phase))) // 2 * 2
        with self._lock:
            self._cam.rate = self._rates[cam_k]
            raw, used = self._cam.capture(b, (d, off))
        region = self._regions[cam_k][d // 2:d // 2 + self.shape[0] // 2, off // 2:off // 2 + self.shape[1] // 2]
        idx = self._index
        self._index += 1
        return LiveFrame(raw, idx, time.time(), time.monotonic(), 12, "simulated", used, region,
                         {"scene": cam_k, "brightness": b})

    def set_exposure(self, settings: ExposureSettings) -> None:
        """Command the simulated camera (applies ``latency_frames`` later)."""
        with self._lock:
            self._cam.request(settings)

    def reconnect(self) -> None:
        """Nothing to reconnect."""

    def close(self) -> None:
        """Stop waiting."""
        self._pacer.interrupt()


def rendered_scene(json_path: Path) -> tuple[NDArray[np.float32], NDArray[np.bool_], dict[str, Any]]:
    """Signal rate, mirror mask and log of one frame rendered by ``pihim simulate``.

    Reads ``FRAME.json`` (``pihim.simulated-frame/1``) and the noise-free
    truth images beside it (``FRAME.S0/DoLP/AoP.tiff``, ``FRAME.labels.tiff``).
    The rate is the ideal mosaic at the frame's logged exposure
    (``log.sensor.exposure.gain_dn``) per 1000 us: with 1000 us at 0 dB the
    simulated camera reproduces the rendered exposure. Mirror pixels are
    those whose first surface is a mirror (label ``direct_kind`` 4).
    """
    import tifffile

    from pihim.render.mosaic import mosaic_from_stokes
    from pihim.render.paths import MIRROR

    stem = json_path.with_suffix("")
    try:
        doc = json.loads(json_path.read_text(encoding="utf-8"))
        log = doc["log"]
        gain = float(log["sensor"]["exposure"]["gain_dn"])
        s0 = tifffile.imread(f"{stem}.S0.tiff").astype(np.float32)
        dolp = np.nan_to_num(tifffile.imread(f"{stem}.DoLP.tiff").astype(np.float32))
        aop = np.radians(np.nan_to_num(tifffile.imread(f"{stem}.AoP.tiff").astype(np.float32)))
        kind = tifffile.imread(f"{stem}.labels.tiff")[..., 0]
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise PihimInputError(f"{json_path}: not a complete pihim simulate frame ({type(exc).__name__}: {exc})") from None
    h, w = s0.shape
    if h % 2 or w % 2 or dolp.shape != s0.shape or aop.shape != s0.shape or kind.shape != s0.shape:
        raise PihimInputError(f"{json_path}: truth images of different or odd sizes")
    lin = s0 * dolp
    mosaic = mosaic_from_stokes(gain * s0, gain * lin * np.cos(2 * aop), gain * lin * np.sin(2 * aop), bit_depth=None)
    rate = (np.asarray(mosaic, np.float32) / np.float32(1000.0)).clip(0, None)
    mirrors = (kind == MIRROR).reshape(h // 2, 2, w // 2, 2).all(axis=(1, 3))
    return rate, mirrors, log


class RenderedSource:
    """The renderer flying a plan: frames of ``pihim simulate`` re-exposed live by a simulated camera.

    Rendering a 5 MP frame takes tens of seconds, so the flight is rendered
    once (``pihim simulate --waypoint plan.json:I`` for each capture
    waypoint, into one folder) and this source cycles through the views,
    ``period_s`` seconds each, as a drone hovering at each capture point. Each
    view's noise-free Stokes images become the scene of a
    :class:`~pihim.live.simcam.SimulatedCamera`, so the adaptive exposure acts
    on it; the mirror pixels come from the render's labels and the logged
    pose travels with the frame (heliostat outlines).

    Parameters
    ----------
    folder : path
        Folder with ``NAME.json`` + ``NAME.S0/DoLP/AoP/labels.tiff`` sets.
    fps, period_s, brightness, latency_frames, settings :
        As :class:`SyntheticSource`.
    """

    controllable = True

    def __init__(self, folder: str | os.PathLike[str], fps: float = 15.0, *, period_s: float = 4.0,
                 brightness: tuple[float, ...] = (1.0,), latency_frames: int = 2,
                 settings: ExposureSettings = ExposureSettings(1000.0)) -> None:
        from pihim.live.simcam import SimulatedCamera

        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise PihimInputError(f"--source synthetic:{folder}: no such folder")
        docs = []
        for p in sorted(self.folder.glob("*.json"), key=_natural_key):
            try:
                if json.loads(p.read_text(encoding="utf-8")).get("schema", "").startswith("pihim.simulated-frame/"):
                    docs.append(p)
            except (OSError, ValueError, AttributeError):
                continue
        if not docs:
            raise PihimInputError(f"--source synthetic:{folder}: no frames rendered by pihim simulate in the folder "
                                  f"(FRAME.json with its S0/DoLP/AoP/labels TIFFs)")
        self._scenes = [rendered_scene(p) for p in docs]
        shapes = {r.shape for r, _, _ in self._scenes}
        if len(shapes) != 1:
            raise PihimInputError(f"--source synthetic:{folder}: rendered frames of different sizes {sorted(shapes)}")
        self.names = [p.stem for p in docs]
        self.shape = next(iter(shapes))  # type: ignore[assignment]
        self.fps = float(fps)
        self.period_s = float(period_s)
        self.brightness = tuple(float(b) for b in brightness)
        self._pacer = _Pacer(fps)
        self._cam = SimulatedCamera(self._scenes[0][0], settings, latency_frames=latency_frames)
        self._index = 0
        self._t0: float | None = None
        self._lock = threading.Lock()

    def describe(self) -> dict[str, Any]:
        """Kind, folder, views, rate and size."""
        return {"kind": "synthetic", "name": f"rendered flight {self.folder} ({len(self._scenes)} views)",
                "fps": self.fps, "width": self.shape[1], "height": self.shape[0], "views": self.names,
                "period_s": self.period_s, "controllable": True, "latency_frames": self._cam.latency_frames}

    def read(self) -> LiveFrame:
        """The current view, taken by the simulated camera."""
        self._pacer.wait()
        now = time.monotonic()
        if self._t0 is None:
            self._t0 = now
        period = int((now - self._t0) // self.period_s)
        k = period % len(self._scenes)
        b = self.brightness[period % len(self.brightness)]
        rate, mirrors, log = self._scenes[k]
        with self._lock:
            self._cam.rate = rate
            raw, used = self._cam.capture(b)
        idx = self._index
        self._index += 1
        return LiveFrame(raw, idx, time.time(), time.monotonic(), 12, "simulated", used, mirrors,
                         {"view": self.names[k], "brightness": b, "log": log})

    def set_exposure(self, settings: ExposureSettings) -> None:
        """Command the simulated camera."""
        with self._lock:
            self._cam.request(settings)

    def reconnect(self) -> None:
        """Nothing to reconnect."""

    def close(self) -> None:
        """Stop waiting."""
        self._pacer.interrupt()


# --------------------------------------------------------------------------- GenICam


#: Pixel formats tried, in order, when none is given: raw mosaic formats that harvesters unpacks
#: (PFNC names), then Lucid's polarized names.
GENICAM_PIXEL_FORMATS: tuple[str, ...] = ("Mono12p", "Mono12Packed", "Mono16", "Mono12", "PolarizeMono12p",
                                          "PolarizeMono12Packed", "PolarizeMono16", "PolarizeMono12", "Mono8",
                                          "PolarizeMono8")


def _node(node_map: Any, name: str) -> Any | None:
    """A node of a GenICam node map, or None when the camera has no such feature."""
    try:
        return getattr(node_map, name)
    except Exception:  # noqa: BLE001 - genicam raises its own types for unknown nodes
        return None


def _set(node_map: Any, name: str, value: Any) -> bool:
    """Set a node if the camera has it and it is writable; report whether it took."""
    node = _node(node_map, name)
    if node is None:
        return False
    try:
        node.value = value
    except Exception:  # noqa: BLE001 - not writable now, out of range...
        return False
    return True


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class GenICamSource:
    """A GenICam camera through ``harvesters`` (optional extra ``pihim[genicam]``).

    GenICam cameras are reached through the vendor's GenTL producer, a
    ``.cti`` library that comes with the camera's SDK (Lucid: the Arena SDK's
    GenTL producer). Give its path (``cti``) or set ``GENICAM_GENTL64_PATH``
    to the folder holding it, as the GenTL standard says.

    On opening, the node map is set up: automatic exposure and gain off
    (pihim's controller drives them), the pixel format (``pixel_format`` or
    the first of :data:`GENICAM_PIXEL_FORMATS` that the camera offers), the
    acquisition frame rate when the camera has one. :meth:`set_exposure`
    writes ``ExposureTime`` (us) and ``Gain`` (dB), clipped to the ranges the
    camera reports.

    Parameters
    ----------
    serial : str, optional
        Serial number of the camera; default the first one found.
    cti : path, optional
        GenTL producer file.
    fps : float
        Acquisition frame rate asked of the camera.
    pixel_format : str, optional
        Pixel format to set.
    timeout_s : float
        Longest wait for a frame before the camera counts as lost.
    harvester_factory : callable, optional
        Makes the ``Harvester``; for tests, a fake with the same interface.
    """

    controllable = True

    def __init__(self, serial: str | None = None, *, cti: str | os.PathLike[str] | None = None, fps: float = 15.0,
                 pixel_format: str | None = None, timeout_s: float = 2.0,
                 harvester_factory: Callable[[], Any] | None = None) -> None:
        if harvester_factory is None:
            try:
                from harvesters.core import Harvester
            except ImportError:
                raise PihimInputError("--source genicam needs harvesters: pip install 'pihim[genicam]' "
                                      "(and the camera vendor's GenTL producer .cti)") from None
            harvester_factory = Harvester
        self.serial = serial
        self.fps = float(fps)
        self.timeout_s = float(timeout_s)
        self.cti_files = self._find_cti(cti)
        self._factory = harvester_factory
        self._wanted_format = pixel_format
        self._h: Any = None
        self._ia: Any = None
        self._index = 0
        self._lock = threading.Lock()
        self._settings: ExposureSettings | None = None
        self._ranges: dict[str, tuple[float, float]] = {}
        try:
            self._open()
        except SourceLost as exc:
            self.close()
            raise PihimInputError(f"--source genicam{':' + serial if serial else ''}: {exc}") from None
        self.shape: tuple[int, int] = self._shape

    @staticmethod
    def _find_cti(cti: str | os.PathLike[str] | None) -> list[str]:
        if cti is not None:
            p = Path(cti)
            if not p.is_file() or p.suffix.lower() != ".cti":
                raise PihimInputError(f"--cti {cti}: not a GenTL producer file (.cti)")
            return [str(p)]
        found: list[str] = []
        for d in os.environ.get("GENICAM_GENTL64_PATH", "").split(os.pathsep):
            if d and Path(d).is_dir():
                found += sorted(str(p) for p in Path(d).glob("*.cti"))
        if not found:
            raise PihimInputError("--source genicam: no GenTL producer; give --cti PATH/TO/PRODUCER.cti (it comes "
                                  "with the camera vendor's SDK, e.g. Lucid's Arena SDK) or set GENICAM_GENTL64_PATH")
        return found

    def _open(self) -> None:
        """Load the producer, find the camera, set up its node map and start acquiring (SourceLost on failure)."""
        try:
            self._h = self._factory()
            for f in self.cti_files:
                self._h.add_file(f)
            self._h.update()
            devices = list(self._h.device_info_list)
        except Exception as exc:  # noqa: BLE001 - genicam raises its own types
            raise SourceLost(f"cannot load the GenTL producer ({_one_line(exc)})") from None
        if not devices:
            raise SourceLost("no GenICam camera found (is it connected and powered, and is the producer the "
                             "right one for it?)")
        key: Any = {"serial_number": self.serial} if self.serial else 0
        try:
            self._ia = self._h.create(key)
        except Exception as exc:  # noqa: BLE001
            serials = ", ".join(str(getattr(d, "serial_number", "?")) for d in devices)
            raise SourceLost(f"cannot open camera {self.serial or '#0'} ({_one_line(exc)}); found: {serials}") from None
        nm = self._ia.remote_device.node_map
        _set(nm, "ExposureAuto", "Off")
        _set(nm, "GainAuto", "Off")
        formats = [self._wanted_format] if self._wanted_format else list(GENICAM_PIXEL_FORMATS)
        pf = _node(nm, "PixelFormat")
        offered = set(getattr(pf, "symbolics", ()) or ()) if pf is not None else set()
        self.pixel_format = None
        for name in formats:
            if (not offered or name in offered) and _set(nm, "PixelFormat", name):
                self.pixel_format = name
                break
        if self._wanted_format and self.pixel_format is None:
            raise SourceLost(f"the camera refuses pixel format {self._wanted_format!r} (offers: "
                             f"{', '.join(sorted(offered)) or 'unknown'})")
        if self.pixel_format is None and pf is not None:
            self.pixel_format = str(pf.value)
        _set(nm, "AcquisitionFrameRateEnable", True)
        _set(nm, "AcquisitionFrameRate", self.fps)
        for name in ("ExposureTime", "Gain"):
            node = _node(nm, name)
            if node is not None:
                try:
                    self._ranges[name] = (float(node.min), float(node.max))
                except Exception:  # noqa: BLE001
                    pass
        try:
            self._shape = (int(nm.Height.value), int(nm.Width.value))
        except Exception as exc:  # noqa: BLE001
            raise SourceLost(f"cannot read the frame size ({_one_line(exc)})") from None
        if self._settings is not None:
            self._write_settings(self._settings)
        try:
            self._ia.start()
        except Exception as exc:  # noqa: BLE001
            raise SourceLost(f"cannot start acquisition ({_one_line(exc)})") from None

    def describe(self) -> dict[str, Any]:
        """Kind, camera, pixel format, rate, size and settable ranges."""
        return {"kind": "genicam", "name": f"GenICam {self.serial or '#0'}", "serial": self.serial,
                "pixel_format": self.pixel_format, "fps": self.fps, "width": self.shape[1],
                "height": self.shape[0], "controllable": True, "cti": self.cti_files,
                "ranges": {k: list(v) for k, v in self._ranges.items()}}

    def _decode(self, component: Any) -> tuple[NDArray, int | None]:
        """The component's pixels as a (H, W) mosaic, and the bit depth."""
        from pihim.camera.frames import read_lucid_raw

        w, h = int(component.width), int(component.height)
        data = np.asarray(component.data)
        fmt = str(getattr(component, "data_format", self.pixel_format) or self.pixel_format)
        bits = 12 if "12" in fmt else 8 if fmt.endswith("8") else None
        if data.size == w * h and data.dtype in (np.uint8, np.uint16):
            return data.reshape(h, w).copy(), bits
        if data.dtype == np.uint8:  # a packed buffer harvesters left as bytes
            try:
                frame = read_lucid_raw(data, w, h, fmt)
            except PihimInputError as exc:
                raise FrameError(f"camera buffer ({fmt}, {data.size} bytes for {w}x{h}): {exc}") from None
            return frame.data, frame.bit_depth
        raise FrameError(f"camera buffer of {data.size} {data.dtype} values does not hold {w}x{h} pixels ({fmt})")

    def read(self) -> LiveFrame:
        """The next frame from the camera (waits up to ``timeout_s``)."""
        if self._ia is None:
            raise SourceLost("camera not connected")
        try:
            with self._ia.fetch(timeout=self.timeout_s) as buffer:
                raw, bits = self._decode(buffer.payload.components[0])
        except FrameError:
            raise
        except Exception as exc:  # noqa: BLE001 - timeouts, device removal: genicam's own exception types
            raise SourceLost(f"camera {self.serial or '#0'} stopped delivering frames ({_one_line(exc)})") from None
        if raw.shape != self.shape:
            raise FrameError(f"camera frame is {raw.shape[1]}x{raw.shape[0]} (WxH) but the stream is "
                             f"{self.shape[1]}x{self.shape[0]}; skipped")
        idx = self._index
        self._index += 1
        return LiveFrame(raw, idx, time.time(), time.monotonic(), bits, self.pixel_format or "unknown",
                         self._settings, None, {"serial": self.serial})

    def _write_settings(self, s: ExposureSettings) -> ExposureSettings:
        nm = self._ia.remote_device.node_map
        t, g = s.exposure_us, s.gain_db
        if "ExposureTime" in self._ranges:
            lo, hi = self._ranges["ExposureTime"]
            t = min(max(t, lo), hi)
        if "Gain" in self._ranges:
            lo, hi = self._ranges["Gain"]
            g = min(max(g, lo), hi)
        _set(nm, "ExposureTime", float(t))
        _set(nm, "Gain", float(g))
        return ExposureSettings(t, max(g, 0.0))

    def set_exposure(self, settings: ExposureSettings) -> None:
        """Write ``ExposureTime`` and ``Gain`` (clipped to the camera's ranges)."""
        with self._lock:
            self._settings = settings
            if self._ia is not None:
                try:
                    self._settings = self._write_settings(settings)
                except Exception:  # noqa: BLE001 - a lost camera shows up in read()
                    pass

    def reconnect(self) -> None:
        """Release the lost camera and open it again (SourceLost while it is not back)."""
        self._release()
        self._open()

    def _release(self) -> None:
        for obj, calls in ((self._ia, ("stop", "destroy")), (self._h, ("reset",))):
            for name in calls:
                try:
                    getattr(obj, name)()
                except Exception:  # noqa: BLE001 - it is gone anyway
                    pass
        self._ia = None
        self._h = None

    def close(self) -> None:
        """Stop acquiring and release the camera and the producer."""
        self._release()


# --------------------------------------------------------------------------- parsing


def open_source(spec: str, *, fps: float = 15.0, size: tuple[int, int] | None = None, seed: int = 0,
                cti: str | None = None, pixel_format: str | None = None, width: int | None = None,
                height: int | None = None, bit_depth: int | None = None) -> FrameSource:
    """Make a source from ``--source DIR|synthetic[:DIR]|genicam[:SERIAL]``.

    Parameters
    ----------
    spec : str
        A folder of frames, ``synthetic`` (synthetic scenes),
        ``synthetic:DIR`` (a flight rendered by ``pihim simulate``,
        :class:`RenderedSource`), ``genicam`` or ``genicam:SERIAL``.
    fps : float
        Frame rate (the camera's acquisition rate for GenICam).
    size : (rows, columns), optional
        Frame size of the synthetic source (default 2048 x 2448).
    seed : int
        Seed of the synthetic scenes.
    cti, pixel_format :
        GenICam producer and pixel format (``pixel_format`` also applies to
        ``.raw`` files with ``width`` and ``height``).
    """
    check_source_options(spec, size=size, pixel_format=pixel_format, width=width, height=height,
                         bit_depth=bit_depth)
    text = spec.strip()
    low = text.lower()
    if low == "synthetic":
        return SyntheticSource(size or (2048, 2448), fps, seed=seed)
    if low.startswith("synthetic:"):
        return RenderedSource(text.split(":", 1)[1], fps)
    if low == "genicam" or low.startswith("genicam:"):
        serial = text.split(":", 1)[1].strip() if ":" in text else None
        return GenICamSource(serial or None, cti=cti, fps=fps, pixel_format=pixel_format)
    return FolderSource(text, fps, width=width, height=height, pixel_format=pixel_format, bit_depth=bit_depth)


def check_source_options(spec: str, *, size: tuple[int, int] | None = None, pixel_format: str | None = None,
                         width: int | None = None, height: int | None = None, bit_depth: int | None = None) -> None:
    """Refuse options that do not apply to the source ``spec`` names (they were silently ignored), and an unknown
    pixel format, before anything is opened (:func:`open_source` calls it too).

    ``size`` sizes synthetic scenes only; ``width``, ``height`` and ``bit_depth``
    describe a folder's ``.raw`` frames; ``pixel_format`` applies to those and to
    a GenICam camera.

    Raises
    ------
    PihimInputError
        ``"--width does not apply to a synthetic source"`` and the like.
    """
    low = spec.strip().lower()
    if not low:  # Path('') would be the working directory
        raise PihimInputError("--source is empty: give a folder of raw frames, synthetic, synthetic:DIR or "
                              "genicam[:SERIAL]")
    raw_options = {"--width": width, "--height": height, "--bit-depth": bit_depth}
    if low == "synthetic" or low.startswith("synthetic:"):
        _refuse_unused({"--pixel-format": pixel_format, **raw_options}, "a synthetic source")
        if low != "synthetic":
            _refuse_unused({"--size": size}, "a rendered flight (its frames have their own size)")
        return
    _refuse_unused({"--size": size}, "a folder or a camera (it sizes synthetic frames)")
    if low == "genicam" or low.startswith("genicam:"):  # its pixel format is the camera's to accept (Mono12, ...)
        _refuse_unused(raw_options, "a GenICam camera (its pixel format decides)")
    elif pixel_format is not None:
        from pihim.camera.frames import normalize_pixel_format

        normalize_pixel_format(pixel_format)  # an unknown .raw format is said as such, TIFFs in the folder or not


def _refuse_unused(options: dict[str, Any], source: str) -> None:
    """One line naming the options given that do not apply to ``source`` (they were silently ignored)."""
    given = [name for name, value in options.items() if value is not None]
    if given:
        raise PihimInputError(f"{' and '.join(given)} {'does' if len(given) == 1 else 'do'} not apply to {source}")
