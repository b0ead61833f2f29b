"""`fluorocal run` on grid plates: a simulated sequence against its truth, and the real ARCADIS frames.

The real frames (../shared/data, skipped when absent) carry the issue's targets: each frame's holes,
scored on alternate lattice rows left out of the fit, against the plate's self-calibrated layout by a
homography, within 0.06 px RMS; and the README's walk-through: one orientation's grid frame calibrates,
the spine frame is undistorted.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from fluorocal import Calibration
from fluorocal.cli import main

from tests.pipeline.plate_orientation import REAL_ORIENTATIONS, real_grid_config
from tests.stages.plate_truth import field_error_px, truth_field


def test_simulated_grid_outputs(simulated_grid):
    out = simulated_grid / "out"
    doc = json.loads((out / "calibration.json").read_text())
    (system,) = doc["systems"]
    assert [o["name"] for o in system["orientations"]] == ["centred"]
    assert system["iop_std_px"] == [None, None, None]  # a plate fixes no interior orientation: said, not faked
    assert "not estimated" in doc["interior_orientation"]
    cal = Calibration.load(out / "calibration.json")
    from fluorocal.stages.errors import InputError

    for call in (lambda: cal.intrinsics("A"), lambda: cal.rays("A", [[1.0, 2.0]])):
        with pytest.raises(InputError, match="grid plate"):  # no geometry to give: refused, never made up
            call()
    report = (out / "report.md").read_text()
    assert "The plate's own errors, estimated" in report
    rows = (out / "object_points.csv").read_text().splitlines()
    assert rows[0] == "id,x,y,z,sx,sy,sz" and len(rows) > 800  # a row per hole seen: 876 measured


def test_simulated_grid_fields_match_truth(simulated_grid):
    truth = json.loads((simulated_grid / "truth.json").read_text())
    cal = Calibration.load(simulated_grid / "out" / "calibration.json")
    size = truth["image_size_px"]
    true = truth_field(truth["systems"][0]["correction_grid"], size, size)
    # the issue's target for a field: within 0.05 px of the truth modulo a homography
    assert field_error_px(cal.field("A", "centred"), true, truth["fov"]) < 0.05


def test_real_grid_frames_held_out_rows(arcadis_dir, tmp_path):
    """The issue's real-data target on two of the six frames (each scored twice: even rows out, odd rows out)."""
    from fluorocal.cache import ArtifactCache
    from fluorocal.config import load_config
    from fluorocal.gather import observations_from_labels
    from fluorocal.graph import default_stages, plate_orientations
    from fluorocal.run import Runner
    from fluorocal.stages.label.lattice import lattice_index
    from fluorocal.stages.plate import PlateParams
    from fluorocal.stages.plate.holdout import holdout_score
    from fluorocal.stages.plate.problem import frame_orientations, plate_problem

    config = load_config(real_grid_config(tmp_path, arcadis_dir, list(REAL_ORIENTATIONS)))
    runner = Runner(config, default_stages(), ArtifactCache(config.cache_dir), until="label", progress=False)
    runner.run()
    labels = [runner.get("label", u) for u in range(len(runner.units))]
    assert all(lab.ok for lab in labels)
    obs = observations_from_labels(runner.units, labels, config)
    groups = frame_orientations(obs, plate_orientations(config, runner.units))
    problem, index = plate_problem(obs, config.phantom, 0, groups, (1024, 1024))
    row = lattice_index(index["hole_ids"])[:, 1]
    score = holdout_score(problem, PlateParams().settings(config.phantom.pitch_mm, True), row, frames=[0, 4])
    # the issue: <= 0.06 px RMS on held-out holes (measured 0.037 by benchmarks/plate.py over all six frames)
    assert score.rms(score.residual_px) < 0.06
    # the plate's own errors matter: the same corrected holes lie > 2.5x farther from the nominal lattice
    assert score.rms(score.nominal_residual_px) > 2.5 * score.rms(score.residual_px)


