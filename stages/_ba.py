"""Numerics of the bundle adjustment in :mod:`stages.adjust`: residuals, problem, solver.

Split as in COLMAP's ``bundle_adjustment.h``:

- residual functions: :func:`linearize` (whitened residuals and analytic
  Jacobians of the collinearity equation for every observation at once);
- a problem builder: :class:`Problem` (indices, whitening, free/fixed
  parameters, the datum, the Schur ordering and its sort orders);
- the solver: :func:`solve` (Levenberg–Marquardt on the Student-t negative
  log-likelihood, a bordered Schur-complement step) and :func:`covariance`.

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
  polynomial distortion model of :mod:`stages._polynomial` (px), ``+= δ``:
  the ideal coordinates are then ``meas_px - Δ_AP(xy_px; xp, yp)``.

A row of the globals vector is one free IOP, ROP or AP parameter; per
observation the global columns are ``(xp, yp, c)``, then ``(δφ (3), δb (3))``
with several systems, then the 7 APs when estimated, of its system, and
:attr:`Problem.gcol` maps them into the globals vector (``-1`` for fixed or
absent ones).
"""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from fluorocal.stages import _polynomial
from fluorocal.stages._geometry import quat_multiply, quat_normalize, quat_to_matrix, rotvec_to_quat
from fluorocal.stages.errors import EstimationError

log = logging.getLogger(__name__)

N_GLOBAL_COLS = 9  # per observation: IOP (3) + ROP rotation (3) + ROP translation (3); the APs follow
_CHUNK = 32768  # observations per chunk in the covariance pass (bounds memory)
_MU_MIN, _MU_MAX = 1e-12, 1e16  # Marquardt damping range
_MU_NUMERICAL = 1e6  # damping beyond which a failing step means the optimum is reached


# --------------------------------------------------------------------------- state


@dataclass(frozen=True)
class State:
    """The estimated quantities (internal, mutable by :func:`apply_step` copies only).

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
        Additional parameters (:mod:`stages._polynomial`); None: all zero.
    """

    points_mm: np.ndarray
    q: np.ndarray
    source_mm: np.ndarray
    iop_px: np.ndarray
    rop_q: np.ndarray
    rop_source_mm: np.ndarray
    ap_px: np.ndarray | None = None


# --------------------------------------------------------------------------- problem


