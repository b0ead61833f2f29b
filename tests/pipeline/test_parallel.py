"""The per-frame stages on a process pool and on a Dask cluster write what a serial run writes, byte for byte.

One small simulated biplanar project (4 + 4 frames of 512 px, as the end-to-end tests use) with three
configs that differ only in their cache and output folders: the serial run of the session's
``calibrated_project`` is the reference; runs through the pool and a loopback ``LocalCluster`` must give the
same cache keys and, per entry, the same files (arrays, tables) and the same artifact structure, for detect and centroid
(computed by the workers) and for label (on the pool, one worker per system; on a cluster, in the main process from
what the workers returned).
The runs stop after label: everything downstream reads only labels.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys

import numpy as np
import pytest
from fluorocal import parallel
from fluorocal.cache import file_sha256
from fluorocal.cli import main
from fluorocal.compute import ComputeConfig
from fluorocal.graph import Stage, default_stages
from fluorocal.stages.learn import uncertainty
from fluorocal.stages.learn.threads import each_system

from tests.conftest import E2E_SIM, copy_project

STAGES = ("detect", "centroid", "label")


@pytest.fixture(scope="module")
def project(calibrated_project, tmp_path_factory):
    """A copy of the session's calibrated project, whose cache (``.fluorocal``) is the serial run's.

    Its 8 frames are fewer than ``MIN_POOL_FRAMES``, so `fluorocal run` computed them in its own process.
    """
    assert 2 * E2E_SIM["n_frames"] < parallel.MIN_POOL_FRAMES
    root = copy_project(calibrated_project, tmp_path_factory.mktemp("parallel") / "project")
    text = (root / "fluorocal.toml").read_text()
    for name in ("pool", "cluster"):
        (root / f"{name}.toml").write_text(
            text.replace('dir = "out"', f'dir = "out_{name}"') + f'\n[cache]\ndir = ".cache_{name}"\n'
        )
    return root


def _entries(cache, folder, stages=STAGES) -> dict:
    """(stage, key) -> (the files' bytes, the artifact's structure) of every entry of ``stages``.

    The structure names each frame by its path: the project's ``folder`` in it is written ``<project>``.
    """
    out = {}
    for stage in stages:
        for entry in sorted((cache / stage).iterdir()):
            manifest = json.loads((entry / "manifest.json").read_text())
            files = {name: (entry / name).read_bytes() for name in manifest["files"]}
            tree = json.loads(json.dumps(manifest["artifact"]).replace(str(folder), "<project>"))
            out[(stage, entry.name)] = (files, tree)
    return out


def _same_as_serial(project, name, calibrated_project) -> None:
    serial = _entries(project / ".fluorocal", calibrated_project)  # computed in calibrated_project, then copied
    other = _entries(project / f".cache_{name}", project)
    assert sorted(other) == sorted(serial)  # the same keys: the same stages, parameters, code and inputs
    # 8 frames: detect + centroid + label
    assert len(serial) == 3 * 2 * E2E_SIM["n_frames"]
    for slot, (files, tree) in serial.items():
        assert other[slot][0] == files, slot  # arrays.npz, table.csv: byte for byte
        assert other[slot][1] == tree, slot


def test_pool_run_equals_serial_run(project, calibrated_project, monkeypatch, caplog):
    monkeypatch.setattr(parallel, "MIN_POOL_FRAMES", 1)  # 8 frames: below the threshold that would keep it serial
    with caplog.at_level(logging.INFO, logger="fluorocal"):
        assert main(["run", str(project / "pool.toml"), "--jobs", "2", "--until", "label"]) == 0
    assert "detect, centroid: 8 frames on 2 local processes" in caplog.text  # the pool did run them
    assert "label: 2 systems on 2 local processes" in caplog.text  # and each system's labelling
    _same_as_serial(project, "pool", calibrated_project)


def test_learn_threads_store_what_a_serial_learn_stores(project, calibrated_project, caplog, monkeypatch):
    """``--jobs 2``: the learn stage's two systems side by side in threads; the same key and bytes as ``--jobs 1``.

    The worker count is how the stage runs, not what it computes: it is in no key. The session's run (every core)
    stored the reference.
    """
    reference = _entries(project / ".fluorocal", calibrated_project, ("learn",))
    given = []  # the worker counts the joint uncertainties were given

    def watched(function, n_systems, workers=1):
        given.append((n_systems, workers))
        return each_system(function, n_systems, workers)

    monkeypatch.setattr(uncertainty, "each_system", watched)
    for jobs in ("1", "2"):
        with caplog.at_level(logging.INFO, logger="fluorocal"):
            assert main(["run", str(project / "pool.toml"), "--jobs", jobs, "--force", "learn"]) == 0
        assert "learn: 1 computed" in caplog.text
        assert given == [(2, int(jobs))]  # the run's worker count reached the learning
        given.clear()
        caplog.clear()
        stored = _entries(project / ".cache_pool", project, ("learn",))
        assert sorted(stored) == sorted(reference) and len(stored) == 1
        for slot, (files, tree) in reference.items():
            assert stored[slot][0] == files  # arrays.npz: byte for byte
            assert _untimed(stored[slot][1]) == _untimed(tree)  # all but the seconds the run took


def _untimed(tree):
    """An artifact's structure without the seconds its computation took (``wall_time_s``, ``adjust_time_s``)."""
    if isinstance(tree, dict):
        return {k: _untimed(v) for k, v in tree.items() if not k.endswith("_time_s")}
    return [_untimed(v) for v in tree] if isinstance(tree, list) else tree


