"""Residual functions of the bundle adjustment: the collinearity equation, whitened, and its analytic Jacobians.

Model (:mod:`stages.adjust`): the ideal coordinates ``meas_px`` of an
observation are projected as ``(xp, yp) + c (p_x, p_y) / p_z`` from its camera
point ``p``, and the residual is ``ideal - projected``, whitened by the
observation's covariance ``C = L L^T`` (``e = L^-1 r``).

Parameters and their local updates
----------------------------------
- object point ``P_i`` (3, mm): ``P += δP``;
- pose of epoch ``j`` of the reference system (system 0): rotation
  ``R_j <- exp([δθ]x) R_j`` (3, rad, a left update in the camera frame) and
  source ``T_j += δT`` (3, mm);
- per system ``s``: IOP ``(xp, yp, c) += δ`` (3, px) when free; for ``s >= 1``
  the relative orientation (ROP) ``R_s <- exp([δφ]x) R_s`` and
  ``b_s += δb``, where system ``s``'s camera frame is
  ``p_s = R_s (p_0 - b_s)`` and ``p_0 = R_j (P - T_j)`` is the reference camera
  frame, so ``b_s`` is system ``s``'s source in the reference camera frame;
- per system, optionally, the 7 additional parameters (APs) of the global
  polynomial distortion model of :mod:`stages.adjust.polynomial` (px), ``+= δ``:
  the ideal coordinates are then ``meas_px - Δ_AP(xy_px; xp, yp)``.

A row of the globals vector is one free IOP, ROP or AP parameter; per
observation the global columns are ``(xp, yp, c)``, then ``(δφ (3), δb (3))``
with several systems, then the 7 APs when estimated, of its system, and
:attr:`stages.adjust.problem.Problem.gcol` maps them into the globals vector (``-1`` for fixed or
absent ones).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from fluorocal.stages.adjust import polynomial
from fluorocal.stages.geometry import quat_to_matrix

if TYPE_CHECKING:
    from fluorocal.stages.adjust.problem import Problem


@dataclass(frozen=True)
class State:
    """The estimated quantities (internal; :func:`stages.adjust.problem.apply_step` returns updated copies).

    Attributes
    ----------
    points_mm : (n, 3) float64 ndarray, mm
    q : (m, 4) float64 ndarray
        Reference-system pose of each epoch, object -> camera, ``(w, x, y, z)``.
    source_mm : (m, 3) float64 ndarray, mm
    iop_px : (S, 3) float64 ndarray, px
    rop_q : (S, 4) float64 ndarray
        System ``s`` camera from reference camera; identity for ``s = 0``.
    rop_source_mm : (S, 3) float64 ndarray, mm
        Source of system ``s`` in the reference camera frame; zero for ``s = 0``.
    ap_px : (S, 7) float64 ndarray or None, px
        Additional parameters (:mod:`stages.adjust.polynomial`); None: all zero.
    """

    points_mm: np.ndarray
    q: np.ndarray
    source_mm: np.ndarray
    iop_px: np.ndarray
    rop_q: np.ndarray
    rop_source_mm: np.ndarray
    ap_px: np.ndarray | None = None


def whitening(sigma_px: np.ndarray) -> np.ndarray:
    """Entries ``(l11, l21, l22)`` of ``L^-1`` for ``C = L L^T`` from ``(σx, σy, ρ)``.

    Parameters
    ----------
    sigma_px : (N, 3) float64 ndarray
        ``(σx px, σy px, ρ)``.

    Returns
    -------
    linv : (N, 3) float64 ndarray, 1/px
    """
    sx, sy, rho = sigma_px.T
    root = np.sqrt(1.0 - rho * rho)
    return np.column_stack([1.0 / sx, -rho / (sx * root), 1.0 / (sy * root)])


def camera_points(state: State, problem: Problem) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame coordinates of every observation.

    Returns
    -------
    p : (N, 3) float64 ndarray, mm
        In the observing system's camera frame.
    p_ref : (N, 3) float64 ndarray, mm
        In the reference (system 0) camera frame.
    R_pose : (m, 3, 3) float64 ndarray
    R_rop : (S, 3, 3) float64 ndarray
    """
    R_pose = quat_to_matrix(state.q)
    R_rop = quat_to_matrix(state.rop_q)
    # gathers by take: several times faster than fancy indexing
    d = state.points_mm.take(problem.point_idx, axis=0) - state.source_mm.take(problem.pose_idx, axis=0)
    p_ref = np.einsum("nij,nj->ni", R_pose.take(problem.pose_idx, axis=0), d)
    if problem.n_systems == 1:
        return p_ref, p_ref, R_pose, R_rop
    # the reference system's observations come first: their relative orientation is the identity
    m = problem.n_reference
    s = problem.sys_idx[m:]
    p = np.empty_like(p_ref)
    p[:m] = p_ref[:m]
    np.einsum("nij,nj->ni", R_rop.take(s, axis=0), p_ref[m:] - state.rop_source_mm.take(s, axis=0), out=p[m:])
    return p, p_ref, R_pose, R_rop


