"""The bead appearance (polarity, diameter range) of `fluorocal run`, estimated once per system."""

from __future__ import annotations

import pytest
from fluorocal.cache import ArtifactCache, artifact_key
from fluorocal.config import load_config
from fluorocal.graph import APPEARANCE_FRAMES, default_stages, stage_params_classes
from fluorocal.run import Runner
from fluorocal.stages.detect import DetectParams, estimate_appearance
from fluorocal.stages.io import read_frames

from tests.conftest import copy_project


@pytest.fixture(scope="module")
def project(tmp_path_factory, calibrated_project):
    return copy_project(calibrated_project, tmp_path_factory.mktemp("appearance") / "project")


def _runner(cfg):
    config = load_config(cfg, stage_params_allowed=stage_params_classes())
    return Runner(config, default_stages(), ArtifactCache(config.cache_dir), progress=False)


def _detect_params(runner):
    return {u: runner.params[("detect", u)][0] for u in range(len(runner.units))}


def test_every_frame_of_a_system_gets_its_first_frames_estimate(project):
    runner = _runner(project / "fluorocal.toml")
    params = _detect_params(runner)
    for s in {u.system for u in runner.units}:
        frames = sorted((u for u in runner.units if u.system == s), key=lambda u: u.exposure)
        expected = estimate_appearance(
            [read_frames(u.path)[u.index] for u in frames[:APPEARANCE_FRAMES]], DetectParams()
        )
        assert expected.polarity == "dark" and expected.max_diameter_px > 0  # resolved: the simulator's steel beads
        for unit in frames:
            assert params[runner.units.index(unit)] == expected


def test_the_estimate_keys_the_same_cached_entries_as_the_values_given(project):
    runner = _runner(project / "fluorocal.toml")
    keys = {u: runner.keys[("detect", u)] for u in range(len(runner.units))}
    # deterministic: planning again (another process, a pool worker) gives the same keys, and the entries the
    # session's run stored under them are found
    assert {u: _runner(project / "fluorocal.toml").keys[("detect", u)] for u in keys} == keys
    assert all(runner.cache.verify("detect", k) for k in keys.values())
    # the values given explicitly (as a [detect] section would give them) make the very same key: the estimate
    # is only those values, so a frame's entry is the one a run with the values given computes and stores
    for u, p in _detect_params(runner).items():
        given = DetectParams(polarity=p.polarity, min_diameter_px=p.min_diameter_px, max_diameter_px=p.max_diameter_px)
        code = runner.codes["detect"]
        assert artifact_key("detect", code, {"params": given}, [runner.units[u].key]) == keys[u]
