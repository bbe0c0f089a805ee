"""Pin the image AoP convention with an oracle that never calls pihim's Stokes code.

Intensities are made with Malus's law from explicit 2-D vectors in
(column, row) pixel coordinates, rows growing downward: a polarizer whose
transmission axis is at displayed angle ``t`` (counter-clockwise from image
right) has direction ``(cos t, -sin t)``. If pihim's AoP turned clockwise, or
the layout angles were read the other way round, these tests fail.
"""

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from pihim.camera import IMX250MZR, polar_image
from pihim.polarimetry import aop_difference_deg


def _direction(angle_deg):
    t = np.radians(angle_deg)
    return np.stack([np.cos(t), -np.sin(t)], axis=-1)  # (col, row), row down


def _malus_mosaic(s0, p, e_angle_deg, layout=IMX250MZR):
    """Raw mosaic for light of intensity s0, DoLP p and field direction angle (displayed)."""
    shape = np.shape(s0)
    pol = layout.angle_map(shape).astype(float)
    e = _direction(e_angle_deg)
    a = _direction(pol)
    cos2 = np.sum(e * a, axis=-1) ** 2
    # partially polarized: unpolarized part (1-p) s0 passes half, polarized part p s0 by Malus
    return s0 * ((1 - p) * 0.5 + p * cos2)


@pytest.mark.parametrize("alpha", [10.0, 30.0, 60.0, 100.0, 150.0])
def test_aop_follows_displayed_field_direction(alpha):
    m = _malus_mosaic(np.full((8, 8), 100.0), 0.8, np.full((8, 8), alpha))
    out = polar_image(m)
    assert np.allclose(out.dolp, 0.8, atol=1e-4)
    assert np.max(aop_difference_deg(out.aop_deg, alpha)) < 1e-3
    assert np.allclose(out.aop_deg, alpha, atol=1e-3)  # folded into [0, 180), not only equal as axes


@pytest.mark.parametrize("t", [5.0, 20.0, 40.0])
def test_scene_rotation_raises_aop(t):
    base = 25.0
    m0 = _malus_mosaic(np.full((4, 4), 100.0), 1.0, np.full((4, 4), base))
    m1 = _malus_mosaic(np.full((4, 4), 100.0), 1.0, np.full((4, 4), base + t))
    d = polar_image(m1).aop_deg - polar_image(m0).aop_deg
    assert np.allclose(d, t, atol=1e-3)  # signed: counter-clockwise rotation increases AoP


@pytest.mark.parametrize("alpha", [20.0, 65.0, 125.0])
def test_polarized_bar_orientation_matches_image_geometry(alpha):
    """A bar lying along its own field direction: AoP equals its drawn orientation."""
    n = 96
    rows, cols = np.mgrid[0:n, 0:n].astype(float)
    u = _direction(alpha)
    x, y = cols - n / 2, rows - n / 2
    along = x * u[0] + y * u[1]
    across = -x * u[1] + y * u[0]
    bar = (np.abs(along) < 36) & (np.abs(across) < 4)
    s0 = np.where(bar, 400.0, 100.0)
    p = np.where(bar, 0.9, 0.0)
    m = _malus_mosaic(s0, p, np.full((n, n), alpha))
    out = polar_image(m, demosaic="superpixel")
    mask = out.dolp > 0.5
    # orientation from second moments of the bar, in pixel coordinates (row down)
    rr, cc = np.nonzero(mask)
    dx, dy = cc - cc.mean(), rr - rr.mean()
    theta_pix = 0.5 * np.degrees(np.arctan2(2 * np.mean(dx * dy), np.mean(dx * dx) - np.mean(dy * dy)))
    displayed = np.mod(-theta_pix, 180.0)  # flip: row axis points down
    assert aop_difference_deg(displayed, alpha) < 2.0
    interior = binary_erosion(mask, iterations=2)  # super-pixels wholly inside the bar
    assert interior.sum() > 20
    assert np.max(aop_difference_deg(out.aop_deg[interior], displayed)) < 2.0
    assert np.max(aop_difference_deg(out.aop_deg[interior], alpha)) < 1e-3
