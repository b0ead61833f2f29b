"""What the alternation returns: its history, one row per iteration, and the result."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class IterationRecord:
    """One row of the alternation's history (the paper's Fig. 5).

    Attributes
    ----------
    iteration : int
        0 is the adjustment with the initial (zero) correction.
    phase : str
        ``"adjust"`` (iteration 0), ``"knn"`` or ``"grid"`` (the refinement).
    cost_adjust : float
        Equation-2 cost (the adjustment's negative log-likelihood) after the update.
    cost_fit : float
        Equation-3 cost of the regression that produced the update (in sample, summed over systems).
    cost_total : float
        Their sum, the convergence criterion.
    k : tuple of int
        Neighbourhood size chosen per system (0 for the gridded least squares).
    rms_px : float
        RMS of the inlier residuals per component after the update, px.
    step_px : float
        Largest change of the correction at an observation, px.
    step_sigma : float
        Largest change of a gridded field at a supported node, in units of that node's uncertainty
        (the field's own ``sigma_px``); NaN for the unsmoothed schemes and iteration 0.
    """

    iteration: int
    phase: str
    cost_adjust: float
    cost_fit: float
    cost_total: float
    k: tuple
    rms_px: float
    step_px: float
    step_sigma: float = float("nan")


@dataclass(frozen=True)
class LearnResult:
    """The outcome of :func:`fluorocal.stages.learn.calibrate`.

    Attributes
    ----------
    scheme : str
    fields : tuple of CorrectionField
        One gridded field per system (for the unsmoothed scheme: the kNN sum
        sampled at the nodes, for storage and ``remap_maps``).
    pointwise : tuple of PointwiseField or None
        The unsmoothed scheme's exact fields (kNN sums), evaluated at new points.
    corrections_px : (N, 2) float64 ndarray, px
        Final ``Δ`` at every observation.
    adjustment : object
        The final :class:`fluorocal.stages.adjust.Adjustment` (with ``Δ`` held at ``corrections_px``).
    history : tuple of IterationRecord
    cv : tuple
        The last cross-validation report per system.
    converged : bool
    stop_reason : str
    wall_time_s : float
    adjust_time_s : float
        Part of ``wall_time_s`` spent in :func:`fluorocal.stages.adjust.adjust_bundle`.
    initial_residual_px : (N, 2) float64 ndarray or None, px
        Residuals of the first adjustment, with no correction (the "before" of the report).
    trained : (N,) bool ndarray or None
        The observations the last regression learned from (None when nothing was learned).

    For scheme ``polynomial`` the ``adjustment`` is the one that estimated
    the model (its ``ap_px``, ``ap_std_px``; held at no correction), and
    ``corrections_px`` is that model at the observations.
    """

    scheme: str
    fields: tuple
    pointwise: tuple | None
    corrections_px: np.ndarray
    adjustment: object
    history: tuple
    cv: tuple
    converged: bool
    stop_reason: str
    wall_time_s: float
    adjust_time_s: float = 0.0
    initial_residual_px: np.ndarray | None = None
    trained: np.ndarray | None = None

    def summary(self) -> str:
        """One line: scheme, in-sample RMS before and after, iterations and how the loop stopped."""
        adj = self.adjustment
        inl = adj.inlier
        after = float(np.sqrt(np.mean(adj.residual_px[inl] ** 2))) if inl.any() else float("nan")
        before = (
            float(np.sqrt(np.mean(self.initial_residual_px[inl] ** 2)))
            if self.initial_residual_px is not None and inl.any()
            else float("nan")
        )
        n_iterations = len(self.history) - 1
        rms = f"in-sample RMS {before:.3f} -> {after:.3f} px"
        return f"{self.scheme}: {rms}, {n_iterations} iterations, {self.stop_reason}"

    def field(self, system: int):
        """The correction to apply to new observations of ``system`` (exact kNN sum when unsmoothed)."""
        return self.pointwise[system] if self.pointwise is not None else self.fields[system]


__all__ = ["IterationRecord", "LearnResult"]
