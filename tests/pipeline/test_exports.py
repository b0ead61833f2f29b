"""`fluorocal export`: every format written, read back with its own reader, and checked against the calibration.

Two calibrations: the session's simulated biplanar project after `fluorocal run` (IOP, poses, object
points and observations: every format), and a 1024² one built here with a smooth field of a few px
(the OpenCV target is stated on a 1024² frame), also saved as a grid plate's (no geometry).
"""

from __future__ import annotations

import ast
import re
import shutil

import cv2
import numpy as np
import pytest
from fluorocal.calibration import Calibration, SystemCalibration
from fluorocal.cli import main
from fluorocal.exports.dlt import from_dlt_frame
from fluorocal.exports.dlt import project as dlt_project
from fluorocal.exports.paper import opk_matrix
from fluorocal.stages.field import CorrectionField, grid_nodes
from fluorocal.stages.geometry import quat_to_matrix
from fluorocal.stages.orientation import OrientationField

SIDE = 1024


def _field(scale: float) -> CorrectionField:
    """A pincushion plus an S-shaped swirl (an image intensifier's two terms), up to ~``scale`` px."""
    x, y = grid_nodes(SIDE, SIDE, 32.0)
    yy, xx = np.meshgrid(y, x, indexing="ij")
    u, v = (xx - SIDE / 2) / (SIDE / 2), (yy - SIDE / 2) / (SIDE / 2)
    r2 = u**2 + v**2
    delta = scale * np.stack([u * r2 - 0.3 * v * r2, v * r2 + 0.3 * u * r2], axis=-1) / 2
    ones = np.ones(xx.shape)
    return CorrectionField(x, y, delta, 0.01 * ones, ones.astype(bool), SIDE, SIDE)


def _frame_1024(seed=0) -> np.ndarray:
    """A 12-bit 1024² frame with structure at every scale and noise, uint16."""
    yy, xx = np.mgrid[0:SIDE, 0:SIDE]
    noise = np.random.default_rng(seed).normal(0, 30, (SIDE, SIDE))
    image = 2000 + 1200 * np.sin(xx / 7.0) * np.cos(yy / 11.0) + 500 * np.sin((xx + yy) / 53.0) + noise
    return np.clip(image, 0, 4095).astype(np.uint16)


def _save_1024(folder, *, geometry: bool):
    """A 1024² calibration: system A with two orientations, B with one field; a grid plate's when not ``geometry``."""
    iop = np.array([500.0, 530.0, 4000.0])
    a = SystemCalibration(
        "A",
        (SIDE, SIDE),
        iop,
        np.zeros(3),
        np.array([1.0, 0, 0, 0]),
        np.zeros(3),
        None,
        (OrientationField("o0", 0.0, 0.0, _field(3.0)), OrientationField("o30", 30.0, 0.0, _field(-2.0))),
    )
    b = SystemCalibration("B", (SIDE, SIDE), iop, np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3), _field(4.0))
    meta = {"scheme": "test"} if geometry else {"scheme": "plate", "geometry_estimated": False}
    path = folder / "calibration.json"
    folder.mkdir(parents=True, exist_ok=True)
    Calibration([a, b], {}, meta).save(path)
    return path


@pytest.fixture(scope="module")
def run_out(tmp_path_factory, calibrated_project):
    """The calibrated project's outputs (calibration, fields and tables), copied: exports cache maps beside them."""
    out = tmp_path_factory.mktemp("export") / "out"
    shutil.copytree(calibrated_project / "out", out, ignore=shutil.ignore_patterns("*.png", "report.md"))
    return out


def _export(calibration, fmt, out, *extra) -> int:
    return main(["--quiet", "export", str(calibration), "--format", fmt, "--out", str(out), *extra])


def _ideal(cal, system, exposure, xyz):
    """The model of fluorocal itself: the undistorted (ideal pinhole) image of object points, px."""
    return cal.undistort_points(system, cal.project(system, exposure, xyz))


def _held_out_points(points_xyz, n=300, seed=1):
    """Object points none of the exports saw: uniform in the phantom's bounding box, mm."""
    lo, hi = points_xyz.min(axis=0), points_xyz.max(axis=0)
    return np.random.default_rng(seed).uniform(lo, hi, (n, 3))


