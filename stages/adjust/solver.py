"""Levenberg–Marquardt on the Student-t negative log-likelihood of the bundle adjustment.

The gradient is exact; the Hessian is the IRLS one ``Σ w J^T J`` until the
variance factor σ² settles, then with Triggs' curvature correction
(:func:`stages.adjust.normal.triggs_corrected`). After every accepted step σ²
(and ν, when estimated) are set to their maximum-likelihood values for the new
residuals (:func:`stages.adjust.robust.ml_hyper`), so the cost history is monotone.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from fluorocal.stages.adjust.collinearity import Projection, State, jacobian, project
from fluorocal.stages.adjust.normal import (
    Normal,
    SingularStep,
    assemble,
    factorize,
    step_from,
    triggs_corrected,
    weighted_jacobian,
)
from fluorocal.stages.adjust.options import SolverOptions
from fluorocal.stages.adjust.problem import Problem, apply_step, split_step
from fluorocal.stages.adjust.robust import ml_hyper, t_cost, t_weights
from fluorocal.stages.errors import EstimationError

log = logging.getLogger(__name__)

_MU_MIN, _MU_MAX = 1e-12, 1e16  # Marquardt damping range
_MU_NUMERICAL = 1e6  # damping beyond which a failing step means the optimum is reached


@dataclass(frozen=True)
class SolverResult:
    """The solution of :func:`solve`: state, ML ``nu`` and ``scale2`` (σ²), and how the iterations ended."""

    state: State
    nu: float
    scale2: float
    cost_history: tuple
    iterations: int
    stop_reason: str
    converged: bool


@dataclass
class _Progress:
    """The iteration's mutable state (one per :func:`solve` call)."""

    state: State
    nu: float
    scale2: float
    cost: float
    mu: float
    history: list = field(default_factory=list)
    growth: float = 2.0
    projection: Projection | None = None  # camera points and residuals at ``state``, kept for its linearisation
    normal: Normal | None = None  # the linearisation at ``state``; None after a move
    settled: bool = False  # σ² changed by < 5 % at the last accepted step
    iteration: int = 0
    stop: str | None = None
    converged: bool = False

    def finish(self, stop: str, converged: bool) -> None:
        self.stop, self.converged = stop, converged


def _cost_at(state: State, problem: Problem, nu: float, scale2: float) -> tuple[float, np.ndarray, Projection | None]:
    """The cost at ``state``, the squared norms ``s`` of its residuals and its projection (None: behind a source)."""
    try:
        projection = project(state, problem)
    except FloatingPointError:
        return math.inf, np.empty(0), None
    s = (projection.e * projection.e).sum(1)
    return t_cost(s, nu, scale2), s, projection


def _hyper(s: np.ndarray, nu: float, scale2: float, options: SolverOptions) -> tuple[float, float]:
    return ml_hyper(
        s,
        nu,
        scale2,
        estimate_scale=options.estimate_scale,
        estimate_nu=options.estimate_nu,
        nu_bounds=options.nu_bounds,
    )


def solve(state: State, problem: Problem, options: SolverOptions) -> SolverResult:
    """Levenberg–Marquardt on the Student-t negative log-likelihood (exact gradient).

    The Hessian is the IRLS one ``Σ w J^T J`` until σ² settles, then with
    Triggs' curvature correction (:func:`stages.adjust.normal.triggs_corrected`),
    which turns the IRLS tail's linear convergence into a faster one.

    Every accepted step lowers ``F(θ, σ², ν)``; after it, σ² (and ν) are set to
    their maximum-likelihood values for the new residuals, which lowers it
    further, so the cost history is monotone.

    Raises
    ------
    EstimationError
        ``state`` puts observed points at or behind a source, or the damped
        system stays singular at the largest damping.
    """
    nu = float(options.nu)
    cost, s, projection = _cost_at(state, problem, nu, 1.0)
    if not math.isfinite(cost):
        raise EstimationError("the initial orientation puts observed points at or behind the X-ray source")
    nu, scale2 = _hyper(s, nu, 1.0, options)
    run = _Progress(state=state, nu=nu, scale2=scale2, cost=t_cost(s, nu, scale2), mu=options.initial_damping)
    run.projection = projection
    run.history.append(run.cost)
    while run.iteration < options.max_iterations and run.stop is None:
        run.iteration += 1
        _iterate(run, problem, options)
    if run.stop is None:
        run.finish(f"maximum number of iterations ({options.max_iterations}) reached", False)
    log.debug(
        "LM stopped after %d iterations: %s (cost %.6g, σ² %.4g, ν %.3g)",
        run.iteration,
        run.stop,
        run.cost,
        run.scale2,
        run.nu,
    )
    return SolverResult(
        state=run.state,
        nu=run.nu,
        scale2=run.scale2,
        cost_history=tuple(run.history),
        iterations=run.iteration,
        stop_reason=run.stop,
        converged=run.converged,
    )


