"""Frame sources: folder replay, the synthetic simulated camera and the GenICam adapter (fake harvesters)."""

from __future__ import annotations

import time

import numpy as np
import pytest
import tifffile

from pihim.errors import PihimInputError
from pihim.live.engine import LiveConfig, LiveEngine
from pihim.live.exposure import ExposureParams, ExposureSettings
from pihim.live.sources import (
    FolderSource,
    FrameError,
    GenICamSource,
    SyntheticSource,
    check_source_options,
    open_source,
)

from .conftest import FakeCamera, FakeHarvester, mosaic


def test_folder_replay_order_loop_and_rate(frame_folder):
    src = FolderSource(frame_folder, fps=50.0)
    assert src.shape == (32, 40)
    assert [p.name for p in src.files] == ["f1.tiff", "f2.tiff", "f10.tiff"]  # natural order
    t0 = time.monotonic()
    frames = [src.read() for _ in range(7)]
    elapsed = time.monotonic() - t0
    levels = [int(np.median(f.raw)) for f in frames]
    assert levels == pytest.approx([1000, 2000, 3000, 1000, 2000, 3000, 1000], abs=3)  # loops
    assert [f.index for f in frames] == list(range(7))
    assert [f.meta["file"] for f in frames[:3]] == ["f1.tiff", "f2.tiff", "f10.tiff"]
    assert elapsed >= 6 / 50.0 * 0.95  # paced: 6 periods between 7 frames
    assert not src.controllable


def test_folder_replay_skips_the_images_pihim_writes_beside_frames(frame_folder):
    # pihim simulate's truth images and pihim polar's products / previews are not raw frames
    for tag in ("S0", "DoLP", "AoP", "labels"):
        tifffile.imwrite(frame_folder / f"f1.{tag}.tiff", np.zeros((32, 40), np.float32))
        (frame_folder / f"f2.{tag}.png").write_bytes(b"\x89PNG")
    for name in ("f1.polar.png", "f1.edges.S0.png", "f1.edges.combined.png", "f1.gradient.combined.tiff"):
        (frame_folder / name).write_bytes(b"\x89PNG")  # pihim polar's figure, pihim edges' maps
    tifffile.imwrite(frame_folder / "f11.v2.tiff", mosaic())  # a dotted name is still a frame
    src = FolderSource(frame_folder, fps=1000.0)
    assert [p.name for p in src.files] == ["f1.tiff", "f2.tiff", "f10.tiff", "f11.v2.tiff"]
    assert [src.read().meta["file"] for _ in range(4)] == ["f1.tiff", "f2.tiff", "f10.tiff", "f11.v2.tiff"]


def test_folder_of_derived_images_only_says_so(tmp_path):
    tifffile.imwrite(tmp_path / "run.S0.tiff", np.zeros((32, 40), np.float32))
    (tmp_path / "run.polar.png").write_bytes(b"\x89PNG")
    with pytest.raises(PihimInputError, match="no frames in the folder .*; 2 images pihim writes beside frames"):
        FolderSource(tmp_path)


def test_folder_wrong_size_frame_is_skipped_and_stream_goes_on(frame_folder):
    tifffile.imwrite(frame_folder / "f3.tiff", mosaic(shape=(16, 20)))
    (frame_folder / "f4.tiff").write_bytes(b"not a tiff")
    src = FolderSource(frame_folder, fps=1000.0)
    got, errors = [], []
    for _ in range(10):
        try:
            got.append(src.read().meta["file"])
        except FrameError as exc:
            errors.append(str(exc))
    assert any("f3.tiff: frame is 20x16 (WxH) but the stream is 40x32; skipped" in e for e in errors)
    assert any("f4.tiff" in e for e in errors)
    assert all("\n" not in e for e in errors)
    assert got[:3] == ["f1.tiff", "f2.tiff", "f10.tiff"] and "f1.tiff" in got[3:]


def test_folder_without_frames_and_missing_folder(tmp_path):
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / ".hidden.tiff").write_bytes(b"x")
    with pytest.raises(PihimInputError, match="no frames in the folder"):
        FolderSource(tmp_path)
    with pytest.raises(PihimInputError, match="no such folder"):
        FolderSource(tmp_path / "nope")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "a.tiff").write_bytes(b"junk")
    with pytest.raises(PihimInputError, match="none of its 1 frame files can be read"):
        FolderSource(bad)


