"""`fluorocal undistort` writes every pixel type back exactly as it came, or refuses it in one line.

With a zero correction field the inverse maps are the pixel centres themselves (checked below), and
a remap at pixel centres reproduces every sample: each lossless type must come back sample for sample,
with its header (sample type, channels, photometric, maxval, rescale, signedness) unchanged. The
outputs are read back with other readers than fluorocal's where one exists (pydicom, tifffile's tags,
raw PGM bytes, OpenCV), and otherwise with OpenImageIO asked for the samples as stored.
"""

from __future__ import annotations

import os
import subprocess
import sys

import cv2
import numpy as np
import pydicom
import pytest
import tifffile
from fluorocal.calibration import Calibration, SystemCalibration
from fluorocal.cli import main
from pydicom import uid

from tests.helpers import save_dicom
from tests.pipeline.synthetic_calibration import H, W, smooth_field


@pytest.fixture()
def identity(tmp_path):
    """A calibration of one system at W x H whose correction field is zero everywhere; its path."""
    iop = np.array([W / 2, H / 2, 1000.0])
    system = SystemCalibration("A", (W, H), iop, np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3), smooth_field(0.0))
    cal = Calibration([system], {}, {"scheme": "test"})
    map_x, map_y = cal.remap_maps("A")
    yy, xx = np.mgrid[0:H, 0:W]
    # the premise of every exact comparison below: a zero field maps each output pixel centre to itself
    assert np.array_equal(map_x, xx) and np.array_equal(map_y, yy)
    path = tmp_path / "cal" / "calibration.json"
    path.parent.mkdir()
    cal.save(path)
    return path


def _undistort(calibration, out, *inputs):
    # --outside keep: the round trip is about the samples' type; the edges' background has its own tests
    args = ["--quiet", "undistort", str(calibration), *map(str, inputs), "--system", "A"]
    return main(args + ["--outside", "keep", "--out", str(out)])


def _ramp(dtype, channels: int = 0, seed: int = 0) -> np.ndarray:
    """Samples spanning ``dtype``'s whole range (its extremes included) in a known pseudo-random order."""
    shape = (H, W, channels) if channels else (H, W)
    rng = np.random.default_rng(seed)
    if np.dtype(dtype).kind == "f":
        values = rng.normal(0, 1000, shape)
        values.flat[:3] = [0.0, -1e30, 1e-30]
        return values.astype(dtype)
    info = np.iinfo(dtype)
    values = rng.integers(info.min, info.max, shape, dtype=np.int64, endpoint=True)
    values.flat[:2] = [info.min, info.max]
    return values.astype(dtype)


def _oiio_samples(path, page: int = 0) -> np.ndarray:
    """The samples of a still as stored (alpha not premultiplied), through OpenImageIO."""
    import OpenImageIO as oiio

    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    assert inp.seek_subimage(page, 0)
    pixels = np.asarray(inp.read_image(str(inp.spec().format)))
    inp.close()
    return pixels[..., 0] if pixels.shape[-1] == 1 else pixels


def _tiff_header(path) -> tuple:
    """Photometric, samples per pixel, extra samples (alpha kind) and sample type of each page, by tifffile."""
    with tifffile.TiffFile(path) as tif:
        return [(p.photometric, p.samplesperpixel, p.extrasamples, p.dtype) for p in tif.pages]


# --- stills -------------------------------------------------------------------------------------------


def _tiff(**kwargs):
    def make(path, data):
        tifffile.imwrite(path, data, **kwargs)

    return make


