"""The cache under attack and under load (issue 13).

No code from a manifest, tampering detected, ``cache clean`` deletes only its own entries,
concurrent runs agree, leftovers are swept.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os

import numpy as np
import pytest
from fluorocal.artifact_codec import UntrustedData, decode
from fluorocal.cache import CHECKSUM, MANIFEST, MARKER, ArtifactCache, CacheWarning
from fluorocal.cli import main
from fluorocal.config import load_config
from fluorocal.run import Runner
from fluorocal.stages.errors import InputError

from tests.pipeline import toy
from tests.pipeline.toy import CALLS, make_project, toy_stages


def _runner(cfg, **kw):
    config = load_config(cfg, stage_params_allowed={s.name: s.params_cls for s in toy_stages()})
    return Runner(config, toy_stages(), ArtifactCache(config.cache_dir), progress=False, **kw)


def _files(root):
    """Every file under ``root`` with its content hash: what must survive a refused clean."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def _rewrite_manifest(entry, edit, *, fix_checksum: bool) -> None:
    manifest = json.loads((entry / MANIFEST).read_text())
    edit(manifest)
    raw = json.dumps(manifest, indent=1).encode()
    (entry / MANIFEST).write_bytes(raw)
    if fix_checksum:  # an attacker who knows the format recomputes the checksum too
        (entry / CHECKSUM).write_text(hashlib.sha256(raw).hexdigest() + "\n")


@pytest.fixture()
def project(tmp_path):
    CALLS.clear()
    return make_project(tmp_path / "project")


# --- finding 1: code execution from the cache ------------------------------------------------------


@pytest.mark.parametrize("fix_checksum", [True, False], ids=["checksum-recomputed", "checksum-stale"])
def test_a_manifest_naming_os_system_runs_nothing_and_is_recomputed(project, tmp_path, fix_checksum):
    runner = _runner(project)
    runner.run()
    marker = tmp_path / "pwned"
    entry = runner.cache.entry_dir("scale", runner.keys[("scale", 0)])

    def inject(manifest):
        manifest["artifact"] = {"__dataclass__": "os:system", "fields": {"command": f"touch {marker}"}}

    _rewrite_manifest(entry, inject, fix_checksum=fix_checksum)
    CALLS.clear()
    rerun = _runner(project)
    with pytest.warns(CacheWarning, match="scale/.*unreadable"):
        report = rerun.run()
    assert not marker.exists()
    assert report.computed == {"mean": 0, "scale": 1, "total": 0} and CALLS == {"scale": 1}
    assert rerun.get("scale", 0).value[0] == pytest.approx(200.0)
    assert rerun.cache.load("scale", rerun.keys[("scale", 0)]).value[0] == pytest.approx(200.0)  # replaced
    assert not marker.exists()


def test_inspect_reads_no_untrusted_type(project, tmp_path, capsys):
    runner = _runner(project)
    runner.run()
    marker = tmp_path / "pwned"
    key = runner.keys[("scale", 0)]

    def inject(manifest):
        manifest["artifact"] = {"__dataclass__": "os:system", "fields": {"command": f"touch {marker}"}}

    _rewrite_manifest(runner.cache.entry_dir("scale", key), inject, fix_checksum=True)
    assert runner.cache.manifest("scale", key) is None  # what `fluorocal inspect` prints from
    with pytest.warns(CacheWarning, match="unregistered type"):
        assert runner.cache.load("scale", key) is None
    assert not marker.exists()


@pytest.mark.parametrize("artifact", [{"__dict__": {"value": 1}}, {"__tuple__": [1, 2]}, 7])
def test_an_entry_decoding_into_another_type_is_recomputed(project, artifact):
    # the attack battery's manifest_dict_payload: a label entry edited to a plain dict (checksums recomputed)
    # decoded, and the run died on it with an AttributeError traceback
    runner = _runner(project)
    runner.run()
    _rewrite_manifest(
        runner.cache.entry_dir("scale", runner.keys[("scale", 0)]),
        lambda m: m.__setitem__("artifact", artifact),
        fix_checksum=True,
    )
    CALLS.clear()
    rerun = _runner(project)
    with pytest.warns(CacheWarning, match="scale/.*not the stage's Value"):  # found before anything is decoded
        rerun.run()
    value = rerun.get("scale", 0)  # what writing the outputs reads
    assert value.value[0] == pytest.approx(200.0) and CALLS == {"scale": 1}


