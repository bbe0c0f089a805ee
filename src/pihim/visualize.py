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
import functools
import threading
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim._atomic import atomic_path
from pihim.errors import PihimInputError


def _ordinal(n: int) -> str:
    """``2nd``, ``3rd``, ``4th``, ``11th``, ``21st`` ..."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def _hsv_to_rgb(h: NDArray, v: NDArray) -> NDArray[np.float64]:
    """Vectorised HSV -> RGB at full saturation, ``h`` and ``v`` in [0, 1].

    With ``h6 = mod(h, 1) * 6``: ``R = v clip(|h6 - 3| - 1, 0, 1)``, ``G = v
    clip(2 - |h6 - 2|, 0, 1)``, ``B = v clip(2 - |h6 - 4|, 0, 1)`` -- the
    sextant formulas of the HSV model (A. R. Smith, "Color gamut transform
    pairs", SIGGRAPH 1978) written without branches, as the compiled kernel
    :func:`pihim._colour_kernels.hue_colour` evaluates them.
    """
    h6 = np.mod(h, 1.0) * 6.0
    r = np.clip(np.abs(h6 - 3.0) - 1.0, 0.0, 1.0)
    g = np.clip(2.0 - np.abs(h6 - 2.0), 0.0, 1.0)
    b = np.clip(2.0 - np.abs(h6 - 4.0), 0.0, 1.0)
    return np.stack([v * r, v * g, v * b], axis=-1)


def _to_u8(x: NDArray) -> NDArray[np.uint8]:
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)


def _output(out: NDArray[np.uint8] | None, shape: tuple[int, ...]) -> NDArray[np.uint8]:
    """``out`` checked to be a writable C-contiguous uint8 array of ``shape``, else a new one."""
    if out is None:
        return np.empty(shape, dtype=np.uint8)
    if out.shape != shape or out.dtype != np.uint8 or not out.flags.c_contiguous or not out.flags.writeable:
        raise PihimInputError(f"out must be a writable C-contiguous uint8 array of shape {shape}, got "
                              f"{out.dtype} {out.shape}")
    return out


def _into(out: NDArray[np.uint8] | None, image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """``image``, copied into ``out`` when given."""
    if out is None:
        return image
    _output(out, image.shape)[...] = image
    return out


def aop_to_rgb(
    aop_deg: ArrayLike,
    dolp: ArrayLike | None = None,
    *,
    dolp_max: float = 1.0,
    out: NDArray[np.uint8] | None = None,
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
    out : numpy.ndarray, optional
        C-contiguous uint8 array of shape ``aop_deg.shape + (3,)`` to write
        the image into (and return), e.g. one recycled from an earlier frame.

    Notes
    -----
    In float64: hue ``h = mod(aop / 180, 1)``, value ``v`` as above,
    saturation 1, converted by the HSV sextant formulas (branch-free form,
    ``_hsv_to_rgb``) and rounded
    (``rint(255 x)``); black where AoP (or DoLP) is not finite. 2-D images
    are computed by one compiled pass (:mod:`pihim._colour_kernels`), other
    shapes with numpy; both give the same pixels.
    """
    a = np.asarray(aop_deg)
    d = None if dolp is None else np.asarray(dolp)
    if d is not None and d.shape != a.shape:
        raise PihimInputError(f"AoP and DoLP shapes differ: {a.shape} vs {d.shape}")
    if a.ndim == 2 and a.dtype in (np.float32, np.float64) and (d is None or d.dtype in (np.float32, np.float64)):
        from pihim._colour_kernels import hue_colour

        rgb = _output(out, (*a.shape, 3))
        hue_colour(np.ascontiguousarray(a), np.ascontiguousarray(a if d is None else d), d is not None,
                   float(dolp_max), rgb)
        return rgb
    a = a.astype(np.float64)
    valid = np.isfinite(a)
    v = np.ones_like(a)
    if d is not None:
        d = d.astype(np.float64)
        valid &= np.isfinite(d)
        with np.errstate(over="ignore"):  # an infinite DoLP (nan_to_num: 1.8e308) saturates, as compiled
            v = np.clip(np.nan_to_num(d) / dolp_max, 0.0, 1.0)
    rgb = _hsv_to_rgb(np.nan_to_num(a) / 180.0, v)
    rgb[~valid] = 0.0
    return _into(out, _to_u8(rgb))


@functools.lru_cache(maxsize=8)
def colour_lut(cmap: str = "viridis") -> NDArray[np.uint8]:
    """The 256-entry uint8 RGB table of a matplotlib colour map (``rint(255 x)`` of its float colours)."""
    from matplotlib import colormaps

    lut = _to_u8(colormaps[cmap].resampled(256)(np.linspace(0.0, 1.0, 256))[:, :3])
    lut.flags.writeable = False
    return lut


def dolp_to_rgb(
    dolp: ArrayLike, *, vmax: float = 1.0, cmap: str = "viridis", out: NDArray[np.uint8] | None = None
) -> NDArray[np.uint8]:
    """DoLP through a perceptual matplotlib colour map over ``[0, vmax]``.

    Entry ``clip(rint(255 dolp / vmax), 0, 255)`` of :func:`colour_lut`;
    black where DoLP is not finite. ``out`` (optional): a C-contiguous uint8
    array of shape ``dolp.shape + (3,)`` to write into and return.
    """
    d = np.asarray(dolp)
    lut = colour_lut(cmap)
    if d.ndim == 2 and d.dtype in (np.float32, np.float64):
        from pihim._colour_kernels import lut_colour

        rgb = _output(out, (*d.shape, 3))
        lut_colour(np.ascontiguousarray(d), float(vmax), lut, rgb)
        return rgb
    d = d.astype(np.float64)
    with np.errstate(over="ignore"):  # an infinite DoLP saturates, as compiled
        idx = np.clip(np.rint(np.nan_to_num(d) / vmax * 255.0), 0, 255).astype(np.intp)
    rgb = lut[idx].copy()
    rgb[~np.isfinite(d)] = 0
    return _into(out, rgb)


def s0_range(s0: ArrayLike, percentiles: tuple[float, float] = (0.5, 99.5)) -> tuple[float, float] | None:
    """The ``numpy.percentile`` values of the finite S0 pixels that :func:`s0_to_gray` stretches between.

    For 2-D float32 images they are computed exactly by histogram selection
    (:func:`pihim._quantiles.percentiles`, no float64 copy). ``None`` when no
    pixel is finite.
    """
    x = np.asarray(s0)
    if x.ndim == 2 and x.dtype == np.float32:
        from pihim._quantiles import percentiles as exact_percentiles

        bounds = exact_percentiles(np.ascontiguousarray(x), percentiles)
        return None if bounds is None else (float(bounds[0]), float(bounds[1]))
    x = x.astype(np.float64)
    finite = x[np.isfinite(x)]
    if finite.size == 0:
        return None
    lo, hi = np.percentile(finite, percentiles)
    return float(lo), float(hi)


def s0_to_gray(
    s0: ArrayLike,
    *,
    percentiles: tuple[float, float] = (0.5, 99.5),
    value_range: tuple[float, float] | None = None,
    out: NDArray[np.uint8] | None = None,
) -> NDArray[np.uint8]:
    """S0 as 8-bit grey with a percentile stretch (NaN -> 0).

    ``lo, hi =`` :func:`s0_range` ``(s0, percentiles)`` (or ``value_range``
    when given), then ``rint(255 clip((s0 - lo) / (hi - lo), 0, 1))``; all 0
    unless ``hi > lo``. 2-D float images take one compiled pass. ``out``
    (optional): a C-contiguous uint8 array of ``s0``'s shape to write into
    and return.
    """
    x = np.asarray(s0)
    bounds = value_range if value_range is not None else s0_range(x, percentiles)
    if bounds is None:
        return _into(out, np.zeros(x.shape, dtype=np.uint8))
    lo, hi = float(bounds[0]), float(bounds[1])
    if x.ndim == 2 and x.dtype in (np.float32, np.float64):
        from pihim._colour_kernels import gray_stretch

        gray = _output(out, x.shape)
        gray_stretch(np.ascontiguousarray(x), lo, hi, gray)
        return gray
    x = x.astype(np.float64)
    scale = (x - lo) / (hi - lo) if hi > lo else np.zeros_like(x)
    return _into(out, _to_u8(np.clip(np.nan_to_num(scale), 0.0, 1.0)))


def write_png(path: str | Path, image: NDArray[np.uint8], *, atomic: bool = True, level: int | None = None) -> Path:
    """Write an RGB ``(H, W, 3)`` or grey ``(H, W)`` uint8 image as PNG, atomically.

    Encoded by :func:`pihim._png.encode_png` (unfiltered rows, fast deflate;
    Intel ISA-L where the ``isal`` package is installed; ``level`` 0-9, 0 stores the
    rows uncompressed). ``atomic=False`` writes ``path`` directly (for a
    caller that already writes under a temporary name).
    """
    from pihim._direct_io import write_bytes, write_file
    from pihim._png import encode_png, stored_png

    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3) or img.size == 0:
        raise PihimInputError("PNG previews must be non-empty uint8 grey or RGB images")
    stored = stored_png(img) if level == 0 else None  # laid out straight into the write buffer
    with atomic_path(path) if atomic else contextlib.nullcontext(Path(path)) as tmp:
        if stored is not None:
            write_file(tmp, *stored)
        else:
            write_bytes(tmp, encode_png(img, level=level))  # past the page cache where allowed (pihim._direct_io)
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
    rgb = _hsv_to_rgb(ang / 180.0, v)
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


