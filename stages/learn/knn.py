"""The kNN regression of residual vectors over the image, and its neighbourhood size by cross-validation.

Chow et al., section IV after equation 2: a k-nearest-neighbour regression of
the adjustment's residual vectors learns the deterministic part ``δ`` of the
residuals (distortion); ``k`` comes from shuffled K-fold cross-validation of
the equation-3 cost, never from the in-sample fit (which would chase noise).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
from fluorocal.stages.artifacts import check_shape, freeze
from fluorocal.stages.errors import InputError
from fluorocal.stages.field import CorrectionField
from fluorocal.stages.learn.nodes import DEFAULT_GRID, GridSpec, check_training, node_coordinates
from fluorocal.stages.learn.robust import capped_cost
from scipy.spatial import KDTree

logger = logging.getLogger(__name__)

#: candidate neighbourhood sizes of the cross-validation: roughly sqrt(2) steps
DEFAULT_K_GRID = (1, 2, 3, 4, 6, 8, 11, 16, 23, 32, 45, 64, 90, 128, 181, 256)


def weighted_neighbour_means(values, weights, idx, ks):
    """Inverse-variance weighted means of the first ``k`` neighbours, for each ``k`` in ``ks``.

    Parameters
    ----------
    values, weights : (N, 2) float64 ndarray
    idx : (M, K) int ndarray
        Neighbour indices, nearest first.
    ks : sequence of int, increasing, each <= K

    Returns
    -------
    (M, len(ks), 2) float64 ndarray
    """
    ks = np.asarray(ks)
    # shape (M, k_max, 4): w, w r (np.take: the same gather, faster than fancy indexing)
    both = np.take(np.concatenate([weights, weights * values], axis=1), idx[:, : ks[-1]], axis=0)
    # the sums between consecutive candidates, then their running sums: one pass over the neighbours
    sums = np.cumsum(np.add.reduceat(both, np.concatenate([[0], ks[:-1]]), axis=1), axis=1)
    return sums[..., 2:] / sums[..., :2]


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
        return self.mean_over(self.neighbours(xy)[1])

    def mean_over(self, idx: np.ndarray) -> np.ndarray:
        """The prediction ``(M, 2)`` px from the neighbour indices ``(M, k_used)`` of :meth:`neighbours`."""
        return weighted_neighbour_means(self.values_px, self.weights, idx, [self.k_used])[:, 0]

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
    neighbour_pool_px: np.ndarray | None = None,
    cost_cap: float | None = None,
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
    neighbour_pool_px : (P, 2) float64 ndarray, px, optional
        Points that ``xy_px`` of this and later calls with the same cache are drawn from (the system's
        observations, of which each iteration trains on the inliers): the cache then keeps every pool
        point's nearest neighbours, from which a later call on other inliers reads its folds' neighbours
        without a KD-tree (the same neighbours). Default: ``xy_px``.
    cost_cap : float, optional
        Bound on each observation's out-of-fold cost ``(r - g)^T C_r^-1 (r - g)``
        (default None: unbounded), see :func:`fluorocal.stages.learn.robust.capped_cost`:
        a gross error then costs every candidate alike. The out-of-fold RMS
        is then that of the observations below the bound.

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
    xy, r, var = check_training(xy_px, residuals_px, residual_var_px2)
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
    _fill_neighbour_cache(cache, xy, folds, seed, int(ks[-1]), neighbour_pool_px)
    cost = np.zeros(len(ks))
    sq = np.zeros(len(ks))
    n_sq = np.zeros(len(ks))
    for test, idx in zip(folds, cache["idx"]):
        train = np.setdiff1d(np.arange(n), test, assume_unique=True)
        g = weighted_neighbour_means(r[train], w[train], idx[:, : ks[-1]], ks)  # shape (n_test, K, 2)
        fold = _fold_costs(r[test][:, None, :] - g, w[test][:, None, :], cost_cap)
        cost, sq, n_sq = cost + fold[0], sq + fold[1], n_sq + fold[2]
    cost /= n
    best = int(np.argmin(cost))
    return CvReport(ks, cost, int(ks[best]), float(np.sqrt(sq[best] / (2 * max(n_sq[best], 1)))), n)


def _fold_costs(err, w, cost_cap):
    """One fold's summed cost, squared error and count per candidate, from its errors ``(n_test, K, 2)``.

    With ``cost_cap`` each observation's cost is bounded at it, and the squared
    error counts only the observations below it (it sets the nodes' uncertainty).
    """
    if cost_cap is None:
        return np.sum(w * err**2, axis=(0, 2)), np.sum(err**2, axis=(0, 2)), len(err)
    z2 = np.sum(w * err**2, axis=2)  # shape (n_test, K)
    below = z2 <= cost_cap
    return (
        np.sum(capped_cost(z2, cost_cap), axis=0),
        np.sum(np.where(below, np.sum(err**2, axis=2), 0.0), 0),
        below.sum(0),
    )


def _fill_neighbour_cache(cache: dict, xy: np.ndarray, folds: list, seed: int, k_max: int, pool=None) -> None:
    """Each fold's ``k_max`` nearest training neighbours of its test points, unless ``cache`` holds them already.

    They are read from the cache's :class:`_NeighbourTable` when it covers ``xy`` (the alternation's inliers
    change by a few observations from one iteration to the next, its coordinates never): the same neighbours as
    a KD-tree of each fold's training points would give, without querying one. ``pool`` (default ``xy``): the
    points of the table, when it is built.
    """
    n_folds = len(folds)
    if (
        cache.get("n_folds") == n_folds
        and cache.get("seed") == seed
        and cache.get("k", 0) >= k_max
        and np.array_equal(cache.get("xy"), xy)
    ):
        return
    table = cache.get("table")
    rows = None if table is None or table.k_max < k_max else table.rows_of(xy)
    if rows is None:
        pool = xy if pool is None else np.asarray(pool, dtype=np.float64)
        table = _NeighbourTable.build(pool, k_max, n_folds, len(xy))
        rows = table.rows_of(xy)
    if rows is None:  # xy is not drawn from the pool
        table, rows = _NeighbourTable.build(xy, k_max, n_folds, len(xy)), np.arange(len(xy))
    nodes = cache.get("nodes") if cache.get("table") is table else None
    cache.clear()
    cache.update(
        nodes=nodes,
        xy=xy.copy(),
        n_folds=n_folds,
        seed=seed,
        k=k_max,
        table=table,
        rows=rows,
        idx=table.fold_neighbours(xy, rows, folds, k_max),
    )


@dataclass(frozen=True)
class _NeighbourTable:
    """Every point's nearest neighbours among a set of points, enough of them to serve the folds of any subset.

    ``idx`` ``(n_base, K)``: the ``K`` nearest of each base point (itself first), nearest first; ``k_max``:
    the most neighbours per fold it was sized for; ``tree``: the base points' KD-tree (to find a subset's rows).
    """

    xy: np.ndarray
    idx: np.ndarray
    k_max: int
    tree: KDTree

    @classmethod
    def build(cls, xy: np.ndarray, k_max: int, n_folds: int, n_used: int) -> "_NeighbourTable":
        """The table of the points ``xy``, sized for ``k_max`` neighbours of folds of ``n_used`` of them."""
        # a test point's own fold takes 1 / n_folds of its neighbours, the points not used the rest of the pool: a
        # margin for their spread (a shortfall costs a query of that point's fold, not a wrong neighbour)
        share = n_used / max(len(xy), 1) * (n_folds - 1) / n_folds
        k = min(len(xy), int(np.ceil(1.05 * (k_max + 1) / share)) + 16)
        xy = xy.copy()
        tree = KDTree(xy)
        _, idx = tree.query(xy, k=k)
        return cls(xy, idx.reshape(len(xy), k).astype(np.int32), k_max, tree)

    def rows_of(self, xy: np.ndarray) -> np.ndarray | None:
        """The base rows of the points ``xy``, one each, or None when one is not a base point (or two share one)."""
        if len(xy) > len(self.xy):
            return None
        if len(xy) == len(self.xy) and np.array_equal(xy, self.xy):
            return np.arange(len(xy))
        # equal coordinates by a binary search of the base points' sorted keys (the KD-tree's nearest at distance 0)
        keys, order = self.sorted_keys
        query = _point_keys(xy)
        at = np.minimum(np.searchsorted(keys, query), len(keys) - 1)
        rows = order[at]
        if not np.array_equal(keys[at], query) or np.bincount(rows, minlength=1).max() > 1:
            return None
        return rows

    @cached_property
    def sorted_keys(self) -> tuple[np.ndarray, np.ndarray]:
        """The base points' :func:`_point_keys` in increasing order, and their rows."""
        keys = _point_keys(self.xy)
        order = np.argsort(keys, kind="stable")
        return keys[order], order

    def positions(self, rows: np.ndarray) -> np.ndarray:
        """Each base point's position among the points at base ``rows`` (-1: not among them)."""
        position = np.full(len(self.xy), -1)
        position[rows] = np.arange(len(rows))
        return position

    def fold_neighbours(self, xy: np.ndarray, rows: np.ndarray, folds: list, k_max: int) -> list:
        """Per fold, ``(n_test, k_max)`` int32 indices into its training points (``xy`` less the fold, in order)."""
        fold_of = np.empty(len(xy), np.int64)
        for f, test in enumerate(folds):
            fold_of[test] = f
        out = []
        for f, test in enumerate(folds):
            train = fold_of != f
            # each base point's index among the fold's training points (-1: not one; the test point itself is not)
            rank = np.full(len(self.xy), -1, np.int32)
            rank[rows[train]] = np.arange(np.count_nonzero(train), dtype=np.int32)
            cand = np.take(rank, np.take(self.idx, rows[test], axis=0))  # shape (n_test, K)
            idx, ok = _first_valid(cand, cand >= 0, k_max)
            if not ok.all():
                train = np.flatnonzero(fold_of != f)
                _, missing = KDTree(xy[train]).query(xy[test[~ok]], k=k_max)
                idx[~ok] = missing.reshape(-1, k_max)
            out.append(idx)
        return out

    def nearest_others(self, xy: np.ndarray, rows: np.ndarray, m: int) -> np.ndarray:
        """Each point's ``m`` nearest other points of ``xy`` ``(n, m)`` (indices into ``xy``, nearest first)."""
        position = self.positions(rows)
        # the m others and the point itself are nearly always among a row's first 2 m + 8 (the rest of the table
        # serves the folds): those first, the whole row where a row is short of m others there
        idx, ok = _other_points(position, self.idx[rows, : 2 * m + 8], np.arange(len(xy)), m)
        short = np.flatnonzero(~ok)
        if len(short) and self.idx.shape[1] > 2 * m + 8:
            idx[short], ok[short] = _other_points(position, self.idx[rows[short]], short, m)
        if not ok.all():
            _, missing = KDTree(xy).query(xy[~ok], k=m + 1)
            idx[~ok] = missing[:, 1:]
        return idx


