"""The outputs of a 3D bead phantom's calibration (:class:`~fluorocal.stages.learn.LearnResult`).

``calibration.json`` with ``field_<system>.npz`` (IOP, ROP, each exposure's pose, the learned field per
system), ``object_points.csv`` (the adjusted beads), ``observations.csv`` and ``report.md`` with its plots.
The grid plate's twin is :mod:`fluorocal.export_plate`; which one runs is the phantom kind's choice
(:mod:`fluorocal.kinds`).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from fluorocal.export_tables import fluorocal_version, write_object_points, write_observations
from fluorocal.figures import Figures
from fluorocal.outputs import inside, safe_name
from fluorocal.report import rms_px
from fluorocal.stages.io import atomic_write

log = logging.getLogger(__name__)


def export_beads(runner, result, obs, excluded, out_dir: Path, figures=None) -> list[Path]:
    """Write a bead phantom's calibration, its object points, observations and report into ``out_dir``.

    ``figures`` (:class:`~fluorocal.figures.Figures`) draws the report's figures (default: every one).
    """
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
    written += write_report(out_dir, runner, obs, result, cal, excluded, figures)
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
        "phantom_kind": runner.config.phantom.kind.name,
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
    """What ``iop_std_px`` and the fields' ``sigma_px`` of a calibration mean (docs/uncertainties.md).

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> print(uncertainty_note(SimpleNamespace(uncertainty=None))[:60])
    docs/uncertainties.md: iop_std_px is the adjustment's, condi
    """
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


def write_report(out_dir: Path, runner, obs, result, cal, excluded=(), figures=None) -> list[Path]:
    """``report.md`` and its plots: residuals before/after, the learned fields, convergence, per-frame RMS.

    ``figures`` (:class:`~fluorocal.figures.Figures`) draws them, or copies those a previous set made from
    the same content (default: draws every one).
    """
    from fluorocal import report

    figures = Figures() if figures is None else figures
    draw = figures.draw
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
        plots.append(draw(inside(out_dir, f"residuals_{file_name}.png"), report.residual_maps, panels, size))
        plots.append(
            draw(
                inside(out_dir, f"field_{file_name}.png"),
                report.field_map,
                field,
                f"learned correction Δ, system {name}",
            )
        )
        sigma_title = f"σ of the correction, system {name}"
        plots.append(draw(inside(out_dir, f"field_sigma_{file_name}.png"), report.field_sigma_map, field, sigma_title))
        labels, rms_b, rms_a = [], [], []
        for u in (u for u in runner.units if u.system == s):
            f = inl & (obs.exposure == u.exposure)
            if f.any():
                labels.append(u.path.stem)
                rms_b.append(rms_px(before[f]) if before is not None else np.nan)
                rms_a.append(rms_px(adj.residual_px[f]))
        path = inside(out_dir, f"frames_{file_name}.png")
        plots.append(draw(path, report.frame_rms, labels, np.array(rms_b), np.array(rms_a)))
    plots.append(draw(inside(out_dir, "convergence.png"), report.convergence, result.history))
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
    return plots + [path, figures.write_record(out_dir)]
