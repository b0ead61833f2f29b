"""The orchestrator and cache: hits, invalidation, corruption and interrupted writes (STYLE.md §7)."""

from __future__ import annotations

import logging
from functools import lru_cache

import numpy as np
import pytest
from fluorocal.cache import ArtifactCache, CacheWarning
from fluorocal.config import load_config
from fluorocal.run import Runner
from fluorocal.stages.io import write_still

from tests.pipeline import toy
from tests.pipeline.toy import CALLS, make_project, toy_stages


def _run(cfg, **kw):
    config = load_config(cfg, stage_params_allowed={s.name: s.params_cls for s in toy_stages()})
    runner = Runner(config, toy_stages(), ArtifactCache(config.cache_dir), progress=False, **kw)
    return runner, runner.run()


@pytest.fixture()
def project(tmp_path):
    CALLS.clear()
    return make_project(tmp_path)


def test_first_run_computes_everything_and_result_is_right(project):
    runner, report = _run(project)
    assert report.computed == {"mean": 3, "scale": 3, "total": 1}
    # frames hold constant 100, 200, 300; scale doubles; total sums
    assert runner.get("total", None).value[0] == pytest.approx(2 * (100 + 200 + 300))


def test_second_run_recomputes_nothing_and_says_so(project, caplog):
    _run(project)
    CALLS.clear()
    with caplog.at_level(logging.INFO, logger="fluorocal.run"):
        runner, report = _run(project)
    assert report.total_computed == 0 and sum(CALLS.values()) == 0
    assert "nothing recomputed" in caplog.text
    assert "nothing recomputed: all 7 artifacts were cached" in report.lines()


def test_param_change_recomputes_only_downstream(project):
    _run(project)
    CALLS.clear()
    project.write_text(project.read_text() + "\n[scale]\nfactor = 3.0\n")
    runner, report = _run(project)
    assert report.computed == {"mean": 0, "scale": 3, "total": 1}
    assert CALLS == {"scale": 3, "total": 1}
    assert runner.get("total", None).value[0] == pytest.approx(3 * 600)


def test_changed_frame_recomputes_that_frame_and_downstream(project):
    _run(project)
    CALLS.clear()
    write_still(project.parent / "frames" / "f1.tif", np.full((8, 10), 1000, np.uint16))
    runner, report = _run(project)
    assert report.computed == {"mean": 1, "scale": 1, "total": 1}
    assert runner.get("total", None).value[0] == pytest.approx(2 * (100 + 1000 + 300))


def test_truncated_artifact_is_detected_and_recomputed(project):
    runner, _ = _run(project)
    key = runner.keys[("total", None)]
    npz = runner.cache.entry_dir("total", key) / "arrays.npz"
    npz.write_bytes(npz.read_bytes()[:20])
    CALLS.clear()
    runner2 = Runner(runner.config, toy_stages(), runner.cache, progress=False)
    with pytest.warns(CacheWarning, match="unreadable"):
        value = runner2.get("total", None).value[0]
    assert value == pytest.approx(1200)
    assert CALLS["total"] == 1
    assert runner2.cache.load("total", key) is not None  # rewritten whole


def test_corrupt_upstream_is_recomputed_when_needed(project):
    runner, _ = _run(project)
    key = runner.keys[("scale", 0)]
    manifest = runner.cache.entry_dir("scale", key) / "manifest.json"
    manifest.write_text(manifest.read_text()[:-40])
    CALLS.clear()
    rerun = Runner(runner.config, toy_stages(), runner.cache, progress=False, force=["total"])
    with pytest.warns(CacheWarning, match="scale"):
        rerun.run()
    assert rerun.get("total", None).value[0] == pytest.approx(1200)
    assert CALLS == {"total": 1, "scale": 1}


def test_interrupted_write_leaves_no_trusted_artifact(project, monkeypatch):
    config = load_config(project)
    cache = ArtifactCache(config.cache_dir)
    runner = Runner(config, toy_stages(), cache, progress=False)
    key = runner.keys[("mean", 0)]

    def crash(*a, **k):
        raise KeyboardInterrupt("simulated crash while writing")

    monkeypatch.setattr("fluorocal.cache.os.replace", crash)
    with pytest.raises(KeyboardInterrupt):
        cache.store("mean", key, toy.Value(np.array([1.0])))
    monkeypatch.undo()
    assert not cache.has("mean", key)
    assert cache.load("mean", key) is None
    leftovers = [p for p in (cache.root / "mean").iterdir()] if (cache.root / "mean").exists() else []
    assert leftovers == []


def test_crash_between_files_leaves_no_manifest(project, monkeypatch):
    """Kill the write after the arrays but before the manifest: the entry must not exist."""
    config = load_config(project)
    cache = ArtifactCache(config.cache_dir)
    runner = Runner(config, toy_stages(), cache, progress=False)
    key = runner.keys[("mean", 0)]
    real_dumps = __import__("json").dumps

    def crash_on_manifest(obj, *a, **k):
        if isinstance(obj, dict) and "files" in obj:
            raise OSError("disk full")
        return real_dumps(obj, *a, **k)

    monkeypatch.setattr("fluorocal.cache.json.dumps", crash_on_manifest)
    with pytest.raises(OSError):
        cache.store("mean", key, toy.Value(np.array([1.0])))
    monkeypatch.undo()
    assert not cache.has("mean", key)
    assert not any((cache.root / "mean").iterdir())


