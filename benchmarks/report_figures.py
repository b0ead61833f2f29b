"""The report's figures of a run project, each drawn again and timed (issue 31: <= 1 s in all).

Each repeat is a fresh process, as a ``fluorocal run`` draws its figures once: it loads the project's
artifacts from the cache (nothing may be computed: run the project first) and digests the plots' code through
the run's memo (untimed), times matplotlib's import (``matplotlib.figure`` and the Agg canvas, what every
figure needs), then writes the calibration's outputs into a temporary folder with every figure drawn (none
copied from the published set), timing each figure's :meth:`fluorocal.figures.Figures.draw` (its key, the plot
and the PNG written) and the export as a whole.

With ``--baseline REV`` the same is measured on the fluorocal of commit ``REV`` (its ``pipeline`` and
``stages`` from ``git archive``), the two in turn (A B B A ...): per figure the median CPU time of each and
their ratio pair by pair.

Usage: ``python benchmarks/report_figures.py [CONFIG] [--repeats N] [--baseline REV] [--frames N]`` (default 6
repeats). Without CONFIG, ``run_speed.py``'s biplanar set (``--frames`` per system, default 75: 9 figures) is
simulated and run in a temporary folder first; ``run_speed.py --keep DIR --sections biplanar`` leaves that
project as ``DIR/fluorocal-biplanar.toml``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ONE_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
ROOT = Path(__file__).resolve().parents[1]


def child(config: Path) -> dict:
    """One process' times, seconds: ``import``, ``export`` and per figure ``cpu`` and ``wall`` (CPU, wall)."""
    from argparse import Namespace

    from fluorocal import export
    from fluorocal.cli_common import project_runner
    from fluorocal.codehash import code_digest
    from fluorocal.figures import Figures

    times: dict[str, tuple[float, float]] = {}

    class TimedFigures(Figures):
        """Every figure drawn (none copied from the published set), each one's CPU and wall seconds kept."""

        def __init__(self, previous=None, memo=None):
            super().__init__(None, memo)

        def draw(self, path, plot, *args):
            c0, t0 = time.process_time(), time.perf_counter()
            out = super().draw(path, plot, *args)
            times[Path(path).name] = (time.process_time() - c0, time.perf_counter() - t0)
            return out

    runner = project_runner(Namespace(config=config, quiet=True))
    computed = {k: v for k, v in runner.run().computed.items() if v}
    if computed:
        raise SystemExit(f"{config}: stages not cached ({computed}); run the project first")
    # the first figure digests the plots' code through the run's memo, which holds the analyses of the code that ran
    # the project (a miss costs ~15 ms): analysed here, untimed, so that no variant pays for not being that code
    code_digest(["fluorocal.report"], getattr(runner, "code_memo", None))
    c0, t0 = time.process_time(), time.perf_counter()
    import matplotlib.backends.backend_agg  # noqa: F401
    import matplotlib.figure  # noqa: F401

    imported = (time.process_time() - c0, time.perf_counter() - t0)
    export.Figures = TimedFigures  # the export's figures (of any commit's fluorocal) all drawn, and timed
    with tempfile.TemporaryDirectory() as out:
        c0, t0 = time.process_time(), time.perf_counter()
        export.export_calibration(runner, Path(out))
        exported = (time.process_time() - c0, time.perf_counter() - t0)
    return {"import": imported, "export": exported, "figures": times}


def baseline_tree(rev: str, folder: Path) -> Path:
    """The fluorocal package of commit ``rev`` in ``folder`` (``fluorocal/`` with ``stages/`` inside): a PYTHONPATH."""
    folder.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "pipeline", "stages"], capture_output=True)
    if archive.returncode != 0:
        raise SystemExit(f"git archive {rev}: {archive.stderr.decode().strip()}")
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive.stdout, check=True)
    (folder / "pipeline").rename(folder / "fluorocal")
    (folder / "stages").rename(folder / "fluorocal" / "stages")
    return folder