def _object_points(out):
    rows = np.loadtxt(out / "object_points.csv", delimiter=",", skiprows=1)
    return rows[:, 0].astype(int), rows[:, 1:4]


# --- opencv ---------------------------------------------------------------------------------------


def _maps_as_documented(fs) -> tuple[np.ndarray, np.ndarray]:
    """``map_x, map_y`` joined from their byte planes by docs/exports.md's lines (no fluorocal code)."""
    h, w = int(fs.getNode("image_height").real()), int(fs.getNode("image_width").real())
    assert all(fs.getNode(f"map_{a}_bytes").mat().dtype == np.uint8 for a in "xy")
    assert all(fs.getNode(f"map_{a}_bytes").mat().shape == (4 * h, w) for a in "xy")
    # docs/exports.md, as it is there:
    planes = [fs.getNode(f"map_{a}_bytes").mat().reshape(4, h, -1) for a in "xy"]
    map_x, map_y = (np.ascontiguousarray(p.transpose(1, 2, 0)).view("<f4")[..., 0] for p in planes)
    return map_x, map_y


def _frames_of_every_type(frame_u16) -> list[np.ndarray]:
    """The frame as each sample type ``Calibration.undistort_image`` takes (uint8, uint16, int16, float32, float64)."""
    signed = (frame_u16.astype(np.int32) - 2048).astype(np.int16)
    scaled = frame_u16.astype(np.float64) / 4095
    return [(frame_u16 >> 4).astype(np.uint8), frame_u16, signed, scaled.astype(np.float32), scaled]


@pytest.fixture(scope="module")
def opencv_export(tmp_path_factory):
    """A 1024² calibration of two systems (A at two orientations) and its OpenCV export, once: ``(json, folder)``."""
    root = tmp_path_factory.mktemp("opencv")
    calibration = _save_1024(root / "cal", geometry=True)
    assert _export(calibration, "opencv", root / "x") == 0
    return calibration, root / "x"


def test_opencv_yaml_read_back_and_remapped_equals_fluorocal_undistort(opencv_export):
    calibration, x = opencv_export
    cal = Calibration.load(calibration)
    frame = _frame_1024()
    names = sorted(p.name for p in x.iterdir())
    assert names == ["opencv_A_o0.yml.gz", "opencv_A_o30.yml.gz", "opencv_B.yml.gz"]
    for name, system, orientation in [("opencv_A_o30.yml.gz", "A", "o30"), ("opencv_B.yml.gz", "B", None)]:
        fs = cv2.FileStorage(str(x / name), cv2.FILE_STORAGE_READ)
        map_x, map_y = _maps_as_documented(fs)
        K = fs.getNode("camera_matrix").mat()
        size = (int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real()))
        nominal = int(fs.getNode("camera_matrix_nominal").real())
        encoding = fs.getNode("map_encoding").string()
        fs.release()
        assert map_x.dtype == np.float32 and map_x.shape == (SIDE, SIDE) and size == (SIDE, SIDE) and nominal == 0
        assert "byte planes" in encoding and "cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR)" in encoding
        np.testing.assert_array_equal(K, [[4000.0, 0, 500.0], [0, 4000.0, 530.0], [0, 0, 1]])
        # the maps come back bit for bit, so the remap is fluorocal's own for every type it resamples: 0 DN
        maps = Calibration.load(calibration).remap_maps(system, orientation=orientation)
        np.testing.assert_array_equal(np.stack([map_x, map_y]).view(np.int32), np.stack(maps).view(np.int32))
        for image in _frames_of_every_type(frame):
            remapped = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            np.testing.assert_array_equal(remapped, cal.undistort_image(system, image, orientation=orientation))
        # the maps do undistort: the field moves pixels by up to a few px (not an identity export)
        assert np.abs(map_x - np.arange(SIDE)).max() > 1.0


