"""Heliostat field model: layout, kinematics and geodesy.

* :mod:`pihim.field.layout` -- :class:`Field`, :class:`HeliostatSpec`,
  :class:`Tower`, :class:`Heliostat`; OpenCSP CSV loaders; the embedded
  NSTTF-like field and a radial-staggered generator for large fields.
* :mod:`pihim.field.kinematics` -- tracking (with the pivot offset), az-el
  drive angles, heliostat and facet frames, on-axis design canting, canting
  deviations (mrad), facet corners, mirror outlines and back structure.
* :mod:`pihim.field.geodesy` -- exact ENU <-> WGS84 conversion (pymap3d).

Field frame: East-North-Up, metres, origin at the tower base.

Examples
--------
>>> import numpy as np
>>> from pihim.field import nsttf_like_field, track_field
>>> field = nsttf_like_field()
>>> pose = track_field(field, np.array([0.3, -0.4, 0.866]))
>>> pose.normals.shape, pose.facet_normals.shape
((218, 3), (218, 25, 3))
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pihim._lazy import lazy_exports

#: Exported names by submodule; a submodule is imported when one of its names is first used.
_EXPORTS: dict[str, list[str]] = {
    "geodesy": [
        "GeodeticOrigin", "NSTTF_ORIGIN_LATITUDE_DEG", "NSTTF_ORIGIN_LONGITUDE_DEG", "enu_to_geodetic",
        "geodetic_to_enu", "nsttf_origin",
    ],
    "kinematics": [
        "BackStructure", "DriveAngles", "FieldPose", "apply_canting_deviation", "back_structure", "canting_angles",
        "canting_deviation", "design_facet_normals", "drive_angles", "facet_centres", "facet_corners",
        "facet_rotations", "focal_lengths", "heliostat_rotation", "mirror_outline", "normals_from_drive",
        "reflect", "rotation_from_drive", "to_enu", "track_field", "tracking_normals",
    ],
    "layout": [
        "Field", "Heliostat", "HeliostatSpec", "NSTTF_BCS_STANDBY", "NSTTF_TOWER", "NSTTF_TOWER_TARGET", "Tower",
        "UFACET_AIM_POINT", "canonical_name", "grid_facet_centroids", "load_facet_centroids", "load_field",
        "nsttf_facet_centroids", "nsttf_like_field", "nsttf_spec", "parse_heliostat_name",
        "radial_staggered_field",
    ],
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static checkers see the names where they are defined
    from pihim.field.geodesy import (  # noqa: F401
        GeodeticOrigin, NSTTF_ORIGIN_LATITUDE_DEG, NSTTF_ORIGIN_LONGITUDE_DEG, enu_to_geodetic, geodetic_to_enu,
        nsttf_origin,
    )
    from pihim.field.kinematics import (  # noqa: F401
        BackStructure, DriveAngles, FieldPose, apply_canting_deviation, back_structure, canting_angles,
        canting_deviation, design_facet_normals, drive_angles, facet_centres, facet_corners, facet_rotations,
        focal_lengths, heliostat_rotation, mirror_outline, normals_from_drive, reflect, rotation_from_drive,
        to_enu, track_field, tracking_normals,
    )
    from pihim.field.layout import (  # noqa: F401
        Field, Heliostat, HeliostatSpec, NSTTF_BCS_STANDBY, NSTTF_TOWER, NSTTF_TOWER_TARGET, Tower,
        UFACET_AIM_POINT, canonical_name, grid_facet_centroids, load_facet_centroids, load_field,
        nsttf_facet_centroids, nsttf_like_field, nsttf_spec, parse_heliostat_name, radial_staggered_field,
    )
