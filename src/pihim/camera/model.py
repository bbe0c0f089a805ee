"""Pinhole camera model of the inspection camera: intrinsics, lens distortion, projection.

The model is OpenCV's [1]_: camera axes x right, y down, z forward; a
camera-frame point ``(X, Y, Z)`` with ``Z > 0`` has normalized coordinates
``x = X / Z``, ``y = Y / Z``, distorted by the Brown-Conrady model (radial
``k1, k2, k3`` and tangential ``p1, p2``, in OpenCV's order
``(k1, k2, p1, p2, k3)``) and mapped to pixels by
``u = fx xd + cx``, ``v = fy yd + cy``. Pixel ``(0, 0)`` is the centre of the
top-left pixel, so the sensor centre is ``((W - 1) / 2, (H - 1) / 2)``.

References
----------
.. [1] OpenCV, "Camera Calibration and 3D Reconstruction" (calib3d module),
   https://docs.opencv.org/4.x/d9/d0c/group__calib3d.html.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim._inputs import finite_number
from pihim.errors import PihimInputError

__all__ = ["DISTORTION_NAMES", "CameraModel", "camera_for_size"]

#: Names of the distortion coefficients, in OpenCV's order.
DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3")


@dataclass(frozen=True)
class CameraModel:
    """A pinhole camera: sensor size, pixel pitch, lens focal length, principal point and distortion.

    Defaults: Lucid Triton TRI050S-PC (Sony IMX250MZR, 2448 x 2048 px,
    3.45 um pixels) with the paper's 35 mm Kowa lens (paper section 2), no
    distortion, principal point at the sensor centre, square pixels.
    Camera axes follow OpenCV: x right, y down, z forward.

    Attributes
    ----------
    width_px, height_px : int
        Sensor size, pixels (columns, rows).
    pixel_size_um : float
        Pixel pitch along x, micrometres.
    focal_length_mm : float
        Lens focal length, millimetres; ``fx = focal_length_mm * 1000 / pixel_size_um`` pixels.
    name : str
        Free-text label.
    principal_point_px : tuple of float or None
        ``(cx, cy)``, pixels; None is the sensor centre ``((W - 1) / 2, (H - 1) / 2)``.
    distortion : tuple of 5 float
        Brown-Conrady coefficients in OpenCV's order ``(k1, k2, p1, p2, k3)``
        (dimensionless, for normalized coordinates); zeros = no distortion.
    pixel_aspect : float
        ``fy / fx`` (1 for square pixels).
    """

    width_px: int = 2448
    height_px: int = 2048
    pixel_size_um: float = 3.45
    focal_length_mm: float = 35.0
    name: str = "Lucid Triton TRI050S-PC + 35 mm"
    principal_point_px: tuple[float, float] | None = None
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    pixel_aspect: float = 1.0

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            object.__setattr__(self, name, _whole_pixels(name, getattr(self, name)))
        if self.width_px < 2 or self.height_px < 2:
            raise PihimInputError("camera sensor must be at least 2x2 pixels")
        if not (self.pixel_size_um > 0 and self.focal_length_mm > 0):
            raise PihimInputError("pixel size and focal length must be positive")
        finite_number(self.pixel_size_um, "pixel size (um)")
        finite_number(self.focal_length_mm, "focal length (mm)")
        aspect = finite_number(self.pixel_aspect, "pixel aspect fy/fx")
        if aspect <= 0:
            raise PihimInputError(f"pixel aspect fy/fx must be positive, got {aspect:g}")
        object.__setattr__(self, "pixel_aspect", aspect)
        if self.principal_point_px is not None:
            pp = np.asarray(self.principal_point_px, dtype=object).ravel()
            if pp.size != 2:
                raise PihimInputError(f"principal point must be (cx, cy) in pixels, got {self.principal_point_px!r}")
            object.__setattr__(self, "principal_point_px",
                               (finite_number(pp[0], "principal point cx"), finite_number(pp[1], "principal point cy")))
        try:
            coeffs = tuple(self.distortion)
        except TypeError:
            raise PihimInputError(f"distortion must be 5 coefficients (k1, k2, p1, p2, k3), got {self.distortion!r}") \
                from None
        if len(coeffs) != 5:
            raise PihimInputError(
                f"distortion must be 5 coefficients (k1, k2, p1, p2, k3) in OpenCV's order, got {len(coeffs)}")
        object.__setattr__(self, "distortion",
                           tuple(finite_number(c, f"distortion coefficient {n}") for c, n in zip(coeffs, DISTORTION_NAMES)))

    # --- intrinsics ---------------------------------------------------------------------------

    @property
    def focal_length_px(self) -> float:
        """Focal length in pixels along x (``fx``)."""
        return self.focal_length_mm * 1000.0 / self.pixel_size_um

    @property
    def fx_px(self) -> float:
        """Focal length along x, pixels."""
        return self.focal_length_px

    @property
    def fy_px(self) -> float:
        """Focal length along y, pixels (``fx * pixel_aspect``)."""
        return self.focal_length_px * self.pixel_aspect

    @property
    def cx_px(self) -> float:
        """Principal point column, pixels."""
        return (self.width_px - 1) / 2.0 if self.principal_point_px is None else self.principal_point_px[0]

    @property
    def cy_px(self) -> float:
        """Principal point row, pixels."""
        return (self.height_px - 1) / 2.0 if self.principal_point_px is None else self.principal_point_px[1]

    @property
    def horizontal_fov_deg(self) -> float:
        """Full horizontal field of view of the pinhole (distortion ignored), deg."""
        return math.degrees(2.0 * math.atan(0.5 * self.width_px / self.focal_length_px))

    @property
    def vertical_fov_deg(self) -> float:
        """Full vertical field of view of the pinhole (distortion ignored), deg."""
        return math.degrees(2.0 * math.atan(0.5 * self.height_px / self.fy_px))

    def intrinsics(self) -> NDArray[np.float64]:
        """OpenCV camera matrix ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, pixels."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    def distortion_coefficients(self) -> NDArray[np.float64]:
        """Distortion coefficients, shape (5,), OpenCV order ``(k1, k2, p1, p2, k3)``."""
        return np.array(self.distortion, dtype=float)

    def ground_sample_distance_m(self, range_m: float) -> float:
        """Size of one pixel at ``range_m`` metres, m."""
        return range_m * self.pixel_size_um * 1e-6 / (self.focal_length_mm * 1e-3)

    # --- distortion ---------------------------------------------------------------------------

    def distort_normalized(self, x: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Apply the Brown-Conrady distortion to normalized coordinates.

        With ``r2 = x^2 + y^2``:
        ``xd = x (1 + k1 r2 + k2 r2^2 + k3 r2^3) + 2 p1 x y + p2 (r2 + 2 x^2)``,
        ``yd = y (1 + k1 r2 + k2 r2^2 + k3 r2^3) + p1 (r2 + 2 y^2) + 2 p2 x y``
        (OpenCV's model restricted to five coefficients).

        Parameters
        ----------
        x, y : array_like
            Undistorted normalized coordinates (``X / Z``, ``Y / Z``), broadcast together.

        Returns
        -------
        xd, yd : ndarray
            Distorted normalized coordinates.
        """
        x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        k1, k2, p1, p2, k3 = self.distortion
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy2 = 2.0 * x * y
        xd = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2
        return xd, yd

    def undistort_normalized(self, xd: ArrayLike, yd: ArrayLike, *, iterations: int = 20,
                             tol: float = 1e-13) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Invert :meth:`distort_normalized` by Newton iteration, vectorised.

        Parameters
        ----------
        xd, yd : array_like
            Distorted normalized coordinates (``(u - cx) / fx``, ``(v - cy) / fy``), broadcast together.
        iterations : int
            Maximum number of Newton steps (each point stops once converged).
        tol : float
            Convergence threshold on the re-distorted residual, normalized units.

        Returns
        -------
        x, y : ndarray
            Undistorted normalized coordinates. Points where the iteration does
            not reach ``tol`` within ``iterations`` steps (outside the region
            where the lens model is invertible) are NaN.

        Notes
        -----
        Starts from ``(xd, yd)`` and solves ``distort(x, y) = (xd, yd)`` with
        the analytic 2x2 Jacobian. Newton converges quadratically: for real
        lenses (``|k1 r2|`` up to a few tenths) three to five steps reach
        1e-15, where OpenCV's fixed-point ``undistortPoints`` converges only
        linearly.
        """
        xd, yd = np.broadcast_arrays(np.asarray(xd, dtype=float), np.asarray(yd, dtype=float))
        if not isinstance(iterations, (int, np.integer)) or isinstance(iterations, bool) or iterations < 1:
            raise PihimInputError(f"iterations must be a positive integer, got {iterations!r}")
        if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol > 0):
            raise PihimInputError(f"tol must be a positive number, got {tol!r}")
        if not any(self.distortion):
            return xd.copy(), yd.copy()
        k1, k2, p1, p2, k3 = self.distortion
        x, y = xd.copy(), yd.copy()
        with np.errstate(all="ignore"):
            for _ in range(int(iterations)):
                ex, ey = self.distort_normalized(x, y)
                ex -= xd
                ey -= yd
                settled = ((np.abs(ex) <= tol) & (np.abs(ey) <= tol)) | ~np.isfinite(ex) | ~np.isfinite(ey)
                if np.all(settled):
                    break
                r2 = x * x + y * y
                radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
                jxx = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
                jyy = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
                jxy = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y  # d xd / d y == d yd / d x
                det = jxx * jyy - jxy * jxy
                x = x - (jyy * ex - jxy * ey) / det
                y = y - (jxx * ey - jxy * ex) / det
            ex, ey = self.distort_normalized(x, y)
            bad = ~((np.abs(ex - xd) <= max(tol, 1e-12)) & (np.abs(ey - yd) <= max(tol, 1e-12)))
        return np.where(bad, np.nan, x), np.where(bad, np.nan, y)

    # --- projection ---------------------------------------------------------------------------

    def project(self, points_cam: ArrayLike) -> NDArray[np.float64]:
        """Pixels of camera-frame points.

        Parameters
        ----------
        points_cam : array_like, shape (..., 3)
            Points in the camera frame (x right, y down, z forward), any length unit.

        Returns
        -------
        ndarray, shape (..., 2)
            ``(u, v)`` pixels (column, row); NaN for points with ``z <= 0``
            (at or behind the camera) and for non-finite points. No field of
            view test: points outside the sensor get pixels outside it.
        """
        p = np.asarray(points_cam, dtype=float)
        if p.ndim < 1 or p.shape[-1] != 3:
            raise PihimInputError(f"camera-frame points must have shape (..., 3), got {p.shape}")
        z = p[..., 2]
        front = z > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = np.where(front, p[..., 0] / z, np.nan)
            yn = np.where(front, p[..., 1] / z, np.nan)
        xd, yd = self.distort_normalized(xn, yn) if any(self.distortion) else (xn, yn)
        return np.stack([self.fx_px * xd + self.cx_px, self.fy_px * yd + self.cy_px], axis=-1)

    def pixel_rays(self, u: ArrayLike, v: ArrayLike) -> NDArray[np.float64]:
        """Unit viewing rays of pixels, in the camera frame (inverse of :meth:`project` up to scale).

        Parameters
        ----------
        u, v : array_like
            Pixel column and row (broadcast together); ``(0, 0)`` is the centre of the top-left pixel.

        Returns
        -------
        ndarray, shape (..., 3)
            Unit directions ``(x, y, 1) / |(x, y, 1)|`` with ``(x, y)`` the
            undistorted normalized coordinates; NaN where the distortion
            cannot be inverted.
        """
        u, v = np.broadcast_arrays(np.asarray(u, dtype=float), np.asarray(v, dtype=float))
        x, y = self.undistort_normalized((u - self.cx_px) / self.fx_px, (v - self.cy_px) / self.fy_px)
        d = np.stack([x, y, np.ones_like(x)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    # --- construction and serialisation ---------------------------------------------------------

    @classmethod
    def from_opencv(cls, camera_matrix: ArrayLike, dist_coeffs: ArrayLike | None, image_size_wh: tuple[int, int],
                    pixel_size_um: float = 3.45, name: str = "OpenCV calibration") -> CameraModel:
        """A camera from an OpenCV calibration (``cv2.calibrateCamera`` output).

        Parameters
        ----------
        camera_matrix : array_like, shape (3, 3)
            ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, pixels (no skew).
        dist_coeffs : array_like or None
            4, 5, 8, 12 or 14 coefficients in OpenCV's order; those beyond
            ``k3`` (rational, thin-prism and tilt terms) must be zero. None or
            empty: no distortion.
        image_size_wh : (int, int)
            Image width and height, pixels.
        pixel_size_um : float
            Pixel pitch, um (only used to express ``fx`` as ``focal_length_mm``).
        name : str

        Returns
        -------
        CameraModel
            ``focal_length_mm = fx * pixel_size_um / 1000``, ``pixel_aspect = fy / fx``.
        """
        k = np.asarray(camera_matrix, dtype=float)
        if k.shape != (3, 3) or not np.all(np.isfinite(k)):
            raise PihimInputError(f"camera matrix must be a finite 3x3 array, got shape {k.shape}")
        if k[0, 1] != 0.0 or k[1, 0] != 0.0 or np.any(k[2] != (0.0, 0.0, 1.0)):
            raise PihimInputError("camera matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
        fx, fy = float(k[0, 0]), float(k[1, 1])
        if not (fx > 0 and fy > 0):
            raise PihimInputError(f"camera matrix focal lengths must be positive, got fx={fx:g}, fy={fy:g}")
        d = np.zeros(0) if dist_coeffs is None else np.asarray(dist_coeffs, dtype=float).ravel()
        if d.size not in (0, 4, 5, 8, 12, 14):
            raise PihimInputError(f"OpenCV distortion must have 4, 5, 8, 12 or 14 coefficients, got {d.size}")
        if not np.all(np.isfinite(d)):
            raise PihimInputError("distortion coefficients must be finite")
        if d.size > 5 and np.any(d[5:] != 0.0):
            raise PihimInputError("only the distortion coefficients k1, k2, p1, p2, k3 are supported; "
                                  f"coefficients 6 to {d.size} (rational, thin-prism, tilt) must be zero")
        coeffs = np.zeros(5)
        coeffs[:min(5, d.size)] = d[:5]
        try:
            w, h = (int(image_size_wh[0]), int(image_size_wh[1]))
        except (TypeError, ValueError, IndexError):
            raise PihimInputError(f"image size must be (width, height) in pixels, got {image_size_wh!r}") from None
        ps = finite_number(pixel_size_um, "pixel size (um)")
        return cls(width_px=w, height_px=h, pixel_size_um=ps, focal_length_mm=fx * ps / 1000.0, name=str(name),
                   principal_point_px=(float(k[0, 2]), float(k[1, 2])),
                   distortion=tuple(float(c) for c in coeffs), pixel_aspect=fy / fx)  # type: ignore[arg-type]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (plain floats, ints and strings).

        Returns
        -------
        dict
            ``width_px``, ``height_px``, ``pixel_size_um``, ``focal_length_mm``,
            ``fx_px``, ``fy_px``, ``cx_px``, ``cy_px``, ``pixel_aspect``,
            ``distortion`` (``{"k1", "k2", "p1", "p2", "k3"}``) and ``name``.
        """
        return {
            "width_px": int(self.width_px),
            "height_px": int(self.height_px),
            "pixel_size_um": float(self.pixel_size_um),
            "focal_length_mm": float(self.focal_length_mm),
            "fx_px": float(self.fx_px),
            "fy_px": float(self.fy_px),
            "cx_px": float(self.cx_px),
            "cy_px": float(self.cy_px),
            "pixel_aspect": float(self.pixel_aspect),
            "distortion": {n: float(c) for n, c in zip(DISTORTION_NAMES, self.distortion)},
            "name": str(self.name),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> CameraModel:
        """Inverse of :meth:`to_dict`.

        Parameters
        ----------
        data : mapping
            ``width_px``, ``height_px``, ``pixel_size_um`` and
            ``focal_length_mm`` (or ``fx_px``) are required. Optional:
            ``pixel_aspect`` (else ``fy_px / fx_px``, else 1), ``cx_px`` and
            ``cy_px`` (else the sensor centre), ``distortion`` as
            ``{"k1", ...}`` or a list of 5 (else none), ``name``. When both
            ``focal_length_mm`` and ``fx_px`` (or ``fy_px``) are given they
            must agree to 1e-9 relative.

        Returns
        -------
        CameraModel
            Equal to the camera that wrote ``data``.
        """
        if not isinstance(data, Mapping):
            raise PihimInputError(f"a camera description must be a mapping, got {type(data).__name__}")
        for key in ("width_px", "height_px", "pixel_size_um"):
            if key not in data:
                raise PihimInputError(f"camera description has no '{key}'")
        width, height = data["width_px"], data["height_px"]
        if not all(isinstance(n, (int, float)) and not isinstance(n, bool) and float(n).is_integer()
                   for n in (width, height)):
            raise PihimInputError(f"camera width_px and height_px must be integers, got {width!r}, {height!r}")
        ps = finite_number(data["pixel_size_um"], "camera pixel_size_um")
        if "focal_length_mm" in data:
            f_mm = finite_number(data["focal_length_mm"], "camera focal_length_mm")
        elif "fx_px" in data:
            f_mm = finite_number(data["fx_px"], "camera fx_px") * ps / 1000.0
        else:
            raise PihimInputError("camera description has neither 'focal_length_mm' nor 'fx_px'")
        fx = f_mm * 1000.0 / ps
        if "pixel_aspect" in data:
            aspect = finite_number(data["pixel_aspect"], "camera pixel_aspect")
        elif "fy_px" in data:
            aspect = finite_number(data["fy_px"], "camera fy_px") / fx
        else:
            aspect = 1.0
        for key, expected in (("fx_px", fx), ("fy_px", fx * aspect)):
            if key in data and abs(finite_number(data[key], f"camera {key}") - expected) > 1e-9 * abs(expected):
                raise PihimInputError(f"camera {key} = {float(data[key])!r} disagrees with focal_length_mm, "
                                      f"pixel_size_um and pixel_aspect (expected {expected!r})")
        pp: tuple[float, float] | None = None
        if ("cx_px" in data) != ("cy_px" in data):
            raise PihimInputError("camera description must give both cx_px and cy_px, or neither")
        if "cx_px" in data:
            pp = (finite_number(data["cx_px"], "camera cx_px"), finite_number(data["cy_px"], "camera cy_px"))
            if pp == ((int(width) - 1) / 2.0, (int(height) - 1) / 2.0):
                pp = None  # the default: keep the round trip exact
        dist = data.get("distortion", None)
        if dist is None:
            coeffs: tuple[Any, ...] = (0.0,) * 5
        elif isinstance(dist, Mapping):
            unknown = set(dist) - set(DISTORTION_NAMES)
            if unknown:
                raise PihimInputError(f"unknown distortion coefficient(s) {sorted(unknown)}; "
                                      f"expected {', '.join(DISTORTION_NAMES)}")
            coeffs = tuple(dist.get(n, 0.0) for n in DISTORTION_NAMES)
        else:
            coeffs = tuple(dist) if isinstance(dist, (list, tuple)) else (dist,)
        extra = {"name": str(data["name"])} if "name" in data else {}
        return cls(width_px=int(width), height_px=int(height), pixel_size_um=ps, focal_length_mm=f_mm,
                   principal_point_px=pp, distortion=coeffs, pixel_aspect=aspect, **extra)  # type: ignore[arg-type]


def _whole_pixels(name: str, v: Any) -> int:
    """A sensor dimension as an int: 1224 or 1224.0 (from a JSON file) are whole, NaN, 3.5, '100' and True not."""
    whole = isinstance(v, (int, np.integer)) or (isinstance(v, (float, np.floating)) and float(v).is_integer())
    if isinstance(v, bool) or not whole:
        raise PihimInputError(f"camera {name} must be a whole number of pixels, got {v!r}")
    return int(v)


def camera_for_size(width: int, height: int) -> CameraModel:
    """The default camera (Triton + 35 mm) at another pixel count, with the same horizontal field of view.

    The focal length is scaled with the width (pixel pitch unchanged), so a
    small frame sees what the full frame sees, with fewer pixels.

    Parameters
    ----------
    width, height : int
        Frame size, pixels.
    """
    width, height = _whole_pixels("width_px", width), _whole_pixels("height_px", height)
    full = CameraModel()
    if (width, height) == (full.width_px, full.height_px):
        return full
    return CameraModel(width_px=width, height_px=height, focal_length_mm=full.focal_length_mm * width / full.width_px,
                       name=f"{full.name}, scaled to {width}x{height} (same horizontal FOV)")
