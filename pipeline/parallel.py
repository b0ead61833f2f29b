"""The per-frame stages on a local process pool or on a Dask cluster; a per-system stage's systems on the pool.

The main process plans every key (:class:`fluorocal.run.Runner`) and hands out
:class:`FrameTask` s: a frame file's path and content hash, which of its frames,
and per frame the stages to compute with their parameters (and any upstream
artifact the cache already held). Paths and parameters travel, pixels do not: a
worker reads its frames where it runs. It returns each artifact encoded as the
cache stores it (:mod:`fluorocal.artifact_codec`); the main process decodes it
with the project's artifact types and alone writes the cache, so each entry has
one writer and holds what a serial run would have written.

The local pool starts its workers from a fork server (a clean, single-threaded
process that has imported the stages once), so forking never copies a parent's
threads or locks; each worker is set to :attr:`ComputeConfig.threads` threads.
A per-system stage (the labelling of a sequence) of several systems runs one :class:`SystemTask` per
system on the local pool: its inputs travel (the system's centroids, the phantom), and its artifacts come
back encoded as the frames' do.
Dask is imported only when a scheduler is given. On a cluster, a worker whose libraries
(:data:`WORKER_PACKAGES`) or fluorocal stage code differ from the main process's is refused
before it computes anything: its artifacts would be cached under keys made from other code.
"""

from __future__ import annotations

import logging
import multiprocessing
import signal
import socket
import threading
import time
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from functools import lru_cache

from fluorocal.artifact_codec import artifact_types, encode
from fluorocal.compute import ComputeConfig, limit_threads
from fluorocal.stages.errors import CalibError, InputError

log = logging.getLogger(__name__)

#: fewest frames worth a local pool. Starting it costs about a second (the fork server imports numpy, OpenCV,
#: scipy and the stages); detect + centroid take 0.06 s of CPU per 512 px frame and 0.12 s per 1024 px frame
#: (measured here), so N cores gain n * t * (1 - 1/N): a second at 9-17 frames of 1024 px (8 or 2 cores),
#: 17-33 of 512 px. Below 16 the pool rarely pays; a serial run of 16 frames takes 1-2 s anyway.
MIN_POOL_FRAMES = 16
#: what the fork server imports once for all workers: this module, the frame readers, and the libraries the
#: per-frame stages import on first use (scipy.spatial alone takes ~1 s, which each worker would pay again)
WORKER_PRELOAD = (
    "fluorocal.parallel",
    "fluorocal.cache",
    "fluorocal.stages.io",
    "cv2",
    "scipy.ndimage",
    "scipy.spatial",
)
#: glibc's mallopt parameters (malloc.h)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: seconds to wait for a Dask scheduler to answer
CONNECT_TIMEOUT_S = 10
#: distributions whose versions must be the same on every Dask worker as here (Dask checks its own)
WORKER_PACKAGES = ("fluorocal", "numpy", "scipy", "opencv-contrib-python-headless", "scikit-image", "pydicom")


class WorkerLost(CalibError, RuntimeError):
    """A worker process died (killed, out of memory) or a cluster worker cannot run this code."""


@dataclass(frozen=True)
class Step:
    """One stage to compute for a frame, with the parameters (and keyword extras) its key was made from."""

    stage: object  # fluorocal.graph.Stage: its function and inputs travel by reference, as code
    params: object
    extras: dict = field(default_factory=dict)
    code: str = ""  # the stage's code digest in the main process (checked by cluster workers)


@dataclass(frozen=True)
class FrameJob:
    """One frame of a file: its index, its label in messages, what to compute and the cached inputs given."""

    unit: int
    index: int
    label: str
    steps: tuple[Step, ...]
    given: dict = field(default_factory=dict)


@dataclass(frozen=True)
class FrameTask:
    """Frames of one file for one worker.

    ``on_cluster``: the worker is a Dask worker, maybe on another machine: it checks that the file
    is the one the keys were made from and that it runs the same stage code, sets ``threads``
    for OpenCV (BLAS and OpenMP keep what the worker started with: Dask's nanny sets one thread),
    and keeps freed memory (:func:`_keep_freed_memory`).
    """

    path: str
    file_sha256: str
    frames: tuple[FrameJob, ...]
    on_cluster: bool = False
    threads: int = 1


@dataclass(frozen=True)
class FrameResult:
    """A frame's computed artifacts, encoded: ``(stage, tree, arrays, seconds)``; and the warnings raised."""

    unit: int
    outputs: tuple
    warnings: tuple = ()


@dataclass(frozen=True)
class SystemTask:
    """One system's frames for a per-system stage: what the stage is called with (the per-frame inputs as lists).

    ``unit``: the system's first frame (in exposure order), naming the task; ``system``: its name in messages.
    """

    unit: int
    system: str
    step: Step
    inputs: tuple


