"""Where the per-frame work runs, and with how many threads: ``[compute]``, ``--jobs``, ``--scheduler``.

``[compute]`` in the project file owns two settings::

    [compute]
    jobs = 8                          # worker processes for the per-frame stages (default: every local core)
    threads = 1                       # BLAS/OpenMP/OpenCV threads per process (default: 1)

A Dask cluster is the user's own choice, never the project file's: ``--scheduler`` or
``FLUOROCAL_SCHEDULER`` (:data:`SCHEDULER_ENV`). Dask exchanges pickled objects with its
scheduler and workers, so a project file from someone else naming their scheduler could
run code on this machine; ``[compute] scheduler`` is refused with that reason.

The thread count is set through the libraries' environment variables
(:data:`THREAD_VARS`), which they read once when they load: :func:`limit_threads`
must run before numpy or OpenCV is imported, as ``fluorocal``'s entry point does.
A variable the user has set wins over the config for its library, and
``FLUOROCAL_THREADS`` wins over ``[compute] threads`` for all of them.

This module imports nothing heavy (no numpy), so the entry point can read the
thread count from the project file before the numerical libraries load. :func:`no_collection` pauses the
cycle collector for work that makes many objects at once (report figures, code digests).
"""

from __future__ import annotations

import contextlib
import gc
import os
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

from fluorocal.stages.errors import InputError

#: environment variables the numerical libraries read at load for their thread counts
THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "OPENCV_FOR_THREADS_NUM",
)
#: the user's override of ``[compute] threads``
THREADS_ENV = "FLUOROCAL_THREADS"
#: most threads or worker processes a setting may ask for (OpenCV takes a C int; no machine has more cores)
MAX_COUNT = 4096
#: the address schemes of a Dask scheduler fluorocal connects to
SCHEDULER_SCHEMES = ("tcp", "tls")
#: the user's own Dask scheduler, used when ``--scheduler`` and ``--jobs`` are not given
SCHEDULER_ENV = "FLUOROCAL_SCHEDULER"


@dataclass(frozen=True)
class ComputeConfig:
    """Where the per-frame stages run: worker processes, threads per process, or a Dask scheduler.

    Attributes
    ----------
    jobs : int or None
        Worker processes of the local pool; None: every core this process may use. 1: serial, in-process.
    threads : int
        BLAS/OpenMP/OpenCV threads of each process (the main one and each worker).
    scheduler : str
        ``tcp://HOST:PORT`` of a Dask scheduler to run the per-frame stages on; empty: run locally.
        Never from the project file (:func:`compute_from_table`); see :func:`where_to_run`.
    """

    jobs: int | None = None
    threads: int = 1
    scheduler: str = ""

    @property
    def workers(self) -> int:
        """The local pool's worker count: ``jobs``, or every usable core."""
        return self.jobs if self.jobs is not None else local_cores()


def local_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS tells it)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


def _key(file_name: str, key: str) -> str:
    return f"{file_name}: [compute] key '{key}'"


