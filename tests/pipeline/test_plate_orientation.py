"""Issue 12's orientation target: a held-out C-arm orientation between calibrated ones, through interpolation.

Calibrated at three orientations 30° apart (tilt 0, 30, 60), the held-out orientations in between (tilt
15, 45) get <= 0.10 px through interpolation, where the transfer from the nearest calibrated one leaves
0.16-0.40 px. Protocol in tests/pipeline/plate_orientation.py (the one benchmarks/orientation.py prints):
every frame labelled by the pipeline with one numbering, the plate calibrated from the three frames, each
held-out frame's holes corrected and compared with the plate's self-calibrated layout by a homography,
RMS residual length per hole, px.

On the real ARCADIS frames (skipped when ../shared/data is absent) and on a small simulated sequence,
where the fields are also compared with the true correction.
"""

from __future__ import annotations

import json
from dataclasses import replace
from types import SimpleNamespace

import pytest
from fluorocal.stages.field import CorrectionField
from fluorocal.stages.orientation import OrientationField, interpolate_field

from tests.conftest import copy_project
from tests.pipeline.plate_orientation import (
    ANGLES_DEG,
    CALIBRATED,
    HELD_OUT,
    calibrate,
    held_out_frame,
    labelled_sequence,
    nearest,
    true_fields,
    write_project,
    write_real_project,
)
from tests.stages.plate_truth import field_error_px

#: the issue's target: RMS residual length per hole at a held-out orientation through interpolation, px
TARGET_PX = 0.10
#: interpolation must recover most of the orientation's change, not only beat the copy: at most this
#: fraction of the better neighbour's transfer (the issue's figures: <= 0.10 against >= 0.16 px)
MAX_RATIO_TO_TRANSFER = 0.6


def _scores(seq, cal, fields, name):
    frame = held_out_frame(seq, cal, fields, name)
    interpolated = interpolate_field(fields, *frame.angles_deg)
    transfers = {f.name: frame.rms_px(f.field) for f in nearest(fields, frame.angles_deg)}
    return frame, interpolated, frame.rms_px(interpolated), transfers


# --- real frames --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def real(arcadis_dir, tmp_path_factory):
    seq = labelled_sequence(write_real_project(tmp_path_factory.mktemp("real_orientations"), arcadis_dir))
    cal, fields = calibrate(seq, CALIBRATED)
    return seq, cal, fields


@pytest.mark.parametrize("name", HELD_OUT)
def test_real_held_out_orientation_through_interpolation(real, name):
    seq, cal, fields = real
    assert not seq.failed  # every frame labelled, one numbering
    frame, _, interpolated_px, transfers = _scores(seq, cal, fields, name)
    # nearly every hole of the frame is scored (~3440 labelled): the figure is not that of a chosen few
    assert frame.n_holes >= 3300
    assert interpolated_px <= TARGET_PX, (interpolated_px, transfers)
    assert interpolated_px <= MAX_RATIO_TO_TRANSFER * min(transfers.values()), (interpolated_px, transfers)
    # the frame is distorted by far more than any of this: uncorrected, a homography leaves > 1 px
    assert frame.rms_px(None) > 1.0


# --- simulated sequence, against truth -------------------------------------------------------------------


@pytest.fixture(scope="module")
def simulated(simulated_tilts, tmp_path_factory):
    """The session's grid frames at five tilts (conftest.py's GRID_TILTS_SIM), labelled and calibrated in a copy."""
    root = copy_project(simulated_tilts, tmp_path_factory.mktemp("sim_orientations") / "project")
    seq = labelled_sequence(root / "fluorocal.toml")
    cal, fields = calibrate(seq, CALIBRATED)
    truth = json.loads((root / "truth.json").read_text())
    return SimpleNamespace(root=root, seq=seq, cal=cal, fields=fields, truth=truth, true=true_fields(truth))


@pytest.mark.parametrize("name", HELD_OUT)
def test_interpolant_on_true_fields(simulated, name):
    """The interpolant alone: the true fields at 0, 30, 60° interpolated to 15 or 45° against the true field there.

    The simulated change follows the earth's field in the intensifier's frame, sines and cosines of the
    tilt: the parabola through samples h = 30° apart leaves at most |f'''| h³ / (9√3) ≈ 0.009 of the
    change's amplitude (below 1 px here), so 0.01 px; the change over 15° is ten times that or more.
    """
    seq, fields, truth, true = simulated.seq, simulated.fields, simulated.truth, simulated.true
    exact = [OrientationField(f.name, f.orbit_deg, f.tilt_deg, true[f.name]) for f in fields]
    error = field_error_px(interpolate_field(exact, *seq.angles_of(name)), true[name], truth["fov"])
    assert error <= 0.01
    # and the change is real: the nearest true field is off by far more than the interpolant's error
    nearest_error = min(field_error_px(f.field, true[name], truth["fov"]) for f in nearest(exact, ANGLES_DEG[name]))
    assert nearest_error >= 10 * max(error, 1e-3)


