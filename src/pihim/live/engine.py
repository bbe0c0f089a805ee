"""The live processing loop: frame -> exposure decision -> polar image -> previews -> packet, in a thread.

:class:`LiveEngine` pulls frames from a :mod:`source <pihim.live.sources>`
in a background thread and, for each one:

1. takes the statistics of the mirror region (the source's, else the
   rasterised heliostat outlines of the overlay, else the whole frame) and,
   for a source that takes commands, asks
   :func:`~pihim.live.exposure.next_exposure` for the next exposure and gain;
2. computes S0, DoLP and AoP at super-pixel resolution
   (:func:`pihim.camera.polar_image`);
3. renders the JPEG previews (:class:`~pihim.live.preview.PreviewRenderer`)
   and packs them with a JSON header into one binary message
   (:func:`pack_packet`);
4. publishes the packet (the web server sends it to every browser) and
   keeps the raw frame for a capture; with ``record_dir`` every frame is
   also queued for writing.

The packet: 4 bytes little-endian header length ``n``, ``n`` bytes of UTF-8
JSON (``pihim.live-frame/1``: frame number, times, exposure, statistics,
outline overlay, the byte length of each image), then the JPEG images one
after the other in the header's order.

Latency is measured from the moment the source hands over the raw frame
(:attr:`LiveFrame.t_monotonic`) to the moment the packet has been written to
a browser's connection (:meth:`LiveEngine.record_send`).
"""

from __future__ import annotations

import collections
import json
import math
import queue
import re
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from pihim.errors import PihimInputError
from pihim.live.exposure import (
    ExposureParams,
    ExposureSettings,
    ExposureState,
    next_exposure,
    region_stats,
)
from pihim.live.sources import FrameError, FrameSource, LiveFrame, SourceLost

__all__ = ["CAPTURE_SCHEMA_ID", "FRAME_SCHEMA_ID", "LiveConfig", "LiveEngine", "pack_packet", "unpack_packet",
           "write_capture"]

FRAME_SCHEMA_ID = "pihim.live-frame/1"
CAPTURE_SCHEMA_ID = "pihim.live-capture/1"
#: Labels a client may attach to a capture: they become part of a file name, so nothing else is accepted.
LABEL_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,47}$")
#: The paper's usability threshold of the DoLP on the heliostat reflection (section 5).
MIRROR_DOLP_MIN = 0.2


def pack_packet(header: dict[str, Any], images: list[tuple[str, bytes]]) -> bytes:
    """One binary message: header length, JSON header (with the image byte counts), images."""
    head = dict(header)
    head["images"] = [{"name": name, "bytes": len(data), "mime": "image/jpeg"} for name, data in images]
    text = json.dumps(head, allow_nan=False, separators=(",", ":")).encode("utf-8")
    return b"".join([struct.pack("<I", len(text)), text, *(data for _, data in images)])


def unpack_packet(packet: bytes) -> tuple[dict[str, Any], dict[str, bytes]]:
    """Inverse of :func:`pack_packet` (for tests and the benchmark client)."""
    (n,) = struct.unpack_from("<I", packet, 0)
    header = json.loads(packet[4:4 + n].decode("utf-8"))
    images, pos = {}, 4 + n
    for item in header["images"]:
        images[item["name"]] = packet[pos:pos + item["bytes"]]
        pos += item["bytes"]
    if pos != len(packet):
        raise ValueError(f"packet of {len(packet)} bytes, header accounts for {pos}")
    return header, images


