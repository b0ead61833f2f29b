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

With ``acceleration="anderson"`` the iterate is the vector of all node
values of the gridded fields: the update ``x <- x + δ(x)`` is a fixed-point
iteration, and Anderson acceleration combines the last few iterates;
a step that raises the cost (the combined cost in the kNN phase, the
adjustment's in the refinement) restarts its history, and so does one that
does not shrink the update (:func:`fluorocal.stages.learn.anderson.anderson_step`).
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
from fluorocal.stages.learn.gauge import gauge_fixed
from fluorocal.stages.learn.grid import cross_validate_smoothness, fit_grid_field
from fluorocal.stages.learn.joint import SystemStep, fit_grids_jointly
from fluorocal.stages.learn.knn import fit_knn_field, node_statistics, pool_neighbours, restricted_k_grid
from fluorocal.stages.learn.network import systems_network
from fluorocal.stages.learn.nodes import image_sizes
from fluorocal.stages.learn.params import LearnParams, Scheme
from fluorocal.stages.learn.polynomial import calibrate_polynomial
from fluorocal.stages.learn.result import IterationRecord, LearnResult
from fluorocal.stages.learn.robust import SCREEN_NEIGHBOURS, local_screen, misfit_inliers
from fluorocal.stages.learn.stopping import decide, previous_total
from fluorocal.stages.learn.uncertainty import learned_uncertainty, with_field_std

logger = logging.getLogger(__name__)

#: conjugate-gradient cap of the refinement's field step inside the loop, and its relative tolerance per what
#: responds: the joint step is linearised afresh at every iteration, so an inexact solve is enough; the beads-alone
#: step's convergence test reads its steps against the field's uncertainty, which a loose solve would blur
LOOP_CG_ITERATIONS = 100
LOOP_CG_TOLERANCE = {"orientation": 1e-3, "points": 1e-6}


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
    refine: str
    acceleration: str
    respond: str  # the refinement's first choice of what responds to its field step: "orientation" or "points"

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
    respond: str = "points"  # what responds to the refinement's field step: "orientation" or "points"


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

    Returns
    -------
    LearnResult

    Notes
    -----
    The iteration and its stopping rule: see the module's docstring.
    """
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
    plan = _plan(params, observations, sizes, adjuster, scheme.estimate_iop, scheme.smooth)
    adj = adjuster(np.zeros((len(observations.xy_px), 2)), None, final=not scheme.learn_field)
    out = adjustment_outcome(adj, observations.sigma_px)
    logger.info("scheme %s: initial adjustment cost %.6g, inlier RMS %.4f px", scheme, out.cost, out.rms_px)
    state = _initial_state(plan, adj, out)
    if not scheme.learn_field:
        return _result(plan, scheme, state, True, "scheme 'none' learns nothing", t0, adj.residual_px)
    while True:
        state = _iterate(plan, state)
        action, converged, reason = _decide(plan, state)
        if action == "refine":
            state = replace(state, phase="grid", phase_start=state.iteration + 1, anderson=state.anderson.restarted())
        elif action == "stop":
            break
    if not converged:
        _warn_capped(reason)
    if params.fast_intermediate:
        # the final solve, warm-started, with the covariance and redundancy numbers
        state = replace(state, adj=adjuster(state.corrections, state.adj, final=True))
    return _result(plan, scheme, state, converged, reason, t0, adj.residual_px)


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
    refine = params.refine if smooth else "none"
    acceleration = "none" if params.acceleration == "anderson" and not smooth else params.acceleration
    respond = "orientation" if params.orientation_response == "yes" else "points"
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
    respond = state.respond
    if phase == "grid" and respond == "orientation" and out.cost > state.out.cost and len(plan.sizes) == 1:
        # the joint step went further than its linearisation holds: this step and the rest of the refinement
        # move the beads alone, the slower step that always descends. Not with several systems: their beads-alone
        # step, every system's field at once with no view held, wanders (a 2 + 2-epoch biplanar set ran to the
        # cap); the stall rule ends a joint refinement whose cost has stopped falling
        logger.info("joint step raised the adjustment's cost (%.6g > %.6g): the beads alone respond from here",
                    out.cost, state.out.cost)  # fmt: skip
        respond = "points"
        state = replace(state, respond=respond, anderson=state.anderson.restarted())
        updates, memory, fit_cost, trained = _regress(plan, state)
        corrections, grids, pointwise, anderson = _update_field(plan, state, updates)
        adj = plan.adjuster(corrections, state.adj, final=False)
        out = adjustment_outcome(adj, plan.observations.sigma_px)
    total = out.cost + fit_cost
    step = float(np.max(np.abs(corrections - state.corrections))) if len(corrections) else 0.0
    step_sigma = _field_step_sigma(state.grids, grids) if plan.smooth else float("nan")
    ks = tuple(int(m.k_prev or 0) if phase == "knn" else 0 for m in memory)
    record = IterationRecord(iteration, phase, out.cost, fit_cost, total, ks, out.rms_px, step, step_sigma)
    history = state.history + (record,)
    logger.info(
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
    if plan.acceleration == "anderson" and _raised(history):
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
        respond,
    )


def _raised(history: tuple) -> bool:
    """Whether the last step raised the cost, the refinement's adjustment cost, the kNN phase's combined one.

    The refinement's in-sample regression cost wanders by tens of percent from step to step (see
    :mod:`fluorocal.stages.learn.stopping`): read in the combined cost, it restarted Anderson's history
    every other step.
    """
    if previous_total(history) is None:
        return False
    last, prev = history[-1], history[-2]
    if last.phase == "grid":
        return last.cost_adjust > prev.cost_adjust
    return last.cost_total > prev.cost_total


def _field_step_sigma(before: tuple, after: tuple) -> float:
    """Largest change of a gridded field at a node supported after the step, in units of that node's sigma."""
    worst = 0.0
    for old, new in zip(before, after):
        change = np.linalg.norm(new.delta_px - old.delta_px, axis=-1)[new.support]
        if change.size:
            worst = max(worst, float(np.max(change / np.maximum(new.sigma_px[new.support], 1e-12))))
    return worst


