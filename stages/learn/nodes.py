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

    def support_mask(self, xy_px: np.ndarray, nodes_px: np.ndarray) -> np.ndarray:
        """``(n_nodes,)`` True where at least ``min_support`` points lie within ``support_radius_px`` of a node."""
        counts = KDTree(xy_px).query_ball_point(nodes_px, r=self.support_radius_px, return_length=True)
        return counts >= self.min_support


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