@dataclass(frozen=True)
class SystemResult:
    """A system's artifacts, one per frame in exposure order, encoded: ``(tree, arrays)``; seconds; warnings."""

    unit: int
    outputs: tuple
    seconds: float
    warnings: tuple = ()


def run_task(task: FrameTask) -> list[FrameResult]:
    """Compute a task's frames (in a worker); the artifacts come back encoded as the cache stores them.

    Raises
    ------
    InputError
        The file cannot be read here, or its content differs from the planned one (another
        machine's copy). A stage's :class:`CalibError` is re-raised naming the frame and stage.
    """
    from fluorocal.steady import read_steady

    where = f"{task.path} on {socket.gethostname()}"
    if task.on_cluster:
        _check_code(task)
        limit_threads(task.threads)
        _keep_freed_memory()
    try:
        # a multi-frame file: these only; another machine's copy or a file being replaced is refused
        frames = read_steady(task.path, task.file_sha256, [job.index for job in task.frames])
    except OSError as exc:
        raise InputError(f"{where}: cannot read ({exc.strerror or exc}); workers must see the frames' paths") from None
    return [_run_frame(job, frame) for job, frame in zip(task.frames, frames)]


def _check_code(task: FrameTask) -> None:
    """Refuse to compute with stage code other than the main process's (another fluorocal on this worker)."""
    for step in {step.stage.name: step for job in task.frames for step in job.steps}.values():
        if _stage_digest(step.stage) != step.code:
            raise WorkerLost(
                f"Dask worker on {socket.gethostname()} runs other fluorocal code for stage {step.stage.name} "
                "than this machine; install the same fluorocal on every worker"
            )


_DIGESTS: dict[str, str] = {}


def _stage_digest(stage) -> str:
    if stage.name not in _DIGESTS:
        _DIGESTS[stage.name] = stage.code_digest()
    return _DIGESTS[stage.name]


def _run_frame(job: FrameJob, frame) -> FrameResult:
    available = {"frame": frame, **job.given}
    outputs = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for step in job.steps:
            stage = step.stage
            t0 = time.perf_counter()
            try:
                artifact = stage.func(*(available[name] for name in stage.inputs), step.params, **step.extras)
            except CalibError as exc:  # named as a serial run names it
                raise type(exc)(f"{job.label}: {stage.name}: {exc}") from exc
            took = time.perf_counter() - t0
            available[stage.name] = artifact
            arrays: dict = {}
            tree = encode(artifact, arrays, "artifact", _stage_types(stage))
            outputs.append((stage.name, tree, arrays, took))
    return FrameResult(job.unit, tuple(outputs), tuple((str(w.message), w.category) for w in caught))


def compute_sequence(stage, inputs, params, extras: dict, system: str) -> tuple[tuple, float]:
    """A per-system stage's artifacts of one system and the seconds they took; its errors name the system."""
    t0 = time.perf_counter()
    try:
        artifacts = tuple(stage.func(*inputs, params, **extras))
    except CalibError as exc:
        raise type(exc)(f"system {system}: {stage.name}: {exc}") from exc
    return artifacts, time.perf_counter() - t0


def run_system_task(task: SystemTask) -> SystemResult:
    """Compute a per-system stage on one system's frames (in a worker); the artifacts come back encoded."""
    stage = task.step.stage
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        artifacts, took = compute_sequence(stage, task.inputs, task.step.params, task.step.extras, task.system)
    outputs = []
    for artifact in artifacts:
        arrays: dict = {}
        outputs.append((encode(artifact, arrays, "artifact", _stage_types(stage)), arrays))
    return SystemResult(task.unit, tuple(outputs), took, tuple((str(w.message), w.category) for w in caught))


@lru_cache(maxsize=16)
def _stage_types(stage) -> dict:
    """The artifact classes ``stage`` returns, found once per worker (resolving the type hints took ~10 ms a frame)."""
    return artifact_types([stage])


def _keep_freed_memory() -> None:
    """Have glibc reuse freed memory for large arrays in this process, as it does by default.

    Dask's nannies start workers with ``MALLOC_TRIM_THRESHOLD_=65536``, which also fixes glibc's
    mmap threshold at 128 KiB: every frame-sized array is then mapped afresh and faulted in page by
    page. Measured on detect + centroid of 1024² frames: 0.7-0.9 s of system time per 10 frames in
    such a worker against 0.1 s in a plain process, and back to 0.04-0.1 s with these thresholds
    (glibc's own upper bounds on 64-bit). Nothing is done outside glibc.
    """
    import ctypes

    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return
    mallopt(M_MMAP_THRESHOLD, 32 << 20)
    mallopt(M_TRIM_THRESHOLD, 64 << 20)


