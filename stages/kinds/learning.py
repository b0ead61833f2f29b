"""The learning stage: a project's calibration from its labelled observations, as the phantom's kind is calibrated.

The stage's entry module, apart from :mod:`.labelling`: it alone imports the solvers, so an edit of them
changes the learning's cache key and not the labels'. A kind's calibration is found in
:data:`CALIBRATIONS` by its :attr:`~fluorocal.stages.kinds.PhantomKind.name`, as its pipeline part is
in :data:`fluorocal.kinds.PARTS`; every kind has one:

>>> from fluorocal.stages.kinds import KINDS
>>> sorted({kind.name for kind in KINDS.values()}) == sorted(CALIBRATIONS)
True
"""

from __future__ import annotations

from dataclasses import dataclass

from fluorocal.stages.kinds import kind_of
from fluorocal.stages.learn import LearnParams, LearnResult, Scheme, calibrate, start_orientation
from fluorocal.stages.learn.order import canonical_order, taken
from fluorocal.stages.plate import PlateCalibration, PlateParams, calibrate_plate

__all__ = ["CALIBRATIONS", "CalibrationSetup", "LearnParams", "learn_calibration"]


@dataclass(frozen=True)
class CalibrationSetup:
    """What the pipeline knows of the project and a kind's calibration needs.

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


def calibrate_beads(
    observations,
    phantom,
    params: LearnParams,
    *,
    setup: CalibrationSetup,
    solver=None,
    selection=None,
    plate=None,
    workers=1,
) -> LearnResult:
    """A 3D bead phantom: start values by resection, then :func:`fluorocal.stages.learn.calibrate`.

    ``plate`` is not read.
    """
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
        workers=workers,
    )


def calibrate_grid_plate(
    observations, phantom, params, *, setup: CalibrationSetup, solver=None, selection=None, plate=None, workers=1
) -> PlateCalibration:
    """A grid plate: :func:`fluorocal.stages.plate.calibrate_plate` with ``plate`` (default ``PlateParams()``).

    A field per orientation and the plate's errors; scheme ``none`` fits homographies only (no field).
    ``params``, ``selection`` (the learning's) and ``workers`` are not read.
    """
    return calibrate_plate(
        observations,
        phantom,
        PlateParams() if plate is None else plate,
        image_size_px=setup.image_size_px,
        orientations=setup.orientations,
        learn_fields=setup.scheme.corrects,
        solver=solver,
    )


#: a kind's :attr:`~fluorocal.stages.kinds.PhantomKind.name` -> how it is calibrated
CALIBRATIONS = {"beads": calibrate_beads, "plate": calibrate_grid_plate}


def learn_calibration(
    observations,
    phantom,
    params: LearnParams,
    *,
    setup: CalibrationSetup,
    solver=None,
    selection=None,
    plate=None,
    workers=1,
) -> LearnResult | PlateCalibration:
    """The learning stage: calibrate from labelled observations, as the phantom's kind is calibrated.

    A 3D bead phantom by start values from resection, then :func:`fluorocal.stages.learn.calibrate`
    (a :class:`~fluorocal.stages.learn.LearnResult`); a grid plate by
    :func:`fluorocal.stages.plate.calibrate_plate` (a field per orientation, the plate's errors estimated;
    a :class:`~fluorocal.stages.plate.PlateCalibration`), with ``plate`` its parameters; scheme ``none``
    then fits homographies only (no field).

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
    workers : int
        Threads for a bead phantom's systems' own work, side by side (the pipeline's worker count; default 1,
        serial): the result is the serial one's, so it is no parameter of the calibration.

    Raises
    ------
    EstimationError
        No frame could be resected, or the adjustment failed as a whole.
    """
    calibration = CALIBRATIONS[kind_of(phantom).name]
    settings = dict(setup=setup, solver=solver, selection=selection, plate=plate, workers=workers)
    return calibration(observations, phantom, params, **settings)
