"""Sub-pixel edge points of beads: derivative-of-Gaussian gradients, non-maximum suppression, log-parabola peaks.

The edge-point step of :mod:`stages.centroid` (its module docstring gives the
method and its reference).
"""

from __future__ import annotations

import numpy as np
from fluorocal.stages._image import background, odd_size


def _gaussian_gradient(image: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives along x and y of the image smoothed by a Gaussian of ``sigma_px``; two (H, W) float32, DN/px."""
    import cv2

    half = int(np.ceil(3 * sigma_px))  # the Gaussian's tails beyond 3 sigma hold 0.3 % of it
    t = np.arange(-half, half + 1, dtype=np.float64)
    g = np.exp(-0.5 * (t / sigma_px) ** 2)
    g /= g.sum()
    # normalised so that a ramp of unit slope gives 1 (cv2 correlates: sum_t dg(t) f(x + t))
    dg = t * g
    dg /= np.sum(t * dg)
    gx = cv2.sepFilter2D(
        image, cv2.CV_32F, dg.astype(np.float32), g.astype(np.float32), borderType=cv2.BORDER_REPLICATE
    )
    gy = cv2.sepFilter2D(
        image, cv2.CV_32F, g.astype(np.float32), dg.astype(np.float32), borderType=cv2.BORDER_REPLICATE
    )
    return gx, gy


def _axis_maxima(magnitude: np.ndarray, owner_image: np.ndarray) -> np.ndarray:
    """``(x, y)`` of the pixels with an owner that are at least both neighbours along x or along y; (K, 2) int64.

    ``owner_image`` is 0 on the border.
    """
    import cv2

    inner, m = magnitude[1:-1, 1:-1], magnitude
    along_x = cv2.compare(inner, cv2.max(m[1:-1, :-2], m[1:-1, 2:]), cv2.CMP_GE)
    along_y = cv2.compare(inner, cv2.max(m[:-2, 1:-1], m[2:, 1:-1]), cv2.CMP_GE)
    owned = cv2.compare(owner_image[1:-1, 1:-1], 0, cv2.CMP_GT)
    found = cv2.findNonZero(cv2.bitwise_and(cv2.bitwise_or(along_x, along_y), owned))
    return found.reshape(-1, 2).astype(np.int64) + 1 if found is not None else np.empty((0, 2), np.int64)


def _window(shape, centre0, r_out, sigma_px: float):
    """The part of a frame of ``shape`` that the edge search looks at: its slices, and its corner ``(x, y)``, px.

    Every search disc (drawn out to ``ceil(r_out) + 1`` px about the rounded centre), its neighbours for the
    non-maximum suppression and the reach of the filter (``ceil(3 sigma_px)``), so that the gradients there
    are those of the whole frame.
    """
    reach = np.ceil(r_out.max()) + 4 + np.ceil(3 * sigma_px)
    # an even corner: centres shifted by it round alike (np.round takes halves to the even neighbour)
    corner = 2 * np.maximum(np.floor((centre0.min(axis=0) - reach) / 2), 0).astype(int)
    end = np.minimum(np.ceil(centre0.max(axis=0) + reach) + 1, shape[::-1]).astype(int)
    return (slice(corner[1], end[1]), slice(corner[0], end[0])), corner.astype(np.float64)


def _annulus_owners(shape, centre0, r_out) -> np.ndarray:
    """Image of each bead's search disc, labelled bead + 1 (0 elsewhere and on the frame's border).

    Returns an (H, W) uint16 (int32 for 65535 beads or more) ndarray.
    Smaller beads are drawn last, so they keep the pixels where annuli overlap.
    """
    import cv2

    # 16-bit labels where they suffice: half the memory to fill and compare
    owner_image = np.zeros(shape, np.uint16 if len(centre0) < 2**16 - 1 else np.int32)
    centre_int = np.round(centre0).astype(int).tolist()
    outer = (np.ceil(r_out) + 1).astype(int).tolist()
    # filled discs are fast to draw (thick circles are polygons); a bead's inside is left to the radius test
    for i in np.argsort(-r_out).tolist():
        cv2.circle(owner_image, centre_int[i], outer[i], i + 1, -1)
    owner_image[[0, -1], :] = 0
    owner_image[:, [0, -1]] = 0
    return owner_image


def _log_parabola_offset(before: np.ndarray, centre: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Sub-pixel offset (px, within ±0.5) of the peak of a parabola through the log magnitudes at -1, 0 and +1.

    The exact peak of a Gaussian profile; 0 where the three are not concave.
    """
    log_b, log_a = np.log(np.maximum(before, 1e-12)), np.log(np.maximum(after, 1e-12))
    log_c = np.log(np.maximum(centre, 1e-12))
    denominator = log_b - 2 * log_c + log_a
    offset = np.where(denominator < 0, 0.5 * (log_b - log_a) / np.where(denominator < 0, denominator, -1.0), 0.0)
    return np.clip(offset, -0.5, 0.5)


