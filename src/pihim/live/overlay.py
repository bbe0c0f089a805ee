"""Expected heliostat outlines in the live image, from a camera pose and the tracking field.

Where the camera pose is known -- a capture waypoint of a ``plan.json``
(:func:`overlay_from_plan`), or the logged pose of a frame
(:func:`overlay_from_log`, the ``log`` of ``pihim simulate``'s
``FRAME.json``) -- the mirror rectangle of every heliostat, tracked for the
time and aim point of the plan or log, is projected into the image
(:func:`pihim.camera.pose.project_points`, the camera model's distortion
included). The operator sees where the heliostats should be: a large offset
between outline and image means a wrong pose, a wrong time, or a heliostat
not tracking. The outlines also give the mirror region for the adaptive
exposure and the DoLP readout when the source does not know it
(:meth:`Overlay.mirror_mask`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pihim.errors import PihimInputError

__all__ = ["Overlay", "overlay_from_log", "overlay_from_plan", "project_outlines"]

#: Points per mirror edge: the outline is drawn as a polyline so that lens distortion bends it.
_EDGE_POINTS = 8


@dataclass(frozen=True, eq=False)
class Overlay:
    """Heliostat outlines in pixel coordinates of a camera.

    Attributes
    ----------
    names : tuple of str
        Heliostat of each outline.
    outlines : tuple of ndarray, shape (K, 2)
        Closed polylines ``(u, v)``, pixels (u right, v down, pixel centres
        at integers), in the camera's image.
    width, height : int
        Image size of the camera the outlines are for.
    source : str
        Where the pose came from (``"plan.json #3"``, ``"frame log"``).
    """

    names: tuple[str, ...]
    outlines: tuple[NDArray[np.float64], ...]
    width: int
    height: int
    source: str = ""

    def normalized(self) -> list[dict[str, Any]]:
        """JSON-ready outlines with coordinates as fractions of the image width and height.

        Fractions make them independent of the preview size: a point at
        ``(u, v)`` is at ``((u + 0.5) / W, (v + 0.5) / H)``.
        """
        out = []
        for name, pts in zip(self.names, self.outlines, strict=True):
            xy = (pts + 0.5) / np.array([self.width, self.height], float)
            out.append({"name": name, "points": np.round(xy, 5).tolist()})
        return out

    def mirror_mask(self, shape: tuple[int, int]) -> NDArray[np.bool_]:
        """Pixels inside the outlines, for an image of ``shape`` (rows, columns) covering the same view."""
        import cv2

        h, w = int(shape[0]), int(shape[1])
        mask = np.zeros((h, w), np.uint8)
        sx, sy = w / self.width, h / self.height
        polys = [np.round((p + 0.5) * (sx, sy) - 0.5).astype(np.int32) for p in self.outlines]
        if polys:
            cv2.fillPoly(mask, polys, 1)
        return mask.astype(bool)


def project_outlines(camera: Any, pose: Any, corners: NDArray[np.float64], names: list[str],
                     source: str = "") -> Overlay:
    """Project mirror rectangles (N, 4, 3) into ``camera`` at ``pose``; keep those in front and in view."""
    from pihim.camera.pose import project_points

    c = np.asarray(corners, float)
    t = np.linspace(0.0, 1.0, _EDGE_POINTS, endpoint=False)
    ring = np.concatenate([c[:, j, None, :] + t[None, :, None] * (c[:, (j + 1) % 4] - c[:, j])[:, None, :]
                           for j in range(4)], axis=1)  # (N, 4 * _EDGE_POINTS, 3)
    cam_pts = (ring - pose.position_m) @ np.asarray(pose.rotation).T
    in_front = np.all(cam_pts[..., 2] > 0.1, axis=1)
    keep_names, keep = [], []
    w, h = camera.width_px, camera.height_px
    for i in np.flatnonzero(in_front):
        uv = project_points(camera, pose, ring[i])
        if not np.all(np.isfinite(uv)):
            continue
        if uv[:, 0].max() < 0 or uv[:, 0].min() > w - 1 or uv[:, 1].max() < 0 or uv[:, 1].min() > h - 1:
            continue
        keep_names.append(names[i])
        keep.append(uv)
    return Overlay(tuple(keep_names), tuple(keep), int(w), int(h), source)


def _field_pose(field: Any, time: Any, site: Any, aim_point: Any) -> Any:
    from pihim.field.kinematics import track_field
    from pihim.sky.sun import sun_position

    sun = sun_position(site, time)
    if not float(sun.elevation_deg) > 0.0:
        raise PihimInputError(f"the sun is below the horizon at {time}: the field does not track")
    return track_field(field, sun.vector, np.asarray(aim_point, float))


def overlay_from_plan(field: Any, plan_path: str | Path, index: int, camera: Any = None) -> Overlay:
    """Outlines seen from capture waypoint ``index`` of a ``plan.json``.

    The field tracks the plan's aim point at the plan's time; the camera is
    ``camera`` or the plan's (``plan.json["camera"]``).
    """
    from pihim._inputs import load_json_file
    from pihim.camera.model import CameraModel
    from pihim.camera.pose import CameraPose
    from pihim.sky.sun import Site

    pose = CameraPose.from_plan_json(plan_path, index)
    doc = load_json_file(Path(plan_path), "plan file")
    try:
        s = doc["site"]
        site = Site(name=str(s.get("name", "plan")), latitude_deg=s["latitude_deg"],
                    longitude_deg=s["longitude_deg"], height_m=s["height_m"], timezone=str(s.get("timezone", "UTC")))
        time, aim = doc["time_iso"], doc["aim_point"]
    except (KeyError, TypeError, AttributeError) as exc:
        raise PihimInputError(f"{plan_path}: plan.json lacks {exc} (time_iso, site, aim_point)") from None
    if camera is None:
        cam_doc = doc.get("camera")
        if isinstance(cam_doc, Mapping):
            cam_doc = {k: v for k, v in cam_doc.items() if k != "principal_point_px"}
            camera = CameraModel.from_dict(cam_doc)
        else:
            camera = CameraModel()
    fp = _field_pose(field, time, site, aim)
    return project_outlines(camera, pose, fp.mirror_outline(), list(field.names), f"{Path(plan_path).name} #{index}")


def overlay_from_log(field: Any, log: Mapping[str, Any]) -> Overlay:
    """Outlines seen from the logged pose of a frame (``pihim simulate``'s ``log``).

    The field is rebuilt from the log alone (time, site, aim point, the
    logged drive angles; :func:`pihim.inspection.pipeline.field_pose_from_log`).
    """
    from pihim.camera.model import CameraModel
    from pihim.camera.pose import CameraPose
    from pihim.inspection.pipeline import field_pose_from_log

    if "camera" not in log or "pose" not in log:
        raise PihimInputError("the frame log has no camera or pose")
    camera = CameraModel.from_dict(log["camera"])
    pose = CameraPose.from_dict(log["pose"])
    fp = field_pose_from_log(field, log)
    return project_outlines(camera, pose, fp.mirror_outline(), list(field.names), "frame log")
