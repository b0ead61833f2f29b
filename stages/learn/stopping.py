"""When the alternation's phase ends: the stopping rules of :func:`fluorocal.stages.learn.calibrate`, on its history.

A phase (the kNN steps, then the gridded refinement) ends when the combined
cost changes by less than ``tolerance`` per observation, when the correction
moves by less than ``step_tolerance`` times the inlier RMS, when (smoothed
schemes, in the refinement or when there is none) the gridded field moves by
less than ``field_tolerance`` times its own uncertainty with the adjustment's
cost stalled (two iterations running), or when the steps contract so fast that the
rest of the way to their fixed point, a geometric series, moves the field by less
than ``field_tolerance`` times its uncertainty and lowers the adjustment's cost by
less than its own noise (issue 31: converged by the measures a user cares about,
the field and the cost). In a refinement whose steps move the orientation too
(Gauss-Newton steps of the joint problem, or steps of the beads alone), it also ends
at the first iteration whose adjustment cost is not below the phase's best by
``stall_tolerance`` of it (the loop keeps its best iterate, never the last, so one
such iteration is enough). Otherwise at its iteration cap.
"""

from __future__ import annotations

import math

import numpy as np
from fluorocal.stages.learn.params import Refine


def decide(
    params, history: tuple, *, n_obs: int, iterations_in_phase: int, refine: Refine, stall_tolerance: float
) -> tuple[str, bool, str]:
    """``(action, converged, reason)``: ``"continue"`` or ``"end of phase"``, and why it ended.

    ``history``: the :class:`~fluorocal.stages.learn.result.IterationRecord` of every iteration so far;
    ``refine``: the loop's refinement (``Refine.NONE`` for the unsmoothed schemes, whatever ``params`` says);
    ``stall_tolerance``: ``params.stall_tolerance`` where the loop applies it, else 0 (off).
    """
    refine = Refine(refine)
    last, phase = history[-1], history[-1].phase
    prev = previous_total(history)
    small_change = prev is not None and abs(last.cost_total - prev) < params.tolerance * max(n_obs, 1)
    small_step = prev is not None and last.step_px < params.step_tolerance * last.rms_px
    # the kNN phase of the recommended loop is a few steps towards the refinement: the field rules end a phase
    # only once the field has been refined, or when there is no refinement to come
    field_phase = phase == "grid" or refine is Refine.NONE
    cost_tolerance = params.tolerance * max(n_obs, 1)
    running = (len(history) - 1, None)
    still_field = field_phase and all(
        _field_settled(history[:end], params.field_tolerance, cost_tolerance) for end in running
    )
    # the loop keeps its best iterate: one iteration that does not improve on it ends the refinement
    stalled = phase == "grid" and _cost_stalled(history, stall_tolerance)
    near = field_phase and _near_fixed_point(history, params.field_tolerance, n_obs)
    done = small_change or small_step or still_field or stalled or near
    cap = params.max_iterations if phase == "knn" else params.refine_iterations
    if not done and iterations_in_phase < cap:
        return "continue", False, ""
    if small_change:
        reason = (
            f"combined cost changed by {abs(last.cost_total - prev):.3g} < {params.tolerance} x {n_obs} observations"
        )
    elif small_step:
        reason = (
            f"the correction moved by at most {last.step_px:.3g} px < {params.step_tolerance} x the residual RMS "
            f"{last.rms_px:.3g} px"
        )
    elif still_field:
        reason = (
            f"the field moved by at most {last.step_sigma:.3g} < {params.field_tolerance} x its own uncertainty "
            "at every supported node and the adjustment's cost stopped falling, two iterations running"
        )
    elif stalled:
        reason = f"the adjustment's cost fell by less than {stall_tolerance:g} of itself below its best"
    elif near:
        reason = (
            f"the steps contract: the field is within {params.field_tolerance} x its own uncertainty of the fixed "
            f"point and the adjustment's cost within its noise (1/sqrt({n_obs} observations) of itself)"
        )
    elif phase == "grid":
        reason = f"maximum number of refinement iterations ({params.refine_iterations}) reached"
    else:
        reason = f"maximum number of iterations ({params.max_iterations}) reached"
    return "end of phase", done, reason


def _phase_costs(history: tuple) -> list:
    """The adjustment's cost (equation 2) at each iteration of the last iteration's phase."""
    return [h.cost_adjust for h in history if h.phase == history[-1].phase]


