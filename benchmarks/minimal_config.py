"""The README's minimal config, end to end, against the simulator's truth.

A user who writes only the core keys ([phantom] file, [[systems]] name / frames / source_image_distance /
pixel_pitch, [output] dir) must get fluorocal's most accurate calibration. This benchmark simulates a
biplanar cube set (strong distortion with local bumps), writes exactly that config, runs
``fluorocal run`` and measures:

- object points: RMS distance (mm) of the adjusted bead centres from the true ones after a 7-parameter
  similarity (the network's datum is free), in sample;
- the learned field: RMS (px) of the learned ideal coordinates against the true ones modulo a homography
  (what the pinhole and the poses absorb), over the field points the data cover, inside 0.9 of the
  field-of-view radius.

Geometries: ``default`` (the simulator's defaults: systems 75 degrees apart, turntable shifts of 10 mm) and
``wide`` (systems 90 degrees apart, larger turntable shifts and heights, a larger principal-point offset),
each at several seeds.

Usage: ``python benchmarks/minimal_config.py [--frames N] [--seeds a,b] [--geometries default,wide]
[--size PX] [--keep DIR]`` (defaults: 40 exposures per system, seeds 11,12, both geometries, 1024 px).
Targets (issue 11): object points within 0.02 mm, field within 0.05 px modulo a homography.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import os
import sys
import tempfile
import time
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
from fluorocal import Calibration  # noqa: E402
from fluorocal.cli import main as fluorocal_main  # noqa: E402
from fluorocal.cmd_simulate import write_dataset  # noqa: E402
from fluorocal.stages.geometry import similarity_fit  # noqa: E402
from fluorocal.stages.simulate import ImageDistortion, SimulateParams, simulate  # noqa: E402

GEOMETRIES = {
    "default": {},
    "wide": {
        "system_angle_deg": 90.0,
        "turntable_translation_mm": 20.0,
        "turntable_height_mm": 25.0,
        "principal_point_offset_px": 15.0,
    },
}

MINIMAL_CONFIG = """[phantom]
file = "phantom.csv"
{systems}
[output]
dir = "out"
"""

SYSTEM = """
[[systems]]
name = "{name}"
frames = "frames/{name}/*{suffix}"
source_image_distance = {sid}
pixel_pitch = {pitch}
"""


def write_minimal_config(root: Path, truth: dict) -> Path:
    """Overwrite the simulator's config with one holding only the README's core keys."""
    systems = "".join(
        SYSTEM.format(name=s["name"], suffix=".tif", sid=s["source_image_distance_mm"], pitch=s["pixel_pitch_mm"])
        for s in truth["systems"]
    )
    cfg = root / "fluorocal.toml"
    cfg.write_text(MINIMAL_CONFIG.format(systems=systems))
    return cfg


def object_point_error_mm(root: Path, truth: dict) -> float:
    true = dict(zip(truth["phantom"]["ids"], np.asarray(truth["phantom"]["true_xyz_mm"])))
    with open(root / "out" / "object_points.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if int(r["id"]) in true]
    est = np.array([[float(r["x"]), float(r["y"]), float(r["z"])] for r in rows])
    ref = np.array([true[int(r["id"])] for r in rows])
    s, R, t = similarity_fit(est, ref)
    return float(np.sqrt(np.mean(np.sum((s * est @ R.T + t - ref) ** 2, axis=1))))


def field_error_px(root: Path, truth: dict, size_px: int) -> dict[str, float]:
    import cv2

    cal = Calibration.load(root / "out" / "calibration.json")
    centre, radius = np.array(truth["fov"]["centre_xy_px"]), truth["fov"]["radius_px"]
    g = np.linspace(0, size_px - 1, 96)
    pts = np.column_stack([a.ravel() for a in np.meshgrid(g, g)])
    pts = pts[np.linalg.norm(pts - centre, axis=1) < 0.9 * radius]
    out = {}
    for system in truth["systems"]:
        name = system["name"]
        true_ideal = ImageDistortion.from_dict(system["distortion"]).undistort_points(pts)
        covered = cal.systems[name].field.support_at(pts)
        ideal = cal.undistort_points(name, pts)
        H, _ = cv2.findHomography(ideal[covered], true_ideal[covered], 0)
        mapped = cv2.perspectiveTransform(ideal[covered][None], H)[0]
        out[name] = float(np.sqrt(np.mean(np.sum((mapped - true_ideal[covered]) ** 2, axis=1))))
    return out


def one_set(geometry: str, seed: int, frames: int, size_px: int, keep: Path | None) -> dict:
    params = SimulateParams(
        n_frames=frames, n_systems=2, image_size_px=size_px, seed=seed, distortion="strong", **GEOMETRIES[geometry]
    )
    root = Path(tempfile.mkdtemp(prefix=f"minimal-{geometry}-{seed}-")) if keep is None else keep / f"{geometry}-{seed}"
    write_dataset(simulate(params), root, replace=True)
    truth = json.loads((root / "truth.json").read_text())
    cfg = write_minimal_config(root, truth)
    t0, c0 = time.perf_counter(), time.process_time()
    with contextlib.redirect_stdout(io.StringIO()):  # the run's own summary table; this prints its own
        code = fluorocal_main(["--quiet", "run", str(cfg)])
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    if code != 0:
        raise SystemExit(f"fluorocal run {cfg} exited {code}")
    return {
        "geometry": geometry,
        "seed": seed,
        "points_mm": object_point_error_mm(root, truth),
        "field_px": field_error_px(root, truth, size_px),
        "wall_s": wall,
        "cpu_s": cpu,
        "root": root,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=40, help="exposures per system (default: 40)")
    ap.add_argument("--seeds", default="11,12", help="comma-separated simulation seeds (default: 11,12)")
    ap.add_argument("--geometries", default="default,wide", help=f"among {', '.join(GEOMETRIES)} (default: both)")
    ap.add_argument("--size", type=int, default=1024, help="image side in px (default: 1024)")
    ap.add_argument("--keep", type=Path, help="write the data sets under this folder instead of temporary ones")
    args = ap.parse_args(argv)
    print(f"minimal config, biplanar cube, strong distortion, {args.frames} + {args.frames} frames, {args.size} px")
    print("| geometry | seed | object points (mm) | field A mod H (px) | field B mod H (px) | run wall (s) | cpu (s) |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for geometry in args.geometries.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            r = one_set(geometry, seed, args.frames, args.size, args.keep)
            rows.append(r)
            fa, fb = r["field_px"].values()
            print(
                f"| {geometry} | {seed} | {r['points_mm']:.4f} | {fa:.4f} | {fb:.4f} | {r['wall_s']:.1f} | "
                f"{r['cpu_s']:.1f} |",
                flush=True,
            )
    worst_points = max(r["points_mm"] for r in rows)
    worst_field = max(max(r["field_px"].values()) for r in rows)
    print(
        f"worst: object points {worst_points:.4f} mm (target <= 0.02: {'met' if worst_points <= 0.02 else 'NOT met'}), "
        f"field {worst_field:.4f} px (target <= 0.05: {'met' if worst_field <= 0.05 else 'NOT met'})"
    )
    return 0


if __name__ == "__main__":
    import docpage

    sys.exit(docpage.run(__file__, main))
