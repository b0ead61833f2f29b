"""Self-supervised distortion learning: a cross-validated kNN field alternating with the adjustment.

Chow et al., section IV after equation 2 and section VI: the residuals of the
robust bundle adjustment hold a deterministic part (distortion, the
intensifier's departure from a pinhole) and a random part. A k-nearest-
neighbour regression of the inlier residual vectors over the image learns the
deterministic part ``δ``; the corrections are accumulated, ``Δ += δ``, at every
observation and the adjustment is repeated with ``Δ`` held constant, until the
sum of the weighted costs of equations 2 and 3 stops falling.

Conventions (docs/concepts.md, "Conventions"): pixel coordinates ``(x, y)`` with the
centre of the top-left pixel at ``(0, 0)``; the correction ``Δ`` acts on
measured (distorted) coordinates, ``ideal = measured - Δ(measured)``.

Modules, one job each
---------------------
- :mod:`~fluorocal.stages.field` (outside this package: the calibration file
  stores it): :class:`CorrectionField`, the gridded ``Δ``, and
  :class:`PointwiseField`, the unsmoothed scheme's sum of kNN models.
- :mod:`.params`: :class:`LearnParams`, its switches' enumerations (:class:`Acceleration`,
  :class:`Refine`, :class:`Training`, :class:`FieldGauge`), :data:`SCHEMES` and the presets
  (``recommended``, the default, and ``paper``, the loop as written).
- :mod:`.nodes`: the node grid and its support rule (:class:`GridSpec`).
- :mod:`.knn`: :class:`KnnModel`, :func:`cross_validate_k` (``k`` from shuffled
  K-fold cross-validation of the equation-3 cost) and :func:`fit_knn_field`.
- :mod:`.grid`: the gridded least-squares field :func:`fit_grid_field` and its
  smoothness by :func:`cross_validate_smoothness` (beyond the paper).
- :mod:`.network`: the systems' orientation linearised at an adjustment (Jacobian, datum, affine modes).
- :mod:`.joint`: :func:`fit_grids_jointly`, the refinement's field step of every system at once with the
  orientation's response (IOP, poses, points) eliminated (beyond the paper).
- :mod:`.robust`: gross errors in the regressions: the local screen, the misfit test, bounded CV costs.
- :mod:`.gauge`: what the orientation reproduces exactly, removed from a field.
- :mod:`.anderson`: Anderson acceleration of the fixed-point iteration.
- :mod:`.adjuster`: every call into :mod:`fluorocal.stages.adjust`.
- :mod:`.loop`: :func:`calibrate`, the alternation, its stopping rule and acceleration.
- :mod:`.order`: the observations' canonical order (one result whatever the order of the rows).
- :mod:`.finish`: the result from the loop's final state.
- :mod:`.polynomial`: scheme ``polynomial``, the expert method the paper
  compares with (a global model estimated in the adjustment).
- :mod:`.result`: :class:`IterationRecord`, :class:`LearnResult`.

The learning stage's entry, which calibrates a bead phantom here and a grid plate by
:mod:`fluorocal.stages.plate`, is the phantom kind's (:mod:`fluorocal.stages.kinds`, above both packages).
"""

from __future__ import annotations

from fluorocal.stages.field import CorrectionField, PointwiseField, grid_nodes
from fluorocal.stages.learn.adjuster import start_orientation
from fluorocal.stages.learn.grid import GridCvReport, cross_validate_smoothness, fit_grid_field
from fluorocal.stages.learn.joint import fit_grid_jointly
from fluorocal.stages.learn.knn import CvReport, KnnModel, cross_validate_k, fit_knn_field
from fluorocal.stages.learn.loop import calibrate
from fluorocal.stages.learn.nodes import GridSpec
from fluorocal.stages.learn.params import (
    PRESETS,
    SCHEMES,
    Acceleration,
    FieldGauge,
    LearnParams,
    Refine,
    Scheme,
    Training,
)
from fluorocal.stages.learn.result import IterationRecord, LearnResult

VERSION = 1

__all__ = [
    "VERSION",
    "SCHEMES",
    "Scheme",
    "PRESETS",
    "LearnParams",
    "Acceleration",
    "Refine",
    "Training",
    "FieldGauge",
    "GridSpec",
    "KnnModel",
    "CvReport",
    "GridCvReport",
    "CorrectionField",
    "PointwiseField",
    "IterationRecord",
    "LearnResult",
    "grid_nodes",
    "cross_validate_k",
    "cross_validate_smoothness",
    "fit_knn_field",
    "fit_grid_field",
    "fit_grid_jointly",
    "calibrate",
    "start_orientation",
]
