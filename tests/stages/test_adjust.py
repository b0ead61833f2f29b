"""Tests of the robust bundle adjustment (the package stages/adjust/): the solve, its statistics, its input.

Synthetic problems come from tests/stages/ba_synthetic.py: beads on four faces
of a 120 mm cube, a tilted turntable ring of exposures at ~950 mm from the
source, c = 4400 px, 1024² images, 0.05 px Gaussian noise unless stated.
The model itself (residuals, Jacobians, the polynomial additional parameters): test_adjust_model.py.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from fluorocal.config import params_from_dict
from fluorocal.stages.adjust import (
    Adjustment,
    DataSelection,
    FreeParameters,
    Orientation,
    SolverOptions,
    adjust_bundle,
)
from fluorocal.stages.adjust.bundle import prepare
from fluorocal.stages.adjust.collinearity import State, residuals
from fluorocal.stages.adjust.problem import apply_step, datum_directions
from fluorocal.stages.adjust.robust import t_cost
from fluorocal.stages.artifacts import Observations, Phantom
from fluorocal.stages.errors import EstimationError, InputError, ShapeError
from fluorocal.stages.geometry import quat_to_matrix, similarity_fit

from tests.stages.ba_synthetic import BIPLANAR, MONO, ScipyProblem, aligned_error_mm, make_problem, rms, with_xy

NOISE_PX = 0.05


def _solve(syn, **options) -> Adjustment:
    return adjust_bundle(syn.observations, (syn.ids, syn.nominal_mm), syn.initial, **options)


@pytest.fixture(scope="module")
def mono():
    return make_problem(**MONO)


@pytest.fixture(scope="module")
def mono_result(mono):
    return _solve(mono)


@pytest.fixture(scope="module")
def biplanar():
    return make_problem(**BIPLANAR)


# --------------------------------------------------------------------------- shape / smoke


def test_output_shapes(mono, mono_result):
    res, obs = mono_result, mono.observations
    n, m = len(mono.ids), len(mono.initial.exposure)
    assert res.xyz_mm.shape == res.xyz_std_mm.shape == (n, 3) and res.xyz_cov_mm2.shape == (n, 3, 3)
    assert res.iop_px.shape == res.iop_std_px.shape == (1, 3)
    assert res.q_cam_from_obj.shape == (m, 4) and res.source_mm.shape == (m, 3) and res.pose_std.shape == (m, 6)
    for name in ("residual_px", "standardized_residual", "redundancy"):
        assert getattr(res, name).shape == (len(obs), 2)
    assert res.weight.shape == res.inlier.shape == res.used.shape == (len(obs),)
    assert res.usable and res.converged and res.used.all()
    assert res.xyz_mm.flags.writeable is False
    # the cost history is monotone (every accepted step and every σ² update lowers it)
    assert np.all(np.diff(res.cost_history) <= 1e-9 * np.abs(res.cost_history[:-1]).max())


def test_orientation_poses_compose_rop(biplanar):
    """System B's pose = ROP composed with A's: the projection through poses(1) matches the residuals' camera frame."""
    truth = biplanar.truth
    q_b, T_b = truth.poses(1)
    R_a = quat_to_matrix(truth.q_cam_from_obj[3])
    R_r = quat_to_matrix(truth.rop_q[1])
    P = biplanar.xyz_true_mm[:5]
    p_expected = (R_r @ (R_a @ (P - truth.source_mm[3]).T - truth.rop_source_mm[1][:, None])).T
    p_got = (quat_to_matrix(q_b[3]) @ (P - T_b[3]).T).T
    np.testing.assert_allclose(p_got, p_expected, atol=1e-9)


# --------------------------------------------------------------------------- ground truth


