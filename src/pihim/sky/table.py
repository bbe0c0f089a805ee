"""Sky Stokes tabulated on a Lambert azimuthal equal-area grid, for compiled kernels.

The ground model's sky integral and the renderer sample the sky thousands
of times per direction bundle; both take it from this table by bilinear
interpolation instead of calling the sky model for every direction.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from pihim.polarimetry.frames import as_stokes4, change_reference, normalize

__all__ = ["SkyTable", "sample_table", "table_axis"]


def table_axis(l: NDArray[np.float64]) -> NDArray[np.float64]:
    """Smooth reference axis ``e_T(l)`` normal to ``l`` over the whole upper hemisphere.

    ``x`` carried by the smallest rotation that takes ``z`` to ``l``:
    ``e_T = x - l_x / (1 + l_z) (l + z)``; unit and normal to ``l`` exactly,
    singular only at the nadir.
    """
    f = l[..., 0] / (1.0 + l[..., 2])
    e = -f[..., None] * l
    e[..., 0] += 1.0
    e[..., 2] -= f
    return e


class SkyTable:
    """Sky Stokes tabulated on a square grid of Lambert azimuthal equal-area coordinates.

    Node ``(X, Y)`` in ``[-sqrt 2, sqrt 2]^2`` is the incoming direction with
    ``l_z = 1 - r^2 / 2`` and ``(l_x, l_y) = (X, Y) sqrt(1 - r^2 / 4)``
    (``r^2 = X^2 + Y^2``); nodes outside the disc are clamped to just above
    the horizon so that interpolation near the horizon stays continuous.
    Stokes are stored in frame ``(d = -l, e_T(l))`` (:func:`table_axis`),
    which is continuous across the zenith, so bilinear interpolation of the
    four components is meaningful everywhere above the horizon. The grid
    spacing is ``2 sqrt 2 / (size - 1)`` rad of Lambert radius, about
    0.63 deg of arc at the zenith and 0.9 deg at the horizon for size 257.
    """

    def __init__(self, sky: object, sun_dir: NDArray[np.float64], size: int) -> None:
        self.sun_dir = np.array(sun_dir, dtype=float)  # the sun it was built for (a copy)
        self.radius = math.sqrt(2.0)
        self.size = size
        self.step = 2.0 * self.radius / (size - 1)
        x = np.linspace(-self.radius, self.radius, size)
        xx, yy = np.meshgrid(x, x, indexing="ij")
        r2 = np.minimum(xx**2 + yy**2, 2.0)
        lz = np.maximum(1.0 - 0.5 * r2, 1e-6)
        k = np.sqrt(np.maximum(1.0 - lz**2, 0.0) / np.maximum(r2, 1e-300))
        l = np.stack([xx * k, yy * k, lz], axis=-1)
        l[r2 == 0.0] = (0.0, 0.0, 1.0)
        l = normalize(l)
        s, e_sky = sky.stokes(l, sun_dir)
        self.table = np.ascontiguousarray(change_reference(as_stokes4(s), -l, e_sky, table_axis(l)))

    def sample(self, l: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Interpolated sky Stokes ``(..., 4)`` arriving from ``l`` and their axes ``e_T(l)`` (numpy)."""
        k = np.sqrt(2.0 / (1.0 + l[..., 2]))
        fx = (l[..., 0] * k + self.radius) / self.step
        fy = (l[..., 1] * k + self.radius) / self.step
        ix = np.clip(fx.astype(np.intp), 0, self.size - 2)
        iy = np.clip(fy.astype(np.intp), 0, self.size - 2)
        tx = (fx - ix)[..., None]
        ty = (fy - iy)[..., None]
        t = self.table
        s = (1 - tx) * (1 - ty) * t[ix, iy] + tx * (1 - ty) * t[ix + 1, iy] + (1 - tx) * ty * t[ix, iy + 1]
        s = s + tx * ty * t[ix + 1, iy + 1]
        return s, table_axis(l)


@njit(inline="always", cache=True)
def sample_table(table, radius, step, lx, ly, lz):  # pragma: no cover - compiled
    """Compiled :meth:`SkyTable.sample` for one direction ``l`` (``lz > -1``).

    Returns ``(s0, s1, s2, s3, ex, ey, ez)``: the bilinearly interpolated
    Stokes vector and its axis ``e_T(l)``. Used inside the numba kernels of the
    ground model and the renderer.
    """
    m = table.shape[0]
    k = math.sqrt(2.0 / (1.0 + lz))
    fx = (lx * k + radius) / step
    fy = (ly * k + radius) / step
    ix = min(max(int(fx), 0), m - 2)
    iy = min(max(int(fy), 0), m - 2)
    tx = fx - ix
    ty = fy - iy
    w00 = (1.0 - tx) * (1.0 - ty)
    w10 = tx * (1.0 - ty)
    w01 = (1.0 - tx) * ty
    w11 = tx * ty
    a = table[ix, iy]
    b = table[ix + 1, iy]
    c = table[ix, iy + 1]
    d = table[ix + 1, iy + 1]
    s0 = w00 * a[0] + w10 * b[0] + w01 * c[0] + w11 * d[0]
    s1 = w00 * a[1] + w10 * b[1] + w01 * c[1] + w11 * d[1]
    s2 = w00 * a[2] + w10 * b[2] + w01 * c[2] + w11 * d[2]
    s3 = w00 * a[3] + w10 * b[3] + w01 * c[3] + w11 * d[3]
    f = lx / (1.0 + lz)
    return s0, s1, s2, s3, 1.0 - f * lx, -f * ly, -f * (lz + 1.0)
