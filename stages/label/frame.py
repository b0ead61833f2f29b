"""One frame labelled: its detections and assumed interior orientation, then a 3D bead phantom or a grid plate.

Which of the two a frame is labelled as is the phantom kind's choice (:mod:`fluorocal.stages.kinds`).
"""

from __future__ import annotations

from fluorocal.stages.artifacts import MIN_PHANTOM_BEADS, Phantom
from fluorocal.stages.errors import InputError
from fluorocal.stages.label.cube import label_cube
from fluorocal.stages.label.detections import Detections, assumed_iop
from fluorocal.stages.label.labels import Labels
from fluorocal.stages.label.lattice import check_lattice, label_grid
from fluorocal.stages.label.params import LabelParams


def label_bead_frame(centroids, phantom: Phantom, params: LabelParams, prior_pose=None, **search) -> Labels:
    """One frame of a 3D bead phantom labelled (:func:`fluorocal.stages.kinds.labelling.label_beads`).

    ``search`` holds the search options a sequence gives (:func:`~.cube.label_cube`).
    """
    if phantom.n_beads < MIN_PHANTOM_BEADS:
        raise InputError(f"phantom must have at least {MIN_PHANTOM_BEADS} beads; got {phantom.n_beads}")
    det = Detections.from_centroids(centroids)
    iop = assumed_iop(det, centroids, params, need_c=True)
    return label_cube(det, phantom, params, iop, prior_pose, **search)


def label_plate_frame(centroids, phantom: Phantom, params: LabelParams) -> Labels:
    """One frame of a grid plate labelled: its holes indexed on the plate's lattice (:func:`~.lattice.label_grid`)."""
    det = Detections.from_centroids(centroids)
    iop = assumed_iop(det, centroids, params, need_c=False)
    check_lattice(phantom.lattice, "label_plate_frame")  # the lattice's geometry would take any other as a square
    if not phantom.pitch_mm > 0:
        raise InputError(f"phantom.pitch_mm must be > 0 for a grid plate; got {phantom.pitch_mm}")
    return label_grid(det, phantom, params, iop)


def checked_seed_frames(seeds_by_frame: dict | None, n_frames: int) -> dict:
    """``seeds_by_frame`` (frame position -> seeds) as a dict, refused when it names a frame outside the sequence."""
    seeds_by_frame = dict(seeds_by_frame or {})
    bad = [i for i in seeds_by_frame if not 0 <= i < n_frames]
    if bad:
        raise InputError(f"seeds_by_frame names frames {bad} outside 0..{n_frames - 1}")
    return seeds_by_frame
