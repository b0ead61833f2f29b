"""The learning's result from the loop's final state: the fields to store, their joint uncertainty, the record."""

from __future__ import annotations

import logging
import time

from fluorocal.stages.field import CorrectionField
from fluorocal.stages.learn.knn import node_statistics
from fluorocal.stages.learn.params import Refine
from fluorocal.stages.learn.result import LearnResult
from fluorocal.stages.learn.uncertainty import learned_uncertainty, with_field_std

logger = logging.getLogger("fluorocal.stages.learn.loop")


def loop_result(plan, scheme: str, state, converged: bool, reason: str, t0: float, initial_residual):
    learned = state.iteration > 0
    fields, pointwise = _stored_fields(plan, state) if learned else (_identity_fields(plan.sizes), None)
    wall = time.perf_counter() - t0
    if learned:
        logger.info(
            "scheme %s: %s after %d iterations (%.1f s, of which %.1f s in the adjustment)",
            scheme,
            reason,
            len(state.history) - 1,
            wall,
            plan.adjuster.seconds,
        )
    cv = tuple(m.cv for m in state.memory) if learned else ()
    uncertainty = None
    # the gridded refinement's fields: σ over the joint problem
    if learned and plan.smooth and plan.refine is not Refine.NONE:
        shape = plan.adjuster.nominal_shape(state.adj)[1]
        args = (state.adj, plan.observations, plan.rows, state.trained, state.grids, state.memory, plan.params)
        options = dict(estimate_iop=plan.estimate_iop, nominal_shape_mm=shape, workers=plan.workers)
        uncertainty = learned_uncertainty(*args, **options)
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


def _stored_fields(plan, state) -> tuple[tuple, tuple | None]:
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


__all__ = ["loop_result"]
