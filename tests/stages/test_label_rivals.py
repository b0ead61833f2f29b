"""Tests of the shortcuts that keep the rival checks cheap (stages/label/rivals.py, iterate.py, correction.py).

The bounded evidence must decide every threshold as the full evidence does, the early end of a search
must rest on a true upper bound, and the vectorised helpers must compute what their definitions say.
Ground truth: the simulator's geometry made detection-like (:func:`detections_from_truth`).
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.stages.label.assign import assign, gate_bound
from fluorocal.stages.label.correction import Correction
from fluorocal.stages.label.cube_frame import make_cube_frame, within_gates
from fluorocal.stages.label.detections import Detections, assumed_iop
from fluorocal.stages.label.iterate import agreement, iterate
from fluorocal.stages.label.markers import marker_poses
from fluorocal.stages.label.motion import OrientationPrior
from fluorocal.stages.label.rivals import _EVIDENCE_MARGIN, evidence, model_evidence, stands_alone
from fluorocal.stages.simulate import SimulateParams, simulate
from scipy.spatial.transform import Rotation

from tests.stages.label_truth import detections_from_truth, params_of


def _labelled(**detection_options):
    """A simulated frame of the default cube, its CubeFrame, its labelling from the markers and the true ids."""
    sp = SimulateParams(n_frames=1, seed=3)
    sim = simulate(sp, render=False)
    params = params_of(sp)
    c, ids = detections_from_truth(sim.truth.frames[0][0], np.random.default_rng(3), **detection_options)
    det = Detections.from_centroids(c)
    frame, _ = make_cube_frame(det, sim.phantom, params, assumed_iop(det, c, params, need_c=True))
    poses, _, _ = marker_poses(frame)
    model = iterate(frame, *poses[0])
    assert np.array_equal(ids[frame.det_idx[model["det"]]], frame.phantom.ids[model["bead"]])
    return frame, model, ids


@pytest.fixture(scope="module")
def labelled_frame():
    """Detections as the benchmarks make them: dropouts, a spurious blob, a fifth of the merged blobs."""
    return _labelled(merged_keep=0.2)


def _poses_around(model: dict, rng) -> list:
    """The labelling's own pose, and poses turned and shifted from it by a little up to a lot."""
    out = [(model["R"], model["T"])]
    for angle_deg, shift_mm in [(0.3, 0.5), (1.0, 3.0), (3.0, 10.0), (10.0, 30.0)] * 3:
        turn = Rotation.from_rotvec(rng.normal(size=3) / np.sqrt(3) * np.radians(angle_deg)).as_matrix()
        out.append((turn @ model["R"], model["T"] + rng.normal(size=3) * shift_mm))
    return out


def test_bounded_evidence_decides_every_threshold_as_the_full_evidence(labelled_frame):
    """``evidence(bound=b) > b`` exactly when the full evidence is, and the bounded value is never lower."""
    frame, model, _ = labelled_frame
    for R, T in _poses_around(model, np.random.default_rng(0)):
        full = evidence(frame, model, R, T)
        for bound in full + np.arange(-40.0, 41.0, 4.0):
            bounded = evidence(frame, model, R, T, bound=bound)
            assert (bounded > bound) == (full > bound)
            assert bounded >= full


def test_evidence_never_exceeds_the_usable_detections(labelled_frame):
    """The bound that ends a search early: no pose explains the frame by more than its usable detections."""
    frame, model, _ = labelled_frame
    for R, T in _poses_around(model, np.random.default_rng(1)):
        assert evidence(frame, model, R, T) <= len(frame.det_xy)


def test_cached_evidence_keeps_an_upper_bound_only_while_it_suffices(labelled_frame):
    """A bound asked first, then the full value: the cache gives the full value, not the bound it kept."""
    frame, model, _ = labelled_frame
    fresh = {k: v for k, v in model.items() if k != "memo"}
    R, T = _poses_around(model, np.random.default_rng(2))[-1]
    full = evidence(frame, fresh, R, T)
    high = full + 100.0
    assert model_evidence(frame, fresh, R, T, bound=high) <= high
    assert model_evidence(frame, fresh, R, T) == full


def test_right_labelling_stands_alone_only_near_the_prior(labelled_frame):
    """Whether a right labelling stands alone is its evidence against the bound, and it never does far from the prior.

    With dropouts, a spurious blob and merged blobs this frame's right labelling falls short of the bound
    by more than a margin; without them (every bead detected, nothing else) it comes within one.
    """
    frame, model, _ = labelled_frame
    near = OrientationPrior.isotropic(model["R"], np.radians(2.0))
    assert stands_alone(frame, model, near) == (evidence(frame, model) > len(frame.det_xy) - _EVIDENCE_MARGIN)
    clean_frame, clean_model, _ = _labelled(dropout=0.0, merged_keep=0.0, n_false=0)
    assert stands_alone(clean_frame, clean_model, OrientationPrior.isotropic(clean_model["R"], np.radians(2.0)))
    # 20 deg away at 2 deg per sigma: 10 sigmas, beyond the prior margin of 3
    turned = Rotation.from_rotvec([0.0, np.radians(20.0), 0.0]).as_matrix() @ clean_model["R"]
    assert not stands_alone(clean_frame, clean_model, OrientationPrior.isotropic(turned, np.radians(2.0)))


def test_agreement_is_the_fraction_of_same_beads():
    """Against its definition, written as a loop: the share of a's detections that b gives the same bead."""
    rng = np.random.default_rng(4)
    for _ in range(20):
        a_det = rng.choice(300, size=rng.integers(1, 200), replace=False)
        b_det = rng.choice(300, size=rng.integers(0, 200), replace=False)
        a = {"det": a_det, "bead": rng.integers(0, 5, len(a_det))}
        b = {"det": b_det, "bead": rng.integers(0, 5, len(b_det))}
        same = dict(zip(b_det.tolist(), b["bead"].tolist()))
        expected = np.mean([same.get(d) == k for d, k in zip(a_det.tolist(), a["bead"].tolist())])
        assert agreement(a, b) == pytest.approx(expected, abs=0.0)


