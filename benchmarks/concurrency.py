"""Several `fluorocal run` processes on one project and one cache at once, and killed runs.

Each round empties the cache and the outputs, starts ``--processes`` runs of the same config at the same
moment and waits for them; in every ``--kill-every``-th round one more run is started first and killed
with SIGKILL after a delay that moves through the stages from round to round. Every run must exit 0, and
every round's results must be identical byte for byte (object_points.csv and the field files) to a
serial run's: an entry written by another process is read, not recomputed or clobbered, and what a
killed run left is never trusted.

Usage: ``python benchmarks/concurrency.py [--rounds 12] [--processes 4] [--kill-every 3] [--keep DIR]``.
Target (issue 13): 4 x 12 runs, 48/48 succeed with identical results.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULT_FILES = ("object_points.csv", "field_A.npz", "field_B.npz", "observations.csv")


def _env() -> dict:
    return {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}


def _fluorocal(*args: str) -> list[str]:
    return [sys.executable, "-m", "fluorocal.cli", "--quiet", *args]


def make_project(root: Path) -> Path:
    """A small biplanar project (4 + 4 frames of 512 px), as the end-to-end tests use."""
    subprocess.run(
        _fluorocal(
            "simulate", str(root), "--frames", "4", "--systems", "2", "--image-size", "512", "512", "--seed", "3"
        ),
        check=True,
        env=_env(),
    )
    return root / "fluorocal.toml"


def digest(out_dir: Path) -> str:
    h = hashlib.sha256()
    for name in RESULT_FILES:
        h.update((out_dir / name).read_bytes())
    return h.hexdigest()


def reset(cfg: Path) -> None:
    subprocess.run(_fluorocal("cache", "clean", str(cfg)), env=_env(), capture_output=True)
    shutil.rmtree(cfg.parent / "out", ignore_errors=True)


def one_round(cfg: Path, n: int, kill_after_s: float | None) -> tuple[list[int], str]:
    """Start ``n`` runs at once (after a killed one, if asked); their exit codes and the results' digest."""
    reset(cfg)
    if kill_after_s is not None:
        victim = subprocess.Popen(
            _fluorocal("run", str(cfg)), env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        time.sleep(kill_after_s)
        victim.send_signal(signal.SIGKILL)
        victim.wait()
    runs = [
        subprocess.Popen(_fluorocal("run", str(cfg)), env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        for _ in range(n)
    ]
    codes = []
    for p in runs:
        _, err = p.communicate()
        codes.append(p.returncode)
        if p.returncode:
            print(f"    a run exited {p.returncode}: {err.decode().strip().splitlines()[-1:]}", flush=True)
    return codes, digest(cfg.parent / "out") if all(c == 0 for c in codes) else ""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=12, help="rounds (default: 12)")
    ap.add_argument("--processes", type=int, default=4, help="concurrent runs per round (default: 4)")
    ap.add_argument("--kill-every", type=int, default=3, help="every Nth round starts with a killed run (default: 3)")
    ap.add_argument("--keep", type=Path, help="make the project here instead of a temporary folder")
    args = ap.parse_args(argv)
    root = args.keep or Path(tempfile.mkdtemp(prefix="fluorocal-concurrency-"))
    cfg = make_project(root / "project")
    t0 = time.perf_counter()
    reset(cfg)
    subprocess.run(_fluorocal("run", str(cfg)), env=_env(), check=True, stdout=subprocess.DEVNULL)
    serial_s = time.perf_counter() - t0
    reference = digest(cfg.parent / "out")
    print(f"serial run: {serial_s:.1f} s; {args.rounds} rounds of {args.processes} concurrent runs on one cache")
    ok = same = 0
    for r in range(args.rounds):
        kill = None
        if args.kill_every and r % args.kill_every == args.kill_every - 1:
            kill = serial_s * ((r // args.kill_every) % 4 + 0.5) / 4  # moves through detect .. learn
        t = time.perf_counter()
        codes, result = one_round(cfg, args.processes, kill)
        ok += sum(c == 0 for c in codes)
        same += sum(c == 0 for c in codes) if result == reference else 0
        killed = f", one run killed after {kill:.1f} s first" if kill is not None else ""
        print(
            f"round {r + 1:2d}: {sum(c == 0 for c in codes)}/{len(codes)} succeeded, results "
            f"{'identical' if result == reference else 'DIFFERENT'} to the serial run{killed} "
            f"({time.perf_counter() - t:.1f} s)",
            flush=True,
        )
    total = args.rounds * args.processes
    print(f"{ok}/{total} runs succeeded; {same}/{total} with results identical to the serial run")
    if args.keep is None:
        shutil.rmtree(root, ignore_errors=True)
    return 0 if ok == same == total else 1


if __name__ == "__main__":
    import docpage

    sys.exit(docpage.run(__file__, main))
