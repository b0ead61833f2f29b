"""Bundle-adjustment speed: fluorocal's robust adjustment beside scipy and pycolmap on the same observations.

Part 1 — one problem, side by side: a cube phantom (400 beads on four faces),
75 exposures with ~300 observations each (22.5 k), 0.05 px noise and 2 %
gross outliers (5–50 px), solved from the same perturbed start by
- fluorocal: ``stages.adjust.adjust_bundle`` (Student-t ν = 4, IOP estimated,
  inner constraints, including the covariance and per-observation statistics);
- ``scipy.optimize.least_squares`` (trf, ``jac_sparsity``, 2-point Jacobian)
  with ``loss='cauchy'`` (f_scale = 2σ) and ``loss='linear'``;
- pycolmap's bundle adjustment (Ceres, Cauchy loss at 2σ, focal length and
  principal point refined) if pycolmap is importable (optional; never a
  project dependency);
and the paper's C++ (42.1 s per iteration at 75 images, about 30 iterations).

Part 2 — scale: 75, 250, 500 and 1000 exposures x 500 beads (~300
observations per exposure), each size in a fresh process: wall and CPU time,
iterations and peak resident memory (ru_maxrss of that process).

BLAS threads: ``OPENBLAS_NUM_THREADS`` defaults to 1 here (``--threads``): the
benchmark machine's 2 vCPUs are shared, and multithreaded BLAS on a busy
machine is several times slower than one thread for these matrix sizes.

Run: ``.venv/bin/python benchmarks/adjust.py [--threads N] [--skip-scipy] [--sizes 75,250,500,1000]``
"""

from __future__ import annotations

import argparse
import os
import sys


def _parse():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--threads", default="1", help="BLAS threads (default 1)")
    p.add_argument("--skip-scipy", action="store_true", help="skip the scipy least_squares runs (default: run them)")
    p.add_argument(
        "--sizes", default="75,250,500,1000", help="exposure counts for the scaling part (default 75,250,500,1000)"
    )
    p.add_argument("--scale-one", type=int, metavar="M", help=argparse.SUPPRESS)
    return p.parse_args()


ARGS = _parse() if __name__ == "__main__" else None
if ARGS is not None:
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = ARGS.threads

import contextlib  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from fluorocal.stages.adjust import adjust_bundle  # noqa: E402
from fluorocal.stages.artifacts import Observations  # noqa: E402

from tests.stages.ba_synthetic import (  # noqa: E402
    ScipyProblem,
    aligned_error_mm,
    make_problem,
    pycolmap_reconstruction,
    rms,
)

PAPER_S_PER_ITERATION = 42.1  # the paper's C++ at 75 images (section VI)
NOISE_PX = 0.05


def corrupted(n_beads: int, n_exposures: int, visible: float, seed: int = 0):
    """The synthetic problem and its observations with 2 % gross outliers (5–50 px)."""
    syn = make_problem(n_beads=n_beads, n_exposures=n_exposures, visible_fraction=visible, noise_px=NOISE_PX, seed=seed)
    obs = syn.observations
    rng = np.random.default_rng(seed + 1)
    xy = obs.xy_px.copy()
    bad = rng.random(len(xy)) < 0.02
    xy[bad] += rng.uniform(5, 50, (bad.sum(), 2)) * rng.choice([-1, 1], (bad.sum(), 2))
    return syn, Observations(obs.system, obs.exposure, obs.bead_id, xy, obs.sigma_px, obs.system_names), bad


def timed(fn, repeat: int = 1):
    """``(result, best wall s, cpu s of that run)``."""
    best = (None, math.inf, math.inf)
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        wall, cpu = time.perf_counter() - t, time.process_time() - c
        if wall < best[1]:
            best = (out, wall, cpu)
    return best


def side_by_side(skip_scipy: bool) -> None:
    syn, obs, bad = corrupted(400, 75, 0.75)
    print(
        f"Part 1: 75 exposures, {len(syn.ids)} beads, {len(obs)} observations ({len(obs) / 75:.0f} per exposure), "
        f"{bad.mean() * 100:.1f} % outliers, noise {NOISE_PX} px, BLAS threads {os.environ['OPENBLAS_NUM_THREADS']}"
    )
    res, wall, cpu = timed(lambda: adjust_bundle(obs, (syn.ids, syn.nominal_mm), syn.initial), repeat=3)
    rows = [
        (
            "fluorocal adjust_bundle (t, ν=4)",
            wall,
            cpu,
            res.iterations,
            rms(aligned_error_mm(res.xyz_mm, syn.xyz_true_mm)),
            f"{(~res.inlier[bad]).mean() * 100:.0f} % of outliers flagged",
        )
    ]
    if not skip_scipy:
        rows += scipy_rows(syn, obs)
    rows += pycolmap_rows(syn, obs)
    print_table(rows)
    ours, ours_cpu = wall, cpu  # fluorocal's solve: the reference of every ratio
    print(
        f"paper's C++: {PAPER_S_PER_ITERATION} s per iteration (about 30 iterations): "
        f"ours {ours:.3f} s for the whole solve = "
        f"{PAPER_S_PER_ITERATION / ours:.0f}x one paper iteration, "
        f"{30 * PAPER_S_PER_ITERATION / ours:.0f}x the paper's solve; "
        f"{ours / res.iterations * 1000:.0f} ms per iteration here "
        f"(wall; {ours_cpu / res.iterations * 1000:.0f} ms cpu)"
    )