def test_opencv_yaml_remap_equals_the_fluorocal_undistort_command(opencv_export, tmp_path):
    calibration, x = opencv_export
    frame = _frame_1024(seed=3)
    source = tmp_path / "frames" / "frame.png"
    source.parent.mkdir()
    assert cv2.imwrite(str(source), frame)  # 16-bit PNG
    assert (
        # --outside keep: the maps alone, as cv2.remap applies them (the edges' background is the command's own)
        main(
            ["--quiet", "undistort", str(calibration), str(source), "--system", "B", "--outside", "keep"]
            + ["--out", str(tmp_path / "u")]
        )
        == 0
    )
    undistorted = cv2.imread(str(tmp_path / "u" / "frame.png"), cv2.IMREAD_UNCHANGED)
    fs = cv2.FileStorage(str(x / "opencv_B.yml.gz"), cv2.FILE_STORAGE_READ)
    map_x, map_y = _maps_as_documented(fs)
    fs.release()
    remapped = cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    assert undistorted.dtype == np.uint16 and undistorted.shape == (SIDE, SIDE)
    # the target, against the command itself: equal to 0 DN
    np.testing.assert_array_equal(remapped, undistorted)


def test_opencv_exports_a_grid_plate_with_the_camera_matrix_flagged_nominal(tmp_path):
    calibration = _save_1024(tmp_path / "cal", geometry=False)
    assert _export(calibration, "opencv", tmp_path / "x") == 0
    fs = cv2.FileStorage(str(tmp_path / "x" / "opencv_B.yml.gz"), cv2.FILE_STORAGE_READ)
    assert int(fs.getNode("camera_matrix_nominal").real()) == 1
    map_x, _ = _maps_as_documented(fs)
    fs.release()
    np.testing.assert_array_equal(map_x, Calibration.load(calibration).remap_maps("B")[0])


@pytest.mark.parametrize("fmt", ["dlt", "mayacam", "mrcal", "paper"])
def test_formats_needing_geometry_refuse_a_grid_plate_in_one_line(tmp_path, capsys, fmt):
    calibration = _save_1024(tmp_path / "cal", geometry=False)
    assert _export(calibration, fmt, tmp_path / "x") == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"--format {fmt} needs the interior orientation" in err and "grid plate" in err
    assert not (tmp_path / "x").exists()  # refused before writing anything


# --- dlt ------------------------------------------------------------------------------------------


def _read_dlt(path) -> np.ndarray:
    """A DLTdv / XMALab coefficient file: 11 rows, one column per camera, no header."""
    coefficients = np.loadtxt(path, delimiter=",", ndmin=2)
    assert coefficients.shape[0] == 11
    return coefficients


def test_dlt_reprojects_held_out_points_as_fluorocal_does(run_out, tmp_path, capsys):
    assert _export(run_out / "calibration.json", "dlt", tmp_path / "x") == 0
    cal = Calibration.load(run_out / "calibration.json")
    _, xyz = _object_points(run_out)
    held_out = _held_out_points(xyz)
    for exposure in sorted(cal.exposures):
        coefficients = _read_dlt(tmp_path / "x" / f"dlt_exposure{exposure}.csv")
        assert coefficients.shape == (11, len(cal.system_names))
        for column, system in enumerate(cal.system_names):
            height = cal.systems[system].image_size_px[1]
            dlt_xy = from_dlt_frame(dlt_project(coefficients[:, column], held_out), height)
            diff = dlt_xy - _ideal(cal, system, exposure, held_out)
            # the target is 0.1 px RMS; a pinhole's DLT is exact, so what is left is float64 rounding
            # of coordinates below 1e3 px through the field's Newton inversion (1e-9 px)
            assert np.sqrt(np.mean(diff**2)) < 1e-6


