"""Tests for the sensor model of the renderer (Stokes image -> 12-bit raw mosaic)."""

import json
import math

import numpy as np
import pytest

from pihim.camera.layout import IMX250MZR
from pihim.errors import PihimInputError
from pihim.polarimetry import AnalyserMatrix
from pihim.render import Exposure, SensorModel, choose_exposure, expose, mosaic_from_stokes
from pihim.render.sensor import lens_blur


def _uniform(shape, s0, s1=0.0, s2=0.0):
    return (np.full(shape, float(s0)), np.full(shape, float(s1)), np.full(shape, float(s2)))


# -- noise figures -------------------------------------------------------------------


def test_default_sensor_is_triton_datasheet():
    s = SensorModel()
    assert s.full_scale_dn == 4095
    assert s.full_well_e == pytest.approx(10**3.9)  # 39 dB = 10 log10(N)
    assert 20 * math.log10(s.full_well_e / s.read_noise_e) == pytest.approx(71.0)
    assert s.electrons_per_dn * 4095 == pytest.approx(s.full_well_e)
    assert s.read_noise_dn == pytest.approx(s.read_noise_e / s.electrons_per_dn)
    d = json.loads(json.dumps(s.describe()))
    assert d["full_scale_dn"] == 4095 and d["layout"] == str(IMX250MZR)
    # the dark level eats into the range: full well maps to full scale minus dark
    assert SensorModel(dark_level_dn=95).electrons_per_dn * 4000 == pytest.approx(s.full_well_e)


def test_snr_near_full_well_is_39_db():
    sensor = SensorModel()
    fill = 0.95  # keep > 4 sigma from full scale so clipping does not bias the std
    s = _uniform((1024, 1024), 2.0)
    exp = choose_exposure(*s, sensor, headroom=fill)
    assert exp.clipped_fraction == 0.0
    raw = expose(*s, sensor, exp, rng=1)
    ch = IMX250MZR.split(raw)[0].astype(float) - sensor.dark_level_dn
    snr_db = 20 * math.log10(ch.mean() / ch.std())
    # measured at 95 % of full well: the datasheet figure within 0.3 dB ...
    assert abs(snr_db - 39.0) < 0.3
    # ... and the exact model: shot + read + quantisation noise at that level
    n = fill * sensor.full_well_e
    var_e = n + sensor.read_noise_e**2 + sensor.electrons_per_dn**2 / 12
    assert snr_db == pytest.approx(10 * math.log10(n**2 / var_e), abs=0.03)
    # extrapolated to full well (shot-noise limited) it is 39 dB
    assert snr_db - 10 * math.log10(fill) == pytest.approx(39.0, abs=0.05)
    assert ch.mean() == pytest.approx(fill * 4095, rel=1e-3)


def test_dark_frame_std_is_read_noise():
    sensor = SensorModel(dark_level_dn=100.0)
    raw = expose(*_uniform((1024, 1024), 0.0), sensor, Exposure(gain_dn=1.0), rng=2)
    v = raw.astype(float)
    assert v.mean() == pytest.approx(100.0, abs=0.01)
    assert v.std() == pytest.approx(sensor.read_noise_dn, rel=0.05)
    # quantisation adds 1/12 DN^2 (Sheppard), the rest is read noise
    assert v.std() == pytest.approx(math.sqrt(sensor.read_noise_dn**2 + 1 / 12), rel=0.01)


# -- exposure -------------------------------------------------------------------------


def _scene():
    """64x64: unpolarized background S0 = 1, top row S0 = 5 polarized at 45 deg (DoLP 0.4)."""
    s0, s1, s2 = _uniform((64, 64), 1.0)
    s0[0], s2[0] = 5.0, 2.0
    return s0, s1, s2


@pytest.mark.parametrize("dark", [0.0, 100.0])
def test_choose_exposure_maps_percentile_to_headroom(dark):
    sensor = SensorModel(dark_level_dn=dark)
    s = _scene()
    exp = choose_exposure(*s, sensor, percentile=99.9, headroom=0.8)
    # the top 64 of 4096 pixels hold the 99.9th percentile; AoP = 45 deg is the
    # 45 deg channel's axis, so the brightest channel is (S0 + sqrt(S1^2 + S2^2)) / 2
    ref = (5.0 + math.hypot(0.0, 2.0)) / 2
    assert exp.reference == pytest.approx(ref, rel=1e-12)
    assert exp.gain_dn == pytest.approx(0.8 * (4095 - dark) / ref, rel=1e-12)
    assert exp.clipped_fraction == 0.0
    raw = expose(*s, sensor, exp, noise=False)
    c45 = IMX250MZR.split(raw)[1]
    assert raw.max() == c45[0].max() == round(dark + 0.8 * (4095 - dark))
    assert json.loads(json.dumps(exp.describe()))["percentile"] == 99.9


