"""Normal equations of the bundle adjustment in Schur blocks, and the datum-constrained (bordered) damped step.

``H δ = b`` with ``H = Σ w J^T J`` and ``b = -Σ w J^T e`` is accumulated by
segment sums over the observations pre-sorted by system and kept block
(:class:`stages.adjust.problem.Problem`), the eliminated blocks (points or
poses) are removed by a Schur complement, and the 7 inner constraints border
the reduced system (:func:`reduced_system`). :func:`factorize` and
:func:`step_from` give the Levenberg–Marquardt step of :mod:`stages.adjust.solver`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from fluorocal.stages.adjust.problem import Problem, segment_starts
from fluorocal.stages.errors import EstimationError


def _outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per observation ``a^T b`` for ``(N, 2, I)`` and ``(N, 2, J)`` -> ``(N, I, J)``."""
    return np.matmul(a.transpose(0, 2, 1), b)


def _segment_grams(J: np.ndarray, starts: np.ndarray, first: int) -> np.ndarray:
    """``Σ J_n^T J_n`` of columns ``first:`` over each run ``starts[i]:starts[i+1]`` of ``J (N, 2, c)``.

    One BLAS product per run: the runs (one per kept block and system) are few
    and long, where a batched per-observation product would be memory bound. The
    columns are sliced in the product (a strided operand BLAS reads in place), and
    the observations are stored in runs (:class:`stages.adjust.problem.Problem`): no copy of ``J``.
    """
    flat = J.reshape(-1, J.shape[2])
    bounds = 2 * np.r_[starts, len(J)]
    k = J.shape[2] - first
    out = np.empty((len(starts), k, k))
    for i in range(len(starts)):
        seg = flat[bounds[i] : bounds[i + 1], first:]
        out[i] = seg.T @ seg
    return out


@dataclass(frozen=True)
class Normal:
    """The normal equations ``H δ = b`` (``b = -gradient``) in Schur-ready blocks.

    Attributes
    ----------
    A : (ne, be, be) float64 ndarray
        Diagonal blocks of the eliminated parameters.
    B : (ne * be, r) float64 ndarray
        Coupling of eliminated and kept parameters (kept = kept blocks, then globals).
    Hyy : (r, r) float64 ndarray
        Kept-kept block.
    b_e : (ne, be) float64 ndarray
    b_y : (r,) float64 ndarray
    """

    A: np.ndarray
    B: np.ndarray
    Hyy: np.ndarray
    b_e: np.ndarray
    b_y: np.ndarray


