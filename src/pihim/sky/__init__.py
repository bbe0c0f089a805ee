"""Sun position and skylight polarization.

``pihim.sky.sun``
    Sites (NSTTF by default), timezone-aware time parsing, NREL SPA sun
    position (via pvlib) as zenith/azimuth (clockwise from North) and an
    East-North-Up unit vector toward the sun.
``pihim.sky.rayleigh``
    Single-scattering Rayleigh skylight (the paper's model, section 3).
``pihim.sky.berry``
    Berry-Dennis-Lee four-neutral-point model (New J. Phys. 6, 162, 2004).
``pihim.sky.radiance``
    CIE standard general sky relative radiance (type 12, clear sky).
``pihim.sky.model``
    :class:`SkyModel`, the interface the reflection models use:
    ``SkyModel(...).stokes(view_dirs, sun_dir, e=None) -> (stokes, e)``,
    and all-sky maps (:func:`sky_map`).

Conventions: ENU field frame, azimuth clockwise from North, degrees at the
API; skylight from sky direction ``v`` travels along ``d = -v`` and, unless a
frame is given, its Stokes vectors use the local meridian "up" as reference
axis (see ``docs/conventions.md``).
"""

from pihim.sky.berry import NeutralPoints, berry_stokes, berry_w, neutral_points
from pihim.sky.model import SkyMap, SkyModel, sky_grid, sky_map
from pihim.sky.radiance import (
    CIE_SKY_TYPES,
    cie_relative_radiance,
    gradation,
    indicatrix,
)
from pihim.sky.rayleigh import meridian_frame, rayleigh_dolp, rayleigh_stokes
from pihim.sky.sun import (
    NSTTF,
    Site,
    SunPosition,
    angles_from_direction,
    direction_from_angles,
    parse_site,
    parse_time,
    require_daylight,
    sun_position,
)

__all__ = [
    "CIE_SKY_TYPES",
    "NSTTF",
    "NeutralPoints",
    "Site",
    "SkyMap",
    "SkyModel",
    "SunPosition",
    "angles_from_direction",
    "berry_stokes",
    "berry_w",
    "cie_relative_radiance",
    "direction_from_angles",
    "gradation",
    "indicatrix",
    "meridian_frame",
    "neutral_points",
    "parse_site",
    "parse_time",
    "rayleigh_dolp",
    "rayleigh_stokes",
    "require_daylight",
    "sky_grid",
    "sky_map",
    "sun_position",
]
