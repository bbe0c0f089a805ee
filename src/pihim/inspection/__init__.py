"""Inspection of heliostats in polarimetric images: edges, contrast and scoring.

* :mod:`pihim.inspection.edges` -- Sobel / Canny edge maps of S0, DoLP and
  (axial) AoP images and their combination (paper section 4.3). Pure numpy;
  runs on the raw frame's images only.
* :mod:`pihim.inspection.contrast` -- Michelson contrast of two 200 x 100 px
  regions either side of an edge and the DoLP / S0 contrast ratio.
* :mod:`pihim.inspection.success` -- scoring against the ground truth: the
  paper's edge-detection success (all facet edges of the heliostat found)
  and success rates over sets (Table 2), optionally only along the stretches
  of the outline where the paper's sky-vs-sky scenario holds. Reads truth;
  the estimator never does.
* :mod:`pihim.inspection.features` -- sub-pixel edge points (combined S0,
  DoLP and axial AoP gradient) for model fitting.
* :mod:`pihim.inspection.pose` -- camera pose refinement on the HUA's facet
  outlines (coarse FFT search, point-to-line ICP with Levenberg-Marquardt).
* :mod:`pihim.inspection.reflection` -- the estimator's forward model: the
  target's outline mirrored in a HUA facet and projected, for candidate
  canting angles or drive-angle errors of the HUA.
* :mod:`pihim.inspection.orientation` -- the HUA's and the target's logged
  drive angles corrected from the reflection (the paper's +-5 deg search,
  a joint least-squares solve).
* :mod:`pihim.inspection.canting` -- per-facet canting from the target's
  outlines mirrored in each facet (the paper's grid search and a continuous
  refinement), relative to the best-fit heliostat orientation.
* :mod:`pihim.inspection.calibration` -- camera calibration on checkerboards
  (OpenCV).
* :mod:`pihim.inspection.pipeline` -- one frame and its log to a refined
  pose and per-facet canting; several frames combined (``pihim canting``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pihim._lazy import lazy_exports

#: Exported names by submodule; a submodule is imported when one of its names is first used.
_EXPORTS: dict[str, list[str]] = {
    "contrast": ["PAPER_ROI_SIZE", "RoiPairContrast", "contrast_ratio", "michelson_contrast", "roi_pair_contrast"],
    "edges": [
        "EDGE_METHODS", "EdgeMap", "EdgeMaps", "IMAGE_TYPES", "axial_gradient_magnitude", "edge_maps",
        "gradient_magnitude", "noise_sigmas", "robust_thresholds", "sensor_noise",
    ],
    "success": [
        "EDGE_NAMES", "EdgeSuccess", "FacetOutlines", "FrameScore", "SuccessRate", "edge_success",
        "facet_outlines_px", "outlines_from_simulation", "outlines_from_truth", "scenario_mask", "score_frame",
        "sky_vs_sky_mask", "success_rate",
    ],
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:  # static checkers see the names where they are defined
    from pihim.inspection.contrast import (  # noqa: F401
        PAPER_ROI_SIZE, RoiPairContrast, contrast_ratio, michelson_contrast, roi_pair_contrast,
    )
    from pihim.inspection.edges import (  # noqa: F401
        EDGE_METHODS, EdgeMap, EdgeMaps, IMAGE_TYPES, axial_gradient_magnitude, edge_maps, gradient_magnitude,
        noise_sigmas, robust_thresholds, sensor_noise,
    )
    from pihim.inspection.success import (  # noqa: F401
        EDGE_NAMES, EdgeSuccess, FacetOutlines, FrameScore, SuccessRate, edge_success, facet_outlines_px,
        outlines_from_simulation, outlines_from_truth, scenario_mask, score_frame, sky_vs_sky_mask, success_rate,
    )
