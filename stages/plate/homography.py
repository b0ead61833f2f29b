"""Plate-to-image homographies in normalised coordinates: projection and its derivatives.

A frame maps the plate's normalised coordinates ``P = (X, Y)`` to normalised image coordinates
``q = ((g0 X + g1 Y + g2) / d, (g3 X + g4 Y + g5) / d)``, ``d = g6 X + g7 Y + 1``. Plate and image
are centred and scaled once for the whole problem (:class:`Normaliser`), so the eight ``g`` are of
order one and the normal equations well conditioned (Hartley's conditioning).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.errors import EstimationError


@dataclass(frozen=True)
class Normaliser:
    """``normalised = (x - centre) / scale`` for a set of 2-D points."""

    centre: np.ndarray
    scale: float

    @classmethod
    def of(cls, points: np.ndarray) -> "Normaliser":
        centre = points.mean(axis=0)
        return cls(centre, float(np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1)))) or 1.0)

    def forward(self, points: np.ndarray) -> np.ndarray:
        return (points - self.centre) / self.scale

    def inverse(self, points: np.ndarray) -> np.ndarray:
        return points * self.scale + self.centre


def initial_homographies(plate_n: np.ndarray, image_n: np.ndarray, frame: np.ndarray, n_frames: int) -> np.ndarray:
    """Per-frame start ``(F, 8)`` by OpenCV's least-squares homography of normalised plate to image points."""
    import cv2

    g = np.zeros((n_frames, 8))
    for f in range(n_frames):
        sel = frame == f
        H, _ = cv2.findHomography(plate_n[sel], image_n[sel], 0)
        if H is None or not np.all(np.isfinite(H)) or abs(H[2, 2]) < 1e-12:
            raise EstimationError(f"frame {f}: no homography fits its {int(sel.sum())} holes (degenerate layout)")
        g[f] = (H / H[2, 2]).ravel()[:8]
    return g


def project(g: np.ndarray, plate_n: np.ndarray) -> np.ndarray:
    """Normalised image points ``(N, 2)`` of normalised plate points ``(N, 2)`` under per-point ``g`` ``(N, 8)``."""
    X, Y = plate_n[:, 0], plate_n[:, 1]
    d = g[:, 6] * X + g[:, 7] * Y + 1.0
    return np.column_stack([(g[:, 0] * X + g[:, 1] * Y + g[:, 2]) / d, (g[:, 3] * X + g[:, 4] * Y + g[:, 5]) / d])


def derivatives(g: np.ndarray, plate_n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projection ``q`` ``(N, 2)`` with ``dq/dg`` ``(N, 2, 8)`` and ``dq/dP`` ``(N, 2, 2)``."""
    X, Y = plate_n[:, 0], plate_n[:, 1]
    d = g[:, 6] * X + g[:, 7] * Y + 1.0
    q = project(g, plate_n)
    x, y = q[:, 0], q[:, 1]
    zero = np.zeros_like(X)
    one = np.ones_like(X)
    dq_dg = (
        np.stack(
            [
                np.stack([X, Y, one, zero, zero, zero, -x * X, -x * Y], 1),
                np.stack([zero, zero, zero, X, Y, one, -y * X, -y * Y], 1),
            ],
            1,
        )
        / d[:, None, None]
    )
    dq_dp = (
        np.stack(
            [
                np.stack([g[:, 0] - x * g[:, 6], g[:, 1] - x * g[:, 7]], 1),
                np.stack([g[:, 3] - y * g[:, 6], g[:, 4] - y * g[:, 7]], 1),
            ],
            1,
        )
        / d[:, None, None]
    )
    return q, dq_dg, dq_dp


def homography_modes(points_n: np.ndarray) -> np.ndarray:
    """The eight displacement fields ``(N, 2, 8)`` of a small homography at normalised points.

    Translation (2), the linear part (4) and the two perspective terms ``(x², xy)``, ``(xy, y²)``: what a
    change of the per-frame homographies reproduces to first order.
    """
    x, y = points_n[:, 0], points_n[:, 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    cols = [
        (one, zero),
        (zero, one),
        (x, zero),
        (y, zero),
        (zero, x),
        (zero, y),
        (x * x, x * y),
        (x * y, y * y),
    ]
    return np.stack([np.stack(c, 1) for c in cols], 2)


__all__ = ["Normaliser", "derivatives", "homography_modes", "initial_homographies", "project"]
