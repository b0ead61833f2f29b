"""Ellipse fits of many bead outlines at once: direct conic fit, robust Gauss-Newton, arc jackknife covariance.

The fitting steps of :mod:`stages.centroid` (its module docstring gives the
method and its references). Every bead is fitted together with every other:
arrays of points tagged by bead, summed per bead by sparse products.
"""

from __future__ import annotations

import numpy as np


def ellipse_axes(quadratic: np.ndarray):
    """Semi-axes and major-axis angle of ``(p - c)^T Q (p - c) = 1`` with ``Q = [[A, B], [B, C]]``.

    Parameters
    ----------
    quadratic : (N, 3) float64 ndarray
        ``(A, B, C)``, px^-2.

    Returns
    -------
    major_px, minor_px, angle_rad : (N,) float64 ndarray
    """
    a, b, c = quadratic.T
    half_trace, root = (a + c) / 2, np.sqrt(((a - c) / 2) ** 2 + b**2)
    with np.errstate(invalid="ignore", divide="ignore"):
        major = 1 / np.sqrt(half_trace - root)  # the smaller eigenvalue of Q belongs to the major axis
        minor = 1 / np.sqrt(half_trace + root)
    # eigenvector of the smaller eigenvalue: angle 0.5 atan2(2B, A - C) is the larger one's direction
    angle = 0.5 * np.arctan2(2 * b, a - c) + np.pi / 2
    angle = (angle + np.pi / 2) % np.pi - np.pi / 2
    return major, minor, angle