def _field_settled(history: tuple, field_tolerance: float, cost_tolerance: float) -> bool:
    """Whether the last iteration moved the field by less than ``field_tolerance`` sigma with the cost stalled.

    The cost has stalled when the adjustment's cost (equation 2) is not below the best of its phase's
    earlier iterations by ``cost_tolerance``. The adjustment's cost, not the combined one:
    the refinement's in-sample regression cost (equation 3 of a joint field step solved
    inexactly) wanders by tens of percent near the fixed point, where the adjustment's settles; while it
    still falls, the field is still being learned, however small one step.
    """
    phase = _phase_costs(history)
    return len(phase) > 2 and history[-1].step_sigma < field_tolerance and phase[-1] > min(phase[:-1]) - cost_tolerance


def _cost_stalled(history: tuple, stall_tolerance: float) -> bool:
    """Whether the adjustment's cost at the last iteration is not below its phase's best by that fraction of it."""
    phase = _phase_costs(history)
    return stall_tolerance > 0 and len(phase) > 2 and phase[-1] > min(phase[:-1]) * (1 - stall_tolerance)


def _near_fixed_point(history: tuple, field_tolerance: float, n_obs: int) -> bool:
    """Whether the steps contract so fast that the rest of the way, estimated, changes nothing the data can tell.

    Steps that contract by ``ρ`` leave ``s ρ / (1 - ρ)`` of the way to the fixed point after a step ``s``, a
    geometric series (:func:`remaining`). The field's rest of the way, in units of each node's own uncertainty,
    is below ``field_tolerance`` (its steps having shrunk twice running, so that one small step after a large
    one is not read as a contraction), and the adjustment's cost's rest of the way down is below one standard
    deviation of the cost itself: a weighted sum of squares of ``2n`` residuals, about ``χ²`` with ``2n``
    degrees of freedom, fluctuates by ``sqrt(2 · 2n)``, ``1/sqrt(n)`` of itself. An estimate, and an optimistic
    one where the contraction slows near the fixed point: on ``benchmarks/run_speed.py``'s sets it ends the
    refinement with 0.039 σ (40 frames) and 0.046 σ (biplanar, 75 + 75) estimated still to go where the later
    steps add up to 0.20 σ and 0.39 σ, and the cost's estimated 80 still to fall where 202 did (its noise 130;
    biplanar: 127 fell, noise 294); the field against the truth is the same as after 11 more iterations
    (0.01636 px; biplanar 0.01541 against 0.01544 px). The extrapolation from the slower of the last two
    ratios would have run the biplanar set two iterations more for nothing (its steps contracted by 0.29,
    then 0.08).
    """
    phase = [h for h in history if h.phase == history[-1].phase][-3:]
    if len(phase) < 3:
        return False
    steps = [h.step_sigma for h in phase]
    falls = [a.cost_adjust - b.cost_adjust for a, b in zip(phase[:-1], phase[1:])]
    shrinking = steps[0] > steps[1] > steps[2]
    cost_noise = phase[-1].cost_adjust / math.sqrt(max(n_obs, 1))
    return bool(shrinking and remaining(*steps[1:]) < field_tolerance and remaining(*falls) < cost_noise)


def remaining(before: float, last: float) -> float:
    """The sum of the steps still to come after ``last`` if each is ``last / before`` of the one before it.

    0 when ``last`` is not positive (nothing left to fall), infinite when the steps do not contract.
    """
    if last <= 0:
        return 0.0
    if not before > last:
        return float("inf")
    rho = last / before
    return last * rho / (1 - rho)


def previous_total(history: tuple) -> float | None:
    """The combined cost of the iteration before the last, if it is of the same phase."""
    return history[-2].cost_total if len(history) > 2 and history[-2].phase == history[-1].phase else None


def cost_raised(history: tuple) -> bool:
    """Whether the last step raised the cost, the refinement's adjustment cost, the kNN phase's combined one.

    The refinement's in-sample regression cost wanders by tens of percent from step to step (see
    the module's docstring): read in the combined cost, it restarted Anderson's history
    every other step.
    """
    if previous_total(history) is None:
        return False
    last, prev = history[-1], history[-2]
    if last.phase == "grid":
        return last.cost_adjust > prev.cost_adjust
    return last.cost_total > prev.cost_total


def field_step_sigma(before: tuple, after: tuple) -> float:
    """Largest change of a gridded field at a node supported after the step, in units of that node's sigma."""
    worst = 0.0
    for old, new in zip(before, after):
        change = np.linalg.norm(new.delta_px - old.delta_px, axis=-1)[new.support]
        if change.size:
            worst = max(worst, float(np.max(change / np.maximum(new.sigma_px[new.support], 1e-12))))
    return worst


__all__ = ["cost_raised", "decide", "field_step_sigma", "previous_total", "remaining"]
