"""Undistortion of frames with inverse maps (``cv2.remap``).

The maps follow docs/concepts.md, "Conventions": ``map_x``, ``map_y`` are float32 of
shape ``(H_out, W_out)`` and give, for each undistorted output pixel centre,
the source coordinate in the distorted (measured) image. Pixels whose source
lies outside the frame get ``border_value``.

Edges (:func:`clear_outside`): an output pixel whose source lies outside the
field's support (where the calibration saw no bead or hole, so the correction
there is a guess) or outside the frame's collimated area (the intensifier's
bright disc, :func:`collimated_area`) is set to the frame's background
(:func:`frame_background`), so that nothing from beyond the calibrated,
exposed part of the detector, such as a detector's bright rim row, is warped
into the picture. ``UndistortParams(outside="keep")`` keeps them as remapped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.artifacts import Radiograph
from fluorocal.stages.errors import InputError, ShapeError

_INTERPOLATION = {"nearest": 0, "linear": 1, "cubic": 2, "lanczos": 4}  # cv2.INTER_* values
#: half the width, px, of each kernel's footprint beyond the nearest pixel: a source pixel that far from an
#: excluded one may still be weighed into the output
_REACH_PX = {"nearest": 0, "linear": 1, "cubic": 2, "lanczos": 4}
#: what :func:`clear_outside` does with output pixels whose source is outside the support or collimated area
OUTSIDE = ("background", "keep")


@dataclass(frozen=True)
class UndistortParams:
    """Parameters of :func:`undistort_frame`.

    Attributes
    ----------
    interpolation : str
        ``"linear"`` (default), ``"cubic"``, ``"lanczos"`` or ``"nearest"``.
    border_value : float
        Value of output pixels whose source falls outside the frame (default 0, the dark outside of the field),
        in the frame's units: the format's black.
    outside : str
        ``"keep"`` (default here; the pure remap) or ``"background"``: :func:`clear_outside` sets output
        pixels whose source lies outside the field's support or the collimated area to the frame's background
        (``fluorocal undistort``'s default).
    collimation_fraction : float
        A source pixel is in the collimated area when it is brighter than black by more than this fraction of
        the frame's 99th percentile brightness (default 0.1: the ARCADIS disc's dark vignetted rim is still
        about half of its centre, its outside about 0 DN; :func:`collimated_area`).
    """

    interpolation: str = "linear"
    border_value: float = 0.0
    outside: str = "keep"
    collimation_fraction: float = 0.1

    def __post_init__(self):
        if self.outside not in OUTSIDE:
            raise InputError(f"outside must be one of {', '.join(OUTSIDE)}; got {self.outside!r}")
        if not 0 < self.collimation_fraction < 1:
            raise InputError(f"collimation_fraction must lie in (0, 1); got {self.collimation_fraction!r}")


def check_shift(shift_px, width_px: int, height_px: int) -> None:
    """Refuse displacements ``(..., 2)`` px that would move pixels beyond a ``width_px`` x ``height_px`` image.

    Every displacement must be finite and shorter than half the image's larger
    side: a correction that large puts much of the frame outside itself (a
    field of 1e30 px would write an all-dark frame).

    Raises
    ------
    InputError
        Naming the largest displacement and the bound.

    Examples
    --------
    >>> check_shift(np.array([[0.5, -3.0]]), 64, 48)
    >>> check_shift(np.array([[1e30, 0.0]]), 64, 48)
    Traceback (most recent call last):
    ...
    fluorocal.stages.errors.InputError: the correction moves pixels by up to 1e+30 px; ...
    """
    shift_px = np.asarray(shift_px, dtype=np.float64)
    if not np.all(np.isfinite(shift_px)):
        raise InputError("the correction is not finite everywhere (NaN or infinite displacements)")
    # max |component| first: the norm of 1e200 would overflow
    largest = float(np.abs(shift_px).max(initial=0.0))
    if largest < 1e100:
        largest = float(np.linalg.norm(shift_px.reshape(-1, 2), axis=1).max(initial=0.0))
    bound = max(int(width_px), int(height_px)) / 2
    if not largest < bound:
        raise InputError(
            f"the correction moves pixels by up to {largest:.3g} px; a {width_px}x{height_px} px image allows less "
            f"than {bound:g} px (half its larger side)"
        )


def check_maps(map_x: np.ndarray, map_y: np.ndarray) -> None:
    """Refuse inverse maps ``(H, W)`` (as :func:`undistort_frame` takes them) that move pixels beyond the image.

    See :func:`check_shift` for the rule.

    Examples
    --------
    >>> yy, xx = np.mgrid[0:3, 0:4].astype(np.float32)
    >>> check_maps(xx + 0.5, yy)
    """
    map_x, map_y = np.asarray(map_x, dtype=np.float64), np.asarray(map_y, dtype=np.float64)
    if map_x.ndim != 2 or map_x.shape != map_y.shape:
        raise ShapeError(f"map_x and map_y must be 2-D of one shape; got {map_x.shape} and {map_y.shape}")
    h, w = map_x.shape
    yy, xx = np.mgrid[0:h, 0:w]
    check_shift(np.stack([map_x - xx, map_y - yy], axis=-1), w, h)


def undistort_frame(
    radiograph: Radiograph, map_x: np.ndarray, map_y: np.ndarray, params: UndistortParams, supported=None
) -> Radiograph:
    """Resample a distorted frame onto the ideal (pinhole) image grid.

    Parameters
    ----------
    radiograph : Radiograph
    map_x, map_y : (H_out, W_out) float32 ndarray, px
        Source coordinates (x = column, y = row) in ``radiograph`` of each output pixel centre.
    params : UndistortParams
    supported : (H_out, W_out) bool ndarray, optional
        Where the output's source lies in the field's support (:func:`supported_output`; None: everywhere);
        used with ``params.outside == "background"`` (:func:`clear_outside`).

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
    out = remap_image(radiograph.image, map_x, map_y, params)
    out = clear_outside(radiograph.image, out, map_x, map_y, params, supported)
    meta = {**radiograph.metadata, "undistorted": True}
    return Radiograph(out, radiograph.bit_depth, radiograph.source, radiograph.frame_index, meta)