def _decide(plan: _Plan, state: _State) -> tuple[str, bool, str]:
    """``(action, converged, reason)``: ``"continue"``, ``"refine"`` (start the refinement) or ``"stop"``."""
    in_phase = state.iteration - state.phase_start + 1
    # the stall rule is the joint step's: the beads-alone step creeps, its cost falling slowly for many iterations
    stall = plan.params.stall_tolerance if state.respond == "orientation" else 0.0
    action, converged, reason = decide(plan.params, state.history, n_obs=len(plan.xy), iterations_in_phase=in_phase,
                                       refine=plan.refine, stall_tolerance=stall)  # fmt: skip
    if action == "continue":
        return action, converged, reason
    if state.phase == "knn" and plan.refine != "none":
        return "refine", False, ""
    return "stop", converged, reason


# ---------------------------------------------------------------------------------------------
# the regression step
# ---------------------------------------------------------------------------------------------


def _regress(plan: _Plan, state: _State) -> tuple[tuple, tuple, float, np.ndarray]:
    """Every system's update, its regression memory after it, the in-sample equation-3 cost of the updates.

    And the mask ``(N,)`` of the observations the updates were fitted to.
    """
    if state.phase == "grid" and plan.refine == "grid+points":
        updates, memory, sels = _regress_jointly(plan, state)
    else:
        updates, memory, sels = zip(*(_regress_system(plan, state, s) for s in range(len(plan.sizes))))
    fit_cost, trained = 0.0, np.zeros(len(plan.xy), bool)
    for model, sel in zip(updates, sels):
        trained[sel] = True
        r, var = state.out.residuals_px[sel], state.out.residual_var_px2[sel]
        fit_cost += float(np.sum((r - model.correction_at(plan.xy[sel])) ** 2 / var))
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
    if plan.params.training != "local":
        return model, mem, sel
    refit = _explained(plan, state, candidates, model)
    if not np.array_equal(refit, sel):
        model, mem = _fit(plan, state, s, refit, mem, refit=model)
    return model, mem, refit