STILLS = {
    # name: (suffix, samples, writer)
    "tiff uint8": (".tif", _ramp(np.uint8), _tiff()),
    "tiff uint16": (".tif", _ramp(np.uint16), _tiff()),
    "tiff int16": (".tif", _ramp(np.int16), _tiff()),
    "tiff uint32": (".tif", _ramp(np.uint32), _tiff()),
    "tiff int32": (".tif", _ramp(np.int32), _tiff()),
    "tiff float32": (".tif", _ramp(np.float32), _tiff()),
    "tiff float64": (".tif", _ramp(np.float64), _tiff()),
    "tiff MinIsWhite uint16": (".tif", _ramp(np.uint16), _tiff(photometric="miniswhite")),
    "tiff RGB uint8": (".tif", _ramp(np.uint8, 3), _tiff(photometric="rgb")),
    "tiff grey+alpha uint16": (
        ".tif",
        _ramp(np.uint16, 2),
        _tiff(photometric="minisblack", extrasamples=["unassalpha"]),
    ),
    "tiff RGBA uint16 unassociated": (
        ".tif",
        _ramp(np.uint16, 4),
        _tiff(photometric="rgb", extrasamples=["unassalpha"]),
    ),
    "png grey uint16": (".png", _ramp(np.uint16), lambda p, d: cv2.imwrite(str(p), d)),
    "png RGB uint8": (".png", _ramp(np.uint8, 3), lambda p, d: cv2.imwrite(str(p), d)),
    "png RGBA uint16": (".png", _ramp(np.uint16, 4), lambda p, d: cv2.imwrite(str(p), d)),
}


@pytest.mark.parametrize("name", list(STILLS))
def test_a_still_comes_back_sample_for_sample_in_its_own_type(identity, tmp_path, name):
    suffix, samples, make = STILLS[name]
    source = tmp_path / f"in{suffix}"
    make(source, samples)
    assert _undistort(identity, tmp_path / "out", source) == 0
    out = tmp_path / "out" / source.name
    stored = _oiio_samples(source)
    if suffix == ".tif":  # the samples as tifffile wrote them (PNG: OpenCV wrote BGR(A), read below)
        np.testing.assert_array_equal(stored, samples)
    back = _oiio_samples(out)
    assert back.dtype == stored.dtype and back.shape == stored.shape
    np.testing.assert_array_equal(back, stored)
    if suffix == ".tif":
        assert _tiff_header(out) == _tiff_header(source)
    else:  # PNG: OpenCV reads the channels as stored (BGR order) in both
        np.testing.assert_array_equal(cv2.imread(str(out), cv2.IMREAD_UNCHANGED), samples)


def test_a_multi_page_tiff_comes_back_page_for_page(identity, tmp_path):
    pages = [_ramp(np.uint16, seed=k) for k in range(3)]
    source = tmp_path / "cine.tif"
    with tifffile.TiffWriter(source) as tif:
        for page in pages:
            tif.write(page)
    assert _undistort(identity, tmp_path / "out", source) == 0
    out = tmp_path / "out" / "cine.tif"
    assert len(_tiff_header(out)) == 3
    for k, page in enumerate(pages):
        np.testing.assert_array_equal(_oiio_samples(out, k), page)


@pytest.mark.parametrize("maxval", [255, 4095, 65535, 1000])
def test_a_pgm_keeps_its_maxval_and_stored_values(identity, tmp_path, maxval):
    rng = np.random.default_rng(maxval)
    samples = rng.integers(0, maxval, (H, W), endpoint=True)
    samples.flat[:2] = [0, maxval]
    word = ">u2" if maxval > 255 else "u1"
    source = tmp_path / "in.pgm"
    source.write_bytes(b"P5\n# a comment\n%d %d\n%d\n" % (W, H, maxval) + samples.astype(word).tobytes())
    assert _undistort(identity, tmp_path / "out", source) == 0
    data = (tmp_path / "out" / "in.pgm").read_bytes()
    header = b"P5\n%d %d\n%d\n" % (W, H, maxval)
    assert data.startswith(header)
    np.testing.assert_array_equal(np.frombuffer(data[len(header) :], word).reshape(H, W), samples)


def test_a_jpeg_is_refused_as_lossy(identity, tmp_path, capsys):
    # re-encoding a JPEG (at any quality) cannot give its samples back: refused, with what to do
    source = tmp_path / "in.jpg"
    cv2.imwrite(str(source), _ramp(np.uint8, 3), [cv2.IMWRITE_JPEG_QUALITY, 100])
    _assert_refused(
        identity,
        tmp_path,
        capsys,
        source,
        "JPEG is lossy: its frames cannot be written back as they came; convert it to TIFF or PNG first",
    )


