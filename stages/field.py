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

import functools
import logging
from dataclasses import dataclass, replace

import numpy as np
from fluorocal.stages.artifacts import check_shape, freeze
from fluorocal.stages.errors import InputError, ShapeError

logger = logging.getLogger(__name__)
#: points inverted at once by ``remap_maps``: they take the same number of Newton steps (changing
#: it changes the maps' last bits)
_MAP_BLOCK_POINTS = 65536
#: points per Newton step computed at once: its ~40 temporaries stay in the processor's cache and
#: are not handed back to the system between steps (measured: a quarter less time than all at once)
_STEP_POINTS = 8192


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
    planes = _node_planes(values)
    result = _bilinear_planes(x_nodes, y_nodes, planes, xy[:, 0], xy[:, 1], gradient=gradient)
    return tuple(r.T for r in result) if gradient else result.T


def _node_planes(values):
    """``(C, H_g * W_g)`` node values, one contiguous plane per channel, of ``(H_g, W_g, C)`` ``values``."""
    return np.ascontiguousarray(np.moveaxis(values, -1, 0).reshape(values.shape[-1], -1))


def _bilinear_planes(x_nodes, y_nodes, planes, x, y, *, gradient=False):
    """:func:`bilinear` on :func:`_node_planes` at points ``(x, y)`` ``(M,)``: ``(C, M)`` results.

    The cell and its weights are found once for all channels and shared by
    the value and the gradient.
    """
    n_x = len(x_nodes)
    xc = np.clip(x, x_nodes[0], x_nodes[-1])
    yc = np.clip(y, y_nodes[0], y_nodes[-1])
    i = np.clip(np.searchsorted(x_nodes, xc, side="right") - 1, 0, n_x - 2)
    j = np.clip(np.searchsorted(y_nodes, yc, side="right") - 1, 0, len(y_nodes) - 2)
    x0, y0 = x_nodes.take(i), y_nodes.take(j)
    hx = x_nodes.take(i + 1) - x0
    hy = y_nodes.take(j + 1) - y0
    tx = (xc - x0) / hx
    ty = (yc - y0) / hy
    k00 = j * n_x + i
    corners = (k00, k00 + 1, k00 + n_x, k00 + n_x + 1)
    out = np.empty((len(planes), len(x)))
    if gradient:
        d_dx, d_dy = np.empty_like(out), np.empty_like(out)
        ty_c = 1 - ty
        inside_x = (x > x_nodes[0]) & (x < x_nodes[-1])
        inside_y = (y > y_nodes[0]) & (y < y_nodes[-1])
    for c, plane in enumerate(planes):
        v00, v01, v10, v11 = (plane.take(k) for k in corners)
        along_top = v01 - v00
        along_bottom = v11 - v10
        top = v00 + tx * along_top
        bottom = v10 + tx * along_bottom
        down = bottom - top
        np.add(top, ty * down, out=out[c])
        if gradient:
            np.multiply((ty_c * along_top + ty * along_bottom) / hx, inside_x, out=d_dx[c])
            np.multiply(down / hy, inside_y, out=d_dy[c])
    return (out, d_dx, d_dy) if gradient else out


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


def _fixed_point(correction_at, u, *, tol_px=1e-9, max_iter=50):
    """Solve ``m - Δ(m) = u`` ``(M, 2)`` for measured ``m`` by the iteration ``m <- u + Δ(m)``.

    It converges whenever the field's gradient is below 1 (any physical
    distortion field: it does not fold the image).
    """
    m = u + correction_at(u)
    for _ in range(max_iter):
        step = u + correction_at(m) - m
        m = m + step
        if len(m) == 0 or np.max(np.abs(step)) < tol_px:
            return m
    _warn_not_converged(np.sum(np.abs(step).max(1) >= tol_px), len(m), tol_px)
    return m


def _warn_not_converged(n_left, n_points, tol_px):
    logger.warning("distort_points: %d of %d points not converged to %.1e px", n_left, n_points, tol_px)


def _newton(interpolate, u, *, tol_px=1e-9, max_iter=50):
    """Solve ``m - Δ(m) = u`` for measured ``m`` ``(2, M)`` given ideal ``u`` ``(2, M)`` by Newton's method.

    ``interpolate(x, y, gradient=...)`` gives ``Δ`` (and ``dΔ/dx``,
    ``dΔ/dy``) ``(2, M)`` at points ``(x, y)`` ``(M,)``, as
    :func:`_bilinear_planes`. Every point takes the same number of steps: until
    the largest step of all is below ``tol_px``. The points are stepped a
    cache-sized part at a time (:class:`_NewtonPart`); the numbers are those of
    stepping all at once.
    """
    parts = [
        _NewtonPart(interpolate, u[:, first : first + _STEP_POINTS]) for first in range(0, u.shape[1], _STEP_POINTS)
    ]
    for _ in range(max_iter):
        if np.max([part.step() for part in parts], initial=0.0) < tol_px:
            break
    else:
        _warn_not_converged(sum(np.sum(part.step_px >= tol_px) for part in parts), u.shape[1], tol_px)
    return np.concatenate([part.result() for part in parts], axis=1) if parts else np.empty_like(u)


