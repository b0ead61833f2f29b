"""One lattice numbering for every frame of a grid plate's sequence: the same hole, the same id.

Each frame's lattice is grown from the hole nearest the image centre (:mod:`.lattice`), so its numbering
starts wherever the plate happens to sit and its lattice vectors may be picked in another of the
lattice's symmetric directions. A lattice looks the same one hole over, so where each hole went cannot
be read from the geometry alone once the plate moved by half a pitch or more (a plate put back by hand).
It can be read from the plate itself: its manufacturing errors (rows displaced, alternate rows offset,
each hole off by a little) are the same in every frame, a fingerprint that moves with the plate.

Each frame's fingerprint is what a homography and a smooth field leave of its hole centres,
mapped back onto the plate (:func:`fingerprint`). A frame is renumbered onto the first labelled frame's
numbering by the lattice symmetry and shift under which the two fingerprints agree best: for each of the
lattice's symmetries, one FFT cross-correlation over all shifts (:func:`match_fingerprints`). When the
plate is too good for its errors to single out a shift, the frame is renumbered by the geometry if the
plate moved less than a third of a pitch (each hole paired with the nearest of the reference frame);
otherwise it fails, with the reason.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from fluorocal.stages.artifacts import Phantom
from fluorocal.stages.label.frame import checked_seed_frames, label_plate_frame
from fluorocal.stages.label.labels import Labels, failed_labels
from fluorocal.stages.label.lattice import lattice_basis, lattice_id, lattice_index, lattice_xyz_mm
from fluorocal.stages.label.params import STATUS_REJECTED, LabelParams

log = logging.getLogger(__name__)

#: a frame with fewer holes than this fraction of the sequence's best frame is not numbered (not the plate)
_MIN_HOLE_FRACTION = 0.2
#: the geometric pairing is trusted when the holes moved less than this fraction of the pitch
_MAX_MOVE_PITCH = 0.33
#: a fingerprint match is trusted when its correlation is at least this ...
_MIN_CORRELATION = 0.3
#: ... and exceeds the best of every other symmetry and shift by this much (a shift along the rows keeps the
#: rows' displacements in register: on a real plate it still correlates about 0.7)
_MIN_MARGIN = 0.1
#: a fingerprint is taken relative to a smooth field (the distortion's share) on nodes this many pitches apart
_FINGERPRINT_SPACING_PITCH = 2.0
#: with a thin-plate prior of this standard deviation, px
_FINGERPRINT_TAU_PX = 10.0


def label_plate_sequence(
    centroids_seq, phantom: Phantom, params: LabelParams, seeds_by_frame: dict | None = None
) -> tuple[Labels, ...]:
    """Label the frames of one system's sequence of a grid plate: each frame's lattice, then one numbering.

    Seeds name frames of the sequence (refused otherwise) but do not steer a plate: its holes are indexed by
    their lattice (:func:`~.frame.label_plate_frame`), and renumbered onto one numbering across the frames
    (:func:`number_lattice_sequence`).
    """
    checked_seed_frames(seeds_by_frame, len(centroids_seq))
    base = replace(params, seeds=())
    out = [label_plate_frame(centroids, phantom, base) for centroids in centroids_seq]
    return number_lattice_sequence(out, phantom.lattice, phantom.pitch_mm)


def number_lattice_sequence(labels_seq, lattice: str, pitch_mm: float) -> tuple[Labels, ...]:
    """Renumber the labelled frames of a grid-plate sequence onto the numbering of its frame with the most holes.

    A frame with fewer than :data:`_MIN_HOLE_FRACTION` of that frame's holes fails: it is not the plate
    (a bead frame "labelled" as a few holes) or too little of it to be followed.
    """
    out = list(labels_seq)
    ok = [i for i, lab in enumerate(out) if lab.ok]
    if not ok:
        return tuple(out)
    ref = max(ok, key=lambda i: len(out[i]))
    reference = out[ref]
    for i in ok:
        if len(out[i]) < _MIN_HOLE_FRACTION * len(reference):
            out[i] = _failed(
                out[i],
                f"only {len(out[i])} holes where frame {ref} of the sequence has {len(reference)}: "
                "not the plate, or too little of it",
            )
    ok = [i for i in ok if out[i].ok]
    if len(ok) < 2:
        return tuple(out)
    ref_print = fingerprint(reference, lattice)
    for i in ok:
        if i != ref:
            out[i] = _renumbered(out[i], reference, ref_print, lattice, pitch_mm)
    return tuple(out)


def _failed(frame: Labels, why: str) -> Labels:
    return failed_labels(frame.detection_status != STATUS_REJECTED, frame.iop, why, "lattice")


@dataclass(frozen=True)
class Fingerprint:
    """A frame's plate errors as seen in it: per hole its lattice index and its offset on the plate (pitches)."""

    ij: np.ndarray  # (K, 2) int64
    offset: np.ndarray  # (K, 2) float64, plate units of one pitch