def _point_keys(xy: np.ndarray) -> np.ndarray:
    """Each point ``(x, y)`` as one ordered key, ``x + i y`` (complex numbers sort by their real parts first)."""
    return np.ascontiguousarray(xy, dtype=np.float64).view(np.complex128).ravel()


def _other_points(position: np.ndarray, table_rows: np.ndarray, own: np.ndarray, m: int):
    """The first ``m`` of each table row ``table_rows`` among the points at ``position``, each row's own ``own`` not."""
    cand = position[table_rows]
    return _first_valid(cand, (cand >= 0) & (cand != own[:, None]), m)


def _first_valid(cand: np.ndarray, valid: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The first ``k`` valid entries of each row of ``cand``, ``(n, k)`` int32, and the rows that have ``k``.

    The rows short of ``k`` are left unset.
    """
    # the running count in the narrowest type that holds a row's length: the same counts, less memory to pass
    count = np.cumsum(valid, axis=1, dtype=np.int16 if valid.shape[1] < 2**15 else np.int64)
    ok = count[:, -1] >= k if count.shape[1] else np.zeros(len(cand), bool)
    first = valid & (count <= k)
    idx, rows = np.empty((len(cand), k), np.int32), slice(None) if ok.all() else ok  # a view, no copy, if all
    idx[rows] = cand[rows][first[rows]].reshape(-1, k)
    return idx, ok


def pool_neighbours(cache: dict, xy_px: np.ndarray, m: int) -> np.ndarray | None:
    """Each point's ``m`` nearest other points of ``xy_px`` ``(n, m)``, from the neighbour table in ``cache``.

    The table is the one :func:`cross_validate_k` left there with ``neighbour_pool_px``; None when there is
    none, or it does not hold every point of ``xy_px``.
    """
    table = cache.get("table")
    xy = np.asarray(xy_px, dtype=np.float64)
    rows = None if table is None or len(xy) <= m else table.rows_of(xy)
    return None if rows is None else table.nearest_others(xy, rows, m)


def node_statistics(model: KnnModel, nodes_px: np.ndarray, cv_rms_px: float, grid: GridSpec, idx=None, counts=None):
    """Per-node uncertainty ``cv_rms / sqrt(n_eff)`` and support mask, both ``(n_nodes,)``.

    ``idx``: the nodes' neighbours from ``model.neighbours(nodes_px)``, ``counts``: the training points within
    ``grid.support_radius_px`` of each node, when already at hand.
    """
    if idx is None:
        _, idx = model.neighbours(nodes_px)
    w = model.weights[idx].mean(axis=2)  # shape (n_nodes, k)
    n_eff = w.sum(1) ** 2 / np.sum(w**2, axis=1)
    sigma = cv_rms_px / np.sqrt(n_eff)
    if counts is None:
        counts = model.tree.query_ball_point(nodes_px, r=grid.support_radius_px, return_length=True)
    return sigma, counts >= grid.min_support


@dataclass(frozen=True)
class _NodeTable:
    """The nodes' ``K`` nearest pool points ``idx``, ``dist`` ``(n_nodes, K)``, nearest first (a subset's nearest)."""

    nodes: np.ndarray
    idx: np.ndarray
    dist: np.ndarray
    k_max: int
    tied: np.ndarray  # (n_nodes,): two of the node's K + 1 nearest at one distance (in the KD-tree's own order)

    @classmethod
    def build(cls, table: _NeighbourTable, nodes: np.ndarray, k_max: int, n_used: int) -> "_NodeTable":
        # as _NeighbourTable's margin: a node short of neighbours in the subset costs a query of its own
        k = min(len(table.xy), int(np.ceil(1.05 * k_max * len(table.xy) / max(n_used, 1))) + 16)
        dist, idx = (a.reshape(len(nodes), -1) for a in table.tree.query(nodes, k=min(k + 1, len(table.xy))))
        tied = np.any(dist[:, 1:] == dist[:, :-1], axis=1)
        return cls(nodes.copy(), idx[:, :k].astype(np.int32), dist[:, :k], k_max, tied)

    def neighbours(self, model: KnnModel, position: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
        """``model.neighbours`` of the nodes and its tree's counts within ``radius`` (training points at ``position``).

        Nodes short of neighbours in their row, or tied, are queried from the tree; the counts too where the ball may
        pass the row's end or has a point at its edge (a root may round onto the radius; the tree compares squares).
        """
        valid = (cand := np.take(position, self.idx)) >= 0
        idx, ok = _first_valid(cand, valid, model.k_used)
        if not (ok := ok & ~self.tied).all():
            idx[~ok] = model.neighbours(self.nodes[~ok])[1]
        counts = np.sum(valid & (inside := self.dist <= radius), axis=1)
        edge = np.take_along_axis(self.dist, np.minimum(inside.sum(1)[:, None] + [-1, 0], inside.shape[1] - 1), 1)
        unsure = inside[:, -1] | np.any(np.abs(edge - radius) <= 1e-9 * radius, axis=1)
        if unsure.any():
            counts[unsure] = model.tree.query_ball_point(self.nodes[unsure], r=radius, return_length=True)
        return idx, counts


def _node_neighbours(cache: dict | None, model: KnnModel, nodes: np.ndarray, radius: float):
    """:meth:`_NodeTable.neighbours` from ``cache``'s node table (built if need be), None if its table lacks a point."""
    table = None if cache is None else cache.get("table")
    if table is None:
        return None
    # the cross-validation's training points' rows, when these are they (the refit's are a few less)
    same = np.array_equal(cache.get("xy"), model.points_px)
    rows = cache["rows"] if same else table.rows_of(model.points_px)
    if rows is None:
        return None
    near = cache.get("nodes")
    if near is None or near.k_max < model.k_used or not np.array_equal(near.nodes, nodes):
        near = cache["nodes"] = _NodeTable.build(table, nodes, model.k_used, len(rows))
    return near.neighbours(model, table.positions(rows), radius)


