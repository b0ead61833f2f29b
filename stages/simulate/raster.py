"""Per-system pixel geometry shared by all of a system's frames: ideal coordinates, rays, field of view."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.simulate.acquisition import SystemTruth
from fluorocal.stages.simulate.distortion import ideal_pixel_map
from fluorocal.stages.simulate.params import SimulateParams


@dataclass(frozen=True, eq=False)
class SystemRaster:
    """Per-system pixel geometry, shared by all of that system's frames.

    Attributes
    ----------
    ideal_xy : (H, W, 2) float64 ndarray, px
        Ideal (undistorted) coordinates of every output pixel centre.
    rays : (3, H*W) float32 ndarray
        Unit ray directions of the pixel centres in the camera frame (components first, for speed).
    fov : (H, W) float32 ndarray
        Intensifier input disc with a one-pixel linear rim (1 inside, 0 outside).
    radial2 : (H, W) float32 ndarray
        ``(r / fov_radius)²`` about the image centre.
    """

    ideal_xy: np.ndarray
    rays: np.ndarray
    fov: np.ndarray
    radial2: np.ndarray


def _pixel_rays(ideal_xy: np.ndarray, iop: np.ndarray) -> np.ndarray:
    """Unit camera-frame rays ``(..., 3)`` through ideal image points ``(..., 2)``."""
    xp, yp, c = iop
    d = np.stack([(ideal_xy[..., 0] - xp) / c, (ideal_xy[..., 1] - yp) / c, np.ones(ideal_xy.shape[:-1])], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def system_raster(params: SimulateParams, system: SystemTruth) -> SystemRaster:
    """The pixel geometry of ``system`` (computed once per system: the exact inverse distortion of every pixel)."""
    size = params.image_size_px
    ideal = ideal_pixel_map(system.distortion, size)
    axis = np.arange(size, dtype=np.float64) - (size - 1) / 2.0
    r = np.hypot(axis[None, :], axis[:, None])
    fov = np.clip(params.fov_radius_px - r + 0.5, 0.0, 1.0).astype(np.float32)
    rays = np.ascontiguousarray(_pixel_rays(ideal, system.iop_px).reshape(-1, 3).T, dtype=np.float32)
    return SystemRaster(ideal, rays, fov, ((r / params.fov_radius_px) ** 2).astype(np.float32))


def local_jacobian(ideal_xy: np.ndarray, flat_idx: np.ndarray) -> np.ndarray:
    """``(M, 2, 2)`` derivative of the ideal map at pixels ``flat_idx`` (central differences)."""
    h, w = ideal_xy.shape[:2]
    y, x = np.divmod(flat_idx, w)
    cols = []
    for dx, dy in ((1, 0), (0, 1)):
        x1, x0 = np.minimum(x + dx, w - 1), np.maximum(x - dx, 0)
        y1, y0 = np.minimum(y + dy, h - 1), np.maximum(y - dy, 0)
        span = (x1 - x0) + (y1 - y0)
        cols.append((ideal_xy[y1, x1] - ideal_xy[y0, x0]) / span[:, None])
    return np.stack(cols, axis=-1)
