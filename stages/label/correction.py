"""The low-order 2D polynomial image correction fitted while labelling.

The image-intensifier distortion leaves residuals of 10-20 px at the field edge that a pinhole cannot
absorb; the labelling predicts bead positions through the pinhole plus this correction.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Correction:
    """``measured ≈ ideal + Σ coef_k · u^a v^b`` with ``(u, v) = (ideal - centre) / scale``."""

    centre: np.ndarray
    scale: float
    degree: int = 0
    coef: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def basis(self, xy: np.ndarray) -> np.ndarray:
        uv = (xy - self.centre) / self.scale
        # shape (degree + 1, N) each: the powers of u and of v
        up = np.ones((self.degree + 1, len(uv)))
        vp = np.ones((self.degree + 1, len(uv)))
        for d in range(1, self.degree + 1):
            up[d] = up[d - 1] * uv[:, 0]
            vp[d] = vp[d - 1] * uv[:, 1]
        i, k = _exponents(self.degree)
        return (up[i] * vp[k]).T

    def distort_points(self, xy: np.ndarray) -> np.ndarray:
        """Predicted measured positions of ideal points ``xy``."""
        if not len(self.coef) or not len(xy):
            return xy
        return xy + self.basis(xy) @ self.coef

    def undistort_points(self, measured: np.ndarray, ideal_guess: np.ndarray) -> np.ndarray:
        """Approximately ideal positions of ``measured`` points, given nearby ideal predictions."""
        if not len(self.coef) or not len(measured):
            return measured
        return measured - self.basis(ideal_guess) @ self.coef


@functools.lru_cache(maxsize=None)
def _exponents(degree: int) -> np.ndarray:
    """``(2, n_terms)``: the powers of u and of v of each term, u^(d - k) v^k, degree d by degree (read-only)."""
    out = np.array([(d - k, k) for d in range(degree + 1) for k in range(d + 1)]).T
    out.flags.writeable = False
    return out


def n_terms(degree: int) -> int:
    return (degree + 1) * (degree + 2) // 2


def max_degree(n_points: int) -> int:
    """Highest polynomial degree fitted to ``n_points`` pairs: at least 3 pairs per coefficient."""
    degree = 0
    while degree < 5 and n_points >= 3 * n_terms(degree + 1):
        degree += 1
    return degree


def fit_correction(
    ideal: np.ndarray, measured: np.ndarray, degree: int, centre: np.ndarray, scale: float
) -> Correction:
    """Least-squares polynomial correction, refitted once without gross outliers."""
    corr = Correction(centre, scale, degree)
    A = corr.basis(ideal)
    d = measured - ideal
    keep = np.ones(len(d), dtype=bool)
    coef = np.zeros((A.shape[1], 2))
    for _ in range(2):
        coef = np.linalg.lstsq(A[keep], d[keep], rcond=None)[0]
        r = np.linalg.norm(d - A @ coef, axis=1)
        keep = r <= max(3.0 * 1.4826 * np.median(r), 0.5)
        if keep.sum() < A.shape[1] + 2:
            break
    return Correction(centre, scale, degree, coef)
