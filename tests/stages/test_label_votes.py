"""Tests of the shift vote (stages/label/votes.py): the fast paths count exactly the votes of its definition.

The strengths of a batch of poses (:func:`shift_strengths`, used to score the prior search's rotation grid)
and the full vote (:func:`shift_votes`) must equal, integer for integer, a plain computation of the
definition: every pair of a detection and a bead votes for the shift that puts the bead on the detection's
ray, binned, then summed over boxes. Ground truth: the simulator's geometry made detection-like.
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.stages.geometry import quat_to_matrix
from fluorocal.stages.label.cube_frame import make_cube_frame
from fluorocal.stages.label.detections import Detections, assumed_iop
from fluorocal.stages.label.votes import rays_of, shift_strength, shift_strengths, shift_votes
from fluorocal.stages.simulate import SimulateParams, simulate
from scipy.spatial.transform import Rotation

from tests.stages.label_truth import detections_from_truth, params_of


@pytest.fixture(scope="module")
def scene():
    """A simulated frame of the default cube as the labelling sees it, its true pose, and 80 of its rays."""
    sp = SimulateParams(n_frames=1, seed=3)
    sim = simulate(sp, render=False)
    params = params_of(sp)
    ft = sim.truth.frames[0][0]
    c, _ = detections_from_truth(ft, np.random.default_rng(3), merged_keep=0.2)
    det = Detections.from_centroids(c)
    frame, _ = make_cube_frame(det, sim.phantom, params, assumed_iop(det, c, params, need_c=True))
    rays = rays_of(frame, frame.det_xy)
    thin = rays[np.linspace(0, len(rays) - 1, 80).astype(int)]
    return frame, quat_to_matrix(ft.q), np.asarray(ft.source_mm, dtype=np.float64), thin


def _reference_votes(frame, R, T, rays, bin_gates, box):
    """The vote by its definition, one pair at a time into the histogram: ``(hist, votes, lo, bin_mm)`` or None."""
    p_cam = (frame.phantom.xyz_mm - T) @ R.T
    p_cam = p_cam[p_cam[:, 2] > 0]
    if len(p_cam) < 4 or not len(rays):
        return None
    bin_mm = bin_gates * frame.params.gate_bead_diameters * frame.diam_ref_px * np.median(p_cam[:, 2]) / frame.iop[2]
    z = p_cam[:, 2] / bin_mm
    fx = rays[:, 0:1] * z - p_cam[:, 0] / bin_mm
    fy = rays[:, 1:2] * z - p_cam[:, 1] / bin_mm
    lo = np.floor([fx.min(), fy.min()])
    ix, iy = np.floor(fx - lo[0]).astype(int), np.floor(fy - lo[1]).astype(int)
    hist = np.zeros((ix.max() + 1, iy.max() + 1), dtype=np.int64)
    np.add.at(hist, (ix.ravel(), iy.ravel()), 1)
    before = box // 2
    padded = np.pad(hist, [(before, box - 1 - before)] * 2)
    votes = np.zeros_like(hist)
    for a in range(box):
        for b in range(box):
            votes += padded[a : a + hist.shape[0], b : b + hist.shape[1]]
    return hist, votes, lo, bin_mm


def _poses(frame, R_true, T_true, rng, n):
    """``n`` poses around the truth: turned by about 4 deg, moved by tens of mm, some with beads behind the source."""
    R = Rotation.from_rotvec(rng.normal(scale=np.radians(4.0), size=(n, 3))).as_matrix() @ R_true
    T = T_true + rng.normal(scale=20.0, size=(n, 3))
    # the source inside the phantom (about half its beads behind it), and far beyond it (none in front)
    T[: n // 8] += frame.phantom.xyz_mm.mean(0) - T_true
    T[n // 8 : n // 6] += R_true[2] * 5000.0
    return R, T


def test_strengths_of_a_batch_are_the_definitions(scene):
    """The strength of each pose of a batch is the largest 2 x 2 sum of its vote on the 1-gate grid, exactly."""
    frame, R_true, T_true, rays = scene
    R, T = _poses(frame, R_true, T_true, np.random.default_rng(7), 150)
    want = []
    for k in range(len(R)):
        vote = _reference_votes(frame, R[k], T[k], rays, 1.0, 2)
        want.append(0.0 if vote is None else float(vote[1].max()))
    got = shift_strengths(frame, R, T, rays)
    # poses of every kind were drawn: beads partly behind the source, none in front, all in front
    behind = [(((frame.phantom.xyz_mm - t) @ r.T)[:, 2] <= 0).mean() for r, t in zip(R, T)]
    assert min(behind) == 0 and max(behind) == 1 and any(0 < b < 1 for b in behind)
    assert np.array_equal(got, want)
    assert [shift_strength(frame, R[k], T[k], rays) for k in range(0, len(R), 15)] == want[::15]
    # at the true pose nearly every detection's bead votes for the true shift (some are spurious or merged blobs)
    assert shift_strength(frame, R_true, T_true, rays) >= 0.7 * len(rays)
    assert np.array_equal(shift_strengths(frame, R[:0], T[:0], rays), np.zeros(0))
    assert np.array_equal(shift_strengths(frame, R[:3], T[:3], rays[:0]), np.zeros(3))


@pytest.mark.parametrize("bin_gates, box", [(0.5, 3), (1.0, 2), (0.7, 4)])
def test_full_vote_is_the_definitions(scene, bin_gates, box):
    """Every output of the full vote (histogram, box sums, grid origin, bin size) equals the definition's."""
    frame, R_true, T_true, rays = scene
    R, T = _poses(frame, R_true, T_true, np.random.default_rng(11), 24)
    voted = 0
    for r, t in zip(R, T, strict=True):
        got = shift_votes(frame, r, t, rays, bin_gates=bin_gates, box=box)
        want = _reference_votes(frame, r, t, rays, bin_gates, box)
        assert (got is None) == (want is None)
        if want is not None:
            voted += 1
            assert len(got) == len(want) == 4
            assert all(np.array_equal(g, w) for g, w in zip(got, want, strict=True))
    assert voted >= len(R) // 2  # not vacuous: most poses put beads in front of the source