def test_folder_sidecar_exposure_travels(frame_folder):
    import json

    (frame_folder / "f1.json").write_text(json.dumps({"schema": "pihim.live-capture/1",
                                                      "exposure": {"exposure_us": 250.0, "gain_db": 3.0}}))
    src = FolderSource(frame_folder, fps=1000.0)
    f = src.read()
    assert f.settings == ExposureSettings(250.0, 3.0)
    assert src.read().settings is None


@pytest.mark.parametrize(("spec", "options", "says"), [
    ("synthetic", {"pixel_format": "mono8"}, "--pixel-format does not apply to a synthetic source"),
    ("synthetic:flight", {"size": (64, 48)}, "--size does not apply to a rendered flight"),
    ("frames", {"size": (64, 48)}, "--size does not apply to a folder or a camera"),
    ("genicam", {"width": 8, "bit_depth": 12}, "--width and --bit-depth do not apply to a GenICam camera"),
    ("frames", {"pixel_format": "Bogus"}, "unknown pixel format 'Bogus'"),  # was 'applies only to .raw' for TIFFs
    (" ", {}, "--source is empty"),  # was "--source : no frames in the folder": the working directory
])
def test_options_of_another_source_are_refused(spec, options, says):
    with pytest.raises(PihimInputError, match=says):
        open_source(spec, **options)
    with pytest.raises(PihimInputError, match=says):
        check_source_options(spec, **options)
    check_source_options("genicam", pixel_format="Mono12")  # a camera's own format names (docs/live.md)
    check_source_options("genicam:123", pixel_format="PolarizeMono12")


def test_synthetic_source_responds_to_exposure():
    src = SyntheticSource((64, 80), fps=1000.0, scenes=1, brightness=(1.0,), drift_px=4, latency_frames=1,
                          settings=ExposureSettings(500.0))
    a = src.read()
    assert a.raw.shape == (64, 80) and a.raw.dtype == np.uint16 and a.bit_depth == 12
    assert a.region is not None and a.region.shape == (32, 40) and a.region.any()
    src.set_exposure(ExposureSettings(250.0))
    b = src.read()
    assert b.settings == ExposureSettings(250.0)
    # a linear sensor: half the exposure, half the signal (mirror pixels, well above the noise)
    m = np.kron(a.region, np.ones((2, 2), bool))
    assert np.median(b.raw[m].astype(float)) / np.median(a.raw[m].astype(float)) == pytest.approx(0.5, rel=0.05)


# --------------------------------------------------------------------------- GenICam through a fake harvesters


@pytest.fixture
def cams(monkeypatch):
    monkeypatch.setattr(FakeHarvester, "cameras", [])
    return FakeHarvester.cameras


def test_genicam_setup_and_frames(cams, fake_cti):
    cam = FakeCamera(rate=0.5)
    cams.append(cam)
    src = GenICamSource("TRI-0001", cti=fake_cti, fps=15.0, harvester_factory=FakeHarvester)
    nm = cam.node_map
    assert nm.ExposureAuto.value == "Off" and nm.GainAuto.value == "Off"
    assert nm.PixelFormat.value == "Mono12p"  # first of the preferred formats the camera offers
    assert nm.AcquisitionFrameRate.value == 15.0
    assert src.shape == (32, 40)
    src.set_exposure(ExposureSettings(2000.0, 6.0))
    assert nm.ExposureTime.value == 2000.0 and nm.Gain.value == 6.0
    f = src.read()
    assert f.raw.shape == (32, 40) and f.bit_depth == 12
    assert np.median(f.raw) == pytest.approx(0.5 * 2000 * 10 ** (6 / 20), abs=3)
    # out-of-range requests are clipped to the camera's ranges
    src.set_exposure(ExposureSettings(1e7, 40.0))
    assert nm.ExposureTime.value == 100_000.0 and nm.Gain.value == 24.0
    src.close()


