"""Accuracy of a map against ground truth: association, Umeyama alignment, APE, Hausdorff, place recognition, plots.

Everything here is a re-implementation on numpy/scipy (no evo, which is GPL), one concept a module:

* :mod:`~mapserver.evaluation.ape`: association by stamp, Umeyama alignment, the translation APE
  (Umeyama 1991) and the Hausdorff distance (OpenRatSLAM2 Eq. 9);
* :mod:`~mapserver.evaluation.maps`: a map JSON document against ground truth (:func:`evaluate_map`:
  the experiences' and the odometry's APE, the RPE of :mod:`mapserver.evaluation.rpe`, the Hausdorff distance);
* :mod:`~mapserver.evaluation.recognition`: place-recognition rates from the map's per-frame record;
* :mod:`~mapserver.evaluation.plots`: the map drawn over the ground truth.

Every name is importable from ``mapserver.evaluation`` itself.
"""

from __future__ import annotations

from mapserver.evaluation.ape import (
    APEResult,
    ape_positions,
    ape_rmse,
    associate,
    hausdorff,
    interpolate_poses,
    umeyama_alignment,
)
from mapserver.evaluation.maps import MapEvaluation, align_map, covered_by, evaluate_map, map_rpe, odo_yaw
from mapserver.evaluation.plots import plot_map_vs_ground_truth
from mapserver.evaluation.recognition import RecognitionSettings, place_recognition

__all__ = [
    "APEResult",
    "MapEvaluation",
    "RecognitionSettings",
    "align_map",
    "ape_positions",
    "ape_rmse",
    "associate",
    "covered_by",
    "evaluate_map",
    "hausdorff",
    "interpolate_poses",
    "map_rpe",
    "odo_yaw",
    "place_recognition",
    "plot_map_vs_ground_truth",
    "umeyama_alignment",
]