@dataclass(frozen=True)
class Problem:
    """Everything about the problem that does not change during a solve.

    Observations are stored sorted by (eliminated block, system) so that the
    eliminated blocks' sums are contiguous segments (``np.add.reduceat``).

    Attributes
    ----------
    point_idx, pose_idx, sys_idx : (N,) int64 ndarray
    meas_px : (N, 2) float64 ndarray, px
        Measured coordinates minus the distortion correction (ideal coordinates).
    linv : (N, 3) float64 ndarray
        ``(l11, l21, l22)`` of the lower-triangular ``L^-1`` with ``C = L L^T``.
    n_points, n_poses, n_systems, n_globals : int
    gcol : (S, G_o) int64 ndarray
        Column of each per-observation global parameter in the globals vector, -1 if fixed:
        3 IOP, then 6 ROP with several systems, then 7 APs when estimated.
    datum : (n, 3, 7) float64 ndarray
        Inner-constraint directions (translation, rotation, scale) at the nominal points.
    eliminate : str
        ``"points"`` or ``"poses"``: the block type removed by the Schur complement.
    e_idx, k_idx : (N,) int64 ndarray
        Eliminated and kept block of each observation.
    e_starts, es_starts : int64 ndarray
        Segment starts of the eliminated blocks and of (eliminated block, system).
    k_order, k_starts, ks_starts : int64 ndarray
        Observation order sorted by (kept block, system) and its segment starts.
    ek_flat : tuple
        Per system ``(selection or None, flat indices)`` of each observation's
        ``be x bk`` coupling block in ``B`` laid out ``(ne, be, r)``.
    ap_xy_px : (N, 2) float64 ndarray or None, px
        Measured coordinates (before any correction), where the APs are evaluated; None without APs.
    ap_radius_px : (S,) float64 ndarray or None, px
        Reference radius ``r0`` of each system's AP model; None: no APs.
    """

    point_idx: np.ndarray
    pose_idx: np.ndarray
    sys_idx: np.ndarray
    meas_px: np.ndarray
    linv: np.ndarray
    n_points: int
    n_poses: int
    n_systems: int
    n_globals: int
    gcol: np.ndarray
    datum: np.ndarray
    eliminate: str
    # derived sort structures
    e_idx: np.ndarray
    k_idx: np.ndarray
    e_starts: np.ndarray
    es_starts: np.ndarray
    es_e: np.ndarray
    es_s: np.ndarray
    k_order: np.ndarray
    k_starts: np.ndarray
    ks_starts: np.ndarray
    ks_k: np.ndarray
    ks_s: np.ndarray
    ek_flat: tuple
    ap_xy_px: np.ndarray | None = None
    ap_radius_px: np.ndarray | None = None

    @property
    def n_obs(self) -> int:
        return len(self.point_idx)

    @property
    def n_ap(self) -> int:
        """Additional parameters per system (0 or 7)."""
        return 0 if self.ap_radius_px is None else _polynomial.N_AP

    @property
    def ap_start(self) -> int:
        """First AP column of :attr:`gcol` (after the IOP and, with several systems, the ROP)."""
        return _ap_start(self.n_systems)

    @property
    def be(self) -> int:
        return 3 if self.eliminate == "points" else 6

    @property
    def bk(self) -> int:
        return 6 if self.eliminate == "points" else 3

    @property
    def ne(self) -> int:
        return self.n_points if self.eliminate == "points" else self.n_poses

    @property
    def nk(self) -> int:
        return self.n_poses if self.eliminate == "points" else self.n_points

    @property
    def n_kept(self) -> int:
        """Size of the reduced (kept) system without the 7 datum multipliers."""
        return self.nk * self.bk + self.n_globals

    @property
    def n_free(self) -> int:
        """Number of free parameters (before the 7 datum constraints)."""
        return 3 * self.n_points + 6 * self.n_poses + self.n_globals


def _ap_start(n_systems: int) -> int:
    """First AP column of :attr:`Problem.gcol`."""
    return N_GLOBAL_COLS if n_systems > 1 else 3


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


def datum_directions(nominal_mm: np.ndarray) -> np.ndarray:
    """Inner-constraint matrix rows ``(n, 3, 7)``: translation, rotation, scale at ``nominal_mm``.

    Columns are scaled to comparable magnitude (rotation and scale by the RMS
    radius) so that the bordered system is well conditioned.
    """
    centred = nominal_mm - nominal_mm.mean(0)
    radius = float(np.sqrt((centred**2).sum(1).mean())) or 1.0
    a = centred / radius
    n = len(a)
    d = np.zeros((n, 3, 7))
    d[:, [0, 1, 2], [0, 1, 2]] = 1.0
    # d(R P)/dω = -[P]x : columns of the rotation part
    x, y, z = a.T
    d[:, 0, 4], d[:, 0, 5] = z, -y
    d[:, 1, 3], d[:, 1, 5] = -z, x
    d[:, 2, 3], d[:, 2, 4] = y, -x
    d[:, :, 6] = a
    return d


def _segments(keys: np.ndarray) -> np.ndarray:
    """Start indices of runs of equal values in a sorted 1-D array."""
    if len(keys) == 0:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])


