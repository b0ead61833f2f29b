"""What the plate calibration's datum needs of homographies: point normalisation and the eight homography modes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Normaliser:
    """``normalised = (x - centre) / scale`` for a set of 2-D points (RMS distance 1 from the centre)."""

    centre: np.ndarray
    scale: float

    @classmethod
    def of(cls, points: np.ndarray) -> "Normaliser":
        centre = points.mean(axis=0)
        return cls(centre, float(np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1)))) or 1.0)

    def forward(self, points: np.ndarray) -> np.ndarray:
        return (points - self.centre) / self.scale


def homography_modes(points_n: np.ndarray) -> np.ndarray:
    """The eight displacement fields ``(N, 2, 8)`` of a small homography at normalised points.

    Translation (2), the linear part (4) and the two perspective terms ``(x², xy)``, ``(xy, y²)``: what a
    change of a homography does to first order.

    Examples
    --------
    >>> homography_modes(np.array([[2.0, 3.0]]))[0, :, 6:]
    array([[4., 6.],
           [6., 9.]])
    """
    x, y = points_n[:, 0], points_n[:, 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    cols = [(one, zero), (zero, one), (x, zero), (y, zero), (zero, x), (zero, y), (x * x, x * y), (x * y, y * y)]
    return np.stack([np.stack(c, 1) for c in cols], 2)


__all__ = ["Normaliser", "homography_modes"]
