"""Outputs of ``fluorocal run`` in the project's output directory.

Every file is written atomically (temporary name, then rename), so an
interrupted run never leaves a half-written output.
"""

from __future__ import annotations

from pathlib import Path

from stages.io import write_csv


def export_outputs(runner) -> list[Path]:
    """Write each per-frame stage's table over all frames as ``<stage>.csv``; return the paths."""
    out_dir = Path(runner.config.output_dir)
    written = []
    for stage in runner.stages:
        if not stage.per_frame:
            continue
        header, rows = None, []
        for u, unit in enumerate(runner.units):
            artifact = runner.get(stage.name, u)
            if not hasattr(artifact, "to_table"):
                break
            h, r = artifact.to_table()
            header = ["system", "file", "frame"] + list(h)
            name = runner.config.systems[unit.system].name
            rows.extend([name, unit.path.name, unit.exposure, *row] for row in r)
        if header is not None:
            path = out_dir / f"{stage.name}.csv"
            write_csv(path, header, rows)
            written.append(path)
    return written
