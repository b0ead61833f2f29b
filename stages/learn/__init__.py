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
- :mod:`.params`: :class:`LearnParams`, :data:`SCHEMES` and the presets
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
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from fluorocal.stages.field import CorrectionField, PointwiseField, grid_nodes
from fluorocal.stages.learn.adjuster import start_orientation
from fluorocal.stages.learn.grid import GridCvReport, cross_validate_smoothness, fit_grid_field
from fluorocal.stages.learn.joint import fit_grid_jointly
from fluorocal.stages.learn.knn import CvReport, KnnModel, cross_validate_k, fit_knn_field
from fluorocal.stages.learn.loop import calibrate
from fluorocal.stages.learn.nodes import GridSpec
from fluorocal.stages.learn.order import canonical_order, taken
from fluorocal.stages.learn.params import PRESETS, SCHEMES, LearnParams
from fluorocal.stages.learn.result import IterationRecord, LearnResult

if TYPE_CHECKING:  # the plate's modules import the learning's: imported where used (see learn_calibration)
    from fluorocal.stages.plate import PlateCalibration

VERSION = 1

__all__ = [
    "VERSION",
    "SCHEMES",
    "PRESETS",
    "LearnParams",
    "GridSpec",
    "KnnModel",
    "CvReport",
    "GridCvReport",
    "CorrectionField",
    "PointwiseField",
    "IterationRecord",
    "LearnResult",
    "CalibrationSetup",
    "grid_nodes",
    "cross_validate_k",
    "cross_validate_smoothness",
    "fit_knn_field",
    "fit_grid_field",
    "fit_grid_jointly",
    "calibrate",
    "learn_calibration",
]


@dataclass(frozen=True)
class CalibrationSetup:
    """What the pipeline knows of the project and :func:`learn_calibration` needs.

    Attributes
    ----------
    scheme : str
        One of :data:`SCHEMES` (config ``[calibration] scheme``).
    image_size_px : tuple of (int, int)
        ``(width, height)`` of each system's frames.
    iop_guess_px : tuple of (float, float, float)
        Start values ``(xp, yp, c)`` per system: the image centre and source-image distance / pixel pitch.
    orientations : tuple of (int, int, str, float or None, float or None)
        A grid plate's frames: ``(system, exposure, orientation name, orbit_deg, tilt_deg)`` each (a
        3D phantom's system is one orientation: empty).
    """

    scheme: str = "knn+iop+smooth"
    image_size_px: tuple = ()
    iop_guess_px: tuple = ()
    orientations: tuple = ()


def learn_calibration(
    observations, phantom, params: LearnParams, *, setup: CalibrationSetup, solver=None, selection=None, plate=None
) -> LearnResult | PlateCalibration:
    """Calibrate from labelled observations: start values by resection, then :func:`calibrate`.

    A grid plate is calibrated by :func:`fluorocal.stages.plate.calibrate_plate` instead (a field per
    orientation, the plate's errors estimated), with ``plate`` its parameters, and the result is a
    :class:`fluorocal.stages.plate.PlateCalibration`; scheme ``none`` then fits homographies only (no field).

    Parameters
    ----------
    observations : Observations
    phantom : Phantom
        Nominal (design) bead coordinates.
    params : LearnParams
    setup : CalibrationSetup
        The scheme (which decides, among others, whether the field is smoothed), image sizes and IOP guesses.
    solver, selection : SolverOptions, DataSelection, optional
        The adjustment's settings from ``[adjust]`` (the free parameters are the scheme's).
    plate : PlateParams, optional
        A grid plate's settings from ``[plate]`` (default ``PlateParams()``).

    Raises
    ------
    EstimationError
        No frame could be resected, or the adjustment failed as a whole.
    """
    if phantom.lattice:
        # imported here: the plate's modules use the learning's grid fits (a cycle at import time otherwise)
        from fluorocal.stages.plate import PlateParams, calibrate_plate

        return calibrate_plate(
            observations,
            phantom,
            PlateParams() if plate is None else plate,
            image_size_px=setup.image_size_px,
            orientations=setup.orientations,
            learn_fields=setup.scheme != "none",
            solver=solver,
        )
    # the resection too sees the rows in the canonical order that calibrate runs on
    initial = start_orientation(taken(observations, canonical_order(observations)), phantom, setup.iop_guess_px)
    return calibrate(
        observations,
        phantom,
        initial,
        image_size=setup.image_size_px,
        scheme=setup.scheme,
        params=params,
        solver=solver,
        selection=selection,
    )
