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
from fluorocal.stages.io import open_stored, probe_frames, read_frames, write_stored_like
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


_WHITE = np.array([[0, 1, 2, 100, 200, 250], [255, 254, 7, 128, 3, 60]], np.uint8)
#: MinIsWhite frames as tifffile stores them: (stored pages, the type's brightest-when-MinIsBlack value, options)
_MIN_IS_WHITE = {
    "uint8": ([_WHITE], 255, {}),
    "uint8 zlib, 2 pages": ([_WHITE, _WHITE[::-1]], 255, {"compression": "zlib"}),
    "uint16, 2 pages": ([_WHITE.astype(np.uint16) * 257, _WHITE.astype(np.uint16)], 65535, {}),
    "uint8 grey + alpha": ([np.stack([_WHITE, _WHITE[::-1]], axis=-1)], 255, {"extrasamples": ["unassalpha"]}),
    "1-bit": ([_WHITE % 2 == 1], 1, {}),
}


def _write_pages(path, pages, photometric, options) -> None:
    with tifffile.TiffWriter(path) as tif:
        for page in pages:
            tif.write(page, photometric=photometric, **options)


@pytest.mark.parametrize("case", list(_MIN_IS_WHITE))
def test_min_is_white_displays_as_min_is_black_of_the_inverted_values(tmp_path, case):
    """Stored 0 is white at every depth: the frame reads as the MinIsBlack file of ``high - stored`` does."""
    pages, high, options = _MIN_IS_WHITE[case]
    _write_pages(tmp_path / "w.tif", pages, "miniswhite", options)
    _write_pages(tmp_path / "b.tif", [~p if p.dtype == bool else high - p for p in pages], "minisblack", options)
    white, black = read_frames(tmp_path / "w.tif"), read_frames(tmp_path / "b.tif")
    assert len(white) == len(pages)
    for page, w, b in zip(pages, white, black, strict=True):
        grey = page[..., 0] if page.ndim == 3 else page
        np.testing.assert_array_equal(w.image, high - grey.astype(np.float32))  # exact: integers below 2**24
        np.testing.assert_array_equal(w.image, b.image)


@pytest.mark.parametrize("case", [c for c in _MIN_IS_WHITE if c != "1-bit"])
def test_min_is_white_is_written_back_as_stored(tmp_path, case):
    """open_stored gives tifffile's stored values; written back they are the same values, type and photometric."""
    pages, high, options = _MIN_IS_WHITE[case]
    _write_pages(tmp_path / "w.tif", pages, "miniswhite", options)
    stored = open_stored(tmp_path / "w.tif")
    assert stored.black == high
    frames = list(stored.frames)
    for page, frame in zip(pages, frames, strict=True):
        np.testing.assert_array_equal(frame, page)
    write_stored_like(tmp_path / "w.tif", iter(frames), tmp_path / "out.tif", len(frames))
    with tifffile.TiffFile(tmp_path / "out.tif", mode="r+b") as tif:  # LZW: tifffile cannot decode it here
        assert [p.photometric for p in tif.pages] == [tifffile.PHOTOMETRIC.MINISWHITE] * len(pages)
        assert [p.dtype for p in tif.pages] == [page.dtype for page in pages]
        for written in tif.pages:
            written.tags["PhotometricInterpretation"].overwrite(1)  # MinIsBlack: its bytes read as they are
    for page, written in zip(pages, open_stored(tmp_path / "out.tif").frames, strict=True):
        np.testing.assert_array_equal(written, page)


def test_min_is_white_4_bit_displays_inverted(tmp_path):
    """4-bit samples (tifffile cannot write them here): OpenImageIO's MinIsBlack file, its nibbles checked, retagged."""
    import OpenImageIO as oiio

    nibbles = np.array([[0, 1, 2, 7, 8, 15]], np.uint8)
    path = str(tmp_path / "w.tif")
    spec = oiio.ImageSpec(6, 1, 1, "uint8")
    spec.attribute("oiio:BitsPerSample", 4)
    spec.attribute("compression", "none")
    out = oiio.ImageOutput.create(path)
    assert out.open(path, spec) and out.write_image((nibbles * 17).reshape(1, 6, 1)) and out.close()
    with tifffile.TiffFile(path, mode="r+b") as tif:
        page = tif.pages[0]
        assert page.bitspersample == 4
        tif.filehandle.seek(page.dataoffsets[0])
        assert tif.filehandle.read(3) == bytes([0x01, 0x27, 0x8F])  # the stored nibbles, packed
        page.tags["PhotometricInterpretation"].overwrite(0)
    (frame,) = read_frames(tmp_path / "w.tif")
    assert frame.bit_depth == 4
    np.testing.assert_array_equal(frame.image, 15.0 - nibbles)