# --- DICOM --------------------------------------------------------------------------------------------


def _dicom(path, samples, *, transfer=uid.ExplicitVRLittleEndian, **tags):
    """A DICOM of ``samples`` (H, W) as stored (int16: signed), in ``transfer`` syntax, with ``tags``."""
    signed = samples.dtype.kind == "i"
    ds = save_dicom(path, np.zeros((1, H, W), np.uint16), PixelRepresentation=int(signed), Rows=H, Columns=W, **tags)
    ds.file_meta.TransferSyntaxUID = transfer
    order = ">" if transfer == uid.ExplicitVRBigEndian else "<"
    ds.PixelData = samples.astype(order + samples.dtype.str[1:]).tobytes()
    pydicom.dcmwrite(path, ds, enforce_file_format=True, little_endian=order == "<", implicit_vr=False)


DICOMS = {
    # name: (stored samples, tags, transfer syntax)
    "unsigned 12-bit": (_ramp(np.uint16) % 4096, {}, uid.ExplicitVRLittleEndian),
    "MONOCHROME1": (_ramp(np.uint16) % 4096, {"PhotometricInterpretation": "MONOCHROME1"}, uid.ExplicitVRLittleEndian),
    "slope 2 intercept -1000": (
        _ramp(np.uint16) % 4096,
        {"RescaleSlope": 2, "RescaleIntercept": -1000},
        uid.ExplicitVRLittleEndian,
    ),
    "signed 12-bit": (
        (_ramp(np.uint16) % 4096).astype(np.int16) - 2048,
        {"BitsStored": 12, "HighBit": 11},
        uid.ExplicitVRLittleEndian,
    ),
    "signed 16-bit with intercept": (
        _ramp(np.int16),
        {"BitsStored": 16, "HighBit": 15, "RescaleIntercept": 1024, "RescaleSlope": 1},
        uid.ExplicitVRLittleEndian,
    ),
    "8-bit": (_ramp(np.uint8), {"BitsAllocated": 8, "BitsStored": 8, "HighBit": 7}, uid.ExplicitVRLittleEndian),
    "big endian": (_ramp(np.uint16) % 4096, {}, uid.ExplicitVRBigEndian),
    "deflated": (_ramp(np.uint16) % 4096, {}, uid.DeflatedExplicitVRLittleEndian),
}


@pytest.mark.parametrize("name", list(DICOMS))
def test_a_dicom_comes_back_with_its_stored_values_and_representation(identity, tmp_path, name):
    samples, tags, transfer = DICOMS[name]
    source = tmp_path / "in.dcm"
    _dicom(source, samples, transfer=transfer, **tags)
    assert _undistort(identity, tmp_path / "out", source) == 0
    back = pydicom.dcmread(tmp_path / "out" / "in.dcm")
    original = pydicom.dcmread(source)
    for tag in ("PixelRepresentation", "BitsAllocated", "BitsStored", "PhotometricInterpretation"):
        assert back.get(tag) == original.get(tag), tag
    for tag in ("RescaleSlope", "RescaleIntercept"):
        assert float(back.get(tag, 0)) == float(original.get(tag, 0)), tag
    assert back.pixel_array.dtype == samples.dtype
    np.testing.assert_array_equal(back.pixel_array, samples)


def test_colour_dicom_is_refused(identity, tmp_path, capsys):
    source = tmp_path / "rgb.dcm"
    ds = save_dicom(source, np.zeros((1, H, W), np.uint16), Rows=H, Columns=W)
    ds.PhotometricInterpretation, ds.SamplesPerPixel, ds.PlanarConfiguration = "RGB", 3, 0
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 8, 8, 7
    ds.PixelData = np.zeros((H, W, 3), np.uint8).tobytes()
    ds.save_as(source, enforce_file_format=True)
    _assert_refused(identity, tmp_path, capsys, source, "DICOM RGB frames are not supported")


# --- video --------------------------------------------------------------------------------------------