def build_problem(
    point_idx: np.ndarray,
    pose_idx: np.ndarray,
    sys_idx: np.ndarray,
    meas_px: np.ndarray,
    sigma_px: np.ndarray,
    nominal_mm: np.ndarray,
    n_poses: int,
    n_systems: int,
    iop_free: np.ndarray,
    eliminate: str,
    *,
    xy_px: np.ndarray | None = None,
    ap_radius_px: np.ndarray | None = None,
    ap_free: np.ndarray | None = None,
) -> tuple[Problem, np.ndarray]:
    """Sort the observations and set up indices, whitening, parameter columns and the datum.

    ``ap_radius_px`` ``(S,)`` (px) adds every system's 7 APs to the globals,
    evaluated at the measured coordinates ``xy_px`` ``(N, 2)`` (default ``meas_px``);
    those where the mask ``ap_free`` ``(7,)`` is False are held at their state values.

    Returns
    -------
    problem : Problem
    perm : (N,) int64 ndarray
        ``problem`` arrays are the inputs taken at ``perm``.
    """
    n_points = len(nominal_mm)
    if eliminate == "auto":
        eliminate = "points" if 6 * n_poses < 3 * n_points else "poses"
    e_all, k_all = (point_idx, pose_idx) if eliminate == "points" else (pose_idx, point_idx)
    perm = np.lexsort((k_all, sys_idx, e_all))
    point_idx, pose_idx, sys_idx = point_idx[perm], pose_idx[perm], sys_idx[perm]
    e_idx, k_idx = e_all[perm], k_all[perm]
    n_sys_keys = max(n_systems, 1)
    e_starts = _segments(e_idx)
    es_key = e_idx * n_sys_keys + sys_idx
    es_starts = _segments(es_key)
    k_order = np.lexsort((sys_idx, k_idx))
    k_sorted = k_idx[k_order]
    k_starts = _segments(k_sorted)
    ks_key = k_sorted * n_sys_keys + sys_idx[k_order]
    ks_starts = _segments(ks_key)

    n_ap = 0 if ap_radius_px is None else _polynomial.N_AP
    ap_start = _ap_start(n_systems)
    gcol = -np.ones((n_systems, ap_start + n_ap), dtype=np.int64)
    n_globals = 0
    for s in range(n_systems):
        if iop_free[s]:
            gcol[s, :3] = np.arange(n_globals, n_globals + 3)
            n_globals += 3
        if s > 0:
            gcol[s, 3:N_GLOBAL_COLS] = np.arange(n_globals, n_globals + 6)
            n_globals += 6
        if n_ap:
            free = np.flatnonzero(np.ones(n_ap, bool) if ap_free is None else ap_free)
            gcol[s, ap_start + free] = np.arange(n_globals, n_globals + len(free))
            n_globals += len(free)

    be, bk = (3, 6) if eliminate == "points" else (6, 3)
    n_kept = (n_poses if eliminate == "points" else n_points) * bk + n_globals
    ek_flat = []
    for s in range(n_systems):
        sel = np.flatnonzero(sys_idx == s) if n_systems > 1 else None
        e_s, k_s = (e_idx, k_idx) if sel is None else (e_idx[sel], k_idx[sel])
        # B laid out (ne, be, r): flat index of row (e, a), column k * bk + b
        flat = (
            (e_s[:, None, None] * be + np.arange(be)[None, :, None]) * n_kept + k_s[:, None, None] * bk + np.arange(bk)
        )
        ek_flat.append((sel, flat.reshape(-1)))
    problem = Problem(
        point_idx=point_idx,
        pose_idx=pose_idx,
        sys_idx=sys_idx,
        meas_px=meas_px[perm],
        linv=whitening(sigma_px[perm]),
        n_points=n_points,
        n_poses=n_poses,
        n_systems=n_systems,
        n_globals=n_globals,
        gcol=gcol,
        datum=datum_directions(nominal_mm),
        eliminate=eliminate,
        e_idx=e_idx,
        k_idx=k_idx,
        e_starts=e_starts,
        es_starts=es_starts,
        es_e=e_idx[es_starts],
        es_s=sys_idx[es_starts],
        k_order=k_order,
        k_starts=k_starts,
        ks_starts=ks_starts,
        ks_k=k_sorted[ks_starts],
        ks_s=sys_idx[k_order][ks_starts],
        ek_flat=tuple(ek_flat),
        ap_xy_px=None if n_ap == 0 else (meas_px if xy_px is None else xy_px)[perm],
        ap_radius_px=None if n_ap == 0 else np.asarray(ap_radius_px, dtype=np.float64).reshape(n_systems),
    )
    return problem, perm


