"""Tests of stages/learn/joint.py and network.py: the refinement's field step with the orientation eliminated.

Ground truth: analytic, on the linearisation of a simulated adjustment (``simulate(render=False)``): residuals made
of a known field and a known orientation change are split back into the two by one step.
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.stages.adjust import FreeParameters, adjust_bundle, index_of, nominal_coordinates
from fluorocal.stages.field import CorrectionField, bilinear_design
from fluorocal.stages.learn.gauge import gauge_fixed
from fluorocal.stages.learn.grid import fit_grid_field
from fluorocal.stages.learn.joint import fit_grid_jointly
from fluorocal.stages.learn.network import linearised_network
from fluorocal.stages.learn.nodes import GridSpec

from tests.stages.test_uncertainty import simulated_set

SIZE, SPACING = 256, 32.0
GRID = GridSpec(spacing_px=SPACING)


@pytest.fixture(scope="module")
def linearised():
    """A 256 px, 6-exposure set adjusted with the true correction held, linearised at the adjustment."""
    (train, _), initial, phantom, system = simulated_set(5, 6, SIZE)
    corr = train[1].xy_px - system.distortion.undistort_points(train[1].xy_px)
    adj = adjust_bundle(train[0], phantom, initial, corr, free=FreeParameters(estimate_iop=True))
    rows = np.flatnonzero(adj.used)
    ids, xyz = nominal_coordinates(phantom)
    nominal = xyz[index_of(adj.bead_id, ids, "bead ids")]
    return adj, train[0], rows, nominal


def cubic_field(xy):
    """A smooth field of ~1 px, cubic: in the null space of the order-4 prior (so the prior biases nothing)."""
    x, y = (xy[:, 0] - SIZE / 2) / (SIZE / 2), (xy[:, 1] - SIZE / 2) / (SIZE / 2)
    return np.column_stack([0.6 * x**3 - 0.3 * x * y**2 + 0.2 * y**2, 0.5 * y**3 + 0.4 * x**2 * y - 0.2 * x * y])


def cubic_case(linearised):
    """``(xy, network, zero field, bilinear design, the cubic field on the grid)`` at the linearised set."""
    adj, obs, rows, _ = linearised
    xy = obs.xy_px[rows]
    zero = CorrectionField.constant(SIZE, SIZE, spacing_px=SPACING)
    A = bilinear_design(zero.x_nodes_px, zero.y_nodes_px, xy)
    truth = zero.with_delta(cubic_field(zero.nodes_px.reshape(-1, 2)).reshape(zero.delta_px.shape))
    return xy, linearised_network(adj, obs, rows, 0), zero, A, truth


def test_one_step_splits_a_field_from_the_orientations_change(linearised):
    # noise-free residuals = a (gauge-free) cubic field + the projection of a random change of every pose and
    # bead; the linearised joint problem's solution is exactly that field: one step recovers it
    adj, _, rows, _ = linearised
    xy, net, zero, A, truth = cubic_case(linearised)
    # gauge-free at the observations: the gauge fields interpolated from the nodes differ from the exact ones at
    # second order, so one removal leaves a ~1e-3 px component; each further one shrinks it by as much again
    for _ in range(4):
        truth = gauge_fixed(truth, xy, adj.iop_px[0], True)
    rng = np.random.default_rng(3)
    d_theta = rng.normal(0, 1e-3, net.J.shape[1])  # rad, mm and px: a change of ~1 px in the image
    d_theta[3 : net.point_col] *= 0.1  # poses: a milliradian moves the image by ~4 px at c ~ 4000 px
    r = (A @ truth.delta_px.reshape(-1, 2)) + (net.J @ d_theta).reshape(2, -1).T
    w = np.full((len(rows), 2), 1 / 0.05**2)
    step = fit_grid_jointly(
        xy, r, w, net, iop_px=adj.iop_px[0], estimate_iop=True, image_size=(SIZE, SIZE), tau_px=0.1,
        base=zero, cv_rms_px=0.05, grid=GRID, order=4, cg_tolerance=1e-12, max_cg_iterations=2000,
    )  # fmt: skip
    q = rng.uniform(16, SIZE - 16, (400, 2))
    # exact up to the conjugate gradients' tolerance, the rounding of a ~1e10-conditioned solve and what is left of
    # the gauge mismatch above: 1e-5 px, against 1e-3 px for one gauge removal and ~0.1 px for the field alone
    np.testing.assert_allclose(step.correction_at(q), truth.correction_at(q), atol=1e-5)
    # the field alone (the orientation held) cannot tell them apart: it absorbs part of J dθ
    alone = fit_grid_field(xy, r, np.full((len(rows), 2), 0.05**2), image_size=(SIZE, SIZE), tau_px=0.1, order=4,
                           grid=GRID)  # fmt: skip
    assert np.abs(alone.correction_at(q) - truth.correction_at(q)).max() > 0.05


def test_network_similarity_modes_project_to_nothing(linearised):
    adj, obs, rows, nominal = linearised
    net = linearised_network(adj, obs, rows, 0, nominal)
    # J E = 0 to first order, relative to |J|: a similarity of object space moves nothing in the image
    scale = np.sqrt(net.J.multiply(net.J).sum())
    assert np.linalg.norm(net.J @ net.datum, axis=0).max() < 1e-9 * scale
    # the affine modes are orthonormal, orthogonal to the similarity (holding them never holds the datum) and live on
    # the points' columns only
    np.testing.assert_allclose(net.affine.T @ net.affine, np.eye(5), atol=1e-12)
    assert np.abs(net.affine.T @ net.datum).max() < 1e-12
    assert not net.affine[: net.point_col].any()


def test_points_alone_respond_when_the_orientation_is_held(linearised):
    # residuals = a cubic field + the projection of a change of the beads alone: with the points responding (the
    # IOP and the poses held) one step recovers the field; the gauge is not held then, so the field need not be free
    # of it (the orientation that could carry it does not move)
    adj, _, rows, _ = linearised
    xy, net, zero, A, truth = cubic_case(linearised)
    d_theta = np.zeros(net.J.shape[1])
    d_theta[net.point_col :] = np.random.default_rng(4).normal(0, 1e-3, net.J.shape[1] - net.point_col)
    r = (A @ truth.delta_px.reshape(-1, 2)) + (net.J @ d_theta).reshape(2, -1).T
    w = np.full((len(rows), 2), 1 / 0.05**2)
    step = fit_grid_jointly(
        xy, r, w, net, iop_px=adj.iop_px[0], estimate_iop=True, image_size=(SIZE, SIZE), tau_px=0.1,
        base=zero, cv_rms_px=0.05, grid=GRID, order=4, cg_tolerance=1e-12, max_cg_iterations=2000, respond="points",
    )  # fmt: skip
    q = np.random.default_rng(5).uniform(16, SIZE - 16, (400, 2))
    # exact up to the solve's tolerance and rounding (as above, without the gauge removals' remainder): 1e-6 px
    np.testing.assert_allclose(step.correction_at(q), truth.correction_at(q), atol=1e-6)


def test_points_inverse_is_the_dense_normal_matrix_inverse(linearised):
    # the beads-alone step's orientation inverse (3x3 blocks less a Woodbury term for the affine hold) against a
    # dense solve of the matrix it stands for: J^T W J + the other systems' information + κ F F^T + the ridge on
    # the Jacobi-scaled diagonal
    from fluorocal.stages.learn.joint import AFFINE_STIFFNESS, POINT_RIDGE, _orientation_inverse
    from scipy.linalg import block_diag

    adj, obs, rows, nominal = linearised
    net = linearised_network(adj, obs, rows, 0, nominal)
    held = slice(net.point_col, None)
    rng = np.random.default_rng(6)
    w, r = rng.uniform(200, 400, (len(rows), 2)), rng.normal(0, 0.05, (len(rows), 2))
    B = rng.normal(size=(len(net.beads), 3, 3))
    info = 1e3 * B @ B.transpose(0, 2, 1)
    solve, b = _orientation_inverse(net.J[:, held], w, r, net, held, info)
    J, wf = net.J[:, held].toarray(), w.T.ravel()
    N = J.T @ (wf[:, None] * J) + block_diag(*info)
    kappa, F = AFFINE_STIFFNESS * np.diag(N).max(), net.affine[held]
    M = N + kappa * F @ F.T + POINT_RIDGE * np.diag(np.diag(N))
    x = rng.normal(size=len(M))
    exact = np.linalg.solve(M, x)
    # two solves of a matrix conditioned ~1e8 (the stiff hold against the weakest bead) agree to ~1e-9 relative
    np.testing.assert_allclose(solve(x), exact, atol=1e-8 * np.abs(exact).max())
    np.testing.assert_allclose(b, J.T @ (wf * r.T.ravel()) - kappa * F @ net.affine_gap_mm, rtol=1e-12)
