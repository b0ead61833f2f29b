"""Config paths and numbers (issue 28): globs anchored at the project's own (escaped) path, numbers in range."""

from __future__ import annotations

import pytest
from fluorocal.cli import main
from fluorocal.compute import limit_threads
from fluorocal.config import ConfigError, load_config
from fluorocal.graph import stage_params_classes
from fluorocal.stages.errors import InputError

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


DIGITS = "a number of thousands of digits"
C_INT = "expected an integer in 0..2147483647"
#: case -> (text replaced, or "" to append; the new text; what the error says)
NUMBERS = {
    "5000-digit float key": ("pixel_pitch = 0.25", "pixel_pitch = " + "9" * 5000, rf"key 'pixel_pitch': {DIGITS}"),
    "5000-digit stage int": ("", "[centroid]\nn_arcs = " + "9" * 5000, rf"key 'n_arcs': {DIGITS}"),
    "n_arcs 10**21": ("", "[centroid]\nn_arcs = " + str(10**21), rf"\[centroid\] key 'n_arcs': {C_INT}"),
    "negative seed": ("", "[learn]\nseed = -1", r"\[learn\] key 'seed': expected an integer in 0..2147483647; got -1"),
    "float 1e400": ("", "[detect]\nmin_snr = 1e400", r"\[detect\] key 'min_snr': expected a finite number"),
    "float -inf": ("", "[detect]\nmin_snr = -inf", r"\[detect\] key 'min_snr': expected a finite number"),
    "threads 10**20": ("", "[compute]\nthreads = " + str(10**20), r"\[compute\] key 'threads': .* at most 4096"),
    "jobs 10**17": ("", "[compute]\njobs = " + str(10**17), r"\[compute\] key 'jobs': .* at most 4096"),
}


@pytest.mark.parametrize("case", list(NUMBERS))
def test_every_number_of_the_config_is_range_checked_naming_the_key(tmp_path, capsys, case):
    old, new, message = NUMBERS[case]
    cfg = make_project(tmp_path / "p")
    text = cfg.read_text()
    cfg.write_text(text.replace(old, new) if old else text + "\n" + new + "\n")
    with pytest.raises(ConfigError, match=message):
        load_config(cfg, stage_params_allowed=stage_params_classes())
    assert main(["--quiet", "run", str(cfg)]) == 2  # one line, no traceback, nothing written
    err = capsys.readouterr().err
    assert err.startswith("fluorocal: error: ") and len(err.splitlines()) == 1 and len(err) < 400
    assert not (tmp_path / "p" / "out").exists() and not (tmp_path / "p" / ".fluorocal").exists()


@pytest.mark.parametrize("value", ["99999999999999999999", "4097", "-1", "1e3"])
def test_fluorocal_threads_out_of_range_is_refused_naming_the_variable(monkeypatch, value):
    monkeypatch.setenv("FLUOROCAL_THREADS", value)
    with pytest.raises(InputError, match=r"environment variable FLUOROCAL_THREADS: expected a positive integer"):
        limit_threads()


def test_numbers_in_range_still_load(tmp_path):
    cfg = make_project(tmp_path / "p")
    cfg.write_text(cfg.read_text() + "\n[learn]\nseed = 0\n\n[compute]\nthreads = 4096\n")
    config = load_config(cfg, stage_params_allowed=stage_params_classes())
    assert config.stage_params["learn"]["seed"] == 0 and config.compute.threads == 4096
