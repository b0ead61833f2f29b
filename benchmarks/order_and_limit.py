"""One answer whatever the order, and how close to the limit (issue 30): the learning against an oracle.

Simulator sets (``stages.simulate``: cube phantom, biplanar, strong distortion with local bumps), observations
= true distorted outline centres + Gaussian noise at the level of fluorocal's own centroids (``--noise``,
default 0.02 px: ``benchmarks/centroid_accuracy.py`` measures 0.019-0.030 px on rendered 1024 px frames).
Even exposures train (``--frames`` per system), odd ones are held out. Two geometries (the biplanar set's two
systems, 75 degrees apart, each calibrated on its own) x ``--seeds``. Per system:

- **order**: the same training observations calibrated again with the exposure blocks permuted and the beads
  permuted within each exposure: the largest difference of the field (px), the IOP (px) and the object
  points (mm) (target: 1e-6 each);
- **out-of-sample 3D**: the held-out exposures adjusted with the learned correction and the calibrated IOP held
  (points and poses free), RMS 3D distance to the true beads after a similarity, mm; beside it the **oracle**:
  the same held-out observations adjusted with the true distortion removed and the IOP free; the ratio
  (target <= 1.3x);
- **field error** modulo a homography over the inner 80 % of the field of view where supported, px
  (target <= 0.008 px), and where it comes from: per band of radius, the field's error against its own σ
  (the joint uncertainty's node σ interpolated);
- the learn stage's iterations, the one it kept and its CPU time.

And the **biplanar two-ray intersection**: both systems' held-out exposures adjusted together (the relative
orientation estimated) with each system's learned correction and IOP held, against the oracle with the true
distortions removed and the IOPs free (target <= 1.1x).

The same table follows for the demo's set (``make demo``'s 8 frames of 512 px per system, seed 7: 4 exposures
train, 4 are held out) unless ``--no-demo``.

Usage: ``python benchmarks/order_and_limit.py [--frames N] [--seeds a,b] [--noise PX] [--size PX] [--no-demo]
[--write-docs]`` (defaults: 20 training + 20 held-out exposures per system, seeds 0,1, 0.02 px, 1024 px).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import learn as bench  # noqa: E402  (benchmarks/learn.py: the simulated sets and the held-out adjustment)
from fluorocal.stages.adjust import FreeParameters, Orientation, adjust_bundle  # noqa: E402
from fluorocal.stages.field import bilinear  # noqa: E402
from fluorocal.stages.geometry import similarity_fit  # noqa: E402
from fluorocal.stages.learn import calibrate  # noqa: E402
from fluorocal.stages.learn.order import taken  # noqa: E402

#: bands of radius (fractions of the field of view's radius) of the error-against-σ table
BANDS = (0.0, 0.2, 0.4, 0.6, 0.8)


def error_3d_mm(test_obs, init: Orientation, nominal, true_xyz, corrections, iop_px, estimate_iop: bool) -> float:
    """The held-out exposures adjusted with ``corrections`` (IOP held at ``iop_px`` or free): RMS 3D error mm."""
    start = Orientation(
        iop_px, init.exposure, init.q_cam_from_obj, init.source_mm, init.rop_q, init.rop_source_mm, init.system_names
    )
    adj = adjust_bundle(test_obs, nominal, start, corrections, free=FreeParameters(estimate_iop=estimate_iop))
    truth = true_xyz[np.searchsorted(nominal.ids, adj.bead_id)]
    scale, R, t = similarity_fit(adj.xyz_mm, truth)
    return float(np.sqrt(np.mean(np.sum((scale * adj.xyz_mm @ R.T + t - truth) ** 2, axis=1))))


def reordered(obs, rng) -> np.ndarray:
    """Exposure blocks permuted, beads permuted within each exposure."""
    blocks = [np.flatnonzero(obs.exposure == e) for e in rng.permutation(np.unique(obs.exposure))]
    return np.concatenate([rng.permutation(b) for b in blocks])


def error_by_radius(res, distortion, size: int, fov_radius_px: float) -> list:
    """Per band of radius: (band, RMS field error mod H px, median node σ px) where the field is supported."""
    import cv2

    field = res.fields[0]
    g = np.linspace(0, size - 1, 96)
    pts = np.column_stack([a.ravel() for a in np.meshgrid(g, g)])
    c = (size - 1) / 2
    radius = np.hypot(pts[:, 0] - c, pts[:, 1] - c) / fov_radius_px
    pts, radius = pts[radius < BANDS[-1]], radius[radius < BANDS[-1]]
    covered = field.support_at(pts)
    true_ideal = distortion.undistort_points(pts)
    learned = pts - field.correction_at(pts)
    H, _ = cv2.findHomography(learned[covered], true_ideal[covered], 0)
    err = np.linalg.norm(cv2.perspectiveTransform(learned[None], H)[0] - true_ideal, axis=1)
    node = res.uncertainty[0].node_std_px if res.uncertainty else np.repeat(field.sigma_px[..., None], 2, axis=-1)
    sigma = np.linalg.norm(bilinear(field.x_nodes_px, field.y_nodes_px, node, pts), axis=1)
    rows = []
    for lo, hi in zip(BANDS[:-1], BANDS[1:]):
        sel = covered & (radius >= lo) & (radius < hi)
        if sel.any():
            rows.append((f"{lo:.1f}-{hi:.1f}", float(np.sqrt(np.mean(err[sel] ** 2))), float(np.median(sigma[sel]))))
    return rows


def one_system(train, test, s: int, acq, nominal, true_xyz, args, p, seed: int) -> dict:
    tr = bench._one_system(train[0], train[0].system == s)
    te = bench._one_system(test[0], test[0].system == s)
    init_tr, init_te = bench._system_orientation(train[1], acq, s), bench._system_orientation(test[1], acq, s)
    system = acq.systems[s]
    c0 = time.process_time()
    res = calibrate(tr, nominal, init_tr, image_size=(args.size, args.size))
    cpu = time.process_time() - c0
    order = reordered(tr, np.random.default_rng([seed, s]))
    other = calibrate(taken(tr, order), nominal, init_tr, image_size=(args.size, args.size))
    diffs = (
        float(np.max(np.abs(other.fields[0].delta_px - res.fields[0].delta_px))),
        float(np.max(np.abs(other.adjustment.iop_px - res.adjustment.iop_px))),
        float(np.max(np.abs(other.adjustment.xyz_mm - res.adjustment.xyz_mm))),
    )
    field = res.field(0)
    ours = error_3d_mm(te, init_te, nominal, true_xyz, field.correction_at(te.xy_px), res.adjustment.iop_px, False)
    true_corr = te.xy_px - system.distortion.undistort_points(te.xy_px)
    oracle = error_3d_mm(te, init_te, nominal, true_xyz, true_corr, init_te.iop_px, True)
    ferr = bench.field_error_px(
        field.correction_at, res.fields[0].support_at, system.distortion, args.size, p.fov_radius_px
    )
    bands = error_by_radius(res, system.distortion, args.size, p.fov_radius_px)
    kept = res.stop_reason.split("kept iteration ")[-1].split(",")[0]
    return dict(
        name=system.name,
        res=res,
        cpu=cpu,
        diffs=diffs,
        ours=ours,
        oracle=oracle,
        ferr=ferr,
        bands=bands,
        iterations=len(res.history) - 1,
        kept=kept,
    )


def two_ray(test, results, acq, nominal, true_xyz) -> tuple[float, float]:
    """Biplanar held-out 3D error mm with the learned corrections and IOP held, and the oracle's (IOP free)."""
    obs, init = test
    learned, truth = np.zeros((len(obs), 2)), np.zeros((len(obs), 2))
    for s, r in enumerate(results):
        rows = obs.system == s
        learned[rows] = r["res"].field(0).correction_at(obs.xy_px[rows])
        truth[rows] = obs.xy_px[rows] - acq.systems[s].distortion.undistort_points(obs.xy_px[rows])
    iop = np.vstack([r["res"].adjustment.iop_px for r in results])
    ours = error_3d_mm(obs, init, nominal, true_xyz, learned, iop, False)
    return ours, error_3d_mm(obs, init, nominal, true_xyz, truth, init.iop_px, True)


