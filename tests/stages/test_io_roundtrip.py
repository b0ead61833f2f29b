"""One reader for every command: a frame displays the same whatever sign, rescale, byte order or photometric stores it.

``read_frames`` (detect, run, check) shows the frames ``open_stored`` (undistort) decodes. The
modality LUT of a DICOM (RescaleSlope/Intercept) is affine, so its frame is its displayed value in
stored steps above the darkest value the file can hold: the same pixels stored any other way read
the same, and detection finds the same beads. The ground truth is the real ARCADIS frame's stored
pixels (pydicom) and arrays written here with tifffile.
"""

from __future__ import annotations

import warnings

import numpy as np
import pydicom
import pytest
import tifffile
from fluorocal.stages.detect import DetectParams, detect_beads
from fluorocal.stages.errors import InputError
from fluorocal.stages.io import open_stored, probe_frames, read_frames
from pydicom import uid


def _copy(source, path, stored: np.ndarray, *, transfer=uid.ExplicitVRLittleEndian, **tags) -> None:
    """The real frame's data set with ``stored`` pixels (int16: signed), ``tags`` and ``transfer`` syntax."""
    ds = pydicom.dcmread(source)
    ds.PixelRepresentation = int(stored.dtype == np.int16)
    for tag, value in tags.items():
        setattr(ds, tag, value)
    ds.file_meta.TransferSyntaxUID = transfer
    order = ">" if transfer == uid.ExplicitVRBigEndian else "<"
    ds.PixelData = stored.astype(order + stored.dtype.str[1:]).tobytes()
    pydicom.dcmwrite(path, ds, enforce_file_format=True, little_endian=order == "<", implicit_vr=False)


@pytest.fixture(scope="module")
def real(arcadis_dir):
    """A real 12-bit ARCADIS bead frame: its path and stored pixels."""
    path = arcadis_dir / "beads_centered_0.dcm"
    return path, pydicom.dcmread(path).pixel_array


def _beads(path) -> np.ndarray:
    (frame,) = read_frames(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a frame's empty-frame warning would fail the test: counted below
        found = detect_beads(frame, DetectParams())
    return found.xy_px[found.accepted]


VARIANTS = {
    # name: (stored pixels from the real ones, tags, transfer syntax)
    "slope 2 intercept -1000": (lambda raw: raw, {"RescaleSlope": 2, "RescaleIntercept": -1000}, None),
    "signed, intercept 2048": (
        lambda raw: raw.astype(np.int16) - 2048,
        {"RescaleSlope": 1, "RescaleIntercept": 2048},
        None,
    ),
    "signed, no rescale": (lambda raw: raw.astype(np.int16) - 2048, {}, None),
    "big endian": (lambda raw: raw, {}, uid.ExplicitVRBigEndian),
    "deflated": (lambda raw: raw, {}, uid.DeflatedExplicitVRLittleEndian),
}


@pytest.mark.parametrize("name", list(VARIANTS))
def test_a_dicom_reads_as_its_pixels_stored_as_tiff_and_finds_the_same_beads(real, tmp_path, name):
    source, raw = real
    stored_of, tags, transfer = VARIANTS[name]
    stored = stored_of(raw)
    _copy(source, tmp_path / "v.dcm", stored, transfer=transfer or uid.ExplicitVRLittleEndian, **tags)
    tifffile.imwrite(tmp_path / "v.tif", raw)  # the same pixels, 12-bit values in a 16-bit TIFF
    (dicom,), (tiff,) = read_frames(tmp_path / "v.dcm"), read_frames(tmp_path / "v.tif")
    np.testing.assert_array_equal(dicom.image, tiff.image)
    assert dicom.bit_depth == 12
    # the one decoder: undistort's stored frames are the file's stored values, in its own sign
    stored_frames = open_stored(tmp_path / "v.dcm")
    (again,) = list(stored_frames.frames)
    assert again.dtype == stored.dtype and np.array_equal(again, stored)
    # the darkest stored value: the border undistort fills with
    assert stored_frames.black == (-2048 if stored.dtype == np.int16 else 0)
    beads = _beads(tmp_path / "v.dcm")
    assert len(beads) > 0  # not a blank frame
    np.testing.assert_array_equal(beads, _beads(tmp_path / "v.tif"))
    np.testing.assert_array_equal(beads, _beads(source))  # and the beads of the file as the C-arm wrote it


def test_monochrome1_reads_inverted_over_its_stored_bits(real, tmp_path):
    source, raw = real
    _copy(source, tmp_path / "m1.dcm", 4095 - raw, PhotometricInterpretation="MONOCHROME1")
    (frame,) = read_frames(tmp_path / "m1.dcm")
    np.testing.assert_array_equal(frame.image, raw.astype(np.float32))
    assert open_stored(tmp_path / "m1.dcm").black == 4095


def test_stills_read_as_displayed(tmp_path):
    rng = np.random.default_rng(5)
    grey = rng.integers(0, 4096, (24, 32)).astype(np.uint16)
    # MinIsWhite: stored 0 is white
    tifffile.imwrite(tmp_path / "w.tif", grey, photometric="miniswhite")
    (frame,) = read_frames(tmp_path / "w.tif")
    np.testing.assert_array_equal(frame.image, 65535.0 - grey)
    assert open_stored(tmp_path / "w.tif").black == 65535
    # int16: offset by the type's smallest value, larger = brighter
    tifffile.imwrite(tmp_path / "s.tif", grey.astype(np.int16) - 2048)
    (frame,) = read_frames(tmp_path / "s.tif")
    np.testing.assert_array_equal(frame.image, grey + 32768.0 - 2048)
    # PGM of maxval 4095: the stored values, 12 bits
    (tmp_path / "g.pgm").write_bytes(b"P5\n32 24\n4095\n" + grey.astype(">u2").tobytes())
    (frame,) = read_frames(tmp_path / "g.pgm")
    assert frame.bit_depth == 12
    np.testing.assert_array_equal(frame.image, grey.astype(np.float32))
    # RGBA 16-bit with unassociated alpha: the luma of the colour as stored, not premultiplied
    rgba = rng.integers(0, 65536, (24, 32, 4)).astype(np.uint16)
    tifffile.imwrite(tmp_path / "c.tif", rgba, photometric="rgb", extrasamples=["unassalpha"])
    (frame,) = read_frames(tmp_path / "c.tif")
    luma = rgba[..., :3] @ np.array([0.299, 0.587, 0.114])
    np.testing.assert_allclose(frame.image, luma, rtol=1e-6)  # float32 rounding of values below 65536


def test_what_undistort_refuses_is_still_read_for_detection(tmp_path):
    half = (np.arange(24 * 32).reshape(24, 32) % 2000).astype(np.float16)
    tifffile.imwrite(tmp_path / "h.tif", half)
    (frame,) = read_frames(tmp_path / "h.tif")
    np.testing.assert_array_equal(frame.image, half.astype(np.float32))
    with pytest.raises(InputError, match="h.tif: half-float samples cannot be written back as stored"):
        open_stored(tmp_path / "h.tif")


def test_pages_of_two_sizes_are_refused_by_every_reader(tmp_path):
    with tifffile.TiffWriter(tmp_path / "two.tif") as tif:
        tif.write(np.zeros((64, 64), np.uint16))
        tif.write(np.zeros((32, 48), np.uint16))
    for call in (probe_frames, read_frames, open_stored):
        with pytest.raises(InputError, match=r"two.tif: pages differ \(48x32 px uint16 x1, 64x64 px uint16 x1\)"):
            call(tmp_path / "two.tif")