def test_force_recomputes_stage_and_downstream(project):
    _run(project)
    CALLS.clear()
    _, report = _run(project, force=["scale"])
    assert report.computed == {"mean": 0, "scale": 3, "total": 1}


def test_until_stops_early(project):
    _, report = _run(project, until="mean")
    assert report.computed == {"mean": 3}


def test_unknown_stage_in_force_is_an_input_error(project):
    from fluorocal.stages.errors import InputError

    with pytest.raises(InputError, match="unknown stage 'nope'"):
        _run(project, force=["nope"])


def test_round_trip_preserves_arrays_and_metadata(tmp_path):
    cache = ArtifactCache(tmp_path / "c")
    art = toy.Value(np.arange(5.0), note="x")
    cache.register({"tests.pipeline.toy:Value": toy.Value})
    cache.store("s", "a" * 64, art)
    back = cache.load("s", "a" * 64)
    assert back.note == "x" and np.array_equal(back.value, art.value)
    assert not back.value.flags.writeable
    assert (tmp_path / "c" / "s" / ("a" * 64) / "table.csv").read_text().startswith("value")


def test_status_reports_cached_stale_missing(project):
    config = load_config(project)
    runner = Runner(config, toy_stages(), ArtifactCache(config.cache_dir), progress=False)
    assert {r["status"] for r in runner.status()} == {"missing"}
    runner.run()
    assert {r["status"] for r in runner.status()} == {"cached"}
    project.write_text(project.read_text() + "\n[scale]\nfactor = 5.0\n")
    config = load_config(project, stage_params_allowed={"scale": toy.ScaleParams})
    status = {
        r["stage"]: r["status"]
        for r in Runner(config, toy_stages(), ArtifactCache(config.cache_dir), progress=False).status()
    }
    assert status == {"mean": "cached", "scale": "stale", "total": "stale"}


def test_a_corrupt_entry_found_on_a_rerun_is_recomputed_and_reported(project, caplog):
    """The summary said "nothing recomputed" while an unreadable entry was recomputed afterwards (issue 13)."""
    runner, _ = _run(project)
    npz = runner.cache.entry_dir("scale", runner.keys[("scale", 1)]) / "arrays.npz"
    npz.write_bytes(npz.read_bytes()[:20])
    CALLS.clear()
    with pytest.warns(CacheWarning, match="scale"), caplog.at_level(logging.INFO, logger="fluorocal.run"):
        rerun, report = _run(project)
    assert CALLS == {"scale": 1}
    assert report.computed == {"mean": 0, "scale": 1, "total": 0}
    assert report.cached == {"mean": 3, "scale": 2, "total": 1}
    assert "nothing recomputed" not in caplog.text and "scale: 1 computed" in caplog.text
    assert rerun.cache.verify("scale", rerun.keys[("scale", 1)])  # the cache is whole again


def test_an_artifact_counted_cached_then_recomputed_counts_computed():
    from fluorocal.run import RunReport

    report = RunReport()
    report.record("label", [0, 1, 2], "cached")
    report.record("label", [0, 1, 2], "computed")  # a system's sequence recomputed after all
    report.record("label", [1], "cached")
    assert report.computed == {"label": 3} and report.cached == {"label": 0}
    assert not any("nothing recomputed" in line for line in report.lines())


def _frame_peak(radiograph, mean: toy.Value, params: toy.ScaleParams) -> toy.Value:
    return toy.Value(np.array([float(radiograph.image.max()) - mean.value[0]]))


def test_a_serial_run_reads_each_frame_once_for_every_stage_that_takes_it(tmp_path, monkeypatch):
    from fluorocal import run as run_module
    from fluorocal.compute import ComputeConfig
    from fluorocal.graph import Stage

    cfg = make_project(tmp_path, n_frames=3)
    stages = [toy_stages()[0], Stage("peak", _frame_peak, toy.ScaleParams, ("frame", "mean"))]
    config = load_config(cfg, stage_params_allowed={s.name: s.params_cls for s in stages})
    reads = []
    real = run_module._read_file_frames.__wrapped__

    def counted(path, sha):
        reads.append(path.name)
        return real(path, sha)

    monkeypatch.setattr(run_module, "_read_file_frames", lru_cache(maxsize=2)(counted))
    runner = Runner(config, stages, ArtifactCache(config.cache_dir), progress=False, compute=ComputeConfig(jobs=1))
    report = runner.run()
    assert report.computed == {"mean": 3, "peak": 3}
    assert sorted(reads) == ["f0.tif", "f1.tif", "f2.tif"]  # stage by stage: 6 reads (3 frames, 2 cached slots)
    assert [runner.get("peak", u).value[0] for u in range(3)] == [0.0, 0.0, 0.0]