def test_clean_solve_matches_own_covariance(mono, mono_result):
    """0.05 px noise: the 3D error after a similarity to the truth is within 1 % of the predicted RMS; IOP in 3σ."""
    res = mono_result
    err = aligned_error_mm(res.xyz_mm, mono.xyz_true_mm)
    predicted = math.sqrt(np.einsum("nii->n", res.xyz_cov_mm2).mean())
    assert rms(err) == pytest.approx(predicted, rel=0.01)  # measured 0.49 % (0.00670 against 0.00673 mm)
    assert np.all(np.abs(res.iop_px - mono.truth.iop_px) <= 3 * res.iop_std_px)
    assert res.sigma0 == pytest.approx(1.0, rel=6e-4)  # sigma_px is the true noise; measured 1.00032
    assert (~res.inlier).mean() < 0.002  # Gaussian data: outliers only by chance (r² > 26 at ν = 4)


def test_biplanar_recovers_rop(biplanar):
    res = _solve(biplanar)
    assert res.usable
    truth = biplanar.truth
    assert np.all(np.abs(res.iop_px - truth.iop_px) <= 3 * res.iop_std_px)
    assert np.all(np.abs(res.rop_source_mm[1] - truth.rop_source_mm[1]) <= 3 * res.rop_std[1, 3:])
    R_err = quat_to_matrix(res.rop_q[1]) @ quat_to_matrix(truth.rop_q[1]).T
    angle_err = np.array([R_err[2, 1] - R_err[1, 2], R_err[0, 2] - R_err[2, 0], R_err[1, 0] - R_err[0, 1]]) / 2
    assert np.all(np.abs(angle_err) <= 3 * res.rop_std[1, :3])
    assert rms(aligned_error_mm(res.xyz_mm, biplanar.xyz_true_mm)) < 0.01  # measured 0.0061 mm
    assert res.n_parameters == 3 * len(biplanar.ids) + 6 * 10 + 2 * 3 + 6


def test_least_squares_matches_scipy():
    """ν = inf gives the least-squares optimum: the same answer as scipy.optimize.least_squares.

    Measured (relative to the largest value): points 9.3e-11, IOP 1.3e-8, sources 2.4e-11, rotations 1.5e-9,
    datum rows 3.3e-8 mm; bounds about 2x.
    """
    from scipy.optimize import least_squares

    syn = make_problem(n_beads=40, n_exposures=6, seed=4)
    res = _solve(syn, solver=SolverOptions(nu=math.inf, function_tolerance=1e-12, parameter_tolerance=1e-14))
    ref = ScipyProblem(syn)
    sol = least_squares(
        ref.residuals, ref.x0(), jac="3-point", method="trf", x_scale="jac", ftol=1e-15, xtol=1e-15, gtol=1e-15
    )
    P, R, T, iop, _, _ = ref.unpack(sol.x)
    assert np.abs(ref.residuals(sol.x)[-7:]).max() < 7e-8  # the datum rows (mm) hold: they act only on the gauge
    np.testing.assert_allclose(res.xyz_mm, P, rtol=0, atol=2e-10 * np.abs(P).max())
    np.testing.assert_allclose(res.iop_px, iop, rtol=2.5e-8)
    np.testing.assert_allclose(res.source_mm, T, rtol=0, atol=5e-11 * np.abs(T).max())
    np.testing.assert_allclose(quat_to_matrix(res.q_cam_from_obj), R, atol=3e-9)


