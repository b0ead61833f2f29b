"""Kinds of calibration object: one object each, behind one interface (:class:`~.base.PhantomKind`).

A 3D bead phantom (:class:`~.beads.BeadPhantom`) and a grid plate of each lattice
(:class:`~.plate.GridPlate`) differ in how their frames are labelled, what calibrates them, which schemes
and config sections they accept, whether two systems' frames pair, and what their outputs and evaluation
say. The kind is looked up in :data:`KINDS` by the spelling of the project's ``[phantom]`` table (the
``lattice`` given, ``""`` for a phantom file alone): the data chooses from this fixed table, and every
caller asks the kind instead of testing ``phantom.lattice``. The pipeline's share of a kind (its exports,
its evaluation, its checks) is :mod:`fluorocal.kinds`, keyed by the kind's :attr:`~.base.PhantomKind.name`.

The stage entries below dispatch on the phantom given: :func:`label_sequence` is the label stage,
:func:`learn_calibration` the learning stage. This package sits above the labelling, the learning and
the plate's packages, so that none of them imports another's kind.
"""

from __future__ import annotations

from fluorocal.stages.errors import InputError
from fluorocal.stages.kinds.base import CalibrationSetup, PhantomKind
from fluorocal.stages.kinds.beads import BeadPhantom
from fluorocal.stages.kinds.plate import GridPlate
from fluorocal.stages.label import LabelParams, Labels
from fluorocal.stages.label.lattice import LATTICES
from fluorocal.stages.learn import LearnParams, LearnResult
from fluorocal.stages.plate import PlateCalibration

#: spelling of the ``[phantom]`` table (its ``lattice``; ``""``: a phantom file) -> the kind it names
KINDS: dict[str, PhantomKind] = {"": BeadPhantom(), **{lattice: GridPlate(lattice) for lattice in LATTICES}}


def phantom_kind(spelling: str) -> PhantomKind:
    """The kind the ``[phantom]`` table's spelling names (:data:`KINDS`).

    Raises
    ------
    InputError
        A spelling of no kind.

    Examples
    --------
    >>> phantom_kind("hex").name, phantom_kind("").noun
    ('plate', 'a 3D bead phantom')
    """
    if spelling not in KINDS:
        given = ", ".join(repr(k) for k in KINDS if k)
        raise InputError(f"phantom.lattice must be one of {given} (or none, for a phantom file); got {spelling!r}")
    return KINDS[spelling]


def kind_of(phantom) -> PhantomKind:
    """The kind of a :class:`~fluorocal.stages.artifacts.Phantom`, by the spelling it carries."""
    return phantom_kind(phantom.lattice)


def label_beads(centroids, phantom, params: LabelParams, prior_pose: tuple | None = None) -> Labels:
    """Give every detection of one frame its phantom bead id (or grid-plate hole id), as the phantom's kind does.

    Parameters
    ----------
    centroids : Centroids
        The centroid stage's output for the frame: ``xy_px (M, 2)``, ``sigma_x``, ``sigma_y``, ``rho``,
        ``major_px``, ``minor_px`` (semi-axes) and ``ok`` per detection.
    phantom : Phantom
        Nominal bead coordinates and roles, or a grid plate (``lattice``, ``pitch_mm``).
    params : LabelParams
        ``source_image_distance_mm`` and ``pixel_pitch_mm`` must be set for a 3D phantom.
    prior_pose : (q, source_mm), optional
        A 3D phantom's approximate pose, e.g. a neighbouring frame's; tried when the markers give no
        acceptable labelling (ignored when seeds are given). Its orientation is taken as right within a few
        degrees (small rotations of it about any axis are searched, :mod:`fluorocal.stages.label.prior`), its
        position not: the phantom's shift across the beam is searched over the whole image and its distance
        over a few %. The labelling found is kept only if no rival explains the frame about as well (a
        periodic bead layout one row off, a pose that a symmetry of the phantom allows), unless the beads'
        sizes or a much nearer prior orientation rule it out; :func:`label_sequence` gives the search the
        sequence's motion as well. A grid plate's holes are indexed on its lattice (no pose needed).

    Returns
    -------
    Labels
        ``ok = False`` with a ``reason`` when the frame could not be labelled reliably.

    Raises
    ------
    InputError
        A 3D phantom without ``source_image_distance_mm`` and ``pixel_pitch_mm``, a phantom of fewer than 4
        beads, a grid plate without a valid lattice or pitch, or seeds naming beads the phantom lacks.
    """
    return kind_of(phantom).label_frame(centroids, phantom, params, prior_pose)


def label_sequence(
    centroids_seq, phantom, params: LabelParams, seeds_by_frame: dict | None = None
) -> tuple[Labels, ...]:
    """The label stage: one system's frames labelled in exposure order, as the phantom's kind labels them.

    A 3D bead phantom's frames each from its own markers or seeds, else from its neighbours
    (:func:`fluorocal.stages.label.label_bead_sequence`); a grid plate's holes on its lattice, with one
    numbering across the frames (:func:`fluorocal.stages.label.label_plate_sequence`).

    Parameters
    ----------
    centroids_seq : sequence of Centroids
        The frames in acquisition order.
    phantom : Phantom
    params : LabelParams
        Its ``seeds`` are ignored here; give them per frame in ``seeds_by_frame``.
    seeds_by_frame : dict of int to tuple, optional
        Frame position -> ``(id, x_px, y_px)`` seeds of that frame.

    Returns
    -------
    tuple of Labels
        One per frame, in order.
    """
    return kind_of(phantom).label_sequence(centroids_seq, phantom, params, seeds_by_frame)


def learn_calibration(
    observations, phantom, params: LearnParams, *, setup: CalibrationSetup, solver=None, selection=None, plate=None
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

    Raises
    ------
    EstimationError
        No frame could be resected, or the adjustment failed as a whole.
    """
    kind = kind_of(phantom)
    return kind.calibrate(observations, phantom, params, setup=setup, solver=solver, selection=selection, plate=plate)


__all__ = [
    "KINDS",
    "BeadPhantom",
    "CalibrationSetup",
    "GridPlate",
    "LearnParams",
    "PhantomKind",
    "kind_of",
    "label_beads",
    "label_sequence",
    "learn_calibration",
    "phantom_kind",
]
