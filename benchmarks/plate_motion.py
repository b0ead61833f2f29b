"""How far the plate must move between C-arm orientations for its layout to be recovered (issue 12).

benchmarks/plate.py's "6 orientations, 1 frame each" scenario, on the simulator's own truth centroids (no
rendering: the true distorted hole centres plus Gaussian noise of 0.03 px, the real frames' centroid
floor), with the plate's play on the intensifier between orientations (``plate_play_mm`` per axis,
``plate_play_deg`` about the beam) raised from the simulator's default (0.6 mm, 0.2 deg: 1-4 px in the image)
up to a free turn. Per row, against the simulator's truth (after the best homography, mm per component):

- plate motion: per hole, the largest distance between its ideal (undistorted) image positions, median;
- layout: the estimated layout, over the holes whose error was estimated (target <= 0.005 mm);
- perfect plate: the same acquisition with a perfect plate, what the method invents;
- smooth part: the layout error and the true plate error, each smoothed by a Gaussian of ``SMOOTH_MM`` (about
  one node spacing of the fields, 16 px): the part of the plate error a smooth field can hold; when the two
  are equal the method recovered none of it (it stayed in the fields);
- rough part: what is left of the layout error after that smoothing (the hole-to-hole part);
- noise-free data residual: on the truth centroids without noise, RMS px per component of what the solve
  leaves of the centres with the estimated layout and with the plate held at its true layout (the fields and
  homographies re-fitted to it): where the first is no larger, the data do not prefer the true layout, and no
  estimator fitting them with these fields can be led to it by the data.

Run: .venv/bin/python benchmarks/plate_motion.py [--seed 3]   (about 3 minutes here)
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

ORIENTATIONS = ((0, 0), (0, 15), (0, 30), (0, 45), (0, 60), (30, 0))
PLAYS = ((0.6, 0.2), (2.4, 0.8), (5.0, 10.0), (5.0, 30.0), (5.0, 180.0))
NOISE_PX = 0.03
SMOOTH_MM = 4.0


def smoothed(xy_mm: np.ndarray, values: np.ndarray, sigma_mm: float) -> np.ndarray:
    """Gaussian-weighted mean of ``values`` ``(K, 2)`` around each point (within 3 sigma)."""
    out = np.empty_like(values)
    for k, near in enumerate(cKDTree(xy_mm).query_ball_point(xy_mm, 3 * sigma_mm)):
        w = np.exp(-0.5 * np.sum((xy_mm[near] - xy_mm[k]) ** 2, axis=1) / sigma_mm**2)
        out[k] = w @ values[near] / w.sum()
    return out


def rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values**2)))


def one(seed: int, play_mm: float, play_deg: float, *, perfect: bool = False, noise_px: float = NOISE_PX):
    """Layout error, its error and the true one after the best homography ``(K_est, 2)``, nominal xy, motion, fits.

    fits: RMS of the data residual (px per component) with the estimated layout and with the true one.
    """
    from fluorocal.stages.geometry import homography_fit
    from fluorocal.stages.plate import PlateParams
    from fluorocal.stages.plate.solve import solve_plate
    from fluorocal.stages.simulate import SimulateParams, simulate

    from tests.stages.plate_truth import truth_problem

    params = SimulateParams(
        phantom="grid",
        n_frames=1,
        seed=seed,
        orientations_deg=ORIENTATIONS,
        plate_play_mm=play_mm,
        plate_play_deg=play_deg,
        **({"plate_error_mm": 0.0} if perfect else {}),
    )
    data = simulate(params, render=False)
    problem, true = truth_problem(data, noise_px, np.random.default_rng(seed))
    sol = solve_plate(problem, PlateParams().settings(params.grid_pitch_mm, True))
    est = sol.plate_estimated
    nominal = problem.nominal_mm[est]
    error = homography_fit(true[est], nominal + sol.plate_error_mm[est])[1]
    true_error = homography_fit(nominal, true[est])[1]
    # the same data explained with the plate fixed at its true layout (less its homography), the fields re-fitted
    held = replace(problem, nominal_mm=problem.nominal_mm + homography_fit(problem.nominal_mm, true)[1])
    at_truth = solve_plate(held, PlateParams().settings(params.grid_pitch_mm, False))
    fit = (rms(sol.residual_px), rms(at_truth.residual_px))
    return rms(error), error, true_error, nominal, _motion_px(data.truth.frames[0]), fit


def _motion_px(frames) -> float:
    """Median over the holes of the largest distance between a hole's ideal (undistorted) image positions, px."""
    ids = np.concatenate([f.ids for f in frames])
    xy = np.vstack([f.outline_ideal_xy_px for f in frames])
    _, hole = np.unique(ids, return_inverse=True)
    lo, hi = np.full((hole.max() + 1, 2), np.inf), np.full((hole.max() + 1, 2), -np.inf)
    np.minimum.at(lo, hole, xy)
    np.maximum.at(hi, hole, xy)
    return float(np.median(np.hypot(*(hi - lo).T)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args(argv)
    print(f"\n## 6 orientations, 1 frame each (seed {args.seed}), truth centroids + {NOISE_PX} px noise, mm\n")
    print(
        "| plate play (mm, deg) | plate motion, median px | layout vs truth | perfect plate | "
        f"smooth part ({SMOOTH_MM:g} mm): error / truth | rough part of the error "
        "| noise-free data residual (px): estimated / true layout |"
    )
    print("|---|---|---|---|---|---|---|")
    for play_mm, play_deg in PLAYS:
        layout, error, true_error, xy, motion, _ = one(args.seed, play_mm, play_deg)
        perfect = one(args.seed, play_mm, play_deg, perfect=True)[0]
        fit = one(args.seed, play_mm, play_deg, noise_px=0.0)[-1]
        smooth_error = smoothed(xy, error, SMOOTH_MM)
        print(
            f"| {play_mm:g}, {play_deg:g} | {motion:.1f} | {layout:.4f} | {perfect:.4f} "
            f"| {rms(smooth_error):.4f} / {rms(smoothed(xy, true_error, SMOOTH_MM)):.4f} "
            f"| {rms(error - smooth_error):.4f} | {fit[0]:.5f} / {fit[1]:.5f} |",
            flush=True,
        )
    print("\ntarget: layout <= 0.005 mm from 6 frames")
    return 0


if __name__ == "__main__":
    import docpage

    sys.exit(docpage.run(__file__, main))
