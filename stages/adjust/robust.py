"""The 2-D Student-t likelihood of whitened residuals: weights, cost, and the ML scale and degrees of freedom.

Shared by the bundle adjustment (:mod:`stages.adjust.solver`) and the
grid-plate homographies (:mod:`stages.adjust.homography`). With ``s`` the
squared Mahalanobis norm of an observation's residual, ``σ²`` the variance
factor and ``ν`` the degrees of freedom, the negative log-likelihood per
observation is, up to constants, ``ρ(s) = (ν+2)/2 log(1 + s/(ν σ²)) + log σ²``
and the IRLS weight ``w = (ν + 2) / (ν + s/σ²)``.
"""

from __future__ import annotations

import math

import numpy as np


def t_weights(s: np.ndarray, nu: float, scale2) -> np.ndarray:
    """IRLS weights ``(ν + 2) / (ν + s/σ²)`` of a 2-D Student-t; 1 for ``ν = inf``.

    ``scale2`` is a scalar or an array like ``s`` (one σ² per observation).

    Examples
    --------
    >>> t_weights(np.array([0.0, 4.0]), 4.0, 1.0)
    array([1.5 , 0.75])
    """
    if math.isinf(nu):
        return np.ones_like(s)
    return (nu + 2.0) / (nu + s / scale2)


def t_rho(s: np.ndarray, nu: float, scale2) -> np.ndarray:
    """Per observation ``(ν+2)/2 log(1 + s/(ν σ²))`` (``s/(2σ²)`` for ``ν = inf``), without the ``log σ²`` term."""
    if math.isinf(nu):
        return 0.5 * s / scale2
    return 0.5 * (nu + 2.0) * np.log1p(s / (nu * scale2))


def t_cost(s: np.ndarray, nu: float, scale2: float) -> float:
    """Negative log-likelihood of squared Mahalanobis norms ``s`` (constants dropped).

    ``Σ (ν+2)/2 log(1 + s/(ν σ²)) + N log σ²``; as ``ν -> inf`` this tends to the
    Gaussian ``Σ s/(2σ²) + N log σ²``. For a 2-D t the normalising constant does
    not depend on ν, so this is also the objective for ν.
    """
    return float(t_rho(s, nu, scale2).sum() + len(s) * math.log(scale2))


def ml_scale(s: np.ndarray, nu: float, scale2: float, *, iterations: int = 100, rtol: float = 1e-10) -> float:
    """Maximum-likelihood variance factor σ² of a 2-D t for fixed residuals (EM fixed point ``σ² = mean(w s) / 2``)."""
    if len(s) == 0:
        return scale2
    floor = 1e-12 * max(float(np.mean(s)), 1e-300)
    for _ in range(iterations):
        new = max(float(np.mean(t_weights(s, nu, scale2) * s)) / 2.0, floor, 1e-300)
        if abs(new - scale2) <= rtol * new:
            return new
        scale2 = new
    return scale2


def ml_scales(s: np.ndarray, counts: np.ndarray, nu: float, scale2: np.ndarray, *, iterations: int = 100) -> np.ndarray:
    """Per-group ML variance factors ``(G,)``: :func:`ml_scale`'s fixed point in every group at once.

    ``s`` ``(N,)`` is sorted by group and ``counts`` ``(G,)`` gives the group
    sizes; iterates until every group has converged.
    """
    seg = np.repeat(np.arange(len(counts)), counts)
    for _ in range(iterations):
        w = t_weights(s, nu, np.repeat(scale2, counts))
        new = np.maximum(np.bincount(seg, w * s, len(counts)) / (2.0 * counts), 1e-300)
        if np.all(np.abs(new - scale2) <= 1e-10 * new):
            return new
        scale2 = new
    return scale2


def ml_nu(s: np.ndarray, scale2: float, bounds: tuple[float, float]) -> float:
    """Maximum-likelihood degrees of freedom of a 2-D t for fixed residuals and scale."""
    from scipy.optimize import minimize_scalar

    res = minimize_scalar(
        lambda log_nu: t_cost(s, math.exp(log_nu), scale2),
        bounds=(math.log(bounds[0]), math.log(bounds[1])),
        method="bounded",
        options={"xatol": 1e-3},
    )
    return float(math.exp(res.x))


def ml_hyper(
    s: np.ndarray, nu: float, scale2: float, *, estimate_scale: bool, estimate_nu: bool, nu_bounds: tuple
) -> tuple[float, float]:
    """Coordinate-descent update of (ν, σ²) for fixed residuals; never increases the cost."""
    for _ in range(3 if estimate_nu else 1):
        if estimate_scale:
            scale2 = ml_scale(s, nu, scale2)
        if estimate_nu:
            nu = ml_nu(s, scale2, nu_bounds)
    return nu, scale2