def test_brightest_channel_is_max_over_analyser_rows():
    # AoP 30 deg lies between channels: the brightest channel (45 deg) sees less
    # than an analyser at the AoP would
    c, d = math.cos(math.radians(60)), math.sin(math.radians(60))
    s0, s1, s2 = _uniform((4, 4), 5.0, 5 * 0.4 * c, 5 * 0.4 * d)
    exp = choose_exposure(s0, s1, s2, SensorModel(), percentile=100)
    assert exp.reference == pytest.approx((5.0 + s2[0, 0]) / 2, rel=1e-12)
    # a calibrated analyser is used as given
    a = AnalyserMatrix.from_parameters([0, 45, 90, 135], [1.0, 1.1, 1.0, 1.0], 100.0)
    exp = choose_exposure(s0, s1, s2, SensorModel(analyser=a), percentile=100)
    assert exp.reference == pytest.approx(float(np.max(a.matrix @ [5.0, s1[0, 0], s2[0, 0]])))


def test_headroom_above_one_clips():
    sensor = SensorModel()
    s = _scene()
    assert choose_exposure(*s, sensor, headroom=0.9).clipped_fraction == 0.0
    exp = choose_exposure(*s, sensor, headroom=1.2)
    # only the 32 top-row pixels of the 45 deg channel exceed full scale
    # (the 90 deg channel there sees 2.5 / 3.5 * 1.2 < 1)
    assert exp.clipped_fraction == pytest.approx(32 / 4096)
    raw = expose(*s, sensor, exp, noise=False)
    assert np.mean(raw == 4095) == pytest.approx(exp.clipped_fraction)


def test_mask_and_non_finite_pixels():
    sensor = SensorModel()
    s0, s1, s2 = _scene()
    mask = np.ones(s0.shape, bool)
    mask[0] = False
    exp = choose_exposure(s0, s1, s2, sensor, mask=mask, headroom=0.9)
    assert exp.reference == pytest.approx(0.5)  # unpolarized background: S0 / 2
    assert exp.clipped_fraction == pytest.approx(64 / 4096)  # the whole bright row
    # NaN pixels are left out without a mask, refused inside one
    s0n = s0.copy()
    s0n[10, 10] = np.nan
    gain = choose_exposure(s0, s1, s2, sensor).gain_dn
    assert choose_exposure(s0n, s1, s2, sensor).gain_dn == pytest.approx(gain)
    with pytest.raises(PihimInputError, match="non-finite"):
        choose_exposure(s0n, s1, s2, sensor, mask=mask)


@pytest.mark.parametrize("case", ["zero", "empty_mask", "all_nan"])
def test_nothing_to_expose_for(case):
    s0, s1, s2 = _uniform((8, 8), 0.0 if case == "zero" else 1.0)
    mask = np.zeros(s0.shape, bool) if case == "empty_mask" else None
    if case == "all_nan":
        s0[:] = np.nan
    with pytest.raises(PihimInputError, match="nothing bright enough to expose for"):
        choose_exposure(s0, s1, s2, SensorModel(), mask=mask)


# -- reproducibility, output type ------------------------------------------------------------


def test_seed_reproducibility():
    sensor = SensorModel(dark_level_dn=50.0)
    s = _scene()
    exp = choose_exposure(*s, sensor)
    a = expose(*s, sensor, exp, rng=7, blur_sigma_px=1.0)
    b = expose(*s, sensor, exp, rng=7, blur_sigma_px=1.0)
    c = expose(*s, sensor, exp, rng=8, blur_sigma_px=1.0)
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()


@pytest.mark.parametrize("bits", [12, 8])
def test_output_dtype_and_range(bits):
    sensor = SensorModel(bit_depth=bits)
    s = _scene()
    raw = expose(*s, sensor, choose_exposure(*s, sensor, headroom=1.2), rng=3)
    assert raw.dtype == np.uint16 and raw.shape == (64, 64)
    assert raw.max() == 2**bits - 1  # clipped on purpose, never beyond full scale


# -- lens blur ----------------------------------------------------------------------------


def test_blur_zero_is_identity():
    sensor = SensorModel()
    s = _scene()
    exp = choose_exposure(*s, sensor)
    a = expose(*s, sensor, exp, rng=5, blur_sigma_px=0.0)
    assert a.tobytes() == expose(*s, sensor, exp, rng=5).tobytes()
    ref = mosaic_from_stokes(
        *(exp.gain_dn * x for x in s),
        electrons_per_dn=sensor.electrons_per_dn,
        read_noise_dn=sensor.read_noise_dn,
        rng=5,
    )
    assert a.tobytes() == ref.astype(np.uint16).tobytes()
    for x, y in zip(lens_blur(*s, 0.0), s):
        assert np.array_equal(x, y)


def test_blur_preserves_uniform_mean():
    s = _uniform((32, 48), 3.0, 0.5, -0.25)
    for x, v in zip(lens_blur(*s, 2.5), (3.0, 0.5, -0.25)):
        assert np.allclose(x, v, rtol=0, atol=1e-12)
    sensor = SensorModel()
    exp = choose_exposure(*s, sensor)
    blurred = expose(*s, sensor, exp, blur_sigma_px=2.5, noise=False).astype(int)
    sharp = expose(*s, sensor, exp, noise=False).astype(int)
    # equal up to round-off at a half-DN rounding boundary (0.9 * 4095 = 3685.5)
    assert np.abs(blurred - sharp).max() <= 1
    assert blurred.mean() == pytest.approx(sharp.mean(), abs=0.5)


