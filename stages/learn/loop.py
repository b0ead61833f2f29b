"""The alternation of the robust adjustment and the regression of its residuals (Chow et al., section IV).

:func:`calibrate` is a short loop over small functions of a frozen loop state
(:class:`_State`): regress every system's residuals (:func:`_regress`), add
the update to the correction, accelerated and gauge-fixed
(:func:`_update_field`), adjust again with the correction held, record the
iteration, and decide (:func:`_decide`) whether to go on, to switch to the
gridded refinement, or to stop.

Each outer iteration: (1) per system, the kNN regression ``δ`` of the
inlier residuals (``k`` by cross-validation of equation 3, restricted after
the first iteration to the candidates near the previous ``k``), (2)
``Δ += δ`` at every observation (inliers and outliers, so an outlier
that turns out to be an inlier is corrected alike), (3) the adjustment
with ``Δ`` held constant, warm-started from the previous solution.
A phase ends by the rules of :mod:`fluorocal.stages.learn.stopping` or at its
iteration cap (``params.max_iterations`` for the kNN phase,
``params.refine_iterations`` for the refinement). With ``params.refine`` the
end of the kNN phase starts the gridded refinement; the end of the last phase
ends the loop.

With ``acceleration="anderson"`` the kNN phase's iterate is the vector of all
node values of the gridded fields: the update ``x <- x + δ(x)`` is a fixed-point
iteration, and Anderson acceleration combines the last few iterates;
a step that raises the combined cost restarts its history, and so does one that
does not shrink the update (:func:`fluorocal.stages.learn.anderson.anderson_step`).
The refinement's joint steps are Gauss-Newton steps of the joint problem: they are
taken as they are (extrapolated by Anderson, they overshot the fixed point and
raised the adjustment's cost near it, issue 30).

The loop keeps its best iterate, the lowest adjustment cost (equation 2) of its last phase, and stops once the
steps' contraction leaves less than ``field_tolerance`` of the field's σ and less than the cost's noise to go, or at
the first refinement step that does not lower the cost by ``stall_tolerance`` of itself: either way a restart from
the result moves the field by a small fraction of its σ.
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass, field, replace

import numpy as np
from fluorocal.stages.adjust import FreeParameters
from fluorocal.stages.errors import EstimationError, NotConvergedWarning
from fluorocal.stages.field import CorrectionField, PointwiseField
from fluorocal.stages.learn.adjuster import Adjuster, Outcome, adjustment_outcome
from fluorocal.stages.learn.anderson import Anderson, anderson_step
from fluorocal.stages.learn.finish import loop_result
from fluorocal.stages.learn.gauge import gauge_fixed
from fluorocal.stages.learn.grid import cross_validate_smoothness, fit_grid_field
from fluorocal.stages.learn.joint import Respond, SystemStep, fit_grids_jointly
from fluorocal.stages.learn.knn import fit_knn_field, pool_neighbours, restricted_k_grid
from fluorocal.stages.learn.network import systems_network
from fluorocal.stages.learn.nodes import image_sizes
from fluorocal.stages.learn.order import canonical_order, taken, unpermuted_result
from fluorocal.stages.learn.params import Acceleration, FieldGauge, LearnParams, Refine, Scheme, Training
from fluorocal.stages.learn.polynomial import calibrate_polynomial
from fluorocal.stages.learn.result import IterationRecord, LearnResult
from fluorocal.stages.learn.robust import SCREEN_NEIGHBOURS, local_screen, misfit_inliers
from fluorocal.stages.learn.stopping import cost_raised, decide, field_step_sigma
from fluorocal.stages.learn.threads import each_system

logger = logging.getLogger(__name__)

#: conjugate-gradient cap of the refinement's field step inside the loop, and its relative tolerance per what
#: responds: the joint step is linearised afresh at every iteration, so an inexact solve is enough; the beads-alone
#: step's convergence test reads its steps against the field's uncertainty, which a loose solve would blur
LOOP_CG_ITERATIONS = 100
LOOP_CG_TOLERANCE = {Respond.ORIENTATION: 1e-3, Respond.POINTS: 1e-6}


@dataclass(frozen=True)
class _Plan:
    """What the scheme and the parameters make of the loop, constant while it runs.

    The unsmoothed schemes run without Anderson acceleration and without the
    gridded refinement (both combine gridded fields).
    """

    params: LearnParams
    observations: object
    rows: tuple  # per system, the rows of its observations
    sizes: tuple  # per system, (width, height) px
    adjuster: Adjuster
    estimate_iop: bool
    smooth: bool
    refine: Refine
    acceleration: Acceleration
    respond: Respond  # the refinement's first choice of what responds to its field step
    workers: int = 1  # threads for the systems' own work (:mod:`fluorocal.stages.learn.threads`)

    @property
    def xy(self) -> np.ndarray:
        return self.observations.xy_px


@dataclass(frozen=True)
class _Memory:
    """One system's regression memory: the last cross-validation, the kNN's ``k`` and neighbours, the prior's ``τ``."""

    cv: object = None
    k_prev: int | None = None
    tau_px: float | None = None
    neighbour_cache: dict = field(default_factory=dict)


