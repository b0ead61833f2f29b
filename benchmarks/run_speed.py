"""End-to-end run speed (issue 15), side by side in one run, on one simulated biplanar data set.

Simulates a biplanar cube set (strong distortion, 1024 px, ``--frames`` exposures per system), writes it
with README-style minimal configs, and measures:

1. **detect + centroid in memory**, CPU per frame on one core (``process_time``, one OpenCV thread), on
   ``--detect-frames`` frames of system A: the polarity and bead size estimated on every frame (before
   issue 15), estimated once for the system (:func:`fluorocal.stages.detect.estimate_appearance` on its
   first frames, the estimate's cost included) with nothing given (what ``fluorocal run`` does now), and
   given explicitly;
2. **the learn stage** of a 40-exposure one-system project (system A's first 40 frames): CPU and wall
   time of the stage alone (detection, centroiding and labelling run first, cached), its iterations and
   why it stopped (target: converged, no cap reached, <= 5 s CPU), and where its time goes (a second run
   under cProfile: the cumulative time of each part); section ``learn-biplanar`` (not run by default): the
   same for the learn stage of both systems' every frame (the project of section 4);
3. **a full ``fluorocal run``** of system A's frames, in subprocesses with fresh caches: with the
   environment's default BLAS/OpenMP threads and forced to one (``OPENBLAS_NUM_THREADS=1
   OMP_NUM_THREADS=1 MKL_NUM_THREADS=1``), ``--repeats`` times each in ABBA order: the median CPU time
   (user + system of the main process, the pool's fork server and its workers: :mod:`tree_cpu`, Linux only)
   and wall of each, and the ratio of the medians. ``fluorocal`` sets one thread
   per library itself unless ``FLUOROCAL_THREADS`` or ``[compute] threads`` say otherwise, so the two
   settings run alike and the ratio shows whether anything still starts threads of its own;
4. **biplanar end to end**: ``fluorocal run`` of both systems, fresh cache, one BLAS thread: wall and CPU
   (target: <= 30 s wall on a quiet machine; the CPU of the main process, the fork server and the workers,
   and their total; ``--serial`` adds the same run with ``--jobs 1``, whose CPU is all the main process's:
   a check of the total), with each stage's time from the run's log and the wall
   time less those (the pool's stages' times are summed over its workers, so it understates the time
   outside the stages, below zero when the systems' labellings ran side by side: ``--profile`` times the phases).

``--profile`` adds a cProfile of the biplanar run (in process, fresh cache): the wall time of its phases
(:data:`RUN_PHASES`: planning, the pool's stages as the main process waits for them, learn, cache writes,
exports), then the top functions by cumulative and by own time, of the main process only (the pool's workers
compute detect, centroid and each system's labelling).

Usage: ``python benchmarks/run_speed.py [--frames N] [--detect-frames N] [--sections a,b,...]
[--profile] [--serial] [--repeats N] [--keep DIR]`` (defaults: 75 exposures per system, 20 frames for
the detection, sections detect,learn,threads,biplanar; ``--keep``: the data set is written there,
and reused when it is the same).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import re
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from dataclasses import asdict
from pathlib import Path

#: runs a command and measures its pool's workers too (Linux only)
TREE_CPU = Path(__file__).with_name("tree_cpu.py")
ONE_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: the environment as a user's shell gives it, without the thread limits set below for this process
USER_ENV = {k: v for k, v in os.environ.items() if k not in ONE_THREAD}
os.environ.update(ONE_THREAD)  # this process's own timings: one BLAS thread (set before numpy loads)

from fluorocal.cli import main as fluorocal_main  # noqa: E402
from fluorocal.cmd_simulate import write_dataset  # noqa: E402
from fluorocal.stages.simulate import SimulateParams, simulate  # noqa: E402
from graph_run import stage_call  # noqa: E402  (benchmarks/graph_run.py: the stage as the graph calls it)

CONFIG = """[phantom]
file = "phantom.csv"
{systems}
[output]
dir = "out-{tag}"

