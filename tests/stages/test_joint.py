"""Tests of stages/learn/joint.py and network.py: the refinement's field step with the orientation eliminated.

Ground truth: analytic, on the linearisation of a simulated adjustment (``simulate(render=False)``, one system, and
a biplanar set): residuals made of a known field per system and a known orientation change are split back into the
fields and the change by one step.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from fluorocal.stages.adjust import FreeParameters, adjust_bundle, index_of, nominal_coordinates
from fluorocal.stages.field import CorrectionField, bilinear_design
from fluorocal.stages.geometry import project, quat_multiply, rotvec_to_quat
from fluorocal.stages.learn.gauge import gauge_fixed
from fluorocal.stages.learn.grid import fit_grid_field
from fluorocal.stages.learn.joint import SystemStep, fit_grid_jointly, fit_grids_jointly
from fluorocal.stages.learn.network import linearised_network, systems_network
from fluorocal.stages.learn.nodes import GridSpec
from scipy.sparse import csr_matrix

from tests.stages.ba_synthetic import simulated_set

SIZE, SPACING = 256, 32.0
GRID = GridSpec(spacing_px=SPACING)
BI_SIZE, BI_GRID = 512, GridSpec(spacing_px=64.0)


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


def cubic_step(adj, xy, net, zero, r, **options):
    """One joint step from ``zero`` on :func:`cubic_case`'s set, the residuals ``r`` at 0.05 px, solved to 1e-12."""
    w = np.full((len(xy), 2), 1 / 0.05**2)
    return fit_grid_jointly(
        xy,
        r,
        w,
        net,
        iop_px=adj.iop_px[0],
        estimate_iop=True,
        image_size=(SIZE, SIZE),
        tau_px=0.1,
        base=zero,
        cv_rms_px=0.05,
        grid=GRID,
        order=4,
        cg_tolerance=1e-12,
        max_cg_iterations=2000,
        **options,
    )


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
    step = cubic_step(adj, xy, net, zero, r)
    q = rng.uniform(16, SIZE - 16, (400, 2))
    # exact up to the conjugate gradients' tolerance, the rounding of a ~1e10-conditioned solve and what is left of
    # the gauge mismatch above: 1e-5 px (measured 6.1e-6), against 1e-3 px for one gauge removal and ~0.1 px for the
    # field alone
    np.testing.assert_allclose(step.correction_at(q), truth.correction_at(q), atol=1e-5)
    # the field alone (the orientation held) cannot tell them apart: it absorbs part of J dθ
    alone = fit_grid_field(
        xy, r, np.full((len(rows), 2), 0.05**2), image_size=(SIZE, SIZE), tau_px=0.1, order=4, grid=GRID
    )
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
    step = cubic_step(adj, xy, net, zero, r, respond="points")
    q = np.random.default_rng(5).uniform(16, SIZE - 16, (400, 2))
    # exact up to the solve's tolerance and rounding (as above, without the gauge removals' remainder): measured
    # 9.4e-9 px, bound 2e-8 px
    np.testing.assert_allclose(step.correction_at(q), truth.correction_at(q), atol=2e-8)


def test_points_inverse_is_the_dense_normal_matrix_inverse(linearised):
    # the beads-alone step's orientation inverse (3x3 blocks less a Woodbury term for the affine hold) against a
    # dense solve of the matrix it stands for: J^T W J + κ F F^T + the ridge on the Jacobi-scaled diagonal
    from fluorocal.stages.learn.joint import AFFINE_STIFFNESS, POINT_RIDGE, _orientation_inverse

    adj, obs, rows, nominal = linearised
    net = linearised_network(adj, obs, rows, 0, nominal)
    held = slice(net.point_col, None)
    rng = np.random.default_rng(6)
    w, r = rng.uniform(200, 400, (len(rows), 2)), rng.normal(0, 0.05, (len(rows), 2))
    solve, b = _orientation_inverse(net.J[:, held], w, r, net, held)
    J, wf = net.J[:, held].toarray(), w.T.ravel()
    N = J.T @ (wf[:, None] * J)
    kappa, F = AFFINE_STIFFNESS * np.diag(N).max(), net.affine[held]
    M = N + kappa * F @ F.T + POINT_RIDGE * np.diag(np.diag(N))
    x = rng.normal(size=len(M))
    exact = np.linalg.solve(M, x)
    # two solves of a matrix conditioned ~1e8 (the stiff hold against the weakest bead) agree to ~1e-9 relative
    # (measured 1.1e-12; the bound is the conditioning's, cond x eps ~ 2e-8, not this machine's rounding)
    np.testing.assert_allclose(solve(x), exact, atol=1e-8 * np.abs(exact).max())
    np.testing.assert_allclose(b, J.T @ (wf * r.T.ravel()) - kappa * F @ net.affine_gap_mm, rtol=1e-12)


