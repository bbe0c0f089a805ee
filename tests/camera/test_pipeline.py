"""Tests for the raw-frame-to-Stokes pipeline (super-pixel route, bit depth, saturation)."""

import numpy as np
import pytest

from pihim.camera import MosaicLayout, polar_image
from pihim.camera.demosaic import superpixel
from pihim.camera.pipeline import BitDepth, resolve_bit_depth
from pihim.errors import PihimInputError
from pihim.polarimetry import AnalyserMatrix, aop_deg, aop_difference_deg, dolp, stokes_from_dolp_aop
from pihim.render import mosaic_from_stokes


def _varying_scene(shape=(64, 96), seed=0):
    rng = np.random.default_rng(seed)
    h, w = shape
    block = lambda lo, hi: np.repeat(np.repeat(rng.uniform(lo, hi, (h // 2, w // 2)), 2, 0), 2, 1)
    s0, p, a = block(200, 3000), block(0.0, 1.0), block(0, 180)
    return stokes_from_dolp_aop(s0, p, a), (s0[::2, ::2], p[::2, ::2], a[::2, ::2])


def test_exact_recovery_spatially_varying():
    (s0, s1, s2), (t0, tp, ta) = _varying_scene()
    m = mosaic_from_stokes(s0, s1, s2, bit_depth=None)
    out = polar_image(m)
    assert out.shape == (32, 48)
    assert np.allclose(out.s0, t0, rtol=1e-5)
    assert np.allclose(out.dolp, tp, atol=1e-5)
    sel = tp > 0.01
    assert np.max(aop_difference_deg(out.aop_deg, ta)[sel]) < 1e-3


def test_kernel_matches_numpy_reference_with_calibration_and_dark():
    (s0, s1, s2), _ = _varying_scene(seed=1)
    an = AnalyserMatrix.from_parameters([1.0, 46.5, 89.0, 134.0], [1.0, 0.95, 1.04, 0.98], [100, 200, 150, 300])
    lay = MosaicLayout.parse("0,45,135,90")
    m = mosaic_from_stokes(s0, s1, s2, lay, an, bit_depth=12, dark_level=64)
    out = polar_image(m, layout=lay, analyser=an, dark_level=64, bit_depth=12)
    ref = an.stokes(superpixel(m, lay) - 64.0)
    assert np.allclose(out.s0, ref[0], rtol=1e-5, atol=1e-3)
    assert np.allclose(out.s1, ref[1], rtol=1e-5, atol=1e-3)
    assert np.allclose(out.s2, ref[2], rtol=1e-5, atol=1e-3)
    ok = ref[0] > 0
    assert np.allclose(out.dolp[ok], dolp(*ref)[ok], atol=1e-5)
    # float32 kernel vs float64 reference: AoP is ill-conditioned as DoLP -> 0
    sel = ok & (dolp(*ref) > 0.02)
    d = aop_difference_deg(out.aop_deg[sel], aop_deg(ref[1], ref[2])[sel])
    assert np.max(d) < 2e-3


def test_saturated_superpixel_flagged_and_nan():
    s = stokes_from_dolp_aop(np.full((8, 8), 1000.0), 0.3, 20.0)
    m = mosaic_from_stokes(*s, bit_depth=12)
    m[2, 3] = 4095  # super-pixel (1, 1)
    out = polar_image(m, bit_depth=12)
    assert out.saturated[1, 1] and out.saturated.sum() == 1
    assert np.isnan(out.dolp[1, 1]) and np.isnan(out.aop_deg[1, 1])
    assert np.isfinite(np.delete(out.dolp.ravel(), 1 * 4 + 1)).all()
    assert out.summary()["fraction_saturated"] == pytest.approx(1 / 16)


def test_bit_depth_resolution():
    m12 = np.array([[0, 4095], [17, 100]], dtype=np.uint16)
    assert resolve_bit_depth(m12) == BitDepth(12)
    assert resolve_bit_depth(m12 << 4) == BitDepth(12, shift=4)  # MSB-aligned in 16-bit words
    assert resolve_bit_depth(np.array([[0, 40000], [1, 3]], np.uint16)) == BitDepth(16)
    assert resolve_bit_depth(np.zeros((2, 2), np.uint8)) == BitDepth(8)
    with pytest.raises(PihimInputError, match="exceed"):
        resolve_bit_depth(np.array([[0, 5000], [1, 3]], np.uint16), 12)
    with pytest.raises(PihimInputError, match="uint8 or uint16"):
        resolve_bit_depth(np.zeros((2, 2), np.int32))


def test_msb_aligned_12bit_gives_same_result():
    s = stokes_from_dolp_aop(np.full((8, 8), 3000.0), 0.4, 70.0)
    m = mosaic_from_stokes(*s, bit_depth=12)
    a = polar_image(m, bit_depth=12)
    b = polar_image(m << 4, bit_depth=12)
    assert np.array_equal(a.dolp, b.dolp) and np.array_equal(a.s0, b.s0)
    # full-scale 4095 stored MSB-aligned is 65520 and still counts as saturated
    m2 = m.copy()
    m2[0, 0] = 4095
    assert polar_image(m2 << 4, bit_depth=12).saturated[0, 0]


@pytest.mark.parametrize("bad", [np.zeros((3, 4), np.uint16), np.zeros((4,), np.uint16), np.zeros((4, 4, 3), np.uint8)])
def test_bad_shapes(bad):
    with pytest.raises(PihimInputError):
        polar_image(bad)


def test_unknown_demosaic():
    with pytest.raises(PihimInputError, match="demosaic"):
        polar_image(np.zeros((4, 4), np.uint16), demosaic="nearest")  # type: ignore[arg-type]


def test_summary_statistics():
    s = stokes_from_dolp_aop(np.full((16, 16), 1000.0), 0.25, 170.0)
    out = polar_image(mosaic_from_stokes(*s, bit_depth=None))
    summ = out.summary()
    assert summ["dolp"]["median"] == pytest.approx(0.25, abs=1e-5)
    assert aop_difference_deg(summ["aop"]["circular_mean_deg"], 170.0) < 1e-3
    assert summ["aop"]["resultant_length"] == pytest.approx(1.0)
    assert (summ["width"], summ["height"]) == (8, 8)


def test_accepts_the_frame_read_frame_returns(tmp_path):
    import tifffile

    from pihim.camera.frames import read_frame

    s, _ = _varying_scene()
    path = tmp_path / "f.tiff"
    tifffile.imwrite(path, mosaic_from_stokes(*s, bit_depth=12))
    frame = read_frame(path)
    a, b = polar_image(frame), polar_image(frame.data, bit_depth=frame.bit_depth)
    assert np.array_equal(a.dolp, b.dolp, equal_nan=True) and a.bit_depth == b.bit_depth
    with pytest.raises(PihimInputError, match=r"2-D array \(or the RawFrame read_frame returns; its array is \.data\)"):
        polar_image(np.float64(3.0))


def test_negative_dark_level_refused():
    with pytest.raises(PihimInputError, match="dark level must be a finite number of raw units >= 0, got -10"):
        polar_image(np.zeros((4, 4), np.uint16), dark_level=-10.0)


@pytest.mark.parametrize("mosaic", [np.full((4, 4), 100, np.uint16), np.full((4, 4), 100.0, np.float32)])
@pytest.mark.parametrize("levels, match", [
    # a saturation level at or below the dark level flags every pixel: all DoLP and AoP would be NaN
    (dict(saturation_level=-1.0), r"saturation level must be above the dark level \(0\)"),
    (dict(saturation_level=0.0), r"saturation level must be above the dark level \(0\)"),
    (dict(dark_level=100.0, saturation_level=50.0), r"above the dark level \(100\)"),
    (dict(saturation_level=float("nan")), "saturation level must be above"),
    # beyond float32 the kernels' cast overflows (numpy's warning, then infinities)
    (dict(saturation_level=1e300), r"at most 3\.403e\+38 \(float32\), got 1e\+300"),
    (dict(dark_level=1e300), r"dark level must be at most 3\.403e\+38 \(float32\)"),
])
def test_dark_and_saturation_levels_out_of_range_are_refused(mosaic, levels, match):
    with pytest.raises(PihimInputError, match=match):
        polar_image(mosaic, **levels)


def test_an_infinite_saturation_level_means_none():
    out = polar_image(np.full((4, 4), 60000.0, np.float32), saturation_level=float("inf"))
    assert not out.saturated.any()


@pytest.mark.parametrize("demosaic", ["superpixel", "full"])
def test_summary_matches_its_numpy_definition(demosaic):
    """The fast summary against the definitions computed with numpy on float64 copies."""
    import math

    (s0, s1, s2), _ = _varying_scene((96, 128), seed=3)
    m = mosaic_from_stokes(s0, s1, s2, bit_depth=12, rng=5, read_noise_dn=2.0, electrons_per_dn=2.5)
    m[10:20, 30:44] = 4095  # saturated block
    out = polar_image(m, demosaic=demosaic, bit_depth=12)
    got = out.summary()
    valid = np.isfinite(out.dolp)
    assert got["fraction_valid"] == valid.mean() and got["fraction_saturated"] == out.saturated.mean() > 0
    for key, image in (("s0", out.s0), ("dolp", out.dolp)):
        x = image[valid].astype(np.float64)
        p05, med, p95 = np.percentile(x, [5, 50, 95])
        assert (got[key]["p05"], got[key]["median"], got[key]["p95"]) == (p05, med, p95)  # exactly
        assert got[key]["mean"] == pytest.approx(x.mean(), rel=1e-12)
    u = np.hypot(out.s1[valid].astype(np.float64), out.s2[valid])
    c = np.mean(np.where(u > 0, out.s1[valid] / np.where(u > 0, u, 1), 1.0))
    s = np.mean(np.where(u > 0, out.s2[valid] / np.where(u > 0, u, 1), 0.0))
    assert got["aop"]["circular_mean_deg"] == pytest.approx(np.mod(0.5 * math.degrees(math.atan2(s, c)), 180), abs=1e-9)
    assert got["aop"]["resultant_length"] == pytest.approx(math.hypot(c, s), rel=1e-12)
    # and within the polynomial atan2's error (1e-4 deg per pixel, divided by the resultant length: the mean
    # vector moves by at most that error) of the circular mean of the AoP image itself
    a = np.radians(2.0 * out.aop_deg[valid].astype(np.float64))
    image_mean = np.mod(0.5 * np.degrees(np.arctan2(np.sin(a).mean(), np.cos(a).mean())), 180)
    assert aop_difference_deg(got["aop"]["circular_mean_deg"], image_mean) < 1.1e-4 / got["aop"]["resultant_length"]


def test_summary_of_a_frame_without_valid_pixels():
    out = polar_image(np.full((8, 8), 4095, np.uint16), bit_depth=12)
    got = out.summary()
    assert got["fraction_valid"] == 0.0 and got["fraction_saturated"] == 1.0
    assert got["s0"]["median"] is None and got["aop"]["circular_mean_deg"] is None


@pytest.mark.parametrize("demosaic", ["superpixel", "full"])
def test_out_writes_into_preallocated_arrays(demosaic):
    (s0, s1, s2), _ = _varying_scene(seed=4)
    m1 = mosaic_from_stokes(s0, s1, s2, bit_depth=12)
    m2 = mosaic_from_stokes(s0[::-1], s1[::-1], s2[::-1], bit_depth=12)
    buf = polar_image(m1, demosaic=demosaic)
    again = polar_image(m2, demosaic=demosaic, out=buf)
    fresh = polar_image(m2, demosaic=demosaic)
    for name in ("s0", "s1", "s2", "dolp", "aop_deg", "saturated"):
        assert getattr(again, name) is getattr(buf, name)
        assert np.array_equal(getattr(again, name), getattr(fresh, name), equal_nan=True)
    with pytest.raises(PihimInputError, match=r"out.s0 must be a writeable C-contiguous float32 array of shape"):
        polar_image(m1[:, :-2], demosaic=demosaic, out=buf)


def test_large_outputs_are_disjoint_views_of_one_aligned_block():
    """A frame-sized result lives in one block starting on a 2 MiB boundary (huge pages), each image apart."""
    from pihim.camera.pipeline import PolarImage

    rng = np.random.default_rng(7)
    raw = rng.integers(0, 4000, (1024, 1024), dtype=np.uint16)
    raw[:2, :2] = 4095  # one saturated super-pixel
    got = polar_image(raw, bit_depth=12)
    arrays = [got.s0, got.s1, got.s2, got.dolp, got.aop_deg, got.saturated]
    assert got.s0.ctypes.data % (2 << 20) == 0
    assert all(a.flags.c_contiguous and a.flags.writeable and a.shape == (512, 512) for a in arrays)
    assert [a.dtype for a in arrays] == [np.float32] * 5 + [np.bool_]
    for i, a in enumerate(arrays):
        for b in arrays[i + 1:]:
            assert not np.shares_memory(a, b)
    separate = PolarImage(*(np.empty((512, 512), np.float32) for _ in range(5)), np.empty((512, 512), np.bool_),
                          "superpixel", None)
    ref = polar_image(raw, bit_depth=12, out=separate)
    for a, b in zip(arrays, [ref.s0, ref.s1, ref.s2, ref.dolp, ref.aop_deg, ref.saturated], strict=True):
        assert np.array_equal(a, b, equal_nan=True)
    assert got.saturated[0, 0] and np.isnan(got.dolp[0, 0]) and got.saturated.sum() == 1


@pytest.mark.parametrize(("kwargs", "says"), [
    ({"layout": "imx250mzr"}, "layout must be a MosaicLayout"),  # was an AttributeError
    ({"analyser": np.tile([0.5, 0.5, 0.0], (4, 1))}, "analyser must be an AnalyserMatrix"),  # "truth value ambiguous"
    ({"dark_level": "5"}, "dark_level must be a number, got '5'"),  # TypeError
    ({"bit_depth": "12"}, "bit_depth must be a number"),
    ({"bit_depth": True}, "bit_depth must be a number, got True"),  # said "True-bit"
])
def test_arguments_of_the_wrong_kind_are_named(kwargs, says):
    raw = np.full((4, 4), 100, np.uint16)
    with pytest.raises(PihimInputError, match=says):
        polar_image(raw, **kwargs)
    assert polar_image(raw, bit_depth=12.0).bit_depth == BitDepth(12)  # a whole float is its number of bits
    with pytest.raises(PihimInputError, match="bit_depth must be a whole number of bits, got 12.5"):
        polar_image(raw, bit_depth=12.5)


@pytest.mark.parametrize(("bits", "shift"), [(0, 0), (17, 0), (12, -1), (12, 5), (True, 0), (12.0, 0)])
def test_a_bit_depth_that_fits_no_16_bit_word_is_refused(bits, shift):
    """BitDepth(0) and BitDepth(12, shift=-1) were accepted."""
    with pytest.raises(PihimInputError, match="BitDepth|do not fit a 16-bit word"):
        BitDepth(bits, shift=shift)
    assert BitDepth(12, shift=4).full_scale == 4095
