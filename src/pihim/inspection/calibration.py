"""Geometric camera calibration from chessboard views (intrinsics and lens distortion).

The canting and pose estimates of the inspection need the camera's focal
length, principal point and distortion; this module measures them with
OpenCV's planar-target method (Zhang [1]_, as implemented in OpenCV [2]_):

1. each image is scaled to 8 bits (0.5th to 99.5th percentile) and the
   ``cols x rows`` inner corners are found with
   ``cv2.findChessboardCorners`` (adaptive threshold, normalised image,
   fast rejection of images without a board);
2. the corners are refined with ``cv2.cornerSubPix`` on the full-precision
   image (float32, same scaling), with a search window of about a third of
   the smallest corner spacing;
3. ``cv2.calibrateCameraExtended`` fits ``fx, fy, cx, cy`` and the five
   Brown-Conrady coefficients ``k1, k2, p1, p2, k3`` (OpenCV's order, the
   model of :class:`pihim.camera.CameraModel`) plus one board pose per view,
   minimising the reprojection error over all corners.

Reprojection errors are reported as OpenCV does: the overall RMS is
``sqrt(sum |e|^2 / N)`` over all ``N`` corners (``e`` the 2-D pixel residual),
and the per-view RMS the same over the corners of that view; they are
recomputed here with ``cv2.projectPoints``.

Images may come from a binned read-out or the super-pixel route of a DoFP
camera (one sample per 2 x 2 block): with ``image_binning=b`` the corners are
mapped to sensor pixels by ``u = b u' + (b - 1) / 2`` (the centre of the
block, pixel ``(0, 0)`` being the centre of the top-left pixel) and the
camera is returned at full sensor resolution.

References
----------
.. [1] Z. Zhang, "A flexible new technique for camera calibration", IEEE
   Trans. Pattern Anal. Mach. Intell. 22(11), 1330-1334 (2000),
   doi:10.1109/34.888718.
.. [2] OpenCV, "Camera Calibration and 3D Reconstruction" (calib3d):
   findChessboardCorners, cornerSubPix, calibrateCamera,
   https://docs.opencv.org/4.x/d9/d0c/group__calib3d.html.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.camera.model import DISTORTION_NAMES, CameraModel
from pihim.errors import PihimInputError
from pihim.render.checkerboard import checkerboard_points

__all__ = ["CALIBRATION_FLAG_NAMES", "CameraCalibration", "CalibrationView", "calibrate_camera", "detect_corners"]

#: OpenCV ``calibrateCamera`` flags understood (and reported by name) here.
CALIBRATION_FLAG_NAMES: dict[str, int] = {
    "CALIB_FIX_PRINCIPAL_POINT": cv2.CALIB_FIX_PRINCIPAL_POINT,
    "CALIB_FIX_ASPECT_RATIO": cv2.CALIB_FIX_ASPECT_RATIO,
    "CALIB_ZERO_TANGENT_DIST": cv2.CALIB_ZERO_TANGENT_DIST,
    "CALIB_FIX_K1": cv2.CALIB_FIX_K1,
    "CALIB_FIX_K2": cv2.CALIB_FIX_K2,
    "CALIB_FIX_K3": cv2.CALIB_FIX_K3,
}
_ALLOWED_FLAGS = 0
for _v in CALIBRATION_FLAG_NAMES.values():
    _ALLOWED_FLAGS |= _v

#: Stop rule of the Levenberg-Marquardt fit in calibrateCamera.
_CALIB_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
#: Stop rule of cornerSubPix (iterations, shift in px).
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-4)
#: Corners must spread over at least this fraction of a 8 x 8 grid of image cells, else a warning.
_MIN_COVERAGE = 0.5
#: Below this normalized radius of the image corners (a field of view under ~40 deg) k3 is hardly separable.
_NARROW_RADIUS = 0.3


def _flag_names(flags: int) -> list[str]:
    return [name for name, v in CALIBRATION_FLAG_NAMES.items() if flags & v]


@dataclass(frozen=True)
class CalibrationView:
    """One input image of a calibration.

    Attributes
    ----------
    name : str
        Label of the image (file name, or ``"image <k>"``).
    used : bool
        Whether its corners entered the fit.
    reason : str or None
        Why it was not used (None when used).
    corners_px : ndarray, shape (cols * rows, 2), or None
        Detected inner corners in sensor pixels, OpenCV order; None if the board was not found.
    rms_px : float or None
        Reprojection RMS of this view's corners, pixels (used views).
    max_error_px : float or None
        Largest corner reprojection error of this view, pixels.
    rvec, tvec : ndarray, shape (3,), or None
        The board pose of this view (OpenCV extrinsics, ``x_cam = R(rvec) X_board + tvec``,
        ``tvec`` in the unit of the square size, metres).
    """

    name: str
    used: bool
    reason: str | None = None
    corners_px: NDArray[np.float64] | None = None
    rms_px: float | None = None
    max_error_px: float | None = None
    rvec: NDArray[np.float64] | None = None
    tvec: NDArray[np.float64] | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the corners are left out)."""
        out: dict[str, Any] = {"name": self.name, "used": self.used, "reason": self.reason,
                               "corners_found": self.corners_px is not None}
        out["rms_px"] = None if self.rms_px is None else float(self.rms_px)
        out["max_error_px"] = None if self.max_error_px is None else float(self.max_error_px)
        out["rvec"] = None if self.rvec is None else [float(v) for v in self.rvec]
        out["tvec_m"] = None if self.tvec is None else [float(v) for v in self.tvec]
        out["distance_m"] = None if self.tvec is None else float(np.linalg.norm(self.tvec))
        return out