def test_a_lossless_video_comes_back_frame_for_frame(identity, tmp_path):
    frames = [_ramp(np.uint8, seed=k) for k in range(5)]
    source = tmp_path / "cine.avi"
    writer = cv2.VideoWriter(str(source), cv2.VideoWriter_fourcc(*"FFV1"), 10, (W, H), isColor=False)
    assert writer.isOpened()
    for frame in frames:
        writer.write(frame)
    writer.release()
    assert _undistort(identity, tmp_path / "out", source) == 0
    cap = cv2.VideoCapture(str(tmp_path / "out" / "cine.avi"))
    fourcc = int(cap.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").decode()
    assert fourcc.upper() == "FFV1"  # the source's codec (FFmpeg reports it in lower case)
    back = []
    while (got := cap.read())[0]:
        back.append(cv2.cvtColor(got[1], cv2.COLOR_BGR2GRAY))
    cap.release()
    assert len(back) == len(frames)
    for frame, again in zip(frames, back):
        np.testing.assert_array_equal(again, frame)


def _video(path, fourcc, frames, *, colour=False):
    writer = cv2.VideoWriter(str(path), fourcc, 10, (W, H), isColor=colour)
    assert writer.isOpened()
    for frame in frames:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR) if colour else frame)
    writer.release()


def test_an_uncompressed_video_comes_back_uncompressed_frame_for_frame(identity, tmp_path):
    # an uncompressed source (FourCC 0) was written back as MJPEG (lossy) before
    frames = [_ramp(np.uint8, seed=k) for k in range(3)]
    source = tmp_path / "raw.avi"
    _video(source, 0, frames)
    assert _undistort(identity, tmp_path / "out", source) == 0
    cap = cv2.VideoCapture(str(tmp_path / "out" / "raw.avi"))
    assert int(cap.get(cv2.CAP_PROP_FOURCC)) == 0
    back = [cv2.cvtColor(cap.read()[1], cv2.COLOR_BGR2GRAY) for _ in frames]
    assert not cap.read()[0]
    cap.release()
    for frame, again in zip(frames, back):
        np.testing.assert_array_equal(again, frame)


@pytest.mark.parametrize(
    ("name", "fourcc", "colour"),
    [("mjpeg.avi", "MJPG", False), ("mpeg4.mp4", "mp4v", False), ("colour_ffv1.avi", "FFV1", True)],
)
def test_a_lossy_or_colour_video_is_refused(identity, tmp_path, capsys, name, fourcc, colour):
    # a lossy codec cannot give the frames back; a colour video would come back grey
    source = tmp_path / name
    _video(source, cv2.VideoWriter_fourcc(*fourcc), [_ramp(np.uint8, seed=k) for k in range(2)], colour=colour)
    why = "cannot be written back exactly: only 8-bit grey FFV1, PNG or uncompressed video can; convert it to"
    _assert_refused(identity, tmp_path, capsys, source, why)


# --- refusals -----------------------------------------------------------------------------------------


def _assert_refused(identity, tmp_path, capsys, source, message):
    out = tmp_path / "out"
    assert _undistort(identity, out, source) == 2
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err], err
    assert str(source) in err and message in err, err
    assert not (out / source.name).exists() and not (out.exists() and any(out.iterdir()))