def _positive_int(value, file_name: str, key: str, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise InputError(f"{_key(file_name, key)}: expected {what}; got {value!r}")
    if value > MAX_COUNT:
        shown = str(value) if len(str(value)) <= 30 else f"{str(value)[:12]}... ({len(str(value))} digits)"
        raise InputError(f"{_key(file_name, key)}: expected {what}, at most {MAX_COUNT}; got {shown}")
    return value


def check_scheduler(value, where: str) -> str:
    """``value`` if it is a Dask scheduler address ``tcp://HOST:PORT`` (or ``tls://``), else an InputError.

    Examples
    --------
    >>> check_scheduler("tcp://10.0.0.5:8786", "--scheduler")
    'tcp://10.0.0.5:8786'
    >>> check_scheduler("host:8786", "--scheduler")
    Traceback (most recent call last):
    ...
    fluorocal.stages.errors.InputError: --scheduler: expected a Dask scheduler address tcp://HOST:PORT; got 'host:8786'
    """
    expected = f"{where}: expected a Dask scheduler address tcp://HOST:PORT; got {value!r}"
    if not isinstance(value, str):
        raise InputError(expected)
    parts = urlsplit(value)
    try:
        port = parts.port
    except ValueError:  # not a number, or out of range
        port = None
    if parts.scheme not in SCHEDULER_SCHEMES or not parts.hostname or port is None or parts.path not in ("", "/"):
        raise InputError(expected)
    return value


def compute_from_table(table, file_name: str) -> ComputeConfig:
    """Validate the ``[compute]`` table of the project file ``file_name``.

    Raises
    ------
    InputError
        A key other than jobs and threads (``scheduler`` with the reason it is not read from a
        project file); jobs or threads not a positive integer. The message names the key.
    """
    if not isinstance(table, dict):
        raise InputError(f"{file_name}: key 'compute': expected a table [compute]; got {table!r}")
    if "scheduler" in table:
        raise InputError(
            f"{_key(file_name, 'scheduler')}: a project file cannot choose a Dask cluster (Dask exchanges "
            "pickled code with it, so a project from someone else could run code here); remove the key and "
            f"pass --scheduler ADDRESS or set {SCHEDULER_ENV} in your own environment"
        )
    unknown = sorted(set(table) - {"jobs", "threads"})
    if unknown:
        raise InputError(f"{_key(file_name, unknown[0])}: unknown key; allowed keys are jobs, threads")
    jobs = table.get("jobs")
    if jobs is not None:
        jobs = _positive_int(jobs, file_name, "jobs", "a positive number of worker processes (1: serial)")
    threads = _positive_int(table.get("threads", 1), file_name, "threads", "a positive number of threads per process")
    return ComputeConfig(jobs, threads)


def where_to_run(config: ComputeConfig, jobs: int | None, scheduler: str | None) -> ComputeConfig:
    """``config`` with the user's choice over it: ``--jobs``, else ``--scheduler``, else ``FLUOROCAL_SCHEDULER``.

    Raises
    ------
    InputError
        The scheduler given is not a Dask scheduler address (naming the flag or variable).
    """
    if jobs is not None:
        return ComputeConfig(jobs, config.threads)
    if scheduler is not None:
        return ComputeConfig(None, config.threads, check_scheduler(scheduler, "--scheduler"))
    from_env = os.environ.get(SCHEDULER_ENV, "")
    if from_env:
        return ComputeConfig(None, config.threads, check_scheduler(from_env, f"environment variable {SCHEDULER_ENV}"))
    return config


def config_threads(config_path: Path | None) -> int | None:
    """``[compute] threads`` of a project file, read without numpy; None when absent or not readable.

    A file that does not parse is left to the full load (:func:`fluorocal.config.load_config`) to refuse.
    """
    if config_path is None:
        return None
    try:
        table = tomllib.loads(Path(config_path).read_bytes().decode("utf-8-sig")).get("compute", {})
        return compute_from_table(table, Path(config_path).name).threads
    except (OSError, ValueError, AttributeError, RecursionError):  # InputError and TOML errors are ValueErrors
        return None


def limit_threads(threads: int | None = None) -> int:
    """Set the libraries' thread counts for this process and the processes it starts; return the count.

    ``FLUOROCAL_THREADS`` wins over ``threads``, which defaults to 1; a library's own
    variable (``OPENBLAS_NUM_THREADS`` ...) set by the user wins for that library.
    Effective for BLAS and OpenMP only if they have not loaded yet; OpenCV is set
    directly when it has.

    Raises
    ------
    InputError
        ``FLUOROCAL_THREADS`` is not a positive integer.
    """
    override = os.environ.get(THREADS_ENV)
    if override is not None:
        threads = _count(override)
        if threads is None:
            shown = override if len(override) <= 30 else override[:12] + "..."
            raise InputError(
                f"environment variable {THREADS_ENV}: expected a positive integer, at most {MAX_COUNT}; got {shown!r}"
            )
    threads = threads or 1
    for var in THREAD_VARS:
        os.environ.setdefault(var, str(threads))
    if "cv2" in sys.modules:
        sys.modules["cv2"].setNumThreads(_count(os.environ["OPENCV_FOR_THREADS_NUM"]) or threads)
    return threads


def _count(text: str) -> int | None:
    """``text`` as a positive integer (ASCII digits only), else None."""
    text = text.strip()
    if not (text.isascii() and text.isdigit()) or len(text) > 6 or not 1 <= int(text) <= MAX_COUNT:
        return None
    return int(text)


@contextlib.contextmanager
def no_collection():
    """Python's cyclic garbage collector off meanwhile (back on after, if it was on).

    For work that makes hundreds of thousands of objects at once: each few hundred allocations would start a
    collection, some of them full passes over the whole process (a figure's artists; a module's syntax tree,
    ~15 % of the code digests' time on a first run).
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()
