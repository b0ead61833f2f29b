"""The result summary of the bundle adjustment: :class:`Adjustment`, with the ``usable`` flag.

:func:`summarise` turns a solution of :func:`stages.adjust.solver.solve` into
the statistics (σ0, redundancy, standardised residuals, the scaled
covariance) and the per-observation outputs in input order.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING

import numpy as np
from fluorocal.stages.adjust import polynomial
from fluorocal.stages.adjust.collinearity import residuals
from fluorocal.stages.adjust.covariance import (
    covariance,
    covariance_factor,
    observation_statistics,
    without_covariance,
)
from fluorocal.stages.adjust.orientation import Orientation
from fluorocal.stages.adjust.robust import t_weights
from fluorocal.stages.artifacts import SCHEMA_VERSION, freeze
from fluorocal.stages.errors import EstimationError

if TYPE_CHECKING:
    from fluorocal.stages.adjust.bundle import Prepared
    from fluorocal.stages.adjust.options import SolverOptions
    from fluorocal.stages.adjust.solver import SolverResult

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Adjustment:
    """Result of :func:`adjust_bundle`.

    Per-observation arrays have one row per input observation, in input order;
    observations that did not enter the adjustment (``used`` False) have zero
    residuals, weight 0 and ``inlier`` False.

    Attributes
    ----------
    bead_id : (n,) int64 ndarray
        Estimated beads.
    xyz_mm : (n, 3) float64 ndarray, mm
        In the nominal frame (inner constraints: no translation, rotation or
        scale relative to the nominal coordinates).
    xyz_std_mm : (n, 3) float64 ndarray, mm
    xyz_cov_mm2 : (n, 3, 3) float64 ndarray, mm²
        Per bead covariance (inner-constraint datum).
    iop_px, iop_std_px : (S, 3) float64 ndarray, px
        Std 0 where the IOP were held fixed.
    iop_cov_px2 : (S, 3, 3) float64 ndarray, px²
    exposure : (M,) int64 ndarray
    q_cam_from_obj : (M, 4) float64 ndarray
    source_mm : (M, 3) float64 ndarray, mm
    pose_std : (M, 6) float64 ndarray
        Rotation std (rad, about the camera axes) and source std (mm).
    rop_q : (S, 4) float64 ndarray
    rop_source_mm : (S, 3) float64 ndarray, mm
    rop_std : (S, 6) float64 ndarray
        Rotation std (rad) and source std (mm); zero for system 0.
    residual_px : (N, 2) float64 ndarray, px
        ``(xy - Δ - Δ_AP) - projection`` (``Δ_AP`` the polynomial model, if estimated).
    standardized_residual : (N, 2) float64 ndarray
        ``v / (σ0 σ sqrt(r))`` per coordinate (Baarda's w).
    redundancy : (N, 2) float64 ndarray
        Diagonal of ``Q_vv P`` per coordinate; sums to ``dof``.
    weight : (N,) float64 ndarray
        Final t-weight ``(ν+2)/(ν+r²/σ²)``.
    inlier : (N,) bool ndarray
    used : (N,) bool ndarray
    sigma0 : float
        A posteriori standard deviation of unit weight from the inliers.
    t_scale : float
        Maximum-likelihood scale σ of the t relative to ``sigma_px``.
    nu : float
    dof : int
        ``2 N_used - (n_free - 7)``.
    n_parameters : int
        Free parameters (before the 7 datum constraints).
    cost_history : tuple of float
        Negative log-likelihood (up to a constant) after each accepted step.
    iterations : int
    stop_reason : str
    converged : bool
    usable : bool
        Converged, finite, and at least ``min_inlier_fraction`` inliers.
    system_names : tuple of str
    additional_parameters : str
        ``"none"`` or ``"polynomial"`` (:class:`stages.adjust.FreeParameters`).
    ap_px, ap_std_px : (S, 7) float64 ndarray, px
        Coefficients ``k1, k2, k3, p1, p2, b1, b2`` (:data:`stages.adjust.polynomial.AP_NAMES`)
        of each system's polynomial distortion model and their standard
        deviations; zero when not estimated.
    ap_cov_px2 : (S, 7, 7) float64 ndarray, px²
    ap_radius_px : (S,) float64 ndarray, px
        The model's reference radius ``r0`` per system (1 when not estimated).
    """

    bead_id: np.ndarray
    xyz_mm: np.ndarray
    xyz_std_mm: np.ndarray
    xyz_cov_mm2: np.ndarray
    iop_px: np.ndarray
    iop_std_px: np.ndarray
    iop_cov_px2: np.ndarray
    exposure: np.ndarray
    q_cam_from_obj: np.ndarray
    source_mm: np.ndarray
    pose_std: np.ndarray
    rop_q: np.ndarray
    rop_source_mm: np.ndarray
    rop_std: np.ndarray
    residual_px: np.ndarray
    standardized_residual: np.ndarray
    redundancy: np.ndarray
    weight: np.ndarray
    inlier: np.ndarray
    used: np.ndarray
    sigma0: float
    t_scale: float
    nu: float
    dof: int
    n_parameters: int
    cost_history: tuple
    iterations: int
    stop_reason: str
    converged: bool
    usable: bool
    system_names: tuple = ("A",)
    additional_parameters: str = "none"
    ap_px: np.ndarray | None = None
    ap_std_px: np.ndarray | None = None
    ap_cov_px2: np.ndarray | None = None
    ap_radius_px: np.ndarray | None = None
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self):
        n_sys, n_ap = len(np.asarray(self.iop_px).reshape(-1, 3)), polynomial.N_AP
        for name, shape, fill in (
            ("ap_px", (n_sys, n_ap), 0.0),
            ("ap_std_px", (n_sys, n_ap), 0.0),
            ("ap_cov_px2", (n_sys, n_ap, n_ap), 0.0),
            ("ap_radius_px", (n_sys,), 1.0),
        ):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(shape, fill))
        check_finite_and_freeze(self)

    def polynomial_correction(self, system: int, xy_px: np.ndarray) -> np.ndarray:
        """``Δ_AP`` (N, 2) px of ``system``'s estimated polynomial model at measured ``xy_px`` (N, 2) px (or 0)."""
        return polynomial.correction_at(xy_px, self.iop_px[system, :2], self.ap_radius_px[system], self.ap_px[system])

    @property
    def orientation(self) -> Orientation:
        """The estimated orientation (for example to start the next solve of the learning loop)."""
        return Orientation(
            iop_px=self.iop_px,
            exposure=self.exposure,
            q_cam_from_obj=self.q_cam_from_obj,
            source_mm=self.source_mm,
            rop_q=self.rop_q,
            rop_source_mm=self.rop_source_mm,
            system_names=self.system_names,
        )


def check_finite_and_freeze(result) -> None:
    """Raise :class:`EstimationError` if a float array of an adjustment result is not finite; freeze it."""
    for f in fields(result):
        value = getattr(result, f.name)
        if isinstance(value, np.ndarray) and value.dtype.kind == "f" and not np.all(np.isfinite(value)):
            raise EstimationError(f"adjustment output {f.name} holds non-finite values")
    freeze(result)


def scatter(values: np.ndarray, where: np.ndarray, n: int, fill=0.0) -> np.ndarray:
    """Rows ``values`` placed at ``where`` of an ``n``-row array filled with ``fill``."""
    out = np.full((n,) + values.shape[1:], fill, dtype=values.dtype)
    out[where] = values
    return out


def summarise(
    observations,
    prepared: Prepared,
    solved: SolverResult,
    solver: SolverOptions,
    additional_parameters: str,
    compute_covariance: bool,
) -> Adjustment:
    """Statistics of the solution and the per-observation outputs in input order.

    ``usable``: converged, finite, and at least ``solver.min_inlier_fraction``
    of the used observations have a t-weight of at least ``solver.outlier_weight``.
    """
    problem, used, state = prepared.problem, prepared.used, solved.state
    r_px, s, w, dof, cov, c_h = _fit_statistics(solved, problem, compute_covariance)
    red, std_res, sigma0, inlier = observation_statistics(r_px, s, w, cov.hat, problem.linv, solver.outlier_weight)

    def std(c):
        return np.sqrt(np.clip(c_h * np.einsum("...ii->...i", c), 0.0, None))

    iop_std, iop_cov, rop_std, ap_std, ap_cov = _global_uncertainties(problem, cov.globals_, c_h)
    where = np.flatnonzero(used)[prepared.perm]  # back to input order

    def back(values, fill=0.0):
        return scatter(values, where, len(observations), fill)

    finite = all(np.all(np.isfinite(arr)) for arr in (state.points_mm, state.q, state.source_mm, state.iop_px, r_px))
    inlier_fraction = float(inlier.mean()) if problem.n_obs else 0.0
    unusable = _unusable(solved.converged, finite, inlier_fraction, solver.min_inlier_fraction)
    usable = not unusable
    log.debug(
        "adjustment: %d iterations (%s), σ0 %.3g, %.2f %% outliers, dof %d%s",
        solved.iterations,
        solved.stop_reason,
        sigma0,
        100 * (1 - inlier_fraction),
        dof,
        f"; not usable: {unusable}" if unusable else "",
    )
    n_ap = problem.n_ap
    return Adjustment(
        bead_id=prepared.ids[prepared.beads_used],
        xyz_mm=state.points_mm,
        xyz_std_mm=std(cov.points),
        xyz_cov_mm2=c_h * cov.points,
        iop_px=state.iop_px,
        iop_std_px=iop_std,
        iop_cov_px2=iop_cov,
        exposure=prepared.exposure,
        q_cam_from_obj=state.q,
        source_mm=state.source_mm,
        pose_std=std(cov.poses),
        rop_q=state.rop_q,
        rop_source_mm=state.rop_source_mm,
        rop_std=rop_std,
        residual_px=back(r_px),
        standardized_residual=back(std_res),
        redundancy=back(red),
        weight=back(w),
        inlier=back(inlier, False),
        used=used.copy(),
        sigma0=float(sigma0),
        t_scale=float(math.sqrt(solved.scale2)),
        nu=float(solved.nu),
        dof=int(dof),
        n_parameters=int(problem.n_free),
        cost_history=tuple(float(c) for c in solved.cost_history),
        iterations=int(solved.iterations),
        stop_reason=solved.stop_reason,
        converged=bool(solved.converged),
        usable=usable,
        system_names=tuple(observations.system_names),
        additional_parameters=additional_parameters,
        ap_px=state.ap_px if n_ap else None,
        ap_std_px=ap_std if n_ap else None,
        ap_cov_px2=ap_cov if n_ap else None,
        ap_radius_px=problem.ap_radius_px,
    )


def solution_weights(solved: SolverResult, problem) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals ``r_px`` (N, 2) px, squared whitened norms ``s`` (N,) and t-weights (N,) at the solution."""
    r_px, e = residuals(solved.state, problem)
    s = (e * e).sum(1)
    return r_px, s, t_weights(s, solved.nu, solved.scale2)


def _unusable(converged: bool, finite: bool, inlier_fraction: float, min_inlier_fraction: float) -> str:
    """Why a solution is not usable, "" when it is (:class:`Adjustment`'s ``usable``)."""
    if not converged:
        return "not converged"
    if not finite:
        return "non-finite parameters"
    if not inlier_fraction >= min_inlier_fraction:  # a NaN minimum is not met
        return f"fewer than {100 * min_inlier_fraction:.1f} % inliers"
    return ""


def _fit_statistics(solved: SolverResult, problem, compute_covariance: bool) -> tuple:
    """Residuals ``r_px`` (N, 2), ``s`` (N,), t-weights (N,), ``dof``, the cofactors and their factor ``c``."""
    r_px, s, w = solution_weights(solved, problem)
    u = problem.n_free - 7
    dof = 2 * problem.n_obs - u
    if dof <= 0:
        raise EstimationError(f"no redundancy: {2 * problem.n_obs} observations for {u} parameters")
    cov = covariance(solved.state, problem, w) if compute_covariance else without_covariance(problem, w, dof)
    return r_px, s, w, dof, cov, covariance_factor(s, w, solved.nu, solved.scale2, u, dof)


def _global_uncertainties(problem, cov_globals: np.ndarray, c_h: float) -> tuple:
    """Per system the IOP std (S, 3) and covariance (S, 3, 3), ROP std (S, 6), the APs' std (S, 7) and cov (S, 7, 7)."""
    n_sys, n_ap = problem.n_systems, problem.n_ap
    iop_std = np.zeros((n_sys, 3))
    iop_cov = np.zeros((n_sys, 3, 3))
    rop_std = np.zeros((n_sys, 6))
    ap_std = np.zeros((n_sys, n_ap))
    ap_cov = np.zeros((n_sys, n_ap, n_ap))
    g_std = np.sqrt(np.clip(c_h * np.diag(cov_globals), 0.0, None)) if problem.n_globals else np.zeros(0)
    for s in range(n_sys):
        cols = problem.gcol[s]
        if cols[0] >= 0:
            iop_std[s] = g_std[cols[:3]]
            iop_cov[s] = c_h * cov_globals[np.ix_(cols[:3], cols[:3])]
        if n_sys > 1 and cols[3] >= 0:
            rop_std[s] = g_std[cols[3:9]]
        if n_ap:
            free = np.flatnonzero(cols[problem.ap_start :] >= 0)
            ap_cols = cols[problem.ap_start + free]
            ap_std[s, free] = g_std[ap_cols]
            ap_cov[s][np.ix_(free, free)] = c_h * cov_globals[np.ix_(ap_cols, ap_cols)]
    return iop_std, iop_cov, rop_std, ap_std, ap_cov
