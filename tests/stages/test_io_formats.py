"""The frame-format registry: sniffing by content then suffix, one-line errors, the one DICOM and PNG writers."""

from __future__ import annotations

import numpy as np
import pydicom
import pytest
from fluorocal.stages.errors import InputError
from fluorocal.stages.io import (
    FORMATS,
    FrameFormat,
    atomic_write,
    frame_format,
    probe_frames,
    read_frames,
    write_dicom,
    write_frames_like,
    write_png,
    write_still,
)
from fluorocal.stages.io.atomic import PNG_SIGNATURE
from fluorocal.stages.io.frames import DICOM, STILL, VIDEO

from tests.helpers import xa_dataset


def test_registry_is_a_tuple_of_entries_in_code():
    assert isinstance(FORMATS, tuple) and FORMATS == (DICOM, VIDEO, STILL)
    assert all(isinstance(f, FrameFormat) and callable(f.read) and callable(f.write_like) for f in FORMATS)


def test_write_dicom_single_and_multi_frame(tmp_path):
    pixels = (np.arange(3 * 20 * 16).reshape(3, 20, 16) % 4096).astype(np.uint16)
    write_dicom(tmp_path / "one.dcm", xa_dataset(20, 16), pixels[0])
    write_dicom(tmp_path / "three.dcm", xa_dataset(20, 16), pixels)
    assert probe_frames(tmp_path / "one.dcm") == (1, (16, 20))
    assert probe_frames(tmp_path / "three.dcm") == (3, (16, 20))
    frames = read_frames(tmp_path / "three.dcm")
    assert [f.bit_depth for f in frames] == [12] * 3 and frames[0].metadata["ImagerPixelSpacing"] == [0.25, 0.25]
    np.testing.assert_array_equal(np.stack([f.image for f in frames]), pixels.astype(np.float32))
    with pytest.raises(InputError, match=r"bad.dcm: pixels must have shape \(\[F,\] 20, 16\); got \(16, 20\)"):
        write_dicom(tmp_path / "bad.dcm", xa_dataset(20, 16), pixels[0].T)
    assert not (tmp_path / "bad.dcm").exists()


def test_content_decides_before_the_suffix(tmp_path):
    img = (np.arange(12 * 10).reshape(12, 10) * 7).astype(np.uint16)
    write_dicom(tmp_path / "really_dicom.tif", xa_dataset(12, 10, bits_stored=16), img)
    write_still(tmp_path / "really_tiff.dcm", img, file_format="tiff")
    assert frame_format(tmp_path / "really_dicom.tif") is DICOM
    assert frame_format(tmp_path / "really_tiff.dcm") is STILL
    (dcm,) = read_frames(tmp_path / "really_dicom.tif")
    (tif,) = read_frames(tmp_path / "really_tiff.dcm")
    assert dcm.metadata["format"] == "dicom" and tif.metadata["format"] == "tiff"
    np.testing.assert_array_equal(dcm.image, tif.image)
    write_frames_like(tmp_path / "really_tiff.dcm", [tif], tmp_path / "out.dcm")  # a TIFF, as its source
    assert frame_format(tmp_path / "out.dcm") is STILL and read_frames(tmp_path / "out.dcm")[0].bit_depth == 16


def test_suffix_decides_when_no_signature_matches(tmp_path):
    bad = tmp_path / "garbage.png"
    bad.write_bytes(b"not an image at all")
    assert frame_format(bad) is STILL
    with pytest.raises(InputError, match="garbage.png: cannot read"):
        read_frames(bad)


def test_unknown_format_is_one_line_naming_the_file_and_the_formats(tmp_path):
    odd = tmp_path / "notes.xyz"
    odd.write_text("hello")
    for call in (read_frames, probe_frames, frame_format):
        with pytest.raises(InputError) as err:
            call(odd)
        message = str(err.value)
        assert "\n" not in message and message.startswith(f"{odd}: not a frame format")
        assert all(f.name in message for f in FORMATS) and ".dcm" in message and ".avi" in message
    with pytest.raises(InputError, match="nope.tif: no such file"):
        probe_frames(tmp_path / "nope.tif")