def fit_knn_field(
    xy_px: np.ndarray,
    residuals_px: np.ndarray,
    residual_var_px2: np.ndarray,
    *,
    image_size: tuple[int, int],
    grid: GridSpec = DEFAULT_GRID,
    smooth: bool = True,
    k_grid=DEFAULT_K_GRID,
    n_folds: int = 10,
    seed: int = 0,
    cv: CvReport | None = None,
    neighbour_cache: dict | None = None,
    neighbour_pool_px: np.ndarray | None = None,
    cost_cap: float | None = None,
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
    image_size : (int, int)
        ``(width, height)`` of the image in px.
    grid : GridSpec
        Nodes and support rule of the gridded field (default 16 px, 32 px, 3).
    smooth : bool
        Resample the kNN prediction onto the grid and interpolate it
        bilinearly (the paper's "smoothed kNN", default True); False returns
        the kNN regressor itself. The scheme decides it.
    k_grid, n_folds, seed
        Of :func:`cross_validate_k` (defaults: :data:`DEFAULT_K_GRID`, 10, 0).
    cv : CvReport, optional
        A cross-validation already run on (nearly) the same observations: its
        ``k`` and out-of-fold RMS are used and none is run (the refit after
        the local outlier test, which drops a few observations).
    neighbour_cache, neighbour_pool_px, cost_cap : optional
        Passed to :func:`cross_validate_k`; the cache's table also serves the nodes' neighbours (``cv`` given too).

    Returns
    -------
    field : CorrectionField or KnnModel
        With ``smooth`` the kNN prediction at the grid nodes (with
        uncertainty and support); otherwise the kNN regressor itself.
    cv : CvReport
        The cross-validation table (``k`` vs mean equation-3 cost).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> xy = rng.uniform(0, 64, (400, 2))
    >>> r = np.full((400, 2), 0.3) + rng.normal(0, 0.05, (400, 2))
    >>> field, cv = fit_knn_field(xy, r, np.full(400, 0.05**2), image_size=(64, 64))
    >>> bool(np.allclose(field.correction_at(np.array([[32.0, 32.0]])), 0.3, atol=0.03))
    True
    """
    xy, r, var = check_training(xy_px, residuals_px, residual_var_px2)
    width, height = (int(s) for s in image_size)
    if cv is None:
        cv = cross_validate_k(
            xy,
            r,
            var,
            k_grid=k_grid,
            n_folds=n_folds,
            seed=seed,
            neighbour_cache=neighbour_cache,
            neighbour_pool_px=neighbour_pool_px,
            cost_cap=cost_cap,
        )
        logger.debug("kNN cross-validation over %d points:\n%s", len(xy), cv.table())
    model = KnnModel(xy, r, 1.0 / var, cv.k)
    if not smooth:
        return model, cv
    return _gridded(model, cv.cv_rms_px, grid, (width, height), neighbour_cache), cv


def _gridded(model: KnnModel, cv_rms_px: float, grid: GridSpec, size: tuple[int, int], cache=None) -> CorrectionField:
    """The kNN prediction at the nodes of ``grid`` over an image of ``size``, with its uncertainty and support.

    ``cache``: a neighbour cache of :func:`cross_validate_k` whose table holds the training points: the nodes'
    neighbours are then read from its node table (the same ones; built there on first use).
    """
    xn, yn = grid.nodes(size)
    nodes = node_coordinates(xn, yn)
    near = _node_neighbours(cache, model, nodes, grid.support_radius_px)
    idx, counts = (model.neighbours(nodes)[1], None) if near is None else near
    delta = model.mean_over(idx).reshape(len(yn), len(xn), 2)
    sigma, support = node_statistics(model, nodes, cv_rms_px, grid, idx=idx, counts=counts)
    shape = delta.shape[:2]
    return CorrectionField(xn, yn, delta, sigma.reshape(shape), support.reshape(shape), *size)


def restricted_k_grid(k_grid: tuple, k_prev: int | None, span: int = 3) -> tuple:
    """The candidates within ``span`` grid steps of the previous choice (all of them at first)."""
    if k_prev is None or k_prev not in k_grid:
        return k_grid
    i = k_grid.index(k_prev)
    return k_grid[max(i - span, 0) : i + span + 1]


__all__ = [
    "DEFAULT_K_GRID",
    "KnnModel",
    "CvReport",
    "cross_validate_k",
    "fit_knn_field",
    "node_statistics",
    "pool_neighbours",
    "restricted_k_grid",
]
