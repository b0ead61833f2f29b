"""Undistortion of frames with inverse maps (``cv2.remap``).

The maps follow README.md "Conventions": ``map_x``, ``map_y`` are float32 of
shape ``(H_out, W_out)`` and give, for each undistorted output pixel centre,
the source coordinate in the distorted (measured) image. Pixels whose source
lies outside the frame get ``border_value``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.artifacts import Radiograph
from fluorocal.stages.errors import InputError, ShapeError

VERSION = 1

_INTERPOLATION = {"nearest": 0, "linear": 1, "cubic": 2, "lanczos": 4}  # cv2.INTER_* values


@dataclass(frozen=True)
class UndistortParams:
    """Parameters of :func:`undistort_frame`.

    Attributes
    ----------
    interpolation : str
        ``"linear"`` (default), ``"cubic"``, ``"lanczos"`` or ``"nearest"``.
    border_value : float
        Value of output pixels whose source falls outside the frame (default 0, the dark outside of the field).
    """

    interpolation: str = "linear"
    border_value: float = 0.0


def check_maps(map_x: np.ndarray, map_y: np.ndarray) -> None:
    """Refuse inverse maps that would move pixels beyond the image.

    Every source coordinate must be finite, and no pixel may move by half the
    image's larger side or more: a correction that large puts much of the frame
    outside itself (a field of 1e30 px would write an all-dark frame).

    Parameters
    ----------
    map_x, map_y : (H, W) float ndarray, px
        Inverse maps of an ``(H, W)`` output, as :func:`undistort_frame` takes them.

    Raises
    ------
    InputError
        Naming the largest displacement and the bound.

    Examples
    --------
    >>> yy, xx = np.mgrid[0:3, 0:4].astype(np.float32)
    >>> check_maps(xx + 0.5, yy)
    >>> check_maps(xx + 1e30, yy)
    Traceback (most recent call last):
    ...
    fluorocal.stages.errors.InputError: the correction moves pixels by up to 1e+30 px; ...
    """
    map_x, map_y = np.asarray(map_x, dtype=np.float64), np.asarray(map_y, dtype=np.float64)
    if map_x.ndim != 2 or map_x.shape != map_y.shape:
        raise ShapeError(f"map_x and map_y must be 2-D of one shape; got {map_x.shape} and {map_y.shape}")
    if not (np.all(np.isfinite(map_x)) and np.all(np.isfinite(map_y))):
        raise InputError("the correction is not finite everywhere in the image (NaN or infinite source coordinates)")
    h, w = map_x.shape
    yy, xx = np.mgrid[0:h, 0:w]
    shift = float(np.hypot(map_x - xx, map_y - yy).max(initial=0.0))
    bound = max(w, h) / 2
    if not shift < bound:
        raise InputError(
            f"the correction moves pixels by up to {shift:.3g} px; a {w}x{h} px image allows less than {bound:g} px "
            "(half its larger side)"
        )


def undistort_frame(
    radiograph: Radiograph, map_x: np.ndarray, map_y: np.ndarray, params: UndistortParams
) -> Radiograph:
    """Resample a distorted frame onto the ideal (pinhole) image grid.

    Parameters
    ----------
    radiograph : Radiograph
    map_x, map_y : (H_out, W_out) float32 ndarray, px
        Source coordinates (x = column, y = row) in ``radiograph`` of each output pixel centre.
    params : UndistortParams

    Returns
    -------
    Radiograph
        Same bit depth, source and metadata; intensities resampled, clipped
        to the source's value range (cubic and Lanczos kernels overshoot).

    Examples
    --------
    >>> img = Radiograph(np.arange(12, dtype=np.float32).reshape(3, 4), 16)
    >>> yy, xx = np.mgrid[0:3, 0:4].astype(np.float32)
    >>> out = undistort_frame(img, xx, yy, UndistortParams())
    >>> bool(np.array_equal(out.image, img.image))
    True
    """
    import cv2

    if params.interpolation not in _INTERPOLATION:
        raise InputError(f"interpolation must be one of {', '.join(_INTERPOLATION)}; got {params.interpolation!r}")
    map_x = np.asarray(map_x, dtype=np.float32)
    map_y = np.asarray(map_y, dtype=np.float32)
    if map_x.ndim != 2 or map_x.shape != map_y.shape:
        raise ShapeError(f"map_x and map_y must be 2-D of one shape; got {map_x.shape} and {map_y.shape}")
    out = cv2.remap(
        radiograph.image,
        map_x,
        map_y,
        interpolation=_INTERPOLATION[params.interpolation],
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float(params.border_value),
    )
    lo, hi = float(radiograph.image.min()), float(radiograph.image.max())
    out = np.clip(out, min(lo, params.border_value), max(hi, params.border_value))
    meta = {**radiograph.metadata, "undistorted": True}
    return Radiograph(out, radiograph.bit_depth, radiograph.source, radiograph.frame_index, meta)
