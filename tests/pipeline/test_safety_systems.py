"""System B given system A's frames, or a system given a copy of its own frame, is refused before any work (issue 28).

Not at learn, where the adjustment's normal equations turn singular, or not, by rounding.
"""

from __future__ import annotations

import shutil

import pytest
from fluorocal.config import ConfigError, load_config
from fluorocal.stages.errors import InputError
from fluorocal.units import frame_units

from tests.pipeline.toy import make_two_system_project


def test_system_b_listing_a_s_frame_files_is_refused_at_load(tmp_path):
    cfg = make_two_system_project(tmp_path / "p")
    cfg.write_text(cfg.read_text().replace('frames = "frames/B/*.tif"', 'frames = "frames/A/*.tif"'))
    with pytest.raises(
        ConfigError, match=r"\[\[systems\]\] #2 key 'frames': system B lists .*frames/A/f0.tif and 2 more"
    ):
        load_config(cfg)


def test_system_b_given_copies_of_a_s_frames_is_refused_before_any_stage(tmp_path):
    root = tmp_path / "p"
    cfg = make_two_system_project(root)
    shutil.copy(root / "frames" / "A" / "f1.tif", root / "frames" / "B" / "f1.tif")  # one copy among B's own
    with pytest.raises(InputError, match=r"frames/B/f1.tif: holds a frame of system A; give each system its own"):
        frame_units(load_config(cfg))


def test_a_frame_file_copied_within_a_system_is_refused_naming_both(tmp_path):
    root = tmp_path / "p"
    cfg = make_two_system_project(root)
    shutil.copy(root / "frames" / "A" / "f0.tif", root / "frames" / "A" / "f2.tif")
    with pytest.raises(InputError, match=r"frames/A/f2.tif: the same content as .*frames/A/f0.tif \(a copied file\?\)"):
        frame_units(load_config(cfg))


def test_systems_with_frames_of_their_own_load(tmp_path):
    units = frame_units(load_config(make_two_system_project(tmp_path / "p")))
    assert [u.system for u in units] == [0, 0, 0, 1, 1, 1]