def test_dlt_rms_is_the_models_on_the_undistorted_beads(run_out, tmp_path):
    """The stated RMS is re-measured here from the tables, through the DLT file and DLTdv's frame."""
    assert _export(run_out / "calibration.json", "dlt", tmp_path / "x") == 0
    cal = Calibration.load(run_out / "calibration.json")
    ids, xyz = _object_points(run_out)
    index = {int(i): k for k, i in enumerate(ids)}
    import csv

    with open(run_out / "observations.csv", newline="") as fh:
        obs = [r for r in csv.DictReader(fh) if r["inlier"].strip().lower() in ("true", "1")]
    with open(tmp_path / "x" / "dlt_rms.csv", newline="") as fh:
        stated = {(int(r["exposure"]), r["system"]): float(r["rms_px"]) for r in csv.DictReader(fh)}
    assert set(stated) == {(e, s) for e in cal.exposures for s in cal.system_names}
    for (exposure, system), rms in stated.items():
        rows = [r for r in obs if r["system"] == system and int(r["exposure"]) == exposure]
        measured = np.array([[float(r["x"]), float(r["y"])] for r in rows])
        points = xyz[[index[int(r["id"])] for r in rows]]
        column = cal.system_names.index(system)
        L = _read_dlt(tmp_path / "x" / f"dlt_exposure{exposure}.csv")[:, column]
        height = cal.systems[system].image_size_px[1]
        dlt_residual = from_dlt_frame(dlt_project(L, points), height) - cal.undistort_points(system, measured)
        model_residual = _ideal(cal, system, exposure, points) - cal.undistort_points(system, measured)
        dlt_rms, model_rms = (float(np.sqrt(np.mean(r**2))) for r in (dlt_residual, model_residual))
        # the target: within 0.1 px RMS of fluorocal's own model through the undistorted coordinates
        assert abs(dlt_rms - model_rms) < 0.1
        assert abs(rms - dlt_rms) < 1e-5  # the file states what the DLT gives (written with 6 decimals)
        assert dlt_rms < 0.2  # the simulated centroids' noise is ~0.05 px: a wrong frame would give pixels


# --- mayacam --------------------------------------------------------------------------------------


def _read_mayacam(path):
    """A MayaCam 2.0 file, line by line as Autoscoper's loader reads it: size, K, R, t."""
    lines = path.read_text().splitlines()
    assert lines[0] == "image size" and lines[3] == "camera matrix" and lines[8] == "rotation"
    assert lines[13] == "translation" and len(lines) == 17
    size = [int(v) for v in lines[1].split(",")]
    K = np.array([[float(v) for v in lines[i].split(",")] for i in (4, 5, 6)])
    R = np.array([[float(v) for v in lines[i].split(",")] for i in (9, 10, 11)])
    t = np.array([float(lines[i]) for i in (14, 15, 16)])
    return size, K, R, t


def test_mayacam_cameras_project_as_fluorocal_on_undistorted_coordinates(run_out, tmp_path):
    assert _export(run_out / "calibration.json", "mayacam", tmp_path / "x") == 0
    cal = Calibration.load(run_out / "calibration.json")
    held_out = _held_out_points(_object_points(run_out)[1])
    assert "fluorocal undistort" in (tmp_path / "x" / "UNDISTORTION.txt").read_text()
    for system in cal.system_names:
        for exposure in cal.exposures:
            size, K, R, t = _read_mayacam(tmp_path / "x" / f"mayacam_{system}_exposure{exposure}.txt")
            assert size == list(cal.systems[system].image_size_px)
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
            xy, _ = cv2.projectPoints(held_out, cv2.Rodrigues(R)[0], t, K, None)
            # exact pinhole: float64 text round trip and the field's inversion tolerance
            np.testing.assert_allclose(xy.reshape(-1, 2), _ideal(cal, system, exposure, held_out), atol=1e-6)


# --- mrcal ----------------------------------------------------------------------------------------


def _read_cameramodel(path) -> tuple[dict, list[str]]:
    """An mrcal .cameramodel: '#' comment lines and a Python-literal dict, read without mrcal."""
    text = path.read_text()
    return ast.literal_eval(text), [line for line in text.splitlines() if line.startswith("#")]


