"""`fluorocal run` labels a system's frames as a sequence: a frame whose markers are hidden follows its neighbour."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from fluorocal.cache import ArtifactCache
from fluorocal.cli import main
from fluorocal.cmd_simulate import write_dataset
from fluorocal.config import load_config
from fluorocal.graph import default_stages, stage_params_classes
from fluorocal.run import Runner, stage_params
from fluorocal.stages import centroid
from fluorocal.stages.kinds.labelling import label_beads
from fluorocal.stages.simulate import SimulateParams, simulate

PARAMS = SimulateParams(n_frames=8, n_systems=1, image_size_px=512, seed=3)
HIDDEN = "frame_001.tif"  # 15 degrees of turntable after frame_000 (8 exposures over 120 degrees of turns)


def test_a_frame_with_its_markers_hidden_is_labelled_from_its_neighbour(tmp_path, monkeypatch):
    data = simulate(PARAMS)
    write_dataset(data, tmp_path)
    truth = data.truth.frames[0][1]
    markers = np.isin(truth.ids, data.phantom.ids[data.phantom.role == "marker"])
    real_centroid_beads = centroid.centroid_beads

    def centroid_without_markers(radiograph, candidates, params):
        """The centroid stage, with every detection of a marker of the hidden frame dropped (flagged not usable)."""
        c = real_centroid_beads(radiograph, candidates, params)
        if Path(c.source).name != HIDDEN or not len(c.xy_px):
            return c
        d = np.linalg.norm(c.xy_px[:, None, :] - truth.outline_xy_px[markers][None, :, :], axis=-1)
        hidden = d.min(axis=1) < 0.5 * truth.diameter_px[markers].max()
        return replace(c, ok=c.ok & ~hidden, reason=np.where(hidden, "shape", c.reason))

    monkeypatch.setattr(centroid, "centroid_beads", centroid_without_markers)
    cfg = tmp_path / "fluorocal.toml"
    assert main(["--quiet", "run", str(cfg), "--until", "label"]) == 0

    config = load_config(cfg, stage_params_allowed=stage_params_classes())
    stages = default_stages()
    runner = Runner(config, stages, ArtifactCache(config.cache_dir), until="label", progress=False)
    assert runner.run().total_computed == 0  # what `fluorocal run` stored, read back
    unit = next(i for i, u in enumerate(runner.units) if u.path.name == HIDDEN)
    c = runner.get("centroid", unit)
    near_marker = np.linalg.norm(c.xy_px[:, None] - truth.outline_xy_px[markers][None], axis=-1).min(axis=1) < 2.0
    assert markers.sum() >= 3 and not (c.ok & near_marker).any(), "a marker is still detected"
    lab = runner.get("label", unit)
    assert lab.ok and lab.pose_source == "prior", lab.summary()
    # no mislabel: each labelled detection lies on its bead (a wrong id is off by a bead pitch, > 10 px)
    where = dict(zip(truth.ids.tolist(), truth.outline_xy_px))
    off = np.linalg.norm(lab.xy_px - np.array([where[i] for i in lab.bead_id.tolist()]), axis=1)
    assert off.max() < 2.0 and lab.n_labelled >= 0.8 * int(c.ok.sum())
    # alone, the frame cannot be labelled: it is the neighbour's pose that labels it
    label = next(s for s in stages if s.name == "label")
    alone = label_beads(c, runner.get("phantom", None), stage_params(label, config, None, [runner.units[unit]]))
    assert not alone.ok and alone.pose_source == "markers", alone.summary()