def weighted_jacobian(
    e: np.ndarray, J: np.ndarray, w: np.ndarray, *, overwrite_j: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """``sqrt(w)``-weighted Jacobian (N, 2, nt) and residuals (N, 2); ``J`` from :func:`collinearity.jacobian`.

    ``overwrite_j``: scale ``J`` in place (a solver's own Jacobian: no second array of its size).
    """
    sw = np.sqrt(w)[:, None]
    if overwrite_j:
        return np.multiply(J, sw[:, :, None], out=J), e * sw
    return J * sw[:, :, None], e * sw


def triggs_corrected(J: np.ndarray, ew: np.ndarray, t: np.ndarray, nu: float) -> np.ndarray:
    """``J`` with each observation's curvature along its residual set to the Student-t value (Triggs' correction).

    The Hessian of ``ρ(t)`` along the residual direction ``n`` is ``w (ν - t)/(ν + t)``
    rather than the IRLS ``w``. With ``D = (ν - t)/(ν + t)`` and ``α = 1 - sqrt(D)``,
    ``(J - α n n^T J)`` gives exactly that curvature for ``t < ν``. Beyond the
    inflection (``t >= ν``, negative curvature) ``α = 1``: no curvature along
    ``n``, the nearest positive semi-definite value. (Ceres keeps the IRLS ``w``
    there, ``α = 0``; with a fifth of the observations beyond ``t = ν`` — a t fitted
    to near-Gaussian noise — that overstated curvature shortens every step and
    halves the convergence rate.) Use it for ``H`` only; the gradient comes from ``J``.

    Parameters
    ----------
    J : (N, 2, K) float64 ndarray
        ``sqrt(w)``-weighted Jacobian.
    ew : (N, 2) float64 ndarray
        ``sqrt(w)``-weighted whitened residuals (their direction is what matters).
    t : (N,) float64 ndarray
        ``s/σ²``.
    """
    d = (nu - t) / (nu + t)
    alpha = 1.0 - np.sqrt(np.clip(d, 0.0, 1.0))
    n_dir = ew / np.maximum(np.linalg.norm(ew, axis=1, keepdims=True), 1e-300)
    # (I - α n n^T) per observation, a 2 x 2 applied to J's rows
    M = (-alpha[:, None] * n_dir)[:, :, None] * n_dir[:, None, :]
    M[:, 0, 0] += 1.0
    M[:, 1, 1] += 1.0
    return np.matmul(M, J)


def gradient(problem: Problem, J: np.ndarray, ew: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``b = -Σ w J^T e`` split into the eliminated ``(ne, be)`` and kept ``(r,)`` parts."""
    be, bk, nk, G = problem.be, problem.bk, problem.nk, problem.n_globals
    bj = np.einsum("nij,ni->nj", J, ew)  # shape (N, nt)
    b_e = -_per_block(problem.es_summer @ bj, problem.es_e)[:, :be]
    b_y = np.zeros(nk * bk + G + 1)
    bk_sums = problem.ks_summer @ bj[:, be:]  # shape (n_ks, bk + ng): per (kept block, system)
    b_y[: nk * bk] = -_per_kept_block(bk_sums[:, :bk], problem).reshape(-1)
    gcols = _gcols(problem, nk * bk, nk * bk + G + 1)
    for s in range(problem.n_systems):
        np.add.at(b_y, gcols[s], -bk_sums[problem.ks_s == s, bk:].sum(0))
    return b_e, b_y[:-1]


def _per_block(sums: np.ndarray, block: np.ndarray) -> np.ndarray:
    """Per-(block, system) ``sums`` (sorted by block, every block present) added over the systems of each block."""
    return np.add.reduceat(sums, segment_starts(block), axis=0)


def _per_kept_block(sums: np.ndarray, problem: Problem) -> np.ndarray:
    """Per-(system, kept block) ``sums`` added over the systems of each kept block."""
    order = problem.ks_by_block
    return _per_block(sums[order], problem.ks_k[order])


def assemble(problem: Problem, J: np.ndarray, ew: np.ndarray, J_hessian: np.ndarray | None = None) -> Normal:
    """Weighted normal equations ``Σ w J^T J`` and ``-Σ w J^T e`` in Schur blocks (no loops over observations).

    ``J, ew`` from :func:`weighted_jacobian` (the gradient); ``J_hessian``
    replaces ``J`` in ``H`` if given (:func:`triggs_corrected`). Batched products of the
    per-observation Jacobians are accumulated by segment sums over observations
    pre-sorted by system and kept block (:attr:`Problem.ks_starts`) and, through
    ``e_order``, by the eliminated block (:attr:`Problem.es_summer`).
    """
    ne, nk, be, bk, G = problem.ne, problem.nk, problem.be, problem.bk, problem.n_globals
    r = nk * bk + G
    b_e, b_y = gradient(problem, J, ew)
    if J_hessian is not None:
        J = J_hessian
    kk = be + bk
    J_e = J[:, :, :be]
    # per (eliminated block, system) sums of the eliminated rows against themselves and the globals:
    # the coupling with the kept block is per observation and goes to B whole
    EA = problem.es_summer @ _outer(J_e, J_e).reshape(len(J), -1)
    A = _per_block(EA.reshape(-1, be, be), problem.es_e)
    # in observation order: a pair seen by two systems gets 0 + x0 + x1, as when added system by system
    B = np.bincount(problem.coupling_index, weights=_outer(J_e, J[:, :, be:kk]).ravel(), minlength=ne * be * r)
    B = B.reshape(ne, be, r)
    Eg = (problem.es_summer @ _outer(J_e, J[:, :, kk:]).reshape(len(J), -1)).reshape(len(EA), be, -1)
    gcols = _gcols(problem, nk * bk, r + 1)
    valid = gcols[problem.es_s] < r  # fixed globals point past the end
    e_rows = np.broadcast_to(problem.es_e[:, None, None], Eg.shape)
    a_rows = np.broadcast_to(np.arange(be)[None, :, None], Eg.shape)
    g_cols = np.broadcast_to(gcols[problem.es_s][:, None, :], Eg.shape)
    keep = np.broadcast_to(valid[:, None, :], Eg.shape)
    np.add.at(B, (e_rows[keep], a_rows[keep], g_cols[keep]), Eg[keep])

    rg = r + 1  # the extra last column collects fixed globals and is dropped
    Hyy = np.zeros((rg, rg))
    KS = _segment_grams(J, problem.ks_starts, be)  # shape (n_ks, bk + ng, bk + ng)
    KK = _per_kept_block(KS[:, :bk, :bk], problem)
    blk = np.arange(nk)[:, None] * bk + np.arange(bk)
    Hyy[blk[:, :, None], blk[:, None, :]] = KK
    KS = KS[:, :, bk:]
    Kg = KS[:, :bk]
    rows = problem.ks_k[:, None, None] * bk + np.arange(bk)[None, :, None]
    cols = gcols[problem.ks_s][:, None, :]
    np.add.at(Hyy, (rows, cols), Kg)
    np.add.at(Hyy, (cols.transpose(0, 2, 1), rows.transpose(0, 2, 1)), Kg.transpose(0, 2, 1))
    for s in range(problem.n_systems):
        idx = gcols[s]
        Hyy[np.ix_(idx, idx)] += KS[problem.ks_s == s, bk:].sum(0)
    return Normal(A=A, B=B.reshape(ne * be, r), Hyy=Hyy[:r, :r], b_e=b_e, b_y=b_y)


def _gcols(problem: Problem, base: int, rg: int) -> np.ndarray:
    """Per system, the 9 global columns in the kept system (fixed ones -> the dropped last column)."""
    return np.where(problem.gcol >= 0, problem.gcol + base, rg - 1)


def _datum_split(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """Datum rows on the eliminated ``(ne, be, 7)`` and kept ``(r, 7)`` parameters."""
    r = problem.n_kept
    if problem.eliminate == "points":
        return problem.datum, np.zeros((r, 7))
    D_y = np.zeros((r, 7))
    D_y[: 3 * problem.n_points] = problem.datum.reshape(-1, 7)
    return np.zeros((problem.ne, problem.be, 7)), D_y


class SingularStep(EstimationError):
    """The damped step's linear system is numerically singular (the solver raises the damping)."""


def _block_chol_inv(A: np.ndarray) -> np.ndarray:
    """``L^-1`` of each SPD block ``A = L L^T``; raises EstimationError if one is not positive definite."""
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError as err:
        raise SingularStep("a parameter block is not determined by its observations (singular normal block)") from err
    eye = np.broadcast_to(np.eye(A.shape[-1]), A.shape)
    return np.linalg.solve(L, eye)


def reduced_system(problem: Problem, normal: Normal, mu: float) -> tuple:
    """Damped bordered Schur complement ``[[S, Q], [Q^T, -R]]``.

    Damping is Marquardt's: ``H + μ diag(H)``.

    Returns
    -------
    Z : (r + 7, r + 7) float64 ndarray
    parts : tuple
        ``(Linv, Gm, LD)`` needed to form right-hand sides and back-substitute.
    """
    ne, be = problem.ne, problem.be
    A = normal.A
    Hyy = normal.Hyy
    if mu > 0:
        A = A + mu * np.einsum("nii->ni", A)[:, :, None] * np.eye(be)
        Hyy = Hyy + np.diag(mu * np.diag(Hyy))
    Linv = _block_chol_inv(A)
    r = normal.Hyy.shape[0]
    # G = blockdiag(L^-1) B, shape (ne * be, r)
    Gm = np.matmul(Linv, normal.B.reshape(ne, be, r)).reshape(ne * be, r)
    D_e, D_y = _datum_split(problem)
    LD = np.matmul(Linv, D_e).reshape(ne * be, 7)
    S = Hyy - _gram(Gm)
    Q = D_y - Gm.T @ LD
    # scale the constraints (κ D^T δ = 0 is the same constraint) to S's magnitude: keeps the
    # bordered matrix well conditioned at any damping
    border = max(float(np.abs(Q).max(initial=0.0)), math.sqrt(float(np.abs(LD.T @ LD).max(initial=0.0))), 1e-300)
    kappa = math.sqrt(max(float(np.diag(S).mean()), 1e-300)) / border
    Q *= kappa
    LD = LD * kappa
    Z = np.empty((r + 7, r + 7))
    Z[:r, :r] = S
    Z[:r, r:] = Q
    Z[r:, :r] = Q.T
    Z[r:, r:] = -(LD.T @ LD)
    return Z, (Linv, Gm, LD)


def _gram(G: np.ndarray) -> np.ndarray:
    """``G^T G`` (NumPy hands ``A.T @ A`` to the symmetric rank-k BLAS update, half the flops of a GEMM)."""
    return G.T @ G


@dataclass(frozen=True)
class Factor:
    """An LU-factorised damped reduced system, reusable for several right-hand sides."""

    lu: tuple
    parts: tuple
    diag_h: np.ndarray  # undamped diagonal of H, eliminated then kept, for the predicted decrease
    mu: float


def factorize(problem: Problem, normal: Normal, mu: float) -> Factor:
    """Form and factorise the damped bordered Schur complement; :class:`SingularStep` if singular."""
    Z, parts = reduced_system(problem, normal, mu)
    with warnings.catch_warnings():
        warnings.simplefilter("error", scipy.linalg.LinAlgWarning)
        try:
            lu = scipy.linalg.lu_factor(Z, check_finite=False)
        except (np.linalg.LinAlgError, ValueError, scipy.linalg.LinAlgWarning) as err:
            raise SingularStep("the damped reduced normal equations are singular") from err
    diag_h = np.concatenate([np.einsum("nii->ni", normal.A).ravel(), np.diag(normal.Hyy)])
    return Factor(lu=lu, parts=parts, diag_h=diag_h, mu=mu)


def step_from(problem: Problem, factor: Factor, b_e: np.ndarray, b_y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The datum-constrained step ``(δ_eliminated (ne, be), δ_kept (r,))`` for right-hand side ``b``.

    With ``Lb = L^-1 b_e`` the reduced right-hand side is ``[b_y - G^T Lb, -LD^T Lb]``;
    the eliminated parameters follow as ``L^-T (Lb - G δy - LD λ)``.
    """
    Linv, Gm, LD = factor.parts
    Lb = np.einsum("nab,nb->na", Linv, b_e).reshape(-1)
    rhs = np.concatenate([b_y - Gm.T @ Lb, -(LD.T @ Lb)])
    sol = scipy.linalg.lu_solve(factor.lu, rhs, check_finite=False)
    if not np.all(np.isfinite(sol)):
        raise SingularStep("the damped reduced normal equations are singular")
    r = len(b_y)
    dy, lam = sol[:r], sol[r:]
    t = Lb - Gm @ dy - LD @ lam
    de = np.einsum("nba,nb->na", Linv, t.reshape(problem.ne, problem.be))
    return de, dy