def test_genicam_packed_buffer_is_unpacked(cams, fake_cti):
    cams.append(FakeCamera(packed=True, rate=0.5))
    src = GenICamSource(None, cti=fake_cti, harvester_factory=FakeHarvester)
    src.set_exposure(ExposureSettings(3000.0))
    f = src.read()
    assert f.raw.dtype == np.uint16 and np.median(f.raw) == pytest.approx(1500, abs=3)


def test_genicam_errors(cams, fake_cti, tmp_path, monkeypatch):
    monkeypatch.delenv("GENICAM_GENTL64_PATH", raising=False)
    with pytest.raises(PihimInputError, match="no GenTL producer"):
        GenICamSource(harvester_factory=FakeHarvester)
    with pytest.raises(PihimInputError, match="not a GenTL producer"):
        GenICamSource(cti=tmp_path / "x.so", harvester_factory=FakeHarvester)
    with pytest.raises(PihimInputError, match="no GenICam camera found"):
        GenICamSource(cti=fake_cti, harvester_factory=FakeHarvester)
    cams.append(FakeCamera(serial="A"))
    with pytest.raises(PihimInputError, match="cannot open camera B.*found: A"):
        GenICamSource("B", cti=fake_cti, harvester_factory=FakeHarvester)
    # the producer folder of GENICAM_GENTL64_PATH is searched for .cti files
    monkeypatch.setenv("GENICAM_GENTL64_PATH", str(fake_cti.parent))
    assert GenICamSource(harvester_factory=FakeHarvester).cti_files == [str(fake_cti)]


def test_genicam_without_harvesters_says_how_to_install(monkeypatch, fake_cti):
    import builtins

    real = builtins.__import__

    def no_harvesters(name, *args, **kwargs):
        if name.startswith("harvesters"):
            raise ImportError(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_harvesters)
    with pytest.raises(PihimInputError, match=r"pip install 'pihim\[genicam\]'"):
        open_source("genicam", cti=str(fake_cti))


def test_genicam_camera_lost_shows_error_and_comes_back(cams, fake_cti):
    """The engine shows the loss, keeps running, reconnects when the camera is back, and re-sends the exposure."""
    cam = FakeCamera(fail_after=3, rate=1.0)
    cams.append(cam)
    src = GenICamSource(None, cti=fake_cti, fps=100.0, harvester_factory=FakeHarvester)
    eng = LiveEngine(src, LiveConfig(exposure=ExposureParams(latency_frames=1), initial_settings=ExposureSettings(800.0),
                                     preview_max_side=64))
    eng.start()
    try:
        deadline = time.monotonic() + 20
        while eng.counters["source_lost"] == 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert eng.counters["source_lost"] >= 1
        time.sleep(0.3)
        assert eng.error is not None and "stopped delivering frames" in eng.error and "retrying" in eng.error
        seq = eng.seq
        cam.present, cam.fail_after = True, None  # plugged back in
        cam.node_map.ExposureTime.value = 5000.0  # a power cycle forgets the settings
        while eng.seq < seq + 3 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert eng.seq >= seq + 3
        assert eng.error is None and eng.last_error is not None
        assert cam.node_map.ExposureTime.value != 5000.0  # the controller's setting was written again
    finally:
        eng.stop()


def test_genicam_closed_loop_through_adapter(cams, fake_cti):
    """Adaptive exposure drives the fake camera's node map until its frames sit inside the band."""
    cam = FakeCamera(rate=3.0, shape=(64, 80))  # 5000 us initially would be far beyond full scale
    cams.append(cam)
    src = GenICamSource(None, cti=fake_cti, fps=200.0, harvester_factory=FakeHarvester)
    eng = LiveEngine(src, LiveConfig(exposure=ExposureParams(latency_frames=1), initial_settings=ExposureSettings(5000.0),
                                     preview_max_side=64, stats_stride=1))
    eng.start()
    try:
        deadline = time.monotonic() + 20
        while eng.seq < 40 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        eng.stop()
    level = 3.0 * cam.node_map.ExposureTime.value * 10 ** (cam.node_map.Gain.value / 20)
    # from clipped (15,000 DN asked) down into the band: at or above the soft median target less its 10 % dead
    # band, under the 0.85 limit
    assert 0.35 / 1.1 * 4095 * 0.95 < level < 0.85 * 4095
    assert eng.counters["exposure_commands"] >= 1
