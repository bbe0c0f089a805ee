"""Synthetic polarimetric frames with known ground truth."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pihim._lazy import lazy_exports

#: Exported names by submodule; a submodule is imported when one of its names is first used.
_EXPORTS: dict[str, list[str]] = {
    "mosaic": ["mosaic_from_stokes"],
    "scenes": ["edge_scene", "uniform_scene"],
    "sensor": ["Exposure", "SensorModel", "choose_exposure", "expose"],
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static checkers see the names where they are defined
    from pihim.render.mosaic import mosaic_from_stokes  # noqa: F401
    from pihim.render.scenes import edge_scene, uniform_scene  # noqa: F401
    from pihim.render.sensor import Exposure, SensorModel, choose_exposure, expose  # noqa: F401
