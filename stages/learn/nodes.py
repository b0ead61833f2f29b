"""What every regression of the learning shares: the node grid with its support rule, and the training data's checks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.artifacts import check_shape
from fluorocal.stages.errors import InputError
from fluorocal.stages.field import grid_nodes
from scipy.spatial import KDTree


@dataclass(frozen=True)
class GridSpec:
    """The grid a learned field lives on and when a node counts as supported by the data.

    Attributes
    ----------
    spacing_px : float
        Largest spacing between nodes (default 16 px), see :func:`fluorocal.stages.field.grid_nodes`.
    support_radius_px : float
        Radius within which a node counts observations (default 32 px).
    min_support : int
        Observations needed within the radius for the node to be supported (default 3).

    Examples
    --------
    >>> x, y = GridSpec(spacing_px=32.0).nodes((64, 32))
    >>> x.tolist(), y.tolist()
    ([-0.5, 31.5, 63.5], [-0.5, 31.5])
    """

    spacing_px: float = 16.0
    support_radius_px: float = 32.0
    min_support: int = 3

    def nodes(self, image_size) -> tuple[np.ndarray, np.ndarray]:
        """Node columns and rows ``(W_g,)``, ``(H_g,)`` px over an image of ``(width, height)`` px."""
        width, height = (int(s) for s in image_size)
        return grid_nodes(width, height, self.spacing_px)

    def support_mask(self, xy_px: np.ndarray, x_nodes_px: np.ndarray, y_nodes_px: np.ndarray) -> np.ndarray:
        """``(H_g * W_g,)`` True where at least ``min_support`` points lie within ``support_radius_px`` of a node.

        The nodes are the grid of ``x_nodes_px`` ``(W_g,)`` and ``y_nodes_px`` ``(H_g,)``, row-major (x fastest).
        Each point is tested against the nodes of its window, the columns and rows within the radius along each
        axis (one more each side for the rounding), as a KD-tree tests it: its squared distance against the
        squared radius, a tenth of the KD-tree's time. When one is within rounding of the radius (where the order
        of the KD-tree's sums could decide it), or the windows are large, the KD-tree counts. Raises
        :class:`~fluorocal.stages.errors.InputError` on a position that is not finite.
        """
        xy = np.asarray(xy_px, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(xy)):
            raise InputError("support_mask: xy_px must be finite")
        xn, yn = (np.asarray(a, dtype=np.float64) for a in (x_nodes_px, y_nodes_px))
        r2 = self.support_radius_px**2
        cols, dx2 = _axis_window(xn, xy[:, 0], self.support_radius_px)
        rows, dy2 = _axis_window(yn, xy[:, 1], self.support_radius_px)
        # a radius of many spacings (the user's) would make the windows' arrays large: the KD-tree counts
        if len(xy) * dx2.shape[1] * dy2.shape[1] <= WINDOW_MAX_ENTRIES:
            d2 = dx2[:, None, :] + dy2[:, :, None]  # shape (n, rows, columns), inf outside the grid
            if not np.any(np.abs(d2 - r2) <= 1e-9 * r2):
                node = rows[:, :, None] * len(xn) + cols[:, None, :]
                return np.bincount(node[d2 <= r2], minlength=len(xn) * len(yn)) >= self.min_support
        counts = KDTree(xy).query_ball_point(node_coordinates(xn, yn), r=self.support_radius_px, return_length=True)
        return counts >= self.min_support


#: most point-node pairs :meth:`GridSpec.support_mask` tests in its windows (22 bytes each at its peak, measured:
#: 180 MB); 30 000 observations on the default grid take 1.5 million
WINDOW_MAX_ENTRIES = 2**23


def _axis_window(nodes: np.ndarray, v: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Each value's window of node indices ``(n, w)`` along one axis and its squared distances (inf past the ends).

    The window holds every node within ``radius`` of the value and one more each side.
    """
    lo = np.searchsorted(nodes, v - radius, side="left") - 1
    hi = np.searchsorted(nodes, v + radius, side="right") + 1
    idx = lo[:, None] + np.arange(max(int(np.max(hi - lo, initial=0)), 0))
    inside = (idx >= 0) & (idx < len(nodes))
    idx = np.clip(idx, 0, len(nodes) - 1)
    d2 = np.where(inside, (v[:, None] - nodes[idx]) ** 2, np.inf)
    return idx, d2


#: the default grid: 16 px spacing, support within 32 px from 3 observations
DEFAULT_GRID = GridSpec()


def node_coordinates(x_nodes_px: np.ndarray, y_nodes_px: np.ndarray) -> np.ndarray:
    """Node coordinates ``(H_g * W_g, 2)`` px, row-major (x varies fastest)."""
    return np.column_stack([a.ravel() for a in np.meshgrid(x_nodes_px, y_nodes_px)])


def check_training(xy_px, residuals_px, residual_var_px2):
    """The training data as float64 arrays ``(N, 2)``, variances broadcast to both components; raise on bad input."""
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


def image_sizes(image_size, n_systems: int) -> tuple[tuple[int, int], ...]:
    """``image_size`` as one ``(width, height)`` per system: a single pair is every system's.

    Raises
    ------
    InputError
        Not a pair or one per system, or not positive.
    """
    arr = np.asarray(image_size, dtype=np.int64)
    if arr.shape == (2,):
        arr = np.tile(arr, (n_systems, 1))
    if arr.shape != (n_systems, 2) or np.any(arr < 1):
        raise InputError(
            f"image_size must be (width, height) or one per system, shape ({n_systems}, 2); got {arr.shape}"
        )
    return tuple((int(w), int(h)) for w, h in arr)
