"""Gross errors in the regressions: a local screen before any fit, the misfit test after it, bounded CV costs.

A gross error (a bead moved by a few px, a label swapped with a neighbour's)
is not shared by its neighbours in the image, unlike distortion. So the
regressions of the learning loop (``training="local"``) take their training
set in two robust steps:

1. :func:`local_screen`: every observation against the leave-one-out
   component-wise *median* of its nearest neighbours' residuals, a local
   estimate that no few gross errors can pull; those whose squared
   standardised misfit exceeds ``chi2`` times the robust scale are left out
   of the cross-validation and of the first fit;
2. :func:`misfit_inliers`: every observation against the field fitted to
   the screened set; the field is refitted to those it explains.

Both are a hard-redescending (skipped) weight on the standardised misfit:
weight 1 below the threshold, 0 above it. And the cross-validations bound
each observation's out-of-fold cost at the same threshold
(:func:`capped_cost`), so a gross error that got through costs every
candidate alike instead of deciding the choice of ``k`` or of the smoothness.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import KDTree

#: neighbours of the local median of :func:`local_screen` (a median over 16 stays put under up to 7 gross errors)
SCREEN_NEIGHBOURS = 16

#: median of a chi-square with 2 degrees of freedom: 2 ln 2 (the robust scale of a squared 2-D Gaussian norm)
CHI2_2_MEDIAN = 2 * np.log(2)


def robust_threshold(z2: np.ndarray, chi2: float) -> float:
    """``chi2`` times the robust scale of squared standardised 2-D misfits ``z2``: ``chi2 median(z2) / (2 ln 2)``.

    Examples
    --------
    >>> round(robust_threshold(np.full(5, 2 * np.log(2)), 23.0), 6)
    23.0
    """
    if len(z2) == 0:
        return float("inf")
    return float(chi2 * max(float(np.median(z2)) / CHI2_2_MEDIAN, 1e-300))


def misfit_inliers(residuals_px, predicted_px, residual_var_px2, chi2: float) -> tuple[np.ndarray, float]:
    """Mask ``(N,)`` of the observations a prediction explains, and the threshold used.

    ``z2 = Σ_c (r - g)² / var`` per observation, kept when ``z2 <= chi2 median(z2) / (2 ln 2)``.
    """
    z2 = np.sum((residuals_px - predicted_px) ** 2 / residual_var_px2, axis=1)
    limit = robust_threshold(z2, chi2)
    return z2 <= limit, limit


@dataclass(frozen=True)
class Screen:
    """The outcome of :func:`local_screen`.

    Attributes
    ----------
    keep : (N,) bool ndarray
        Observations the local median explains.
    cost_cap : float
        The threshold on the squared standardised misfit, the cap of the CV costs (:func:`capped_cost`).
    """

    keep: np.ndarray
    cost_cap: float


def local_screen(
    xy_px, residuals_px, residual_var_px2, *, chi2: float, n_neighbours: int = SCREEN_NEIGHBOURS, neighbours=None
) -> Screen:
    """Screen observations against the leave-one-out median residual of their nearest neighbours.

    Parameters
    ----------
    xy_px, residuals_px : (N, 2) float64 ndarray, px
    residual_var_px2 : (N, 2) float64 ndarray, px²
    chi2 : float
        Threshold in units of the robust scale (``LearnParams.screen_chi2``).
    n_neighbours : int
        Neighbours of the median (default 16; fewer when there are fewer observations).
    neighbours : (N, >= n_neighbours) int ndarray, optional
        Each observation's nearest other observations (indices, nearest first), when at hand
        (:func:`fluorocal.stages.learn.knn.pool_neighbours`); default: a KD-tree's.

    Returns
    -------
    Screen

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> xy = rng.uniform(0, 100, (500, 2))
    >>> r = 0.01 * xy + rng.normal(0, 0.05, (500, 2))
    >>> r[:10] += 5.0
    >>> screen = local_screen(xy, r, np.full((500, 2), 0.05**2), chi2=23.0)
    >>> bool(screen.keep[:10].any()), round(float(screen.keep[10:].mean()), 2)
    (False, 1.0)
    """
    xy, r, var = (np.asarray(a, dtype=np.float64) for a in (xy_px, residuals_px, residual_var_px2))
    m = min(int(n_neighbours), len(xy) - 1)
    if m < 3:
        return Screen(np.ones(len(xy), bool), float("inf"))
    if neighbours is not None and np.shape(neighbours)[1] >= m:
        idx = np.asarray(neighbours)[:, :m]
    else:
        # the nearest is the observation itself (or one at the same place: a tie, dropped alike)
        idx = KDTree(xy).query(xy, k=m + 1)[1][:, 1:]
    local = np.median(r[idx], axis=1)  # shape (N, 2)
    keep, limit = misfit_inliers(r, local, var, chi2)
    return Screen(keep, limit)


def capped_cost(z2: np.ndarray, cap: float | None) -> np.ndarray:
    """Out-of-fold costs ``z2`` bounded at ``cap`` (None: unbounded, the plain equation-3 cost).

    Examples
    --------
    >>> capped_cost(np.array([1.0, 50.0]), 23.0).tolist(), capped_cost(np.array([50.0]), None).tolist()
    ([1.0, 23.0], [50.0])
    """
    return z2 if cap is None else np.minimum(z2, cap)


__all__ = ["SCREEN_NEIGHBOURS", "Screen", "capped_cost", "local_screen", "misfit_inliers", "robust_threshold"]
