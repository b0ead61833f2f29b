"""`fluorocal run` end to end on a small simulated biplanar set, checked against the simulator's truth."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from fluorocal import Calibration
from fluorocal.cli import main
from fluorocal.stages.io import read_frames
from fluorocal.stages.simulate import ImageDistortion, SimulateParams

from tests.conftest import E2E_SIM, copy_project
from tests.helpers import rms_modulo_homography

PARAMS = SimulateParams(**E2E_SIM)


@pytest.fixture(scope="module")
def project(tmp_path_factory, calibrated_project):
    """The session's calibrated project (its config as the simulator writes it: no [learn] block), copied."""
    return copy_project(calibrated_project, tmp_path_factory.mktemp("e2e") / "project")


def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_outputs_are_written(project):
    out = project / "out"
    for name in (
        "calibration.json",
        "field_A.npz",
        "field_B.npz",
        "object_points.csv",
        "observations.csv",
        "report.md",
        "convergence.png",
        "residuals_A.png",
        "field_sigma_A.png",
    ):
        assert (out / name).is_file(), name
    assert "RMS before" in (out / "report.md").read_text()
    # the recommended loop states the IOP's σ over the joint problem, and says so (README "Uncertainties")
    doc = json.loads((out / "calibration.json").read_text())
    assert "joint problem" in doc["uncertainty"] and "joint problem" in (out / "report.md").read_text()
    header = list(_rows(out / "observations.csv")[0])
    assert (
        header[:9] == ["system", "file", "exposure", "id", "x", "y", "sigma_x", "sigma_y", "rho"]
        and header[-1] == "inlier"
    )


def test_labels_match_the_truth(project):
    """Every observation is a bead the truth has in that frame, within 0.5 px of its outline centre (no mislabels)."""
    truth = json.loads((project / "truth.json").read_text())
    frames = {(f["system"], f["exposure"]): f["beads"] for f in truth["frames"]}
    errors = []
    for row in _rows(project / "out" / "observations.csv"):
        beads = frames[(row["system"], int(row["exposure"]))]
        i = beads["ids"].index(int(row["id"]))
        errors.append(
            np.hypot(float(row["x"]) - beads["outline_xy_px"][i][0], float(row["y"]) - beads["outline_xy_px"][i][1])
        )
    errors = np.array(errors)
    # a mislabel is off by a bead pitch (> 10 px); centroids of isolated beads are good to a few hundredths of a pixel,
    # those of beads touching a neighbour to a few tenths
    assert errors.max() < 2.0 and np.percentile(errors, 99) < 0.1 and len(errors) > 500


def test_calibration_api_is_consistent(project):
    cal = Calibration.load(project / "out" / "calibration.json")
    assert cal.system_names == ["A", "B"]
    rng = np.random.default_rng(0)
    xy = rng.uniform(100, 412, (50, 2))
    for name in cal.system_names:
        # the inverse is solved by Newton iteration to 1e-6 px; 1e-3 px is the bound
        np.testing.assert_allclose(cal.undistort_points(name, cal.distort_points(name, xy)), xy, atol=1e-3)
    obs = _rows(project / "out" / "observations.csv")
    pts = {
        int(r["id"]): np.array([float(r["x"]), float(r["y"]), float(r["z"])])
        for r in _rows(project / "out" / "object_points.csv")
    }
    rows = [r for r in obs if r["system"] == "B" and r["inlier"] == "1" and int(r["id"]) in pts]
    exposure = int(rows[0]["exposure"])
    rows = [r for r in rows if int(r["exposure"]) == exposure]
    measured = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    predicted = cal.project("B", exposure, np.array([pts[int(r["id"])] for r in rows]))
    residual = np.array([[float(r["residual_x"]), float(r["residual_y"])] for r in rows])
    # projecting the adjusted points reproduces the measurements up to the adjustment's own residuals
    rms_pred = np.sqrt(np.mean((predicted - measured) ** 2))
    assert rms_pred == pytest.approx(np.sqrt(np.mean(residual**2)), rel=0.1, abs=0.01)