class _BarTicks:
    """Ticks and tick labels of a vertical colour bar, redrawn quickly for each new value range.

    The bar's own ``YAxis`` redraw (locator, formatter, tick update and a
    layout pass over the tick labels) took about 25 ms of a frame; this draws
    the same ticks -- the axis's own locator, matplotlib's
    :class:`~matplotlib.ticker.ScalarFormatter` for the labels, both placed
    where the laid-out axis put its ticks -- as one marker line and a few
    text artists. The axis itself then draws only its label, pinned where
    the layout put it (for five-digit tick labels).

    Parameters
    ----------
    colorbar : matplotlib.colorbar.Colorbar
        A vertical colour bar of a figure drawn once (laid out).
    """

    def __init__(self, colorbar: object) -> None:
        from matplotlib.lines import Line2D
        from matplotlib.text import Text
        from matplotlib.ticker import NullLocator
        from matplotlib.transforms import IdentityTransform

        cax = colorbar.ax  # type: ignore[attr-defined]
        axis = cax.yaxis
        figure = cax.get_figure(root=True)
        tick = axis.get_major_ticks()[0]
        label = tick.label2 if tick.label2.get_visible() else tick.label1
        mark = tick.tick2line if tick.tick2line.get_visible() else tick.tick1line
        self._locator = axis.get_major_locator()  # bound to the axis: its tick spacing follows the bar's length
        box = cax.bbox
        self._y0, self._height = float(box.y0), float(box.height)
        pixels = IdentityTransform()
        self._label_x = float(label.get_transform().transform(label.get_position())[0])
        self._marks = Line2D([], [])
        self._marks.update_from(mark)
        self._marks.set(transform=pixels, clip_on=False, figure=figure, animated=True)
        self._mark_x = float(mark.get_transform().transform((mark.get_xdata()[0], 0.0))[0])
        self._label_style = label
        self._labels: list[Text] = []
        self._stamps: dict[str, tuple[NDArray[np.uint8], int, int]] = {}
        offset = axis.offsetText
        self._offset = Text()
        self._offset.update_from(offset)
        self._offset.set(transform=pixels, figure=figure, animated=True,
                         position=offset.get_transform().transform(offset.get_position()))
        self._figure = figure
        # the axis keeps only its label, where the layout put it
        axis.set_label_coords(*axis.label.get_transform().transform(axis.label.get_position()), transform=pixels)
        axis.set_major_locator(NullLocator())

    def _label(self, k: int) -> object:
        from matplotlib.text import Text
        from matplotlib.transforms import IdentityTransform

        while len(self._labels) <= k:
            text = Text()
            text.update_from(self._label_style)
            text.set(transform=IdentityTransform(), figure=self._figure, animated=True)
            self._labels.append(text)
        return self._labels[k]

    def draw(self, lo: float, hi: float, pixels: NDArray[np.uint8]) -> list[tuple[float, str]]:
        """Draw the ticks of the range ``lo < hi`` over a background without them; return ``(value, label)``s.

        ``pixels`` is the canvas's RGBA buffer (rows top down). A label
        drawn once is kept as the pixels it drew (over the plain figure
        background right of the bar) and stamped at its next position,
        whole pixels as matplotlib's Agg places text: tick values repeat
        from frame to frame, and a text draw costs about 1 ms.
        """
        from matplotlib.ticker import ScalarFormatter

        span = hi - lo
        locs = np.asarray(self._locator.tick_values(lo, hi), dtype=float)
        locs = locs[(locs >= lo - 1e-10 * span) & (locs <= hi + 1e-10 * span)]  # as matplotlib keeps them
        formatter = ScalarFormatter()
        formatter.create_dummy_axis()
        formatter.axis.set_view_interval(lo, hi)  # type: ignore[union-attr]
        texts = formatter.format_ticks(locs)
        ys = self._y0 + (locs - lo) / span * self._height
        self._marks.set_data(np.full(len(ys), self._mark_x), ys)
        self._figure.draw_artist(self._marks)
        height = pixels.shape[0]
        for k, (y, text) in enumerate(zip(ys, texts, strict=True)):
            # labels sit on whole pixels (within half a pixel of their tick): Agg then draws a string the same at
            # any height, shifted by whole rows, so a kept label stamps exactly where a drawn one would be
            y = float(round(y))
            anchor = int(height - y)
            stamp = self._stamps.get(text)
            if stamp is not None and 0 <= anchor + stamp[1] <= height - stamp[0].shape[0]:
                patch, dr, c0 = stamp
                r0 = anchor + dr
                pixels[r0:r0 + patch.shape[0], c0:c0 + patch.shape[1]] = patch
                continue
            artist = self._label(k)
            artist.set(position=(self._label_x, y), text=text)  # type: ignore[attr-defined]
            self._figure.draw_artist(artist)
            box = artist.get_window_extent()  # type: ignore[attr-defined]
            r0, r1 = height - int(np.ceil(box.y1)) - 1, height - int(np.floor(box.y0)) + 1
            c0, c1 = int(np.floor(box.x0)) - 1, int(np.ceil(box.x1)) + 1
            if 0 <= r0 and r1 <= height and 0 <= c0 and c1 <= pixels.shape[1]:  # kept only whole
                if len(self._stamps) >= 512:
                    self._stamps.clear()
                self._stamps[text] = (pixels[r0:r1, c0:c1].copy(), r0 - anchor, c0)
        self._offset.set_text(formatter.get_offset())
        self._figure.draw_artist(self._offset)
        return [(float(v), t) for v, t in zip(locs, texts, strict=True)]