@pytest.mark.parametrize("name", HELD_OUT)
def test_simulated_held_out_orientation_through_interpolation(simulated, name):
    seq, cal, fields, truth, true = simulated.seq, simulated.cal, simulated.fields, simulated.truth, simulated.true
    assert not seq.failed
    frame, interpolated, interpolated_px, transfers = _scores(seq, cal, fields, name)
    assert frame.n_holes >= 700  # of ~810 holes in the field of view
    assert interpolated_px <= TARGET_PX, (interpolated_px, transfers)
    assert interpolated_px <= MAX_RATIO_TO_TRANSFER * min(transfers.values()), (interpolated_px, transfers)
    # against truth: the interpolated field is no worse than the calibrated fields it comes from, but for
    # the interpolant's own error (<= 0.01 px, test above)
    error = field_error_px(interpolated, true[name], truth["fov"])
    own = [field_error_px(f.field, true[f.name], truth["fov"]) for f in nearest(fields, frame.angles_deg)]
    assert error <= max(own) + 0.01, (error, own)
    transfer_errors = [field_error_px(f.field, true[name], truth["fov"]) for f in nearest(fields, frame.angles_deg)]
    assert error < min(transfer_errors), (error, transfer_errors)
    identity = CorrectionField.constant(true[name].width_px, true[name].height_px)
    assert field_error_px(identity, true[name], truth["fov"]) > 0.3  # the sequence is distorted


@pytest.mark.parametrize("name", HELD_OUT)
def test_simulated_interpolated_field_against_truth(simulated, name):
    """The issue's field target (0.05 px of the truth modulo a homography) at a held-out orientation.

    Three frames of ~0.03 px centroid noise on a 16-px node grid (about one hole per node per frame)
    and the plate's errors estimated from them: 0.05 px (measured 0.027 px by benchmarks/orientation.py at 1024 px).
    """
    seq, fields, truth, true = simulated.seq, simulated.fields, simulated.truth, simulated.true
    interpolated = interpolate_field(fields, *seq.angles_of(name))
    assert field_error_px(interpolated, true[name], truth["fov"]) <= 0.05


def test_simulated_transfer_is_the_real_c_arms(simulated):
    """The small sequence changes with orientation as the real C-arm does, so its target means the same.

    The issue measured 0.16-0.25 px on the real frames for a field used 15° off; 0.03 px either side
    for this sequence's own noise and plate.
    """
    seq, cal, fields = simulated.seq, simulated.cal, simulated.fields
    _, _, _, transfers = _scores(seq, cal, fields, "tilt15")
    assert all(0.13 <= v <= 0.28 for v in transfers.values()), transfers


def test_through_fluorocal_run_and_the_calibration_file(simulated):
    """The user's route: `fluorocal run` on the three frames, then ``Calibration.field(system, orientation=angles)``.

    The held-out frames (numbered in the five-frame sequence) corrected by the field the calibration file
    interpolates, against ``object_points.csv``'s layout: the same observations and solve as in-process,
    so the same figure up to the files' round trip (1e-6 px), and the target holds for what `fluorocal
    run` writes.
    """
    import numpy as np
    from fluorocal.calibration import Calibration
    from fluorocal.cli import main
    from fluorocal.stages.io import OBJECT_POINTS, read_table

    seq, cal, fields = simulated.seq, simulated.cal, simulated.fields
    root = simulated.root
    files = {n: next((root / "frames" / "A").glob(f"frame_*_{n}.dcm")).relative_to(root) for n in CALIBRATED}
    config = write_project(
        root / "three.toml",
        {n: f.as_posix() for n, f in files.items()},
        phantom='file = "phantom.csv"\nlattice = "hex"\npitch = 3.6',
        geometry="source_image_distance = 1100\npixel_pitch = 0.25",
        output_dir="out3",
    )
    assert main(["--quiet", "run", str(config)]) == 0
    calibration = Calibration.load(root / "out3" / "calibration.json")
    points = read_table(root / "out3" / "object_points.csv", OBJECT_POINTS)
    layout = {int(i): (x, y) for i, x, y in zip(points["id"], points["x"], points["y"])}
    for name in HELD_OUT:
        frame = held_out_frame(seq, cal, fields, name)
        field = calibration.field("A", orientation={"orbit": frame.angles_deg[0], "tilt": frame.angles_deg[1]})
        from_file = np.array([layout[int(i)] for i in frame.hole_id])
        via_files = replace(frame, layout_mm=from_file).rms_px(field)
        assert via_files <= TARGET_PX
        assert abs(via_files - frame.rms_px(interpolate_field(fields, *frame.angles_deg))) <= 1e-6
