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


def _colour_bar(lo, hi):
    """A figure with one vertical grey colour bar over ``[lo, hi]``, drawn by matplotlib."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    fig = Figure(figsize=(2.0, 4.0), dpi=110)
    canvas = FigureCanvasAgg(fig)
    cax = fig.add_axes((0.2, 0.1, 0.12, 0.8))
    bar = fig.colorbar(ScalarMappable(Normalize(lo, hi), cmap="gray"), cax=cax)
    cax.tick_params(labelsize=7)
    canvas.draw()
    return canvas, bar


_RANGES = [(437.2, 4512.9), (500.0, 4400.0), (30001.0, 30009.5), (0.013, 0.52), (-20.0, 20.0), (1.0, 65535.0),
           (437.2, 4512.9)]


def test_bar_ticks_draw_what_matplotlib_draws():
    """The figure's S0 colour bar ticks (:class:`_BarTicks`) against matplotlib's own colour bar of each range.

    The same label strings (offset text included), the same tick-mark and
    offset-text pixels, and each label's ink within a pixel of where
    matplotlib draws it (ours sit on whole pixels). Labels kept from earlier
    frames are stamped: the last range repeats the first, after others.
    """
    from pihim.visualize import _BarTicks

    canvas, bar = _colour_bar(0.0, 60000.0)  # laid out once, as PolarFigure does
    ticks = _BarTicks(bar)
    canvas.draw()
    background = canvas.copy_from_bbox(canvas.figure.bbox)
    right = int(np.ceil(bar.ax.bbox.x1)) + 1  # the bar itself is the background's
    for lo, hi in _RANGES:
        ref_canvas, ref_bar = _colour_bar(lo, hi)
        want = np.asarray(ref_canvas.buffer_rgba())[..., :3]
        canvas.restore_region(background)
        drawn = ticks.draw(lo, hi, np.asarray(canvas.buffer_rgba()))
        got = np.asarray(canvas.buffer_rgba())[..., :3]
        height = want.shape[0]
        span = hi - lo
        labels = [t for t in ref_bar.ax.get_yticklabels() if lo - 1e-9 * span <= t.get_position()[1] <= hi + 1e-9 * span]
        assert [t.get_text() for t in labels] == [text for _, text in drawn] and len(drawn) >= 3, (lo, hi)
        covered = np.zeros(want.shape[:2], bool)
        for label in labels:
            box = label.get_window_extent()
            r0, r1 = height - int(np.ceil(box.y1)) - 2, height - int(np.floor(box.y0)) + 2
            c0, c1 = int(np.floor(box.x0)) - 1, int(np.ceil(box.x1)) + 1
            ink = [255 - img[r0:r1, c0:c1].min(axis=2).astype(float) for img in (got, want)]
            centres = [np.array([(w * np.arange(w.shape[0])[:, None]).sum(), (w * np.arange(w.shape[1])).sum()])
                       / w.sum() for w in ink]
            assert np.abs(centres[0] - centres[1]).max() <= 1.0, (lo, hi, label)
            assert abs(ink[0].sum() / ink[1].sum() - 1.0) < 0.1  # the same glyphs
            covered[r0 - 1:r1 + 1, c0:c1] = True
        outside = np.ones(want.shape[:2], bool)
        outside[:, :right] = False
        outside &= ~covered
        assert np.array_equal(got[outside], want[outside]), (lo, hi)  # tick marks and offset text exactly
        offset = ref_bar.ax.yaxis.get_offset_text().get_text()
        assert (offset != "") == ((lo, hi) == (30001.0, 30009.5)), offset


def test_bar_ticks_stamped_labels_equal_drawn_ones():
    """A label kept from an earlier frame and stamped gives the pixels of drawing it afresh."""
    from pihim.visualize import _BarTicks

    def frames(warm):
        canvas, bar = _colour_bar(0.0, 60000.0)
        ticks = _BarTicks(bar)
        canvas.draw()
        background = canvas.copy_from_bbox(canvas.figure.bbox)
        out = []
        for lo, hi in (warm + [(437.2, 4512.9), (512.5, 4388.0)]):
            canvas.restore_region(background)
            ticks.draw(lo, hi, np.asarray(canvas.buffer_rgba()))
            out.append(np.asarray(canvas.buffer_rgba()).copy())
        return out[len(warm):], ticks

    fresh, fresh_ticks = frames([])
    stamped, ticks = frames([(480.0, 4501.0), (390.0, 4410.0)])
    assert set(fresh_ticks._stamps) <= set(ticks._stamps)
    for a, b in zip(fresh, stamped, strict=True):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("shape", [(40, 30), (1, 40, 30)])  # the compiled and the numpy path
def test_colourings_write_into_out(shape):
    """``out=`` gives the same pixels in the array passed (reused frame to frame), whatever it held before."""
    rng = np.random.default_rng(11)
    a = rng.uniform(0, 180, shape).astype(np.float32)
    d = rng.uniform(0, 1, shape).astype(np.float32)
    s = rng.normal(1000, 300, shape).astype(np.float32)
    d.flat[3] = np.nan
    cases = [(lambda **k: aop_to_rgb(a, d, **k), (*shape, 3)), (lambda **k: dolp_to_rgb(d, **k), (*shape, 3)),
             (lambda **k: s0_to_gray(s, **k), shape)]
    for colour, out_shape in cases:
        out = rng.integers(0, 256, out_shape, dtype=np.uint8)
        assert colour(out=out) is out
        assert np.array_equal(out, colour())
        with pytest.raises(PihimInputError, match="out must be"):
            colour(out=np.zeros((2, *out_shape), np.uint8))


@pytest.mark.parametrize("level", [0, 1, 3, 6, 9])
def test_png_levels_decode_to_the_same_pixels(level):
    """Every deflate level gives the same pixels (OpenCV's libpng); level 0 stores the rows uncompressed."""
    from pihim import _png

    img = np.random.default_rng(level).integers(0, 256, (61, 47, 3), dtype=np.uint8)
    data = _png.encode_png(img, level=level)
    back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)[..., ::-1]
    assert np.array_equal(back, img)
    rows = 61 * (1 + 47 * 3)
    if level == 0:  # stored blocks: the rows, 5 bytes per block of up to 65535, zlib's 6 and the chunks' 57
        assert rows < len(data) <= rows + 5 * (rows // 65535 + 1) + 6 + 57
    with pytest.raises(ValueError, match="0-9"):
        _png.encode_png(img, level=10)


@pytest.mark.parametrize("shape", [(1, 1), (1024, 1224, 3), (300, 700, 3), (35, 40), (9, 7, 4), (2, 22000, 3)])
def test_stored_png_decodes_and_checks_out(tmp_path, shape):
    """Level 0 laid out block by block (whole rows per stored block, the last one partial): libpng decodes it
    (checking the CRCs and zlib's Adler-32), zlib inflates it, and ``write_png`` writes the same file."""
    import zlib

    from pihim import _png
    from pihim.visualize import write_png

    img = np.random.default_rng(sum(shape)).integers(0, 256, shape, dtype=np.uint8)
    data = _png.encode_png(img, level=0)
    back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img.ndim == 3:
        back = back[..., [2, 1, 0, 3][: img.shape[2]]]
    assert np.array_equal(back, img)
    stream = zlib.decompress(data[41:-16])  # IDAT data: the zlib stream, its Adler-32 checked
    rows = np.frombuffer(stream, np.uint8).reshape(shape[0], -1)
    assert not rows[:, 0].any() and np.array_equal(rows[:, 1:], img.reshape(shape[0], -1))
    if img.ndim == 2 or img.shape[2] == 3:
        assert write_png(tmp_path / "x.png", img, level=0).read_bytes() == data
    assert (_png.stored_png(img) is None) == (shape[1] * (shape[2] if img.ndim == 3 else 1) + 1 > 65535)
