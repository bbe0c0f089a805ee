"""Optional cross-check against polanalyser (an independent implementation)."""

import numpy as np
import pytest

from pihim.camera import IMX250MZR, polar_image
from pihim.camera.demosaic import bilinear
from pihim.polarimetry import aop_difference_deg, stokes_from_dolp_aop
from pihim.render import mosaic_from_stokes

pa = pytest.importorskip("polanalyser")


def _scene(seed=0, shape=(32, 48)):
    rng = np.random.default_rng(seed)
    h, w = shape
    blk = lambda lo, hi: np.kron(rng.uniform(lo, hi, (h // 2, w // 2)), np.ones((2, 2)))
    return stokes_from_dolp_aop(blk(500, 3000), blk(0.05, 0.9), blk(0, 180))


def test_superpixel_stokes_dolp_aop_match_polanalyser():
    m = mosaic_from_stokes(*_scene(), bit_depth=None)
    ours = polar_image(m)
    channels = IMX250MZR.split(m)  # 0, 45, 90, 135
    muellers = [pa.polarizer(np.radians(a)) for a in (0.0, 45.0, 90.0, 135.0)]
    s = pa.calcStokes(channels, muellers)
    assert np.allclose(ours.s0, s[..., 0], rtol=1e-5)
    assert np.allclose(ours.dolp, pa.cvtStokesToDoLP(s), atol=1e-5)
    theirs_aop = np.degrees(pa.cvtStokesToAoLP(s))
    assert np.max(aop_difference_deg(ours.aop_deg, theirs_aop)) < 1e-3


def test_bilinear_matches_polanalyser_demosaic():
    rng = np.random.default_rng(1)
    m = rng.uniform(0, 4000, (32, 48))
    theirs = np.asarray(pa.demosaicing(m, pa.COLOR_PolarMono))  # (4, H, W): 0, 45, 90, 135
    ours = bilinear(m)
    inner = (slice(None), slice(2, -2), slice(2, -2))
    assert np.allclose(ours[inner], theirs[inner], rtol=1e-3, atol=1.0)
