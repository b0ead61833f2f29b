"""The adjustment seen from the alternation: every call into :mod:`fluorocal.stages.adjust` lives here.

The learning runs the robust bundle adjustment with the correction held
constant (:class:`Adjuster`), reads what the regression needs from its result
(:func:`adjustment_outcome`, :meth:`Adjuster.nominal_shape`)
and starts from a resection (:func:`start_orientation`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import numpy as np
from fluorocal.stages.adjust import (
    DataSelection,
    FreeParameters,
    Orientation,
    SolverOptions,
    adjust_bundle,
    index_of,
    initial_orientation,
    nominal_coordinates,
)

logger = logging.getLogger(__name__)

#: smallest redundancy number used for a residual's variance (a nearly determined observation
#: has a tiny residual variance; flooring it keeps such points from dominating equation 3)
MIN_REDUNDANCY = 0.05


class Adjuster:
    """``adjuster(corrections_px, previous, final=True) -> Adjustment``: the adjustment with Δ held constant.

    ``previous`` is None (start from ``initial``) or a previous
    :class:`fluorocal.stages.adjust.Adjustment`, from which the solve is
    warm-started in the poses, IOP, ROP *and* object points (the points as
    ``start_points``, so every solve's inner constraints refer to the same
    nominal design). With ``fast``, a solve that is not ``final`` runs
    without the covariance, with fewer iterations and a looser cost
    tolerance. ``free`` says which parameters every solve estimates: the
    scheme's choice (the kNN schemes estimate no additional parameters, so
    the learned field is the whole correction). ``seconds`` accumulates the
    time spent solving.
    """

    def __init__(
        self,
        observations,
        phantom,
        initial,
        *,
        free: FreeParameters,
        solver: SolverOptions | None = None,
        selection: DataSelection | None = None,
        fast: bool = False,
    ):
        self.observations, self.initial, self.fast = observations, initial, fast
        self.free, self.selection = free, selection or DataSelection()
        self.final_solver = solver or SolverOptions()
        # intermediate solves: no covariance, fewer iterations and a looser cost tolerance: 1e-6 per observation
        # (at least 1e-3), far below the noise the inexact field fits leave in the combined cost
        self.fast_solver = replace(
            self.final_solver,
            function_tolerance=max(self.final_solver.function_tolerance, 1e-3, 1e-6 * len(observations.xy_px)),
            max_iterations=min(self.final_solver.max_iterations, 10),
        )
        self.nominal = nominal_coordinates(phantom)
        self.seconds = 0.0

    def __call__(self, corrections_px, previous, final=True):
        t0 = time.perf_counter()
        intermediate = self.fast and not final
        try:
            adj = self._solve(corrections_px, previous, intermediate)
        finally:
            self.seconds += time.perf_counter() - t0
        # an intermediate solve stopped at its iteration cap is expected, not the user's concern
        if not intermediate and not adj.usable:
            inliers = 100 * float(adj.inlier[adj.used].mean()) if adj.used.any() else 0.0
            logger.warning("adjustment not usable: %s, %.1f %% inliers", adj.stop_reason, inliers)
        return adj

    def nominal_shape(self, adj) -> tuple[np.ndarray, np.ndarray]:
        """The adjusted bead coordinates ``(n_beads, 3)`` mm of ``adj`` and the nominal design's of the same beads."""
        nominal_ids, nominal_xyz = self.nominal
        return adj.xyz_mm, nominal_xyz[index_of(adj.bead_id, nominal_ids, "bead ids of the adjustment")]

    def _solve(self, corrections_px, previous, intermediate: bool):
        observations, initial = self.observations, self.initial
        options = {
            "free": self.free,
            "solver": self.fast_solver if intermediate else self.final_solver,
            "selection": self.selection,
            "compute_covariance": not intermediate,
        }
        if previous is None:
            return adjust_bundle(observations, self.nominal, initial, corrections_px, **options)
        # epochs the adjustment dropped keep their initial pose
        q, src = initial.q_cam_from_obj.copy(), initial.source_mm.copy()
        at = np.searchsorted(initial.exposure, previous.exposure)
        q[at], src[at] = previous.q_cam_from_obj, previous.source_mm
        warm = Orientation(
            previous.iop_px, initial.exposure, q, src, previous.rop_q, previous.rop_source_mm, initial.system_names
        )
        start = (previous.bead_id, previous.xyz_mm)
        return adjust_bundle(observations, self.nominal, warm, corrections_px, start_points=start, **options)


def start_orientation(observations, phantom, iop_guess_px):
    """Start values of every pose by resection (:func:`fluorocal.stages.adjust.initial_orientation`)."""
    return initial_orientation(observations, phantom, np.asarray(iop_guess_px, dtype=np.float64))


@dataclass(frozen=True)
class Outcome:
    """What the alternation needs from an :class:`fluorocal.stages.adjust.Adjustment`."""

    residuals_px: np.ndarray
    residual_var_px2: np.ndarray
    inlier: np.ndarray
    cost: float
    rms_px: float


def adjustment_outcome(adj, sigma_px: np.ndarray) -> Outcome:
    """Residuals ``(xy - Δ) - projection``, their variances ``σ0² σ² r`` and the inlier mask."""
    inlier = adj.inlier & adj.used
    red = np.clip(adj.redundancy, MIN_REDUNDANCY, None)
    var = (adj.sigma0 * sigma_px[:, :2]) ** 2 * red
    rms = float(np.sqrt(np.mean(adj.residual_px[inlier] ** 2))) if inlier.any() else float("nan")
    return Outcome(adj.residual_px, var, inlier, float(adj.cost_history[-1]), rms)


__all__ = ["Adjuster", "Outcome", "adjustment_outcome", "start_orientation"]
