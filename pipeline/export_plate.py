"""Outputs of ``fluorocal run`` for a grid plate: the calibration with a field per orientation, the plate's layout.

Beside :mod:`fluorocal.export` (which writes a bead phantom's): ``calibration.json`` holds, per system,
one field per C-arm orientation and a nominal interior orientation (a plate fixes none; its standard
deviations are null); ``object_points.csv`` is the plate's self-calibrated layout (``z = 0``, the
holes' estimated positions and their standard deviations, mm); ``observations.csv`` and ``report.md``
as for a bead phantom, the report with the plate's error map and how the field changes with orientation.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from fluorocal.outputs import inside, safe_name
from fluorocal.report import rms_px
from fluorocal.stages.io import atomic_write

#: what calibration.json says of a plate's interior orientation
IOP_NOTE = (
    "not estimated: a grid plate on the intensifier fixes no interior orientation; "
    "iop_px is the nominal one from [[systems]] source_image_distance and pixel_pitch"
)


def plate_calibration(runner, result):
    """The :class:`~fluorocal.calibration.Calibration` of a grid plate's :class:`PlateCalibration`."""
    from fluorocal.calibration import Calibration, SystemCalibration
    from fluorocal.export_tables import fluorocal_version
    from fluorocal.stages.geometry import iop_guess
    from fluorocal.stages.orientation import OrientationField

    systems = []
    for s, config in enumerate(runner.config.systems):
        size = next(u.size_px for u in runner.units if u.system == s)
        orientations = tuple(
            OrientationField(name, *_angles(result.orientation_angles_deg[o]), result.fields[o])
            for o, name in enumerate(result.orientation_names)
            if result.orientation_system[o] == s
        )
        iop = np.asarray(iop_guess(size, config.source_image_distance_mm, config.pixel_pitch_mm), float)
        systems.append(
            SystemCalibration(
                config.name,
                tuple(size),
                iop,
                np.full(3, np.nan),
                np.array([1.0, 0, 0, 0]),
                np.zeros(3),
                orientations=orientations,
            )
        )
    inl = result.inlier
    meta = {
        "fluorocal_version": fluorocal_version(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "config": str(runner.config.path),
        "scheme": result.scheme,
        "phantom_kind": runner.config.phantom.kind.name,
        "interior_orientation": IOP_NOTE,
        "geometry_estimated": False,
        "statistics": {
            "n_observations": int(len(inl)),
            "n_inliers": int(inl.sum()),
            "n_outliers": int((~inl).sum()),
            "rms_px_before": rms_px(result.initial_residual_px[inl]),
            "rms_px_in_sample": rms_px(result.residual_px[inl]),
            "plate_holes_estimated": int(result.plate_estimated.sum()),
            "plate_error_rms_mm": _rms_mm(result.plate_error_mm[result.plate_estimated]),
            "iterations": int(result.iterations),
            "converged": bool(result.converged),
            "stop_reason": result.stop_reason,
            "wall_time_s": float(result.wall_time_s),
        },
    }
    return Calibration(systems, {}, meta)


def _angles(pair) -> tuple:
    return (None, None) if not np.all(np.isfinite(pair)) else (float(pair[0]), float(pair[1]))


def _rms_mm(error_mm: np.ndarray) -> float:
    return float(np.sqrt(np.mean(error_mm**2))) if len(error_mm) else 0.0


def export_plate(runner, result, obs, excluded, out_dir: Path, figures=None) -> list[Path]:
    """Write a grid plate's calibration, layout, observations and report into ``out_dir``.

    ``figures`` (:class:`~fluorocal.figures.Figures`) draws the report's figures (default: every one).
    """
    from fluorocal.export_tables import write_object_points, write_observations

    cal = plate_calibration(runner, result)
    written = cal.save(inside(out_dir, "calibration.json"))
    layout = np.column_stack([result.nominal_mm + result.plate_error_mm, np.zeros(len(result.hole_id))])
    std = np.column_stack([result.plate_error_std_mm, result.plate_error_std_mm, np.zeros(len(result.hole_id))])
    write_object_points(inside(out_dir, "object_points.csv"), result.hole_id, layout, std)
    written.append(inside(out_dir, "object_points.csv"))
    corrections = obs.xy_px - _corrected(result, obs)
    write_observations(
        inside(out_dir, "observations.csv"),
        obs,
        files={(u.system, u.exposure): u.path.name for u in runner.units},
        corrections_px=corrections,
        residual_px=result.residual_px,
        inlier=result.inlier,
    )
    written.append(inside(out_dir, "observations.csv"))
    return written + write_plate_report(out_dir, runner, obs, result, cal, excluded, figures)


def _corrected(result, obs) -> np.ndarray:
    """Each observation corrected by its frame's orientation's field."""
    of_obs = _orientation_of_obs(result, obs)
    out = obs.xy_px.copy()
    for o in np.unique(of_obs):
        sel = of_obs == o
        out[sel] = result.fields[o].undistort_points(obs.xy_px[sel])
    return out


def write_plate_report(out_dir: Path, runner, obs, result, cal, excluded=(), figures=None) -> list[Path]:
    """``report.md`` of a grid plate: RMS per orientation, fields, the plate's errors, the change with orientation.

    ``figures`` as for :func:`export_plate`.
    """
    from fluorocal import report
    from fluorocal.figures import Figures
    from fluorocal.orientations import orientation_report

    figures = Figures() if figures is None else figures

    inl = result.inlier
    lines = [
        "# fluorocal calibration report: grid plate",
        "",
        f"Config: `{runner.config.path}`; made by `fluorocal run` (fluorocal {cal.meta['fluorocal_version']}).",
        "All figures are in-sample (the training frames), px per component, unless marked otherwise. "
        "The interior orientation is " + IOP_NOTE + ".",
        *([f"Excluded (labelling failed): {'; '.join(excluded)}."] if excluded else []),
        "",
        *_plate_lines(result, runner.config.phantom.pitch_mm),
        "",
        *_smoothness_lines(result),
        "",
        "| system | orientation | orbit (deg) | tilt (deg) | frames | holes | outliers | RMS before (px) "
        "| RMS after (px) | max Δ where supported (px) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    of_obs = _orientation_of_obs(result, obs)
    plots, embedded_below = [], []  # the orientation plots are embedded with their own table
    for o, name in enumerate(result.orientation_names):
        sel = of_obs == o
        system = result.system_names[result.orientation_system[o]]
        field = result.fields[o]
        max_delta = float(np.linalg.norm(field.delta_px, axis=-1)[field.support].max(initial=0.0))
        orbit, tilt = (f"{a:g}" if np.isfinite(a) else "-" for a in result.orientation_angles_deg[o])
        lines.append(
            f"| {system} | {name} | {orbit} | {tilt} | {int((result.frame_orientation == o).sum())} "
            f"| {int(sel.sum())} | {int((sel & ~inl).sum())} | {rms_px(result.initial_residual_px[sel & inl]):.3f} "
            f"| {rms_px(result.residual_px[sel & inl]):.3f} | {max_delta:.2f} |"
        )
        stem = f"{safe_name(system, what='system name')}_{safe_name(name, what='orientation name')}"
        plots.append(
            figures.draw(
                inside(out_dir, f"field_{stem}.png"), report.field_map, field, f"correction Δ, {system} {name}"
            )
        )
    for s, system in enumerate(result.system_names):
        sel = (obs.system == s) & inl
        size = cal.systems[system].image_size_px
        panels = [
            ("before: homography of the nominal plate", obs.xy_px[sel], result.initial_residual_px[sel]),
            ("after: fields and plate errors", obs.xy_px[sel], result.residual_px[sel]),
        ]
        name = safe_name(system, what="system name")
        plots.append(figures.draw(inside(out_dir, f"residuals_{name}.png"), report.residual_maps, panels, size))
        if result.plate_estimated[result.hole_system == s].any():
            pitch_mm = runner.config.phantom.pitch_mm
            plots.append(figures.draw(inside(out_dir, f"plate_{name}.png"), plate_map, result, s, pitch_mm))
        change_plots, change_lines = orientation_report(out_dir, system, cal.systems[system].orientations)
        embedded_below += change_plots
        lines += ["", *change_lines]
    lines += ["", *(f"![{p.stem}]({p.name})" for p in plots)]
    path = inside(out_dir, "report.md")
    atomic_write(path, lambda tmp: Path(tmp).write_text("\n".join(lines) + "\n", encoding="utf-8"))
    return plots + embedded_below + [path, figures.write_record(out_dir)]


def _orientation_of_obs(result, obs) -> np.ndarray:
    orientation = {
        (int(s), int(e)): int(o)
        for s, e, o in zip(result.frame_system, result.frame_exposure, result.frame_orientation)
    }
    return np.array([orientation[(s, e)] for s, e in zip(obs.system.tolist(), obs.exposure.tolist())], np.int64)


def _smoothness_lines(result) -> list[str]:
    lines = []
    for s, name in enumerate(result.system_names):
        line = (
            f"System {name}: the field common to its orientations has a difference prior of order "
            f"{result.smoothness_order[s, 0]}, τ = {result.smoothness_tau_px[s, 0]:g} px"
        )
        if (result.orientation_system == s).sum() > 1:
            line += (
                f"; each orientation's deviation from it order {result.smoothness_order[s, 1]}, "
                f"τ = {result.smoothness_tau_px[s, 1]:g} px"
                + (" (both chosen by cross-validation)." if result.iterations >= 3 else " (start values).")
            )
        else:
            line += (
                " (chosen by cross-validation)" if result.iterations >= 3 else " (start value)"
            ) + "; one orientation."
        lines.append(line)
    return lines


def _plate_lines(result, pitch_mm: float) -> list[str]:
    est = result.plate_estimated
    if not est.any():
        return [
            "The plate is taken as nominal: its manufacturing errors were not estimated (one frame, a plate that "
            "did not move across the image between frames, or scheme none), so they cannot be told from the "
            "distortion here. Calibrate from two frames or more with the plate carried across the image between "
            "them (the C-arm turned, or the plate moved) to estimate them."
        ]
    err = result.plate_error_mm[est]
    return [
        f"The plate's own errors, estimated for {int(est.sum())} of {len(est)} holes (seen in two frames or more): "
        f"{_rms_mm(err):.4f} mm RMS per component ({_rms_mm(err) / pitch_mm:.4f} pitch), largest "
        f"{float(np.linalg.norm(err, axis=1).max()):.4f} mm, each known to "
        f"{float(np.median(result.plate_error_std_mm[est])):.4f} mm (median standard deviation). "
        "They are not learned as distortion."
    ]


#: arrows per side of a plate map: one hole per cell of this grid, so that each arrow can be seen
PLATE_MAP_CELLS = 20


def plate_map(path: Path, result, system: int, pitch_mm: float) -> Path:
    """The plate's estimated errors as arrows on the plate (mm), one hole per cell, magnified to be seen.

    An arrow of the 95th percentile's length spans a cell (:data:`PLATE_MAP_CELLS` per side); the colour
    bar gives the error's length in mm.
    """
    from fluorocal.report import add_colorbar, new_figure, save_figure

    sel = (result.hole_system == system) & result.plate_estimated
    xy, err = result.nominal_mm[sel], result.plate_error_mm[sel]
    cell = max(float(np.ptp(xy, axis=0).max()) / PLATE_MAP_CELLS, pitch_mm)
    _, shown = np.unique(np.floor((xy - xy.min(axis=0)) / cell), axis=0, return_index=True)
    xy, err = xy[shown], err[shown]
    length = np.linalg.norm(err, axis=1)
    gain = cell / max(float(np.percentile(length, 95)), 1e-12)
    fig, (ax,) = new_figure(1, width=6.4, height=5.6, colorbar=True)
    arrows = ax.quiver(
        xy[:, 0],
        xy[:, 1],
        err[:, 0],
        err[:, 1],
        length,
        angles="xy",
        scale_units="xy",
        scale=1 / gain,
        cmap="viridis",
        width=0.005,
        headwidth=3,
        headlength=4,
    )
    ax.set_aspect("equal")
    ax.set_xlabel("plate x (mm)")
    ax.set_ylabel("plate y (mm)")
    name = result.system_names[system]
    ax.set_title(f"plate errors, system {name}: {len(xy)} of {int(sel.sum())} holes, arrows x{gain:.0f}")
    add_colorbar(fig, arrows, [ax], "plate error (mm)")
    return save_figure(fig, path)