def test_pages_of_two_sizes_are_refused(identity, tmp_path, capsys):
    source = tmp_path / "two.tif"
    with tifffile.TiffWriter(source) as tif:
        tif.write(_ramp(np.uint16))
        tif.write(_ramp(np.uint16)[: H // 2, : W // 2])
    _assert_refused(identity, tmp_path, capsys, source, "pages differ")


def test_half_floats_are_refused(identity, tmp_path, capsys):
    source = tmp_path / "half.tif"
    tifffile.imwrite(source, _ramp(np.uint8).astype(np.float16))
    _assert_refused(identity, tmp_path, capsys, source, "half-float samples cannot be written back")


def test_a_bitmap_is_refused(identity, tmp_path, capsys):
    source = tmp_path / "bits.pbm"
    source.write_bytes(b"P4\n%d %d\n" % (W, H) + bytes(W // 8 * H))
    _assert_refused(identity, tmp_path, capsys, source, "a bitmap (PBM) cannot be written back")


def test_the_edges_background_leaves_an_alpha_channel_as_remapped(identity, tmp_path):
    """With the default ``--outside background``, colour channels are cleared outside the disc, alpha is not.

    A bright disc on black with an opaque alpha: a zero field gives every sample back inside the disc, black
    outside it, and the alpha (no intensity: it has no disc) exactly (found in review: it was cleared to 0).
    """
    yy, xx = np.mgrid[0:H, 0:W]
    disc = (xx - W / 2) ** 2 + (yy - H / 2) ** 2 < (0.4 * H) ** 2
    frame = np.zeros((H, W, 4), np.uint16)
    frame[..., :3] = np.where(disc, 40000, 0)[..., None]
    frame[..., 3] = 65535
    source = tmp_path / "rgba.png"
    assert cv2.imwrite(str(source), frame)
    args = ["--quiet", "undistort", str(identity), str(source), "--system", "A", "--out", str(tmp_path / "u")]
    assert main(args) == 0
    back = _oiio_samples(tmp_path / "u" / "rgba.png")
    np.testing.assert_array_equal(back[..., 3], frame[..., 3])
    # inside the disc, beyond the linear kernel's reach (1 px) of its rim, every colour sample comes back
    inner = (xx - W / 2) ** 2 + (yy - H / 2) ** 2 < (0.4 * H - 2) ** 2
    np.testing.assert_array_equal(back[..., :3][inner], frame[..., :3][inner])
    assert back[..., :3][~disc].max() == 0


# --- file names under an ASCII locale -------------------------------------------------------------------

#: a C locale and ASCII output, as on a bare server or in a container (no UTF-8 mode)
ASCII_LOCALE = {"LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONIOENCODING": "ascii"}


def _undistort_in_c_locale(calibration, out, source: bytes):
    """Run the CLI in a subprocess under :data:`ASCII_LOCALE` on the file named by ``source`` (raw bytes)."""
    args = [os.fsencode(a) for a in (sys.executable, "-m", "fluorocal.cli", "--quiet", "undistort", calibration)]
    args += [source, b"--system", b"A", b"--outside", b"keep", b"--out", os.fsencode(out)]
    env = {k: v for k, v in os.environ.items() if not k.startswith(("LC_", "LANG"))} | ASCII_LOCALE
    return subprocess.run(args, env=env, capture_output=True)


def test_a_non_ascii_file_name_is_read_and_written_under_the_c_locale(identity, tmp_path):
    # Python decodes the name with surrogates there; OpenImageIO refused them (a TypeError, exit 2)
    samples = _ramp(np.uint16)
    name = "fr\u00e4me_\u0394.tif".encode()  # UTF-8 bytes, as a UTF-8 system names it
    tifffile.imwrite(tmp_path / os.fsdecode(name), samples)
    done = _undistort_in_c_locale(identity, tmp_path / "out", os.fsencode(tmp_path / os.fsdecode(name)))
    assert done.returncode == 0, done.stderr
    assert b"Traceback" not in done.stderr
    np.testing.assert_array_equal(_oiio_samples(tmp_path / "out" / os.fsdecode(name)), samples)


def test_a_file_name_that_is_not_utf8_is_refused_in_one_ascii_line(identity, tmp_path):
    source = tmp_path / os.fsdecode(b"fr\xe4me.tif")  # Latin-1, which the libraries cannot open by name
    tifffile.imwrite(source, _ramp(np.uint16))
    done = _undistort_in_c_locale(identity, tmp_path / "out", os.fsencode(source))
    assert done.returncode == 2 and done.stdout == b""
    err = done.stderr.decode("ascii").strip()  # ASCII: the name's byte as an escape
    assert err.splitlines() == [err], err
    assert err.startswith("fluorocal: error: ") and "fr\\xe4me.tif: file name is not UTF-8" in err, err
    assert "rename the file" in err
    assert not (tmp_path / "out").exists()
