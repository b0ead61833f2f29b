"""Tests of stages/learn/ and stages/field.py: the kNN regression, its cross-validation, the gridded field, its gauge.

The loop that alternates the field with the adjustment: ``test_learn_loop.py``.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from fluorocal.config import params_from_dict
from fluorocal.stages.errors import InputError, ShapeError
from fluorocal.stages.learn import (
    CorrectionField,
    KnnModel,
    LearnParams,
    PointwiseField,
    cross_validate_k,
    cross_validate_smoothness,
    fit_grid_field,
    fit_knn_field,
    grid_nodes,
)
from hypothesis import given, settings
from hypothesis import strategies as st

W, H = 256, 192


def smooth_field(xy):
    """A radial + sigmoid-like field of about 1.5 px, gradient well below 1 (no folding)."""
    x = (xy[:, 0] - W / 2) / (W / 2)
    y = (xy[:, 1] - H / 2) / (H / 2)
    r2 = x * x + y * y
    return np.column_stack([1.2 * x * r2 + 0.3 * np.sin(2.5 * y), 1.2 * y * r2 - 0.2 * np.cos(2 * x)])


def sample(rng, n, sigma_px, field=smooth_field):
    xy = rng.uniform(-0.5, [W - 0.5, H - 0.5], (n, 2))
    return xy, field(xy) + rng.normal(0, sigma_px, (n, 2)), np.full((n, 2), sigma_px**2)


# ---------------------------------------------------------------------------------------------
# shapes, errors, degenerate input
# ---------------------------------------------------------------------------------------------


def test_grid_nodes_cover_image_with_at_most_spacing():
    xn, yn = grid_nodes(W, H, 16.0)
    assert xn[0] == -0.5 and xn[-1] == W - 0.5 and yn[0] == -0.5 and yn[-1] == H - 0.5
    assert np.diff(xn).max() <= 16.0 + 1e-12 and np.diff(yn).max() <= 16.0 + 1e-12


def test_empty_queries_keep_shape():
    f = CorrectionField.constant(W, H, (0.1, 0.2))
    assert f.correction_at(np.empty((0, 2))).shape == (0, 2)
    assert f.undistort_points(np.empty((0, 2))).shape == (0, 2)
    assert f.distort_points(np.empty((0, 2))).shape == (0, 2)
    model = KnnModel(np.zeros((3, 2)), np.ones((3, 2)), np.ones((3, 2)), 2)
    assert model.correction_at(np.empty((0, 2))).shape == (0, 2)


def test_errors_name_the_argument():
    rng = np.random.default_rng(0)
    xy, r, var = sample(rng, 50, 0.1)
    with pytest.raises(ShapeError, match="residuals_px"):
        fit_knn_field(xy, r[:, :1], var, image_size=(W, H))
    with pytest.raises(InputError, match="residual_var_px2"):
        fit_knn_field(xy, r, -var, image_size=(W, H))
    with pytest.raises(ShapeError, match="xy_px"):
        CorrectionField.constant(W, H).correction_at(np.zeros((4, 3)))
    with pytest.raises(InputError, match="n_folds"):
        LearnParams(n_folds=1)
    with pytest.raises(InputError, match="acceleration"):
        LearnParams(acceleration="magic")
    with pytest.raises(InputError, match="preset"):
        LearnParams(preset="fastest")
    with pytest.raises(InputError, match="key 'k': unknown"):
        params_from_dict(LearnParams, {"k": 3})  # config tables become Params in the pipeline


def test_tiny_training_set_clips_k_grid():
    # 12 points, 10 folds: training folds hold 10 points, so k <= 10 only
    rng = np.random.default_rng(1)
    xy, r, var = sample(rng, 12, 0.1)
    cv = cross_validate_k(xy, r, var, k_grid=(1, 5, 10, 50), n_folds=10, seed=0)
    assert cv.k_grid.tolist() == [1, 5, 10]


# ---------------------------------------------------------------------------------------------
# ground truth
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("smooth", [True, False])
def test_constant_field_recovered_exactly(smooth):
    # noise-free constant residuals: any weighted mean of them is the constant (to rounding)
    rng = np.random.default_rng(2)
    xy = rng.uniform(0, [W, H], (500, 2))
    r = np.tile([0.7, -0.4], (500, 1))
    field, cv = fit_knn_field(xy, r, np.full(500, 0.01), smooth=smooth, image_size=(W, H))
    q = rng.uniform(0, [W, H], (100, 2))
    np.testing.assert_allclose(field.correction_at(q), np.tile([0.7, -0.4], (100, 1)), atol=1e-12)


def test_smooth_field_recovered_within_noise_bound():
    # 20000 points over 256x192 px: the field varies little over a kNN neighbourhood, so
    # the error is dominated by the averaged noise sigma/sqrt(k), plus the interpolation and
    # neighbourhood bias that the CV trades against it. Measured 0.0174 px = 0.98 sigma/sqrt(k), k = 32
    # (seed 3); bound 1.7 sigma/sqrt(k) RMS, interior only.
    rng = np.random.default_rng(3)
    sigma = 0.1
    xy, r, var = sample(rng, 20000, sigma)
    field, cv = fit_knn_field(xy, r, var, image_size=(W, H))
    q = rng.uniform([16, 16], [W - 16, H - 16], (4000, 2))
    rms = np.sqrt(np.mean((field.correction_at(q) - smooth_field(q)) ** 2))
    assert rms < 1.7 * sigma / np.sqrt(cv.k), (rms, cv.k)
    # the out-of-fold RMS is the noise (the model's own error is small beside it)
    assert sigma <= cv.cv_rms_px < 1.1 * sigma
    # the per-node uncertainty is of the size of the actual error (measured 1.05x; within a factor 2)
    interior = field.sigma_px[2:-2, 2:-2]
    assert rms / 2 < np.median(interior) < 2 * rms


def test_cv_picks_larger_k_for_noisier_data():
    rng = np.random.default_rng(4)
    ks = []
    for sigma in (0.01, 0.05, 0.2, 0.8):
        xy, r, var = sample(rng, 8000, sigma)
        ks.append(cross_validate_k(xy, r, var, k_grid=LearnParams().k_grid, n_folds=10, seed=0).k)
    assert ks == sorted(ks) and ks[-1] > 4 * ks[0], ks


def test_cv_never_picks_k1_on_noise():
    # pure noise: the best predictor is the global mean, i.e. the largest k
    rng = np.random.default_rng(5)
    xy, r, var = sample(rng, 3000, 0.3, field=lambda xy: np.zeros_like(xy))
    cv = cross_validate_k(xy, r, var, k_grid=(1, 3, 10, 30, 100, 300), n_folds=10, seed=0)
    assert cv.k == 300
    # the in-sample fit with k=1 would have zero cost; out of fold it costs twice the noise
    assert cv.cv_cost[0] > 3.5  # ≈ 2 components x (1 + 1)


def test_equation3_weighting_a_high_variance_point_barely_moves_the_field():
    # a 10 px "residual" with variance 1e4 x the others beside 9 unit-weight zeros:
    # inverse-variance weighted mean = 10 / (1 + 9e4) px
    xy = np.array([[50.0, 50.0]] + [[50.0 + dx, 50.0 + dy] for dx in (-1, 0, 1) for dy in (-1, 0, 1)])
    r = np.zeros((10, 2))
    r[0] = 10.0
    var = np.ones((10, 2))
    var[0] = 1e4
    model = KnnModel(xy, r, 1.0 / var, 10)
    g = model.correction_at(np.array([[50.0, 50.0]]))
    np.testing.assert_allclose(g, [[10.0 / (1 + 9e4)] * 2], rtol=1e-9)
    unweighted = KnnModel(xy, r, np.ones((10, 2)), 10).correction_at(np.array([[50.0, 50.0]]))
    np.testing.assert_allclose(unweighted, [[1.0, 1.0]])


def test_mask_false_far_from_data():
    rng = np.random.default_rng(6)
    xy = rng.uniform([0, 0], [W / 2, H], (2000, 2))  # data only in the left half
    r = np.zeros((2000, 2))
    field, _ = fit_knn_field(xy, r, np.ones(2000), image_size=(W, H))
    xn = field.x_nodes_px
    assert field.support[:, xn < W / 2 - 8].all()
    assert not field.support[:, xn > W / 2 + 2 * 16 + 1].any()
    assert field.support_at(np.array([[10.0, 10.0], [W - 10.0, 10.0]])).tolist() == [True, False]


def test_gridded_least_squares_recovers_the_field_without_kNN_blur():
    # 20000 points, 17 x 13 nodes: ~90 observations per node, so the unsmoothed node noise is about
    # sigma / sqrt(90 / 4) = 0.021 px (each point spreads over 4 nodes); the prior smooths below it:
    # measured 0.0082 px (seed 9), 0.39x that noise and 0.45x the kNN field's error; bound 0.7x
    # of each (interior only)
    rng = np.random.default_rng(9)
    sigma = 0.1
    xy, r, var = sample(rng, 20000, sigma)
    cv = cross_validate_smoothness(xy, r, var, image_size=(W, H))
    field = fit_grid_field(xy, r, var, image_size=(W, H), tau_px=cv.tau_px, cv_rms_px=cv.cv_rms_px)
    q = rng.uniform([16, 16], [W - 16, H - 16], (4000, 2))
    rms = np.sqrt(np.mean((field.correction_at(q) - smooth_field(q)) ** 2))
    assert rms < 0.7 * sigma / np.sqrt(20000 / field.delta_px[..., 0].size / 4), rms
    knn, _ = fit_knn_field(xy, r, var, image_size=(W, H))
    assert rms < 0.7 * np.sqrt(np.mean((knn.correction_at(q) - smooth_field(q)) ** 2))


@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_difference_prior_null_space_is_the_polynomials_below_its_order(order):
    from fluorocal.stages.learn.grid import difference_operator

    ny, nx = 9, 11
    D = difference_operator(ny, nx, order)
    yy, xx = np.mgrid[0:ny, 0:nx].astype(float)
    # every monomial of degree < order is free (exact up to rounding of the integer stencils)
    for i in range(order):
        for j in range(order - i):
            assert np.abs(D @ (xx**i * yy**j).ravel()).max() < 1e-9 * max(nx, ny) ** (i + j)
    # degree == order is penalised: its order-th derivative is a nonzero constant
    assert np.abs(D @ (xx**order).ravel()).max() >= 1.0


@pytest.mark.parametrize("n_side", [30, 101])
def test_factor_spd_solves_the_grid_normal_matrix(n_side):
    # both of factor_spd's paths (banded Cholesky up to BANDED_MAX_NODES nodes, sparse LU beyond) against a direct
    # sparse solve of a grid's normal matrix: data at random points plus an order-3 prior
    from fluorocal.stages.field import bilinear_design
    from fluorocal.stages.learn.grid import BANDED_MAX_NODES, difference_operator, factor_spd
    from scipy.sparse import diags
    from scipy.sparse.linalg import spsolve

    rng = np.random.default_rng(13)
    nodes = np.arange(n_side) * 16.0 - 0.5
    A = bilinear_design(nodes, nodes, rng.uniform(0, nodes[-1], (4 * n_side**2, 2)))
    D = difference_operator(n_side, n_side, 3)
    M = (A.T @ A + D.T @ D / 0.1**2 + diags(np.full(n_side**2, 1e-6))).tocsr()
    assert (M.shape[0] > BANDED_MAX_NODES) == (n_side == 101)
    b = rng.normal(size=(n_side**2, 2))
    exact = spsolve(M.tocsc(), b)
    # two factorisations of a matrix conditioned ~1e8 here agree to ~1e-8 of the solution's scale
    np.testing.assert_allclose(factor_spd(M).solve(b), exact, atol=1e-7 * np.abs(exact).max())
    np.testing.assert_allclose(factor_spd(M).solve(b[:, 0]), exact[:, 0], atol=1e-7 * np.abs(exact).max())


@pytest.mark.parametrize("n_side", [30, 101])
def test_factor_sum_is_the_factor_of_the_sparse_sum(n_side):
    # the data part and the prior laid out in band form apart and summed there are the sparse sum's matrix to the
    # last bit (each entry the same additions in the same order), so the banded factors are identical; beyond
    # BANDED_MAX_NODES the terms are summed sparse, and the solve is checked against a direct one
    from fluorocal.stages.field import bilinear_design
    from fluorocal.stages.learn.grid import difference_operator, factor_spd, factor_sum, prior_term
    from scipy.sparse import diags
    from scipy.sparse.linalg import spsolve

    rng = np.random.default_rng(17)
    nodes = np.arange(n_side) * 16.0 - 0.5
    A = bilinear_design(nodes, nodes, rng.uniform(0, nodes[-1], (4 * n_side**2, 2)))
    data = (A.T.multiply(rng.uniform(0.5, 2.0, A.shape[0])) @ A).tocsr()
    D = difference_operator(n_side, n_side, 4)
    reg = (D.T @ D).tocsr() / 0.3**2
    ridge = 1e-6
    summed = data + reg + diags(np.full(n_side**2, ridge))
    b = rng.normal(size=n_side**2)
    split = factor_sum((data, prior_term(reg, n_side**2)), ridge)
    if n_side == 30:
        np.testing.assert_array_equal(split.factor, factor_spd(summed).factor)
    exact = spsolve(summed.tocsc(), b)
    np.testing.assert_allclose(split.solve(b), exact, atol=1e-7 * np.abs(exact).max())


def test_factor_sum_drops_a_diagonal_its_terms_cancel():
    # diag(3) + offdiag(1) and diag(1) - offdiag(1) sum to 4 I: the cancelled off-diagonal leaves the band, as it
    # leaves a sparse sum's pattern, and the factor is 2 on the diagonal alone
    from fluorocal.stages.learn.grid import factor_sum, lower_band
    from scipy.sparse import diags

    n = 7
    plus = diags([np.ones(n - 1), np.full(n, 3.0), np.ones(n - 1)], [-1, 0, 1])
    minus = diags([-np.ones(n - 1), np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    factor = factor_sum((plus, lower_band(minus)), 0.0)
    np.testing.assert_array_equal(factor.factor, np.full((1, n), 2.0))
    np.testing.assert_allclose(factor.solve(np.arange(n, dtype=float)), np.arange(n) / 4.0, rtol=1e-15)


@pytest.mark.parametrize("order", [1, 2])
def test_factor_sum_leaves_its_band_terms_as_they_were(order):
    # the sum is factored in place, and a cross-validation lays each term out once for every fold and candidate: the
    # terms come out bit for bit as they went in, the data's band the wider (order 1) or the prior's (order 2), and a
    # second factorisation of them is the first's
    from fluorocal.stages.field import bilinear_design
    from fluorocal.stages.learn.grid import factor_sum, lower_band, prior_normal

    rng = np.random.default_rng(3)
    nodes = np.arange(9) * 16.0 - 0.5
    A = bilinear_design(nodes, nodes, rng.uniform(0, nodes[-1], (300, 2)))
    terms = (lower_band((A.T.multiply(rng.uniform(0.5, 2.0, 300)) @ A).tocsr()), lower_band(prior_normal(9, 9, order)))
    before = [t.copy() for t in terms]
    first = factor_sum(terms, 1e-6).factor.copy()
    for t, b in zip(terms, before):
        np.testing.assert_array_equal(t, b)
    np.testing.assert_array_equal(factor_sum(terms, 1e-6).factor, first)


@pytest.mark.parametrize("n_side", [9, 101])  # 101 x 101 nodes: past the band's limit, the sparse matrix itself
def test_scaled_prior_is_the_prior_normal_over_tau_squared(n_side):
    """``D^T D / τ²`` as :func:`factor_sum` takes it, at two τ of one grid (its band laid out once, scaled per τ)."""
    from fluorocal.stages.learn.grid import prior_normal, prior_term, scaled_prior
    from scipy.sparse import issparse

    for order in (1, 2):
        for tau in (0.3, 7.0):
            expected = prior_normal(n_side, n_side, order) / tau**2
            prior, want = scaled_prior(n_side, n_side, order, tau), prior_term(expected, n_side**2)
            assert (prior.reg != expected).nnz == 0
            if issparse(want):
                assert issparse(prior.term) and (prior.term != want).nnz == 0
            else:
                np.testing.assert_array_equal(prior.term, want)


@pytest.mark.parametrize("n_side", [9, 101])
def test_scaled_prior_is_kept_read_only(n_side):
    """The prior is kept and handed to every joint step: a write into it, which would change the next step's, raises."""
    from fluorocal.stages.learn.grid import scaled_prior

    prior = scaled_prior(n_side, n_side, 2, 0.3)
    assert scaled_prior(n_side, n_side, 2, 0.3) is prior and scaled_prior(n_side, n_side, 2, 0.31) is not prior
    term = prior.term.data if prior.term is prior.reg else prior.term
    for a in (prior.reg.data, prior.reg.indices, prior.reg.indptr, term):
        with pytest.raises(ValueError, match="read-only"):
            a[0] += 1