def _regress_jointly(plan: _Plan, state: _State):
    """The refinement's joint step (:func:`_regress_system`'s, every system's field at once): updates, memory, rows."""
    screened = [_screened(plan, state, s) for s in range(len(plan.sizes))]
    sels = [sel for _, sel, _ in screened]
    memory = tuple(_smoothness(plan, state, s, sel, state.memory[s], cap) for s, (_, sel, cap) in enumerate(screened))
    updates = _fit_jointly(plan, state, sels, memory)
    if plan.params.training == "local":
        refits = [_explained(plan, state, candidates, u) for (candidates, _, _), u in zip(screened, updates)]
        if not all(np.array_equal(a, b) for a, b in zip(refits, sels)):
            updates, sels = _fit_jointly(plan, state, refits, memory, start=updates), refits
    return updates, memory, sels


def _screened(plan: _Plan, state: _State, s: int):
    """System ``s``'s candidate observations, those its regression learns from and their out-of-fold cost cap."""
    params, out, rows = plan.params, state.out, plan.rows[s]
    local = params.training == "local"
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
    screen = local_screen(plan.xy[sel], out.residuals_px[sel], out.residual_var_px2[sel], chi2=params.screen_chi2,
                          neighbours=near)  # fmt: skip
    return sel, _enough(sel, screen.keep, params.n_folds), screen.cost_cap


def _explained(plan: _Plan, state: _State, candidates: np.ndarray, model) -> np.ndarray:
    """The ``candidates`` the fitted ``model`` explains (the local training's misfit test)."""
    r, var = state.out.residuals_px[candidates], state.out.residual_var_px2[candidates]
    explained, _ = misfit_inliers(r, model.correction_at(plan.xy[candidates]), var, plan.params.outlier_chi2)
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
        model, _ = fit_knn_field(plan.xy[sel], r, var, cv=mem.cv, **knn)
        return model, mem
    k_grid = restricted_k_grid(params.k_grid, mem.k_prev)
    model, cv = fit_knn_field(
        plan.xy[sel], r, var, k_grid=k_grid, neighbour_cache=mem.neighbour_cache,
        neighbour_pool_px=plan.xy[plan.rows[s]], cost_cap=cost_cap, **knn
    )  # fmt: skip
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
    cv = cross_validate_smoothness(plan.xy[sel], out.residuals_px[sel], out.residual_var_px2[sel],
                                   image_size=plan.sizes[s], grid=params.grid, tau_grid_px=params.tau_grid_px,
                                   orders=params.smoothness_orders, n_folds=params.smoothness_folds, seed=params.seed,
                                   base_px=state.grids[s].delta_px, cost_cap=cost_cap)  # fmt: skip
    name = plan.observations.system_names[s]
    logger.info("system %s: gridded refinement, smoothness order %d, tau %.3g px (CV)", name, cv.order, cv.tau_px)
    return replace(mem, cv=cv, tau_px=cv.tau_px)


def _fit_jointly(plan: _Plan, state: _State, sels: list, memory: tuple, start=None) -> tuple:
    """Every system's refinement update by the joint problem's step (:func:`fit_grids_jointly`), from ``sels``.

    ``start``: updates of nearly the same observations to start the iterative solve from.
    """
    params, adj, observations = plan.params, state.adj, plan.observations
    nominal = plan.adjuster.nominal_shape(adj)[1] if params.affine_datum else None
    network = systems_network(adj, observations, sels, range(len(sels)), nominal)
    steps = []
    for s, (sel, mem) in enumerate(zip(sels, memory)):
        t_weight = adj.weight[sel, None] if params.training == "inliers" else 1.0
        w_obs = t_weight / (adj.sigma0 * observations.sigma_px[sel, :2]) ** 2
        r = state.out.residuals_px[sel]
        base, origin = state.grids[s], None if start is None else start[s].delta_px
        steps.append(SystemStep(plan.xy[sel], r, w_obs, adj.iop_px[s], plan.sizes[s], mem.tau_px, base,
                                mem.cv.cv_rms_px, mem.cv.order, origin))  # fmt: skip
    cg = dict(max_cg_iterations=LOOP_CG_ITERATIONS, cg_tolerance=LOOP_CG_TOLERANCE[state.respond])
    return fit_grids_jointly(steps, network, estimate_iop=plan.estimate_iop, grid=params.grid, respond=state.respond,
                             **cg)  # fmt: skip


