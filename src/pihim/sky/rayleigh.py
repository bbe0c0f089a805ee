"""Single-scattering Rayleigh skylight polarization in 3-D Stokes frames.

For skylight arriving from the sky direction ``v`` (unit vector from the
observer toward the sky) with the sun in direction ``s``, the scattering
angle ``g`` is the angle between ``v`` and ``s`` and

.. math::

    \\mathrm{DoLP} = d_{max}\\, \\frac{\\sin^2 g}{1 + \\cos^2 g},

the electric field oscillating **perpendicular to the scattering plane** (the
plane containing ``s`` and ``v``), i.e. along ``s x v`` [1]_, [2]_. The light
travels along ``d = -v``. This is the model of the paper's Fig. 2c-d and of
section 4.1 [3]_; ``d_max`` < 1 accounts, crudely, for depolarisation by
multiple scattering, aerosols and molecular anisotropy.

Implementation: with ``n = s x v`` (``|n|^2 = sin^2 g``) and a frame
``(d, e)``, the field makes the angle ``alpha`` with ``e`` where
``cos alpha ~ n.e`` and ``sin alpha ~ n.(d x e)``, so

.. math::

    S_1 = S_0\\, d_{max} \\frac{(n\\cdot e)^2 - (n\\cdot(d\\times e))^2}{1 + \\cos^2 g},\\quad
    S_2 = S_0\\, d_{max} \\frac{2 (n\\cdot e)(n\\cdot(d\\times e))}{1 + \\cos^2 g},

which has no singularity at the sun or the antisun (there ``n = 0`` and the
light is unpolarized).

References
----------
.. [1] K. L. Coulson, *Polarization and Intensity of Light in the
   Atmosphere*, A. Deepak Publishing, 1988, ch. 2 and 6.
.. [2] G. Horvath, D. Varju, *Polarized Light in Animal Vision*, Springer,
   2004, ch. 4 (Rayleigh sky pattern, E-vector perpendicular to the
   scattering plane).
.. [3] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone" (pihim paper), section 3 and Fig. 2c-d.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError

__all__ = [
    "meridian_frame",
    "pack_stokes",
    "prepare_frame",
    "rayleigh_components",
    "rayleigh_core",
    "rayleigh_dolp",
    "rayleigh_stokes",
]


def rayleigh_dolp(scattering_angle_deg: ArrayLike, dmax: float = 1.0) -> NDArray[np.float64]:
    """Rayleigh single-scattering DoLP ``dmax sin^2 g / (1 + cos^2 g)`` for scattering angles in degrees.

    ``dmax`` (the DoLP at 90 deg from the sun) must lie in [0, 1], as in
    :class:`pihim.sky.model.SkyModel`.
    """
    if not 0.0 <= dmax <= 1.0:
        raise PihimInputError(f"dmax must lie in [0, 1], got {dmax!r}")
    g_rad = np.radians(np.asarray(scattering_angle_deg, dtype=float))
    c2 = np.cos(g_rad) ** 2
    return dmax * (1.0 - c2) / (1.0 + c2)


def _unit(v: ArrayLike, what: str) -> NDArray[np.float64]:
    v = np.asarray(v, dtype=float)
    if v.ndim == 0 or v.shape[-1] != 3:
        raise PihimInputError(f"{what} need 3 components on the last axis, got shape {np.shape(v)}")
    n = np.sqrt(v[..., 0] ** 2 + v[..., 1] ** 2 + v[..., 2] ** 2)
    if not np.all(np.isfinite(n)) or np.any(n == 0.0):
        raise PihimInputError(f"{what} must be finite, non-zero vectors")
    if np.all(np.abs(n - 1.0) < 1e-12):
        return v
    return v / n[..., None]


def _dot(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Dot product along the last axis (faster than einsum for broadcast 3-vectors)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _cross(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cross product along the last axis, broadcasting."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


def meridian_frame(view_dirs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Default reference axes ``e`` and ``d x e`` for skylight from unit sky directions ``v``.

    ``e`` is :func:`~pihim.polarimetry.frames.perpendicular_reference` of
    ``d = -v`` (the zenith direction projected perpendicular to ``v``: "up"
    along the local meridian; East where ``v`` is vertical), written in closed
    form: with ``r = sqrt(x^2 + y^2)``, ``e = (-z x / r, -z y / r, r)`` and
    ``d x e = (-y / r, x / r, 0)`` -- horizontal, pointing to the left of an
    observer who faces the azimuth of ``v``.
    """
    v = np.asarray(view_dirs, dtype=float)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    r = np.hypot(x, y)
    weak = r < 1e-9
    if np.any(weak):
        # perpendicular_reference's fallback: East projected perpendicular to d
        ef = np.stack([1.0 - x * x, -x * y, -x * z], axis=-1)
        ef /= np.linalg.norm(ef, axis=-1, keepdims=True)
        r_safe = np.where(weak, 1.0, r)
    else:
        r_safe = r
    inv = 1.0 / r_safe
    e = np.stack([-z * x * inv, -z * y * inv, r], axis=-1)
    f = np.stack([-y * inv, x * inv, np.zeros_like(x)], axis=-1)
    if np.any(weak):
        e = np.where(weak[..., None], ef, e)
        f = np.where(weak[..., None], _cross(-v, ef), f)
    return e, f


