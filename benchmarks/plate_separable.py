"""What of the simulated plate's errors six C-arm orientations can separate from the fields (issue 12).

benchmarks/plate.py's "6 orientations, 1 frame each" scenario on the simulator's truth centroids (no rendering:
the true distorted hole centres plus Gaussian noise, 0.03 px by default, the real frames' centroid floor), solved
by ``solve_plate`` with the default ``[plate]`` (or ``--plate``). Figures against the truth, after the best
homography, mm per component:

- layout: the estimated layout over the holes whose error was estimated (target <= 0.005 mm); field: each
  orientation's field against the true correction modulo a homography, worst, px;
- oracle: the layout from the same centres with the true fields known (each frame's homography fitted to the
  true layout, the corrected centres mapped back onto the plate and averaged): the noise floor;
- smooth parts (``--decompose``): the layout error and the true plate error as seen in frame 0, each fitted by a
  field on 16 / 32 / 64 px nodes (order-3 prior, tau 0.1 px); "error + truth" near 0 means the estimate holds
  none of the truth's part at that scale (it stayed in the fields);
- ``--split S --keep rough|smooth``: the acquisition re-made with only the rough (or only the smooth) part of the
  true plate error, the smooth part being what a field on ``S`` px nodes takes of it in frame 0;
- ``--field-px A``: the simulator's random distortion field (a cubic B-spline on 64 px, 0.6 px RMS at the
  default "strong" level) set to ``A`` px RMS: how much of the loss is the fields' own fine structure.

Run: .venv/bin/python benchmarks/plate_separable.py [--seed 3] [--noise 0.03] [--decompose] [--oracle]
     [--split 64 --keep rough] [--field-px 0.0] [--plate KEY=VALUE ...]   (under a minute of CPU per run)
"""

from __future__ import annotations

import argparse
import ast
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

ORIENTATIONS = ((0, 0), (0, 15), (0, 30), (0, 45), (0, 60), (30, 0))


def rms(values) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def smooth_part(xy_px: np.ndarray, values_px: np.ndarray, spacing_px: float, tau_px: float) -> np.ndarray:
    """What a field on ``spacing_px`` nodes with an order-3 prior of ``tau_px`` takes of ``values_px`` at ``xy_px``."""
    from fluorocal.stages.learn.grid import fit_grid_field
    from fluorocal.stages.learn.nodes import GridSpec

    grid = GridSpec(spacing_px=spacing_px, support_radius_px=2 * spacing_px)
    var = np.full(len(xy_px), 0.03**2)
    field = fit_grid_field(xy_px, values_px, var, image_size=(1024, 1024), tau_px=tau_px, grid=grid, order=3)
    return field.correction_at(xy_px)


def _jacobians(H: np.ndarray, plate_mm: np.ndarray, eps: float = 1e-3) -> np.ndarray:
    """``(N, 2, 2)`` derivative of the homography ``H`` (image px from plate mm) at ``plate_mm``."""
    at = cv2.perspectiveTransform(plate_mm[None], H)[0]
    cols = [(cv2.perspectiveTransform((plate_mm + step)[None], H)[0] - at) / eps for step in ([eps, 0], [0, eps])]
    return np.stack(cols, axis=-1)


def keep_part(problem, true_mm, spacing_px: float, keep: str):
    """The problem and true layout re-made with only the rough (``keep="rough"``) or smooth part of the plate error."""
    from fluorocal.stages.geometry import homography_fit

    error = homography_fit(problem.nominal_mm, true_mm)[1]
    first = problem.frame == 0
    H0 = homography_fit(true_mm[problem.hole[first]], problem.xy_px[first])[0]
    px_per_mm = float(np.sqrt(abs(np.linalg.det(H0[:2, :2]))))
    smooth = np.zeros_like(true_mm)
    h0 = problem.hole[first]
    smooth[h0] = smooth_part(problem.xy_px[first], error[h0] * px_per_mm, spacing_px, 0.1) / px_per_mm
    remove = smooth if keep == "rough" else error - smooth
    xy = problem.xy_px.copy()
    for f in range(problem.n_frames):
        sel = problem.frame == f
        H = homography_fit(true_mm[problem.hole[sel]], xy[sel])[0]
        xy[sel] -= np.einsum("nij,nj->ni", _jacobians(H, true_mm[problem.hole[sel]]), remove[problem.hole[sel]])
    return replace(problem, xy_px=xy), true_mm - remove