def _mrcal_project(model: dict, p: np.ndarray) -> np.ndarray:
    """LENSMODEL_SPLINED_STEREOGRAPHIC_order=3 projection, point by point as mrcal.c's _project_point_splined."""
    found = re.fullmatch(
        r"LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=(\d+)_Ny=(\d+)_fov_x_deg=(\d+)", model["lensmodel"]
    )
    nx, ny, fov = (int(v) for v in found.groups())
    fx, fy, cx, cy, *control = model["intrinsics"]
    assert len(control) == 2 * nx * ny
    u_edge = np.tan(np.radians(fov / 2) / 2) * 2
    segments_per_u = (nx - 1 - 2) / (u_edge * 2)

    def abcd(t):
        return [(1 - t) ** 3 / 6, (3 * t**3 / 2 - 3 * t**2 + 2) / 3, (-3 * t**3 + 3 * t**2 + 3 * t + 1) / 6, t**3 / 6]

    q = []
    for x, y, z in p:
        scale = 2.0 / (np.sqrt(x * x + y * y + z * z) + z)
        ux, uy = x * scale, y * scale
        ix, iy = ux * segments_per_u + (nx - 1) / 2, uy * segments_per_u + (ny - 1) / 2
        ix0, iy0 = min(max(int(ix), 1), nx - 3), min(max(int(iy), 1), ny - 3)
        wx, wy = abcd(ix - ix0), abcd(iy - iy0)
        delta = [0.0, 0.0]
        for b in range(4):
            for a in range(4):
                k = 2 * ((iy0 - 1 + b) * nx + (ix0 - 1 + a))
                delta[0] += wy[b] * wx[a] * control[k]
                delta[1] += wy[b] * wx[a] * control[k + 1]
        q.append([(ux + delta[0]) * fx + cx, (uy + delta[1]) * fy + cy])
    return np.array(q)


def test_mrcal_splined_model_reads_back_and_its_stated_fit_error_holds(run_out, tmp_path):
    assert _export(run_out / "calibration.json", "mrcal", tmp_path / "x") == 0
    cal = Calibration.load(run_out / "calibration.json")
    for system in cal.system_names:
        model, comments = _read_cameramodel(tmp_path / "x" / f"{system}.cameramodel")
        assert model["lensmodel"].startswith("LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_")
        assert model["imagersize"] == list(cal.systems[system].image_size_px)
        s = cal.systems[system]
        R = cv2.Rodrigues(np.array(model["extrinsics"][:3]))[0]
        np.testing.assert_allclose(R, quat_to_matrix(s.rop_q), atol=1e-12)
        np.testing.assert_allclose(-R.T @ np.array(model["extrinsics"][3:]), s.rop_source_mm, atol=1e-9)
        header = next(c for c in comments if "RMS" in c)
        stated_rms = float(header.split("RMS ")[1].split(" px")[0])
        stated_max = float(header.split("max ")[1].split(" px")[0])
        # re-measured at pixels the fit did not use (random, where the field is supported), through an
        # evaluation of the model written from mrcal's source, not the exporter's code
        measured = np.random.default_rng(2).uniform(0, np.array(s.image_size_px) - 1, (400, 2))
        measured = measured[cal.field(system).support_at(measured)]
        ideal = cal.undistort_points(system, measured)
        xp, yp, c = s.iop_px
        q = _mrcal_project(model, np.column_stack([(ideal - [xp, yp]) / c, np.ones(len(ideal))]))
        error = q - measured
        rms = float(np.sqrt(np.mean(error**2)))
        # the stated error holds off the fitted grid: RMS within half again of it (plus 1 mpx), no pixel
        # beyond the stated maximum by more than half again; and it is small (the field is smooth on
        # 16 px nodes, the spline's knots 8 px apart)
        assert rms < 1.5 * stated_rms + 0.001 and np.linalg.norm(error, axis=1).max() < 1.5 * stated_max + 0.001
        assert stated_rms < 0.02


# --- paper ----------------------------------------------------------------------------------------


def _read_rows(path):
    return [line.split() for line in path.read_text().splitlines() if line and not line.startswith("#")]


