"""Tests for the polarimetric colour renderings."""

import cv2
import numpy as np
import pytest

from pihim.errors import PihimInputError
from pihim.visualize import aop_to_rgb, dolp_to_rgb, polar_figure_png, s0_to_gray, write_png


def test_aop_hue_is_cyclic_and_ordered():
    rgb = aop_to_rgb(np.array([0.0, 60.0, 120.0, 179.999, 180.0]))
    assert tuple(rgb[0]) == (255, 0, 0)  # 0 deg red
    assert tuple(rgb[1]) == (0, 255, 0)  # 60 deg green
    assert tuple(rgb[2]) == (0, 0, 255)  # 120 deg blue
    assert np.abs(rgb[3].astype(int) - rgb[0].astype(int)).max() <= 1  # wraps: 180 == 0
    assert tuple(rgb[4]) == tuple(rgb[0])


def test_aop_brightness_follows_dolp_and_nan_is_black():
    rgb = aop_to_rgb(np.array([30.0, 30.0, np.nan, 30.0]), np.array([1.0, 0.25, 0.5, np.nan]))
    assert rgb[0].max() == 255 and rgb[1].max() == 64
    assert rgb[2].max() == 0 and rgb[3].max() == 0
    with pytest.raises(PihimInputError):
        aop_to_rgb(np.zeros(3), np.zeros(4))


def test_dolp_map_is_monotonic_in_luminance():
    rgb = dolp_to_rgb(np.linspace(0, 1, 11)).astype(float)
    luma = rgb @ [0.2126, 0.7152, 0.0722]
    assert np.all(np.diff(luma) > 0)
    assert dolp_to_rgb(np.array([np.nan])).max() == 0


def test_s0_stretch_and_png_roundtrip(tmp_path):
    s0 = np.linspace(0, 1000, 64).reshape(8, 8)
    g = s0_to_gray(s0, percentiles=(0, 100))
    assert g.min() == 0 and g.max() == 255 and g.dtype == np.uint8
    rgb = aop_to_rgb(np.full((4, 4), 120.0))
    p = write_png(tmp_path / "a.png", rgb)
    back = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)[..., ::-1]
    assert np.array_equal(back, rgb)  # written as RGB, not BGR
    assert [f.name for f in tmp_path.iterdir()] == ["a.png"]


@pytest.mark.parametrize("atomic", [True, False])
def test_polar_figure_png_atomic_or_in_place(tmp_path, atomic):
    """Atomic: a new file renamed over the old one (new inode); ``atomic=False``: written in place (same inode)."""
    rng = np.random.default_rng(0)
    s0 = rng.uniform(1000, 2000, (40, 50))
    dolp = rng.uniform(0, 1, (40, 50))
    aop = rng.uniform(0, 180, (40, 50))
    path = tmp_path / "f.polar.png"
    path.write_bytes(b"old")
    inode = path.stat().st_ino
    assert polar_figure_png(s0, dolp, aop, path, title="t", dpi=50, atomic=atomic) == path
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.shape[:2] == (220, 800)  # 16 x 4.4 in at 50 dpi
    assert (path.stat().st_ino == inode) is (not atomic)
    assert [f.name for f in tmp_path.iterdir()] == ["f.polar.png"]


def test_polar_figure_png_refuses_mismatched_shapes(tmp_path):
    with pytest.raises(PihimInputError, match="one shape"):
        polar_figure_png(np.zeros((4, 4)), np.zeros((4, 5)), np.zeros((4, 4)), tmp_path / "x.png")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("backend", ["default", "zlib"])
