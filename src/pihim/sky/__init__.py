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

from __future__ import annotations

from typing import TYPE_CHECKING

from pihim._lazy import lazy_exports

#: Exported names by submodule; a submodule is imported when one of its names is first used.
_EXPORTS: dict[str, list[str]] = {
    "berry": ["NeutralPoints", "berry_stokes", "berry_w", "neutral_points"],
    "model": ["SkyMap", "SkyModel", "sky_grid", "sky_map"],
    "radiance": ["CIE_SKY_TYPES", "cie_relative_radiance", "gradation", "indicatrix"],
    "rayleigh": ["meridian_frame", "rayleigh_dolp", "rayleigh_stokes"],
    "sun": [
        "NSTTF", "Site", "SunPosition", "angles_from_direction", "direction_from_angles", "parse_site",
        "parse_time", "require_daylight", "sun_position",
    ],
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static checkers see the names where they are defined
    from pihim.sky.berry import NeutralPoints, berry_stokes, berry_w, neutral_points  # noqa: F401
    from pihim.sky.model import SkyMap, SkyModel, sky_grid, sky_map  # noqa: F401
    from pihim.sky.radiance import CIE_SKY_TYPES, cie_relative_radiance, gradation, indicatrix  # noqa: F401
    from pihim.sky.rayleigh import meridian_frame, rayleigh_dolp, rayleigh_stokes  # noqa: F401
    from pihim.sky.sun import (  # noqa: F401
        NSTTF, Site, SunPosition, angles_from_direction, direction_from_angles, parse_site, parse_time,
        require_daylight, sun_position,
    )
