"""Issue 32, angles from the frames: `fluorocal undistort` follows the C-arm angles each frame records.

Ground truth: the simulator's grid plate seen through a C-arm whose distortion changes with its tilt (the
earth field), at 0, 15, 30, 45 and 60 degrees; the calibration holds the true correction at 0, 30 and 60
degrees, so the frames at 15 and 45 degrees take an interpolated field.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pydicom
import pytest
from fluorocal.calibration import Calibration, SystemCalibration
from fluorocal.cli import main
from fluorocal.config import load_config
from fluorocal.orientations import frame_orientations
from fluorocal.stages.errors import InputError
from fluorocal.stages.geometry import homography_fit
from fluorocal.stages.io import read_frames
from fluorocal.stages.io.dicom import frame_angles_deg
from fluorocal.stages.orientation import OrientationField
from fluorocal.units import frame_units

from tests.pipeline.orientation_toys import angled_dicom
from tests.stages.plate_truth import truth_field

SIZE = 512
TILTS = (0.0, 15.0, 30.0, 45.0, 60.0)
CALIBRATED = {"centred": 0.0, "tilt30": 30.0, "tilt60": 60.0}
#: corrected points against the truth modulo a homography, px: the true fields on the simulator's 8 px correction
#: grid leave 0.0013 px at the calibrated tilts and 0.0045 px interpolated at 15 and 45 deg (measured), the next
#: orientation's field (15 deg off) 0.090-0.149 px, the centred one at 60 deg 0.468 px
TOL_PX = 0.05


def _undistort(*inputs, calibration, out, options=(), system="A"):
    args = ["--quiet", "undistort", str(calibration), *map(str, inputs), "--system", system]
    return main(args + ["--out", str(out), *options])


def _residual_px(ideal_true, ideal_est) -> float:
    return float(np.sqrt(np.mean(homography_fit(ideal_true, ideal_est)[1] ** 2)))


@pytest.fixture(scope="module")
def rotational(simulated_tilts, tmp_path_factory):
    """Simulated frames at :data:`TILTS`, their truth, and a calibration of the true fields at :data:`CALIBRATED`.

    The frames are the session's (tests/conftest.py's GRID_TILTS_SIM), single-frame DICOMs as `fluorocal simulate`
    writes them; read only, the calibration is written in this module's own folder.
    """
    root = tmp_path_factory.mktemp("rotational")
    truth = json.loads((simulated_tilts / "truth.json").read_text())
    assert truth["params"]["image_size_px"] == SIZE and [f["tilt_deg"] for f in truth["frames"]] == list(TILTS)
    fields = {o["name"]: truth_field(o["correction_grid"], SIZE, SIZE) for o in truth["systems"][0]["orientations"]}
    orientations = [OrientationField(n, 0.0, t, fields[n]) for n, t in CALIBRATED.items()]
    system = SystemCalibration(
        "A",
        (SIZE, SIZE),
        np.array([SIZE / 2, SIZE / 2, 4000.0]),
        np.zeros(3),
        np.array([1.0, 0, 0, 0]),
        np.zeros(3),
        None,
        tuple(orientations),
    )
    calibration = root / "cal" / "calibration.json"
    calibration.parent.mkdir()
    Calibration([system], {}, {"scheme": "truth", "geometry_estimated": False}).save(calibration)
    files = sorted((simulated_tilts / "frames" / "A").glob("*.dcm"))
    return root, files, truth, calibration


def _run_file(files, path: Path, tilts, how: str) -> Path:
    """A rotational run: the frames of ``files`` in one multi-frame DICOM, ``PositionerMotion`` DYNAMIC.

    The per-frame angles ``tilts`` are in the per-frame functional groups (``how="groups"``) or increments.
    """
    from pydicom.dataset import Dataset

    ds = pydicom.dcmread(files[0])
    frames = np.stack([pydicom.dcmread(f).pixel_array for f in files])
    ds.NumberOfFrames, ds.PositionerMotion = len(files), "DYNAMIC"
    ds.PixelData = frames.astype("<u2").tobytes()
    if how == "groups":
        del ds.PositionerPrimaryAngle, ds.PositionerSecondaryAngle
        items = []
        for tilt in tilts:
            position, item = Dataset(), Dataset()
            position.PositionerPrimaryAngle, position.PositionerSecondaryAngle = 0, tilt
            item.PositionerPositionSequence = [position]
            items.append(item)
        ds.PerFrameFunctionalGroupsSequence = items
    else:  # the start angles, then each frame's offset from them (DICOM PS3.3 C.8.7.5.1.3)
        ds.PositionerPrimaryAngle, ds.PositionerSecondaryAngle = 0, tilts[0]
        ds.PositionerPrimaryAngleIncrement = [0] * len(tilts)
        ds.PositionerSecondaryAngleIncrement = [t - tilts[0] for t in tilts]
    ds.save_as(path, enforce_file_format=True)
    return path


def _header(path: Path, start, primary, secondary, n: int = 4) -> Path:
    """A header-only rotational run: ``n`` frames, start angles ``start``, the two increments as given."""
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, XRayAngiographicImageStorage, generate_uid

    meta = FileMetaDataset()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = XRayAngiographicImageStorage, generate_uid()
    ds = FileDataset(str(path), {}, file_meta=meta, preamble=b"\0" * 128)
    ds.NumberOfFrames, ds.PositionerMotion = n, "DYNAMIC"
    ds.PositionerPrimaryAngle, ds.PositionerSecondaryAngle = start
    ds.PositionerPrimaryAngleIncrement, ds.PositionerSecondaryAngleIncrement = primary, secondary
    ds.save_as(path, enforce_file_format=True)
    return path


def test_angle_increments_read_as_the_dicom_standard_defines_them(tmp_path):
    """DICOM PS3.3 C.8.7.5.1.3's two forms of the increments, and the absolute angles it permits.

    One value is the average change per frame; one per frame, each frame's offset from the start angles (not the
    change since the frame before); a vector of absolute angles with start angles 0 reads the same.
    """
    average = _header(tmp_path / "a.dcm", (10, -5), 2.5, -1.0)
    assert frame_angles_deg(average) == ((10.0, -5.0), (12.5, -6.0), (15.0, -7.0), (17.5, -8.0))
    # a sweep of 200 degrees: its offsets reach beyond 180, its angles do not
    sweep = _header(tmp_path / "s.dcm", (-100, 0), [0, 50, 150, 200], 0)
    assert [a for a, _ in frame_angles_deg(sweep)] == [-100.0, -50.0, 50.0, 100.0]
    offsets = _header(tmp_path / "b.dcm", (10, -5), [0, 5, 10, 20], [0, 0, 1, 1])
    assert frame_angles_deg(offsets) == ((10.0, -5.0), (15.0, -5.0), (20.0, -4.0), (30.0, -4.0))
    absolute = _header(tmp_path / "c.dcm", (0, 0), [10, 15, 20, 30], [-5, -5, -4, -4])
    assert frame_angles_deg(absolute) == frame_angles_deg(offsets)
    with pytest.raises(InputError, match=r"d\.dcm: PositionerPrimaryAngleIncrement has 2 values for 4 frames"):
        frame_angles_deg(_header(tmp_path / "d.dcm", (0, 0), [1, 2], [0, 0]))


def test_simulate_writes_the_c_arm_angles(rotational):
    _, files, truth, _ = rotational
    recorded = [frame_angles_deg(f) for f in files]
    assert recorded == [((0.0, t),) for t in TILTS] and [f["tilt_deg"] for f in truth["frames"]] == list(TILTS)


@pytest.mark.slow
@pytest.mark.parametrize("how", ["groups", "increments"])
def test_a_rotational_run_is_undistorted_frame_by_frame_with_each_frames_field(rotational, tmp_path, how):
    _, files, truth, calibration = rotational
    run = _run_file(files, tmp_path / "run.dcm", TILTS, how)
    assert frame_angles_deg(run) == tuple((0.0, t) for t in TILTS)
    assert _undistort(run, calibration=calibration, out=tmp_path / "u", options=["--outside", "keep"]) == 0
    cal = Calibration.load(calibration)
    out = pydicom.dcmread(tmp_path / "u" / "run.dcm")
    assert "frame by frame: 0/0, 0/15, 0/30, 0/45, 0/60" in out.DerivationDescription
    sources = [f.image.astype(np.uint16) for f in read_frames(run)]
    for k, (tilt, frame, source) in enumerate(zip(TILTS, truth["frames"], sources)):
        angles = {"orbit": 0.0, "tilt": tilt}
        # the frame was remapped with the field at its own angles ...
        np.testing.assert_array_equal(out.pixel_array[k], cal.undistort_image("A", source, orientation=angles))
        # ... which puts its holes where the truth has them
        distorted, ideal = (np.array(frame["beads"][key]) for key in ("distorted_xy_px", "ideal_xy_px"))
        assert _residual_px(ideal, cal.undistort_points("A", distorted, orientation=angles)) < TOL_PX
    # one field for the whole run would not do: the centred field leaves more than the tolerance at 60 deg
    last = truth["frames"][-1]["beads"]
    centred = cal.undistort_points("A", np.array(last["distorted_xy_px"]), orientation="centred")
    assert _residual_px(np.array(last["ideal_xy_px"]), centred) > 2 * TOL_PX
    assert not np.array_equal(out.pixel_array[-1], cal.undistort_image("A", sources[-1], orientation="centred"))


@pytest.mark.slow
def test_a_frame_beyond_the_calibrated_angles_is_refused_naming_it_and_the_range(rotational, tmp_path, capsys):
    _, files, _, calibration = rotational
    run = _run_file(files[:3], tmp_path / "run.dcm", (0.0, 30.0, 75.0), "groups")
    assert _undistort(run, calibration=calibration, out=tmp_path / "u") == 2
    err = capsys.readouterr().err
    assert "run.dcm, frame 2: at the C-arm angles it records" in err and "orbit 0°, tilt 0..60°" in err
    assert not (tmp_path / "u").exists()
    # --orientation overrides the recorded angles
    assert _undistort(run, calibration=calibration, out=tmp_path / "v", options=["--orientation", "tilt60"]) == 0


def test_the_calibration_groups_frames_by_their_recorded_angles_within_the_read_out_tolerance(tmp_path):
    frames = tmp_path / "frames"
    for name, angles in {"a": (30, 0), "b": (30.04, 0), "c": (30.1, 0), "d": None}.items():
        angled_dicom(frames / f"{name}.dcm", angles=angles)
    (tmp_path / "phantom.csv").write_text("id,x,y,z\n1,0,0,0\n2,10,0,0\n3,0,10,0\n4,0,0,10\n")
    (tmp_path / "project.toml").write_text(
        '[phantom]\nfile = "phantom.csv"\n\n[[systems]]\nname = "A"\nframes = "frames/*.dcm"\n'
        "source_image_distance = 1100\npixel_pitch = 0.25\n"
    )
    config = load_config(tmp_path / "project.toml")
    got = [tuple(o) for o in frame_orientations(config, frame_units(config))]
    # 0.04 deg apart: within the read-out's 0.05 deg, one orientation; 0.1 deg (one DICOM step): another
    assert got == [("orbit30_tilt0", 30.0, 0.0)] * 2 + [("orbit30.1_tilt0", 30.1, 0.0), ("d", None, None)]


# --- the real frames, with angles written into copies -----------------------------------------------------------

#: the C-arm angles written into copies of the real frames: two calibrated orientations and one in between
REAL = {"grid_orbit_30.dcm": (30.0, 0.0), "grid_tilt_45.dcm": (0.0, 45.0), "spine_centered_0.dcm": (15.0, 0.0)}


@pytest.mark.slow
def test_real_frames_with_recorded_angles_equal_the_explicit_orientation(arcadis_calibration, arcadis_dir, tmp_path):
    folder = tmp_path / "with_angles"  # copies in the test's own folder: the shared data stay untouched
    folder.mkdir()
    for name, (orbit, tilt) in REAL.items():
        ds = pydicom.dcmread(Path(arcadis_dir) / name)
        ds.PositionerPrimaryAngle, ds.PositionerSecondaryAngle = orbit, tilt
        ds.save_as(folder / name)
    cal_args = {"calibration": arcadis_calibration, "system": "arcadis"}
    assert _undistort(folder, out=tmp_path / "recorded", **cal_args) == 0
    for name, (orbit, tilt) in REAL.items():
        explicit = tmp_path / f"explicit_{name}"
        assert (
            _undistort(folder / name, out=explicit, options=["--orientation", f"orbit={orbit},tilt={tilt}"], **cal_args)
            == 0
        )
        recorded = pydicom.dcmread(tmp_path / "recorded" / name)
        assert recorded.PixelData == pydicom.dcmread(explicit / name).PixelData  # byte for byte
        where = f"orbit {orbit:g} deg, tilt {tilt:g} deg (the C-arm angles the file records)"
        assert where in recorded.DerivationDescription
    # a copy recorded beyond the calibrated orientations is refused
    shutil.copyfile(folder / "grid_orbit_30.dcm", tmp_path / "beyond.dcm")
    ds = pydicom.dcmread(tmp_path / "beyond.dcm")
    ds.PositionerPrimaryAngle = 45
    ds.save_as(tmp_path / "beyond.dcm")
    assert _undistort(tmp_path / "beyond.dcm", out=tmp_path / "refused", **cal_args) == 2
    assert not (tmp_path / "refused").exists()
