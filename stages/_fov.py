"""Frame-level estimates for bead detection: the intensifier's field of view, pixel noise and bead polarity.

Steps 1 and 3 of :mod:`stages.detect` (its module docstring gives the method),
and the distance of points to the field's outline.
"""

from __future__ import annotations

import numpy as np
from fluorocal.stages._image import log_image, odd_size


def field_of_view(image: np.ndarray, half: np.ndarray | None = None):
    """Outline and mask of the intensifier's bright field.

    ``half``, optional: ``image`` reduced 2x by ``cv2.INTER_AREA``, reduced further instead of ``image`` when
    that averages the same pixels (one pass less over the full frame).

    Returns
    -------
    hull_xy : (K, 2) float64 ndarray, px
        Convex outline of the field, ``(x, y)``.
    mask : (H, W) uint8 ndarray
        1 inside the outline.

    or ``None`` when the frame has no bright region (blank).
    """
    import cv2

    height, width = image.shape
    # about 256 px across is plenty for an outline good to a reduced pixel
    factor = max(1, min(height, width) // 256)
    source = image
    if half is not None and factor % 2 == 0 and height % factor == 0 and width % factor == 0:
        source = half
    small = (
        cv2.resize(source, (width // factor, height // factor), interpolation=cv2.INTER_AREA) if factor > 1 else image
    )
    # every other reduced pixel is plenty for the levels
    sample = small[::2, ::2]
    bright_level = float(np.percentile(sample, 99))
    if not bright_level > 0:
        return None
    # a fifth of the bright level separates the field from the dark surround (below a grid plate, the
    # vignetted rim and dense anatomy); the edge is then put at half the field's median level
    inside = (small > 0.5 * _median(sample[sample > 0.2 * bright_level])).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStatsWithAlgorithm(inside, 8, cv2.CV_32S, cv2.CCL_BBDT)
    if n < 2:
        return None
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    contours, _ = cv2.findContours((labels == largest).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    hull_small = cv2.convexHull(np.concatenate(contours)).reshape(-1, 2).astype(np.float64)
    # a reduced pixel i covers full pixels [f*i, f*i + f - 1], centred on f*i + (f-1)/2
    hull_xy = factor * hull_small + (factor - 1) / 2
    hull_xy = np.clip(hull_xy, 0, [width - 1, height - 1])
    mask = np.zeros((height, width), np.uint8)
    cv2.fillConvexPoly(mask, np.round(hull_xy).astype(np.int32), 1)
    return hull_xy, mask


def pixel_noise(image: np.ndarray, fov_mask: np.ndarray) -> float:
    """Robust per-pixel noise sigma of the log image inside the field (MAD of horizontal differences)."""
    # every 4th row and pair of columns is plenty for a median
    left, right = image[::4, 0:-1:4], image[::4, 1::4]
    n_columns = min(left.shape[1], right.shape[1])
    diff = np.abs(
        log_image(np.ascontiguousarray(right[:, :n_columns])) - log_image(np.ascontiguousarray(left[:, :n_columns]))
    )
    diff = diff[fov_mask[::4, 1::4][:, :n_columns] > 0]
    if diff.size == 0:
        return 1e-3
    # the difference of two independent pixels has sqrt(2) times their noise; 1.4826 turns a MAD into a sigma
    return max(float(1.4826 * _median(diff) / np.sqrt(2)), 1e-4)


def _median(values: np.ndarray) -> float:
    """The median of a non-empty array, by a full sort (numpy's partition is several times slower on 1e4-1e5 px)."""
    ordered = np.sort(values, axis=None)
    return (float(ordered[(ordered.size - 1) // 2]) + float(ordered[ordered.size // 2])) / 2


def bead_polarity(image: np.ndarray, fov_mask: np.ndarray) -> str:
    """``"dark"`` or ``"bright"``: which tail of the log image minus its running median is heavier.

    Beads are a small fraction of the field (or, for a grid plate, a minority
    against the plate); the median tracks the majority, so the beads form the
    heavier tail of the residual. The test runs on every ``step``-th pixel
    (about 128 px across, every 4th at least) with a median over about 60 full
    px, wider than any bead.
    """
    import cv2

    height, width = image.shape
    step = max(4, min(height, width) // 128)
    # a sample of the intensities, not averages (averaging would mix a grid plate's holes into it)
    small = log_image(np.ascontiguousarray(image[::step, ::step]))
    inside = cv2.erode(np.ascontiguousarray(fov_mask[::step, ::step]), np.ones((5, 5), np.uint8))
    # medianBlur takes large kernels only on 8-bit data: 30 levels per unit of ln(I) is enough to compare tails
    quantised = np.clip(small * 30, 0, 255).astype(np.uint8)
    residual = quantised.astype(np.int16) - cv2.medianBlur(quantised, odd_size(60 / step)).astype(np.int16)
    values = residual[inside > 0]
    if values.size == 0:
        return "dark"
    low, high = np.percentile(values, [0.2, 99.8])
    return "dark" if -low >= high else "bright"


def fov_clearance(points_xy: np.ndarray, hull_xy: np.ndarray) -> np.ndarray:
    """Distance (px) from each point to the edge of the convex field outline, negative outside; (N,).

    Inside a convex polygon the distance to its outline is the smallest
    distance to the lines through its edges.
    """
    start, end = hull_xy, np.roll(hull_xy, -1, axis=0)
    edge = end - start
    length = np.hypot(edge[:, 0], edge[:, 1])
    keep = length > 0
    start, edge, length = start[keep], edge[keep], length[keep]
    to_centre = hull_xy.mean(axis=0) - start[0]
    inward = 1.0 if edge[0, 0] * to_centre[1] - edge[0, 1] * to_centre[0] >= 0 else -1.0
    # shape (N, K): signed distance of each point to each edge line, positive on the inner side
    cross = edge[None, :, 0] * (points_xy[:, None, 1] - start[None, :, 1]) - edge[None, :, 1] * (
        points_xy[:, None, 0] - start[None, :, 0]
    )
    return (inward * cross / length).min(axis=1) if len(length) else np.full(len(points_xy), np.inf)
