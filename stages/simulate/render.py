"""Image formation: Beer-Lambert transmission, heel effect, blur, veiling glare, vignetting, field of view, noise."""

from __future__ import annotations

import numpy as np
from fluorocal.stages.geometry import check_points
from fluorocal.stages.simulate.absorption import background_line_integral, feature_line_integrals
from fluorocal.stages.simulate.acquisition import SystemTruth
from fluorocal.stages.simulate.params import SimulateParams
from fluorocal.stages.simulate.raster import SystemRaster, system_raster


def _blur_sigma_px(params: SimulateParams) -> float:
    """Gaussian sigma (px) of focal-spot penumbra and intensifier blur.

    The penumbra is the cube's at the isocentre's magnification, the plate's at its own (near 1: none).
    """
    magnification = params.grid_magnification if params.phantom == "grid" else params.magnification
    focal = params.focal_spot_mm * (magnification - 1.0) / 2.3548
    return float(np.hypot(focal, params.intensifier_blur_mm) / params.pixel_pitch_mm)


def _correlated(noise: np.ndarray, sigma_px: float) -> np.ndarray:
    """White unit-variance noise ``(H, W)`` float32 smoothed by a Gaussian of ``sigma_px``, still of unit variance."""
    import cv2

    half = int(np.ceil(4 * sigma_px))
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma_px) ** 2)
    kernel = (kernel / kernel.sum()).astype(np.float32)
    smoothed = cv2.sepFilter2D(noise, -1, kernel, kernel, borderType=cv2.BORDER_REFLECT)
    return smoothed / np.float32(np.sum(kernel.astype(np.float64) ** 2))


def _form_image(
    params: SimulateParams, raster: SystemRaster, transmission: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Detector chain from transmission ``(H, W)`` to quantised DN ``(H, W) uint16``."""
    import cv2

    size = params.image_size_px
    y = (np.arange(size, dtype=np.float32) - (size - 1) / 2.0) / np.float32(params.fov_radius_px)
    heel = (1.0 + params.heel * y)[:, None]
    primary = (transmission * heel * raster.fov).astype(np.float32)
    sigma = _blur_sigma_px(params)
    if sigma > 0.05:
        primary = cv2.GaussianBlur(primary, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    if params.glare_fraction > 0:
        # veiling glare: a wide Gaussian, computed at 1/8 resolution (it has no fine detail)
        f = 8 if size >= 64 else 1
        low = cv2.resize(primary, (size // f, size // f), interpolation=cv2.INTER_AREA) if f > 1 else primary
        low = cv2.GaussianBlur(
            low, (0, 0), params.glare_sigma_mm / params.pixel_pitch_mm / f, borderType=cv2.BORDER_CONSTANT
        )
        glare = cv2.resize(low, (size, size), interpolation=cv2.INTER_LINEAR) if f > 1 else low
        primary = (1.0 - params.glare_fraction) * primary + params.glare_fraction * glare
    exposure = params.open_field_dn * (params.grid_exposure_gain if params.phantom == "grid" else 1.0)
    signal = exposure * primary * (1.0 - params.vignetting * raster.radial2)
    image = signal + params.dark_dn
    if params.noise_scale > 0:
        # quantum noise by its normal approximation (>= ~500 quanta per pixel inside the field)
        std = params.noise_scale * np.sqrt(
            params.gain_dn_per_quantum * np.maximum(signal, 0) + params.electronic_noise_dn**2
        )
        noise = rng.standard_normal(image.shape, dtype=np.float32)
        if params.noise_sigma_px > 0:
            noise = _correlated(noise, params.noise_sigma_px)
        image = image + std * noise
    return np.clip(np.rint(image), 0, 2**params.bit_depth - 1).astype(np.uint16)


def render_frame(
    params: SimulateParams,
    system: SystemTruth,
    q: np.ndarray,
    source_mm: np.ndarray,
    xyz_mm: np.ndarray,
    diameter_mm: np.ndarray,
    *,
    rng: np.random.Generator,
    raster: SystemRaster | None = None,
) -> np.ndarray:
    """Render one radiograph of beads (or plate holes) at true positions ``xyz_mm``.

    Parameters
    ----------
    params : SimulateParams
    system : SystemTruth
        IOP and distortion of the imaging system.
    q, source_mm : pose ``(q, T)`` of the exposure (object -> camera).
    xyz_mm : (N, 3) float64 ndarray, mm
    diameter_mm : (N,) float64 ndarray, mm
    rng : numpy Generator
        Noise source.
    raster : optional
        The system's cached pixel geometry (computed if None).

    Returns
    -------
    image : (H, W) uint16 ndarray, DN
        Values in ``0 .. 2**bit_depth - 1``.
    """
    xyz_mm = check_points("xyz_mm", xyz_mm, 3)
    raster = raster or system_raster(params, system)
    size = params.image_size_px
    background = background_line_integral(params, raster.rays, q, source_mm).astype(np.float64)
    line, edge_idx, edge_line = feature_line_integrals(params, raster, system, q, source_mm, xyz_mm, diameter_mm)
    transmission = np.exp(-(background + line))
    transmission[edge_idx] = np.mean(np.exp(-(background[edge_idx, None] + edge_line)), axis=1)
    return _form_image(params, raster, transmission.reshape(size, size), rng)
