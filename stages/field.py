"""The correction-field model a calibration stores: ``Δ`` on a grid of nodes, interpolated bilinearly.

A correction field maps measured (distorted) pixel coordinates to ideal
pinhole ones, ``ideal = measured - Δ(measured)`` (docs/concepts.md, "Conventions":
``(x, y)`` with the centre of the top-left pixel at ``(0, 0)``).

- :class:`CorrectionField`: ``Δ`` on a rectilinear grid of nodes over the
  image with bilinear interpolation, a per-node uncertainty and a support
  mask; ``undistort_points``, ``distort_points`` (Newton) and ``remap_maps``
  (inverse maps for ``cv2.remap``). This is what the calibration file holds.
- :class:`PointwiseField`: a sum of regressors evaluated at the points (the
  unsmoothed kNN scheme's exact field).
- :func:`grid_nodes`, :func:`bilinear`, :func:`bilinear_design`: the grid and
  its interpolation, shared with the learning (:mod:`fluorocal.stages.learn`).

This module imports neither the learning nor the labelling, so loading a
calibration stays light.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from fluorocal.stages.artifacts import check_shape, freeze
from fluorocal.stages.errors import InputError, ShapeError

logger = logging.getLogger(__name__)
#: points inverted at once by ``remap_maps`` (its Newton iteration holds ~20 float64 values per point)
_MAP_BLOCK_POINTS = 65536


def bilinear(x_nodes, y_nodes, values, xy, *, gradient=False):
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


def bilinear_design(x_nodes, y_nodes, xy):
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
        Where enough observations lay near the node (see the learning's ``min_support``).
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
        return bilinear(self.x_nodes_px, self.y_nodes_px, self.delta_px, _as_points("xy_px", xy_px))

    def _jacobian(self, xy_px):
        _, d_dx, d_dy = bilinear(self.x_nodes_px, self.y_nodes_px, self.delta_px, xy_px, gradient=True)
        return d_dx, d_dy

    def support_at(self, xy_px: np.ndarray) -> np.ndarray:
        """True ``(N,)`` where all four surrounding nodes are supported."""
        s = bilinear(
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
        map_x = np.empty((height_px, width_px), np.float32)
        map_y = np.empty((height_px, width_px), np.float32)
        rows = max(1, _MAP_BLOCK_POINTS // max(width_px, 1))  # a block of rows at a time: bounded memory
        for top in range(0, height_px, rows):
            yy, xx = np.mgrid[top : min(top + rows, height_px), 0:width_px].astype(np.float64)
            src = self.distort_points(np.column_stack([xx.ravel(), yy.ravel()]))
            map_x[top : top + rows] = src[:, 0].reshape(xx.shape)
            map_y[top : top + rows] = src[:, 1].reshape(xx.shape)
        return map_x, map_y


@dataclass(frozen=True)
class PointwiseField(_FieldOps):
    """The unsmoothed scheme's correction: a sum of kNN regressors, one per alternation step.

    Attributes
    ----------
    terms : tuple
        Regressors with a ``correction_at(xy_px)`` method (the learning's ``KnnModel``).
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

    def add(self, term) -> "PointwiseField":
        """``Δ + δ`` with ``δ`` a new regressor (anything with ``correction_at``)."""
        return replace(self, terms=self.terms + (term,))

    def to_grid(self, spacing_px: float, sigma_px=None, support=None) -> CorrectionField:
        """Sample the field at the nodes of a grid of at most ``spacing_px`` (for storage and ``remap_maps``)."""
        xn, yn = grid_nodes(self.width_px, self.height_px, spacing_px)
        shape = (len(yn), len(xn))
        nodes = np.column_stack([a.ravel() for a in np.meshgrid(xn, yn)])
        delta = self.correction_at(nodes).reshape(shape + (2,))
        sigma = np.zeros(shape) if sigma_px is None else sigma_px
        support = np.ones(shape, bool) if support is None else support
        return CorrectionField(xn, yn, delta, sigma, support, self.width_px, self.height_px)


__all__ = ["CorrectionField", "PointwiseField", "bilinear", "bilinear_design", "grid_nodes"]
