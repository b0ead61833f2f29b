"""`fluorocal undistort`'s DICOM outputs as a derived series, and existing outputs refused unless --overwrite.

The calibration and frames are those of ``test_undistort_api`` (a smooth field of a few px, sub-pixel
maps); every attribute is read back with pydicom from the files the command wrote.
"""

from __future__ import annotations

import os

import cv2
import numpy as np
import pydicom
import pytest
from fluorocal.calibration import Calibration
from fluorocal.cli import main
from pydicom import uid

from tests.helpers import save_dicom
from tests.pipeline.synthetic_calibration import textured_frame


def _undistort(saved, out, *inputs, system="B", options=()):
    # --outside keep: these tests compare with the API's plain remap (edges: tests/pipeline/test_clinic_edges.py)
    args = ["--quiet", "undistort", str(saved), *map(str, inputs), "--system", system]
    args += ["--outside", "keep"]
    return main(args + ["--out", str(out), *options])


@pytest.fixture()
def two_series(tmp_path):
    """Two DICOM files of one series (the first of 2 frames), one of another, and a TIFF: ``(paths, data sets)``."""
    folder = tmp_path / "frames"
    folder.mkdir()
    series_1, series_2, study = uid.generate_uid(), uid.generate_uid(), uid.generate_uid()
    spec = [
        ("s1_a.dcm", series_1, [textured_frame(0), textured_frame(1)]),
        ("s1_b.dcm", series_1, [textured_frame(2)]),
        ("s2_a.dcm", series_2, [textured_frame(3)]),
    ]
    sources = {}
    for name, series, frames in spec:
        sources[name] = save_dicom(
            folder / name, np.stack(frames), SeriesInstanceUID=series, StudyInstanceUID=study, Rows=64, Columns=96
        )
    cv2.imwrite(str(folder / "still.tif"), textured_frame(4))
    return folder, sources


def test_one_new_series_per_source_series_and_run(saved, tmp_path, two_series):
    folder, sources = two_series
    assert _undistort(saved, tmp_path / "u", folder) == 0
    out = {name: pydicom.dcmread(tmp_path / "u" / name) for name in sources}
    # one run: the outputs of one source series share one new series, the other source series gets another
    assert out["s1_a.dcm"].SeriesInstanceUID == out["s1_b.dcm"].SeriesInstanceUID
    assert out["s2_a.dcm"].SeriesInstanceUID != out["s1_a.dcm"].SeriesInstanceUID
    originals = {ds.SeriesInstanceUID for ds in sources.values()}
    assert not originals & {ds.SeriesInstanceUID for ds in out.values()}
    # a new instance per output, each referencing its original
    assert len({ds.SOPInstanceUID for ds in out.values()} | {ds.SOPInstanceUID for ds in sources.values()}) == 6
    cal = Calibration.load(saved)
    for name, ds in out.items():
        (reference,) = ds.SourceImageSequence
        assert reference.ReferencedSOPInstanceUID == sources[name].SOPInstanceUID
        assert reference.ReferencedSOPClassUID == sources[name].SOPClassUID
        assert list(ds.ImageType) == ["DERIVED", "SECONDARY", "SINGLE PLANE"]
        assert ds.SeriesDescription == "Spine AP (undistorted)" and ds.DerivationCodeSequence[0].CodeValue == "113085"
        description = ds.DerivationDescription
        # the calibration by file name and content, the system and its field
        assert "calibration calibration.json (content sha256 " + cal.content_sha256[:16] + ")" in description
        assert "system B, the system's one field, linear interpolation" in description
        assert (ds.Rows, ds.Columns, ds.BitsAllocated, ds.BitsStored) == (64, 96, 16, 12)
    # pixel data: each frame is the API's undistorted frame (the same remap of the same stored values)
    pixels = out["s1_a.dcm"].pixel_array
    assert pixels.shape == (2, 64, 96) and out["s1_a.dcm"].NumberOfFrames == 2
    for i, seed in enumerate((0, 1)):
        np.testing.assert_array_equal(pixels[i], cal.undistort_image("B", textured_frame(seed)))
    np.testing.assert_array_equal(out["s2_a.dcm"].pixel_array, cal.undistort_image("B", textured_frame(3)))
    # the TIFF beside them is written as before
    np.testing.assert_array_equal(
        cv2.imread(str(tmp_path / "u" / "still.tif"), cv2.IMREAD_UNCHANGED), cal.undistort_image("B", textured_frame(4))
    )
    # another run of the same sources: another series
    assert _undistort(saved, tmp_path / "v", folder / "s1_a.dcm") == 0
    again = pydicom.dcmread(tmp_path / "v" / "s1_a.dcm")
    assert again.SeriesInstanceUID not in {ds.SeriesInstanceUID for ds in out.values()} | originals