def test_two_ray_intersection_recovers_the_points(project):
    cal = Calibration.load(project / "out" / "calibration.json")
    obs = [r for r in _rows(project / "out" / "observations.csv") if r["inlier"] == "1"]
    pts = {
        int(r["id"]): np.array([float(r["x"]), float(r["y"]), float(r["z"])])
        for r in _rows(project / "out" / "object_points.csv")
    }
    exposure = 1
    seen = {
        s: {
            int(r["id"]): (float(r["x"]), float(r["y"]))
            for r in obs
            if r["system"] == s and int(r["exposure"]) == exposure
        }
        for s in "AB"
    }
    common = sorted(set(seen["A"]) & set(seen["B"]) & set(pts))
    assert len(common) > 50
    xyz, miss = cal.intersect({s: np.array([seen[s][i] for i in common]) for s in "AB"}, exposure=exposure)
    err = np.linalg.norm(xyz - np.array([pts[i] for i in common]), axis=1)
    # a wrong pairing, pose or ROP would put points millimetres off (beads are 3.5 mm, 10 mm apart); with in-sample
    # residuals of a few tenths of a pixel at ~0.37 mm per pixel in the object, intersections agree to a few
    # tenths of a mm
    residual = np.array([[float(r["residual_x"]), float(r["residual_y"])] for r in obs])
    tol_mm = 3 * np.sqrt(np.mean(residual**2)) * PARAMS.pixel_pitch_mm / PARAMS.magnification
    assert np.sqrt(np.mean(err**2)) < tol_mm and np.median(miss) < tol_mm


def test_learned_field_moves_toward_the_truth(project):
    """Learned ideal coordinates are closer to the true ones (modulo a homography) than with no correction."""
    import cv2

    truth = json.loads((project / "truth.json").read_text())
    cal = Calibration.load(project / "out" / "calibration.json")
    centre, radius = np.array(truth["fov"]["centre_xy_px"]), truth["fov"]["radius_px"]
    g = np.linspace(0, 511, 64)
    pts = np.column_stack([a.ravel() for a in np.meshgrid(g, g)])
    pts = pts[np.linalg.norm(pts - centre, axis=1) < 0.7 * radius]

    def err(ideal, true_ideal, support):
        H, _ = cv2.findHomography(ideal[support], true_ideal[support], 0)
        return np.sqrt(
            np.mean(np.sum((cv2.perspectiveTransform(ideal[None], H)[0] - true_ideal) ** 2, axis=1)[support])
        )

    for system in truth["systems"]:
        true_ideal = ImageDistortion.from_dict(system["distortion"]).undistort_points(pts)
        support = cal.systems[system["name"]].field.support_at(pts)

        # 4 frames per system at 512 px learn the field only coarsely (measured 0.19 / 0.11 px against 0.44 px with no
        # correction); benchmarks/learn.py measures the full-size case. Halving the error is the bound here.
        ideal = cal.undistort_points(system["name"], pts)
        assert err(ideal, true_ideal, support) < 0.5 * err(pts, true_ideal, support)


def test_polynomial_scheme_end_to_end_reuses_the_labels(project, caplog):
    """Only the learning stage reruns; the global model lowers the field error (its radial + decentring part only)."""
    import logging

    cfg = project / "fluorocal.toml"
    text = cfg.read_text()
    assert 'scheme = "knn+iop+smooth"' in text and 'dir = "out"' in text
    poly = project / "polynomial.toml"
    poly.write_text(
        text.replace('scheme = "knn+iop+smooth"', 'scheme = "polynomial"').replace(
            'dir = "out"', 'dir = "out_polynomial"'
        )
    )
    with caplog.at_level(logging.INFO):
        assert main(["run", str(poly)]) == 0
    for stage, computed in (("detect", 0), ("centroid", 0), ("label", 0), ("learn", 1)):
        assert f"{stage}: {computed} computed" in caplog.text, stage
    cal = Calibration.load(project / "out_polynomial" / "calibration.json")
    assert cal.meta["scheme"] == "polynomial"
    truth = json.loads((project / "truth.json").read_text())
    centre, radius = np.array(truth["fov"]["centre_xy_px"]), truth["fov"]["radius_px"]
    g = np.linspace(0, 511, 64)
    pts = np.column_stack([a.ravel() for a in np.meshgrid(g, g)])
    pts = pts[np.linalg.norm(pts - centre, axis=1) < 0.7 * radius]
    for system in truth["systems"]:
        true_ideal = ImageDistortion.from_dict(system["distortion"]).undistort_points(pts)
        # measured 0.44 -> 0.34 px on system A: the simulator's distortion has local components no global model follows
        assert rms_modulo_homography(
            cal.undistort_points(system["name"], pts), true_ideal
        ) < 0.9 * rms_modulo_homography(pts, true_ideal)


