"""[compute]: jobs, threads and scheduler validated at load; the thread environment set before the libraries load."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from fluorocal.cli import main
from fluorocal.compute import SCHEDULER_ENV, THREAD_VARS, THREADS_ENV, ComputeConfig, limit_threads, where_to_run
from fluorocal.config import ConfigError, load_config
from fluorocal.stages.errors import InputError

from tests.pipeline.toy import make_project


@pytest.mark.parametrize(
    "section, match",
    [
        ("jobs = 0", r"\[compute\] key 'jobs': expected a positive number of worker processes \(1: serial\); got 0"),
        ("jobs = -2", r"\[compute\] key 'jobs': expected a positive number"),
        ('jobs = "4"', r"\[compute\] key 'jobs': expected a positive number .*; got '4'"),
        ("jobs = 2.5", r"\[compute\] key 'jobs': expected a positive number"),
        ("jobs = true", r"\[compute\] key 'jobs': expected a positive number"),
        ("threads = 0", r"\[compute\] key 'threads': expected a positive number of threads per process; got 0"),
        (
            'scheduler = "tcp://10.0.0.5:8786"',
            r"\[compute\] key 'scheduler': a project file cannot choose a Dask cluster .* FLUOROCAL_SCHEDULER",
        ),
        ("workers = 4", r"\[compute\] key 'workers': unknown key; allowed keys are jobs, threads"),
    ],
)
def test_bad_compute_section_names_the_key(tmp_path, section, match):
    path = make_project(tmp_path)
    path.write_text(path.read_text() + f"\n[compute]\n{section}\n")
    with pytest.raises(ConfigError, match=match) as info:
        load_config(path)
    assert "\n" not in str(info.value) and str(info.value).startswith(f"{path.name}: ")


def test_compute_section_is_read(tmp_path):
    path = make_project(tmp_path)
    assert load_config(path).compute == ComputeConfig(jobs=None, threads=1, scheduler="")
    path.write_text(path.read_text() + "\n[compute]\nthreads = 2\njobs = 3\n")
    assert load_config(path).compute == ComputeConfig(jobs=3, threads=2, scheduler="")


def test_the_users_scheduler_comes_from_the_flag_or_the_environment(monkeypatch):
    """A cluster is chosen by the user (flag, then FLUOROCAL_SCHEDULER), never by the project file; --jobs wins."""
    config = ComputeConfig(jobs=3, threads=2)
    monkeypatch.delenv(SCHEDULER_ENV, raising=False)
    assert where_to_run(config, None, None) == config
    assert where_to_run(config, None, "tcp://h:1") == ComputeConfig(None, 2, "tcp://h:1")
    monkeypatch.setenv(SCHEDULER_ENV, "tcp://env-host:8786")
    assert where_to_run(config, None, None) == ComputeConfig(None, 2, "tcp://env-host:8786")
    assert where_to_run(config, None, "tcp://h:1").scheduler == "tcp://h:1"
    assert where_to_run(config, 1, None) == ComputeConfig(1, 2, "")
    monkeypatch.setenv(SCHEDULER_ENV, "env-host:8786")
    with pytest.raises(InputError, match=f"^environment variable {SCHEDULER_ENV}: expected a Dask scheduler address"):
        where_to_run(config, None, None)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--jobs", "0"], "argument --jobs: expected a positive integer; got '0'"),
        (["--jobs", "2", "--scheduler", "tcp://h:1"], "argument --scheduler: not allowed with argument --jobs"),
    ],
)
def test_bad_jobs_on_the_command_line(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as info:
        main(["run", str(make_project(tmp_path)), *argv])
    assert info.value.code == 2 and message in capsys.readouterr().err


def test_bad_scheduler_on_the_command_line(tmp_path, capsys):
    assert main(["--quiet", "run", str(make_project(tmp_path)), "--scheduler", "h:8786"]) == 2
    err = capsys.readouterr().err
    assert err == "fluorocal: error: --scheduler: expected a Dask scheduler address tcp://HOST:PORT; got 'h:8786'\n"


@pytest.fixture
def clean_thread_env(monkeypatch):
    for var in (*THREAD_VARS, THREADS_ENV):
        monkeypatch.delenv(var, raising=False)
    return monkeypatch


def test_threads_default_to_one_and_the_users_variables_win(clean_thread_env):
    clean_thread_env.setenv("OPENBLAS_NUM_THREADS", "3")
    assert limit_threads(None) == 1
    assert os.environ["OMP_NUM_THREADS"] == "1" and os.environ["OPENCV_FOR_THREADS_NUM"] == "1"
    assert os.environ["OPENBLAS_NUM_THREADS"] == "3"  # set by the user: left alone


def test_fluorocal_threads_wins_over_the_config(clean_thread_env):
    clean_thread_env.setenv(THREADS_ENV, "4")
    assert limit_threads(2) == 4 and os.environ["MKL_NUM_THREADS"] == "4"
    for bad in ("many", "\u00b2", "0"):  # a superscript two passes str.isdigit but is no count
        clean_thread_env.setenv(THREADS_ENV, bad)
        with pytest.raises(ValueError, match="environment variable FLUOROCAL_THREADS: expected a positive integer"):
            limit_threads(2)


@pytest.mark.parametrize("command", [["inspect"], ["cache", "clean"]])
def test_the_thread_limits_are_set_before_numpy_loads(tmp_path, command):
    """The limits reach BLAS only if set before numpy loads it: nothing ``main`` imports first (its parser) loads it.

    (A command module importing numpy at its top left the main process's BLAS at every core, whatever the limits.)
    """
    path = make_project(tmp_path)
    code = (
        "import sys; import fluorocal.compute as c; seen = []; limit = c.limit_threads; "
        "c.limit_threads = lambda *a: (seen.append('numpy' in sys.modules), limit(*a))[1]; "
        f"from fluorocal.cli import main; assert main(['--quiet', *{command!r}, {str(path)!r}]) == 0; print(seen)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split("\n")[-2] == "[False]"


@pytest.mark.parametrize(
    "section, env, expected", [("", {}, "1 1"), ("threads = 2", {}, "2 2"), ("threads = 2", {THREADS_ENV: "3"}, "3 3")]
)
def test_the_entry_point_sets_threads_before_the_libraries_load(tmp_path, section, env, expected):
    """In a fresh process: OpenCV's thread count and BLAS's variable follow [compute] threads and FLUOROCAL_THREADS."""
    path = make_project(tmp_path)
    path.write_text(path.read_text() + f"\n[compute]\n{section}\n")
    code = (
        "import sys; from fluorocal.cli import main; "
        "assert 'numpy' not in sys.modules; "
        f"assert main(['--quiet', 'cache', 'clean', {str(path)!r}]) == 0; "
        "import cv2, os; print(cv2.getNumThreads(), os.environ['OPENBLAS_NUM_THREADS'])"
    )
    base = {k: v for k, v in os.environ.items() if k not in (*THREAD_VARS, THREADS_ENV)}
    done = subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split("\n")[-2] == expected