def test_outliers_and_swapped_labels_are_flagged(mono, mono_result):
    """5 % gross errors (5–50 px) and 1 % swapped labels: >= 95 % flagged, accuracy within 10 % of the clean solve."""
    rng = np.random.default_rng(11)
    obs = mono.observations
    n = len(obs)
    xy = obs.xy_px.copy()
    gross = rng.choice(n, int(0.05 * n), replace=False)
    xy[gross] += rng.uniform(5, 50, (len(gross), 2)) * rng.choice([-1, 1], (len(gross), 2))
    bead = obs.bead_id.copy()
    rest = np.setdiff1d(np.arange(n), gross)
    swapped = []
    for j in rng.permutation(np.unique(obs.exposure)):
        cand = rng.permutation(rest[obs.exposure[rest] == j])
        for a, b in zip(cand[0::2], cand[1::2]):
            if len(swapped) >= int(0.01 * n):
                break
            # only swaps that move the label by more than 5 px count as corrupted
            if np.linalg.norm(xy[a] - xy[b]) > 5:
                bead[a], bead[b] = bead[b], bead[a]
                swapped += [a, b]
    corrupted = np.r_[gross, swapped]
    res = adjust_bundle(with_xy(obs, xy, bead), (mono.ids, mono.nominal_mm), mono.initial)
    assert res.usable
    assert (~res.inlier[corrupted]).mean() >= 0.95
    clean_err = rms(aligned_error_mm(mono_result.xyz_mm, mono.xyz_true_mm))
    assert rms(aligned_error_mm(res.xyz_mm, mono.xyz_true_mm)) <= 1.10 * clean_err
    assert np.all(np.abs(res.iop_px - mono_result.iop_px) <= 1.0 * mono_result.iop_std_px)
    assert (~res.inlier).sum() <= len(corrupted) * 1.05 + 5  # few clean observations lost


# --------------------------------------------------------------------------- properties


def test_gauge_and_parameter_counts(mono, mono_result):
    res = mono_result
    n, m, n_obs = len(mono.ids), len(mono.initial.exposure), len(mono.observations)
    assert res.n_parameters == 3 * n + 6 * m + 3
    assert res.dof == 2 * n_obs - (res.n_parameters - 7)  # 7 datum constraints
    assert res.redundancy.sum() == pytest.approx(res.dof, rel=1e-9)
    assert np.all((res.redundancy > 0) & (res.redundancy < 1 + 1e-9))


def test_inner_constraints_hold(mono_result, mono):
    """No translation, rotation or scale of the estimated points relative to the nominal ones (to first order)."""
    D = datum_directions(mono.nominal_mm).reshape(-1, 7)
    delta = (mono_result.xyz_mm - mono.nominal_mm).ravel()
    assert np.abs(D.T @ delta).max() < 1e-9 * len(mono.ids)
    s, R, t = similarity_fit(mono.nominal_mm, mono_result.xyz_mm)
    assert abs(s - 1) < 1e-5 and np.abs(t).max() < 0.05


def test_fixed_iop_and_rop_are_bit_identical(mono):
    res = _solve(mono, free=FreeParameters(estimate_iop=False))
    assert np.array_equal(res.iop_px, mono.initial.iop_px)
    assert np.array_equal(res.rop_q, mono.initial.rop_q) and np.array_equal(
        res.rop_source_mm, mono.initial.rop_source_mm
    )
    assert np.all(res.iop_std_px == 0)
    assert res.n_parameters == 3 * len(mono.ids) + 6 * len(mono.initial.exposure)


def test_schur_orderings_agree(biplanar):
    a = _solve(biplanar, solver=SolverOptions(schur="points", function_tolerance=1e-10))
    b = _solve(biplanar, solver=SolverOptions(schur="poses", function_tolerance=1e-10))
    np.testing.assert_allclose(a.xyz_mm, b.xyz_mm, atol=1e-7)
    np.testing.assert_allclose(a.iop_px, b.iop_px, atol=1e-6)
    np.testing.assert_allclose(a.xyz_std_mm, b.xyz_std_mm, rtol=1e-6)
    np.testing.assert_allclose(a.redundancy, b.redundancy, atol=1e-6)  # t-weights move with the 1e-10 stop


