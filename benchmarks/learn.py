"""Benchmark of the distortion learning (issue 7): the paper's four schemes and ours, out of sample.

Simulator geometry (``stages.simulate``: cube phantom, strong distortion with a
smooth random component), observations = true distorted outline centres +
0.05 px noise (no image rendering: this measures the learning, not the
detection). Exposures alternate between training and held-out (the paper's
uniform split). Per system and method:

- out-of-sample 3D error: the held-out exposures adjusted with the learned
  correction and the calibrated IOP held fixed (object points and poses
  free), RMS 3D distance to the true bead centres after a 7-parameter
  similarity (``stages.geometry.similarity_fit``), mm;
- out-of-sample reprojection RMS of that adjustment (inliers, px);
- field error: ideal coordinates from the learned correction against the true
  ones after the best homography, RMS over the inner 80 % (radius) of the
  field of view, px;
- wall time of the calibration (training), s.

The oracle is the same held-out adjustment handed the true correction and the
true IOP; "no calibration" is scheme ``none`` (IOP estimated, no field).

Usage: ``python benchmarks/learn.py [--frames N] [--systems S] [--size PX]
[--seed N | --seeds a,b,...] [--schemes a,b,...]``
(defaults: 75 training + 75 held-out exposures, 1 system, 1024 px, every scheme).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fluorocal.stages.adjust import FreeParameters, Orientation, adjust_bundle  # noqa: E402
from fluorocal.stages.artifacts import Observations  # noqa: E402
from fluorocal.stages.geometry import similarity_fit  # noqa: E402
from fluorocal.stages.learn import LearnParams, calibrate  # noqa: E402

# the simulated observation sets are the tests' too: one definition, in the tests' helpers
from tests.stages.ba_synthetic import NOISE_PX, simulated_sets, truth_observations  # noqa: E402, F401
from tests.stages.ba_synthetic import rough_start as _initial  # noqa: E402, F401

#: the paper's loop as written (learn from the adjustment's inliers, no gauge, every solve in full)
PLAIN = {"preset": "paper"}

#: the recommended preset (its values read from it) with two options at their former defaults (one smoothness
#: order, no step rule): the base of the ablations below; its kNN cap restated (each run sets max_iterations to
#: --iterations unless given here)
OURS = {"preset": "recommended", "max_iterations": 3, "smoothness_orders": (2,), "step_tolerance": 0.0}

RECOMMENDED = "ours: recommended [learn] block (+ stop when the field stops moving)"

METHODS = {
    # name: (scheme, LearnParams overrides); each run also sets max_iterations (--iterations) unless given here
    "none": ("none", {}),
    # the expert method the paper compares with: global radial + decentring + affinity model in the adjustment
    "polynomial": ("polynomial", {}),
    "knn": ("knn", PLAIN),
    "knn+iop": ("knn+iop", PLAIN),
    "knn+smooth": ("knn+smooth", PLAIN),
    "knn+iop+smooth": ("knn+iop+smooth", PLAIN),
    "ours: anderson + grid refine": (
        "knn+iop+smooth",
        {**PLAIN, "acceleration": "anderson", "refine": "grid", "max_iterations": 3},
    ),
    "ours: anderson + joint grid+points refine": (
        "knn+iop+smooth",
        {**PLAIN, "acceleration": "anderson", "refine": "grid+points", "max_iterations": 3},
    ),
    "ours: same + affine datum": (
        "knn+iop+smooth",
        {**PLAIN, "acceleration": "anderson", "refine": "grid+points", "max_iterations": 3, "affine_datum": True},
    ),
    # local outlier test, field gauge, fast intermediate solves (the recommended preset's)
    "ours: same + local outliers + gauge + fast solves": ("knn+iop+smooth", OURS),
    # the same with the smoothness prior's order chosen by CV with its weight
    "ours: same + prior order by CV": ("knn+iop+smooth", {**OURS, "smoothness_orders": (2, 3, 4)}),
    # LearnParams' defaults, the recommended preset (the iteration cap restated: --iterations sets the others')
    RECOMMENDED: ("knn+iop+smooth", {"preset": "recommended", "max_iterations": 3}),
    # ablations of our loop
    "ours defaults without gauge": ("knn+iop+smooth", {**OURS, "field_gauge": "none"}),
    "ours defaults with full intermediate solves": ("knn+iop+smooth", {**OURS, "fast_intermediate": False}),
    "ours defaults with inlier training": ("knn+iop+smooth", {**OURS, "training": "inliers"}),
}


def held_out(test_obs, test_init, nominal, true_xyz, corrections, iop_px):
    """Adjust the held-out exposures with the corrections and IOP held fixed: (3D RMS mm, reprojection RMS px)."""
    init = Orientation(
        iop_px,
        test_init.exposure,
        test_init.q_cam_from_obj,
        test_init.source_mm,
        test_init.rop_q,
        test_init.rop_source_mm,
        test_init.system_names,
    )
    adj = adjust_bundle(test_obs, nominal, init, corrections, free=FreeParameters(estimate_iop=False))
    truth = true_xyz[np.searchsorted(nominal.ids, adj.bead_id)]
    scale, R, t = similarity_fit(adj.xyz_mm, truth)
    err = np.linalg.norm(scale * adj.xyz_mm @ R.T + t - truth, axis=1)
    return float(np.sqrt(np.mean(err**2))), float(np.sqrt(np.mean(adj.residual_px[adj.inlier] ** 2)))


def field_error_px(correction, support_at, distortion, size: int, fov_radius_px: float) -> tuple[float, float]:
    """RMS px of learned vs true ideal coordinates after the best homography.

    Returns ``(covered, inner)``: over the inner 80 % (radius) of the field of
    view where the learned field is supported by observations (the homography
    fitted there), and over the whole inner 80 % (with that homography).
    """
    g = np.linspace(0, size - 1, 96)
    pts = np.column_stack([a.ravel() for a in np.meshgrid(g, g)])
    c = (size - 1) / 2
    pts = pts[np.hypot(pts[:, 0] - c, pts[:, 1] - c) < 0.8 * fov_radius_px]
    return _modulo_homography(correction, distortion, pts, support_at(pts))


def _modulo_homography(correction, distortion, pts, covered):
    import cv2

    true_ideal = distortion.undistort_points(pts)
    learned = pts - correction(pts)
    H, _ = cv2.findHomography(learned[covered], true_ideal[covered], 0)
    err = np.linalg.norm(cv2.perspectiveTransform(learned[None], H)[0] - true_ideal, axis=1)
    return float(np.sqrt(np.mean(err[covered] ** 2))), float(np.sqrt(np.mean(err**2)))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=75, help="training (and held-out) exposures per system (default 75)")
    ap.add_argument("--systems", type=int, default=1, help="1 or 2 systems, each calibrated on its own (default 1)")
    ap.add_argument("--size", type=int, default=1024, help="image side px (default 1024)")
    ap.add_argument("--seed", type=int, default=0, help="simulation seed (default 0)")
    ap.add_argument(
        "--seeds",
        help="comma-separated seeds, each a new simulated set; "
        "adds a table of the 3D error relative to each set's oracle",
    )
    ap.add_argument("--schemes", default=",".join(METHODS), help="comma-separated methods (default: all)")
    ap.add_argument(
        "--iterations",
        type=int,
        default=20,
        help="iteration cap of the paper's schemes (default 20, as the issue's anchor)",
    )
    ap.add_argument("-v", "--verbose", action="store_true", help="log the alternation")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(name)s: %(message)s")
    logging.getLogger("fluorocal.stages.adjust").setLevel(logging.ERROR)
    names = [m.strip() for m in args.schemes.split(",") if m.strip()]
    seeds = [int(v) for v in args.seeds.split(",")] if args.seeds else [args.seed]
    rows = {seed: run_set(args, seed, names) for seed in seeds}
    print()
    print(
        "| seed | system | method | out-of-sample 3D (mm) | out-of-sample reproj. RMS (px) | field error mod H, "
        "covered (px) | same, inner 80 % (px) | wall (s) | iterations |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for seed, per_set in rows.items():
        for sysname, name, e3, rp, ferr, wall, it, _ in per_set:
            print(
                f"| {seed} | {sysname} | {name} | {e3:.4f} | {rp:.4f} | {ferr[0]:.4f} | {ferr[1]:.4f} | {wall:.1f} | "
                f"{it} |"
            )
    if len(seeds) > 1:
        print("\nout-of-sample 3D error / the same set's oracle, per seed and mean:")
        for name in names:
            ratios = [
                row[2] / oracle[2]
                for per_set in rows.values()
                for oracle, row in _with_oracle(per_set)
                if row[1] == name
            ]
            print(
                f"  {name}: {', '.join(f'{r:.2f}x' for r in ratios)}; mean {np.mean(ratios):.2f}x, worst "
                f"{max(ratios):.2f}x"
            )


def _with_oracle(per_set):
    """``(oracle row, row)`` pairs of one set's table (each system's oracle row precedes its methods)."""
    oracle = None
    for row in per_set:
        if row[1].startswith("oracle"):
            oracle = row
        else:
            yield oracle, row


def run_set(args, seed: int, names) -> list:
    """One simulated set: the oracle and every method, per system.

    Rows ``(system, method, 3D, reproj, field, wall, iterations, stop)``.
    """
    t0 = time.perf_counter()
    (train, test), nominal, true_xyz, acq, p = simulated_sets(args.frames, args.systems, args.size, seed)
    print(
        f"seed {seed}: simulated {len(train[0])} training + {len(test[0])} held-out observations "
        f"({args.frames} + {args.frames} exposures x {args.systems} system(s), {args.size} px, noise {NOISE_PX} px) "
        f"in {time.perf_counter() - t0:.1f} s"
    )
    rows = []
    for s in range(args.systems):
        sel_tr = train[0].system == s
        sel_te = test[0].system == s
        tr = _one_system(train[0], sel_tr)
        te = _one_system(test[0], sel_te)
        init_tr = _system_orientation(train[1], acq, s)
        init_te = _system_orientation(test[1], acq, s)
        system = acq.systems[s]
        true_corr = te.xy_px - system.distortion.undistort_points(te.xy_px)
        e3, rp = held_out(te, init_te, nominal, true_xyz, true_corr, system.iop_px[None])
        rows.append((system.name, "oracle (true distortion + IOP)", e3, rp, (0.0, 0.0), 0.0, 0, ""))
        for name in names:
            scheme, over = METHODS[name]
            t = time.perf_counter()
            res = calibrate(
                tr,
                nominal,
                init_tr,
                image_size=(args.size, args.size),
                scheme=scheme,
                params=LearnParams(**{"max_iterations": args.iterations, **over}),
            )
            wall = time.perf_counter() - t
            field = res.field(0)
            corr = field.correction_at(te.xy_px)
            e3, rp = held_out(te, init_te, nominal, true_xyz, corr, res.adjustment.iop_px)
            ferr = field_error_px(
                field.correction_at, res.fields[0].support_at, system.distortion, args.size, p.fov_radius_px
            )
            at_test = _modulo_homography(field.correction_at, system.distortion, te.xy_px, np.ones(len(te), bool))[0]
            print(f"    field error mod H at the held-out observations: {at_test:.4f} px")
            rows.append((system.name, name, e3, rp, ferr, wall, len(res.history) - 1, res.stop_reason))
            print(
                f"  {system.name} {name}: 3D {e3:.4f} mm, reproj {rp:.4f} px, field {ferr[0]:.4f} / {ferr[1]:.4f} px, "
                f"{wall:.1f} s ({res.adjust_time_s:.1f} s adjusting), {len(res.history) - 1} it",
                flush=True,
            )
    return rows


def _one_system(obs: Observations, sel: np.ndarray) -> Observations:
    return Observations(
        np.zeros(sel.sum()),
        obs.exposure[sel],
        obs.bead_id[sel],
        obs.xy_px[sel],
        obs.sigma_px[sel],
        system_names=(obs.system_names[int(obs.system[sel][0])],),
    )


def _system_orientation(init: Orientation, acq, s: int) -> Orientation:
    """System ``s``'s own start orientation (its poses as the reference system)."""
    q, src = init.poses(s)
    return Orientation(init.iop_px[s : s + 1], init.exposure, q, src, system_names=(init.system_names[s],))


if __name__ == "__main__":
    import docpage

    docpage.run(__file__, main)
