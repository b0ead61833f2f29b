"""Benchmark of ``fluorocal evaluate``'s protocol on the simulated biplanar set (issue 14).

The simulator's biplanar set (two systems, strong distortion, 75 + 75 epochs
of 1024 px, seed 0), observations = true distorted outline centres + 0.05 px
noise (``benchmarks/learn.py``'s ``truth_observations``: no rendering, so this
times the protocol, not the detection and labelling), the check points of the
simulator's ``reference.csv`` (true centres + survey noise). The protocol is the
one ``fluorocal evaluate`` runs after the labelling
(``fluorocal.stages.evaluate.evaluate``, with the project's defaults:
``LearnParams()`` and ``[adjust]``'s): odd epochs held out, 5 training sizes,
schemes none, polynomial, knn+iop+smooth (fluorocal's default) and opencv.

Printed: the Markdown table ``fluorocal evaluate`` writes, the total wall time, and
fluorocal's out-of-sample 3D error (two-ray mean) against every peer's at every size.

Usage: ``OPENBLAS_NUM_THREADS=1 python benchmarks/evaluate.py [--frames N] [--size PX] [--seed S]
[--sizes a,b,...] [--schemes a,b,...]``
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fluorocal.compute import limit_threads  # noqa: E402
from fluorocal.evaluation import markdown  # noqa: E402
from fluorocal.kinds.beads import BeadPart  # noqa: E402
from fluorocal.stages import simulate as sim  # noqa: E402
from fluorocal.stages.evaluate import EvaluationSetup, default_train_sizes, evaluate, heldout_epochs  # noqa: E402
from fluorocal.stages.geometry import iop_guess  # noqa: E402

from benchmarks.learn import truth_observations  # noqa: E402

OURS = "knn+iop+smooth"
PEERS = ("none", "polynomial", "opencv")
TARGET_RATIO = 2.0


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=150, help="epochs in all, half held out (default 150)")
    ap.add_argument("--size", type=int, default=1024, help="image side px (default 1024)")
    ap.add_argument("--seed", type=int, default=0, help="simulation seed (default 0)")
    ap.add_argument("--sizes", help="training sizes (default: 5 evenly spaced up to all training epochs)")
    ap.add_argument("--schemes", default=",".join((*PEERS[:2], OURS, PEERS[2])), help="comma-separated schemes")
    args = ap.parse_args(argv)
    limit_threads()  # one thread per library, as `fluorocal evaluate` runs
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    logging.getLogger("fluorocal.stages.adjust").setLevel(logging.ERROR)
    t0, cpu0 = time.perf_counter(), time.process_time()
    p = sim.SimulateParams(
        n_frames=args.frames, n_systems=2, seed=args.seed, image_size_px=args.size, distortion="strong"
    )
    data = sim.simulate(p, render=False)
    obs = truth_observations(data, np.random.default_rng([args.seed, 7]))
    heldout = heldout_epochs(np.unique(obs.exposure), "odd")
    n_train = args.frames - len(heldout)
    sizes = tuple(int(v) for v in args.sizes.split(",")) if args.sizes else default_train_sizes(n_train)
    schemes = [s.strip() for s in args.schemes.split(",") if s.strip()]
    guess = tuple(
        tuple(iop_guess((args.size, args.size), s.source_image_distance_mm, p.pixel_pitch_mm))
        for s in data.truth.acquisition.systems
    )
    setup = EvaluationSetup(
        data.phantom,
        ((args.size, args.size),) * 2,
        guess,
        reference=(data.phantom.ids, data.truth.reference_xyz_mm),
    )
    print(
        f"simulated {len(obs)} observations ({args.frames} epochs x 2 systems, {args.size} px, {len(heldout)} held "
        f"out) in {time.perf_counter() - t0:.1f} s; sizes {sizes}; schemes {schemes}",
        flush=True,
    )

    def progress(s):
        print(f"  {s.scheme}, {s.n_train} epochs: two-ray mean {s.tworay_mean_mm:.4f} mm, {s.wall_s:.1f} s", flush=True)

    scores = evaluate(obs, heldout, sizes, schemes, setup, progress=progress).scores
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    print()
    print(markdown(scores, OURS, [f"benchmarks/evaluate.py --frames {args.frames} --seed {args.seed}"], BeadPart()))
    print(f"total wall time {wall:.1f} s, CPU time {cpu:.1f} s (target <= 600 s wall)")
    by = {(s.scheme, s.n_train): s.tworay_mean_mm for s in scores}
    worst = np.inf
    for size in sizes:
        ours = by.get((OURS, size))
        for peer in PEERS:
            if ours is not None and (peer, size) in by:
                ratio = by[(peer, size)] / ours
                worst = min(worst, ratio)
                print(f"  {size} epochs: {peer} {by[(peer, size)]:.4f} mm / {OURS} {ours:.4f} mm = {ratio:.2f}x")
    verdict = "met" if worst >= TARGET_RATIO else "NOT met"
    print(
        f"smallest peer/fluorocal ratio of the out-of-sample two-ray mean 3D error: {worst:.2f}x "
        f"(target >= {TARGET_RATIO:.0f}x: {verdict})"
    )


if __name__ == "__main__":
    import docpage

    docpage.run(__file__, main)
