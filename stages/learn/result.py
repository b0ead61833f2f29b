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
    uncertainty : tuple of JointUncertainty or None
        Per system, the IOP's and the field's uncertainty with the field estimated jointly
        (:mod:`fluorocal.stages.learn.uncertainty`); None where it is not defined (schemes
        without the gauge-fixed gridded refinement or without the IOP). Where given, the
        ``fields``' ``sigma_px`` are its node σ and :attr:`iop_std_px` its IOP σ.

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
    uncertainty: tuple | None = None

    @property
    def iop_std_px(self) -> np.ndarray:
        """``(S, 3)`` px: the IOP's σ, with the field estimated jointly where known, else the adjustment's."""
        std = np.array(self.adjustment.iop_std_px, dtype=np.float64)
        for s, u in enumerate(self.uncertainty or ()):
            std[s] = u.iop_std_px
        return std

    def point_std_px(self, system: int, xy_px: np.ndarray, sigma_xy_px: np.ndarray) -> np.ndarray:
        """``(n, 2)`` px: predicted σ of undistorted points ``xy - Δ(xy)`` measured with σ ``sigma_xy_px`` ``(n, 2)``.

        The field's per-component node σ interpolated bilinearly (adjacent nodes taken as fully
        correlated, as a smooth field's are nearly) combined with the measurement's. Without a joint
        uncertainty, the stored field's ``sigma_px`` stands for both components.
        """
        from fluorocal.stages.field import bilinear

        field = self.fields[system]
        if self.uncertainty is not None:
            node = self.uncertainty[system].node_std_px
        else:
            node = np.repeat(field.sigma_px[..., None], 2, axis=-1)
        at = bilinear(field.x_nodes_px, field.y_nodes_px, node, np.asarray(xy_px, dtype=np.float64))
        return np.sqrt(at**2 + np.asarray(sigma_xy_px, dtype=np.float64) ** 2)

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