def scipy_rows(syn, obs) -> list[tuple]:
    """Rows of ``scipy.optimize.least_squares`` (trf, sparse 2-point Jacobian), Cauchy loss and no loss."""
    from scipy.optimize import least_squares

    ref = ScipyProblem(_with(syn, obs))
    sparsity = ref.sparsity()
    rows = []
    for loss in ("cauchy", "linear"):
        sol, wall, cpu = timed(
            lambda loss=loss: least_squares(
                ref.residuals,
                ref.x0(),
                jac_sparsity=sparsity,
                method="trf",
                loss=loss,
                f_scale=2.0,
                x_scale="jac",
                max_nfev=100,
            )
        )
        P = ref.unpack(sol.x)[0]
        rows.append(
            (
                f"scipy least_squares trf {loss}",
                wall,
                cpu,
                sol.nfev,
                rms(aligned_error_mm(P, syn.xyz_true_mm)),
                f"status {sol.status}: {sol.message[:40]}",
            )
        )
    return rows


def pycolmap_rows(syn, obs) -> list[tuple]:
    """Rows of pycolmap's bundle adjustment (Ceres, Cauchy loss at 2σ), one thread and all; a note if not importable."""
    try:
        import pycolmap
    except ImportError:
        return [
            ("pycolmap (not importable)", math.nan, math.nan, 0, math.nan, "pip install pycolmap to compare (optional)")
        ]
    pycolmap.logging.minloglevel = 2  # errors only: no per-run banner
    rows = []
    for threads in (1, -1):

        def run(threads=threads):
            rec = pycolmap_reconstruction(syn, obs.xy_px)
            opts = pycolmap.BundleAdjustmentOptions()
            opts.print_summary = False
            opts.refine_principal_point = True
            opts.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
            opts.ceres.loss_function_scale = 2 * NOISE_PX
            opts.ceres.solver_options.num_threads = threads
            with _stderr_silenced():  # COLMAP logs each run from C++ whatever minloglevel says
                t, c = time.perf_counter(), time.process_time()
                pycolmap.bundle_adjustment(rec, opts)
                ba = time.perf_counter() - t, time.process_time() - c
            return rec, *ba

        (rec, ba_s, ba_cpu), wall, cpu = timed(run, repeat=3)
        X = np.array([rec.point3D(i + 1).xyz for i in range(len(syn.ids))])
        rows.append(
            (
                f"pycolmap {pycolmap.__version__} BA, {'1 thread' if threads == 1 else 'all threads'}",
                ba_s,
                ba_cpu,
                0,
                rms(aligned_error_mm(X, syn.xyz_true_mm)),
                f"+{wall - ba_s:.2f} s to build the reconstruction (not counted)",
            )
        )
    return rows


def print_table(rows) -> None:
    """The side-by-side table; the first row (ours) is the reference of the ratios."""
    _, ours, ours_cpu, *_ = rows[0]
    print(
        f"{'solver':44s} {'wall s':>8s} {'cpu s':>7s} {'iter/nfev':>9s} {'3D rms mm':>10s} "
        f"{'wall/ours':>9s} {'cpu/ours':>8s}  note"
    )
    for name, wall, cpu, it, err, note in rows:
        print(
            f"{name:44s} {wall:8.3f} {cpu:7.3f} {it:9d} {err:10.4f} {wall / ours:8.1f}x {cpu / ours_cpu:7.1f}x  {note}"
        )


@contextlib.contextmanager
def _stderr_silenced():
    """Point file descriptor 2 at /dev/null for the duration (output written from C++ included)."""
    sys.stderr.flush()
    saved = os.dup(2)
    with open(os.devnull, "w") as null:
        os.dup2(null.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def _with(syn, obs):
    from dataclasses import replace

    return replace(syn, observations=obs)


def scale_one(m: int) -> None:
    """One scaling run in this process; prints a JSON line."""
    syn, obs, bad = corrupted(500, m, 0.6, seed=2)
    res, wall, cpu = timed(lambda: adjust_bundle(obs, (syn.ids, syn.nominal_mm), syn.initial))
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        json.dumps(
            {
                "m": m,
                "n_obs": len(obs),
                "wall": wall,
                "cpu": cpu,
                "iterations": res.iterations,
                "peak_mb": peak_mb,
                "usable": res.usable,
                "err": rms(aligned_error_mm(res.xyz_mm, syn.xyz_true_mm)),
                "flagged": float((~res.inlier[bad]).mean()),
            }
        )
    )


def scaling(sizes) -> None:
    print("\nPart 2: scaling, 500 beads, ~300 observations per exposure, 2 % outliers (each size in a fresh process)")
    print(
        f"{'exposures':>9s} {'observations':>12s} {'wall s':>8s} {'cpu s':>7s} {'iterations':>10s} "
        f"{'cpu ms/iter':>11s} "
        f"{'peak MB':>8s} {'3D rms mm':>10s} {'flagged':>8s} {'cpu / cpu@first':>15s}"
    )
    base = None
    for m in sizes:
        out = subprocess.run(
            [sys.executable, __file__, "--threads", os.environ["OPENBLAS_NUM_THREADS"], "--scale-one", str(m)],
            capture_output=True,
            text=True,
            check=True,
        )
        r = json.loads(out.stdout.strip().splitlines()[-1])
        base = base or r["cpu"]
        print(
            f"{r['m']:9d} {r['n_obs']:12d} {r['wall']:8.2f} {r['cpu']:7.2f} {r['iterations']:10d} "
            f"{1000 * r['cpu'] / r['iterations']:11.0f} {r['peak_mb']:8.0f} {r['err']:10.4f} "
            f"{100 * r['flagged']:7.0f}% "
            f"{r['cpu'] / base:15.1f}"
        )
    print("wall > cpu means the process waited for a CPU (the machine is shared); cpu is this process's own time")


if __name__ == "__main__":
    if ARGS.scale_one:
        scale_one(ARGS.scale_one)
    else:
        side_by_side(ARGS.skip_scipy)
        scaling([int(s) for s in ARGS.sizes.split(",")])
