"""Projects sharing one cache (issue 28): ``cache clean`` never removes another project's entries.

Two toy projects (tests/pipeline/toy.py) in one folder share its default cache; they differ in the
``mean`` offset, so each has entries of its own. A failure to write the cache keeps the computed result.
"""

from __future__ import annotations

import logging

import pytest
from fluorocal.cache import PROJECTS, ArtifactCache
from fluorocal.cli import main
from fluorocal.config import load_config
from fluorocal.run import Runner

from tests.pipeline.toy import CALLS, make_project, toy_stages


def _runner(cfg, **kw):
    config = load_config(cfg, stage_params_allowed={s.name: s.params_cls for s in toy_stages()})
    return Runner(config, toy_stages(), ArtifactCache(config.cache_dir), progress=False, **kw)


def _entries(root) -> set[tuple[str, str]]:
    cache = ArtifactCache(root)
    return {(s, k) for s in ("mean", "scale", "total") for k in cache.keys(s)}


@pytest.fixture()
def two_projects(tmp_path):
    """Configs A and B in one folder (one cache), both run; B's mean offset differs."""
    CALLS.clear()
    a = make_project(tmp_path / "project")
    b = a.with_name("b.toml")
    b.write_text(a.read_text() + "\n[mean]\noffset = 1.0\n")
    ra, rb = _runner(a), _runner(b)
    ra.run()
    rb.run()
    own_a = {(n, k) for (n, _), k in ra.keys.items()}
    own_b = {(n, k) for (n, _), k in rb.keys.items()}
    assert own_a.isdisjoint(own_b)  # every key depends on the mean: no entry is shared
    assert _entries(ra.cache.root) == own_a | own_b
    return a, b, own_a, own_b, ra.cache.root


def test_cache_clean_of_one_project_keeps_the_other_s_entries(two_projects):
    a, b, own_a, own_b, root = two_projects
    assert main(["-q", "cache", "clean", str(a)]) == 0
    assert _entries(root) == own_b
    CALLS.clear()
    _runner(b).run()
    assert sum(CALLS.values()) == 0  # B's cache is whole: nothing recomputed
    ArtifactCache(root).clean(project=b)  # (the CLI reads B's toy [mean] section as an unknown key)
    assert not root.exists()  # the last project's clean removes the folder


def test_stale_clean_keeps_the_other_project_s_entries(two_projects):
    a, b, own_a, own_b, root = two_projects
    a.write_text(a.read_text() + "\n[scale]\nfactor = 3.0\n")  # A's scale and total entries are now stale
    runner = _runner(a)
    current = {(n, k) for (n, _), k in runner.keys.items()}
    runner.cache.clean(keep=current, project=a)
    assert _entries(root) == own_b | (own_a & current)
    assert {s for s, _ in own_a - current} == {"scale", "total"}


def test_entries_no_project_records_are_kept_when_another_project_uses_the_cache(two_projects):
    a, b, own_a, own_b, root = two_projects
    for record in (root / PROJECTS).iterdir():  # as a cache of an earlier version: no records
        record.unlink()
    ArtifactCache(root).record_use(b, own_b)
    ArtifactCache(root).clean(project=a)  # A is not recorded: every entry may be B's or an unrecorded one's
    assert _entries(root) == own_a | own_b


def test_a_cache_that_cannot_be_written_keeps_the_computed_result(tmp_path, monkeypatch, caplog):
    """A cache refusing the project stage's entry (full, read-only) keeps the result for this run."""
    CALLS.clear()
    cfg = make_project(tmp_path / "project")
    runner = _runner(cfg)
    store = ArtifactCache.store

    def refuse_total(self, stage, key, artifact, **kw):
        if stage == "total":
            raise PermissionError(13, "Permission denied", str(self.entry_dir(stage, key)))
        return store(self, stage, key, artifact, **kw)

    monkeypatch.setattr(ArtifactCache, "store", refuse_total)
    with caplog.at_level(logging.WARNING, logger="fluorocal.run"):
        runner.run()
    # frames of 100, 200, 300 (toy.make_project), scaled by 2 and summed: the total is still at hand
    assert float(runner.get("total", None).value[0]) == pytest.approx(2 * (100 + 200 + 300))
    assert "could not cache total/" in caplog.text
    assert runner.cache.keys("total") == []
