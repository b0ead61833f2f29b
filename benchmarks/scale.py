"""Scale: detect + centroid of many frames serially, on the process pool and on a Dask LocalCluster.

Usage: ``OPENBLAS_NUM_THREADS=1 python benchmarks/scale.py [--frames 500] [--workers 2] [--image-size 1024]
[--keep DIR]``.

The frames (one system, ``--image-size`` px, 16-bit TIFF) are made once into a temporary folder (or
``--keep DIR``, reused when it is there): ``fluorocal simulate`` renders :data:`DISTINCT` frames, and
the rest are copies of them with one corner pixel set to the copy's number, so every file has its own
content hash (its own cache key) while simulating stays quick. The same project is then run through
``Runner(..., until="centroid")`` in three modes, each into its own empty cache: serially
(``jobs = 1``), on the local process pool (``jobs = --workers``) and on a ``LocalCluster`` of
``--workers`` single-threaded worker processes on loopback. With ``--repeat N`` the modes run in turn
N times and each keeps its run of least CPU time (this machine is shared: the least is the least
disturbed). Every mode's cache entries are compared with the serial run's: the same keys, and per
entry the same files byte for byte and the same artifact structure.

Start-up is measured apart. The cluster is started for its runs only (its scheduler and nannies
live in this process and would otherwise tick beside the other modes), and its workers have
imported the stages' libraries before the clock starts (as a running cluster has); so has this
process for the serial run. The pool's start-up (its fork server importing numpy, OpenCV, scipy and the stages) is timed
once on its own and printed, with the pool's overhead including it: every `fluorocal run` pays it
once, and the fork server then stays up in this process, so the pool rows show the per-frame cost.

What is measured, and why so. This machine's two vCPUs are shared (about one core of throughput,
and other jobs run beside this one), so two workers cannot show a speed-up: their wall-clock rate
is about the serial one. The overhead of running elsewhere is therefore measured in CPU time:
``cpu s`` is the CPU time of this process and of every process it started (the pool's fork server
and workers, the cluster's workers; live ones read from ``/proc``, reaped ones from ``getrusage``),
over the run; ``main`` is this process's share (the serial run's work; for the others decoding and
storing the results, and for the LocalCluster also its scheduler and nannies, which live in this
process); ``workers`` the rest (for the serial run: all of it). ``frames/worker-cpu-s`` is the
throughput each worker would have on a core of its own. ``overhead`` is the mode's CPU time over
the serial run's, minus one: what shipping tasks and results, decoding and storing them and Dask's
bookkeeping cost beyond the work; ``per worker`` is the workers' throughput against the serial
run's, minus one (target: within 15 %: above -15 %).
``frames/s`` (wall) and its share per worker are printed as measured. The machine's other jobs
move every CPU figure by 10-20 % from run to run (what else runs on the two vCPUs changes the CPU
time a frame takes), and Dask's bookkeeping runs on a clock, so it grows with the wall
time a loaded machine stretches. Linux only.

Undistortion at scale (10 000 frames, peak memory) is measured beside this by the undistortion
benchmark; see :func:`undistort_section`, the place it joins this one.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads: one thread per process, as fluorocal sets
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENCV_FOR_THREADS_NUM", "1")

#: frames rendered by the simulator; the others are marked copies of them
DISTINCT = 20
STAGES = ("detect", "centroid")


def make_frames(root: Path, n_frames: int, image_size_px: int) -> Path:
    """A one-system project of ``n_frames`` frames under ``root``; its config path.

    The simulated frames are reused when ``root`` holds them at this size; the copies are made anew.
    """
    cfg = root / "fluorocal.toml"
    frames = root / "frames" / "A"
    distinct = min(DISTINCT, n_frames)
    size_file = root / "image_size_px.txt"
    simulated = sorted(frames.glob("frame_???.tif"))
    if not (cfg.is_file() and len(simulated) == distinct and size_file.is_file()) or size_file.read_text() != str(
        image_size_px
    ):
        shutil.rmtree(root, ignore_errors=True)
        subprocess.run(
            [sys.executable, "-m", "fluorocal.cli", "--quiet", "simulate", str(root), "--frames", str(distinct)]
            + ["--systems", "1", "--image-size", str(image_size_px), str(image_size_px), "--seed", "5"],
            check=True,
        )
        size_file.write_text(str(image_size_px))
        simulated = sorted(frames.glob("frame_???.tif"))
    from fluorocal.stages.io import read_frames, write_still
    from fluorocal.stages.io.pixels import to_source_dtype

    for old in frames.glob("frame_????.tif"):
        old.unlink()
    images = [to_source_dtype(read_frames(p)[0]) for p in simulated]
    for i in range(distinct, n_frames):
        image = images[i % distinct].copy()
        image[0, 0] = i  # its own content: its own key
        write_still(frames / f"frame_{i:04d}.tif", image, attributes={"DateTime": "2026:01:01 00:00:00"})
    return cfg


def cpu_seconds() -> float:
    """CPU time (user + system) of this process and of all it started: reaped, and live (read from /proc)."""
    total = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        usage = resource.getrusage(who)
        total += usage.ru_utime + usage.ru_stime
    tick = os.sysconf("SC_CLK_TCK")
    for pid in _descendants(os.getpid()):
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile: reaped, so counted by whoever reaped it
            continue
        total += sum(int(v) for v in fields[11:15]) / tick  # utime, stime, cutime, cstime
    return total


def _descendants(pid: int) -> list[int]:
    out, stack = [], [pid]
    while stack:
        parent = stack.pop()
        children = []
        for task in Path(f"/proc/{parent}/task").glob("*"):  # every thread's children (a nanny's are its thread's)
            try:
                children += [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                continue
        out += children
        stack += children
    return out


def run_once(cfg: Path, cache_name: str, compute) -> tuple[float, float, float, Path]:
    """Wall, CPU and this process's CPU seconds of detect + centroid of every frame, into an empty cache."""
    from graph_run import runner_for

    cache_dir = cfg.parent / cache_name
    shutil.rmtree(cache_dir, ignore_errors=True)
    runner = runner_for(cfg, "centroid", cache_dir=cache_dir, compute=compute)
    cpu0, own0, wall0 = cpu_seconds(), _own_cpu(), time.perf_counter()
    runner.run()
    return time.perf_counter() - wall0, cpu_seconds() - cpu0, _own_cpu() - own0, cache_dir