@dataclass(frozen=True)
class _State:
    """The loop's state after an iteration."""

    iteration: int
    phase: str  # "knn", then "grid" (the refinement)
    phase_start: int
    corrections: np.ndarray  # shape (N, 2): Δ at every observation
    adj: object  # the adjustment with Δ held at ``corrections``
    out: Outcome
    grids: tuple  # of CorrectionField, the smoothed schemes' fields
    pointwise: tuple  # of PointwiseField, the unsmoothed schemes' fields
    memory: tuple  # of _Memory
    anderson: Anderson
    history: tuple  # of IterationRecord
    updates: tuple = ()  # the last regression's update per system
    trained: np.ndarray | None = None  # shape (N,): the observations the last regression learned from
    respond: Respond = Respond.POINTS  # what responds to the refinement's field step


def calibrate(
    observations,
    phantom,
    initial,
    *,
    image_size,
    scheme: str = "knn+iop+smooth",
    params: LearnParams | None = None,
    solver=None,
    selection=None,
    workers: int = 1,
) -> LearnResult:
    """Alternate the robust adjustment and the kNN regression of its residuals (paper, section IV).

    Parameters
    ----------
    observations : Observations
        Labelled measured coordinates of every system.
    phantom : Phantom
        Nominal bead coordinates (the adjustment's datum).
    initial
        Initial orientation for :func:`fluorocal.stages.adjust.adjust_bundle`.
    image_size : (int, int) or (S, 2) array_like
        ``(width, height)`` px of each system's images.
    scheme : str
        ``"knn"``, ``"knn+iop"``, ``"knn+smooth"``, ``"knn+iop+smooth"`` (the
        paper's four; "iop" = the adjustment estimates the interior
        orientation, otherwise it is held at its initial value and the field
        absorbs it), ``"none"`` (adjustment only, IOP estimated) or
        ``"polynomial"`` (no kNN loop: the adjustment estimates the IOP and
        the global polynomial model, see
        :func:`fluorocal.stages.learn.polynomial.calibrate_polynomial`).
    params : LearnParams, optional
        Default ``LearnParams()``: the recommended preset (``acceleration`` and ``refine`` go
        beyond the paper); ``LearnParams(preset="paper")`` is the paper's loop.
        Whether the field is smoothed is the scheme's.
    solver : SolverOptions, optional
        The adjustment's solver options (``[adjust]``; default ``SolverOptions()``).
    selection : DataSelection, optional
        Which observations enter the adjustment (``[adjust]``; default ``DataSelection()``).
        Which parameters it estimates is the scheme's: the IOP for ``"iop"`` schemes and
        ``"none"``, the polynomial model's for ``"polynomial"``.
    workers : int
        The systems' regressions and joint uncertainties side by side in up to this many threads
        (:mod:`fluorocal.stages.learn.threads`); the result is the serial one's. Default 1: serial.

    Returns
    -------
    LearnResult

    Notes
    -----
    The iteration and its stopping rule: see the module's docstring. The result does not depend on the
    order of the observations' rows: the loop runs on them in a canonical order
    (:mod:`fluorocal.stages.learn.order`), and the per-observation arrays are returned in the caller's.
    """
    order = canonical_order(observations)
    args = (taken(observations, order), phantom, initial, image_size, scheme, params, solver, selection, workers)
    return unpermuted_result(_calibrate_sorted(*args), order)