def _finite_or_none(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


# --------------------------------------------------------------------------- capture files


def capture_name(frame: LiveFrame, label: str | None = None) -> str:
    """File stem of a capture: UTC time to the millisecond, frame number, optional label."""
    if label is not None and not LABEL_RE.match(label):
        raise PihimInputError("capture label must be 1-48 letters, digits, '_' or '-', starting with a letter "
                              "or digit")
    stamp = datetime.fromtimestamp(frame.time_unix, UTC).strftime("%Y%m%dT%H%M%S.%f")[:-3] + "Z"
    return f"{stamp}-{frame.index:06d}" + (f"-{label}" if label else "")


def write_capture(directory: Path, frame: LiveFrame, info: dict[str, Any], *, label: str | None = None
                  ) -> dict[str, Any]:
    """Write a frame's raw mosaic (TIFF) and its JSON record (``pihim.live-capture/1``) into ``directory``.

    The TIFF is written under a temporary name and renamed when complete,
    then the JSON, likewise: a capture whose JSON exists is complete (the
    JSON holds the TIFF's size and SHA-256). The file names are made here
    from the frame's time and number (and a checked label); nothing the
    browser sends becomes a path.

    Returns
    -------
    dict
        The JSON record, with ``raw_file`` and ``json_file`` (names in ``directory``).
    """
    import hashlib

    import tifffile

    from pihim._atomic import atomic_path, write_json_atomic

    stem = capture_name(frame, label)
    directory = Path(directory)
    raw_path, json_path = directory / f"{stem}.tiff", directory / f"{stem}.json"
    for p in (raw_path, json_path):  # defence in depth: the name cannot leave the folder
        if p.parent.resolve() != directory.resolve() or p.name.startswith("."):
            raise PihimInputError(f"capture name {p.name!r} escapes the capture folder")
    with atomic_path(raw_path) as tmp:
        tifffile.imwrite(tmp, np.ascontiguousarray(frame.raw), photometric="minisblack")
    digest = hashlib.sha256(raw_path.read_bytes()).hexdigest()
    h, w = frame.shape
    record = {
        "schema": CAPTURE_SCHEMA_ID,
        "raw_file": raw_path.name,
        "raw_bytes": raw_path.stat().st_size,
        "raw_sha256": digest,
        "width": int(w),
        "height": int(h),
        "dtype": str(frame.raw.dtype),
        "bit_depth": frame.bit_depth,
        "pixel_format": frame.pixel_format,
        "frame_index": int(frame.index),
        "time_utc": datetime.fromtimestamp(frame.time_unix, UTC).isoformat(timespec="milliseconds"),
        "label": label,
        "exposure": None if frame.settings is None else frame.settings.to_dict(),
        **info,
    }
    write_json_atomic(json_path, record)
    record["json_file"] = json_path.name
    return record


# --------------------------------------------------------------------------- engine


@dataclass
class LiveConfig:
    """Settings of the live loop.

    Attributes
    ----------
    exposure : ExposureParams or None
        Adaptive exposure parameters; ``None`` turns the controller off.
    exposure_cap_us : float or None
        Motion-blur cap on the exposure (:func:`~pihim.live.exposure.motion_blur_exposure_cap_us`).
    initial_settings : ExposureSettings
        First command sent to a controllable source; with the controller off
        (``exposure=None``), the settings it keeps. Default 1000 us with the
        controller, the source's own without.
    preview_max_side, jpeg_quality : int
        Preview size and quality.
    layout, analyser, dark_level :
        Passed to :func:`pihim.camera.polar_image`.
    capture_dir : Path
        Where the capture button writes.
    record_dir : Path or None
        Where every frame is written (``--record``).
    overlay : pihim.live.overlay.Overlay or None
        Fixed outlines (from a plan); frames with a pose log get their own.
    overlay_from_log : callable or None
        ``log -> Overlay`` for frames that carry a log (folder replay of
        simulated frames).
    record_queue : int
        Frames waiting to be written before new ones are dropped.
    stats_stride : int
        Super-pixel stride of the exposure statistics (2: a quarter of the
        pixels of a 5 MP frame, 1.3 million samples).
    threads : int or None
        numba threads of the processing thread. Default: 1 on machines with
        at most 2 cores (a parallel kernel whose second thread is
        descheduled by the web server or another process waits a whole
        scheduler slice: on a busy 2-core machine one thread is 2-3 times
        faster), else numba's default.
    """

    exposure: ExposureParams | None = field(default_factory=ExposureParams)
    exposure_cap_us: float | None = None
    initial_settings: ExposureSettings | None = None
    preview_max_side: int = 640
    jpeg_quality: int = 80
    layout: Any = None
    analyser: Any = None
    dark_level: float = 0.0
    capture_dir: Path = Path("captures")
    record_dir: Path | None = None
    overlay: Any = None
    overlay_from_log: Callable[[dict[str, Any]], Any] | None = None
    record_queue: int = 8
    stats_stride: int = 2
    threads: int | None = None


class LiveEngine:
    """Runs a source through the live pipeline in a background thread (see the module notes).

    Parameters
    ----------
    source : FrameSource
    config : LiveConfig
    on_packet : callable, optional
        Called (from the engine thread) after each new packet or status change.
    """

    def __init__(self, source: FrameSource, config: LiveConfig | None = None,
                 on_packet: Callable[[], None] | None = None) -> None:
        from pihim.live.preview import PreviewRenderer

        self.source = source
        self.config = config or LiveConfig()
        self.on_packet = on_packet
        self.preview = PreviewRenderer(self.config.preview_max_side, self.config.jpeg_quality)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.seq = 0
        self.packet: bytes | None = None
        self.packet_t_raw = 0.0
        self.frame: LiveFrame | None = None
        self.frame_info: dict[str, Any] = {}
        self.error: str | None = None
        self.error_time: float | None = None
        self.last_error: dict[str, Any] | None = None
        self.status_seq = 0
        self.counters = collections.Counter()
        self.latencies_ms: collections.deque[float] = collections.deque(maxlen=2048)
        self.process_ms: collections.deque[float] = collections.deque(maxlen=2048)
        self.process_cpu_ms: collections.deque[float] = collections.deque(maxlen=2048)
        self.source_cpu_ms: collections.deque[float] = collections.deque(maxlen=2048)
        self._frame_times: collections.deque[float] = collections.deque(maxlen=64)
        self._state = ExposureState()
        self._commanded: ExposureSettings | None = None
        self._log_overlays: dict[str, Any] = {}
        self._record_q: queue.Queue | None = None
        self._record_thread: threading.Thread | None = None
        self.started_monotonic = time.monotonic()

    # ---------------------------------------------------------------- lifecycle

    def start(self) -> None:
        """Start the processing thread (and the recording thread with ``record_dir``)."""
        if self.source.controllable and (self.config.exposure is not None or self.config.initial_settings is not None):
            first = self.config.initial_settings or ExposureSettings(1000.0)  # also a fixed exposure, no controller
            self.source.set_exposure(first)
            self._commanded = first
        if self.config.record_dir is not None:
            self._record_q = queue.Queue(maxsize=self.config.record_queue)
            self._record_thread = threading.Thread(target=self._record_loop, name="pihim-live-record", daemon=True)
            self._record_thread.start()
        self._thread = threading.Thread(target=self._run, name="pihim-live-engine", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the threads and close the source."""
        self._stop.set()
        try:
            self.source.close()
        except Exception:  # noqa: BLE001 - closing a lost camera may fail
            pass
        if self._thread is not None:
            self._thread.join(timeout)
        if self._record_q is not None:
            self._record_q.put(None)
            if self._record_thread is not None:
                self._record_thread.join(timeout)

    # ---------------------------------------------------------------- loop

    def _set_error(self, message: str | None) -> None:
        with self._lock:
            if message is not None:
                self.last_error = {"message": message, "time_unix": time.time()}
            if message != self.error:
                self.error = message
                self.error_time = time.time() if message else None
                self.status_seq += 1
                changed = True
            else:
                changed = False
        if changed and self.on_packet is not None:
            self.on_packet()

    def _run(self) -> None:
        import os

        import numba

        threads = self.config.threads or (1 if (os.cpu_count() or 1) <= 2 else None)
        if threads is not None:
            numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
        self._warm_up()
        while not self._stop.is_set():
            c0 = time.thread_time()
            try:
                frame = self.source.read()
            except FrameError as exc:
                self.counters["frames_skipped"] += 1
                self._set_error(str(exc))
                continue
            except SourceLost as exc:
                self.counters["source_lost"] += 1
                self._set_error(f"{exc}; retrying")
                self._reconnect(str(exc))
                continue
            except Exception as exc:  # noqa: BLE001 - keep serving; show what happened
                self.counters["source_errors"] += 1
                self._set_error(f"source error: {type(exc).__name__}: {' '.join(str(exc).split())}")
                self._stop.wait(0.5)
                continue
            if self._stop.is_set():
                break
            self.source_cpu_ms.append(1e3 * (time.thread_time() - c0))
            try:
                self._process(frame)
            except Exception as exc:  # noqa: BLE001 - one bad frame must not stop the view
                self.counters["frames_failed"] += 1
                self._set_error(f"frame {frame.index}: {type(exc).__name__}: {' '.join(str(exc).split())}")

    def _warm_up(self) -> None:
        """Compile (or load from numba's cache) the kernels on a tiny frame before the first real one."""
        from pihim.camera.pipeline import polar_image

        tiny = np.full((4, 4), 100, np.uint16)
        region_stats(tiny, np.ones((2, 2), bool), bit_depth=12)
        region_stats(tiny, None, bit_depth=12)
        pol = polar_image(tiny, bit_depth=12)
        self.preview.render(pol.s0, pol.dolp, pol.aop_deg)

    def _reconnect(self, cause: str) -> None:
        while not self._stop.is_set():
            try:
                self.source.reconnect()
            except SourceLost as exc:
                self._set_error(f"{cause}; reconnecting: {exc}; retrying")
                self._stop.wait(1.0)
                continue
            except Exception as exc:  # noqa: BLE001
                self._set_error(f"{cause}; reconnect failed: {type(exc).__name__}: {exc}; retrying")
                self._stop.wait(1.0)
                continue
            if self._commanded is not None:
                self.source.set_exposure(self._commanded)
            return

    def _overlay_for(self, frame: LiveFrame) -> Any:
        log = frame.meta.get("log")
        if isinstance(log, dict) and self.config.overlay_from_log is not None:
            key = json.dumps([log.get("time"), log.get("pose")], sort_keys=True, default=str)
            if key not in self._log_overlays:
                try:
                    self._log_overlays[key] = self.config.overlay_from_log(log)
                except PihimInputError as exc:
                    self._log_overlays[key] = None
                    self._set_error(f"overlay: {exc}")
            if len(self._log_overlays) > 256:
                self._log_overlays.clear()
            return self._log_overlays[key]
        return self.config.overlay

    def _process(self, frame: LiveFrame) -> None:
        from pihim.camera.layout import IMX250MZR
        from pihim.camera.pipeline import polar_image

        t0 = frame.t_monotonic
        tp = time.monotonic()
        cpu0 = time.thread_time()
        cfg = self.config
        overlay = self._overlay_for(frame)
        region = frame.region
        region_kind = "source" if region is not None else "frame"
        h, w = frame.shape
        if region is None and overlay is not None and overlay.outlines:
            region = overlay.mirror_mask((h // 2, w // 2))
            region_kind = "outlines"
        stats = region_stats(frame.raw, region, bit_depth=frame.bit_depth, dark_level=cfg.dark_level,
                             stride=cfg.stats_stride)
        t_stats = time.monotonic()
        decision = None
        current = ExposureSettings(1000.0)
        if cfg.exposure is not None:
            current = self._commanded or frame.settings or ExposureSettings(1000.0)
            decision = next_exposure(stats, current, cfg.exposure, self._state, exposure_cap_us=cfg.exposure_cap_us)
            self._state = decision.state
            if self.source.controllable:
                if decision.changed:
                    self.source.set_exposure(decision.settings)
                    self.counters["exposure_commands"] += 1
                self._commanded = decision.settings
        pol = polar_image(frame.raw, layout=cfg.layout or IMX250MZR, analyser=cfg.analyser, demosaic="superpixel",
                          dark_level=cfg.dark_level, bit_depth=frame.bit_depth)
        t_polar = time.monotonic()
        imgs = self.preview.render(pol.s0, pol.dolp, pol.aop_deg)
        t_prev = time.monotonic()
        step = imgs.step
        dolp_small = pol.dolp[::step, ::step]
        if region is not None:
            rmask = region if region.shape == pol.shape else region[::2, ::2]
            sel = dolp_small[rmask[::step, ::step]]
        else:
            sel = dolp_small.ravel()
        sel = sel[np.isfinite(sel)]
        dolp_region = float(np.median(sel)) if sel.size else None
        self._frame_times.append(t0)
        fps = None
        if len(self._frame_times) >= 2 and self._frame_times[-1] > self._frame_times[0]:
            fps = (len(self._frame_times) - 1) / (self._frame_times[-1] - self._frame_times[0])
        shown = frame.settings or (self._commanded if self.source.controllable else None)
        header = {
            "schema": FRAME_SCHEMA_ID,
            "seq": self.seq + 1,
            "frame_index": frame.index,
            "time_unix": frame.time_unix,
            "t_raw_monotonic": t0,
            "width": int(w),
            "height": int(h),
            "preview": {"width": imgs.width, "height": imgs.height, "step": step * 2},
            "exposure": None if shown is None else shown.to_dict(),
            "controller": None if decision is None else {
                "reason": decision.reason,
                "next": decision.settings.to_dict(),
                "scale": decision.settings.brightness / current.brightness,
                "applies": self.source.controllable,
            },
            "region": region_kind,
            "region_stats": stats.to_dict(),
            "fraction_saturated_superpixels": float(pol.saturated.mean()),
            "dolp_mirrors": _finite_or_none(dolp_region),
            "dolp_usable": None if dolp_region is None or region is None else dolp_region >= MIRROR_DOLP_MIN,
            "fps": _finite_or_none(fps),
            "process_ms": {"stats": 1e3 * (t_stats - tp), "polar": 1e3 * (t_polar - t_stats),
                           "preview": 1e3 * (t_prev - t_polar), "total": 1e3 * (time.monotonic() - tp)},
            "wait_ms": 1e3 * (tp - t0),
            "source": {k: v for k, v in frame.meta.items() if k != "log"},
            "overlay": None if overlay is None else {"source": overlay.source, "outlines": overlay.normalized()},
            "error": self.error,
            "last_error": self.last_error,
            "counters": dict(self.counters),
        }
        packet = pack_packet(header, [("s0", imgs.s0), ("dolp", imgs.dolp), ("aop", imgs.aop)])
        info = {
            "source": self.source.describe(),
            "region": region_kind,
            "region_stats": stats.to_dict(),
            "fraction_saturated_superpixels": header["fraction_saturated_superpixels"],
            "dolp_mirrors": header["dolp_mirrors"],
            "pose": frame.meta.get("log", {}).get("pose") if isinstance(frame.meta.get("log"), dict) else None,
            "overlay_source": None if overlay is None else overlay.source,
        }
        with self._lock:
            self.seq += 1
            self.packet = packet
            self.packet_t_raw = t0
            self.frame = frame
            self.frame_info = info
            self.process_ms.append(1e3 * (time.monotonic() - tp))
            self.process_cpu_ms.append(1e3 * (time.thread_time() - cpu0))
            self.counters["frames"] += 1
        if self.error is not None and not self.error.startswith("overlay"):
            self._set_error(None)
        if self._record_q is not None:
            try:
                self._record_q.put_nowait((frame, info))
            except queue.Full:
                self.counters["record_dropped"] += 1
        if self.on_packet is not None:
            self.on_packet()

    # ---------------------------------------------------------------- outputs

    def latest(self) -> tuple[int, bytes | None, float]:
        """``(seq, packet, t_raw_monotonic)`` of the newest packet."""
        with self._lock:
            return self.seq, self.packet, self.packet_t_raw

    def record_send(self, t_raw: float) -> None:
        """Note that a packet whose frame arrived at ``t_raw`` has been written to a client."""
        self.latencies_ms.append(1e3 * (time.monotonic() - t_raw))

    def capture(self, label: str | None = None) -> dict[str, Any]:
        """Write the newest raw frame to the capture folder (see :func:`write_capture`)."""
        with self._lock:
            frame, info = self.frame, dict(self.frame_info)
        if frame is None:
            raise LookupError("no frame yet")
        record = write_capture(self.config.capture_dir, frame, info, label=label)
        self.counters["captures"] += 1
        return record

    def _record_loop(self) -> None:
        assert self._record_q is not None
        while True:
            item = self._record_q.get()
            if item is None:
                return
            frame, info = item
            try:
                write_capture(self.config.record_dir, frame, info)  # type: ignore[arg-type]
                self.counters["recorded"] += 1
            except Exception as exc:  # noqa: BLE001 - disk full etc.: say so, keep going
                self.counters["record_errors"] += 1
                self._set_error(f"--record: {type(exc).__name__}: {exc}")

    def status(self) -> dict[str, Any]:
        """JSON-ready state: counters, error, frame rate and latency figures."""

        def pct(values: collections.deque[float]) -> dict[str, float | None]:
            arr = np.array(values, float)
            if arr.size == 0:
                return {"p50": None, "p95": None, "max": None, "n": 0}
            p50, p95 = np.percentile(arr, [50, 95])
            return {"p50": float(p50), "p95": float(p95), "max": float(arr.max()), "n": int(arr.size)}

        with self._lock:
            lat, proc = collections.deque(self.latencies_ms), collections.deque(self.process_ms)
            pcpu, scpu = collections.deque(self.process_cpu_ms), collections.deque(self.source_cpu_ms)
            times = list(self._frame_times)
        fps = (len(times) - 1) / (times[-1] - times[0]) if len(times) >= 2 and times[-1] > times[0] else None
        return {
            "seq": self.seq,
            "error": self.error,
            "last_error": self.last_error,
            "counters": dict(self.counters),
            "fps": fps,
            "latency_ms": pct(lat),
            "process_ms": pct(proc),
            "process_cpu_ms": pct(pcpu),
            "source_cpu_ms": pct(scpu),
            "source": self.source.describe(),
            "commanded": None if self._commanded is None else self._commanded.to_dict(),
            "uptime_s": time.monotonic() - self.started_monotonic,
        }