def _own_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run_on_cluster(cfg: Path, cache_name: str, workers: int, profiler: bool):
    """:func:`run_once` on a LocalCluster started (and warmed up) for it: no cluster idles beside the other modes.

    ``profiler``: Dask's own statistical profiler runs in each worker (Dask's default), sampling the
    task thread's stack every 10 ms; off, as README recommends for fluorocal's workers, it costs nothing.
    """
    import dask
    from distributed import Client, LocalCluster
    from fluorocal.compute import ComputeConfig

    with dask.config.set({"distributed.worker.profile.enabled": profiler}):  # the nannies pass it to the workers
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
        )
    with cluster:
        with Client(cluster) as client:
            seen = set(client.run(dask.config.get, "distributed.worker.profile.enabled").values())
        assert seen == {profiler}, f"workers' profiler setting {seen}, wanted {profiler}"
        warm_up(cluster)
        return run_once(cfg, cache_name, ComputeConfig(scheduler=cluster.scheduler_address))


def warm_up(cluster) -> None:
    """Have the cluster's workers import what the pool's fork server imports: a running cluster has done so once."""
    from distributed import Client
    from fluorocal.parallel import WORKER_PRELOAD

    with Client(cluster) as client:
        for module in WORKER_PRELOAD:
            client.run(importlib.import_module, module)


def entries(cache: Path) -> dict:
    """(stage, key) -> (files' bytes, artifact structure) of the detect and centroid entries."""
    out = {}
    for stage in STAGES:
        for entry in sorted((cache / stage).iterdir()):
            manifest = json.loads((entry / "manifest.json").read_text())
            out[(stage, entry.name)] = ({f: (entry / f).read_bytes() for f in manifest["files"]}, manifest["artifact"])
    return out


def undistort_section(args) -> list[str]:
    """The place for undistortion at scale (10 000 frames, peak memory): added with the streaming undistortion."""
    return []