def test_orientation_inverse_is_the_dense_normal_matrix_inverse(linearised):
    # the joint step's orientation inverse (the beads eliminated first, the datum and the affine hold as borders)
    # against a dense solve of the matrix it stands for: J^T W J + κ F F^T, plus, Jacobi-scaled, a unit curvature
    # along each similarity mode and the ridge on the beads' diagonal
    from fluorocal.stages.learn.joint import AFFINE_STIFFNESS, POINT_RIDGE, _orientation_inverse

    adj, obs, rows, nominal = linearised
    net = linearised_network(adj, obs, rows, 0, nominal)
    held = slice(0, None)
    rng = np.random.default_rng(7)
    w, r = rng.uniform(200, 400, (len(rows), 2)), rng.normal(0, 0.05, (len(rows), 2))
    solve, b = _orientation_inverse(net.J, w, r, net, held)
    J, wf = net.J.toarray(), w.T.ravel()
    N = J.T @ (wf[:, None] * J)
    d = np.sqrt(np.diag(N))
    kappa, F = AFFINE_STIFFNESS * np.diag(N)[net.point_col :].max(), net.affine
    E = d[:, None] * net.datum
    E /= np.linalg.norm(E, axis=0)
    ridge = np.where(np.arange(len(N)) >= net.point_col, POINT_RIDGE, 0.0)
    M = N + kappa * F @ F.T + d[:, None] * (E @ E.T + np.diag(ridge)) * d[None, :]
    x = rng.normal(size=(len(M), 2))
    exact = np.linalg.solve(M, x)
    # two solves of a matrix conditioned ~1e10 agree to ~1e-7 relative (measured 6.5e-9; the bound is the
    # conditioning's, not this machine's rounding)
    np.testing.assert_allclose(solve(x), exact, atol=1e-7 * np.abs(exact).max())
    np.testing.assert_allclose(solve(x[:, 0]), exact[:, 0], atol=1e-7 * np.abs(exact).max())
    np.testing.assert_allclose(b, J.T @ (wf * r.T.ravel()) - kappa * F @ net.affine_gap_mm, rtol=1e-12)


@pytest.fixture(scope="module")
def biplanar_linearised():
    """A 512 px, 6 + 6-exposure biplanar set adjusted with the true corrections held, and its two systems' rows."""
    from tests.stages.ba_synthetic import simulated_sets

    (train, _), phantom, _, acq, _ = simulated_sets(6, 2, BI_SIZE, 0)
    obs, initial = train
    corr = np.empty_like(obs.xy_px)
    for s, system in enumerate(acq.systems):
        at = obs.system == s
        corr[at] = obs.xy_px[at] - system.distortion.undistort_points(obs.xy_px[at])
    adj = adjust_bundle(obs, phantom, initial, corr, free=FreeParameters(estimate_iop=True))
    rows = [np.flatnonzero(adj.used & (obs.system == s)) for s in range(2)]
    return adj, obs, rows


def _bi_field(xy, s):
    """System ``s``'s smooth cubic field of ~1 px on the 512 px image (the two systems' differ)."""
    x, y = (xy[:, 0] - BI_SIZE / 2) / (BI_SIZE / 2), (xy[:, 1] - BI_SIZE / 2) / (BI_SIZE / 2)
    sign = 1.0 if s == 0 else -1.0
    return np.column_stack([0.6 * x**3 + sign * 0.3 * x * y**2 + 0.2 * y**2, 0.5 * y**3 - sign * 0.4 * x**2 * y])


