"""The exports' figures on a calibration: the OpenCV maps through cv2.FileStorage and the DLT against fluorocal.

Usage::

    fluorocal simulate demo && fluorocal run demo/fluorocal.toml
    OPENBLAS_NUM_THREADS=1 python benchmarks/exports.py demo/out/calibration.json

Exports the calibration with ``--format opencv`` and ``--format dlt`` into a temporary folder, then

- reads each OpenCV YAML back with ``cv2.FileStorage``, remaps a synthetic 12-bit frame of the
  calibrated size with ``cv2.remap`` and prints the RMS difference (DN) from
  ``Calibration.undistort_image`` (what ``fluorocal undistort`` uses);
- reads each DLT file back and prints, per system and training exposure, the RMS (px per coordinate)
  of the DLT's reprojection of 1000 held-out points (uniform in the object points' bounding box)
  against fluorocal's own model through the undistorted coordinates, and the reprojection RMS of the
  DLT and of the model against the undistorted inlier observations.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import tempfile
from pathlib import Path

import cv2
import numpy as np
from fluorocal.calibration import Calibration
from fluorocal.cli import main
from fluorocal.exports.dlt import from_dlt_frame
from fluorocal.exports.dlt import project as dlt_project


def _frame(width: int, height: int) -> np.ndarray:
    yy, xx = np.mgrid[0:height, 0:width]
    noise = np.random.default_rng(0).normal(0, 30, (height, width))
    image = 2000 + 1200 * np.sin(xx / 7.0) * np.cos(yy / 11.0) + 500 * np.sin((xx + yy) / 53.0) + noise
    return np.clip(image, 0, 4095).astype(np.uint16)


def _rms(a) -> float:
    return float(np.sqrt(np.mean(np.asarray(a, dtype=float) ** 2)))


def opencv_figures(cal: Calibration, folder: Path) -> None:
    for path in sorted(folder.glob("opencv_*.yml.gz")):
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        system, orientation = fs.getNode("system").string(), fs.getNode("orientation").string() or None
        map_x, map_y = fs.getNode("map_x").mat(), fs.getNode("map_y").mat()
        fs.release()
        frame = _frame(*cal.systems[system].image_size_px)
        remapped = cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        reference = cal.undistort_image(system, frame, orientation=orientation)
        print(
            f"opencv {path.name}: {frame.shape[1]}x{frame.shape[0]} frame, cv2.FileStorage + cv2.remap vs "
            f"undistort_image: RMS {_rms(remapped.astype(float) - reference):.6f} DN"
        )


def dlt_figures(cal: Calibration, folder: Path) -> None:
    out = cal.path.parent
    points = np.loadtxt(out / "object_points.csv", delimiter=",", skiprows=1)
    index = {int(i): k for k, i in enumerate(points[:, 0])}
    xyz = points[:, 1:4]
    held_out = np.random.default_rng(1).uniform(xyz.min(axis=0), xyz.max(axis=0), (1000, 3))
    with open(out / "observations.csv", newline="") as fh:
        obs = [r for r in csv.DictReader(fh) if r["inlier"].strip().lower() in ("true", "1")]
    worst = 0.0
    for exposure in sorted(cal.exposures):
        coefficients = np.loadtxt(folder / f"dlt_exposure{exposure}.csv", delimiter=",", ndmin=2)
        for column, system in enumerate(cal.system_names):
            height = cal.systems[system].image_size_px[1]
            L = coefficients[:, column]
            model = cal.undistort_points(system, cal.project(system, exposure, held_out))
            diff = _rms(from_dlt_frame(dlt_project(L, held_out), height) - model)
            rows = [r for r in obs if r["system"] == system and int(r["exposure"]) == exposure]
            ideal = cal.undistort_points(system, np.array([[float(r["x"]), float(r["y"])] for r in rows]))
            beads = xyz[[index[int(r["id"])] for r in rows]]
            dlt_rms = _rms(from_dlt_frame(dlt_project(L, beads), height) - ideal)
            model_rms = _rms(cal.undistort_points(system, cal.project(system, exposure, beads)) - ideal)
            worst = max(worst, diff, abs(dlt_rms - model_rms))
            print(
                f"dlt exposure {exposure} system {system}: held-out points DLT vs model RMS {diff:.2e} px; "
                f"{len(rows)} inlier beads: DLT {dlt_rms:.4f} px, model {model_rms:.4f} px"
            )
    print(f"dlt: largest difference from fluorocal's model {worst:.2e} px RMS (target 0.1 px)")


def measure(calibration: Path) -> None:
    cal = Calibration.load(calibration)
    with tempfile.TemporaryDirectory() as tmp:
        for fmt in ("opencv", "dlt"):
            with contextlib.redirect_stdout(io.StringIO()):  # the export's own list of files
                code = main(["--quiet", "export", str(calibration), "--format", fmt, "--out", f"{tmp}/{fmt}"])
            if code != 0:
                raise SystemExit(f"fluorocal export --format {fmt} failed")
        opencv_figures(cal, Path(tmp) / "opencv")
        dlt_figures(cal, Path(tmp) / "dlt")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("calibration", type=Path, help="calibration.json of `fluorocal run` (tables beside it)")
    import docpage

    docpage.run(__file__, lambda: measure(parser.parse_args().calibration))