def fingerprint(labels: Labels, lattice: str) -> Fingerprint:
    """What a homography and a smooth field leave of a frame's hole centres, mapped onto the plate.

    The field (bilinear on nodes two pitches apart, a thin-plate prior) follows the distortion down to a
    few pitches; what it leaves is the plate's errors and the noise.
    """
    import cv2
    from fluorocal.stages.geometry import homography_fit
    from fluorocal.stages.learn.grid import fit_grid_field
    from fluorocal.stages.learn.nodes import GridSpec

    ij = lattice_index(labels.bead_id)
    plate = ij @ lattice_basis(lattice).T  # plate coordinates in pitches
    H, residual = homography_fit(plate, labels.xy_px)
    mapped = labels.xy_px - residual
    pitch_px = float(np.sqrt(abs(np.linalg.det(H[:2, :2]))))
    grid = GridSpec(spacing_px=_FINGERPRINT_SPACING_PITCH * pitch_px)
    size = tuple(int(np.ceil(v)) + 1 for v in labels.xy_px.max(axis=0))
    field = fit_grid_field(
        labels.xy_px, labels.xy_px - mapped, np.ones(len(ij)), image_size=size, tau_px=_FINGERPRINT_TAU_PX, grid=grid
    )
    back = cv2.perspectiveTransform(field.undistort_points(labels.xy_px)[None], np.linalg.inv(H))[0]
    return Fingerprint(ij, back - plate)


def lattice_symmetries(lattice: str) -> list[np.ndarray]:
    """The integer matrices ``M`` (index space) of the lattice's rotations and reflections."""
    if lattice == "hex":
        turn, mirror = np.array([[0, -1], [1, 1]]), np.array([[1, 1], [0, -1]])
        n_turns = 6
    else:
        turn, mirror = np.array([[0, -1], [1, 0]]), np.array([[1, 0], [0, -1]])
        n_turns = 4
    out, M = [], np.eye(2, dtype=np.int64)
    for _ in range(n_turns):
        out += [M, M @ mirror]
        M = turn @ M
    return out


def match_fingerprints(frame: Fingerprint, reference: Fingerprint, lattice: str):
    """The map ``ij_ref = M ij + t`` under which the fingerprints correlate best; ``(M, t, corr, margin)``.

    ``corr`` is the best correlation coefficient of the offsets over the shared holes, ``margin`` its
    lead over the best of every other symmetry and shift.
    """
    basis = lattice_basis(lattice)
    scores = []  # (corr, M, t)
    for M in lattice_symmetries(lattice):
        turn = basis @ M @ np.linalg.inv(basis)  # the symmetry on the plate: offsets turn with the holes
        ij = frame.ij @ M.T
        corr, t = _best_shift(ij, frame.offset @ turn.T, reference.ij, reference.offset)
        scores += [(c, M, s) for c, s in zip(corr, t)]
    scores.sort(key=lambda x: -x[0])
    best = scores[0]
    rival = next((c for c, M, t in scores[1:] if not (np.array_equal(M, best[1]) and np.array_equal(t, best[2]))), 0.0)
    return best[1], best[2], best[0], best[0] - rival


