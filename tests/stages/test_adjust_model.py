"""Tests of the bundle adjustment's model (stages/adjust/): residuals, Jacobians, the polynomial additional parameters.

Residuals at hand-computed points and against stages/geometry.project, the analytic Jacobian against
central differences, and the polynomial model: by hand, its Jacobian, recovered by the adjustment.
Synthetic problems as in test_adjust.py (tests/stages/ba_synthetic.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from fluorocal.stages.adjust import FreeParameters, SolverOptions, adjust_bundle, polynomial
from fluorocal.stages.adjust.bundle import prepare
from fluorocal.stages.adjust.collinearity import State, jacobian, jacobian_blocks, linearize, residuals
from fluorocal.stages.adjust.normal import assemble, triggs_corrected, weighted_jacobian
from fluorocal.stages.adjust.problem import apply_step, build_problem, segment_starts, segment_summer
from fluorocal.stages.artifacts import Observations

from tests.stages.ba_synthetic import BIPLANAR, MONO, aligned_error_mm, make_problem, rms, with_xy

NOISE_PX = 0.05


@pytest.fixture(scope="module")
def mono():
    return make_problem(**MONO)


@pytest.fixture(scope="module")
def biplanar():
    return make_problem(**BIPLANAR)


# --------------------------------------------------------------------------- residuals and Jacobians


def _tiny_problem(sigma, correction):
    """One bead at (10, -20, 0) mm seen from a source at (0, 0, -1000) mm, identity rotation, c = 4400 px."""
    problem, _ = build_problem(
        np.array([0]),
        np.array([0]),
        np.array([0]),
        np.array([[557.0, 423.5]]) - correction,
        np.array([sigma]),
        np.array([[10.0, -20.0, 0.0]]),
        1,
        1,
        np.array([True]),
        "points",
    )
    state = State(
        np.array([[10.0, -20.0, 0.0]]),
        np.array([[1.0, 0, 0, 0]]),
        np.array([[0.0, 0, -1000]]),
        np.array([[512.0, 512.0, 4400.0]]),
        np.array([[1.0, 0, 0, 0]]),
        np.zeros((1, 3)),
    )
    return problem, state


def test_residuals_at_hand_computed_point():
    # p_cam = (10, -20, 1000): projection (512 + 4400 * 0.01, 512 - 4400 * 0.02) = (556, 424);
    # ideal = (557, 423.5) - Δ(0.5, 0.25) = (556.5, 423.25); residual (0.5, -0.75) px
    problem, state = _tiny_problem([0.1, 0.2, 0.0], np.array([[0.5, 0.25]]))
    r, e = residuals(state, problem)
    np.testing.assert_array_equal(r, [[0.5, -0.75]])
    np.testing.assert_allclose(e, [[5.0, -3.75]], rtol=1e-15)
    # correlated: e2 = (r2 - ρ σy/σx r1) / (σy sqrt(1 - ρ²)) = (-0.75 - 0.5) / (0.2 * sqrt(0.75))
    problem, state = _tiny_problem([0.1, 0.2, 0.5], np.array([[0.5, 0.25]]))
    r, e = residuals(state, problem)
    np.testing.assert_allclose(e, [[5.0, -1.25 / (0.2 * math.sqrt(0.75))]], rtol=1e-14)
    C = np.array([[0.01, 0.5 * 0.1 * 0.2], [0.5 * 0.1 * 0.2, 0.04]])
    assert (e**2).sum() == pytest.approx(float(r[0] @ np.linalg.solve(C, r[0])), rel=1e-13)


def test_residuals_match_geometry_project(biplanar):
    """The adjustment's model reproduces stages/geometry.project through Orientation.poses for both systems."""
    prep = prepare(biplanar.observations, (biplanar.ids, biplanar.xyz_true_mm), biplanar.truth)
    state = State(
        biplanar.xyz_true_mm.copy(),
        *(
            np.array(a)
            for a in (
                biplanar.truth.q_cam_from_obj,
                biplanar.truth.source_mm,
                biplanar.truth.iop_px,
                biplanar.truth.rop_q,
                biplanar.truth.rop_source_mm,
            )
        ),
    )
    r, _ = residuals(state, prep.problem)
    noise = biplanar.observations.xy_px - biplanar.ideal_px
    np.testing.assert_allclose(r, noise[prep.used][prep.perm], atol=1e-9)


