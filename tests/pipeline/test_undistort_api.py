"""``Calibration.remap_maps`` and ``undistort_image``, the maps' cache beside the calibration, and the stream.

The field here is a smooth pincushion-like correction of a few px (not a constant shift), so the
maps are sub-pixel everywhere and the equalities below test the resampling, not integer moves.
"""

from __future__ import annotations

import dataclasses
import threading
import time
import warnings

import cv2
import numpy as np
import pydicom
import pytest
from fluorocal.calibration import Calibration
from fluorocal.cli import main
from fluorocal.maps import MapCacheWarning, maps_folder
from fluorocal.stages.artifacts import Radiograph
from fluorocal.stages.errors import InputError, ShapeError
from fluorocal.stages.io import read_frames, write_frames_like
from fluorocal.stages.io.pixels import to_source_dtype
from fluorocal.stages.undistort import UndistortParams, undistort_frame
from fluorocal.streaming import stream

from tests.helpers import save_dicom
from tests.pipeline.synthetic_calibration import (
    H,
    W,
    count_map_computations,
    smooth_field,
    synthetic_calibration,
    textured_frame,
)

SC = "SecondaryCaptureImageStorage"  # the DICOMs streamed here: secondary captures

# --- remap_maps and undistort_image -------------------------------------------------------------------


def test_maps_are_the_fields_distortion_of_each_pixel_centre(saved):
    cal = Calibration.load(saved)
    map_x, map_y = cal.remap_maps("B")
    assert map_x.dtype == map_y.dtype == np.float32 and map_x.shape == (H, W) and not map_x.flags.writeable
    # the source of output pixel (x, y) is the measured point whose undistortion is (x, y): undistorting the
    # maps gives the pixel grid back, to float32 rounding of coordinates below 100 px (~1e-5) plus the
    # field's Newton inversion tolerance (1e-9)
    src = np.column_stack([map_x.ravel(), map_y.ravel()]).astype(np.float64)
    yy, xx = np.mgrid[0:H, 0:W]
    np.testing.assert_allclose(cal.undistort_points("B", src), np.column_stack([xx.ravel(), yy.ravel()]), atol=2e-5)
    # another output size: the same coordinates, cropped (as newImageSize)
    small_x, _ = cal.remap_maps("B", image_size=(40, 30))
    np.testing.assert_array_equal(small_x, map_x[:30, :40])


