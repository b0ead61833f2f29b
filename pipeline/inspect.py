"""Debug overlays for ``fluorocal inspect CONFIG STAGE --frame N``."""

from __future__ import annotations

from pathlib import Path

from fluorocal.outputs import inside, safe_name
from fluorocal.stages.errors import InputError
from fluorocal.stages.io import write_png


def write_stage_overlay(runner, stage: str, frame: int) -> Path:
    """Draw the overlay of a per-frame stage for frame ``frame`` into ``<output>/overlays/`` and return its path.

    Computes (and caches) what the overlay needs if it is not cached yet.
    """
    from fluorocal.overlay import render_label_overlay, render_overlay

    radiograph = runner.get("frame", frame)
    if stage == "detect":
        image = render_overlay(radiograph, runner.get("detect", frame))
    elif stage == "centroid":
        image = render_overlay(radiograph, runner.get("detect", frame), runner.get("centroid", frame))
    elif stage == "label":
        image = render_label_overlay(radiograph, runner.get("centroid", frame), runner.get("label", frame))
    else:
        raise InputError(f"stage {stage!r} has no per-frame overlay; use detect, centroid or label")
    unit = runner.units[frame]
    system = safe_name(runner.config.systems[unit.system].name, what="system name")
    path = inside(inside(runner.config.output_dir, "overlays"), f"{safe_name(stage)}_{system}_{unit.exposure:04d}.png")
    write_png(path, image)
    return path


def stage_summary(runner, stage: str) -> str:
    """One line for a per-frame ``stage`` over every cached frame, system by system ("" when none is cached).

    (A cache entry's own summary is its frame's alone.)
    """
    by_system: dict[str, list] = {}
    for u, unit in enumerate(runner.units):
        artifact = runner.cache.load(stage, runner.keys[(stage, u)], warn=False)
        if artifact is not None:
            by_system.setdefault(runner.config.systems[unit.system].name, []).append(artifact)
    return "; ".join(f"system {name}: {_totals(artifacts)}" for name, artifacts in by_system.items())


def _totals(artifacts: list) -> str:
    """The counts of one system's artifacts of a per-frame stage, summed over its frames."""
    from fluorocal.gather import labelling_line
    from fluorocal.stages.centroid import Centroids
    from fluorocal.stages.detect import BeadCandidates
    from fluorocal.stages.label import Labels

    n = len(artifacts)
    if isinstance(artifacts[0], BeadCandidates):
        accepted, found = sum(a.n_accepted for a in artifacts), sum(len(a) for a in artifacts)
        return f"{n} frames, {accepted} accepted of {found} candidates"
    if isinstance(artifacts[0], Centroids):
        fitted = sum(int(a.ok.sum()) for a in artifacts)
        return f"{n} frames, {fitted} fitted, {sum(len(a) for a in artifacts) - fitted} failed"
    if isinstance(artifacts[0], Labels):
        return f"{labelling_line(artifacts)} labelled, {sum(a.n_labelled for a in artifacts)} detections with an id"
    return f"{n} frames"
