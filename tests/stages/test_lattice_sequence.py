"""One lattice numbering across a grid plate's frames (stages/label/lattice_sequence.py).

Frames of the synthetic plate (tests/stages/plate_synthetic.py) are given arbitrary numberings — a
random lattice symmetry and shift each, as the per-frame lattice growth gives — and must come back on
one numbering, hole for hole (the same physical hole, the same id in every frame), from the plate's own
errors; a perfect plate moved by more than a third of a pitch cannot be followed and must fail with its
reason, never be misnumbered.
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.stages.label.labels import Labels
from fluorocal.stages.label.lattice import lattice_id, lattice_index, lattice_xyz_mm
from fluorocal.stages.label.lattice_sequence import lattice_symmetries, number_lattice_sequence

from tests.stages.plate_synthetic import PITCH_MM, make_plate


def _labels(ids, xy) -> Labels:
    n = len(ids)
    return Labels(
        np.arange(n),
        ids,
        xy,
        np.tile([0.02, 0.02, 0.0], (n, 1)),
        lattice_xyz_mm(lattice_index(ids), "hex", PITCH_MM),
        np.zeros(n, np.int8),
        np.full(4, np.nan),
        np.full(3, np.nan),
        np.array([255.5, 255.5, np.nan]),
        n_labelled=n,
        pose_source="lattice",
    )


def _frames(problem, true_ids, seed):
    """Each frame's Labels under a random symmetry and shift of its numbering, and its true ids."""
    rng = np.random.default_rng(seed)
    symmetries = lattice_symmetries("hex")
    out, truth = [], []
    for f in range(problem.n_frames):
        sel = problem.frame == f
        ij = lattice_index(true_ids[problem.hole[sel]])
        M = symmetries[rng.integers(len(symmetries))] if f else np.eye(2, dtype=np.int64)
        shown = ij @ M.T + (rng.integers(-4, 5, 2) if f else 0)
        out.append(_labels(lattice_id(shown), problem.xy_px[sel]))
        truth.append(true_ids[problem.hole[sel]])
    return out, truth


@pytest.mark.parametrize("turn_deg, shift_mm", [(30, 10), (2, 1)])
def test_frames_renumbered_onto_the_first(turn_deg, shift_mm):
    problem, ids, _ = make_plate(5, 4, turn_deg=turn_deg, shift_mm=shift_mm, plate_error_mm=0.02, noise_px=0.02)
    frames, truth = _frames(problem, ids, seed=1)
    numbered = number_lattice_sequence(frames, "hex", PITCH_MM)
    assert all(lab.ok for lab in numbered)
    _assert_one_numbering(numbered, truth)


def _assert_one_numbering(numbered, truth):
    """Every labelled frame maps each true hole to one id, the same in every frame (a bijection)."""
    id_of = {}
    for lab, true_ids in zip(numbered, truth):
        if not lab.ok:
            continue
        for t, new in zip(true_ids.tolist(), lab.bead_id.tolist()):
            assert id_of.setdefault(t, new) == new
        assert np.allclose(lab.object_xyz_mm, lattice_xyz_mm(lattice_index(lab.bead_id), "hex", PITCH_MM))
    assert len(set(id_of.values())) == len(id_of)


def test_perfect_plate_moved_far_fails_with_reason():
    problem, ids, _ = make_plate(6, 2, turn_deg=30, shift_mm=10, plate_error_mm=0.0, noise_px=0.02)
    frames, _ = _frames(problem, ids, seed=2)
    numbered = number_lattice_sequence(frames, "hex", PITCH_MM)
    assert sum(lab.ok for lab in numbered) == 1  # the reference frame
    failed = next(lab for lab in numbered if not lab.ok)
    assert "manufacturing errors are too small" in failed.reason


def test_a_frame_of_a_few_holes_is_not_numbered():
    """A bead frame "labelled" as a handful of holes is not the plate: it fails, the plate's frames do not."""
    problem, ids, _ = make_plate(10, 3, turn_deg=5, shift_mm=2, plate_error_mm=0.02, noise_px=0.02)
    frames, truth = _frames(problem, ids, seed=4)
    few = _labels(frames[0].bead_id[:12], frames[0].xy_px[:12])
    numbered = number_lattice_sequence([few, *frames[1:]], "hex", PITCH_MM)
    assert not numbered[0].ok and "not the plate" in numbered[0].reason
    assert all(lab.ok for lab in numbered[1:])
    _assert_one_numbering(numbered[1:], truth[1:])


def test_perfect_plate_barely_moved_numbered_by_position():
    problem, ids, _ = make_plate(7, 2, turn_deg=0.2, shift_mm=0.4, plate_error_mm=0.0, noise_px=0.02)
    frames, truth = _frames(problem, ids, seed=3)
    numbered = number_lattice_sequence(frames, "hex", PITCH_MM)
    assert all(lab.ok for lab in numbered)
    _assert_one_numbering(numbered, truth)
