"""One lattice numbering for every frame of a grid plate's sequence: the same hole, the same id.

Each frame's lattice is grown from the hole nearest the image centre (:mod:`.lattice`), so its numbering
starts wherever the plate happens to sit: between C-arm orientations the plate moves by several pixels
and the numbering by a hole or so, and the lattice vectors may be picked in another of the lattice's
symmetric directions. Each frame is renumbered onto the numbering of the labelled frame whose holes lie
nearest its own (so a sequence is followed step by step): every hole is paired with the nearest hole of
that frame, and the integer map between the two numberings (a lattice symmetry and a shift) is fitted to
the pairs. A plate that moved by half a pitch or more between every pair of frames cannot be followed:
the frame then fails, with the reason.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from fluorocal.stages.label.labels import Labels, failed_labels
from fluorocal.stages.label.lattice import lattice_id, lattice_index, lattice_xyz_mm
from fluorocal.stages.label.params import STATUS_REJECTED

#: a pairing is trusted when the holes moved less than this fraction of the pitch between the frames
_MAX_MOVE_PITCH = 0.35
#: and the integer map explains at least this fraction of the pairs exactly
_MIN_AGREEMENT = 0.9


def number_lattice_sequence(labels_seq, lattice: str, pitch_mm: float) -> tuple[Labels, ...]:
    """Renumber the labelled frames of a grid-plate sequence onto the first labelled frame's numbering."""
    from scipy.spatial import cKDTree

    out = list(labels_seq)
    done = [i for i, lab in enumerate(out) if lab.ok][:1]
    todo = [i for i, lab in enumerate(out) if lab.ok][1:]
    while todo:
        # the frame nearest a numbered one: the smallest median move between the two
        best = None
        for i in todo:
            for j in done:
                d, _ = cKDTree(out[j].xy_px).query(out[i].xy_px)
                move = float(np.median(d))
                if best is None or move < best[0]:
                    best = (move, i, j)
        _, i, j = best
        out[i] = _renumbered(out[i], out[j], lattice, pitch_mm)
        todo.remove(i)
        if out[i].ok:
            done.append(i)
    return tuple(out)


def _renumbered(frame: Labels, reference: Labels, lattice: str, pitch_mm: float) -> Labels:
    """``frame`` with ids on ``reference``'s numbering, or failed when the plate moved too far to tell."""
    from scipy.spatial import cKDTree

    ij, ij_ref = lattice_index(frame.bead_id), lattice_index(reference.bead_id)
    spacing = float(np.median(cKDTree(frame.xy_px).query(frame.xy_px, k=2)[0][:, 1]))
    d, nn = cKDTree(reference.xy_px).query(frame.xy_px)
    near = d < _MAX_MOVE_PITCH * spacing
    if near.sum() < max(7, 0.5 * len(ij)):
        return _failed(
            frame,
            f"the plate moved by about half a hole pitch or more from every other frame "
            f"(median {float(np.median(d)):.1f} px); its holes cannot be numbered like theirs",
        )
    A = np.column_stack([ij[near], np.ones(int(near.sum()))])
    M = np.rint(np.linalg.lstsq(A, ij_ref[nn[near]], rcond=None)[0]).astype(np.int64)  # (3, 2): [M^T; t]
    mapped = ij @ M[:2] + M[2]
    agree = np.mean(np.all(mapped[near] == ij_ref[nn[near]], axis=1))
    if abs(round(np.linalg.det(M[:2].astype(float)))) != 1 or agree < _MIN_AGREEMENT:
        return _failed(
            frame,
            f"its lattice numbering agrees with the neighbouring frame's for only {agree:.0%} "
            "of the holes; the plate moved too far between the frames to follow it",
        )
    return replace(frame, bead_id=lattice_id(mapped), object_xyz_mm=lattice_xyz_mm(mapped, lattice, pitch_mm))


def _failed(frame: Labels, why: str) -> Labels:
    return failed_labels(frame.detection_status != STATUS_REJECTED, frame.iop, why, "lattice")
