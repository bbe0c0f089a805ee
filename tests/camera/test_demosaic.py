"""Full-resolution demosaicing: numpy definition, fused kernel and quality.

The numpy route :func:`pihim.camera.demosaic.full_resolution` defines the
method; ``polar_image(..., demosaic="full")`` runs the fused numba kernel,
which must agree with it. Quality is measured against per-channel bilinear
interpolation on synthetic scenes with sharp edges and known ground truth.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pihim.camera import _kernels
from pihim.camera.demosaic import (
    FULLRES_GRAD_EPS,
    bilinear,
    full_resolution,
    full_resolution_support,
    superpixel,
)
from pihim.camera.layout import IMX250MZR, MosaicLayout
from pihim.camera.pipeline import polar_image
from pihim.polarimetry.analyser import AnalyserMatrix
from pihim.polarimetry.stokes import aop_deg, aop_difference_deg, dolp
from pihim.render.mosaic import mosaic_from_stokes
from pihim.render.scenes import edge_scene, uniform_scene

#: every layout reachable from the IMX250MZR default by ROI offsets and read-out reversal
LAYOUTS = sorted(
    {
        MosaicLayout.from_sensor(offset_x=ox, offset_y=oy, reverse_x=rx, reverse_y=ry)
        for ox, oy, rx, ry in itertools.product((0, 1), repeat=4)
    },
    key=str,
)
NON_IDEAL = AnalyserMatrix.from_parameters(
    (1.5, 44.0, 91.0, 134.2), transmission=(1.0, 0.96, 1.03, 0.98), extinction_ratio=(180, 150, 220, 90)
)


def _stokes_of(pi) -> np.ndarray:
    return np.stack([pi.s0, pi.s1, pi.s2]).astype(np.float64)


def _metrics(est: np.ndarray, truth: tuple[np.ndarray, ...]) -> tuple[float, float, float]:
    """S0 PSNR (dB, peak max S0), DoLP PSNR (dB, peak 1), AoP RMSE (deg, true DoLP > 0.1)."""
    s0t, s1t, s2t = truth
    psnr_s0 = 10 * np.log10(s0t.max() ** 2 / np.mean((est[0] - s0t) ** 2))
    p_true = dolp(s0t, s1t, s2t)
    p_est = np.nan_to_num(dolp(*est), nan=0.0)
    psnr_p = 10 * np.log10(1.0 / np.mean((p_est - p_true) ** 2))
    sel = p_true > 0.1
    d = aop_difference_deg(aop_deg(est[1], est[2]), aop_deg(s1t, s2t))[sel]
    return float(psnr_s0), float(psnr_p), float(np.sqrt(np.mean(d**2)))


def test_layout_set_is_complete() -> None:
    # offsets give the 4 rotations of the pattern, reversal the 4 mirrored ones
    assert len(LAYOUTS) == 8
    assert IMX250MZR in LAYOUTS


# -- exactness on uniform and affine fields -----------------------------------------------------


@pytest.mark.parametrize("layout", LAYOUTS, ids=str)
@pytest.mark.parametrize("analyser", [None, NON_IDEAL], ids=["ideal", "calibrated"])
def test_uniform_field_exact_numpy(layout: MosaicLayout, analyser: AnalyserMatrix | None) -> None:
    rng = np.random.default_rng(7)
    a = analyser or AnalyserMatrix.ideal()
    for _ in range(5):
        s = uniform_scene((10, 14), rng.uniform(10, 5000), rng.uniform(0, 1), rng.uniform(0, 180))
        m = mosaic_from_stokes(*s, layout=layout, analyser=a, bit_depth=None)
        expected = a.intensities(*(x[0, 0] for x in s))
        got = full_resolution(m, layout)
        np.testing.assert_allclose(got, np.broadcast_to(expected[:, None, None], got.shape), rtol=1e-12, atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(
    s0=st.floats(1.0, 8000.0),
    p=st.floats(0.0, 1.0),
    aop=st.floats(0.0, 180.0, exclude_max=True),
    layout_index=st.integers(0, len(LAYOUTS) - 1),
    calibrated=st.booleans(),
)
def test_uniform_field_exact_kernel(s0: float, p: float, aop: float, layout_index: int, calibrated: bool) -> None:
    layout = LAYOUTS[layout_index]
    a = NON_IDEAL if calibrated else AnalyserMatrix.ideal()
    truth = uniform_scene((12, 18), s0, p, aop)
    m = mosaic_from_stokes(*truth, layout=layout, analyser=a, bit_depth=None)
    pi = polar_image(m, layout=layout, analyser=a, demosaic="full")
    tol = 2e-6 * s0
    for got, want in zip(_stokes_of(pi), truth, strict=True):
        np.testing.assert_allclose(got, want, rtol=0, atol=tol)
    np.testing.assert_allclose(pi.dolp, p, rtol=0, atol=1e-5)
    if p > 1e-3:
        assert np.all(aop_difference_deg(pi.aop_deg, aop) < 2e-3 / p + 1e-3)
    assert not pi.saturated.any()


@pytest.mark.parametrize("layout", LAYOUTS[:4], ids=str)
def test_affine_field_exact_away_from_border(layout: MosaicLayout) -> None:
    # channel intensities that are affine in (x, y) are reproduced exactly:
    # the one-sided Newton estimates err in opposite directions and get equal weights
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:24, 0:30].astype(float)
    ch = np.stack([rng.uniform(500, 1500) + rng.uniform(-20, 20) * xx + rng.uniform(-20, 20) * yy for _ in range(4)])
    m = layout.merge(np.stack([c[r::2, q::2] for c, (r, q) in zip(ch, layout.channel_positions, strict=True)]))
    got = full_resolution(m, layout)
    np.testing.assert_allclose(got[:, 3:-3, 3:-3], ch[:, 3:-3, 3:-3], rtol=1e-12, atol=1e-9)
    bil = bilinear(m, layout)
    np.testing.assert_allclose(bil[:, 1:-1, 1:-1], ch[:, 1:-1, 1:-1], rtol=1e-12, atol=1e-9)


def test_measured_channel_is_kept() -> None:
    rng = np.random.default_rng(0)
    m = rng.uniform(0, 4095, (16, 20))
    for layout in LAYOUTS:
        out = full_resolution(m, layout)
        ch = layout.channel_map(m.shape)
        kept = np.take_along_axis(out, ch[None].astype(np.intp), axis=0)[0]
        np.testing.assert_array_equal(kept, m)


# -- kernel == numpy definition ----------------------------------------------------------------


@pytest.mark.parametrize("layout", LAYOUTS, ids=str)
def test_kernel_matches_numpy_definition(layout: MosaicLayout) -> None:
    truth = edge_scene((48, 64), 11)
    m = mosaic_from_stokes(*truth, layout=layout, analyser=NON_IDEAL, bit_depth=12, dark_level=64.0,
                           read_noise_dn=2.0, electrons_per_dn=2.5, rng=5)
    pi = polar_image(m, layout=layout, analyser=NON_IDEAL, demosaic="full", dark_level=64.0, bit_depth=12)
    ref = NON_IDEAL.stokes(full_resolution(m.astype(np.float64) - 64.0, layout))
    scale = np.abs(ref[0]).max()
    np.testing.assert_allclose(_stokes_of(pi), ref, rtol=0, atol=1e-4 * scale)
    ok = ref[0] > 0.05 * scale
    np.testing.assert_allclose(pi.dolp[ok], dolp(*ref)[ok], rtol=0, atol=1e-4)
    sel = ok & (dolp(*ref) > 0.05)
    assert np.all(aop_difference_deg(pi.aop_deg, aop_deg(ref[1], ref[2]))[sel] < 0.02)


@pytest.mark.parametrize("shape", [(2, 2), (2, 4), (4, 2), (6, 8), (18, 34), (34, 18)])
def test_kernel_matches_numpy_on_small_and_odd_block_shapes(shape: tuple[int, int]) -> None:
    # exercises the mirrored borders, including mirrors deeper than the image
    m = np.random.default_rng(sum(shape)).integers(0, 4096, shape).astype(np.uint16)
    pi = polar_image(m, demosaic="full", bit_depth=12)
    ref = AnalyserMatrix.ideal().stokes(full_resolution(m))
    np.testing.assert_allclose(_stokes_of(pi), ref, rtol=0, atol=1e-4 * np.abs(ref[0]).max())


def test_kernel_eps_matches_definition() -> None:
    assert float(_kernels._FR_EPS) == pytest.approx(FULLRES_GRAD_EPS)


def test_polar_image_full_shape_and_types() -> None:
    m = mosaic_from_stokes(*edge_scene((40, 56), 1), bit_depth=12)
    pi = polar_image(m, demosaic="full")
    assert pi.shape == (40, 56)
    assert pi.demosaic == "full"
    for img in (pi.s0, pi.s1, pi.s2, pi.dolp, pi.aop_deg):
        assert img.dtype == np.float32 and img.shape == (40, 56)
    assert pi.saturated.shape == (40, 56) and pi.saturated.dtype == np.bool_
    assert np.all(np.isfinite(pi.s0)) and np.all(np.isfinite(pi.dolp))
    a = pi.aop_deg
    assert np.all((a >= 0) & (a < 180))


# -- saturation --------------------------------------------------------------------------------


def _expected_saturation(raw: np.ndarray, level: float) -> np.ndarray:
    fp = full_resolution_support()
    pad = np.pad(raw >= level, 3, mode="reflect")
    h, w = raw.shape
    out = np.zeros((h, w), dtype=bool)
    for di, dj in zip(*np.nonzero(fp), strict=True):
        out |= pad[di : di + h, dj : dj + w]
    return out


def test_support_footprint_is_the_dependency_set() -> None:
    rng = np.random.default_rng(1)
    m = rng.uniform(100, 4000, (16, 16))
    base = full_resolution(m)
    seen = np.zeros((7, 7), dtype=bool)
    for i0, j0 in ((7, 7), (7, 8), (8, 7), (8, 8)):
        for _ in range(6):
            mm = m.copy()
            mm[i0, j0] += rng.uniform(-2000, 2000)
            ii, jj = np.nonzero(np.any(full_resolution(mm) != base, axis=0))
            assert np.all(np.abs(i0 - ii) <= 3) and np.all(np.abs(j0 - jj) <= 3)
            seen[i0 - ii + 3, j0 - jj + 3] = True
    fp = full_resolution_support()
    assert np.array_equal(seen, fp)  # tight: no pixel outside matters, every pixel inside can
    assert np.array_equal(fp, fp[::-1]) and np.array_equal(fp, fp.T)


@pytest.mark.parametrize("where", [(9, 12), (10, 13), (0, 0), (0, 5), (19, 23), (1, 22)])
def test_saturation_propagates_to_support(where: tuple[int, int]) -> None:
    m = mosaic_from_stokes(*uniform_scene((20, 24), 2000.0, 0.3, 30.0), bit_depth=12)
    m[where] = 4095
    pi = polar_image(m, demosaic="full", bit_depth=12)
    expected = _expected_saturation(m, 4095)
    np.testing.assert_array_equal(pi.saturated, expected)
    assert expected.sum() >= 12
    assert np.all(np.isnan(pi.dolp[expected])) and np.all(np.isnan(pi.aop_deg[expected]))
    assert np.all(np.isfinite(pi.dolp[~expected])) and np.all(np.isfinite(pi.aop_deg[~expected]))
    if where == (9, 12):  # interior: exactly the footprint around the pixel
        np.testing.assert_array_equal(pi.saturated[6:13, 9:16], full_resolution_support())
        assert pi.saturated.sum() == full_resolution_support().sum()


def test_saturation_level_and_random_pattern() -> None:
    rng = np.random.default_rng(4)
    m = rng.integers(0, 3000, (30, 36)).astype(np.uint16)
    m[rng.uniform(size=m.shape) < 0.01] = 3500
    pi = polar_image(m, demosaic="full", bit_depth=12, saturation_level=3400)
    np.testing.assert_array_equal(pi.saturated, _expected_saturation(m, 3400))


def test_nonpositive_s0_gives_nan() -> None:
    m = np.zeros((8, 10), dtype=np.uint16)
    pi = polar_image(m, demosaic="full", bit_depth=12, dark_level=1.0)
    assert np.all(np.isnan(pi.dolp)) and np.all(np.isnan(pi.aop_deg))


# -- quality against bilinear ------------------------------------------------------------------


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("noisy", [False, True], ids=["clean", "noisy"])
def test_full_resolution_beats_bilinear_on_edges(seed: int, noisy: bool) -> None:
    truth = edge_scene((128, 160), seed)
    kw = {"read_noise_dn": 2.0, "electrons_per_dn": 2.5, "rng": 10 + seed} if noisy else {}
    m = mosaic_from_stokes(*truth, bit_depth=12, **kw)
    a = AnalyserMatrix.ideal()
    bil = _metrics(a.stokes(bilinear(m)), truth)
    full = _metrics(a.stokes(full_resolution(m)), truth)
    kern = _metrics(_stokes_of(polar_image(m, demosaic="full", bit_depth=12)), truth)
    for got in (full, kern):
        assert got[0] > bil[0] + 3.0, (got, bil)  # S0 PSNR, dB
        assert got[1] > bil[1] + 3.0, (got, bil)  # DoLP PSNR, dB
        assert got[2] < 0.75 * bil[2], (got, bil)  # AoP RMSE on polarized pixels, deg
    np.testing.assert_allclose(kern, full, rtol=1e-3)


def test_superpixel_route_unchanged() -> None:
    m = np.arange(16, dtype=np.uint16).reshape(4, 4)
    np.testing.assert_array_equal(superpixel(m)[:, 0, 0], [m[1, 1], m[0, 1], m[0, 0], m[1, 0]])


# -- scenes ------------------------------------------------------------------------------------


def test_edge_scene_is_valid_ground_truth() -> None:
    s0, s1, s2 = edge_scene((96, 128), 3)
    again = edge_scene((96, 128), 3)
    for x, y in zip((s0, s1, s2), again, strict=True):
        np.testing.assert_array_equal(x, y)
    assert s0.shape == (96, 128) and s0.dtype == np.float64
    p = dolp(s0, s1, s2)
    assert s0.min() > 0 and p.max() <= 1.0
    assert 0.5 * (s0 + np.hypot(s1, s2)).max() <= 4000.0  # no 12-bit saturation
    assert (p > 0.1).mean() > 0.1  # polarized facets present
    # sharp edges with partial-coverage pixels in between
    g = np.abs(np.diff(s0, axis=1))
    assert g.max() > 1000
    assert np.unique(np.round(s0)).size > 500


def test_uniform_scene_values() -> None:
    s0, s1, s2 = uniform_scene((4, 6), 1000.0, 0.5, 45.0)
    np.testing.assert_allclose(s0, 1000.0)
    np.testing.assert_allclose(s1, 0.0, atol=1e-9)
    np.testing.assert_allclose(s2, 500.0)


def test_edge_scene_of_a_wide_strip_has_no_negative_light() -> None:
    """A 16 x 400 frame (live --size 400x16) drove the ground's S0 gradient below zero: the Stokes builder now refuses
    that, so the scene keeps it at zero (black ground) instead; ordinary shapes are unchanged."""
    for seed in range(6):
        s0, _, _ = edge_scene((16, 400), seed)
        assert np.all(s0 >= 0)
    assert edge_scene((64, 96), 3)[0].min() > 0  # nothing clipped in an ordinary frame