def test_factor_spd_sums_duplicate_entries_and_refuses_a_singular_matrix():
    # a matrix given with an entry split in two (COO duplicates) is their sum; [[2+2, 1], [1, 2]] x = [1, 0]
    from fluorocal.stages.errors import EstimationError
    from fluorocal.stages.learn.grid import factor_spd
    from scipy.sparse import coo_matrix

    M = coo_matrix(([2.0, 2.0, 1.0, 1.0, 2.0], ([0, 0, 0, 1, 1], [0, 0, 1, 0, 1])), shape=(2, 2)).tocsr()
    np.testing.assert_allclose(factor_spd(M).solve(np.array([1.0, 0.0])), [2 / 7, -1 / 7], rtol=1e-12)
    singular = coo_matrix(([1.0, 1.0, 1.0, 1.0], ([0, 0, 1, 1], [0, 1, 0, 1])), shape=(2, 2)).tocsr()
    with pytest.raises(EstimationError, match="singular"):
        factor_spd(singular)


def test_second_order_prior_is_the_thin_plate_energy():
    from fluorocal.stages.learn.grid import difference_operator

    rng = np.random.default_rng(12)
    ny, nx = 7, 8
    v = rng.normal(size=(ny, nx))
    thin_plate = (
        np.sum(np.diff(v, 2, axis=1) ** 2)
        + np.sum(np.diff(v, 2, axis=0) ** 2)
        + 2 * np.sum(np.diff(np.diff(v, axis=0), axis=1) ** 2)
    )
    D = difference_operator(ny, nx, 2)
    assert np.sum((D @ v.ravel()) ** 2) == pytest.approx(thin_plate, rel=1e-12)


