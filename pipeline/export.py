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
import time
from pathlib import Path

import numpy as np
from fluorocal.export_tables import fluorocal_version, write_object_points, write_observations
from fluorocal.outputs import check_output_dir, inside, publish, safe_name, sweep
from fluorocal.report import rms_px
from fluorocal.stages.io import OBSERVATIONS, atomic_write, columns_of, write_table

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
    return publish(target, write, owner=runner.config.path)


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


def calibration_from_result(runner, result):
    """The :class:`Calibration` of a learning result, with the statistics of the solve."""
    from fluorocal.calibration import Calibration, SystemCalibration

    adj = result.adjustment
    names = [s.name for s in runner.config.systems]
    sizes = [next(u.size_px for u in runner.units if u.system == s) for s in range(len(names))]
    for name, std in zip(names, result.iop_std_px):
        if not np.isfinite(std).all():  # written as null: say why
            bad = ", ".join(p for p, v in zip(("xp", "yp", "c"), std) if not np.isfinite(v))
            log.warning(
                "system %s: no finite uncertainty for %s (the data barely determine it); written as null", name, bad
            )
    systems = [
        SystemCalibration(
            name,
            tuple(sizes[s]),
            adj.iop_px[s],
            result.iop_std_px[s],
            adj.rop_q[s],
            adj.rop_source_mm[s],
            **_field_or_orientation(runner.config.systems[s], result.fields[s]),
        )
        for s, name in enumerate(names)
    ]
    exposures = {int(e): (q, t) for e, q, t in zip(adj.exposure, adj.q_cam_from_obj, adj.source_mm)}
    meta = {
        "fluorocal_version": fluorocal_version(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "config": str(runner.config.path),
        "scheme": result.scheme,
        "conventions": "docs/concepts.md#conventions: px with the top-left pixel centre at (0, 0), x right, y down; "
        "ideal = measured - Δ(measured); q (w, x, y, z) rotates object vectors into the camera frame",
        "uncertainty": uncertainty_note(result),
        "statistics": {
            "sigma0": float(adj.sigma0),
            "nu": float(adj.nu),
            "n_observations": int(len(adj.inlier)),
            "n_inliers": int(adj.inlier.sum()),
            "n_outliers": int((adj.used & ~adj.inlier).sum()),
            "n_unused": int((~adj.used).sum()),
            "rms_px_in_sample": rms_px(adj.residual_px[adj.inlier]),
            "iterations": len(result.history) - 1,
            "converged": bool(result.converged),
            "stop_reason": result.stop_reason,
            "wall_time_s": float(result.wall_time_s),
        },
    }
    return Calibration(systems, exposures, meta)


def uncertainty_note(result) -> str:
    """What ``iop_std_px`` and the fields' ``sigma_px`` of a calibration mean (docs/uncertainties.md)."""
    if result.uncertainty is not None:
        return (
            "docs/uncertainties.md: iop_px under the field gauge (the field has no least-squares principal-point "
            "shift, scaling or camera rotation at the training observations); iop_std_px and the fields' sigma_px "
            "over the joint problem (IOP, poses, points and field estimated together)"
        )
    return (
        "docs/uncertainties.md: iop_std_px is the adjustment's, conditional on the field (too small: a free "
        "field trades against the principal point and c); the fields' sigma_px the regression's own"
    )


def _field_or_orientation(system, field) -> dict:
    """A bead phantom's system is one orientation: named (with its angles) when the config's group names it."""
    from fluorocal.stages.orientation import OrientationField

    if len(system.orientations) != 1:
        return {"field": field}
    group = system.orientations[0]
    return {"orientations": (OrientationField(group.name, group.orbit_deg, group.tilt_deg, field),)}


def export_calibration(runner, out_dir: Path | None = None) -> list[Path]:
    """Write the calibration, its tables and its report into ``out_dir`` (default: the run's output folder)."""
    from fluorocal.gather import failed_frames, observations_from_labels

    out_dir = Path(runner.config.output_dir if out_dir is None else out_dir)
    result = runner.get("learn", None)
    labels = [runner.get("label", u) for u in range(len(runner.units))]
    obs = observations_from_labels(runner.units, labels, runner.config)
    excluded = failed_frames(runner.units, labels, runner.config)
    if excluded:
        log.warning("%d frame(s) excluded, labelling failed: %s", len(excluded), "; ".join(excluded))
    if not runner.config.phantom.kind.estimates_geometry:
        from fluorocal.export_plate import export_plate

        return export_plate(runner, result, obs, excluded, out_dir)
    adj = result.adjustment
    cal = calibration_from_result(runner, result)
    written = cal.save(inside(out_dir, "calibration.json"))

    write_object_points(inside(out_dir, "object_points.csv"), adj.bead_id, adj.xyz_mm, adj.xyz_std_mm)
    written.append(inside(out_dir, "object_points.csv"))
    write_observations(
        inside(out_dir, "observations.csv"),
        obs,
        files={(u.system, u.exposure): u.path.name for u in runner.units},
        corrections_px=result.corrections_px,
        residual_px=adj.residual_px,
        inlier=adj.inlier,
    )
    written.append(inside(out_dir, "observations.csv"))
    written += write_report(out_dir, runner, obs, result, cal, excluded)
    return written


def write_report(out_dir: Path, runner, obs, result, cal, excluded=()) -> list[Path]:
    """``report.md`` and its plots: residuals before/after, the learned fields, convergence, per-frame RMS."""
    from fluorocal import report

    adj = result.adjustment
    before = getattr(result, "initial_residual_px", None)
    lines = [
        "# fluorocal calibration report",
        "",
        f"Config: `{runner.config.path}`; scheme `{result.scheme}`; "
        f"made by `fluorocal run` (fluorocal {cal.meta['fluorocal_version']}).",
        "All figures are in-sample (the training frames) unless marked otherwise.",
        *([f"Excluded (labelling failed): {'; '.join(excluded)}."] if excluded else []),
        "",
        "| system | frames | observations | inliers | outliers | RMS before (px) | RMS after (px) "
        "| xp (px) | yp (px) | c (px) | max Δ where supported (px) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    plots = []
    for s, name in enumerate(obs.system_names):
        file_name = safe_name(name, what="system name")
        sel = obs.system == s
        inl = sel & adj.inlier
        size = cal.systems[name].image_size_px
        rms_before = rms_px(before[inl]) if before is not None else float("nan")
        n_frames = sum(1 for u in runner.units if u.system == s)
        iop, iop_sd = cal.systems[name].iop_px, cal.systems[name].iop_std_px
        field = result.fields[s]
        # nodes without data hold the prior's extrapolation, which can be large far outside the field of view
        max_delta = float(np.linalg.norm(field.delta_px, axis=-1)[field.support].max(initial=0.0))
        lines.append(
            f"| {name} | {n_frames} | {int(sel.sum())} | {int(inl.sum())} "
            f"| {int((sel & adj.used & ~adj.inlier).sum())} | {rms_before:.3f} | {rms_px(adj.residual_px[inl]):.3f} "
            f"| {iop[0]:.2f} ± {iop_sd[0]:.2f} | {iop[1]:.2f} ± {iop_sd[1]:.2f} | {iop[2]:.1f} ± {iop_sd[2]:.1f} "
            f"| {max_delta:.2f} |"
        )
        panels = ([("before: no correction", obs.xy_px[inl], before[inl])] if before is not None else []) + [
            ("after: calibrated", obs.xy_px[inl], adj.residual_px[inl])
        ]
        plots.append(report.residual_maps(inside(out_dir, f"residuals_{file_name}.png"), panels, size))
        plots.append(
            report.field_map(
                inside(out_dir, f"field_{file_name}.png"), result.fields[s], f"learned correction Δ, system {name}"
            )
        )
        plots.append(
            report.field_sigma_map(
                inside(out_dir, f"field_sigma_{file_name}.png"), result.fields[s], f"σ of the correction, system {name}"
            )
        )
        labels, rms_b, rms_a = [], [], []
        for u in (u for u in runner.units if u.system == s):
            f = inl & (obs.exposure == u.exposure)
            if f.any():
                labels.append(u.path.stem)
                rms_b.append(rms_px(before[f]) if before is not None else np.nan)
                rms_a.append(rms_px(adj.residual_px[f]))
        plots.append(
            report.frame_rms(inside(out_dir, f"frames_{file_name}.png"), labels, np.array(rms_b), np.array(rms_a))
        )
    plots.append(report.convergence(inside(out_dir, "convergence.png"), result.history))
    st = cal.meta["statistics"]
    lines += [
        "",
        f"Adjustment: σ0 = {st['sigma0']:.3f}, ν = {st['nu']:.1f}, {st['n_outliers']} outlier(s) flagged, "
        f"{st['n_unused']} observation(s) not estimable; {st['iterations']} iteration(s) of the alternation, "
        f"{'converged' if st['converged'] else 'not converged'} ({st['stop_reason']}), {st['wall_time_s']:.1f} s.",
        "",
        f"IOP ± σ and the field's σ: {cal.meta.get('uncertainty', 'see docs/uncertainties.md')}.",
        "",
    ]
    lines += [f"![{p.stem}]({p.name})" for p in plots]
    path = inside(out_dir, "report.md")
    atomic_write(path, lambda tmp: Path(tmp).write_text("\n".join(lines) + "\n", encoding="utf-8"))
    return plots + [path]