@pytest.mark.parametrize("n_systems", [1, 2])
def test_perturbing_any_parameter_increases_cost(n_systems):
    """±0.2σ in any point coordinate (every 7th bead), pose, IOP or ROP parameter raises the cost at the optimum."""
    syn = make_problem(n_beads=60, n_exposures=8, n_systems=n_systems, seed=6)
    solver = SolverOptions(function_tolerance=1e-11, parameter_tolerance=1e-14)
    res = adjust_bundle(syn.observations, (syn.ids, syn.nominal_mm), syn.initial, solver=solver)
    prep = prepare(syn.observations, (syn.ids, syn.nominal_mm), res.orientation, solver=solver)
    problem = prep.problem
    state = State(
        res.xyz_mm.copy(),
        res.q_cam_from_obj.copy(),
        res.source_mm.copy(),
        res.iop_px.copy(),
        res.rop_q.copy(),
        res.rop_source_mm.copy(),
    )
    scale2 = res.t_scale**2

    def cost(st):
        e = residuals(st, problem)[1]
        return t_cost((e * e).sum(1), res.nu, scale2)

    c0 = cost(state)
    zp, zc, zg = np.zeros((problem.n_points, 3)), np.zeros((problem.n_poses, 6)), np.zeros(problem.n_globals)
    cases = []
    for i in range(0, problem.n_points, 7):
        for k in range(3):
            d = zp.copy()
            d[i, k] = 0.2 * res.xyz_std_mm[i, k]
            cases.append((d, zc, zg))
    for j in range(problem.n_poses):
        for k in range(6):
            d = zc.copy()
            d[j, k] = 0.2 * res.pose_std[j, k]
            cases.append((zp, d, zg))
    for sys_ in range(n_systems):
        std = np.r_[res.iop_std_px[sys_], res.rop_std[sys_]]
        for k, col in enumerate(problem.gcol[sys_]):
            if col >= 0:
                d = zg.copy()
                d[col] = 0.2 * std[k]
                cases.append((zp, zc, d))
    assert len(cases) == 3 * len(range(0, problem.n_points, 7)) + 6 * problem.n_poses + problem.n_globals
    for dp, dc, dg in cases:
        for sign in (1, -1):
            assert cost(apply_step(state, problem, sign * dp, sign * dc, sign * dg)) > c0


def test_covariance_matches_monte_carlo():
    """Predicted covariance vs 40 noisy repetitions (ν = 4 on Gaussian data, so the sandwich factor matters).

    With 40 runs a variance is known to about ±22 % (1σ, sqrt(2/39)). On this seed
    the IOP eigenvalue ratios are 0.89-1.13 (bound 0.8-1.25), the major axis of the
    (xp, yp) ellipse is 0.48 degrees off (bound 1; it is elongated 5:1, so its angle
    is well determined) and the trace ratio of the 3n = 180 point coordinates is
    1.085 (bound 0.85-1.17).
    """
    syn = make_problem(n_beads=60, n_exposures=8, seed=3)
    rng = np.random.default_rng(5)
    iops, pts, pts_pred, iop_pred = [], [], [], []
    for _ in range(40):
        xy = syn.ideal_px + rng.normal(0, NOISE_PX, syn.ideal_px.shape)
        res = adjust_bundle(with_xy(syn.observations, xy), (syn.ids, syn.nominal_mm), syn.initial)
        iops.append(res.iop_px[0])
        iop_pred.append(res.iop_cov_px2[0])
        pts.append(res.xyz_mm.ravel())
        pts_pred.append(np.einsum("nii->", res.xyz_cov_mm2))
    emp = np.cov(np.array(iops).T)
    pred = np.mean(iop_pred, axis=0)
    w_emp, v_emp = np.linalg.eigh(emp)
    w_pred, v_pred = np.linalg.eigh(pred)
    assert np.all((w_emp / w_pred > 0.8) & (w_emp / w_pred < 1.25)), w_emp / w_pred
    e_emp, ax_emp = np.linalg.eigh(emp[:2, :2])
    e_pred, ax_pred = np.linalg.eigh(pred[:2, :2])
    cos = abs(float(ax_emp[:, 1] @ ax_pred[:, 1]))
    assert np.degrees(np.arccos(min(cos, 1.0))) < 1
    trace_ratio = np.array(pts).var(0, ddof=1).sum() / np.mean(pts_pred)
    assert 0.85 < trace_ratio < 1.17, trace_ratio


# --------------------------------------------------------------------------- errors and degenerate input


