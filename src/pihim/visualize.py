"""Colour renderings of polarimetric images, as polarimetry users expect them.

* AoP: cyclic HSV hue (0 and 180 deg share a colour), optionally with the
  value channel weighted by DoLP so that unpolarized regions go dark.
* DoLP: a perceptually uniform colour map (viridis by default), 0..``vmax``.
* S0: grey levels with a robust percentile stretch.

NaN (masked) pixels render black. All functions return ``uint8`` RGB arrays
(``(H, W, 3)``; ``(H, W)`` for grey) and never modify their inputs.

References
----------
.. [1] P. Kovesi, "Good colour maps: how to design them", arXiv:1509.03700
   (2015) -- why a perceptual map for DoLP and a cyclic one for AoP.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim._atomic import atomic_path
from pihim.errors import PihimInputError


def _hsv_to_rgb(h: NDArray, s: NDArray, v: NDArray) -> NDArray[np.float64]:
    """Vectorised HSV -> RGB, all inputs in [0, 1]."""
    h6 = np.mod(h, 1.0) * 6.0
    c = v * s
    x = c * (1.0 - np.abs(np.mod(h6, 2.0) - 1.0))
    z = np.zeros_like(c)
    sector = np.floor(h6).astype(int) % 6
    r = np.choose(sector, [c, x, z, z, x, c])
    g = np.choose(sector, [x, c, c, x, z, z])
    b = np.choose(sector, [z, z, x, c, c, x])
    m = v - c
    return np.stack([r + m, g + m, b + m], axis=-1)


def _to_u8(x: NDArray) -> NDArray[np.uint8]:
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)


def aop_to_rgb(
    aop_deg: ArrayLike,
    dolp: ArrayLike | None = None,
    *,
    dolp_max: float = 1.0,
) -> NDArray[np.uint8]:
    """AoP as cyclic hue (0 deg red, 60 green, 120 blue); value from DoLP if given.

    Parameters
    ----------
    aop_deg : array_like
        AoP in degrees (any real value; taken modulo 180).
    dolp : array_like, optional
        If given, the brightness is ``clip(dolp / dolp_max, 0, 1)``.
    dolp_max : float
        DoLP that maps to full brightness.
    """
    a = np.asarray(aop_deg, dtype=np.float64)
    valid = np.isfinite(a)
    v = np.ones_like(a)
    if dolp is not None:
        d = np.asarray(dolp, dtype=np.float64)
        if d.shape != a.shape:
            raise PihimInputError(f"AoP and DoLP shapes differ: {a.shape} vs {d.shape}")
        valid &= np.isfinite(d)
        v = np.clip(np.nan_to_num(d) / dolp_max, 0.0, 1.0)
    rgb = _hsv_to_rgb(np.nan_to_num(a) / 180.0, np.ones_like(a), v)
    rgb[~valid] = 0.0
    return _to_u8(rgb)


def dolp_to_rgb(dolp: ArrayLike, *, vmax: float = 1.0, cmap: str = "viridis") -> NDArray[np.uint8]:
    """DoLP through a perceptual matplotlib colour map over ``[0, vmax]``."""
    from matplotlib import colormaps

    d = np.asarray(dolp, dtype=np.float64)
    lut = colormaps[cmap].resampled(256)(np.linspace(0.0, 1.0, 256))[:, :3]
    idx = np.clip(np.rint(np.nan_to_num(d) / vmax * 255.0), 0, 255).astype(np.intp)
    rgb = lut[idx]
    rgb[~np.isfinite(d)] = 0.0
    return _to_u8(rgb)


def s0_to_gray(s0: ArrayLike, *, percentiles: tuple[float, float] = (0.5, 99.5)) -> NDArray[np.uint8]:
    """S0 as 8-bit grey with a percentile stretch (NaN -> 0)."""
    x = np.asarray(s0, dtype=np.float64)
    finite = x[np.isfinite(x)]
    if finite.size == 0:
        return np.zeros(x.shape, dtype=np.uint8)
    lo, hi = np.percentile(finite, percentiles)
    scale = (x - lo) / (hi - lo) if hi > lo else np.zeros_like(x)
    return _to_u8(np.clip(np.nan_to_num(scale), 0.0, 1.0))


def write_png(path: str | Path, image: NDArray[np.uint8], *, atomic: bool = True) -> Path:
    """Write an RGB ``(H, W, 3)`` or grey ``(H, W)`` uint8 image as PNG, atomically.

    ``atomic=False`` writes ``path`` directly (for a caller that already
    writes under a temporary name).
    """
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3):
        raise PihimInputError("PNG previews must be uint8 grey or RGB images")
    if img.ndim == 3:
        img = img[..., ::-1]  # OpenCV writes BGR
    with atomic_path(path) if atomic else contextlib.nullcontext(Path(path)) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(img)):
            raise OSError(f"{path}: could not write PNG")
    return Path(path)


#: Colour settings for hemisphere maps: (colour map, vmin, vmax).
POLAR_MAP_STYLES: dict[str, tuple[str, float, float]] = {
    "dolp": ("viridis", 0.0, 1.0),
    "aop": ("twilight", 0.0, 180.0),
    "aop_difference": ("magma", 0.0, 90.0),
}


def polar_map_png(
    values: ArrayLike,
    path: str | Path,
    *,
    style: str,
    label: str,
    title: str,
    markers: tuple[tuple[float, float, str, str], ...] = (),
    atomic: bool = True,
) -> Path:
    """Write a hemisphere map as a polar plot PNG (atomically unless ``atomic`` is false).

    North up, azimuth clockwise (a map seen from above), radius = zenith
    angle 0-90 deg, as the paper's Fig. 2c-d and 5c-d.

    Parameters
    ----------
    values : array_like, shape (nz, na)
        Cell values on a regular grid: rows are zenith bands from 0 to 90 deg,
        columns azimuth bins from 0 (North) clockwise to 360 deg. NaN cells are blank.
    style : {"dolp", "aop", "aop_difference"}
        Colour map and range (:data:`POLAR_MAP_STYLES`); AoP uses a cyclic map.
    markers : tuple of (azimuth_deg, zenith_deg, matplotlib marker, name)
        Points to mark (e.g. the sun as ``"*"``).
    atomic : bool
        Write through a temporary sibling and rename (default); false writes
        ``path`` directly, for a caller that writes a group of files
        (:func:`pihim._atomic.write_group`).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if style not in POLAR_MAP_STYLES:
        raise PihimInputError(f"unknown map style {style!r}")
    cmap, vmin, vmax = POLAR_MAP_STYLES[style]
    data = np.asarray(values, dtype=float)
    nz, na = data.shape
    theta_edges = np.radians(np.linspace(0.0, 360.0, na + 1))
    r_edges = np.linspace(0.0, 90.0, nz + 1)
    fig = Figure(figsize=(6.4, 5.6), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="polar")
    ax.set_theta_zero_location("N")
    ax.set_theta_direction(-1)
    mesh = ax.pcolormesh(theta_edges, r_edges, data, cmap=cmap, vmin=vmin, vmax=vmax, shading="flat", rasterized=True)
    for az, zen, marker, name in markers:
        if 0.0 <= zen <= 90.0:
            ax.plot([np.radians(az)], [zen], marker=marker, markersize=13 if marker == "*" else 9,
                    color="gold" if marker == "*" else "white", markeredgecolor="black", linestyle="none", label=name)
    ax.set_ylim(0.0, 90.0)
    ax.set_yticks([30.0, 60.0, 90.0])
    ax.set_yticklabels(["30", "60", "90"], fontsize=8)
    for lab in ax.get_yticklabels():
        lab.set_bbox({"facecolor": "white", "alpha": 0.7, "edgecolor": "none", "pad": 1.0})
    ax.set_rlabel_position(22.5)
    ax.set_xticks(np.radians([0, 90, 180, 270]))
    ax.set_xticklabels(["N", "E", "S", "W"])
    ax.set_title(title, fontsize=10)
    cb = fig.colorbar(mesh, ax=ax, shrink=0.8, pad=0.08)
    cb.set_label(label)
    if style == "aop":
        cb.set_ticks([0, 45, 90, 135, 180])
    with atomic_path(path) if atomic else contextlib.nullcontext(Path(path)) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)