@pytest.mark.parametrize("eliminate", ["points", "poses"])
def test_analytic_jacobian_matches_central_differences(biplanar, eliminate):
    """Every Jacobian block against central differences through the local parametrisation.

    Step h = 1e-6 in each parameter's unit (mm, rad, px): the truncation error is
    O(h² |e'''|) ~ 1e-8 and the rounding error eps |e| / h ~ 1e-16 * 1e3 / 1e-6 = 1e-7
    (|e| up to ~1e3 whitened at the perturbed start), against entries up to ~1e5
    (4400 px/rad / 0.05 px): a tolerance of 1e-6 relative to the largest entry
    plus 1e-5 absolute leaves margin while catching any sign or index error.
    """
    sigma = biplanar.observations.sigma_px.copy()
    sigma[:, 1] *= 1.5
    sigma[:, 2] = 0.3
    obs = Observations(
        biplanar.observations.system,
        biplanar.observations.exposure,
        biplanar.observations.bead_id,
        biplanar.observations.xy_px,
        sigma,
        biplanar.observations.system_names,
    )
    prep = prepare(obs, (biplanar.ids, biplanar.nominal_mm), biplanar.initial, solver=SolverOptions(schur=eliminate))
    problem, state = prep.problem, prep.state
    e0, J_point, J_pose, J_glob = linearize(state, problem)
    h = 1e-6

    def fd(d_points, d_poses, d_glob):
        ep = residuals(apply_step(state, problem, d_points, d_poses, d_glob), problem)[1]
        em = residuals(apply_step(state, problem, -d_points, -d_poses, -d_glob), problem)[1]
        return (ep - em) / (2 * h)

    zp, zc, zg = np.zeros((problem.n_points, 3)), np.zeros((problem.n_poses, 6)), np.zeros(problem.n_globals)
    checks = []
    for i, k in [(0, 0), (7, 1), (33, 2)]:
        d = zp.copy()
        d[i, k] = h
        sel = problem.point_idx == i
        checks.append((fd(d, zc, zg)[sel], J_point[sel, :, k]))
    for j in (0, 5):
        for k in range(6):
            d = zc.copy()
            d[j, k] = h
            sel = problem.pose_idx == j
            checks.append((fd(zp, d, zg)[sel], J_pose[sel, :, k]))
    for s in range(2):
        for k, col in enumerate(problem.gcol[s]):
            if col < 0:
                continue
            d = zg.copy()
            d[col] = h
            sel = problem.sys_idx == s
            checks.append((fd(zp, zc, d)[sel], J_glob[sel, :, k]))
    assert len(checks) == 3 + 12 + 3 + 9
    for numeric, analytic in checks:
        scale = np.abs(analytic).max()
        np.testing.assert_allclose(analytic, numeric, rtol=0, atol=1e-6 * scale + 1e-5)


def test_three_systems_jacobian_with_a_missing_epoch_and_shuffled_observations():
    """``∂e/∂P`` and ``∂e/∂(δθ, T)`` of three systems against central differences (as above).

    An epoch left out and the observations in random order: each observation's ``R_s R_j`` must be
    that of its own (epoch, system) pair whatever the pairs' numbering.
    """
    syn = make_problem(n_beads=40, n_exposures=7, n_systems=3, seed=2, visible_fraction=0.8)
    o = syn.observations
    keep = np.random.default_rng(1).permutation(np.flatnonzero(o.exposure != np.unique(o.exposure)[2]))
    columns = (o.system, o.exposure, o.bead_id, o.xy_px, o.sigma_px)
    obs = Observations(*(c[keep] for c in columns), o.system_names)
    prep = prepare(obs, (syn.ids, syn.nominal_mm), syn.initial)
    problem, state, h = prep.problem, prep.state, 1e-6
    _, J_point, J_pose, _ = linearize(state, problem)
    zp, zc, zg = np.zeros((problem.n_points, 3)), np.zeros((problem.n_poses, 6)), np.zeros(problem.n_globals)
    for j in range(problem.n_poses):
        sel = problem.pose_idx == j
        assert len(np.unique(problem.sys_idx[sel])) == 3
        for k in range(6):
            d = zc.copy()
            d[j, k] = h
            ep = residuals(apply_step(state, problem, zp, d, zg), problem)[1]
            em = residuals(apply_step(state, problem, zp, -d, zg), problem)[1]
            scale = np.abs(J_pose[sel, :, k]).max()
            np.testing.assert_allclose(J_pose[sel, :, k], ((ep - em) / (2 * h))[sel], rtol=0, atol=1e-6 * scale + 1e-5)
    for i in (0, 17):
        d = zp.copy()
        d[i, 2] = h
        ep = residuals(apply_step(state, problem, d, zc, zg), problem)[1]
        em = residuals(apply_step(state, problem, -d, zc, zg), problem)[1]
        sel = problem.point_idx == i
        scale = np.abs(J_point[sel, :, 2]).max()
        np.testing.assert_allclose(J_point[sel, :, 2], ((ep - em) / (2 * h))[sel], rtol=0, atol=1e-6 * scale + 1e-5)


