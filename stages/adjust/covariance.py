"""Uncertainty of the bundle adjustment: cofactors under the inner constraints, Huber's sandwich, redundancy numbers.

:func:`covariance` inverts the bordered normal matrix at the solution
(per-block cofactors and ``J Q J^T`` per observation); :func:`covariance_factor`
scales them (Huber's sandwich for the t M-estimator, σ̂0² for least squares);
:func:`observation_statistics` gives each observation's redundancy numbers,
standardised residual and inlier flag (shared with :func:`stages.adjust.adjust_plate`).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from fluorocal.stages.adjust.collinearity import State, jacobian, jacobian_blocks
from fluorocal.stages.adjust.normal import assemble, reduced_system, weighted_jacobian
from fluorocal.stages.adjust.problem import Problem
from fluorocal.stages.errors import EstimationError

_CHUNK = 32768  # observations per chunk in the covariance pass (bounds memory)


@dataclass(frozen=True)
class Covariance:
    """Cofactors ``Q = (J^T W J)^-1`` under the inner constraints (unscaled).

    Attributes
    ----------
    points : (n, 3, 3) float64 ndarray
    poses : (m, 6, 6) float64 ndarray
    globals_ : (G, G) float64 ndarray
    hat : (N, 2, 2) float64 ndarray
        ``J_o Q J_o^T`` per observation with the whitened, unweighted Jacobian.
    """

    points: np.ndarray
    poses: np.ndarray
    globals_: np.ndarray
    hat: np.ndarray


def covariance(state: State, problem: Problem, w: np.ndarray) -> Covariance:
    """Inner-constraint cofactor blocks and per-observation ``J Q J^T`` at ``state`` with weights ``w``.

    With ``M = [[A, B], [B^T, C]]`` the bordered normal matrix (``A`` the
    eliminated blocks, ``C`` the kept parameters and the 7 multipliers) and
    ``Z = C - B^T A^-1 B``, the inverse is ``A^-1 + F Z^-1 F^T`` on the
    eliminated, ``-F Z^-1`` across and ``Z^-1`` on the kept part, ``F = A^-1 B``.
    """
    e, J = jacobian(state, problem)
    J_point, J_pose, J_glob = jacobian_blocks(problem, J)
    normal = assemble(problem, *weighted_jacobian(e, J, w))
    Z, (Linv, Gm, LD) = reduced_system(problem, normal, 0.0)
    ne, be, bk, nk = problem.ne, problem.be, problem.bk, problem.nk
    r = normal.Hyy.shape[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error", scipy.linalg.LinAlgWarning)
        try:
            Zinv = scipy.linalg.inv(Z, check_finite=False)
        except (np.linalg.LinAlgError, ValueError, scipy.linalg.LinAlgWarning) as err:
            raise EstimationError(
                "the normal equations are singular at the solution: some parameters are not determined by this "
                "network (for example rotations all about one axis leave the principal point and the tilt "
                "inseparable); vary the phantom's tilt between exposures or hold the IOP fixed (estimate_iop=False)"
            ) from err
    Zinv = 0.5 * (Zinv + Zinv.T)
    # F = A^-1 [B, D_e] = L^-T [Gm, LD], shape (ne, be, r + 7)
    F = np.einsum("nba,nbr->nar", Linv, np.concatenate([Gm, LD], axis=1).reshape(ne, be, r + 7))
    Ainv = np.einsum("nca,ncb->nab", Linv, Linv)
    FZ = (F.reshape(ne * be, r + 7) @ Zinv).reshape(ne, be, r + 7)
    cov_e = Ainv + np.einsum("nar,nbr->nab", FZ, F)
    kb = Zinv[: nk * bk, : nk * bk].reshape(nk, bk, nk, bk)
    ar = np.arange(nk)
    cov_k = kb[ar, :, ar, :]
    cov_g = Zinv[nk * bk : r, nk * bk : r]
    cov_points, cov_poses = (cov_e, cov_k) if problem.eliminate == "points" else (cov_k, cov_e)

    JE, JK = (J_point, J_pose) if problem.eliminate == "points" else (J_pose, J_point)
    gcols = np.where(problem.gcol >= 0, problem.gcol + nk * bk, -1)
    hat = np.empty((problem.n_obs, 2, 2))
    # J Q J^T = JE A^-1 JE^T + (U - V) Z^-1 (U - V)^T with U = JE F_e, V = [JK, Jg] on the kept columns
    PE = cov_e - Ainv  # F Z^-1 F^T per eliminated block
    # the kept columns of an observation depend only on its (kept block, system): gather Z^-1 once per pair
    n_sys = problem.n_systems
    pair_cols = np.concatenate(
        [np.repeat(np.arange(nk), n_sys)[:, None] * bk + np.arange(bk), gcols[np.tile(np.arange(n_sys), nk)]], axis=1
    )
    pair_valid = pair_cols >= 0
    pair_cols = np.where(pair_valid, pair_cols, 0)
    pair_Z = Zinv[pair_cols[:, :, None], pair_cols[:, None, :]]
    for lo in range(0, problem.n_obs, _CHUNK):
        sl = slice(lo, lo + _CHUNK)
        ei, pair = problem.e_idx[sl], problem.k_idx[sl] * n_sys + problem.sys_idx[sl]
        je, jk, jg = JE[sl], JK[sl], J_glob[sl]
        cols_c = pair_cols[pair]
        jv = np.concatenate([jk, jg], axis=2) * pair_valid[pair][:, None, :]
        t1 = je @ (Ainv[ei] + PE[ei]) @ je.transpose(0, 2, 1)
        rows = ei[:, None, None] * be + np.arange(be)[None, :, None]
        FZc = FZ.reshape(ne * be, r + 7)[rows, cols_c[:, None, :]]  # (n, be, kc)
        t2 = je @ FZc @ jv.transpose(0, 2, 1)
        t3 = jv @ pair_Z[pair] @ jv.transpose(0, 2, 1)
        hat[sl] = t1 - t2 - t2.transpose(0, 2, 1) + t3
    return Covariance(points=cov_points, poses=cov_poses, globals_=cov_g, hat=hat)


def without_covariance(problem: Problem, w: np.ndarray, dof: int) -> Covariance:
    """Zero cofactors and the mean redundancy for every observation: ``hat = (1 - r̄)/w I``, ``r̄ = dof / 2N``.

    The stand-in when the dense inverse is skipped (``compute_covariance=False``).
    """
    ng = problem.n_globals
    hat = ((1.0 - dof / (2.0 * problem.n_obs)) / w)[:, None, None] * np.eye(2)
    return Covariance(np.zeros((problem.n_points, 3, 3)), np.zeros((problem.n_poses, 6, 6)), np.zeros((ng, ng)), hat)


def covariance_factor(s: np.ndarray, w: np.ndarray, nu: float, scale2: float, n_unknowns: int, dof: int) -> float:
    """The factor ``c`` of the covariance ``c Q``: Huber's sandwich for the t, ``Σ s / dof`` for least squares.

    ``c = K² [Σ w² s / dof] mean(w) / mean(a)²`` with ``a = w ν/(ν + s/σ²)`` the
    averaged ψ' and ``K = 1 + (u / 2N) var(a) / mean(a)²`` his small-sample
    correction (``u = n_unknowns``, the free parameters less the 7 datum
    constraints; ``s`` the squared Mahalanobis residuals) [1]_.

    References
    ----------
    .. [1] P. J. Huber, Robust Statistics, Wiley 1981, section 7.6.
    """
    if math.isinf(nu):
        return float(s.sum() / dof)
    a = w * nu / (nu + s / scale2)
    a_bar = float(np.mean(a))
    K = 1.0 + n_unknowns / (2.0 * len(s)) * float(np.var(a)) / a_bar**2
    return K * K * float((w * w * s).sum() / dof) * float(np.mean(w)) / a_bar**2


def observation_statistics(r_px, s, w, hat, linv, outlier_weight):
    """Redundancy numbers, standardised residuals, σ0 and inlier flags from ``J Q J^T`` per observation.

    Returns
    -------
    redundancy : (N, 2) float64 ndarray
        ``diag(L (I - w J Q J^T) L^-1)``: the diagonal of ``Q_vv P`` with ``P = w C^-1``.
    standardized : (N, 2) float64 ndarray
        ``v / (σ0 σ sqrt(r))`` (Baarda's w).
    sigma0 : float
        ``sqrt(Σ_inliers s / Σ_inliers r)``.
    inlier : (N,) bool ndarray
    """
    n = len(s)
    l11, l21, l22 = linv.T
    L = np.zeros((n, 2, 2))
    L[:, 0, 0] = 1.0 / l11
    L[:, 1, 0] = -l21 / (l11 * l22)
    L[:, 1, 1] = 1.0 / l22
    Linv = np.zeros((n, 2, 2))
    Linv[:, 0, 0], Linv[:, 1, 0], Linv[:, 1, 1] = l11, l21, l22
    red = np.einsum("nii->ni", L @ (np.eye(2) - w[:, None, None] * hat) @ Linv)
    inlier = w >= outlier_weight
    red_in = red[inlier].sum()
    sigma0 = math.sqrt(s[inlier].sum() / red_in) if red_in > 0 else math.sqrt(s.mean() / 2)
    sig_xy = np.sqrt(np.einsum("nij,nij->ni", L, L))  # diag of C = L L^T
    denom = sigma0 * sig_xy * np.sqrt(np.clip(red, 0.0, None))
    std_res = np.divide(r_px, denom, out=np.zeros_like(r_px), where=denom > 1e-12 * sig_xy)
    return red, std_res, sigma0, inlier
