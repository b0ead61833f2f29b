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
