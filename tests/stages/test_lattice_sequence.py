"""One lattice numbering across a grid plate's frames (stages/label/lattice_sequence.py).

Frames of the synthetic plate (tests/stages/plate_synthetic.py) are given arbitrary numberings — a
random lattice symmetry and shift each, as the per-frame lattice growth gives — and must come back on
the first frame's numbering, hole for hole, from the plate's own errors; a perfect plate moved by more
than a third of a pitch cannot be followed and must fail with its reason, never be misnumbered.
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
    # the first frame keeps the true numbering, so every frame must now carry the true ids, hole for hole
    for lab, true_ids in zip(numbered, truth):
        assert np.array_equal(lab.bead_id, true_ids)
        assert np.allclose(lab.object_xyz_mm, lattice_xyz_mm(lattice_index(true_ids), "hex", PITCH_MM))


def test_perfect_plate_moved_far_fails_with_reason():
    problem, ids, _ = make_plate(6, 2, turn_deg=30, shift_mm=10, plate_error_mm=0.0, noise_px=0.02)
    frames, _ = _frames(problem, ids, seed=2)
    numbered = number_lattice_sequence(frames, "hex", PITCH_MM)
    assert numbered[0].ok
    assert not numbered[1].ok
    assert "manufacturing errors are too small" in numbered[1].reason


def test_perfect_plate_barely_moved_numbered_by_position():
    problem, ids, _ = make_plate(7, 2, turn_deg=0.2, shift_mm=0.4, plate_error_mm=0.0, noise_px=0.02)
    frames, truth = _frames(problem, ids, seed=3)
    numbered = number_lattice_sequence(frames, "hex", PITCH_MM)
    assert numbered[1].ok
    assert np.array_equal(numbered[1].bead_id, truth[1])