def remap_image(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, params: UndistortParams) -> np.ndarray:
    """Resample an image array of any dtype through inverse maps: ``cv2.remap`` and, for overshooting kernels, a clip.

    Parameters
    ----------
    image : (H, W) ndarray, uint8, uint16 or float32
        The distorted frame, in its own dtype (integer frames are remapped in OpenCV's fixed point,
        which rounds like ``np.rint`` of the float result; see Notes).
    map_x, map_y : (H_out, W_out) float32 ndarray, px
        Source coordinates (x = column, y = row) in ``image`` of each output pixel centre.
    params : UndistortParams

    Returns
    -------
    (H_out, W_out) ndarray of ``image``'s dtype
        Cubic and Lanczos results clipped to the image's value range and ``params.border_value``
        (those kernels overshoot); linear and nearest need no clip, their outputs being convex
        combinations of the inputs and the border value.

    Notes
    -----
    ``benchmarks/undistort.py`` measures the choices: OpenCV's linear remap of a ``uint16`` frame
    and ``np.rint`` of the same remap of the frame as float32 are 0 DN apart, while the fixed-point
    map pair of ``cv2.convertMaps`` (``CV_16SC2``) is slower with OpenCV 5 and tens of DN apart:
    float32 maps are the only kind used.

    Examples
    --------
    >>> img = np.arange(12, dtype=np.uint16).reshape(3, 4)
    >>> yy, xx = np.mgrid[0:3, 0:4].astype(np.float32)
    >>> remap_image(img, xx + 1, yy, UndistortParams())
    array([[ 1,  2,  3,  0],
           [ 5,  6,  7,  0],
           [ 9, 10, 11,  0]], dtype=uint16)
    """
    import cv2

    if params.interpolation not in _INTERPOLATION:
        raise InputError(f"interpolation must be one of {', '.join(_INTERPOLATION)}; got {params.interpolation!r}")
    map_x = np.asarray(map_x, dtype=np.float32)
    map_y = np.asarray(map_y, dtype=np.float32)
    if map_x.ndim != 2 or map_x.shape != map_y.shape:
        raise ShapeError(f"map_x and map_y must be 2-D of one shape; got {map_x.shape} and {map_y.shape}")
    out = cv2.remap(
        image,
        map_x,
        map_y,
        interpolation=_INTERPOLATION[params.interpolation],
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float(params.border_value),
    )
    if params.interpolation in ("cubic", "lanczos"):
        border = params.border_value
        bounds = np.array([min(float(image.min()), border), max(float(image.max()), border)]).astype(out.dtype)
        out = np.clip(out, bounds[0], bounds[1], out=out)
    return out


