"""Grid-plate calibration benchmark: issue 12's targets measured in one run.

1. Real ARCADIS grid frames (../shared/data/arcadis/grid_*.dcm, six C-arm orientations, one frame each):
   every frame's holes scored on alternate lattice rows left out of the fit (each frame twice: even rows
   out, odd rows out; every other frame complete), corrected by the frame's orientation's field and compared
   by a best-fitting homography with (a) the plate's self-calibrated layout and (b) the nominal lattice.
   Side by side on the same split: fluorocal with the plate taken as nominal (its errors not estimated),
   and a per-frame 2-D polynomial of order 9 from the plate to the image (discorpy's kind of model),
   scored against the nominal lattice and against fluorocal's self-calibrated layout.
   Figures: RMS of the held-out residual, px, per component (the residual's length / sqrt 2); target
   <= 0.06 px against the self-calibrated layout.
2. Simulated plates with manufacturing errors of 0.02 mm (2-D RMS) against the simulator's truth:
   (a) the plate moved by hand between 6 frames at one C-arm orientation, (b) 6 C-arm orientations, one
   frame each (the plate moves a few px between them). Figures: the estimated layout against the true one
   after the best homography, mm per component (target <= 0.005 mm from 6 frames; over the holes whose
   error was estimated and over all), and each orientation's field against the true correction modulo
   a homography over the field of view, px per component (target <= 0.05 px).

Run: .venv/bin/python benchmarks/plate.py [--skip-sim] [--skip-real] [--plate KEY=VALUE ...]
     [--seed-moved 5] [--seed-orientations 3]   (about 5 minutes here)
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

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ARCADIS = ROOT.parent / "shared" / "data" / "arcadis"


def real_frames() -> None:
    from fluorocal.graph import plate_orientations
    from fluorocal.stages.label.lattice import lattice_index
    from fluorocal.stages.plate.holdout import holdout_score
    from fluorocal.stages.plate.problem import frame_orientations, plate_problem
    from graph_run import labelled_observations, run_until

    from tests.pipeline.test_plate_run import REAL_ORIENTATIONS, real_grid_config

    with tempfile.TemporaryDirectory() as tmp:
        runner = run_until(real_grid_config(Path(tmp), ARCADIS, list(REAL_ORIENTATIONS)), "label")
        config = runner.config
        obs = labelled_observations(runner)
        groups = frame_orientations(obs, plate_orientations(config, runner.units))
    problem, index = plate_problem(obs, config.phantom, 0, groups, (1024, 1024))
    row = lattice_index(index["hole_ids"])[:, 1]
    pitch = config.phantom.pitch_mm
    t0 = time.process_time()
    ours = holdout_score(problem, PLATE.settings(pitch, True), row)
    cpu = time.process_time() - t0
    nominal = holdout_score(problem, PLATE.settings(pitch, False), row)
    layout = _full_layout(problem, pitch)
    poly_nom, poly_lay = _polynomial_peer(problem, row, 9, layout)
    names = [groups.names[o] for o in index["orientations"]]
    print("\n## Real ARCADIS grid frames: held-out alternate lattice rows, px per component (RMS)\n")
    print(
        "| frame | fluorocal vs self-calibrated layout | fluorocal vs nominal lattice "
        "| fluorocal, plate taken as nominal | polynomial 9 vs nominal | polynomial 9 vs self-calibrated layout |"
    )
    print("|---|---|---|---|---|---|")
    per, per_nom = ours.per_frame(), nominal.per_frame()
    for f, name in enumerate(names):
        a, b = per[f]
        print(
            f"| {name} | {a / np.sqrt(2):.4f} | {b / np.sqrt(2):.4f} | {per_nom[f][0] / np.sqrt(2):.4f} "
            f"| {poly_nom[f]:.4f} | {poly_lay[f]:.4f} |"
        )
    rms = ours.rms(ours.residual_px) / np.sqrt(2)
    print(
        f"| all | {rms:.4f} | {ours.rms(ours.nominal_residual_px) / np.sqrt(2):.4f} "
        f"| {nominal.rms(nominal.residual_px) / np.sqrt(2):.4f} | {np.sqrt(np.mean(np.square(poly_nom))):.4f} "
        f"| {np.sqrt(np.mean(np.square(poly_lay))):.4f} |"
    )
    print(
        f"\nheld-out RMS {rms:.4f} px per component ({rms * np.sqrt(2):.4f} px as a length): target <= 0.06 px: "
        f"{'met' if rms * np.sqrt(2) <= 0.06 else 'NOT met'}; {2 * problem.n_frames} solves in {cpu:.1f} s CPU"
    )


def _full_layout(problem, pitch_mm: float) -> np.ndarray:
    from fluorocal.stages.plate.solve import solve_plate

    sol = solve_plate(problem, PLATE.settings(pitch_mm, True))
    return problem.nominal_mm + sol.plate_error_mm


def _polynomial_peer(problem, row, order: int, layout) -> tuple[list, list]:
    """Per frame: RMS (px per component) of a 2-D polynomial plate -> image fitted on the other rows."""
    out_nom, out_lay = [], []
    for f in range(problem.n_frames):
        res = {"nom": [], "lay": []}
        for parity in (0, 1):
            sel = problem.frame == f
            test = sel & (row[problem.hole] % 2 == parity)
            train = sel & ~test
            for key, plate in (("nom", problem.nominal_mm), ("lay", layout)):
                coef, basis = _poly_fit(plate[problem.hole[train]], problem.xy_px[train], order)
                res[key].append(problem.xy_px[test] - basis(plate[problem.hole[test]]) @ coef)
        out_nom.append(float(np.sqrt(np.mean(np.vstack(res["nom"]) ** 2))))
        out_lay.append(float(np.sqrt(np.mean(np.vstack(res["lay"]) ** 2))))
    return out_nom, out_lay


def _poly_fit(plate, image, order):
    centre, scale = plate.mean(0), float(np.abs(plate - plate.mean(0)).max())

    def basis(p):
        u, v = ((p - centre) / scale).T
        return np.column_stack([u ** (d - k) * v**k for d in range(order + 1) for k in range(d + 1)])

    return np.linalg.lstsq(basis(plate), image, rcond=None)[0], basis


def simulated(label: str, sim_args: dict) -> None:
    from fluorocal import Calibration
    from fluorocal.cli import main
    from fluorocal.cmd_simulate import write_dataset
    from fluorocal.stages.label.lattice import lattice_index, lattice_xyz_mm
    from fluorocal.stages.simulate import SimulateParams, simulate

    from tests.stages.plate_truth import field_error_px, layout_error_mm, true_layout, truth_field

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "project"
        write_dataset(simulate(SimulateParams(phantom="grid", **sim_args)), root)
        if PLATE_TOML:  # the --plate settings, as the project's [plate] section
            with open(root / "fluorocal.toml", "a") as fh:
                fh.write("\n[plate]\n" + PLATE_TOML)
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):  # the run's own summary table is not the benchmark's
            assert main(["--quiet", "run", str(root / "fluorocal.toml")]) == 0
        wall = time.perf_counter() - t0
        truth = json.loads((root / "truth.json").read_text())
        out = root / "out"
        with open(out / "observations.csv") as fh:
            rows = list(csv.DictReader(fh))
        first_file = min(r["file"] for r in rows)
        first = [r for r in rows if r["file"] == first_file]
        xy = np.array([[float(r["x"]), float(r["y"])] for r in first])
        match = true_layout(truth, xy, np.array([int(r["id"]) for r in first]))
        pts = np.genfromtxt(out / "object_points.csv", delimiter=",", names=True)
        est = {int(i): (x, y, s) for i, x, y, s in zip(pts["id"], pts["x"], pts["y"], pts["sx"])}
        ids = [k for k in match if k in est]
        E = np.array([est[k][:2] for k in ids])
        T = np.array([match[k] for k in ids])
        estimated = np.array([est[k][2] > 0 for k in ids])
        N = lattice_xyz_mm(lattice_index(np.array(ids)), "hex", truth["params"]["grid_pitch_mm"])[:, :2]
        cal = Calibration.load(out / "calibration.json")
        size = truth["image_size_px"]
        orientations = truth["systems"][0].get("orientations") or [
            {"name": "centred", "correction_grid": truth["systems"][0]["correction_grid"]}
        ]
        field_err = [
            field_error_px(cal.field("A", o["name"]), truth_field(o["correction_grid"], size, size), truth["fov"])
            for o in orientations
        ]
    layout_est = layout_error_mm(E[estimated], T[estimated])
    print(
        f"| {label} | {len(ids)} ({int(estimated.sum())} estimated) | {layout_est:.4f} "
        f"| {layout_error_mm(E, T):.4f} | {layout_error_mm(N, T):.4f} | {max(field_err):.4f} "
        f"| {np.mean(field_err):.4f} | {wall:.1f} |"
    )


PLATE = None  # the [plate] settings of this run (--plate)
PLATE_TOML = ""  # the same, as TOML lines


def _plate_params(pairs):
    """``PlateParams`` from ``KEY=VALUE`` strings (values as Python literals)."""
    import ast

    from fluorocal.stages.plate import PlateParams

    return PlateParams(**{k: ast.literal_eval(v) for k, v in (p.split("=", 1) for p in pairs)})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--skip-real", action="store_true", help="skip the real frames")
    ap.add_argument("--skip-sim", action="store_true", help="skip the simulated plates")
    ap.add_argument(
        "--plate", action="append", default=[], metavar="KEY=VALUE", help="a [plate] setting (default: none)"
    )
    ap.add_argument("--seed-moved", type=int, default=5, help="simulation seed of the hand-moved plate (default 5)")
    ap.add_argument(
        "--seed-orientations", type=int, default=3, help="simulation seed of the six orientations (default 3)"
    )
    args = ap.parse_args(argv)
    global PLATE, PLATE_TOML
    PLATE = _plate_params(args.plate)
    PLATE_TOML = "".join(f"{pair.split('=', 1)[0]} = {pair.split('=', 1)[1]}\n" for pair in args.plate)
    if not args.skip_real:
        if ARCADIS.is_dir():
            real_frames()
        else:
            print(f"real frames not present at {ARCADIS}: skipped")
    if not args.skip_sim:
        print("\n## Simulated plates (plate errors 0.02 mm), against the truth\n")
        print(
            "| set | holes matched | layout vs truth, estimated holes (mm) | layout vs truth, all (mm) "
            "| nominal vs truth (mm) | field vs truth, worst orientation (px) | mean (px) | run wall (s) |"
        )
        print("|---|---|---|---|---|---|---|---|")
        seed = args.seed_moved
        simulated(f"plate moved by hand, 6 frames, one orientation (seed {seed})", {"n_frames": 6, "seed": seed})
        orientations = ((0, 0), (0, 15), (0, 30), (0, 45), (0, 60), (30, 0))
        seed = args.seed_orientations
        simulated(
            f"6 orientations, 1 frame each (seed {seed})",
            {"n_frames": 1, "seed": seed, "orientations_deg": orientations},
        )
        print("\ntargets: layout <= 0.005 mm from 6 frames; field <= 0.05 px modulo a homography")
    return 0


if __name__ == "__main__":
    import docpage

    sys.exit(docpage.run(__file__, main))
