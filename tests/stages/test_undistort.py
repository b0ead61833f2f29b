"""Undistortion by inverse maps, and writing frames back in their own format and bit depth."""

from __future__ import annotations

import numpy as np
import pydicom
import pytest
from fluorocal.stages.artifacts import Radiograph
from fluorocal.stages.errors import InputError, ShapeError
from fluorocal.stages.io import read_frames, write_frames_like, write_still
from fluorocal.stages.undistort import UndistortParams, undistort_frame


def _grid(h, w):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    return xx, yy


def _smooth_image(h=40, w=50):
    yy, xx = np.mgrid[0:h, 0:w]
    return (1000 + 300 * np.sin(xx / 7.0) * np.cos(yy / 9.0)).astype(np.float32)


@pytest.mark.parametrize("interp", ["nearest", "linear", "cubic", "lanczos"])
def test_identity_maps_reproduce_the_frame(interp):
    img = Radiograph(_smooth_image(), 12)
    out = undistort_frame(img, *_grid(40, 50), UndistortParams(interpolation=interp))
    np.testing.assert_allclose(out.image, img.image, atol=1e-3)  # exact up to float32 kernel sums
    assert out.bit_depth == 12 and out.metadata["undistorted"]


def test_integer_shift_moves_content_and_fills_border():
    img = Radiograph(_smooth_image(), 12)
    xx, yy = _grid(40, 50)
    out = undistort_frame(img, xx + 3, yy - 2, UndistortParams(border_value=0))
    # output (x, y) reads the source at (x + 3, y - 2)
    np.testing.assert_allclose(out.image[2:, :-3], img.image[:-2, 3:], atol=1e-3)
    assert np.all(out.image[:2, :] == 0) and np.all(out.image[:, -3:] == 0)


def test_subpixel_shift_of_a_linear_ramp_is_exact_with_linear_interpolation():
    ramp = np.tile(np.arange(50, dtype=np.float32) * 10, (40, 1))
    xx, yy = _grid(40, 50)
    out = undistort_frame(Radiograph(ramp, 16), xx + 0.25, yy, UndistortParams())
    # bilinear interpolation of a linear ramp is exact; OpenCV's 5-bit sub-pixel table quantises 0.25 exactly
    np.testing.assert_allclose(out.image[:, :-1], ramp[:, :-1] + 2.5, atol=1e-3)


def test_bad_maps_and_params():
    img = Radiograph(_smooth_image(), 12)
    xx, yy = _grid(40, 50)
    with pytest.raises(ShapeError, match="map_x and map_y"):
        undistort_frame(img, xx, yy[:-1], UndistortParams())
    with pytest.raises(InputError, match="interpolation must be one of"):
        undistort_frame(img, xx, yy, UndistortParams(interpolation="spline"))


def test_tiff_written_in_source_dtype(tmp_path):
    src = tmp_path / "in.tif"
    write_still(src, (np.arange(40 * 50).reshape(40, 50) % 4096).astype(np.uint16))
    (frame,) = read_frames(src)
    write_frames_like(src, [frame], tmp_path / "out.tif")
    (back,) = read_frames(tmp_path / "out.tif")
    np.testing.assert_array_equal(back.image, frame.image)
    assert back.bit_depth == 16


def test_dicom_written_like_the_source(arcadis_dir, tmp_path):
    src = arcadis_dir / "spine_centered_0.dcm"
    (frame,) = read_frames(src)
    xx, yy = _grid(*frame.shape)
    out = undistort_frame(frame, xx, yy, UndistortParams())
    write_frames_like(src, [out], tmp_path / "u.dcm")
    ds_in, ds_out = pydicom.dcmread(src), pydicom.dcmread(tmp_path / "u.dcm")
    assert ds_out.BitsStored == ds_in.BitsStored == 12 and ds_out.Rows == 1024
    assert ds_out.SOPInstanceUID != ds_in.SOPInstanceUID and ds_out.PatientID == ds_in.PatientID
    assert "fluorocal" in ds_out.DerivationDescription
    np.testing.assert_array_equal(ds_out.pixel_array, ds_in.pixel_array)  # identity maps: same pixels


def test_maps_moving_pixels_beyond_the_image_are_refused():
    from fluorocal.stages.undistort import check_maps

    xx, yy = _grid(40, 50)
    check_maps(xx + 3, yy - 2)  # a few pixels: a real correction
    with pytest.raises(InputError, match="moves pixels by up to 1e\\+30 px"):
        check_maps(xx + 1e30, yy)
    with pytest.raises(InputError, match="moves pixels by up to 25 px"):  # half of the 50 px side is too far
        check_maps(xx + 25, yy)
    nan = yy.copy()
    nan[3, 4] = np.nan
    with pytest.raises(InputError, match="not finite"):
        check_maps(xx, nan)
