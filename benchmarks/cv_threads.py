"""A biplanar learning's two smoothness cross-validations, one after the other and side by side in two threads.

The inputs are those the learn stage hands :func:`fluorocal.stages.learn.grid.cross_validate_smoothness` (its
refinement's first step) on the biplanar set of ``run_speed.py`` (``--keep DIR``: a folder that script wrote,
reused; its learn stage runs up to the second cross-validation to take them). Each setting runs ``--repeats``
times in ABBA order: serial (``each_system(..., workers=1)``) and threaded (``workers=2``), wall and CPU time
(``process_time``: all threads) of both systems' CVs, their medians and the ratio of the walls; and whether the
two settings' reports are the same to the bit. Run with another worktree's environment to measure its code
(the script imports ``fluorocal`` from the interpreter's).

Usage: ``python benchmarks/cv_threads.py --keep DIR [--repeats N]``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
import warnings
from pathlib import Path

os.environ.update({"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"})  # before numpy

import numpy as np  # noqa: E402
from fluorocal.stages.learn import loop  # noqa: E402
from fluorocal.stages.learn.grid import cross_validate_smoothness  # noqa: E402
from fluorocal.stages.learn.threads import each_system  # noqa: E402
from graph_run import stage_call  # noqa: E402
from run_speed import write_config  # noqa: E402


class _Taken(Exception):
    """Both systems' CV inputs taken: the learn stage stops."""


def cv_inputs(root: Path) -> list:
    """``(args, kwargs)`` of the learn stage's first two :func:`cross_validate_smoothness` calls (one per system)."""
    truth = json.loads((root / "truth.json").read_text())
    func, inputs, params, extras = stage_call(write_config(root, truth, "learnbi", ("A", "B")), "learn")
    taken = []

    def taking(*args, **kw):
        taken.append((args, kw))
        if len(taken) == 2:
            raise _Taken
        return cross_validate_smoothness(*args, **kw)

    loop.cross_validate_smoothness = taking
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            func(*inputs, params, **{**extras, "workers": 1})
    except _Taken:
        return taken
    finally:
        loop.cross_validate_smoothness = cross_validate_smoothness
    raise SystemExit("the learn stage made fewer than two smoothness cross-validations")


def timed(calls: list, workers: int) -> tuple[float, float, tuple]:
    """Wall and CPU seconds of both CVs in up to ``workers`` threads, and their reports."""
    t0, c0 = time.perf_counter(), time.process_time()
    reports = each_system(lambda s: cross_validate_smoothness(*calls[s][0], **calls[s][1]), len(calls), workers)
    return time.perf_counter() - t0, time.process_time() - c0, reports


def same(a, b) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("tau_grid_px", "cv_cost", "order_grid")) and (
        (a.tau_px, a.cv_rms_px, a.order) == (b.tau_px, b.cv_rms_px, b.order)
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--keep", type=Path, required=True, help="run_speed.py's data folder (its --keep)")
    ap.add_argument("--repeats", type=int, default=4, help="runs of each setting, ABBA: even (default 4)")
    args = ap.parse_args(argv)
    if args.repeats < 2 or args.repeats % 2:
        ap.error(f"--repeats must be an even number of at least 2 (ABBA order); got {args.repeats}")
    calls = cv_inputs(args.keep)
    n_obs = [len(c[0][0]) for c in calls]
    print(
        f"smoothness CVs of the biplanar set's refinement ({n_obs[0]} + {n_obs[1]} observations), load "
        f"{os.getloadavg()[0]:.1f}"
    )
    runs = {1: [], 2: []}
    for i in range(args.repeats):
        for workers in (1, 2) if i % 4 in (0, 3) else (2, 1):
            runs[workers].append(timed(calls, workers))
    for workers, label in ((1, "serial"), (2, "2 threads")):
        walls, cpus = [r[0] for r in runs[workers]], [r[1] for r in runs[workers]]
        print(
            f"  {label:<9}: wall {statistics.median(walls):.2f} s (runs {', '.join(f'{w:.2f}' for w in walls)}), "
            f"CPU {statistics.median(cpus):.2f} s"
        )
    ratio = statistics.median(r[0] for r in runs[1]) / statistics.median(r[0] for r in runs[2])
    identical = all(same(a, b) for r in runs[2] for a, b in zip(runs[1][0][2], r[2]))
    print(
        f"  serial / threaded wall: {ratio:.2f}; threaded reports the serial ones to the bit: {identical}; "
        f"load {os.getloadavg()[0]:.1f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