# ---------------------------------------------------------------------------------------------
# the update of the correction
# ---------------------------------------------------------------------------------------------


def _update_field(plan: _Plan, state: _State, updates: tuple):
    """``Δ += δ``: the corrections at every observation, the fields and the acceleration's memory after it."""
    corrections = state.corrections.copy()
    xy, rows = plan.xy, plan.rows
    if plan.smooth:
        return _update_grids(plan, state, updates, corrections)
    factor = plan.params.relaxation if plan.acceleration == "overrelax" else 1.0
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
    if plan.acceleration == "anderson":
        mask = np.concatenate([np.repeat(u.support.ravel(), 2) for u in updates])
        x_new, anderson = anderson_step(anderson, x, x + dx, mask)
    elif plan.acceleration == "overrelax":
        x_new = x + params.relaxation * dx
    else:
        x_new = x + dx
    grids = _split_nodes(state.grids, updates, x_new)
    if params.field_gauge != "none":
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


# ---------------------------------------------------------------------------------------------
# the result
# ---------------------------------------------------------------------------------------------


def _result(plan: _Plan, scheme: str, state: _State, converged: bool, reason: str, t0: float, initial_residual):
    learned = state.iteration > 0
    fields, pointwise = _stored_fields(plan, state) if learned else (_identity_fields(plan.sizes), None)
    wall = time.perf_counter() - t0
    if learned:
        logger.info(
            "scheme %s: %s after %d iterations (%.1f s, of which %.1f s in the adjustment)",
            scheme,
            reason,
            state.iteration,
            wall,
            plan.adjuster.seconds,
        )
    cv = tuple(m.cv for m in state.memory) if learned else ()
    uncertainty = None
    if learned and plan.smooth and plan.refine != "none":  # the gridded refinement's fields: σ over the joint problem
        shape = plan.adjuster.nominal_shape(state.adj)[1]
        args = (state.adj, plan.observations, plan.rows, state.trained, state.grids, state.memory, plan.params)
        uncertainty = learned_uncertainty(*args, estimate_iop=plan.estimate_iop, nominal_shape_mm=shape)
        fields = fields if uncertainty is None else tuple(map(with_field_std, fields, uncertainty))
    return LearnResult(
        scheme=scheme,
        fields=fields,
        pointwise=pointwise,
        corrections_px=state.corrections,
        adjustment=state.adj,
        history=state.history,
        cv=cv,
        converged=converged,
        stop_reason=reason,
        wall_time_s=wall,
        adjust_time_s=plan.adjuster.seconds,
        initial_residual_px=initial_residual,
        trained=state.trained,
        uncertainty=uncertainty,
    )


def _identity_fields(sizes) -> tuple:
    return tuple(CorrectionField.constant(w, h) for w, h in sizes)


def _stored_fields(plan: _Plan, state: _State) -> tuple[tuple, tuple | None]:
    """The gridded fields to store, and the unsmoothed schemes' exact (pointwise) fields."""
    if plan.smooth:
        return state.grids, None
    fields = []
    for s, (model, mem) in enumerate(zip(state.updates, state.memory)):
        grid = state.pointwise[s].to_grid(plan.params.grid_spacing_px)
        sigma, support = node_statistics(model, grid.nodes_px, mem.cv.cv_rms_px, plan.params.grid)
        fields.append(
            grid.with_delta(
                grid.delta_px, sigma_px=sigma.reshape(grid.sigma_px.shape), support=support.reshape(grid.support.shape)
            )
        )
    return tuple(fields), state.pointwise


__all__ = ["calibrate"]
