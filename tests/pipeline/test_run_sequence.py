"""Per-system stages (the labelling of a system's frames as a sequence): what a run computes and caches."""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.cache import ArtifactCache, CacheWarning
from fluorocal.config import load_config
from fluorocal.run import Runner
from fluorocal.stages.io import write_still

from tests.pipeline.toy import CALLS, make_two_system_project, sequence_stages


def _run(cfg, **kw):
    config = load_config(cfg, stage_params_allowed={s.name: s.params_cls for s in sequence_stages()})
    runner = Runner(config, sequence_stages(), ArtifactCache(config.cache_dir), progress=False, **kw)
    return runner, runner.run()


@pytest.fixture()
def project(tmp_path):
    CALLS.clear()
    return make_two_system_project(tmp_path)


def test_one_call_per_system_and_one_artifact_per_frame(project):
    runner, report = _run(project)
    assert report.computed == {"mean": 6, "running": 6, "total": 1}
    assert CALLS == {"mean": 6, "running": 2, "total": 1}
    # running sums restart for each system, in exposure order
    assert [float(runner.get("running", u).value[0]) for u in range(6)] == [100, 300, 600, 1000, 3000, 6000]


def test_second_run_recomputes_nothing(project):
    _run(project)
    CALLS.clear()
    _, report = _run(project)
    assert report.total_computed == 0 and sum(CALLS.values()) == 0


def test_param_change_recomputes_the_sequences_and_downstream_only(project):
    _run(project)
    CALLS.clear()
    project.write_text(project.read_text() + "\n[running]\nstart = 1.0\n")
    _, report = _run(project)
    assert report.computed == {"mean": 0, "running": 6, "total": 1}
    assert CALLS == {"running": 2, "total": 1}


def test_changed_frame_recomputes_its_frame_and_its_system_sequence(project):
    _run(project)
    CALLS.clear()
    write_still(project.parent / "frames" / "A" / "f0.tif", np.full((8, 10), 50, np.uint16))
    runner, report = _run(project)
    assert report.computed == {"mean": 1, "running": 3, "total": 1}
    assert CALLS == {"mean": 1, "running": 1, "total": 1}
    # every later frame of A follows the change; B is untouched
    assert [float(runner.get("running", u).value[0]) for u in range(6)] == [50, 250, 550, 1000, 3000, 6000]


def test_a_corrupt_frame_entry_recomputes_its_system_once(project):
    runner, _ = _run(project)
    key = runner.keys[("running", 4)]
    npz = runner.cache.entry_dir("running", key) / "arrays.npz"
    npz.write_bytes(npz.read_bytes()[:20])
    CALLS.clear()
    rerun = Runner(runner.config, sequence_stages(), runner.cache, progress=False, force=["total"])
    with pytest.warns(CacheWarning, match="running"):
        rerun.run()
    assert CALLS == {"running": 1, "total": 1}
    assert float(rerun.get("running", 4).value[0]) == 3000
    assert rerun.cache.load("running", key) is not None


def test_force_recomputes_each_system_once(project):
    _run(project)
    CALLS.clear()
    _, report = _run(project, force=["running"])
    assert report.computed == {"mean": 0, "running": 6, "total": 1}
    assert CALLS == {"running": 2, "total": 1}


def test_status_counts_frames(project):
    runner, _ = _run(project)
    assert {r["stage"]: (r["n"], r["status"]) for r in runner.status()}["running"] == (6, "cached")
