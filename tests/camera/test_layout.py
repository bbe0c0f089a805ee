"""Tests for the mosaic layout: default, parsing, ROI offsets and reversed read-out."""

import numpy as np
import pytest

from pihim.camera import IMX250MZR, MosaicLayout, polar_image
from pihim.errors import PihimInputError
from pihim.polarimetry import aop_difference_deg, stokes_from_dolp_aop
from pihim.render import mosaic_from_stokes


def test_default_is_imx250mzr():
    assert MosaicLayout() == IMX250MZR == MosaicLayout.parse("imx250mzr")
    assert IMX250MZR.angles_deg == ((90, 45), (135, 0))
    # channel order 0, 45, 90, 135 -> positions (1,1), (0,1), (0,0), (1,0)
    assert IMX250MZR.channel_positions == ((1, 1), (0, 1), (0, 0), (1, 0))
    assert str(IMX250MZR) == "90,45,135,0"


@pytest.mark.parametrize("text", ["0,45,90", "0,45,90,90", "a,b,c,d", "bayer", "0,45,90,136",
                                  # issue 10: OverflowError, and silent truncation to whole degrees
                                  "inf,45,90,135", "nan,45,90,135", "0.7,45.9,90.2,135.1", "1e400,45,90,135"])
def test_bad_layouts(text):
    with pytest.raises(PihimInputError):
        MosaicLayout.parse(text)


def test_parse_roundtrip_all_permutations():
    import itertools

    for perm in itertools.permutations([0, 45, 90, 135]):
        lay = MosaicLayout.parse(",".join(map(str, perm)))
        assert MosaicLayout.parse(str(lay)) == lay
        m = np.arange(16, dtype=np.uint16).reshape(4, 4)
        assert np.array_equal(lay.merge(lay.split(m)), m)


def _scene(shape=(32, 48)):
    rng = np.random.default_rng(3)
    h, w = shape
    s0 = np.full(shape, 1000.0)
    p = np.full(shape, 0.6)
    a = np.repeat(rng.uniform(0, 180, (h // 2, w // 2)), 2, 0).repeat(2, 1)  # constant per super-pixel
    return stokes_from_dolp_aop(s0, p, a), a


@pytest.mark.parametrize("oy, ox", [(0, 1), (1, 0), (1, 1)])
def test_odd_roi_offset(oy, ox):
    (s0, s1, s2), a = _scene((36, 52))
    sensor = mosaic_from_stokes(s0, s1, s2, IMX250MZR, bit_depth=None)
    crop = sensor[oy : oy + 32, ox : ox + 48]
    lay = MosaicLayout.from_sensor(offset_x=ox, offset_y=oy)
    # ground truth on the crop's super-pixel grid: the crop super-pixels straddle
    # scene super-pixels, so render a crop-aligned uniform scene instead
    s = stokes_from_dolp_aop(np.full((32, 48), 800.0), 0.5, 33.0)
    m = mosaic_from_stokes(*s, lay, bit_depth=None)
    out = polar_image(m, layout=lay)
    assert np.allclose(out.dolp, 0.5, atol=1e-4)
    assert np.allclose(aop_difference_deg(out.aop_deg, 33.0), 0.0, atol=1e-3)
    # the crop of the sensor mosaic is consistent with the shifted layout: the
    # pixel at crop (0, 0) carries the sensor's angle at (oy, ox)
    assert lay.angles_deg[0][0] == IMX250MZR.angles_deg[oy % 2][ox % 2]
    assert crop.shape == (32, 48)


@pytest.mark.parametrize("rx, ry", [(True, False), (False, True), (True, True)])
def test_reversed_readout_mirrors_aop(rx, ry):
    (s0, s1, s2), a = _scene()
    sensor = mosaic_from_stokes(s0, s1, s2, IMX250MZR, bit_depth=None)
    img = sensor[:: -1 if ry else 1, :: -1 if rx else 1]
    lay = MosaicLayout.from_sensor(reverse_x=rx, reverse_y=ry)
    out = polar_image(img, layout=lay)
    a_sp = a[::2, ::2][:: -1 if ry else 1, :: -1 if rx else 1]
    # one mirror flips orientation (a -> 180 - a), two mirrors restore it
    expected = (180.0 - a_sp) % 180.0 if rx != ry else a_sp
    assert np.max(aop_difference_deg(out.aop_deg, expected)) < 1e-3
    assert np.allclose(out.dolp, 0.6, atol=1e-5)
    # using the unreversed layout by mistake gives wrong angles
    wrong = polar_image(img, layout=IMX250MZR)
    assert np.max(aop_difference_deg(wrong.aop_deg, expected)) > 10.0


def test_reversal_mirrors_45_and_135():
    r = IMX250MZR.reversed_x()
    assert r.angles_deg == ((135, 90), (0, 45))
    assert IMX250MZR.reversed_x().reversed_x() == IMX250MZR


def test_split_rejects_bad_shapes():
    with pytest.raises(PihimInputError, match="even"):
        IMX250MZR.split(np.zeros((3, 4)))
    with pytest.raises(PihimInputError, match="2-D"):
        IMX250MZR.split(np.zeros((2, 4, 3)))


def test_whole_float_angles_accepted_fractional_refused():
    assert str(MosaicLayout.parse("90.0,45,135,0")) == "90,45,135,0"
    assert MosaicLayout(((90.0, 45.0), (135.0, 0.0))) == IMX250MZR
    for bad in (((90.5, 45), (135, 0)), ((float("inf"), 45), (135, 0))):
        with pytest.raises(PihimInputError):
            MosaicLayout(bad)
