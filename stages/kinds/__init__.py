"""Kinds of calibration object: one object each, behind one interface (:class:`~.base.PhantomKind`).

A 3D bead phantom (:class:`~.beads.BeadPhantom`) and a grid plate of each lattice
(:class:`~.plate.GridPlate`) differ in how their frames are labelled, what calibrates them, which schemes
and config sections they accept, whether two systems' frames pair, and what their outputs and evaluation
say. The kind is looked up in :data:`KINDS` by the spelling of the project's ``[phantom]`` table (the
``lattice`` given, ``""`` for a phantom file alone): the data chooses from this fixed table, and every
caller asks the kind instead of testing ``phantom.lattice``. The table is light to import (a kind imports
its labelling when called), so the config and the command line read their spellings from it
(:data:`LATTICE_SPELLINGS`). The pipeline's share of a kind (its exports, its evaluation, its checks) is
:mod:`fluorocal.kinds`, keyed by the kind's :attr:`~.base.PhantomKind.name`.

The stage entries dispatch on the phantom given, each in a module of its own so that a stage's cache key
covers only the code it runs: :func:`.labelling.label_sequence` is the label stage (it imports the
labelling alone), :func:`.learning.learn_calibration` the learning stage (the solvers, a kind's
calibration found in :data:`.learning.CALIBRATIONS` by its name). This package sits above the labelling,
the learning and the plate's packages, so that none of them imports another's kind.
"""

from __future__ import annotations

from fluorocal.stages.errors import InputError
from fluorocal.stages.kinds.base import PhantomKind
from fluorocal.stages.kinds.beads import BeadPhantom
from fluorocal.stages.kinds.plate import GridPlate
from fluorocal.stages.lattices import LATTICES

#: spelling of the ``[phantom]`` table (its ``lattice``; ``""``: a phantom file) -> the kind it names
KINDS: dict[str, PhantomKind] = {"": BeadPhantom(), **dict.fromkeys(LATTICES, GridPlate())}

#: the values ``[phantom] lattice`` takes: every spelling of :data:`KINDS` but a phantom file's ``""``
LATTICE_SPELLINGS = tuple(spelling for spelling in KINDS if spelling)


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
        given = ", ".join(map(repr, LATTICE_SPELLINGS))
        raise InputError(f"phantom.lattice must be one of {given} (or none, for a phantom file); got {spelling!r}")
    return KINDS[spelling]


def kind_of(phantom) -> PhantomKind:
    """The kind of a :class:`~fluorocal.stages.artifacts.Phantom`, by the spelling it carries."""
    return phantom_kind(phantom.lattice)


__all__ = ["KINDS", "LATTICE_SPELLINGS", "BeadPhantom", "GridPlate", "PhantomKind", "kind_of", "phantom_kind"]
