"""Published outputs survive every option (issue 28).

``--until`` after a full run publishes its tables beside the published set, never over it; a second
project is refused an output folder another project published into; a project sharing the first's cache
and cleaning it leaves the first's entries.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from fluorocal.cache import ArtifactCache
from fluorocal.cli import main
from fluorocal.outputs import MANIFEST, publish

from tests.conftest import copy_project


@pytest.fixture(scope="module")
def project(tmp_path_factory, calibrated_project):
    return copy_project(calibrated_project, tmp_path_factory.mktemp("safety") / "project")


def _snapshot(folder):
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_until_after_a_full_run_keeps_the_published_set(project, capsys):
    out = project / "out"
    before = _snapshot(out)
    assert {"calibration.json", "field_A.npz", "report.md"} <= set(before)
    assert main(["--quiet", "run", str(project / "fluorocal.toml"), "--until", "label"]) == 0
    after = _snapshot(out)
    assert {k: v for k, v in after.items() if not k.startswith("until-label/")} == before
    assert "until-label/label.csv" in after
    assert f"partial results (--until label): {out / 'until-label'}" in capsys.readouterr().out
    # the next full run publishes its set and carries the partial results over untouched
    assert main(["--quiet", "run", str(project / "fluorocal.toml")]) == 0
    final = _snapshot(out)
    assert final["until-label/label.csv"] == after["until-label/label.csv"]
    assert {"calibration.json", "field_A.npz", "report.md"} <= set(final)


def test_a_second_project_is_refused_the_first_s_output_folder(project, capsys):
    out = project / "out"
    assert json.loads((out / MANIFEST).read_text())["project"] == "../fluorocal.toml"  # moved with the project
    other = project / "other.toml"
    other.write_text((project / "fluorocal.toml").read_text())  # the same [output] dir
    before = _snapshot(out)
    assert main(["--quiet", "run", str(other)]) == 2
    err = capsys.readouterr().err
    assert "holds the outputs of another project" in err and str(project / "fluorocal.toml") in err
    assert _snapshot(out) == before
    other.unlink()


def test_evaluate_is_refused_another_project_s_output_folder(project, capsys):
    """``evaluate --out`` into a folder that another project published: refused before any work (found in review)."""
    out = project / "out"
    other = project / "other_eval.toml"
    text = (project / "fluorocal.toml").read_text()
    assert 'dir = "out"' in text
    other.write_text(text.replace('dir = "out"', 'dir = "out_other"'))  # its own [output] dir
    before = _snapshot(out)
    assert main(["--quiet", "evaluate", str(other), "--out", str(out)]) == 2
    assert "holds the outputs of another project" in capsys.readouterr().err
    assert _snapshot(out) == before
    other.unlink()


def test_publish_records_its_owner_and_refuses_another(tmp_path):
    from fluorocal.outputs import check_output_dir
    from fluorocal.stages.errors import InputError

    def write(folder):
        (folder / "a.txt").write_text("a")
        return [folder / "a.txt"]

    publish(tmp_path / "out", write, owner=tmp_path / "one.toml")
    assert check_output_dir(tmp_path / "out", keep_out=[], owner=tmp_path / "one.toml") == tmp_path / "out"
    with pytest.raises(InputError, match="another project"):
        check_output_dir(tmp_path / "out", keep_out=[], owner=tmp_path / "two.toml")


def test_a_record_nested_too_deep_is_read_as_none_never_a_traceback(tmp_path):
    """An output folder's record of 100 000 nested lists (RecursionError in the decoder) records nothing.

    As a folder written before sets were published: no owner to refuse, the next set published over it, the
    files the set does not replace kept (not a traceback before any work, nor a swap left half done).
    """
    from fluorocal.outputs import check_output_dir

    out = tmp_path / "out"
    out.mkdir()
    (out / MANIFEST).write_text("[" * 100_000 + "]" * 100_000)
    (out / "notes.txt").write_text("mine")
    assert check_output_dir(out, keep_out=[], owner=tmp_path / "one.toml") == out

    def write(folder):
        (folder / "a.txt").write_text("a")
        return [folder / "a.txt"]

    assert publish(out, write, owner=tmp_path / "one.toml") == [out / "a.txt"]
    assert {p.name: p.read_text() for p in out.iterdir() if p.name != MANIFEST} == {"a.txt": "a", "notes.txt": "mine"}
    assert json.loads((out / MANIFEST).read_text()) == {"entries": ["a.txt"], "project": "../one.toml"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing left beside it


def test_cache_clean_of_a_project_sharing_the_cache_keeps_the_first_s_entries(project):
    cache = ArtifactCache(project / ".fluorocal")
    before = {s: cache.keys(s) for s in ("detect", "centroid", "label", "learn")}
    assert all(before.values())
    other = project / "other.toml"
    text = (project / "fluorocal.toml").read_text().replace('dir = "out"', 'dir = "out_other"')
    assert "[detect]" not in text and "out_other" in text
    other.write_text(text + "\n[detect]\nmin_snr = 7.5\n")  # keys of its own: every entry of A is stale to it
    for argv in (["--quiet", "cache", "clean", "--stale", str(other)], ["--quiet", "cache", "clean", str(other)]):
        assert main(argv) == 0
        assert {s: cache.keys(s) for s in before} == before
    other.unlink()


def test_no_traceback_under_an_ascii_locale(project):
    """``LC_ALL=C`` without Python's UTF-8 mode, ASCII output: the run prints its table with escapes.

    It died writing report.md and printing its table (``UnicodeEncodeError`` on "Δ"). Every stage is
    cached: the run republishes the set.
    """
    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONIOENCODING": "ascii"}
    argv = [sys.executable, "-m", "fluorocal.cli", "run", str(project / "fluorocal.toml")]
    done = subprocess.run(argv, env=env, capture_output=True, timeout=900, check=False)
    assert done.returncode == 0, done.stderr.decode("ascii", "replace")
    assert b"Traceback" not in done.stderr
    assert b"max \\u0394 where supported" in done.stdout  # the table's header, Δ escaped
    assert "max Δ where supported" in (project / "out" / "report.md").read_text(encoding="utf-8")