def _dense_jacobian(problem, J):
    """The Jacobian ``(N, 2, n_free)`` with every block in its own columns: eliminated, kept, globals."""
    J_point, J_pose, J_glob = jacobian_blocks(problem, J)
    n_p, n_c = 3 * problem.n_points, 6 * problem.n_poses
    point_at, pose_at = (0, n_p) if problem.eliminate == "points" else (n_c, 0)
    dense = np.zeros((problem.n_obs, 2, n_p + n_c + problem.n_globals))
    for n in range(problem.n_obs):
        i, j, cols = problem.point_idx[n], problem.pose_idx[n], problem.gcol[problem.sys_idx[n]]
        dense[n, :, point_at + 3 * i : point_at + 3 * i + 3] = J_point[n]
        dense[n, :, pose_at + 6 * j : pose_at + 6 * j + 6] = J_pose[n]
        dense[n][:, n_p + n_c + cols[cols >= 0]] = J_glob[n][:, cols >= 0]
    return dense


@pytest.mark.parametrize(
    ("eliminate", "n_systems", "aps"),
    [("points", 3, False), ("poses", 3, False), ("points", 1, True), ("poses", 1, True)],
)
def test_schur_blocks_are_the_dense_normal_equations(eliminate, n_systems, aps):
    """``assemble``'s blocks against ``Σ J_h^T J_h`` and ``-Σ J^T e`` of the dense Jacobian.

    Three systems (pairs seen by several systems add up) or one with its additional parameters (the
    globals' columns of the stacked Jacobian), an epoch left out, the observations shuffled, random
    weights, and a Hessian Jacobian (Triggs') other than the gradient's.
    """
    syn = make_problem(n_beads=40, n_exposures=7, n_systems=n_systems, seed=2, visible_fraction=0.8)
    o = syn.observations
    keep = np.random.default_rng(3).permutation(np.flatnonzero(o.exposure != np.unique(o.exposure)[2]))
    obs = Observations(*(c[keep] for c in (o.system, o.exposure, o.bead_id, o.xy_px, o.sigma_px)), o.system_names)
    free = FreeParameters(additional_parameters="polynomial" if aps else "none")
    prep = prepare(obs, (syn.ids, syn.nominal_mm), syn.initial, free=free, solver=SolverOptions(schur=eliminate))
    problem = prep.problem
    assert problem.eliminate == eliminate
    e, J = jacobian(prep.state, problem)
    Jw, ew = weighted_jacobian(e, J, np.random.default_rng(4).uniform(0.2, 1.5, problem.n_obs))
    Jh = triggs_corrected(Jw, ew, (e * e).sum(1), 4.0)
    normal = assemble(problem, Jw, ew, Jh)
    dense_h = _dense_jacobian(problem, Jh).reshape(2 * problem.n_obs, -1)
    H = dense_h.T @ dense_h
    b = -np.einsum("nij,ni->j", _dense_jacobian(problem, Jw), ew)
    ne_be = problem.ne * problem.be
    tol = 1e-12 * np.abs(H).max()
    blocks = H[:ne_be, :ne_be].reshape(problem.ne, problem.be, problem.ne, problem.be)
    ar = np.arange(problem.ne)
    np.testing.assert_allclose(normal.A, blocks[ar, :, ar, :], rtol=0, atol=tol)
    np.testing.assert_allclose(normal.B, H[:ne_be, ne_be:], rtol=0, atol=tol)
    np.testing.assert_allclose(normal.Hyy, H[ne_be:, ne_be:], rtol=0, atol=tol)
    np.testing.assert_allclose(normal.b_e.ravel(), b[:ne_be], rtol=0, atol=1e-12 * np.abs(b).max())
    np.testing.assert_allclose(normal.b_y, b[ne_be:], rtol=0, atol=1e-12 * np.abs(b).max())


