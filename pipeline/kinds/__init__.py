"""The pipeline's share of each phantom kind: what its outputs, its evaluation and its checks are.

A kind (:class:`~fluorocal.stages.kinds.PhantomKind`, looked up once from the ``[phantom]`` table as
``config.phantom.kind``) owns the stages' side: labelling, calibrating, the schemes and sections it takes.
Its pipeline side is a :class:`KindPart` here (:mod:`.beads`, :mod:`.plate`), found in :data:`PARTS` by
the kind's :attr:`~fluorocal.stages.kinds.PhantomKind.name`: ``fluorocal run`` writes what
:meth:`KindPart.export` writes, ``fluorocal evaluate`` runs :meth:`KindPart.evaluate`, ``fluorocal
check`` measures a later frame against :meth:`KindPart.check_setup`. The commands ask the part; they do
not test the phantom.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

from fluorocal.kinds.beads import BeadPart
from fluorocal.kinds.plate import PlatePart


class KindPart(Protocol):
    """What the pipeline does differently for one kind of phantom.

    Attributes
    ----------
    scored_on : str
        What ``fluorocal evaluate`` scores the calibration on, as a message says it.
    figures : dict of str to str
        The figures its evaluation compares (each lower is better), by
        :class:`~fluorocal.stages.evaluate.Score` field, with their headings.
    rms_columns : dict of str to str
        The RMS columns of its evaluation's table, by ``Score`` field, with their headings.
    trained_on : str
        What a training size counts (``"epochs"``, ``"frames"``), as the table and the plots say it.
    """

    scored_on: str
    figures: dict
    rms_columns: dict
    trained_on: str

    def export(self, runner, result, obs, excluded, out_dir: Path, figures) -> list[Path]:
        """Write the learning stage's ``result`` (``calibration.json``, tables, report) into ``out_dir``."""

    def evaluate(self, args, config, runner, out_dir: Path) -> int:
        """``fluorocal evaluate`` on the project (``args`` as parsed); the exit code."""

    def check_setup(self, tables, config, table):
        """What later frames are checked against (:mod:`fluorocal.check_setups`), from the object points ``table``."""


#: a kind's :attr:`~fluorocal.stages.kinds.PhantomKind.name` -> its pipeline part
PARTS: dict[str, KindPart] = {"beads": BeadPart(), "plate": PlatePart()}


def part_of(kind) -> KindPart:
    """The pipeline part of the phantom kind ``kind`` (``config.phantom.kind``).

    Examples
    --------
    >>> from fluorocal.stages.kinds import phantom_kind
    >>> type(part_of(phantom_kind("square"))).__name__
    'PlatePart'
    """
    return PARTS[kind.name]