def test_cv_chooses_a_higher_prior_order_for_a_strong_smooth_field():
    """A strong (about 9 px) smooth field, ~9 noisy points per node: a higher prior order smooths harder.

    The thin-plate prior must stay loose not to bias the field's large-scale part, so it
    smooths the noise little; a higher order leaves low-degree polynomials free.

    Bound: the CV's choice among orders 2-4 is at least 15 % closer to the truth (RMS,
    interior) than the CV's best thin-plate fit (about 23 % on this seed); both within
    0.75x the unsmoothed node noise sigma / sqrt(n / n_nodes / 4) = 0.066 px (measured 0.031 px
    thin-plate, 0.024 px order 4).
    """
    rng = np.random.default_rng(11)
    sigma = 0.1

    def strong(p):
        return 6 * smooth_field(p)

    xy, r, var = sample(rng, 2000, sigma, strong)
    q = rng.uniform([16, 16], [W - 16, H - 16], (4000, 2))
    rms = {}
    for orders in [(2,), (2, 3, 4)]:
        cv = cross_validate_smoothness(xy, r, var, image_size=(W, H), orders=orders)
        assert cv.order in orders and cv.order_grid.shape == cv.tau_grid_px.shape == cv.cv_cost.shape
        assert set(cv.order_grid.tolist()) == set(orders)
        field = fit_grid_field(xy, r, var, image_size=(W, H), tau_px=cv.tau_px, cv_rms_px=cv.cv_rms_px, order=cv.order)
        rms[orders] = (cv.order, np.sqrt(np.mean((field.correction_at(q) - strong(q)) ** 2)))
        assert rms[orders][1] < 0.75 * sigma / np.sqrt(len(xy) / field.delta_px[..., 0].size / 4)
    assert rms[(2, 3, 4)][0] > 2
    assert rms[(2, 3, 4)][1] < 0.85 * rms[(2,)][1], rms