def test_inspect_does_not_call_a_tampered_entry_cached(project, tmp_path):
    # the attack battery's manifest_os_system_learn_inspect: `inspect` said "cached 1/1" for an entry `run` recomputes
    runner = _runner(project)
    runner.run()
    key = runner.keys[("scale", 0)]

    def inject(manifest):
        manifest["artifact"] = {"__dataclass__": "os:system", "fields": {"command": "true"}}

    _rewrite_manifest(runner.cache.entry_dir("scale", key), inject, fix_checksum=True)
    status = {r["stage"]: (r["status"], r["n"] - r["cached"]) for r in _runner(project).status()}
    assert status["scale"] == ("stale", 1)  # the tampered entry alone is not counted
    assert status["mean"] == ("cached", 0)


def test_decoding_builds_only_registered_classes_with_their_own_fields():
    types = {"tests.pipeline.toy:Value": toy.Value}
    tree = {"__dataclass__": "tests.pipeline.toy:Value", "fields": {"value": {"__array__": "v"}, "note": "x"}}
    value = decode(tree, {"v": np.ones(2)}, types)
    assert isinstance(value, toy.Value) and value.note == "x"
    for tree in (
        {"__dataclass__": "builtins:eval", "fields": {}},
        {"__dataclass__": "tests.pipeline.toy:Value", "fields": {"__class__": 1}},
        {"__dataclass__": "tests.pipeline.toy:Value", "fields": {"value": {"__array__": "missing"}}},
        {"__import__": "os"},
        [1, 2],
    ):
        with pytest.raises(UntrustedData):
            decode(tree, {}, types)


def test_a_hand_edited_number_in_a_manifest_is_detected(project):
    runner = _runner(project)
    runner.run()
    key = runner.keys[("total", None)]

    def edit(manifest):
        manifest["provenance"]["wall_seconds"] += 1.0

    _rewrite_manifest(runner.cache.entry_dir("total", key), edit, fix_checksum=False)
    CALLS.clear()
    rerun = _runner(project)
    with pytest.warns(CacheWarning, match=f"total/{key[:12]} unreadable .*{CHECKSUM}"):
        report = rerun.run()
    assert report.computed["total"] == 1 and CALLS == {"total": 1}
    assert rerun.cache.verify("total", key)


# --- finding 2: cache clean ------------------------------------------------------------------------


