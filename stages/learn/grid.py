"""The gridded least-squares field (beyond the paper): node values fitted to the residuals under a smoothness prior.

:func:`fit_grid_field` minimises equation 3 with the bilinear grid field
itself as the regression function, plus a difference prior on the node
values (:func:`difference_operator`); :func:`cross_validate_smoothness`
chooses the prior's order and weight by shuffled K-fold cross-validation.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from fluorocal.stages.artifacts import freeze
from fluorocal.stages.errors import EstimationError
from fluorocal.stages.field import CorrectionField, bilinear_design
from fluorocal.stages.learn.nodes import DEFAULT_GRID, GridSpec, check_training
from fluorocal.stages.learn.nogil import cholesky_band, solve_band
from fluorocal.stages.learn.robust import capped_cost

#: forward-difference stencils of the smoothness prior's orders
DIFFERENCE_STENCILS = {1: (-1.0, 1.0), 2: (1.0, -2.0, 1.0), 3: (-1.0, 3.0, -3.0, 1.0), 4: (1.0, -4.0, 6.0, -4.0, 1.0)}

#: candidate smoothness priors of the cross-validation, px
DEFAULT_TAU_GRID_PX = (0.03, 0.1, 0.3, 1.0, 3.0)


def difference_operator(n_y: int, n_x: int, order: int):
    """Sparse ``D`` whose ``|D v|²`` is the discrete ``order``-th order energy of node values ``v``.

    The rows are the mixed differences ``Δx^(m-a) Δy^a v`` weighted by
    ``sqrt(C(m, a))``, ``a = 0 .. m`` (row-major ``v``, x fastest): for
    ``m = 2`` the thin-plate energy (second differences along x and y and the
    √2-weighted cross difference). Its null space is the polynomials of total
    degree below ``m``.
    """
    from math import comb

    from scipy.sparse import diags, identity, kron, vstack

    def diff(n, k):
        if k == 0:
            return identity(n)
        c = DIFFERENCE_STENCILS[k]
        return diags(list(c), list(range(k + 1)), shape=(max(n - k, 0), n))

    return vstack(
        [np.sqrt(comb(order, a)) * kron(diff(n_y, a), diff(n_x, order - a)) for a in range(order + 1)]
    ).tocsr()


#: largest matrix (nodes) factored in band form by :func:`factor_sum`: LAPACK's banded Cholesky factors the
#: default 65 x 65 grid (1024 px at 16 px) 2-3x faster than SuperLU and solves 1.5x faster; at 129 x 129 nodes its
#: solves (work ``n x bandwidth``) fell behind SuperLU's, which the conjugate gradients call far more often
BANDED_MAX_NODES = 10_000


@dataclass(frozen=True)
class BandedCholesky:
    """``M = L L^T`` of a symmetric positive definite matrix in LAPACK's lower band storage; ``solve`` as SuperLU's."""

    factor: np.ndarray  # shape (bandwidth + 1, n), Fortran order

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return solve_band(self.factor, rhs)


def factor_spd(M):
    """Factor a sparse symmetric positive definite matrix: an object whose ``solve(rhs)`` gives ``M^-1 rhs``.

    Up to ``BANDED_MAX_NODES`` a banded Cholesky in the matrix's own (row-major node) order, whose band is
    the prior's order in node rows; beyond, a sparse LU with a symmetric fill-reducing ordering and no
    pivoting, several times faster than SuperLU's default (COLAMD, partial pivoting) on the grid's normal
    matrices, whose band widens with the prior's order; an SPD matrix needs no pivoting for stability.
    Raises :class:`~fluorocal.stages.errors.EstimationError` when ``M`` is singular or (banded) not positive
    definite.
    """
    return factor_sum((M,), 0.0)


def factor_sum(terms, ridge: float):
    """:func:`factor_spd` of ``terms[0] + terms[1] + ... + ridge I``, each term sparse or its :func:`lower_band`.

    In band form each term is laid out once (a cross-validation's data part serves every candidate prior, a
    prior every fold) and the sum taken entry by entry in the sparse sum's order: the same matrix, to the
    last bit, without building the sparse sum and laying it out at every factorisation. The sum is laid out
    in Fortran order, as LAPACK reads it, and factored in place.
    """
    from scipy.sparse import diags, issparse

    n = terms[0].shape[-1]
    if n > BANDED_MAX_NODES:
        return _sparse_factor(sum(terms[1:], terms[0]) + diags(np.full(n, ridge)))
    bands = [lower_band(t) if issparse(t) else t for t in terms]
    widest = max(range(len(bands)), key=lambda i: len(bands[i]))
    if len(bands) <= 2:
        # a copy of the wider band plus the other: a pass less than zeros plus each, the same sum (two terms
        # add alike in either order)
        ab = np.array(bands[widest], order="F")
        bands = bands[:widest] + bands[widest + 1 :]
    else:
        ab = np.zeros((len(bands[widest]), n), order="F")
    for b in bands:
        ab[: len(b)] += b
    ab[0] += ridge
    # a lower diagonal the terms cancel exactly is out of the band, as out of a sparse sum's pattern
    width = len(ab)
    while width > 1 and not ab[width - 1].any():
        width -= 1
    return _banded_factor(ab if width == len(ab) else np.asfortranarray(ab[:width]))


def lower_band(M) -> np.ndarray:
    """A sparse symmetric ``M``'s lower triangle in LAPACK's lower band storage ``(bandwidth + 1, n)``.

    The lower storage, not the upper: LAPACK's banded Cholesky (``pbtrf``) factors it a quarter faster on the
    grid's matrices (measured, 65 x 65 nodes, orders 2 to 4).
    """
    # duplicates summed in CSR (the band below takes one entry per position): it sorts each row's few entries,
    # where COO's would sort them all (a sparse product's rows are unsorted): several times faster
    csr = M.tocsr(copy=True)
    csr.sum_duplicates()
    coo = csr.tocoo()
    lower = (coo.row >= coo.col) & (coo.data != 0)
    row, col = coo.row[lower], coo.col[lower]
    band = int(np.max(row - col, initial=0))
    ab = np.zeros((band + 1, M.shape[0]), order="F")  # as factor_sum lays out the sum: its additions contiguous
    ab[row - col, col] = coo.data[lower]
    return ab


def _sparse_factor(M):
    from scipy.sparse.linalg import splu

    try:
        return splu(M.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError as exc:
        raise _singular(exc) from None


def _banded_factor(ab: np.ndarray) -> BandedCholesky:
    """The banded Cholesky factor of the lower band ``ab`` (Fortran order; overwritten), the GIL released."""
    try:
        return BandedCholesky(cholesky_band(ab))
    except np.linalg.LinAlgError as exc:
        raise _singular(exc) from None


def _singular(exc) -> EstimationError:
    return EstimationError(f"the field's normal equations are singular ({exc}): too few observations for its nodes")


def _grid_solve(A, prior: "_Prior", w, r, base=None):
    """Node values ``v`` minimising ``Σ w (r - A v)² + |D (base + v)|² / τ²`` per component; ``(n_nodes, 2)``.

    ``prior``: the prior's ``D^T D / τ²`` (:func:`scaled_prior`). ``base`` ``(n_nodes, 2)`` is the field already
    accumulated: the prior acts on the total field, so the alternation's fixed point is the regularised fit, not a
    pure least-squares one.
    """
    return _solve_regularised(grid_normal(A, w, r), prior, base)


def grid_normal(A, w, r):
    """The data part of :func:`_grid_solve`'s normal equations: ``([A^T W_c A per component], A^T W r, max w)``.

    One matrix serves both components when their weights are equal (the usual case).
    """
    AtW = [A.T.multiply(w[:, c]).tocsr() for c in range(2)]
    N0 = AtW[0] @ A
    N = [N0, N0 if np.array_equal(w[:, 1], w[:, 0]) else AtW[1] @ A]
    return N, np.column_stack([AtW[c] @ r[:, c] for c in range(2)]), float(w.max())


@dataclass(frozen=True)
class _Prior:
    """The prior's ``D^T D / τ²`` (sparse) and the term :func:`factor_sum` adds (its band, up to the band's limit)."""

    reg: object
    term: object


@lru_cache(maxsize=4)
def scaled_prior(n_y: int, n_x: int, order: int, tau_px: float) -> _Prior:
    """The prior ``D^T D / τ²`` of :func:`prior_normal`'s grid and order, laid out for :func:`factor_sum`; read-only.

    Its band is that of ``D^T D`` scaled (laid out once per grid and order: the same numbers as the scaled
    matrix's band, a fraction of its cost). Kept for the last few grids, orders and ``τ``: the refinement's
    joint steps take a system's prior again at every step.
    """
    scale = 1 / tau_px**2  # one factor for the matrix and its band: a sparse matrix's division multiplies by it
    reg = prior_normal(n_y, n_x, order) * scale
    term = reg if n_y * n_x > BANDED_MAX_NODES else _prior_band(n_y, n_x, order) * scale
    for a in (reg.data, reg.indices, reg.indptr) + (() if term is reg else (term,)):
        a.flags.writeable = False
    return _Prior(reg, term)


@lru_cache(maxsize=8)
def _prior_band(n_y: int, n_x: int, order: int) -> np.ndarray:
    band = lower_band(prior_normal(n_y, n_x, order))
    band.flags.writeable = False
    return band


def prior_term(reg, n: int):
    """The prior ``reg`` as :func:`factor_sum` takes it for ``n`` unknowns: its band, up to the band's limit."""
    return reg if n > BANDED_MAX_NODES else lower_band(reg)


def _in_band_form(normal):
    """``normal`` (:func:`grid_normal`'s) with its data matrices laid out in band form, once for every prior."""
    N, b, w_max = normal
    if b.shape[0] > BANDED_MAX_NODES:
        return normal
    first = lower_band(N[0])
    return [first, first if N[1] is N[0] else lower_band(N[1])], b, w_max


def _solve_regularised(normal, prior: _Prior, base=None):
    """:func:`_grid_solve` of the data part ``normal`` (:func:`grid_normal`'s, its matrices sparse or in band form)."""
    N, b, w_max = normal
    # a tiny ridge keeps nodes far from all data (fixed only through the prior's null space) determined
    ridge = 1e-10 * max(w_max, 1.0)
    out = np.empty(b.shape)
    lu = None
    for c in range(2):
        if lu is None or N[c] is not N[0]:
            lu = factor_sum((N[c], prior.term), ridge)
        rhs = b[:, c] if base is None else b[:, c] - prior.reg @ base[:, c]
        out[:, c] = lu.solve(rhs)
    return out


@dataclass(frozen=True)
class GridCvReport:
    """Cross-validation of the smoothness of the gridded least-squares field.

    Attributes
    ----------
    tau_grid_px : (T,) float64 ndarray, px
        Candidate prior standard deviations of a node's difference of the
        prior's order, as evaluated (``tau_grid_px`` of the parameters in
        increasing order, for each order in turn, up to the first rise of the cost).
    cv_cost : (T,) float64 ndarray
        Mean out-of-fold equation-3 cost per observation.
    tau_px : float
        The chosen candidate.
    cv_rms_px : float
        Out-of-fold RMS per component at ``tau_px``.
    order : int
        The chosen order of the difference prior.
    order_grid : (T,) int64 ndarray or None
        The order of each candidate (None: all ``order``).
    """

    tau_grid_px: np.ndarray
    cv_cost: np.ndarray
    tau_px: float
    cv_rms_px: float
    order: int = 2
    order_grid: np.ndarray | None = None

    def __post_init__(self):
        object.__setattr__(self, "tau_grid_px", np.asarray(self.tau_grid_px, dtype=np.float64))
        object.__setattr__(self, "cv_cost", np.asarray(self.cv_cost, dtype=np.float64))
        object.__setattr__(self, "order", int(self.order))
        order_grid = np.full(len(self.tau_grid_px), self.order) if self.order_grid is None else self.order_grid
        object.__setattr__(self, "order_grid", np.asarray(order_grid, dtype=np.int64))
        freeze(self)


def cross_validate_smoothness(
    xy_px,
    residuals_px,
    residual_var_px2,
    *,
    image_size,
    grid: GridSpec = DEFAULT_GRID,
    tau_grid_px=DEFAULT_TAU_GRID_PX,
    orders=(2,),
    n_folds: int = 5,
    seed: int = 0,
    base_px=None,
    cost_cap: float | None = None,
    groups=None,
) -> GridCvReport:
    """Choose the smoothness prior of :func:`fit_grid_field` by shuffled K-fold CV of equation 3.

    Parameters
    ----------
    xy_px, residuals_px, residual_var_px2, image_size, grid
        As in :func:`fit_grid_field`.
    tau_grid_px : sequence of float, px
        Candidate prior standard deviations (default 0.03, 0.1, 0.3, 1, 3 px).
    orders : sequence of int
        Candidate orders of the difference prior (default ``(2,)``).
    n_folds, seed : int
        Folds (default 5) and the seed of their shuffling (default 0).
    base_px : (H_g, W_g, 2) or (n_nodes, 2) float64 ndarray, px, optional
        The field accumulated so far (see Notes).
    cost_cap : float, optional
        Bound on each observation's out-of-fold cost (default None: unbounded),
        as in :func:`fluorocal.stages.learn.knn.cross_validate_k`.
    groups : (N,) int ndarray, optional
        Observations of one group (a grid plate's hole, seen in several frames) fall in one fold, so
        that a field is not rewarded for reproducing at a point what other observations of the same
        object put there (default: every observation its own group).

    Returns
    -------
    GridCvReport
        Candidates: every order with the ``τ`` in increasing order, up to the
        first whose cost rises (each candidate costs a sparse factorisation per fold).

    Notes
    -----
    With ``base_px`` the prior acts on ``base + δ``; the fit of ``δ`` to the
    residuals ``r`` is then the fit of the total field to ``r + base(x)``, so
    the out-of-fold cost judges the total field, not the update.
    """
    base = None if base_px is None else np.asarray(base_px, dtype=np.float64).reshape(-1, 2)
    xy, r, var = check_training(xy_px, residuals_px, residual_var_px2)
    xn, yn = grid.nodes(image_size)
    A = bilinear_design(xn, yn, xy)
    w = 1.0 / var
    n = len(xy)
    folds = _folds(n, n_folds, seed, groups)
    # the data part of each fold's normal equations, shared by every candidate
    normals = [
        _in_band_form(grid_normal(A[train], w[train], r[train]))
        for train in (np.setdiff1d(np.arange(n), test, assume_unique=True) for test in folds)
    ]
    tests = [(A[test], w[test], r[test]) for test in folds]
    evaluated = []  # (order, tau, cost, RMS)
    for order in orders:
        for tau in sorted(tau_grid_px):
            cost, rms = _out_of_fold(normals, tests, scaled_prior(len(yn), len(xn), order, tau), base, cost_cap)
            rising = bool(evaluated) and evaluated[-1][0] == order and cost > evaluated[-1][2]
            evaluated.append((order, tau, cost, rms))
            if rising:
                # past this order's minimum (taken as unimodal in log tau): larger ones only fit more of the noise
                break
    orders, taus, costs, rms = (np.array(c) for c in zip(*evaluated))
    best = int(np.argmin(costs))
    return GridCvReport(taus, costs, float(taus[best]), float(rms[best]), int(orders[best]), orders)


def _folds(n: int, n_folds: int, seed: int, groups) -> list[np.ndarray]:
    """Shuffled K-fold split of ``n`` observations; observations of one group stay together."""
    rng = np.random.default_rng(seed)
    if groups is None:
        return np.array_split(rng.permutation(n), min(n_folds, n))
    unique, member = np.unique(np.asarray(groups), return_inverse=True)
    fold_of_group = np.empty(len(unique), np.int64)
    fold_of_group[rng.permutation(len(unique))] = np.arange(len(unique)) % min(n_folds, len(unique))
    return [np.flatnonzero(fold_of_group[member] == k) for k in range(min(n_folds, len(unique)))]


def _out_of_fold(normals, tests, prior: _Prior, base, cost_cap):
    """Mean out-of-fold equation-3 cost (each observation's bounded at ``cost_cap``) and RMS per component.

    With ``cost_cap`` the RMS is that of the observations below it.
    """
    cost = sq = 0.0
    n = n_sq = 0
    for normal, (A_test, w_test, r_test) in zip(normals, tests):
        err = r_test - A_test @ _solve_regularised(normal, prior, base)
        n += len(err)
        if cost_cap is None:
            cost += float(np.sum(w_test * err**2))
            sq += float(np.sum(err**2))
            n_sq += len(err)
        else:
            z2 = np.sum(w_test * err**2, axis=1)
            cost += float(np.sum(capped_cost(z2, cost_cap)))
            sq += float(np.sum(err[z2 <= cost_cap] ** 2))
            n_sq += int(np.sum(z2 <= cost_cap))
    return cost / n, float(np.sqrt(sq / (2 * max(n_sq, 1))))


@lru_cache(maxsize=8)
def prior_normal(n_y: int, n_x: int, order: int):
    """``D^T D`` of :func:`difference_operator`, sparse CSR; read-only, built once per grid and order.

    Every field step of the refinement and every candidate of its cross-validation needs it.
    """
    matrix = _difference_normal(n_y, n_x, int(order))
    for a in (matrix.data, matrix.indices, matrix.indptr):
        a.flags.writeable = False
    return matrix


def _difference_normal(n_y: int, n_x: int, order: int):
    D = difference_operator(n_y, n_x, order)
    return (D.T @ D).tocsr()


def fit_grid_field(
    xy_px: np.ndarray,
    residuals_px: np.ndarray,
    residual_var_px2: np.ndarray,
    *,
    image_size: tuple[int, int],
    tau_px: float,
    grid: GridSpec = DEFAULT_GRID,
    cv_rms_px: float | None = None,
    base: CorrectionField | None = None,
    order: int = 2,
    support: np.ndarray | None = None,
) -> CorrectionField:
    """Fit the node values of a bilinear grid to the residuals directly (weighted least squares).

    Minimises ``Σ_i (r_i - g(x_i))^T C_r^-1 (r_i - g(x_i)) + |D (base + δ)|² / τ²``: equation 3
    with ``g`` the bilinear grid field instead of a kNN average, plus a
    thin-plate smoothness prior ``D`` (second differences of the node values,
    standard deviation ``τ`` px). Unlike the kNN mean it does not blur the field
    over a neighbourhood, so its fixed point in the alternation is the field
    itself rather than a smoothed copy of it.

    Parameters
    ----------
    xy_px, residuals_px, residual_var_px2
        As in :func:`fluorocal.stages.learn.knn.fit_knn_field`.
    image_size : (int, int)
        ``(width, height)`` px.
    tau_px : float
        Prior standard deviation of a second difference, px (see :func:`cross_validate_smoothness`).
    grid : GridSpec
        Nodes and support rule (default 16 px, 32 px, 3).
    cv_rms_px : float, optional
        Out-of-fold RMS for the node uncertainty (default: the in-sample RMS).
    base : CorrectionField, optional
        The field accumulated so far, on the same grid: the prior then acts on
        ``base + δ`` (the alternation's total field) and the returned ``δ`` is the update.
    order : int
        Order of the difference prior (default 2, the thin-plate energy; see
        ``LearnParams.smoothness_orders``).
    support : (H_g * W_g,) bool ndarray, optional
        ``grid.support_mask`` of ``xy_px`` at the nodes, when the caller fits the same points again
        (default: computed).

    Returns
    -------
    CorrectionField
        The update ``δ``, with node uncertainty ``cv_rms / sqrt(n_eff)``
        (``n_eff`` the bilinear weight the observations put on the node).
    """
    xy, r, var = check_training(xy_px, residuals_px, residual_var_px2)
    width, height = (int(s) for s in image_size)
    xn, yn = grid.nodes((width, height))
    A = bilinear_design(xn, yn, xy)
    prior = scaled_prior(len(yn), len(xn), order, float(tau_px))
    v = _grid_solve(A, prior, 1.0 / var, r, None if base is None else base.delta_px.reshape(-1, 2))
    if cv_rms_px is None:
        cv_rms_px = float(np.sqrt(np.mean((r - A @ v) ** 2)))
    return grid_result(xn, yn, v, A, xy, cv_rms_px, grid, (width, height), support)


def grid_result(xn, yn, values, A, xy, cv_rms_px, grid: GridSpec, image_size, support=None) -> CorrectionField:
    """A least-squares grid field with node uncertainty ``cv_rms / sqrt(n_eff)`` and support mask.

    ``n_eff`` is the bilinear weight the observations put on the node; ``support`` (default: computed) is
    ``grid.support_mask`` of ``xy`` at the nodes.
    """
    n_eff = np.asarray(A.sum(axis=0)).ravel()
    sigma = cv_rms_px / np.sqrt(np.maximum(n_eff, 1e-3))
    shape = (len(yn), len(xn))
    return CorrectionField(
        xn,
        yn,
        values.reshape(shape + (2,)),
        sigma.reshape(shape),
        (grid.support_mask(xy, xn, yn) if support is None else support).reshape(shape),
        *image_size,
    )


__all__ = [
    "DIFFERENCE_STENCILS",
    "GridCvReport",
    "cross_validate_smoothness",
    "difference_operator",
    "factor_spd",
    "factor_sum",
    "fit_grid_field",
    "grid_result",
    "prior_normal",
    "prior_term",
    "scaled_prior",
    "lower_band",
]