#: the sample types ``cv2.remap`` resamples as they are; others go through float64
_REMAPPED = (np.uint8, np.uint16, np.int16, np.float32, np.float64)


def remap_stored(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, params: UndistortParams) -> np.ndarray:
    """:func:`remap_image` for a frame as a file stores it: every channel, any integer or float sample type.

    Parameters
    ----------
    image : (H, W) or (H, W, C) ndarray
        The frame's samples; each channel is resampled on its own (with ``params.border_value``).
    map_x, map_y : (H_out, W_out) float32 ndarray, px
    params : UndistortParams

    Returns
    -------
    (H_out, W_out) or (H_out, W_out, C) ndarray of ``image``'s dtype
        Types ``cv2.remap`` does not take (int8, 32-bit integers) are resampled in float64 (exact
        for them) and rounded back, clipped to the type's range.

    Examples
    --------
    >>> img = np.arange(24, dtype=np.uint32).reshape(3, 4, 2) * 100_000
    >>> yy, xx = np.mgrid[0:3, 0:4].astype(np.float32)
    >>> bool(np.array_equal(remap_stored(img, xx, yy, UndistortParams()), img))
    True
    """
    if image.ndim == 3:
        channels = [remap_stored(image[..., c], map_x, map_y, params) for c in range(image.shape[2])]
        return np.stack(channels, axis=-1)
    if image.dtype in _REMAPPED:
        return remap_image(image, map_x, map_y, params)
    info = np.iinfo(image.dtype)
    out = remap_image(image.astype(np.float64), map_x, map_y, params)
    return np.clip(np.rint(out), info.min, info.max).astype(image.dtype)