@pytest.mark.parametrize("respond", ["orientation", "points"])
def test_one_step_splits_two_systems_fields_from_the_whole_orientations_change(biplanar_linearised, respond):
    # noise-free residuals of both systems = each system's (gauge-free) cubic field + the projection of a random
    # change of both IOPs, every pose of both systems and the beads they share (the beads alone with
    # respond="points"); the linearised joint problem's solution is exactly the two fields: one step recovers both
    adj, obs, rows = biplanar_linearised
    net = systems_network(adj, obs, rows, (0, 1))
    assert net.n_systems == 2
    rng = np.random.default_rng(7)
    d_theta = rng.normal(0, 1e-3, net.J.shape[1])  # px, rad and mm
    d_theta[6 : net.point_col] *= 0.1  # poses: a milliradian moves the image by ~2 px at c ~ 2000 px
    if respond == "points":
        # the beads alone, by ~0.3 mm (with the orientation responding they stay small: the phantom's affine shape,
        # which a random change has too, trades against the field through weak perspective effects only, and the
        # step does not move along what the data barely fix)
        d_theta[: net.point_col] = 0.0
        d_theta[net.point_col :] *= 300
    moved = (net.J @ d_theta).reshape(2, -1).T
    zero = CorrectionField.constant(BI_SIZE, BI_SIZE, spacing_px=BI_GRID.spacing_px)
    steps, truths, start = [], [], 0
    for s, sel in enumerate(rows):
        xy = obs.xy_px[sel]
        truth = zero.with_delta(_bi_field(zero.nodes_px.reshape(-1, 2), s).reshape(zero.delta_px.shape))
        for _ in range(4 if respond == "orientation" else 0):  # gauge-free at the observations (as above)
            truth = gauge_fixed(truth, xy, adj.iop_px[s], True)
        A = bilinear_design(zero.x_nodes_px, zero.y_nodes_px, xy)
        r = A @ truth.delta_px.reshape(-1, 2) + moved[start : start + len(sel)]
        start += len(sel)
        w = np.full((len(sel), 2), 1 / 0.05**2)
        steps.append(SystemStep(xy, r, w, adj.iop_px[s], (BI_SIZE, BI_SIZE), 0.1, zero, 0.05, order=4))
        truths.append(truth)
    fields = fit_grids_jointly(
        steps, net, estimate_iop=True, grid=BI_GRID, cg_tolerance=1e-12, max_cg_iterations=4000, respond=respond
    )
    q = np.random.default_rng(8).uniform(32, BI_SIZE - 32, (400, 2))
    # as the one-system tests: exact up to the solve's tolerance, its rounding and (with the orientation
    # responding) what is left of the gauge mismatch, against ~1 px of field and of the orientation's change;
    # measured 2.5e-6 px (orientation) and 2.1e-7 px (points), bounds 2x
    atol = 5e-6 if respond == "orientation" else 4e-7
    assert np.abs(moved).max() > 0.3
    for field, truth, step in zip(fields, truths, steps):
        np.testing.assert_allclose(field.correction_at(q), truth.correction_at(q), atol=atol)
        # the field alone (the orientation held) cannot tell them apart
        var = np.full(step.weights.shape, 0.05**2)
        alone = fit_grid_field(
            step.xy_px, step.residuals_px, var, image_size=step.image_size, tau_px=0.1, order=4, grid=BI_GRID
        )
        assert np.abs(alone.correction_at(q) - truth.correction_at(q)).max() > 100 * atol


def _projections(adj, obs, rows, orientation, xyz_mm) -> np.ndarray:
    """``(n, 2)`` px: the projections of ``rows`` (system by system) under ``orientation``, beads at ``xyz_mm``."""
    out = []
    for s, sel in enumerate(rows):
        q_s, T_s = orientation.poses(s)
        epoch = np.searchsorted(adj.exposure, obs.exposure[sel])
        bead = np.searchsorted(adj.bead_id, obs.bead_id[sel])
        xy = np.empty((len(sel), 2))
        for e in np.unique(epoch):
            at = epoch == e
            xy[at] = project(xyz_mm[bead[at]], q_s[e], T_s[e], orientation.iop_px[s])
        out.append(xy)
    return np.concatenate(out)


def _moved(adj, obs, rows, net, d_theta):
    """The orientation and the beads of ``adj`` moved by ``d_theta`` in the network's parameters, exactly."""
    ori = adj.orientation
    epochs = np.unique(np.concatenate([np.searchsorted(adj.exposure, obs.exposure[r]) for r in rows]))
    ref = d_theta[6 : 6 + 6 * len(epochs)].reshape(-1, 6)
    rop = d_theta[6 + 6 * len(epochs) : net.point_col].reshape(-1, 6)
    q, src = ori.q_cam_from_obj.copy(), ori.source_mm.copy()
    q[epochs] = quat_multiply(rotvec_to_quat(ref[:, :3]), q[epochs])
    src[epochs] += ref[:, 3:]
    rop_q, rop_src = ori.rop_q.copy(), ori.rop_source_mm.copy()
    rop_q[1:] = quat_multiply(rotvec_to_quat(rop[:, :3]), rop_q[1:])
    rop_src[1:] += rop[:, 3:]
    moved = replace(
        ori,
        iop_px=ori.iop_px + d_theta[:6].reshape(2, 3),
        q_cam_from_obj=q,
        source_mm=src,
        rop_q=rop_q,
        rop_source_mm=rop_src,
    )
    xyz = adj.xyz_mm.copy()
    xyz[net.beads] += d_theta[net.point_col :].reshape(-1, 3)
    return moved, xyz