def test_cv_neighbour_cache_gives_the_same_table_and_skips_the_queries(monkeypatch):
    from fluorocal.stages.learn import knn as learn

    rng = np.random.default_rng(14)
    xy, r, var = sample(rng, 2000, 0.1)
    plain = cross_validate_k(xy, r, var, k_grid=(1, 4, 16, 64), n_folds=10, seed=0)
    cache = {}
    first = cross_validate_k(xy, r, var, k_grid=(1, 4, 16, 64), n_folds=10, seed=0, neighbour_cache=cache)
    # other residuals (the next iteration), fewer neighbours: served from the cache, no KD-tree
    monkeypatch.setattr(learn, "KDTree", lambda *a, **k: pytest.fail("queried again"))
    r2 = r + rng.normal(0, 0.1, r.shape)
    again = cross_validate_k(xy, r2, var, k_grid=(4, 16), n_folds=10, seed=0, neighbour_cache=cache)
    monkeypatch.undo()
    fresh = cross_validate_k(xy, r2, var, k_grid=(4, 16), n_folds=10, seed=0)
    np.testing.assert_array_equal(first.cv_cost, plain.cv_cost)
    np.testing.assert_allclose(again.cv_cost, fresh.cv_cost, rtol=1e-12)
    # other coordinates invalidate it
    moved = cross_validate_k(xy + 1.0, r2, var, k_grid=(4, 16), n_folds=10, seed=0, neighbour_cache=cache)
    np.testing.assert_allclose(
        moved.cv_cost, cross_validate_k(xy + 1.0, r2, var, k_grid=(4, 16), n_folds=10, seed=0).cv_cost, rtol=1e-12
    )