def test_input_errors(mono):
    obs, start = mono.observations, mono.initial
    nominal = (mono.ids, mono.nominal_mm)
    with pytest.raises(ShapeError, match=r"corrections_px must have shape \(\d+, 2\)"):
        adjust_bundle(obs, nominal, start, np.zeros((3, 2)))
    with pytest.raises(InputError, match="bead_id not in the nominal"):
        adjust_bundle(obs, (mono.ids[1:], mono.nominal_mm[1:]), start)
    with pytest.raises(InputError, match="exposure not in initial.exposure"):
        adjust_bundle(
            obs, nominal, Orientation(start.iop_px, start.exposure[1:], start.q_cam_from_obj[1:], start.source_mm[1:])
        )
    with pytest.raises(InputError, match="system"):
        adjust_bundle(
            obs,
            nominal,
            Orientation(np.tile(start.iop_px, (2, 1)), start.exposure, start.q_cam_from_obj, start.source_mm),
        )
    with pytest.raises(InputError, match="nu must be > 0"):
        SolverOptions(nu=0)
    with pytest.raises(InputError, match="key 'loss': unknown"):
        params_from_dict(SolverOptions, {"nu": 4, "loss": "cauchy"})  # config tables become Params in the pipeline
    with pytest.raises(InputError, match="schur"):
        SolverOptions(schur="cameras")
    with pytest.raises(InputError, match="must be an Observations"):
        adjust_bundle(obs.xy_px, nominal, start)


def test_reference_system_with_a_relative_orientation_is_refused(biplanar):
    """System 0 is the reference frame (its observations skip the ROP): a rotated or shifted one is an input error."""
    i = biplanar.initial
    for rop_q, rop_t in (([np.cos(0.05), np.sin(0.05), 0, 0], [0, 0, 0]), ([1, 0, 0, 0], [5.0, 0, 0])):
        q, t = i.rop_q.copy(), i.rop_source_mm.copy()
        q[0], t[0] = rop_q, rop_t
        start = Orientation(i.iop_px, i.exposure, i.q_cam_from_obj, i.source_mm, q, t, i.system_names)
        with pytest.raises(InputError, match=r"rop_q\[0\] must be the identity"):
            adjust_bundle(biplanar.observations, (biplanar.ids, biplanar.nominal_mm), start)


def test_empty_and_too_few_exposures(mono):
    obs = mono.observations
    nominal = (mono.ids, mono.nominal_mm)
    empty = Observations(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros((0, 2)), np.zeros((0, 3)))
    with pytest.raises(InputError, match="min_exposures = 3"):
        adjust_bundle(empty, nominal, mono.initial)
    keep = obs.exposure < 2
    two = Observations(obs.system[keep], obs.exposure[keep], obs.bead_id[keep], obs.xy_px[keep], obs.sigma_px[keep])
    with pytest.raises(InputError, match="at least min_exposures = 3 frames.*got 2"):
        adjust_bundle(two, nominal, mono.initial)


def test_all_exposures_from_one_pose(mono):
    """Five frames from the same pose: no bead's depth is determined -> a clear EstimationError."""
    obs = mono.observations
    keep = obs.exposure == 0
    n = int(keep.sum())
    rng = np.random.default_rng(0)
    same = Observations(
        np.zeros(5 * n),
        np.repeat(np.arange(5), n),
        np.tile(obs.bead_id[keep], 5),
        np.tile(obs.xy_px[keep], (5, 1)) + rng.normal(0, NOISE_PX, (5 * n, 2)),
        np.tile(obs.sigma_px[keep], (5, 1)),
    )
    start = Orientation(
        mono.initial.iop_px,
        np.arange(5),
        np.tile(mono.initial.q_cam_from_obj[0], (5, 1)),
        np.tile(mono.initial.source_mm[0], (5, 1)),
    )
    with pytest.raises(EstimationError, match="one pose"):
        adjust_bundle(same, (mono.ids, mono.nominal_mm), start)


