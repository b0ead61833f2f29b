"""The learning stage: a project's calibration from its labelled observations, by kind of phantom.

A 3D bead phantom is calibrated by the learning loop (:func:`fluorocal.stages.learn.calibrate`, start
values by resection), a grid plate by the plate's own solve (:func:`fluorocal.stages.plate.calibrate_plate`).
This module sits above both packages, so that neither imports the other.
"""

from __future__ import annotations

from dataclasses import dataclass

from fluorocal.stages.learn import LearnParams, LearnResult, Scheme, calibrate, start_orientation
from fluorocal.stages.learn.order import canonical_order, taken
from fluorocal.stages.plate import PlateCalibration, PlateParams, calibrate_plate

__all__ = ["CalibrationSetup", "LearnParams", "learn_calibration"]


@dataclass(frozen=True)
class CalibrationSetup:
    """What the pipeline knows of the project and :func:`learn_calibration` needs.

    Attributes
    ----------
    scheme : Scheme
        Config ``[calibration] scheme``; a spelling given is parsed (:meth:`Scheme.parse`).
    image_size_px : tuple of (int, int)
        ``(width, height)`` of each system's frames.
    iop_guess_px : tuple of (float, float, float)
        Start values ``(xp, yp, c)`` per system: the image centre and source-image distance / pixel pitch.
    orientations : tuple of (int, int, str, float or None, float or None)
        A grid plate's frames: ``(system, exposure, orientation name, orbit_deg, tilt_deg)`` each (a
        3D phantom's system is one orientation: empty).
    """

    scheme: Scheme = Scheme.KNN_IOP_SMOOTH
    image_size_px: tuple = ()
    iop_guess_px: tuple = ()
    orientations: tuple = ()

    def __post_init__(self):
        object.__setattr__(self, "scheme", Scheme.parse(self.scheme, where="CalibrationSetup.scheme"))


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
        return calibrate_plate(
            observations,
            phantom,
            PlateParams() if plate is None else plate,
            image_size_px=setup.image_size_px,
            orientations=setup.orientations,
            learn_fields=setup.scheme.corrects,
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
