"""DICOM written like a source as a derived instance: new series and instance, references, derivation codes.

Every attribute is read back with pydicom from the file written; the expected values are the DICOM
standard's (PS3.3 C.7.6.1 General Image module; PS3.16 CID 7203 "Image Derivation" and CID 7202
"Source Image Purposes of Reference", as pydicom's code dictionary has them), not the writer's.
"""

from __future__ import annotations

import numpy as np
import pydicom
import pytest
from fluorocal.stages.errors import InputError
from fluorocal.stages.io import Derivation, read_frames, series_of, write_frames_like, write_still, write_stored_like
from pydicom import uid
from pydicom.sr._cid_dict import cid_concepts
from pydicom.sr.codedict import codes

from tests.helpers import save_dicom

H, W = 24, 32


def _frames(n: int) -> np.ndarray:
    return (np.arange(n * H * W).reshape(n, H, W) * 7 % 4096).astype(np.uint16)


def _code(item) -> tuple[str, str, str]:
    return item.CodeValue, item.CodingSchemeDesignator, item.CodeMeaning


@pytest.mark.parametrize("n_frames", [1, 3])
def test_a_derived_instance_carries_every_attribute_of_a_derived_series(tmp_path, n_frames):
    source = tmp_path / "src.dcm"
    original = save_dicom(source, _frames(n_frames))
    derivation = Derivation("geometric distortion corrected with calibration.json", "1.2.826.0.1.3680043.8.498.42")
    pixels = _frames(n_frames)[:, ::-1, ::-1].copy()  # stands for the undistorted frames: any change of content
    write_stored_like(source, iter(pixels), tmp_path / "out.dcm", n_frames, derivation=derivation)
    out = pydicom.dcmread(tmp_path / "out.dcm")
    # a new instance in the derivation's series, the study, patient and SOP class of the source
    assert out.SOPInstanceUID not in ("", original.SOPInstanceUID)
    assert out.file_meta.MediaStorageSOPInstanceUID == out.SOPInstanceUID
    assert out.SeriesInstanceUID == derivation.series_uid
    assert (out.StudyInstanceUID, out.PatientID, out.SOPClassUID) == (
        original.StudyInstanceUID,
        "P1",
        uid.XRayAngiographicImageStorage,
    )
    # PS3.3 C.7.6.1.1.2: value 1 DERIVED, value 2 SECONDARY (created after the examination); value 3 kept
    assert list(out.ImageType) == ["DERIVED", "SECONDARY", "SINGLE PLANE"]
    assert out.SeriesDescription == "Spine AP (undistorted)"
    (reference,) = out.SourceImageSequence
    assert reference.ReferencedSOPClassUID == uid.XRayAngiographicImageStorage
    assert reference.ReferencedSOPInstanceUID == original.SOPInstanceUID
    purpose = codes.DCM.SourceImageForImageProcessingOperation  # CID 7202
    assert [_code(c) for c in reference.PurposeOfReferenceCodeSequence] == [
        (purpose.value, purpose.scheme_designator, purpose.meaning)
    ]
    # CID 7203 has no geometric-correction code: undistortion is a spatial resampling onto the pinhole grid
    assert "SpatialResampling" in cid_concepts[7203]["DCM"]
    resampling = codes.DCM.SpatialResampling
    assert [_code(c) for c in out.DerivationCodeSequence] == [
        (resampling.value, resampling.scheme_designator, resampling.meaning)
    ]
    assert out.DerivationDescription == derivation.description
    # the pixel layout of the source, the frames as given
    for tag in ("Rows", "Columns", "BitsAllocated", "BitsStored", "HighBit", "PixelRepresentation", "SamplesPerPixel"):
        assert out[tag].value == original[tag].value, tag
    assert int(out.get("NumberOfFrames", 1)) == n_frames
    np.testing.assert_array_equal(out.pixel_array.reshape(pixels.shape), pixels)


@pytest.mark.parametrize(
    "image_type, description, expected_type, expected_description",
    [
        ("ORIGINAL", "x" * 64, ["DERIVED", "SECONDARY"], "x" * 50 + " (undistorted)"),  # LO: 64 characters at most
        (None, None, ["DERIVED", "SECONDARY"], "(undistorted)"),
        (["ORIGINAL", "PRIMARY"], "", ["DERIVED", "SECONDARY"], "(undistorted)"),
    ],
    ids=["one-value-long-description", "absent", "two-values-empty-description"],
)
def test_image_type_and_series_description_of_odd_sources(
    tmp_path, image_type, description, expected_type, expected_description
):
    source = tmp_path / "src.dcm"
    save_dicom(source, _frames(1), ImageType=image_type, SeriesDescription=description)
    (frame,) = read_frames(source)
    write_frames_like(source, [frame], tmp_path / "out.dcm")
    out = pydicom.dcmread(tmp_path / "out.dcm")
    # a single-valued ImageType is one value, not a string to slice into characters
    assert list(out.ImageType) == expected_type
    assert out.SeriesDescription == expected_description and len(out.SeriesDescription) <= 64