def run_tasks(tasks: list[FrameTask], compute: ComputeConfig, *, preload: tuple[str, ...] = ()):
    """Yield each task's results as they complete, from the Dask scheduler if one is set, else from a local pool.

    ``preload``: modules the pool's fork server imports once (the stages' own).
    """
    if compute.scheduler:
        yield from _on_cluster(tasks, compute.scheduler)
        return
    yield from on_local_pool(run_task, tasks, compute, preload=preload)


def start_fork_server(compute: ComputeConfig, preload: tuple[str, ...] = ()) -> None:
    """Start the local pool's fork server now, importing ``preload``: its start-up then overlaps this process's work.

    The server imports its libraries and stages for about a second; started before a run plans its keys (code
    digests, frame hashes), the pool's workers are ready when the first frame is handed out.
    """
    from multiprocessing import forkserver

    limit_threads(compute.threads)  # the fork server inherits these before it loads the libraries
    multiprocessing.get_context("forkserver").set_forkserver_preload([*WORKER_PRELOAD, *preload])
    # Ctrl-C goes to the whole process group: the server, until it has imported its libraries, would die of it
    # (a traceback on the terminal). It inherits SIGINT ignored (not blocked: the resource tracker's start unblocks it).
    here = threading.current_thread() is threading.main_thread()  # where signal handlers can be set
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if here else None
    try:
        forkserver.ensure_running()
    finally:
        if here:
            signal.signal(signal.SIGINT, previous)


def on_local_pool(function, tasks: list, compute: ComputeConfig, *, preload: tuple[str, ...] = ()):
    """Yield ``function(task)`` of each task as it completes, on a local pool of ``compute.workers`` processes at most.

    The workers are forked from the process's one fork server (:func:`start_fork_server`, here on first use or
    earlier) with ``preload`` imported; a later pool's workers are forked from that same server.
    """
    start_fork_server(compute, preload)
    context = multiprocessing.get_context("forkserver")
    level = logging.getLogger().getEffectiveLevel()
    workers = min(compute.workers, len(tasks))
    with ProcessPoolExecutor(
        workers, mp_context=context, initializer=_init_worker, initargs=(compute.threads, level)
    ) as pool:
        futures = [pool.submit(function, task) for task in tasks]
        try:
            for future in as_completed(futures):
                yield future.result()
        except BrokenProcessPool:
            raise WorkerLost(
                "a worker process died (killed, out of memory, or it failed to start: see above); the frames "
                "computed so far are cached: run again, with fewer --jobs if memory is short"
            ) from None
        finally:
            for future in futures:
                future.cancel()


def _init_worker(threads: int, level: int) -> None:
    """A pool worker: Ctrl-C is the main process's to handle; its threads and log level are the main's."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    limit_threads(threads)
    logging.basicConfig(level=level, format="%(message)s")


def _on_cluster(tasks: list[FrameTask], scheduler: str):
    try:
        from distributed import Client
        from distributed import as_completed as completed
        from distributed.client import FutureCancelledError
        from distributed.scheduler import KilledWorker
    except ImportError:
        raise InputError(
            f"a Dask scheduler is set ({scheduler}) but Dask is not installed; "
            "pip install 'fluorocal[cluster]' (or drop --scheduler / FLUOROCAL_SCHEDULER)"
        ) from None
    client = _connect(Client, scheduler)
    with client:
        _check_versions(client.get_versions(packages=list(WORKER_PACKAGES)), scheduler)
        futures = client.map(run_task, tasks, pure=False)
        try:
            for future in completed(futures, loop=client.loop):
                yield future.result()
        except (KilledWorker, FutureCancelledError) as exc:
            raise WorkerLost(
                f"the Dask cluster at {scheduler} lost the task ({type(exc).__name__}: a worker died or was "
                "restarted); the frames computed so far are cached: run again"
            ) from None
        finally:
            client.cancel(futures)


def _connect(client_cls, scheduler: str):
    try:
        return client_cls(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise InputError(
            f"cannot reach the Dask scheduler at {scheduler} ({exc}); start it or fix --scheduler / FLUOROCAL_SCHEDULER"
        ) from None
    except TypeError as exc:  # tls:// without Dask's TLS settings
        raise InputError(
            f"cannot connect to {scheduler}: {exc}; set distributed.comm.tls.ca-file, client.cert and client.key "
            "in your Dask configuration"
        ) from None


def _check_versions(versions: dict, scheduler: str) -> None:
    """Refuse workers whose :data:`WORKER_PACKAGES` versions differ from this process's."""
    here = versions["client"]["packages"]
    for address, info in sorted(versions["workers"].items()):
        theirs = (info or {}).get("packages", {})
        for package in WORKER_PACKAGES:
            if theirs.get(package) != here.get(package):
                raise WorkerLost(
                    f"Dask worker {address} of {scheduler} has {package} {theirs.get(package) or 'missing'} "
                    f"where this machine has {here.get(package) or 'none'}; install the same versions on every worker"
                )