def _aop_wheel(ax: object, dolp_weighted: bool) -> None:
    """A hue wheel keyed to AoP (axial: opposite directions share a colour), angles counter-clockwise."""
    n = 256
    y, x = np.mgrid[-1.0:1.0:n * 1j, -1.0:1.0:n * 1j]
    r = np.hypot(x, y)
    ang = np.mod(np.degrees(np.arctan2(y, x)), 180.0)  # image up = +y: counter-clockwise from the right
    v = np.clip(r, 0.0, 1.0) if dolp_weighted else np.ones_like(r)
    rgb = _hsv_to_rgb(ang / 180.0, np.ones_like(r), v)
    rgba = np.concatenate([rgb, (r <= 1.0)[..., None].astype(float)], axis=-1)
    ax.imshow(rgba, origin="lower", extent=(-1, 1, -1, 1))  # type: ignore[attr-defined]
    for deg in (0, 45, 90, 135):
        t = np.radians(deg)
        ax.text(1.3 * np.cos(t), 1.3 * np.sin(t), f"{deg}", ha="center", va="center", fontsize=8)  # type: ignore[attr-defined]
    ax.set_xlim(-1.6, 1.6)  # type: ignore[attr-defined]
    ax.set_ylim(-1.6, 1.6)  # type: ignore[attr-defined]
    ax.set_aspect("equal")  # type: ignore[attr-defined]
    ax.axis("off")  # type: ignore[attr-defined]
    ax.set_title("AoP key, deg\n(counter-clockwise\nfrom image right)" + ("\nbrightness = DoLP" if dolp_weighted else ""),
                 fontsize=8)  # type: ignore[attr-defined]


