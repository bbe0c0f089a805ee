"""Synthetic checkerboard frames with known camera ground truth (for camera calibration).

A planar chessboard target is imaged by a :class:`~pihim.camera.CameraModel`
(pinhole + OpenCV distortion) at a :class:`~pihim.camera.CameraPose`. The
frames are what :func:`pihim.inspection.calibration.calibrate_camera` is
tested on, so they are rendered without any shortcut through the lens model
that the calibration fits:

* every pixel is split into ``n x n`` strata with one sub-sample each, in
  an n-rooks arrangement (all ``n**2`` sub-samples on distinct columns and
  rows, see :func:`_sample_offsets`; pixel ``(0, 0)`` is the centre of the
  top-left pixel, as in docs/conventions.md);
* each sub-sample is back-projected through the lens
  (:meth:`CameraModel.pixel_rays`: Newton inversion of the distortion) and
  the pose into a ray, intersected with the board plane ``z = 0`` and given
  the colour of the square it lands in;
* the pixel value is the mean of its sub-samples (a box-filtered,
  antialiased image: an edge crossing a pixel gives the covered fraction to
  ``1 / n**2``, so corners are placed to a small fraction of a pixel).

Pixels whose four corners see one uniform cell of the board (between square
edges) take that colour without sub-sampling, which is exact (see
:func:`render_checkerboard`); only the pixels along edges are sub-sampled.

Board frame (the "world" of the pose): ``x`` along the board's columns,
``y`` along its rows, ``z = x cross y``; the board lies in ``z = 0``. The
``cols x rows`` *inner* corners (OpenCV's ``patternSize``) are at
``(i * square, j * square, 0)``, ``i = 0 .. cols - 1`` varying fastest
(:func:`checkerboard_points`, the object points of ``cv2.calibrateCamera``).
The board therefore has ``(cols + 1) x (rows + 1)`` squares covering
``[-square, cols * square] x [-square, rows * square]``; the square holding
the corner ``(-square, -square)`` is dark. Around the squares runs a white
margin (``margin_squares`` squares wide, the quiet zone corner detectors
need); beyond it, and for rays that miss the plane, a uniform background.

Radiometry: ``S0`` is in units of the white paper (white = 1, dark squares
``1 - contrast``, background ``background``). With ``polarized=True`` the
surfaces also carry linear polarization (matte white paper weakly polarized,
dark print more so, the background differently again), so that a
calibration run on ``S0`` from a DoFP mosaic is checked to ignore it. With a
:class:`~pihim.render.sensor.SensorModel` the Stokes image is also exposed
into a raw 12-bit DoFP mosaic with the sensor's shot and read noise
(:func:`pihim.render.sensor.expose`), i.e. what the Triton would record.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.camera.model import CameraModel
from pihim.camera.pose import CameraPose, project_points
from pihim._inputs import finite_number
from pihim.errors import PihimInputError
from pihim.render.sensor import Exposure, SensorModel, choose_exposure, expose, lens_blur

__all__ = [
    "CheckerboardFrame",
    "board_view_pose",
    "checkerboard_points",
    "render_checkerboard",
]

#: Linear polarization (DoLP, AoP deg) of white paper, dark print and background with ``polarized=True``.
POLARIZATION = {"white": (0.03, 10.0), "dark": (0.25, 35.0), "background": (0.12, 100.0)}

#: Sub-samples processed at once (bounds the temporaries to some tens of MB).
_BAND_SAMPLES = 500_000


def _board_size(cols: Any, rows: Any) -> tuple[int, int]:
    ok = all(isinstance(n, (int, np.integer)) and not isinstance(n, bool) for n in (cols, rows))
    if not ok or int(cols) < 2 or int(rows) < 2:
        raise PihimInputError(f"board must have at least 2x2 inner corners (integers), got {cols!r}x{rows!r}")
    return int(cols), int(rows)


def _positive(value: Any, what: str) -> float:
    x = finite_number(value, what)
    if not x > 0:
        raise PihimInputError(f"{what} must be a positive finite number, got {value!r}")
    return x


def checkerboard_points(cols: int, rows: int, square_m: float) -> NDArray[np.float64]:
    """Inner corners of a ``cols x rows`` chessboard in the board frame, OpenCV order.

    Parameters
    ----------
    cols, rows : int
        Inner corners per row and per column (OpenCV's ``patternSize =
        (cols, rows)``; a board of ``(cols + 1) x (rows + 1)`` squares).
    square_m : float
        Side of a square, metres (any length unit: it sets the unit of the poses).

    Returns
    -------
    ndarray, shape (cols * rows, 3)
        ``(i * square_m, j * square_m, 0)`` with ``i`` (column) varying
        fastest, row ``j`` after row: the object points of
        ``cv2.calibrateCamera`` for the corners ``cv2.findChessboardCorners``
        returns.
    """
    c, r = _board_size(cols, rows)
    s = _positive(square_m, "square size")
    jj, ii = np.mgrid[0:r, 0:c]
    return np.stack([ii.ravel() * s, jj.ravel() * s, np.zeros(c * r)], axis=-1).astype(np.float64)


def board_view_pose(cols: int, rows: int, square_m: float, *, distance_m: float, yaw_deg: float = 0.0,
                    pitch_deg: float = 0.0, roll_deg: float = 0.0,
                    target_offset_m: ArrayLike = (0.0, 0.0)) -> CameraPose:
    """A camera pose looking at the board (board frame as the world), for calibration views.

    The frontal view has the camera axes equal to the board axes (image
    right = board x, image down = board y, optical axis = board z) with the
    camera ``distance_m`` in front of the aim point. The camera is then swung
    about the aim point: the camera axes are the columns of
    ``Ry(yaw) Rx(pitch) Rz(roll)`` (board-frame rotations: yaw about the
    board's y axis, pitch about its x axis, roll about the optical axis).

    Parameters
    ----------
    cols, rows : int
        Inner corners (the aim point defaults to the centre of the corner grid).
    square_m : float
        Square side, metres.
    distance_m : float
        Distance from the camera centre to the aim point along the optical axis, metres.
    yaw_deg, pitch_deg, roll_deg : float
        Swing of the view, deg.
    target_offset_m : (float, float)
        Aim point offset from the centre of the corner grid, in the board plane, metres.

    Returns
    -------
    CameraPose
        ``x_cam = R (X_board - C)``; ``rvec_tvec()`` are OpenCV's extrinsics of the board.
    """
    c, r = _board_size(cols, rows)
    s = _positive(square_m, "square size")
    d = _positive(distance_m, "distance")
    off = np.asarray(target_offset_m, dtype=float).ravel()
    if off.shape != (2,) or not np.all(np.isfinite(off)):
        raise PihimInputError(f"target offset must be two finite numbers (x, y) in metres, got {target_offset_m!r}")
    y, p, q = (math.radians(finite_number(a, name))
               for a, name in ((yaw_deg, "yaw"), (pitch_deg, "pitch"), (roll_deg, "roll")))
    ry = np.array([[math.cos(y), 0.0, math.sin(y)], [0.0, 1.0, 0.0], [-math.sin(y), 0.0, math.cos(y)]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(p), -math.sin(p)], [0.0, math.sin(p), math.cos(p)]])
    rz = np.array([[math.cos(q), -math.sin(q), 0.0], [math.sin(q), math.cos(q), 0.0], [0.0, 0.0, 1.0]])
    axes = ry @ rx @ rz  # columns: camera right, down, forward in the board frame
    target = np.array([0.5 * (c - 1) * s + off[0], 0.5 * (r - 1) * s + off[1], 0.0])
    return CameraPose(position_m=target - d * axes[:, 2], rotation=axes.T)


@dataclass(frozen=True)
class CheckerboardFrame:
    """A rendered checkerboard view and its ground truth.

    Attributes
    ----------
    s0, s1, s2 : ndarray, shape (H, W), float64
        Noise-free Stokes image, white paper = 1 (``s1 = s2 = 0`` unless polarized).
    corners_px : ndarray, shape (cols * rows, 2)
        True ``(u, v)`` pixels of the inner corners, :func:`pihim.camera.project_points`
        of :func:`checkerboard_points` (``cv2.projectPoints``), in OpenCV order.
    outline_px : ndarray, shape (64, 2)
        Pixels of 64 points along the outer edge of the squares (16 per side).
    raw : ndarray of uint16, shape (H, W), or None
        The DoFP mosaic the sensor records (shot and read noise), when a sensor was given.
    exposure : Exposure or None
        The exposure used for ``raw``.
    """

    s0: NDArray[np.float64]
    s1: NDArray[np.float64]
    s2: NDArray[np.float64]
    corners_px: NDArray[np.float64]
    outline_px: NDArray[np.float64]
    raw: NDArray[np.uint16] | None = None
    exposure: Exposure | None = None

    def board_inside(self, border_px: float = 2.0) -> bool:
        """True when all the squares lie at least ``border_px`` inside the image (the board is detectable whole)."""
        h, w = self.s0.shape
        p = self.outline_px
        return bool(np.all(np.isfinite(p)) and p[:, 0].min() >= border_px - 0.5 and p[:, 1].min() >= border_px - 0.5
                    and p[:, 0].max() <= w - 0.5 - border_px and p[:, 1].max() <= h - 0.5 - border_px)


def _sample_offsets(n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Sub-sample offsets ``(du, dv)`` from the pixel centre, each shape (n, n) (row stratum, column stratum).

    One sample per cell of an ``n x n`` grid over the pixel, placed in an
    n-rooks pattern: the sample of row stratum ``a``, column stratum ``b`` is
    at ``du = (b + (a + 0.5) / n) / n - 0.5``, ``dv = (a + (b + 0.5) / n) / n - 0.5``,
    so that the ``n**2`` samples have distinct columns and distinct rows. A
    pixel-aligned edge is then resolved to ``1 / n**2`` of a pixel instead of
    the ``1 / n`` of a plain grid.
    """
    a, b = np.mgrid[0:n, 0:n].astype(np.float64)
    return (b + (a + 0.5) / n) / n - 0.5, (a + (b + 0.5) / n) / n - 0.5


@functools.lru_cache(maxsize=2)
def _corner_directions(camera: CameraModel) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Undistorted normalized coordinates of the pixel corners, shape (H + 1, W + 1) each (cached)."""
    u = np.arange(camera.width_px + 1) - 0.5
    v = np.arange(camera.height_px + 1) - 0.5
    rays = camera.pixel_rays(u[None, :], v[:, None])
    with np.errstate(invalid="ignore", divide="ignore"):
        x, y = rays[..., 0] / rays[..., 2], rays[..., 1] / rays[..., 2]
    x.setflags(write=False)
    y.setflags(write=False)
    return x, y


class _Board:
    """The board's colours as a function of normalized camera coordinates, for one pose.

    Classes: 0 white (paper and margin), 1 dark square, 2 background (beyond
    the margin, or the ray misses the plane). The board plane is cut by the
    lines ``x = k`` and ``y = k`` (in squares) of the square edges and the
    margin's outer edges into convex rectangular cells of one colour each;
    :meth:`cells` numbers them.
    """

    def __init__(self, pose: CameraPose, cols: int, rows: int, square_m: float, margin_squares: float) -> None:
        self.r = np.asarray(pose.rotation, dtype=np.float64)
        self.c = np.asarray(pose.position_m, dtype=np.float64)
        self.square = square_m
        m = margin_squares
        # squares cover [-1, cols] x [-1, rows] (in squares), the margin [-1 - m, cols + m] x [-1 - m, rows + m]
        self.bx = np.unique(np.concatenate([[-1.0 - m], np.arange(-1.0, cols + 1.0), [cols + m]]))
        self.by = np.unique(np.concatenate([[-1.0 - m], np.arange(-1.0, rows + 1.0), [rows + m]]))
        # colour of every cell (interval ix of bx, iy of by; 0 and len are the unbounded ends)
        mid_x = self._midpoints(self.bx)
        mid_y = self._midpoints(self.by)
        gx, gy = np.meshgrid(mid_x, mid_y, indexing="ij")
        on_board = (gx >= -1.0 - m) & (gx < cols + m) & (gy >= -1.0 - m) & (gy < rows + m)
        in_squares = (gx >= -1.0) & (gx < cols) & (gy >= -1.0) & (gy < rows)
        dark = in_squares & ((np.floor(gx) + np.floor(gy)) % 2.0 == 0.0)  # the square at (-1, -1) is dark
        self.table = np.where(dark, 1, np.where(on_board, 0, 2)).astype(np.int8)
        self.ny = len(self.by) + 1

    @staticmethod
    def _midpoints(b: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.concatenate([[b[0] - 1.0], 0.5 * (b[:-1] + b[1:]), [b[-1] + 1.0]])

    def cells(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.int64]:
        """Cell number of the board point seen along normalized ``(x, y)``; -1 where the ray misses the plane."""
        r, c = self.r, self.c
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            # world direction d = R^T (x, y, 1) = x R[0] + y R[1] + R[2]; the plane is z = 0
            dz = x * r[0, 2] + y * r[1, 2] + r[2, 2]
            t = -c[2] / dz
            gx = (c[0] + t * (x * r[0, 0] + y * r[1, 0] + r[2, 0])) / self.square
            gy = (c[1] + t * (x * r[0, 1] + y * r[1, 1] + r[2, 1])) / self.square
            hit = (t > 0) & np.isfinite(t) & np.isfinite(gx) & np.isfinite(gy)
        ix = np.searchsorted(self.bx, np.where(hit, gx, 0.0), side="right")
        iy = np.searchsorted(self.by, np.where(hit, gy, 0.0), side="right")
        return np.where(hit, ix * self.ny + iy, -1)

    def colours(self, cells: NDArray[np.int64]) -> NDArray[np.int8]:
        """Class (0 white, 1 dark, 2 background) of cell numbers from :meth:`cells`."""
        flat = self.table.ravel()
        return np.where(cells >= 0, flat[np.maximum(cells, 0)], 2).astype(np.int8)


def _subsampled(camera: CameraModel, board: _Board, rows: NDArray, cols: NDArray,
                n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Fractions of the ``n x n`` sub-samples of pixels ``(rows, cols)`` on dark squares and background."""
    dark = np.empty(rows.size)
    background = np.empty(rows.size)
    du, dv = _sample_offsets(n)
    step = max(1, _BAND_SAMPLES // (n * n))
    for k0 in range(0, rows.size, step):
        k1 = min(k0 + step, rows.size)
        u = cols[k0:k1, None, None] + du
        v = rows[k0:k1, None, None] + dv
        d = camera.pixel_rays(u, v)  # (P, n, n, 3)
        with np.errstate(invalid="ignore", divide="ignore"):
            colour = board.colours(board.cells(d[..., 0] / d[..., 2], d[..., 1] / d[..., 2]))
        dark[k0:k1] = (colour == 1).mean(axis=(1, 2))
        background[k0:k1] = (colour == 2).mean(axis=(1, 2))
    return dark, background


def _coverage(camera: CameraModel, pose: CameraPose, cols: int, rows: int, square_m: float, n: int,
              margin_squares: float, adaptive: bool) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Fractions of each pixel's sub-samples on dark squares and on the background."""
    h, w = camera.height_px, camera.width_px
    board = _Board(pose, cols, rows, square_m, margin_squares)
    dark = np.zeros((h, w))
    background = np.zeros((h, w))
    if adaptive:
        # a pixel whose four corners see the same convex cell lies in it entirely: its sub-samples all agree
        x, y = _corner_directions(camera)
        cell = board.cells(x, y)
        cell[~(np.isfinite(x) & np.isfinite(y))] = -2  # lens not invertible there: never uniform
        uniform = (cell[:-1, :-1] == cell[:-1, 1:]) & (cell[:-1, :-1] == cell[1:, :-1]) \
            & (cell[:-1, :-1] == cell[1:, 1:]) & (cell[:-1, :-1] != -2)
        colour = board.colours(cell[:-1, :-1])
        dark[uniform & (colour == 1)] = 1.0
        background[uniform & (colour == 2)] = 1.0
        todo_r, todo_c = np.nonzero(~uniform)
    else:
        todo_r, todo_c = (a.ravel() for a in np.mgrid[0:h, 0:w])
    f_dark, f_bg = _subsampled(camera, board, todo_r.astype(np.float64), todo_c.astype(np.float64), n)
    dark[todo_r, todo_c] = f_dark
    background[todo_r, todo_c] = f_bg
    return dark, background


def render_checkerboard(
    camera: CameraModel,
    pose: CameraPose,
    cols: int,
    rows: int,
    square_m: float,
    *,
    supersample: int = 4,
    contrast: float = 0.9,
    background: float = 0.3,
    margin_squares: float = 1.0,
    polarized: bool = False,
    blur_sigma_px: float = 0.0,
    sensor: SensorModel | None = None,
    headroom: float = 0.8,
    noise: bool = True,
    rng: np.random.Generator | int | None = None,
    adaptive: bool = True,
) -> CheckerboardFrame:
    """Render a chessboard target seen by a posed camera, antialiased, with its true corner pixels.

    Parameters
    ----------
    camera : CameraModel
        Intrinsics and distortion (the ground truth a calibration should recover).
    pose : CameraPose
        Camera pose in the board frame (see the module docstring;
        :func:`board_view_pose` builds one).
    cols, rows : int
        Inner corners, OpenCV's ``patternSize = (cols, rows)``.
    square_m : float
        Square side, in the length unit of the pose (metres).
    supersample : int
        ``n``: each pixel averages ``n x n`` stratified sub-samples (1 .. 16).
    contrast : float
        Dark squares are ``1 - contrast`` of the white paper, in (0, 1].
    background : float
        ``S0`` beyond the white margin and where rays miss the board plane, >= 0.
    margin_squares : float
        Width of the white margin around the squares, in squares, >= 0.
    polarized : bool
        Give the surfaces the linear polarization of :data:`POLARIZATION`
        (``S1``, ``S2`` non-zero); ``S0`` is unchanged.
    blur_sigma_px : float
        Gaussian lens blur (sigma, pixels) applied to the Stokes images, >= 0.
    sensor : SensorModel, optional
        If given, also expose the Stokes image into a raw DoFP mosaic
        (:func:`pihim.render.sensor.choose_exposure` with ``headroom`` at the
        99.9th percentile, then :func:`pihim.render.sensor.expose`); the
        image sides must then be even.
    headroom : float
        Fraction of full scale the brightest (white) pixels reach in the raw frame.
    noise : bool
        Shot and read noise in the raw frame (``False``: only quantisation).
    rng : numpy.random.Generator or int, optional
        Noise source for the raw frame.
    adaptive : bool
        Skip the sub-samples of pixels whose four corners see one uniform
        cell of the board (see Notes); ``False`` samples every pixel (the
        reference, same image, ~10x slower).

    Returns
    -------
    CheckerboardFrame
        ``s0`` (and ``s1``, ``s2``), the true ``corners_px`` and, with a sensor, ``raw``.

    Notes
    -----
    The board plane is cut by the square edges and the margin's outer edges
    into convex cells of one colour (the region where rays miss the plane is
    a half-plane of the image, convex too). A pixel footprint is the
    projective image of a square, bent by the lens by far less than the
    ``1 / (2 n)`` px between the pixel border and its outermost sub-samples
    (the bulge of a 1-px edge is ``~ f''/8``: 4e-6 px for the 13 deg test
    lens, 1e-3 px for a 62 deg one with k1 = -0.2), so when the four pixel corners see the same cell every
    sub-sample does and the pixel is that colour: only pixels straddling an
    edge (a few per cent) are sub-sampled. The corner rays are computed once
    per camera (cached); the sub-sample rays per view.
    ``adaptive=False`` gives the same image to rounding
    [tests/inspection/test_calibration.py].
    """
    if not isinstance(camera, CameraModel):
        raise PihimInputError(f"camera must be a CameraModel, got {type(camera).__name__}")
    if not isinstance(pose, CameraPose):
        raise PihimInputError(f"pose must be a CameraPose, got {type(pose).__name__}")
    c, r = _board_size(cols, rows)
    s = _positive(square_m, "square size")
    if isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer)) \
            or not 1 <= supersample <= 16:
        raise PihimInputError(f"supersample must be an integer in 1..16, got {supersample!r}")
    k = finite_number(contrast, "contrast")
    if not 0.0 < k <= 1.0:
        raise PihimInputError(f"contrast must be in (0, 1], got {contrast!r}")
    bg = finite_number(background, "background")
    if not bg >= 0.0:
        raise PihimInputError(f"background must be a finite number >= 0, got {background!r}")
    m = finite_number(margin_squares, "margin_squares")
    if not m >= 0.0:
        raise PihimInputError(f"margin_squares must be a finite number >= 0, got {margin_squares!r}")

    f_dark, f_bg = _coverage(camera, pose, c, r, s, int(supersample), m, bool(adaptive))
    f_white = np.clip(1.0 - f_dark - f_bg, 0.0, 1.0)
    levels = {"white": 1.0, "dark": 1.0 - k, "background": bg}
    fractions = {"white": f_white, "dark": f_dark, "background": f_bg}
    s0 = sum(levels[name] * fractions[name] for name in levels)
    s1 = np.zeros_like(s0)
    s2 = np.zeros_like(s0)
    if polarized:
        for name, (dolp, aop) in POLARIZATION.items():
            two_a = math.radians(2.0 * aop)
            s1 += levels[name] * dolp * math.cos(two_a) * fractions[name]
            s2 += levels[name] * dolp * math.sin(two_a) * fractions[name]
    if blur_sigma_px:
        s0, s1, s2 = lens_blur(s0, s1, s2, blur_sigma_px)
    corners = project_points(camera, pose, checkerboard_points(c, r, s))
    t = np.linspace(0.0, 1.0, 16, endpoint=False)
    x0, x1, y0, y1 = -s, c * s, -s, r * s
    edge = np.concatenate([np.stack([x0 + (x1 - x0) * t, np.full(16, y0)], -1),
                           np.stack([np.full(16, x1), y0 + (y1 - y0) * t], -1),
                           np.stack([x1 - (x1 - x0) * t, np.full(16, y1)], -1),
                           np.stack([np.full(16, x0), y1 - (y1 - y0) * t], -1)])
    outline = project_points(camera, pose, np.column_stack([edge, np.zeros(64)]))
    raw = exposure = None
    if sensor is not None:
        exposure = choose_exposure(s0, s1, s2, sensor, percentile=99.9, headroom=headroom)
        raw = expose(s0, s1, s2, sensor, exposure, rng=rng, noise=noise)
    return CheckerboardFrame(s0=s0, s1=s1, s2=s2, corners_px=corners, outline_px=outline, raw=raw, exposure=exposure)
