"""The frames of one system's sequence: each labelled from its own markers or seeds, else from its neighbours."""

from __future__ import annotations

import logging
from dataclasses import replace

from fluorocal.stages.artifacts import Phantom
from fluorocal.stages.geometry import iop_guess, quat_to_matrix
from fluorocal.stages.label.frame import checked_seed_frames, label_bead_frame
from fluorocal.stages.label.labels import Labels
from fluorocal.stages.label.motion import Motion, neighbours, predict
from fluorocal.stages.label.params import LabelParams

log = logging.getLogger(__name__)

# a frame whose orientation lies this many standard deviations from its neighbours' prediction is checked
_SUSPECT_SIGMAS = 6.0


def label_bead_sequence(
    centroids_seq, phantom: Phantom, params: LabelParams, seeds_by_frame: dict | None = None
) -> tuple[Labels, ...]:
    """Label the frames of one system's sequence of a 3D bead phantom, each from its own evidence, else its neighbours.

    First every frame is labelled alone: from its seeds (``seeds_by_frame[i]``, ``(id, x_px, y_px)``
    triples) or its markers. A frame labelled from its markers whose labelling leaves much of it
    unexplained, or whose pose lies far from its neighbours', is weighed against the labellings found near
    its neighbours' orientation (:func:`_suspect`); the former is not first searched around its own pose, as
    a frame alone is (:func:`~fluorocal.stages.label.cube.label_cube`), unless fewer than two frames are
    labelled alone. Then each frame that failed is labelled from its labelled
    neighbours, those nearest a labelled frame first, and each frame so labelled serves its own neighbours in turn:
    the orientation is predicted between the nearest labelled frames on either side (or from one side
    and the sequence's mean motion per frame), and rotations about it are searched with the position
    free (:func:`fluorocal.stages.label.prior.label_from_prior`), then turns about the turntable axis
    over the full circle. Each frame is accepted or rejected on its own evidence, and a frame that
    still fails keeps the reasons of both attempts.

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
    n = len(centroids_seq)
    seeds_by_frame = checked_seed_frames(seeds_by_frame, n)
    base = replace(params, seeds=())
    out = []
    for i in range(n):
        seeds = tuple(tuple(s) for s in seeds_by_frame.get(i, ()))
        # a doubtful marker labelling is weighed against the neighbours below, not first searched around (seconds)
        own = replace(base, seeds=seeds) if seeds else base
        out.append(label_bead_frame(centroids_seq[i], phantom, own, search_around=False))
    if sum(lab.ok for lab in out) < 2:  # no neighbour to weigh it against before it serves them: as alone
        out = [label_bead_frame(c, phantom, base) if _doubtful(lab) else lab for c, lab in zip(centroids_seq, out)]
    own_reason = [lab.reason for lab in out]
    c_assumed = float(iop_guess((1, 1), params.source_image_distance_mm, params.pixel_pitch_mm)[2])
    tried: dict[int, tuple] = {}  # frame -> the labelled neighbours it was last tried from
    checked = set(seeds_by_frame)  # frames whose pose was checked against their neighbours' (seeds: trusted)
    while True:
        labelled = {i: lab for i, lab in enumerate(out) if lab.ok}
        if not labelled:  # no frame to start from: every frame keeps its own reason
            return out
        rotations = {i: quat_to_matrix(lab.q) for i, lab in labelled.items()}
        motion = Motion.of(rotations, {i: _depth(lab, phantom, c_assumed) for i, lab in labelled.items()})
        suspect = _suspect(labelled, rotations, checked, motion)
        if suspect is not None:
            # weighed against the labellings found near its neighbours' orientation (before it serves as a
            # neighbour itself)
            i, why = suspect
            log.debug("frame %d is weighed against its neighbours' labellings: %s", i, why)
            checked.add(i)
            others = {j: lab for j, lab in labelled.items() if j != i}
            lab = _from_neighbours(centroids_seq[i], phantom, base, i, others, motion, pool=True)
            out[i] = lab if lab.ok else replace(lab, reason=f"{why}: {lab.reason}")
            continue
        # a frame is tried again when the labellings of its nearest labelled neighbours change
        pending = [(i, neighbours(i, rotations)) for i in range(n) if i not in labelled]
        pending = [(i, nb) for i, nb in pending if nb != (None, None) and tried.get(i) != _key(nb, labelled)]
        if not pending:
            return tuple(out)
        # nearest a labelled frame first, those between two labelled frames before those beside one
        i, nb = min(pending, key=lambda e: (min(abs(e[0] - j) for j in e[1] if j is not None), None in e[1]))
        tried[i] = _key(nb, labelled)
        lab = _from_neighbours(centroids_seq[i], phantom, base, i, labelled, motion, pool=False)
        out[i] = lab if lab.ok else replace(lab, reason=f"{own_reason[i]}; from the neighbouring frames: {lab.reason}")
        checked.add(i)


def _depth(lab: Labels, phantom: Phantom, c_assumed: float) -> float:
    """The phantom centre's distance from the source (mm) in a labelled frame, as the assumed camera sees it.

    The labelling refines the principal distance ``c``, and the depth it finds scales with it: the depth
    seen with the assumed ``c`` (as the next frame's search starts) is the found one times ``c_assumed / c``.
    """
    z = float((quat_to_matrix(lab.q) @ (phantom.xyz_mm.mean(0) - lab.source_mm))[2])
    return z * c_assumed / float(lab.iop[2])


def _key(nb: tuple, labelled: dict) -> tuple:
    """The neighbours ``nb`` with their poses: what a frame was last tried from."""
    return tuple(None if j is None else (j, labelled[j].q.tobytes()) for j in nb)


def _from_neighbours(
    centroids, phantom: Phantom, params: LabelParams, i: int, labelled: dict, motion: Motion, *, pool: bool
) -> Labels:
    """Frame ``i`` labelled from the orientation its ``labelled`` neighbours predict (with its markers: ``pool``)."""
    prior, near, _ = predict(i, {j: quat_to_matrix(lab.q) for j, lab in labelled.items()}, motion)
    return label_bead_frame(
        centroids,
        phantom,
        params,
        (labelled[near].q, labelled[near].source_mm),
        orientation_prior=prior,
        turn_search=True,
        from_markers=pool,
        pool=pool,
        reference=labelled[near],
    )


def _doubtful(lab: Labels) -> bool:
    """True for a frame labelled from its own markers whose labelling leaves much of it unexplained."""
    return lab.ok and lab.pose_source == "markers" and not lab.explains_most


def _suspect(labelled: dict, rotations: dict, checked: set, motion) -> tuple[int, str] | None:
    """A labelled frame, not ``checked`` yet, to weigh against its neighbours, and why; None if there is none.

    First a frame labelled from its own markers whose labelling leaves much of it unexplained: a marker
    pose a few degrees off converges with the polynomial correction bent to fit, its residuals as small as
    the truth's, and no slip or symmetry of it is the truth, while a wobbling turntable puts that pose
    well within its neighbours' prediction. Then the frame farthest from its neighbours' prediction, when
    beyond ``_SUSPECT_SIGMAS`` of the prediction's uncertainty.
    """
    if len(labelled) < 2:
        return None
    for i, lab in labelled.items():
        if i not in checked and _doubtful(lab):
            return i, "its labelling from its markers leaves much of the frame unexplained, and from its neighbours"
    worst, worst_d = None, _SUSPECT_SIGMAS
    for i, R in rotations.items():
        if i in checked:
            continue
        predicted = predict(i, rotations, motion)
        if predicted is not None and predicted[0].distance(R) > worst_d:
            worst, worst_d = i, predicted[0].distance(R)
    return None if worst is None else (worst, f"its pose is {worst_d:.1f} sigmas from its neighbours' prediction")
