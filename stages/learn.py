"""Self-supervised distortion learning: a cross-validated kNN field alternating with the adjustment.

Chow et al., section IV after equation 2 and section VI: the residuals of the
robust bundle adjustment hold a deterministic part (distortion, the
intensifier's departure from a pinhole) and a random part. A k-nearest-
neighbour regression of the inlier residual vectors over the image learns the
deterministic part ``δ``; the corrections are accumulated, ``Δ += δ``, at every
observation and the adjustment is repeated with ``Δ`` held constant, until the
sum of the weighted costs of equations 2 and 3 stops falling.

Conventions (README.md, "Conventions"): pixel coordinates ``(x, y)`` with the
centre of the top-left pixel at ``(0, 0)``; the correction ``Δ`` acts on
measured (distorted) coordinates, ``ideal = measured - Δ(measured)``.

Pieces
------
- :class:`KnnModel`: the kNN regressor itself (inverse-variance weighted mean
  of the ``k`` nearest residuals, the minimiser of equation 3 for a locally
  constant field), evaluated anywhere with a KD-tree.
- :func:`cross_validate_k`: ``k`` from shuffled K-fold cross-validation of the
  equation-3 cost, never from the in-sample fit (which would chase noise).
- :class:`CorrectionField`: the stored result, ``Δ`` on a rectilinear grid of
  nodes over the image with bilinear interpolation (the paper's "smoothed
  kNN"), a per-node uncertainty and a support mask; ``undistort_points``,
  ``distort_points`` (Newton) and ``remap_maps`` (inverse maps for ``cv2.remap``).
- :class:`PointwiseField`: the unsmoothed scheme's ``Δ``, a sum of kNN models.
- :func:`fit_knn_field`: one regression step (cross-validation, then the kNN
  model or its gridded resampling).
- :func:`calibrate`: the alternation with :func:`stages.adjust.adjust_bundle`
  and its schemes (``none``, ``knn``, ``knn+iop``, ``knn+smooth``,
  ``knn+iop+smooth``), and ``polynomial``: the expert method the paper
  compares with, a global radial + decentring (+ affinity) model estimated
  in the adjustment (:mod:`stages._polynomial`), sampled onto the same grid.

Beyond the paper (``LearnParams.acceleration`` and ``LearnParams.refine``)
-------------------------------------------------------------------------
- Over-relaxation or Anderson acceleration of the fixed-point iteration.
- After the kNN loop, a refinement that fits the grid's node values to the
  residuals by weighted least squares with a thin-plate smoothness prior on
  the total field (:func:`fit_grid_field`; the prior chosen by
  cross-validation of equation 3), optionally together with 3D shifts of the
  object points (:func:`fit_grid_with_points`), which removes most of the
  coupling that makes the plain alternation slow (the free phantom absorbs
  part of the field at every adjustment).
- ``LearnParams.training="local"``: learn from every observation the
  adjustment used, less those the field itself cannot explain, instead of the
  adjustment's inliers (which, before the distortion is modelled, exclude the
  strongly distorted rim, so the rim is never learned and the loop stalls).
- ``LearnParams.field_gauge="orientation"``: remove from the field, after
  every update, what the IOP and a common rotation of the poses reproduce
  exactly (an 8-parameter homography's 4 to 6 orientation directions), so the
  IOP cannot drift along this gauge (they become the best pinhole over the
  observed area).
- ``LearnParams.fast_intermediate``: intermediate adjustments without the
  covariance and with a short, looser LM; only the final solve in full.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
from fluorocal.stages import _polynomial
from fluorocal.stages.adjust import _lookup, _nominal_table
from fluorocal.stages.artifacts import check_shape, freeze
from fluorocal.stages.errors import EstimationError, InputError, ShapeError
from scipy.spatial import KDTree

logger = logging.getLogger(__name__)

VERSION = 1

#: calibration schemes: the adjustment alone, the paper's four, and the global polynomial model in the adjustment
SCHEMES = ("none", "knn", "knn+iop", "knn+smooth", "knn+iop+smooth", "polynomial")

_DEFAULT_K_GRID = (1, 2, 3, 4, 6, 8, 11, 16, 23, 32, 45, 64, 90, 128, 181, 256)

#: forward-difference stencils of the smoothness prior's orders
_DIFFERENCE_STENCILS = {1: (-1.0, 1.0), 2: (1.0, -2.0, 1.0), 3: (-1.0, 3.0, -3.0, 1.0), 4: (1.0, -4.0, 6.0, -4.0, 1.0)}


@dataclass(frozen=True)
class LearnParams:
    """Parameters of the kNN regression and of the alternation.

    Attributes
    ----------
    k_grid : tuple of int
        Candidate neighbourhood sizes for the cross-validation (default
        1, 2, 3, 4, 6, ..., 181, 256: roughly ``sqrt(2)`` steps). Candidates larger
        than a training fold are dropped.
    n_folds : int
        Folds of the cross-validation (default 10, as in the paper).
    grid_spacing_px : float
        Largest spacing between grid nodes (default 16 px); the nodes are
        spread evenly over ``[-0.5, W - 0.5]`` and ``[-0.5, H - 0.5]``.
    smooth : bool
        Resample the kNN prediction onto the grid and interpolate it
        bilinearly (the paper's "smoothed kNN", default True); False predicts
        the kNN directly at the points.
    seed : int
        Seed of the fold shuffling (default 0).
    support_radius_px : float or None
        Radius within which a node counts observations for the support mask
        (default None: twice ``grid_spacing_px``).
    min_support : int
        Observations needed within ``support_radius_px`` of a node for it to be
        supported (default 3).
    max_iterations : int
        Cap on the alternation's outer iterations (default 30, the paper's typical count).
    tolerance : float
        Stop when the combined cost changes by less than ``tolerance`` per
        observation between iterations (default 1e-4).
    step_tolerance : float
        Also stop when the largest change of the correction at any observation
        falls below this fraction of the inlier residual RMS (default 0: off,
        the paper's criterion alone). Inexact inner solves leave the combined
        cost a little noisy near the fixed point; the step still shows that
        the field has stopped moving.
    acceleration : str
        ``"none"`` (the paper's plain fixed-point loop, default),
        ``"overrelax"`` (``Δ += relaxation δ``) or ``"anderson"`` (Anderson
        acceleration of the gridded field's fixed-point iteration; needs ``smooth``).
    relaxation : float
        Step factor of ``"overrelax"`` (default 1.5; 1 is the plain loop).
    anderson_depth : int
        Past iterates Anderson acceleration combines (default 10).
    refine : str
        ``"none"`` (default: the paper's kNN only), ``"grid"``: once the kNN
        alternation has converged, continue alternating with the gridded
        least-squares field of :func:`fit_grid_field`, or ``"grid+points"``:
        the same with the field estimated jointly with the object points
        (:func:`fit_grid_with_points`). Both need ``smooth``.
    tau_grid_px : tuple of float
        Candidate smoothness priors (px, standard deviation of a node's
        difference of the prior's order, second by default) for the
        refinement, chosen by cross-validation (default
        0.03, 0.1, 0.3, 1, 3 px; the prior acts on the total field, whose
        strong radial part has second differences of ~0.1 px at a 16 px
        spacing near the rim of a 1024 px image, so smaller values bias it).
    smoothness_folds : int
        Folds of that cross-validation (default 5: it runs once per system and
        each fold costs a sparse factorisation per candidate).
    smoothness_orders : tuple of int
        Candidate orders ``m`` of the difference prior (default ``(2,)``: the
        thin-plate energy, second differences). The prior penalises the
        discrete ``m``-th order energy ``Σ_a C(m, a) (∂^m Δ / ∂x^(m-a) ∂y^a)²``
        (null space: the polynomials of degree below ``m``); a higher order
        assumes a smoother field and biases its large-scale, strong part
        (the radial distortion) less, so it can smooth the noise harder. With
        several candidates the cross-validation chooses the order together
        with ``τ`` (each order costs ``len(tau_grid_px)`` candidates more).
    refine_iterations : int
        Cap on the alternation's iterations with the gridded least-squares field (default 15).
    affine_datum : bool
        With ``refine="grid+points"``: hold the phantom's affine shape beyond a
        similarity (stretches and shears: 5 degrees of freedom) at the nominal
        design's while refining (default False, the paper's inner constraints
        only). In a free network these deformations trade off against an
        image aspect ratio or shear of the field through weak perspective
        effects only; see :func:`fit_grid_with_points`.
    training : str
        Which observations each regression learns from. ``"inliers"``: the
        adjustment's inliers (the paper). ``"local"`` (default): every
        observation the adjustment used, less those the fitted field itself
        cannot explain (squared standardised misfit above ``outlier_chi2``
        times its median / ln 4, the robust scale of a 2-D Gaussian), refitted
        without them. While the distortion is still unmodelled the
        adjustment's t-weights flag the strongly distorted rim of the field as
        outliers, so an inlier-only regression never learns the rim and the
        loop stalls; gross errors (mislabels), unlike distortion, are not
        shared by their neighbours, which is what the local test uses. With
        ``"local"`` the joint refinement also weights observations by their
        variances only, not their t-weights.
    field_gauge : str
        ``"orientation"`` (default): after every update, remove from each
        system's field its least-squares component (over the observations)
        that the orientation parameters reproduce exactly: an image rotation
        and the two "keystone" fields of a common rotation of every pose
        (absorbed, biplanar, by the ROP), and, when the IOP are estimated, a
        principal-point shift and a principal-distance scaling. These trade
        one for one between field and adjustment; left free they let the
        IOP (and the alternation's fixed point) drift without bound, as on a
        turntable set. The IOP then are the best pinhole over the observed
        area, and the field the departure from it. ``"none"``: the paper (the
        field keeps whatever the loop leaves in it).
    outlier_chi2 : float
        Threshold of the local outlier test of ``training="local"`` (default
        23: a 2-D Gaussian exceeds it with probability 1e-5).
    fast_intermediate : bool
        Solve the loop's intermediate adjustments without the covariance and
        redundancy numbers (each observation gets the mean redundancy), with
        ``function_tolerance`` at least 1e-3 and at most 10 iterations (they
        are warm-started), and only the final solve in full (default True).
        False: every solve with the given AdjustParams (the paper's loop).

    The paper's four schemes as written: ``acceleration="none"``,
    ``refine="none"``, ``training="inliers"``, ``field_gauge="none"``,
    ``fast_intermediate=False``.
    """

    k_grid: tuple = _DEFAULT_K_GRID
    n_folds: int = 10
    grid_spacing_px: float = 16.0
    smooth: bool = True
    seed: int = 0
    support_radius_px: float | None = None
    min_support: int = 3
    max_iterations: int = 30
    tolerance: float = 1e-4
    step_tolerance: float = 0.0
    acceleration: str = "none"
    relaxation: float = 1.5
    anderson_depth: int = 10
    refine: str = "none"
    tau_grid_px: tuple = (0.03, 0.1, 0.3, 1.0, 3.0)
    smoothness_folds: int = 5
    smoothness_orders: tuple[int, ...] = (2,)
    refine_iterations: int = 15
    affine_datum: bool = False
    training: str = "local"
    field_gauge: str = "orientation"
    outlier_chi2: float = 23.0
    fast_intermediate: bool = True

    def __post_init__(self):
        object.__setattr__(self, "k_grid", tuple(sorted({int(k) for k in self.k_grid})))
        if not self.k_grid or self.k_grid[0] < 1:
            raise InputError(f"k_grid must hold positive integers; got {self.k_grid}")
        if self.n_folds < 2:
            raise InputError(f"n_folds must be >= 2; got {self.n_folds}")
        if not self.grid_spacing_px > 0:
            raise InputError(f"grid_spacing_px must be > 0; got {self.grid_spacing_px}")
        if self.acceleration not in ("none", "overrelax", "anderson"):
            raise InputError(f"acceleration must be 'none', 'overrelax' or 'anderson'; got {self.acceleration!r}")
        if self.acceleration == "anderson" and not self.smooth:
            raise InputError("acceleration='anderson' needs smooth=True (it combines gridded fields)")
        if self.refine not in ("none", "grid", "grid+points"):
            raise InputError(f"refine must be 'none', 'grid' or 'grid+points'; got {self.refine!r}")
        if self.refine != "none" and not self.smooth:
            raise InputError("refine='grid' needs smooth=True (it refines the gridded field)")
        if self.affine_datum and self.refine != "grid+points":
            raise InputError(
                f"affine_datum needs refine='grid+points' (it constrains the point shifts); got refine={self.refine!r}"
            )
        object.__setattr__(self, "tau_grid_px", tuple(float(t) for t in self.tau_grid_px))
        if not self.tau_grid_px or min(self.tau_grid_px) <= 0:
            raise InputError(f"tau_grid_px must hold positive values; got {self.tau_grid_px}")
        object.__setattr__(self, "smoothness_orders", tuple(sorted({int(m) for m in self.smoothness_orders})))
        if not self.smoothness_orders or not set(self.smoothness_orders) <= set(_DIFFERENCE_STENCILS):
            raise InputError(
                f"smoothness_orders must hold orders among {tuple(_DIFFERENCE_STENCILS)}; got {self.smoothness_orders}"
            )
        if not 0 < self.relaxation < 2:
            raise InputError(f"relaxation must lie in (0, 2); got {self.relaxation}")
        if self.max_iterations < 1:
            raise InputError(f"max_iterations must be >= 1; got {self.max_iterations}")
        if self.training not in ("inliers", "local"):
            raise InputError(f"training must be 'inliers' or 'local'; got {self.training!r}")
        if self.field_gauge not in ("none", "orientation"):
            raise InputError(f"field_gauge must be 'none' or 'orientation'; got {self.field_gauge!r}")
        if not self.step_tolerance >= 0:
            raise InputError(f"step_tolerance must be >= 0; got {self.step_tolerance}")
        if not self.outlier_chi2 > 0:
            raise InputError(f"outlier_chi2 must be > 0; got {self.outlier_chi2}")

    @property
    def support_radius(self) -> float:
        """Support radius in px (``support_radius_px`` or twice the grid spacing)."""
        return float(self.support_radius_px if self.support_radius_px is not None else 2 * self.grid_spacing_px)


# ---------------------------------------------------------------------------------------------
# kNN regression
# ---------------------------------------------------------------------------------------------


def _check_training(xy_px, residuals_px, residual_var_px2):
    xy = np.asarray(xy_px, dtype=np.float64)
    r = np.asarray(residuals_px, dtype=np.float64)
    var = np.asarray(residual_var_px2, dtype=np.float64)
    check_shape("xy_px", xy, (None, 2))
    check_shape("residuals_px", r, (len(xy), 2))
    if var.ndim == 1:
        var = np.repeat(var[:, None], 2, axis=1)
    check_shape("residual_var_px2", var, (len(xy), 2))
    if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(r))):
        raise InputError("xy_px and residuals_px must be finite")
    if not np.all(var > 0) or not np.all(np.isfinite(var)):
        raise InputError("residual_var_px2 must be finite and > 0")
    return xy, r, var


def _weighted_neighbour_means(values, weights, idx, ks):
    """Inverse-variance weighted means of the first ``k`` neighbours, for each ``k`` in ``ks``.

    Parameters
    ----------
    values, weights : (N, 2) float64 ndarray
    idx : (M, K) int ndarray
        Neighbour indices, nearest first.
    ks : sequence of int, each <= K

    Returns
    -------
    (M, len(ks), 2) float64 ndarray
    """
    w = weights[idx]  # shape (M, K, 2)
    cw = np.cumsum(w, axis=1)
    cwr = np.cumsum(w * values[idx], axis=1)
    sel = np.asarray(ks) - 1
    return cwr[:, sel] / cw[:, sel]


@dataclass(frozen=True)
class KnnModel:
    """A kNN regressor of residual vectors over the image.

    The prediction at ``x`` is, per component, the inverse-variance weighted
    mean of the residuals of the ``k`` nearest training points: the
    minimiser of equation 3 of the paper for a field that is constant over
    the neighbourhood.

    Attributes
    ----------
    points_px : (N, 2) float64 ndarray, px
        Training coordinates (measured).
    values_px : (N, 2) float64 ndarray, px
        Training residual vectors.
    weights : (N, 2) float64 ndarray, 1/px²
        Inverse residual variances (diagonal of ``C_r^-1``).
    k : int
        Neighbourhood size (clipped to N when used).
    """

    points_px: np.ndarray
    values_px: np.ndarray
    weights: np.ndarray
    k: int

    def __post_init__(self):
        for name in ("points_px", "values_px", "weights"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        n = len(self.points_px)
        check_shape("points_px", self.points_px, (n, 2))
        check_shape("values_px", self.values_px, (n, 2))
        check_shape("weights", self.weights, (n, 2))
        if n == 0:
            raise InputError("KnnModel needs at least one training point")
        if self.k < 1:
            raise InputError(f"k must be >= 1; got {self.k}")
        freeze(self)

    @cached_property
    def tree(self) -> KDTree:
        """KD-tree over the training points (built on first use)."""
        return KDTree(self.points_px)

    @property
    def k_used(self) -> int:
        return min(int(self.k), len(self.points_px))

    def neighbours(self, xy_px: np.ndarray, k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Distances ``(M, k)`` px and indices ``(M, k)`` of the nearest training points."""
        k = self.k_used if k is None else min(k, len(self.points_px))
        dist, idx = self.tree.query(np.asarray(xy_px, dtype=np.float64).reshape(-1, 2), k=k)
        return dist.reshape(-1, k), idx.reshape(-1, k)

    def correction_at(self, xy_px: np.ndarray) -> np.ndarray:
        """KNN prediction ``(M, 2)`` px at measured coordinates ``xy_px`` ``(M, 2)`` px."""
        xy = np.asarray(xy_px, dtype=np.float64).reshape(-1, 2)
        if len(xy) == 0:
            return np.empty((0, 2))
        _, idx = self.neighbours(xy)
        return _weighted_neighbour_means(self.values_px, self.weights, idx, [self.k_used])[:, 0]

    def scaled(self, factor: float) -> "KnnModel":
        """The same regressor with its values multiplied by ``factor`` (over-relaxation)."""
        return replace(self, values_px=self.values_px * factor)


@dataclass(frozen=True)
class CvReport:
    """Cross-validation of the neighbourhood size.

    Attributes
    ----------
    k_grid : (K,) int64 ndarray
        Candidates evaluated.
    cv_cost : (K,) float64 ndarray
        Mean out-of-fold equation-3 cost per observation,
        ``mean_i (r_i - g(x_i))^T C_r^-1 (r_i - g(x_i))`` (dimensionless; 2 for
        a perfect model of the deterministic part and correct variances).
    k : int
        The chosen ``k`` (smallest cost).
    cv_rms_px : float
        Out-of-fold RMS per component of ``r - g`` at the chosen ``k``, px.
    n_points : int
        Observations used.
    """

    k_grid: np.ndarray
    cv_cost: np.ndarray
    k: int
    cv_rms_px: float
    n_points: int

    def __post_init__(self):
        object.__setattr__(self, "k_grid", np.asarray(self.k_grid, dtype=np.int64))
        object.__setattr__(self, "cv_cost", np.asarray(self.cv_cost, dtype=np.float64))
        freeze(self)

    def table(self) -> str:
        """The CV table as text, one ``k cost`` line per candidate, the chosen one starred."""
        return "\n".join(f"{k:5d} {c:12.6g}{' *' if k == self.k else ''}" for k, c in zip(self.k_grid, self.cv_cost))


def cross_validate_k(
    xy_px: np.ndarray,
    residuals_px: np.ndarray,
    residual_var_px2: np.ndarray,
    *,
    k_grid,
    n_folds: int,
    seed: int,
    neighbour_cache: dict | None = None,
) -> CvReport:
    """Choose ``k`` by shuffled K-fold cross-validation of the equation-3 cost.

    Parameters
    ----------
    xy_px : (N, 2) float64 ndarray, px
        Measured coordinates of the (inlier) observations.
    residuals_px : (N, 2) float64 ndarray, px
        Residual vectors of the adjustment.
    residual_var_px2 : (N, 2) or (N,) float64 ndarray, px²
        Variances of the residuals (the diagonal of ``C_r``).
    k_grid : sequence of int
    n_folds : int
    seed : int
        Seed of the shuffling of the observations into folds.
    neighbour_cache : dict, optional
        Filled with each fold's neighbour indices, and reused by a later call
        on the same coordinates, folds and at most as many neighbours (they
        depend on the coordinates only, not on the residuals: the
        alternation's iterations share them).

    Returns
    -------
    CvReport

    Notes
    -----
    Each observation is predicted only from the other folds, so a ``k`` that
    fits noise (``k = 1`` reproduces each residual in sample) pays for it
    out of fold. The cost is equation 3,
    ``G = (r - g)^T C_r^-1 (r - g)`` with diagonal ``C_r``, averaged over the
    observations.
    """
    xy, r, var = _check_training(xy_px, residuals_px, residual_var_px2)
    n = len(xy)
    n_folds = min(int(n_folds), n)
    if n_folds < 2:
        raise InputError(f"cross-validation needs at least 2 observations; got {n}")
    w = 1.0 / var
    folds = np.array_split(np.random.default_rng(seed).permutation(n), n_folds)
    n_train_min = n - max(len(f) for f in folds)
    ks = np.array([k for k in sorted(set(int(k) for k in k_grid)) if k <= n_train_min], dtype=np.int64)
    if len(ks) == 0:
        raise InputError(f"k_grid {tuple(k_grid)} has no candidate <= the training fold size {n_train_min}")
    cache = neighbour_cache if neighbour_cache is not None else {}
    if not (
        cache.get("n_folds") == n_folds
        and cache.get("seed") == seed
        and cache.get("k", 0) >= ks[-1]
        and np.array_equal(cache.get("xy"), xy)
    ):
        cache.clear()
        cache.update(xy=xy.copy(), n_folds=n_folds, seed=seed, k=int(ks[-1]), idx=[])
        for test in folds:
            train = np.setdiff1d(np.arange(n), test, assume_unique=True)
            _, idx = KDTree(xy[train]).query(xy[test], k=int(ks[-1]))
            cache["idx"].append(idx.reshape(len(test), -1).astype(np.int32))
    cost = np.zeros(len(ks))
    sq = np.zeros(len(ks))
    for test, idx in zip(folds, cache["idx"]):
        train = np.setdiff1d(np.arange(n), test, assume_unique=True)
        g = _weighted_neighbour_means(r[train], w[train], idx[:, : ks[-1]], ks)  # shape (n_test, K, 2)
        err = r[test][:, None, :] - g
        cost += np.sum(w[test][:, None, :] * err**2, axis=(0, 2))
        sq += np.sum(err**2, axis=(0, 2))
    cost /= n
    best = int(np.argmin(cost))
    return CvReport(ks, cost, int(ks[best]), float(np.sqrt(sq[best] / (2 * n))), n)


# ---------------------------------------------------------------------------------------------
# Fields
# ---------------------------------------------------------------------------------------------


def _bilinear(x_nodes, y_nodes, values, xy, *, gradient=False):
    """Bilinear interpolation of node values on a rectilinear grid, clamped outside.

    Parameters
    ----------
    x_nodes : (W_g,) float64 ndarray, increasing
    y_nodes : (H_g,) float64 ndarray, increasing
    values : (H_g, W_g, C) float64 ndarray
    xy : (M, 2) float64 ndarray

    Returns
    -------
    out : (M, C) float64 ndarray
    d_dx, d_dy : (M, C) float64 ndarray
        Only with ``gradient=True``; zero where the coordinate was clamped.
    """
    x = np.clip(xy[:, 0], x_nodes[0], x_nodes[-1])
    y = np.clip(xy[:, 1], y_nodes[0], y_nodes[-1])
    i = np.clip(np.searchsorted(x_nodes, x, side="right") - 1, 0, len(x_nodes) - 2)
    j = np.clip(np.searchsorted(y_nodes, y, side="right") - 1, 0, len(y_nodes) - 2)
    hx = x_nodes[i + 1] - x_nodes[i]
    hy = y_nodes[j + 1] - y_nodes[j]
    tx = ((x - x_nodes[i]) / hx)[:, None]
    ty = ((y - y_nodes[j]) / hy)[:, None]
    v00, v01 = values[j, i], values[j, i + 1]
    v10, v11 = values[j + 1, i], values[j + 1, i + 1]
    top = v00 + tx * (v01 - v00)
    bottom = v10 + tx * (v11 - v10)
    out = top + ty * (bottom - top)
    if not gradient:
        return out
    inside_x = ((xy[:, 0] > x_nodes[0]) & (xy[:, 0] < x_nodes[-1]))[:, None]
    inside_y = ((xy[:, 1] > y_nodes[0]) & (xy[:, 1] < y_nodes[-1]))[:, None]
    d_dx = ((1 - ty) * (v01 - v00) + ty * (v11 - v10)) / hx[:, None] * inside_x
    d_dy = (bottom - top) / hy[:, None] * inside_y
    return out, d_dx, d_dy


def _bilinear_design(x_nodes, y_nodes, xy):
    """Sparse matrix ``(M, H_g * W_g)`` mapping flattened node values to bilinear values at ``xy``."""
    from scipy.sparse import csr_matrix

    n_x = len(x_nodes)
    x = np.clip(xy[:, 0], x_nodes[0], x_nodes[-1])
    y = np.clip(xy[:, 1], y_nodes[0], y_nodes[-1])
    i = np.clip(np.searchsorted(x_nodes, x, side="right") - 1, 0, n_x - 2)
    j = np.clip(np.searchsorted(y_nodes, y, side="right") - 1, 0, len(y_nodes) - 2)
    tx = (x - x_nodes[i]) / (x_nodes[i + 1] - x_nodes[i])
    ty = (y - y_nodes[j]) / (y_nodes[j + 1] - y_nodes[j])
    cols = np.stack([j * n_x + i, j * n_x + i + 1, (j + 1) * n_x + i, (j + 1) * n_x + i + 1], 1)
    vals = np.stack([(1 - tx) * (1 - ty), tx * (1 - ty), (1 - tx) * ty, tx * ty], 1)
    rows = np.repeat(np.arange(len(xy)), 4)
    return csr_matrix((vals.ravel(), (rows, cols.ravel())), shape=(len(xy), n_x * len(y_nodes)))


def _invert_correction(correction_at, xy_ideal, *, jacobian=None, tol_px=1e-9, max_iter=50):
    """Solve ``m - Δ(m) = u`` for measured ``m`` given ideal ``u`` (the distortion).

    Newton's method when ``jacobian(m) -> (dΔ/dx, dΔ/dy)`` is given (each
    ``(M, 2)``), else the fixed-point iteration ``m <- u + Δ(m)``, which
    converges whenever the field's gradient is below 1 (any physical
    distortion field: it does not fold the image).
    """
    u = np.asarray(xy_ideal, dtype=np.float64).reshape(-1, 2)
    m = u + correction_at(u)
    for _ in range(max_iter):
        if jacobian is None:
            step = u + correction_at(m) - m
        else:
            f = m - correction_at(m) - u
            ddx, ddy = jacobian(m)
            # J = I - dΔ/dm, per point 2x2: [[1 - dΔx/dx, -dΔx/dy], [-dΔy/dx, 1 - dΔy/dy]]
            a, b = 1 - ddx[:, 0], -ddy[:, 0]
            c, d = -ddx[:, 1], 1 - ddy[:, 1]
            det = a * d - b * c
            step = -np.column_stack([d * f[:, 0] - b * f[:, 1], -c * f[:, 0] + a * f[:, 1]]) / det[:, None]
        m = m + step
        if len(m) == 0 or np.max(np.abs(step)) < tol_px:
            break
    else:
        logger.warning(
            "distort_points: %d of %d points not converged to %.1e px",
            np.sum(np.abs(step).max(1) >= tol_px),
            len(m),
            tol_px,
        )
    return m


class _FieldOps:
    """Operations every correction field derives from its ``correction_at``."""

    def undistort_points(self, xy_measured_px: np.ndarray) -> np.ndarray:
        """Ideal pinhole coordinates ``xy - Δ(xy)`` ``(N, 2)`` px of measured points ``(N, 2)`` px."""
        xy = _as_points("xy_measured_px", xy_measured_px)
        return xy - self.correction_at(xy)

    def distort_points(self, xy_ideal_px: np.ndarray) -> np.ndarray:
        """Measured coordinates ``(N, 2)`` px whose undistortion is ``xy_ideal_px`` ``(N, 2)`` px.

        The inverse of :meth:`undistort_points`, by Newton's method on the
        bilinear field (gridded fields) or fixed-point iteration (others).
        """
        return _invert_correction(self.correction_at, _as_points("xy_ideal_px", xy_ideal_px), jacobian=self._jacobian)

    _jacobian = None


def _as_points(name, xy):
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ShapeError(f"{name} must have shape (N, 2); got {xy.shape}")
    if not np.all(np.isfinite(xy)):
        raise InputError(f"{name} must be finite")
    return xy


def grid_nodes(width_px: int, height_px: int, spacing_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Evenly spaced node coordinates covering the image ``[-0.5, W-0.5] × [-0.5, H-0.5]``.

    Returns
    -------
    x_nodes_px : (W_g,) float64 ndarray, px
    y_nodes_px : (H_g,) float64 ndarray, px
        Spacing at most ``spacing_px``, at least two nodes per axis.

    Examples
    --------
    >>> x, y = grid_nodes(64, 32, 16.0)
    >>> x.tolist(), y.tolist()
    ([-0.5, 15.5, 31.5, 47.5, 63.5], [-0.5, 15.5, 31.5])
    """
    if width_px < 1 or height_px < 1:
        raise InputError(f"image size must be positive; got {width_px}x{height_px}")
    nx = max(int(np.ceil(width_px / spacing_px)), 1) + 1
    ny = max(int(np.ceil(height_px / spacing_px)), 1) + 1
    return np.linspace(-0.5, width_px - 0.5, nx), np.linspace(-0.5, height_px - 0.5, ny)


@dataclass(frozen=True)
class CorrectionField(_FieldOps):
    """A correction field ``Δ`` on a rectilinear grid of nodes, interpolated bilinearly.

    Attributes
    ----------
    x_nodes_px : (W_g,) float64 ndarray, px
        Increasing node columns.
    y_nodes_px : (H_g,) float64 ndarray, px
        Increasing node rows.
    delta_px : (H_g, W_g, 2) float64 ndarray, px
        ``(Δx, Δy)`` at the nodes; ``ideal = measured - Δ(measured)``.
    sigma_px : (H_g, W_g) float64 ndarray, px
        Standard uncertainty of each node's ``Δ`` per component, from the
        out-of-fold error of the cross-validation and the number of
        observations that support the node (``cv_rms / sqrt(n_eff)``).
    support : (H_g, W_g) bool ndarray
        Where enough observations lay near the node (see ``LearnParams.min_support``).
    width_px, height_px : int
        Image size the grid covers.

    Notes
    -----
    Outside the node range (outside the image) the coordinates are clamped:
    the field is extended by its edge values.

    Examples
    --------
    >>> f = CorrectionField.constant(64, 48, (0.5, -0.25))
    >>> f.undistort_points(np.array([[10.0, 20.0]]))
    array([[ 9.5 , 20.25]])
    >>> f.distort_points(np.array([[9.5, 20.25]]))
    array([[10., 20.]])
    """

    x_nodes_px: np.ndarray
    y_nodes_px: np.ndarray
    delta_px: np.ndarray
    sigma_px: np.ndarray
    support: np.ndarray
    width_px: int
    height_px: int
    schema_version: int = 1

    def __post_init__(self):
        for name in ("x_nodes_px", "y_nodes_px", "delta_px", "sigma_px"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        object.__setattr__(self, "support", np.asarray(self.support, dtype=bool))
        object.__setattr__(self, "width_px", int(self.width_px))
        object.__setattr__(self, "height_px", int(self.height_px))
        gw, gh = len(self.x_nodes_px), len(self.y_nodes_px)
        check_shape("x_nodes_px", self.x_nodes_px, (None,))
        check_shape("y_nodes_px", self.y_nodes_px, (None,))
        if gw < 2 or gh < 2 or np.any(np.diff(self.x_nodes_px) <= 0) or np.any(np.diff(self.y_nodes_px) <= 0):
            raise ShapeError("x_nodes_px and y_nodes_px must be increasing with at least 2 nodes each")
        check_shape("delta_px", self.delta_px, (gh, gw, 2))
        check_shape("sigma_px", self.sigma_px, (gh, gw))
        check_shape("support", self.support, (gh, gw))
        if not np.all(np.isfinite(self.delta_px)):
            raise InputError("delta_px must be finite")
        freeze(self)

    @classmethod
    def constant(
        cls, width_px: int, height_px: int, delta_px=(0.0, 0.0), *, spacing_px: float = 16.0
    ) -> "CorrectionField":
        """A field equal to ``delta_px`` everywhere (zero: the identity), supported everywhere."""
        xn, yn = grid_nodes(width_px, height_px, spacing_px)
        delta = np.broadcast_to(np.asarray(delta_px, dtype=np.float64), (len(yn), len(xn), 2)).copy()
        return cls(xn, yn, delta, np.zeros((len(yn), len(xn))), np.ones((len(yn), len(xn)), bool), width_px, height_px)

    @property
    def nodes_px(self) -> np.ndarray:
        """Node coordinates ``(H_g * W_g, 2)`` px, row-major (x varies fastest)."""
        xx, yy = np.meshgrid(self.x_nodes_px, self.y_nodes_px)
        return np.column_stack([xx.ravel(), yy.ravel()])

    def correction_at(self, xy_px: np.ndarray) -> np.ndarray:
        """``Δ`` ``(N, 2)`` px at measured coordinates ``xy_px`` ``(N, 2)`` px (bilinear, clamped outside)."""
        return _bilinear(self.x_nodes_px, self.y_nodes_px, self.delta_px, _as_points("xy_px", xy_px))

    def _jacobian(self, xy_px):
        _, d_dx, d_dy = _bilinear(self.x_nodes_px, self.y_nodes_px, self.delta_px, xy_px, gradient=True)
        return d_dx, d_dy

    def support_at(self, xy_px: np.ndarray) -> np.ndarray:
        """True ``(N,)`` where all four surrounding nodes are supported."""
        s = _bilinear(
            self.x_nodes_px, self.y_nodes_px, self.support[..., None].astype(float), _as_points("xy_px", xy_px)
        )
        return s[:, 0] > 1 - 1e-9

    def with_delta(self, delta_px: np.ndarray, **changes) -> "CorrectionField":
        """The same grid with other node values (and optionally other sigma/support)."""
        return replace(self, delta_px=delta_px, **changes)

    def add(self, other: "CorrectionField") -> "CorrectionField":
        """``Δ + δ`` on the same grid: the accumulation step of the alternation.

        The uncertainty and support are ``other``'s: every regression sees the
        same observations, and the latest one judges the accumulated field.
        """
        if not (
            np.array_equal(self.x_nodes_px, other.x_nodes_px) and np.array_equal(self.y_nodes_px, other.y_nodes_px)
        ):
            raise InputError("other must be on the same grid as this field")
        return replace(self, delta_px=self.delta_px + other.delta_px, sigma_px=other.sigma_px, support=other.support)

    def remap_maps(self, width_px: int | None = None, height_px: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Inverse maps for ``cv2.remap``: the distorted source of each undistorted pixel centre.

        Parameters
        ----------
        width_px, height_px : int, optional
            Output size (default: the field's image size).

        Returns
        -------
        map_x, map_y : (H_out, W_out) float32 ndarray, px
            ``distort_points`` of the output pixel centres ``(x, y)``.
        """
        width_px = self.width_px if width_px is None else int(width_px)
        height_px = self.height_px if height_px is None else int(height_px)
        yy, xx = np.mgrid[0:height_px, 0:width_px].astype(np.float64)
        src = self.distort_points(np.column_stack([xx.ravel(), yy.ravel()]))
        return (
            src[:, 0].reshape(height_px, width_px).astype(np.float32),
            src[:, 1].reshape(height_px, width_px).astype(np.float32),
        )


@dataclass(frozen=True)
class PointwiseField(_FieldOps):
    """The unsmoothed scheme's correction: a sum of kNN regressors, one per alternation step.

    Attributes
    ----------
    terms : tuple of KnnModel
    width_px, height_px : int
    """

    terms: tuple
    width_px: int
    height_px: int

    def correction_at(self, xy_px: np.ndarray) -> np.ndarray:
        """``Δ`` ``(N, 2)`` px at measured ``xy_px`` ``(N, 2)`` px: the sum of the terms' predictions."""
        xy = _as_points("xy_px", xy_px)
        out = np.zeros((len(xy), 2))
        for term in self.terms:
            out += term.correction_at(xy)
        return out

    def add(self, term: KnnModel) -> "PointwiseField":
        """``Δ + δ`` with ``δ`` a new kNN regressor."""
        return replace(self, terms=self.terms + (term,))

    def to_grid(self, params: LearnParams, sigma_px=None, support=None) -> CorrectionField:
        """Sample the field at grid nodes (for storage and ``remap_maps``)."""
        xn, yn = grid_nodes(self.width_px, self.height_px, params.grid_spacing_px)
        shape = (len(yn), len(xn))
        nodes = np.column_stack([a.ravel() for a in np.meshgrid(xn, yn)])
        delta = self.correction_at(nodes).reshape(shape + (2,))
        sigma = np.zeros(shape) if sigma_px is None else sigma_px
        support = np.ones(shape, bool) if support is None else support
        return CorrectionField(xn, yn, delta, sigma, support, self.width_px, self.height_px)


# ---------------------------------------------------------------------------------------------
# One regression step
# ---------------------------------------------------------------------------------------------


def _node_statistics(model: KnnModel, nodes_px, cv: CvReport, params: LearnParams):
    """Per-node uncertainty ``cv_rms / sqrt(n_eff)`` and support mask, both ``(n_nodes,)``."""
    _, idx = model.neighbours(nodes_px)
    w = model.weights[idx].mean(axis=2)  # shape (n_nodes, k)
    n_eff = w.sum(1) ** 2 / np.sum(w**2, axis=1)
    sigma = cv.cv_rms_px / np.sqrt(n_eff)
    counts = np.array([len(c) for c in model.tree.query_ball_point(nodes_px, r=params.support_radius)])
    return sigma, counts >= params.min_support


def fit_knn_field(
    xy_px: np.ndarray,
    residuals_px: np.ndarray,
    residual_var_px2: np.ndarray,
    params: LearnParams,
    *,
    image_size: tuple[int, int],
    cv: CvReport | None = None,
    neighbour_cache: dict | None = None,
) -> tuple[CorrectionField | KnnModel, CvReport]:
    """Learn the deterministic part of the residuals: one kNN regression step.

    Parameters
    ----------
    xy_px : (N, 2) float64 ndarray, px
        Measured coordinates of the inlier observations of one system.
    residuals_px : (N, 2) float64 ndarray, px
        Their adjustment residuals, measured minus projected (after the
        current correction), so that ``Δ += δ`` reduces them.
    residual_var_px2 : (N, 2) or (N,) float64 ndarray, px²
        Residual variances, the diagonal of ``C_r`` (equation 3's weights are their inverses).
    params : LearnParams
    image_size : (int, int)
        ``(width, height)`` of the image in px.
    cv : CvReport, optional
        A cross-validation already run on (nearly) the same observations: its
        ``k`` and out-of-fold RMS are used and none is run (the refit after
        the local outlier test, which drops a few observations).
    neighbour_cache : dict, optional
        Passed to :func:`cross_validate_k`.

    Returns
    -------
    field : CorrectionField or KnnModel
        With ``params.smooth`` the kNN prediction at the grid nodes (with
        uncertainty and support); otherwise the kNN regressor itself.
    cv : CvReport
        The cross-validation table (``k`` vs mean equation-3 cost).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> xy = rng.uniform(0, 64, (400, 2))
    >>> r = np.full((400, 2), 0.3) + rng.normal(0, 0.05, (400, 2))
    >>> field, cv = fit_knn_field(xy, r, np.full(400, 0.05**2), LearnParams(), image_size=(64, 64))
    >>> bool(np.allclose(field.correction_at(np.array([[32.0, 32.0]])), 0.3, atol=0.03))
    True
    """
    xy, r, var = _check_training(xy_px, residuals_px, residual_var_px2)
    width, height = (int(s) for s in image_size)
    if cv is None:
        cv = cross_validate_k(
            xy, r, var, k_grid=params.k_grid, n_folds=params.n_folds, seed=params.seed, neighbour_cache=neighbour_cache
        )
        logger.debug("kNN cross-validation over %d points:\n%s", len(xy), cv.table())
    model = KnnModel(xy, r, 1.0 / var, cv.k)
    if not params.smooth:
        return model, cv
    xn, yn = grid_nodes(width, height, params.grid_spacing_px)
    nodes = np.column_stack([a.ravel() for a in np.meshgrid(xn, yn)])
    delta = model.correction_at(nodes).reshape(len(yn), len(xn), 2)
    sigma, support = _node_statistics(model, nodes, cv, params)
    return CorrectionField(
        xn, yn, delta, sigma.reshape(delta.shape[:2]), support.reshape(delta.shape[:2]), width, height
    ), cv


# ---------------------------------------------------------------------------------------------
# Gridded least-squares refinement (beyond the paper)
# ---------------------------------------------------------------------------------------------


def _difference_operator(n_y: int, n_x: int, order: int):
    """Sparse ``D`` whose ``|D v|²`` is the discrete ``order``-th order energy of node values ``v``.

    The rows are the mixed differences ``Δx^(m-a) Δy^a v`` weighted by
    ``sqrt(C(m, a))``, ``a = 0 .. m`` (row-major ``v``, x fastest): for
    ``m = 2`` the thin-plate energy (second differences along x and y and the
    √2-weighted cross difference). Its null space is the polynomials of total
    degree below ``m``.
    """
    from math import comb

    from scipy.sparse import diags, identity, kron, vstack

    def diff(n, k):
        if k == 0:
            return identity(n)
        c = _DIFFERENCE_STENCILS[k]
        return diags(list(c), list(range(k + 1)), shape=(max(n - k, 0), n))

    return vstack(
        [np.sqrt(comb(order, a)) * kron(diff(n_y, a), diff(n_x, order - a)) for a in range(order + 1)]
    ).tocsr()


def _factor_spd(M):
    """Sparse LU of a symmetric positive definite matrix: a symmetric fill-reducing ordering, no pivoting.

    Several times faster than SuperLU's default (COLAMD, partial pivoting) on
    the grid's normal matrices, whose band widens with the prior's order; an
    SPD matrix needs no pivoting for stability.
    """
    from scipy.sparse.linalg import splu

    return splu(M.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})


def _grid_solve(A, DtD, w, r, tau_px, base=None):
    """Node values ``v`` minimising ``Σ w (r - A v)² + |D (base + v)|² / τ²`` per component; ``(n_nodes, 2)``.

    ``base`` ``(n_nodes, 2)`` is the field already accumulated: the prior acts
    on the total field, so the alternation's fixed point is the regularised
    fit, not a pure least-squares one.
    """
    return _solve_normal(_grid_normal(A, w, r), DtD, tau_px, base)


def _grid_normal(A, w, r):
    """The data part of :func:`_grid_solve`'s normal equations: ``([A^T W_c A per component], A^T W r, max w)``.

    One matrix serves both components when their weights are equal (the usual case).
    """
    AtW = [A.T.multiply(w[:, c]).tocsr() for c in range(2)]
    N0 = AtW[0] @ A
    N = [N0, N0 if np.array_equal(w[:, 1], w[:, 0]) else AtW[1] @ A]
    return N, np.column_stack([AtW[c] @ r[:, c] for c in range(2)]), float(w.max())


def _solve_normal(normal, DtD, tau_px, base=None):
    """Solve the normal equations of :func:`_grid_normal` with the prior ``DtD / τ²`` on ``base + v``."""
    from scipy.sparse import diags

    N, b, w_max = normal
    reg = DtD / tau_px**2
    # a tiny ridge keeps nodes far from all data (fixed only through the prior's null space) determined
    ridge = diags(np.full(b.shape[0], 1e-10 * max(w_max, 1.0)))
    out = np.empty(b.shape)
    lu = None
    for c in range(2):
        if lu is None or N[c] is not N[0]:
            lu = _factor_spd(N[c] + reg + ridge)
        rhs = b[:, c] if base is None else b[:, c] - reg @ base[:, c]
        out[:, c] = lu.solve(rhs)
    return out


@dataclass(frozen=True)
class GridCvReport:
    """Cross-validation of the smoothness of the gridded least-squares field.

    Attributes
    ----------
    tau_grid_px : (T,) float64 ndarray, px
        Candidate prior standard deviations of a node's difference of the
        prior's order, as evaluated (``tau_grid_px`` of the parameters in
        increasing order, for each order in turn, up to the first rise of the cost).
    cv_cost : (T,) float64 ndarray
        Mean out-of-fold equation-3 cost per observation.
    tau_px : float
        The chosen candidate.
    cv_rms_px : float
        Out-of-fold RMS per component at ``tau_px``.
    order : int
        The chosen order of the difference prior.
    order_grid : (T,) int64 ndarray or None
        The order of each candidate (None: all ``order``).
    """

    tau_grid_px: np.ndarray
    cv_cost: np.ndarray
    tau_px: float
    cv_rms_px: float
    order: int = 2
    order_grid: np.ndarray | None = None

    def __post_init__(self):
        object.__setattr__(self, "tau_grid_px", np.asarray(self.tau_grid_px, dtype=np.float64))
        object.__setattr__(self, "cv_cost", np.asarray(self.cv_cost, dtype=np.float64))
        object.__setattr__(self, "order", int(self.order))
        order_grid = np.full(len(self.tau_grid_px), self.order) if self.order_grid is None else self.order_grid
        object.__setattr__(self, "order_grid", np.asarray(order_grid, dtype=np.int64))
        freeze(self)


def cross_validate_smoothness(
    xy_px, residuals_px, residual_var_px2, *, image_size, params: LearnParams, base_px=None
) -> GridCvReport:
    """Choose the smoothness prior of :func:`fit_grid_field` by shuffled K-fold CV of equation 3.

    Parameters as in :func:`fit_grid_field`; candidates: every order of
    ``params.smoothness_orders`` with the ``τ`` of ``params.tau_grid_px`` in
    increasing order, up to the first whose cost rises (each candidate costs
    a sparse factorisation per fold).

    Notes
    -----
    With ``base_px`` the prior acts on ``base + δ``; the fit of ``δ`` to the
    residuals ``r`` is then the fit of the total field to ``r + base(x)``, so
    the out-of-fold cost judges the total field, not the update.
    """
    base = None if base_px is None else np.asarray(base_px, dtype=np.float64).reshape(-1, 2)
    xy, r, var = _check_training(xy_px, residuals_px, residual_var_px2)
    xn, yn = grid_nodes(*image_size, params.grid_spacing_px)
    A = _bilinear_design(xn, yn, xy)
    w = 1.0 / var
    n = len(xy)
    folds = np.array_split(np.random.default_rng(params.seed).permutation(n), min(params.smoothness_folds, n))
    # the data part of each fold's normal equations, shared by every candidate
    normals = [
        _grid_normal(A[train], w[train], r[train])
        for train in (np.setdiff1d(np.arange(n), test, assume_unique=True) for test in folds)
    ]
    tests = [(A[test], w[test], r[test]) for test in folds]
    evaluated = []  # (order, tau, cost, sq)
    for order in params.smoothness_orders:
        D = _difference_operator(len(yn), len(xn), order)
        DtD = (D.T @ D).tocsr()
        for tau in sorted(params.tau_grid_px):
            cost = sq = 0.0
            for normal, (A_test, w_test, r_test) in zip(normals, tests):
                err = r_test - A_test @ _solve_normal(normal, DtD, tau, base)
                cost += float(np.sum(w_test * err**2))
                sq += float(np.sum(err**2))
            cost /= n
            rising = bool(evaluated) and evaluated[-1][0] == order and cost > evaluated[-1][2]
            evaluated.append((order, tau, cost, sq))
            if rising:
                # past this order's minimum (taken as unimodal in log tau): larger ones only fit more of the noise
                break
    orders, taus, costs, sqs = (np.array(c) for c in zip(*evaluated))
    best = int(np.argmin(costs))
    return GridCvReport(taus, costs, float(taus[best]), float(np.sqrt(sqs[best] / (2 * n))), int(orders[best]), orders)


def fit_grid_field(
    xy_px: np.ndarray,
    residuals_px: np.ndarray,
    residual_var_px2: np.ndarray,
    params: LearnParams,
    *,
    image_size: tuple[int, int],
    tau_px: float,
    cv_rms_px: float | None = None,
    base: CorrectionField | None = None,
    order: int = 2,
) -> CorrectionField:
    """Fit the node values of a bilinear grid to the residuals directly (weighted least squares).

    Minimises ``Σ_i (r_i - g(x_i))^T C_r^-1 (r_i - g(x_i)) + |D (base + δ)|² / τ²``: equation 3
    with ``g`` the bilinear grid field instead of a kNN average, plus a
    thin-plate smoothness prior ``D`` (second differences of the node values,
    standard deviation ``τ`` px). Unlike the kNN mean it does not blur the field
    over a neighbourhood, so its fixed point in the alternation is the field
    itself rather than a smoothed copy of it.

    Parameters
    ----------
    xy_px, residuals_px, residual_var_px2
        As in :func:`fit_knn_field`.
    params : LearnParams
        ``grid_spacing_px``, ``support_radius_px`` and ``min_support`` are used.
    image_size : (int, int)
        ``(width, height)`` px.
    tau_px : float
        Prior standard deviation of a second difference, px (see :func:`cross_validate_smoothness`).
    cv_rms_px : float, optional
        Out-of-fold RMS for the node uncertainty (default: the in-sample RMS).
    base : CorrectionField, optional
        The field accumulated so far, on the same grid: the prior then acts on
        ``base + δ`` (the alternation's total field) and the returned ``δ`` is the update.
    order : int
        Order of the difference prior (default 2, the thin-plate energy; see
        ``LearnParams.smoothness_orders``).

    Returns
    -------
    CorrectionField
        The update ``δ``, with node uncertainty ``cv_rms / sqrt(n_eff)``
        (``n_eff`` the bilinear weight the observations put on the node).
    """
    xy, r, var = _check_training(xy_px, residuals_px, residual_var_px2)
    width, height = (int(s) for s in image_size)
    xn, yn = grid_nodes(width, height, params.grid_spacing_px)
    A = _bilinear_design(xn, yn, xy)
    D = _difference_operator(len(yn), len(xn), int(order))
    v = _grid_solve(
        A, (D.T @ D).tocsr(), 1.0 / var, r, float(tau_px), None if base is None else base.delta_px.reshape(-1, 2)
    )
    if cv_rms_px is None:
        cv_rms_px = float(np.sqrt(np.mean((r - A @ v) ** 2)))
    return _grid_result(xn, yn, v, A, xy, cv_rms_px, params, (width, height))


def _grid_result(xn, yn, values, A, xy, cv_rms_px, params, image_size) -> CorrectionField:
    """A least-squares grid field with node uncertainty ``cv_rms / sqrt(n_eff)`` and support mask.

    ``n_eff`` is the bilinear weight the observations put on the node.
    """
    n_eff = np.asarray(A.sum(axis=0)).ravel()
    sigma = cv_rms_px / np.sqrt(np.maximum(n_eff, 1e-3))
    nodes = np.column_stack([a.ravel() for a in np.meshgrid(xn, yn)])
    shape = (len(yn), len(xn))
    return CorrectionField(
        xn,
        yn,
        values.reshape(shape + (2,)),
        sigma.reshape(shape),
        _support_mask(xy, nodes, params).reshape(shape),
        *image_size,
    )


# ---------------------------------------------------------------------------------------------
# Fixed-point acceleration
# ---------------------------------------------------------------------------------------------


class _Anderson:
    """Anderson acceleration (type II, Walker & Ni 2011) of ``x <- g(x)`` with a restart safeguard.

    ``step(x, g, mask)`` returns the next iterate from the current one and its
    image ``g(x)``. Only the entries selected by ``mask`` at the first step
    after a restart (the grid nodes the data support) are combined; the
    others take the plain step, since nodes far from all data barely change
    the cost and would only add noise to the least-squares combination.
    ``restart()`` forgets the history (after a step that raised the cost).
    """

    def __init__(self, depth: int):
        self.depth = depth
        self.restart()

    def restart(self):
        self._x = self._g = self._mask = None
        self._dF, self._dG = [], []

    def step(self, x: np.ndarray, g: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        if self._mask is None:
            self._mask = np.ones(len(x), bool) if mask is None else np.asarray(mask, bool).copy()
        out = g.copy()
        xm, gm = x[self._mask], g[self._mask]
        f = gm - xm
        if self._x is not None:
            self._dF.append(f - (self._g - self._x))
            self._dG.append(gm - self._g)
            self._dF, self._dG = self._dF[-self.depth :], self._dG[-self.depth :]
        self._x, self._g = xm, gm
        if self._dF:
            dF = np.column_stack(self._dF)
            dG = np.column_stack(self._dG)
            # Tikhonov-regularised least squares keeps the combination bounded when the differences are collinear
            lam = 1e-10 * float(np.sum(dF * dF))
            gamma = np.linalg.solve(dF.T @ dF + lam * np.eye(dF.shape[1]), dF.T @ f)
            out[self._mask] = gm - dG @ gamma
        return out


# ---------------------------------------------------------------------------------------------
# The alternation
# ---------------------------------------------------------------------------------------------


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
    """

    iteration: int
    phase: str
    cost_adjust: float
    cost_fit: float
    cost_total: float
    k: tuple
    rms_px: float
    step_px: float


@dataclass(frozen=True)
class LearnResult:
    """The outcome of :func:`calibrate`.

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
        The final :class:`stages.adjust.Adjustment` (with ``Δ`` held at ``corrections_px``).
    history : tuple of IterationRecord
    cv : tuple
        The last cross-validation report per system.
    converged : bool
    stop_reason : str
    wall_time_s : float
    adjust_time_s : float
        Part of ``wall_time_s`` spent in :func:`stages.adjust.adjust_bundle`.
    initial_residual_px : (N, 2) float64 ndarray or None, px
        Residuals of the first adjustment, with no correction (the "before" of the report).

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
        return f"{self.scheme}: in-sample RMS {before:.3f} -> {after:.3f} px, {len(self.history) - 1} iterations, {self.stop_reason}"

    def field(self, system: int):
        """The correction to apply to new observations of ``system`` (exact kNN sum when unsmoothed)."""
        return self.pointwise[system] if self.pointwise is not None else self.fields[system]


def _scheme_flags(scheme: str) -> tuple[bool, bool, bool]:
    """``(learn, estimate_iop, smooth)`` of a scheme name (``polynomial`` learns no kNN field)."""
    if scheme not in SCHEMES:
        raise InputError(f"scheme must be one of {', '.join(SCHEMES)}; got {scheme!r}")
    if scheme in ("none", "polynomial"):
        return False, True, True
    parts = set(scheme.split("+"))
    return True, "iop" in parts, "smooth" in parts


def _restricted_k_grid(k_grid: tuple, k_prev: int | None, span: int = 3) -> tuple:
    """The candidates within ``span`` grid steps of the previous choice (all of them at first)."""
    if k_prev is None or k_prev not in k_grid:
        return k_grid
    i = k_grid.index(k_prev)
    return k_grid[max(i - span, 0) : i + span + 1]


def _image_sizes(image_size, n_systems: int) -> list[tuple[int, int]]:
    arr = np.asarray(image_size, dtype=np.int64)
    if arr.shape == (2,):
        arr = np.tile(arr, (n_systems, 1))
    if arr.shape != (n_systems, 2) or np.any(arr < 1):
        raise InputError(
            f"image_size must be (width, height) or one per system, shape ({n_systems}, 2); got {arr.shape}"
        )
    return [(int(w), int(h)) for w, h in arr]


def calibrate(
    observations,
    phantom,
    initial,
    *,
    image_size,
    scheme: str = "knn+iop+smooth",
    params: LearnParams = LearnParams(),
    adjust_params=None,
) -> LearnResult:
    """Alternate the robust adjustment and the kNN regression of its residuals (paper, section IV).

    Parameters
    ----------
    observations : Observations
        Labelled measured coordinates of every system.
    phantom : Phantom
        Nominal bead coordinates (the adjustment's datum).
    initial
        Initial orientation for :func:`stages.adjust.adjust_bundle`.
    image_size : (int, int) or (S, 2) array_like
        ``(width, height)`` px of each system's images.
    scheme : str
        ``"knn"``, ``"knn+iop"``, ``"knn+smooth"``, ``"knn+iop+smooth"`` (the
        paper's four; "iop" = the adjustment estimates the interior
        orientation, otherwise it is held at its initial value and the field
        absorbs it), ``"none"`` (adjustment only, IOP estimated) or
        ``"polynomial"`` (no kNN loop: the adjustment estimates the IOP and
        the global polynomial model, see :func:`_calibrate_polynomial`).
    params : LearnParams
        ``smooth`` is set from the scheme; ``acceleration`` and ``refine``
        go beyond the paper (defaults: the paper's plain loop).
    adjust_params : AdjustParams, optional
        Of the adjustment (its IOP flag is set from the scheme).

    Returns
    -------
    LearnResult

    Notes
    -----
    Each outer iteration: (1) per system, the kNN regression ``δ`` of the
    inlier residuals (``k`` by cross-validation of equation 3, restricted after
    the first iteration to the candidates near the previous ``k``), (2)
    ``Δ += δ`` at every observation (inliers and outliers, so an outlier
    that turns out to be an inlier is corrected alike), (3) the adjustment
    with ``Δ`` held constant, warm-started from the previous solution.
    The loop stops when the combined cost (equation 2 + equation 3) changes by
    less than ``params.tolerance`` per observation, or after
    ``params.max_iterations``.

    With ``acceleration="anderson"`` the iterate is the vector of all node
    values of the gridded fields: the update ``x <- x + δ(x)`` is a fixed-point
    iteration, and Anderson acceleration combines the last few iterates;
    a step that raises the combined cost restarts its history.
    """
    t0 = time.perf_counter()
    learn, estimate_iop, smooth = _scheme_flags(scheme)
    if scheme == "polynomial":
        return _calibrate_polynomial(
            observations,
            phantom,
            initial,
            _image_sizes(image_size, len(observations.system_names)),
            params,
            adjust_params,
        )
    if smooth:
        params = replace(params, smooth=True)
    else:
        # Anderson and the gridded refinement combine gridded fields: the unsmoothed scheme runs without them
        params = replace(
            params,
            smooth=False,
            refine="none",
            acceleration="none" if params.acceleration == "anderson" else params.acceleration,
        )
    n_systems = len(observations.system_names)
    sizes = _image_sizes(image_size, n_systems)
    xy = observations.xy_px
    n_obs = len(xy)
    rows = [np.flatnonzero(observations.system == s) for s in range(n_systems)]
    corrections = np.zeros((n_obs, 2))
    run = _adjuster(observations, phantom, initial, adjust_params, estimate_iop, fast=params.fast_intermediate)
    nominal_ids, nominal_xyz = _nominal_table(phantom)
    adj = run(corrections, None, final=not learn)
    initial_residual = adj.residual_px
    out = _adjustment_outcome(adj, observations.sigma_px)
    history = [IterationRecord(0, "adjust", out.cost, 0.0, out.cost, (), out.rms_px, 0.0)]
    logger.info("scheme %s: initial adjustment cost %.6g, inlier RMS %.4f px", scheme, out.cost, out.rms_px)
    if not learn:
        return LearnResult(
            scheme,
            tuple(CorrectionField.constant(w, h) for w, h in sizes),
            None,
            corrections,
            adj,
            tuple(history),
            (),
            True,
            "scheme 'none' learns nothing",
            time.perf_counter() - t0,
            run.seconds,
            initial_residual,
        )

    grids = [CorrectionField.constant(w, h, spacing_px=params.grid_spacing_px) for w, h in sizes]
    pointwise = [PointwiseField((), w, h) for w, h in sizes]
    k_prev: list = [None] * n_systems
    taus: list = [None] * n_systems
    cvs: list = [None] * n_systems
    knn_caches = [{} for _ in range(n_systems)]
    anderson = _Anderson(params.anderson_depth)

    def fit_system(s, sel, adj, out, phase, refit=False):
        """One regression step of system ``s`` on observations ``sel``: the update and the rows used.

        ``refit``: the same step again without the local outliers, with the ``k`` just chosen.
        """
        r, var = out.residuals_px[sel], out.residual_var_px2[sel]
        if phase == "grid":
            if taus[s] is None:
                cvs[s] = cross_validate_smoothness(
                    xy[sel], r, var, image_size=sizes[s], params=params, base_px=grids[s].delta_px
                )
                taus[s] = cvs[s].tau_px
                logger.info(
                    "system %s: gridded refinement, smoothness order %d, tau %.3g px (CV)",
                    observations.system_names[s],
                    cvs[s].order,
                    taus[s],
                )
            if params.refine == "grid+points":
                bead, J = _point_jacobians(adj, observations, sel)
                t_weight = adj.weight[sel, None] if params.training == "inliers" else 1.0
                w_obs = t_weight / (adj.sigma0 * observations.sigma_px[sel, :2]) ** 2
                shape = (
                    (adj.xyz_mm, nominal_xyz[_lookup(adj.bead_id, nominal_ids, "bead ids of the adjustment")])
                    if params.affine_datum
                    else None
                )
                model = fit_grid_with_points(
                    xy[sel],
                    r,
                    w_obs,
                    bead,
                    J,
                    params,
                    image_size=sizes[s],
                    tau_px=taus[s],
                    base=grids[s],
                    cv_rms_px=cvs[s].cv_rms_px,
                    shape_mm=shape,
                    max_cg_iterations=_LOOP_CG_ITERATIONS,
                    order=cvs[s].order,
                )
            else:
                model = fit_grid_field(
                    xy[sel],
                    r,
                    var,
                    params,
                    image_size=sizes[s],
                    tau_px=taus[s],
                    cv_rms_px=cvs[s].cv_rms_px,
                    base=grids[s],
                    order=cvs[s].order,
                )
        elif refit:
            model, _ = fit_knn_field(xy[sel], r, var, params, image_size=sizes[s], cv=cvs[s])
        else:
            model, cvs[s] = fit_knn_field(
                xy[sel],
                r,
                var,
                replace(params, k_grid=_restricted_k_grid(params.k_grid, k_prev[s])),
                image_size=sizes[s],
                neighbour_cache=knn_caches[s],
            )
            k_prev[s] = cvs[s].k
        return model, sel

    phase = "knn"
    phase_start = 1
    converged, stop = False, f"maximum number of iterations ({params.max_iterations}) reached"
    iteration = 0
    while True:
        iteration += 1
        fit_cost = 0.0
        updates = []
        for s in range(n_systems):
            if params.training == "local":
                sel = rows[s][adj.used[rows[s]]]
            else:
                sel = rows[s][out.inlier[rows[s]]]
            if len(sel) < params.n_folds:
                raise EstimationError(
                    f"system {observations.system_names[s]} has {len(sel)} inlier observations; the regression needs at least {params.n_folds}"
                )
            if params.training == "local":
                # gross errors are what the field cannot explain: fit to all, test every
                # observation against the fitted field, refit without the misfits
                candidates = sel
                model, _ = fit_system(s, candidates, adj, out, phase)
                r, var = out.residuals_px[candidates], out.residual_var_px2[candidates]
                z2 = np.sum((r - model.correction_at(xy[candidates])) ** 2 / var, axis=1)
                keep = z2 <= params.outlier_chi2 * max(float(np.median(z2)) / (2 * np.log(2)), 1e-300)
                sel = candidates[keep] if keep.sum() >= params.n_folds else candidates
                if len(sel) < len(candidates):
                    model, _ = fit_system(s, sel, adj, out, phase, refit=True)
            else:
                model, sel = fit_system(s, sel, adj, out, phase)
            r, var = out.residuals_px[sel], out.residual_var_px2[sel]
            fit_cost += float(np.sum((r - model.correction_at(xy[sel])) ** 2 / var))
            updates.append(model)

        old = corrections.copy()
        if smooth:
            x = np.concatenate([g.delta_px.ravel() for g in grids])
            dx = np.concatenate([u.delta_px.ravel() for u in updates])
            if params.acceleration == "anderson":
                x_new = anderson.step(x, x + dx, np.concatenate([np.repeat(u.support.ravel(), 2) for u in updates]))
            elif params.acceleration == "overrelax":
                x_new = x + params.relaxation * dx
            else:
                x_new = x + dx
            grids = _split_nodes(grids, updates, x_new)
            if params.field_gauge != "none":
                grids = [_gauge_fixed(g, xy[rows[s]], adj.iop_px[s], estimate_iop) for s, g in enumerate(grids)]
            for s in range(n_systems):
                corrections[rows[s]] = grids[s].correction_at(xy[rows[s]])
        else:
            factor = params.relaxation if params.acceleration == "overrelax" else 1.0
            for s in range(n_systems):
                pointwise[s] = pointwise[s].add(updates[s].scaled(factor))
                corrections[rows[s]] += factor * updates[s].correction_at(xy[rows[s]])

        adj = run(corrections, adj, final=False)
        out = _adjustment_outcome(adj, observations.sigma_px)
        total = out.cost + fit_cost
        step = float(np.max(np.abs(corrections - old))) if n_obs else 0.0
        ks = tuple(int(k or 0) if phase == "knn" else 0 for k in k_prev)
        history.append(IterationRecord(iteration, phase, out.cost, fit_cost, total, ks, out.rms_px, step))
        logger.info(
            "iteration %d (%s): cost %.6g + %.6g = %.6g, RMS %.4f px, step %.4f px, k %s",
            iteration,
            phase,
            out.cost,
            fit_cost,
            total,
            out.rms_px,
            step,
            ks,
        )
        prev = history[-2].cost_total if len(history) > 2 and history[-2].phase == phase else None
        if params.acceleration == "anderson" and prev is not None and total > prev:
            anderson.restart()
        small_change = prev is not None and abs(total - prev) < params.tolerance * max(n_obs, 1)
        small_step = prev is not None and step < params.step_tolerance * out.rms_px
        done = small_change or small_step
        cap = params.max_iterations if phase == "knn" else params.refine_iterations
        if done or iteration - phase_start + 1 >= cap:
            if phase == "knn" and params.refine != "none":
                phase, phase_start = "grid", iteration + 1
                anderson.restart()
                continue
            converged = done
            if small_change:
                stop = f"combined cost changed by {abs(total - prev):.3g} < {params.tolerance} x {n_obs} observations"
            elif small_step:
                stop = f"the correction moved by at most {step:.3g} px < {params.step_tolerance} x the residual RMS {out.rms_px:.3g} px"
            elif phase == "grid":
                stop = f"maximum number of refinement iterations ({params.refine_iterations}) reached"
            break

    if params.fast_intermediate:
        # the final solve, warm-started, with the covariance and redundancy numbers
        adj = run(corrections, adj, final=True)
    if smooth:
        fields, pw = tuple(grids), None
    else:
        fields = []
        for s, (model, cv) in enumerate(zip(updates, cvs)):
            grid = pointwise[s].to_grid(params)
            sigma, support = _node_statistics(model, grid.nodes_px, cv, params)
            fields.append(
                grid.with_delta(
                    grid.delta_px,
                    sigma_px=sigma.reshape(grid.sigma_px.shape),
                    support=support.reshape(grid.support.shape),
                )
            )
        fields, pw = tuple(fields), tuple(pointwise)
    wall = time.perf_counter() - t0
    logger.info(
        "scheme %s: %s after %d iterations (%.1f s, of which %.1f s in the adjustment)",
        scheme,
        stop,
        iteration,
        wall,
        run.seconds,
    )
    return LearnResult(
        scheme,
        fields,
        pw,
        corrections,
        adj,
        tuple(history),
        tuple(cvs),
        converged,
        stop,
        wall,
        run.seconds,
        initial_residual,
    )


def _calibrate_polynomial(observations, phantom, initial, sizes, params: LearnParams, adjust_params) -> LearnResult:
    """Scheme ``polynomial``: the adjustment estimates the IOP and each system's global polynomial model; no kNN loop.

    Iteration 0 is the plain adjustment (no correction: the "before" of the
    report, as in the other schemes); iteration 1 the adjustment with the
    model (:mod:`stages._polynomial`: the coefficients ``adjust_params`` does
    not hold fixed, by default all but the affinity ``b1, b2``), warm-started
    from it. Each system's model is sampled at the nodes of the usual grid
    (``params.grid_spacing_px``) relative to its estimated principal point;
    ``corrections_px`` is the model itself at every observation. Node
    ``sigma_px`` is the model's standard uncertainty there propagated from the
    coefficients' covariance, ``sqrt((σ²_Δx + σ²_Δy) / 2)`` with
    ``σ²_Δ = b C_ap b^T`` (``b`` the node's row of the design matrix; the
    principal point's own uncertainty is not included), and ``support`` marks
    nodes with ``params.min_support`` used observations within
    ``params.support_radius``, as for the learned fields.
    """
    t0 = time.perf_counter()
    xy = observations.xy_px
    plain = _adjuster(observations, phantom, initial, adjust_params, True, fast=True)
    model = _adjuster(observations, phantom, initial, adjust_params, True, additional_parameters="polynomial")
    zero = np.zeros((len(xy), 2))
    first = plain(zero, None, final=False)
    adj = model(zero, first)
    before, out = _adjustment_outcome(first, observations.sigma_px), _adjustment_outcome(adj, observations.sigma_px)
    corrections = np.zeros((len(xy), 2))
    fields = []
    for s, (w, h) in enumerate(sizes):
        rows = np.flatnonzero(observations.system == s)
        corrections[rows] = adj.polynomial_correction(s, xy[rows])
        grid = CorrectionField.constant(w, h, spacing_px=params.grid_spacing_px)
        nodes = grid.nodes_px
        B = _polynomial.basis(nodes, adj.iop_px[s, :2], adj.ap_radius_px[s])
        var = np.einsum("nci,ij,ncj->n", B, adj.ap_cov_px2[s], B) / 2
        fields.append(
            grid.with_delta(
                adj.polynomial_correction(s, nodes).reshape(grid.delta_px.shape),
                sigma_px=np.sqrt(var).reshape(grid.sigma_px.shape),
                support=_support_mask(xy[rows[adj.used[rows]]], nodes, params).reshape(grid.support.shape),
            )
        )
    step = float(np.abs(corrections).max(initial=0.0))
    history = (
        IterationRecord(0, "adjust", before.cost, 0.0, before.cost, (), before.rms_px, 0.0),
        IterationRecord(1, "polynomial", out.cost, 0.0, out.cost, (), out.rms_px, step),
    )
    logger.info(
        "scheme polynomial: inlier RMS %.4f -> %.4f px, coefficients %s px",
        before.rms_px,
        out.rms_px,
        np.round(adj.ap_px, 4).tolist(),
    )
    stop = f"polynomial model estimated in the adjustment ({adj.stop_reason})"
    seconds = plain.seconds + model.seconds
    return LearnResult(
        "polynomial",
        tuple(fields),
        None,
        corrections,
        adj,
        history,
        (),
        adj.converged,
        stop,
        time.perf_counter() - t0,
        seconds,
        first.residual_px,
    )


def _support_mask(xy_px: np.ndarray, nodes_px: np.ndarray, params: LearnParams) -> np.ndarray:
    """``(n_nodes,)`` True where at least ``params.min_support`` points lie within ``params.support_radius`` of a node."""
    counts = np.array([len(c) for c in KDTree(xy_px).query_ball_point(nodes_px, r=params.support_radius)])
    return counts >= params.min_support


def _gauge_basis(xy_px, iop_px, with_iop: bool) -> np.ndarray:
    """Image displacement fields ``(n, 2, K)`` px the orientation parameters reproduce exactly (to first order).

    A common rotation of every pose about the camera axes (absorbed, in a
    biplanar set, by the ROP) displaces the image by ``c ω × ...``: a rotation
    about the principal point and two "keystone" fields
    ``(c + x'²/c, x'y'/c)``, ``(x'y'/c, c + y'²/c)`` (``x' = x - xp``). With
    the IOP estimated, a shift of the principal point (the two translations)
    and of the principal distance (a scaling about the principal point) too.
    """
    xp, yp, c = (float(v) for v in iop_px)
    u, v = xy_px[:, 0] - xp, xy_px[:, 1] - yp
    cols = [np.stack([-v, u], 1), np.stack([c + u * u / c, u * v / c], 1), np.stack([u * v / c, c + v * v / c], 1)]
    if with_iop:
        one, zero = np.ones_like(u), np.zeros_like(u)
        cols += [np.stack([one, zero], 1), np.stack([zero, one], 1), np.stack([u, v], 1)]
    return np.stack(cols, 2)


def _gauge_fixed(field: "CorrectionField", xy_px: np.ndarray, iop_px, with_iop: bool) -> "CorrectionField":
    """The field less its least-squares component (at the observations) that the orientation reproduces.

    These components trade exactly against the adjustment's parameters (see
    :func:`_gauge_basis`): left in the field they make the alternation's
    fixed point, and the IOP, drift; removed, the adjustment carries them.
    """
    B = _gauge_basis(xy_px, iop_px, with_iop)
    scale = np.sqrt(np.mean(B**2, axis=(0, 1)))
    A = (B / scale).reshape(-1, B.shape[2])
    coef, *_ = np.linalg.lstsq(A, field.correction_at(xy_px).reshape(-1), rcond=None)
    nodes = field.nodes_px
    at_nodes = (_gauge_basis(nodes, iop_px, with_iop) / scale).reshape(-1, B.shape[2]) @ coef
    return field.with_delta(field.delta_px - at_nodes.reshape(field.delta_px.shape))


#: conjugate-gradient cap of the joint field-and-points step inside the loop: an inexact inner
#: solve is enough, since the next iteration starts from the new residuals
_LOOP_CG_ITERATIONS = 100


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
# The adjustment, seen from the alternation
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Outcome:
    """What the alternation needs from an :class:`stages.adjust.Adjustment`."""

    residuals_px: np.ndarray
    residual_var_px2: np.ndarray
    inlier: np.ndarray
    cost: float
    rms_px: float


#: smallest redundancy number used for a residual's variance (a nearly determined observation
#: has a tiny residual variance; flooring it keeps such points from dominating equation 3)
_MIN_REDUNDANCY = 0.05


def _adjustment_outcome(adj, sigma_px: np.ndarray) -> _Outcome:
    """Residuals ``(xy - Δ) - projection``, their variances ``σ0² σ² r`` and the inlier mask."""
    inlier = adj.inlier & adj.used
    red = np.clip(adj.redundancy, _MIN_REDUNDANCY, None)
    var = (adj.sigma0 * sigma_px[:, :2]) ** 2 * red
    rms = float(np.sqrt(np.mean(adj.residual_px[inlier] ** 2))) if inlier.any() else float("nan")
    return _Outcome(adj.residual_px, var, inlier, float(adj.cost_history[-1]), rms)


def _adjuster(
    observations,
    phantom,
    initial,
    adjust_params,
    estimate_iop: bool,
    fast: bool = False,
    additional_parameters: str = "none",
):
    """``run(corrections_px, previous) -> Adjustment``: the adjustment with Δ held constant.

    ``previous`` is None (start from ``initial``) or a previous
    :class:`stages.adjust.Adjustment`, from which the solve is
    warm-started in the poses, IOP, ROP *and* object points (the points as
    ``start_points``, so every solve's inner constraints refer to the same
    nominal design).
    ``additional_parameters`` applies to every solve: the kNN schemes keep
    "none", so the learned field is the whole correction.
    """
    from fluorocal.stages.adjust import AdjustParams, Orientation, adjust_bundle

    final_params = replace(
        adjust_params if adjust_params is not None else AdjustParams(),
        estimate_iop=estimate_iop,
        additional_parameters=additional_parameters,
    )
    # intermediate solves: no covariance, fewer iterations and a looser cost tolerance: 1e-6 per observation
    # (at least 1e-3), far below the noise the inexact field fits leave in the combined cost
    fast_params = replace(
        final_params,
        compute_covariance=False,
        function_tolerance=max(final_params.function_tolerance, 1e-3, 1e-6 * len(observations.xy_px)),
        max_iterations=min(final_params.max_iterations, 10),
    )
    nominal = _nominal_table(phantom)

    def run(corrections_px, previous, final=True):
        t0 = time.perf_counter()
        intermediate = fast and not final
        try:
            adj = solve(corrections_px, previous, fast_params if intermediate else final_params)
        finally:
            run.seconds += time.perf_counter() - t0
        # an intermediate solve stopped at its iteration cap is expected, not the user's concern
        if not intermediate and not adj.usable:
            inliers = 100 * float(adj.inlier[adj.used].mean()) if adj.used.any() else 0.0
            logger.warning("adjustment not usable: %s, %.1f %% inliers", adj.stop_reason, inliers)
        return adj

    run.seconds = 0.0

    def solve(corrections_px, previous, params):
        if previous is None:
            return adjust_bundle(observations, nominal, initial, corrections_px, params)
        # epochs the adjustment dropped keep their initial pose
        q, src = initial.q_cam_from_obj.copy(), initial.source_mm.copy()
        at = np.searchsorted(initial.exposure, previous.exposure)
        q[at], src[at] = previous.q_cam_from_obj, previous.source_mm
        warm = Orientation(
            previous.iop_px, initial.exposure, q, src, previous.rop_q, previous.rop_source_mm, initial.system_names
        )
        return adjust_bundle(
            observations, nominal, warm, corrections_px, params, start_points=(previous.bead_id, previous.xyz_mm)
        )

    return run


# ---------------------------------------------------------------------------------------------
# Joint refinement of the gridded field and the object points (beyond the paper)
# ---------------------------------------------------------------------------------------------


def _point_jacobians(adj, observations, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bead index ``(n,)`` into ``adj.bead_id`` and ``d projection / d P`` ``(n, 2, 3)`` px/mm of observations ``rows``.

    From the collinearity equation ``x = xp + c p_x / p_z`` with
    ``p = R (P - T)`` at the adjustment's estimate (``R``, ``T`` the pose of
    the observation's system and epoch).
    """
    from fluorocal.stages._geometry import quat_to_matrix

    order = np.argsort(adj.bead_id)
    bead = order[np.searchsorted(adj.bead_id, observations.bead_id[rows], sorter=order)]
    epoch = np.searchsorted(adj.exposure, observations.exposure[rows])
    system = observations.system[rows]
    orientation = adj.orientation
    R = np.empty((len(rows), 3, 3))
    T = np.empty((len(rows), 3))
    for s in np.unique(system):
        q_s, T_s = orientation.poses(int(s))
        at = system == s
        R[at] = quat_to_matrix(q_s[epoch[at]])
        T[at] = T_s[epoch[at]]
    c = adj.iop_px[system, 2]
    p = np.einsum("nij,nj->ni", R, adj.xyz_mm[bead] - T)
    # shape (n, 2, 3): c / p_z [[1, 0, -p_x/p_z], [0, 1, -p_y/p_z]] R
    D = np.zeros((len(rows), 2, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 0, 2] = -p[:, 0] / p[:, 2]
    D[:, 1, 2] = -p[:, 1] / p[:, 2]
    return bead, (c / p[:, 2])[:, None, None] * D @ R


def _affine_shape_modes(points_mm: np.ndarray, nominal_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal directions ``B`` ``(3 n, 5)`` of the affine deformations beyond a similarity, and ``B^T (P - P_nom)``.

    The deformations ``dP_i = E (P_i - mean P)`` with ``E`` symmetric and
    traceless (stretches and shears); ``P_nom`` is the nominal design brought
    onto ``P`` by a 7-parameter similarity, so only shape differs.
    """
    from fluorocal.stages._geometry import similarity_fit

    c = points_mm - points_mm.mean(0)
    r3 = 1 / np.sqrt(3.0)
    mats = [np.diag([1.0, -1.0, 0.0]), np.diag([r3, r3, -2 * r3])]
    for i, j in ((0, 1), (0, 2), (1, 2)):
        e = np.zeros((3, 3))
        e[i, j] = e[j, i] = 1.0
        mats.append(e)
    B, _ = np.linalg.qr(np.column_stack([(c @ e.T).ravel() for e in mats]))
    scale, R, t = similarity_fit(nominal_mm, points_mm)
    aligned = scale * nominal_mm @ R.T + t
    return B, B.T @ (points_mm - aligned).ravel()


def fit_grid_with_points(
    xy_px: np.ndarray,
    residuals_px: np.ndarray,
    weights: np.ndarray,
    bead_index: np.ndarray,
    point_jacobian: np.ndarray,
    params: LearnParams,
    *,
    image_size: tuple[int, int],
    tau_px: float,
    base: CorrectionField,
    cv_rms_px: float,
    shape_mm: tuple[np.ndarray, np.ndarray] | None = None,
    max_cg_iterations: int = 400,
    order: int = 2,
) -> CorrectionField:
    """Gridded field update estimated jointly with corrections to the object points (poses held).

    The alternation is slow along the field components that a deformation of
    the (unknown, free-network) phantom can mimic: each adjustment moves the
    points to absorb part of the remaining field, and the next regression sees
    only what is left. Here the update ``δ`` of the node values and a 3D shift
    ``dP`` of every bead are estimated together from the linearised model
    ``r ≈ A δ + J dP``, minimising ``Σ w (r - A δ - J dP)² + |D (base + δ)|² / τ²``;
    the shifts are eliminated bead by bead (3×3 blocks) and the reduced system
    in ``δ`` is solved by conjugate gradients preconditioned with the
    field-only normal matrix (a sparse LU).

    Parameters
    ----------
    xy_px : (n, 2) float64 ndarray, px
        Measured coordinates (inliers of one system).
    residuals_px : (n, 2) float64 ndarray, px
    weights : (n, 2) float64 ndarray, 1/px²
        Observation weights (inverse variances, times the t-weights).
    bead_index : (n,) int ndarray
        Bead of each observation (``0 .. n_beads - 1``).
    point_jacobian : (n, 2, 3) float64 ndarray, px/mm
        Derivative of the projection by the bead's coordinates.
    params, image_size, tau_px, base, cv_rms_px
        As in :func:`fit_grid_field`.
    shape_mm : ((n_beads, 3), (n_beads, 3)) float64 ndarrays, mm, optional
        Current and nominal bead coordinates. When given, the five affine
        deformations beyond a similarity (stretches and shears) of the
        shifted points ``P + dP`` are held at the nominal design's by a stiff
        penalty: the free network's similarity datum leaves them to weak
        perspective effects, and a field that mimics them (an image aspect
        ratio or shear) would otherwise stretch the reconstruction.
    max_cg_iterations : int
    order : int
        Order of the difference prior (default 2), as in :func:`fit_grid_field`.

    Returns
    -------
    CorrectionField
        The update ``δ`` (not ``base + δ``).
    """
    from scipy.sparse import block_diag, csr_matrix, diags, vstack
    from scipy.sparse.linalg import LinearOperator, cg

    xy, r, w = (np.asarray(a, dtype=np.float64) for a in (xy_px, residuals_px, weights))
    width, height = (int(s) for s in image_size)
    xn, yn = grid_nodes(width, height, params.grid_spacing_px)
    n = len(xy)
    A = _bilinear_design(xn, yn, xy)
    n_nodes = A.shape[1]
    D = _difference_operator(len(yn), len(xn), int(order))
    reg = (D.T @ D).tocsr() / tau_px**2
    ridge = 1e-10 * max(float(w.max()), 1.0)
    AtW = [A.T.multiply(w[:, c]).tocsr() for c in range(2)]
    Nvv = block_diag([AtW[0] @ A + reg, AtW[1] @ A + reg], format="csc") + diags(np.full(2 * n_nodes, ridge))
    base_v = base.delta_px.reshape(-1, 2)
    bv = np.concatenate([AtW[c] @ r[:, c] - reg @ base_v[:, c] for c in range(2)])

    n_beads = len(shape_mm[0]) if shape_mm is not None else (int(bead_index.max()) + 1 if n else 0)
    cols = (3 * bead_index[:, None] + np.arange(3)).ravel()
    # J_c as sparse (n, 3 n_beads): row o holds d proj_c / d P of its bead
    Jc = [
        csr_matrix((point_jacobian[:, c, :].ravel(), (np.repeat(np.arange(n), 3), cols)), shape=(n, 3 * n_beads))
        for c in range(2)
    ]
    Nvp = vstack([AtW[c] @ Jc[c] for c in range(2)]).tocsr()
    # per-bead 3x3 blocks sum_o J^T W J, inverted
    Npp = np.zeros((n_beads, 3, 3))
    np.add.at(Npp, bead_index, np.einsum("nci,nc,ncj->nij", point_jacobian, w, point_jacobian))
    trace = np.trace(Npp, axis1=1, axis2=2)
    # beads without observations here (seen only by another system) get a unit-scale block
    Npp += np.maximum(1e-9 * trace, 1e-6 * max(float(trace.max(initial=0.0)), 1e-300))[:, None, None] * np.eye(3)
    Npp_inv = np.linalg.inv(Npp)
    bp = np.zeros((n_beads, 3))
    np.add.at(bp, bead_index, np.einsum("nci,nc->ni", point_jacobian, w * r))

    def apply_block_inv(x):
        return np.einsum("bij,bj->bi", Npp_inv, x.reshape(-1, 3)).ravel()

    apply_pp_inv = apply_block_inv
    if shape_mm is not None:
        B, gap = _affine_shape_modes(*shape_mm)
        kappa = 1e2 * float(np.max(trace))
        # penalty kappa |B^T (P + dP) - B^T P_nominal|^2: rank-5 term, inverted by Woodbury
        bp = bp - kappa * (B @ gap).reshape(-1, 3)
        NiB = np.column_stack([apply_block_inv(b) for b in B.T])
        core = np.linalg.inv(np.eye(B.shape[1]) / kappa + B.T @ NiB)

        def apply_pp_inv(x):
            return apply_block_inv(x) - NiB @ (core @ (NiB.T @ x))

    Npv = Nvp.T.tocsr()
    rhs = bv - Nvp @ apply_pp_inv(bp.ravel())
    op = LinearOperator(
        (2 * n_nodes, 2 * n_nodes), matvec=lambda v: Nvv @ v - Nvp @ apply_pp_inv(Npv @ v), dtype=np.float64
    )
    # the preconditioner, block by block: one factorisation when both components weigh alike
    blocks = (
        [Nvv[:n_nodes, :n_nodes]]
        if np.array_equal(w[:, 0], w[:, 1])
        else [Nvv[:n_nodes, :n_nodes], Nvv[n_nodes:, n_nodes:]]
    )
    lus = [_factor_spd(blk) for blk in blocks]

    def precondition(v):
        return np.concatenate([lus[0].solve(v[:n_nodes]), lus[-1].solve(v[n_nodes:])])

    pre = LinearOperator((2 * n_nodes, 2 * n_nodes), matvec=precondition, dtype=np.float64)
    v, info = cg(op, rhs, rtol=1e-6, maxiter=max_cg_iterations, M=pre)
    if info > 0:
        logger.info("joint field-and-points step: CG stopped after %d iterations short of its tolerance", info)
    return _grid_result(xn, yn, np.column_stack([v[:n_nodes], v[n_nodes:]]), A, xy, cv_rms_px, params, (width, height))


__all__ = [
    "VERSION",
    "SCHEMES",
    "LearnParams",
    "KnnModel",
    "CvReport",
    "GridCvReport",
    "CorrectionField",
    "PointwiseField",
    "IterationRecord",
    "LearnResult",
    "grid_nodes",
    "cross_validate_k",
    "cross_validate_smoothness",
    "fit_knn_field",
    "fit_grid_field",
    "fit_grid_with_points",
    "calibrate",
]


# ---------------------------------------------------------------------------------------------
# The pipeline's entry
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CalibrationSetup:
    """What the pipeline knows of the project and :func:`learn_calibration` needs.

    Attributes
    ----------
    scheme : str
        One of :data:`SCHEMES` (config ``[calibration] scheme``).
    image_size_px : tuple of (int, int)
        ``(width, height)`` of each system's frames.
    iop_guess_px : tuple of (float, float, float)
        Start values ``(xp, yp, c)`` per system: the image centre and source-image distance / pixel pitch.
    """

    scheme: str = "knn+iop+smooth"
    image_size_px: tuple = ()
    iop_guess_px: tuple = ()


def learn_calibration(
    observations, phantom, params: LearnParams, *, setup: CalibrationSetup, adjust=None
) -> LearnResult:
    """Calibrate from labelled observations: start values by resection, then :func:`calibrate`.

    Parameters
    ----------
    observations : Observations
    phantom : Phantom
        Nominal (design) bead coordinates.
    params : LearnParams
    setup : CalibrationSetup
    adjust : AdjustParams, optional

    Raises
    ------
    InputError
        A grid-plate phantom (its lattice ids are per frame; calibrate it with a bead phantom).
    EstimationError
        No frame could be resected, or the adjustment failed as a whole.
    """
    from fluorocal.stages.adjust import initial_orientation

    if phantom.lattice:
        raise InputError(
            "calibrating from a grid plate is not supported by `fluorocal run` yet: use a 3D bead phantom (the grid's holes are detected and indexed by `fluorocal detect` / `fluorocal label`)"
        )
    initial = initial_orientation(observations, phantom, np.asarray(setup.iop_guess_px, dtype=np.float64))
    return calibrate(
        observations,
        phantom,
        initial,
        image_size=setup.image_size_px,
        scheme=setup.scheme,
        params=params,
        adjust_params=adjust,
    )