def prepare_frame(
    view_dirs: ArrayLike, sun_dir: ArrayLike, e: ArrayLike | None
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Validated unit ``v``, ``s``, frame axis ``e`` and ``d x e`` for skylight from ``view_dirs``.

    ``e`` defaults to the local meridian "up" (:func:`meridian_frame`, equal
    to ``perpendicular_reference(-v)``). A given ``e`` must be perpendicular
    to ``v`` (to 1e-6) and is normalised.

    Returns
    -------
    v, s, e, f : numpy.ndarray
        ``v`` (..., 3), ``s`` broadcastable to it, ``e`` (..., 3) and
        ``f = d x e`` (..., 3) with ``d = -v``.
    """
    v = _unit(view_dirs, "view directions")
    s = _unit(sun_dir, "sun directions")
    try:
        shape = np.broadcast_shapes(v.shape, s.shape)
    except ValueError:
        raise PihimInputError(
            f"sun direction shape {s.shape} does not broadcast against view directions {v.shape}"
        ) from None
    if shape != v.shape:
        v = np.broadcast_to(v, shape)
    if e is None:
        e_arr, f = meridian_frame(v)
        return v, s, e_arr, f
    e_arr = _unit(e, "reference axes e")
    try:
        e_arr = np.array(np.broadcast_to(e_arr, shape), dtype=float)
    except ValueError:
        raise PihimInputError(f"reference axes of shape {e_arr.shape} do not match view directions {shape}") from None
    if np.any(np.abs(_dot(e_arr, v)) > 1e-6):
        raise PihimInputError("reference axes e must be perpendicular to the view directions")
    return v, s, e_arr, _cross(-v, e_arr)


def stokes_in_frame(
    components: Callable[..., tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]],
    view_dirs: ArrayLike,
    sun_dir: ArrayLike,
    e: ArrayLike | None,
    *params: Any,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Validate the inputs, build the Stokes frame and pack ``components`` into ``(..., 4)`` Stokes vectors.

    The common body of :func:`rayleigh_stokes`,
    :func:`pihim.sky.berry.berry_stokes` and
    :meth:`pihim.sky.model.SkyModel.stokes`.

    Parameters
    ----------
    components : callable
        ``components(v, s, e, f, *params) -> (S0, S1, S2)`` on prepared unit
        vectors (e.g. :func:`rayleigh_components`).
    view_dirs, sun_dir, e : array_like
        As for :func:`prepare_frame`.
    *params
        Passed to ``components`` after the four vectors.

    Returns
    -------
    tuple of numpy.ndarray
        :func:`pack_stokes` of the components, shape (..., 4), and the
        reference axes ``e`` of its frame ``(d, e)``, shape (..., 3).
    """
    v, s, e_arr, f = prepare_frame(view_dirs, sun_dir, e)
    return pack_stokes(*components(v, s, e_arr, f, *params)), e_arr


def rayleigh_components(
    v: NDArray[np.float64],
    s: NDArray[np.float64],
    e: NDArray[np.float64],
    f: NDArray[np.float64],
    dmax: float,
    s0: ArrayLike,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Rayleigh ``(S0, S1, S2)`` as separate arrays for prepared unit vectors (no validation)."""
    n = _cross(s, v)  # E-field direction, |n| = sin g
    cos_g = _dot(v, s)
    ne = _dot(n, e)
    nf = _dot(n, f)
    s0 = np.broadcast_to(np.asarray(s0, dtype=float), cos_g.shape)
    k = s0 * (dmax / (1.0 + cos_g * cos_g))
    return s0, k * (ne * ne - nf * nf), k * (2.0 * ne * nf)


def pack_stokes(
    s0: NDArray[np.float64], s1: NDArray[np.float64], s2: NDArray[np.float64]
) -> NDArray[np.float64]:
    """C-ordered ``(..., 4)`` Stokes array ``(S0, S1, S2, 0)`` from components."""
    out = np.empty((*np.shape(s1), 4))
    out[..., 0] = s0
    out[..., 1] = s1
    out[..., 2] = s2
    out[..., 3] = 0.0
    return out


def rayleigh_core(
    v: NDArray[np.float64],
    s: NDArray[np.float64],
    e: NDArray[np.float64],
    f: NDArray[np.float64],
    dmax: float,
    s0: ArrayLike,
) -> NDArray[np.float64]:
    """Rayleigh Stokes ``(..., 4)`` for prepared unit vectors (no validation; see :func:`rayleigh_stokes`)."""
    return pack_stokes(*rayleigh_components(v, s, e, f, dmax, s0))


def rayleigh_stokes(
    view_dirs: ArrayLike,
    sun_dir: ArrayLike,
    e: ArrayLike | None = None,
    *,
    dmax: float = 1.0,
    s0: ArrayLike = 1.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Stokes vectors of Rayleigh skylight arriving from ``view_dirs``.

    Parameters
    ----------
    view_dirs : array_like, shape (..., 3)
        Unit ENU vectors from the observer toward the sky. The light
        propagates along ``d = -view_dirs``.
    sun_dir : array_like, shape (3,) or broadcastable
        Unit ENU vector toward the sun.
    e : array_like, shape (..., 3), optional
        Reference axis of the returned Stokes vectors, perpendicular to the
        view directions. Default: the local meridian "up"
        (:func:`meridian_frame`).
    dmax : float
        DoLP at 90 deg from the sun, in [0, 1].
    s0 : array_like
        Total intensity S0 (broadcast against ``view_dirs[..., 0]``).

    Returns
    -------
    stokes : numpy.ndarray, shape (..., 4)
        ``(S0, S1, S2, S3)`` in the frame ``(d, e)``; ``S3 = 0``.
    e : numpy.ndarray, shape (..., 3)
        The reference axes used.

    Notes
    -----
    No horizon handling here: directions below the horizon are evaluated
    like any other (:class:`pihim.sky.model.SkyModel` zeroes them).
    """
    return stokes_in_frame(rayleigh_components, view_dirs, sun_dir, e, dmax, s0)