def test_without_a_derivation_each_file_is_its_own_new_series(tmp_path):
    source = tmp_path / "src.dcm"
    original = save_dicom(source, _frames(1))
    (frame,) = read_frames(source)
    write_frames_like(source, [frame], tmp_path / "a.dcm")
    write_frames_like(source, [frame], tmp_path / "b.dcm")
    a, b = pydicom.dcmread(tmp_path / "a.dcm"), pydicom.dcmread(tmp_path / "b.dcm")
    assert len({a.SeriesInstanceUID, b.SeriesInstanceUID, original.SeriesInstanceUID}) == 3
    assert len({a.SOPInstanceUID, b.SOPInstanceUID, original.SOPInstanceUID}) == 3
    assert a.DerivationDescription == Derivation().description


def test_a_rescaled_source_takes_the_general_path_and_is_derived_too(tmp_path):
    source = tmp_path / "src.dcm"
    original = save_dicom(source, _frames(1), RescaleSlope=2, RescaleIntercept=-100)
    (frame,) = read_frames(source)
    write_frames_like(source, [frame], tmp_path / "out.dcm", derivation=Derivation("d", "1.2.3.4"))
    out = pydicom.dcmread(tmp_path / "out.dcm")
    assert out.SeriesInstanceUID == "1.2.3.4" and out.DerivationDescription == "d"
    assert out.SourceImageSequence[0].ReferencedSOPInstanceUID == original.SOPInstanceUID
    np.testing.assert_array_equal(out.pixel_array, _frames(1)[0])  # stored values back exactly: nothing resampled


def test_series_of_names_the_series_and_refuses_what_cannot_be_referenced(tmp_path):
    original = save_dicom(tmp_path / "a.dcm", _frames(1))
    assert series_of(tmp_path / "a.dcm") == original.SeriesInstanceUID
    save_dicom(tmp_path / "no_series.dcm", _frames(1), SeriesInstanceUID=None)
    save_dicom(tmp_path / "no_series_2.dcm", _frames(1), SeriesInstanceUID=None)
    # a file without a series joins no other file's series
    assert series_of(tmp_path / "no_series.dcm") != series_of(tmp_path / "no_series_2.dcm")
    write_still(tmp_path / "a.tif", _frames(1)[0])
    assert series_of(tmp_path / "a.tif") is None
    ds = save_dicom(tmp_path / "bare.dcm", _frames(1))
    del ds.SOPInstanceUID, ds.file_meta.MediaStorageSOPInstanceUID  # neither the data set nor its file meta has one
    ds.preamble = b"\0" * 128
    ds.save_as(tmp_path / "bare.dcm", enforce_file_format=False)
    with pytest.raises(InputError, match=r"bare.dcm: DICOM file has no SOPInstanceUID"):
        series_of(tmp_path / "bare.dcm")


def test_a_derivation_description_must_fit_dicoms_short_text():
    with pytest.raises(InputError, match="1 to 1024 characters; got 0"):
        Derivation("")
    with pytest.raises(InputError, match="got 1025"):
        Derivation("x" * 1025)


def test_a_real_arcadis_frame_written_as_derived_keeps_its_pixels(arcadis_dir, tmp_path):
    src = arcadis_dir / "spine_centered_0.dcm"
    original = pydicom.dcmread(src)
    frames = read_frames(src)
    write_frames_like(src, frames, tmp_path / "u.dcm", derivation=Derivation("real", "1.2.3"))
    out = pydicom.dcmread(tmp_path / "u.dcm")
    assert out.SeriesInstanceUID == "1.2.3" and out.SOPInstanceUID != original.SOPInstanceUID
    assert out.SourceImageSequence[0].ReferencedSOPInstanceUID == original.SOPInstanceUID
    assert out.SourceImageSequence[0].ReferencedSOPClassUID == original.SOPClassUID
    assert list(out.ImageType[:2]) == ["DERIVED", "SECONDARY"]
    assert out.DerivationCodeSequence[0].CodeValue == "113085"
    assert (out.Rows, out.Columns, out.BitsStored, out.BitsAllocated) == (
        original.Rows,
        original.Columns,
        original.BitsStored,
        original.BitsAllocated,
    )
    np.testing.assert_array_equal(out.pixel_array, original.pixel_array)  # written back unchanged: equal