def edge_points(
    image,
    centre0,
    radius0,
    polarity,
    sigma_px: float,
    *,
    annulus_fraction: float,
    min_annulus_px: float,
    min_cos_radial: float,
    min_gradient_fraction: float,
):
    """Sub-pixel edge points around every bead.

    Parameters
    ----------
    image : (H, W) float32 ndarray
    centre0 : (n, 2) float64 ndarray, px
    radius0 : (n,) float64 ndarray, px
    polarity : {"dark", "bright"}
    sigma_px : float
        Scale of the edge filter, px.
    annulus_fraction, min_annulus_px : float
        Half-width of the search annulus about each radius: ``max(annulus_fraction * radius0, min_annulus_px)``.
    min_cos_radial : float
        Least cosine between a point's gradient and the radial direction (sign by ``polarity``).
    min_gradient_fraction : float
        Least gradient magnitude, as a fraction of the bead's strongest.

    Returns
    -------
    points_xy : (P, 2) float64 ndarray, px
    owner : (P,) int64 ndarray
        Bead (row of ``centre0``) each point belongs to; sorted ascending.
    """
    import cv2

    half_width = np.maximum(annulus_fraction * radius0, min_annulus_px)
    r_in, r_out = np.maximum(radius0 - half_width, 0.0), radius0 + half_width
    window, corner_xy = _window(image.shape, centre0, r_out, sigma_px)
    centre0 = centre0 - corner_xy
    # the beads alone: a flat closing (opening) also removes steps such as a phantom wall's edge next to a
    # bead, which would otherwise pull the gradient maxima on that side
    square_px = odd_size(1.25 * 2 * radius0.max() + 8)
    gx, gy = _gaussian_gradient(image[window] - background(image, polarity, square_px, reduce=True)[window], sigma_px)
    magnitude = cv2.magnitude(gx, gy)
    owner_image = _annulus_owners(magnitude.shape, centre0, r_out)
    width = magnitude.shape[1]
    # non-maximum suppression along the gradient's dominant axis: over the frame, the pixels that are a
    # maximum along x or along y; then, at those in an annulus, the test along the dominant axis (strictly
    # greater than the pixel before it, so that a plateau gives one point)
    found_xy = _axis_maxima(magnitude, owner_image)
    flat = found_xy[:, 1] * width + found_xy[:, 0]
    gx_p, gy_p, centre_mag = gx.ravel()[flat], gy.ravel()[flat], magnitude.ravel()[flat]
    horizontal = np.abs(gx_p) >= np.abs(gy_p)
    step = np.where(horizontal, 1, width)
    before, after = magnitude.ravel()[flat - step], magnitude.ravel()[flat + step]
    owner = owner_image.ravel()[flat].astype(np.int64) - 1
    # radial direction from the candidate centre; the gradient of a dark bead points outward, of a bright one inward
    ux, uy = found_xy[:, 0] - centre0[owner, 0], found_xy[:, 1] - centre0[owner, 1]
    sign = 1.0 if polarity == "dark" else -1.0
    radial = sign * (gx_p * ux + gy_p * uy) >= min_cos_radial * centre_mag * np.sqrt(ux * ux + uy * uy)
    keep = radial & (centre_mag > before) & (centre_mag >= after)
    found_xy, owner, centre_mag, horizontal, before, after = (
        v[keep] for v in (found_xy, owner, centre_mag, horizontal, before, after)
    )

    offset = _log_parabola_offset(before, centre_mag, after)
    x = found_xy[:, 0] + np.where(horizontal, offset, 0.0)
    y = found_xy[:, 1] + np.where(horizontal, 0.0, offset)
    # sorted by bead (raster order within each)
    order = np.argsort(owner.astype(np.uint16) if len(centre0) < 2**16 else owner, kind="stable")  # 16 bits: radix
    x, y, owner, centre_mag = (v[order] for v in (x, y, owner, centre_mag))
    keep = _strong_in_annulus(x, y, owner, centre_mag, centre0, r_in, r_out, min_gradient_fraction)
    return np.column_stack([x[keep], y[keep]]) + corner_xy, owner[keep]


def _strong_in_annulus(x, y, owner, magnitude, centre0, r_in, r_out, min_gradient_fraction: float) -> np.ndarray:
    """Points of each bead (``owner`` sorted) at least ``min_gradient_fraction`` of its strongest and in its annulus.

    Drops weak maxima (noise) and points outside ``r_in .. r_out`` of their bead's ``centre0``; (P,) bool.
    """
    dx, dy = x - centre0[owner, 0], y - centre0[owner, 1]
    dist = np.sqrt(dx * dx + dy * dy)
    strongest = np.zeros(len(r_in))
    if len(owner):
        starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
        strongest[owner[starts]] = np.maximum.reduceat(magnitude, starts)
    return (magnitude >= min_gradient_fraction * strongest[owner]) & (dist >= r_in[owner]) & (dist <= r_out[owner])