def test_weighted_neighbour_means_are_the_inverse_variance_means_of_the_first_k():
    from fluorocal.stages.learn.knn import weighted_neighbour_means

    rng = np.random.default_rng(16)
    values, weights = rng.normal(size=(50, 2)), rng.uniform(0.5, 4.0, (50, 2))
    idx = np.array([rng.permutation(50)[:12] for _ in range(7)])
    ks = [1, 3, 4, 9]  # the last below the neighbours given: the rest must not count
    got = weighted_neighbour_means(values, weights, idx, ks)
    for j, k in enumerate(ks):
        w, v = weights[idx[:, :k]], values[idx[:, :k]]
        # sums of a dozen terms in another order: equal to rounding
        np.testing.assert_allclose(got[:, j], np.sum(w * v, axis=1) / np.sum(w, axis=1), rtol=1e-13)


def test_cv_neighbour_pool_serves_other_inliers_with_the_folds_own_neighbours():
    """A later iteration's inliers (some dropped, some back) read their folds' neighbours from the pool's table.

    They must be exactly a fresh KD-tree's of each fold's training points, so the CV table is the same to
    rounding (the sums run over the same neighbours in the same order); a fold of 2 (half the neighbours in the
    test fold) and a large ``k`` make the table fall short for some points, which are queried instead.
    """
    from fluorocal.stages.learn import knn as learn

    rng = np.random.default_rng(15)
    pool, r, var = sample(rng, 3000, 0.1)
    cache = {}
    for n_folds, k_grid in [(10, (1, 4, 16, 64)), (10, (4, 16)), (2, (4, 16, 64))]:
        sel = np.sort(rng.choice(len(pool), 2900, replace=False))
        cached = cross_validate_k(
            pool[sel],
            r[sel],
            var[sel],
            k_grid=k_grid,
            n_folds=n_folds,
            seed=0,
            neighbour_cache=cache,
            neighbour_pool_px=pool,
        )
        fresh = cross_validate_k(pool[sel], r[sel], var[sel], k_grid=k_grid, n_folds=n_folds, seed=0)
        np.testing.assert_allclose(cached.cv_cost, fresh.cv_cost, rtol=1e-12)
        folds = np.array_split(np.random.default_rng(0).permutation(len(sel)), n_folds)
        for test, idx in zip(folds, cache["idx"]):
            train = np.setdiff1d(np.arange(len(sel)), test)
            _, expected = learn.KDTree(pool[sel][train]).query(pool[sel][test], k=max(k_grid))
            np.testing.assert_array_equal(idx, expected)
    assert cache["table"].xy.shape == pool.shape  # built once, over the pool


