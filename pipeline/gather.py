"""Per-project inputs assembled from per-frame artifacts."""

from __future__ import annotations

import logging

import numpy as np

from stages.artifacts import Observations
from stages.errors import InputError

log = logging.getLogger(__name__)


def observations_from_labels(units, labels, config) -> Observations:
    """The observations table of every labelled bead of every frame that labelled.

    Frames whose labelling failed contribute nothing; they are listed in a
    warning with their reason. ``exposure`` is the frame's position in its
    system's sorted frame list, so biplanar frames pair in sorted order.

    Raises
    ------
    InputError
        No frame of some system could be labelled.
    """
    parts = []
    failed = []
    for unit, lab in zip(units, labels):
        if not lab.ok:
            failed.append(f"{unit.label} ({lab.reason})")
            continue
        n = len(lab)
        parts.append((np.full(n, unit.system), np.full(n, unit.exposure), lab.bead_id, lab.xy_px, lab.sigma_px))
    if failed:
        log.warning("%d frame(s) excluded, labelling failed: %s", len(failed), "; ".join(failed))
    names = tuple(s.name for s in config.systems)
    if not parts:
        raise InputError("no frame could be labelled; check the phantom file, the [[systems]] geometry and `fluorocal inspect CONFIG label`")
    system, exposure, bead_id, xy, sigma = (np.concatenate(p) for p in zip(*parts))
    for s, name in enumerate(names):
        if not np.any(system == s):
            raise InputError(f"no frame of system {name} could be labelled; see `fluorocal inspect CONFIG label`")
    return Observations(system, exposure, bead_id, xy, sigma, names)
