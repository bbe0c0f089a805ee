"""Sub-pixel edge points of polarimetric images, for model fitting.

The estimators (:mod:`pihim.inspection.pose`, :mod:`pihim.inspection.canting`)
fit projected model outlines to edge *points*, not to edge maps: every edge
pixel of a Canny map is moved along its gradient direction to the maximum of
a parabola through the gradient magnitudes at -1, 0, +1 pixel, which
localises a blurred step to a few hundredths of a pixel.

The gradient is the quadrature sum of three normalised gradients, so that an
edge seen in any of S0, DoLP or AoP counts:

* S0 divided by its median (linear: the gradient of ``log S0`` would move a
  blurred step's peak toward its dark side by about half a pixel),
* DoLP,
* the axial AoP: the gradient of ``(cos 2a, sin 2a)`` times DoLP, half the
  length of the change of the unit axial vector (no false edge at the
  0/180 deg wrap; weak where the light is barely polarized).

References
----------
.. [1] J. Canny, "A computational approach to edge detection", IEEE PAMI 8(6),
   679-698 (1986), doi:10.1109/TPAMI.1986.4767851.
.. [2] F. Devernay, "A non-maxima suppression method for edge detection with
   sub-pixel accuracy", INRIA RR-2724 (1995) (parabolic sub-pixel peak).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pihim.errors import PihimInputError

__all__ = ["EdgePoints", "combined_gradient", "edge_points"]


@dataclass(frozen=True, eq=False)
class EdgePoints:
    """Sub-pixel edge points.

    Attributes
    ----------
    xy : ndarray, shape (N, 2)
        Positions ``(u, v)`` in pixels (OpenCV convention: pixel centres at
        integers).
    normal : ndarray, shape (N, 2)
        Unit gradient directions.
    strength : ndarray, shape (N,)
        Gradient magnitude at the point.
    """

    xy: NDArray[np.float64]
    normal: NDArray[np.float64]
    strength: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    def select(self, mask: NDArray[np.bool_]) -> EdgePoints:
        return EdgePoints(self.xy[mask], self.normal[mask], self.strength[mask])


def _sobel(img: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    import cv2

    gx = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3, scale=0.125, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3, scale=0.125, borderType=cv2.BORDER_REPLICATE)
    return gx, gy


def combined_gradient(
    s0: NDArray, dolp: NDArray | None, aop_deg: NDArray | None, *, smooth_px: float = 1.0
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Gradient ``(gx, gy, magnitude)`` combining log S0, DoLP and axial AoP (see the module notes).

    NaN pixels (saturated) are filled with their neighbourhood's values
    first; ``smooth_px`` is a Gaussian pre-smoothing (pixels, 0 for none).
    ``dolp`` and ``aop_deg`` None: the gradient of S0 alone (the same as
    all-zero DoLP and AoP images, without their cost).
    """
    import cv2

    s0 = np.asarray(s0, float)
    if s0.ndim != 2 or (dolp is None) != (aop_deg is None) or (
            dolp is not None and (np.shape(dolp) != s0.shape or np.shape(aop_deg) != s0.shape)):
        raise PihimInputError("S0, DoLP and AoP must be 2-D images of one shape (or DoLP and AoP both None)")
    scale = float(np.nanmedian(s0))
    if not scale > 0:
        scale = float(np.nanmax(s0)) if np.nanmax(s0) > 0 else 1.0
    with np.errstate(invalid="ignore"):
        ls0 = s0 / scale
        chans = [ls0]
        if dolp is not None:
            p = np.clip(np.asarray(dolp, float), 0.0, 1.0)
            a = np.radians(np.asarray(aop_deg, float))
            chans += [p, p * np.cos(2 * a), p * np.sin(2 * a)]
    weights = [1.0, 4.0, 2.0, 2.0]
    if len(chans) == 1:  # S0 alone: its own gradient (no orientation or weighting to combine)
        c = _filled(ls0)
        if smooth_px > 0:
            c = cv2.GaussianBlur(c, (0, 0), smooth_px)
        gx, gy = _sobel(c)
        return gx, gy, np.sqrt(gx * gx + gy * gy)
    gx_t = np.zeros_like(s0)
    gy_t = np.zeros_like(s0)
    mag2 = np.zeros_like(s0)
    for c, w in zip(chans, weights[:len(chans)]):
        c = _filled(c)
        if smooth_px > 0:
            c = cv2.GaussianBlur(c, (0, 0), smooth_px)
        gx, gy = _sobel(c)
        # orient the channel's gradient along the summed one so that signs do not cancel
        sign = np.where(gx * gx_t + gy * gy_t < 0, -1.0, 1.0)
        gx_t += w * sign * gx
        gy_t += w * sign * gy
        mag2 += (w * w) * (gx * gx + gy * gy)
    return gx_t, gy_t, np.sqrt(mag2)