@pytest.mark.parametrize("ordered", [True, False])
def test_segment_summer_sums_every_segment_in_any_row_order(ordered):
    """``segment_summer`` against ``np.add.at``: keys with gaps (blocks seen nowhere), rows sorted or in an order."""
    rng = np.random.default_rng(5)
    keys = rng.choice(np.array([0, 2, 3, 7, 8, 11]), size=300)  # 1, 4-6, 9, 10: no rows
    X = rng.normal(size=(300, 5))
    order = np.argsort(keys, kind="stable")
    if ordered:
        keys, X, order = keys[order], X[order], None
    sorted_keys = keys if order is None else keys[order]
    starts = segment_starts(sorted_keys)
    expected = np.zeros((12, 5))
    np.add.at(expected, keys, X)
    np.testing.assert_array_equal(sorted_keys[starts], [0, 2, 3, 7, 8, 11])
    np.testing.assert_allclose(segment_summer(starts, len(keys), order) @ X, expected[sorted_keys[starts]], atol=1e-12)


# --------------------------------------------------------------------------- additional parameters (polynomial)

#: a polynomial distortion in px at the reference radius 700 px (k1, k2, k3, p1, p2, b1, b2): a few px radial,
#: sub-px decentring and affinity, as in image intensifiers after the S-distortion
AP_TRUE = np.array([4.0, -1.0, 0.3, 0.6, -0.4, 0.5, 0.3])
AP_RADIUS_PX = 700.0


def _polynomially_distorted(syn, ap=AP_TRUE, radius_px=AP_RADIUS_PX):
    """``syn``'s observations distorted by the polynomial model at the true principal point (same noise).

    Returns the observations and the true correction at them (``ideal = measured - Δ``).
    """
    obs = syn.observations
    pp = syn.truth.iop_px[obs.system, :2]
    measured = syn.ideal_px.copy()
    for _ in range(50):  # m = ideal + Δ(m): a contraction, |∂Δ/∂m| ~ 0.03
        measured = syn.ideal_px + polynomial.correction_at(measured, pp, radius_px, np.tile(ap, (len(obs), 1)))
    measured += obs.xy_px - syn.ideal_px
    return with_xy(obs, measured), polynomial.correction_at(measured, pp, radius_px, np.tile(ap, (len(obs), 1)))


def test_polynomial_model_at_hand_computed_points():
    pp = np.array([500.0, 400.0])
    # u = 0.6, v = 0.8 (ρ = 1): each coefficient's term by hand
    xy = np.array([[560.0, 480.0]])
    expected = {
        "k1": (0.6, 0.8),
        "k2": (0.6, 0.8),
        "k3": (0.6, 0.8),
        "p1": (1 + 2 * 0.36, 2 * 0.48),
        "p2": (2 * 0.48, 1 + 2 * 0.64),
        "b1": (0.6, 0.0),
        "b2": (0.8, 0.0),
    }
    for i, name in enumerate(polynomial.AP_NAMES):
        ap = np.zeros(7)
        ap[i] = 1.0
        np.testing.assert_allclose(polynomial.correction_at(xy, pp, 100.0, ap), [expected[name]], rtol=1e-14)
    # another reference radius describes the same field with rescaled coefficients
    ap = AP_TRUE
    other = polynomial.rescaled(ap, 700.0, 350.0)
    pts = np.random.default_rng(0).uniform(0, 1000, (50, 2))
    np.testing.assert_allclose(
        polynomial.correction_at(pts, pp, 350.0, other), polynomial.correction_at(pts, pp, 700.0, ap), rtol=1e-12
    )