def test_two_systems_network_is_the_rigs_jacobian(biplanar_linearised):
    # the Jacobian by both IOPs, the epochs' reference poses, system B's ROP and the shared beads against central
    # differences of the projections under the orientation moved along a random direction (Orientation.poses composes
    # the ROP with the reference pose); a similarity of the whole object space projects to nothing
    adj, obs, rows = biplanar_linearised
    net = systems_network(adj, obs, rows, (0, 1))
    d_theta = np.random.default_rng(9).normal(0, 1e-3, net.J.shape[1])  # px, rad and mm
    h = 1e-2
    plus, minus = (_projections(adj, obs, rows, *_moved(adj, obs, rows, net, k * h * d_theta)) for k in (1, -1))
    linear = (net.J @ d_theta).reshape(2, -1).T
    # central differences: truncation ~(h |dθ|)² relative, rounding ~1e-13 px / (h |J dθ|): measured 3.0e-10
    # relative, bound 2x; a wrong column (a missing ROP term is of the order of the ROP's columns themselves) is far
    # above it
    np.testing.assert_allclose((plus - minus) / (2 * h), linear, atol=6e-10 * np.abs(linear).max())
    scale = np.sqrt(net.J.multiply(net.J).sum())
    assert np.linalg.norm(net.J @ net.datum, axis=0).max() < 1e-9 * scale
    # laid out as the canonical CSR a conversion from COO gives (each row's columns increasing, none twice), so that
    # every product with it sums in that order
    coo = net.J.tocoo()
    canonical = csr_matrix((coo.data, (coo.row, coo.col)), shape=net.J.shape)
    for name in ("indptr", "indices", "data"):
        np.testing.assert_array_equal(getattr(net.J, name), getattr(canonical, name))


def test_second_system_alone_network_datum_projects_to_nothing(biplanar_linearised):
    # system B's observations alone (the per-system network of the joint uncertainty): a similarity of object space
    # still moves nothing in B's image; parametrised by the epochs' reference poses, B's ROP offset had no column and
    # the scale mode moved B's sources (found in review)
    adj, obs, rows = biplanar_linearised
    net = linearised_network(adj, obs, rows[1], 1)
    scale = np.sqrt(net.J.multiply(net.J).sum())
    assert np.linalg.norm(net.J @ net.datum, axis=0).max() < 1e-9 * scale


def test_deflated_preconditioner_is_symmetric_positive_definite_and_exact_on_its_coarse_space():
    # the conjugate gradients need a symmetric positive definite preconditioner, from any start (the loop's steps
    # start from the last one's); Q + (I - QA) M (I - AQ) (Tang et al.'s BNN) is one, for A and M so, and it inverts
    # A exactly on span(W): analytic, on random matrices (the one-sided A-DEF2, Q + (I - QA) M, is not symmetric)
    from fluorocal.stages.learn.joint import _deflated

    rng = np.random.default_rng(12)
    n, k = 40, 6
    X, Y = rng.normal(size=(n, n)), rng.normal(size=(n, n))
    A, M = X @ X.T + 1e-2 * np.eye(n), np.linalg.inv(Y @ Y.T + 1e-2 * np.eye(n))
    W, _ = np.linalg.qr(rng.normal(size=(n, k)))
    apply = _deflated(lambda x: M @ x, lambda x: A @ x, W)
    P = np.column_stack([apply(e) for e in np.eye(n)])
    np.testing.assert_allclose(P, P.T, atol=1e-10 * np.abs(P).max())
    assert np.linalg.eigvalsh((P + P.T) / 2).min() > 0
    np.testing.assert_allclose(apply(A @ W), W, atol=1e-8)


def test_a_coarse_space_the_product_does_not_see_leaves_the_preconditioner_undeflated():
    # W^T A W singular (A nil on a direction of W): no coarse solve, the plain preconditioner, not a LinAlgError
    from fluorocal.stages.learn.joint import _deflated

    n = 10
    W = np.eye(n)[:, :2]
    A = np.diag(np.r_[0.0, np.ones(n - 1)])
    apply = _deflated(lambda x: 2.0 * x, lambda x: A @ x, W)
    x = np.arange(n, dtype=float)
    np.testing.assert_array_equal(apply(x), 2.0 * x)