@dataclass(frozen=True)
class CameraCalibration:
    """Result of :func:`calibrate_camera`.

    Attributes
    ----------
    camera : CameraModel
        The calibrated camera (sensor pixels), from :meth:`CameraModel.from_opencv`.
    rms_px : float
        Overall reprojection RMS over all corners of the used views, pixels.
    views : tuple of CalibrationView
        Every input image, in input order, used or rejected.
    board : (int, int)
        Inner corners ``(cols, rows)``.
    square_m : float
        Square side, metres.
    flags : int
        OpenCV calibration flags used.
    image_binning : int
        Binning of the images relative to the sensor (2 for DoFP super-pixel S0).
    std_intrinsics : dict
        One-sigma uncertainties from ``calibrateCameraExtended`` (``fx_px``,
        ``fy_px``, ``cx_px``, ``cy_px`` and the distortion coefficients):
        OpenCV's estimate from the residuals, assuming independent corner
        errors; it understates the spread of ``k1`` when ``k2`` and ``k3``
        are fitted too (0.015 reported against 0.036 by Monte Carlo for a
        13 deg lens).
    coverage : float
        Fraction of the cells of an 8 x 8 grid over the image holding at least one used corner.
    warnings : tuple of str
    """

    camera: CameraModel
    rms_px: float
    views: tuple[CalibrationView, ...]
    board: tuple[int, int]
    square_m: float
    flags: int
    image_binning: int = 1
    std_intrinsics: dict[str, float] = field(default_factory=dict)
    coverage: float = 1.0
    warnings: tuple[str, ...] = ()

    @property
    def views_used(self) -> tuple[CalibrationView, ...]:
        """Views whose corners entered the fit."""
        return tuple(v for v in self.views if v.used)

    @property
    def views_rejected(self) -> tuple[CalibrationView, ...]:
        """Views left out, each with its ``reason``."""
        return tuple(v for v in self.views if not v.used)

    @property
    def per_view_rms_px(self) -> NDArray[np.float64]:
        """Reprojection RMS of each used view, pixels, in input order."""
        return np.array([v.rms_px for v in self.views_used], dtype=float)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record (schema ``pihim.camera/1``, ``src/pihim/schemas/camera.schema.json``).

        The top level is :meth:`CameraModel.to_dict` (so that
        :meth:`CameraModel.from_dict` reads the file back) plus ``schema``,
        ``camera_matrix``, ``distortion_coefficients`` (OpenCV's array) and
        ``rms_px``; how it was obtained is under ``calibration``. No NaN or
        infinity.
        """
        cam = self.camera
        out: dict[str, Any] = {"schema": "pihim.camera/1"}
        out.update(cam.to_dict())
        out["camera_matrix"] = [[float(v) for v in row] for row in cam.intrinsics()]
        out["distortion_coefficients"] = [float(v) for v in cam.distortion_coefficients()]
        out["rms_px"] = float(self.rms_px)
        used = self.per_view_rms_px
        out["calibration"] = {
            "method": "OpenCV chessboard: findChessboardCorners + cornerSubPix, calibrateCamera (k1 k2 p1 p2 k3)",
            "board": {"cols": self.board[0], "rows": self.board[1], "square_m": float(self.square_m)},
            "flags": _flag_names(self.flags),
            "image_binning": int(self.image_binning),
            "rms_px": float(self.rms_px),
            "max_view_rms_px": float(used.max()),
            "views_used": len(self.views_used),
            "views_rejected": len(self.views_rejected),
            "coverage": float(self.coverage),
            "std": {k: float(v) for k, v in self.std_intrinsics.items()},
            "views": [v.to_dict() for v in self.views],
            "warnings": list(self.warnings),
        }
        return out


# -- detection -------------------------------------------------------------------------------


def _check_board(board: Any) -> tuple[int, int]:
    try:
        cols, rows = board
    except (TypeError, ValueError):
        raise PihimInputError(f"board must be (cols, rows) inner corners, got {board!r}") from None
    ok = all(isinstance(n, (int, np.integer)) and not isinstance(n, bool) for n in (cols, rows))
    if not ok or cols < 3 or rows < 3:
        raise PihimInputError(f"board must have at least 3x3 inner corners (integers), got {board!r}")
    if cols == rows:
        raise PihimInputError(f"board {cols}x{rows} is square: use a board with different numbers of inner "
                              "corners per row and column (its orientation is then unambiguous)")
    return int(cols), int(rows)


def _as_image(image: ArrayLike, label: str) -> NDArray[np.float64]:
    try:
        a = np.asarray(image)
    except Exception:  # noqa: BLE001
        raise PihimInputError(f"{label}: not an image array") from None
    if a.ndim != 2 or a.dtype.kind not in "uif" or min(a.shape) < 8:
        raise PihimInputError(f"{label}: expected a 2-D grey image of at least 8x8 pixels, "
                              f"got shape {a.shape} and dtype {a.dtype}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise PihimInputError(f"{label}: image has non-finite pixels (NaN or inf)")
    return a


def _scaled(image: NDArray[np.float64]) -> tuple[NDArray[np.uint8], NDArray[np.float32]] | None:
    """8-bit and float32 versions scaled 0.5th..99.5th percentile to 0..255; None if flat."""
    lo, hi = np.percentile(image, [0.5, 99.5])
    if not hi > lo:
        return None
    f = (image - lo) * (255.0 / (hi - lo))
    return np.clip(np.rint(f), 0, 255).astype(np.uint8), f.astype(np.float32)


def detect_corners(image: ArrayLike, board: tuple[int, int], *,
                   label: str = "image") -> tuple[NDArray[np.float64] | None, str | None]:
    """Find and refine the inner corners of a chessboard in one grey image.

    Parameters
    ----------
    image : array_like, shape (H, W)
        Grey image (any real dtype, any scale: it is rescaled).
    board : (int, int)
        Inner corners ``(cols, rows)`` (OpenCV's ``patternSize``).
    label : str
        Name used in error messages.

    Returns
    -------
    corners : ndarray, shape (cols * rows, 2), or None
        ``(u, v)`` pixels of the image (pixel ``(0, 0)`` = centre of the
        top-left pixel), OpenCV order (row by row); None if not found.
    reason : str or None
        Why the board was not found.
    """
    cols, rows = _check_board(board)
    img = _as_image(image, label)
    scaled = _scaled(img)
    if scaled is None:
        return None, "blank image (no contrast)"
    img8, imgf = scaled
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    found, corners = cv2.findChessboardCorners(img8, (cols, rows), flags=flags)
    if not found or corners is None or len(corners) != cols * rows:
        return None, f"no {cols}x{rows} chessboard found"
    c = corners.reshape(rows, cols, 2).astype(np.float64)
    spacing = min(float(np.min(np.linalg.norm(np.diff(c, axis=1), axis=-1))),
                  float(np.min(np.linalg.norm(np.diff(c, axis=0), axis=-1))))
    if spacing < 6.0:
        return None, f"chessboard squares too small ({spacing:.1f} px between corners; need >= 6)"
    half = int(min(15, max(2, math.floor(spacing / 3.0))))
    refined = cv2.cornerSubPix(imgf, corners.astype(np.float32), (half, half), (-1, -1), _SUBPIX_CRITERIA)
    return refined.reshape(-1, 2).astype(np.float64), None


# -- calibration -----------------------------------------------------------------------------


def _coverage(points: NDArray[np.float64], width: int, height: int) -> float:
    cells = np.zeros((8, 8), dtype=bool)
    i = np.clip((points[:, 1] / height * 8).astype(int), 0, 7)
    j = np.clip((points[:, 0] / width * 8).astype(int), 0, 7)
    cells[i, j] = True
    return float(cells.mean())


def calibrate_camera(
    images: Sequence[ArrayLike],
    board: tuple[int, int],
    square_m: float,
    *,
    pixel_size_um: float = 3.45,
    flags: int = 0,
    image_binning: int = 1,
    names: Sequence[str] | None = None,
    max_view_rms_px: float | None = None,
    name: str = "pihim calibrate-camera",
) -> CameraCalibration:
    """Calibrate a camera (intrinsics and k1 k2 p1 p2 k3) from chessboard images.

    Parameters
    ----------
    images : sequence of array_like, each (H, W)
        Grey images of a planar chessboard in different poses (all the same
        size); 10 to 20 views spread over the image, tilted by 20 to 45 deg,
        are customary. Any real dtype and scale.
    board : (int, int)
        Inner corners ``(cols, rows)``, OpenCV's ``patternSize`` (a 9x6 board
        has 10 x 7 squares); the two must differ.
    square_m : float
        Side of a square, metres (sets the unit of the view translations only).
    pixel_size_um : float
        Sensor pixel pitch, um, to express ``fx`` as a focal length in mm.
    flags : int
        OpenCV ``calibrateCamera`` flags, a combination of
        :data:`CALIBRATION_FLAG_NAMES`; 0 (default) fits ``fx, fy, cx, cy``
        and all of ``k1, k2, p1, p2, k3``.
    image_binning : int
        Sensor pixels per image pixel along each axis (2 for the super-pixel
        S0 of a DoFP mosaic): corners are mapped to sensor pixels by
        ``u = b u' + (b - 1) / 2`` and the camera has ``b`` times the image size.
    names : sequence of str, optional
        Labels of the images in the result and messages (default ``image 0``, ...).
    max_view_rms_px : float, optional
        If given, views whose RMS exceeds it after a first fit are rejected
        and the camera is fitted again without them.
    name : str
        Name of the returned :class:`CameraModel`.

    Returns
    -------
    CameraCalibration

    Raises
    ------
    PihimInputError
        Bad arguments, images of different sizes, no image with a detectable
        board, or fewer than 3 usable views.
    """
    cols, rows = _check_board(board)
    try:
        square = float(square_m)
    except (TypeError, ValueError):
        raise PihimInputError(f"square size must be a number, got {square_m!r}") from None
    if not (math.isfinite(square) and square > 0):
        raise PihimInputError(f"square size must be positive, got {square_m!r}")
    if isinstance(flags, bool) or not isinstance(flags, (int, np.integer)) or int(flags) & ~_ALLOWED_FLAGS:
        raise PihimInputError(f"unsupported calibration flags {flags!r}; combine {', '.join(CALIBRATION_FLAG_NAMES)}")
    if isinstance(image_binning, bool) or not isinstance(image_binning, (int, np.integer)) or image_binning < 1:
        raise PihimInputError(f"image binning must be a positive integer, got {image_binning!r}")
    if max_view_rms_px is not None:
        try:
            gate = float(max_view_rms_px)
        except (TypeError, ValueError):
            gate = math.nan
        if not (math.isfinite(gate) and gate > 0):
            raise PihimInputError(f"max_view_rms_px must be a positive number of pixels, got {max_view_rms_px!r}")
    images = list(images)
    if not images:
        raise PihimInputError("no images given")
    labels = [f"image {k}" for k in range(len(images))] if names is None else [str(n) for n in names]
    if len(labels) != len(images):
        raise PihimInputError(f"got {len(labels)} names for {len(images)} images")
    arrays = [_as_image(im, lab) for im, lab in zip(images, labels)]
    shape = arrays[0].shape
    for a, lab in zip(arrays[1:], labels[1:]):
        if a.shape != shape:
            raise PihimInputError(f"images have different sizes: {labels[0]} is {shape[1]}x{shape[0]}, "
                                  f"{lab} is {a.shape[1]}x{a.shape[0]} (WxH)")
    b = int(image_binning)
    width, height = shape[1] * b, shape[0] * b

    detected: list[tuple[NDArray[np.float64] | None, str | None]] = []
    for a, lab in zip(arrays, labels):
        corners, reason = detect_corners(a, (cols, rows), label=lab)
        if corners is not None:
            corners = b * corners + 0.5 * (b - 1)
        detected.append((corners, reason))
    found = [k for k, (c, _) in enumerate(detected) if c is not None]
    if not found:
        raise PihimInputError(f"no image with a detectable {cols}x{rows} chessboard among {len(images)} "
                              f"(first: {labels[0]}: {detected[0][1]})")
    objp = checkerboard_points(cols, rows, square).astype(np.float32)

    def fit(use: list[int]) -> tuple[NDArray, NDArray, Sequence, Sequence, NDArray]:
        if len(use) < 3:
            bad = [f"{labels[k]}: {why}" for k, why in rejected.items()]
            raise PihimInputError(f"only {len(use)} usable view(s) of the {cols}x{rows} chessboard, need at least 3"
                                  + (f" ({'; '.join(bad[:3])}{'; ...' if len(bad) > 3 else ''})" if bad else ""))
        img_pts = [detected[k][0].astype(np.float32).reshape(-1, 1, 2) for k in use]  # type: ignore[union-attr]
        try:
            out = cv2.calibrateCameraExtended([objp] * len(use), img_pts, (width, height), None, None,
                                              flags=int(flags), criteria=_CALIB_CRITERIA)
        except cv2.error as exc:
            raise PihimInputError(f"OpenCV calibration failed: {' '.join(str(exc).split())[-200:]}") from None
        _, k_mat, dist, rvecs, tvecs, std_in, _, _ = out
        return k_mat, dist.ravel(), rvecs, tvecs, std_in.ravel()  # type: ignore[return-value]

    rejected: dict[int, str] = {k: why for k, (c, why) in enumerate(detected) if c is None}  # type: ignore[misc]
    use = found
    k_mat, dist, rvecs, tvecs, std_in = fit(use)
    errors = _view_errors(objp, [detected[k][0] for k in use], k_mat, dist, rvecs, tvecs)
    if max_view_rms_px is not None:
        bad = [k for k, e in zip(use, errors) if _rms(e) > max_view_rms_px]
        if bad:
            for k, e in zip(use, errors):
                if k in bad:
                    rejected[k] = f"reprojection RMS {_rms(e):.3f} px > {float(max_view_rms_px):g} px"
            use = [k for k in use if k not in bad]
            k_mat, dist, rvecs, tvecs, std_in = fit(use)
            errors = _view_errors(objp, [detected[k][0] for k in use], k_mat, dist, rvecs, tvecs)

    dist5 = np.zeros(5)
    dist5[:min(5, dist.size)] = dist[:5]
    camera = CameraModel.from_opencv(k_mat, dist5, (width, height), pixel_size_um=pixel_size_um, name=name)
    rms = _rms(np.concatenate(errors))
    views: list[CalibrationView] = []
    pos = {k: j for j, k in enumerate(use)}
    for k, lab in enumerate(labels):
        corners = detected[k][0]
        if k in pos:
            j = pos[k]
            e = errors[j]
            views.append(CalibrationView(lab, True, None, corners, _rms(e), float(np.max(np.linalg.norm(e, axis=1))),
                                         np.asarray(rvecs[j], float).ravel(), np.asarray(tvecs[j], float).ravel()))
        else:
            views.append(CalibrationView(lab, False, rejected[k], corners))
    std_names = ("fx_px", "fy_px", "cx_px", "cy_px", *DISTORTION_NAMES)
    std = {n: float(v) for n, v in zip(std_names, std_in) if math.isfinite(float(v))}
    used_pts = np.concatenate([detected[k][0] for k in use])  # type: ignore[misc]
    coverage = _coverage(used_pts, width, height)
    warnings: list[str] = []
    if coverage < _MIN_COVERAGE:
        warnings.append(f"the board corners cover only {100 * coverage:.0f}% of the image (8x8 cells); "
                        "distortion is poorly constrained where there are none")
    r_max = _corner_radius(camera)
    if not flags & cv2.CALIB_FIX_K3 and r_max < _NARROW_RADIUS:
        k1, k2, _, _, k3 = camera.distortion
        warnings.append(f"narrow field of view (image corners at normalized radius {r_max:.2f}): k1, k2 and k3 "
                        f"trade off against each other (fitted {k1:+.3g}, {k2:+.3g}, {k3:+.3g}); "
                        "consider fixing k3 (--fix-k3, CALIB_FIX_K3)")
    if len(use) < 6:
        warnings.append(f"only {len(use)} views used; 10 or more in varied tilts are recommended")
    return CameraCalibration(camera=camera, rms_px=rms, views=tuple(views), board=(cols, rows), square_m=square,
                             flags=int(flags), image_binning=b, std_intrinsics=std, coverage=coverage,
                             warnings=tuple(warnings))


def _corner_radius(camera: CameraModel) -> float:
    """Largest normalized (undistorted-scale) radius of the image corners, ``|((u - cx) / fx, (v - cy) / fy)|``."""
    u = np.array([-0.5, camera.width_px - 0.5])
    v = np.array([-0.5, camera.height_px - 0.5])
    x = (u[:, None] - camera.cx_px) / camera.fx_px
    y = (v[None, :] - camera.cy_px) / camera.fy_px
    return float(np.sqrt(x**2 + y**2).max())


def _rms(e: NDArray[np.float64]) -> float:
    """RMS length of 2-D residuals, shape (N, 2): ``sqrt(sum |e|^2 / N)`` (OpenCV's reprojection error)."""
    return math.sqrt(float(np.sum(e**2)) / e.shape[0])


def _view_errors(objp: NDArray, corners: list, k_mat: NDArray, dist: NDArray, rvecs: Sequence,
                 tvecs: Sequence) -> list[NDArray[np.float64]]:
    """Reprojection residuals (detected - projected), shape (N, 2) per view."""
    out = []
    for c, rv, tv in zip(corners, rvecs, tvecs):
        proj, _ = cv2.projectPoints(objp, rv, tv, k_mat, dist)
        out.append(np.asarray(c, float).reshape(-1, 2) - proj.reshape(-1, 2))
    return out