@pytest.mark.parametrize("eliminate", ["points", "poses"])
def test_ap_jacobian_matches_central_differences(biplanar, eliminate):
    """The AP columns and the principal point's (which the AP model depends on) against central differences.

    At the perturbed start with nonzero APs on both systems (|e| up to ~2e3 whitened). Step
    h = 1e-4 px: the residuals are linear in the APs and a polynomial of small curvature in
    (xp, yp, c), so truncation is negligible, and the rounding error eps |e| / h ~
    2e-16 * 2e3 / 1e-4 = 4e-9 stays far below 1e-6 of the smallest column (c: ~2 per px;
    measured worst 1e-8 relative).
    """
    from dataclasses import replace

    obs, _ = _polynomially_distorted(biplanar)
    prep = prepare(
        obs,
        (biplanar.ids, biplanar.nominal_mm),
        biplanar.initial,
        None,
        free=FreeParameters(additional_parameters="polynomial", fixed_additional_parameters=()),
        solver=SolverOptions(schur=eliminate),
    )
    problem = prep.problem
    assert problem.gcol.shape == (2, 16) and problem.n_globals == 2 * 3 + 6 + 2 * 7  # IOP, ROP of B, APs
    state = replace(prep.state, ap_px=np.array([AP_TRUE, -0.5 * AP_TRUE[::-1]]))
    _, _, _, J_glob = linearize(state, problem)
    zp, zc = np.zeros((problem.n_points, 3)), np.zeros((problem.n_poses, 6))
    h = 1e-4
    worst = 0.0
    for s in range(2):
        sel = problem.sys_idx == s
        for k, col in enumerate(problem.gcol[s]):
            if col < 0:
                continue
            d = np.zeros(problem.n_globals)
            d[col] = h
            ep = residuals(apply_step(state, problem, zp, zc, d), problem)[1]
            em = residuals(apply_step(state, problem, zp, zc, -d), problem)[1]
            numeric = ((ep - em) / (2 * h))[sel]
            analytic = J_glob[sel, :, k]
            worst = max(worst, float(np.abs(analytic - numeric).max() / np.abs(analytic).max()))
    assert worst < 1e-6, worst


def test_polynomial_distortion_is_recovered_by_the_adjustment(mono):
    """Observations distorted exactly by the AP model (+ 0.05 px noise): the coefficients come back within 3σ.

    The 3D error is compared with the same solve handed the true correction
    (the physical limit): the 7 extra parameters, partly correlated with the
    IOP and the free network, may cost some accuracy but not more than 1.8x
    (measured 0.0104 vs 0.0067 mm; without the APs 0.043 mm).
    """
    obs, true_corr = _polynomially_distorted(mono)
    nominal = (mono.ids, mono.nominal_mm)
    # all seven: the tilted cube at 950 mm determines the affinity too
    res = adjust_bundle(
        obs,
        nominal,
        mono.initial,
        free=FreeParameters(additional_parameters="polynomial", fixed_additional_parameters=()),
    )
    assert res.usable and res.additional_parameters == "polynomial"
    r0 = res.ap_radius_px[0]
    assert r0 == pytest.approx(polynomial.reference_radius(obs.xy_px))
    truth = polynomial.rescaled(AP_TRUE, AP_RADIUS_PX, r0)
    z = (res.ap_px[0] - truth) / res.ap_std_px[0]
    assert np.all(np.abs(z) < 3), z
    assert np.all(np.abs(res.iop_px - mono.truth.iop_px) <= 3 * res.iop_std_px)
    np.testing.assert_allclose(res.ap_std_px[0], np.sqrt(np.diag(res.ap_cov_px2[0])))
    # the residuals are the noise: 0.05 px times sqrt(redundancy)
    assert rms(res.residual_px[res.inlier]) < 1.05 * NOISE_PX
    err = rms(aligned_error_mm(res.xyz_mm, mono.xyz_true_mm))
    oracle = rms(aligned_error_mm(adjust_bundle(obs, nominal, mono.initial, true_corr).xyz_mm, mono.xyz_true_mm))
    plain = rms(aligned_error_mm(adjust_bundle(obs, nominal, mono.initial).xyz_mm, mono.xyz_true_mm))
    assert err < 1.8 * oracle and err < 0.4 * plain, (err, oracle, plain)
    assert err == pytest.approx(math.sqrt(np.einsum("nii->n", res.xyz_cov_mm2).mean()), rel=0.25)
    # the reported model is the one the residuals were computed with: r = (xy - Δ_AP(xy)) - projection
    from fluorocal.stages.geometry import project

    point = np.searchsorted(res.bead_id, obs.bead_id)
    projected = np.empty_like(obs.xy_px)
    for j, ep in enumerate(res.exposure):
        sel = obs.exposure == ep
        projected[sel] = project(res.xyz_mm[point[sel]], res.q_cam_from_obj[j], res.source_mm[j], res.iop_px[0])
    np.testing.assert_allclose(
        obs.xy_px - res.polynomial_correction(0, obs.xy_px) - projected, res.residual_px, atol=1e-9
    )
    # the estimated correction at the observations is the true one up to what the orientation absorbs
    # (a principal-point shift, a scale, a common rotation: a homography); measured 0.001 px mod H of 0.4 px RMS
    import cv2

    ideal = obs.xy_px - res.polynomial_correction(0, obs.xy_px)
    H, _ = cv2.findHomography(ideal, obs.xy_px - true_corr, 0)
    assert rms(cv2.perspectiveTransform(ideal[None], H)[0] - (obs.xy_px - true_corr)) < 0.01 * rms(true_corr)
    assert res.n_parameters == 3 * len(mono.ids) + 6 * len(mono.initial.exposure) + 3 + 7