class _NewtonPart:
    """Points on their way to ``m - Δ(m) = u`` by Newton's method, for :func:`_newton`.

    A point whose iterate no longer changes, bit for bit, is a fixed point of
    the iteration (its next step would be computed from the same numbers) and
    is set aside: its later steps are its last one, and it is not recomputed.
    """

    def __init__(self, interpolate, u):
        self._interpolate = interpolate
        self._u = u
        self._m = u + interpolate(u[0], u[1])  # shape (2, M): x and y planes
        self._result = self._m.copy()
        self._moving = np.arange(u.shape[1])
        #: each point's latest step (its larger component), px
        self.step_px = np.zeros(u.shape[1])

    def step(self) -> float:
        """One Newton step of the points still moving; the largest latest step of all points (px)."""
        m, u = self._m, self._u
        delta, d_dx, d_dy = self._interpolate(m[0], m[1], gradient=True)
        f = m - delta
        f -= u
        # J = I - dΔ/dm, per point 2x2: [[1 - dΔx/dx, -dΔx/dy], [-dΔy/dx, 1 - dΔy/dy]]
        a, b = 1 - d_dx[0], -d_dy[0]
        c, d = -d_dx[1], 1 - d_dy[1]
        det = a * d - b * c
        step = np.empty_like(f)
        np.subtract(d * f[0], b * f[1], out=step[0])
        np.add(-c * f[0], a * f[1], out=step[1])
        np.negative(step, out=step)
        step /= det
        new = m + step
        self.step_px[self._moving] = np.maximum(np.abs(step[0]), np.abs(step[1]))
        moved = np.any(new.view(np.int64) != m.view(np.int64), axis=0)
        if not moved.all():
            self._result[:, self._moving[~moved]] = new[:, ~moved]
            self._moving, new, u = self._moving[moved], new[:, moved], u[:, moved]
        self._m, self._u = new, u
        return np.max(self.step_px, initial=0.0)

    def result(self) -> np.ndarray:
        """The iterates ``(2, M)`` px."""
        self._result[:, self._moving] = self._m
        return self._result


class _FieldOps:
    """Operations every correction field derives from its ``correction_at``."""

    def undistort_points(self, xy_measured_px: np.ndarray) -> np.ndarray:
        """Ideal pinhole coordinates ``xy - Δ(xy)`` ``(N, 2)`` px of measured points ``(N, 2)`` px."""
        xy = _as_points("xy_measured_px", xy_measured_px)
        return xy - self.correction_at(xy)

    def distort_points(self, xy_ideal_px: np.ndarray) -> np.ndarray:
        """Measured coordinates ``(N, 2)`` px whose undistortion is ``xy_ideal_px`` ``(N, 2)`` px.

        The inverse of :meth:`undistort_points`, by fixed-point iteration
        (a gridded field uses Newton's method).
        """
        return _fixed_point(self.correction_at, _as_points("xy_ideal_px", xy_ideal_px))


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

    def distort_points(self, xy_ideal_px: np.ndarray) -> np.ndarray:
        """Measured coordinates ``(N, 2)`` px whose undistortion is ``xy_ideal_px`` ``(N, 2)`` px (Newton's method)."""
        u = _as_points("xy_ideal_px", xy_ideal_px)
        return np.ascontiguousarray(_newton(self._interpolator(), np.ascontiguousarray(u.T)).T)

    def _interpolator(self):
        """``interpolate(x_px, y_px, gradient=...)``: ``Δ`` (and ``dΔ/dx``, ``dΔ/dy``) ``(2, M)`` at ``(M,)`` points.

        The node planes are laid out once, for every Newton step that interpolates.
        """
        return functools.partial(_bilinear_planes, self.x_nodes_px, self.y_nodes_px, _node_planes(self.delta_px))

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
        interpolate = self._interpolator()
        for top in range(0, height_px, rows):
            yy, xx = np.mgrid[top : min(top + rows, height_px), 0:width_px].astype(np.float64)
            src = _newton(interpolate, np.stack([xx.ravel(), yy.ravel()]))
            map_x[top : top + rows] = src[0].reshape(xx.shape)
            map_y[top : top + rows] = src[1].reshape(xx.shape)
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