def _calibrate_sorted(observations, phantom, initial, image_size, scheme, params, solver, selection, workers):
    """:func:`calibrate` of observations in canonical order."""
    t0 = time.perf_counter()
    params = LearnParams() if params is None else params
    scheme = Scheme.parse(scheme)
    sizes = image_sizes(image_size, len(observations.system_names))
    settings = {"solver": solver, "selection": selection}
    if scheme.polynomial:
        fixed = params.polynomial_fixed
        return calibrate_polynomial(observations, phantom, initial, sizes, params.grid, fixed=fixed, **settings)
    free = FreeParameters(estimate_iop=scheme.estimate_iop)
    adjuster = Adjuster(observations, phantom, initial, free=free, fast=params.fast_intermediate, **settings)
    plan = replace(_plan(params, observations, sizes, adjuster, scheme.estimate_iop, scheme.smooth), workers=workers)
    adj = adjuster(np.zeros((len(observations.xy_px), 2)), None, final=not scheme.learn_field)
    out = adjustment_outcome(adj, observations.sigma_px)
    logger.debug("scheme %s: initial adjustment cost %.6g, inlier RMS %.4f px", scheme, out.cost, out.rms_px)
    state = _initial_state(plan, adj, out)
    if not scheme.learn_field:
        return loop_result(plan, scheme, state, True, "scheme 'none' learns nothing", t0, adj.residual_px)
    best = state
    while True:
        state = _iterate(plan, state)
        best = state if best is None or _better(state, best) else best
        action, converged, reason = _decide(plan, state)
        if action == "refine":
            state = replace(state, phase="grid", phase_start=state.iteration + 1, anderson=state.anderson.restarted())
            best = None  # the refinement's best is among its own iterates
        elif action == "stop":
            break
    if not converged:
        _warn_capped(reason)
    logger.debug(
        "scheme %s: stopped at iteration %d, the best iterate kept: iteration %d (adjustment cost %.6g)",
        scheme,
        state.iteration,
        best.iteration,
        best.out.cost,
    )
    reason = f"{reason}; stopped at iteration {state.iteration}, kept iteration {best.iteration}, the best"
    state = replace(best, history=state.history)
    if params.fast_intermediate:
        # the final solve, warm-started, with the covariance and redundancy numbers
        state = replace(state, adj=adjuster(state.corrections, state.adj, final=True))
    return loop_result(plan, scheme, state, converged, reason, t0, adj.residual_px)


def _better(state: _State, best: _State) -> bool:
    """Whether ``state`` improves on ``best``, the phase's best iterate so far: a lower adjustment cost (equation 2).

    Equation 2, the robust cost of the adjustment with the field held, is the measure a user cares about: how
    well the corrected observations fit one orientation; the refinement's field steps, Gauss-Newton steps of
    the joint problem, lower it to their fixed point. The regression's own cost (equation 3) is normalised by
    each adjustment's variance factor, so it is not comparable from one iteration to the next.
    """
    return state.out.cost < best.out.cost


def _warn_capped(reason: str) -> None:
    warnings.warn(
        f"the learning stopped short of convergence ({reason}); the field may be less accurate than the data "
        "allow: raise [learn] refine_iterations (or max_iterations)",
        NotConvergedWarning,
        stacklevel=3,
    )


def _plan(params: LearnParams, observations, sizes, adjuster: Adjuster, estimate_iop: bool, smooth: bool) -> _Plan:
    rows = tuple(np.flatnonzero(observations.system == s) for s in range(len(sizes)))
    # Anderson and the gridded refinement combine gridded fields: the unsmoothed schemes run without them
    refine = params.refine if smooth else Refine.NONE
    anderson = params.acceleration is Acceleration.ANDERSON
    acceleration = Acceleration.NONE if anderson and not smooth else params.acceleration
    respond = Respond.ORIENTATION if params.orientation_response else Respond.POINTS
    return _Plan(params, observations, rows, sizes, adjuster, estimate_iop, smooth, refine, acceleration, respond)