def test_png_encoder_roundtrip_through_opencv(backend, monkeypatch):
    """The small encoder's files decode (by OpenCV's libpng) to the same pixels, with ISA-L or with zlib."""
    import zlib

    from pihim import _png

    if backend == "zlib":
        monkeypatch.setattr(_png, "_deflate", zlib)
    rng = np.random.default_rng(3)
    for shape in [(1, 1), (5, 7), (5, 7, 3), (3, 4, 4), (257, 300, 3)]:
        img = rng.integers(0, 256, shape, dtype=np.uint8)
        back = cv2.imdecode(np.frombuffer(_png.encode_png(img), np.uint8), cv2.IMREAD_UNCHANGED)
        if img.ndim == 3:
            back = back[..., [2, 1, 0, 3][: img.shape[2]]]  # OpenCV returns BGR(A)
        assert np.array_equal(back, img), shape
    with pytest.raises(ValueError):
        _png.encode_png(np.zeros((2, 2), np.float32))


def test_polar_figure_is_reused_and_follows_each_frame(tmp_path):
    """Frames of one size share the laid-out figure; each PNG still shows its own images and S0 range."""
    import pihim.visualize as vis

    rng = np.random.default_rng(1)
    s0 = rng.uniform(1000, 2000, (60, 80)).astype(np.float32)
    dolp = rng.uniform(0, 0.6, (60, 80)).astype(np.float32)
    aop = rng.uniform(0, 180, (60, 80)).astype(np.float32)
    a = vis.polar_figure_png(s0, dolp, aop, tmp_path / "a.png", title="a")
    figure = next(iter(vis._FIGURES.values()))
    b = vis.polar_figure_png(s0 * 10, dolp[::-1], aop, tmp_path / "b.png", title="b")
    assert next(iter(vis._FIGURES.values())) is figure  # not laid out again
    ia, ib = (cv2.imread(str(p))[..., ::-1] for p in (a, b))
    assert ia.shape == ib.shape and not np.array_equal(ia, ib)
    # the DoLP panel shows the flipped DoLP: its pixels come from dolp_to_rgb of the data (inside the axes frame)
    r0, r1, c0, c1, rows, cols = figure._boxes[1]
    shown = dolp_to_rgb(dolp[::-1]).take(rows, 0).take(cols, 1)
    assert np.array_equal(ib[r0 + 2:r1 - 2, c0 + 2:c1 - 2], shown[2:-2, 2:-2])
    with pytest.raises(PihimInputError, match="laid out for"):
        figure.render(s0[:10], dolp[:10], aop[:10])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_colourings_equal_the_numpy_formulation(dtype):
    """2-D images take the compiled kernels, other shapes the numpy formulation: same pixels, edge values too."""
    rng = np.random.default_rng(7)
    a = rng.uniform(-400, 400, (60, 50)).astype(dtype)
    a.flat[:8] = [np.nan, np.inf, -0.0, 180.0, -1e-17, 1e300 if dtype == np.float64 else 3e38, 359.99999, -180.0]
    d = rng.uniform(-0.2, 1.5, a.shape).astype(dtype)
    d.flat[10:13] = [np.nan, np.inf, 0.5]
    s = rng.normal(1000, 300, a.shape).astype(dtype)
    s.flat[20:23] = [np.nan, np.inf, -np.inf]
    assert np.array_equal(aop_to_rgb(a, d), aop_to_rgb(a[None], d[None])[0])
    assert np.array_equal(aop_to_rgb(a, d, dolp_max=0.3), aop_to_rgb(a[None], d[None], dolp_max=0.3)[0])
    assert np.array_equal(aop_to_rgb(a), aop_to_rgb(a[None])[0])
    assert np.array_equal(dolp_to_rgb(d, vmax=0.5), dolp_to_rgb(d[None], vmax=0.5)[0])
    assert np.array_equal(s0_to_gray(s), s0_to_gray(s.ravel()).reshape(s.shape))


def test_ordinal_suffixes():
    from pihim.visualize import _ordinal

    assert [_ordinal(n) for n in (1, 2, 3, 4, 11, 12, 13, 21, 22, 102, 111)] == [
        "1st", "2nd", "3rd", "4th", "11th", "12th", "13th", "21st", "22nd", "102nd", "111th"]
