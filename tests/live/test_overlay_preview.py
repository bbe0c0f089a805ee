"""Heliostat outline overlay (analytic pinhole geometry) and the preview colours (against pihim.visualize)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import tifffile

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose
from pihim.field import UFACET_AIM_POINT, nsttf_like_field, track_field
from pihim.live.engine import LiveConfig, LiveEngine, unpack_packet
from pihim.live.overlay import overlay_from_log, project_outlines
from pihim.live.preview import PreviewRenderer
from pihim.live.sources import FolderSource
from pihim.sky.sun import NSTTF, sun_position
from pihim.visualize import aop_to_rgb, dolp_to_rgb

from .conftest import mosaic

TIME = "2021-05-13T13:00-06:00"
RANGE_M = 40.0


@pytest.fixture(scope="module")
def frontal():
    """The field at TIME and a camera RANGE_M in front of 8E3 on its mirror normal, looking at its centre."""
    field = nsttf_like_field()
    fp = track_field(field, sun_position(NSTTF, TIME).vector, np.asarray(UFACET_AIM_POINT, float))
    i = field.names.index("8E3")
    c, n = fp.mirror_centres[i], fp.normals[i]
    pose = CameraPose.look_at(c + RANGE_M * n, c)
    return field, fp, i, pose


def test_frontal_outline_matches_pinhole_geometry(frontal):
    field, fp, i, pose = frontal
    cam = CameraModel()
    ov = project_outlines(cam, pose, fp.mirror_outline(), list(field.names), "test")
    assert "8E3" in ov.names
    pts = ov.outlines[ov.names.index("8E3")]
    # centred on the principal point
    assert pts.mean(axis=0) == pytest.approx([cam.cx_px, cam.cy_px], abs=0.5)
    # a rectangle facing the camera at range R: sides f * W / R and f * H / R pixels
    spec = field.spec
    w_px = cam.fx_px * 2 * spec.mirror_half_width_m / RANGE_M
    h_px = cam.fy_px * 2 * spec.mirror_half_height_m / RANGE_M
    assert np.ptp(pts[:, 0]) == pytest.approx(w_px, rel=1e-3) or np.ptp(pts[:, 0]) == pytest.approx(h_px, rel=1e-3)
    assert np.ptp(pts[:, 0]) * np.ptp(pts[:, 1]) == pytest.approx(w_px * h_px, rel=2e-3)
    # the rasterised region covers that area (in super-pixels of a half-size mask)
    mask = ov.mirror_mask((cam.height_px // 2, cam.width_px // 2))
    assert mask.sum() == pytest.approx(w_px * h_px / 4, rel=0.03)


def _log(field, pose, cam, heliostats=()):
    return {"time": TIME, "site": NSTTF.as_dict(), "aim_point_m": list(UFACET_AIM_POINT), "camera": cam.to_dict(),
            "pose": pose.to_dict(), "heliostats": list(heliostats)}


def test_overlay_from_log_uses_logged_drive_angles(frontal):
    field, fp, i, pose = frontal
    cam = CameraModel()
    direct = project_outlines(cam, pose, fp.mirror_outline(), list(field.names))
    from_log = overlay_from_log(field, _log(field, pose, cam))
    k = from_log.names.index("8E3")
    np.testing.assert_allclose(from_log.outlines[k], direct.outlines[direct.names.index("8E3")], atol=1e-6)
    # a logged heliostat 5 deg off in azimuth is drawn where it was logged, not where it should be
    da = fp.drive
    moved = overlay_from_log(field, _log(field, pose, cam, [{"name": "8E3", "az_deg": float(da.azimuth_deg[i]) + 5.0,
                                                               "el_deg": float(da.elevation_deg[i])}]))
    shift = np.abs(moved.outlines[moved.names.index("8E3")] - from_log.outlines[k]).max()
    assert shift > 50


def test_engine_draws_outlines_from_frame_logs(frontal, tmp_path):
    field, fp, i, pose = frontal
    cam = CameraModel()
    d = tmp_path / "replay"
    d.mkdir()
    tifffile.imwrite(d / "a.tiff", mosaic(shape=(64, 80)))
    (d / "a.json").write_text(json.dumps({"schema": "pihim.simulated-frame/1", "log": _log(field, pose, cam)}))
    src = FolderSource(d, fps=100.0)
    eng = LiveEngine(src, LiveConfig(exposure=None, preview_max_side=64,
                                     overlay_from_log=lambda log: overlay_from_log(field, log)))
    eng._process(src.read())  # noqa: SLF001 - one frame, synchronously
    header, _ = unpack_packet(eng.latest()[1])
    assert header["region"] == "outlines"
    names = [o["name"] for o in header["overlay"]["outlines"]]
    assert "8E3" in names
    pts = np.array(header["overlay"]["outlines"][names.index("8E3")]["points"])
    assert pts.mean(axis=0) == pytest.approx([0.5, 0.5], abs=2e-3)  # normalised: the image centre


def test_preview_colours_match_visualize():
    pr = PreviewRenderer(max_side=64)
    rng = np.random.default_rng(1)
    dolp = rng.random((48, 64)).astype(np.float32)
    aop = (rng.random((48, 64)) * 180).astype(np.float32)
    s0 = rng.random((48, 64)).astype(np.float32) * 1000
    dolp[0, :5] = np.nan
    aop[0, :5] = np.nan
    from pihim.live import _kernels

    g = np.empty((48, 64), np.uint8)
    dd = np.empty((48, 64, 3), np.uint8)
    aa = np.empty((48, 64, 3), np.uint8)
    _kernels.colorize(s0, dolp, aop, 1, 0.0, 255.0 / 1000.0, 255.0, pr._dolp_lut, 180, 64, pr._aop_lut, g, dd, aa)  # noqa: SLF001
    ref_d = dolp_to_rgb(dolp)[..., ::-1]
    ref_a = aop_to_rgb(aop, dolp)[..., ::-1]
    ok = np.isfinite(dolp)
    # DoLP: 256 levels, the same colour map; AoP: 1-degree hue bins and 64 brightness levels
    assert np.abs(dd[ok].astype(int) - ref_d[ok]).max() <= 3
    assert np.percentile(np.abs(aa[ok].astype(int) - ref_a[ok]), 99) <= 12
    assert (dd[~ok] == 0).all() and (aa[~ok] == 0).all()
    assert np.abs(g.astype(int) - np.clip(np.rint(s0 * 0.255), 0, 255)).max() <= 1
    # the JPEGs decode to the decimated size
    imgs = pr.render(np.kron(s0, np.ones((4, 4), np.float32)), np.kron(dolp, np.ones((4, 4), np.float32)),
                     np.kron(aop, np.ones((4, 4), np.float32)))
    assert imgs.step == 4 and (imgs.height, imgs.width) == (48, 64)  # 192x256 in 64 px: every 4th
    assert cv2.imdecode(np.frombuffer(imgs.aop, np.uint8), cv2.IMREAD_COLOR).shape == (48, 64, 3)


def test_rendered_flight_source(frontal, tmp_path):
    """A folder laid out as ``pihim simulate`` writes it: re-exposed live, mirrors from labels, pose for outlines."""
    from pihim.live.exposure import ExposureSettings
    from pihim.live.sources import open_source
    from pihim.render.scenes import edge_scene

    field, fp, i, pose = frontal
    cam = CameraModel(width_px=80, height_px=64, focal_length_mm=35.0 * 80 / 2448)
    s0, s1, s2 = edge_scene((64, 80), rng=2)
    labels = np.zeros((64, 80, 7), np.int32)
    labels[..., 0] = np.where(np.hypot(s1, s2) / s0 > 0.12, 4, 2)  # mirror / ground
    d = tmp_path / "flight"
    d.mkdir()
    tifffile.imwrite(d / "v0.S0.tiff", s0.astype(np.float32))
    tifffile.imwrite(d / "v0.DoLP.tiff", (np.hypot(s1, s2) / s0).astype(np.float32))
    tifffile.imwrite(d / "v0.AoP.tiff", np.mod(np.degrees(0.5 * np.arctan2(s2, s1)), 180).astype(np.float32))
    tifffile.imwrite(d / "v0.labels.tiff", labels)
    log = {**_log(field, pose, cam), "sensor": {"exposure": {"gain_dn": 1.0}}}
    (d / "v0.json").write_text(json.dumps({"schema": "pihim.simulated-frame/1", "log": log, "truth": {}}))
    src = open_source(f"synthetic:{d}", fps=1000.0)
    assert src.controllable and src.shape == (64, 80)
    f = src.read()
    from pihim.render.mosaic import mosaic_from_stokes

    mosaic_ideal = mosaic_from_stokes(s0, s1, s2, bit_depth=None)
    # 1000 us at 0 dB reproduces the rendered exposure, up to shot and read noise
    assert np.median(f.raw.astype(float) - mosaic_ideal) == pytest.approx(0.0, abs=2.0)
    sp = (labels[..., 0] == 4).reshape(32, 2, 40, 2).all(axis=(1, 3))
    assert np.array_equal(f.region, sp)
    assert f.meta["log"]["pose"] == pose.to_dict()
    src.set_exposure(ExposureSettings(500.0))
    src.read()
    g = src.read()
    assert g.settings == ExposureSettings(500.0)
    assert np.median(g.raw[np.kron(sp, np.ones((2, 2), bool))].astype(float)) == pytest.approx(
        0.5 * np.median(mosaic_ideal[np.kron(sp, np.ones((2, 2), bool))]), rel=0.05)


@pytest.mark.parametrize(("level", "grey"), [(8190.0, 255), (0.0, 0)])
def test_a_flat_frame_shows_its_level(level, grey):
    """A frame clipped everywhere has nothing to stretch: S0 shows white (its level against 0), not black; an
    all-zero frame stays black."""
    s0 = np.full((48, 64), level, np.float32)
    nan = np.full_like(s0, np.nan)  # DoLP and AoP of clipped pixels
    imgs = PreviewRenderer(max_side=64).render(s0, nan, nan)
    assert (cv2.imdecode(np.frombuffer(imgs.s0, np.uint8), cv2.IMREAD_GRAYSCALE) == grey).all()