@pytest.mark.parametrize("cache_dir", [".", ".."])
def test_cache_clean_refuses_a_folder_it_did_not_create(tmp_path, cache_dir, capsys):
    cfg = make_project(tmp_path / "project", extra_toml=f'\n[cache]\ndir = "{cache_dir}"\n')
    (tmp_path / "sibling").mkdir()
    (tmp_path / "sibling" / "keep.txt").write_text("precious")
    before = _files(tmp_path)
    assert main(["-q", "cache", "clean", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "not a fluorocal cache" in err
    assert str((cfg.parent / cache_dir)) in err
    assert _files(tmp_path) == before


def test_a_run_refuses_a_cache_folder_holding_other_files(tmp_path):
    cfg = make_project(tmp_path / "project", extra_toml='\n[cache]\ndir = "."\n')
    before = _files(tmp_path)
    with pytest.raises(InputError, match="not a fluorocal cache"):
        _runner(cfg).run()
    assert _files(tmp_path) == before


def test_cache_clean_deletes_only_the_cache_s_own_entries(project):
    runner = _runner(project)
    runner.run()
    root = runner.cache.root
    assert (root / MARKER).is_file()
    (root / "mean" / "notes.txt").write_text("mine")  # someone else's files inside the cache folder
    (root / "README").write_text("mine too")
    assert main(["-q", "cache", "clean", str(project)]) == 0
    left = sorted(str(p.relative_to(root)) for p in root.rglob("*"))
    assert left == [MARKER, "README", "mean", "mean/notes.txt"]
    (root / "mean" / "notes.txt").unlink()
    (root / "README").unlink()
    assert main(["-q", "cache", "clean", str(project)]) == 0
    assert not root.exists()  # nothing but its own files left: the folder goes too
    assert (project.parent / "phantom.csv").is_file() and len(list((project.parent / "frames").iterdir())) == 3


def test_cache_clean_does_not_follow_symlinks(project, tmp_path):
    runner = _runner(project)
    runner.run()
    outside = tmp_path / "outside"
    (outside / ("b" * 64)).mkdir(parents=True)
    (outside / ("b" * 64) / "data").write_text("x")
    os.symlink(outside, runner.cache.root / "linked")
    os.symlink(outside / ("b" * 64), runner.cache.root / "mean" / ("c" * 64))
    runner.cache.clean()
    assert (outside / ("b" * 64) / "data").read_text() == "x"


# --- finding 6: concurrency ------------------------------------------------------------------------


def _worker(cfg: str):
    """One process's run of the toy pipeline: its total and how many artifacts it computed."""
    CALLS.clear()
    runner = _runner(cfg)
    report = runner.run()
    return float(runner.get("total", None).value[0]), report.total_computed


def test_four_processes_on_one_cache_all_succeed_with_identical_results(tmp_path):
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(4) as pool:
        for rep in range(4):
            cfg = make_project(tmp_path / f"rep{rep}")
            results = pool.map(_worker, [str(cfg)] * 4, chunksize=1)
            assert [total for total, _ in results] == [pytest.approx(1200.0)] * 4
            # the lock per entry: each of the 7 artifacts computed by exactly one process
            assert sum(n for _, n in results) == 7
            cache = ArtifactCache(cfg.parent / ".fluorocal")
            assert not [p for p in cache.root.rglob(".tmp-*")]


def test_an_entry_published_meanwhile_is_accepted_and_a_broken_one_replaced(tmp_path):
    cache = ArtifactCache(tmp_path / "c", types={"tests.pipeline.toy:Value": toy.Value})
    key = "d" * 64
    cache.store("mean", key, toy.Value(np.array([1.0])))
    cache.store("mean", key, toy.Value(np.array([1.0])))  # the rename meets an intact entry: kept
    assert cache.load("mean", key).value[0] == 1.0
    (cache.entry_dir("mean", key) / "arrays.npz").write_bytes(b"broken")
    cache.store("mean", key, toy.Value(np.array([2.0])))  # a broken entry is displaced
    assert cache.load("mean", key).value[0] == 2.0
    assert sorted(p.name for p in (cache.root / "mean").iterdir()) == [key]


@pytest.mark.parametrize("replacement", ["file", "symlink"])
def test_an_entry_replaced_by_a_file_or_link_is_a_miss_and_displaced(tmp_path, replacement):
    cache = ArtifactCache(tmp_path / "c", types={"tests.pipeline.toy:Value": toy.Value})
    key = "e" * 64
    cache.store("mean", key, toy.Value(np.array([1.0])))
    entry = cache.entry_dir("mean", key)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep.txt").write_text("a user's file")
    for p in entry.iterdir():
        p.unlink()
    entry.rmdir()
    entry.write_text("x") if replacement == "file" else entry.symlink_to(outside, target_is_directory=True)
    with pytest.warns(CacheWarning, match="unreadable"):
        assert cache.load("mean", key) is None
    cache.store("mean", key, toy.Value(np.array([2.0])))
    assert cache.load("mean", key).value[0] == 2.0
    assert sorted(p.name for p in (cache.root / "mean").iterdir()) == [key]
    assert (outside / "keep.txt").read_text() == "a user's file"  # a link is removed, not followed


# --- finding 8: leftovers ----------------------------------------------------------------------------


def test_leftover_temporaries_are_swept_on_start_but_not_a_live_writer_s(project):
    runner = _runner(project)
    runner.run()
    stage_dir = runner.cache.root / "mean"
    dead = stage_dir / f".tmp-{'e' * 64}-abc_12"
    live = stage_dir / f".tmp-{'f' * 64}-xyz_34"
    foreign = stage_dir / ".tmp-someone-else"
    for d in (dead, live, foreign):
        d.mkdir()
        (d / "arrays.npz").write_bytes(b"half")
    with runner.cache.lock("mean", "f" * 64):
        _runner(project).run()
    assert not dead.exists() and live.exists() and foreign.exists()
    _runner(project).run()
    assert not live.exists() and foreign.exists()


def test_the_registry_holds_the_project_s_artifact_classes_and_nothing_else():
    from fluorocal.artifact_codec import artifact_types
    from fluorocal.graph import default_stages

    names = {name.rsplit(":", 1)[1] for name in artifact_types(default_stages())}
    assert {"BeadCandidates", "Centroids", "Labels", "LearnResult", "Adjustment", "CorrectionField"} <= names
    assert all(name.startswith("fluorocal.stages.") for name in artifact_types(default_stages()))


def test_an_entry_of_the_previous_format_is_a_quiet_miss(project):
    runner = _runner(project)
    runner.run()
    entry = runner.cache.entry_dir("total", runner.keys[("total", None)])
    _rewrite_manifest(entry, lambda m: m.update(format_version=1), fix_checksum=False)
    (entry / CHECKSUM).unlink()  # as the previous format wrote it
    CALLS.clear()
    assert _runner(project).run().computed["total"] == 1 and CALLS == {"total": 1}  # no CacheWarning (an error here)


def test_a_cache_another_process_makes_meanwhile_is_accepted(tmp_path, monkeypatch):
    """A cache another process makes between this one's marker check and its listing is accepted (seen in CI).

    This process found no marker; the other made the cache (marker, locks, a stage folder); this one then
    listed the folder and refused it as a stranger's.
    """
    from fluorocal import cache as cache_module

    root = tmp_path / ".fluorocal"
    listing = cache_module._only_cache_files
    made = ArtifactCache(tmp_path / "made")
    made.prepare_root()  # what a cache's start-up writes: its marker

    def meanwhile(path):
        # the other process's start-up, between this one's marker check and its listing
        (root / MARKER).write_bytes((made.root / MARKER).read_bytes())
        (root / "detect").mkdir(exist_ok=True)
        return listing(path)

    root.mkdir()
    monkeypatch.setattr(cache_module, "_only_cache_files", meanwhile)
    ArtifactCache(root).prepare_root()  # no InputError
    assert (root / MARKER).is_file()
    monkeypatch.undo()
    (root / MARKER).unlink()
    (root / "notes.txt").write_text("a user's file")
    with pytest.raises(InputError, match="holds files that are not a fluorocal cache"):
        ArtifactCache(root).prepare_root()  # a stranger's folder is still refused


def test_each_stage_entry_has_its_kind_including_the_per_system_label_stage():
    # the attack battery's manifest_dict_payload: the label stage returns a tuple per system, one Labels per
    # frame's entry; without its kind a label entry edited into a dict still reached the run (AttributeError)
    from fluorocal.artifact_codec import stage_kinds
    from fluorocal.graph import default_stages
    from fluorocal.stages.label import Labels

    assert stage_kinds(default_stages())["label"] is Labels


@pytest.mark.parametrize("linked", [".code", ".locks", ".projects"])
def test_a_folder_with_a_symlinked_cache_file_is_no_cache(tmp_path, linked):
    """A link in an unmarked folder may lead out of it: the folder is not taken for a cache (is_dir follows links)."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    root = tmp_path / ".fluorocal"
    root.mkdir()
    (root / linked).symlink_to(elsewhere)
    with pytest.raises(InputError, match="holds files that are not a fluorocal cache"):
        ArtifactCache(root).prepare_root()


def test_a_symlinked_code_memo_folder_is_neither_read_nor_written(tmp_path):
    """``<cache>/.code`` linked out of the cache: its analyses are not used and nothing is written through it."""
    from fluorocal.codehash import code_digest

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "analyses.json").write_text('{"' + "0" * 64 + '": ["' + "0" * 64 + '", ["os"], []]}')
    before = (elsewhere / "analyses.json").read_bytes()
    cache = ArtifactCache(tmp_path / ".fluorocal")
    cache.prepare_root()
    (cache.root / ".code").symlink_to(elsewhere)
    memo = cache.code_memo()
    assert memo.entries == {}
    code_digest(["tests.pipeline.toy"], memo)
    memo.save()
    assert sorted(p.name for p in elsewhere.iterdir()) == ["analyses.json"]
    assert (elsewhere / "analyses.json").read_bytes() == before


def test_a_symlinked_marker_does_not_make_a_folder_a_cache(tmp_path, capsys):
    """A marker linked from elsewhere (a valid one's bytes) is none the cache wrote: no run, no clean, nothing gone."""
    from fluorocal.cache import MARKER_CONTENT

    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "marker").write_text(json.dumps(MARKER_CONTENT) + "\n")
    cfg = make_project(tmp_path / "project")
    root = cfg.parent / ".fluorocal"
    root.mkdir()
    (root / MARKER).symlink_to(tmp_path / "elsewhere" / "marker")
    (root / "mean").mkdir()  # a stage's folder name: clean would delete entries under it
    (root / "mean" / ("a" * 64)).mkdir()
    before = _files(tmp_path)
    with pytest.raises(InputError, match="holds files that are not a fluorocal cache"):
        ArtifactCache(root).prepare_root()
    assert main(["-q", "cache", "clean", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "not a fluorocal cache" in err
    assert _files(tmp_path) == before


def test_json_nested_too_deep_is_a_one_line_refusal_or_an_unreadable_record(project, capsys):
    """A marker or a project record of 100 000 nested lists (RecursionError in the decoder): never a traceback.

    The marker: ``cache clean`` refuses the folder in one line, deleting nothing. A project's record: read as
    one that lists nothing (the clean goes on).
    """
    runner = _runner(project)
    runner.run()
    root = runner.cache.root
    records = sorted((root / ".projects").glob("*.json"))
    assert records  # not vacuous: the run recorded its entries
    records[0].write_text("[" * 100_000 + "]" * 100_000)
    assert ArtifactCache(root).clean() > 0
    (root / MARKER).write_text("[" * 100_000 + "]" * 100_000)
    before = _files(root)
    assert main(["-q", "cache", "clean", str(project)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "not a fluorocal cache" in err
    assert _files(root) == before
