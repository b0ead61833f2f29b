"""The paper's evaluation protocol (Chow et al., section VI, TABLE I) on any project's labelled observations.

Half the epochs are withheld; for each training size and scheme the rig is
calibrated on a subset of the rest and scored in sample and out of sample:
reprojection RMS, object points against surveyed check points (rigid and
similarity fits) and, for a biplanar rig, two-ray intersection of the
held-out pairs (per-axis RMSE and mean 3D error after a rigid fit).

Modules
-------
- :mod:`.split`: held-out epochs and training subsets;
- :mod:`.metrics`: the figures, pure functions of points;
- :mod:`.protocol`: :func:`evaluate`, the calibrations (:func:`learned_interior`,
  the OpenCV peer :func:`opencv_interior`) and :func:`score_interior`;
- :mod:`.plate`: a grid plate's protocol, scored on held-out holes
  (:func:`~fluorocal.stages.evaluate.plate.evaluate_plate`).
"""

from __future__ import annotations

from fluorocal.stages.evaluate.metrics import (
    biplanar_errors,
    biplanar_pairs,
    check_point_errors,
    ideal_points,
    mapping_errors,
    summarise,
    two_ray_points,
)
from fluorocal.stages.evaluate.protocol import (
    OPENCV,
    Evaluation,
    EvaluationSetup,
    HeldOutResiduals,
    Interior,
    Score,
    evaluate,
    learned_interior,
    opencv_interior,
    score_interior,
)
from fluorocal.stages.evaluate.split import (
    HOLDOUT_RULES,
    MIN_TRAIN,
    check_train_sizes,
    default_train_sizes,
    heldout_epochs,
    min_train_epochs,
    training_subset,
)

__all__ = [
    "OPENCV",
    "HOLDOUT_RULES",
    "MIN_TRAIN",
    "Evaluation",
    "EvaluationSetup",
    "HeldOutResiduals",
    "Interior",
    "Score",
    "evaluate",
    "learned_interior",
    "opencv_interior",
    "score_interior",
    "heldout_epochs",
    "min_train_epochs",
    "default_train_sizes",
    "check_train_sizes",
    "training_subset",
    "biplanar_errors",
    "biplanar_pairs",
    "check_point_errors",
    "ideal_points",
    "mapping_errors",
    "summarise",
    "two_ray_points",
]
