"""Adaptive exposure: statistics against numpy, the decision rule, and the closed loop on a simulated camera."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pihim.errors import PihimInputError
from pihim.live.exposure import (
    ExposureParams,
    ExposureSettings,
    ExposureState,
    RegionStats,
    motion_blur_exposure_cap_us,
    next_exposure,
    region_stats,
)
from pihim.live.simcam import SensorNoise, SimulatedCamera
from pihim.render.mosaic import mosaic_from_stokes
from pihim.render.scenes import edge_scene

#: Frames after a 100x brightness step by which the loop must have settled (camera latency 2 frames).
CONVERGENCE_FRAMES = 14


def _nearest_rank(values: np.ndarray, q: float) -> float:
    """Independent oracle: the nearest-rank percentile of sorted values."""
    v = np.sort(values.ravel())
    return float(v[max(1, math.ceil(q * v.size)) - 1])


def test_region_stats_match_numpy_oracle():
    rng = np.random.default_rng(4)
    raw = rng.integers(0, 4096, size=(64, 80), dtype=np.uint16)
    raw[:2, :4] = 4095
    st = region_stats(raw, bit_depth=12)
    assert st.count == raw.size
    assert st.p_hi_dn == _nearest_rank(raw, 0.999)
    assert st.median_dn == _nearest_rank(raw, 0.5)
    assert st.fraction_saturated == pytest.approx(np.mean(raw >= 4095))


def test_region_stats_super_pixel_mask_and_stride():
    rng = np.random.default_rng(5)
    raw = rng.integers(0, 4000, size=(40, 48), dtype=np.uint16)
    sp = rng.random((20, 24)) < 0.3
    full = np.kron(sp, np.ones((2, 2), bool))
    st = region_stats(raw, sp, bit_depth=12)
    assert st.count == full.sum()
    assert st.p_hi_dn == _nearest_rank(raw[full], 0.999)
    assert st.median_dn == _nearest_rank(raw[full], 0.5)
    # a full-size mask gives the same as the super-pixel mask it expands
    assert region_stats(raw, full, bit_depth=12) == st
    # stride 2: every other super-pixel row and column, all four pixels of each
    sub = np.zeros_like(sp)
    sub[::2, ::2] = sp[::2, ::2]
    st2 = region_stats(raw, sp, bit_depth=12, stride=2)
    sel = np.kron(sub, np.ones((2, 2), bool))
    assert st2.count == sel.sum()
    assert st2.median_dn == _nearest_rank(raw[sel], 0.5)


def test_region_stats_msb_aligned_and_empty():
    raw = (np.arange(16, dtype=np.uint16).reshape(4, 4) * 200) << 4  # 12-bit values in the high bits
    st = region_stats(raw, bit_depth=12)
    assert st.p_hi_dn == 3000.0
    empty = region_stats(raw, np.zeros((2, 2), bool))
    assert empty.count == 0
    d = next_exposure(empty, ExposureSettings(1000.0))
    assert not d.changed and d.reason == "empty region"
    with pytest.raises(PihimInputError):
        region_stats(raw, np.zeros((3, 3), bool))


def _stats(p_hi: float, median: float, sat: float = 0.0) -> RegionStats:
    return RegionStats(1000, p_hi * 4095, median * 4095, sat, 99.9, 4095.0)


def test_decision_rules():
    p = ExposureParams(latency_frames=2)
    cur = ExposureSettings(1000.0)
    # over the limit: one undamped step that puts p_hi on the aim
    d = next_exposure(_stats(0.95, 0.4), cur, p)
    assert d.changed and d.reason == "over limit"
    assert d.settings.exposure_us == pytest.approx(1000.0 * 0.75 / 0.95)
    assert d.state.hold_frames == 1
    # the next frame is still taken with the old settings: hold
    d2 = next_exposure(_stats(0.95, 0.4), d.settings, p, d.state)
    assert not d2.changed and d2.reason == "hold" and d2.state.hold_frames == 0
    # inside the band between aim and limit: nothing, even if the median is low
    assert next_exposure(_stats(0.80, 0.1), cur, p).reason == "in band"
    # dark frame: damped step toward the smaller of the two targets
    d3 = next_exposure(_stats(0.2, 0.05), cur, p)
    want = min(0.75 / 0.2, 0.35 / 0.05)
    assert d3.settings.exposure_us == pytest.approx(1000.0 * want ** p.damping)
    # clipped with a clipped median: the fixed step
    d4 = next_exposure(_stats(1.0, 1.0, 0.9), cur, p)
    assert d4.reason == "clipped" and d4.settings.exposure_us == pytest.approx(1000.0 / p.clipped_step)
    # clipped, median readable: median to target, at least halving
    d5 = next_exposure(_stats(1.0, 0.9, 0.3), cur, p)
    assert d5.settings.exposure_us == pytest.approx(1000.0 * 0.35 / 0.9)
    d6 = next_exposure(_stats(1.0, 0.2, 0.001), cur, p)
    assert d6.settings.exposure_us == pytest.approx(500.0)


def test_exposure_before_gain_and_caps():
    p = ExposureParams(exposure_max_us=2000.0, gain_max_db=12.0, latency_frames=1)
    cur = ExposureSettings(1000.0)
    d = next_exposure(_stats(0.05, 0.02), cur, p)  # wants min(0.75/0.05, 0.35/0.02) = 15x, damped
    target = 1000.0 * 15.0 ** p.damping
    assert d.settings.exposure_us == 2000.0  # exposure first, to its cap
    assert d.settings.gain_db == pytest.approx(20 * math.log10(target / 2000.0))
    assert d.settings.brightness == pytest.approx(target)
    # going down from (2000 us, +6 dB): the gain gives way first, the exposure stays at its cap
    cur2 = ExposureSettings(2000.0, 20 * math.log10(2.0))
    d2 = next_exposure(_stats(0.95, 0.5), cur2, p)
    assert d2.settings.brightness == pytest.approx(cur2.brightness * 0.75 / 0.95)
    assert d2.settings.exposure_us == 2000.0
    assert d2.settings.gain_db == pytest.approx(20 * math.log10(2.0 * 0.75 / 0.95))
    # and below 2000 us of brightness the gain is 0 dB
    d2b = next_exposure(_stats(0.95, 0.5), ExposureSettings(2000.0), p)
    assert d2b.settings.gain_db == 0.0 and d2b.settings.exposure_us == pytest.approx(2000.0 * 0.75 / 0.95)
    # the gain stops at its maximum
    d2c = next_exposure(_stats(0.001, 0.0005), ExposureSettings(2000.0, 11.0), p)
    assert d2c.settings.gain_db == pytest.approx(12.0)
    # a motion-blur cap below the camera's maximum wins
    d3 = next_exposure(_stats(0.05, 0.02), cur, p, exposure_cap_us=1200.0)
    assert d3.settings.exposure_us == 1200.0


def test_motion_blur_cap_analytic():
    # GSD at 30 m with 3.45 um pixels and 35 mm: 2.957 mm; 5 m/s sweeps 1690.8 px/s
    cap = motion_blur_exposure_cap_us(5.0, 30.0)
    assert cap == pytest.approx(1e6 * 30.0 * 3.45e-6 / 0.035 / 5.0, rel=1e-12)
    assert motion_blur_exposure_cap_us(5.0, 30.0, max_blur_px=2.0) == pytest.approx(2 * cap)
    # a 10 deg/s turn: omega f / p = 0.1745 * 0.035 / 3.45e-6 px/s
    turn = motion_blur_exposure_cap_us(0.0, 30.0, angular_rate_deg_s=10.0)
    assert turn == pytest.approx(1e6 / (math.radians(10.0) * 0.035 / 3.45e-6))
    assert math.isinf(motion_blur_exposure_cap_us(0.0, 30.0))
    with pytest.raises(PihimInputError):
        motion_blur_exposure_cap_us(-1.0, 30.0)


@pytest.fixture(scope="module")
def scene():
    """Signal rate (DN/us at 0 dB) and mirror mask of a small synthetic heliostat scene."""
    s0, s1, s2 = edge_scene((128, 160), rng=3)
    rate = mosaic_from_stokes(s0, s1, s2, bit_depth=None) / 4000.0  # well exposed at 4000 us
    mirrors = (np.hypot(s1, s2) / s0 > 0.12) & (s0 > 1500)
    return rate, mirrors


def _run_loop(rate, mirrors, step, *, cam_latency, frames=90, step_at=30, params=None):
    """Closed loop: the controller commands the simulated camera; the scene brightness steps by ``step``."""
    params = params or ExposureParams(latency_frames=2, exposure_max_us=1e6)
    cam = SimulatedCamera(rate, ExposureSettings(4000.0), latency_frames=cam_latency, seed=7,
                          noise=SensorNoise())
    state, cur = ExposureState(), cam.settings
    log = []
    for k in range(frames):
        raw, used = cam.capture(1.0 if k < step_at else step)
        st = region_stats(raw, mirrors)
        d = next_exposure(st, cur, params, state)
        log.append({"k": k, "brightness": used.brightness, "sat": st.fraction_saturated, "p_hi": st.p_hi,
                    "median": st.median, "changed": d.changed})
        if d.changed:
            cam.request(d.settings)
            cur = d.settings
        state = d.state
    return log


@pytest.mark.parametrize("step", [100.0, 0.01])
@pytest.mark.parametrize("cam_latency", [1, 2])
def test_closed_loop_brightness_step(scene, step, cam_latency):
    rate, mirrors = scene
    log = _run_loop(rate, mirrors, step, cam_latency=cam_latency)
    step_at = 30
    # settled before the step (no command for the last 10 frames)
    assert not any(r["changed"] for r in log[step_at - 10:step_at])
    before = log[step_at - 1]["brightness"]
    changes = [r["k"] for r in log if r["changed"] and r["k"] >= step_at]
    assert changes, "the controller must react to a 100x step"
    settled = changes[-1] + cam_latency  # first frame taken with the last command
    assert settled - step_at <= CONVERGENCE_FRAMES, f"settled {settled - step_at} frames after the step"
    after = log[settled:]
    assert len(after) >= 40
    # after convergence: under 0.1 % saturated, p_hi under the limit, no further command (no oscillation)
    assert max(r["sat"] for r in after) < 1e-3
    assert max(r["p_hi"] for r in after) <= 0.85
    assert not any(r["changed"] for r in after)
    # the exposure compensates the step (brightness x step = the same signal), within the band
    assert log[-1]["brightness"] * step / before == pytest.approx(1.0, rel=0.25)
    # monotone approach: the commanded brightness changes direction at most once
    b = np.log([r["brightness"] for r in log[step_at:]])
    signs = np.sign(np.diff(b)[np.abs(np.diff(b)) > 1e-12])
    assert np.count_nonzero(np.diff(signs)) <= 1


def test_closed_loop_quiet_scene_never_hunts(scene):
    rate, mirrors = scene
    log = _run_loop(rate, mirrors, 1.0, cam_latency=2, frames=200)
    # 200 frames of shot and read noise in a well exposed scene: not a single command
    assert not any(r["changed"] for r in log)


def test_params_validation():
    with pytest.raises(PihimInputError):
        ExposureParams(aim=0.9, limit=0.85)
    with pytest.raises(PihimInputError):
        ExposureParams(latency_frames=0)
    with pytest.raises(PihimInputError):
        ExposureSettings(-1.0)
    with pytest.raises(PihimInputError):
        ExposureSettings(10.0, -3.0)


def test_a_cap_or_a_percentile_out_of_range_is_refused():
    """A cap of -5 us commanded the shortest exposure at full gain (NaN was ignored); percentile 150 reported
    a level above full scale."""
    for cap in (-5.0, 0.0, math.nan):
        with pytest.raises(PihimInputError, match="exposure_cap_us must be a positive number"):
            next_exposure(_stats(0.5, 0.3), ExposureSettings(1000.0), exposure_cap_us=cap)
    raw = np.full((8, 8), 1000, np.uint16)
    for q in (150.0, -1.0, math.nan):
        with pytest.raises(PihimInputError, match="percentile must be in"):
            region_stats(raw, percentile=q)
    assert region_stats(raw, percentile=100.0).p_hi_dn == 1000
