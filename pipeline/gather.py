"""Per-project inputs assembled from per-frame artifacts."""

from __future__ import annotations

import numpy as np
from fluorocal.stages.artifacts import Observations
from fluorocal.stages.errors import InputError


def failed_frames(units, labels) -> list[str]:
    """``"frame (reason)"`` of every frame whose labelling failed."""
    return [f"{unit.label} ({lab.reason})" for unit, lab in zip(units, labels) if not lab.ok]


def observations_from_labels(units, labels, config) -> Observations:
    """The observations table of every labelled bead of every frame that labelled.

    Frames whose labelling failed contribute nothing (:func:`failed_frames`
    lists them; the export reports them once per run). ``exposure`` is the
    frame's position in its system's sorted frame list, so biplanar frames
    pair in sorted order.

    Raises
    ------
    InputError
        No frame of some system could be labelled.
    """
    parts = [
        (np.full(len(lab), unit.system), np.full(len(lab), unit.exposure), lab.bead_id, lab.xy_px, lab.sigma_px)
        for unit, lab in zip(units, labels)
        if lab.ok
    ]
    names = tuple(s.name for s in config.systems)
    if not parts:
        raise InputError(
            "no frame could be labelled; check the phantom file, the [[systems]] geometry "
            "and `fluorocal inspect CONFIG label`"
        )
    system, exposure, bead_id, xy, sigma = (np.concatenate(p) for p in zip(*parts))
    for s, name in enumerate(names):
        if not np.any(system == s):
            raise InputError(f"no frame of system {name} could be labelled; see `fluorocal inspect CONFIG label`")
    return Observations(system, exposure, bead_id, xy, sigma, names)