# the scheduler serves HTTP even without a dashboard, on port 8787 when free: another cluster on this machine moves
# it elsewhere, with a warning and (distributed's) a socket left to the collector from the failed attempt
@pytest.mark.filterwarnings("ignore:Port 8787 is already in use:UserWarning", "ignore:unclosed <socket:ResourceWarning")
def test_cluster_run_equals_serial_run(project, calibrated_project, caplog):
    distributed = pytest.importorskip("distributed", reason="Dask is the test extra's: pip install -e '.[test]'")
    with distributed.LocalCluster(
        processes=True, n_workers=2, threads_per_worker=1, host="127.0.0.1", dashboard_address=None
    ) as cluster:
        address = cluster.scheduler_address
        with caplog.at_level(logging.INFO, logger="fluorocal"):
            assert main(["run", str(project / "cluster.toml"), "--scheduler", address, "--until", "label"]) == 0
    assert f"detect, centroid: 8 frames on {address}" in caplog.text
    _same_as_serial(project, "cluster", calibrated_project)


def test_small_projects_stay_serial(project, caplog):
    """Fewer frames than MIN_POOL_FRAMES: no pool is started (its start-up would cost more than it gains)."""
    assert 2 * E2E_SIM["n_frames"] < parallel.MIN_POOL_FRAMES
    with caplog.at_level(logging.INFO, logger="fluorocal"):
        argv = ["run", str(project / "pool.toml"), "--jobs", "2", "--until", "centroid", "--force", "detect"]
        assert main(argv) == 0
    assert "local processes" not in caplog.text and "detect: 8 computed" in caplog.text


def test_small_projects_label_serially(project, caplog):
    """Fewer frames than MIN_POOL_FRAMES: the systems' labellings stay in this process too."""
    with caplog.at_level(logging.INFO, logger="fluorocal"):
        assert main(["run", str(project / "pool.toml"), "--jobs", "2", "--until", "label", "--force", "label"]) == 0
    assert "local processes" not in caplog.text and "label: 8 computed" in caplog.text