def test_second_run_recomputes_nothing(project, caplog):
    import logging

    with caplog.at_level(logging.INFO):
        assert main(["run", str(project / "fluorocal.toml")]) == 0
    assert "nothing recomputed" in caplog.text


def test_inspect_and_overlay(project, capsys):
    assert main(["inspect", str(project / "fluorocal.toml")]) == 0
    table = capsys.readouterr().out
    assert all(f"{stage}" in table for stage in ("detect", "centroid", "label", "learn")) and "missing" not in table
    assert main(["inspect", str(project / "fluorocal.toml"), "label", "--frame", "5"]) == 0
    assert (project / "out" / "overlays" / "label_B_0001.png").is_file()


def test_undistort_keeps_format_and_depth(project, tmp_path):
    frame = project / "frames" / "A" / "frame_000.tif"
    assert (
        main(
            [
                "--quiet",
                "undistort",
                str(project / "out" / "calibration.json"),
                "--system",
                "A",
                "--outside",
                "keep",  # the maps alone: the edges' background has its own tests (test_clinic_edges.py)
                "--out",
                str(tmp_path),
                str(frame),
            ]
        )
        == 0
    )
    (src,), (dst,) = read_frames(frame), read_frames(tmp_path / frame.name)
    assert dst.image.shape == src.image.shape and dst.bit_depth == src.bit_depth
    # exactly the calibration's own resampling of the stored pixels (and that moved them)
    stored = src.image.astype(np.uint16)  # a 16-bit TIFF: read as float32, every value exact
    expected = Calibration.load(project / "out" / "calibration.json").undistort_image("A", stored)
    np.testing.assert_array_equal(dst.image, expected.astype(np.float32))
    assert np.abs(dst.image - src.image).max() > 0


def test_undistort_unknown_system_is_exit_2(project, tmp_path, capsys):
    frame = project / "frames" / "A" / "frame_000.tif"
    assert (
        main(
            [
                "undistort",
                str(project / "out" / "calibration.json"),
                "--system",
                "C",
                "--out",
                str(tmp_path),
                str(frame),
            ]
        )
        == 2
    )
    assert "--system 'C' is not in" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


@pytest.mark.filterwarnings("default::UserWarning")
def test_a_frame_without_beads_is_excluded_with_a_warning(project, tmp_path, capsys, caplog):
    import logging
    import shutil

    from fluorocal.stages.io import write_still

    root = tmp_path / "p"
    # the cache comes along (keys are content hashes): only the new frame, its labels and the adjustment recompute
    # (scheme "none": the exclusion is the point here, the learned field is tested above)
    shutil.copytree(project, root, ignore=shutil.ignore_patterns("out"))
    config = root / "fluorocal.toml"
    config.write_text(config.read_text().replace('scheme = "knn+iop+smooth"', 'scheme = "none"'))
    assert 'scheme = "none"' in config.read_text()
    write_still(root / "frames" / "B" / "frame_002.tif", np.full((512, 512), 1500, np.uint16))  # open field, no phantom
    with caplog.at_level(logging.WARNING):
        assert main(["run", str(root / "fluorocal.toml")]) == 0
    assert "frame_002.tif" in capsys.readouterr().err  # the detector's warning names the frame
    excluded = [r.getMessage() for r in caplog.records if "excluded" in r.getMessage()]
    assert len(excluded) == 1 and "frame_002.tif" in excluded[0]  # once per run
    assert (root / "out" / "calibration.json").is_file()
    listed = [
        line
        for line in (root / "out" / "report.md").read_text().splitlines()
        if line.startswith("Excluded (labelling failed):")
    ]
    assert len(listed) == 1 and "frame_002.tif" in listed[0]