def _linearised(run: _Progress, problem: Problem) -> Normal:
    """The normal equations at ``run.state`` with the current t-weights."""
    e, J = jacobian(run.state, problem, run.projection)
    s_now = (e * e).sum(1)
    J, ew = weighted_jacobian(e, J, t_weights(s_now, run.nu, run.scale2), overwrite_j=True)
    # near the optimum (σ² settled) the IRLS curvature overstates the t's: correct it there only,
    # since far away the corrected model oversteps
    J_h = triggs_corrected(J, ew, s_now / run.scale2, run.nu) if run.settled else None
    return assemble(problem, J, ew, J_h)


def _iterate(run: _Progress, problem: Problem, options: SolverOptions) -> None:
    """One iteration: a damped step, accepted (and σ², ν updated) or rejected (damping raised)."""
    if run.normal is None:
        run.normal = _linearised(run, problem)
    normal, mu = run.normal, run.mu
    try:
        factor = factorize(problem, normal, mu)
        de, dy = step_from(problem, factor, normal.b_e, normal.b_y)
    except SingularStep:
        if mu >= _MU_NUMERICAL and len(run.history) > 1:
            # only reached after a long run of rejected steps at the optimum
            run.finish("no further decrease within numerical precision", True)
            return
        if mu >= _MU_MAX:
            raise
        run.mu = min(max(mu, _MU_MIN) * 10.0, _MU_MAX)
        return
    trial = apply_step(run.state, problem, *split_step(problem, de, dy))
    new_cost, s_new, projection = _cost_at(trial, problem, run.nu, run.scale2)
    step = np.concatenate([de.ravel(), dy])
    # decrease predicted by the quadratic model, in cost units (H and b are without 1/σ²):
    # (H + μ diag H) δ = b on the constraint surface gives ½ (b·δ + μ δ^T diag(H) δ)
    b = np.concatenate([normal.b_e.ravel(), normal.b_y])
    predicted = 0.5 * (b @ step + mu * (factor.diag_h * step * step).sum()) / run.scale2
    actual = run.cost - new_cost
    state = run.state
    x_norm = math.sqrt(float((state.points_mm**2).sum() + (state.source_mm**2).sum() + (state.iop_px**2).sum()))
    small_step = float(np.linalg.norm(step)) <= options.parameter_tolerance * (x_norm + options.parameter_tolerance)
    if math.isfinite(new_cost) and actual > 0 and predicted > 0:
        _accept(run, trial, projection, s_new, actual / predicted, small_step, options)
    elif (
        small_step
        or 0 <= predicted <= options.function_tolerance
        or (math.isfinite(new_cost) and abs(actual) <= options.function_tolerance)
    ):
        run.finish("no further decrease within the tolerances", True)
    else:
        run.mu *= run.growth
        run.growth *= 2.0
        if run.mu > _MU_MAX:
            run.finish(f"damping exceeded {_MU_MAX:g} without decrease", False)


def _accept(run: _Progress, trial: State, projection, s_new: np.ndarray, rho: float, small_step: bool, options) -> None:
    """Move to ``trial`` (gain ratio ``rho``), update the damping, σ² and ν, and test the stopping rules."""
    run.state, run.projection = trial, projection
    run.normal = None
    run.mu = max(run.mu * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), _MU_MIN)
    run.growth = 2.0
    previous_scale2 = run.scale2
    run.nu, run.scale2 = _hyper(s_new, run.nu, run.scale2, options)
    run.settled = not math.isinf(run.nu) and abs(run.scale2 / previous_scale2 - 1) < 0.05
    new_total = t_cost(s_new, run.nu, run.scale2)
    change = run.cost - new_total
    run.cost = new_total
    run.history.append(run.cost)
    if change <= options.function_tolerance:
        run.finish("cost change below function_tolerance", True)
    elif small_step:
        run.finish("step below parameter_tolerance", True)