def _filled(c: NDArray) -> NDArray:
    """``c`` with its non-finite pixels replaced by the median of the finite ones."""
    finite = np.isfinite(c)
    if not finite.all():
        c = np.where(finite, c, np.nanmedian(c))
    return c


def _median_and_percentile(a: NDArray, q: float) -> tuple[float, float]:
    """``(np.median(a), np.percentile(a, q))``, ``q > 50``, from one selection and one on its upper half.

    The same order statistics and interpolation formulas as numpy's (the median: the mean
    of the two middle values for an even count; the percentile: linear between the order
    statistics around ``(n - 1) q / 100``), bit for bit.
    """
    v = np.ravel(a)
    n = v.size
    pos = (n - 1) * np.true_divide(q, 100)
    k = int(np.floor(pos))
    lo, hi = (n - 1) // 2, n // 2
    if n < 4 or k < hi or np.isnan(v).any():
        return float(np.median(v)), float(np.percentile(v, q))
    part = np.partition(v, hi)
    med = part[hi] if lo == hi else np.mean(np.array([np.max(part[:hi]), part[hi]]))
    # order statistics k and k + 1 lie in the upper part (every value there is >= part[hi])
    upper = np.partition(part[hi:], [k - hi, k + 1 - hi] if k + 1 < n else [k - hi])
    a_k = upper[k - hi]
    b_k = upper[k + 1 - hi] if k + 1 < n else a_k
    gamma = pos - k
    diff = b_k - a_k
    pct = b_k - diff * (1 - gamma) if gamma >= 0.5 else a_k + diff * gamma
    return float(med), float(pct)


def edge_points(
    s0: NDArray,
    dolp: NDArray | None = None,
    aop_deg: NDArray | None = None,
    *,
    smooth_px: float = 1.0,
    threshold: float | None = None,
    mask: NDArray[np.bool_] | None = None,
) -> EdgePoints:
    """Sub-pixel edge points of a polarimetric image (non-maximum suppression along the gradient).

    Parameters
    ----------
    s0, dolp, aop_deg : ndarray, shape (H, W)
        DoLP and AoP None (the default): edges of S0 alone.
    smooth_px : float
        Gaussian pre-smoothing, pixels.
    threshold : float, optional
        Minimum gradient magnitude; default five times the median absolute
        gradient (a noise estimate) or the 90th percentile, whichever is
        larger.
    mask : ndarray of bool, optional
        Only pixels where ``mask`` is True.

    Returns
    -------
    EdgePoints
    """
    from pihim.inspection import _kernels

    gx, gy, mag = combined_gradient(s0, dolp, aop_deg, smooth_px=smooth_px)
    if threshold is None:
        sel = mag if mask is None else mag[mask]
        if sel.size == 0:
            raise PihimInputError("no pixels to look for edges in")
        med, p90 = _median_and_percentile(sel, 90)
        threshold = max(5.0 * med, p90)
    use_mask = mask is not None
    m = np.asarray(mask, bool) if use_mask else np.zeros((1, 1), bool)
    if use_mask and m.shape != mag.shape:
        raise PihimInputError(f"the mask must have the image's shape {mag.shape}, got {m.shape}")
    xy, nrm, strength = _kernels.edge_nms(gx, gy, mag, float(threshold), m, use_mask)
    return EdgePoints(xy, nrm, strength)
