"""Analytic bead frames for the detect and centroid tests (and, until the simulator is used, the benchmark).

Each bead is a disc whose pixel coverage is integrated by supersampling, so a
pixel on the outline takes the exact fraction of its area the disc covers (to
1 / supersample^2); the frame is then blurred by a Gaussian (the spread
function of an image intensifier), given Gaussian noise and optionally
quantised to 12-bit integers.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def render_beads(
    shape: tuple[int, int],
    centres_xy: np.ndarray,
    radii_px: np.ndarray | float,
    *,
    polarity: str = "dark",
    background_dn: float = 1400.0,
    contrast: float = 0.9,
    blur_sigma_px: float = 0.0,
    noise_dn: float = 0.0,
    vignetting: float = 0.0,
    field_radius_px: float = 0.0,
    axis_ratio: float = 1.0,
    angle_rad: float = 0.0,
    supersample: int = 8,
    dtype=np.float32,
    seed: int = 0,
) -> np.ndarray:
    """Render beads as supersampled discs on an optionally vignetted field.

    Parameters
    ----------
    shape : (H, W)
    centres_xy : (N, 2) float ndarray, px
        Disc centres ``(x, y)``, pixel-centre convention (top-left pixel at 0, 0).
    radii_px : float or (N,) float ndarray, px
        Semi-major axis of each bead's outline.
    polarity : {"dark", "bright"}
        Dark: ``I = B (1 - contrast * coverage)``; bright: ``I = B (1 + contrast * coverage)``.
    background_dn : float
        Open-field level B at the centre, DN.
    contrast : float
    blur_sigma_px : float
        Gaussian blur after rendering (10-90 % edge width = 2.56 sigma).
    noise_dn : float
        Standard deviation of additive Gaussian noise, DN.
    vignetting : float
        Fractional fall-off of B at the frame's corner (quadratic in radius).
    field_radius_px : float
        Radius of a round field of view (0 outside); 0 = the whole frame.
    axis_ratio : float
        Minor over major semi-axis (1: discs).
    angle_rad : float
        Direction of the major axis, from +x toward +y.
    supersample : int
        Subsamples per pixel along each axis.
    dtype : numpy dtype
        ``np.float32`` or ``np.uint16`` (rounded and clipped to 12 bits).
    seed : int

    Returns
    -------
    (H, W) ndarray of ``dtype``, DN
    """
    height, width = shape
    coverage = _coverage(shape, centres_xy, radii_px, axis_ratio, angle_rad, supersample)
    yy, xx = np.mgrid[0:height, 0:width]
    rr2 = ((xx - (width - 1) / 2) ** 2 + (yy - (height - 1) / 2) ** 2) / (
        ((width - 1) / 2) ** 2 + ((height - 1) / 2) ** 2
    )
    field = background_dn * (1 - vignetting * rr2)
    sign = -1.0 if polarity == "dark" else 1.0
    image = field * (1 + sign * contrast * coverage)
    if field_radius_px > 0:
        image = image * (rr2 * (((width - 1) / 2) ** 2 + ((height - 1) / 2) ** 2) <= field_radius_px**2)
    if blur_sigma_px > 0:
        image = ndimage.gaussian_filter(image, blur_sigma_px, mode="nearest")
    if noise_dn > 0:
        image = image + np.random.default_rng(seed).normal(0.0, noise_dn, shape)
    if np.dtype(dtype) == np.uint16:
        return np.clip(np.round(image), 0, 4095).astype(np.uint16)
    return image.astype(dtype)


def _coverage(shape, centres_xy, radii_px, axis_ratio: float, angle_rad: float, supersample: int) -> np.ndarray:
    """(H, W) float64: the fraction of each pixel the beads' outlines cover (overlaps: the larger fraction)."""
    height, width = shape
    centres_xy = np.asarray(centres_xy, dtype=np.float64).reshape(-1, 2)
    radii = np.broadcast_to(np.asarray(radii_px, dtype=np.float64), (len(centres_xy),))
    coverage = np.zeros(shape, np.float64)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    for (cx, cy), radius in zip(centres_xy, radii):
        x0, x1 = max(int(np.floor(cx - radius)) - 1, 0), min(int(np.ceil(cx + radius)) + 2, width)
        y0, y1 = max(int(np.floor(cy - radius)) - 1, 0), min(int(np.ceil(cy + radius)) + 2, height)
        # shape (h, s, w, s): subsample positions of the patch's pixels
        sx = (np.arange(x0, x1)[:, None] + offsets[None, :]).ravel() - cx
        sy = (np.arange(y0, y1)[:, None] + offsets[None, :]).ravel() - cy
        cos, sin = np.cos(angle_rad), np.sin(angle_rad)
        # coordinates along the major and minor axes
        along = sx[None, :] * cos + sy[:, None] * sin
        across = -sx[None, :] * sin + sy[:, None] * cos
        inside = (along / radius) ** 2 + (across / (radius * axis_ratio)) ** 2 <= 1
        cover = inside.reshape(y1 - y0, supersample, x1 - x0, supersample).mean(axis=(1, 3))
        coverage[y0:y1, x0:x1] = np.maximum(coverage[y0:y1, x0:x1], cover)
    return coverage


def bead_grid(shape: tuple[int, int], pitch_px: float, margin_px: float, *, seed: int = 0) -> np.ndarray:
    """Centres on a square grid with random sub-pixel offsets; (N, 2) float64, px."""
    rng = np.random.default_rng(seed)
    xs = np.arange(margin_px, shape[1] - margin_px, pitch_px)
    ys = np.arange(margin_px, shape[0] - margin_px, pitch_px)
    grid = np.array([(x, y) for y in ys for x in xs], dtype=np.float64)
    return grid + rng.uniform(-0.5, 0.5, grid.shape)
