"""Frame readers: DICOM (real ARCADIS frames, MONOCHROME1), TIFF bit depths, video; clear errors."""

from __future__ import annotations

import numpy as np
import pydicom
import pytest
from fluorocal.stages.errors import InputError
from fluorocal.stages.io import probe_frames, read_frames, read_phantom, write_still


def test_real_arcadis_dicom_reads_as_12_bit(arcadis_dir):
    path = arcadis_dir / "beads_centered_0.dcm"
    (frame,) = read_frames(path)
    raw = pydicom.dcmread(path).pixel_array
    assert frame.image.dtype == np.float32 and frame.image.shape == (1024, 1024)
    assert frame.bit_depth == 12 and frame.metadata["modality"] == "XA"
    assert np.array_equal(frame.image, raw.astype(np.float32))  # no rescale tags: modality LUT is identity
    assert probe_frames(path) == (1, (1024, 1024))


def test_monochrome1_and_multiframe_dicom(arcadis_dir, tmp_path):
    ds = pydicom.dcmread(arcadis_dir / "grid_centered_0.dcm")
    raw = ds.pixel_array[:64, :48].copy()
    ds.PhotometricInterpretation = "MONOCHROME1"
    ds.Rows, ds.Columns, ds.NumberOfFrames = 64, 48, 2
    ds.PixelData = np.stack([raw, raw // 2]).astype(np.uint16).tobytes()
    ds.RescaleSlope, ds.RescaleIntercept = 2, 10
    ds.save_as(tmp_path / "mf.dcm")
    frames = read_frames(tmp_path / "mf.dcm")
    assert len(frames) == 2 and probe_frames(tmp_path / "mf.dcm") == (2, (48, 64))
    # displayed 2 v + 10, inverted (MONOCHROME1): in stored steps above the darkest 12-bit value (stored 4095)
    np.testing.assert_array_equal(frames[0].image, 4095.0 - raw)
    np.testing.assert_array_equal(frames[1].image, 4095.0 - raw // 2)


@pytest.mark.parametrize("dtype, bits", [(np.uint8, 8), (np.uint16, 16), (np.float32, 32)])
def test_tiff_round_trip_keeps_values_and_depth(tmp_path, dtype, bits):
    img = (np.arange(30 * 20).reshape(30, 20) % 250).astype(dtype)
    write_still(tmp_path / "a.tif", img)
    (frame,) = read_frames(tmp_path / "a.tif")
    np.testing.assert_array_equal(frame.image, img.astype(np.float32))
    assert frame.bit_depth == bits


def test_png_and_video(tmp_path):
    import cv2

    img = (np.arange(32 * 24).reshape(24, 32) % 200).astype(np.uint8)
    write_still(tmp_path / "a.png", img)
    np.testing.assert_array_equal(read_frames(tmp_path / "a.png")[0].image, img)
    writer = cv2.VideoWriter(str(tmp_path / "v.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (32, 24), isColor=False)
    for k in range(3):
        writer.write(np.full((24, 32), 50 * (k + 1), np.uint8))
    writer.release()
    frames = read_frames(tmp_path / "v.avi")
    assert len(frames) == 3
    # MJPG is lossy: flat frames come back within a few DN
    assert [round(float(f.image.mean()) / 50) for f in frames] == [1, 2, 3]


def test_unreadable_files_name_the_file(tmp_path):
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"not an image")
    with pytest.raises(InputError, match="bad.tif: cannot read"):
        read_frames(bad)
    with pytest.raises(InputError, match="nope.dcm: no such file"):
        read_frames(tmp_path / "nope.dcm")


def test_phantom_csv(tmp_path):
    p = tmp_path / "p.csv"
    p.write_text("id,x,y,z,diameter,role\n1,0,0,0,3.5,\n2,1,2,3,5,marker\n3,9,0,0,3.5,\n4,0,9,0,3.5,\n")
    ph = read_phantom(p)
    assert ph.n_beads == 4 and list(ph.role) == ["", "marker", "", ""] and ph.xyz_mm[1].tolist() == [1, 2, 3]
    p.write_text("id,x,y\n1,0,0\n")
    with pytest.raises(InputError, match="missing z"):
        read_phantom(p)
    p.write_text("id,x,y,z\n1,0,zero,0\n")
    with pytest.raises(InputError, match=r"p.csv:2: not a number"):
        read_phantom(p)


@pytest.mark.parametrize(
    "stored, photometric",
    [
        (np.array([[-32768, -1, 0, 1, 32767]], np.int16), "minisblack"),
        (np.array([[0, 1, 4095, 65534, 65535]], np.uint16), "miniswhite"),
        (np.array([[-128, -1, 0, 5, 127]], np.int8), "miniswhite"),
        (np.array([[0, 1, 2, 65534, 65535]], np.uint16), "minisblack"),
    ],
)
def test_integer_tiff_displays_exact_steps_above_the_darkest_value(tmp_path, stored, photometric):
    """Displayed = stored steps above the darkest value the type holds (inverted for MinIsWhite), exactly."""
    import tifffile

    tifffile.imwrite(tmp_path / "f.tif", stored, photometric=photometric)
    (frame,) = read_frames(tmp_path / "f.tif")
    info = np.iinfo(stored.dtype)
    steps = [(info.max - v if photometric == "miniswhite" else v - info.min) for v in stored.ravel().tolist()]
    assert frame.image.dtype == np.float32
    assert frame.image.ravel().tolist() == [float(s) for s in steps]


@pytest.mark.parametrize("dtype", [np.uint16, np.int16])
@pytest.mark.parametrize("photometric", ["minisblack", "miniswhite"])
def test_every_16_bit_value_displays_as_its_exact_step(tmp_path, dtype, photometric):
    """All 65536 stored values of a 16-bit TIFF: displayed = steps above the darkest value, exact in float32."""
    import tifffile

    info = np.iinfo(dtype)
    stored = np.arange(info.min, info.max + 1, dtype=np.int64)
    tifffile.imwrite(tmp_path / "f.tif", stored.astype(dtype).reshape(256, 256), photometric=photometric)
    (frame,) = read_frames(tmp_path / "f.tif")
    steps = info.max - stored if photometric == "miniswhite" else stored - info.min
    assert frame.image.dtype == np.float32
    np.testing.assert_array_equal(frame.image.ravel().astype(np.int64), steps)
    np.testing.assert_array_equal(frame.image.ravel(), steps.astype(np.float64))


@pytest.mark.parametrize("maxval", [100, 200, 254, 1000, 4095, 40000, 65534])
def test_every_pgm_value_up_to_a_maxval_displays_as_itself(tmp_path, maxval):
    """A PGM's 0..maxval (not 2^n - 1; the decoder's scaled words less than 2 apart too) displayed as stored."""
    stored = np.zeros(-(-(maxval + 1) // 256) * 256, np.int64)
    stored[: maxval + 1] = np.arange(maxval + 1)
    dtype = ">u2" if maxval > 255 else "u1"
    header = f"P5\n256 {stored.size // 256}\n{maxval}\n".encode()
    (tmp_path / "f.pgm").write_bytes(header + stored.astype(dtype).tobytes())
    (frame,) = read_frames(tmp_path / "f.pgm")
    np.testing.assert_array_equal(frame.image.ravel(), stored.astype(np.float64))
