"""Polarizer calibration of a DoFP camera: the analyser matrix from a rotated linear polarizer.

Procedure
---------
Light the camera with a spatially uniform (or at least temporally stable),
unpolarized source seen through a linear reference polarizer, and record one
frame per polarizer angle ``phi_j`` (degrees counter-clockwise from image
right, the project's image AoP convention; at least four distinct angles,
preferably evenly spread over 180 deg, e.g. every 22.5 or 10 deg). The
Stokes vector incident on the sensor is then

.. math:: S_j = L \\, [1, \\; p \\cos 2\\phi_j, \\; p \\sin 2\\phi_j]^T

with ``p`` the DoLP of the reference polarizer (1 for a good sheet or
Glan-type polarizer) and ``L`` the unknown, constant source radiance in DN.
Channel ``k`` of the analyser (:class:`~pihim.polarimetry.analyser.AnalyserMatrix`,
row ``a_k``) records ``I_kj = a_k . S_j``. The mean of the channel over a
region of interest (ROI; super-pixels saturated in any frame excluded, the
same super-pixels in every frame) is therefore linear in the three entries
of ``L a_k``; stacking the frames gives, per channel, a linear least-squares
problem with the ``N x 3`` design matrix ``[1, p cos 2phi_j, p sin 2phi_j]``
(the "super-pixel" flavour of the rotating-polarizer calibration of [1]_).
The unknown ``L`` is removed by normalising the mean channel transmission
``t_k = 2 a_k0`` to 1.

Per-frame intensity drift (optional, ``fit_frame_scale=True``): the source
may drift between frames, ``S_j = L g_j [...]``. The scales ``g_j`` (mean 1)
are then estimated jointly with the matrix by non-linear least squares
(Levenberg-Marquardt on the bilinear model ``g_j (A x_j)_k``, started from
the drift-free fit). This works because all four channels see the same
``g_j`` while their modulation curves differ in phase. Four frames would
leave a single degree of freedom for 15 unknowns (nothing would check the
fit), so at least five distinct angles are required; the fit is rejected if
its Jacobian is ill-conditioned.

Degeneracies to be aware of: a mechanical zero offset of the reference
polarizer rotates all four fitted channel angles by the same amount (it
cannot be separated from a common rotation of the micro-polarizer array),
and an over- or under-estimated ``p`` scales all diattenuations by
``p_true / p``. The fitted angles are in the displayed-image frame of the
``layout``; a wrong layout or a clockwise angle sense shows up as channels
fitted about 90 deg from nominal, which is reported in
:attr:`PolarizerCalibration.warnings`.

References
----------
.. [1] S. B. Powell and V. Gruev, "Calibration methods for division-of-focal-plane
   polarimeters", Opt. Express 21(18), 21039-21055 (2013),
   doi:10.1364/OE.21.021039.
.. [2] J. S. Tyo, D. L. Goldstein, D. B. Chenault, J. A. Shaw, "Review of
   passive imaging polarimetry for remote sensing applications",
   Appl. Opt. 45(22), 5453-5469 (2006), doi:10.1364/AO.45.005453
   (analyser matrix, pseudo-inverse reconstruction, condition number).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.camera.frames import RawFrame
from pihim.camera.layout import IMX250MZR, MosaicLayout, check_mosaic_shape
from pihim.camera.pipeline import BitDepth, resolve_bit_depth
from pihim.errors import PihimInputError
from pihim.polarimetry.analyser import NOMINAL_ANGLES_DEG, AnalyserMatrix

#: Fewest distinct polarizer angles (modulo 180 deg) accepted.
MIN_DISTINCT_ANGLES = 4
#: Fewest distinct polarizer angles when per-frame drift is fitted.
MIN_DISTINCT_ANGLES_DRIFT = 5
#: Largest accepted condition number of the angle design matrix [1, cos 2phi, sin 2phi].
MAX_DESIGN_CONDITION = 100.0

_ANGLE_WARN_DEG = 10.0
_RESIDUAL_WARN = 0.01
_DESIGN_WARN = 10.0
_DIATTENUATION_WARN = 1.005
_EXCLUDED_WARN = 0.5
_ZERO_WARN = 0.01
_MAX_DRIFT_CONDITION = 1e4


# -- result ---------------------------------------------------------------------------


def _frozen(a: ArrayLike) -> NDArray[np.float64]:
    arr = np.array(a, dtype=np.float64)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class PolarizerCalibration:
    """Result of a rotating-polarizer calibration.

    Attributes
    ----------
    analyser : AnalyserMatrix
        Fitted 4x3 analyser matrix, normalised to a mean channel transmission
        of 1; rows in channel order 0/45/90/135 deg.
    polarizer_angles_deg : numpy.ndarray, shape (N,)
        Reference polarizer angle of each frame, degrees counter-clockwise
        from image right.
    polarizer_dolp : float
        DoLP assumed for the reference polarizer.
    channel_means_dn : numpy.ndarray, shape (4, N)
        Measured dark-subtracted mean of each channel in each frame (DN).
    residual_rms_dn : numpy.ndarray, shape (4,)
        RMS over frames of measured minus modelled channel mean (DN).
    residual_rms_relative : numpy.ndarray, shape (4,)
        ``residual_rms_dn`` divided by the channel's unpolarized-equivalent
        level ``L t_k / 2`` (dimensionless).
    source_s0_dn : float
        Fitted source radiance ``L`` (S0 in DN for a transmission-1 channel).
    frame_scale : numpy.ndarray, shape (N,), or None
        Fitted relative source intensity per frame (mean 1) when drift was
        fitted, else None.
    condition_number : float
        2-norm condition number of the fitted analyser matrix (1.414 for the
        ideal analyser; larger means more noise amplification [2]_).
    design_condition_number : float
        Condition number of the angle design matrix ``[1, cos 2phi, sin 2phi]``
        (1.414 for evenly spread angles).
    roi : (int, int, int, int) or None
        ROI actually used, ``(x, y, width, height)`` in mosaic pixels.
    superpixels_used : int or None
        Number of super-pixels averaged per channel and frame.
    fraction_excluded : float or None
        Fraction of ROI super-pixels excluded as saturated.
    layout : MosaicLayout or None
    dark_level : float or None
        Dark level subtracted, in raw units after any MSB shift.
    bit_depth : BitDepth or None
    frame_names : tuple of str or None
    warnings : tuple of str
        One-line notes on suspicious results (not errors).
    """

    analyser: AnalyserMatrix
    polarizer_angles_deg: NDArray[np.float64]
    polarizer_dolp: float
    channel_means_dn: NDArray[np.float64]
    residual_rms_dn: NDArray[np.float64]
    residual_rms_relative: NDArray[np.float64]
    source_s0_dn: float
    frame_scale: NDArray[np.float64] | None
    condition_number: float
    design_condition_number: float
    roi: tuple[int, int, int, int] | None = None
    superpixels_used: int | None = None
    fraction_excluded: float | None = None
    layout: MosaicLayout | None = None
    dark_level: float | None = None
    bit_depth: BitDepth | None = None
    frame_names: tuple[str | None, ...] | None = None
    warnings: tuple[str, ...] = ()

    # -- derived ---------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        """Number of calibration frames."""
        return int(self.polarizer_angles_deg.size)

    @property
    def matrix(self) -> NDArray[np.float64]:
        """The fitted 4x3 analyser matrix."""
        return self.analyser.matrix

    @property
    def transmission(self) -> NDArray[np.float64]:
        """Per-channel transmission ``t_k`` (mean 1)."""
        return self.analyser.transmission

    @property
    def angles_deg(self) -> NDArray[np.float64]:
        """Per-channel transmission-axis angle, degrees in [0, 180)."""
        return self.analyser.angles_deg

    @property
    def diattenuation(self) -> NDArray[np.float64]:
        """Per-channel diattenuation ``d_k``."""
        return self.analyser.diattenuation

    @property
    def extinction_ratio(self) -> NDArray[np.float64]:
        """Per-channel extinction ratio ``(1 + d) / (1 - d)`` (inf for d >= 1)."""
        return self.analyser.extinction_ratio

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record.

        The top level holds :meth:`AnalyserMatrix.to_dict` (so that
        :meth:`AnalyserMatrix.load` reads the file) plus ``diattenuation``;
        everything about how the matrix was obtained is under
        ``"calibration"``. Contains no NaN or infinity.
        """
        out = self.analyser.to_dict()
        out["diattenuation"] = self.diattenuation.tolist()
        depth = self.bit_depth
        out["calibration"] = {
            "method": "rotating linear polarizer; per-channel linear least squares on ROI means",
            "n_frames": self.n_frames,
            "polarizer_angles_deg": self.polarizer_angles_deg.tolist(),
            "polarizer_dolp": float(self.polarizer_dolp),
            "fit_frame_scale": self.frame_scale is not None,
            "frame_scale": None if self.frame_scale is None else self.frame_scale.tolist(),
            "source_s0_dn": float(self.source_s0_dn),
            "channel_means_dn": self.channel_means_dn.tolist(),
            "residual_rms_dn": self.residual_rms_dn.tolist(),
            "residual_rms_relative": self.residual_rms_relative.tolist(),
            "condition_number": float(self.condition_number),
            "design_condition_number": float(self.design_condition_number),
            "roi": None
            if self.roi is None
            else dict(zip(("x", "y", "width", "height"), (int(v) for v in self.roi), strict=True)),
            "superpixels_used": self.superpixels_used,
            "fraction_excluded": None if self.fraction_excluded is None else float(self.fraction_excluded),
            "layout": None if self.layout is None else str(self.layout),
            "dark_level": None if self.dark_level is None else float(self.dark_level),
            "bit_depth": None if depth is None else depth.bits,
            "msb_shift": None if depth is None else depth.shift,
            "frames": None if self.frame_names is None else list(self.frame_names),
            "warnings": list(self.warnings),
        }
        return out


