"""Image helpers shared by the detect and centroid stages (private).

Images are ``(H, W)`` float32 arrays indexed ``img[y, x]``; see
``stages/geometry.py`` for the pixel convention.
"""

from __future__ import annotations

import numpy as np


def frame_name(radiograph) -> str:
    """``source[frame_index]`` of a :class:`~stages.artifacts.Radiograph`, for warnings and logs."""
    return f"{radiograph.source or '<array>'}[{radiograph.frame_index}]"


def odd_size(value: float) -> int:
    """The smallest odd integer >= ``value`` (a filter side, px).

    Examples
    --------
    >>> odd_size(4.2), odd_size(5.0), odd_size(6.0)
    (5, 5, 7)
    """
    return int(2 * np.ceil((value - 1) / 2) + 1)


def log_image(image: np.ndarray) -> np.ndarray:
    """``ln(max(I, 0) + 1)``; float32, (H, W)."""
    import cv2

    return cv2.log(np.maximum(image, 0) + np.float32(1))


def background(image: np.ndarray, polarity: str, square_px: int, *, reduce: bool = False) -> np.ndarray:
    """The frame without its beads: a grey-level closing (dark beads) or opening (bright) by a square; (H, W) float32.

    A flat closing (opening) removes every dark (bright) blob narrower than
    the square and restores monotone edges, so ``image - background`` keeps
    the beads and leaves ramps and straight steps (bone edges, a phantom wall)
    at zero.

    Parameters
    ----------
    image : (H, W) float32 ndarray
    polarity : {"dark", "bright"}
    square_px : int
        Side of the square, px (odd); it must reach past a bead and its
        blurred skirt from any point inside it.
    reduce : bool
        Compute on a 2x-reduced copy (``square_px`` then counts full-frame
        px) and bring it back by bilinear interpolation: within a pixel of
        the full computation where the background is smooth, and 4x cheaper.
    """
    import cv2

    op = cv2.MORPH_CLOSE if polarity == "dark" else cv2.MORPH_OPEN
    if not reduce:
        return cv2.morphologyEx(image, op, cv2.getStructuringElement(cv2.MORPH_RECT, (square_px, square_px)))
    height, width = image.shape
    small = cv2.resize(image, (width // 2, height // 2), interpolation=cv2.INTER_AREA)
    side = odd_size(square_px / 2)
    small = cv2.morphologyEx(small, op, cv2.getStructuringElement(cv2.MORPH_RECT, (side, side)))
    return cv2.resize(small, (width, height), interpolation=cv2.INTER_LINEAR)


def bead_signal(log_frame: np.ndarray, polarity: str, square_px: int) -> np.ndarray:
    """Polarity-signed top-hat of a log image: the beads' contrast, positive for either polarity; (H, W) float32.

    A flat closing (opening) commutes with any increasing map of the grey levels, so it runs on the image
    mapped onto 65536 levels over its range (about twice as fast as on float32): the top-hat is the float
    image's to within half a level: under 1e-4 for the log of 16-bit data (a range under 12).
    """
    import cv2

    low, high = cv2.minMaxLoc(log_frame)[:2]
    levels = cv2.normalize(log_frame, None, 0, 65535, cv2.NORM_MINMAX, cv2.CV_16U)
    op = cv2.MORPH_CLOSE if polarity == "dark" else cv2.MORPH_OPEN
    filled = cv2.morphologyEx(levels, op, cv2.getStructuringElement(cv2.MORPH_RECT, (square_px, square_px)))
    filled = filled.astype(np.float32) * np.float32((high - low) / 65535) + np.float32(low)
    return filled - log_frame if polarity == "dark" else log_frame - filled