def pool_start_up(workers: int) -> tuple[float, float]:
    """CPU and wall seconds to start the pool's fork server and workers (once per `fluorocal run`).

    The fork server then stays up in this process, so the pool runs measured after it show the
    per-frame cost alone.
    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from fluorocal.parallel import WORKER_PRELOAD

    cpu0, wall0 = cpu_seconds(), time.perf_counter()
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([*WORKER_PRELOAD, "fluorocal.stages.detect", "fluorocal.stages.centroid"])
    with ProcessPoolExecutor(workers, mp_context=context) as pool:
        list(pool.map(abs, range(workers)))
    return cpu_seconds() - cpu0, time.perf_counter() - wall0


def report(best: dict, modes: dict, n_frames: int, start_cpu: float, start_wall: float) -> bool:
    """Print the table; whether every mode's entries equal the serial run's.

    ``workers`` is the CPU time of the processes doing the frames' work (the serial run's own
    process; otherwise every process but this one); ``per worker`` compares the frames per
    CPU-second of those with the serial run's.
    """
    serial_cpu = best["serial"][1]
    reference = entries(best["serial"][3])
    print(
        f"{'mode':<24} {'wall s':>6} {'frames/s':>8} {'/worker':>7} {'cpu s':>6} {'main':>5} {'workers':>7} "
        f"{'frames/worker-cpu-s':>19} {'overhead':>8} {'per worker':>10}"
    )
    identical = True
    for mode, (wall, cpu, main_cpu, cache) in best.items():
        n_workers = modes[mode][0]
        worker_cpu = cpu if mode == "serial" else cpu - main_cpu
        same = mode == "serial" or entries(cache) == reference
        identical &= same
        versus = "-" if mode == "serial" else f"{cpu / serial_cpu - 1:+.1%}"
        per_worker = "-" if mode == "serial" else f"{serial_cpu / worker_cpu - 1:+.1%}"
        print(
            f"{mode:<24} {wall:>6.1f} {n_frames / wall:>8.1f} {n_frames / wall / n_workers:>7.1f} {cpu:>6.1f} "
            f"{main_cpu:>5.1f} {worker_cpu:>7.1f} {n_frames / worker_cpu:>19.1f} {versus:>8} {per_worker:>10}"
            + ("" if mode == "serial" else f"  identical to serial: {'yes' if same else 'NO'}")
        )
    pool = next(m for m in best if m.startswith("pool"))
    print(
        f"pool start-up (fork server importing the stages; once per run): {start_cpu:.1f} cpu-s, "
        f"{start_wall:.1f} s wall; pool overhead with it: {(best[pool][1] + start_cpu) / serial_cpu - 1:+.1%}"
    )
    if identical:
        print(f"identical: {len(reference)} cache entries (detect + centroid) equal byte for byte in every mode")
    return identical


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=500, help="frames to detect and centroid (default: 500)")
    parser.add_argument("--workers", type=int, default=2, help="pool processes and cluster workers (default: 2)")
    parser.add_argument("--image-size", type=int, default=1024, help="frame side, px (default: 1024)")
    parser.add_argument("--repeat", type=int, default=1, help="runs per mode, the least CPU kept (default: 1)")
    parser.add_argument("--keep", type=Path, help="folder for the frames, reused by later runs (default: a temp one)")
    args = parser.parse_args()

    from fluorocal import parallel
    from fluorocal.compute import ComputeConfig

    if args.frames < parallel.MIN_POOL_FRAMES:
        parser.error(f"--frames must be at least {parallel.MIN_POOL_FRAMES}: fewer run serially without a pool")
    for module in parallel.WORKER_PRELOAD:  # the serial run's libraries loaded before its clock, as the others'
        importlib.import_module(module)
    root = args.keep or Path(tempfile.mkdtemp(prefix="fluorocal-scale-"))
    t0 = time.perf_counter()
    cfg = make_frames(root / "project", args.frames, args.image_size)
    print(f"{args.frames} frames of {args.image_size} px ready in {time.perf_counter() - t0:.1f} s ({root})")
    try:
        modes = {
            "serial": (1, ComputeConfig(jobs=1)),
            f"pool, {args.workers} processes": (args.workers, ComputeConfig(jobs=args.workers)),
            f"LocalCluster, {args.workers} workers": (args.workers, "profiler"),
            "  Dask profiler off": (args.workers, "no profiler"),
        }
        start_cpu, start_wall = pool_start_up(args.workers)
        best = {}
        for _ in range(args.repeat):  # the modes in turn; per mode the run of least CPU time
            for i, (mode, (_, compute)) in enumerate(modes.items()):
                run = (
                    run_on_cluster(cfg, f".cache_{i}", args.workers, compute == "profiler")
                    if isinstance(compute, str)
                    else run_once(cfg, f".cache_{i}", compute)
                )
                if mode not in best or run[1] < best[mode][1]:
                    best[mode] = run
        if not report(best, modes, args.frames, start_cpu, start_wall):
            return 1
        for line in undistort_section(args):
            print(line)
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    import docpage

    sys.exit(docpage.run(__file__, main))