#: the demo's set (``make demo``: 8 frames of 512 px per system, seed 7): 4 exposures train, 4 are held out
DEMO = {"frames": 4, "size": 512, "seeds": (7,)}


def run_sets(frames: int, size: int, seeds, args) -> None:
    """Every seed's two systems and their two-ray intersection: the table of one set."""
    args = argparse.Namespace(**{**vars(args), "frames": frames, "size": size})
    table, biplanar = [], []
    for seed in seeds:
        (train, test), nominal, true_xyz, acq, p = bench.simulated_sets(frames, 2, size, seed)
        results = [one_system(train, test, s, acq, nominal, true_xyz, args, p, seed) for s in range(2)]
        for r in results:
            table.append((seed, r))
            bands = "; ".join(f"{b}: error {e:.4f} px vs sigma {s:.4f} px" for b, e, s in r["bands"])
            print(f"seed {seed} system {r['name']}: field error by radius (of the FOV's): {bands}", flush=True)
        biplanar.append((seed, *two_ray(test, results, acq, nominal, true_xyz)))
    print(f"\n{frames} + {frames} exposures per system, {size} px, noise {args.noise} px")
    print(
        "| seed | system | order: field / IOP px, points mm (max diff) | 3D ours mm | 3D oracle mm | ratio "
        "| field err mod H px (covered / inner 80 %) | iterations (kept) | learn CPU s |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for seed, r in table:
        d = r["diffs"]
        print(
            f"| {seed} | {r['name']} | {d[0]:.1e} / {d[1]:.1e}, {d[2]:.1e} | {r['ours']:.5f} | {r['oracle']:.5f} | "
            f"{r['ours'] / r['oracle']:.2f}x | {r['ferr'][0]:.4f} / {r['ferr'][1]:.4f} | {r['iterations']} "
            f"({r['kept']}) | {r['cpu']:.1f} |"
        )
    print("\nbiplanar two-ray intersection (held-out, both systems adjusted together):")
    for seed, ours, oracle in biplanar:
        print(f"  seed {seed}: ours {ours:.5f} mm, oracle {oracle:.5f} mm, ratio {ours / oracle:.2f}x (target 1.1x)")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=20, help="training (and held-out) exposures per system (20)")
    ap.add_argument("--seeds", default="0,1", help="comma-separated simulation seeds (default 0,1)")
    ap.add_argument("--noise", type=float, default=0.02, help="centre noise px (default 0.02)")
    ap.add_argument("--size", type=int, default=1024, help="image side px (default 1024)")
    ap.add_argument("--no-demo", action="store_true", help="leave out the demo's set (4 + 4 exposures of 512 px)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    logging.getLogger("fluorocal.stages.adjust").setLevel(logging.ERROR)
    warnings.simplefilter("ignore")
    bench.NOISE_PX = args.noise
    run_sets(args.frames, args.size, [int(v) for v in args.seeds.split(",")], args)
    if not args.no_demo:
        print("\nthe demo's set:")
        run_sets(DEMO["frames"], DEMO["size"], DEMO["seeds"], args)


if __name__ == "__main__":
    import docpage

    sys.exit(docpage.run(__file__, main))