[cache]
dir = "cache-{tag}"
"""

SYSTEM = """
[[systems]]
name = "{name}"
frames = {frames}
source_image_distance = {sid}
pixel_pitch = {pitch}
"""


def write_config(root: Path, truth: dict, tag: str, systems: tuple[str, ...], n_frames: int | None = None) -> Path:
    """A minimal config of ``systems`` (their first ``n_frames`` frames), with its own output and cache folders."""
    blocks = []
    for s in truth["systems"]:
        if s["name"] not in systems:
            continue
        frames = sorted((root / "frames" / s["name"]).glob("*.tif"))[:n_frames]
        listed = "[" + ", ".join(f'"{f.relative_to(root).as_posix()}"' for f in frames) + "]"
        blocks.append(
            SYSTEM.format(name=s["name"], frames=listed, sid=s["source_image_distance_mm"], pitch=s["pixel_pitch_mm"])
        )
    cfg = root / f"fluorocal-{tag}.toml"
    cfg.write_text(CONFIG.format(systems="".join(blocks), tag=tag))
    shutil.rmtree(root / f"cache-{tag}", ignore_errors=True)
    return cfg


def detect_speed(root: Path, n_frames: int) -> None:
    import cv2
    from fluorocal.stages.centroid import CentroidParams, centroid_beads
    from fluorocal.stages.detect import DetectParams, detect_beads, estimate_appearance
    from fluorocal.stages.io import read_frames

    cv2.setNumThreads(1)
    frames = [read_frames(f)[0] for f in sorted((root / "frames" / "A").glob("*.tif"))[:n_frames]]
    once = estimate_appearance(frames[:3], DetectParams())
    variants = {
        "estimated on every frame": (DetectParams(), False),
        "estimated once per system": (DetectParams(), True),
        "given": (once, False),
    }
    print(f"\n1. detect + centroid in memory, {len(frames)} frames of 1024x1024, one core (CPU time)")
    for name, (params, per_system) in variants.items():
        c0 = time.process_time()
        p = estimate_appearance(frames[:3], params) if per_system else params
        c_est = time.process_time() - c0
        n_beads, c_det, c_cen = 0, 0.0, 0.0
        for frame in frames:
            t = time.process_time()
            found = detect_beads(frame, p)
            t2 = time.process_time()
            n_beads += len(centroid_beads(frame, found, CentroidParams()).xy_px)
            c_det, c_cen = c_det + t2 - t, c_cen + time.process_time() - t2
        total = c_est + c_det + c_cen
        print(
            f"  {name:<27}: {len(frames) / total:5.1f} frames/s per core (detect {1e3 * c_det / len(frames):5.1f} ms"
            f" + centroid {1e3 * c_cen / len(frames):5.1f} ms per frame, estimate {1e3 * c_est:5.1f} ms once); "
            f"{n_beads / len(frames):.0f} beads/frame"
        )


def learn_speed(root: Path, truth: dict) -> None:
    """The learn stage alone at the default refinement cap and at the earlier cap of 15; its error vs the truth."""
    from dataclasses import replace

    cfg = write_config(root, truth, "learn40", ("A",), 40)
    func, inputs, params, extras = stage_call(cfg, "learn")
    print("\n2. learn stage of a 40-exposure one-system project (observations from the cached labelling)")
    for name, p in (("default", params), ("refine_iterations=15", replace(params, refine_iterations=15))):
        t0, c0 = time.perf_counter(), time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the capped run's NotConvergedWarning: its figures say it
            result = func(*inputs, p, **extras)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        field_px, points_mm = learn_truth_errors(result, truth)
        print(
            f"  {name:<21}: {cpu:.1f} s CPU, {wall:.1f} s wall; {len(result.history) - 1} iterations; converged "
            f"{result.converged}: {result.stop_reason}\n"
            f"  {'':<21}  field vs truth (mod a homography) {field_px:.4f} px, object points {points_mm:.4f} mm"
        )
    learn_parts(func, inputs, params, extras)


def learn_biplanar(root: Path, truth: dict, n_frames: int) -> None:
    """The learn stage of the biplanar set (both systems, every frame): its CPU, and where it goes."""
    cfg = write_config(root, truth, "learnbi", ("A", "B"))
    func, inputs, params, extras = stage_call(cfg, "learn")
    print(f"\n2b. learn stage of the biplanar {n_frames} + {n_frames} project (observations from the cached labelling)")
    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = func(*inputs, params, **extras)
    print(
        f"  {time.process_time() - c0:.1f} s CPU, {time.perf_counter() - t0:.1f} s wall ({extras.get('workers', 1)} "
        f"workers); {len(result.history) - 1} iterations; converged "
        f"{result.converged}: {result.stop_reason}"
    )
    learn_parts(func, inputs, params, extras)


#: the learn stage's parts timed by :func:`learn_parts`: label -> (module path suffix, function name)
LEARN_PARTS = {
    "start values (resection)": ("learn/adjuster.py", "start_orientation"),
    "bundle adjustments": ("adjust/bundle.py", "adjust_bundle"),
    "kNN regressions": ("learn/knn.py", "fit_knn_field"),
    "smoothness cross-validation": ("learn/grid.py", "cross_validate_smoothness"),
    "joint field steps": ("learn/joint.py", "fit_grids_jointly"),
    "gross-error screens": ("learn/robust.py", "local_screen"),
    "joint uncertainty (issue 14)": ("learn/uncertainty.py", "learned_uncertainty"),
}


def learn_parts(func, inputs, params, extras) -> None:
    """Where the default learn stage's time goes: a second run under cProfile (CPU time), cumulative time per part.

    The second run is serial (one worker): cProfile sees only the thread it started in, not the systems' threads.
    """
    profiler = cProfile.Profile(time.process_time)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c0 = time.process_time()
        profiler.runcall(func, *inputs, params, **{**extras, **({"workers": 1} if "workers" in extras else {})})
        cpu = time.process_time() - c0
    stats = pstats.Stats(profiler).stats  # (file, line, name) -> (primitive calls, calls, own, cumulative, callers)
    print(f"  where the default's CPU time goes (a second run under cProfile, serial, {cpu:.1f} s CPU there):")
    total = 0.0
    for label, (suffix, name) in LEARN_PARTS.items():
        calls, seconds = profiled(stats, suffix, name)
        total += seconds
        print(f"    {label:<29}: {seconds:5.2f} s in {calls} call(s)")
    print(f"    {'the rest':<29}: {cpu - total:5.2f} s")


def learn_truth_errors(result, truth: dict) -> tuple[float, float]:
    """System A's learned field and bead positions against the simulator's truth.

    The field: RMS px of the ideal coordinates modulo a homography, in the covered field of view. The
    beads: RMS mm after a similarity.
    """
    import cv2
    import numpy as np
    from fluorocal.stages.geometry import similarity_fit
    from fluorocal.stages.simulate import ImageDistortion

    (system,) = [s for s in truth["systems"] if s["name"] == "A"]
    field = result.fields[0]
    centre, radius = np.array(truth["fov"]["centre_xy_px"]), truth["fov"]["radius_px"]
    g = np.linspace(0, field.width_px - 1, 96)
    pts = np.column_stack([a.ravel() for a in np.meshgrid(g, g)])
    pts = pts[(np.linalg.norm(pts - centre, axis=1) < 0.9 * radius) & field.support_at(pts)]
    true_ideal = ImageDistortion.from_dict(system["distortion"]).undistort_points(pts)
    ideal = field.undistort_points(pts)
    H, _ = cv2.findHomography(ideal, true_ideal, 0)
    field_px = float(np.sqrt(np.mean(np.sum((cv2.perspectiveTransform(ideal[None], H)[0] - true_ideal) ** 2, 1))))
    true = dict(zip(truth["phantom"]["ids"], np.asarray(truth["phantom"]["true_xyz_mm"])))
    adj = result.adjustment
    keep = [i for i, b in enumerate(adj.bead_id) if int(b) in true]
    est, ref = adj.xyz_mm[keep], np.array([true[int(adj.bead_id[i])] for i in keep])
    s, R, t = similarity_fit(est, ref)
    return field_px, float(np.sqrt(np.mean(np.sum((s * est @ R.T + t - ref) ** 2, axis=1))))


def run_subprocess(cfg: Path, env: dict, *options: str) -> tuple[float, dict, str]:
    """``fluorocal run`` of ``cfg`` in a fresh process and cache: (wall s, CPU s, its log).

    The CPU (user + system, from :mod:`tree_cpu`): ``main``, the main process; ``fork server``, the pool's
    fork server itself (its imports) and multiprocessing's resource tracker; ``workers``, the pool's workers;
    ``total``, their sum.
    """
    shutil.rmtree(cfg.parent / cfg.stem.replace("fluorocal-", "cache-"), ignore_errors=True)
    command = [sys.executable, "-m", "fluorocal.cli", "run", str(cfg), *options]
    with tempfile.TemporaryDirectory() as tmp:
        measured = Path(tmp) / "cpu.json"
        t0 = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, str(TREE_CPU), str(measured), *command], env=env, capture_output=True, text=True
        )
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise SystemExit(f"fluorocal run {cfg} exited {proc.returncode}: {proc.stderr[-2000:]}")
        parts = json.loads(measured.read_text())
    cpu = {"main": parts["main_s"], "fork server": parts["orphans_own_s"], "workers": parts["orphans_children_s"]}
    return wall, {**cpu, "total": sum(cpu.values())}, proc.stdout + proc.stderr


def cpu_parts(cpu: dict) -> str:
    return ", ".join(f"{name} {seconds:.1f}" for name, seconds in cpu.items() if name != "total")


def thread_ratio(root: Path, truth: dict, n_frames: int, repeats: int) -> None:
    """The same run with the default threads and with one, ``repeats`` times each in ABBA order: the medians."""
    import numpy as np

    cfg = write_config(root, truth, "threads", ("A",))
    envs = {"default threads": USER_ENV, "one BLAS thread": {**USER_ENV, **ONE_THREAD}}
    runs = {name: [] for name in envs}
    for i in range(repeats):
        for name in list(envs)[:: 1 if i % 2 == 0 else -1]:  # ABBA: what runs first, on a warmer machine, alternates
            wall, took, _ = run_subprocess(cfg, envs[name])
            runs[name].append((wall, took["total"]))
    print(f"\n3. fluorocal run of {n_frames} frames (one system), fresh cache, in a subprocess, {repeats} runs each")
    cpu = {}
    for name, times in runs.items():
        walls, cpus = np.array(times).T
        cpu[name] = float(np.median(cpus))
        listed = ", ".join(f"{c:.1f}" for c in cpus)
        print(f"  {name} : median {cpu[name]:6.1f} s CPU ({listed}), median {np.median(walls):6.1f} s wall")
    ratio = cpu["default threads"] / cpu["one BLAS thread"]
    print(f"  CPU ratio default / one thread (medians): {ratio:.3f}x (target <= 1.05x)")


def biplanar(root: Path, truth: dict, n_frames: int, profile: bool, serial: bool) -> None:
    cfg = write_config(root, truth, "biplanar", ("A", "B"))
    wall, cpu, log = run_subprocess(cfg, {**USER_ENV, **ONE_THREAD})
    print(f"\n4. biplanar {n_frames} + {n_frames} end to end (fluorocal run, fresh cache, one BLAS thread)")
    print(
        f"  {wall:.1f} s wall, {cpu['total']:.1f} s CPU ({cpu_parts(cpu)}) (target <= 30 s wall on a quiet "
        f"machine); load {os.getloadavg()[0]:.1f}"
    )
    stages = 0.0
    for line in log.splitlines():
        if re.search(r"computed|stopped|converged|reached|after \d+ iterations", line):
            print(f"    | {line.strip()}")
        stages += sum(float(t) for t in re.findall(r"computed in ([0-9.]+) s", line))
    # the pool's stages' times (detect and centroid per frame, label per system) are summed over its workers:
    # the difference understates the time outside the stages by what the workers ran side by side (--profile
    # times the phases themselves)
    outside = wall - stages
    print(
        f"  wall less the stages' logged times (start-up, code digests, cache, outputs, report; the pool's stages "
        f"summed over its workers): {outside:.1f} s"
    )
    if serial:  # a check of the CPU figure: no pool, every stage in the main process
        wall_1, cpu_1, _ = run_subprocess(cfg, {**USER_ENV, **ONE_THREAD}, "--jobs", "1")
        print(
            f"  the same serial (--jobs 1): {wall_1:.1f} s wall, {cpu_1['total']:.1f} s CPU ({cpu_parts(cpu_1)}); "
            f"load {os.getloadavg()[0]:.1f}"
        )
    if profile:
        write_config(root, truth, "biplanar", ("A", "B"))
        profiler = cProfile.Profile()
        t0 = time.perf_counter()
        profiler.runcall(fluorocal_main, ["--quiet", "run", str(cfg)])
        run_phases(pstats.Stats(profiler).stats, time.perf_counter() - t0)
        for key in ("cumulative", "tottime"):
            out = io.StringIO()
            pstats.Stats(profiler, stream=out).sort_stats(key).print_stats(30)
            print(f"\n  cProfile of the biplanar run, by {key}:")
            print("\n".join("    " + line for line in out.getvalue().splitlines()[6:40]))


#: the phases of ``fluorocal run`` timed by :func:`run_phases`: label -> (module path suffix, function name)
RUN_PHASES = {
    "config (with the stages' imports)": ("pipeline/cli_common.py", "load_project"),
    "plan: frame hashes": ("pipeline/units.py", "frame_units"),
    "plan: code digests": ("pipeline/graph.py", "code_digest"),
    "plan: keys (with the code digests)": ("pipeline/run.py", "_plan"),
    "detect + centroid (pool)": ("pipeline/run.py", "_run_frame_stages"),
    "label, systems side by side (pool)": ("pipeline/run.py", "_run_system_stages"),
    "label in this process": ("pipeline/run.py", "_compute_system_now"),
    "learn": ("stages/kinds/learning.py", "learn_calibration"),
    "cache writes (all stages)": ("pipeline/cache.py", "store"),
    "exports (tables, calibration, report)": ("pipeline/export.py", "export_outputs"),
}


def run_phases(stats: dict, wall: float) -> None:
    """Where the profiled run's wall time goes in the main process (cProfile's clock: wall), phase by phase."""
    print(
        f"\n  the run's phases in the main process (wall, under cProfile: {wall:.1f} s in all; the profiler's cost "
        "per call weighs most on phases of many small calls: cache writes, code digests)"
    )
    for label, (suffix, name) in RUN_PHASES.items():
        calls, seconds = profiled(stats, suffix, name)
        print(f"    {label:<38}: {seconds:6.2f} s in {calls} call(s)")


def profiled(stats: dict, suffix: str, name: str) -> tuple[int, float]:
    """Calls and cumulative seconds in ``stats`` (``pstats.Stats(...).stats``) of function ``name`` in ``suffix``."""
    hits = [v for (file, _, fn), v in stats.items() if fn == name and file.replace(os.sep, "/").endswith(suffix)]
    return sum(v[1] for v in hits), sum(v[3] for v in hits)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=75, help="exposures per system (default 75)")
    ap.add_argument("--detect-frames", type=int, default=20, help="frames timed in section 1 (default 20)")
    ap.add_argument("--sections", default="detect,learn,threads,biplanar", help="comma-separated (default: all)")
    ap.add_argument("--seed", type=int, default=11, help="simulation seed (default 11)")
    ap.add_argument("--profile", action="store_true", help="also profile the biplanar run with cProfile")
    ap.add_argument("--serial", action="store_true", help="also run the biplanar set with --jobs 1 (a CPU check)")
    ap.add_argument(
        "--repeats", type=int, default=4, help="runs of each thread setting in section 3, ABBA: even (default 4)"
    )
    ap.add_argument("--keep", type=Path, help="write the data set here instead of a temporary folder")
    args = ap.parse_args(argv)
    if args.repeats < 2 or args.repeats % 2:
        ap.error(f"--repeats must be an even number of at least 2 (ABBA order); got {args.repeats}")
    sections = set(args.sections.split(","))
    root = Path(tempfile.mkdtemp(prefix="run-speed-")) if args.keep is None else args.keep
    t0 = time.perf_counter()
    # the learn section takes system A's first 40 frames
    n = max(args.frames, 40)
    params = SimulateParams(n_frames=n, n_systems=2, image_size_px=1024, seed=args.seed, distortion="strong")
    if not (root / "truth.json").is_file() or json.loads((root / "truth.json").read_text())["params"] != json.loads(
        json.dumps(asdict(params))
    ):
        write_dataset(simulate(params), root, replace=True)
    truth = json.loads((root / "truth.json").read_text())
    print(
        f"run speed: biplanar cube, strong distortion, {params.n_frames} + {params.n_frames} frames of 1024 px "
        f"(simulated and written in {time.perf_counter() - t0:.0f} s); {os.cpu_count()} CPUs, "
        f"load {os.getloadavg()[0]:.1f}"
    )
    if "detect" in sections:
        detect_speed(root, args.detect_frames)
    if "learn" in sections:
        learn_speed(root, truth)
    if "learn-biplanar" in sections:
        learn_biplanar(root, truth, params.n_frames)
    if "threads" in sections:
        thread_ratio(root, truth, params.n_frames, args.repeats)
    if "biplanar" in sections:
        biplanar(root, truth, params.n_frames, args.profile, args.serial)
    if args.keep is None:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    import docpage

    sys.exit(docpage.run(__file__, main))