@pytest.mark.parametrize("eliminate", ["points", "poses"])
def test_linearizing_from_the_cost_evaluations_projection_changes_nothing(biplanar, eliminate):
    """The solver linearises from the camera points and residuals of its cost evaluation: the same arrays to the bit.

    Biplanar, with nonzero APs on both systems (the AP basis enters the residuals), at the perturbed start.
    """
    from dataclasses import replace

    from fluorocal.stages.adjust.collinearity import project

    obs, _ = _polynomially_distorted(biplanar)
    free = FreeParameters(additional_parameters="polynomial", fixed_additional_parameters=())
    nominal, solver = (biplanar.ids, biplanar.nominal_mm), SolverOptions(schur=eliminate)
    prep = prepare(obs, nominal, biplanar.initial, None, free=free, solver=solver)
    state = replace(prep.state, ap_px=np.array([AP_TRUE, -0.5 * AP_TRUE[::-1]]))
    fresh = linearize(state, prep.problem)
    reused = linearize(state, prep.problem, project(state, prep.problem))
    assert np.array_equal(residuals(state, prep.problem)[1], fresh[0])
    for a, b in zip(fresh, reused, strict=True):
        assert np.array_equal(a, b)


def test_triggs_correction_scales_only_the_rows_along_the_residual():
    """Per observation, ``n^T J_h = sqrt(D) n^T J`` with ``D = (ν - t)/(ν + t)`` clipped to [0, 1], ``m^T J_h = m^T J``.

    ``n`` the residual's direction, ``m`` its normal: the corrected Jacobian's curvature along the
    residual is the Student-t one and unchanged across it (random J, residuals on both sides of ν).
    """
    from fluorocal.stages.adjust.normal import triggs_corrected

    rng = np.random.default_rng(3)
    J, ew = rng.normal(size=(50, 2, 7)), rng.normal(size=(50, 2))
    nu, t = 4.0, rng.uniform(0.0, 12.0, 50)
    Jh = triggs_corrected(J, ew, t, nu)
    n = ew / np.linalg.norm(ew, axis=1, keepdims=True)
    m = np.column_stack([-n[:, 1], n[:, 0]])
    along = lambda A, d: np.einsum("ni,nij->nj", d, A)  # noqa: E731
    root_d = np.sqrt(np.clip((nu - t) / (nu + t), 0.0, 1.0))[:, None]
    assert np.allclose(along(Jh, n), root_d * along(J, n), rtol=0, atol=1e-13)
    assert np.allclose(along(Jh, m), along(J, m), rtol=0, atol=1e-13)
    assert (t > nu).any() and (t < nu).any()