def test_video_probe_counts_what_read_returns(tmp_path):
    import cv2

    writer = cv2.VideoWriter(str(tmp_path / "v.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (32, 24), isColor=False)
    for k in range(4):
        writer.write(np.full((24, 32), 40 * (k + 1), np.uint8))
    writer.release()
    # a video named like a still is still a video: AVI's RIFF signature decides
    (tmp_path / "v.avi").rename(tmp_path / "v.png")
    assert frame_format(tmp_path / "v.png") is VIDEO
    assert probe_frames(tmp_path / "v.png") == (len(read_frames(tmp_path / "v.png")), (32, 24)) == (4, (32, 24))


@pytest.mark.parametrize("dtype, bits", [(np.uint8, 8), (np.uint16, 16)])
def test_still_written_like_its_source_keeps_type_and_depth(tmp_path, dtype, bits):
    img = (np.arange(20 * 30).reshape(20, 30) % 250).astype(dtype)
    write_still(tmp_path / "src.tif", img)
    frames = read_frames(tmp_path / "src.tif")
    write_frames_like(tmp_path / "src.tif", frames, tmp_path / "out.tif")
    (back,) = read_frames(tmp_path / "out.tif")
    assert back.bit_depth == bits and back.metadata["format"] == "tiff"
    np.testing.assert_array_equal(back.image, img.astype(np.float32))
    with pytest.raises(InputError, match="writing 2 frames to a still image"):
        write_frames_like(tmp_path / "src.tif", frames * 2, tmp_path / "two.tif")


def test_real_dicom_written_like_keeps_tags(arcadis_dir, tmp_path):
    src = arcadis_dir / "beads_centered_0.dcm"
    frames = read_frames(src)
    write_frames_like(src, frames, tmp_path / "u.dcm")
    a, b = pydicom.dcmread(src), pydicom.dcmread(tmp_path / "u.dcm")
    assert b.SOPInstanceUID != a.SOPInstanceUID and b.ImageType[:2] == ["DERIVED", "SECONDARY"]
    assert (b.Rows, b.Columns, b.BitsStored, b.Modality) == (a.Rows, a.Columns, a.BitsStored, a.Modality)
    np.testing.assert_array_equal(b.pixel_array, a.pixel_array)


def test_write_png_from_an_array_or_encoded_bytes(tmp_path):
    import cv2

    bgr = np.zeros((8, 10, 3), np.uint8)
    bgr[2:5, 3:7] = (10, 200, 30)
    write_png(tmp_path / "a.png", bgr)
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "a.png")), bgr)
    encoded = (tmp_path / "a.png").read_bytes()
    assert encoded.startswith(PNG_SIGNATURE)
    write_png(tmp_path / "b.png", encoded)
    assert (tmp_path / "b.png").read_bytes() == encoded
    with pytest.raises(InputError, match="c.png: the bytes given are not a PNG"):
        write_png(tmp_path / "c.png", b"GIF89a")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.png"]  # no temporary file left


def test_atomic_write_leaves_nothing_when_the_writer_fails(tmp_path):
    def _fail(tmp):
        with open(tmp, "w") as fh:
            fh.write("half")
        raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError):
        atomic_write(tmp_path / "x.csv", _fail)
    assert list(tmp_path.iterdir()) == []


def _multi_frame_files(tmp_path) -> dict:
    """The same 4 distinct frames as a multi-frame DICOM, a 4-page TIFF and an AVI (lossless: raw grey)."""
    import cv2
    import OpenImageIO as oiio

    pixels = np.stack([(np.arange(24 * 32).reshape(24, 32) * (k + 1)) % 250 for k in range(4)]).astype(np.uint16)
    write_dicom(tmp_path / "m.dcm", xa_dataset(24, 32), pixels)
    spec = oiio.ImageSpec(32, 24, 1, "uint16")
    out = oiio.ImageOutput.create(str(tmp_path / "m.tif"))
    assert out.open(str(tmp_path / "m.tif"), [spec] * 4)
    for k in range(4):
        if k:
            assert out.open(str(tmp_path / "m.tif"), spec, "appendsubimage")
        assert out.write_image(pixels[k][..., None])
    out.close()
    writer = cv2.VideoWriter(str(tmp_path / "m.avi"), cv2.VideoWriter_fourcc(*"FFV1"), 10, (32, 24), isColor=False)
    for k in range(4):
        writer.write(pixels[k].astype(np.uint8))
    writer.release()
    return {"m.dcm": DICOM, "m.tif": STILL, "m.avi": VIDEO}


@pytest.mark.parametrize("name", ["m.dcm", "m.tif", "m.avi"])
def test_reading_some_frames_gives_exactly_those_of_a_full_read(tmp_path, name):
    """A pool worker reads only its frames of a multi-frame file: they must equal the full read's, bit for bit."""
    formats = _multi_frame_files(tmp_path)
    path = tmp_path / name
    assert frame_format(path) is formats[name]
    every = read_frames(path)
    assert len(every) == 4 and len({f.image.tobytes() for f in every}) == 4  # four distinct frames
    some = read_frames(path, [2, 0, 3])
    assert [f.frame_index for f in some] == [2, 0, 3]
    for got, want in zip(some, (every[2], every[0], every[3])):
        np.testing.assert_array_equal(got.image, want.image)
        assert got.image.dtype == want.image.dtype and got.bit_depth == want.bit_depth
        assert got.metadata == want.metadata and got.source == want.source
    assert read_frames(path, []) == []
    with pytest.raises(InputError, match=rf"^{path}: holds .*frame.*; frame 4 asked for$"):
        read_frames(path, [1, 4])
    with pytest.raises(InputError, match=rf"^{path}: frames are numbered from 0; frame -1 asked for$"):
        read_frames(path, [-1])
    for bad in (1.7, True):  # never rounded or taken as a number: an index is an integer
        with pytest.raises(InputError, match="frame indices must be integers"):
            read_frames(path, [bad])
