"""Compiled inner loops of the pose, canting and edge estimators (private).

The fits evaluate the projection of a few thousand model points tens of
thousands of times per frame. Going through :class:`pihim.camera.CameraPose`
(validation of the rotation at every construction) and
:func:`pihim.camera.pose.project_points` costs far more than the arithmetic,
so the inner loops use these numba kernels on raw arrays instead. Each is
held to an independent statement by ``tests/inspection/test_kernels.py``.

* :func:`project_rc`: pixels of world points through a world -> camera
  rotation ``R`` and a camera centre ``C``: the arithmetic of
  ``CameraModel.project(CameraPose(C, R).world_to_camera(X))`` (pinhole and
  the five-coefficient Brown-Conrady model, NaN at or behind the camera;
  held to ``cv2.projectPoints``);
* :func:`project_rc_jacobian`: the same with the analytic derivatives of
  ``(u, v)`` by the six pose parameters of the fits -- a rotation vector
  ``w`` applied in the camera frame (``R(w) = exp([w]x) R0``) and the
  position offset -- by the chain rule through the pinhole and the
  distortion polynomial; ``d x_cam / d w = -[x_cam]x J_l(w)`` with ``J_l``
  the left Jacobian of SO(3) [1]_;
* :func:`bilinear`, :func:`sobel_bilinear`: sampling with the conventions of
  ``scipy.ndimage.map_coordinates(order=1, mode="constant", cval=0)`` (zero
  outside ``[0, n - 1]`` on either axis, and for NaN), of an image and of
  its ``cv2.Sobel`` gradient (computed where sampled);
* :func:`solve`: trust-region least squares for three residual kinds
  (:func:`problem`): the chamfer alignment of the pose (``1 - proximity``
  of the projected outline), the pose's point-to-line ICP and a facet's
  mirrored outline (canting). The algorithm of
  ``scipy.optimize.least_squares(method="trf")`` without bounds -- scaled
  variables, Moré's exact trust-region step [2]_, the soft-L1 loss by
  rescaling residuals and Jacobian [3]_ -- with the analytic Jacobians, all
  in one compiled loop;
* :func:`edge_nms`: the non-maximum suppression and parabolic sub-pixel peak
  of :func:`pihim.inspection.features.edge_points`;
* :func:`grid_counts`, :func:`grid_scores`: the canting grid searches' chamfer counts and score of every node;
* :func:`line_normals`, :func:`nearest_within`: the unit normals of projected
  polylines, and the nearest model point of each edge point within a gate
  (a bucket grid; of two coincident points -- a corner, which ends one side
  and starts the next -- the one whose line passes nearer the edge point);
* :func:`mirror_project`, :func:`reflect_in_mask`: the target's outline
  mirrored in a facet's plane and projected, for many canting angles or
  turns of the heliostat at once, and a canting fit's round (one pair of
  angles, with the polyline normals and whether each point falls in the
  facet's mask); :func:`unique_inverse`: ``np.unique(..., return_inverse=True)``
  of small indices without a sort;
* :func:`facet_normal`, :func:`refine_reflection`: a facet's normal at a pair
  of canting angles, and a whole canting fit (its rounds of projection,
  matching and :func:`solve`, over a window of the outline points near the
  facet's mask) in one call that releases the GIL, so that a facet's
  refinements from several starts run on threads.

References
----------
.. [1] J. Solà, J. Deray, D. Atchuthan, "A micro Lie theory for state
   estimation in robotics", arXiv:1812.01537 (2018) (the left Jacobian of
   SO(3)).
.. [2] J. J. Moré, "The Levenberg-Marquardt algorithm: implementation and
   theory", Numerical Analysis, Lecture Notes in Mathematics 630, 105-116
   (1977), doi:10.1007/BFb0067700.
.. [3] B. Triggs, P. McLauchlan, R. Hartley, A. Fitzgibbon, "Bundle
   adjustment -- a modern synthesis", Vision Algorithms: Theory and
   Practice, LNCS 1883, 298-372 (2000), doi:10.1007/3-540-44480-7_21.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

__all__ = ["CHAMFER", "POINT_TO_LINE", "REFLECTION", "bilinear", "camera_vector", "edge_nms", "facet_normal",
           "grid_counts", "grid_scores", "jacobian", "left_jacobian", "line_normals", "mirror_project",
           "nearest_within", "problem", "project_pose", "project_rc", "project_rc_jacobian", "refine_reflection",
           "reflect_in_mask", "residuals", "rotation_from_vector", "sobel_bilinear", "solve", "unique_inverse"]


def camera_vector(camera) -> NDArray[np.float64]:
    """``(fx, fy, cx, cy, k1, k2, p1, p2, k3)`` of a :class:`pihim.camera.CameraModel`, pixels."""
    return np.array([camera.fx_px, camera.fy_px, camera.cx_px, camera.cy_px, *camera.distortion], float)


def project_pose(camera, pose, pts: NDArray) -> NDArray[np.float64]:
    """:func:`project_rc` for a :class:`pihim.camera.CameraModel` and a :class:`pihim.camera.CameraPose`."""
    return project_rc(np.array(pose.rotation, float), np.array(pose.position_m, float),
                      np.ascontiguousarray(pts, dtype=float), camera_vector(camera))


@njit(cache=True, error_model="numpy")
def rotation_from_vector(w: NDArray) -> NDArray:  # pragma: no cover - compiled
    """Rotation matrix of a rotation vector (Rodrigues' formula), radians."""
    th2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    th = math.sqrt(th2)
    if th < 1e-4:  # series to 1e-17
        a = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
        b = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
    else:
        a = math.sin(th) / th
        b = (1.0 - math.cos(th)) / th2
    x, y, z = w[0], w[1], w[2]
    r = np.empty((3, 3))
    r[0, 0] = 1.0 - b * (y * y + z * z)
    r[1, 1] = 1.0 - b * (x * x + z * z)
    r[2, 2] = 1.0 - b * (x * x + y * y)
    r[0, 1] = b * x * y - a * z
    r[1, 0] = b * x * y + a * z
    r[0, 2] = b * x * z + a * y
    r[2, 0] = b * x * z - a * y
    r[1, 2] = b * y * z - a * x
    r[2, 1] = b * y * z + a * x
    return r


@njit(cache=True, error_model="numpy")
def left_jacobian(w: NDArray) -> NDArray:  # pragma: no cover - compiled
    """Left Jacobian of SO(3): ``exp([w + dw]x) = exp([J_l(w) dw]x) exp([w]x)`` to first order."""
    th2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    th = math.sqrt(th2)
    if th < 1e-4:
        b = 0.5 - th2 / 24.0
        c = 1.0 / 6.0 - th2 / 120.0
    else:
        b = (1.0 - math.cos(th)) / th2
        c = (th - math.sin(th)) / (th2 * th)
    x, y, z = w[0], w[1], w[2]
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + b * k + c * (k @ k)


@njit(cache=True, error_model="numpy")
def _distort(xn: float, yn: float, cam: NDArray) -> tuple[float, float]:  # pragma: no cover - compiled
    k1, k2, p1, p2, k3 = cam[4], cam[5], cam[6], cam[7], cam[8]
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy2 = 2.0 * xn * yn
    xd = xn * radial + p1 * xy2 + p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + p2 * xy2
    return xd, yd


@njit(cache=True, error_model="numpy")
def project_rc(rot: NDArray, centre: NDArray, pts: NDArray, cam: NDArray) -> NDArray:  # pragma: no cover
    """Pixels ``(u, v)`` (N, 2) of world points (N, 3); NaN at or behind the camera."""
    n = pts.shape[0]
    out = np.empty((n, 2))
    for i in range(n):
        dx = pts[i, 0] - centre[0]
        dy = pts[i, 1] - centre[1]
        dz = pts[i, 2] - centre[2]
        px = rot[0, 0] * dx + rot[0, 1] * dy + rot[0, 2] * dz
        py = rot[1, 0] * dx + rot[1, 1] * dy + rot[1, 2] * dz
        pz = rot[2, 0] * dx + rot[2, 1] * dy + rot[2, 2] * dz
        if not pz > 0.0:
            out[i, 0] = np.nan
            out[i, 1] = np.nan
            continue
        xd, yd = _distort(px / pz, py / pz, cam)
        out[i, 0] = cam[0] * xd + cam[2]
        out[i, 1] = cam[1] * yd + cam[3]
    return out


@njit(cache=True, error_model="numpy")
def _pixel_jacobian(px, py, pz, cam):  # pragma: no cover - compiled
    """``d(u, v) / d(px, py, pz)`` at a camera-frame point: the rows ``(a0, a1, a2)``, ``(b0, b1, b2)``.

    ``diag(fx, fy) Jd [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]`` with ``Jd`` the Jacobian of
    the distortion polynomial at the normalised point.
    """
    k1, k2, p1, p2, k3 = cam[4], cam[5], cam[6], cam[7], cam[8]
    iz = 1.0 / pz
    xn = px * iz
    yn = py * iz
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    jxx = radial + 2.0 * xn * xn * dradial + 2.0 * p1 * yn + 6.0 * p2 * xn
    jyy = radial + 2.0 * yn * yn * dradial + 6.0 * p1 * yn + 2.0 * p2 * xn
    jxy = 2.0 * xn * yn * dradial + 2.0 * p1 * xn + 2.0 * p2 * yn
    a0 = cam[0] * jxx * iz
    a1 = cam[0] * jxy * iz
    b0 = cam[1] * jxy * iz
    b1 = cam[1] * jyy * iz
    return a0, a1, -(a0 * xn + a1 * yn), b0, b1, -(b0 * xn + b1 * yn)


@njit(cache=True, error_model="numpy")
def _pose_jacobian(px, py, pz, cam, rot, jl, ux, vx):  # pragma: no cover - compiled
    """``d u`` and ``d v`` by the pose parameters (rotation vector, position offset) into ``ux``, ``vx`` (6,).

    ``d p / d w_k = J_l[:, k] x p`` (``-[p]x J_l``) and ``d p / d C = -R``.
    """
    a0, a1, a2, b0, b1, b2 = _pixel_jacobian(px, py, pz, cam)
    for k in range(3):
        l0, l1, l2 = jl[0, k], jl[1, k], jl[2, k]
        d0 = l1 * pz - l2 * py
        d1 = l2 * px - l0 * pz
        d2 = l0 * py - l1 * px
        ux[k] = a0 * d0 + a1 * d1 + a2 * d2
        vx[k] = b0 * d0 + b1 * d1 + b2 * d2
        ux[3 + k] = -(a0 * rot[0, k] + a1 * rot[1, k] + a2 * rot[2, k])
        vx[3 + k] = -(b0 * rot[0, k] + b1 * rot[1, k] + b2 * rot[2, k])


@njit(cache=True, error_model="numpy")
def project_rc_jacobian(rot0: NDArray, centre0: NDArray, x: NDArray, pts: NDArray,
                        cam: NDArray) -> tuple[NDArray, NDArray]:  # pragma: no cover - compiled
    """Pixels (N, 2) at the pose ``(exp([x[:3]]x) rot0, centre0 + x[3:])`` and their Jacobian (N, 2, 6).

    Points at or behind the camera get NaN pixels and a zero Jacobian.
    """
    rot = rotation_from_vector(x[:3]) @ rot0
    c0, c1, c2 = centre0[0] + x[3], centre0[1] + x[4], centre0[2] + x[5]
    jl = left_jacobian(x[:3])
    n = pts.shape[0]
    uv = np.empty((n, 2))
    jac = np.zeros((n, 2, 6))
    ux = np.empty(6)
    vx = np.empty(6)
    for i in range(n):
        dx = pts[i, 0] - c0
        dy = pts[i, 1] - c1
        dz = pts[i, 2] - c2
        px = rot[0, 0] * dx + rot[0, 1] * dy + rot[0, 2] * dz
        py = rot[1, 0] * dx + rot[1, 1] * dy + rot[1, 2] * dz
        pz = rot[2, 0] * dx + rot[2, 1] * dy + rot[2, 2] * dz
        if not pz > 0.0:
            uv[i, 0] = np.nan
            uv[i, 1] = np.nan
            continue
        xd, yd = _distort(px / pz, py / pz, cam)
        uv[i, 0] = cam[0] * xd + cam[2]
        uv[i, 1] = cam[1] * yd + cam[3]
        _pose_jacobian(px, py, pz, cam, rot, jl, ux, vx)
        for c in range(6):
            jac[i, 0, c] = ux[c]
            jac[i, 1, c] = vx[c]
    return uv, jac


@njit(cache=True, error_model="numpy")
def _bilinear_at(img, u, v):  # pragma: no cover - compiled
    h, w = img.shape
    if not (u >= 0.0 and u <= w - 1 and v >= 0.0 and v <= h - 1):
        return 0.0, -1, -1, 0.0, 0.0
    j0 = int(math.floor(u))
    i0 = int(math.floor(v))
    a = u - j0
    b = v - i0
    return 1.0, i0, j0, a, b


@njit(cache=True, error_model="numpy")
def _lerp(img, i0, j0, a, b):  # pragma: no cover - compiled
    h, w = img.shape
    i1 = min(i0 + 1, h - 1)
    j1 = min(j0 + 1, w - 1)
    return ((1.0 - b) * ((1.0 - a) * img[i0, j0] + a * img[i0, j1])
            + b * ((1.0 - a) * img[i1, j0] + a * img[i1, j1]))


@njit(cache=True, error_model="numpy")
def bilinear(img: NDArray, u: NDArray, v: NDArray) -> NDArray:  # pragma: no cover - compiled
    """``img`` sampled at columns ``u`` and rows ``v`` (bilinear; 0 outside ``[0, n-1]`` and for NaN)."""
    out = np.zeros(u.shape[0])
    for k in range(u.shape[0]):
        ok, i0, j0, a, b = _bilinear_at(img, u[k], v[k])
        if ok > 0.0:
            out[k] = _lerp(img, i0, j0, a, b)
    return out


@njit(cache=True, error_model="numpy")
def _reflect101(k, n):  # pragma: no cover - compiled
    """OpenCV's default border (``BORDER_REFLECT_101``): -1 -> 1, n -> n - 2."""
    if k < 0:
        return -k
    if k >= n:
        return 2 * n - 2 - k
    return k


@njit(cache=True, error_model="numpy")
def _sobel_at(img, i, j):  # pragma: no cover - compiled
    """``cv2.Sobel(img, ksize=3) / 8`` in x and y at pixel (i, j) (default border)."""
    h, w = img.shape
    im = _reflect101(i - 1, h)
    ip = _reflect101(i + 1, h)
    jm = _reflect101(j - 1, w)
    jp = _reflect101(j + 1, w)
    gx = ((img[im, jp] - img[im, jm]) + 2.0 * (img[i, jp] - img[i, jm]) + (img[ip, jp] - img[ip, jm])) / 8.0
    gy = ((img[ip, jm] - img[im, jm]) + 2.0 * (img[ip, j] - img[im, j]) + (img[ip, jp] - img[im, jp])) / 8.0
    return gx, gy


@njit(cache=True, error_model="numpy")
def _sobel_lerp(img, i0, j0, a, b):  # pragma: no cover - compiled
    """Bilinear interpolation of the Sobel gradient images (as ``map_coordinates`` of them).

    The four Sobel values come from the 4 x 4 neighbourhood of ``(i0, j0)`` (OpenCV's
    default border); on the last row or column, where the bilinear corners clamp, from
    each corner's own neighbourhood.
    """
    h, w = img.shape
    if i0 + 1 >= h or j0 + 1 >= w:
        i1 = min(i0 + 1, h - 1)
        j1 = min(j0 + 1, w - 1)
        x00, y00 = _sobel_at(img, i0, j0)
        x01, y01 = _sobel_at(img, i0, j1)
        x10, y10 = _sobel_at(img, i1, j0)
        x11, y11 = _sobel_at(img, i1, j1)
        gx = (1.0 - b) * ((1.0 - a) * x00 + a * x01) + b * ((1.0 - a) * x10 + a * x11)
        gy = (1.0 - b) * ((1.0 - a) * y00 + a * y01) + b * ((1.0 - a) * y10 + a * y11)
        return gx, gy
    r0, r1, r2, r3 = _reflect101(i0 - 1, h), i0, i0 + 1, _reflect101(i0 + 2, h)
    c0, c1, c2, c3 = _reflect101(j0 - 1, w), j0, j0 + 1, _reflect101(j0 + 2, w)
    p00, p01, p02, p03 = img[r0, c0], img[r0, c1], img[r0, c2], img[r0, c3]
    p10, p11, p12, p13 = img[r1, c0], img[r1, c1], img[r1, c2], img[r1, c3]
    p20, p21, p22, p23 = img[r2, c0], img[r2, c1], img[r2, c2], img[r2, c3]
    p30, p31, p32, p33 = img[r3, c0], img[r3, c1], img[r3, c2], img[r3, c3]
    # Sobel at the corners (1, 1), (1, 2), (2, 1), (2, 2) of the 4 x 4 patch
    x11 = (p02 - p00) + 2.0 * (p12 - p10) + (p22 - p20)
    x12 = (p03 - p01) + 2.0 * (p13 - p11) + (p23 - p21)
    x21 = (p12 - p10) + 2.0 * (p22 - p20) + (p32 - p30)
    x22 = (p13 - p11) + 2.0 * (p23 - p21) + (p33 - p31)
    y11 = (p20 - p00) + 2.0 * (p21 - p01) + (p22 - p02)
    y12 = (p21 - p01) + 2.0 * (p22 - p02) + (p23 - p03)
    y21 = (p30 - p10) + 2.0 * (p31 - p11) + (p32 - p12)
    y22 = (p31 - p11) + 2.0 * (p32 - p12) + (p33 - p13)
    gx = ((1.0 - b) * ((1.0 - a) * x11 + a * x12) + b * ((1.0 - a) * x21 + a * x22)) / 8.0
    gy = ((1.0 - b) * ((1.0 - a) * y11 + a * y12) + b * ((1.0 - a) * y21 + a * y22)) / 8.0
    return gx, gy


@njit(cache=True, error_model="numpy")
def sobel_bilinear(img: NDArray, u: NDArray, v: NDArray) -> NDArray:  # pragma: no cover - compiled
    """The Sobel gradient of ``img`` (``cv2.Sobel(ksize=3) / 8``) sampled bilinearly at (u, v): (N, 2)."""
    out = np.zeros((u.shape[0], 2))
    for k in range(u.shape[0]):
        ok, i0, j0, a, b = _bilinear_at(img, u[k], v[k])
        if ok > 0.0:
            out[k, 0], out[k, 1] = _sobel_lerp(img, i0, j0, a, b)
    return out


#: Residual kinds of :func:`solve` (the first item of a :func:`problem`).
CHAMFER = 0
POINT_TO_LINE = 1
REFLECTION = 2


def problem(kind: int, rot: NDArray, centre: NDArray, pts: NDArray, cam: NDArray, *, prox: NDArray | None = None,
            q: NDArray | None = None, aux: NDArray | None = None, idx: NDArray | None = None,
            gate: float = 0.0) -> tuple:
    """The arguments of one least-squares problem for :func:`solve`, :func:`residuals` and :func:`jacobian`.

    Parameters
    ----------
    kind : {CHAMFER, POINT_TO_LINE, REFLECTION}
    rot, centre : ndarray
        The camera's world -> camera rotation (3, 3) and centre (3,), metres: the pose the
        pose parameters perturb (``CHAMFER``, ``POINT_TO_LINE``: ``x = (w, dC)``,
        ``R = exp([w]x) rot``, ``C = centre + dC``) or the fixed pose (``REFLECTION``).
    pts : ndarray, shape (N, 3)
        Model points, ENU metres (see :func:`_evaluate` for their layout per kind).
    cam : ndarray, shape (9,)
        :func:`camera_vector`.
    prox : ndarray, 2-D, float32
        ``CHAMFER``: the proximity map.
    q : ndarray, shape (M, 2) or (M, 4)
        ``POINT_TO_LINE``: the matched edge points; ``REFLECTION``: the matched edge
        points and the unit normals of the model's lines there.
    aux : ndarray, shape (15,)
        ``REFLECTION``: the HUA's rotation (9, row-major), the facet centre (3, ENU) and
        its design normal (3, heliostat frame).
    idx : ndarray of int
        ``REFLECTION``: the model point of each residual.
    gate : float
        Residual where it is undefined (``POINT_TO_LINE``, ``REFLECTION``), pixels.
    """
    f64 = np.float64
    return (int(kind), np.ascontiguousarray(rot, dtype=f64), np.ascontiguousarray(centre, dtype=f64),
            np.ascontiguousarray(pts, dtype=f64), np.ascontiguousarray(cam, dtype=f64),
            np.ascontiguousarray(prox, dtype=np.float32) if prox is not None else np.zeros((1, 1), np.float32),
            np.ascontiguousarray(q, dtype=f64) if q is not None else np.zeros((0, 2)),
            np.ascontiguousarray(aux, dtype=f64) if aux is not None else np.zeros(0),
            np.ascontiguousarray(idx, dtype=np.int64) if idx is not None else np.zeros(0, np.int64),
            float(gate))


@njit(cache=True, error_model="numpy")
def _chamfer_eval(prob, x, want_jac, f, jac):  # pragma: no cover - compiled
    """``1 - prox(u, v)`` at each model point (1 outside the map or behind the camera, zero
    Jacobian row); the gradient is the map's Sobel gradient, bilinearly interpolated."""
    rot0, centre0, pts, cam, prox = prob[1], prob[2], prob[3], prob[4], prob[5]
    rot = rotation_from_vector(x[:3]) @ rot0
    c0, c1, c2 = centre0[0] + x[3], centre0[1] + x[4], centre0[2] + x[5]
    jl = left_jacobian(x[:3])
    ux = np.empty(6)
    vx = np.empty(6)
    for i in range(f.shape[0]):
        f[i] = 1.0
        if want_jac:
            for c in range(6):
                jac[i, c] = 0.0
        dx = pts[i, 0] - c0
        dy = pts[i, 1] - c1
        dz = pts[i, 2] - c2
        px = rot[0, 0] * dx + rot[0, 1] * dy + rot[0, 2] * dz
        py = rot[1, 0] * dx + rot[1, 1] * dy + rot[1, 2] * dz
        pz = rot[2, 0] * dx + rot[2, 1] * dy + rot[2, 2] * dz
        if not pz > 0.0:
            continue
        xd, yd = _distort(px / pz, py / pz, cam)
        ok, i0, j0, a, b = _bilinear_at(prox, cam[0] * xd + cam[2], cam[1] * yd + cam[3])
        if ok == 0.0:
            continue
        f[i] = 1.0 - _lerp(prox, i0, j0, a, b)
        if want_jac:
            g0, g1 = _sobel_lerp(prox, i0, j0, a, b)
            _pose_jacobian(px, py, pz, cam, rot, jl, ux, vx)
            for c in range(6):
                jac[i, c] = -(g0 * ux[c] + g1 * vx[c])


@njit(cache=True, error_model="numpy")
def _line_eval(prob, x, want_jac, f, jac):  # pragma: no cover - compiled
    """Signed distance of edge point ``q[i]`` from the line through model point ``i`` along the
    central difference of its neighbours; ``pts`` holds the M model points, then their
    previous and their next sample on the outline (3 M rows). ``gate`` (zero Jacobian row)
    where undefined."""
    rot0, centre0, pts, cam, q, gate = prob[1], prob[2], prob[3], prob[4], prob[6], prob[9]
    rot = rotation_from_vector(x[:3]) @ rot0
    c0, c1, c2 = centre0[0] + x[3], centre0[1] + x[4], centre0[2] + x[5]
    jl = left_jacobian(x[:3])
    m = f.shape[0]
    uv = np.empty((3, 2))
    duv = np.zeros((3, 2, 6))
    ux = np.empty(6)
    vx = np.empty(6)
    for i in range(m):
        front = True
        for k in range(3):
            r = i + k * m
            dx = pts[r, 0] - c0
            dy = pts[r, 1] - c1
            dz = pts[r, 2] - c2
            px = rot[0, 0] * dx + rot[0, 1] * dy + rot[0, 2] * dz
            py = rot[1, 0] * dx + rot[1, 1] * dy + rot[1, 2] * dz
            pz = rot[2, 0] * dx + rot[2, 1] * dy + rot[2, 2] * dz
            if not pz > 0.0:
                front = False
                break
            xd, yd = _distort(px / pz, py / pz, cam)
            uv[k, 0] = cam[0] * xd + cam[2]
            uv[k, 1] = cam[1] * yd + cam[3]
            if want_jac:
                _pose_jacobian(px, py, pz, cam, rot, jl, ux, vx)
                for c in range(6):
                    duv[k, 0, c] = ux[c]
                    duv[k, 1, c] = vx[c]
        f[i] = gate
        if want_jac:
            for c in range(6):
                jac[i, c] = 0.0
        if not front:
            continue
        tx = uv[2, 0] - uv[1, 0]
        ty = uv[2, 1] - uv[1, 1]
        ln = math.hypot(tx, ty)
        if not ln > 0.0:
            continue
        tx /= ln
        ty /= ln
        ddx = q[i, 0] - uv[0, 0]
        ddy = q[i, 1] - uv[0, 1]
        f[i] = tx * ddy - ty * ddx
        if want_jac:
            for c in range(6):
                # d(t / |t|) = (I - t t^T) dt / |t|; d(q - uv) = -duv
                dtx = (duv[2, 0, c] - duv[1, 0, c]) / ln
                dty = (duv[2, 1, c] - duv[1, 1, c]) / ln
                along = tx * dtx + ty * dty
                dtx -= along * tx
                dty -= along * ty
                jac[i, c] = (dtx * ddy - dty * ddx) - (tx * duv[0, 1, c] - ty * duv[0, 0, c])


@njit(cache=True, error_model="numpy")
def _reflection_eval(prob, x, want_jac, f, jac):  # pragma: no cover - compiled
    """Signed distance of edge point ``q[i, :2]`` from the line through model point
    ``idx[i]`` mirrored in the facet tilted by ``x = (az, el)`` mrad
    (``R_y(az) R_x(-el)`` of the design normal, :func:`pihim.field.apply_canting_deviation`),
    along the held unit normal ``q[i, 2:]``; ``gate`` (zero Jacobian row) where undefined."""
    rot, centre, pts, cam, q, aux, idx, gate = prob[1], prob[2], prob[3], prob[4], prob[6], prob[7], prob[8], prob[9]
    rh = aux[0:9]
    fc = aux[9:12]
    nd = aux[12:15]
    az = x[0] * 1e-3
    el = x[1] * 1e-3
    ca, sa = math.cos(az), math.sin(az)
    ce, se = math.cos(el), math.sin(el)
    m1 = np.array([nd[0], ce * nd[1] + se * nd[2], -se * nd[1] + ce * nd[2]])
    dm1 = np.array([0.0, -se * nd[1] + ce * nd[2], -ce * nd[1] - se * nd[2]])  # d m1 / d el
    loc = np.array([ca * m1[0] + sa * m1[2], m1[1], -sa * m1[0] + ca * m1[2]])
    loc_a = np.array([-sa * m1[0] + ca * m1[2], 0.0, -ca * m1[0] - sa * m1[2]])  # d / d az
    loc_e = np.array([ca * dm1[0] + sa * dm1[2], dm1[1], -sa * dm1[0] + ca * dm1[2]])  # d / d el
    n = np.empty(3)
    na = np.empty(3)
    ne = np.empty(3)
    for r in range(3):
        n[r] = rh[3 * r] * loc[0] + rh[3 * r + 1] * loc[1] + rh[3 * r + 2] * loc[2]
        na[r] = 1e-3 * (rh[3 * r] * loc_a[0] + rh[3 * r + 1] * loc_a[1] + rh[3 * r + 2] * loc_a[2])
        ne[r] = 1e-3 * (rh[3 * r] * loc_e[0] + rh[3 * r + 1] * loc_e[1] + rh[3 * r + 2] * loc_e[2])
    k_pts = pts.shape[0]
    uv = np.empty((k_pts, 2))
    duv = np.zeros((k_pts, 2, 2))
    for k in range(k_pts):
        e0, e1, e2 = pts[k, 0] - fc[0], pts[k, 1] - fc[1], pts[k, 2] - fc[2]
        d = e0 * n[0] + e1 * n[1] + e2 * n[2]
        vx_, vy_, vz_ = pts[k, 0] - 2.0 * d * n[0], pts[k, 1] - 2.0 * d * n[1], pts[k, 2] - 2.0 * d * n[2]
        dx, dy, dz = vx_ - centre[0], vy_ - centre[1], vz_ - centre[2]
        px = rot[0, 0] * dx + rot[0, 1] * dy + rot[0, 2] * dz
        py = rot[1, 0] * dx + rot[1, 1] * dy + rot[1, 2] * dz
        pz = rot[2, 0] * dx + rot[2, 1] * dy + rot[2, 2] * dz
        if not pz > 0.0:
            uv[k, 0] = np.nan
            uv[k, 1] = np.nan
            continue
        xd, yd = _distort(px / pz, py / pz, cam)
        uv[k, 0] = cam[0] * xd + cam[2]
        uv[k, 1] = cam[1] * yd + cam[3]
        if want_jac:
            a0, a1, a2, b0, b1, b2 = _pixel_jacobian(px, py, pz, cam)
            for c in range(2):
                dn = na if c == 0 else ne
                dd = e0 * dn[0] + e1 * dn[1] + e2 * dn[2]
                # d V = -2 (dd n + d dn), then d p = R d V
                w0 = -2.0 * (dd * n[0] + d * dn[0])
                w1 = -2.0 * (dd * n[1] + d * dn[1])
                w2 = -2.0 * (dd * n[2] + d * dn[2])
                q0 = rot[0, 0] * w0 + rot[0, 1] * w1 + rot[0, 2] * w2
                q1 = rot[1, 0] * w0 + rot[1, 1] * w1 + rot[1, 2] * w2
                q2 = rot[2, 0] * w0 + rot[2, 1] * w1 + rot[2, 2] * w2
                duv[k, 0, c] = a0 * q0 + a1 * q1 + a2 * q2
                duv[k, 1, c] = b0 * q0 + b1 * q1 + b2 * q2
    for i in range(f.shape[0]):
        k = idx[i]
        r = (q[i, 0] - uv[k, 0]) * q[i, 2] + (q[i, 1] - uv[k, 1]) * q[i, 3]
        ok = math.isfinite(r)
        f[i] = r if ok else gate
        if want_jac:
            for c in range(2):
                jac[i, c] = -(duv[k, 0, c] * q[i, 2] + duv[k, 1, c] * q[i, 3]) if ok else 0.0


@njit(cache=True, error_model="numpy")
def _evaluate(prob, x, want_jac, f, jac):  # pragma: no cover - compiled
    """Residuals ``f`` (and their Jacobian ``jac``) of ``prob`` at parameters ``x``."""
    kind = prob[0]
    if kind == CHAMFER:
        _chamfer_eval(prob, x, want_jac, f, jac)
    elif kind == POINT_TO_LINE:
        _line_eval(prob, x, want_jac, f, jac)
    else:
        _reflection_eval(prob, x, want_jac, f, jac)


@njit(cache=True, error_model="numpy")
def _sym_eig(a, w, v):  # pragma: no cover - compiled
    """Eigenvalues ``w`` and eigenvectors (columns of ``v``) of the small symmetric matrix ``a``
    by cyclic Jacobi rotations (to rounding; ``a`` is not changed)."""
    n = a.shape[0]
    b = a.copy()
    for i in range(n):
        for j in range(n):
            v[i, j] = 1.0 if i == j else 0.0
    for _ in range(60):
        off = 0.0
        scale = 0.0
        for i in range(n):
            scale += b[i, i] * b[i, i]
            for j in range(i + 1, n):
                off += b[i, j] * b[i, j]
        if not off > 1e-32 * scale:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = b[p, q]
                if apq == 0.0:
                    continue
                theta = (b[q, q] - b[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                sn = t * c
                for k in range(n):  # columns p, q
                    bkp = b[k, p]
                    bkq = b[k, q]
                    b[k, p] = c * bkp - sn * bkq
                    b[k, q] = sn * bkp + c * bkq
                for k in range(n):  # rows p, q
                    bpk = b[p, k]
                    bqk = b[q, k]
                    b[p, k] = c * bpk - sn * bqk
                    b[q, k] = sn * bpk + c * bqk
                for k in range(n):
                    vkp = v[k, p]
                    vkq = v[k, q]
                    v[k, p] = c * vkp - sn * vkq
                    v[k, q] = sn * vkp + c * vkq
    for i in range(n):
        w[i] = b[i, i]


@njit(cache=True, error_model="numpy")
def _step_for(s2, suf, vmat, alpha, p):  # pragma: no cover - compiled
    """``p = -V (suf / (s2 + alpha))``; returns ``|p|``."""
    n = s2.shape[0]
    for i in range(n):
        p[i] = 0.0
    for k in range(n):
        c = suf[k] / (s2[k] + alpha)
        for i in range(n):
            p[i] -= vmat[i, k] * c
    nn = 0.0
    for i in range(n):
        nn += p[i] * p[i]
    return math.sqrt(nn)


@njit(cache=True, error_model="numpy")
def _phi(s2, suf, alpha, delta):  # pragma: no cover - compiled
    """``|p(alpha)| - delta`` and its derivative by ``alpha``."""
    pn2 = 0.0
    d3 = 0.0
    for k in range(s2.shape[0]):
        den = s2[k] + alpha
        pn2 += (suf[k] / den) ** 2
        d3 += suf[k] ** 2 / den ** 3
    pn = math.sqrt(pn2)
    return pn - delta, -d3 / pn


@njit(cache=True, error_model="numpy")
def _tr_step(s2, suf, vmat, delta, alpha0, m, p):  # pragma: no cover - compiled
    """Moré's trust-region step (into ``p``) from the eigen-decomposition of the scaled normal matrix.

    ``s2`` are the eigenvalues (squared singular values of the scaled Jacobian),
    ``suf = V^T g``; the step is ``-V suf / (s2 + alpha)`` with ``alpha = 0`` if that
    Gauss-Newton step is inside the region, else ``|step| = delta`` to 1 % (then scaled
    onto the boundary). ``m`` is the number of residuals (rank test as for an SVD of the
    Jacobian). Returns ``alpha``.
    """
    n = s2.shape[0]
    smax = 0.0
    smin = np.inf
    sufn = 0.0
    for k in range(n):
        smax = max(smax, s2[k])
        smin = min(smin, s2[k])
        sufn += suf[k] * suf[k]
    full_rank = math.sqrt(max(smin, 0.0)) > 2.220446049250313e-16 * m * math.sqrt(max(smax, 0.0))
    if full_rank and _step_for(s2, suf, vmat, 0.0, p) <= delta:
        return 0.0
    alpha_upper = math.sqrt(sufn) / delta
    alpha_lower = 0.0
    if full_rank:
        phi, dphi = _phi(s2, suf, 0.0, delta)
        alpha_lower = -phi / dphi
    alpha = alpha0
    if alpha == 0.0 and not full_rank:
        alpha = max(0.001 * alpha_upper, math.sqrt(alpha_lower * alpha_upper))
    for _ in range(10):
        if alpha < alpha_lower or alpha > alpha_upper:
            alpha = max(0.001 * alpha_upper, math.sqrt(alpha_lower * alpha_upper))
        phi, dphi = _phi(s2, suf, alpha, delta)
        if phi < 0:
            alpha_upper = alpha
        ratio = phi / dphi
        alpha_lower = max(alpha_lower, alpha - ratio)
        alpha -= (phi + delta) * ratio / delta
        if abs(phi) < 0.01 * delta:
            break
    pn = _step_for(s2, suf, vmat, alpha, p)
    if pn > 0:
        for i in range(n):
            p[i] *= delta / pn
    return alpha


@njit(cache=True, error_model="numpy")
def _robust(f, f_scale, soft_l1, jac, scale_jac):  # pragma: no cover - compiled
    """Cost ``0.5 sum rho(f)``; with ``scale_jac`` also the residuals and Jacobian rescaled in
    place so that Gauss-Newton on them is the robust problem's (as ``least_squares``).

    ``soft_l1``: ``rho(f) = 2 c^2 (sqrt(1 + (f / c)^2) - 1)``, ``c = f_scale``; else ``f^2``.
    """
    if not soft_l1:
        return 0.5 * (f * f).sum()
    cost = 0.0
    c2 = f_scale * f_scale
    for i in range(f.shape[0]):
        t = 1.0 + f[i] * f[i] / c2
        st = math.sqrt(t)
        cost += c2 * (st - 1.0)
        if scale_jac:
            rho1 = 1.0 / st
            rho2 = -0.5 / (t * st) / c2
            js = rho1 + 2.0 * rho2 * f[i] * f[i]
            if js < 2.220446049250313e-16:
                js = 2.220446049250313e-16
            js = math.sqrt(js)
            f[i] *= rho1 / js
            for c in range(jac.shape[1]):
                jac[i, c] *= js
    return cost


@njit(cache=True, error_model="numpy")
def _normal_equations(jac, f, x_scale, a, g):  # pragma: no cover - compiled
    """``g = J^T f`` and the scaled normal matrix ``a = (J D)^T (J D)``, ``D = diag(x_scale)``."""
    n = jac.shape[1]
    for c in range(n):
        g[c] = 0.0
        for d in range(n):
            a[c, d] = 0.0
    for i in range(jac.shape[0]):
        fi = f[i]
        for c in range(n):
            jc = jac[i, c]
            if jc == 0.0:
                continue
            g[c] += jc * fi
            for d in range(c, n):
                a[c, d] += jc * jac[i, d]
    for c in range(n):
        for d in range(c, n):
            a[c, d] *= x_scale[c] * x_scale[d]
            a[d, c] = a[c, d]


@njit(cache=True, error_model="numpy", nogil=True)
def solve(prob: tuple, x0: NDArray, m: int, x_scale: NDArray, max_nfev: int, soft_l1: bool,
          f_scale: float) -> tuple[NDArray, NDArray, NDArray]:  # pragma: no cover - compiled
    """Parameters minimising the (robust) sum of squared residuals of ``prob`` from ``x0``.

    Trust-region least squares in the variables scaled by ``x_scale`` -- the algorithm of
    ``scipy.optimize.least_squares(method="trf", tr_solver="exact")`` without bounds: Moré's
    exact step, the radius set from ``|x0 / x_scale|`` (at least 1), quartered or doubled on
    the ratio of actual to predicted reduction, ``ftol = xtol = gtol = 1e-8``, at most
    ``max_nfev`` residual evaluations -- with the analytic Jacobian of :func:`_evaluate`.
    ``m`` is the number of residuals.

    Returns
    -------
    x : ndarray
    fun : ndarray, shape (m,)
        The residuals at ``x`` (no loss applied).
    jac : ndarray, shape (m, n)
        The Jacobian at ``x``, rows scaled for the loss as ``least_squares``' ``jac``.
    """
    n = x0.shape[0]
    x = x0.copy()
    x_new = np.empty(n)
    f = np.empty(m)
    jac = np.empty((m, n))
    f_new = np.empty(m)
    jac_new = np.empty((m, n))
    _evaluate(prob, x, True, f, jac)
    f_true = f.copy()
    nfev = 1
    cost = _robust(f, f_scale, soft_l1, jac, True)
    delta = 0.0
    for i in range(n):
        delta += (x0[i] / x_scale[i]) ** 2
    # at least one scaled unit: a start a rounding error off zero would otherwise begin with a radius
    # of 1e-14, whose first step already meets ``ftol`` (scipy's "1 if zero" has that trap)
    delta = max(math.sqrt(delta), 1.0)
    alpha = 0.0
    tol = 1e-8
    done = False
    g = np.empty(n)
    gh = np.empty(n)
    a = np.empty((n, n))
    s2 = np.empty(n)
    vmat = np.empty((n, n))
    suf = np.empty(n)
    h = np.empty(n)
    while not done:
        _normal_equations(jac, f, x_scale, a, g)
        gmax = 0.0
        for i in range(n):
            gmax = max(gmax, abs(g[i]))
            gh[i] = g[i] * x_scale[i]
        if gmax < tol or nfev >= max_nfev:
            break
        _sym_eig(a, s2, vmat)
        for k in range(n):
            suf[k] = 0.0
            for i in range(n):
                suf[k] += vmat[i, k] * gh[i]
        actual = -1.0
        cost_new = cost
        while actual <= 0.0 and nfev < max_nfev:
            alpha = _tr_step(s2, suf, vmat, delta, alpha, m, h)
            quad = 0.0
            lin = 0.0
            hn = 0.0
            step_norm = 0.0
            x_norm = 0.0
            for i in range(n):
                ah = 0.0
                for k in range(n):
                    ah += a[i, k] * h[k]
                quad += h[i] * ah
                lin += gh[i] * h[i]
                hn += h[i] * h[i]
                st = x_scale[i] * h[i]
                step_norm += st * st
                x_norm += x[i] * x[i]
                x_new[i] = x[i] + st
            predicted = -(0.5 * quad + lin)
            hn = math.sqrt(hn)
            step_norm = math.sqrt(step_norm)
            x_norm = math.sqrt(x_norm)
            # the Jacobian comes with the trial residuals: most trial steps are taken
            _evaluate(prob, x_new, True, f_new, jac_new)
            nfev += 1
            cost_new = _robust(f_new, f_scale, soft_l1, jac_new, False)
            actual = cost - cost_new
            if predicted > 0:
                ratio = actual / predicted
            elif predicted == 0.0 and actual == 0.0:
                ratio = 1.0
            else:
                ratio = 0.0
            delta_new = delta
            if ratio < 0.25:
                delta_new = 0.25 * hn
            elif ratio > 0.75 and hn > 0.95 * delta:
                delta_new = 2.0 * delta
            if (actual < tol * cost and ratio > 0.25) or step_norm < tol * (tol + x_norm):
                done = True
                break
            if delta_new > 0:
                alpha *= delta / delta_new
            delta = delta_new
        if actual > 0.0:
            x, x_new = x_new, x
            cost = cost_new
            f, f_new = f_new, f
            jac, jac_new = jac_new, jac
            for i in range(m):  # an element loop: a slice copy would compile numba's shape-mismatch error
                f_true[i] = f[i]
            _robust(f, f_scale, soft_l1, jac, True)
    return x, f_true, jac


def residuals(prob: tuple, x: NDArray, m: int) -> NDArray[np.float64]:
    """The residuals (m,) of ``prob`` at ``x`` (no loss applied): :func:`solve` with one evaluation."""
    return solve(prob, np.asarray(x, float), m, np.ones(len(x)), 1, False, 1.0)[1]


def jacobian(prob: tuple, x: NDArray, m: int) -> NDArray[np.float64]:
    """The Jacobian (m, n) of :func:`residuals` at ``x``: :func:`solve` with one evaluation."""
    return solve(prob, np.asarray(x, float), m, np.ones(len(x)), 1, False, 1.0)[2]


@njit(cache=True, error_model="numpy")
def edge_nms(gx: NDArray, gy: NDArray, mag: NDArray, threshold: float, mask: NDArray,
             use_mask: bool) -> tuple[NDArray, NDArray, NDArray]:  # pragma: no cover - compiled
    """Sub-pixel edge points by non-maximum suppression along the quantised gradient direction.

    For each interior pixel with ``mag >= threshold`` (and ``mask`` if ``use_mask``): the
    unit gradient ``n = (gx, gy) / |(gx, gy)|`` rounded to the nearest of the eight
    neighbour offsets ``o``; kept if ``mag >= mag[+o]`` and ``mag > mag[-o]``; moved along
    ``o`` to the vertex of the parabola through the three magnitudes (clipped to half a
    pixel). Returns ``xy`` (N, 2), ``normal`` (N, 2) and ``strength`` (N,) in row-major
    pixel order.
    """
    h, w = mag.shape
    keep = np.zeros((h, w), np.bool_)
    n = 0
    for i in range(1, h - 1):
        for j in range(1, w - 1):
            c = mag[i, j]
            if not c >= threshold:
                continue
            if use_mask and not mask[i, j]:
                continue
            g0 = gx[i, j]
            g1 = gy[i, j]
            nrm = math.hypot(g0, g1)
            if not nrm > 0.0:
                continue
            ox = int(np.rint(g0 / nrm))
            oy = int(np.rint(g1 / nrm))
            if ox == 0 and oy == 0:
                continue
            if c >= mag[i + oy, j + ox] and c > mag[i - oy, j - ox]:
                keep[i, j] = True
                n += 1
    xy = np.empty((n, 2))
    normal = np.empty((n, 2))
    strength = np.empty(n)
    k = 0
    for i in range(1, h - 1):
        for j in range(1, w - 1):
            if not keep[i, j]:
                continue
            g0 = gx[i, j]
            g1 = gy[i, j]
            nrm = math.hypot(g0, g1)
            nx = g0 / nrm
            ny = g1 / nrm
            ox = int(np.rint(nx))
            oy = int(np.rint(ny))
            c = mag[i, j]
            ff = mag[i + oy, j + ox]
            bb = mag[i - oy, j - ox]
            den = ff - 2.0 * c + bb
            off = 0.5 * (bb - ff) / den if den < 0 else 0.0
            off = min(max(off, -0.5), 0.5)
            xy[k, 0] = j + off * ox
            xy[k, 1] = i + off * oy
            normal[k, 0] = nx
            normal[k, 1] = ny
            strength[k] = c
            k += 1
    return xy, normal, strength


@njit(cache=True, error_model="numpy", parallel=True)
def grid_counts(coef: NDArray, az: NDArray, el: NDArray, sub: NDArray, r0: int, c0: int, dt: NDArray,
                tol: float) -> tuple[NDArray, NDArray]:  # pragma: no cover - compiled
    """Counts of each node of a canting grid search: model points inside the mask, and of those near an edge.

    Model point ``n`` lies at pixel ``sum_k coef[k, n] b_k(a, e)`` with the quadratic basis
    ``b = (1, a, e, a^2, e^2, a e)`` at node ``(a, e) = (az[i], el[j])`` (node ``i * len(el) + j``).
    Rounded to the nearest pixel, it counts if the facet mask ``sub`` (an image crop) holds
    it, and scores if the distance transform ``dt`` (the same crop) there is ``<= tol``.
    A node's score is the share of its counted points that score, or -1 with fewer than
    ``min_inside`` counted. The crop's first pixel is ``(r0, c0)`` of the image.
    """
    n_el = el.shape[0]
    n_pts = coef.shape[1]
    hh, ww = sub.shape
    n_in = np.zeros(az.shape[0] * n_el, np.int64)
    n_near = np.zeros(az.shape[0] * n_el, np.int64)
    for i in prange(az.shape[0]):  # rows of the grid: disjoint nodes, one thread each
        a = az[i]
        for n in range(n_pts):
            # u(e) = ua + e (ub + uc e) along this row of the grid, v alike
            ua = coef[0, n, 0] + a * (coef[1, n, 0] + a * coef[3, n, 0])
            ub = coef[2, n, 0] + a * coef[5, n, 0]
            uc = coef[4, n, 0]
            va = coef[0, n, 1] + a * (coef[1, n, 1] + a * coef[3, n, 1])
            vb = coef[2, n, 1] + a * coef[5, n, 1]
            vc = coef[4, n, 1]
            for j in range(n_el):
                e = el[j]
                u = ua + e * (ub + uc * e) - c0
                v = va + e * (vb + vc * e) - r0
                if not (u > -0.5 and u < ww + 0.5 and v > -0.5 and v < hh + 0.5):
                    continue  # (and NaN)
                r = int(np.rint(v))
                c = int(np.rint(u))
                if r < 0 or r >= hh or c < 0 or c >= ww or not sub[r, c]:
                    continue
                g = i * n_el + j
                n_in[g] += 1
                if dt[r, c] <= tol:
                    n_near[g] += 1
    return n_in, n_near


def grid_scores(coef: NDArray, az: NDArray, el: NDArray, sub: NDArray, r0: int, c0: int, dt: NDArray, tol: float,
                min_inside: int) -> NDArray:
    """Chamfer score of each node of the canting grid search (:func:`grid_counts`): the share of the
    points inside the mask that lie near an edge, or -1 with fewer than ``min_inside`` inside."""
    n_in, n_near = grid_counts(coef, az, el, sub, r0, c0, dt, tol)
    return np.where(n_in >= min_inside, n_near / np.maximum(n_in, 1), -1.0)


@njit(cache=True, error_model="numpy")
def line_normals(uv: NDArray, seg: NDArray) -> NDArray:  # pragma: no cover - compiled
    """Unit normals (N, 2) of projected polylines: ``(-t_y, t_x)`` of the unit central difference
    of each point's neighbours on the same segment (one-sided at its ends); NaN where undefined."""
    n = uv.shape[0]
    out = np.empty((n, 2))
    for i in range(n):
        p = i - 1 if i > 0 and seg[i - 1] == seg[i] else i
        q = i + 1 if i < n - 1 and seg[i + 1] == seg[i] else i
        tx = uv[q, 0] - uv[p, 0]
        ty = uv[q, 1] - uv[p, 1]
        ln = math.sqrt(tx * tx + ty * ty)
        tx = tx / ln
        ty = ty / ln
        out[i, 0] = -ty
        out[i, 1] = tx
    return out


@njit(cache=True, error_model="numpy")
def unique_inverse(idx: NDArray, n: int) -> tuple[NDArray, NDArray]:  # pragma: no cover - compiled
    """``np.unique(idx, return_inverse=True)`` for indices in ``[0, n)``, in O(n + len(idx)) without a sort."""
    seen = np.zeros(n, np.bool_)
    for i in idx:
        seen[i] = True
    pos = np.empty(n, np.int64)
    used = np.empty(n, np.int64)
    c = 0
    for k in range(n):
        if seen[k]:
            pos[k] = c
            used[c] = k
            c += 1
    inv = np.empty(len(idx), np.int64)
    for i in range(len(idx)):
        inv[i] = pos[idx[i]]
    return used[:c].copy(), inv


@njit(cache=True, error_model="numpy", nogil=True)
def mirror_project(pts: NDArray, normals: NDArray, centre: NDArray, turns: NDArray, pivot: NDArray, rot: NDArray,
                   cpos: NDArray, cam: NDArray) -> NDArray:  # pragma: no cover - compiled
    """Pixels (G, N, 2) of world points (N, 3) mirrored in the plane through ``centre`` with unit normal
    ``normals[g]`` (G, 3), projected (:func:`project_rc`): a facet's reflection of the target for G canting
    angle pairs. With ``turns`` (G, 3, 3) the points are first turned about ``pivot`` by ``turns[g]`` (G
    turns of the heliostat, a normal each); with ``turns`` of no rows, not at all."""
    g_n, n = normals.shape[0], pts.shape[0]
    turned = turns.shape[0] > 0
    out = np.empty((g_n, n, 2))
    virt = np.empty((n, 3))
    w = np.empty(3)
    for g in range(g_n):
        nv = normals[g]
        for i in range(n):
            if turned:
                m = turns[g]
                for k in range(3):
                    w[k] = pivot[k] + (m[k, 0] * (pts[i, 0] - pivot[0]) + m[k, 1] * (pts[i, 1] - pivot[1])
                                       + m[k, 2] * (pts[i, 2] - pivot[2]))
            else:
                for k in range(3):
                    w[k] = pts[i, k]
            t = 2.0 * ((w[0] - centre[0]) * nv[0] + (w[1] - centre[1]) * nv[1] + (w[2] - centre[2]) * nv[2])
            for k in range(3):
                virt[i, k] = w[k] - t * nv[k]
        out[g] = project_rc(rot, cpos, virt, cam)
    return out


@njit(cache=True, error_model="numpy")
def reflect_in_mask(pts: NDArray, seg: NDArray, centre: NDArray, normal: NDArray, rot: NDArray, cpos: NDArray,
                    cam: NDArray, sub: NDArray, r0: int,
                    c0: int) -> tuple[NDArray, NDArray, NDArray, NDArray]:  # pragma: no cover - compiled
    """World points (N, 3) mirrored in the plane through ``centre`` with unit ``normal``, projected
    (:func:`project_rc`), with their polyline normals (:func:`line_normals`), whether each falls in a mask and
    whether it is also usable (in the mask with a finite normal): one pass for a canting fit's round.

    The mask is ``sub`` at rows ``r0..``, columns ``c0..`` of the image, a point in it when the pixel its
    ``(u, v)`` rounds to (half to even) is True (``pihim.inspection.reflection._Mask.inside``).
    """
    n = pts.shape[0]
    uv = mirror_project(pts, normal.reshape(1, 3), centre, np.zeros((0, 3, 3)), centre, rot, cpos, cam)[0]
    nrm = line_normals(uv, seg)
    hh, ww = sub.shape
    ins = np.zeros(n, np.bool_)
    usable = np.zeros(n, np.bool_)
    for i in range(n):
        u, v = uv[i, 0], uv[i, 1]
        if not (u > c0 - 1.5 and u < c0 + ww + 0.5 and v > r0 - 1.5 and v < r0 + hh + 0.5):
            continue
        r = int(np.rint(v)) - r0
        c = int(np.rint(u)) - c0
        if 0 <= r < hh and 0 <= c < ww and sub[r, c]:
            ins[i] = True
            usable[i] = np.isfinite(nrm[i, 0]) and np.isfinite(nrm[i, 1])
    return uv, nrm, ins, usable


@njit(cache=True, error_model="numpy")
def nearest_within(model: NDArray, obs: NDArray, gate: float,
                   normals: NDArray) -> tuple[NDArray, NDArray]:  # pragma: no cover - compiled
    """For each point of ``obs`` (M, 2), the index of the nearest point of ``model`` (N, 2, finite)
    closer than ``gate`` (-1 if none), and whether another model point is exactly as near.

    Of equally near points (a polyline's corner, which ends one side and starts the next) the one whose line
    -- through it with its unit normal of ``normals`` (N, 2) -- passes nearest the edge point is taken, the
    first of those alike; with ``normals`` of no rows, the first. A bucket grid of cells at least ``gate``
    wide, about one model point each (at most 512 x 512 cells).
    """
    n = model.shape[0]
    lines = normals.shape[0] == n
    out = np.full(obs.shape[0], -1, np.int64)
    tie = np.zeros(obs.shape[0], np.bool_)
    if n == 0 or not gate > 0:
        return out, tie
    x0, y0 = model[:, 0].min(), model[:, 1].min()
    x1, y1 = model[:, 0].max(), model[:, 1].max()
    # cells of about the area per model point, at least the gate: a gate of a pixel or two over a large model
    # would make far more cells to build than points to sort into them
    cell = max(gate, (x1 - x0) / 512.0, (y1 - y0) / 512.0, math.sqrt((x1 - x0) * (y1 - y0) / n))
    nx = int((x1 - x0) / cell) + 1
    ny = int((y1 - y0) / cell) + 1
    start = np.zeros(nx * ny + 1, np.int64)
    cid = np.empty(n, np.int64)
    for k in range(n):
        cid[k] = int((model[k, 1] - y0) / cell) * nx + int((model[k, 0] - x0) / cell)
        start[cid[k] + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for k in range(n):  # counting sort by cell
        order[fill[cid[k]]] = k
        fill[cid[k]] += 1
    g2 = gate * gate
    for m in range(obs.shape[0]):
        ox = obs[m, 0]
        oy = obs[m, 1]
        if not (ox > x0 - gate and ox < x1 + gate and oy > y0 - gate and oy < y1 + gate):
            continue
        # the cells the gate's disc reaches
        cxa = max(int(math.floor((ox - gate - x0) / cell)), 0)
        cxb = min(int(math.floor((ox + gate - x0) / cell)), nx - 1)
        cya = max(int(math.floor((oy - gate - y0) / cell)), 0)
        cyb = min(int(math.floor((oy + gate - y0) / cell)), ny - 1)
        best = g2
        bi = -1
        same = False
        for yy in range(cya, cyb + 1):
            for xx in range(cxa, cxb + 1):
                c = yy * nx + xx
                for t in range(start[c], start[c + 1]):
                    k = order[t]
                    dx = model[k, 0] - ox
                    dy = model[k, 1] - oy
                    d2 = dx * dx + dy * dy
                    if d2 < best:
                        best = d2
                        bi = k
                        same = False
                    elif d2 == best and bi >= 0:
                        same = True
                        if lines:
                            dk = abs(normals[k, 0] * dx + normals[k, 1] * dy)
                            db = abs(normals[bi, 0] * (model[bi, 0] - ox) + normals[bi, 1] * (model[bi, 1] - oy))
                            if dk < db or (dk == db and k < bi):
                                bi = k
                        elif k < bi:
                            bi = k
        out[m] = bi
        tie[m] = same
    return out, tie


@njit(cache=True, error_model="numpy")
def facet_normal(aux: NDArray, az: float, el: float) -> NDArray:  # pragma: no cover - compiled
    """World (ENU) unit normal of a facet tilted by canting ``(az, el)`` mrad: its design normal (heliostat
    frame) turned about the heliostat's x axis by ``el``, then about its y axis by ``az``, then by the HUA's
    rotation (``aux`` as for a ``REFLECTION`` problem: rotation row-major, centre, design normal) --
    ``rot @ pihim.field.kinematics.apply_canting_deviation(normal, az, el)`` for one pair of angles, without
    its validation and broadcasting (every round of every canting fit)."""
    x, y, z = aux[12], aux[13], aux[14]
    c, s = math.cos(el * 1e-3), math.sin(el * 1e-3)
    y, z = c * y + s * z, -s * y + c * z
    c, s = math.cos(az * 1e-3), math.sin(az * 1e-3)
    t0, t1, t2 = c * x + s * z, y, -s * x + c * z
    out = np.empty(3)
    for i in range(3):
        out[i] = aux[3 * i] * t0 + aux[3 * i + 1] * t1 + aux[3 * i + 2] * t2
    return out


@njit(cache=True, error_model="numpy")
def _window_project(pts, seg, centre, normal, rot, cpos, cam, sub, r0, c0, box, window_px, rate, az, el,
                    ref, where, part_pts, part_seg):  # pragma: no cover - compiled
    """A round's :func:`reflect_in_mask` of the outline points in a fit's window (see :func:`refine_reflection`).

    ``ref`` (3,) holds whether the window is set and its angles; ``where`` the indices of its points, ``part_pts``
    and ``part_seg`` those points. Returns the projection, whether it was of the window's points, and the window.
    """
    if ref[0] > 0.0 and rate * math.hypot(az - ref[1], el - ref[2]) < window_px:
        uv, nrm, ins, usable = reflect_in_mask(part_pts, part_seg, centre, normal, rot, cpos, cam, sub, r0, c0)
        return uv, nrm, ins, usable, True, where, part_pts, part_seg
    uv, nrm, ins, usable = reflect_in_mask(pts, seg, centre, normal, rot, cpos, cam, sub, r0, c0)
    if box[0] <= box[1]:  # the mask has a pixel: the points within ``window_px`` of its box, and their neighbours
        n = uv.shape[0]
        near = np.zeros(n, np.bool_)
        for i in range(n):
            u, v = uv[i, 0], uv[i, 1]
            near[i] = (u > box[2] - window_px and u < box[3] + window_px and v > box[0] - window_px
                       and v < box[1] + window_px)
        keep = near.copy()
        for i in range(n):
            if near[i]:
                if i > 0:
                    keep[i - 1] = True
                if i < n - 1:
                    keep[i + 1] = True
        where = np.flatnonzero(keep)
        part_pts = np.empty((where.shape[0], 3))
        part_seg = np.empty(where.shape[0], np.int64)
        for k in range(where.shape[0]):
            for d in range(3):
                part_pts[k, d] = pts[where[k], d]
            part_seg[k] = seg[where[k]]
        ref[0], ref[1], ref[2] = 1.0, az, el
    return uv, nrm, ins, usable, False, where, part_pts, part_seg


@njit(cache=True, error_model="numpy", nogil=True)
def refine_reflection(pts: NDArray, seg: NDArray, aux: NDArray, rot: NDArray, cpos: NDArray, cam: NDArray,
                      sub: NDArray, r0: int, c0: int, box: NDArray, rate: float, window_px: float, obs: NDArray,
                      dt: NDArray, gates: NDArray, az: float, el: float, x_scale: NDArray, min_usable: int,
                      min_hits: int, f_scale: float) -> tuple:  # pragma: no cover - compiled
    """A facet's canting fit from ``(az, el)`` mrad: point-to-line ICP, one round per gate of ``gates`` (px).

    Each round mirrors the target's outline ``pts`` (N, 3; polyline ids ``seg``) in the facet at the current
    angles and projects it (:func:`reflect_in_mask`, the facet's mask ``sub`` at ``(r0, c0)``); pairs each edge
    point of ``obs`` (M, 2) with its nearest usable outline point within the gate (:func:`nearest_within`, with
    line normals); and solves the two angles by :func:`solve` (soft-L1 with scale ``f_scale``, at most 200
    evaluations) on the ``REFLECTION`` residuals of the matched points, line normals held for the round.

    The window: a round projects only the points within ``window_px`` of the mask's bounding box ``box`` (first
    and last row, first and last column; first > last for an empty mask) at the angles where all were last
    projected, and their neighbours along the outline, while ``rate`` (px per mrad, a bound of any point's
    motion) times the angles' distance from those stays below ``window_px``: no other point can reach the mask,
    so the points in it, their order and line normals are those of all points.

    Returns
    -------
    status : int
        0, or 1 when fewer than ``min_usable`` outline points are usable in the mask, 2 when fewer than
        ``min_hits`` edge points match.
    count : int
        The usable or matched count that failed (0 with status 0).
    az, el : float
        The fitted angles, mrad.
    r : ndarray, shape (K,)
        The last round's residuals, px (no loss applied).
    idx : ndarray of int, shape (K,)
        The outline point of each residual.
    q, nq : ndarray, shape (K, 2)
        The matched edge points and the outline's line normals there.
    inside : int
        Outline points in the mask at the fitted angles.
    support : float
        The share of those on an image edge: the distance transform ``dt`` (the whole image) ``<= 1.5`` at the
        pixel each rounds to; 0 with none inside.
    """
    centre = aux[9:12].copy()
    ref = np.zeros(3)
    where = np.zeros(0, np.int64)
    part_pts = np.zeros((0, 3))
    part_seg = np.zeros(0, np.int64)
    r = np.zeros(0)
    idx = np.zeros(0, np.int64)
    q = np.zeros((0, 2))
    nq = np.zeros((0, 2))
    no_prox = np.zeros((1, 1), np.float32)
    for gi in range(gates.shape[0]):
        gate = gates[gi]
        normal = facet_normal(aux, az, el)
        uv, nrm, ins, usable, windowed, where, part_pts, part_seg = _window_project(
            pts, seg, centre, normal, rot, cpos, cam, sub, r0, c0, box, window_px, rate, az, el, ref, where,
            part_pts, part_seg)
        use = np.flatnonzero(usable)
        if use.shape[0] < min_usable:
            return 1, use.shape[0], az, el, r, idx, q, nq, 0, 0.0
        model = np.empty((use.shape[0], 2))
        mnrm = np.empty((use.shape[0], 2))
        for i in range(use.shape[0]):
            model[i, 0], model[i, 1] = uv[use[i], 0], uv[use[i], 1]
            mnrm[i, 0], mnrm[i, 1] = nrm[use[i], 0], nrm[use[i], 1]
        j, _ = nearest_within(model, obs, gate, mnrm)
        hit = np.flatnonzero(j >= 0)
        if hit.shape[0] < min_hits:
            return 2, hit.shape[0], az, el, r, idx, q, nq, 0, 0.0
        k = np.empty(hit.shape[0], np.int64)
        q = np.empty((hit.shape[0], 2))
        nq = np.empty((hit.shape[0], 2))
        qn = np.empty((hit.shape[0], 4))
        for i in range(hit.shape[0]):
            k[i] = use[j[hit[i]]]
            q[i, 0], q[i, 1] = obs[hit[i], 0], obs[hit[i], 1]
            nq[i, 0], nq[i, 1] = nrm[k[i], 0], nrm[k[i], 1]
            qn[i, 0], qn[i, 1], qn[i, 2], qn[i, 3] = q[i, 0], q[i, 1], nq[i, 0], nq[i, 1]
        # only the matched outline points move; their line normals are held for the round
        used, inv = unique_inverse(k, uv.shape[0])
        if windowed:
            idx = where[k]
            used = where[used]
        else:
            idx = k
        moved = np.empty((used.shape[0], 3))
        for i in range(used.shape[0]):
            for d in range(3):
                moved[i, d] = pts[used[i], d]
        prob = (REFLECTION, rot, cpos, moved, cam, no_prox, qn, aux, inv, gate)
        x0 = np.empty(2)
        x0[0], x0[1] = az, el
        x, r, _ = solve(prob, x0, hit.shape[0], x_scale, 200, True, f_scale)
        az, el = x[0], x[1]
    normal = facet_normal(aux, az, el)
    uv, nrm, ins, usable, windowed, where, part_pts, part_seg = _window_project(
        pts, seg, centre, normal, rot, cpos, cam, sub, r0, c0, box, window_px, rate, az, el, ref, where,
        part_pts, part_seg)
    inside = 0
    on_edge = 0
    for i in range(uv.shape[0]):
        if ins[i]:
            inside += 1
            if dt[int(np.rint(uv[i, 1])), int(np.rint(uv[i, 0]))] <= 1.5:
                on_edge += 1
    support = on_edge / inside if inside else 0.0
    return 0, 0, az, el, r, idx, q, nq, inside, support