def test_coupling_products_are_those_of_the_formed_matrix():
    # the fields' coupling to the orientation, N_vθ = [A_s^T W_sc J_sc] stacked by system s and component c, applied
    # through its factors: its products and its transpose's against the matrix formed (two systems, J's x rows then
    # y rows, system by system in each; the node vector each system's x components, then its y ones)
    from types import SimpleNamespace

    from fluorocal.stages.learn.joint import _coupling
    from scipy.sparse import random as sparse_random
    from scipy.sparse import vstack

    rng = np.random.default_rng(5)
    nodes = np.arange(6) * 16.0
    n_obs, n_theta = (30, 20), 15
    parts = []
    for n in n_obs:
        xy = rng.uniform(0, nodes[-1], (n, 2))
        A = bilinear_design(nodes, nodes, xy)
        w = rng.uniform(0.5, 2.0, (n, 2))
        parts.append(SimpleNamespace(xy=xy, n_nodes=A.shape[1], AtW=[A.T.multiply(w[:, c]).tocsr() for c in range(2)]))
    J = sparse_random(2 * sum(n_obs), n_theta, density=0.3, random_state=7, format="csr")
    total = sum(n_obs)
    starts = (0, n_obs[0], total)
    blocks = [p.AtW[c] @ J[c * total + a : c * total + b] for p, a, b in zip(parts, starts, starts[1:]) for c in (0, 1)]
    N = vstack(blocks).toarray()
    to_fields, to_orientation = _coupling(parts, J)
    y, v = rng.normal(size=(n_theta, 3)), rng.normal(size=(N.shape[0], 3))
    np.testing.assert_allclose(to_fields(y), N @ y, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(to_fields(y[:, 0]), N @ y[:, 0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(to_orientation(v), N.T @ v, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(to_orientation(v[:, 0]), N.T @ v[:, 0], rtol=1e-12, atol=1e-12)


def test_normal_matrix_and_its_scalings_are_the_sparse_products_bit_for_bit():
    # the orientation's normal matrix J^T W J and its Jacobi scaling, formed without the sparse products'
    # conversions: the same numbers in the same layout, so every later product sums alike (a Jacobian of 12
    # entries per row, like the network's, with its own rows' order unsorted before canonicalisation)
    from fluorocal.stages.learn.joint import _jacobi_scaled, _normal_matrix, _row_scaled
    from scipy.sparse import csr_matrix, diags

    rng = np.random.default_rng(9)
    n_rows, n_cols = 400, 90
    cols = np.array([rng.choice(n_cols, 12, replace=False) for _ in range(n_rows)])
    J = csr_matrix((rng.normal(size=cols.size), (np.repeat(np.arange(n_rows), 12), cols.ravel())), (n_rows, n_cols))
    w = rng.uniform(0.5, 2.0, n_rows)
    expected_jw = J.multiply(w[:, None]).tocsr()
    expected_n = (J.T @ expected_jw).tocsr()
    s = 1.0 / np.sqrt(expected_n.diagonal())
    expected_scaled = (diags(s) @ expected_n @ diags(s)).tocsr()
    jw = _row_scaled(J, w)
    n = _normal_matrix(J.T.tocsr(), jw)
    for got, expected in ((jw, expected_jw), (n, expected_n), (_jacobi_scaled(n, s), expected_scaled)):
        for name in ("indptr", "indices", "data"):
            np.testing.assert_array_equal(getattr(got, name), getattr(expected, name))


def test_field_blocks_multiply_as_their_block_diagonal_matrix_bit_for_bit():
    # the joint step's field blocks (A^T W_c A + the prior + the ridge, per system and component), multiplied block
    # by block: the numbers of the block-diagonal matrix's product, for a vector and for a block of vectors
    from fluorocal.stages.learn.grid import prior_normal
    from fluorocal.stages.learn.joint import _block_product, _field_normal
    from scipy.sparse import block_diag, diags

    rng = np.random.default_rng(13)
    nodes = np.arange(7) * 16.0
    blocks, expected = [], []
    for n in (60, 90):
        A = bilinear_design(nodes, nodes, rng.uniform(0, nodes[-1], (n, 2)))
        w = rng.uniform(0.5, 2.0, (n, 2))
        reg = prior_normal(7, 7, 2) / 0.3**2
        Nvv, _, _, data, ridge = _field_normal(A, w, rng.normal(size=(n, 2)), reg, np.zeros((49, 2)))
        blocks += list(Nvv)
        expected.append(block_diag([data[0] + reg, data[1] + reg], format="csc") + diags(np.full(98, ridge)))
    formed = block_diag(expected, format="csr")
    for v in (rng.normal(size=formed.shape[0]), rng.normal(size=(formed.shape[0], 4))):
        np.testing.assert_array_equal(_block_product(blocks, v), formed @ v)