def test_bead_seen_once_is_dropped_with_message(mono, caplog):
    obs = mono.observations
    lone = mono.ids[5]
    first = np.flatnonzero(obs.bead_id == lone)[0]
    keep = (obs.bead_id != lone) | (np.arange(len(obs)) == first)
    sub = Observations(obs.system[keep], obs.exposure[keep], obs.bead_id[keep], obs.xy_px[keep], obs.sigma_px[keep])
    with caplog.at_level(logging.DEBUG, logger="fluorocal.stages.adjust"):
        res = adjust_bundle(
            sub,
            Phantom(mono.ids, mono.nominal_mm, np.full(len(mono.ids), np.nan), np.full(len(mono.ids), "")),
            mono.initial,
        )
    assert "dropping 1 observation(s) of 1 bead(s)" in caplog.text
    i_lone = int(np.flatnonzero(sub.bead_id == lone)[0])
    assert not res.used[i_lone] and not res.inlier[i_lone] and res.weight[i_lone] == 0
    assert lone not in res.bead_id and len(res.bead_id) == len(mono.ids) - 1
    assert res.usable and np.all(np.isfinite(res.residual_px))


def test_unusable_solution_logs_its_own_reason(mono, caplog):
    """A solve stopped at its iteration cap is not usable for that reason, not for its inliers."""
    with caplog.at_level(logging.DEBUG, logger="fluorocal.stages.adjust"):
        res = _solve(mono, solver=SolverOptions(max_iterations=1))
    assert not res.usable and not res.converged and res.inlier[res.used].mean() >= SolverOptions().min_inlier_fraction
    assert "not usable: not converged" in caplog.text and "% inliers" not in caplog.text.split("not usable")[1]


def _two_rays_one_gross(mono, bead_at: int, shift_px) -> tuple[Observations, int, np.ndarray]:
    """``mono``'s observations with bead ``mono.ids[bead_at]`` seen in two epochs only, the second ray moved."""
    obs = mono.observations
    bead = mono.ids[bead_at]
    rows = np.flatnonzero(obs.bead_id == bead)
    keep = (obs.bead_id != bead) | np.isin(np.arange(len(obs)), rows[:2])
    xy = obs.xy_px.copy()
    xy[rows[1]] += shift_px
    sub = Observations(obs.system[keep], obs.exposure[keep], obs.bead_id[keep], xy[keep], obs.sigma_px[keep])
    return sub, bead, np.flatnonzero(sub.bead_id == bead)


@pytest.mark.parametrize("bead_at", [5, 60, 150])
def test_bead_left_with_one_inlier_ray_is_dropped(mono, mono_result, bead_at, caplog):
    """Two rays, one a gross error: the t-fit puts the point on the good ray wherever the bad one pulls it.

    Its depth (and the covariance) is then undetermined, as if the bead were seen
    once; the adjustment must drop it and solve again, not return a point far off
    or fail on a singular covariance (found by benchmarks/robust.py: a swapped
    label on a bead seen twice put it 270 mm off and stopped the learning loop).
    """
    sub, bead, rows = _two_rays_one_gross(mono, bead_at, np.array([9.0, -12.0]))
    with caplog.at_level(logging.DEBUG, logger="fluorocal.stages.adjust"):
        res = adjust_bundle(sub, (mono.ids, mono.nominal_mm), mono.initial)
    # every bead reported is where it truly is: the clean solve's worst is 0.016 mm (measured here too), the sliding
    # point's 4-5 mm
    truth = mono.xyz_true_mm[np.searchsorted(mono.ids, res.bead_id)]
    assert aligned_error_mm(res.xyz_mm, truth).max() < 0.03
    assert bead not in res.bead_id and not res.used[rows].any() and res.used.sum() == len(sub) - 2
    assert "1 bead(s) left with inliers in fewer than 2 epochs" in caplog.text
    assert res.usable and np.all(np.isfinite(res.xyz_std_mm)) and np.all(np.isfinite(res.iop_std_px))
    # the rest is the clean solve less one bead's two rays: far within the IOP's standard deviations
    assert np.all(np.abs(res.iop_px - mono_result.iop_px) <= 0.5 * mono_result.iop_std_px)