def collimated_area(image: np.ndarray, black: float = 0.0, fraction: float = 0.1) -> np.ndarray:
    """Where a frame is exposed: the intensifier's disc (or the collimator's opening), as a ``(H, W)`` bool mask.

    Brightness is measured from ``black`` (the type's darkest value, which sets the direction: MinIsWhite frames
    are bright towards it) and counted from the frame's own dark level (its 1st percentile: a signed frame whose
    outside sits far above the type's minimum is not taken as exposed everywhere). The pixels brighter than that
    level by more than ``fraction`` of the way to the 99th percentile, their largest 8-connected region, and that
    region's convex hull (dark anatomy or beads inside stay in). A frame with no such pixel is exposed everywhere
    (nothing is taken for outside).

    Examples
    --------
    >>> img = np.zeros((5, 7), np.uint16); img[1:4, 2:6] = 1000
    >>> collimated_area(img).astype(int)[2]
    array([0, 0, 1, 1, 1, 1, 0])
    >>> signed = np.zeros((5, 7), np.int16); signed[1:4, 2:6] = 1500  # outside at 0, the type's black -32768
    >>> collimated_area(signed, black=-32768).astype(int)[2]
    array([0, 0, 1, 1, 1, 1, 0])
    """
    import cv2

    brightness = np.abs(np.asarray(image, dtype=np.float32) - np.float32(black))
    sample = brightness[::4, ::4] if brightness.size > 1 << 16 else brightness  # every 16th pixel is plenty
    dark, bright99 = (float(v) for v in np.percentile(sample, [1, 99]))
    level = dark + fraction * (bright99 - dark)
    bright = (brightness > level).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(bright, connectivity=8)
    if not bright99 > dark or n < 2:
        return np.ones(brightness.shape, bool)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    contours, _ = cv2.findContours((labels == largest).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    mask = np.zeros(brightness.shape, np.uint8)
    cv2.fillConvexPoly(mask, cv2.convexHull(np.concatenate(contours)), 1)
    return mask.astype(bool)


def frame_background(image: np.ndarray, collimated: np.ndarray, black: float = 0.0) -> float:
    """The frame's background: the median outside its collimated area, or ``black`` when under 1 % lies outside.

    Examples
    --------
    >>> img = np.full((10, 10), 7.0); img[1:9, 1:9] = 900
    >>> frame_background(img, img > 100)
    7.0
    """
    outside = np.asarray(image)[~collimated]
    return float(np.median(outside)) if outside.size >= 0.01 * collimated.size else float(black)


def supported_output(field, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """``(H_out, W_out)`` bool: where the output pixel's source lies in ``field``'s support (a CorrectionField).

    The support (1 at supported nodes, 0 at the others) is interpolated bilinearly and compared with 1/2:
    the boundary runs midway between supported and unsupported nodes, a smooth curve rather than the
    node grid's steps.

    Examples
    --------
    >>> from fluorocal.stages.field import CorrectionField
    >>> f = CorrectionField.constant(64, 16)  # nodes at x = -0.5, 15.5, 31.5, 47.5, 63.5
    >>> f = f.with_delta(f.delta_px, support=f.support & (f.x_nodes_px < 30))
    >>> yy, xx = np.mgrid[0:16, 0:64].astype(np.float32)
    >>> int(np.flatnonzero(supported_output(f, xx, yy)[0])[-1])  # midway between the nodes at 15.5 and 31.5
    23
    """
    from fluorocal.stages.field import bilinear

    xy = np.column_stack([np.ravel(map_x), np.ravel(map_y)]).astype(np.float64)
    level = bilinear(field.x_nodes_px, field.y_nodes_px, field.support[..., None].astype(float), xy)[:, 0]
    return (level >= 0.5).reshape(np.shape(map_x))


def clear_outside(
    image: np.ndarray, out: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, params: UndistortParams, supported=None
) -> np.ndarray:
    """``out`` (the remap of ``image``) with pixels whose source is outside set to the frame's background.

    Outside: beyond the frame, outside ``image``'s :func:`collimated_area` (within the interpolation kernel's
    reach), or where ``supported`` (``(H_out, W_out)`` bool, :func:`supported_output`; None: everywhere) is
    False. The background is :func:`frame_background`, in ``image``'s units and dtype. With
    ``params.outside == "keep"``, ``out`` unchanged.

    Examples
    --------
    >>> img = np.zeros((6, 6), np.uint16); img[1:5, 1:5] = 800; img[0] = 4095  # a bright rim row
    >>> yy, xx = np.mgrid[0:6, 0:6].astype(np.float32)
    >>> out = remap_image(img, xx, yy, UndistortParams())
    >>> int(clear_outside(img, out, xx, yy, UndistortParams(outside="background"))[0].max())
    0
    """
    import cv2

    if params.outside == "keep":
        return out
    collimated = collimated_area(image, params.border_value, params.collimation_fraction)
    reach = _REACH_PX[params.interpolation]
    inside = collimated.astype(np.uint8)
    if reach:  # a source pixel within the kernel's reach of an excluded one is excluded too
        inside = cv2.erode(inside, np.ones((2 * reach + 1, 2 * reach + 1), np.uint8), borderValue=0)
    exposed = cv2.remap(inside, np.asarray(map_x, np.float32), np.asarray(map_y, np.float32), cv2.INTER_NEAREST)
    keep = exposed.astype(bool) if supported is None else exposed.astype(bool) & supported
    background = frame_background(image, collimated, params.border_value)
    if np.issubdtype(out.dtype, np.integer):
        background = np.clip(np.rint(background), np.iinfo(out.dtype).min, np.iinfo(out.dtype).max)
    out = out.copy()
    out[~keep] = background
    return out
