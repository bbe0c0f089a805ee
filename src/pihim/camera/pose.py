"""Camera pose in the field frame: position, attitude, world <-> camera transforms and projection.

A :class:`CameraPose` is the camera's position ``C`` in the field frame
(East-North-Up metres) and the rotation ``R`` taking field vectors into the
OpenCV camera frame (x right, y down, z forward)::

    x_cam = R @ (X - C)

so the rows of ``R`` are the camera's right, down and forward axes written in
ENU. The attitude angles are those of the flight plans
(docs/conventions.md, "Flight plans" and "Camera and image frames"):

* ``heading_deg``: azimuth of the optical axis, clockwise from North, [0, 360);
* ``pitch_deg``: elevation of the optical axis, negative below the horizon
  (-90 straight down);
* ``roll_deg``: right-hand rotation of the camera about its optical axis
  (forward) turning camera x (right) toward camera y (down) -- "right wing
  down" for a camera looking forward. The scene then turns counter-clockwise
  in the displayed image.

With zero roll the camera x axis is horizontal and the image is upright; the
axes are exactly those of :func:`pihim.planning.sightlines.camera_frame`.
OpenCV's extrinsics are ``rvec = Rodrigues(R)`` and ``tvec = -R C``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pihim.camera.model import CameraModel
from pihim.errors import PihimInputError

if TYPE_CHECKING:
    from pihim.planning.model import Waypoint

__all__ = ["CameraPose", "pixel_rays_world", "project_points"]

_ORTHO_TOL = 1e-9
_VERTICAL_TOL = 1e-12  # horizontal part of a unit optical axis below which it counts as vertical


def _vector3(value: ArrayLike, what: str) -> NDArray[np.float64]:
    """A finite float array of shape (3,), or a one-line PihimInputError."""
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise PihimInputError(f"{what} must be 3 numbers, got {value!r}") from None
    if a.shape == (3, 1):
        a = a[:, 0]
    if a.shape != (3,):
        raise PihimInputError(f"{what} must have shape (3,), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise PihimInputError(f"{what} must be finite, got {a.tolist()}")
    return a


def _number(value: Any, what: str, unit: str = "degrees") -> float:
    """``value`` as a finite float, or a one-line error naming ``what`` and its ``unit``."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise PihimInputError(f"{what} must be a number of {unit}, got {value!r}") from None
    if not math.isfinite(x):
        raise PihimInputError(f"{what} must be finite, got {x!r}")
    return x


def _points(points: ArrayLike, what: str) -> NDArray[np.float64]:
    p = np.asarray(points, dtype=float)
    if p.ndim < 1 or p.shape[-1] != 3:
        raise PihimInputError(f"{what} must have shape (..., 3), got {p.shape}")
    return p