def _best_shift(ij, offset, ij_ref, offset_ref, n_best: int = 3):
    """The ``n_best`` shifts ``t``, and their correlations, that align ``offset`` at ``ij + t`` with the reference."""
    lo = np.minimum(ij.min(0), ij_ref.min(0))
    size = np.maximum(ij.max(0), ij_ref.max(0)) - lo + 1
    shape = tuple(int(v) for v in 2 * size)

    def grids(idx, values):
        g = np.zeros(shape + (3,))
        at = tuple((idx - lo).T)
        g[at + (slice(0, 2),)] = values - values.mean(0)
        g[at + (2,)] = 1.0
        return np.fft.rfft2(g, axes=(0, 1))

    a, b = grids(ij, offset), grids(ij_ref, offset_ref)
    cross = sum(np.fft.irfft2(np.conj(a[..., c]) * b[..., c], s=shape, axes=(0, 1)) for c in range(2))
    overlap = np.fft.irfft2(np.conj(a[..., 2]) * b[..., 2], s=shape, axes=(0, 1))
    energy = float(np.sqrt(np.sum((offset - offset.mean(0)) ** 2) * np.sum((offset_ref - offset_ref.mean(0)) ** 2)))
    # normalise by the overlap so a shift sharing few holes cannot win by luck
    n = min(len(ij), len(ij_ref))
    corr = np.where(overlap > 0.25 * n, cross / max(energy, 1e-30) * n / np.maximum(overlap, 1.0), 0.0)
    flat = np.argsort(corr, axis=None)[::-1][:n_best]
    shifts = np.column_stack(np.unravel_index(flat, shape))
    shifts = np.where(shifts >= np.array(shape) // 2, shifts - np.array(shape), shifts)
    return corr.ravel()[flat], [s.astype(np.int64) for s in shifts]


def _renumbered(frame: Labels, reference: Labels, ref_print: Fingerprint, lattice: str, pitch_mm: float) -> Labels:
    """``frame`` on ``reference``'s numbering, or failed when neither its plate errors nor its position tell."""
    M, t, corr, margin = match_fingerprints(fingerprint(frame, lattice), ref_print, lattice)
    log.debug("plate fingerprint against the reference frame: correlation %.3f, lead %.3f", corr, margin)
    ij = lattice_index(frame.bead_id)
    if corr >= _MIN_CORRELATION and margin >= _MIN_MARGIN:
        mapped = ij @ M.T + t
    else:
        mapped = _nearest_numbering(frame, reference)
        if mapped is None:
            return _failed(
                frame,
                f"the plate moved by a third of a hole pitch or more from the reference frame and its "
                f"manufacturing errors are too small to follow it (fingerprint correlation {corr:.2f}, lead "
                f"{margin:.2f}); keep the plate still between frames (it may shift by less than a third of a pitch)",
            )
    return replace(frame, bead_id=lattice_id(mapped), object_xyz_mm=lattice_xyz_mm(mapped, lattice, pitch_mm))


def _nearest_numbering(frame: Labels, reference: Labels) -> np.ndarray | None:
    """Lattice indices on ``reference``'s numbering by pairing each hole with its nearest, if the plate barely moved."""
    from scipy.spatial import cKDTree

    ij, ij_ref = lattice_index(frame.bead_id), lattice_index(reference.bead_id)
    spacing = float(np.median(cKDTree(frame.xy_px).query(frame.xy_px, k=2)[0][:, 1]))
    d, nn = cKDTree(reference.xy_px).query(frame.xy_px)
    near = d < _MAX_MOVE_PITCH * spacing
    if near.sum() < max(7, 0.5 * len(ij)):
        return None
    A = np.column_stack([ij[near], np.ones(int(near.sum()))])
    M = np.rint(np.linalg.lstsq(A, ij_ref[nn[near]], rcond=None)[0]).astype(np.int64)  # (3, 2): [M^T; t]
    mapped = ij @ M[:2] + M[2]
    agree = np.mean(np.all(mapped[near] == ij_ref[nn[near]], axis=1))
    if abs(round(float(np.linalg.det(M[:2].astype(float))))) != 1 or agree < 0.9:
        return None
    return mapped