def _initial_state(plan: _Plan, adj, out: Outcome) -> _State:
    """Iteration 0: the adjustment with no correction, zero fields."""
    spacing = plan.params.grid_spacing_px
    return _State(
        iteration=0,
        phase="knn",
        phase_start=1,
        corrections=np.zeros((len(plan.xy), 2)),
        adj=adj,
        out=out,
        grids=tuple(CorrectionField.constant(w, h, spacing_px=spacing) for w, h in plan.sizes),
        pointwise=tuple(PointwiseField((), w, h) for w, h in plan.sizes),
        memory=tuple(_Memory() for _ in plan.sizes),
        anderson=Anderson(plan.params.anderson_depth),
        history=(IterationRecord(0, "adjust", out.cost, 0.0, out.cost, (), out.rms_px, 0.0),),
        respond=plan.respond,
    )


def _iterate(plan: _Plan, state: _State) -> _State:
    """One outer iteration: regress, update the correction, adjust with it held, record."""
    iteration, phase = state.iteration + 1, state.phase
    updates, memory, fit_cost, trained = _regress(plan, state)
    corrections, grids, pointwise, anderson = _update_field(plan, state, updates)
    adj = plan.adjuster(corrections, state.adj, final=False)
    out = adjustment_outcome(adj, plan.observations.sigma_px)
    total = out.cost + fit_cost
    step = float(np.max(np.abs(corrections - state.corrections))) if len(corrections) else 0.0
    step_sigma = field_step_sigma(state.grids, grids) if plan.smooth else float("nan")
    ks = tuple(int(m.k_prev or 0) if phase == "knn" else 0 for m in memory)
    record = IterationRecord(iteration, phase, out.cost, fit_cost, total, ks, out.rms_px, step, step_sigma)
    history = state.history + (record,)
    logger.debug(
        "iteration %d (%s): cost %.6g + %.6g = %.6g, RMS %.4f px, step %.4f px (%.2f sigma), k %s",
        iteration,
        phase,
        out.cost,
        fit_cost,
        total,
        out.rms_px,
        step,
        step_sigma,
        ks,
    )
    if plan.acceleration is Acceleration.ANDERSON and cost_raised(history):
        anderson = anderson.restarted()
    return _State(
        iteration,
        phase,
        state.phase_start,
        corrections,
        adj,
        out,
        grids,
        pointwise,
        memory,
        anderson,
        history,
        updates,
        trained,
        state.respond,
    )


def _decide(plan: _Plan, state: _State) -> tuple[str, bool, str]:
    """``(action, converged, reason)``: ``"continue"``, ``"refine"`` (start the refinement) or ``"stop"``."""
    in_phase = state.iteration - state.phase_start + 1
    action, converged, reason = decide(
        plan.params,
        state.history,
        n_obs=len(plan.xy),
        iterations_in_phase=in_phase,
        refine=plan.refine,
        stall_tolerance=plan.params.stall_tolerance,
    )
    if action == "continue":
        return action, converged, reason
    if state.phase == "knn" and plan.refine is not Refine.NONE:
        return "refine", False, ""
    return "stop", converged, reason


# ---------------------------------------------------------------------------------------------
# the regression step
# ---------------------------------------------------------------------------------------------


