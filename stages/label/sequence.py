"""The frames of one system's sequence labelled in order, each frame's pose passed on to its neighbours."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from fluorocal.stages.artifacts import Phantom
from fluorocal.stages.errors import InputError
from fluorocal.stages.geometry import quat_to_matrix
from fluorocal.stages.label.frame import label_beads, label_frame
from fluorocal.stages.label.labels import Labels
from fluorocal.stages.label.lattice_sequence import number_lattice_sequence
from fluorocal.stages.label.params import LabelParams

# the turntable axis is estimated from the sequence once its labelled frames span this turn
_MIN_AXIS_TURN_DEG = 3.0


def label_sequence(
    centroids_seq, phantom: Phantom, params: LabelParams, seeds_by_frame: dict | None = None
) -> tuple[Labels, ...]:
    """Label the frames of one system's sequence, passing each frame's pose on to its neighbours.

    Frames with seeds (``seeds_by_frame[i]``, ``(id, x_px, y_px)`` triples) are labelled from them; the
    others from the markers and from the pose of the nearest labelled frame before them (a forward
    pass), then, for frames still unlabelled, of the nearest one after them (a backward pass). The
    neighbour's position is searched over the whole image (see :func:`label_beads`); a frame that
    still fails is searched over turns about the turntable axis, estimated from the labelled frames'
    orientations (before they span a few degrees: the image's vertical axis). Each frame is still
    accepted or rejected on its own evidence.

    Parameters
    ----------
    centroids_seq : sequence of Centroids
        The frames in acquisition order.
    phantom : Phantom
    params : LabelParams
        Its ``seeds`` are ignored here; give them per frame in ``seeds_by_frame``.
    seeds_by_frame : dict of int to tuple, optional

    Returns
    -------
    tuple of Labels
        One per frame, in order.
    """
    seeds_by_frame = dict(seeds_by_frame or {})
    n = len(centroids_seq)
    bad = [i for i in seeds_by_frame if not 0 <= i < n]
    if bad:
        raise InputError(f"seeds_by_frame names frames {bad} outside 0..{n - 1}")
    base = replace(params, seeds=())
    out: list[Labels | None] = [None] * n
    rotations: dict[int, np.ndarray] = {}  # frame -> R (object to camera) of the labelled frames

    def run(i, prior):
        seeds = tuple(tuple(s) for s in seeds_by_frame.get(i, ()))
        if seeds:
            return label_beads(centroids_seq[i], phantom, replace(base, seeds=seeds))
        axis = _turntable_axis(list(rotations.values())) if prior is not None else None
        return label_frame(centroids_seq[i], phantom, base, prior, axis)

    def keep(i):
        if out[i].ok and not phantom.lattice:
            rotations[i] = quat_to_matrix(out[i].q)
            return (out[i].q, out[i].source_mm)
        return None

    prior = None
    for i in range(n):
        out[i] = run(i, prior)
        prior = keep(i) or prior
    prior = None
    for i in reversed(range(n)):
        if not out[i].ok and prior is not None:
            out[i] = run(i, prior)
        prior = keep(i) or prior
    if phantom.lattice:  # one numbering of the plate's holes across the frames
        return number_lattice_sequence(out, phantom.lattice, phantom.pitch_mm)
    return tuple(out)


def _turntable_axis(rotations: list) -> np.ndarray | None:
    """The axis (camera frame) about which the phantom turns between the labelled frames of a sequence.

    A turntable turns the phantom about an axis fixed in the lab, hence in the camera frame of a
    system: ``R_j R_i^T`` is a turn about it. The axis is the principal direction of the rotation
    vectors of every labelled frame relative to the first, once they span at least
    ``_MIN_AXIS_TURN_DEG``; before that, the image's vertical axis (a turntable seen by a horizontal
    beam, the usual setup). None without a labelled frame.
    """
    from scipy.spatial.transform import Rotation

    if not rotations:
        return None
    Rs = np.asarray(rotations)
    rotvecs = Rotation.from_matrix(Rs @ Rs[0].T).as_rotvec()
    if np.degrees(np.linalg.norm(rotvecs, axis=1).max()) < _MIN_AXIS_TURN_DEG:
        return np.array([0.0, 1.0, 0.0])
    return np.linalg.eigh(rotvecs.T @ rotvecs)[1][:, -1]