def test_paper_files_read_back_through_the_papers_collinearity(run_out, tmp_path):
    assert _export(run_out / "calibration.json", "paper", tmp_path / "x") == 0
    cal = Calibration.load(run_out / "calibration.json")
    folder = tmp_path / "x"
    iop = {r[0]: np.array(r[1:4], dtype=float) for r in _read_rows(folder / "calibration.iop")}
    eop = {(int(r[0]), r[1]): np.array(r[2:8], dtype=float) for r in _read_rows(folder / "calibration.eop")}
    xyz = {int(r[0]): np.array(r[1:4], dtype=float) for r in _read_rows(folder / "calibration.xyz")}
    pho = _read_rows(folder / "calibration.pho")
    assert set(eop) == {(e, s) for e in cal.exposures for s in cal.system_names}
    ids, points = _object_points(run_out)
    assert sorted(xyz) == sorted(ids.tolist())
    for (exposure, system), values in eop.items():
        xp, yp, c = iop[system]
        T, M = values[:3], opk_matrix(values[3:])
        d = (points - T) @ M.T
        paper_xy = np.column_stack([xp - c * d[:, 0] / d[:, 2], yp - c * d[:, 1] / d[:, 2]])
        ideal = _ideal(cal, system, exposure, points)
        # the paper's frame: x = column, y = -row; exact up to float64 text and the field's inversion
        np.testing.assert_allclose(paper_xy, np.column_stack([ideal[:, 0], -ideal[:, 1]]), atol=1e-6)
    # observations: measured (x, -y) and the correction; x - Δx is fluorocal's undistortion of x
    rows = [r for r in pho if r[-1] == "1"]
    assert len(rows) > 500
    for system in cal.system_names:
        mine = np.array([r[3:5] + r[8:10] for r in rows if r[0] == system], dtype=float)
        ideal = cal.undistort_points(system, np.column_stack([mine[:, 0], -mine[:, 1]]))
        np.testing.assert_allclose(mine[:, :2] - mine[:, 2:], np.column_stack([ideal[:, 0], -ideal[:, 1]]), atol=1e-6)


# --- the command ----------------------------------------------------------------------------------


def test_out_must_be_new_or_empty_unless_overwrite(run_out, tmp_path, capsys):
    out = tmp_path / "x"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert _export(run_out / "calibration.json", "mayacam", out) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "is not empty" in err and "--overwrite" in err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert _export(run_out / "calibration.json", "mayacam", out, "--overwrite") == 0
    assert (out / "notes.txt").read_text() == "mine" and (out / "mayacam_A_exposure0.txt").is_file()


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    assert _export(tmp_path / "missing.json", "dlt", tmp_path / "x") == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "missing.json" in err
    (tmp_path / "file").write_text("")
    assert _export(tmp_path / "missing.json", "dlt", tmp_path / "file") == 2
    assert "is a file" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # argparse: an unknown format is a usage error
        _export(tmp_path / "missing.json", "colmap", tmp_path / "x")
    assert exc.value.code == 2


def test_without_the_tables_paper_and_dlt_write_what_the_calibration_holds(run_out, tmp_path, capsys):
    bare = tmp_path / "bare"
    bare.mkdir()
    for f in [run_out / "calibration.json", *run_out.glob("field_*.npz")]:
        shutil.copy(f, bare / f.name)
    assert _export(bare / "calibration.json", "paper", tmp_path / "p") == 0
    assert sorted(p.name for p in (tmp_path / "p").iterdir()) == ["calibration.eop", "calibration.iop"]
    assert "no .xyz or .pho" in capsys.readouterr().out
    assert _export(bare / "calibration.json", "dlt", tmp_path / "d") == 0
    assert "no RMS" in capsys.readouterr().out
    rows = (tmp_path / "d" / "dlt_rms.csv").read_text().splitlines()[1:]
    assert rows and all(r.endswith(",0,nan") for r in rows)


def test_observations_without_exposure_or_inlier_are_refused_in_one_line(run_out, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(run_out, out)
    lines = (out / "observations.csv").read_text().splitlines()
    header = lines[0].split(",")
    keep = [i for i, name in enumerate(header) if name != "inlier"]
    (out / "observations.csv").write_text("\n".join(",".join(r.split(",")[i] for i in keep) for r in lines) + "\n")
    assert _export(out / "calibration.json", "paper", tmp_path / "x") == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "observations.csv: lacks column(s) inlier" in err