def test_knn_refit_with_a_given_cv_uses_its_k_without_cross_validating(monkeypatch):
    from fluorocal.stages.learn import knn as learn

    rng = np.random.default_rng(13)
    xy, r, var = sample(rng, 3000, 0.1)
    field, cv = fit_knn_field(xy, r, var, image_size=(W, H))
    monkeypatch.setattr(learn, "cross_validate_k", lambda *a, **k: pytest.fail("cross-validated again"))
    again, cv_again = fit_knn_field(xy, r, var, image_size=(W, H), cv=cv)
    assert cv_again is cv
    np.testing.assert_array_equal(again.delta_px, field.delta_px)
    np.testing.assert_array_equal(again.sigma_px, field.sigma_px)


def test_affine_shape_modes_ignore_similarities_and_see_stretches():
    from fluorocal.stages.geometry import quat_to_matrix
    from fluorocal.stages.learn.network import affine_shape_modes

    rng = np.random.default_rng(12)
    nominal = rng.uniform(-50, 50, (200, 3))
    R = quat_to_matrix(np.array([0.9, 0.1, -0.3, 0.2]))
    moved = 1.02 * nominal @ R.T + [5.0, -3.0, 7.0]
    B, gap = affine_shape_modes(moved, nominal)
    np.testing.assert_allclose(B.T @ B, np.eye(5), atol=1e-12)
    # a similarity is no shape change
    assert np.abs(gap).max() < 1e-9
    # a 0.2 % horizontal stretch is seen: its traceless part (2/3 of it) displaces points by ~0.1 %
    stretched = moved * [1.002, 1.002, 1.0]
    _, gap = affine_shape_modes(stretched, nominal)
    assert np.linalg.norm(gap) > 0.5 * 0.002 * np.linalg.norm(moved[:, :2] - moved[:, :2].mean(0)) / 2