@pytest.mark.parametrize("degree", range(6))
def test_correction_basis_is_the_monomials(degree):
    """Column ``(d, k)`` is ``u^(d-k) v^k`` of the scaled coordinates (1e-12: products of numbers below ~2)."""
    rng = np.random.default_rng(degree)
    corr = Correction(np.array([512.0, 500.0]), 700.0, degree)
    xy = rng.uniform(0.0, 1024.0, (50, 2))
    u, v = ((xy - corr.centre) / corr.scale).T
    expected = np.column_stack([u ** (d - k) * v**k for d in range(degree + 1) for k in range(d + 1)])
    np.testing.assert_allclose(corr.basis(xy), expected, rtol=0, atol=1e-12)


def test_a_labelling_found_again_keeps_the_better_of_the_two(monkeypatch):
    """A labelling found again (agreeing on 90 % of its labels) is not kept beside the first: the better stays.

    ``prior._merged`` keeps the one with more evidence, in the first one's place (the order found decides ties).
    """
    from fluorocal.stages.label import prior

    # stand-in labellings: a family (labellings of one family agree fully) and an evidence
    monkeypatch.setattr(prior, "agreement", lambda f, g: 1.0 if f["family"] == g["family"] else 0.0)
    monkeypatch.setattr(prior, "evidence", lambda frame, f: f["evidence"])
    a, b = {"family": "a", "evidence": 100.0}, {"family": "b", "evidence": 90.0}
    better_a, worse_b, c = {"family": "a", "evidence": 101.0}, {"family": "b", "evidence": 80.0}, {"family": "c"}
    assert prior._merged(None, [a, b], [better_a, worse_b, c]) == [better_a, b, c]
    assert prior._merged(None, [a], [{"family": "a", "evidence": 100.0}]) == [a]  # a tie keeps the first found


def test_within_gates_is_the_nearest_points_own_gate():
    """Against brute force: a point is within the gate of the tree point nearest it (all distances computed).

    Gates of a few px around points a few px apart: some points lie within their nearest point's gate, some
    within another's only (which does not count), some beyond every gate.
    """
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(5)
    for _ in range(20):
        centres = rng.uniform(0.0, 100.0, (rng.integers(2, 60), 2))
        gate = rng.uniform(0.5, 6.0, len(centres))
        xy = rng.uniform(-10.0, 110.0, (200, 2))
        d = np.linalg.norm(xy[:, None] - centres[None], axis=2)
        nearest = d.argmin(1)
        expected = d[np.arange(len(xy)), nearest] <= gate[nearest]
        assert np.array_equal(within_gates(cKDTree(centres), xy, gate), expected)


def test_within_gates_counts_a_point_at_the_gate_itself():
    """Against brute force on an integer lattice: many distances equal to the gates, the widest too.

    A point at its nearest point's gate is within it (``d <= gate``, as the evidence reads a gate), though the
    tree's bounded query finds only points strictly nearer than its bound. Points with two nearest points
    (a tie, either one's gate may decide) are left out.
    """
    from scipy.spatial import cKDTree

    at_gate = np.array([[3.0, 0.0], [0.0, 3.0]])
    assert within_gates(cKDTree([[0.0, 0.0], [10.0, 0.0]]), at_gate, np.array([3.0, 1.0])).all()
    rng = np.random.default_rng(6)
    for _ in range(50):
        centres = np.unique(rng.integers(0, 20, (rng.integers(2, 40), 2)), axis=0).astype(float)
        gate = rng.integers(1, 6, len(centres)).astype(float)
        xy = rng.integers(-3, 23, (300, 2)).astype(float)
        d = np.linalg.norm(xy[:, None] - centres[None], axis=2)
        nearest = d.argmin(1)
        expected = d[np.arange(len(xy)), nearest] <= gate[nearest]
        single = np.sort(d, axis=1)[:, 1] > d.min(1)
        assert np.array_equal(within_gates(cKDTree(centres), xy, gate)[single], expected[single])


def test_a_gated_query_finds_every_point_at_the_gate():
    """Points at the gate's distance (to rounding) in many directions, found by a query bounded by :func:`gate_bound`.

    Each one that the unbounded query puts within the gate is found (as the evidence and the assignment read a gate).
    """
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(7)
    gate = rng.uniform(0.5, 60.0, 2000)
    angle = rng.uniform(0.0, 2 * np.pi, len(gate))
    xy = gate[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    tree = cKDTree([[0.0, 0.0]])
    d, _ = tree.query(xy)
    at_gate = d <= gate
    assert at_gate.sum() > 500  # about half of them, the others a rounding beyond
    for g, p in zip(gate[at_gate], xy[at_gate]):
        assert np.isfinite(tree.query(p, distance_upper_bound=gate_bound(np.array([0.5 * g, g])))[0])


def test_a_detection_at_the_widest_gate_is_assigned():
    """A detection 5 px (a 3-4-5 triangle, exact) from a prediction whose gate is 5 px, the widest: they pair."""
    from scipy.spatial import cKDTree

    det = np.array([[3.0, 4.0], [52.0, 0.0]])
    i_pred, i_det = assign(np.array([[0.0, 0.0], [50.0, 0.0]]), np.array([5.0, 1.0]), det, cKDTree(det))
    assert sorted(zip(i_pred.tolist(), i_det.tolist())) == [(0, 0)]
