"""Edge contrast between two regions of interest (paper sections 4.2 and 4.3).

The paper measures contrast on two **200 x 100 pixel** regions on either side
of an edge (e.g. mirror-reflected ground and the real ground beside it):
each region's mean and standard deviation, then

* for S0 and DoLP images, the **Michelson contrast** of the two region means,
  ``|a - b| / (a + b)`` (:func:`michelson_contrast`);
* the **contrast ratio** of the DoLP image over the S0 image at the same
  edge (:func:`contrast_ratio`); the paper's "average contrast ratio 5.93"
  is the mean of this ratio over five sky-vs-sky DoLP images;
* for AoP images (axial angles), Michelson contrast means nothing; the
  regions' axial (circular, doubled-angle) means are compared by their
  axial difference in [0, 90] deg (:func:`pihim.polarimetry.aop_difference_deg`)
  and the raw difference of the paper's Table 1 is reported beside it.

Region geometry (:func:`roi_pair_contrast`): the edge passes through
``edge_point`` ``(u, v)`` (column, row; pixel centres are integers) with the
unit normal ``n``; the tangent is ``t = (-n_v, n_u)``. Region **a** is on
the ``-n`` side, region **b** on the ``+n`` side; each is ``size[0]`` pixels
along the edge by ``size[1]`` pixels across it, starting ``gap_px`` from the
edge line. Each region is sampled on a 1-pixel grid (``size[0] * size[1]``
points, nearest pixel), so an axis-aligned edge takes exactly 200 x 100
pixels per side; points outside the image or on NaN pixels are dropped
(``n_a``, ``n_b`` count the pixels used).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError
from pihim.polarimetry.stokes import aop_difference_deg, aop_raw_difference_deg

__all__ = ["PAPER_ROI_SIZE", "RoiPairContrast", "contrast_ratio", "michelson_contrast", "roi_pair_contrast"]

#: The paper's regions: 200 px along the edge, 100 px across it.
PAPER_ROI_SIZE: tuple[int, int] = (200, 100)


def _mean(x: ArrayLike) -> float:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        return float(a)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else math.nan


def michelson_contrast(a: ArrayLike, b: ArrayLike) -> float:
    """Michelson contrast ``|a - b| / (a + b)`` of two regions' means.

    Parameters
    ----------
    a, b : float or array_like
        Region means, or the regions' pixel values (their finite mean is taken).
        Meant for non-negative quantities (S0, DoLP).

    Returns
    -------
    float
        In [0, 1] for non-negative means; NaN if ``a + b == 0`` or a region
        is empty. A mean a little below zero (S0 of a dark region after the
        dark level is subtracted, noise) gives a value a little above 1.
    """
    ma, mb = _mean(a), _mean(b)
    total = ma + mb
    if not math.isfinite(total) or total == 0.0:
        return math.nan
    return abs(ma - mb) / total


@dataclass(frozen=True)
class RoiPairContrast:
    """Statistics of two regions either side of an edge (see the module notes).

    For a linear image (``axial=False``): ``mean_*``/``std_*`` are the
    arithmetic mean and standard deviation, ``contrast`` the Michelson
    contrast of the means, ``difference = mean_b - mean_a``. For an AoP image
    (``axial=True``): means are axial circular means in [0, 180) deg, the
    standard deviations circular ones of the axial data (deg),
    ``difference`` the axial difference in [0, 90] deg, ``raw_difference``
    ``|mean_a - mean_b|`` (the paper's Table 1), and ``contrast`` NaN.
    """

    mean_a: float
    std_a: float
    n_a: int
    mean_b: float
    std_b: float
    n_b: int
    contrast: float
    difference: float
    raw_difference: float
    axial: bool
    corners_a: tuple[tuple[float, float], ...]
    corners_b: tuple[tuple[float, float], ...]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record (NaN as None)."""

        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        return {
            "a": {"mean": num(self.mean_a), "std": num(self.std_a), "pixels": self.n_a,
                  "corners_px": [list(c) for c in self.corners_a]},
            "b": {"mean": num(self.mean_b), "std": num(self.std_b), "pixels": self.n_b,
                  "corners_px": [list(c) for c in self.corners_b]},
            "contrast": num(self.contrast),
            "difference": num(self.difference),
            "raw_difference": num(self.raw_difference),
            "axial": self.axial,
        }


def _direction(normal_dir: Any) -> NDArray[np.float64]:
    if isinstance(normal_dir, (int, float)) and not isinstance(normal_dir, bool):
        a = math.radians(float(normal_dir))
        n = np.array([math.cos(a), -math.sin(a)])  # counter-clockwise from image right, as displayed
    else:
        n = np.asarray(normal_dir, dtype=float).reshape(-1)
        if n.shape != (2,):
            raise PihimInputError(f"normal_dir must be (du, dv) or an angle in deg, got {normal_dir!r}")
    norm = float(np.hypot(*n)) if np.all(np.isfinite(n)) else 0.0
    if norm == 0.0:
        raise PihimInputError(f"normal_dir must be a finite non-zero direction, got {normal_dir!r}")
    return n / norm


def _axial_stats(deg: NDArray[np.float64]) -> tuple[float, float]:
    """Axial circular mean (deg, [0, 180)) and circular standard deviation (deg) of orientations."""
    if deg.size == 0:
        return math.nan, math.nan
    two = np.radians(2.0 * deg)
    c, s = float(np.cos(two).mean()), float(np.sin(two).mean())
    r = min(1.0, math.hypot(c, s))
    mean = math.degrees(0.5 * math.atan2(s, c)) % 180.0
    std = math.degrees(0.5 * math.sqrt(-2.0 * math.log(r))) if r > 0 else math.inf
    return mean, std


def roi_pair_contrast(
    image: ArrayLike,
    edge_point: ArrayLike,
    normal_dir: Any,
    size: tuple[int, int] = PAPER_ROI_SIZE,
    *,
    gap_px: float = 0.0,
    axial: bool = False,
) -> RoiPairContrast:
    """Means, standard deviations and contrast of two regions either side of an edge.

    Parameters
    ----------
    image : array_like, shape (H, W)
        S0, DoLP (``axial=False``) or AoP in degrees (``axial=True``).
    edge_point : array_like, (u, v)
        A point of the edge, pixels (column, row).
    normal_dir : (du, dv) or float
        Edge normal in pixel coordinates, or its angle in degrees
        counter-clockwise from image right as displayed (``(cos a, -sin a)``).
        Region b lies on its side.
    size : (int, int)
        Region size along the edge and across it, pixels; the paper's 200 x 100.
    gap_px : float
        Distance from the edge line to each region, pixels (to keep mixed
        edge pixels out).
    axial : bool
        Treat the image as AoP (axial statistics, see :class:`RoiPairContrast`).

    Returns
    -------
    RoiPairContrast
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise PihimInputError(f"image must be 2-D, got shape {img.shape}")
    p = np.asarray(edge_point, dtype=float).reshape(-1)
    if p.shape != (2,) or not np.all(np.isfinite(p)):
        raise PihimInputError(f"edge_point must be a finite (u, v), got {edge_point!r}")
    try:
        along, across = (int(v) for v in size)
    except (TypeError, ValueError):
        raise PihimInputError(f"size must be two integers (along, across), got {size!r}") from None
    if along < 1 or across < 1:
        raise PihimInputError(f"size must be positive, got {size!r}")
    if not math.isfinite(gap_px) or gap_px < 0:
        raise PihimInputError(f"gap_px must be >= 0, got {gap_px!r}")
    n = _direction(normal_dir)
    t = np.array([-n[1], n[0]])
    ta = (np.arange(along) - (along - 1) / 2.0)[:, None]
    sa = (gap_px + 0.5 + np.arange(across))[None, :]
    h, w = img.shape
    stats = []
    corners = []
    for sign in (-1.0, 1.0):
        pts = p + ta[..., None] * t + sign * sa[..., None] * n  # (along, across, 2)
        uu = np.rint(pts[..., 0]).astype(np.int64).ravel()
        vv = np.rint(pts[..., 1]).astype(np.int64).ravel()
        ok = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
        vals = img[vv[ok], uu[ok]]
        vals = vals[np.isfinite(vals)]
        if axial:
            mean, std = _axial_stats(vals)
        elif vals.size:
            mean, std = float(vals.mean()), float(vals.std())
        else:
            mean, std = math.nan, math.nan
        stats.append((mean, std, int(vals.size)))
        half = along / 2.0
        near, far = sign * gap_px, sign * (gap_px + across)
        corners.append(tuple(tuple(float(x) for x in p + a * t + d * n)
                             for a, d in ((-half, near), (half, near), (half, far), (-half, far))))
    (ma, sa_, na), (mb, sb, nb) = stats
    if axial:
        contrast = math.nan
        diff = float(aop_difference_deg(ma, mb))
        raw = float(aop_raw_difference_deg(ma, mb))
    else:
        contrast = michelson_contrast(ma, mb)
        diff = mb - ma
        raw = abs(diff)
    return RoiPairContrast(ma, sa_, na, mb, sb, nb, contrast, diff, raw, bool(axial), corners[0], corners[1])


def contrast_ratio(dolp_contrast: float | RoiPairContrast, s0_contrast: float | RoiPairContrast) -> float:
    """DoLP-image contrast over S0-image contrast at the same edge (the paper's 5.93 is its mean over five images).

    Parameters
    ----------
    dolp_contrast, s0_contrast : float or RoiPairContrast
        Michelson contrasts (or the :func:`roi_pair_contrast` results) of the
        DoLP and S0 images on the same regions.

    Returns
    -------
    float
        ``inf`` if only the S0 contrast is zero, NaN if both are (or either is NaN).
    """
    num = dolp_contrast.contrast if isinstance(dolp_contrast, RoiPairContrast) else float(dolp_contrast)
    den = s0_contrast.contrast if isinstance(s0_contrast, RoiPairContrast) else float(s0_contrast)
    if not (math.isfinite(num) and math.isfinite(den)) or num < 0 or den < 0:
        return math.nan
    if den == 0.0:
        return math.inf if num > 0 else math.nan
    return num / den