# -- ROI ---------------------------------------------------------------------------------


def default_roi(shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Central half of each side of a mosaic, ``(x, y, width, height)``, on even pixels.

    Parameters
    ----------
    shape : (int, int)
        Mosaic (rows, columns), both even.
    """
    h, w = shape
    x, y = _even(w // 4), _even(h // 4)
    return x, y, max(2, _even(w // 2)), max(2, _even(h // 2))


def _even(v: int) -> int:
    return v - (v % 2)


def _roi_bounds(roi: Sequence[int] | None, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Validate an (x, y, w, h) ROI and snap it inward to whole super-pixels: (x0, y0, x1, y1)."""
    h, w = shape
    if roi is None:
        roi = default_roi(shape)
    if len(roi) != 4:
        raise PihimInputError(f"ROI must be X,Y,WIDTH,HEIGHT, got {tuple(roi)!r}")
    try:
        x, y, rw, rh = (int(v) for v in roi)
    except (TypeError, ValueError):
        raise PihimInputError(f"ROI must be four integers, got {tuple(roi)!r}") from None
    if x < 0 or y < 0 or rw <= 0 or rh <= 0 or x + rw > w or y + rh > h:
        raise PihimInputError(
            f"ROI x={x}, y={y}, width={rw}, height={rh} does not lie inside the {w}x{h} (WxH) frame"
        )
    x0, y0 = x + (x % 2), y + (y % 2)
    x1, y1 = _even(x + rw), _even(y + rh)
    if x1 - x0 < 2 or y1 - y0 < 2:
        raise PihimInputError(f"ROI {x},{y},{rw},{rh} contains no whole 2x2 super-pixel")
    return x0, y0, x1, y1


# -- measurement --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ChannelMeans:
    """Per-frame channel means over the calibration ROI.

    Attributes
    ----------
    means : numpy.ndarray, shape (4, N)
        Dark-subtracted mean of channels 0/45/90/135 deg in each frame (DN).
    roi : (int, int, int, int)
        ROI used, ``(x, y, width, height)`` in mosaic pixels.
    superpixels_used : int
        Super-pixels averaged (the same ones in every frame).
    fraction_excluded : float
        Fraction of ROI super-pixels excluded as saturated in some frame.
    bit_depth : BitDepth or None
        Bit depth applied to all frames (None for float input).
    names : tuple of (str or None)
        Source path of each frame when known.
    fraction_zero : float
        Largest fraction, over frames, of ROI pixels reading 0 (clipped at
        black; such clipping biases the means upward).
    """

    means: NDArray[np.float64]
    roi: tuple[int, int, int, int]
    superpixels_used: int
    fraction_excluded: float
    bit_depth: BitDepth | None
    names: tuple[str | None, ...]
    fraction_zero: float = 0.0


def _label(i: int, n: int, name: str | None) -> str:
    return name if name else f"frame {i + 1} of {n}"


def measure_channel_means(
    frames: Sequence[ArrayLike | RawFrame],
    *,
    layout: MosaicLayout = IMX250MZR,
    dark_level: float = 0.0,
    bit_depth: int | None = None,
    saturation_level: float | None = None,
    roi: Sequence[int] | None = None,
) -> ChannelMeans:
    """Mean dark-subtracted intensity of each channel in each frame over a common ROI.

    Super-pixels with any pixel at or above the saturation level in *any*
    frame are excluded from every frame, so that all frames average the same
    scene points (a non-uniform illumination then only rescales ``L``).
    See :func:`calibrate_polarizer` for the parameters.
    """
    n = len(frames)
    if n == 0:
        raise PihimInputError("no calibration frames given")
    datas: list[NDArray] = []
    names: list[str | None] = []
    declared: list[int | None] = []
    for i, f in enumerate(frames):
        if isinstance(f, RawFrame):
            data, name, bits = np.asarray(f.data), (None if f.path is None else str(f.path)), f.bit_depth
        else:
            data, name, bits = np.asarray(f), None, None
        label = _label(i, n, name)
        try:
            check_mosaic_shape(data)
        except PihimInputError as exc:
            raise PihimInputError(f"{label}: {exc}") from None
        if datas and data.shape != datas[0].shape:
            h0, w0 = datas[0].shape
            raise PihimInputError(
                f"{label}: frame is {data.shape[1]}x{data.shape[0]} (WxH) but the first frame is {w0}x{h0}"
            )
        if data.dtype.kind not in "uf" or (data.dtype.kind == "u" and data.dtype not in (np.uint8, np.uint16)):
            raise PihimInputError(f"{label}: raw frames must be uint8, uint16 or float, got {data.dtype}")
        if datas and data.dtype != datas[0].dtype:
            raise PihimInputError(f"{label}: pixel type {data.dtype} differs from the first frame ({datas[0].dtype})")
        datas.append(data)
        names.append(name)
        declared.append(bits)
    if not math.isfinite(dark_level) or dark_level < 0:
        raise PihimInputError(f"dark level must be a finite number of raw units >= 0, got {dark_level:g}")

    depth: BitDepth | None
    if datas[0].dtype.kind == "f":
        depth = None
        sat = math.inf if saturation_level is None else float(saturation_level)
    else:
        bits = bit_depth
        if bits is None and all(b is not None for b in declared):
            if len(set(declared)) > 1:
                raise PihimInputError(
                    f"frames state different bit depths ({sorted(set(declared))}); pass an explicit bit depth"
                )
            bits = declared[0]
        brightest = int(np.argmax([int(d.max()) for d in datas]))
        try:
            depth = resolve_bit_depth(datas[brightest], bits)
        except PihimInputError as exc:
            raise PihimInputError(f"{_label(brightest, n, names[brightest])}: {exc}") from None
        if depth.shift:
            low = np.asarray(2**depth.shift - 1, dtype=datas[0].dtype)
            for i, d in enumerate(datas):
                if np.any(d & low):
                    raise PihimInputError(
                        f"{_label(i, n, names[i])}: not {depth.bits}-bit MSB-aligned like the brightest frame; "
                        "pass an explicit bit depth"
                    )
        sat = float(depth.full_scale if saturation_level is None else saturation_level)

    x0, y0, x1, y1 = _roi_bounds(roi, datas[0].shape)
    crops = []
    union = np.zeros(((y1 - y0) // 2, (x1 - x0) // 2), dtype=bool)
    zero = 0.0
    for i, d in enumerate(datas):
        crop = d[y0:y1, x0:x1]
        if depth is not None and depth.shift:
            crop = crop >> depth.shift
        ch = layout.split(crop)
        saturated = np.any(ch >= sat, axis=0)
        if saturated.all():
            raise PihimInputError(
                f"{_label(i, n, names[i])}: every super-pixel in the ROI is saturated; reduce the exposure"
            )
        union |= saturated
        if depth is not None:
            zero = max(zero, float(np.mean(crop == 0)))
        crops.append(ch)
    keep = ~union
    used = int(keep.sum())
    if used == 0:
        raise PihimInputError(
            "no super-pixel in the ROI is unsaturated in all frames; reduce the exposure or choose another ROI"
        )
    means = np.empty((4, n), dtype=np.float64)
    for j, ch in enumerate(crops):
        for k in range(4):
            means[k, j] = ch[k][keep].astype(np.float64).mean() - dark_level
    if not np.all(np.isfinite(means)):
        raise PihimInputError("calibration frames contain non-finite values in the ROI")
    return ChannelMeans(
        means=means,
        roi=(x0, y0, x1 - x0, y1 - y0),
        superpixels_used=used,
        fraction_excluded=float(union.mean()),
        bit_depth=depth,
        names=tuple(names),
        fraction_zero=zero,
    )


# -- fitting ------------------------------------------------------------------------------


def _design(angles_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    phi = np.radians(2.0 * angles_deg)
    return np.stack([np.ones_like(phi), np.cos(phi), np.sin(phi)], axis=1)


def _check_angles(angles_deg: ArrayLike, n_frames: int, fit_frame_scale: bool) -> NDArray[np.float64]:
    try:
        ang = np.asarray(angles_deg, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise PihimInputError("polarizer angles must be numbers (degrees)") from None
    if not np.all(np.isfinite(ang)):
        raise PihimInputError("polarizer angles must be finite numbers (degrees)")
    if ang.size != n_frames:
        raise PihimInputError(f"got {n_frames} frames but {ang.size} polarizer angles; give one angle per frame")
    distinct = np.unique(np.round(np.mod(ang, 180.0), 6) % 180.0).size
    need = MIN_DISTINCT_ANGLES_DRIFT if fit_frame_scale else MIN_DISTINCT_ANGLES
    if distinct < need:
        what = " to fit per-frame drift" if fit_frame_scale else ""
        raise PihimInputError(
            f"need at least {need} distinct polarizer angles (modulo 180 deg){what}, got {distinct}"
        )
    cond = float(np.linalg.cond(_design(ang)))
    if not cond <= MAX_DESIGN_CONDITION:
        raise PihimInputError(
            f"polarizer angles cover too little of 0-180 deg (design condition number {cond:.3g} > "
            f"{MAX_DESIGN_CONDITION:g}); spread them over the half turn"
        )
    return ang


def _check_dolp(polarizer_dolp: float) -> float:
    try:
        p = float(polarizer_dolp)
    except (TypeError, ValueError):
        raise PihimInputError(f"reference polarizer DoLP must be a number, got {polarizer_dolp!r}") from None
    if not 0.0 < p <= 1.0:
        raise PihimInputError(f"reference polarizer DoLP must be in (0, 1], got {polarizer_dolp}")
    return p


def _fit_drift(
    means: NDArray[np.float64], design: NDArray[np.float64], rows0: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Jointly fit rows (4x3) and per-frame scales ``g`` in ``means[k, j] = g_j (rows @ design_j)_k``."""
    from scipy.optimize import least_squares  # local: scipy import is slow

    n = design.shape[0]
    level = float(np.mean(np.abs(means))) or 1.0
    m = means / level

    def unpack(theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return theta[:12].reshape(4, 3), np.exp(np.concatenate([[0.0], theta[12:]]))

    def resid(theta: NDArray[np.float64]) -> NDArray[np.float64]:
        rows, g = unpack(theta)
        return ((rows @ design.T) * g - m).ravel()

    def jac(theta: NDArray[np.float64]) -> NDArray[np.float64]:
        rows, g = unpack(theta)
        model = rows @ design.T  # (4, N)
        j = np.zeros((4, n, 12 + n - 1))
        for k in range(4):
            j[k, :, 3 * k : 3 * k + 3] = design * g[:, None]
        for f in range(1, n):
            j[:, f, 12 + f - 1] = model[:, f] * g[f]
        return j.reshape(4 * n, -1)

    theta0 = np.concatenate([(rows0 / level).ravel(), np.zeros(n - 1)])
    sol = least_squares(resid, theta0, jac=jac, method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    jm = jac(sol.x)
    sv = np.linalg.svd(jm, compute_uv=False)
    if not (sol.success and sv[-1] * _MAX_DRIFT_CONDITION > sv[0]):
        raise PihimInputError(
            "per-frame drift cannot be separated from the analyser with these polarizer angles; "
            "use more, evenly spread angles or do not fit drift"
        )
    rows, g = unpack(sol.x)
    gm = float(g.mean())
    return rows * (level * gm), g / gm


def fit_analyser(
    channel_means: ArrayLike,
    angles_deg: ArrayLike,
    *,
    polarizer_dolp: float = 1.0,
    fit_frame_scale: bool = False,
) -> PolarizerCalibration:
    """Fit the analyser matrix to per-frame channel means.

    Parameters
    ----------
    channel_means : array_like, shape (4, N)
        Dark-subtracted mean intensity (DN) of channels 0/45/90/135 in each
        of the ``N`` frames.
    angles_deg : array_like, shape (N,)
        Reference polarizer angle per frame, degrees counter-clockwise from
        image right. At least :data:`MIN_DISTINCT_ANGLES` distinct values
        modulo 180 (:data:`MIN_DISTINCT_ANGLES_DRIFT` with drift fitting).
    polarizer_dolp : float
        DoLP ``p`` of the reference polarizer, in (0, 1].
    fit_frame_scale : bool
        Also fit a per-frame source intensity factor (mean 1); see the
        module notes.

    Returns
    -------
    PolarizerCalibration
        Without ROI/frame metadata (see :func:`calibrate_polarizer`).
    """
    m = np.asarray(channel_means, dtype=np.float64)
    if m.ndim != 2 or m.shape[0] != 4:
        raise PihimInputError(f"channel means must have shape (4, N), got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise PihimInputError("channel means must be finite")
    p = _check_dolp(polarizer_dolp)
    ang = _check_angles(angles_deg, m.shape[1], fit_frame_scale)
    base = _design(ang)
    design = base * np.array([1.0, p, p])
    coef, *_ = np.linalg.lstsq(design, m.T, rcond=None)
    rows = coef.T  # (4, 3), includes the source level L
    g: NDArray[np.float64] | None = None
    if fit_frame_scale:
        rows, g = _fit_drift(m, design, rows)
    t_raw = 2.0 * rows[:, 0]
    if np.any(t_raw <= 0):
        bad = ", ".join(f"{NOMINAL_ANGLES_DEG[k]:g}" for k in np.flatnonzero(t_raw <= 0))
        raise PihimInputError(
            f"fitted transmission of channel(s) {bad} deg is not positive; check the dark level and the frames"
        )
    level = float(t_raw.mean())
    try:
        analyser = AnalyserMatrix(rows / level)
    except PihimInputError as exc:
        raise PihimInputError(f"calibration failed: {exc}") from None
    scale = np.ones(ang.size) if g is None else g
    model = level * (analyser.matrix @ design.T) * scale
    rms = np.sqrt(np.mean((m - model) ** 2, axis=1))
    rel = rms / (0.5 * level * analyser.transmission)
    return PolarizerCalibration(
        analyser=analyser,
        polarizer_angles_deg=_frozen(ang),
        polarizer_dolp=p,
        channel_means_dn=_frozen(m),
        residual_rms_dn=_frozen(rms),
        residual_rms_relative=_frozen(rel),
        source_s0_dn=level,
        frame_scale=None if g is None else _frozen(g),
        condition_number=float(np.linalg.cond(analyser.matrix)),
        design_condition_number=float(np.linalg.cond(base)),
        warnings=_warnings(analyser, rel, float(np.linalg.cond(base))),
    )


def _warnings(analyser: AnalyserMatrix, rel: NDArray[np.float64], design_cond: float) -> tuple[str, ...]:
    out: list[str] = []
    dev = (analyser.angles_deg - np.array(NOMINAL_ANGLES_DEG) + 90.0) % 180.0 - 90.0
    for k, nominal in enumerate(NOMINAL_ANGLES_DEG):
        if abs(dev[k]) > _ANGLE_WARN_DEG:
            out.append(
                f"channel {nominal:g} deg: fitted axis {analyser.angles_deg[k]:.1f} deg is {dev[k]:+.1f} deg off "
                "nominal; check the layout and that angles run counter-clockwise from image right"
            )
    for k, nominal in enumerate(NOMINAL_ANGLES_DEG):
        if analyser.diattenuation[k] > _DIATTENUATION_WARN:
            out.append(
                f"channel {nominal:g} deg: fitted diattenuation {analyser.diattenuation[k]:.4f} > 1; "
                "the reference polarizer DoLP is probably set too low"
            )
    for k, nominal in enumerate(NOMINAL_ANGLES_DEG):
        if rel[k] > _RESIDUAL_WARN:
            out.append(
                f"channel {nominal:g} deg: residual RMS is {100 * rel[k]:.2g}% of the channel level; "
                "the frames do not follow the polarizer model (drift, stray light, wrong angles?)"
            )
    if design_cond > _DESIGN_WARN:
        out.append(
            f"polarizer angles are poorly spread (design condition number {design_cond:.3g}); "
            "spread them evenly over 180 deg"
        )
    return tuple(out)


def calibrate_polarizer(
    frames: Sequence[ArrayLike | RawFrame],
    angles_deg: ArrayLike,
    *,
    layout: MosaicLayout = IMX250MZR,
    dark_level: float = 0.0,
    bit_depth: int | None = None,
    saturation_level: float | None = None,
    polarizer_dolp: float = 1.0,
    roi: Sequence[int] | None = None,
    fit_frame_scale: bool = False,
) -> PolarizerCalibration:
    """Estimate the 4x3 analyser matrix from frames behind a rotated linear polarizer.

    Parameters
    ----------
    frames : sequence of numpy.ndarray or RawFrame
        Raw mosaics (``uint8``/``uint16``; float accepted for synthetic data),
        all of the same shape, of a uniformly lit scene behind the reference
        polarizer. Several frames may share an angle (they are all fitted).
    angles_deg : array_like, shape (N,)
        Reference polarizer angle of each frame, degrees counter-clockwise
        from image right (the image AoP convention), at least four distinct
        values modulo 180 deg spread over the half turn.
    layout : MosaicLayout
        Micro-polarizer arrangement of the frames (default IMX250MZR).
    dark_level : float
        Dark level in raw units after any MSB shift (DN), subtracted from the
        channel means.
    bit_depth : int, optional
        ADC bits. Default: the frames' stated bit depth, else decided from
        the brightest frame as in :func:`~pihim.camera.pipeline.resolve_bit_depth`
        and applied to all frames.
    saturation_level : float, optional
        Raw value (after shift) at or above which a pixel is saturated;
        default the full scale. Super-pixels saturated in any frame are
        excluded from all frames.
    polarizer_dolp : float
        DoLP of the reference polarizer, in (0, 1].
    roi : (int, int, int, int), optional
        ``(x, y, width, height)`` in mosaic pixels, snapped inward to whole
        super-pixels; default the central half of each side
        (:func:`default_roi`).
    fit_frame_scale : bool
        Fit a per-frame source intensity drift jointly (needs at least five
        distinct angles).

    Returns
    -------
    PolarizerCalibration

    Raises
    ------
    PihimInputError
        Fewer than four distinct angles, angle/frame count mismatch, frames
        of different shapes or types, ROI outside the frame, all ROI
        super-pixels saturated, or a degenerate fit.

    Examples
    --------
    >>> import numpy as np
    >>> from pihim.render.mosaic import mosaic_from_stokes
    >>> angles = np.arange(0, 180, 22.5)
    >>> frames = [mosaic_from_stokes(np.full((8, 8), 2000.0), 2000 * np.cos(np.radians(2 * a)),
    ...                              2000 * np.sin(np.radians(2 * a)), bit_depth=None) for a in angles]
    >>> cal = calibrate_polarizer(frames, angles)
    >>> cal.transmission.round(6).tolist(), cal.angles_deg.round(6).tolist()
    ([1.0, 1.0, 1.0, 1.0], [0.0, 45.0, 90.0, 135.0])
    """
    if len(frames) == 0:
        raise PihimInputError("no calibration frames given")
    _check_angles(angles_deg, len(frames), fit_frame_scale)  # fail fast, before touching the frames
    _check_dolp(polarizer_dolp)
    meas = measure_channel_means(
        frames,
        layout=layout,
        dark_level=dark_level,
        bit_depth=bit_depth,
        saturation_level=saturation_level,
        roi=roi,
    )
    fit = fit_analyser(meas.means, angles_deg, polarizer_dolp=polarizer_dolp, fit_frame_scale=fit_frame_scale)
    warnings = list(fit.warnings)
    if meas.fraction_excluded > _EXCLUDED_WARN:
        warnings.append(
            f"{100 * meas.fraction_excluded:.0f}% of the ROI super-pixels were saturated in some frame and excluded"
        )
    if meas.fraction_zero > _ZERO_WARN:
        warnings.append(
            f"up to {100 * meas.fraction_zero:.1f}% of the ROI pixels of a frame read 0; clipping at black "
            "biases the channel means (raise the camera black level and pass it as the dark level)"
        )
    return PolarizerCalibration(
        analyser=fit.analyser,
        polarizer_angles_deg=fit.polarizer_angles_deg,
        polarizer_dolp=fit.polarizer_dolp,
        channel_means_dn=fit.channel_means_dn,
        residual_rms_dn=fit.residual_rms_dn,
        residual_rms_relative=fit.residual_rms_relative,
        source_s0_dn=fit.source_s0_dn,
        frame_scale=fit.frame_scale,
        condition_number=fit.condition_number,
        design_condition_number=fit.design_condition_number,
        roi=meas.roi,
        superpixels_used=meas.superpixels_used,
        fraction_excluded=meas.fraction_excluded,
        layout=layout,
        dark_level=float(dark_level),
        bit_depth=meas.bit_depth,
        frame_names=meas.names,
        warnings=tuple(warnings),
    )


__all__ = [
    "ChannelMeans",
    "MAX_DESIGN_CONDITION",
    "MIN_DISTINCT_ANGLES",
    "MIN_DISTINCT_ANGLES_DRIFT",
    "PolarizerCalibration",
    "calibrate_polarizer",
    "default_roi",
    "fit_analyser",
    "measure_channel_means",
]
