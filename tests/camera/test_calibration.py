"""Tests of the rotating-polarizer calibration of the analyser matrix."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pihim._atomic import write_json_atomic
from pihim.camera import IMX250MZR, MosaicLayout, polar_image
from pihim.camera.calibration import (
    PolarizerCalibration,
    calibrate_polarizer,
    default_roi,
    fit_analyser,
    measure_channel_means,
)
from pihim.camera.frames import RawFrame
from pihim.errors import PihimInputError
from pihim.polarimetry import AnalyserMatrix, aop_difference_deg, stokes_from_dolp_aop
from pihim.render import mosaic_from_stokes

#: A plausibly bad sensor: unequal gains, 1-2 deg axis offsets, finite extinction ratios.
TRUE = AnalyserMatrix.from_parameters(
    [1.5, 46.2, 88.8, 136.7], [1.0, 0.93, 1.06, 0.97], [120.0, 80.0, 300.0, 150.0]
)
TRUE_T = TRUE.transmission / TRUE.transmission.mean()  # calibration normalises the mean gain to 1
ANGLES = np.arange(0.0, 180.0, 15.0)
DARK = 64.0


def render_calibration_frames(
    angles,
    analyser=TRUE,
    *,
    shape=(128, 128),
    level=3000.0,
    polarizer_dolp=1.0,
    drift=None,
    vignetting=0.15,
    layout=IMX250MZR,
    bit_depth=12,
    noise=True,
    seed=0,
):
    """Frames of a vignetted, uniformly lit scene behind a polarizer at each angle.

    Noise model: Poisson shot noise at 2 e-/DN, 2.5 DN read noise, 12-bit
    quantisation and clipping, a dark offset of ``DARK`` DN.
    """
    rng = np.random.default_rng(seed)
    h, w = shape
    yy, xx = np.mgrid[:h, :w]
    falloff = 1.0 - vignetting * (((yy - h / 2) ** 2 + (xx - w / 2) ** 2) / (h * h / 4))
    frames = []
    for j, a in enumerate(angles):
        g = 1.0 if drift is None else drift[j]
        s = stokes_from_dolp_aop(level * g * falloff, polarizer_dolp, a)
        frames.append(
            mosaic_from_stokes(
                *s,
                layout=layout,
                analyser=analyser,
                bit_depth=bit_depth,
                dark_level=DARK if noise else 0.0,
                read_noise_dn=2.5 if noise else 0.0,
                electrons_per_dn=2.0 if noise else None,
                rng=rng,
            )
        )
    return frames


def assert_recovers(cal: PolarizerCalibration, *, t_rel=5e-3, ang_deg=0.1, d_abs=2e-3, true=TRUE):
    t_true = true.transmission / true.transmission.mean()
    assert np.max(np.abs(cal.transmission / t_true - 1)) < t_rel
    assert np.max(aop_difference_deg(cal.angles_deg, true.angles_deg)) < ang_deg
    assert np.max(np.abs(cal.diattenuation - true.diattenuation)) < d_abs


@pytest.fixture(scope="module")
def noisy_calibration():
    return calibrate_polarizer(render_calibration_frames(ANGLES), ANGLES, dark_level=DARK)


# -- recovery -------------------------------------------------------------------------


@pytest.mark.parametrize("layout", [IMX250MZR, MosaicLayout(((0, 45), (135, 90))), IMX250MZR.reversed_x()])
def test_noiseless_recovery_is_exact(layout):
    frames = render_calibration_frames(
        ANGLES[::2], layout=layout, bit_depth=None, noise=False, shape=(16, 24), vignetting=0.0
    )
    cal = calibrate_polarizer(frames, ANGLES[::2], layout=layout)
    scale = TRUE.transmission.mean()
    assert np.allclose(cal.matrix, TRUE.matrix / scale, atol=1e-12)
    assert np.all(cal.residual_rms_relative < 1e-12)
    assert cal.warnings == ()
    # the source level in DN of S0 as seen by a channel of transmission 1
    assert cal.source_s0_dn == pytest.approx(3000 * scale)


def test_wrong_layout_is_not_silently_accepted():
    frames = render_calibration_frames(ANGLES, bit_depth=None, noise=False, shape=(16, 16), vignetting=0.0)
    cal = calibrate_polarizer(frames, ANGLES, layout=MosaicLayout(((45, 90), (0, 135))))
    assert not np.allclose(cal.angles_deg, TRUE.angles_deg, atol=1)
    assert any("off nominal" in w for w in cal.warnings)


def test_noisy_recovery_meets_tolerances(noisy_calibration):
    cal = noisy_calibration
    assert_recovers(cal, t_rel=5e-3, ang_deg=0.1, d_abs=2e-3)
    # the extinction ratios (120, 80, 300, 150) are the most sensitive quantity
    assert np.allclose(cal.extinction_ratio, TRUE.extinction_ratio, rtol=0.15)
    assert cal.n_frames == ANGLES.size
    assert np.all(cal.residual_rms_relative < 2e-3)
    assert cal.condition_number == pytest.approx(np.linalg.cond(cal.matrix))
    assert cal.design_condition_number == pytest.approx(np.sqrt(2))
    assert cal.roi == default_roi((128, 128)) == (32, 32, 64, 64)
    assert cal.superpixels_used == 32 * 32 and cal.fraction_excluded == 0.0
    assert cal.bit_depth.bits == 12 and cal.warnings == ()


def test_black_clipping_is_flagged():
    frames = [np.clip(f.astype(np.int32) - 100, 0, None).astype(np.uint16) for f in render_calibration_frames(ANGLES)]
    cal = calibrate_polarizer(frames, ANGLES)
    assert any("read 0" in w for w in cal.warnings)


def test_without_dark_subtraction_diattenuation_is_biased():
    frames = render_calibration_frames(ANGLES)
    cal = calibrate_polarizer(frames, ANGLES, dark_level=0.0)
    # a 64 DN offset on ~1500 DN channels lowers the apparent diattenuation by ~4%
    assert np.all(TRUE.diattenuation - cal.diattenuation > 0.02)


def _patch_scene(seed=3):
    """Uniform patches of known DoLP x AoP; returns raw mosaic and the truth per patch."""
    dolps = np.array([0.1, 0.3, 0.6, 0.9])
    aops = np.arange(0.0, 180.0, 30.0)
    p = 32  # pixels per patch side -> 256 super-pixels per patch
    d = np.kron(dolps[:, None] * np.ones((1, aops.size)), np.ones((p, p)))
    a = np.kron(np.ones((dolps.size, 1)) * aops[None], np.ones((p, p)))
    raw = mosaic_from_stokes(
        *stokes_from_dolp_aop(2500.0, d, a),
        analyser=TRUE,
        dark_level=DARK,
        read_noise_dn=2.5,
        electrons_per_dn=2.0,
        rng=seed,
    )
    return raw, dolps, aops, p // 2


def _patch_errors(raw, analyser, dolps, aops, q):
    """Max DoLP error over all patches and max AoP error over patches with DoLP >= 0.3.

    Errors are of the patch-mean Stokes vector, so they measure bias, not pixel noise.
    """
    img = polar_image(raw, analyser=analyser, dark_level=DARK)
    shape = (dolps.size, q, aops.size, q)
    s0, s1, s2 = (x.reshape(shape).mean(axis=(1, 3)) for x in (img.s0, img.s1, img.s2))
    d_err = np.abs(np.hypot(s1, s2) / s0 - dolps[:, None])
    a_err = aop_difference_deg(np.degrees(0.5 * np.arctan2(s2, s1)), aops[None])
    return d_err.max(), a_err[dolps >= 0.3].max()


def test_calibrated_analyser_beats_ideal_on_a_test_scene(noisy_calibration):
    raw, dolps, aops, q = _patch_scene()
    d_cal, a_cal = _patch_errors(raw, noisy_calibration.analyser, dolps, aops, q)
    d_ideal, a_ideal = _patch_errors(raw, None, dolps, aops, q)
    d_true, a_true = _patch_errors(raw, TRUE, dolps, aops, q)
    # calibrated: small in absolute terms, and as good as knowing the true analyser
    assert d_cal < 4e-3 and a_cal < 0.3
    assert d_cal < d_true + 1e-3 and a_cal < a_true + 0.05
    # uncalibrated: the gain and axis errors show up clearly
    assert d_ideal > 0.05 and a_ideal > 2.0
    assert d_cal < d_ideal / 10 and a_cal < a_ideal / 5


def test_noiseless_test_scene_per_pixel(noisy_calibration):
    """Per-pixel DoLP/AoP on a noise-free scene: only the calibration error remains."""
    rng = np.random.default_rng(7)
    d = np.kron(rng.uniform(0.2, 1.0, (16, 16)), np.ones((2, 2)))
    a = np.kron(rng.uniform(0.0, 180.0, (16, 16)), np.ones((2, 2)))
    raw = mosaic_from_stokes(*stokes_from_dolp_aop(2000.0, d, a), analyser=TRUE, bit_depth=None)
    cal = polar_image(raw, analyser=noisy_calibration.analyser)
    ideal = polar_image(raw)
    d_cal, d_ideal = (np.abs(x.dolp - d[::2, ::2]).max() for x in (cal, ideal))
    a_cal, a_ideal = (aop_difference_deg(x.aop_deg, a[::2, ::2]).max() for x in (cal, ideal))
    assert d_cal < 2e-3 and a_cal < 0.1
    assert d_cal < d_ideal / 10 and a_cal < a_ideal / 10


def test_repeated_angles_are_averaged():
    angles = np.repeat([0.0, 45.0, 90.0, 135.0], 3)
    cal = calibrate_polarizer(render_calibration_frames(angles, seed=1), angles, dark_level=DARK)
    assert cal.n_frames == 12
    assert_recovers(cal, t_rel=5e-3, ang_deg=0.15, d_abs=3e-3)


def test_saturated_superpixels_are_excluded():
    frames = render_calibration_frames(ANGLES)
    h, w = frames[0].shape
    for f in frames:  # a glint inside the ROI, clipped at full scale in every frame
        f[h // 2 - 8 : h // 2 + 8, w // 2 - 8 : w // 2 + 8] = 4095
    cal = calibrate_polarizer(frames, ANGLES, dark_level=DARK)
    assert cal.fraction_excluded == pytest.approx(64 / 1024)
    assert cal.superpixels_used == 1024 - 64
    assert_recovers(cal)
    # the same frames with saturation detection disabled give a visibly wrong matrix
    bad = calibrate_polarizer(frames, ANGLES, dark_level=DARK, saturation_level=1e9)
    assert np.max(np.abs(bad.diattenuation - TRUE.diattenuation)) > 0.02


def test_partially_saturated_frames_use_common_superpixels():
    """A bright spot that saturates only at some angles is excluded from every frame."""
    frames = render_calibration_frames(ANGLES, level=2000.0)
    h, w = frames[0].shape
    bright = render_calibration_frames(ANGLES, level=4200.0, seed=5)
    sl = (slice(h // 2 - 10, h // 2 + 10), slice(w // 2 - 10, w // 2 + 10))
    for f, b in zip(frames, bright, strict=True):
        f[sl] = b[sl]
    cal = calibrate_polarizer(frames, ANGLES, dark_level=DARK)
    assert cal.fraction_excluded == pytest.approx(100 / 1024)
    assert_recovers(cal)


def test_msb_aligned_16bit_frames_match_12bit():
    frames = render_calibration_frames(ANGLES[::2], shape=(64, 64))
    a = calibrate_polarizer(frames, ANGLES[::2], dark_level=DARK)
    b = calibrate_polarizer([f << 4 for f in frames], ANGLES[::2], dark_level=DARK)
    assert b.bit_depth.shift == 4 and b.bit_depth.bits == 12
    assert np.allclose(a.matrix, b.matrix, atol=1e-12)


def test_rawframe_input_and_names():
    frames = render_calibration_frames(ANGLES[::2], shape=(32, 32))
    raws = [RawFrame(f, 12, "tiff", Path(f"f{j}.tiff")) for j, f in enumerate(frames)]
    cal = calibrate_polarizer(raws, ANGLES[::2], dark_level=DARK)
    assert cal.frame_names == tuple(f"f{j}.tiff" for j in range(len(raws)))
    assert cal.bit_depth.bits == 12


def test_reference_polarizer_dolp():
    frames = render_calibration_frames(
        ANGLES, polarizer_dolp=0.95, bit_depth=None, noise=False, shape=(16, 16), vignetting=0.0
    )
    right = calibrate_polarizer(frames, ANGLES, polarizer_dolp=0.95)
    wrong = calibrate_polarizer(frames, ANGLES)
    assert np.allclose(right.diattenuation, TRUE.diattenuation, atol=1e-12)
    assert np.allclose(wrong.diattenuation, 0.95 * TRUE.diattenuation, atol=1e-12)
    # underestimating the reference DoLP pushes the diattenuation above 1: warned
    over = calibrate_polarizer(frames, ANGLES, polarizer_dolp=0.9)
    assert any("diattenuation" in w for w in over.warnings)


def test_drift_fit():
    rng = np.random.default_rng(11)
    drift = 1.0 + 0.05 * rng.standard_normal(ANGLES.size)
    frames = render_calibration_frames(ANGLES, drift=drift, seed=2)
    plain = calibrate_polarizer(frames, ANGLES, dark_level=DARK)
    fitted = calibrate_polarizer(frames, ANGLES, dark_level=DARK, fit_frame_scale=True)
    assert plain.frame_scale is None
    assert np.max(np.abs(plain.transmission / TRUE_T - 1)) > 0.005  # drift spoils the plain fit ...
    assert any("residual RMS" in w for w in plain.warnings)  # ... and it says so
    assert_recovers(fitted, t_rel=5e-3, ang_deg=0.1, d_abs=2e-3)
    assert np.allclose(fitted.frame_scale, drift / drift.mean(), atol=2e-3)
    assert fitted.frame_scale.mean() == pytest.approx(1.0)
    assert np.all(fitted.residual_rms_relative < 2e-3) and fitted.warnings == ()


def test_fit_analyser_on_means_matches_forward_model():
    angles = np.array([0.0, 30.0, 60.0, 90.0, 120.0, 150.0])
    s = np.stack([np.ones_like(angles), np.cos(np.radians(2 * angles)), np.sin(np.radians(2 * angles))])
    means = 1234.0 * TRUE.matrix @ s
    cal = fit_analyser(means, angles)
    assert np.allclose(cal.matrix, TRUE.matrix / TRUE.transmission.mean(), atol=1e-12)
    assert cal.source_s0_dn == pytest.approx(1234.0 * TRUE.transmission.mean())
    assert cal.roi is None and cal.frame_names is None


# -- serialisation ------------------------------------------------------------------------


def test_to_dict_is_loadable_by_analyser_matrix(noisy_calibration, tmp_path):
    d = noisy_calibration.to_dict()
    text = json.dumps(d, allow_nan=False)  # strict JSON
    assert {"schema", "matrix", "transmission", "angles_deg", "extinction_ratio"} <= set(d)
    c = d["calibration"]
    assert c["n_frames"] == ANGLES.size and c["polarizer_angles_deg"] == ANGLES.tolist()
    assert c["roi"] == {"x": 32, "y": 32, "width": 64, "height": 64}
    assert c["bit_depth"] == 12 and c["msb_shift"] == 0 and c["dark_level"] == DARK
    assert c["layout"] == "90,45,135,0" and c["fit_frame_scale"] is False
    assert len(c["residual_rms_dn"]) == 4 and np.array(c["channel_means_dn"]).shape == (4, ANGLES.size)
    assert c["condition_number"] == pytest.approx(noisy_calibration.condition_number)
    path = write_json_atomic(tmp_path / "cal.json", d)
    loaded = AnalyserMatrix.load(path)
    assert np.array_equal(loaded.matrix, noisy_calibration.matrix)
    assert AnalyserMatrix.from_dict(json.loads(text)).matrix.tolist() == d["matrix"]


def test_to_dict_of_ideal_analyser_has_no_infinities():
    frames = render_calibration_frames(
        ANGLES[::3], AnalyserMatrix.ideal(), bit_depth=None, noise=False, shape=(8, 8), vignetting=0.0
    )
    cal = calibrate_polarizer(frames, ANGLES[::3])
    d = cal.to_dict()
    json.dumps(d, allow_nan=False)
    assert all(v is None or v > 1e10 for v in d["extinction_ratio"])


# -- validation ---------------------------------------------------------------------------


def _frames4(n=4, shape=(16, 16)):
    return render_calibration_frames(np.arange(n) * 180.0 / n, shape=shape, seed=4)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: (_frames4(), [0.0, 45.0, 90.0]), "4 frames but 3 polarizer angles"),
        (lambda: (_frames4(), [0.0, 45.0, 90.0, 180.0]), "at least 4 distinct polarizer angles"),
        (lambda: (_frames4(), [0.0, 45.0, 90.0, float("nan")]), "finite"),
        (lambda: (_frames4(), [0.0, 1.0, 2.0, 3.0]), "cover too little"),
        (lambda: ([], []), "no calibration frames"),
        (lambda: (_frames4()[:3] + [_frames4(1, (16, 18))[0]], [0, 45, 90, 135]), "18x16 .* first frame is 16x16"),
        (lambda: (_frames4()[:3] + [np.zeros((16, 16), np.uint8)], [0, 45, 90, 135]), "pixel type uint8"),
        (lambda: (_frames4()[:3] + [np.zeros((15, 16), np.uint16)], [0, 45, 90, 135]), "frame 4 of 4: .*even"),
        (lambda: (_frames4()[:3] + [np.full((16, 16), 4095, np.uint16)], [0, 45, 90, 135]), "frame 4 of 4: every"),
    ],
)
def test_bad_input_raises_one_line(make, match):
    frames, angles = make()
    with pytest.raises(PihimInputError, match=match) as exc:
        calibrate_polarizer(frames, angles, dark_level=DARK)
    assert "\n" not in str(exc.value)


def test_bad_options_raise_one_line():
    frames = _frames4()
    cases = [
        (dict(polarizer_dolp=0.0), "DoLP must be in"),
        (dict(polarizer_dolp=1.5), "DoLP must be in"),
        (dict(roi=(10, 10, 20, 20)), "does not lie inside"),
        (dict(roi=(3, 3, 2, 2)), "no whole 2x2 super-pixel"),
        (dict(roi=(0, 0, 16)), "X,Y,WIDTH,HEIGHT"),
        (dict(fit_frame_scale=True), "at least 5 distinct"),
        (dict(dark_level=float("inf")), "dark level must be a finite number"),
        (dict(dark_level=-10.0), "dark level must be a finite number of raw units >= 0, got -10"),
        (dict(bit_depth=10), "exceed 10-bit"),
    ]
    for kwargs, match in cases:
        with pytest.raises(PihimInputError, match=match) as exc:
            calibrate_polarizer(frames, [0, 45, 90, 135], **kwargs)
        assert "\n" not in str(exc.value)


def test_saturation_in_different_places_leaves_nothing():
    frames = _frames4()
    frames[0][:8] = 4095  # top half of the ROI saturated in one frame,
    frames[1][8:] = 4095  # bottom half in another
    with pytest.raises(PihimInputError, match="no super-pixel in the ROI is unsaturated in all frames"):
        calibrate_polarizer(frames, [0, 45, 90, 135], roi=(0, 0, 16, 16))


def test_roi_snapping_and_default():
    assert default_roi((2048, 2448)) == (612, 512, 1224, 1024)
    assert default_roi((2, 2)) == (0, 0, 2, 2)
    m = measure_channel_means(_frames4(), roi=(3, 1, 9, 8))
    assert m.roi == (4, 2, 8, 6) and m.superpixels_used == 12


def test_clockwise_angles_are_flagged(noisy_calibration):
    """Angles given clockwise swap the 45 and 135 deg channels: warned, not silently used."""
    cal = fit_analyser(noisy_calibration.channel_means_dn, -ANGLES)
    assert any(w.startswith("channel 45 deg") and "off nominal" in w for w in cal.warnings)
    assert any(w.startswith("channel 135 deg") and "off nominal" in w for w in cal.warnings)
