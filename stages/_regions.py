"""Half-maximum regions of a flattened frame: steps 4 and 5 of :mod:`stages.detect` (its docstring gives the method).

Coordinates follow ``stages/geometry.py``: ``(x, y)`` with x = column, y = row,
the centre of the top-left pixel at ``(0, 0)``.
"""

from __future__ import annotations

import numpy as np
from fluorocal.stages._image import bead_signal, odd_size
from fluorocal.stages.geometry import xy_to_rc


def flatten(log_frame, fov_mask, polarity, d_min, d_max, min_sigma_px: float):
    """Smoothed top-hat (bead contrast positive) as log contrast and as intensity change; the change's running maximum.

    The top-hat is smoothed by a Gaussian of a sixth of ``d_min``, at least ``min_sigma_px`` (px of ``log_frame``).

    Returns
    -------
    smooth : (H, W) float32 ndarray
        Log contrast.
    change, local_change : (H, W) float32 ndarray
        :func:`intensity_change` of ``smooth``, and its maximum over a
        square of ``d_max`` px (that of ``smooth``, as the change grows with
        the contrast).
    """
    import cv2

    # the square must reach past the bead and its blurred skirt (a few px each side) from any point inside it
    tophat = bead_signal(log_frame, polarity, odd_size(1.25 * d_max + 8)) * fov_mask.astype(np.float32)
    smooth = cv2.GaussianBlur(tophat, (0, 0), max(min_sigma_px, d_min / 6))
    change = intensity_change(smooth, polarity)
    return smooth, change, cv2.dilate(change, np.ones((odd_size(d_max),) * 2, np.uint8))


def intensity_change(log_contrast, polarity: str):
    """Fraction by which a log contrast ``P`` changes the intensity: ``1 - exp(-P)`` (dark) or ``exp(P) - 1`` (bright).

    Thresholding a bead at a fraction ``q`` of its peak *change* (not at
    ``q P``) puts a blurred bead's half-maximum contour on its outline, as in
    the intensity image. Works on float32 images and on floats.
    """
    if polarity == "dark":
        return -np.expm1(-log_contrast)
    return np.expm1(np.minimum(log_contrast, np.float32(20)))  # exp overflows float32 beyond 88