def _rolled(right: NDArray[np.float64], down: NDArray[np.float64],
            roll_deg: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Right and down axes after a roll (right-hand about forward, right toward down)."""
    if roll_deg == 0.0:
        return right, down
    roll_rad = math.radians(roll_deg)
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    return c * right + s * down, c * down - s * right


def _zero_roll_frame(heading_deg: float, pitch_deg: float) -> tuple[NDArray, NDArray, NDArray]:
    """Right, down, forward (ENU) for zero roll: the same operations as ``sightlines.camera_frame``."""
    h = np.radians(np.asarray(heading_deg, float))
    p = np.radians(np.asarray(pitch_deg, float))
    forward = np.stack([np.cos(p) * np.sin(h), np.cos(p) * np.cos(h), np.sin(p)], axis=-1)
    right = np.stack([np.cos(h), -np.sin(h), np.zeros_like(h)], axis=-1)
    return right, np.cross(forward, right), forward


@dataclass(frozen=True, eq=False)
class CameraPose:
    """Position and attitude of a camera in the field frame.

    Attributes
    ----------
    position_m : ndarray, shape (3,)
        Camera centre, field ENU metres (x East, y North, z Up). Read-only.
    rotation : ndarray, shape (3, 3)
        World -> camera rotation: ``x_cam = rotation @ (X - position_m)``;
        rows are the camera x (right), y (down) and z (forward) axes in ENU.
        Orthonormal with determinant +1 (checked to 1e-9). Read-only.

    Notes
    -----
    Both arrays are copied and made read-only. Two poses are equal when both
    arrays are equal element by element.
    """

    position_m: NDArray[np.float64]
    rotation: NDArray[np.float64]

    def __post_init__(self) -> None:
        pos = _vector3(self.position_m, "camera position").copy()
        try:
            rot = np.array(self.rotation, dtype=float)
        except (TypeError, ValueError):
            raise PihimInputError(f"camera rotation must be a 3x3 array of numbers, got {self.rotation!r}") from None
        if rot.shape != (3, 3):
            raise PihimInputError(f"camera rotation must have shape (3, 3), got {rot.shape}")
        if not np.all(np.isfinite(rot)):
            raise PihimInputError("camera rotation must be finite")
        err = float(np.max(np.abs(rot @ rot.T - np.eye(3))))
        if err > _ORTHO_TOL:
            raise PihimInputError(f"camera rotation must be orthonormal (max |R R^T - I| = {err:.3g} > 1e-9)")
        det = float(np.linalg.det(rot))
        if abs(det - 1.0) > _ORTHO_TOL:
            raise PihimInputError(f"camera rotation must be a proper rotation with determinant +1, got {det:.6g}")
        pos.setflags(write=False)
        rot.setflags(write=False)
        object.__setattr__(self, "position_m", pos)
        object.__setattr__(self, "rotation", rot)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraPose):
            return NotImplemented
        return bool(np.array_equal(self.position_m, other.position_m) and np.array_equal(self.rotation, other.rotation))

    def __hash__(self) -> int:
        return hash((self.position_m.tobytes(), self.rotation.tobytes()))

    def __repr__(self) -> str:
        x, y, z = self.position_m
        return (f"CameraPose(position_m=[{x:.6g}, {y:.6g}, {z:.6g}], heading_deg={self.heading_deg:.6g}, "
                f"pitch_deg={self.pitch_deg:.6g}, roll_deg={self.roll_deg:.6g})")

    # --- constructors ---------------------------------------------------------------------------

    @classmethod
    def from_axes(cls, position_m: ArrayLike, right: ArrayLike, down: ArrayLike, forward: ArrayLike) -> CameraPose:
        """A pose from its camera axes written in ENU (the rows of :attr:`rotation`)."""
        return cls(position_m=np.asarray(position_m, float), rotation=np.array([right, down, forward], dtype=float))

    @classmethod
    def from_attitude(cls, position_m: ArrayLike, heading_deg: float, pitch_deg: float,
                      roll_deg: float = 0.0) -> CameraPose:
        """A pose from heading, pitch and roll.

        Parameters
        ----------
        position_m : array_like, shape (3,)
            Camera centre, ENU metres.
        heading_deg : float
            Azimuth of the optical axis, deg clockwise from North.
        pitch_deg : float
            Elevation of the optical axis, deg, negative below the horizon (-90 straight down).
        roll_deg : float
            Right-hand rotation about the optical axis turning camera x
            (right) toward camera y (down), deg ("right wing down").

        Returns
        -------
        CameraPose
            With zero roll, right = ``(cos h, -sin h, 0)`` (horizontal),
            forward = ``(cos p sin h, cos p cos h, sin p)``, down = forward x
            right: bit for bit :func:`pihim.planning.sightlines.camera_frame`.
            At pitch +-90 the heading still sets the right axis, so looking
            straight down with heading 0 the image top points North.
        """
        h = _number(heading_deg, "heading")
        p = _number(pitch_deg, "pitch")
        r = _number(roll_deg, "roll")
        right, down, forward = _zero_roll_frame(h, p)
        right, down = _rolled(right, down, r)
        return cls.from_axes(position_m, right, down, forward)

    @classmethod
    def look_at(cls, position_m: ArrayLike, target_m: ArrayLike, roll_deg: float = 0.0) -> CameraPose:
        """A pose at ``position_m`` whose optical axis passes through ``target_m``.

        Parameters
        ----------
        position_m, target_m : array_like, shape (3,)
            Camera centre and a point on the optical axis, ENU metres; must differ.
        roll_deg : float
            Roll about the optical axis, as in :meth:`from_attitude`.

        Returns
        -------
        CameraPose
            With zero roll, right = ``unit(forward x Up)`` is horizontal and
            down has a negative Up component (an upright image). For a
            vertical optical axis the heading is taken as 0, i.e. right =
            East: looking straight down the image top points North, looking
            straight up it points South (the limit of a North-looking camera
            tilted up), as :meth:`from_attitude` with heading 0 and pitch +-90.
        """
        pos = _vector3(position_m, "camera position")
        tgt = _vector3(target_m, "look-at target")
        d = tgt - pos
        n = float(np.linalg.norm(d))
        if not n > 0:
            raise PihimInputError(f"look-at target equals the camera position {pos.tolist()}")
        forward = d / n
        horiz = math.hypot(forward[0], forward[1])
        if horiz < _VERTICAL_TOL:
            forward = np.array([0.0, 0.0, math.copysign(1.0, forward[2])])
            right = np.array([1.0, 0.0, 0.0])
        else:
            right = np.array([forward[1] / horiz, -forward[0] / horiz, 0.0])  # unit(forward x Up)
        down = np.cross(forward, right)
        right, down = _rolled(right, down, _number(roll_deg, "roll"))
        return cls.from_axes(pos, right, down, forward)

    @classmethod
    def from_waypoint(cls, waypoint: Waypoint | Mapping[str, Any]) -> CameraPose:
        """The camera pose planned at a waypoint.

        Parameters
        ----------
        waypoint : Waypoint or mapping
            A :class:`pihim.planning.model.Waypoint` or a mapping with the
            same keys (a ``plan.json`` waypoint): ``x_m``, ``y_m``, ``z_m``
            (ENU metres), ``heading_deg``, ``gimbal_pitch_deg`` and optionally
            ``roll_deg`` (default 0; planned gimbals do not roll).

        Returns
        -------
        CameraPose
            :meth:`from_attitude` at the waypoint.
        """
        keys = ("x_m", "y_m", "z_m", "heading_deg", "gimbal_pitch_deg")
        if isinstance(waypoint, Mapping):
            missing = [k for k in keys if k not in waypoint]
            if missing:
                raise PihimInputError(f"waypoint has no {', '.join(repr(k) for k in missing)}")
            get = waypoint.get
        else:
            missing = [k for k in keys if not hasattr(waypoint, k)]
            if missing:
                raise PihimInputError(f"not a waypoint ({type(waypoint).__name__} has no {missing[0]!r})")

            def get(k: str, default: Any = None) -> Any:
                return getattr(waypoint, k, default)

        x, y, z, heading, pitch = (_number(get(k), f"waypoint {k}", "metres" if k.endswith("_m") else "degrees")
                                   for k in keys)
        roll = _number(get("roll_deg", 0.0), "waypoint roll_deg")
        return cls.from_attitude((x, y, z), heading, pitch, roll)

    @classmethod
    def from_plan_json(cls, path: str | Path, index: int) -> CameraPose:
        """The camera pose of one planned image of a ``plan.json`` written by ``pihim plan``.

        Parameters
        ----------
        path : str or path-like
            A ``plan.json`` (schema ``pihim.plan/1``).
        index : int
            0-based position among the capture waypoints: the waypoints with
            ``capture`` true in ``passes[*].waypoints``, pass after pass and
            in each pass in document order (the count of
            ``export.counts.capture_waypoints``). ``flights[*].waypoints``
            repeat the same waypoints and are not counted.

        Returns
        -------
        CameraPose
            :meth:`from_waypoint` of that waypoint.
        """
        from pihim._inputs import load_json_file

        p = Path(path)
        if not p.exists():
            raise PihimInputError(f"plan file not found: {p}")
        doc = load_json_file(p, "plan file")
        schema = doc.get("schema") if isinstance(doc, dict) else None
        passes = doc.get("passes") if isinstance(doc, dict) else None
        if (schema is not None and schema != "pihim.plan/1") or not isinstance(passes, list) \
                or not all(isinstance(q, dict) and isinstance(q.get("waypoints"), list) for q in passes):
            raise PihimInputError(f"{p} is not a pihim plan.json (schema pihim.plan/1 with passes and waypoints)")
        captures = [w for q in passes for w in q["waypoints"] if isinstance(w, dict) and w.get("capture") is True]
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
            raise PihimInputError(f"capture index must be an integer, got {index!r}")
        n = len(captures)
        if not 0 <= index < n:
            span = f"0..{n - 1}" if n else "none"
            raise PihimInputError(f"capture index {index} out of range: {p} has {n} capture waypoints ({span})")
        return cls.from_waypoint(captures[int(index)])

    @classmethod
    def from_rvec_tvec(cls, rvec: ArrayLike, tvec: ArrayLike) -> CameraPose:
        """A pose from OpenCV extrinsics (``cv2.solvePnP``, ``cv2.calibrateCamera``).

        Parameters
        ----------
        rvec : array_like, shape (3,) or (3, 1)
            Rodrigues rotation vector of ``R`` (world -> camera), radians.
        tvec : array_like, shape (3,) or (3, 1)
            Translation, world units: ``x_cam = R X + t``, so ``t = -R C``.

        Returns
        -------
        CameraPose
            ``rotation = R``, ``position_m = -R^T t``.
        """
        from scipy.spatial.transform import Rotation

        r_vec = _vector3(rvec, "rvec")
        t = _vector3(tvec, "tvec")
        rot = Rotation.from_rotvec(r_vec).as_matrix()
        return cls(position_m=-rot.T @ t, rotation=rot)

    def rvec_tvec(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """OpenCV extrinsics ``(rvec, tvec)``, each shape (3,): ``x_cam = Rodrigues(rvec) X + tvec``."""
        from scipy.spatial.transform import Rotation

        rvec = Rotation.from_matrix(np.array(self.rotation)).as_rotvec()
        return rvec, -(self.rotation @ self.position_m)

    # --- axes and angles ------------------------------------------------------------------------

    @property
    def right(self) -> NDArray[np.float64]:
        """Camera x axis (image right), ENU unit vector."""
        return self.rotation[0].copy()

    @property
    def down(self) -> NDArray[np.float64]:
        """Camera y axis (image down), ENU unit vector."""
        return self.rotation[1].copy()

    @property
    def forward(self) -> NDArray[np.float64]:
        """Camera z axis (optical axis), ENU unit vector."""
        return self.rotation[2].copy()

    def _attitude(self) -> tuple[float, float, float]:
        f, r = self.rotation[2], self.rotation[0]
        horiz = math.hypot(f[0], f[1])
        pitch = math.degrees(math.atan2(f[2], horiz))
        if horiz < _VERTICAL_TOL:
            # vertical optical axis: heading and roll are one rotation; report roll 0 and put it in the heading
            heading_rad = math.atan2(-r[1], r[0])
            roll = 0.0
        else:
            heading_rad = math.atan2(f[0], f[1])
            right0 = np.array([math.cos(heading_rad), -math.sin(heading_rad), 0.0])
            down0 = np.cross(f, right0)
            roll = math.degrees(math.atan2(float(r @ down0), float(r @ right0)))
        heading = math.degrees(heading_rad) % 360.0
        return (0.0 if heading >= 360.0 else heading), pitch, roll

    @property
    def heading_deg(self) -> float:
        """Azimuth of the optical axis, deg clockwise from North, [0, 360).

        For a vertical optical axis, the heading that :meth:`from_attitude`
        needs with zero roll (right = ``(cos h, -sin h, 0)``).
        """
        return self._attitude()[0]

    @property
    def pitch_deg(self) -> float:
        """Elevation of the optical axis, deg, [-90, 90], negative below the horizon."""
        return self._attitude()[1]

    @property
    def roll_deg(self) -> float:
        """Roll about the optical axis, deg, (-180, 180], positive turning right toward down (0 if vertical)."""
        return self._attitude()[2]

    # --- transforms -----------------------------------------------------------------------------

    def world_to_camera(self, points: ArrayLike) -> NDArray[np.float64]:
        """Camera-frame coordinates of ENU points: ``R (X - C)``, shape (..., 3) -> (..., 3)."""
        p = _points(points, "world points")
        return (p - self.position_m) @ self.rotation.T

    def camera_to_world(self, points: ArrayLike) -> NDArray[np.float64]:
        """ENU coordinates of camera-frame points: ``R^T x + C``, shape (..., 3) -> (..., 3)."""
        p = _points(points, "camera-frame points")
        return p @ self.rotation + self.position_m

    def perturbed(self, position_sigma_m: float, attitude_sigma_deg: float,
                  rng: np.random.Generator | int | None = None) -> CameraPose:
        """A randomly perturbed copy of this pose (e.g. GNSS / gimbal errors).

        Parameters
        ----------
        position_sigma_m : float
            Standard deviation of independent Gaussian noise added to each of
            x, y and z, metres.
        attitude_sigma_deg : float
            Standard deviation of independent Gaussian noise added to each of
            heading, pitch and roll (:attr:`heading_deg`, :attr:`pitch_deg`,
            :attr:`roll_deg`), deg; the pose is rebuilt with
            :meth:`from_attitude` (pitch is not clipped to [-90, 90]).
        rng : numpy.random.Generator or int or None
            Random generator, or a seed for ``numpy.random.default_rng``.

        Returns
        -------
        CameraPose
            A new pose; this one is unchanged.
        """
        sp = _number(position_sigma_m, "position sigma", "metres")
        sa = _number(attitude_sigma_deg, "attitude sigma")
        if sp < 0 or sa < 0:
            raise PihimInputError(f"noise sigmas must be >= 0, got {sp:g} m and {sa:g} deg")
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        dpos = gen.normal(0.0, sp, 3) if sp > 0 else np.zeros(3)
        datt = gen.normal(0.0, sa, 3) if sa > 0 else np.zeros(3)
        h, p, r = self._attitude()
        return CameraPose.from_attitude(self.position_m + dpos, h + datt[0], p + datt[1], r + datt[2])

    # --- serialisation --------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description.

        Returns
        -------
        dict
            ``position_m`` (list, ENU metres), ``rotation`` (list of its three
            rows), ``heading_deg``, ``pitch_deg`` and ``roll_deg``.
        """
        h, p, r = self._attitude()
        return {
            "position_m": [float(v) for v in self.position_m],
            "rotation": [[float(v) for v in row] for row in self.rotation],
            "heading_deg": h,
            "pitch_deg": p,
            "roll_deg": r,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> CameraPose:
        """Inverse of :meth:`to_dict`: uses ``position_m`` and ``rotation`` (the angles are informative)."""
        if not isinstance(data, Mapping):
            raise PihimInputError(f"a camera pose must be a mapping, got {type(data).__name__}")
        for key in ("position_m", "rotation"):
            if key not in data:
                raise PihimInputError(f"camera pose has no '{key}'")
        return cls(position_m=data["position_m"], rotation=data["rotation"])


def project_points(camera: CameraModel, pose: CameraPose, points_world: ArrayLike) -> NDArray[np.float64]:
    """Pixels of field points seen by a posed camera.

    Parameters
    ----------
    camera : CameraModel
    pose : CameraPose
    points_world : array_like, shape (..., 3)
        ENU metres.

    Returns
    -------
    ndarray, shape (..., 2)
        ``(u, v)`` pixels, distortion included (``cv2.projectPoints`` with
        ``pose.rvec_tvec()``, ``camera.intrinsics()`` and
        ``camera.distortion_coefficients()``); NaN at or behind the camera.
    """
    return camera.project(pose.world_to_camera(points_world))


def pixel_rays_world(camera: CameraModel, pose: CameraPose, u: ArrayLike,
                     v: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Viewing rays of pixels in the field frame.

    Parameters
    ----------
    camera : CameraModel
    pose : CameraPose
    u, v : array_like
        Pixel column and row, broadcast together.

    Returns
    -------
    origins : ndarray, shape (..., 3)
        The camera centre, ENU metres, broadcast to the rays' shape (a read-only view).
    directions : ndarray, shape (..., 3)
        Unit ENU directions; :func:`project_points` of ``origins + s directions``
        (``s > 0``) gives back ``(u, v)``.
    """
    d = camera.pixel_rays(u, v) @ pose.rotation
    return np.broadcast_to(pose.position_m, d.shape), d