class PolarFigure:
    """The captioned S0 / DoLP / AoP figure of :func:`polar_figure_png`, drawn once and reused.

    matplotlib draws the figure once per image size (axes, colour bars,
    labels, the AoP wheel; about 0.2-0.6 s); each frame then only pastes
    its three decimated images into the axes (nearest-neighbour, as the
    figure's ``interpolation="nearest"``) and redraws the parts that change,
    the S0 colour bar's ticks (its raw-unit range follows the frame,
    :class:`_BarTicks`) and the title, with matplotlib's blitting. That
    takes about 10 ms instead of a full draw. Not thread-safe (matplotlib is not): use one
    instance per thread.

    Parameters
    ----------
    shape : (int, int)
        Shape of the S0, DoLP and AoP images the figure will show.
    titled : bool
        Leave room for a title (:meth:`render`'s ``title``).
    max_side, dpi : see :func:`polar_figure_png`
    """

    def __init__(self, shape: tuple[int, int], *, titled: bool = True, max_side: int = 900, dpi: float = 110.0) -> None:
        from matplotlib import colormaps
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        h, w = (int(v) for v in shape)
        if h < 1 or w < 1:
            raise PihimInputError(f"the figure needs non-empty images, got shape {shape}")
        self.shape = (h, w)
        self.step = max(1, int(np.ceil(max(h, w) / max_side)))
        small = (len(range(0, h, self.step)), len(range(0, w, self.step)))
        placeholder = np.zeros(small)
        fig = Figure(figsize=(16.0, 4.4), dpi=dpi, layout="constrained")
        self._canvas = FigureCanvasAgg(fig)
        grid = fig.add_gridspec(1, 4, width_ratios=(1.0, 1.0, 1.0, 0.4))
        self._axes = [fig.add_subplot(grid[0, j]) for j in range(3)]
        ax0, ax1, ax2 = self._axes
        # laid out for five-digit raw units (16-bit data), so that any frame's S0 colour bar labels fit
        self._im0 = ax0.imshow(placeholder, cmap=colormaps["gray"].with_extremes(bad="black"), vmin=0.0,
                               vmax=60000.0, interpolation="nearest")
        self._cb0 = fig.colorbar(self._im0, ax=ax0, fraction=0.046, pad=0.02)
        self._cb0.set_label("S0 (raw units)", fontsize=8)
        self._cb0.ax.tick_params(labelsize=7)
        ax0.set_title("S0: total intensity", fontsize=10)
        im1 = ax1.imshow(placeholder, cmap=colormaps["viridis"].with_extremes(bad="black"), vmin=0.0, vmax=1.0,
                         interpolation="nearest")
        cb1 = fig.colorbar(im1, ax=ax1, fraction=0.046, pad=0.02)
        cb1.set_label("DoLP", fontsize=8)
        cb1.ax.tick_params(labelsize=7)
        ax1.set_title("DoLP: degree of linear polarization", fontsize=10)
        ax2.imshow(np.zeros((*small, 3)), interpolation="nearest")
        ax2.set_title("AoP: angle of polarization", fontsize=10)
        # the hue wheel beside it is the key: a linear colour bar would hide that 0 and 180 deg meet
        for ax in self._axes:
            ax.set_xlabel("x (px)" + (f", every {_ordinal(self.step)} pixel" if self.step > 1 else ""), fontsize=8)
            ax.tick_params(labelsize=7)
        _aop_wheel(fig.add_subplot(grid[0, 3]), dolp_weighted=True)
        self._title = fig.suptitle("placeholder" if titled else "", fontsize=11)
        self._canvas.draw()  # lay out once, then freeze the layout
        fig.set_layout_engine("none")
        self._s0_ticks = _BarTicks(self._cb0)  # the S0 colour bar's axis now draws only its label
        # what changes from frame to frame is drawn over a background that lacks it; the axes frames (spines)
        # are the background's, put back over each pasted image's border
        self._title.set_animated(True)
        for im in (self._im0, im1, *ax2.get_images()):
            im.set_visible(False)
        self._canvas.draw()
        self._background = self._canvas.copy_from_bbox(fig.bbox)
        background = np.asarray(self._canvas.buffer_rgba())
        self._fig = fig
        # pixel boxes of the three images in the canvas buffer, and the data pixel of every box pixel
        height = int(self._canvas.get_width_height()[1])
        self._boxes = []
        for ax in self._axes:
            box = ax.get_window_extent()
            c0, c1 = int(round(box.x0)), int(round(box.x1))
            r0, r1 = height - int(round(box.y1)), height - int(round(box.y0))
            rows = np.clip(((np.arange(r0, r1) + 0.5 - r0) * small[0] / max(r1 - r0, 1)).astype(np.intp), 0,
                           small[0] - 1)
            cols = np.clip(((np.arange(c0, c1) + 0.5 - c0) * small[1] / max(c1 - c0, 1)).astype(np.intp), 0,
                           small[1] - 1)
            self._boxes.append((r0, r1, c0, c1, rows, cols))
        # the pixels of the axes frames (black spines, 0.8 pt: within a pixel of each box's rounded edge) inside
        # the boxes, to lay back over the pasted images: drawn over the white face, a pixel's level is 255 times
        # (1 - the spine's coverage of it), by which the image's pixel under it is scaled
        ring = np.zeros(background.shape[:2], dtype=bool)
        for r0, r1, c0, c1, _, _ in self._boxes:
            ring[r0:r1, c0:c1] = True
            ring[r0 + 2:r1 - 2, c0 + 2:c1 - 2] = False
        ring &= np.any(background[..., :3] != np.asarray(self._axes[0].get_facecolor()[:3]) * 255, axis=-1)
        self._frame_at = np.nonzero(ring)
        self._frame_cover = background[self._frame_at][:, :3].astype(np.uint16)

    def render(
        self,
        s0: ArrayLike,
        dolp: ArrayLike,
        aop_deg: ArrayLike,
        *,
        title: str = "",
        previews: tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.uint8], tuple[float, float]] | None = None,
    ) -> bytes:
        """PNG bytes of the figure for one frame's images (of the shape given at construction).

        Parameters
        ----------
        s0, dolp, aop_deg : array_like, shape (H, W)
        title : str
        previews : tuple, optional
            ``(grey, dolp_rgb, aop_rgb, (lo, hi))``: the full-size previews
            of these images (:func:`s0_to_gray` with the S0 range ``(lo,
            hi)``, :func:`dolp_to_rgb`, :func:`aop_to_rgb` with DoLP) when
            already made; the figure then shows them decimated (its S0 colour
            bar spans ``(lo, hi)``) instead of colouring the images again.
        """
        from pihim._png import encode_png

        a_s0, a_d, a_a = (np.asarray(v) for v in (s0, dolp, aop_deg))
        if not (a_s0.ndim == 2 and a_s0.shape == a_d.shape == a_a.shape):
            raise PihimInputError(f"S0, DoLP and AoP must be 2-D images of one shape, got {a_s0.shape}, "
                                  f"{a_d.shape}, {a_a.shape}")
        if a_s0.shape != self.shape:
            raise PihimInputError(f"this figure was laid out for {self.shape} images, got {a_s0.shape}")
        k = self.step
        if previews is not None:
            gray, dolp_rgb, aop_rgb, (lo, hi) = previews
            panels = (gray[..., None], dolp_rgb, aop_rgb)  # every k-th pixel of these is shown
        else:
            k = 1  # panels made from every k-th pixel
            a_s0, a_d, a_a = (np.ascontiguousarray(v[::self.step, ::self.step]) for v in (a_s0, a_d, a_a))
            s0f = a_s0.astype(np.float32, copy=False)
            bounds = s0_range(s0f)
            lo, hi = bounds if bounds is not None else (0.0, 1.0)
            panels = (_gray_levels(s0f, lo, hi if hi > lo else lo + 1.0)[..., None], dolp_to_rgb(a_d),
                      aop_to_rgb(a_a, a_d))
        hi = hi if hi > lo else lo + 1.0
        self._canvas.restore_region(self._background)
        buf = np.asarray(self._canvas.buffer_rgba())
        for (r0, r1, c0, c1, rows, cols), rgb in zip(self._boxes, panels, strict=True):
            buf[r0:r1, c0:c1, :3] = rgb.take(rows * k, axis=0).take(cols * k, axis=1)  # rows first: fewer
        under = buf[self._frame_at][:, :3].astype(np.uint16)
        buf[(*self._frame_at, slice(0, 3))] = (under * self._frame_cover + 127) // 255
        self._title.set_text(title)
        self._fig.draw_artist(self._title)
        self._s0_ticks.draw(lo, hi, buf)
        return encode_png(np.asarray(self._canvas.buffer_rgba())[..., :3])


