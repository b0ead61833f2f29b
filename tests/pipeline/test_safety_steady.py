"""A frame file that changes while it is read is refused for the run, and nothing of it is cached (issue 28).

A frame replaced while detection ran (and restored before the next run) left the other file's
detections cached under the original's key: the next run served another frame's beads. The change is
simulated by a reader that rewrites the file as it reads it (tests/pipeline/toy.py frames: constant
values 100, 200, 300).
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal import graph
from fluorocal.cache import ArtifactCache, file_sha256
from fluorocal.config import load_config
from fluorocal.run import Runner, _read_file_frames
from fluorocal.stages import io
from fluorocal.stages.detect import DetectParams, estimate_appearance
from fluorocal.stages.errors import InputError
from fluorocal.stages.io import write_still

from tests.pipeline.toy import CALLS, make_project, toy_stages


def _runner(cfg):
    config = load_config(cfg, stage_params_allowed={s.name: s.params_cls for s in toy_stages()})
    return Runner(config, toy_stages(), ArtifactCache(config.cache_dir), progress=False)


@pytest.mark.parametrize("when", ["during", "before"])
def test_a_frame_replaced_while_the_run_reads_it_is_refused_and_not_cached(tmp_path, monkeypatch, when):
    CALLS.clear()
    _read_file_frames.cache_clear()
    cfg = make_project(tmp_path / "project")
    victim = tmp_path / "project" / "frames" / "f1.tif"
    original = victim.read_bytes()
    runner = _runner(cfg)  # planned: f1.tif's key is the hash of its 200s
    read = io.read_frames

    def replace(path):
        write_still(path, np.full((8, 10), 900, np.uint16))  # another frame's content

    def replacing_reader(path, indices=None):
        frames = read(path, indices)
        if path.name == victim.name and when == "during":
            replace(path)  # the replacement lands while the reader decodes the file
        return frames

    monkeypatch.setattr(io, "read_frames", replacing_reader)
    if when == "before":
        replace(victim)  # replaced between the plan and the read
    with pytest.raises(InputError, match=rf"f1.tif: changed {'while' if when == 'during' else 'before'} fluorocal"):
        runner.run()
    victim_key = runner.keys[("mean", 1)]
    assert not runner.cache.has("mean", victim_key)  # nothing read from it was cached under its key
    monkeypatch.setattr(io, "read_frames", read)
    victim.write_bytes(original)  # restored before the next run
    _read_file_frames.cache_clear()
    again = _runner(cfg)
    again.run()
    assert again.keys[("mean", 1)] == victim_key
    assert float(again.get("mean", 1).value[0]) == 200.0  # f1.tif's own mean, not the replacement's 900


def test_the_bead_appearance_estimate_reads_only_a_file_that_holds_still(tmp_path, monkeypatch):
    # the appearance of a system's first frames goes into every frame's detect key: read like every other frame
    graph._system_appearance.cache_clear()
    path = tmp_path / "f.tif"
    frame = np.full((64, 64), 3000, np.uint16)
    frame[20:30, 20:30] = 500  # a dark bead-like blob
    write_still(path, frame)
    planned = file_sha256(path)
    expected = estimate_appearance(io.read_frames(path), DetectParams())
    assert graph._system_appearance(((path, planned, 0),), DetectParams()) == expected
    graph._system_appearance.cache_clear()
    write_still(path, np.full((64, 64), 900, np.uint16))  # replaced after the run was planned
    with pytest.raises(InputError, match=r"f.tif: changed before fluorocal read it"):
        graph._system_appearance(((path, planned, 0),), DetectParams())
    write_still(path, frame)
    read = io.read_frames

    def replacing_reader(path, indices=None):
        frames = read(path, indices)
        write_still(path, np.full((64, 64), 900, np.uint16))  # lands while the reader decodes the file
        return frames

    monkeypatch.setattr(io, "read_frames", replacing_reader)
    with pytest.raises(InputError, match=r"f.tif: changed while fluorocal read it"):
        graph._system_appearance(((path, planned, 0),), DetectParams())
