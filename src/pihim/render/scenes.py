"""Synthetic full-resolution Stokes scenes with known ground truth.

The scenes are the test targets of the demosaicing routes: piecewise-smooth
Stokes fields whose discontinuities (heliostat facets against the ground,
dark gaps between facets, thin structures) are where per-channel
interpolation of a DoFP mosaic produces false polarization. Edges are
rendered with sub-pixel accuracy by area supersampling, so the ground truth
is what an ideal pixel integrating over its footprint would see; render the
raw mosaic with :func:`pihim.render.mosaic.mosaic_from_stokes`.

All Stokes values are in digital numbers of the mosaic model: unpolarized
light of ``S0`` gives ``S0 / 2`` DN per ideal pixel, so ``S0 <= 2 * 4095 /
(1 + DoLP)`` keeps a 12-bit sensor unsaturated.

Image coordinates: pixel ``(i, j)`` covers ``[j, j + 1) x [i, i + 1)`` in
``(x, y)``, y pointing down the rows.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from pihim.errors import PihimInputError
from pihim.polarimetry.stokes import stokes_from_dolp_aop

StokesField = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]


def _check_shape(shape: tuple[int, int]) -> tuple[int, int]:
    try:
        h, w = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise PihimInputError(f"shape must be (rows, columns), got {shape!r}") from None
    if h < 2 or w < 2:
        raise PihimInputError(f"scene shape must be at least 2x2, got {shape!r}")
    return h, w


def uniform_scene(
    shape: tuple[int, int], s0: float, dolp: float, aop_deg: float
) -> StokesField:
    """A spatially uniform, partially linearly polarized field.

    Parameters
    ----------
    shape : (int, int)
        (rows, columns).
    s0 : float
        Total intensity in DN (see module docstring).
    dolp : float
        Degree of linear polarization in [0, 1].
    aop_deg : float
        Angle of polarization in degrees, counter-clockwise from image right.

    Returns
    -------
    s0, s1, s2 : numpy.ndarray, shape ``shape``
        float64 Stokes components.
    """
    h, w = _check_shape(shape)
    if not 0.0 <= dolp <= 1.0:
        raise PihimInputError(f"DoLP must be in [0, 1], got {dolp}")
    return stokes_from_dolp_aop(np.full((h, w), float(s0)), dolp, aop_deg)


def _coverage(
    vertices: NDArray[np.float64], shape: tuple[int, int], supersample: int
) -> tuple[tuple[slice, slice], NDArray[np.float64]] | None:
    """Fraction of each pixel's area inside a convex polygon.

    Parameters
    ----------
    vertices : (n, 2) array of (x, y)
        Convex polygon, either orientation.
    shape : (int, int)
        Image shape.
    supersample : int
        Sub-samples per pixel side.

    Returns
    -------
    (rows, cols), coverage : the bounding-box slices and the coverage inside
    them, or ``None`` when the polygon misses the image.
    """
    h, w = shape
    x0 = max(int(np.floor(vertices[:, 0].min())), 0)
    x1 = min(int(np.ceil(vertices[:, 0].max())), w)
    y0 = max(int(np.floor(vertices[:, 1].min())), 0)
    y1 = min(int(np.ceil(vertices[:, 1].max())), h)
    if x1 <= x0 or y1 <= y0:
        return None
    n = supersample
    sub = (np.arange(n) + 0.5) / n
    xs = (np.arange(x0, x1)[:, None] + sub[None, :]).ravel()
    ys = (np.arange(y0, y1)[:, None] + sub[None, :]).ravel()
    # signed area decides the orientation; inside = same side of every edge
    v = vertices
    area2 = np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1])
    sign = 1.0 if area2 >= 0 else -1.0
    inside = np.ones((ys.size, xs.size), dtype=bool)
    for k in range(len(v)):
        ax, ay = v[k]
        bx, by = v[(k + 1) % len(v)]
        cross_x = (bx - ax) * (ys[:, None] - ay)
        cross_y = (by - ay) * (xs[None, :] - ax)
        inside &= sign * (cross_x - cross_y) >= 0.0
    cov = inside.reshape(y1 - y0, n, x1 - x0, n).mean(axis=(1, 3))
    return (slice(y0, y1), slice(x0, x1)), cov


def _paint(
    field: list[NDArray[np.float64]],
    vertices: NDArray[np.float64],
    stokes: Callable[[NDArray[np.float64], NDArray[np.float64]], StokesField],
    supersample: int,
) -> None:
    """Composite a polygon of (pixel-centre sampled) Stokes over ``field`` in place.

    Each pixel becomes ``(1 - c) * old + c * new`` with ``c`` the polygon's
    area coverage of the pixel: the intensity a pixel integrating over its
    footprint would record, as Stokes vectors add incoherently. ``stokes``
    maps pixel-centre coordinates ``(x, y)`` of the polygon's bounding box to
    the polygon's Stokes components there.
    """
    got = _coverage(vertices, field[0].shape, supersample)
    if got is None:
        return
    (rows, cols), cov = got
    yy, xx = np.mgrid[rows, cols].astype(np.float64) + 0.5
    for f, s in zip(field, stokes(xx, yy), strict=True):
        f[rows, cols] = (1.0 - cov) * f[rows, cols] + cov * s


def _linear_field(
    xx: NDArray[np.float64],
    yy: NDArray[np.float64],
    centre: tuple[float, float],
    value: float,
    gradient: tuple[float, float],
) -> NDArray[np.float64]:
    """``value`` at ``centre`` plus a linear ramp with the (d/dx, d/dy) ``gradient``."""
    return value + gradient[0] * (xx - centre[0]) + gradient[1] * (yy - centre[1])


def _quad(cx: float, cy: float, half_w: float, half_h: float, angle: float, skew: float) -> NDArray[np.float64]:
    """Corners (x, y) of a rotated, slightly sheared rectangle (a facet seen in perspective)."""
    local = np.array([[-half_w, -half_h], [half_w, -half_h], [half_w, half_h], [-half_w, half_h]])
    local[:, 0] += skew * local[:, 1]
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + np.array([cx, cy])


def edge_scene(
    shape: tuple[int, int] = (256, 320),
    rng: np.random.Generator | int | None = None,
    *,
    n_heliostats: int | None = None,
    supersample: int = 4,
) -> StokesField:
    """A heliostat-field-like scene with sharp, partly oblique edges.

    The scene contains, painted in this order:

    * ground: S0 about 900-1500 DN with a gentle gradient, DoLP 0.02-0.08,
      AoP near horizontal with a slow drift;
    * a few darker ground patches (roads, shadows), axis aligned or rotated;
    * ``n_heliostats`` heliostats: a dark frame (S0 about 150-400 DN,
      DoLP about 0.05) carrying a grid of 2-3 x 2-4 facets that reflect the
      sky: S0 2000-4000 DN, DoLP 0.15-0.6 and an AoP shared by the heliostat
      up to a few degrees of per-facet canting, with smooth sky gradients
      inside each facet. The dark gaps between facets are 1-4 px wide. About
      one heliostat in three is axis aligned, the others are rotated and
      sheared so their edges are oblique;
    * a few thin (1-2 px) bright, polarized lines (specular glints on
      torque tubes).

    Heliostat half-widths are 8-20 % of ``min(H, W, 512)`` pixels, so at
    sensor size they stay about 80-200 px wide and their number grows with
    the image area. Polygon edges are anti-aliased by
    ``supersample x supersample`` area sampling; inside a polygon the Stokes
    field is evaluated at pixel centres. If needed the whole field is scaled
    so that the brightest ideal pixel, ``(S0 + |S_lin|) / 2``, is at most
    4000 DN: a noise-free 12-bit rendering does not saturate.

    Parameters
    ----------
    shape : (int, int)
        (rows, columns); any size >= 16 x 16.
    rng : numpy.random.Generator or int, optional
        Random source or seed.
    n_heliostats : int, optional
        Number of heliostats; default ``6 H W / min(H, W, 512)**2``
        (clipped to 2..400), which covers roughly a third of the image.
    supersample : int
        Sub-samples per pixel side for the edge coverage.

    Returns
    -------
    s0, s1, s2 : numpy.ndarray, shape ``shape``
        float64 ground-truth Stokes components in DN.
    """
    h, w = _check_shape(shape)
    if h < 16 or w < 16:
        raise PihimInputError(f"edge scene needs at least 16x16 pixels, got {shape!r}")
    if supersample < 1:
        raise PihimInputError("supersample must be >= 1")
    gen = np.random.default_rng(rng)
    scale = float(min(h, w))
    centre = (w / 2, h / 2)

    # ground: smooth S0 with a gentle ripple, weak near-horizontal polarization
    g_s0 = (gen.uniform(900, 1500), tuple(gen.uniform(-0.6, 0.6, 2) * 400 / scale))
    g_phase = gen.uniform()
    g_p = (gen.uniform(0.02, 0.08), tuple(gen.uniform(-0.02, 0.02, 2) / scale))
    g_a = (gen.uniform(-15, 15), tuple(gen.uniform(-20, 20, 2) / scale))

    def ground(xx: NDArray, yy: NDArray, gain: float = 1.0, p_gain: float = 1.0, da: float = 0.0) -> StokesField:
        s0 = _linear_field(xx, yy, centre, *g_s0)
        s0 = s0 + 80 * np.sin(2 * np.pi * (xx / (0.7 * scale) + g_phase)) * np.cos(2 * np.pi * yy / (0.9 * scale))
        s0 = np.maximum(s0, 0.0)  # the gradient crosses zero across a frame ~10x wider than high: black, not negative
        p = np.clip(_linear_field(xx, yy, centre, *g_p) * p_gain, 0.0, 1.0)
        return stokes_from_dolp_aop(gain * s0, p, _linear_field(xx, yy, centre, *g_a) + da)

    def constant(s0: float, p: float, a: float) -> Callable[[NDArray, NDArray], StokesField]:
        return lambda xx, yy: stokes_from_dolp_aop(np.full(xx.shape, s0), p, a)

    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    field = list(ground(xx, yy))
    del xx, yy

    # darker ground patches (roads, shadows)
    for _ in range(int(gen.integers(2, 5))):
        cx, cy = gen.uniform(0, w), gen.uniform(0, h)
        angle = 0.0 if gen.uniform() < 0.5 else gen.uniform(-np.pi / 4, np.pi / 4)
        quad = _quad(cx, cy, gen.uniform(0.1, 0.5) * scale, gen.uniform(0.03, 0.12) * scale, angle, 0.0)
        gain, p_gain, da = gen.uniform(0.35, 0.7), gen.uniform(0.8, 1.5), gen.uniform(-5, 5)
        _paint(field, quad, lambda x, y, g=gain, pg=p_gain, d=da: ground(x, y, g, pg, d), supersample)

    # heliostat size is capped (about 80-200 px wide at sensor size); their
    # number grows with the image area instead
    size = min(scale, 512.0)
    n_helio = n_heliostats if n_heliostats is not None else int(np.clip(6.0 * h * w / size**2, 2, 400))
    for k in range(n_helio):
        cx, cy = gen.uniform(0.05 * w, 0.95 * w), gen.uniform(0.05 * h, 0.95 * h)
        half_w = gen.uniform(0.08, 0.2) * size
        half_h = half_w * gen.uniform(0.45, 0.9)
        if k % 3 == 0:
            angle, skew = 0.0, 0.0
        else:
            angle, skew = gen.uniform(-np.pi / 5, np.pi / 5), gen.uniform(-0.25, 0.25)
        frame = _quad(cx, cy, half_w, half_h, angle, skew)
        _paint(field, frame, constant(gen.uniform(150, 400), gen.uniform(0.02, 0.1), gen.uniform(0, 180)), supersample)
        n_r, n_c = int(gen.integers(2, 4)), int(gen.integers(2, 5))
        gap = gen.uniform(1.0, 4.0)  # px between facets
        base_aop = gen.uniform(0, 180)
        base_p = gen.uniform(0.15, 0.6)
        fw = (2 * half_w - (n_c + 1) * gap) / n_c
        fh = (2 * half_h - (n_r + 1) * gap) / n_r
        if fw < 2 or fh < 2:
            continue
        c, s = np.cos(angle), np.sin(angle)
        for r in range(n_r):
            for q in range(n_c):
                # facet centre in the heliostat frame, then skewed and rotated
                ly = -half_h + gap + fh / 2 + r * (fh + gap)
                lx = -half_w + gap + fw / 2 + q * (fw + gap) + skew * ly
                fc = (cx + c * lx - s * ly, cy + s * lx + c * ly)
                facet = _quad(fc[0], fc[1], fw / 2, fh / 2, angle, skew)
                s0_f = (gen.uniform(2000, 4000), tuple(gen.uniform(-3, 3, 2)))
                p_f = (base_p + gen.uniform(-0.05, 0.05), tuple(gen.uniform(-0.001, 0.001, 2)))
                a_f = (base_aop + gen.uniform(-4, 4), tuple(gen.uniform(-0.1, 0.1, 2)))

                def sky(x: NDArray, y: NDArray, fc=fc, s0_f=s0_f, p_f=p_f, a_f=a_f) -> StokesField:
                    return stokes_from_dolp_aop(
                        np.clip(_linear_field(x, y, fc, *s0_f), 1500, 4800),
                        np.clip(_linear_field(x, y, fc, *p_f), 0.0, 0.65),
                        _linear_field(x, y, fc, *a_f),
                    )

                _paint(field, facet, sky, supersample)

    # thin glints
    for _ in range(int(gen.integers(2, 5))):
        cx, cy = gen.uniform(0, w), gen.uniform(0, h)
        angle = float(gen.choice([0.0, np.pi / 2, gen.uniform(-np.pi, np.pi)]))
        line = _quad(cx, cy, gen.uniform(0.1, 0.3) * scale, gen.uniform(0.5, 1.0), angle, 0.0)
        _paint(field, line, constant(gen.uniform(2500, 4500), gen.uniform(0.2, 0.7), gen.uniform(0, 180)), supersample)

    s0, s1, s2 = field
    # keep every ideal pixel below 12-bit full scale: I_max = (S0 + |S_lin|) / 2
    peak = 0.5 * (s0 + np.hypot(s1, s2)).max()
    if peak > 4000.0:
        k = 4000.0 / peak
        s0, s1, s2 = s0 * k, s1 * k, s2 * k
    return s0, s1, s2
