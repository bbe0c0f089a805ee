"""Tests of :mod:`pihim.inspection.edges`: Sobel scale, step position, axial AoP gradients, thresholds, NaN."""

import math
import warnings

import numpy as np
import pytest

from pihim.errors import PihimInputError
from pihim.inspection.edges import (
    IMAGE_TYPES,
    EdgeMap,
    axial_gradient_magnitude,
    edge_maps,
    gradient_magnitude,
    robust_thresholds,
)

H, W = 48, 64


def _grid():
    return np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))


def _interior(a, m=2):
    return a[m:-m, m:-m]


def test_sobel_of_a_ramp_is_its_slope_per_pixel():
    x, y = _grid()
    g = gradient_magnitude(0.3 * x - 0.1 * y + 7.0)
    assert g.shape == (H, W) and g.dtype == np.float64
    np.testing.assert_allclose(_interior(g), math.hypot(0.3, 0.1), rtol=1e-12)


def test_step_gives_half_its_height_on_the_two_pixels_beside_it():
    x, _ = _grid()
    img = np.where(x >= 20, 5.0, 1.0)  # step between columns 19 and 20
    g = gradient_magnitude(img)
    np.testing.assert_allclose(g[:, 19], 2.0)
    np.testing.assert_allclose(g[:, 20], 2.0)
    others = np.delete(g, [19, 20], axis=1)
    assert np.all(others == 0.0)
    dolp = np.full((H, W), 0.5)
    aop = np.full((H, W), 30.0)
    sob = edge_maps(img, dolp, aop, "sobel")
    assert set(np.nonzero(sob["S0"].edges.any(axis=0))[0]) == {19, 20}
    assert sob["S0"].edges[:, 19].all() and sob["S0"].edges[:, 20].all()
    can = edge_maps(img, dolp, aop, "canny")
    cols = np.nonzero(can["S0"].edges.any(axis=0))[0]
    assert len(cols) == 1 and cols[0] in (19, 20)  # one pixel thick, on the step
    assert can["S0"].edges[2:-2, cols[0]].all()
    # a uniform image has no edges in any map
    for m in (sob, can):
        assert not m["DoLP"].edges.any() and not m["AoP"].edges.any()


def test_aop_wrap_from_179_to_0_is_not_an_edge():
    x, _ = _grid()
    rate = 0.5  # deg per pixel
    aop = np.mod(170.0 + rate * x, 180.0)  # crosses 179.x -> 0 near column 20
    assert aop.max() > 179.0 and aop.min() < 1.0
    g = axial_gradient_magnitude(aop)
    np.testing.assert_allclose(_interior(g), rate, rtol=2e-4)  # deg per pixel, uniform across the wrap
    # the raw angle would see a ~90 deg/px cliff there: the test is meaningful
    assert gradient_magnitude(aop).max() > 80.0
    # the same ramp next to a real 90 deg step: edges only at the step
    img = np.where(x >= 48, np.mod(aop + 90.0, 180.0), aop)
    maps = edge_maps(np.ones((H, W)), np.full((H, W), 0.8), img, "sobel")
    cols = set(np.nonzero(maps["AoP"].edges.any(axis=0))[0])
    assert cols == {47, 48}
    canny = edge_maps(np.ones((H, W)), np.full((H, W), 0.8), img, "canny")
    assert set(np.nonzero(canny["AoP"].edges.any(axis=0))[0]) <= {47, 48}
    assert canny["AoP"].edges.sum() >= H - 4


def test_axial_step_scale_and_dolp_weight():
    x, _ = _grid()
    aop = np.where(x >= 30, 100.0, 10.0)  # 90 deg apart
    g = axial_gradient_magnitude(aop)
    np.testing.assert_allclose(g[:, 29], 90.0 / math.pi, rtol=1e-12)  # (90 / pi) * sin(90 deg)
    # 5 and 175 deg are 10 deg apart (axially), not 170
    g10 = axial_gradient_magnitude(np.where(x >= 30, 175.0, 5.0))
    np.testing.assert_allclose(g10[:, 29], 90.0 / math.pi * math.sin(math.radians(10.0)), rtol=1e-12)
    half = axial_gradient_magnitude(aop, np.full((H, W), 0.5))
    np.testing.assert_allclose(half, 0.5 * g, rtol=1e-12)