# --------------------------------------------------------------------------- residuals


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
    d = state.points_mm[problem.point_idx] - state.source_mm[problem.pose_idx]
    p_ref = np.einsum("nij,nj->ni", R_pose[problem.pose_idx], d)
    if problem.n_systems == 1:
        return p_ref, p_ref, R_pose, R_rop
    s = problem.sys_idx
    p = np.einsum("nij,nj->ni", R_rop[s], p_ref - state.rop_source_mm[s])
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


def _residuals_from_camera(
    state: State, problem: Problem, p: np.ndarray, ap_basis: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    z = p[:, 2]
    if not np.all(z > 1e-6):
        raise FloatingPointError("point at or behind the source")
    iop = state.iop_px[problem.sys_idx]
    f = iop[:, :2] + iop[:, 2:3] * p[:, :2] / z[:, None]
    r = problem.meas_px - f
    if problem.n_ap:
        B = _ap_basis(state, problem) if ap_basis is None else ap_basis
        r -= np.einsum("nij,nj->ni", B, ap_values(state, problem)[problem.sys_idx])
    return r, whiten(problem.linv, r)


def ap_values(state: State, problem: Problem) -> np.ndarray:
    """The APs ``(S, n_ap)`` px of ``state`` (zeros where the state holds none)."""
    return np.zeros((problem.n_systems, problem.n_ap)) if state.ap_px is None else state.ap_px


def _ap_basis(state: State, problem: Problem, *, derivatives: bool = False):
    """The AP design matrix ``(N, 2, 7)`` at every observation (and its ``u``, ``v`` derivatives), see :func:`stages._polynomial.basis`."""
    s = problem.sys_idx
    return _polynomial.basis(problem.ap_xy_px, state.iop_px[s, :2], problem.ap_radius_px[s], derivatives=derivatives)


def _ap_columns(state: State, problem: Problem, basis: tuple, J_glob: np.ndarray) -> None:
    """Fill the AP columns of ``J_glob`` and add the APs' dependence on the principal point to its ``xp``, ``yp`` columns.

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


def linearize(state: State, problem: Problem) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Whitened residuals and their analytic Jacobians for every observation.

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
    p, p_ref, R_pose, R_rop = camera_points(state, problem)
    basis = _ap_basis(state, problem, derivatives=True) if problem.n_ap else None
    _, e = _residuals_from_camera(state, problem, p, None if basis is None else basis[0])
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
    if problem.n_systems == 1:
        K = Jp
        R_full = R_pose[problem.pose_idx]
    else:
        R_s = R_rop[problem.sys_idx]
        K = Jp @ R_s
        R_full = R_s @ R_pose[problem.pose_idx]
    J_point = Jp @ R_full
    J_pose = np.empty((len(a), 2, 6))
    # ∂p/∂δθ = -R_s [p_ref]x, so each row k of K maps to p_ref x k
    _cross_rows(p_ref, K, J_pose[:, :, :3])
    np.negative(J_point, out=J_pose[:, :, 3:])
    n_g = problem.gcol.shape[1]
    J_glob = np.empty((len(a), 2, n_g))
    # -L^-1 ∂(projection)/∂(xp, yp, c) with ∂/∂iop = [[1, 0, u], [0, 1, v]]
    J_glob[:, 0, 0] = -l11
    J_glob[:, 0, 1] = 0.0
    J_glob[:, 0, 2] = -l11 * u
    J_glob[:, 1, 0] = -l21
    J_glob[:, 1, 1] = -l22
    J_glob[:, 1, 2] = -(l21 * u + l22 * v)
    if problem.n_systems > 1:
        _cross_rows(p, Jp, J_glob[:, :, 3:6])
        np.negative(K, out=J_glob[:, :, 6:9])
    if basis is not None:
        _ap_columns(state, problem, basis, J_glob)
    return e, J_point, J_pose, J_glob


def _cross_rows(a: np.ndarray, K: np.ndarray, out: np.ndarray) -> None:
    """``out[n, r] = a[n] x K[n, r]`` for ``a (N, 3)`` and ``K, out (N, 2, 3)``."""
    ax, ay, az = a[:, 0:1], a[:, 1:2], a[:, 2:3]
    kx, ky, kz = K[:, :, 0], K[:, :, 1], K[:, :, 2]
    out[:, :, 0] = ay * kz - az * ky
    out[:, :, 1] = az * kx - ax * kz
    out[:, :, 2] = ax * ky - ay * kx


# --------------------------------------------------------------------------- robust cost


def t_weights(s: np.ndarray, nu: float, scale2: float) -> np.ndarray:
    """IRLS weights ``(ν + 2) / (ν + s/σ²)`` of a 2-D Student-t; 1 for ``ν = inf``."""
    if math.isinf(nu):
        return np.ones_like(s)
    return (nu + 2.0) / (nu + s / scale2)


def t_cost(s: np.ndarray, nu: float, scale2: float) -> float:
    """Negative log-likelihood of squared Mahalanobis norms ``s`` (constants dropped).

    ``Σ (ν+2)/2 log(1 + s/(ν σ²)) + N log σ²``; as ``ν -> inf`` this tends to the
    Gaussian ``Σ s/(2σ²) + N log σ²``. For a 2-D t the normalising constant does
    not depend on ν, so this is also the objective for ν.
    """
    if math.isinf(nu):
        rho = 0.5 * s / scale2
    else:
        rho = 0.5 * (nu + 2.0) * np.log1p(s / (nu * scale2))
    return float(rho.sum() + len(s) * math.log(scale2))


def ml_scale(s: np.ndarray, nu: float, scale2: float, *, iterations: int = 100, rtol: float = 1e-10) -> float:
    """Maximum-likelihood variance factor σ² of a 2-D t for fixed residuals (EM fixed point)."""
    if len(s) == 0:
        return scale2
    floor = 1e-12 * max(float(np.mean(s)), 1e-300)
    for _ in range(iterations):
        new = max(float(np.mean(t_weights(s, nu, scale2) * s)) / 2.0, floor, 1e-300)
        if abs(new - scale2) <= rtol * new:
            return new
        scale2 = new
    return scale2


def ml_nu(s: np.ndarray, scale2: float, bounds: tuple[float, float]) -> float:
    """Maximum-likelihood degrees of freedom of a 2-D t for fixed residuals and scale."""
    from scipy.optimize import minimize_scalar

    res = minimize_scalar(
        lambda log_nu: t_cost(s, math.exp(log_nu), scale2),
        bounds=(math.log(bounds[0]), math.log(bounds[1])),
        method="bounded",
        options={"xatol": 1e-3},
    )
    return float(math.exp(res.x))


# --------------------------------------------------------------------------- normal equations


def _outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per observation ``a^T b`` for ``(N, 2, I)`` and ``(N, 2, J)`` -> ``(N, I, J)``."""
    return np.matmul(a.transpose(0, 2, 1), b)


def _segment_grams(J: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """``Σ J_n^T J_n`` over each run of observations ``starts[i]:starts[i+1]`` of ``J (N, 2, c)`` -> ``(runs, c, c)``.

    One BLAS product per run: the runs (one per kept block and system) are few
    and long, where a batched per-observation product would be memory bound.
    """
    flat = J.reshape(-1, J.shape[2])
    bounds = 2 * np.r_[starts, len(J)]
    out = np.empty((len(starts), J.shape[2], J.shape[2]))
    for i in range(len(starts)):
        seg = flat[bounds[i] : bounds[i + 1]]
        out[i] = seg.T @ seg
    return out


def _atb(a: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Per observation ``a^T e`` for ``(N, 2, I)`` and ``(N, 2)`` -> ``(N, I)``."""
    return a[:, 0, :] * e[:, :1] + a[:, 1, :] * e[:, 1:]


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


def weighted_jacobian(problem: Problem, e, J_point, J_pose, J_glob, w) -> tuple[np.ndarray, np.ndarray]:
    """``sqrt(w)``-weighted stacked Jacobian ``[J_eliminated | J_kept | J_globals]`` (N, 2, nt) and residuals (N, 2)."""
    JE, JK = (J_point, J_pose) if problem.eliminate == "points" else (J_pose, J_point)
    sw = np.sqrt(w)[:, None, None]
    J = np.concatenate([JE, JK, J_glob], axis=2)
    J *= sw
    return J, e * sw[:, :, 0]


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
    along = np.einsum("nij,ni->nj", J, n_dir) * alpha[:, None]
    return J - np.einsum("ni,nj->nij", n_dir, along)


def gradient(problem: Problem, J: np.ndarray, ew: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``b = -Σ w J^T e`` split into the eliminated ``(ne, be)`` and kept ``(r,)`` parts."""
    be, bk, nk, G = problem.be, problem.bk, problem.nk, problem.n_globals
    bj = -_atb(J, ew)  # shape (N, nt)
    b_e = np.add.reduceat(bj[:, :be], problem.e_starts, axis=0)
    b_y = np.zeros(nk * bk + G + 1)
    bk_sorted = bj[problem.k_order, be:]
    b_y[: nk * bk] = np.add.reduceat(bk_sorted[:, :bk], problem.k_starts, axis=0).reshape(-1)
    bg = np.add.reduceat(bk_sorted[:, bk:], problem.ks_starts, axis=0)
    gcols = _gcols(problem, nk * bk, nk * bk + G + 1)
    for s in range(problem.n_systems):
        np.add.at(b_y, gcols[s], bg[problem.ks_s == s].sum(0))
    return b_e, b_y[:-1]


def assemble(problem: Problem, J: np.ndarray, ew: np.ndarray, J_hessian: np.ndarray | None = None) -> Normal:
    """Weighted normal equations ``Σ w J^T J`` and ``-Σ w J^T e`` in Schur blocks (no loops over observations).

    ``J, ew`` from :func:`weighted_jacobian` (the gradient); ``J_hessian``
    replaces ``J`` in ``H`` if given (:func:`triggs_corrected`). Batched products of the
    per-observation Jacobians are accumulated by segment sums
    (``np.add.reduceat``) over observations pre-sorted by the eliminated block
    (and, through ``k_order``, by the kept block).
    """
    ne, nk, be, bk, G = problem.ne, problem.nk, problem.be, problem.bk, problem.n_globals
    r = nk * bk + G
    b_e, b_y = gradient(problem, J, ew)
    if J_hessian is not None:
        J = J_hessian
    kk = be + bk
    OE = _outer(J[:, :, :be], J)  # shape (N, be, nt): eliminated rows
    A = np.add.reduceat(OE[:, :, :be], problem.e_starts, axis=0)
    EK = OE[:, :, be:kk].reshape(len(J), -1)
    B = np.zeros(ne * be * r)
    for i, (sel, flat) in enumerate(problem.ek_flat):
        # within one system each (eliminated, kept) pair is observed at most once
        if i == 0:
            B[flat] = EK[sel].ravel() if sel is not None else EK.ravel()
        else:
            B[flat] += EK[sel].ravel()
    B = B.reshape(ne, be, r)
    Eg = np.add.reduceat(OE[:, :, kk:], problem.es_starts, axis=0)
    gcols = _gcols(problem, nk * bk, r + 1)
    valid = gcols[problem.es_s] < r  # fixed globals point past the end
    e_rows = np.broadcast_to(problem.es_e[:, None, None], Eg.shape)
    a_rows = np.broadcast_to(np.arange(be)[None, :, None], Eg.shape)
    g_cols = np.broadcast_to(gcols[problem.es_s][:, None, :], Eg.shape)
    keep = np.broadcast_to(valid[:, None, :], Eg.shape)
    np.add.at(B, (e_rows[keep], a_rows[keep], g_cols[keep]), Eg[keep])

    rg = r + 1  # the extra last column collects fixed globals and is dropped
    Hyy = np.zeros((rg, rg))
    KS = _segment_grams(J[problem.k_order, :, be:], problem.ks_starts)  # shape (n_ks, bk + ng, bk + ng)
    KK = np.add.reduceat(KS[:, :bk, :bk], _segments(problem.ks_k), axis=0)
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
    Gm = np.einsum("nab,nbr->nar", Linv, normal.B.reshape(ne, be, r)).reshape(ne * be, r)
    D_e, D_y = _datum_split(problem)
    LD = np.einsum("nab,nbk->nak", Linv, D_e).reshape(ne * be, 7)
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


def split_step(problem: Problem, de: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step as ``(δpoints (n, 3), δposes (m, 6), δglobals (G,))``."""
    nkb = problem.nk * problem.bk
    kept = dy[:nkb].reshape(problem.nk, problem.bk)
    if problem.eliminate == "points":
        return de, kept, dy[nkb:]
    return kept, de, dy[nkb:]


def apply_step(state: State, problem: Problem, d_points, d_poses, d_glob) -> State:
    """The state after a step, with the quaternions updated multiplicatively."""
    iop = state.iop_px.copy()
    rop_q = state.rop_q.copy()
    rop_t = state.rop_source_mm.copy()
    ap = ap_values(state, problem).copy() if problem.n_ap else state.ap_px
    g = np.r_[d_glob, 0.0]  # fixed globals (-1) read the trailing zero
    for s in range(problem.n_systems):
        cols = problem.gcol[s]
        if cols[0] >= 0:
            iop[s] += g[cols[:3]]
        if problem.n_systems > 1 and cols[3] >= 0:
            rop_q[s] = quat_normalize(quat_multiply(rotvec_to_quat(g[cols[3:6]]), rop_q[s]))
            rop_t[s] += g[cols[6:9]]
        if problem.n_ap:
            ap[s] += g[cols[problem.ap_start :]]
    return State(
        points_mm=state.points_mm + d_points,
        q=quat_normalize(quat_multiply(rotvec_to_quat(d_poses[:, :3]), state.q)),
        source_mm=state.source_mm + d_poses[:, 3:],
        iop_px=iop,
        rop_q=rop_q,
        rop_source_mm=rop_t,
        ap_px=ap,
    )


# --------------------------------------------------------------------------- solver


@dataclass(frozen=True)
class SolverOptions:
    """Levenberg–Marquardt settings (see :class:`stages.adjust.AdjustParams`)."""

    nu: float
    estimate_nu: bool
    nu_bounds: tuple[float, float]
    estimate_scale: bool
    max_iterations: int
    function_tolerance: float
    parameter_tolerance: float
    initial_damping: float


@dataclass(frozen=True)
class SolverResult:
    state: State
    nu: float
    scale2: float
    cost_history: tuple
    iterations: int
    stop_reason: str
    converged: bool


def _cost_at(state: State, problem: Problem, nu: float, scale2: float) -> tuple[float, np.ndarray]:
    try:
        _, e = residuals(state, problem)
    except FloatingPointError:
        return math.inf, np.empty(0)
    s = (e * e).sum(1)
    return t_cost(s, nu, scale2), s


def _update_hyper(s: np.ndarray, nu: float, scale2: float, options: SolverOptions) -> tuple[float, float]:
    """Coordinate-descent update of (σ², ν) for fixed residuals; never increases the cost."""
    for _ in range(3 if options.estimate_nu else 1):
        if options.estimate_scale:
            scale2 = ml_scale(s, nu, scale2)
        if options.estimate_nu:
            nu = ml_nu(s, scale2, options.nu_bounds)
    return nu, scale2


def solve(state: State, problem: Problem, options: SolverOptions) -> SolverResult:
    """Levenberg–Marquardt on the Student-t negative log-likelihood (exact gradient).

    The Hessian is the IRLS one ``Σ w J^T J`` until σ² settles, then with
    Triggs' curvature correction (:func:`triggs_corrected`), which turns the
    IRLS tail's linear convergence into a faster one.

    Every accepted step lowers ``F(θ, σ², ν)``; after it, σ² (and ν) are set to
    their maximum-likelihood values for the new residuals, which lowers it
    further, so the cost history is monotone.
    """
    nu = options.nu
    cost, s = _cost_at(state, problem, nu, 1.0)
    if not math.isfinite(cost):
        raise EstimationError("the initial orientation puts observed points at or behind the X-ray source")
    scale2 = 1.0
    nu, scale2 = _update_hyper(s, nu, scale2, options)
    cost = t_cost(s, nu, scale2)
    history = [cost]
    mu = options.initial_damping
    growth = 2.0
    stop = f"maximum number of iterations ({options.max_iterations}) reached"
    converged = False
    iteration = 0
    normal = None  # the linearisation at ``state``; None after a move
    settled = False  # σ² changed by < 5 % at the last accepted step
    while iteration < options.max_iterations:
        iteration += 1
        if normal is None:
            e, J_point, J_pose, J_glob = linearize(state, problem)
            s_now = (e * e).sum(1)
            J, ew = weighted_jacobian(problem, e, J_point, J_pose, J_glob, t_weights(s_now, nu, scale2))
            # near the optimum (σ² settled) the IRLS curvature overstates the t's: correct it there only,
            # since far away the corrected model oversteps
            J_h = triggs_corrected(J, ew, s_now / scale2, nu) if settled else None
            normal = assemble(problem, J, ew, J_h)
            del J, J_h, ew, J_point, J_pose, J_glob
        try:
            factor = factorize(problem, normal, mu)
            de, dy = step_from(problem, factor, normal.b_e, normal.b_y)
        except SingularStep:
            if mu >= _MU_NUMERICAL and len(history) > 1:
                # only reached after a long run of rejected steps at the optimum
                stop, converged = "no further decrease within numerical precision", True
                break
            if mu >= _MU_MAX:
                raise
            mu = min(max(mu, _MU_MIN) * 10.0, _MU_MAX)
            continue
        d_points, d_poses, d_glob = split_step(problem, de, dy)
        trial = apply_step(state, problem, d_points, d_poses, d_glob)
        new_cost, s_new = _cost_at(trial, problem, nu, scale2)
        step = np.concatenate([de.ravel(), dy])
        # decrease predicted by the quadratic model, in cost units (H and b are without 1/σ²):
        # (H + μ diag H) δ = b on the constraint surface gives ½ (b·δ + μ δ^T diag(H) δ)
        b = np.concatenate([normal.b_e.ravel(), normal.b_y])
        predicted = 0.5 * (b @ step + mu * (factor.diag_h * step * step).sum()) / scale2
        actual = cost - new_cost
        x_norm = math.sqrt(float((state.points_mm**2).sum() + (state.source_mm**2).sum() + (state.iop_px**2).sum()))
        small_step = float(np.linalg.norm(step)) <= options.parameter_tolerance * (x_norm + options.parameter_tolerance)
        if math.isfinite(new_cost) and actual > 0 and predicted > 0:
            rho = actual / predicted
            state = trial
            normal = None
            mu = max(mu * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), _MU_MIN)
            growth = 2.0
            previous_scale2 = scale2
            nu, scale2 = _update_hyper(s_new, nu, scale2, options)
            settled = not math.isinf(nu) and abs(scale2 / previous_scale2 - 1) < 0.05
            new_total = t_cost(s_new, nu, scale2)
            change = cost - new_total
            cost = new_total
            history.append(cost)
            if change <= options.function_tolerance:
                stop, converged = "cost change below function_tolerance", True
                break
            if small_step:
                stop, converged = "step below parameter_tolerance", True
                break
        else:
            if (
                small_step
                or 0 <= predicted <= options.function_tolerance
                or (math.isfinite(new_cost) and abs(actual) <= options.function_tolerance)
            ):
                stop, converged = "no further decrease within the tolerances", True
                break
            mu *= growth
            growth *= 2.0
            if mu > _MU_MAX:
                stop = f"damping exceeded {_MU_MAX:g} without decrease"
                break
    log.debug("LM stopped after %d iterations: %s (cost %.6g, σ² %.4g, ν %.3g)", iteration, stop, cost, scale2, nu)
    return SolverResult(
        state=state,
        nu=nu,
        scale2=scale2,
        cost_history=tuple(history),
        iterations=iteration,
        stop_reason=stop,
        converged=converged,
    )


# --------------------------------------------------------------------------- covariance


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
    e, J_point, J_pose, J_glob = linearize(state, problem)
    normal = assemble(problem, *weighted_jacobian(problem, e, J_point, J_pose, J_glob, w))
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
