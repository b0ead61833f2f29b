"""The exports' figures on a calibration: the OpenCV maps through cv2.FileStorage and the DLT against fluorocal.

Usage::

    fluorocal simulate demo && fluorocal run demo/fluorocal.toml
    OPENBLAS_NUM_THREADS=1 python benchmarks/exports.py demo/out/calibration.json

Without a calibration (as ``make bench`` runs it), the demo's set (``make demo``: 8 + 8 frames of 512 px,
seed 7) is simulated and run in a temporary folder first.

Exports the calibration with ``--format opencv`` and ``--format dlt`` into a temporary folder, then

- times the OpenCV export twice, in this process (CPU and wall seconds, the whole export and per
  file): first from a copy of the calibration with no maps cached beside it (the maps are computed,
  as on a first export), then again (the maps read from that cache);
- prints each OpenCV file's size (bytes, as ``du -b``), reads it back with ``cv2.FileStorage``,
  remaps a synthetic 12-bit frame of the calibrated size with ``cv2.remap`` and prints the largest
  difference (DN) from ``Calibration.undistort_image`` (what ``fluorocal undistort`` uses);
- reads each DLT file back and prints, per system and training exposure, the RMS (px per coordinate)
  of the DLT's reprojection of 1000 held-out points (uniform in the object points' bounding box)
  against fluorocal's own model through the undistorted coordinates, and the reprojection RMS of the
  DLT and of the model against the undistorted inlier observations (a grid plate's calibration has
  no DLT: skipped).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from fluorocal.calibration import Calibration
from fluorocal.cli import main
from fluorocal.exports.common import has_geometry
from fluorocal.exports.dlt import from_dlt_frame
from fluorocal.exports.dlt import project as dlt_project
from fluorocal.exports.opencv import read_maps


def _frame(width: int, height: int) -> np.ndarray:
    yy, xx = np.mgrid[0:height, 0:width]
    noise = np.random.default_rng(0).normal(0, 30, (height, width))
    image = 2000 + 1200 * np.sin(xx / 7.0) * np.cos(yy / 11.0) + 500 * np.sin((xx + yy) / 53.0) + noise
    return np.clip(image, 0, 4095).astype(np.uint16)


def _rms(a) -> float:
    return float(np.sqrt(np.mean(np.asarray(a, dtype=float) ** 2)))


def _export(calibration: Path, fmt: str, out: Path) -> tuple[float, float]:
    """Export ``calibration`` as ``fmt`` into ``out``; the CPU and wall seconds it took in this process."""
    cpu, wall = time.process_time(), time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):  # the export's own list of files
        code = main(["--quiet", "export", str(calibration), "--format", fmt, "--out", str(out)])
    if code != 0:
        raise SystemExit(f"fluorocal export --format {fmt} failed")
    return time.process_time() - cpu, time.perf_counter() - wall


def opencv_timed(calibration: Path, tmp: Path) -> Path:
    """The OpenCV export timed without and with the maps cached, from a copy of the calibration's folder."""
    copy = tmp / "calibration"
    shutil.copytree(calibration.parent, copy, ignore=shutil.ignore_patterns("*.maps", "*.png", "report.md"))
    print(f"opencv export, OpenCV {cv2.__version__}:")
    for run, what in (("first", "maps computed"), ("second", "maps cached")):
        cpu, wall = _export(copy / calibration.name, "opencv", tmp / run)
        n = len(list((tmp / run).glob("opencv_*.yml.gz")))
        print(
            f"  {run} export ({what}): {n} files in {cpu:.2f} s CPU, {wall:.2f} s wall; "
            f"per file {cpu / n:.2f} s CPU, {wall / n:.2f} s wall"
        )
    return tmp / "second"


def _float_maps_bytes(map_x, map_y, folder: Path) -> int:
    """The size of the maps written as float32 FileStorage matrices (base64, gzip), for comparison."""
    path = folder.parent / "float32.yml.gz"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML | cv2.FILE_STORAGE_BASE64)
    fs.write("map_x", map_x)
    fs.write("map_y", map_y)
    fs.release()
    return path.stat().st_size


def opencv_figures(cal: Calibration, folder: Path) -> None:
    for path in sorted(folder.glob("opencv_*.yml.gz")):
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        system, orientation = fs.getNode("system").string(), fs.getNode("orientation").string() or None
        fs.release()
        map_x, map_y = read_maps(path)
        frame = _frame(*cal.systems[system].image_size_px)
        remapped = cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        reference = cal.undistort_image(system, frame, orientation=orientation)
        print(
            f"opencv {path.name}: {path.stat().st_size} bytes ({_float_maps_bytes(map_x, map_y, folder)} as float32 "
            f"matrices); {frame.shape[1]}x{frame.shape[0]} frame, "
            f"cv2.FileStorage + cv2.remap vs undistort_image: largest difference "
            f"{np.abs(remapped.astype(float) - reference).max():g} DN"
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


def demo_calibration(root: Path) -> Path:
    """The calibration of ``make demo``'s set, simulated and run in ``root``."""
    simulate = ["simulate", str(root), "--frames", "8", "--systems", "2", "--seed", "7", "--image-size", "512", "512"]
    for argv in (simulate, ["--quiet", "run", str(root / "fluorocal.toml")]):
        with contextlib.redirect_stdout(io.StringIO()):
            if main(argv) != 0:
                raise SystemExit(f"fluorocal {' '.join(argv)} failed")
    return root / "out" / "calibration.json"


def measure(calibration: Path | None) -> None:
    if calibration is None:
        with tempfile.TemporaryDirectory() as tmp:
            return measure(demo_calibration(Path(tmp)))
    cal = Calibration.load(calibration)
    with tempfile.TemporaryDirectory() as tmp:
        opencv_figures(cal, opencv_timed(calibration.resolve(), Path(tmp)))
        if not has_geometry(cal):
            print("dlt: none (a grid plate's calibration has no interior orientation or poses)")
            return
        _export(calibration, "dlt", Path(tmp) / "dlt")
        dlt_figures(cal, Path(tmp) / "dlt")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "calibration",
        type=Path,
        nargs="?",
        help="calibration.json of `fluorocal run` (tables beside it; default: the demo's set, simulated and run)",
    )
    import docpage

    docpage.run(__file__, lambda: measure(parser.parse_args().calibration))
