"""Outputs of ``fluorocal run`` in the project's output directory.

- ``<stage>.csv`` for each per-frame stage that has a table (today: ``label.csv``,
  system, file, exposure, id, x, y, σx, σy, ρ), over all frames;
- ``calibration.json`` with ``field_<system>.npz`` (:mod:`fluorocal.calibration`);
- ``object_points.csv`` (id,x,y,z,sx,sy,sz mm);
- ``observations.csv`` (system, file, exposure, id, x, y, σx, σy, ρ, the
  correction Δ, the residuals and the inlier flag);
- ``report.md`` with its PNG plots.

The tables follow the schemas :data:`fluorocal.stages.io.OBSERVATIONS` and
:data:`fluorocal.stages.io.OBJECT_POINTS`, so ``fluorocal adjust`` reads
``observations.csv`` and ``label.csv`` back as they are.

The outputs are published as a set (:func:`fluorocal.outputs.publish`):
written into a staging folder beside the output folder and swapped in, so a
reader sees the previous run's complete set or this run's, never a mixture,
and an interrupted run leaves the previous set. Every file name is built from
checked names (:func:`fluorocal.outputs.safe_name`) inside its folder
(:func:`fluorocal.outputs.inside`).
"""

from __future__ import annotations

import logging
from pathlib import Path

from fluorocal.figures import Figures
from fluorocal.outputs import check_output_dir, inside, publish, safe_name, sweep
from fluorocal.stages.io import OBSERVATIONS, columns_of, write_table

log = logging.getLogger(__name__)


def check_outputs(config, out_dir=None) -> Path:
    """Check, before any work, that the run's outputs can be written; return the output folder, resolved.

    ``out_dir`` is the folder (default: the config's ``[output] dir``; ``fluorocal evaluate`` gives its own).

    The system names must be safe file names (:func:`~fluorocal.outputs.safe_name`), the output
    folder a folder (or absent) that holds none of the project's inputs or cache, with a writable
    parent. What an interrupted run left beside it is swept (:func:`~fluorocal.outputs.sweep`).

    Raises
    ------
    InputError
        Naming the system or the path at fault.
    """
    for system in config.systems:
        safe_name(system.name, what="system name")
    keep_out = [("the config", config.path), ("the cache", config.cache_dir)]
    if out_dir is not None:  # another command's outputs (fluorocal evaluate) never go over the run's
        keep_out.append(("the project's outputs ([output] dir)", config.output_dir))
    if getattr(config.phantom, "file", None) is not None:
        keep_out.append(("the phantom", config.phantom.file))
    for system in config.systems:
        keep_out += [(f"frame {f} of system {system.name}", f) for f in system.frames]
        if system.seeds is not None:
            keep_out.append((f"the seeds of system {system.name}", system.seeds))
    # the run's folder or another command's (evaluate): refused if another project published there
    out_dir = check_output_dir(config.output_dir if out_dir is None else out_dir, keep_out=keep_out, owner=config.path)
    sweep(out_dir)
    return out_dir


def export_outputs(runner) -> list[Path]:
    """Publish every output the run's stages support as one set; return the paths written.

    A run stopped before ``learn`` (``--until``) never replaces the published set (its calibration, fields
    and report): it publishes its tables as their own set in :func:`partial_dir`, inside the output folder,
    where later runs carry them over. With nothing to write, the output folder is left as it is.
    """
    partial = "learn" not in runner.by_name

    def write(staging: Path) -> list[Path]:
        written = _stage_tables(runner, staging)
        if not partial:
            written += export_calibration(runner, staging)
        return written

    target = partial_dir(runner) if partial else runner.config.output_dir
    written = publish(target, write, owner=runner.config.path)
    memo = getattr(runner, "code_memo", None)
    if memo is not None:  # what the figures' code digests added to it (the run saved it before)
        memo.save()
    return written


def partial_dir(runner) -> Path:
    """Where a run stopped early publishes its tables: ``<output dir>/until-<last stage>``."""
    last = safe_name(runner.stages[-1].name, what="stage name") if runner.stages else "nothing"
    return inside(runner.config.output_dir, f"until-{last}")


def _stage_tables(runner, out_dir: Path | None = None) -> list[Path]:
    out_dir = Path(runner.config.output_dir if out_dir is None else out_dir)
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
            header = ["system", "file", "exposure"] + list(h)
            name = runner.config.systems[unit.system].name
            rows.extend([name, unit.path.name, unit.exposure, *row] for row in r)
        if header is not None:
            path = inside(out_dir, f"{safe_name(stage.name, what='stage name')}.csv")
            write_table(path, OBSERVATIONS, columns_of(header, rows))
            written.append(path)
    return written


def export_calibration(runner, out_dir: Path | None = None) -> list[Path]:
    """Write the calibration, its tables and its report into ``out_dir`` (default: the run's output folder).

    What they are is the phantom kind's (:func:`fluorocal.kinds.part_of`): :mod:`fluorocal.export_beads`,
    :mod:`fluorocal.export_plate`.
    """
    from fluorocal.gather import failed_frames, observations_from_labels
    from fluorocal.kinds import part_of

    out_dir = Path(runner.config.output_dir if out_dir is None else out_dir)
    figures = Figures(runner.config.output_dir, getattr(runner, "code_memo", None))  # the published set's
    result = runner.get("learn", None)
    labels = [runner.get("label", u) for u in range(len(runner.units))]
    obs = observations_from_labels(runner.units, labels, runner.config)
    excluded = failed_frames(runner.units, labels, runner.config)
    if excluded:
        log.warning("%d frame(s) excluded, labelling failed: %s", len(excluded), "; ".join(excluded))
    return part_of(runner.config.phantom.kind).export(runner, result, obs, excluded, out_dir, figures)
