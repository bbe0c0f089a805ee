"""The analyser matrix of a four-channel division-of-focal-plane polarimeter.

Each channel ``k`` of a DoFP super-pixel measures

.. math:: I_k = \\tfrac{1}{2} t_k \\left(S_0 + d_k (S_1 \\cos 2\\theta_k
          + S_2 \\sin 2\\theta_k)\\right), \\qquad d_k = \\frac{ER_k - 1}{ER_k + 1}

with transmission (gain) ``t_k``, transmission-axis angle ``theta_k`` and
extinction ratio ``ER_k = T_max / T_min`` (diattenuation ``d_k``). Stacked,
``I = A S`` with ``A`` the 4x3 analyser matrix; Stokes are recovered by least
squares, ``S = pinv(A) I``. For the ideal analyser (t = 1, ER = inf, angles
0/45/90/135) the pseudo-inverse is exactly the paper's eq. (1).

Channels are always ordered by nominal angle: 0, 45, 90, 135 deg.

References
----------
.. [1] M. Tian et al., "Heliostat Optical Error Inspection with Polarimetric
   Imaging Drone", eq. (1) and section 4.4 (channel transmission correction).
.. [2] J. S. Tyo, D. L. Goldstein, D. B. Chenault, J. A. Shaw, "Review of
   passive imaging polarimetry for remote sensing applications",
   Appl. Opt. 45(22), 5453-5469 (2006), doi:10.1364/AO.45.005453.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.errors import PihimInputError

#: Nominal transmission-axis angles of the four channels, in channel order.
NOMINAL_ANGLES_DEG: tuple[float, float, float, float] = (0.0, 45.0, 90.0, 135.0)

_SCHEMA_ID = "pihim.analyser/1"

#: Channel transmissions ``t_k`` accepted in an analyser matrix (the ideal analyser has 1).
TRANSMISSION_RANGE = (1e-3, 1e3)
#: Largest condition number accepted (the ideal analyser has sqrt(2); noise is amplified by up to this).
MAX_CONDITION_NUMBER = 1e6


@dataclass(frozen=True)
class AnalyserMatrix:
    """A 4x3 analyser matrix ``A`` with ``I = A @ [S0, S1, S2]``.

    Parameters
    ----------
    matrix : array_like, shape (4, 3)
        Rows are channels in nominal-angle order (0, 45, 90, 135 deg).

    Examples
    --------
    >>> A = AnalyserMatrix.ideal()
    >>> A.pinv.round(3)
    array([[ 0.5,  0.5,  0.5,  0.5],
           [ 1. ,  0. , -1. ,  0. ],
           [ 0. ,  1. ,  0. , -1. ]])
    """

    matrix: NDArray[np.float64]
    pinv: NDArray[np.float64] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        m = np.array(self.matrix, dtype=np.float64)
        if m.shape != (4, 3):
            raise PihimInputError(f"analyser matrix must be a finite 4x3 array, got shape {m.shape}")
        if not np.all(np.isfinite(m)):
            row, col = (int(i) for i in np.argwhere(~np.isfinite(m))[0])
            raise PihimInputError(f"analyser matrix must be finite; entry [{row}][{col}] is {float(m[row, col])!r}")
        if np.linalg.matrix_rank(m) < 3:
            raise PihimInputError("analyser matrix is rank deficient: Stokes cannot be recovered")
        t = 2.0 * m[:, 0]
        lo, hi = TRANSMISSION_RANGE
        if not np.all((t >= lo) & (t <= hi)):
            raise PihimInputError(
                f"analyser matrix transmissions (twice its first column) must be in [{lo:g}, {hi:g}], "
                f"got {', '.join(f'{v:.3g}' for v in t)}"
            )
        cond = float(np.linalg.cond(m))
        if not cond <= MAX_CONDITION_NUMBER:
            raise PihimInputError(
                f"analyser matrix is ill-conditioned (condition number {cond:.3g} > {MAX_CONDITION_NUMBER:g}): "
                "Stokes cannot be recovered reliably"
            )
        m.setflags(write=False)
        p = np.linalg.pinv(m)
        # snap round-off (e.g. 1e-17 instead of 0 for the ideal matrix) so that
        # unpolarized light gives S1 = S2 = 0 exactly
        p[np.abs(p) < 1e-12 * np.abs(p).max()] = 0.0
        p.setflags(write=False)
        object.__setattr__(self, "matrix", m)
        object.__setattr__(self, "pinv", p)

    @classmethod
    def ideal(cls) -> AnalyserMatrix:
        """Ideal polarizers at 0/45/90/135 deg (reproduces paper eq. 1)."""
        return _IDEAL

    @classmethod
    def from_parameters(
        cls,
        angles_deg: ArrayLike,
        transmission: ArrayLike = 1.0,
        extinction_ratio: ArrayLike = math.inf,
    ) -> AnalyserMatrix:
        """Build the matrix from per-channel angle, transmission and extinction ratio.

        Parameters
        ----------
        angles_deg : array_like, shape (4,)
            Transmission-axis angles in degrees, channel order 0/45/90/135.
        transmission : float or array_like, shape (4,)
            Channel gain ``t_k``: unpolarized light of intensity S0 gives
            ``t_k * S0 / 2``.
        extinction_ratio : float or array_like, shape (4,)
            ``T_max / T_min`` (>= 1; ``inf`` for an ideal polarizer).
        """
        theta = np.radians(np.broadcast_to(np.asarray(angles_deg, dtype=float), (4,)))
        t = np.broadcast_to(np.asarray(transmission, dtype=float), (4,))
        er = np.broadcast_to(np.asarray(extinction_ratio, dtype=float), (4,))
        if np.any(t <= 0) or np.any(er < 1) or np.any(np.isnan(er)):
            raise PihimInputError("transmission must be > 0 and extinction ratio >= 1")
        with np.errstate(invalid="ignore"):
            d = np.where(np.isinf(er), 1.0, (er - 1.0) / (er + 1.0))
        rows = 0.5 * t[:, None] * np.stack(
            [np.ones(4), d * np.cos(2 * theta), d * np.sin(2 * theta)], axis=1
        )
        return cls(rows)

    # -- derived parameters -------------------------------------------------
    @property
    def transmission(self) -> NDArray[np.float64]:
        """Per-channel gain ``t_k = 2 A[k, 0]``."""
        return 2.0 * self.matrix[:, 0]

    @property
    def diattenuation(self) -> NDArray[np.float64]:
        """Per-channel diattenuation ``d_k`` in [0, 1]."""
        return np.hypot(self.matrix[:, 1], self.matrix[:, 2]) / self.matrix[:, 0]

    @property
    def extinction_ratio(self) -> NDArray[np.float64]:
        """Per-channel extinction ratio ``(1 + d) / (1 - d)`` (inf for d >= 1)."""
        d = self.diattenuation
        with np.errstate(divide="ignore"):
            return np.where(d >= 1.0, np.inf, (1.0 + d) / (1.0 - d))

    @property
    def angles_deg(self) -> NDArray[np.float64]:
        """Per-channel transmission-axis angle in degrees, in [0, 180)."""
        return np.mod(0.5 * np.degrees(np.arctan2(self.matrix[:, 2], self.matrix[:, 1])), 180.0)

    # -- application ------------------------------------------------------------
    def intensities(self, s0: ArrayLike, s1: ArrayLike, s2: ArrayLike) -> NDArray[np.float64]:
        """Forward model: channel intensities, shape ``(4, *broadcast_shape)``."""
        s = np.stack(np.broadcast_arrays(*(np.asarray(x, float) for x in (s0, s1, s2))))
        return np.tensordot(self.matrix, s, axes=(1, 0))

    def stokes(self, intensities: ArrayLike) -> NDArray[np.float64]:
        """Least-squares Stokes ``pinv(A) @ I``; input shape ``(4, ...)``, output ``(3, ...)``."""
        i = np.asarray(intensities, dtype=float)
        if i.shape[:1] != (4,):
            raise PihimInputError(f"expected 4 channel intensities on axis 0, got shape {i.shape}")
        return np.tensordot(self.pinv, i, axes=(1, 0))

    # -- serialisation ------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (schema ``pihim.analyser/1``)."""
        er = self.extinction_ratio
        return {
            "schema": _SCHEMA_ID,
            "channel_angles_nominal_deg": list(NOMINAL_ANGLES_DEG),
            "matrix": self.matrix.tolist(),
            "transmission": self.transmission.tolist(),
            "angles_deg": self.angles_deg.tolist(),
            "extinction_ratio": [None if math.isinf(v) else float(v) for v in er],
        }

    @classmethod
    def from_dict(cls, obj: dict[str, Any]) -> AnalyserMatrix:
        """Inverse of :meth:`to_dict`; only ``matrix`` is required."""
        if not isinstance(obj, dict) or "matrix" not in obj:
            raise PihimInputError("calibration JSON has no 'matrix' entry")
        rows = obj["matrix"]
        if isinstance(rows, list) and any(isinstance(v, bool) for row in rows if isinstance(row, list) for v in row):
            raise PihimInputError("calibration 'matrix' is not numeric: it holds true or false")
        try:
            m = np.asarray(rows, dtype=float)
        except (TypeError, ValueError) as exc:
            raise PihimInputError(f"calibration 'matrix' is not numeric: {exc}") from None
        return cls(m)

    @classmethod
    def load(cls, path: str | Path) -> AnalyserMatrix:
        """Read a calibration JSON file written by ``pihim calibrate-polarizer``."""
        from pihim._inputs import load_json_file

        p = Path(path)
        if not p.exists():
            raise PihimInputError(f"{p}: calibration file not found")
        obj = load_json_file(p, "calibration JSON")
        try:
            return cls.from_dict(obj)
        except PihimInputError as exc:
            raise PihimInputError(f"{p}: {exc}") from None


_IDEAL = AnalyserMatrix.from_parameters(NOMINAL_ANGLES_DEG)