def simulated_project(root: Path, frames: int) -> Path:
    """``run_speed.py``'s biplanar set of ``frames`` per system, simulated and run in ``root``: its config."""
    import run_speed  # benchmarks/run_speed.py
    from fluorocal.cli import main
    from fluorocal.cmd_simulate import write_dataset
    from fluorocal.stages.simulate import SimulateParams, simulate

    params = SimulateParams(n_frames=frames, n_systems=2, image_size_px=1024, seed=11, distortion="strong")
    write_dataset(simulate(params), root, replace=True)
    config = run_speed.write_config(root, json.loads((root / "truth.json").read_text()), "biplanar", ("A", "B"))
    with contextlib.redirect_stdout(io.StringIO()):  # the run's own table of results
        code = main(["--quiet", "run", str(config)])
    if code != 0:
        raise SystemExit(f"fluorocal run {config} failed")
    return config


def measure(config: Path, pythonpath: str | None) -> dict:
    """:func:`child` in a fresh process, one BLAS thread, fluorocal from ``pythonpath`` (None: this checkout)."""
    env = {**os.environ, **ONE_THREAD}
    env.pop("PYTHONPATH", None)
    if pythonpath is not None:
        env["PYTHONPATH"] = pythonpath
    proc = subprocess.run(
        [sys.executable, __file__, "--child", str(config)], env=env, capture_output=True, text=True, cwd="/"
    )
    if proc.returncode != 0:
        raise SystemExit(f"{config}: the measuring process exited {proc.returncode}: {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.splitlines()[-1])


def report(runs: dict[str, list[dict]]) -> None:
    """Per figure and in all, the median CPU (and wall) ms of each variant and the CPU ratio's median."""
    import numpy as np

    names = list(runs)
    first = runs[names[0]][0]["figures"]

    def cpu(name, pick):
        return np.array([pick(r) for r in runs[name]], float)

    rows = [(f, lambda r, f=f: r["figures"][f][0], lambda r, f=f: r["figures"][f][1]) for f in first]
    rows += [
        (
            "all figures",
            lambda r: sum(c for c, _ in r["figures"].values()),
            lambda r: sum(w for _, w in r["figures"].values()),
        ),
        ("matplotlib's import", lambda r: r["import"][0], lambda r: r["import"][1]),
        ("figures + import", lambda r: r["import"][0] + sum(c for c, _ in r["figures"].values()), None),
        ("the whole export", lambda r: r["export"][0], lambda r: r["export"][1]),
    ]
    head = "".join(f" | {n + ' CPU (wall) ms':>24}" for n in names)
    print(f"  {'figure':<24}{head}" + (" | ratio B/A (CPU, median of pairs)" if len(names) == 2 else ""))
    for label, pick_cpu, pick_wall in rows:
        cells = ""
        for n in names:
            c = 1e3 * np.median(cpu(n, pick_cpu))
            w = f"({1e3 * np.median(cpu(n, pick_wall)):6.0f})" if pick_wall else " " * 8
            cells += f" | {c:15.0f} {w}"
        if len(names) == 2:
            cells += f" | {np.median(cpu(names[1], pick_cpu) / cpu(names[0], pick_cpu)):.2f}"
        print(f"  {label:<24}{cells}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("config", type=Path, nargs="?", help="a project already run (default: simulate and run one)")
    ap.add_argument("--frames", type=int, default=75, help="exposures per system without CONFIG (default 75)")
    ap.add_argument("--repeats", type=int, default=6, help="processes per variant (default 6)")
    ap.add_argument("--baseline", metavar="REV", help="also measure commit REV's fluorocal, in turn with this one")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.config.resolve())))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        config = (args.config or simulated_project(Path(tmp) / "project", args.frames)).resolve()
        variants = {"this": None}
        if args.baseline:
            variants = {args.baseline: str(baseline_tree(args.baseline, Path(tmp) / "baseline")), "this": None}
        runs = {name: [] for name in variants}
        for i in range(args.repeats):
            for name in list(variants)[:: 1 if i % 2 == 0 else -1]:  # ABBA: what runs first alternates
                runs[name].append(measure(config, variants[name]))
    shown = args.config or f"a simulated biplanar set of {args.frames} + {args.frames} frames"
    print(
        f"report figures of {shown}: {args.repeats} fresh processes per variant, one BLAS thread; "
        f"load {os.getloadavg()[0]:.1f} at the end"
    )
    report(runs)
    return 0


if __name__ == "__main__":
    import docpage

    sys.exit(docpage.run(__file__, main))