def test_unreachable_scheduler_is_one_line(project, monkeypatch, capsys):
    monkeypatch.setattr(parallel, "CONNECT_TIMEOUT_S", 1)
    args = ["--quiet", "run", str(project / "cluster.toml"), "--scheduler", "tcp://127.0.0.1:9", "--force", "detect"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert (
        err.startswith("fluorocal: error: cannot reach the Dask scheduler at tcp://127.0.0.1:9")
        and err.count("\n") == 1
    )


def test_missing_dask_is_one_line(project, monkeypatch, capsys):
    monkeypatch.setitem(__import__("sys").modules, "distributed", None)  # as if Dask were not installed
    args = ["--quiet", "run", str(project / "cluster.toml"), "--scheduler", "tcp://127.0.0.1:9", "--force", "detect"]
    assert main(args) == 2
    assert "Dask is not installed; pip install 'fluorocal[cluster]'" in capsys.readouterr().err


def test_tls_without_settings_is_one_line(project, monkeypatch, capsys):
    pytest.importorskip("distributed", reason="Dask is the test extra's: pip install -e '.[test]'")
    monkeypatch.setattr(parallel, "CONNECT_TIMEOUT_S", 1)
    args = ["--quiet", "run", str(project / "cluster.toml"), "--scheduler", "tls://127.0.0.1:9", "--force", "detect"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("fluorocal: error: cannot connect to tls://127.0.0.1:9: ") and "client.cert" in err


def _frame_file(project):
    return next(p for p in sorted((project / "frames").rglob("*")) if p.is_file())


def test_a_killed_pool_worker_is_one_clear_error(project):
    """A worker that dies (here: os._exit, as the OOM killer ends one) ends the run with WorkerLost, no traceback."""
    import os

    die = Stage("die", os._exit, int, inputs=())  # called as os._exit(params): the worker process ends at once
    frame = _frame_file(project)  # its hash as planned: the worker reads it steadily, then dies
    task = parallel.FrameTask(str(frame), file_sha256(frame), (parallel.FrameJob(0, 0, "f", (parallel.Step(die, 3),)),))
    with pytest.raises(parallel.WorkerLost, match="a worker process died .* run again"):
        list(parallel.run_tasks([task], ComputeConfig(jobs=1)))


def test_a_cluster_worker_with_other_stage_code_refuses(project):
    """The main process's code digest travels with each step; a worker running other code computes nothing."""
    stage = next(s for s in default_stages() if s.name == "detect")
    step = parallel.Step(stage, None, code="0" * 64)  # not the digest of this checkout's detect code
    frame = _frame_file(project)
    task = parallel.FrameTask(str(frame), file_sha256(frame), (parallel.FrameJob(0, 0, "f", (step,)),), on_cluster=True)
    with pytest.raises(parallel.WorkerLost, match="runs other fluorocal code for stage detect"):
        parallel.run_task(task)


def test_cluster_workers_with_other_library_versions_are_refused():
    same = {"packages": {p: "1.0" for p in parallel.WORKER_PACKAGES}}
    other = {"packages": {**same["packages"], "numpy": "0.9"}}
    parallel._check_versions({"client": same, "workers": {"tcp://a:1": same}}, "tcp://s:1")  # all alike: accepted
    with pytest.raises(
        parallel.WorkerLost, match=r"worker tcp://b:1 of tcp://s:1 has numpy 0\.9 where this machine has 1\.0"
    ):
        parallel._check_versions({"client": same, "workers": {"tcp://a:1": same, "tcp://b:1": other}}, "tcp://s:1")


def test_a_task_on_a_multi_frame_file_computes_its_own_frames(project, tmp_path):
    """A task decodes only its frames of a multi-frame file, and each job gets its own frame (not the file's first)."""
    from fluorocal.artifact_codec import artifact_types, decode
    from fluorocal.stages.detect import DetectParams, detect_beads
    from fluorocal.stages.io import read_frames, write_dicom

    from tests.helpers import xa_dataset

    singles = sorted((project / "frames").rglob("*.tif"))[:3]
    stored = np.stack([read_frames(p)[0].image.astype(np.uint16) for p in singles])
    multi = tmp_path / "three.dcm"
    write_dicom(multi, xa_dataset(*stored.shape[1:], bits_stored=16), stored)
    stage = next(s for s in default_stages() if s.name == "detect")
    params = DetectParams(polarity="dark", min_diameter_px=4.0, max_diameter_px=30.0)
    jobs = tuple(parallel.FrameJob(u, i, f"frame {i}", (parallel.Step(stage, params),)) for u, i in ((0, 2), (1, 0)))
    results = parallel.run_task(parallel.FrameTask(str(multi), file_sha256(multi), jobs))
    for result, index in zip(results, (2, 0)):
        ((name, tree, arrays, _),) = result.outputs
        got = decode(tree, arrays, artifact_types([stage]))
        want = detect_beads(read_frames(multi)[index], params)
        assert got.n_accepted > 10 and np.array_equal(got.xy_px, want.xy_px)  # frame `index`, found as a serial run


def _runner(project, cache_dir, jobs: int):
    from fluorocal.cache import ArtifactCache
    from fluorocal.config import load_config
    from fluorocal.graph import stage_params_classes
    from fluorocal.run import Runner

    config = load_config(project / "pool.toml", stage_params_allowed=stage_params_classes())
    cache = ArtifactCache(cache_dir)
    return Runner(config, default_stages(), cache, progress=False, compute=ComputeConfig(jobs=jobs), start_pool=True)


def test_fork_server_started_before_planning_on_first_runs_only(project, monkeypatch, tmp_path):
    """A run whose cache holds no detect entry starts the pool's fork server at once, with the pool's stages."""
    started = []
    monkeypatch.setattr(parallel, "start_fork_server", lambda compute, preload: started.append(preload))
    monkeypatch.setattr(parallel, "MIN_POOL_FRAMES", 1)
    _runner(project, tmp_path / "fresh", 2)  # a first run
    assert started == [("fluorocal.stages.detect", "fluorocal.stages.centroid", "fluorocal.stages.kinds.labelling")]
    _runner(project, project / ".fluorocal", 2)  # the serial run's cache: every detect entry there
    _runner(project, tmp_path / "fresh", 1)  # --jobs 1: no pool
    monkeypatch.setattr(parallel, "MIN_POOL_FRAMES", 2 * E2E_SIM["n_frames"] + 1)
    _runner(project, tmp_path / "fresh", 2)  # fewer frame files than a pool is worth
    assert len(started) == 1


def test_a_systems_labelling_failing_on_the_pool_names_the_system(project):
    """A per-system stage's error in a worker ends the run with that error, naming the system as a serial run does."""
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.label import LabelParams

    runner = _runner(project, project / ".fluorocal", 1)
    label = runner.by_name["label"]
    inputs = ([runner.get("centroid", 0)], runner.get("phantom", None))
    step = parallel.Step(label, LabelParams())  # no geometry: a 3D phantom cannot be labelled
    task = parallel.SystemTask(0, "A", step, inputs)
    with pytest.raises(InputError, match="^system A: label: params.source_image_distance_mm"):
        list(parallel.on_local_pool(parallel.run_system_task, [task], ComputeConfig(jobs=2)))


def test_ctrl_c_while_the_fork_server_starts_leaves_it_quiet(tmp_path):
    """Ctrl-C reaches the whole process group: the fork server, still importing, must not die with a traceback.

    `fluorocal run` starts it before planning, when a user is likely to press Ctrl-C; the main process alone
    answers it ("fluorocal: interrupted").
    """
    script = (
        "import os, signal, time\n"
        "from multiprocessing import forkserver\n"
        "from fluorocal import parallel\n"
        "from fluorocal.compute import ComputeConfig\n"
        "parallel.start_fork_server(ComputeConfig(jobs=2), ('fluorocal.stages.detect',))\n"
        "pid = forkserver._forkserver._forkserver_pid\n"
        "os.kill(pid, signal.SIGINT)\n"  # at once: the server has not imported its libraries yet
        "time.sleep(3)\n"
        "assert os.waitpid(pid, os.WNOHANG) == (0, 0)\n"  # still serving
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert done.returncode == 0 and "KeyboardInterrupt" not in done.stderr, done.stderr[-2000:]
