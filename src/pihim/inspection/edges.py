"""Edge maps of S0, DoLP and AoP images (paper section 4.3).

Pure functions on numpy arrays; no file I/O and no ground truth.

Gradients
---------
:func:`gradient_magnitude` is the 3x3 Sobel operator scaled by 1/8, so that
it estimates the derivative **per pixel**: a ramp of slope ``s`` per pixel
gives ``s``; a step of height ``h`` gives ``h / 2`` on the two pixels beside
it. Borders replicate the outermost pixels.

AoP is an orientation (axial, period 180 deg): its raw values jump from 179
to 0 where nothing changes in the scene. :func:`axial_gradient_magnitude`
therefore never differentiates the angle itself but the unit vector
``(cos 2a, sin 2a)``, and reports

``(90 / pi) * sqrt(|grad cos 2a|^2 + |grad sin 2a|^2)``,

which is ``|grad a|`` in **deg per pixel** wherever the AoP varies smoothly
(and is blind to the 0/180 wrap); a step between two orientations that
differ axially by ``D`` deg gives ``(90 / pi) * sin(D)`` (28.6 for 90 deg).
With ``dolp`` the magnitude is multiplied by the DoLP averaged over the 3x3
Sobel support (clipped to [0, 1]): AoP noise grows like 1 / DoLP, so
unpolarized regions, where AoP means nothing, do not make edges.

NaN (saturated pixels have NaN DoLP and AoP, see :func:`pihim.camera.polar_image`)
are handled by filling each NaN pixel that a valid pixel's 3x3 Sobel reads
with its nearest valid neighbour's value before differentiating, which adds
no step of its own; the gradient is then NaN on the invalid pixels
themselves, and they never count as edges.

float32 images (those of :func:`pihim.camera.polar_image`) are
differentiated in float32, float64 ones in float64 (other numbers become
float64): the gradients agree to about 1e-4 of the map's largest value, and
float32 is about four times faster on a 5-megapixel frame (0.7 against 2.8
s for the Canny maps here, ``benchmarks/bench_edges.py``).

Noise weighting
---------------
One threshold per map suits a frame whose noise is alike everywhere; it is
not: a DoFP pixel's shot noise grows as the square root of its signal, so
the DoLP and AoP of a dark region (the dark back of the target that a
UFACET pair's facets reflect) are mostly noise, and their gradients there
pass a threshold set by the bright majority (14-15 % of the pixels of the
demo's frames became DoLP or AoP edges). Given per-pixel noise standard
deviations (``noise=`` of :func:`edge_maps`, from :func:`noise_sigmas`),
each gradient map is divided by its image's noise before the thresholds:
S0 by ``sigma_S0``, DoLP by ``sigma_DoLP`` and the DoLP-weighted AoP by
``(90 / pi) sigma_DoLP`` (an AoP's noise is ``sigma_DoLP / (2 DoLP)``
radians, so the weighted map's is that times DoLP). The maps are then in
multiples of the pixel noise per pixel, and an edge is a step that stands
out of its own region's noise (the demo frames' DoLP and AoP maps: about
3 % of the pixels).

:func:`noise_sigmas` takes the four analyser channels of a quad at
``S0 / 2`` each (the ideal DoFP), each with shot noise (``electrons_per_dn``
electrons per DN), read noise and the ADC's quantisation noise: ``var(I) =
(S0 / 2) / g + r^2 + 1/12`` DN^2, ``sigma_S0 = sqrt(var(I))`` (S0 is half
the sum of four channels), ``sigma_DoLP = sqrt(2 var(I)) / S0`` (S1 and S2
are differences of two channels), with S0 the 3x3 mean. ``sigma_S0`` and
the AoP's scaling are exact for this model at any polarization;
``sigma_DoLP`` is first order and leaves out the covariance of S0 and S1,
so it is about right for a moderately polarized pixel (0.96-0.98 of the
true spread at DoLP 0.3) but about 1.2x too large at DoLP 0.8 and 1.5x at
DoLP 0 (where the DoLP's noise is not Gaussian): a residual, pixel-dependent
error of tens of per cent against the several-fold one of the plain maps.
Demosaicing scales every pixel's noise about alike, which the relative
thresholds do not see. The log's ``sensor.model`` is taken to describe the
frame as it was taken (its gain).

Edge pixels and thresholds
--------------------------
Each gradient map gets one threshold from robust statistics of its finite
values ``g`` (:func:`robust_thresholds`):

* ``sigma = 1.4826 * MAD(g)`` (the median absolute deviation scaled to a
  Gaussian standard deviation), at least ``1e-3 * median(g)`` so that a
  perfectly smooth image does not turn round-off into edges;
* ``high = max(median(g) + n_sigma * sigma, floor_fraction * P99.5(g))``:
  an edge is an outlier of the background gradient distribution (noise plus
  smooth shading), and on noise-free images, where ``sigma`` collapses, at
  least a tenth (default) of the strong-edge level;
* ``low = low_ratio * high`` (Canny's hysteresis threshold; default 0.4,
  within Canny's recommended 2:1 to 3:1).

``method="sobel"``: edge pixels are ``gradient > high`` (edges are about
two pixels thick). ``method="canny"``: OpenCV's Canny (``cv2.Canny(dx, dy,
low, high, L2gradient=True)``) on the same Sobel gradients, so non-maximum
suppression and hysteresis act on the very maps returned (for AoP the
gradient direction is the principal direction of the structure tensor of
``(cos 2a, sin 2a)``); edges are one pixel thick.

The **combined** map is the per-pixel maximum of the three gradient maps,
each divided by its own ``high`` threshold (so 1 means "at threshold"), and
its edge pixels are the union of the three binary maps.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError
from pihim.inspection._log import sensor_entries

__all__ = [
    "EDGE_METHODS",
    "IMAGE_TYPES",
    "EdgeMap",
    "EdgeMaps",
    "axial_gradient_magnitude",
    "edge_maps",
    "gradient_magnitude",
    "noise_sigmas",
    "robust_thresholds",
    "sensor_noise",
]

#: Edge detectors of :func:`edge_maps`.
EDGE_METHODS: tuple[str, ...] = ("sobel", "canny")
#: Image types of :class:`EdgeMaps`, in order; the combined map comes last.
IMAGE_TYPES: tuple[str, ...] = ("S0", "DoLP", "AoP", "combined")

EdgeMethod = Literal["sobel", "canny"]

#: Scale of the 3x3 Sobel kernel to a per-pixel derivative.
_SOBEL_SCALE = 1.0 / 8.0
#: Axial (cos 2a, sin 2a) gradient to AoP degrees per pixel.
_AXIAL_DEG = 90.0 / math.pi
#: Largest int16 magnitude handed to cv2.Canny (strong gradients are clipped, direction kept).
_CANNY_CLIP = 32000.0
#: cv2.Canny sees the high threshold as this many int16 units.
_CANNY_HIGH_UNITS = 1000.0


# --------------------------------------------------------------------------- helpers


def _image(name: str, image: ArrayLike) -> NDArray[np.floating]:
    """A validated 2-D image: float32 and float64 keep their precision, other numbers become float64."""
    a = np.asarray(image)
    if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < 1:
        raise PihimInputError(f"{name} must be a non-empty 2-D image, got shape {a.shape}")
    if a.dtype.kind not in "fiub":
        raise PihimInputError(f"{name} must be numeric, got dtype {a.dtype}")
    return a if a.dtype in (np.float32, np.float64) else a.astype(np.float64)


#: Largest read noise :func:`sensor_noise` accepts, DN (a 16-bit raw range).
_MAX_READ_NOISE_DN = 65535.0

#: Neighbour offsets (row, column) in the order :func:`_fill_nearest` takes them: sides, then corners.
_NEIGHBOURS = ((0, -1), (0, 1), (-1, 0), (1, 0), (-1, -1), (-1, 1), (1, -1), (1, 1))


def _fill_nearest(image: NDArray[np.floating]) -> tuple[NDArray[np.floating], NDArray[np.bool_]]:
    """NaN/inf pixels next to a finite one replaced by their nearest finite neighbour; returns (filled, valid).

    The 3x3 Sobel of a valid pixel reads only pixels in its 3x3
    neighbourhood, so an invalid pixel it reads has a valid pixel at
    distance 1 or sqrt(2): its nearest is a side neighbour if one is valid
    (the first valid of left, right, up, down), else a corner one. Such a
    pixel takes that neighbour's value, which adds no step to the valid
    pixel's gradient. Invalid pixels with no valid neighbour are read by no
    valid pixel's gradient and become 0.
    """
    valid = np.isfinite(image)
    if valid.all():
        return image, valid
    if not valid.any():
        return np.zeros_like(image), valid
    rows, cols = image.shape
    filled = np.where(valid, image, 0).astype(image.dtype, copy=False)
    r0, c0 = np.nonzero(~valid)
    todo = np.ones(r0.size, dtype=bool)
    for dr, dc in _NEIGHBOURS:
        r, c = r0 + dr, c0 + dc
        take = todo & (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
        take[take] = valid[r[take], c[take]]
        filled[r0[take], c0[take]] = image[r[take], c[take]]
        todo &= ~take
    return filled, valid


def _sobel_xy(image: NDArray[np.floating]) -> tuple[NDArray[np.floating], NDArray[np.floating]]:
    """Per-pixel derivatives d/dcolumn and d/drow (Sobel / 8, replicated borders), in the image's precision."""
    import cv2  # imported where used: the command line's --help need not load OpenCV

    img = np.ascontiguousarray(image)
    gx = cv2.Sobel(img, -1, 1, 0, ksize=3, scale=_SOBEL_SCALE, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(img, -1, 0, 1, ksize=3, scale=_SOBEL_SCALE, borderType=cv2.BORDER_REPLICATE)
    return gx, gy


def _magnitude(x: NDArray[np.floating], y: NDArray[np.floating]) -> NDArray[np.floating]:
    """``sqrt(x^2 + y^2)`` elementwise; ``np.hypot`` (3x slower) where the squares over- or underflow.

    Not ``cv2.magnitude``: its result varies in the last bit from call to call
    (its threads split the image differently), and outputs must repeat.
    """
    with np.errstate(over="ignore", under="ignore"):
        m = np.multiply(x, x)
        m += y * y
        np.sqrt(m, out=m)
        # below sqrt(tiny) x 2^12 a square has lost bits to underflow (or is 0); inf: overflowed; NaN too
        redo = ~(m >= np.sqrt(np.finfo(m.dtype).tiny) * 4096.0) | np.isinf(m)
        if redo.any():
            m[redo] = np.hypot(x[redo], y[redo])
    return m


def _scalar_gradient(image: ArrayLike, name: str) -> tuple[NDArray, NDArray, NDArray, NDArray[np.bool_]]:
    """(magnitude, dx, dy, valid) of a scalar image; magnitude NaN where the input was not finite."""
    filled, valid = _fill_nearest(_image(name, image))
    gx, gy = _sobel_xy(filled)
    mag = _magnitude(gx, gy)
    mag[~valid] = np.nan
    return mag, gx, gy, valid


def _axial_gradient(aop_deg: ArrayLike, dolp: ArrayLike | None, *,
                    direction: bool = False) -> tuple[NDArray, NDArray | None, NDArray | None, NDArray[np.bool_]]:
    """(magnitude, dx, dy, valid) of an AoP image; dx, dy along the principal direction (if asked for)."""
    import cv2  # imported where used: the command line's --help need not load OpenCV

    a, valid = _fill_nearest(_image("AoP", aop_deg))
    two_a = a * a.dtype.type(math.pi / 90.0)  # 2a in radians, in the image's precision
    cx, cy = _sobel_xy(np.cos(two_a))
    sx, sy = _sobel_xy(np.sin(two_a))
    gx, gy = _magnitude(cx, sx), _magnitude(cy, sy)  # |d/dx (cos 2a, sin 2a)|, |d/dy (...)|
    mag = _magnitude(gx, gy)
    mag *= mag.dtype.type(_AXIAL_DEG)
    if dolp is not None:
        d = _image("DoLP", dolp)
        if d.shape != a.shape:
            raise PihimInputError(f"DoLP shape {d.shape} differs from AoP shape {a.shape}")
        d_filled, d_valid = _fill_nearest(d)
        weight = cv2.blur(np.clip(d_filled, 0.0, 1.0).astype(mag.dtype, copy=False), (3, 3),
                          borderType=cv2.BORDER_REPLICATE)
        mag *= weight
        valid = valid & d_valid
    dx = dy = None
    if direction:
        # principal direction t of the structure tensor [[jxx, jxy], [jxy, jyy]]: tan 2t = 2 jxy / (jxx - jyy);
        # cos t and sin t from cos 2t by the half-angle formulas (t in (-90, 90] deg, the sign of sin t that of jxy)
        c2, s2 = (gx - gy) * (gx + gy), 2.0 * (cx * cy + sx * sy)
        r = _magnitude(c2, s2)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos2t = np.where(r > 0, c2 / r, 1.0).astype(mag.dtype, copy=False)
        dx = mag * np.sqrt(np.maximum(0.5 * (1.0 + cos2t), 0.0))
        dy = np.copysign(mag * np.sqrt(np.maximum(0.5 * (1.0 - cos2t), 0.0)), s2)
    mag[~valid] = np.nan
    return mag, dx, dy, valid


def gradient_magnitude(image: ArrayLike) -> NDArray[np.floating]:
    """Sobel gradient magnitude, per pixel (see the module notes).

    Parameters
    ----------
    image : array_like, shape (H, W)
        Any real image (S0, DoLP, ...); NaN pixels are allowed.

    Returns
    -------
    ndarray, shape (H, W)
        float32 for a float32 image, else float64: ``hypot(d/dx, d/dy)`` with the 3x3 Sobel kernel scaled by 1/8 (a ramp
        of slope ``s`` per pixel gives ``s``); NaN where the input is NaN.
    """
    return _scalar_gradient(image, "image")[0]


def axial_gradient_magnitude(aop_deg: ArrayLike, dolp: ArrayLike | None = None) -> NDArray[np.floating]:
    """Gradient magnitude of an axial AoP image, in deg per pixel (optionally DoLP-weighted).

    The gradient of ``(cos 2a, sin 2a)``, never of the raw angle, so the
    0/180 deg wrap makes no edge (see the module notes for the scale).

    Parameters
    ----------
    aop_deg : array_like, shape (H, W)
        AoP in degrees (any real values; only ``2a`` modulo 360 matters).
    dolp : array_like, shape (H, W), optional
        If given, the magnitude is multiplied by the 3x3 mean DoLP (clipped to
        [0, 1]).

    Returns
    -------
    ndarray, shape (H, W)
        float32 for a float32 AoP image, else float64; NaN where the AoP (or
        the DoLP, if given) is NaN.
    """
    return _axial_gradient(aop_deg, dolp)[0]


def noise_sigmas(
    s0: ArrayLike,
    *,
    electrons_per_dn: float | None = None,
    read_noise_dn: float = 0.0,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Per-pixel noise standard deviations of S0 (DN) and DoLP of a DoFP sensor (see the module notes).

    Parameters
    ----------
    s0 : array_like, shape (H, W)
        S0 in DN above the dark level (:class:`pihim.camera.PolarImage` ``.s0``);
        NaN allowed.
    electrons_per_dn : float, optional
        Conversion gain, electrons per DN (the frame log's
        ``sensor.model.electrons_per_dn``); default 1: a shot-noise-limited
        sensor of unknown gain (the noise then scales as ``sqrt(S0)``, which is
        all :func:`edge_maps`' relative thresholds need).
    read_noise_dn : float
        Read noise per pixel, DN.

    Returns
    -------
    sigma_s0, sigma_dolp : ndarray of float32, shape (H, W)
        ``sigma_DoLP`` is infinite where the local S0 is not positive (no
        polarization can be measured there).

    References
    ----------
    .. [1] J. S. Tyo, D. L. Goldstein, D. B. Chenault, J. A. Shaw, "Review of
       passive imaging polarimetry for remote sensing applications", Appl.
       Opt. 45(22), 5453-5469 (2006), doi:10.1364/AO.45.005453 (noise of
       Stokes estimates from analyser channels).
    """
    import cv2  # imported where used: the command line's --help need not load OpenCV

    a = _image("S0", s0)
    g = 1.0 if electrons_per_dn is None else float(electrons_per_dn)
    r = float(read_noise_dn)
    if not (1e-6 <= g <= 1e6):
        raise PihimInputError(f"electrons_per_dn must be in [1e-06, 1e+06], got {electrons_per_dn!r}")
    if not (0.0 <= r <= _MAX_READ_NOISE_DN):
        raise PihimInputError(f"read_noise_dn must be in [0, {_MAX_READ_NOISE_DN:g}], got {read_noise_dn!r}")
    local = cv2.blur(np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32), (3, 3),
                     borderType=cv2.BORDER_REPLICATE)
    var_i = np.maximum(local, 0.0) * np.float32(0.5 / g) + np.float32(r * r + 1.0 / 12.0)
    sigma_s0 = np.sqrt(var_i)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma_dolp = np.where(local > 0, np.sqrt(2.0 * var_i) / local, np.float32(np.inf)).astype(np.float32)
    return sigma_s0, sigma_dolp


def sensor_noise(log: Mapping[str, Any]) -> dict[str, float | None]:
    """The noise model a frame's ``log["sensor"]["model"]`` records, for :func:`noise_sigmas`.

    Returns ``{"electrons_per_dn", "read_noise_dn"}``: None (unknown gain: a
    shot-noise-limited sensor) and 0 DN where the log is silent; a malformed
    entry is a :class:`PihimInputError`.
    """
    _, model = sensor_entries(log)
    out: dict[str, float | None] = {"electrons_per_dn": None, "read_noise_dn": 0.0}
    for name, lo, hi in (("electrons_per_dn", 1e-6, 1e6), ("read_noise_dn", 0.0, _MAX_READ_NOISE_DN)):
        if name not in model:
            continue
        v = model[name]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (lo <= v <= hi):
            raise PihimInputError(f"log sensor {name} must be a number in [{lo:g}, {hi:g}], got {v!r}")
        out[name] = float(v)
    return out


def robust_thresholds(
    gradient: ArrayLike,
    *,
    n_sigma: float = 5.0,
    floor_fraction: float = 0.1,
    low_ratio: float = 0.4,
) -> tuple[float, float]:
    """``(high, low)`` edge thresholds of a gradient map from robust statistics.

    ``high = max(median + n_sigma * 1.4826 * MAD, floor_fraction * P99.5)``
    over the finite values (the MAD-sigma at least 1e-3 of the median);
    ``low = low_ratio * high``. ``(inf, inf)`` if no value is finite.
    ``n_sigma`` and ``floor_fraction`` must be finite and >= 0, ``low_ratio``
    in (0, 1] (low above high is no hysteresis), as :func:`edge_maps` asks.
    """
    for name, value in (("n_sigma", n_sigma), ("floor_fraction", floor_fraction), ("low_ratio", low_ratio)):
        if not (math.isfinite(value) and value >= 0):
            raise PihimInputError(f"{name} must be a finite number >= 0, got {value!r}")
    if not 0 < low_ratio <= 1:
        raise PihimInputError(f"low_ratio must be in (0, 1], got {low_ratio!r}")
    g = np.asarray(gradient)
    if g.dtype == np.float32:  # the maps of edge_maps: exact selection without a float64 copy
        from pihim._quantiles import percentiles

        stats = percentiles(g, (50.0, 99.5))
        if stats is None:
            return math.inf, math.inf
        med, p995 = stats
        with np.errstate(invalid="ignore"):
            mad = percentiles(np.abs(g - np.float32(med)), (50.0,))[0]  # type: ignore[index]
    else:
        g = np.asarray(g, dtype=np.float64)
        g = g[np.isfinite(g)]
        if g.size == 0:
            return math.inf, math.inf
        med = float(np.median(g))
        mad = float(np.median(np.abs(g - med)))
        p995 = float(np.percentile(g, 99.5))
    sigma = max(1.4826 * mad, 1e-3 * abs(med))
    high = max(med + float(n_sigma) * sigma, float(floor_fraction) * p995)
    return high, float(low_ratio) * high


def _canny(mag: NDArray, dx: NDArray, dy: NDArray, valid: NDArray[np.bool_], high: float,
           low: float) -> NDArray[np.bool_]:
    """OpenCV Canny on given gradients: scaled so that ``high`` is 1000 int16 units."""
    import cv2  # imported where used: the command line's --help need not load OpenCV

    if not math.isfinite(high) or high <= 0.0:
        # no finite gradient, or a flat image: nothing can be an edge
        return np.zeros(mag.shape, dtype=bool)
    scale = _CANNY_HIGH_UNITS / high
    # int16 units: each gradient vector scaled by 1000 / high, shortened (direction kept) to at most 32000
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.fmin(mag.dtype.type(scale), mag.dtype.type(_CANNY_CLIP) / mag)  # NaN magnitude: scale
    factor[~valid] = 0.0

    def units(d: NDArray) -> NDArray[np.int16]:
        v = d * factor
        if not np.isfinite(v).all():  # an overflowing gradient times 0
            v = np.nan_to_num(v, copy=False)
        np.clip(v, -_CANNY_CLIP, _CANNY_CLIP, out=v)
        return np.rint(v, out=v).astype(np.int16)

    out = cv2.Canny(units(dx), units(dy), low * scale, _CANNY_HIGH_UNITS, L2gradient=True)
    return (out > 0) & valid


# --------------------------------------------------------------------------- results


@dataclass(frozen=True, eq=False)
class EdgeMap:
    """Edges of one image type.

    Attributes
    ----------
    gradient : ndarray of float32, shape (H, W)
        Gradient magnitude (S0 units per pixel, DoLP per pixel, AoP deg per
        pixel (times DoLP if weighted); for ``combined``, multiples of each
        map's own ``high`` threshold). NaN where the input was invalid.
    edges : ndarray of bool, shape (H, W)
        Edge pixels.
    high, low : float
        Thresholds used (``low`` is Canny's hysteresis threshold; for the
        Sobel method it is reported but not used).
    units : str
        What ``gradient`` measures.
    """

    gradient: NDArray[np.float32]
    edges: NDArray[np.bool_]
    high: float
    low: float
    units: str

    def stats(self) -> dict[str, Any]:
        """JSON-ready statistics: edge pixel fraction, gradient percentiles, thresholds."""
        from pihim._quantiles import percentiles

        n = self.gradient.size
        finite = np.isfinite(self.gradient)
        n_valid = int(finite.sum())
        q = (50.0, 90.0, 99.0, 100.0)
        if not n_valid:
            stats = None
        elif self.gradient.dtype == np.float32:  # exact selection without a float64 copy
            stats = percentiles(self.gradient, q)
        else:
            stats = [float(v) for v in np.percentile(self.gradient[finite].astype(np.float64), q)]
        if stats is not None:
            p50, p90, p99, top = stats
            grad = {"p50": p50, "p90": p90, "p99": p99, "max": top}
        else:
            grad = {"p50": None, "p90": None, "p99": None, "max": None}

        def _num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        return {
            "edge_fraction": float(self.edges.sum()) / n if n else 0.0,
            "valid_fraction": n_valid / n if n else 0.0,
            "gradient": grad,
            "threshold_high": _num(self.high),
            "threshold_low": _num(self.low),
            "units": self.units,
        }


@dataclass(frozen=True, eq=False)
class EdgeMaps:
    """Edge maps of S0, DoLP and AoP and their combination (see :func:`edge_maps`).

    Index by image type: ``maps["DoLP"].edges``; :data:`IMAGE_TYPES` lists them.
    """

    s0: EdgeMap
    dolp: EdgeMap
    aop: EdgeMap
    combined: EdgeMap
    method: str
    parameters: dict[str, Any] = field(default_factory=dict)

    def __getitem__(self, image_type: str) -> EdgeMap:
        key = str(image_type).strip().lower()
        table = {"s0": self.s0, "dolp": self.dolp, "aop": self.aop, "combined": self.combined}
        if key not in table:
            raise KeyError(f"unknown image type {image_type!r}; choose one of {', '.join(IMAGE_TYPES)}")
        return table[key]

    def items(self) -> list[tuple[str, EdgeMap]]:
        """``(image type, EdgeMap)`` in :data:`IMAGE_TYPES` order."""
        return [(name, self[name]) for name in IMAGE_TYPES]

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns) of the maps."""
        return self.s0.gradient.shape  # type: ignore[return-value]

    def summary(self) -> dict[str, Any]:
        """Per-image-type statistics (:meth:`EdgeMap.stats`), keyed by image type."""
        return {name: m.stats() for name, m in self.items()}


def edge_maps(
    s0: ArrayLike,
    dolp: ArrayLike,
    aop_deg: ArrayLike,
    method: EdgeMethod = "sobel",
    *,
    n_sigma: float = 5.0,
    floor_fraction: float = 0.1,
    low_ratio: float = 0.4,
    aop_dolp_weighted: bool = True,
    noise: tuple[ArrayLike, ArrayLike] | None = None,
) -> EdgeMaps:
    """Edge maps of the S0, DoLP and AoP images of one frame, and their combination.

    Parameters
    ----------
    s0, dolp, aop_deg : array_like, shape (H, W)
        Images of the same shape (e.g. :class:`pihim.camera.PolarImage`
        ``.s0``, ``.dolp``, ``.aop_deg``); NaN marks invalid pixels.
    method : {"sobel", "canny"}
        Thresholded Sobel magnitude, or Canny (non-maximum suppression and
        hysteresis) on the same gradients; see the module notes.
    n_sigma, floor_fraction, low_ratio : float
        Threshold rule of :func:`robust_thresholds`, applied per image type.
    aop_dolp_weighted : bool
        Weight the AoP gradient by the local DoLP (default).
    noise : (sigma_s0, sigma_dolp), optional
        Per-pixel noise standard deviations of S0 and DoLP, shape (H, W)
        (:func:`noise_sigmas`): each gradient map is divided by its image's
        noise before the thresholds (see the module notes), and is then in
        multiples of the pixel noise. Needs ``aop_dolp_weighted``.

    Returns
    -------
    EdgeMaps
    """
    if method not in EDGE_METHODS:
        raise PihimInputError(f"unknown edge method {method!r}; choose one of {', '.join(EDGE_METHODS)}")
    for name, v in (("n_sigma", n_sigma), ("floor_fraction", floor_fraction), ("low_ratio", low_ratio)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise PihimInputError(f"{name} must be a finite number >= 0, got {v!r}")
    if not 0 < low_ratio <= 1:
        raise PihimInputError(f"low_ratio must be in (0, 1], got {low_ratio!r}")
    s0_a, dolp_a, aop_a = _image("S0", s0), _image("DoLP", dolp), _image("AoP", aop_deg)
    if not (s0_a.shape == dolp_a.shape == aop_a.shape):
        raise PihimInputError(
            f"S0, DoLP and AoP must have the same shape, got {s0_a.shape}, {dolp_a.shape}, {aop_a.shape}"
        )
    sigmas: dict[str, NDArray] = {}
    if noise is not None:
        if not aop_dolp_weighted:
            raise PihimInputError("noise weighting needs the DoLP-weighted AoP gradient (aop_dolp_weighted)")
        if not (isinstance(noise, (tuple, list)) and len(noise) == 2):
            raise PihimInputError("noise must be a pair (sigma_s0, sigma_dolp) of images")
        sig_s0, sig_dolp = _image("sigma_s0", noise[0]), _image("sigma_dolp", noise[1])
        if not (sig_s0.shape == sig_dolp.shape == s0_a.shape):
            raise PihimInputError(f"the noise images must have the images' shape {s0_a.shape}, got "
                                  f"{sig_s0.shape} and {sig_dolp.shape}")
        if not ((sig_s0 > 0).all() and (sig_dolp > 0).all()):  # NaN fails too; inf (no signal) is allowed
            raise PihimInputError("the noise standard deviations must be > 0 (inf where nothing is measured)")
        sigmas = {"S0": sig_s0, "DoLP": sig_dolp, "AoP": sig_dolp * sig_dolp.dtype.type(_AXIAL_DEG)}
    grads = {
        "S0": (*_scalar_gradient(s0_a, "S0"), "S0 per pixel"),
        "DoLP": (*_scalar_gradient(dolp_a, "DoLP"), "DoLP per pixel"),
        "AoP": (*_axial_gradient(aop_a, dolp_a if aop_dolp_weighted else None, direction=method == "canny"),
                "AoP deg per pixel x DoLP" if aop_dolp_weighted else "AoP deg per pixel"),
    }
    maps: dict[str, EdgeMap] = {}
    for name, (mag, dx, dy, valid, units) in grads.items():
        if sigmas:
            with np.errstate(divide="ignore", invalid="ignore"):
                mag, dx, dy = (None if d is None else d / sigmas[name] for d in (mag, dx, dy))
            units = f"{units}, in multiples of the pixel noise"
        high, low = robust_thresholds(mag, n_sigma=n_sigma, floor_fraction=floor_fraction, low_ratio=low_ratio)
        if method == "sobel":
            with np.errstate(invalid="ignore"):
                edges = np.isfinite(mag) & (mag > high)
        else:
            edges = _canny(mag, dx, dy, valid, high, low)
        maps[name] = EdgeMap(mag.astype(np.float32, copy=False), edges, high, low, units)
    combined_grad: NDArray[np.float32] | None = None
    for m in maps.values():  # np.fmax: NaN only where every map is NaN
        if math.isfinite(m.high) and m.high > 0:
            with np.errstate(over="ignore"):  # a threshold beyond float32 (the gradients are float32)
                norm = m.gradient / np.float32(m.high)
        else:
            norm = np.where(np.isfinite(m.gradient), np.float32(0.0), np.float32(np.nan))
        combined_grad = norm if combined_grad is None else np.fmax(combined_grad, norm, out=combined_grad)
    combined_edges = maps["S0"].edges | maps["DoLP"].edges | maps["AoP"].edges
    combined = EdgeMap(combined_grad, combined_edges, 1.0, float(low_ratio),
                       "multiples of each image type's high threshold")
    params = {"n_sigma": float(n_sigma), "floor_fraction": float(floor_fraction), "low_ratio": float(low_ratio),
              "aop_dolp_weighted": bool(aop_dolp_weighted), "noise_weighted": bool(sigmas)}
    return EdgeMaps(maps["S0"], maps["DoLP"], maps["AoP"], combined, str(method), params)