def whiten(linv: np.ndarray, r: np.ndarray) -> np.ndarray:
    """``L^-1 r`` for ``(N, 2)`` or ``(N, 2, K)`` arrays ``r``."""
    l11, l21, l22 = (linv[:, i].reshape((-1,) + (1,) * (r.ndim - 2)) for i in range(3))
    return np.stack([l11 * r[:, 0], l21 * r[:, 0] + l22 * r[:, 1]], axis=1)


def residuals(state: State, problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """Residuals ``ideal - projected`` in px and whitened, or raise if a point is behind a source.

    Returns
    -------
    r_px : (N, 2) float64 ndarray, px
    e : (N, 2) float64 ndarray
        ``L^-1 r_px`` (unit variance under the observations' covariance).
    """
    p, _, _, _ = camera_points(state, problem)
    return _residuals_from_camera(state, problem, p)


@dataclass(frozen=True)
class Projection:
    """A state's :func:`camera_points` and whitened residuals ``e`` (N, 2): what :func:`linearize` can reuse."""

    camera: tuple
    e: np.ndarray


def project(state: State, problem: Problem) -> Projection:
    """:func:`residuals`' whitened residuals with the camera points they came from (raises as it does)."""
    camera = camera_points(state, problem)
    return Projection(camera, _residuals_from_camera(state, problem, camera[0])[1])


def _residuals_from_camera(
    state: State, problem: Problem, p: np.ndarray, ap_basis: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    z = p[:, 2]
    if not np.all(z > 1e-6):
        raise FloatingPointError("point at or behind the source")
    iop = state.iop_px.take(problem.sys_idx, axis=0)
    r = np.empty_like(problem.meas_px)
    for i in range(2):  # column by column: (N, 2) arrays' short rows are slow to broadcast
        r[:, i] = problem.meas_px[:, i] - (iop[:, i] + iop[:, 2] * p[:, i] / z)
    if problem.n_ap:
        B = _ap_basis(state, problem) if ap_basis is None else ap_basis
        r -= np.einsum("nij,nj->ni", B, ap_values(state, problem)[problem.sys_idx])
    return r, whiten(problem.linv, r)


def ap_values(state: State, problem: Problem) -> np.ndarray:
    """The APs ``(S, n_ap)`` px of ``state`` (zeros where the state holds none)."""
    return np.zeros((problem.n_systems, problem.n_ap)) if state.ap_px is None else state.ap_px


def _ap_basis(state: State, problem: Problem, *, derivatives: bool = False):
    """The AP design matrix (N, 2, 7) at every observation, and its ``u``, ``v`` derivatives.

    See :func:`stages.adjust.polynomial.basis`.
    """
    s = problem.sys_idx
    return polynomial.basis(problem.ap_xy_px, state.iop_px[s, :2], problem.ap_radius_px[s], derivatives=derivatives)


def _ap_columns(state: State, problem: Problem, basis: tuple, J_glob: np.ndarray) -> None:
    """Fill the AP columns of ``J_glob``; add the APs' dependence on the principal point to its ``xp``, ``yp`` columns.

    ``ideal = meas - B(u, v) a`` with ``u = (x - xp) / r0``, ``v = (y - yp) / r0``:
    ``∂e/∂a = -L^-1 B`` and ``∂e/∂xp`` gains ``L^-1 (∂B/∂u a) / r0`` (``yp``: ``∂B/∂v``).
    """
    B, dB_du, dB_dv = basis
    s = problem.sys_idx
    a = ap_values(state, problem)[s]
    inv_r0 = 1.0 / problem.ap_radius_px[s, None]
    J_glob[:, :, problem.ap_start :] = -whiten(problem.linv, B)
    J_glob[:, :, 0] += whiten(problem.linv, np.einsum("nij,nj->ni", dB_du, a) * inv_r0)
    J_glob[:, :, 1] += whiten(problem.linv, np.einsum("nij,nj->ni", dB_dv, a) * inv_r0)


def linearize(
    state: State, problem: Problem, projection: Projection | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Whitened residuals and their analytic Jacobians for every observation.

    ``projection``: :func:`project` of the same ``state``, if already evaluated (not evaluated again).

    Returns
    -------
    e : (N, 2) float64 ndarray
        Whitened residuals ``L^-1 (ideal - projected)``.
    J_point : (N, 2, 3) float64 ndarray
        ``∂e/∂P`` (per mm).
    J_pose : (N, 2, 6) float64 ndarray
        ``∂e/∂(δθ, T)`` (per rad, per mm) of the epoch's reference pose.
    J_glob : (N, 2, G_o) float64 ndarray
        ``∂e/∂(xp, yp, c, δφ, b, APs)`` of the observation's system, the columns of
        :attr:`Problem.gcol` (``δφ, b`` only with several systems, the APs only when estimated).
    """
    e, J = jacobian(state, problem, projection)
    return (e, *jacobian_blocks(problem, J))


def jacobian_blocks(problem: Problem, J: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Views ``(J_point, J_pose, J_glob)`` of :func:`jacobian`'s ``J``."""
    point, pose = (0, 3) if problem.eliminate == "points" else (6, 0)
    return J[:, :, point : point + 3], J[:, :, pose : pose + 6], J[:, :, 9:]


def jacobian(state: State, problem: Problem, projection: Projection | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`linearize`'s residuals ``e`` (N, 2) and Jacobians in one array ``J`` (N, 2, 9 + G_o).

    The columns of ``J`` are the eliminated block's, the kept block's (points
    or poses, :attr:`Problem.eliminate`), then the globals': the order of the
    normal equations' Schur blocks (:func:`stages.adjust.normal.assemble`),
    written in place, so that no copy stacks them.
    """
    basis = _ap_basis(state, problem, derivatives=True) if problem.n_ap else None
    if projection is None:
        p, p_ref, R_pose, R_rop = camera_points(state, problem)
        _, e = _residuals_from_camera(state, problem, p, None if basis is None else basis[0])
    else:
        (p, p_ref, R_pose, R_rop), e = projection.camera, projection.e
    l11, l21, l22 = (problem.linv[:, i] for i in range(3))
    iz = 1.0 / p[:, 2]
    u, v = p[:, 0] * iz, p[:, 1] * iz
    a = state.iop_px[problem.sys_idx, 2] * iz
    # Jp = -L^-1 ∂(projection)/∂p with ∂/∂p = a [[1, 0, -u], [0, 1, -v]], shape (N, 2, 3)
    Jp = np.empty((len(a), 2, 3))
    Jp[:, 0, 0] = -l11 * a
    Jp[:, 0, 1] = 0.0
    Jp[:, 0, 2] = l11 * a * u
    Jp[:, 1, 0] = -l21 * a
    Jp[:, 1, 1] = -l22 * a
    Jp[:, 1, 2] = a * (l21 * u + l22 * v)
    m = problem.n_reference  # the first observations, the reference system's (relative orientation the identity)
    if problem.n_systems == 1:
        K = Jp
        R_full = R_pose.take(problem.pose_idx, axis=0)
    else:
        K = Jp.copy()
        np.matmul(Jp[m:], R_rop.take(problem.sys_idx[m:], axis=0), out=K[m:])
        # R_s R_j of each (epoch, system) pair once, then gathered: far fewer pairs than observations
        R_pairs = (R_rop[None, :] @ R_pose[:, None]).reshape(-1, 3, 3)
        R_full = R_pairs.take(problem.pose_idx * problem.n_systems + problem.sys_idx, axis=0)
    J = np.empty((len(a), 2, 9 + problem.gcol.shape[1]))
    J_point, J_pose, J_glob = jacobian_blocks(problem, J)
    np.matmul(Jp, R_full, out=J_point)
    # ∂p/∂δθ = -R_s [p_ref]x, so each row k of K maps to p_ref x k
    _cross_rows(p_ref, K, J_pose[:, :, :3])
    np.negative(J_point, out=J_pose[:, :, 3:])
    # -L^-1 ∂(projection)/∂(xp, yp, c) with ∂/∂iop = [[1, 0, u], [0, 1, v]]
    J_glob[:, 0, 0] = -l11
    J_glob[:, 0, 1] = 0.0
    J_glob[:, 0, 2] = -l11 * u
    J_glob[:, 1, 0] = -l21
    J_glob[:, 1, 1] = -l22
    J_glob[:, 1, 2] = -(l21 * u + l22 * v)
    if problem.n_systems > 1:
        J_glob[:m, :, 3:9] = 0.0  # the reference system has no relative orientation (its columns are dropped)
        _cross_rows(p[m:], Jp[m:], J_glob[m:, :, 3:6])
        np.negative(K[m:], out=J_glob[m:, :, 6:9])
    if basis is not None:
        _ap_columns(state, problem, basis, J_glob)
    return e, J


def _cross_rows(a: np.ndarray, K: np.ndarray, out: np.ndarray) -> None:
    """``out[n, r] = a[n] x K[n, r]`` for ``a (N, 3)`` and ``K, out (N, 2, 3)``."""
    ax, ay, az = a[:, 0:1], a[:, 1:2], a[:, 2:3]
    kx, ky, kz = K[:, :, 0], K[:, :, 1], K[:, :, 2]
    out[:, :, 0] = ay * kz - az * ky
    out[:, :, 1] = az * kx - ax * kz
    out[:, :, 2] = ax * ky - ay * kx