def _regress(plan: _Plan, state: _State) -> tuple[tuple, tuple, float, np.ndarray]:
    """Every system's update, its regression memory after it, the in-sample equation-3 cost of the updates.

    And the mask ``(N,)`` of the observations the updates were fitted to. The joint step's fit of the residuals
    is its field update and the orientation's response together (issue 30: read without the response, its
    equation-3 cost was hundreds of times the adjustment's, and the combined cost jumped by orders of magnitude).
    """
    if state.phase == "grid" and plan.refine is Refine.GRID_POINTS:
        updates, memory, sels, responses = _regress_jointly(plan, state)
    else:
        n_systems = len(plan.sizes)  # the systems side by side in threads (:mod:`.threads`)
        updates, memory, sels = zip(*each_system(lambda s: _regress_system(plan, state, s), n_systems, plan.workers))
        responses = (0.0,) * len(updates)
    fit_cost, trained = 0.0, np.zeros(len(plan.xy), bool)
    for model, sel, response in zip(updates, sels, responses):
        trained[sel] = True
        r, var = state.out.residuals_px[sel], state.out.residual_var_px2[sel]
        fit_cost += float(np.sum((r - model.correction_at(plan.xy[sel]) - response) ** 2 / var))
    return tuple(updates), tuple(memory), fit_cost, trained


def _regress_system(plan: _Plan, state: _State, s: int):
    """System ``s``'s update, its memory after it and the observations it was fitted to.

    With ``training="local"``, gross errors are what the field cannot explain
    (:mod:`fluorocal.stages.learn.robust`): screen every used observation
    against its neighbours' median residual, cross-validate and fit to those
    it keeps (each out-of-fold cost bounded at the screen's threshold), test
    every observation against the fitted field, refit to those it explains.
    """
    candidates, sel, cost_cap = _screened(plan, state, s)
    model, mem = _fit(plan, state, s, sel, state.memory[s], cost_cap=cost_cap)
    if plan.params.training is not Training.LOCAL:
        return model, mem, sel
    refit = _explained(plan, state, candidates, model)
    if not np.array_equal(refit, sel):
        model, mem = _fit(plan, state, s, refit, mem, refit=model)
    return model, mem, refit


def _regress_jointly(plan: _Plan, state: _State):
    """The refinement's joint step (:func:`_regress_system`'s, every system's field at once): updates, memory, rows."""
    screened = [_screened(plan, state, s) for s in range(len(plan.sizes))]
    sels = [sel for _, sel, _ in screened]
    cv = [(sel, state.memory[s], cap) for s, (_, sel, cap) in enumerate(screened)]
    memory = each_system(lambda s: _smoothness(plan, state, s, *cv[s]), len(cv), plan.workers)
    updates, responses = _fit_jointly(plan, state, sels, memory)
    if plan.params.training is Training.LOCAL:
        # the misfit test reads the step's whole fit at the candidates: the field's update and the orientation's
        # response, the latter known at the training rows (and set aside, nil, at the others)
        fits = [_at_rows(c, sel, resp) for (c, _, _), sel, resp in zip(screened, sels, responses)]
        refits = [_explained(plan, state, c, u, fit) for (c, _, _), u, fit in zip(screened, updates, fits)]
        if not all(np.array_equal(a, b) for a, b in zip(refits, sels)):
            (updates, responses), sels = _fit_jointly(plan, state, refits, memory, start=updates), refits
    return updates, memory, sels, responses