# ---------------------------------------------------------------------------------------------
# properties of the field
# ---------------------------------------------------------------------------------------------


def _bumpy_grid_field():
    xn, yn = grid_nodes(W, H, 16.0)
    xx, yy = np.meshgrid(xn, yn)
    nodes = np.column_stack([xx.ravel(), yy.ravel()])
    delta = smooth_field(nodes).reshape(len(yn), len(xn), 2)
    # a local bump of 0.5 px: the field's gradient stays well below 1
    delta += 0.5 * np.exp(-((xx - 60) ** 2 + (yy - 90) ** 2) / (2 * 20.0**2))[..., None]
    return CorrectionField(xn, yn, delta, np.zeros(xx.shape), np.ones(xx.shape, bool), W, H)


@settings(deadline=None, derandomize=True, max_examples=60)
@given(
    st.lists(
        st.tuples(
            st.floats(-0.5, W - 0.5, allow_nan=False, width=64), st.floats(-0.5, H - 0.5, allow_nan=False, width=64)
        ),
        min_size=1,
        max_size=20,
    )
)
def test_distort_undistort_round_trip(points):
    field = _bumpy_grid_field()
    ideal = np.array(points)
    back = field.undistort_points(field.distort_points(ideal))
    # measured at most 2.8e-14 px over 2e5 random points; bound: the Newton step tolerance, 1e-9 px
    assert np.max(np.abs(back - ideal)) < 1e-9


def test_round_trip_pointwise_field():
    rng = np.random.default_rng(7)
    xy, r, var = sample(rng, 3000, 0.05)
    model, _ = fit_knn_field(xy, r, var, smooth=False, image_size=(W, H))
    field = PointwiseField((model,), W, H)
    ideal = rng.uniform(20, 170, (200, 2))
    # kNN predictions are piecewise constant: the fixed point is exact where it exists, and it exists at every
    # one of these points (measured: at most 1.4e-14 px, half a unit in the last place of 170); judged by the worst
    back = field.undistort_points(field.distort_points(ideal))
    assert np.abs(back - ideal).max() <= 4 * np.spacing(170.0)


def test_identity_field_remap_is_the_pixel_grid():
    field = CorrectionField.constant(W, H)
    map_x, map_y = field.remap_maps()
    assert map_x.dtype == np.float32 and map_x.shape == (H, W)
    yy, xx = np.mgrid[0:H, 0:W]
    np.testing.assert_array_equal(map_x, xx)
    np.testing.assert_array_equal(map_y, yy)
    img = np.random.default_rng(8).uniform(0, 4095, (H, W)).astype(np.float32)
    out = cv2.remap(img, map_x, map_y, interpolation=cv2.INTER_LINEAR)
    np.testing.assert_array_equal(out, img)