@pytest.mark.parametrize("interpolation", ["linear", "nearest", "cubic"])
def test_undistort_image_equals_remap_with_the_maps_and_the_old_path(saved, interpolation):
    cal = Calibration.load(saved)
    frame = textured_frame()
    out = cal.undistort_image("A", frame, orientation="o30", interpolation=interpolation)
    assert out.dtype == np.uint16 and out.shape == frame.shape
    map_x, map_y = cal.remap_maps("A", orientation="o30")
    code = {"linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST, "cubic": cv2.INTER_CUBIC}[interpolation]
    bare = cv2.remap(frame, map_x, map_y, code, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if interpolation == "cubic":  # the kernel overshoots: clipped to the frame's range and the border value
        bare = np.clip(bare, 0, frame.max())
    np.testing.assert_array_equal(out, bare)
    # the old path: the frame as float32, remapped, rounded back to the source's integers. OpenCV remaps uint16
    # in fixed point (15-bit weights) and float32 in float: the two may round a value across a half DN, so they
    # may differ by 1 DN, never more
    old = to_source_dtype(undistort_frame(Radiograph(frame, 12), map_x, map_y, UndistortParams(interpolation)))
    assert np.abs(out.astype(int) - old).max() <= 1


def test_undistort_image_keeps_the_orientation_semantics(saved):
    cal = Calibration.load(saved)
    frame = textured_frame()
    # orbit 15 is halfway between o0 (+2 scale) and o30 (-2 scale): the field is 0, the maps the identity grid
    halfway = cal.undistort_image("A", frame, orientation={"orbit": 15, "tilt": 0})
    np.testing.assert_array_equal(halfway, frame)
    assert not np.array_equal(cal.undistort_image("A", frame, orientation="o0"), frame)
    with pytest.raises(InputError, match="calibrated at 2 orientations"):
        cal.undistort_image("A", frame)
    with pytest.raises(InputError, match="beyond the calibrated orientations"):
        cal.remap_maps("A", orientation={"orbit": 45, "tilt": 0})


def test_undistort_image_refuses_bad_frames_and_sizes(saved):
    cal = Calibration.load(saved)
    with pytest.raises(ShapeError, match=r"calibrated size, shape \(64, 96\); got \(64, 95\)"):
        cal.undistort_image("B", np.zeros((H, W - 1), np.uint16))
    with pytest.raises(InputError, match="image dtype must be one of"):
        cal.undistort_image("B", np.zeros((H, W), np.int64))
    with pytest.raises(InputError, match="image_size must be"):
        cal.remap_maps("B", image_size=(0, 10))
    with pytest.raises(InputError, match="system 'C' is not in this calibration"):
        cal.remap_maps("C")


# --- the cache beside the calibration -------------------------------------------------------------------


def test_maps_are_computed_once_and_read_back_from_the_cache(saved, monkeypatch):
    calls = count_map_computations(monkeypatch)
    first = Calibration.load(saved).remap_maps("A", orientation="o0")
    assert len(calls) == 1 and len(list(maps_folder(saved).glob("*.npy"))) == 1
    cal = Calibration.load(saved)  # a new process, in effect: only the disk cache is shared
    again = cal.remap_maps("A", orientation="o0")
    cal.remap_maps("A", orientation="o0")  # and in memory
    assert len(calls) == 1
    np.testing.assert_array_equal(np.stack(again), np.stack(first))
    # another orientation, system or size is another entry
    cal.remap_maps("A", orientation="o30")
    cal.remap_maps("B")
    cal.remap_maps("B", image_size=(W, H - 1))
    assert len(calls) == 4 and len(list(maps_folder(saved).glob("*.npy"))) == 4


def test_a_changed_calibration_never_meets_its_old_maps(saved, monkeypatch):
    calls = count_map_computations(monkeypatch)
    Calibration.load(saved).remap_maps("B")
    cal = synthetic_calibration()
    cal.systems["B"] = dataclasses.replace(cal.systems["B"], field=smooth_field(0.5))
    cal.save(saved)  # same file names, other field: another content hash
    new_x, _ = Calibration.load(saved).remap_maps("B")
    assert len(calls) == 2
    expected_x, _ = smooth_field(0.5).remap_maps()
    np.testing.assert_array_equal(new_x, expected_x)


@pytest.mark.parametrize(
    "damage",
    [
        lambda f: f.write_bytes(f.read_bytes()[:200]),  # truncated
        lambda f: f.write_bytes(b"not an npy file"),
        lambda f: f.write_bytes(f.read_bytes()[:-4] + b"\x00\x00\x80\x7f"),  # one value changed (to +inf)
    ],
    ids=["truncated", "garbage", "one-value-changed"],
)
def test_a_corrupt_cached_map_is_recomputed_with_a_warning(saved, monkeypatch, damage):
    calls = count_map_computations(monkeypatch)
    good = np.stack(Calibration.load(saved).remap_maps("B"))
    (entry,) = maps_folder(saved).glob("*.npy")
    damage(entry)
    with pytest.warns(MapCacheWarning, match="corrupt cached undistortion maps"):
        again = np.stack(Calibration.load(saved).remap_maps("B"))
    assert len(calls) == 2
    np.testing.assert_array_equal(again, good)
    (rewritten,) = maps_folder(saved).glob("*.npy")  # stored again, whole
    np.testing.assert_array_equal(np.load(rewritten, allow_pickle=False), good)


def test_a_cache_that_cannot_be_written_costs_only_the_cache(saved):
    maps_folder(saved).write_text("a file where the folder would be")
    with pytest.warns(MapCacheWarning, match="cannot cache the undistortion maps"):
        map_x, _ = Calibration.load(saved).remap_maps("B")
    np.testing.assert_array_equal(map_x, smooth_field(1.5).remap_maps()[0])


def test_a_calibration_in_memory_caches_in_memory_only(tmp_path, monkeypatch):
    calls = count_map_computations(monkeypatch)
    cal = synthetic_calibration()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cal.remap_maps("B")
        cal.undistort_image("B", textured_frame())
    assert len(calls) == 1 and not list(tmp_path.iterdir())


# --- the stream -------------------------------------------------------------------------------------------


def test_stream_keeps_order_and_memory_bounded():
    depth, n = 3, 60
    produced, consumed, most_in_flight = [0], [0], [0]

    def items():
        for i in range(n):
            produced[0] += 1
            most_in_flight[0] = max(most_in_flight[0], produced[0] - consumed[0])
            yield i

    def consume(results):
        out = []
        for r in results:
            time.sleep(0.002)  # a slow writer: the reader runs ahead until the queues are full
            consumed[0] += 1
            out.append(r)
        assert out == [10 * i for i in range(n)]

    stream(items(), lambda i: 10 * i, consume, depth=depth)
    assert consumed[0] == n
    # two queues of `depth`, one item in each of the three steps' hands, one being produced
    assert most_in_flight[0] <= 2 * depth + 4


@pytest.mark.parametrize("where", ["read", "transform", "write"])
def test_stream_raises_the_first_failure_and_stops_every_step(where):
    def items():
        for i in range(1000):
            if where == "read" and i == 5:
                raise InputError("bad frame 5")
            yield i

    def transform(i):
        if where == "transform" and i == 5:
            raise InputError("bad frame 5")
        return i

    def consume(results):
        for i in results:
            if where == "write" and i == 5:
                raise InputError("bad frame 5")

    before = threading.active_count()
    with pytest.raises(InputError, match="bad frame 5"):
        stream(items(), transform, consume, depth=2)
    assert threading.active_count() == before


# --- fluorocal undistort: streamed output equals frame by frame ------------------------------------------


def _undistort(saved, out, *inputs, system="B"):
    # --outside keep: these tests compare with the API's plain remap (edges: tests/pipeline/test_clinic_edges.py)
    args = ["--quiet", "undistort", str(saved), *map(str, inputs), "--system", system]
    args += ["--outside", "keep"]
    return main(args + ["--out", str(out)])


def test_streamed_folder_equals_frame_by_frame(saved, tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    frames = [textured_frame(seed) for seed in range(5)]
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"f{i}.tif"), f)
    (folder / "notes.txt").write_text("not a frame")
    assert _undistort(saved, tmp_path / "u", folder) == 0
    cal = Calibration.load(saved)
    assert sorted(p.name for p in (tmp_path / "u").iterdir()) == [f"f{i}.tif" for i in range(5)]
    for i, f in enumerate(frames):
        (back,) = read_frames(tmp_path / "u" / f"f{i}.tif")
        assert back.bit_depth == 16
        np.testing.assert_array_equal(back.image, cal.undistort_image("B", f).astype(np.float32))


@pytest.mark.parametrize(
    "photometric, syntax", [("MONOCHROME2", "ImplicitVRLittleEndian"), ("MONOCHROME1", "ExplicitVRLittleEndian")]
)
def test_streamed_multiframe_dicom_equals_frame_by_frame(saved, tmp_path, photometric, syntax):
    from pydicom import uid

    src = tmp_path / "run.dcm"
    ds = save_dicom(
        src, np.stack([textured_frame(seed) for seed in range(3)]), photometric=photometric, syntax=syntax, sop_class=SC
    )
    assert _undistort(saved, tmp_path / "u", src) == 0
    out = pydicom.dcmread(tmp_path / "u" / "run.dcm")
    assert out.SOPInstanceUID != ds.SOPInstanceUID and out.PatientID == "P1" and out.NumberOfFrames == 3
    assert out.PhotometricInterpretation == photometric and out.ImageType[:2] == ["DERIVED", "SECONDARY"]
    assert out.file_meta.TransferSyntaxUID == uid.ExplicitVRLittleEndian
    # frame by frame through the old path: read (MONOCHROME1 inverted), undistort, write like the source
    cal = Calibration.load(saved)
    maps = cal.remap_maps("B")
    one_by_one = [undistort_frame(f, *maps, UndistortParams()) for f in read_frames(src)]
    write_frames_like(src, one_by_one, tmp_path / "old.dcm")
    old = pydicom.dcmread(tmp_path / "old.dcm").pixel_array
    # streamed: stored values remapped with the stored value of black as border; the old path remaps the
    # inverted float values and rounds: 1 DN at most between them (see the test of undistort_image)
    assert np.abs(out.pixel_array.astype(int) - old).max() <= 1
    np.testing.assert_array_equal(read_frames(tmp_path / "u" / "run.dcm")[0].image[0, 0], 0.0)  # black border


def test_maps_computed_in_blocks_of_rows_equal_one_inversion_of_every_pixel():
    field = smooth_field(2.0)
    # 2048 px wide: 32 rows per block of 65536 points, so 70 rows are three blocks, the last one short
    map_x, map_y = field.remap_maps(2048, 70)
    yy, xx = np.mgrid[0:70, 0:2048]
    src = field.distort_points(np.column_stack([xx.ravel(), yy.ravel()]).astype(np.float64))
    # Newton stops per block when its largest step is below 1e-9 px, so the two differ by far less than float32's
    # spacing at 2048 px (1.2e-4 px): at most one rounding step of the float32 maps
    np.testing.assert_allclose(map_x, src[:, 0].reshape(70, 2048), rtol=0, atol=1.3e-4)
    np.testing.assert_allclose(map_y, src[:, 1].reshape(70, 2048), rtol=0, atol=1.3e-4)


def test_streamed_multipage_tiff_equals_frame_by_frame(saved, tmp_path):
    frames = [textured_frame(seed) for seed in range(3)]
    src = tmp_path / "pages.tif"
    assert cv2.imwritemulti(str(src), frames)
    assert _undistort(saved, tmp_path / "u", src) == 0
    back = read_frames(tmp_path / "u" / "pages.tif")
    cal = Calibration.load(saved)
    assert len(back) == 3 and all(b.bit_depth == 16 for b in back)
    for b, f in zip(back, frames):
        np.testing.assert_array_equal(b.image, cal.undistort_image("B", f))


def test_a_frame_of_the_wrong_size_writes_nothing(saved, tmp_path, capsys):
    folder = tmp_path / "frames"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.tif"), textured_frame())
    cv2.imwrite(str(folder / "b.tif"), textured_frame()[:, :-1])
    assert _undistort(saved, tmp_path / "u", folder) == 2
    assert "b.tif: frame is 95x64 px; system B was calibrated at 96x64" in capsys.readouterr().err
    assert not (tmp_path / "u").exists()


@pytest.mark.parametrize("suffix", [".tif", ".dcm"])
def test_a_stream_short_of_frames_leaves_no_file(tmp_path, suffix):
    from fluorocal.stages.io import write_stored_like

    src = tmp_path / f"src{suffix}"
    if suffix == ".tif":
        assert cv2.imwritemulti(str(src), [textured_frame(0), textured_frame(1)])
    else:
        save_dicom(src, np.stack([textured_frame(0), textured_frame(1)]), sop_class=SC)
    with pytest.raises(InputError, match=r"expected 2 frame\(s\).*got 1"):
        write_stored_like(src, iter([textured_frame(0)]), tmp_path / f"out{suffix}", 2)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"src{suffix}"]  # no output, no temporary file
