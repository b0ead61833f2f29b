"""Per-project inputs assembled from per-frame artifacts."""

from __future__ import annotations

import numpy as np
from fluorocal.stages.artifacts import Observations
from fluorocal.stages.errors import InputError


def frame_description(unit, config) -> str:
    """A frame as a user finds it: its system, its file and, in a multi-frame file, its index.

    The file is relative to the config, as its frames are given: ``"system A: frames/A/cine.dcm frame 3"``.
    """
    system = config.systems[unit.system].name
    path, root = unit.path.resolve(), config.root.resolve()
    where = path.relative_to(root) if path.is_relative_to(root) else path
    return f"system {system}: {where}" + (f" frame {unit.index}" if unit.index else "")


def failed_frames(units, labels, config) -> list[str]:
    """``"system S: file (reason)"`` of every frame whose labelling failed (:func:`frame_description`)."""
    return [f"{frame_description(unit, config)} ({lab.reason})" for unit, lab in zip(units, labels) if not lab.ok]


def labelling_line(labels) -> str:
    """Frames labelled in one line, and how many of them from their neighbours' poses: ``"4/5 frames (1 ...)"``.

    A frame labelled from its neighbours (``pose_source`` ``"prior"``) is one whose own markers or seeds
    did not do; that first attempt is logged at DEBUG only.
    """
    ok = sum(lab.ok for lab in labels)
    recovered = sum(lab.ok and lab.pose_source == "prior" for lab in labels)
    return f"{ok}/{len(labels)} frames" + (f" ({recovered} recovered from their neighbours)" if recovered else "")


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