@pytest.mark.parametrize(
    "options, where",
    [
        (["--orientation", "o30"], "system A, orientation o30, cubic interpolation"),
        (
            ["--orientation", "orbit=15,tilt=0"],
            "system A, orientation interpolated at orbit 15 deg, tilt 0 deg, cubic interpolation",
        ),
    ],
)
def test_the_description_names_the_orientation(saved, tmp_path, options, where):
    src = tmp_path / "one.dcm"
    save_dicom(src, textured_frame(0)[None], Rows=64, Columns=96)
    assert _undistort(saved, tmp_path / "u", src, system="A", options=options + ["--interpolation", "cubic"]) == 0
    assert pydicom.dcmread(tmp_path / "u" / "one.dcm").DerivationDescription.endswith(where)


def _snapshot(folder):
    return {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(folder.iterdir())}


@pytest.mark.parametrize("existing", ["s2_a.dcm", "still.tif"])
def test_an_existing_output_is_refused_before_anything_is_written(saved, tmp_path, two_series, capsys, existing):
    folder, _ = two_series
    out = tmp_path / "u"
    out.mkdir()
    (out / existing).write_bytes(b"an earlier result")
    before = _snapshot(out)
    assert _undistort(saved, out, folder) == 2
    err = capsys.readouterr().err.strip()
    # one line naming the file and what to do; the files sorted before it were not written either
    assert err.splitlines() == [err] and f"{out / existing}: already exists; add --overwrite" in err
    assert _snapshot(out) == before
    # with --overwrite every output is written, the earlier one replaced
    assert _undistort(saved, out, folder, options=["--overwrite"]) == 0
    assert sorted(os.listdir(out)) == ["s1_a.dcm", "s1_b.dcm", "s2_a.dcm", "still.tif"]
    assert (out / existing).read_bytes() != b"an earlier result"


def test_a_folder_in_the_place_of_an_output_is_refused_even_with_overwrite(saved, tmp_path, capsys):
    cv2.imwrite(str(tmp_path / "a.tif"), textured_frame(0))
    (tmp_path / "u" / "a.tif").mkdir(parents=True)
    assert _undistort(saved, tmp_path / "u", tmp_path / "a.tif", options=["--overwrite"]) == 2
    assert "a.tif: is a folder, where the undistorted a.tif would go" in capsys.readouterr().err
    assert (tmp_path / "u" / "a.tif").is_dir() and not any((tmp_path / "u" / "a.tif").iterdir())


def test_a_dicom_that_cannot_be_referenced_is_refused_before_anything_is_written(saved, tmp_path, capsys):
    folder = tmp_path / "frames"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.tif"), textured_frame(0))
    ds = save_dicom(folder / "b.dcm", textured_frame(1)[None], Rows=64, Columns=96)
    del ds.SOPInstanceUID, ds.file_meta.MediaStorageSOPInstanceUID
    ds.preamble = b"\0" * 128
    ds.save_as(folder / "b.dcm", enforce_file_format=False)
    assert _undistort(saved, tmp_path / "u", folder) == 2
    assert "b.dcm: DICOM file has no SOPInstanceUID" in capsys.readouterr().err
    assert not (tmp_path / "u").exists()
