"""Issue 32, the quality check: `fluorocal check CALIBRATION FRAME...` on later grid-plate or bead-phantom frames.

On the real ARCADIS frames (the calibration's own, taken as the "later" frames: no others exist) every
calibrated orientation passes; the tilt-60 frame checked against the centred field fails (the field changes by
0.43 px RMS between the two orientations); a simulated frame of another C-arm and plate fails, saying why. On
the shared simulated biplanar bead project, system A's frame passes A's calibration and B's frame (another
C-arm's distortion, the same phantom) fails it.
"""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pydicom
import pytest
from fluorocal.cli import main
from fluorocal.cmd_check import FIRST_RECORD_COLUMNS, RECORD_COLUMNS, TOLERANCES_PX, append_record
from fluorocal.stages.errors import InputError

from tests.pipeline.orientation_toys import orientation_calibration

#: the six real grid frames and the angles written into their copies (fixtures/arcadis/orientations.toml's)
GRID = {
    "grid_centered_0.dcm": (0, 0),
    "grid_orbit_30.dcm": (30, 0),
    "grid_tilt_15.dcm": (0, 15),
    "grid_tilt_30.dcm": (0, 30),
    "grid_tilt_45.dcm": (0, 45),
    "grid_tilt_60.dcm": (0, 60),
}


def _check(calibration, *frames, record, options=()):
    return main(["--quiet", "check", str(calibration), *map(str, frames), "--record", str(record), *options])


def _rows(record: Path) -> list[dict]:
    with open(record, newline="") as fh:
        return list(csv.DictReader(fh))


def test_the_record_is_appended_and_a_foreign_csv_refused(tmp_path):
    record = tmp_path / "qa.csv"
    row = ["2026-01-01T00:00:00"] + ["x"] * (len(RECORD_COLUMNS) - 1)
    append_record(record, [row])
    append_record(record, [row])
    assert [list(r.values()) for r in _rows(record)] == [row, row]
    # a record the grid-plate check began (its count column was n_holes) is continued under today's header
    first = tmp_path / "first.csv"
    first.write_text(",".join(FIRST_RECORD_COLUMNS) + "\n" + ",".join(row) + "\n")
    append_record(first, [row])
    assert [list(r.values()) for r in _rows(first)] == [row, row] and "n_points" in first.read_text()
    (tmp_path / "other.csv").write_text("a,b\n1,2\n")
    with pytest.raises(InputError, match="not a fluorocal QA record"):
        append_record(tmp_path / "other.csv", [row])
    assert (tmp_path / "other.csv").read_text() == "a,b\n1,2\n"


def test_a_calibration_without_its_project_is_bad_input(tmp_path, capsys):
    calibration = tmp_path / "cal" / "calibration.json"
    calibration.parent.mkdir()
    orientation_calibration().save(calibration)
    frame = tmp_path / "f.tif"
    frame.write_bytes(b"")
    assert _check(calibration, frame, record=tmp_path / "qa.csv", options=["--system", "A"]) == 2
    assert "cannot read its project config" in capsys.readouterr().err and not (tmp_path / "qa.csv").exists()
    assert _check(calibration, frame, record=tmp_path / "qa.csv", options=["--tol-rms", "0"]) == 2


def test_a_bead_phantom_frame_passes_its_systems_calibration_and_another_c_arms_fails(calibrated_project, tmp_path):
    calibration, frames, record = (
        calibrated_project / "out" / "calibration.json",
        calibrated_project / "frames",
        tmp_path / "qa.csv",
    )
    own = _check(calibration, frames / "A" / "frame_000.tif", record=record, options=["--system", "A"])
    other = _check(calibration, frames / "B" / "frame_000.tif", record=record, options=["--system", "A"])
    mine, theirs = _rows(record)
    assert (own, other) == (0, 1) and (mine["result"], theirs["result"]) == ("pass", "fail")
    # on its own frame the centroids' noise alone: measured 0.024 px RMS over 247 beads (bounds about 2x)
    assert float(mine["rms_px"]) < 0.05 and float(mine["p95_px"]) < 0.1 and int(mine["n_points"]) > 200
    # B's distortion is not A's: measured 0.36 px RMS, 1.52 px at most
    assert float(theirs["rms_px"]) > 0.2 and "no longer holds" in theirs["reason"]
    # the mm at the detector are the px at the config's pitch (0.5 mm)
    assert float(mine["rms_mm"]) == pytest.approx(0.5 * float(mine["rms_px"]), abs=1e-6)  # the record keeps 6 decimals