def test_nan_pixels_make_no_false_edges():
    x, y = _grid()
    dolp = np.where(x >= 40, 0.6, 0.2)  # a real DoLP step at column 40
    aop = np.full((H, W), 45.0)
    dolp = dolp.copy()
    aop = aop.copy()
    hole = (y >= 10) & (y < 30) & (x >= 10) & (x < 25)  # a saturated block inside a uniform region
    dolp[hole] = np.nan
    aop[hole] = np.nan
    s0 = np.ones((H, W))
    for method in ("sobel", "canny"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            maps = edge_maps(s0, dolp, aop, method)
        d = maps["DoLP"]
        assert np.all(np.isnan(d.gradient[hole])) and not d.edges[hole].any()
        assert np.all(np.isfinite(d.gradient[~hole]))
        edge_cols = set(np.nonzero(d.edges.any(axis=0))[0])
        assert edge_cols and edge_cols <= {39, 40}  # the step, and nothing around the hole
        assert not maps["AoP"].edges.any()
        assert np.all(np.isnan(maps["AoP"].gradient[hole]))
        assert maps["combined"].edges.sum() == d.edges.sum()


def test_all_nan_and_flat_images():
    nan = np.full((8, 8), np.nan)
    maps = edge_maps(np.zeros((8, 8)), nan, nan)
    for name, m in maps.items():
        assert not m.edges.any(), name
    st = maps["DoLP"].stats()
    assert st["valid_fraction"] == 0.0 and st["threshold_high"] is None and st["gradient"]["p50"] is None
    assert maps["S0"].stats()["edge_fraction"] == 0.0


def test_robust_threshold_rule():
    rng = np.random.default_rng(1)
    g = np.abs(rng.normal(0.0, 1.0, 100_000))
    med = np.median(g)
    mad = np.median(np.abs(g - med))
    high, low = robust_thresholds(g, n_sigma=5.0, floor_fraction=0.0, low_ratio=0.4)
    assert high == pytest.approx(med + 5.0 * 1.4826 * mad) and low == pytest.approx(0.4 * high)
    # noise-free: sigma collapses and the floor (a fraction of the strong-edge level) decides
    sparse = np.zeros(10_000)
    sparse[:200] = 3.0
    assert robust_thresholds(sparse)[0] == pytest.approx(0.3)
    assert robust_thresholds([np.nan, np.inf])[0] == math.inf


def test_noisy_step_found_with_few_false_edges():
    rng = np.random.default_rng(7)
    x, _ = _grid()
    big = np.tile(np.where(x >= 32, 1.0, 0.0), (4, 1))  # 192 x 64
    s0 = 100.0 + 20.0 * big + rng.normal(0.0, 1.0, big.shape)
    maps = edge_maps(s0, np.full(big.shape, 0.3), np.zeros(big.shape), "sobel")
    e = maps["S0"].edges
    assert e[2:-2, 31].all() and e[2:-2, 32].all()
    false = np.delete(e, [31, 32], axis=1)
    assert false.mean() < 1e-3
    can = edge_maps(s0, np.full(big.shape, 0.3), np.zeros(big.shape), "canny")["S0"].edges
    assert (can[2:-2, 31] | can[2:-2, 32]).mean() > 0.98
    assert np.delete(can, [30, 31, 32, 33], axis=1).mean() < 1e-3


def test_combined_is_the_union_and_normalised():
    x, y = _grid()
    s0 = np.where(x >= 20, 2.0, 1.0)
    dolp = np.where(y >= 30, 0.7, 0.1)
    aop = np.where(x >= 50, 120.0, 30.0)
    maps = edge_maps(s0, dolp, aop, "sobel")
    c = maps["combined"]
    np.testing.assert_array_equal(c.edges, maps["S0"].edges | maps["DoLP"].edges | maps["AoP"].edges)
    assert c.high == 1.0
    ratio = np.nanmax(np.stack([maps[t].gradient / maps[t].high for t in ("S0", "DoLP", "AoP")]), axis=0)
    np.testing.assert_allclose(c.gradient, ratio, rtol=1e-6)
    assert [name for name, _ in maps.items()] == list(IMAGE_TYPES)
    assert set(maps.summary()) == set(IMAGE_TYPES)
    assert maps["dolp"] is maps.dolp and maps.shape == (H, W)


def test_bad_input_is_refused():
    a = np.zeros((8, 8))
    with pytest.raises(PihimInputError, match="same shape"):
        edge_maps(a, np.zeros((8, 6)), a)
    with pytest.raises(PihimInputError, match="edge method"):
        edge_maps(a, a, a, "laplace")
    with pytest.raises(PihimInputError, match="2-D"):
        gradient_magnitude(np.zeros((2, 3, 4)))
    with pytest.raises(PihimInputError, match="low_ratio"):
        edge_maps(a, a, a, low_ratio=0.0)
    with pytest.raises(KeyError):
        edge_maps(a, a, a)["RGB"]


def test_float32_thresholds_and_statistics_equal_float64s():
    rng = np.random.default_rng(2)
    g = np.abs(rng.normal(0.0, 1.0, (300, 200))).astype(np.float32)
    g[:3] = np.nan
    g[5, :7] = np.inf
    np.testing.assert_allclose(robust_thresholds(g), robust_thresholds(g.astype(np.float64)), rtol=1e-6)
    fin = g[np.isfinite(g)].astype(np.float64)
    st = EdgeMap(g, np.zeros(g.shape, bool), 1.0, 0.4, "u").stats()
    want = np.percentile(fin, [50, 90, 99])
    assert [st["gradient"][k] for k in ("p50", "p90", "p99")] == pytest.approx(want, rel=1e-12)
    assert st["gradient"]["max"] == fin.max() and st["valid_fraction"] == fin.size / g.size


def test_nan_pixels_take_a_nearest_valid_neighbour_so_valid_gradients_see_no_step():
    from scipy import ndimage

    from pihim.inspection.edges import _fill_nearest

    rng = np.random.default_rng(3)
    image = rng.normal(size=(40, 50))
    bad = ndimage.binary_dilation(rng.random((40, 50)) < 0.01) | (rng.random((40, 50)) < 0.03)  # blobs, single pixels
    image[bad] = np.nan
    image[0, :5] = np.inf
    filled, valid = _fill_nearest(image)
    assert np.array_equal(valid, np.isfinite(image)) and np.array_equal(filled[valid], image[valid])
    # every invalid pixel a valid pixel's 3x3 Sobel reads holds the value of a valid pixel at the least distance
    read = ndimage.binary_dilation(valid, np.ones((3, 3), bool)) & ~valid
    assert 50 < read.sum() < valid.size - valid.sum()  # some invalid pixels are read, some are not
    dist = ndimage.distance_transform_edt(~valid)
    for r, c in zip(*np.nonzero(read)):
        near = [image[r + dr, c + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1)
                if 0 <= r + dr < 40 and 0 <= c + dc < 50 and valid[r + dr, c + dc]
                and math.isclose(math.hypot(dr, dc), dist[r, c])]
        assert filled[r, c] in near
    # the invalid pixels no valid pixel's Sobel reads may hold anything: the valid gradients stay
    deep = ~valid & ~read
    assert deep.any()
    other = filled.copy()
    other[deep] = 7e3
    g = gradient_magnitude(image)
    np.testing.assert_array_equal(g[valid], gradient_magnitude(other)[valid])
    assert np.isnan(g[~valid]).all()


def test_float32_images_give_the_float64_gradients_and_edges():
    rng = np.random.default_rng(5)
    x, y = _grid()
    aop = (30.0 * np.sin(x / 7.0) + 20.0 * y / H + rng.normal(0, 2.0, (H, W))) % 180.0
    dolp = np.clip(0.3 + 0.2 * (x > 30) + rng.normal(0, 0.02, (H, W)), 0, 1)
    s0 = 100.0 + 50.0 * (y > 20) + rng.normal(0, 1.0, (H, W))
    dolp[5:9, 40:44] = np.nan  # a saturated patch
    aop[5:9, 40:44] = np.nan
    for method in ("sobel", "canny"):
        m64 = edge_maps(s0, dolp, aop, method)
        m32 = edge_maps(s0.astype(np.float32), dolp.astype(np.float32), aop.astype(np.float32), method)
        for name in IMAGE_TYPES:
            g64 = m64[name].gradient
            np.testing.assert_allclose(m32[name].gradient, g64, rtol=1e-4, atol=1e-4 * np.nanmax(g64), err_msg=name)
            assert (m32[name].edges != m64[name].edges).mean() < 0.002, (method, name)


def test_axial_direction_is_the_structure_tensors_principal_axis():
    from pihim.inspection.edges import _axial_gradient

    rng = np.random.default_rng(11)
    aop = rng.uniform(0.0, 180.0, (H, W))
    mag, dx, dy, _ = _axial_gradient(aop, None, direction=True)
    # reference: the angle doubled, differentiated, and the tensor's axis by atan2
    a2 = np.radians(2.0 * aop)
    import cv2

    def sobel(img, ox, oy):
        return cv2.Sobel(img, cv2.CV_64F, ox, oy, ksize=3, scale=1 / 8, borderType=cv2.BORDER_REPLICATE)

    cx, cy, sx, sy = sobel(np.cos(a2), 1, 0), sobel(np.cos(a2), 0, 1), sobel(np.sin(a2), 1, 0), sobel(np.sin(a2), 0, 1)
    t = 0.5 * np.arctan2(2.0 * (cx * cy + sx * sy), cx**2 + sx**2 - cy**2 - sy**2)
    np.testing.assert_allclose(mag, (90 / np.pi) * np.sqrt(cx**2 + sx**2 + cy**2 + sy**2), rtol=1e-12)
    np.testing.assert_allclose(dx, mag * np.cos(t), atol=1e-9 * mag.max())
    np.testing.assert_allclose(dy, mag * np.sin(t), atol=1e-9 * mag.max())


def test_the_same_frame_gives_the_same_maps_bit_for_bit():
    # a multi-threaded elementwise kernel (cv2.magnitude) once varied in the last bit from call to call
    rng = np.random.default_rng(9)
    x, y = np.meshgrid(np.arange(1536, dtype=np.float32), np.arange(1024, dtype=np.float32))
    s0 = (1000.0 + 500.0 * (x > 700) + rng.normal(0, 20.0, x.shape)).astype(np.float32)
    dolp = np.clip(0.3 + 0.2 * (y > 400) + rng.normal(0, 0.03, x.shape), 0, 1).astype(np.float32)
    aop = ((40.0 * np.sin(x / 50.0) + rng.normal(0, 3.0, x.shape)) % 180.0).astype(np.float32)
    dolp[rng.random(x.shape) < 1e-3] = np.nan
    aop[np.isnan(dolp)] = np.nan
    first = edge_maps(s0, dolp, aop, "canny")
    for _ in range(3):
        again = edge_maps(s0, dolp, aop, "canny")
        for name in IMAGE_TYPES:
            np.testing.assert_array_equal(again[name].gradient, first[name].gradient, err_msg=name)
            np.testing.assert_array_equal(again[name].edges, first[name].edges, err_msg=name)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_tiny_and_huge_gradients_keep_their_size(dtype):
    x, _ = _grid()
    ramp = (x * 3.0).astype(dtype)  # slope 3 per pixel
    big = np.finfo(dtype).max / 16
    for scale in (dtype(1e-30) if dtype == np.float32 else 1e-300, dtype(1.0), big / 1e3):
        g = gradient_magnitude(ramp * scale)
        np.testing.assert_allclose(_interior(g), 3.0 * scale, rtol=1e-5)
    # thresholds and edges of a step scale with it (the squares of a float32 1e-30 underflow)
    step = np.where(x >= 32, 1.0, 0.0).astype(dtype)
    ref = edge_maps(step, step, np.zeros_like(step), "canny")["S0"]
    tiny = edge_maps(step * dtype(1e-30), step, np.zeros_like(step), "canny")["S0"]
    assert tiny.high == pytest.approx(ref.high * 1e-30, rel=1e-5)
    np.testing.assert_array_equal(tiny.edges, ref.edges)


def test_float64_gradient_statistics_are_numpys():
    rng = np.random.default_rng(4)
    g = np.abs(rng.normal(0.0, 1.0, (50, 40)))
    g[0, 0] = 1e39  # beyond float32
    g[1, :3] = np.nan
    st = EdgeMap(g, np.zeros(g.shape, bool), 1.0, 0.4, "u").stats()
    fin = g[np.isfinite(g)]
    assert [st["gradient"][k] for k in ("p50", "p90", "p99")] == pytest.approx(np.percentile(fin, [50, 90, 99]),
                                                                              rel=1e-15)
    assert st["gradient"]["max"] == 1e39 and st["valid_fraction"] == fin.size / g.size


def test_noise_sigmas_follow_the_quad_noise_model():
    from pihim.inspection.edges import noise_sigmas

    s0 = np.full((6, 7), 800.0)
    s0[:, 4:] = 50.0
    s0[0, 0] = np.nan  # counts as 0 in its 3x3 mean
    g, r = 2.0, 1.5
    sig_s0, sig_p = noise_sigmas(s0, electrons_per_dn=g, read_noise_dn=r)
    assert sig_s0[1, 1] == pytest.approx(math.sqrt(800.0 * 8 / 9 / 2 / g + r * r + 1 / 12), rel=1e-6)
    var_i = 800.0 / 2 / g + r * r + 1 / 12
    assert sig_s0[3, 1] == pytest.approx(math.sqrt(var_i), rel=1e-6)
    assert sig_p[3, 1] == pytest.approx(math.sqrt(2 * var_i) / 800.0, rel=1e-6)
    var_dark = 50.0 / 2 / g + r * r + 1 / 12
    assert sig_p[3, 6] == pytest.approx(math.sqrt(2 * var_dark) / 50.0, rel=1e-6)
    # a shot-noise-limited sensor of unknown gain: sigma_DoLP ~ 1 / sqrt(S0)
    _, p1 = noise_sigmas(np.full((3, 3), 400.0))
    _, p4 = noise_sigmas(np.full((3, 3), 1600.0))
    assert p1[1, 1] / p4[1, 1] == pytest.approx(2.0, rel=1e-3)
    assert np.isinf(noise_sigmas(np.zeros((3, 3)))[1]).all()  # no light: no polarization to measure
    for bad in ({"electrons_per_dn": 0.0}, {"electrons_per_dn": math.nan}, {"electrons_per_dn": 1e300},
                {"read_noise_dn": -1.0}, {"read_noise_dn": 1e200}):
        with pytest.raises(PihimInputError):
            noise_sigmas(s0, **bad)


def test_sensor_noise_reads_the_log():
    from pihim.inspection.edges import sensor_noise

    assert sensor_noise({}) == {"electrons_per_dn": None, "read_noise_dn": 0.0}
    log = {"sensor": {"model": {"electrons_per_dn": 1.94, "read_noise_dn": 1.15}}}
    assert sensor_noise(log) == {"electrons_per_dn": 1.94, "read_noise_dn": 1.15}
    for bad in ({"sensor": [1]}, {"sensor": {"model": 3}}, {"sensor": {"model": {"electrons_per_dn": -1}}},
                {"sensor": {"model": {"read_noise_dn": "x"}}}, {"sensor": {"model": {"electrons_per_dn": True}}},
                {"sensor": {"model": {"read_noise_dn": None}}}, {"sensor": {"model": {"read_noise_dn": 1e200}}},
                {"sensor": {"model": {"electrons_per_dn": 10**400}}}):
        with pytest.raises(PihimInputError):
            sensor_noise(bad)


def test_noise_weighting_keeps_a_dark_regions_noise_out_of_the_maps():
    """A DoFP frame, bright on the left with a DoLP step, dark on the right: shot noise makes the dark half's DoLP
    and AoP noise; with one threshold per map it floods them, divided by each pixel's noise it does not."""
    from pihim.camera import polar_image
    from pihim.inspection.edges import noise_sigmas
    from pihim.render.mosaic import mosaic_from_stokes

    h, w = 128, 256
    x, _ = np.meshgrid(np.arange(w), np.arange(h))
    s0 = np.where(x < 128, 3000.0, 60.0)
    dolp = np.where(x < 64, 0.1, 0.5)  # the step at column 64, in the bright half
    s1, s2 = s0 * dolp, np.zeros_like(s0)
    raw = mosaic_from_stokes(s0, s1, s2, electrons_per_dn=2.0, read_noise_dn=1.2, rng=1)
    pim = polar_image(raw, demosaic="full", bit_depth=12)
    plain = edge_maps(pim.s0, pim.dolp, pim.aop_deg, "canny")
    weighted = edge_maps(pim.s0, pim.dolp, pim.aop_deg, "canny",
                         noise=noise_sigmas(pim.s0, electrons_per_dn=2.0, read_noise_dn=1.2))
    dark = x >= 136
    assert plain["DoLP"].edges[dark].mean() > 0.05  # the noise of the dark half, as edges
    assert weighted["DoLP"].edges[dark].mean() < 0.005
    assert weighted["AoP"].edges[dark].mean() < 0.005
    step = weighted["DoLP"].edges[8:-8, 60:69]
    assert step.any(axis=1).mean() > 0.95  # the DoLP step is found along its length
    sig_s0, sig_dolp = noise_sigmas(pim.s0, electrons_per_dn=2.0, read_noise_dn=1.2)
    np.testing.assert_allclose(weighted["S0"].gradient, plain["S0"].gradient / sig_s0, rtol=1e-6)
    np.testing.assert_allclose(weighted["DoLP"].gradient, plain["DoLP"].gradient / sig_dolp, rtol=1e-6)
    np.testing.assert_allclose(weighted["AoP"].gradient, plain["AoP"].gradient / (sig_dolp * (90 / np.pi)), rtol=1e-5)
    assert weighted.parameters["noise_weighted"] and not plain.parameters["noise_weighted"]
    assert "multiples of the pixel noise" in weighted["DoLP"].units
    with pytest.raises(PihimInputError):
        edge_maps(pim.s0, pim.dolp, pim.aop_deg, noise=(pim.s0, pim.s0[:, :10]))
    with pytest.raises(PihimInputError):
        edge_maps(pim.s0, pim.dolp, pim.aop_deg, noise=noise_sigmas(pim.s0), aop_dolp_weighted=False)
    for bad in (0.0, -1.0, np.nan):
        sig = np.ones_like(pim.s0)
        sig[3, 3] = bad
        with pytest.raises(PihimInputError):
            edge_maps(pim.s0, pim.dolp, pim.aop_deg, noise=(sig, np.ones_like(sig)))


@pytest.mark.parametrize(("kwargs", "says"), [({"n_sigma": math.nan}, "n_sigma must be a finite number >= 0"),
                                              ({"n_sigma": -1.0}, "n_sigma"), ({"low_ratio": 5.0}, r"low_ratio must be in \(0, 1\]"),
                                              ({"floor_fraction": -0.1}, "floor_fraction must be a finite number >= 0")])
def test_robust_thresholds_refuse_settings_without_meaning(kwargs, says):
    """n_sigma=nan gave (nan, nan); low_ratio=5 put the low threshold above the high one. The bounds are
    edge_maps' own (n_sigma 0 and floor_fraction 1.5 are accepted by both)."""
    with pytest.raises(PihimInputError, match=says):
        robust_thresholds(np.linspace(0.0, 1.0, 100), **kwargs)
    robust_thresholds(np.linspace(0.0, 1.0, 100), n_sigma=0.0, floor_fraction=1.5)
