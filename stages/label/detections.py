"""A frame's detections as the labelling sees them, and the interior orientation it assumes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.errors import InputError
from fluorocal.stages.geometry import iop_guess
from fluorocal.stages.label.params import LabelParams


@dataclass(frozen=True)
class Detections:
    """The detections of a frame, with the usable ones flagged."""

    xy_px: np.ndarray  # (M, 2)
    sigma_px: np.ndarray  # (M, 3)
    size_px: np.ndarray  # (M,) apparent diameter (twice the minor semi-axis), NaN when unknown
    axis_ratio: np.ndarray  # (M,) major / minor semi-axis, NaN when unknown
    valid: np.ndarray  # (M,) bool

    @classmethod
    def from_centroids(cls, centroids) -> "Detections":
        xy = np.asarray(centroids.xy_px, dtype=np.float64).reshape(-1, 2)
        m = len(xy)

        def column(name, default):
            value = getattr(centroids, name, None)
            return (
                np.full(m, default, dtype=np.float64)
                if value is None
                else np.asarray(value, dtype=np.float64).reshape(m)
            )

        sigma = np.column_stack([column("sigma_x", np.nan), column("sigma_y", np.nan), column("rho", 0.0)])
        ok = getattr(centroids, "ok", None)
        valid = np.ones(m, dtype=bool) if ok is None else np.asarray(ok, dtype=bool).reshape(m).copy()
        valid &= np.isfinite(xy).all(1) & np.isfinite(sigma).all(1)
        minor = column("minor_px", np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = column("major_px", np.nan) / minor
        # the minor axis, not the area: two touching beads merged into one blob keep a small minor axis
        return cls(xy, sigma, 2.0 * minor, ratio, valid)


def _image_size(centroids, params: LabelParams) -> tuple[float, float] | None:
    """``(width, height)`` px from the params or the centroids' image shape, else None."""
    if params.image_size_px:
        return float(params.image_size_px[0]), float(params.image_size_px[1])
    shape = getattr(centroids, "image_shape", None)  # (H, W), if the centroid stage records it
    if shape is not None and len(shape) == 2 and all(s > 0 for s in shape):
        return float(shape[1]), float(shape[0])
    return None


def assumed_iop(det: Detections, centroids, params: LabelParams, *, need_c: bool) -> np.ndarray:
    """``(xp, yp, c)``: principal point at the image centre, ``c = SID / pitch``.

    Without the image size, the centre of the detections' bounding box stands in for the image centre
    (the field of view of an image intensifier is centred on the detector); the pose absorbs the difference.
    """
    if need_c and not (params.source_image_distance_mm > 0 and params.pixel_pitch_mm > 0):
        raise InputError(
            "params.source_image_distance_mm and params.pixel_pitch_mm must be > 0 to label a 3D phantom; "
            f"got {params.source_image_distance_mm}, {params.pixel_pitch_mm}"
        )
    size = _image_size(centroids, params)
    guess = iop_guess(size or (1, 1), params.source_image_distance_mm, params.pixel_pitch_mm)
    if size is not None:
        return guess
    c = guess[2]  # the principal point comes from the detections below
    pts = det.xy_px[det.valid]
    if not len(pts):
        return np.array([0.0, 0.0, c])
    return np.array([*(0.5 * (pts.min(0) + pts.max(0))), c])
