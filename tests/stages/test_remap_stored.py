"""``remap_stored``: a frame as its file stores it (any sample type, any channel count) through inverse maps.

Ground truth is analytic: at pixel centres every kernel's weights are one tap of 1 (identity), and a
half-pixel linear shift is the mean of two neighbours, rounded half to even like ``np.rint`` for the
types resampled through float64.
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.stages.undistort import UndistortParams, remap_stored

H, W = 24, 32
TYPES = [np.uint8, np.int8, np.uint16, np.int16, np.uint32, np.int32, np.float32, np.float64]


def _samples(dtype, channels: int) -> np.ndarray:
    rng = np.random.default_rng(7)
    shape = (H, W, channels) if channels > 1 else (H, W)
    if np.dtype(dtype).kind == "f":
        return rng.normal(0, 1000, shape).astype(dtype)
    info = np.iinfo(dtype)
    values = rng.integers(info.min, info.max, shape, dtype=np.int64, endpoint=True)
    values.flat[:2] = [info.min, info.max]
    return values.astype(dtype)


@pytest.mark.parametrize("interpolation", ["nearest", "linear", "cubic", "lanczos"])
@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("dtype", TYPES)
def test_pixel_centres_give_every_sample_back(dtype, channels, interpolation):
    image = _samples(dtype, channels)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    out = remap_stored(image, xx, yy, UndistortParams(interpolation))
    assert out.dtype == image.dtype and out.shape == image.shape
    np.testing.assert_array_equal(out, image)


@pytest.mark.parametrize("dtype", [np.int8, np.uint32, np.int32])
def test_types_opencv_does_not_remap_go_through_float64_and_round(dtype):
    image = _samples(dtype, 1)
    yy, xx = np.mgrid[0:H, 0 : W - 1].astype(np.float32)
    out = remap_stored(image, xx + 0.5, yy, UndistortParams("linear"))
    mean = (image[:, :-1].astype(np.float64) + image[:, 1:]) / 2
    np.testing.assert_array_equal(out, np.rint(mean).astype(dtype))