def oracle_layout(problem, true_mm, true_fields) -> np.ndarray:
    """Per hole, the mean of its centres corrected by the true fields, mapped back onto the plate ``(K, 2)`` mm."""
    from fluorocal.stages.geometry import homography_fit

    corrected = problem.xy_px.copy()
    for o, field in enumerate(true_fields):
        sel = problem.orientation == o
        corrected[sel] -= field.correction_at(problem.xy_px[sel])
    total, count = np.zeros_like(true_mm), np.zeros(len(true_mm))
    for f in range(problem.n_frames):
        sel = problem.frame == f
        H = homography_fit(true_mm[problem.hole[sel]], corrected[sel])[0]
        np.add.at(total, problem.hole[sel], cv2.perspectiveTransform(corrected[sel][None], np.linalg.inv(H))[0])
        np.add.at(count, problem.hole[sel], 1)
    return total / np.maximum(count, 1)[:, None]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--noise", type=float, default=0.03, help="centroid noise, px per component (default 0.03)")
    ap.add_argument("--decompose", action="store_true", help="the errors' smooth and rough parts")
    ap.add_argument("--oracle", action="store_true", help="the layout with the true fields known")
    ap.add_argument("--split", type=float, default=0.0, help="node spacing (px) splitting smooth from rough")
    ap.add_argument("--keep", choices=("rough", "smooth"), default="rough")
    ap.add_argument("--field-px", type=float, default=None, help="RMS of the simulator's random field, px")
    ap.add_argument("--plate", action="append", default=[], metavar="KEY=VALUE", help="a [plate] setting")
    args = ap.parse_args(argv)

    import fluorocal.stages.simulate.distortion as simulated_distortion
    from fluorocal.stages.geometry import homography_fit
    from fluorocal.stages.plate import PlateParams
    from fluorocal.stages.plate.solve import solve_plate
    from fluorocal.stages.simulate import SimulateParams, simulate
    from fluorocal.stages.simulate.truth import truth_to_dict

    from tests.stages.plate_truth import field_error_px, truth_field, truth_problem

    if args.field_px is not None:
        levels = simulated_distortion._DISTORTION_LEVELS
        levels["strong"] = levels["strong"][:4] + (args.field_px,)
    params = SimulateParams(phantom="grid", n_frames=1, seed=args.seed, orientations_deg=ORIENTATIONS)
    data = simulate(params, render=False)
    problem, true = truth_problem(data, args.noise, np.random.default_rng(args.seed))
    if args.split:
        problem, true = keep_part(problem, true, args.split, args.keep)
    plate = PlateParams(**{k: ast.literal_eval(v) for k, v in (p.split("=", 1) for p in args.plate)})
    t0 = time.process_time()
    sol = solve_plate(problem, plate.settings(params.grid_pitch_mm, True))
    cpu = time.process_time() - t0
    est = sol.plate_estimated
    nominal = problem.nominal_mm[est]
    error = homography_fit(true[est], nominal + sol.plate_error_mm[est])[1]
    true_error = homography_fit(nominal, true[est])[1]
    truth = truth_to_dict(data)
    size = truth["image_size_px"]
    fields = [truth_field(o["correction_grid"], size, size) for o in truth["systems"][0]["orientations"]]
    field_err = [field_error_px(sol.fields[o], f, truth["fov"]) for o, f in enumerate(fields)]
    part = f", only the {args.keep} part ({args.split:g} px)" if args.split else ""
    field_rms = "default" if args.field_px is None else f"{args.field_px:g} px"
    print(
        f"seed {args.seed}, noise {args.noise:g} px, random field {field_rms}{part}, "
        f"[plate] {args.plate or 'default'}: "
        f"layout {rms(error):.4f} mm (true plate error {rms(true_error):.4f}),"
        f" field worst {max(field_err):.4f} px; smoothness {sol.smoothness}; {sol.stop_reason}; {cpu:.0f} s CPU"
    )
    if args.oracle:
        oracle = oracle_layout(problem, true, fields)[est]
        print(f"  true fields known (noise floor): layout {rms(homography_fit(true[est], oracle)[1]):.4f} mm")
    if args.decompose:
        first = problem.frame == 0
        where = dict(zip(problem.hole[first].tolist(), problem.xy_px[first]))
        holes = np.flatnonzero(est)
        seen = np.array([h in where for h in holes])
        xy = np.array([where[h] for h in holes[seen]])
        px_per_mm = float(np.sqrt(abs(np.linalg.det(sol.homography[0][:2, :2]))))
        for spacing in (16, 32, 64):
            se = smooth_part(xy, error[seen] * px_per_mm, spacing, 0.1) / px_per_mm
            st = smooth_part(xy, true_error[seen] * px_per_mm, spacing, 0.1) / px_per_mm
            print(
                f"  on {spacing} px nodes: smooth part of the error {rms(se):.4f}, of the truth {rms(st):.4f}, "
                f"error + truth {rms(se + st):.4f}; rough part of the error {rms(error[seen] - se):.4f} mm"
            )
    return 0


if __name__ == "__main__":
    import docpage

    sys.exit(docpage.run(__file__, main))
