"""Config paths and numbers (issue 28): globs anchored at the project's own (escaped) path."""

from __future__ import annotations

from fluorocal.config import load_config

from tests.pipeline.toy import make_project


def test_a_project_path_holding_glob_characters_reads_its_own_frames(tmp_path):
    """A project in ``scan[1]/`` beside ``scan1/``: unescaped, ``scan[1]/frames/*.tif`` matched ``scan1/``'s."""
    make_project(tmp_path / "scan1", n_frames=2)
    cfg = make_project(tmp_path / "scan[1]", n_frames=3)
    frames = load_config(cfg).systems[0].frames
    assert frames == tuple(tmp_path / "scan[1]" / "frames" / f"f{i}.tif" for i in range(3))


def test_the_user_s_own_pattern_still_globs(tmp_path):
    cfg = make_project(tmp_path / "p*q", n_frames=3)
    cfg.write_text(cfg.read_text().replace("frames/*.tif", "frames/f[02].tif"))
    assert [f.name for f in load_config(cfg).systems[0].frames] == ["f0.tif", "f2.tif"]