def _gray_levels(x: NDArray[np.float32], lo: float, hi: float) -> NDArray[np.uint8]:
    """matplotlib's ``gray`` colour map on ``[lo, hi]`` as uint8 levels (NaN black, as the figure's ``bad``)."""
    t = (x.astype(np.float64) - lo) / (hi - lo)
    levels = np.clip(np.floor(np.nan_to_num(t, nan=-1.0) * 256.0), 0, 255)
    colours = _gray_lut()
    out = colours[levels.astype(np.intp)]
    out[~np.isfinite(x)] = 0
    return out


@functools.lru_cache(maxsize=1)
def _gray_lut() -> NDArray[np.uint8]:
    """The 256 grey levels of matplotlib's ``gray`` colour map, as it renders them (uint8)."""
    from matplotlib import colormaps

    return colormaps["gray"](np.arange(256), bytes=True)[:, 0].copy()


_FIGURES: dict[tuple[int, int, bool, int, float], PolarFigure] = {}
_FIGURES_LOCK = threading.Lock()


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
    previews: tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.uint8], tuple[float, float]] | None = None,
) -> Path:
    """S0, DoLP and AoP side by side with titles, colour bars and an AoP hue wheel, as one PNG.

    The captioned companion of the bare previews (:func:`s0_to_gray`,
    :func:`dolp_to_rgb`, :func:`aop_to_rgb`): S0 in grey with its raw-unit
    colour bar (0.5-99.5 percentile stretch), DoLP on viridis 0..1 with a
    colour bar, AoP as DoLP-weighted cyclic hue with a wheel giving the angle
    (degrees counter-clockwise from image right, 0 and 180 the same colour;
    ``docs/conventions.md``). NaN (saturated) pixels are black. Images larger
    than ``max_side`` are shown decimated (every k-th pixel).

    Figures of images of the same shape reuse one :class:`PolarFigure`
    (laid out once; a frame then costs a few milliseconds), kept per
    thread-safe cache entry.

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
    previews : tuple, optional
        The frame's full-size previews and S0 range, see :meth:`PolarFigure.render`.

    Returns
    -------
    Path
    """
    a_s0, a_d, a_a = (np.asarray(v) for v in (s0, dolp, aop_deg))
    if not (a_s0.ndim == 2 and a_s0.shape == a_d.shape == a_a.shape):
        raise PihimInputError(f"S0, DoLP and AoP must be 2-D images of one shape, got {a_s0.shape}, "
                              f"{a_d.shape}, {a_a.shape}")
    key = (int(a_s0.shape[0]), int(a_s0.shape[1]), bool(title), int(max_side), float(dpi))
    with _FIGURES_LOCK:  # one figure at a time: matplotlib is not thread-safe
        figure = _FIGURES.get(key)
        if figure is None:
            _FIGURES.clear()  # keep only the latest size
            figure = _FIGURES[key] = PolarFigure(a_s0.shape, titled=bool(title), max_side=max_side, dpi=dpi)
        data = figure.render(a_s0, a_d, a_a, title=title, previews=previews)
    from pihim._direct_io import write_bytes

    with atomic_path(path) if atomic else contextlib.nullcontext(Path(path)) as tmp:
        write_bytes(tmp, data)  # past the page cache where allowed (pihim._direct_io)
    return Path(path)