def _second_moments(img, c):
    w = img / img.sum()
    y, x = np.indices(img.shape)
    return float(np.sum(w * (y - c) ** 2)), float(np.sum(w * (x - c) ** 2))


@pytest.mark.parametrize("sigma", [1.0, 2.0, 3.5])
def test_blur_spreads_point_with_sigma(sigma):
    s0, s1, s2 = _uniform((64, 64), 0.0)
    s0[32, 32] = 1.0
    b0, b1, b2 = lens_blur(s0, s1, s2, sigma)
    assert b0.sum() == pytest.approx(1.0)
    assert not b1.any() and not b2.any()
    vy, vx = _second_moments(b0, 32)
    assert math.sqrt(vy) == pytest.approx(sigma, rel=0.01)
    assert math.sqrt(vx) == pytest.approx(sigma, rel=0.01)
    # through the sensor (noise-free, unpolarized: raw = gain * S0 / 2 on every channel)
    peak = 1 / (2 * math.pi * sigma**2)
    exp = Exposure(gain_dn=2 * 3900 / peak)
    raw = expose(s0, s1, s2, SensorModel(), exp, blur_sigma_px=sigma, noise=False).astype(float)
    assert raw.sum() == pytest.approx(exp.gain_dn / 2, rel=0.005)
    vy, vx = _second_moments(raw, 32)
    assert math.sqrt(vy) == pytest.approx(sigma, rel=0.02)
    assert math.sqrt(vx) == pytest.approx(sigma, rel=0.02)


# -- bad input ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"bit_depth": 0}, "bit_depth"),
        ({"bit_depth": 17}, "bit_depth"),
        ({"bit_depth": 12.0}, "bit_depth"),
        ({"snr_db": 0.0}, "snr_db"),
        ({"snr_db": -3.0}, "snr_db"),
        ({"snr_db": float("nan")}, "snr_db"),
        ({"dynamic_range_db": 0.0}, "dynamic_range_db"),
        ({"dark_level_dn": -1.0}, "dark_level_dn"),
        ({"dark_level_dn": 4095.0}, "dark_level_dn"),
        ({"analyser": "ideal"}, "analyser"),
        ({"layout": "90,45,135,0"}, "layout"),
    ],
)
def test_bad_sensor(kwargs, match):
    with pytest.raises(PihimInputError, match=match):
        SensorModel(**kwargs)


def test_bad_exposure_and_expose_inputs():
    sensor = SensorModel()
    s = _scene()
    exp = choose_exposure(*s, sensor)
    with pytest.raises(PihimInputError, match="blur_sigma_px"):
        expose(*s, sensor, exp, blur_sigma_px=-1.0)
    s0n = s[0].copy()
    s0n[3, 4] = np.nan
    with pytest.raises(PihimInputError, match="non-finite"):
        expose(s0n, s[1], s[2], sensor, exp)
    with pytest.raises(PihimInputError, match="even"):
        expose(*(x[:, :63] for x in s), sensor, exp)
    for g in (0.0, -1.0, float("inf")):
        with pytest.raises(PihimInputError, match="gain_dn"):
            Exposure(gain_dn=g)
    for kw in ({"percentile": 0.0}, {"percentile": 101.0}, {"headroom": 0.0}):
        with pytest.raises(PihimInputError):
            choose_exposure(*s, sensor, **kw)


@pytest.mark.parametrize(("kwargs", "says"), [
    ({"s0": np.full((4, 4), np.nan)}, "must be finite to be quantised"),  # was an all-zero mosaic and a warning
    ({"dark_level": np.nan}, "dark_level must be a finite number >= 0"),  # was zeros too
    ({"read_noise_dn": -5.0}, "read_noise_dn must be"),  # was silently no noise
    ({"bit_depth": 12.5}, "bit_depth must be an integer"),
    ({"layout": "imx250mzr"}, "layout must be a MosaicLayout"),  # was an AttributeError
    ({"electrons_per_dn": np.nan}, "electrons_per_dn must be a finite number > 0"),
])
def test_mosaic_from_stokes_refuses_what_it_used_to_turn_into_zeros(kwargs, says):
    args = {"s0": np.full((4, 4), 100.0), "s1": 0.0, "s2": 0.0, **kwargs}
    with pytest.raises(PihimInputError, match=says):
        mosaic_from_stokes(args.pop("s0"), args.pop("s1"), args.pop("s2"), **args)
    # the float mosaic keeps a NaN where the scene has one (nothing is quantised)
    assert np.isnan(mosaic_from_stokes(np.full((4, 4), np.nan), 0.0, 0.0, bit_depth=None)).all()


@pytest.mark.parametrize(("name", "value"), [("percentile", 200.0), ("percentile", -1.0), ("clipped_fraction", 1.5)])
def test_an_exposure_record_out_of_range_is_refused(name, value):
    """Exposure(1, percentile=200) was accepted."""
    with pytest.raises(PihimInputError, match=f"{name} must be in"):
        Exposure(1.0, **{name: value})