def _at_rows(candidates: np.ndarray, rows: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` ``(len(rows), 2)`` given at ``rows``, a subset of ``candidates``, at every candidate (0 elsewhere)."""
    out = np.zeros((len(candidates), 2))
    out[np.searchsorted(candidates, rows)] = values
    return out


def _screened(plan: _Plan, state: _State, s: int):
    """System ``s``'s candidate observations, those its regression learns from and their out-of-fold cost cap."""
    params, out, rows = plan.params, state.out, plan.rows[s]
    local = params.training is Training.LOCAL
    sel = rows[state.adj.used[rows]] if local else rows[out.inlier[rows]]
    if len(sel) < params.n_folds:
        raise EstimationError(
            f"system {plan.observations.system_names[s]} has {len(sel)} inlier observations; "
            f"the regression needs at least {params.n_folds}"
        )
    if not local:
        return sel, sel, None
    # the kNN's neighbour table of the system's observations, once its first cross-validation built it
    near = pool_neighbours(state.memory[s].neighbour_cache, plan.xy[sel], SCREEN_NEIGHBOURS)
    screen = local_screen(
        plan.xy[sel], out.residuals_px[sel], out.residual_var_px2[sel], chi2=params.screen_chi2, neighbours=near
    )
    return sel, _enough(sel, screen.keep, params.n_folds), screen.cost_cap


def _explained(plan: _Plan, state: _State, candidates: np.ndarray, model, response=0.0) -> np.ndarray:
    """The ``candidates`` the fitted ``model`` (plus the orientation's ``response``) explains (the misfit test)."""
    r, var = state.out.residuals_px[candidates], state.out.residual_var_px2[candidates]
    fit = model.correction_at(plan.xy[candidates]) + response
    explained, _ = misfit_inliers(r, fit, var, plan.params.outlier_chi2)
    return _enough(candidates, explained, plan.params.n_folds)


def _enough(candidates: np.ndarray, keep: np.ndarray, n_min: int) -> np.ndarray:
    """``candidates[keep]``, or all of them when fewer than ``n_min`` would be kept."""
    return candidates[keep] if keep.sum() >= n_min else candidates


def _fit(plan: _Plan, state: _State, s: int, sel: np.ndarray, mem: _Memory, refit=None, cost_cap=None):
    """One regression of system ``s`` on observations ``sel``: the update and the memory after it.

    ``refit``: the update just fitted, when this is the same step again (after the local outlier test), with
    the ``k`` just chosen. ``cost_cap`` bounds each observation's out-of-fold cost in the cross-validations.
    """
    if state.phase == "grid":
        return _fit_grid(plan, state, s, sel, mem, cost_cap)
    params = plan.params
    r, var = state.out.residuals_px[sel], state.out.residual_var_px2[sel]
    knn = dict(image_size=plan.sizes[s], grid=params.grid, smooth=plan.smooth, n_folds=params.n_folds, seed=params.seed)
    if refit is not None:
        model, _ = fit_knn_field(plan.xy[sel], r, var, cv=mem.cv, neighbour_cache=mem.neighbour_cache, **knn)
        return model, mem
    k_grid = restricted_k_grid(params.k_grid, mem.k_prev)
    model, cv = fit_knn_field(
        plan.xy[sel],
        r,
        var,
        k_grid=k_grid,
        neighbour_cache=mem.neighbour_cache,
        neighbour_pool_px=plan.xy[plan.rows[s]],
        cost_cap=cost_cap,
        **knn,
    )
    return model, replace(mem, cv=cv, k_prev=cv.k)


def _fit_grid(plan: _Plan, state: _State, s: int, sel: np.ndarray, mem: _Memory, cost_cap=None):
    """The refinement's update of system ``s`` by the gridded least squares alone (``refine="grid"``)."""
    mem = _smoothness(plan, state, s, sel, mem, cost_cap)
    xy, r, var = plan.xy[sel], state.out.residuals_px[sel], state.out.residual_var_px2[sel]
    fit = dict(image_size=plan.sizes[s], tau_px=mem.tau_px, grid=plan.params.grid, base=state.grids[s])
    return fit_grid_field(xy, r, var, cv_rms_px=mem.cv.cv_rms_px, order=mem.cv.order, **fit), mem


def _smoothness(plan: _Plan, state: _State, s: int, sel: np.ndarray, mem: _Memory, cost_cap=None) -> _Memory:
    """System ``s``'s memory with the refinement's smoothness prior, cross-validated once (its first step)."""
    if mem.tau_px is not None:
        return mem
    params, out = plan.params, state.out
    cv = cross_validate_smoothness(
        plan.xy[sel],
        out.residuals_px[sel],
        out.residual_var_px2[sel],
        image_size=plan.sizes[s],
        grid=params.grid,
        tau_grid_px=params.tau_grid_px,
        orders=params.smoothness_orders,
        n_folds=params.smoothness_folds,
        seed=params.seed,
        base_px=state.grids[s].delta_px,
        cost_cap=cost_cap,
    )
    name = plan.observations.system_names[s]
    logger.debug("system %s: gridded refinement, smoothness order %d, tau %.3g px (CV)", name, cv.order, cv.tau_px)
    return replace(mem, cv=cv, tau_px=cv.tau_px)


def _fit_jointly(plan: _Plan, state: _State, sels: list, memory: tuple, start=None) -> tuple:
    """Every system's refinement update by the joint step (:func:`fit_grids_jointly`) and the response, from ``sels``.

    ``start``: updates of nearly the same observations to start the iterative solve from.
    """
    params, adj, observations = plan.params, state.adj, plan.observations
    nominal = plan.adjuster.nominal_shape(adj)[1] if params.affine_datum else None
    network = systems_network(adj, observations, sels, range(len(sels)), nominal)
    steps = []
    for s, (sel, mem) in enumerate(zip(sels, memory)):
        t_weight = adj.weight[sel, None] if params.training is Training.INLIERS else 1.0
        w_obs = t_weight / (adj.sigma0 * observations.sigma_px[sel, :2]) ** 2
        r = state.out.residuals_px[sel]
        base, origin = state.grids[s], None if start is None else start[s].delta_px
        steps.append(
            SystemStep(
                plan.xy[sel],
                r,
                w_obs,
                adj.iop_px[s],
                plan.sizes[s],
                mem.tau_px,
                base,
                mem.cv.cv_rms_px,
                mem.cv.order,
                origin,
            )
        )
    cg = dict(max_cg_iterations=LOOP_CG_ITERATIONS, cg_tolerance=LOOP_CG_TOLERANCE[state.respond])
    return fit_grids_jointly(
        steps,
        network,
        estimate_iop=plan.estimate_iop,
        grid=params.grid,
        respond=state.respond,
        with_response=True,
        **cg,
    )


# ---------------------------------------------------------------------------------------------
# the update of the correction
# ---------------------------------------------------------------------------------------------


def _update_field(plan: _Plan, state: _State, updates: tuple):
    """``Δ += δ``: the corrections at every observation, the fields and the acceleration's memory after it."""
    corrections = state.corrections.copy()
    xy, rows = plan.xy, plan.rows
    if plan.smooth:
        return _update_grids(plan, state, updates, corrections)
    factor = plan.params.relaxation if plan.acceleration is Acceleration.OVERRELAX else 1.0
    pointwise = tuple(f.add(u.scaled(factor)) for f, u in zip(state.pointwise, updates))
    for s, u in enumerate(updates):
        corrections[rows[s]] += factor * u.correction_at(xy[rows[s]])
    return corrections, state.grids, pointwise, state.anderson


def _update_grids(plan: _Plan, state: _State, updates: tuple, corrections: np.ndarray):
    """The gridded fields' update: plain, over-relaxed or Anderson-accelerated, then gauge-fixed."""
    params, xy, rows = plan.params, plan.xy, plan.rows
    x = np.concatenate([g.delta_px.ravel() for g in state.grids])
    dx = np.concatenate([u.delta_px.ravel() for u in updates])
    anderson = state.anderson
    if plan.acceleration is Acceleration.ANDERSON and state.phase == "knn":
        mask = np.concatenate([np.repeat(u.support.ravel(), 2) for u in updates])
        x_new, anderson = anderson_step(anderson, x, x + dx, mask)
    elif plan.acceleration is Acceleration.OVERRELAX:
        x_new = x + params.relaxation * dx
    else:
        x_new = x + dx
    grids = _split_nodes(state.grids, updates, x_new)
    if params.field_gauge is not FieldGauge.NONE:
        grids = [gauge_fixed(g, xy[rows[s]], state.adj.iop_px[s], plan.estimate_iop) for s, g in enumerate(grids)]
    for s, g in enumerate(grids):
        corrections[rows[s]] = g.correction_at(xy[rows[s]])
    return corrections, tuple(grids), state.pointwise, anderson


def _split_nodes(grids, updates, x_new):
    """New gridded fields from the flattened node vector ``x_new`` (sigma and support of the updates)."""
    out, start = [], 0
    for g, u in zip(grids, updates):
        n = g.delta_px.size
        out.append(
            g.with_delta(x_new[start : start + n].reshape(g.delta_px.shape), sigma_px=u.sigma_px, support=u.support)
        )
        start += n
    return out


__all__ = ["calibrate"]