def _solve(matrices: np.ndarray, rhs: np.ndarray, damping: float = 1e-10) -> np.ndarray:
    """Solve stacks of small symmetric systems ``(..., k, k) x = (..., k)``, Marquardt-damped; (..., k).

    ``damping`` times each diagonal is added (plus a tiny absolute ridge), so
    a bead without points gives a zero step instead of an exception;
    singular stacks fall back to the pseudo-inverse.
    """
    diagonal = np.einsum("...ii->...i", matrices)
    damped = matrices + (damping * diagonal + 1e-300)[..., None] * np.eye(matrices.shape[-1])
    try:
        return np.linalg.solve(damped, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return (np.linalg.pinv(damped) @ rhs[..., None])[..., 0]


def _group_sum(owner: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum ``values`` (P, ...) over the points of each of ``n`` groups; (n, ...).

    As a sparse product ``S @ values`` with ``S[owner[p], p] = 1``: several
    times faster than ``np.add.reduceat``, and the points need no sorting.
    """
    from scipy import sparse

    n_points = len(owner)
    # 32-bit indices, as scipy keeps them (64-bit ones are checked and converted on every call)
    summer = sparse.csc_matrix(
        (np.ones(n_points), owner.astype(np.int32), np.arange(n_points + 1, dtype=np.int32)), shape=(n, n_points)
    )
    return np.asarray(summer @ values.reshape(n_points, -1)).reshape((n,) + values.shape[1:])


def _group_normal(owner: np.ndarray, left: np.ndarray, right: np.ndarray, n: int) -> np.ndarray:
    """Per-group ``sum_p left_p right_p^T`` of (P, k) rows; (n, k, k).

    One sparse product: ``left`` spread into a ``(n k, P)`` matrix whose
    column ``p`` holds ``left_p`` in the rows of group ``owner[p]``, times
    ``right``. No (P, k, k) array of products is formed.
    """
    from scipy import sparse

    n_points, k = left.shape
    # 32-bit indices, as scipy keeps them (64-bit ones are checked and converted on every call)
    rows = (owner.astype(np.int32)[:, None] * np.int32(k) + np.arange(k, dtype=np.int32)).ravel()
    columns = np.arange(0, n_points * k + 1, k, dtype=np.int32)
    spread = sparse.csc_matrix((left.ravel(), rows, columns), shape=(n * k, n_points))
    return np.asarray(spread @ right).reshape(n, k, right.shape[1])


def _algebraic_fit(points_xy, owner, centre0, n):
    """Direct linear fit of ``A u^2 + 2B uv + C v^2 + D u + E v = 1`` (u, v relative to ``centre0``).

    Returns
    -------
    (n, 5) float64 ndarray
        ``(cx, cy, A, B, C)``: centre and quadratic form; NaN where singular.
    """
    u = points_xy - centre0[owner]
    # shape (P, 5): one row of the design matrix per point
    design = np.column_stack([u[:, 0] ** 2, 2 * u[:, 0] * u[:, 1], u[:, 1] ** 2, u[:, 0], u[:, 1]])
    normal = _group_normal(owner, design, design, n)
    rhs = _group_sum(owner, design, n)
    solvable = np.abs(np.linalg.det(normal)) > 1e-300
    coef = np.full((n, 5), np.nan)
    if solvable.any():
        coef[solvable] = _solve(normal[solvable], rhs[solvable])
    m = np.stack([coef[:, [0, 1]], coef[:, [1, 2]]], axis=1)  # shape (n, 2, 2)
    g = coef[:, 3:]
    out = np.full((n, 5), np.nan)
    good = solvable & np.all(np.isfinite(coef), axis=1)
    good[good] = np.linalg.det(m[good]) > 0
    if good.any():
        # x^T M x + g^T x = 1  <=>  (x - c)^T M (x - c) = 1 + c^T M c  with  c = -M^-1 g / 2
        c = -0.5 * np.linalg.solve(m[good], g[good][:, :, None])[:, :, 0]
        scale = 1 + np.einsum("ni,nij,nj->n", c, m[good], c)
        q = m[good] / scale[:, None, None]
        out[good] = np.column_stack([centre0[good] + c, q[:, 0, 0], q[:, 0, 1], q[:, 1, 1]])
    return out


def _radial_residuals(points_xy, owner, fit, with_jacobian: bool):
    """Radial distance of each point from its bead's ellipse and its derivative.

    ``r = |u| (1 - s^(-1/2))``, ``u = p - c``, ``s = u^T Q u``: the distance from
    the point to where the ray from the centre through it crosses the ellipse.

    Returns
    -------
    r : (P,) float64 ndarray, px
    jacobian : (P, 5) float64 ndarray
        ``dr / d(cx, cy, A, B, C)`` (only if ``with_jacobian``).
    """
    # one contiguous gather per parameter: (cx, cy, A, B, C) of each point's bead
    cx, cy, a, b, c = (column[owner] for column in fit.T)
    ux, uy = points_xy[:, 0] - cx, points_xy[:, 1] - cy
    s = np.maximum(a * ux * ux + 2 * b * ux * uy + c * uy * uy, 1e-12)
    norm = np.maximum(np.sqrt(ux * ux + uy * uy), 1e-12)  # np.hypot is several times slower
    inv_sqrt_s = 1 / np.sqrt(s)
    shrink = 1 - inv_sqrt_s
    r = norm * shrink
    if not with_jacobian:
        return r, None
    # dr = d|u| (1 - s^-1/2) + |u| s^-3/2 ds / 2
    half_ds_factor = 0.5 * norm * inv_sqrt_s / s
    radial_factor = shrink / norm
    ux_scaled = ux * half_ds_factor
    # shape (P, 5): one row per point
    jac = np.column_stack(
        [
            -ux * radial_factor - 2 * (a * ux + b * uy) * half_ds_factor,
            -uy * radial_factor - 2 * (b * ux + c * uy) * half_ds_factor,
            ux * ux_scaled,
            2 * uy * ux_scaled,
            uy * uy * half_ds_factor,
        ]
    )
    return r, jac


def _arc_groups(points_xy, owner, centre0, n_arcs: int) -> np.ndarray:
    """Index ``bead * n_arcs + arc`` of each point; (P,) int64.

    The arcs cut each outline into ``n_arcs`` equal angles about ``centre0``.
    """
    angle = np.arctan2(points_xy[:, 1] - centre0[owner, 1], points_xy[:, 0] - centre0[owner, 0])
    arc = np.minimum(((angle + np.pi) * (n_arcs / (2 * np.pi))).astype(np.int64), n_arcs - 1)
    return owner * n_arcs + arc


def fit_ellipses(
    points_xy, owner, centre0, radius0, *, n_arcs: int, n_rounds: int, n_iterations: int, outlier_sigma: float
):
    """Robust Gauss-Newton ellipse fits of all beads at once.

    Parameters
    ----------
    points_xy : (P, 2) float64 ndarray, px
        Edge points.
    owner : (P,) int64 ndarray
        Row of ``centre0`` each point belongs to.
    centre0 : (n, 2) float64 ndarray, px
    radius0 : (n,) float64 ndarray, px
    n_arcs : int
        Arcs of each outline for the jackknife covariance.
    n_rounds, n_iterations : int
        Robust rounds (outliers re-identified), and Gauss-Newton steps in each.
    outlier_sigma : float
        Points beyond this many robust standard deviations are dropped.

    Returns
    -------
    fit : (n, 5) float64 ndarray
        ``(cx, cy, A, B, C)``.
    rmse : (n,) float64 ndarray, px
    n_inliers : (n,) int64 ndarray
    covariance : (n, 2, 2) float64 ndarray, px^2
        Of each centre.
    """
    n = len(centre0)
    fit = _algebraic_fit(points_xy, owner, centre0, n)
    # a fit that failed starts from the candidate's circle
    circle = np.column_stack([centre0, 1 / radius0**2, np.zeros(n), 1 / radius0**2])
    fit = np.where(np.all(np.isfinite(fit), axis=1)[:, None], fit, circle)
    arc = _arc_groups(points_xy, owner, centre0, n_arcs)

    weights = np.ones(len(owner))
    for _ in range(n_rounds):
        r, jac = _radial_residuals(points_xy, owner, fit, True)
        # scale per bead: 1.2533 mean |r| is sigma for Gaussian residuals, taken over the previous round's
        # inliers (all points at first, which only makes the first trimming lenient); a floor keeps
        # noise-free synthetic beads from rejecting good points
        mean_abs = np.bincount(owner, weights * np.abs(r), n) / np.maximum(np.bincount(owner, weights, n), 1)
        weights = (np.abs(r) <= outlier_sigma * np.maximum(1.2533 * mean_abs, 0.02)[owner]).astype(np.float64)
        for iteration in range(n_iterations):
            if iteration:
                r, jac = _radial_residuals(points_xy, owner, fit, True)
            wj = jac * weights[:, None]
            # the last step's normal equations, summed per arc, also give the jackknife its pieces
            # shape (n, n_arcs, 5, 5) and (n, n_arcs, 5)
            hessian_arc = _group_normal(arc, wj, jac, n * n_arcs).reshape(n, n_arcs, 5, 5)
            gradient_arc = _group_sum(arc, wj * r[:, None], n * n_arcs).reshape(n, n_arcs, 5)
            step = _solve(hessian_arc.sum(axis=1), -gradient_arc.sum(axis=1), damping=1e-6)
            fit = fit + np.nan_to_num(step)
    r, _ = _radial_residuals(points_xy, owner, fit, False)
    n_inliers = np.bincount(owner, weights, n).round().astype(np.int64)
    rmse = np.sqrt(np.bincount(owner, weights * r * r, n) / np.maximum(n_inliers, 1))
    return fit, rmse, n_inliers, _arc_jackknife_covariance(hessian_arc, gradient_arc)


def _arc_jackknife_covariance(hessian_arc: np.ndarray, gradient_arc: np.ndarray) -> np.ndarray:
    """Covariance of each centre by a delete-one-arc jackknife; (n, 2, 2) px^2.

    Parameters
    ----------
    hessian_arc : (n, n_arcs, 5, 5) float64 ndarray
        Gauss-Newton normal matrix ``J_a^T W J_a`` of each arc of each outline.
    gradient_arc : (n, n_arcs, 5) float64 ndarray
        ``J_a^T W r_a``.

    Notes
    -----
    Dropping arc ``a`` moves the solution by ``(H - H_a)^-1 g_a`` (one
    Gauss-Newton step from the solution, where the total gradient vanishes;
    the pieces come from the last step, a small step from it, so their mean is
    subtracted). Unlike ``s^2 H^-1`` this keeps the correlation of neighbouring
    edge points (they share smoothed pixels, and real intensifier noise is
    itself correlated), as long as it is shorter than an arc.
    """
    n_arcs = hessian_arc.shape[1]
    gradient_arc = gradient_arc - gradient_arc.mean(axis=1, keepdims=True)
    hessian = hessian_arc.sum(axis=1, keepdims=True)
    shift = _solve(hessian - hessian_arc, gradient_arc)[..., :2]
    shift -= shift.mean(axis=1, keepdims=True)
    return (n_arcs - 1) / n_arcs * np.einsum("nki,nkj->nij", shift, shift)