def polar_figure_png(
    s0: ArrayLike,
    dolp: ArrayLike,
    aop_deg: ArrayLike,
    path: str | Path,
    *,
    title: str = "",
    max_side: int = 900,
    dpi: float = 110.0,
    atomic: bool = True,
) -> Path:
    """S0, DoLP and AoP side by side with titles, colour bars and an AoP hue wheel, as one PNG.

    The captioned companion of the bare previews (:func:`s0_to_gray`,
    :func:`dolp_to_rgb`, :func:`aop_to_rgb`): S0 in grey with its raw-unit
    colour bar (0.5-99.5 percentile stretch), DoLP on viridis 0..1 with a
    colour bar, AoP as DoLP-weighted cyclic hue with a wheel giving the angle
    (degrees counter-clockwise from image right, 0 and 180 the same colour;
    ``docs/conventions.md``). NaN (saturated) pixels are black. Images larger
    than ``max_side`` are shown decimated (every k-th pixel).

    Parameters
    ----------
    s0, dolp, aop_deg : array_like, shape (H, W)
    path : str or path-like
        Output PNG, written atomically unless ``atomic`` is false.
    title : str
        Figure title (e.g. the frame name).
    max_side : int
        Largest image side drawn, pixels.
    dpi : float
        Resolution of the PNG.
    atomic : bool
        ``False`` writes ``path`` directly, for a caller that already writes
        under a temporary name (``pihim polar``'s per-frame group).

    Returns
    -------
    Path
    """
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    a_s0, a_d, a_a = (np.asarray(v) for v in (s0, dolp, aop_deg))
    if not (a_s0.ndim == 2 and a_s0.shape == a_d.shape == a_a.shape):
        raise PihimInputError(f"S0, DoLP and AoP must be 2-D images of one shape, got {a_s0.shape}, "
                              f"{a_d.shape}, {a_a.shape}")
    k = max(1, int(np.ceil(max(a_s0.shape) / max_side)))
    # decimate before converting: a full-size float64 copy of a large frame is not needed for the figure
    a_s0, a_d, a_a = (v[::k, ::k].astype(np.float64) for v in (a_s0, a_d, a_a))
    finite = a_s0[np.isfinite(a_s0)]
    lo, hi = (np.percentile(finite, (0.5, 99.5)) if finite.size else (0.0, 1.0))
    hi = hi if hi > lo else lo + 1.0
    fig = Figure(figsize=(16.0, 4.4), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(1, 4, width_ratios=(1.0, 1.0, 1.0, 0.4))
    ax0, ax1, ax2 = (fig.add_subplot(grid[0, j]) for j in range(3))
    im0 = ax0.imshow(np.where(np.isfinite(a_s0), a_s0, np.nan), cmap=colormaps["gray"].with_extremes(bad="black"),
                     vmin=lo, vmax=hi, interpolation="nearest")
    cb0 = fig.colorbar(im0, ax=ax0, fraction=0.046, pad=0.02)
    cb0.set_label("S0 (raw units)", fontsize=8)
    cb0.ax.tick_params(labelsize=7)
    ax0.set_title("S0: total intensity", fontsize=10)
    im1 = ax1.imshow(a_d, cmap=colormaps["viridis"].with_extremes(bad="black"), vmin=0.0, vmax=1.0,
                     interpolation="nearest")
    cb1 = fig.colorbar(im1, ax=ax1, fraction=0.046, pad=0.02)
    cb1.set_label("DoLP", fontsize=8)
    cb1.ax.tick_params(labelsize=7)
    ax1.set_title("DoLP: degree of linear polarization", fontsize=10)
    ax2.imshow(aop_to_rgb(a_a, a_d), interpolation="nearest")
    ax2.set_title("AoP: angle of polarization", fontsize=10)
    # the hue wheel beside it is the key: a linear colour bar would hide that 0 and 180 deg meet
    for ax in (ax0, ax1, ax2):
        ax.set_xlabel("x (px)" + (f", every {k}th" if k > 1 else ""), fontsize=8)
        ax.tick_params(labelsize=7)
    _aop_wheel(fig.add_subplot(grid[0, 3]), dolp_weighted=True)
    if title:
        fig.suptitle(title, fontsize=11)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    with atomic_path(path) if atomic else contextlib.nullcontext(Path(path)) as tmp:
        Path(tmp).write_bytes(buf.getvalue())
    return Path(path)