def test_a_frame_is_labelled_with_the_projects_own_tables_and_its_kind_is_the_calibrations(
    calibrated_project, tmp_path
):
    from fluorocal.calibration import Calibration
    from fluorocal.check_setups import PhantomSetup
    from fluorocal.cmd_check import reference_setup

    calibration = calibrated_project / "out" / "calibration.json"
    cal = Calibration.load(calibration)
    config = tmp_path / "fluorocal.toml"  # the project's config with a table of its own, beside its phantom
    text = (calibrated_project / "fluorocal.toml").read_text().replace('"frames/', f'"{calibrated_project}/frames/')
    config.write_text(text + "\n[detect]\nmin_snr = 12.5\n[label]\nmin_labelled = 25\n")
    shutil.copy(calibrated_project / "phantom.csv", tmp_path / "phantom.csv")
    cal.meta["config"] = str(config)
    setup = reference_setup(cal, calibration, "A")
    assert isinstance(setup, PhantomSetup)
    assert (setup.tables.detect.min_snr, setup.tables.label.min_labelled) == (12.5, 25)
    # a config that now names a plate does not turn a bead calibration into a plate's
    config.write_text(text.replace('file = "phantom.csv"', 'lattice = "hex"\npitch = 3.3'))
    with pytest.raises(InputError, match="made with a 3D bead phantom, but its config .* now names a grid plate"):
        reference_setup(cal, calibration, "A")
    # the kind is the one calibration.json names; one written before it named its kind: the kinds its
    # geometry_estimated allows (with two kinds, exactly the bead phantom)
    assert cal.meta["phantom_kind"] == "beads"
    del cal.meta["phantom_kind"]
    with pytest.raises(InputError, match="made with a 3D bead phantom, but its config .* now names a grid plate"):
        reference_setup(cal, calibration, "A")
    cal.meta["phantom_kind"] = "wand"  # a kind this version does not know
    with pytest.raises(InputError, match="made with a kind of object named 'wand', but its config"):
        reference_setup(cal, calibration, "A")
    # a phantom_kind that contradicts geometry_estimated was edited: refused naming both, whatever the config
    # names (a bead calibration, which estimated the geometry, is never checked as a plate's, nor said a plate's)
    cal.meta["phantom_kind"] = "plate"
    for named in (text, text.replace('file = "phantom.csv"', 'lattice = "hex"\npitch = 3.3')):
        config.write_text(named)
        with pytest.raises(InputError, match="its phantom_kind 'plate' contradicts its geometry_estimated true"):
            reference_setup(cal, calibration, "A")
    cal.meta.update(phantom_kind="beads", geometry_estimated=False)
    with pytest.raises(InputError, match="its phantom_kind 'beads' contradicts its geometry_estimated false"):
        reference_setup(cal, calibration, "A")


def test_the_defaults_are_stated_in_the_help(capsys):
    with pytest.raises(SystemExit):
        main(["check", "--help"])
    text = capsys.readouterr().out
    assert all(f"--tol-{name} {value:g} px" in text for name, value in TOLERANCES_PX.items())


@pytest.mark.slow
def test_real_frames_pass_at_their_orientation_and_fail_at_the_wrong_one(arcadis_calibration, arcadis_dir, tmp_path):
    folder = tmp_path / "later"  # copies with the C-arm angles written in: the shared data stay untouched
    folder.mkdir()
    for name, (orbit, tilt) in GRID.items():
        ds = pydicom.dcmread(Path(arcadis_dir) / name)
        ds.PositionerPrimaryAngle, ds.PositionerSecondaryAngle = orbit, tilt
        ds.save_as(folder / name)
    record = tmp_path / "qa_record.csv"
    assert _check(arcadis_calibration, folder, record=record) == 0
    rows = _rows(record)
    assert [r["file"] for r in rows] == sorted(GRID) and all(r["result"] == "pass" for r in rows)
    # in sample: about 0.02 px per component, well inside the 0.1 px tolerance; mm = px x 0.21 mm
    assert all(float(r["rms_px"]) < 0.05 and int(r["n_points"]) > 3000 for r in rows)
    assert all(abs(float(r["rms_mm"]) - 0.21 * float(r["rms_px"])) < 1e-5 for r in rows)
    assert (tmp_path / "qa_trend.png").stat().st_size > 0
    # the centred field on the tilt-60 frame: the field moved by 0.4 px between them, the check fails
    wrong = ["--orientation", "centred"]
    assert _check(arcadis_calibration, folder / "grid_tilt_60.dcm", record=record, options=wrong) == 1
    last = _rows(record)[-1]
    assert last["result"] == "fail" and float(last["rms_px"]) > 0.3 and "RMS" in last["reason"]
    assert len(_rows(record)) == len(GRID) + 1


@pytest.mark.slow
def test_a_frame_of_another_c_arm_fails_with_its_reason(arcadis_calibration, tmp_path):
    from fluorocal.cmd_simulate import write_dataset
    from fluorocal.stages.simulate import SimulateParams, simulate

    data = simulate(SimulateParams(phantom="grid", n_frames=1, image_size_px=1024, seed=9))
    write_dataset(data, tmp_path / "sim", fmt="dicom")
    (frame,) = sorted((tmp_path / "sim" / "frames" / "A").glob("*.dcm"))
    assert pydicom.dcmread(frame).Rows == 1024
    record = tmp_path / "qa.csv"
    assert _check(arcadis_calibration, frame, record=record, options=["--orientation", "centred"]) == 1
    (row,) = _rows(record)
    assert row["result"] == "fail" and "another plate, or another C-arm" in row["reason"]
    assert np.isnan(float(row["rms_px"]))