def test_remap_maps_are_distort_points_of_pixel_centres():
    field = _bumpy_grid_field()
    map_x, map_y = field.remap_maps(64, 48)
    centres = np.array([[0.0, 0.0], [63.0, 47.0], [20.0, 30.0]])
    src = field.distort_points(centres)
    got = np.column_stack(
        [
            map_x[centres[:, 1].astype(int), centres[:, 0].astype(int)],
            map_y[centres[:, 1].astype(int), centres[:, 0].astype(int)],
        ]
    )
    # float32 storage of values below 64 px: half a unit in the last place, 1.9e-6 (measured 1.6e-6)
    np.testing.assert_allclose(got, src, atol=np.spacing(np.float32(32.0)))


def test_constant_extension_outside_the_grid():
    field = _bumpy_grid_field()
    inside = field.correction_at(np.array([[-0.5, 50.0], [W - 0.5, H - 0.5]]))
    outside = field.correction_at(np.array([[-40.0, 50.0], [W + 30, H + 30]]))
    np.testing.assert_array_equal(inside, outside)


def test_add_accumulates_on_the_same_grid():
    a = CorrectionField.constant(W, H, (0.1, 0.2))
    b = CorrectionField.constant(W, H, (0.3, -0.1))
    np.testing.assert_allclose(a.add(b).correction_at(np.array([[5.0, 5.0]])), [[0.4, 0.1]])
    with pytest.raises(InputError, match="same grid"):
        a.add(CorrectionField.constant(W, H, spacing_px=32.0))


# ---------------------------------------------------------------------------------------------
# beyond the paper: the field's gauge
# ---------------------------------------------------------------------------------------------


def test_gauge_removes_what_the_orientation_reproduces_and_keeps_the_rest():
    from fluorocal.stages.learn.gauge import gauge_basis, gauge_fixed

    rng = np.random.default_rng(4)
    iop = (130.0, 90.0, 900.0)
    xy = rng.uniform(0, [W, H], (600, 2))
    # a principal-point shift, a scale, an image rotation and a keystone: all orientation
    coef = np.array([0.002, -0.001, 0.0015, 0.4, -0.3, 0.01])
    nodes = CorrectionField.constant(W, H).nodes_px
    gauge = (gauge_basis(nodes, iop, True) @ coef).reshape(-1, 2)
    field = CorrectionField.constant(W, H).with_delta(gauge.reshape(CorrectionField.constant(W, H).delta_px.shape))
    fixed = gauge_fixed(field, xy, iop, with_iop=True)
    assert np.abs(fixed.correction_at(xy)).max() < 8e-5 * np.abs(field.correction_at(xy)).max()  # measured 4.4e-5
    # with the IOP held, a scaling (a principal distance error) stays in the field: no rotation of
    # the poses reproduces it (a shift does: a common pan or tilt of every pose)
    scale = field.with_delta((0.004 * (nodes - iop[:2])).reshape(field.delta_px.shape))
    kept = gauge_fixed(scale, xy, iop, with_iop=False).correction_at(xy)
    # (only its mean over the observations goes, a shift: they are not centred on the principal point;
    # measured 0.079)
    assert np.sqrt(np.mean((kept - scale.correction_at(xy)) ** 2)) < 0.1 * np.sqrt(
        np.mean(scale.correction_at(xy) ** 2)
    )
    # a radial field loses only its projection: applying the gauge twice changes (almost) nothing more
    radial = field.with_delta(smooth_field(nodes).reshape(field.delta_px.shape))
    once = gauge_fixed(radial, xy, iop, with_iop=True)
    twice = gauge_fixed(once, xy, iop, with_iop=True)
    # bilinear vs quadratic basis: measured 3.8e-4 px
    np.testing.assert_allclose(twice.delta_px, once.delta_px, atol=7e-4)
    assert np.sqrt(np.mean(once.correction_at(xy) ** 2)) > 0.3  # measured 0.316
