"""A calibration proves what it is (issue 28): field files match their recorded SHA-256, every number is checked.

A field file whose nodes were scaled (x2, x0.5) was used as if it were the calibration's; a NaN or zero
quaternion in the ROP or a pose, or a NaN source, was loaded and exported; a 3-number quaternion was a
traceback. Each is now a one-line :class:`ArtifactError` naming the file and the key.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from fluorocal import Calibration
from fluorocal.calibration_doc import DOCUMENT_SHA256, document_sha256
from fluorocal.cli import main
from fluorocal.stages.errors import ArtifactError
from fluorocal.stages.io import write_still

from tests.pipeline.synthetic_calibration import H, W, synthetic_calibration


@pytest.fixture()
def cal_path(tmp_path):
    """The synthetic two-system calibration of test_undistort_api with one exposure's pose, saved."""
    cal = synthetic_calibration()
    cal = Calibration(list(cal.systems.values()), {0: (np.array([1.0, 0, 0, 0]), np.array([0, 0, -1000.0]))}, {})
    path = tmp_path / "cal" / "calibration.json"
    path.parent.mkdir()
    cal.save(path)
    return path


def _edit(path, change) -> None:
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


def test_the_file_records_the_sha256_of_each_field_file_and_of_itself(cal_path):
    doc = json.loads(cal_path.read_text())
    entries = [doc["systems"][1]["field"]] + [o["field"] for o in doc["systems"][0]["orientations"]]
    for entry in entries:
        assert entry["sha256"] == hashlib.sha256((cal_path.parent / entry["file"]).read_bytes()).hexdigest()
    assert doc[DOCUMENT_SHA256] == document_sha256(doc)
    doc["scheme"] = "edited"
    assert document_sha256(doc) != doc[DOCUMENT_SHA256]


@pytest.mark.parametrize("scale", [2.0, 0.5])
def test_a_field_file_that_does_not_match_is_refused_by_load_undistort_and_export(cal_path, tmp_path, capsys, scale):
    field = cal_path.parent / "field_B.npz"
    with np.load(field) as npz:
        arrays = dict(npz)
    arrays["x_nodes_px"] = arrays["x_nodes_px"] * scale  # a valid field, but not this calibration's
    arrays["y_nodes_px"] = arrays["y_nodes_px"] * scale
    np.savez(field, **arrays)
    with pytest.raises(ArtifactError, match=r"field_B.npz: field file does not match calibration.json"):
        Calibration.load(cal_path)
    frame = tmp_path / "frame.tif"
    write_still(frame, np.full((H, W), 1000, np.uint16))
    undistort = ["-q", "undistort", str(cal_path), str(frame), "--system", "B"]
    for argv in (
        [*undistort, "--out", str(tmp_path / "u")],
        ["-q", "export", str(cal_path), "--format", "opencv", "--out", str(tmp_path / "x")],
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("fluorocal: error: ") and str(field) in err and len(err.splitlines()) == 1
    assert not (tmp_path / "u").exists() and not (tmp_path / "x").exists()


NAN = float("nan")
ROP_A, ROP_B, EXPOSURE = ("systems", 0, "rop"), ("systems", 1, "rop"), ("exposures", 0)
#: case -> (where in the document, key, value, what the error says)
BAD_NUMBERS = {
    "rop q nan": (ROP_A, "q_cam_from_ref", [NAN, 0, 0, 0], "rop q_cam_from_ref must be 4 finite"),
    "rop q zero": (ROP_A, "q_cam_from_ref", [0, 0, 0, 0], "rop q_cam_from_ref must be a unit quaternion"),
    "rop q of 3": (ROP_A, "q_cam_from_ref", [1, 0, 0], "rop q_cam_from_ref must be 4 finite"),
    "rop source nan": (ROP_B, "source_in_ref_camera_mm", [0, NAN, 0], "source_in_ref_camera_mm must be 3 finite"),
    "rop source text": (ROP_B, "source_in_ref_camera_mm", "0,0,0", "source_in_ref_camera_mm must be 3 finite"),
    "iop std of 2": (("systems", 1), "iop_std_px", [0.1, 0.1], "iop_std_px must be 3 finite"),
    "iop inf": (("systems", 1, "iop_px"), "xp", float("inf"), "iop_px must be 3 finite"),
    "exposure q nan": (EXPOSURE, "q_cam_from_obj", [NAN, 0, 0, 0], "exposure 0: q_cam_from_obj must be 4"),
    "exposure q not unit": (EXPOSURE, "q_cam_from_obj", [2, 0, 0, 0], "exposure 0: q_cam_from_obj must be a unit"),
    "exposure source nan": (EXPOSURE, "source_mm", [0, 0, NAN], "exposure 0: source_mm must be 3 finite"),
    "exposure number text": (EXPOSURE, "exposure", "0", "exposure's number must be an integer"),
    "orbit nan": (("systems", 0, "orientations", 0), "orbit_deg", NAN, "orientation o0: orbit_deg must be a finite"),
}


def _set(where, key, value):
    def change(doc):
        for part in where:
            doc = doc[part]
        doc[key] = value

    return change


@pytest.mark.parametrize("case", list(BAD_NUMBERS))
def test_every_number_of_a_loaded_calibration_is_checked(cal_path, tmp_path, capsys, case):
    *at, message = BAD_NUMBERS[case]
    _edit(cal_path, _set(*at))
    with pytest.raises(ArtifactError, match=message) as err:
        Calibration.load(cal_path)
    assert str(cal_path) in str(err.value)
    assert main(["-q", "export", str(cal_path), "--format", "dlt", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fluorocal: error: ") and message in err and len(err.splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_an_edited_but_valid_calibration_is_read_with_a_note_in_the_log(cal_path, caplog):
    _edit(cal_path, lambda d: d.update(scheme="by hand"))
    with caplog.at_level("WARNING", logger="fluorocal.calibration_doc"):
        cal = Calibration.load(cal_path)
    assert cal.meta["scheme"] == "by hand" and "was edited after fluorocal wrote it" in caplog.text