def test_real_walkthrough_grid_to_spine(arcadis_dir, tmp_path, capsys):
    """README: the centred grid frame calibrates its orientation; the spine frame and the grid frame are undistorted.

    The README's own config (fixtures/arcadis/centred.toml), its frames pointed at ``arcadis_dir``; the table the
    README quotes is the one the run prints.
    """
    root = Path(__file__).resolve().parents[2]
    fixture = root / "fixtures" / "arcadis" / "centred.toml"
    (tmp_path / "project").mkdir()
    config = tmp_path / "project" / "centred.toml"
    config.write_text(fixture.read_text().replace("../../../shared/data/arcadis", str(arcadis_dir)))
    assert main(["--quiet", "run", str(config)]) == 0
    printed = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| arcadis |")]
    quoted = [line for line in (root / "README.md").read_text().splitlines() if line.startswith("| arcadis |")]
    assert printed and quoted == printed
    cal_path = tmp_path / "project" / "out-centred" / "calibration.json"
    out = tmp_path / "undistorted"
    spine, grid = arcadis_dir / "spine_centered_0.dcm", arcadis_dir / "grid_centered_0.dcm"
    assert (
        main(
            [
                "--quiet",
                "undistort",
                str(cal_path),
                "--system",
                "arcadis",
                "--orientation",
                "centred",
                "--out",
                str(out),
                str(spine),
                str(grid),
            ]
        )
        == 0
    )
    from fluorocal.stages.io import read_frames

    written = read_frames(out / "spine_centered_0.dcm")[0]
    source = read_frames(spine)[0]
    assert written.image.shape == source.image.shape and written.bit_depth == source.bit_depth
    # the undistorted grid frame: its holes lie on a homography of the lattice to within the plate's own errors
    # (0.19 px per component on this plate), where the raw frame is 1.5 px off
    assert _lattice_rms_px(out / "grid_centered_0.dcm") < 0.3
    assert _lattice_rms_px(grid) > 1.0


def _lattice_rms_px(path: Path) -> float:
    """RMS per component of the frame's holes about the best homography of the nominal lattice, px."""
    import cv2
    from fluorocal.stages.artifacts import Phantom
    from fluorocal.stages.centroid import CentroidParams, centroid_beads
    from fluorocal.stages.detect import DetectParams, detect_beads
    from fluorocal.stages.io import read_frames
    from fluorocal.stages.kinds.labelling import label_beads
    from fluorocal.stages.label import LabelParams

    frame = read_frames(path)[0]
    centroids = centroid_beads(frame, detect_beads(frame, DetectParams()), CentroidParams())
    labels = label_beads(centroids, Phantom([], [], [], [], "hex", 3.3), LabelParams(image_size_px=(1024, 1024)))
    H, _ = cv2.findHomography(labels.object_xyz_mm[:, :2], labels.xy_px, 0)
    mapped = cv2.perspectiveTransform(labels.object_xyz_mm[None, :, :2], H)[0]
    return float(np.sqrt(np.mean((labels.xy_px - mapped) ** 2)))


def test_bead_phantom_with_several_orientations_is_refused(tmp_path, capsys):
    """A bead phantom's system is one orientation (the phantom moves, the C-arm does not): groups are refused."""
    from tests.pipeline.toy import make_project

    groups = 'orientations = [{name = "a", frames = ["frames/f0.tif"]}, {name = "b", frames = "frames/f[12].tif"}]\n'
    cfg = make_project(tmp_path, extra_toml=groups)
    rc = main(["run", str(cfg)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "Traceback" not in err
    assert "orientations" in err and "3D bead phantom" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("section, lattice", [("plate", False), ("learn", True)])
def test_section_of_the_other_phantom_is_refused(tmp_path, capsys, section, lattice):
    """[plate] with a bead phantom, [learn] with a grid plate: refused, not silently ignored."""
    from tests.pipeline.toy import make_project

    cfg = make_project(tmp_path, extra_toml=f"\n[{section}]\nmax_iterations = 3\n")
    if lattice:
        cfg.write_text(cfg.read_text().replace('file = "phantom.csv"', 'lattice = "hex"\npitch = 3.6'))
    rc = main(["run", str(cfg)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "Traceback" not in err
    assert f"[{section}] does not apply" in err


def test_bead_phantom_orientation_named_in_the_calibration(calibrated_project, tmp_path):
    """One named group for a bead phantom's system: the calibration carries its name and angles."""
    from tests.conftest import copy_project

    project = copy_project(calibrated_project, tmp_path / "project")
    cfg = project / "fluorocal.toml"
    text = cfg.read_text()
    text = text.replace(
        'frames = "frames/A/',
        'orientations = [{name = "lab", frames = "frames/A/*.tif", orbit = 0, tilt = 0}]\nframes = "frames/A/',
        1,
    )
    cfg.write_text(text)
    assert main(["--quiet", "run", str(cfg)]) == 0
    cal = Calibration.load(project / "out" / "calibration.json")
    assert cal.orientation_names("A") == ["lab"]
    xy = np.array([[100.0, 200.0]])
    assert np.array_equal(cal.undistort_points("A", xy, orientation="lab"), cal.undistort_points("A", xy))


def test_grid_plate_systems_need_not_pair_frames(tmp_path):
    """Two systems with a grid plate each are calibrated apart: unequal frame counts are not a pairing error."""
    from fluorocal.config import load_config
    from fluorocal.units import frame_units

    from tests.pipeline.toy import make_two_system_project

    cfg = make_two_system_project(tmp_path)
    cfg.write_text(cfg.read_text().replace('file = "phantom.csv"', 'lattice = "hex"\npitch = 3.6'))
    (tmp_path / "frames" / "B" / "f1.tif").unlink()
    units = frame_units(load_config(cfg))
    assert [sum(u.system == s for u in units) for s in (0, 1)] == [3, 2]