def test_bead_with_two_good_rays_is_kept(mono, caplog):
    """The same bead with both rays good stays: only a bead its inliers no longer determine is dropped."""
    sub, bead, rows = _two_rays_one_gross(mono, 5, np.zeros(2))
    with caplog.at_level(logging.DEBUG, logger="fluorocal.stages.adjust"):
        res = adjust_bundle(sub, (mono.ids, mono.nominal_mm), mono.initial)
    assert "left with inliers" not in caplog.text
    assert bead in res.bead_id and res.used[rows].all() and res.inlier[rows].all()


def test_points_behind_the_source_are_rejected(mono):
    start = mono.initial
    # sources mirrored through the phantom's centre: every bead now lies behind its source
    flipped = Orientation(start.iop_px, start.exposure, start.q_cam_from_obj, -start.source_mm)
    with pytest.raises(EstimationError, match="behind the X-ray source"):
        adjust_bundle(
            mono.observations, (mono.ids, mono.nominal_mm), flipped, selection=DataSelection(min_ray_angle_deg=0.0)
        )


def test_estimate_nu_on_heavy_tails():
    """Student-t (ν = 3) noise: the estimated ν is small; Gaussian noise: it is large."""
    syn = make_problem(n_beads=80, n_exposures=8, seed=8)
    rng = np.random.default_rng(3)
    n = len(syn.ideal_px)
    t_noise = NOISE_PX * rng.standard_normal((n, 2)) / np.sqrt(rng.chisquare(3, n) / 3)[:, None]
    heavy = adjust_bundle(
        with_xy(syn.observations, syn.ideal_px + t_noise),
        (syn.ids, syn.nominal_mm),
        syn.initial,
        solver=SolverOptions(estimate_nu=True),
    )
    light = _solve(syn, solver=SolverOptions(estimate_nu=True))
    assert 1.5 < heavy.nu < 6
    assert light.nu > 20


# --------------------------------------------------------------------------- grid plates


def _plate_problem(n_frames=4, seed=0):
    """A 30 x 30 square grid plate (5 mm pitch) seen under 4 perspective homographies, 0.05 px noise."""
    rng = np.random.default_rng(seed)
    g = np.arange(-15, 15) * 5.0
    X, Y = np.meshgrid(g, g)
    xyz = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    ids = np.arange(len(xyz))
    rows, Hs = [], []
    for _ in range(n_frames):
        H = np.array([[6.0, 0.3, 512], [-0.2, 6.1, 500], [1e-4, -2e-4, 1.0]]) + rng.normal(
            0, [[0.05, 0.05, 5], [0.05, 0.05, 5], [5e-5, 5e-5, 0]]
        )
        p = np.c_[xyz[:, :2], np.ones(len(xyz))] @ H.T
        rows.append(p[:, :2] / p[:, 2:])
        Hs.append(H / H[2, 2])
    ideal = np.concatenate(rows)
    n = len(ideal)
    obs = Observations(
        np.zeros(n),
        np.repeat(np.arange(n_frames), len(xyz)),
        np.tile(ids, n_frames),
        ideal + rng.normal(0, NOISE_PX, (n, 2)),
        np.tile([NOISE_PX, NOISE_PX, 0.0], (n, 1)),
    )
    return obs, (ids, xyz), np.array(Hs), ideal