def pixel_index(points_xy: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(row, col)`` of the pixel containing each point, clipped to the image; (N, 2) int64."""
    return np.clip(np.round(xy_to_rc(points_xy)).astype(np.int64), 0, np.array(shape) - 1)


def regions(
    flattened, fraction: float, floor: float, polarity: str, connectivity: int = 8, within=None, core_fraction=None
) -> tuple[dict, np.ndarray, np.ndarray]:
    """Regions above ``fraction`` of their local peak in intensity (peaks below ``floor`` ignored), measured.

    Parameters
    ----------
    flattened : tuple of three (H, W) float32 ndarray
        ``smooth, change, local_change`` as :func:`flatten` returns them.
    fraction : float
    floor : float
        Log contrast below which a peak is ignored.
    polarity : {"dark", "bright"}
    connectivity : {8, 4}
        Pixels touching at a corner belong to one region (8) or not (4).
    within : (H, W) uint8 ndarray, optional
        Only its non-zero pixels can belong to a region.
    core_fraction : float, optional
        Also count each region's pixels above this fraction of their local peak (``core_area``, px).

    Returns
    -------
    blobs : dict of ndarray
        ``xy_px`` (N, 2) px; ``radius_px`` (N,) px (equal-area disc);
        ``contrast`` (N,) log contrast at the centre; ``axis_ratio`` (N,)
        minor/major of the moment ellipse; ``fill`` (N,) area over
        moment-ellipse area; ``minor_diameter_px`` (N,) px; ``core_area`` (N,)
        with ``core_fraction``.
    labels : (H, W) int32 ndarray
        Region ``i`` is labelled ``i + 1``; 0 is background.
    boxes : (N, 4) int32 ndarray
        Bounding box ``(x, y, width, height)`` of each region, px.
    """
    import cv2

    smooth, change, local_change = flattened
    above = cv2.compare(change, local_change * np.float32(fraction), cv2.CMP_GE)
    region = cv2.bitwise_and(above, cv2.compare(local_change, float(intensity_change(floor, polarity)), cv2.CMP_GE))
    if within is not None:
        region = cv2.bitwise_and(region, within)  # non-zero (1) only inside
    # the block-based algorithm (8-connectivity; OpenCV picks its own for 4): twice the default's speed on sparse masks
    n, labels, stats, centres = cv2.connectedComponentsWithStatsWithAlgorithm(
        region, connectivity, cv2.CV_32S, cv2.CCL_BBDT
    )
    n_blobs = n - 1
    area = stats[1:, cv2.CC_STAT_AREA].astype(np.float64)
    # cv2 centroids are the mean (col, row) = (x, y) of each region's pixel centres
    mean_xy = centres[1:].reshape(-1, 2)
    found = cv2.findNonZero(region)
    # shape (K, 2): (x, y) of every region pixel
    pixel_xy = found.reshape(-1, 2) if found is not None else np.empty((0, 2), np.int32)
    lab = labels[pixel_xy[:, 1], pixel_xy[:, 0]] - 1
    dx, dy = pixel_xy[:, 0] - mean_xy[lab, 0], pixel_xy[:, 1] - mean_xy[lab, 1]
    # second moments of each region; a pixel is a unit square, which adds 1/12 px^2 along each axis
    sxx = np.bincount(lab, dx * dx, n_blobs) / np.maximum(area, 1) - 1 / 12
    syy = np.bincount(lab, dy * dy, n_blobs) / np.maximum(area, 1) - 1 / 12
    sxy = np.bincount(lab, dx * dy, n_blobs) / np.maximum(area, 1)
    half_trace, root = (sxx + syy) / 2, np.sqrt(((sxx - syy) / 2) ** 2 + sxy**2)
    lam_max, lam_min = np.maximum(half_trace + root, 1e-6), np.maximum(half_trace - root, 1e-6)
    # a round bead peaks at its centre; elsewhere the value at the centre is a lower bound that rejects oddly
    # shaped blobs
    centre_rc = pixel_index(mean_xy, labels.shape)
    contrast = smooth[centre_rc[:, 0], centre_rc[:, 1]].astype(np.float64)
    blobs = {
        "xy_px": mean_xy,
        "radius_px": np.sqrt(area / np.pi),
        "contrast": contrast,
        "axis_ratio": np.sqrt(lam_min / lam_max),
        # a disc of radius R has both moments R^2/4, so its moment ellipse has area 4 pi sqrt(l1 l2) = pi R^2
        "fill": area / (4 * np.pi * np.sqrt(lam_min * lam_max)),
        "minor_diameter_px": 4 * np.sqrt(lam_min),
    }
    if core_fraction is not None:
        core = change[pixel_xy[:, 1], pixel_xy[:, 0]] >= local_change[pixel_xy[:, 1], pixel_xy[:, 0]] * core_fraction
        blobs["core_area"] = np.bincount(lab, core, n_blobs)
    return blobs, labels, stats[1:, :4]


def cores(flattened, labels, boxes, parents, fraction: float, floor: float, polarity: str, connectivity: int):
    """:func:`regions` above ``fraction`` inside the regions ``parents`` of ``labels``, and the parent of each.

    The parents' bounding boxes are laid side by side (a column of zeros between two) in one small mosaic,
    labelled at once: the same regions as over the whole frame, at the cost of the parents' pixels only
    (over the whole frame, masked to the parents, when that is smaller).

    Parameters
    ----------
    flattened : tuple of three (H, W) float32 ndarray
        ``smooth, change, local_change`` as :func:`flatten` returns them.
    labels, boxes : as :func:`regions` returns them
    parents : (P,) int64 ndarray
        Rows of ``boxes`` (regions labelled ``parents + 1``).
    fraction, floor, polarity, connectivity :
        As :func:`regions` takes them.

    Returns
    -------
    blobs : dict of ndarray
        As :func:`regions` (frame px), for each region whose centre lies in its parent.
    parent : (M,) int64 ndarray
        The region (a value of ``parents``) each lies in.
    """
    widths = boxes[parents, 2] + 1
    starts = np.concatenate([[0], np.cumsum(widths)[:-1]])
    shape = (int(boxes[parents, 3].max()), int(widths.sum()))
    if shape[0] * shape[1] >= labels.size:
        blobs, _, _ = regions(flattened, fraction, floor, polarity, connectivity, within=_member(labels, parents))
        centre_rc = pixel_index(blobs["xy_px"], labels.shape)
        parent = labels[centre_rc[:, 0], centre_rc[:, 1]].astype(np.int64) - 1
        keep = np.isin(parent, parents)
        return {k: v[keep] for k, v in blobs.items()}, parent[keep]
    mosaic = [np.zeros(shape, np.float32) for _ in flattened]
    inside = np.zeros(shape, np.uint8)
    for i, x0 in zip(parents.tolist(), starts.tolist()):
        x, y, w, h = boxes[i].tolist()
        for tile, image in zip(mosaic, flattened):
            tile[:h, x0 : x0 + w] = image[y : y + h, x : x + w]
        inside[:h, x0 : x0 + w] = labels[y : y + h, x : x + w] == i + 1
    blobs, _, _ = regions(mosaic, fraction, floor, polarity, connectivity, within=inside)
    tile = np.searchsorted(starts, blobs["xy_px"][:, 0], side="right") - 1
    parent = parents[tile]
    blobs["xy_px"] = blobs["xy_px"] + boxes[parent, :2] - np.column_stack([starts[tile], np.zeros(len(tile))])
    # a region bent around its centre (which then lies outside its parent) is no bead
    centre_rc = pixel_index(blobs["xy_px"], labels.shape)
    keep = labels[centre_rc[:, 0], centre_rc[:, 1]] == parent + 1
    return {k: v[keep] for k, v in blobs.items()}, parent[keep]


def _member(labels: np.ndarray, regions_: np.ndarray) -> np.ndarray:
    """1 where ``labels`` is one of ``regions_ + 1``; (H, W) uint8."""
    lookup = np.zeros(int(labels.max()) + 1, np.uint8)
    lookup[regions_ + 1] = 1
    return lookup[labels]
