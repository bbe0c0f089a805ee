"""Shared pieces of the live-view tests: small frames and a fake harvesters camera."""

from __future__ import annotations

import contextlib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import tifffile

from pihim.camera.frames import pack_mono12p


def mosaic(shape=(32, 40), value=1000, seed=0) -> np.ndarray:
    """A 12-bit raw mosaic with a little noise and a known value level."""
    rng = np.random.default_rng(seed)
    return np.clip(value + rng.normal(0, 5, size=shape), 0, 4095).astype(np.uint16)


@pytest.fixture
def frame_folder(tmp_path: Path) -> Path:
    """A folder of three small TIFF frames with distinct levels, named so that natural order differs from text order."""
    d = tmp_path / "frames"
    d.mkdir()
    for name, value in (("f2.tiff", 2000), ("f10.tiff", 3000), ("f1.tiff", 1000)):
        tifffile.imwrite(d / name, mosaic(value=value))
    return d


class FakeNode:
    """A GenICam feature node: value, range, symbolics; records writes."""

    def __init__(self, value, lo=None, hi=None, symbolics=(), writable=True):
        self._value = value
        self.min, self.max = lo, hi
        self.symbolics = tuple(symbolics)
        self.writable = writable
        self.writes = []

    @property
    def value(self):
        return self._value

    @value.setter
    def value(self, v):
        if not self.writable:
            raise RuntimeError("AccessException: node not writable")
        if self.symbolics and v not in self.symbolics:
            raise RuntimeError(f"InvalidArgumentException: {v!r}")
        if self.min is not None and not self.min <= v <= self.max:
            raise RuntimeError(f"OutOfRangeException: {v!r}")
        self.writes.append(v)
        self._value = v


class FakeCamera:
    """The camera behind the fake harvesters: a uniform scene whose raw level follows ExposureTime and Gain.

    ``fail_after`` frames it raises (unplugged); ``packed`` delivers Mono12p bytes instead of unpacked pixels.
    """

    def __init__(self, serial="TRI-0001", shape=(32, 40), rate=2.0, fail_after=None, packed=False):
        self.serial = serial
        self.shape = shape
        self.rate = rate  # DN per us at 0 dB
        self.fail_after = fail_after
        self.packed = packed
        self.delivered = 0
        self.present = True
        h, w = shape
        self.node_map = SimpleNamespace(
            ExposureAuto=FakeNode("Continuous", symbolics=("Off", "Continuous")),
            GainAuto=FakeNode("Continuous", symbolics=("Off", "Continuous")),
            PixelFormat=FakeNode("Mono8", symbolics=("Mono8", "Mono12p", "Mono16")),
            AcquisitionFrameRateEnable=FakeNode(False),
            AcquisitionFrameRate=FakeNode(10.0, 1.0, 30.0),
            ExposureTime=FakeNode(5000.0, 15.0, 100_000.0),
            Gain=FakeNode(0.0, 0.0, 24.0),
            Width=FakeNode(w),
            Height=FakeNode(h),
        )

    def frame(self):
        nm = self.node_map
        level = self.rate * nm.ExposureTime.value * 10 ** (nm.Gain.value / 20)
        return np.clip(mosaic(self.shape, level, seed=self.delivered), 0, 4095).astype(np.uint16)


class FakeAcquirer:
    def __init__(self, cam: FakeCamera):
        self.cam = cam
        self.remote_device = SimpleNamespace(node_map=cam.node_map)
        self.started = False

    def start(self):
        self.started = True

    def stop(self):
        self.started = False

    def destroy(self):
        pass

    @contextlib.contextmanager
    def fetch(self, timeout=0):
        cam = self.cam
        if not cam.present or (cam.fail_after is not None and cam.delivered >= cam.fail_after):
            cam.present = False
            raise RuntimeError("GenTL IoException: device removed")
        raw = cam.frame()
        cam.delivered += 1
        h, w = cam.shape
        if cam.packed:
            data, fmt = np.frombuffer(pack_mono12p(raw), np.uint8), "PolarizeMono12p"
        else:
            data, fmt = raw.ravel(), cam.node_map.PixelFormat.value
        comp = SimpleNamespace(data=data, width=w, height=h, data_format=fmt)
        yield SimpleNamespace(payload=SimpleNamespace(components=[comp]))


class FakeHarvester:
    """The parts of ``harvesters.core.Harvester`` that pihim uses."""

    cameras: list[FakeCamera] = []

    def __init__(self):
        self.files = []
        self.device_info_list = []

    def add_file(self, path):
        self.files.append(path)

    def update(self):
        self.device_info_list = [SimpleNamespace(serial_number=c.serial) for c in self.cameras if c.present]

    def create(self, key):
        present = [c for c in self.cameras if c.present]
        if isinstance(key, dict):
            match = [c for c in present if c.serial == key.get("serial_number")]
            if not match:
                raise ValueError("no device found")
            return FakeAcquirer(match[0])
        return FakeAcquirer(present[key])

    def reset(self):
        pass


@pytest.fixture
def fake_cti(tmp_path: Path) -> Path:
    p = tmp_path / "Producer.cti"
    p.write_bytes(b"\0")
    return p