def test_plate_homographies_recover_truth_and_flag_outliers():
    from fluorocal.stages.adjust import adjust_plate

    obs, nominal, H_true, ideal = _plate_problem()
    rng = np.random.default_rng(1)
    xy = obs.xy_px.copy()
    bad = rng.choice(len(xy), len(xy) // 20, replace=False)
    xy[bad] += rng.uniform(5, 50, (len(bad), 2)) * rng.choice([-1, 1], (len(bad), 2))
    res = adjust_plate(with_xy(obs, xy), nominal)
    assert res.usable and res.homography.shape == (4, 3, 3)
    np.testing.assert_allclose(res.homography, H_true, rtol=1e-3, atol=1e-6)
    assert (~res.inlier[bad]).mean() >= 0.99
    clean = np.setdiff1d(np.arange(len(xy)), bad)
    assert rms(res.residual_px[clean]) == pytest.approx(NOISE_PX, rel=0.007)  # measured 0.04982 px
    assert res.dof == 2 * len(xy) - 8 * 4
    assert res.redundancy.sum() == pytest.approx(res.dof, rel=1e-9)
    assert res.sigma0 == pytest.approx(1.0, rel=0.0025)  # measured 0.99867
    # Δ enters as ideal = measured - Δ: shifting observations and corrections together changes nothing
    shifted = adjust_plate(with_xy(obs, xy + 3.0), nominal, np.full((len(xy), 2), 3.0))
    np.testing.assert_allclose(shifted.homography, res.homography, rtol=1e-9, atol=1e-12)


def test_plate_errors():
    from fluorocal.stages.adjust import adjust_plate

    obs, nominal, _, _ = _plate_problem(n_frames=1)
    with pytest.raises(ShapeError, match="corrections_px"):
        adjust_plate(obs, nominal, np.zeros((2, 2)))
    few = Observations(obs.system[:3], obs.exposure[:3], obs.bead_id[:3], obs.xy_px[:3], obs.sigma_px[:3])
    with pytest.raises(InputError, match="no frame has >= 6 observations"):
        adjust_plate(few, nominal)


def test_warm_start_reaches_the_same_solution_faster(mono, mono_result):
    """The learning loop restarts from the previous solution: same optimum, fewer iterations."""
    res = adjust_bundle(
        mono.observations,
        (mono.ids, mono.nominal_mm),
        mono_result.orientation,
        start_points=(mono_result.bead_id, mono_result.xyz_mm),
    )
    assert res.iterations < mono_result.iterations
    np.testing.assert_allclose(res.xyz_mm, mono_result.xyz_mm, atol=0.05 * mono_result.xyz_std_mm.min())
    np.testing.assert_allclose(res.iop_px, mono_result.iop_px, atol=0.05 * mono_result.iop_std_px.min())


def test_skipping_the_covariance_keeps_the_estimate(mono, mono_result):
    # the learning loop's intermediate solves skip the dense inverse: same estimate, mean redundancy
    fast = _solve(mono, compute_covariance=False)
    np.testing.assert_allclose(fast.xyz_mm, mono_result.xyz_mm, atol=1e-9)
    np.testing.assert_allclose(fast.iop_px, mono_result.iop_px, atol=1e-9)
    assert not fast.xyz_std_mm.any() and not fast.iop_std_px.any()
    red = fast.redundancy[fast.used]
    np.testing.assert_allclose(red, fast.dof / (2 * fast.used.sum()))
    np.testing.assert_allclose(red.mean(), mono_result.redundancy[mono_result.used].mean(), rtol=1e-9)
    assert abs(fast.sigma0 / mono_result.sigma0 - 1) < 0.05
    np.testing.assert_array_equal(fast.inlier, mono_result.inlier)


# --------------------------------------------------------------------------- additional parameters: off by default


def test_without_additional_parameters_they_are_reported_zero(mono_result):
    assert mono_result.additional_parameters == "none"
    assert mono_result.ap_px.shape == mono_result.ap_std_px.shape == (1, 7) and not mono_result.ap_px.any()
    with pytest.raises(InputError, match="additional_parameters must be 'none' or 'polynomial'"):
        FreeParameters(additional_parameters="radial")
    with pytest.raises(InputError, match=r"fixed_additional_parameters must name some of k1, k2, .*got \['k4'\]"):
        FreeParameters(fixed_additional_parameters=["k1", "k4"])
