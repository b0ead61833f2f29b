"""C-arm orientations of a project's frames, and how a calibration's field changes with them.

- :func:`frame_orientations`: the orientation of every frame of a project: the
  config's ``orientations`` groups, or by default the frames' recorded C-arm
  angles (frames within the read-out tolerance share one orientation, named by
  its angles), a frame without angles its own, named by its file stem; angles
  from the config, else from the DICOM header.
- :func:`orientation_report`: the plots and Markdown lines of how a system's
  field changes with orientation (for the run report and ``fluorocal inspect``).
- :func:`inspect_calibration`: ``fluorocal inspect calibration.json``.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np
from fluorocal.outputs import MAX_NAME_LENGTH, inside, safe_name
from fluorocal.stages.errors import InputError
from fluorocal.stages.orientation import ANGLE_TOL_DEG, field_change, reference_orientation

#: at most this many arrow maps in one orientation plot
MAX_MAPS = 12


class FrameOrientation(NamedTuple):
    """The C-arm orientation of one frame: its name, and its angles in degrees (None when unknown)."""

    name: str
    orbit_deg: float | None
    tilt_deg: float | None


def default_orientation_name(path, index: int | None = None) -> str:
    """A frame's default orientation name: its file stem (+ ``_<index>`` in a multi-frame file).

    Characters a file name may not hold become ``_``, so the name is a :func:`safe_name`.

    Examples
    --------
    >>> default_orientation_name("frames/grid_orbit_30.dcm")
    'grid_orbit_30'
    >>> default_orientation_name("frames/cine run.dcm", 3)
    'cine_run_3'
    """
    stem = Path(path).stem + ("" if index is None else f"_{index}")
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", stem).lstrip(".")[:MAX_NAME_LENGTH]
    return safe_name(name or "frame", what="orientation name")


def _dicom_angles(path: Path) -> tuple[float | None, float | None]:
    """The C-arm angles a frame file records (DICOM header), or ``(None, None)``."""
    from fluorocal.stages.io import dicom, frame_format

    if frame_format(path).name != dicom.NAME:
        return None, None
    return dicom.positioner_angles_deg(path)


def frame_orientations(config, units, *, read_angles=_dicom_angles) -> tuple[FrameOrientation, ...]:
    """The C-arm orientation of each frame unit, in the order of ``units``.

    Parameters
    ----------
    config : fluorocal.config.Config
    units : sequence of fluorocal.units.FrameUnit
        Frames of ``config`` (``.system``: index into ``config.systems``, ``.path``, ``.index``).
    read_angles : callable (Path) -> (orbit_deg or None, tilt_deg or None), optional
        Reads a frame file's angles (default: the DICOM tags ``PositionerPrimaryAngle`` and
        ``PositionerSecondaryAngle``; None for other formats).

    Returns
    -------
    tuple of FrameOrientation
        One per unit. When the system's config gives ``orientations``, the unit's group: its name and
        angles, or, where the group gives none, the angles its frames' files record (they must agree).
        Otherwise the frames whose files record angles within :data:`ANGLE_TOL_DEG` of a first such
        frame's (the C-arm's read-out resolution) are one orientation, named by those angles
        (:func:`angle_orientation_name`); a frame without recorded angles is its own orientation, named
        by :func:`default_orientation_name` (with ``_<index>`` for the frames of a multi-frame file).

    Raises
    ------
    InputError
        Two files of one system would give the same default name; the frames of one group record
        different angles; a file's angles cannot be read.
    """
    cache: dict[Path, tuple] = {}

    def angles(path: Path):
        if path not in cache:
            cache[path] = read_angles(path)
        return cache[path]

    group_of = {  # (system index, resolved frame path) -> its group in the config
        (s, Path(f).resolve()): g
        for s, system in enumerate(config.systems)
        for g in system.orientations
        for f in g.frames
    }
    out = []
    by_angles: dict[int, list[tuple[float, float]]] = {}  # per system: the first angles of each angle group
    for unit in units:
        system = config.systems[unit.system]
        group = group_of.get((unit.system, Path(unit.path).resolve()))
        if group is not None:
            known = (group.orbit_deg, group.tilt_deg)
            if known[0] is None:
                known = _group_angles(system.name, group, [angles(Path(f)) for f in group.frames])
            out.append(FrameOrientation(group.name, *known))
            continue
        if system.orientations:
            raise InputError(f"{unit.path}: frame of system {system.name!r} is in none of its orientations")
        recorded = angles(Path(unit.path))
        if recorded[0] is not None:
            firsts = by_angles.setdefault(unit.system, [])
            first = next(
                (a for a in firsts if math.hypot(a[0] - recorded[0], a[1] - recorded[1]) <= ANGLE_TOL_DEG), None
            )
            if first is None:
                firsts.append(first := (recorded[0], recorded[1]))
            out.append(FrameOrientation(angle_orientation_name(*first), *first))
            continue
        n_in_file = sum(1 for u in units if u.system == unit.system and Path(u.path) == Path(unit.path))
        name = default_orientation_name(unit.path, unit.index if n_in_file > 1 else None)
        out.append(FrameOrientation(name, None, None))
    _check_default_names(config, units, out)
    return tuple(out)


def angle_orientation_name(orbit_deg: float, tilt_deg: float) -> str:
    """The name of the orientation of the frames recorded at these C-arm angles.

    Examples
    --------
    >>> angle_orientation_name(30.0, -7.5)
    'orbit30_tilt-7.5'
    """
    return safe_name(f"orbit{orbit_deg:g}_tilt{tilt_deg:g}", what="orientation name")


def _group_angles(system: str, group, recorded) -> tuple[float | None, float | None]:
    """The angles the frames of a group record: None when none does, refused when they disagree."""
    given = [(a, f) for a, f in zip(recorded, group.frames) if a[0] is not None]
    if not given:
        return None, None
    (first, first_file), *rest = given
    for a, f in rest:
        if math.hypot(a[0] - first[0], a[1] - first[1]) > ANGLE_TOL_DEG:
            raise InputError(
                f"orientation {group.name!r} of system {system!r}: its frames record different angles "
                f"({first_file.name}: orbit {first[0]:g}°, tilt {first[1]:g}°; {f.name}: orbit {a[0]:g}°, "
                f"tilt {a[1]:g}°); give orbit and tilt in the config, or split the group"
            )
    return first


def _check_default_names(config, units, orientations) -> None:
    seen: dict[tuple[int, str], Path] = {}
    for unit, o in zip(units, orientations):
        if config.systems[unit.system].orientations or o.orbit_deg is not None:  # angle groups span files
            continue
        other = seen.setdefault((unit.system, o.name), Path(unit.path))
        if other != Path(unit.path):
            raise InputError(
                f"frames {other} and {unit.path} of system {config.systems[unit.system].name!r} would both be "
                f"orientation {o.name!r}; name the orientations in the config's [[systems]] orientations"
            )


# --- how the field changes with orientation -------------------------------------------------------


def orientation_report(out_dir: Path, system_name: str, orientation_fields) -> tuple[list[Path], list[str]]:
    """Plots and Markdown lines of how a system's field changes with C-arm orientation.

    Each orientation's field is compared with a reference orientation's (the one nearest orbit 0°,
    tilt 0°, else the first; :func:`~fluorocal.stages.orientation.field_change`) at the nodes both
    support: RMS and largest difference as is, and modulo a homography (the part no change of pose
    or interior orientation absorbs).

    Parameters
    ----------
    out_dir : Path
        Folder the PNGs are written into: ``orientations_<system>.png`` (the figures per
        orientation) and ``orientation_maps_<system>.png`` (arrow maps of the differences modulo a
        homography, at most :data:`MAX_MAPS`).
    system_name : str
        The system (a :func:`safe_name`).
    orientation_fields : sequence of fluorocal.stages.orientation.OrientationField
        The system's calibrated orientations, all on one grid.

    Returns
    -------
    paths : list of Path
        The PNGs written; empty for fewer than two orientations.
    lines : list of str
        Markdown: a heading, a table with a row per orientation, and the images (by file name, for a
        report in ``out_dir``).
    """
    fields = list(orientation_fields)
    if len(fields) < 2:
        return [], []
    system = safe_name(system_name, what="system name")
    ref = reference_orientation(fields)
    changes = [field_change(fields[ref].field, o.field) for o in fields]
    lines = [
        f"### How the field changes with orientation, system {system_name}",
        "",
        f"Against orientation {fields[ref].describe()}, at the nodes both fields support, px; "
        "modulo H: after the best homography between the two (what a change of pose or IOP absorbs).",
        "",
        "| orientation | orbit (°) | tilt (°) | RMS Δ − Δref (px) | max (px) | RMS modulo H (px) | max modulo H (px) |",
        "|---|---|---|---|---|---|---|",
    ]
    for o, c in zip(fields, changes):
        lines.append(
            f"| {o.name} | {_deg(o.orbit_deg)} | {_deg(o.tilt_deg)} | {c.rms_px:.3f} | {c.max_px:.3f} "
            f"| {c.rms_mod_h_px:.3f} | {c.max_mod_h_px:.3f} |"
        )
    paths = [
        _change_plot(inside(out_dir, f"orientations_{system}.png"), system_name, fields, changes),
        _change_maps(inside(out_dir, f"orientation_maps_{system}.png"), fields, changes, ref),
    ]
    lines += [""] + [f"![{p.stem}]({p.name})" for p in paths]
    return paths, lines


def _deg(angle: float | None) -> str:
    return "–" if angle is None else f"{angle:g}"


def _change_plot(path: Path, system_name: str, fields, changes) -> Path:
    """RMS and largest change per orientation, as is and modulo a homography."""
    from fluorocal.report import new_figure, save_figure, text_height_in

    names = [o.describe() for o in fields]
    bottom_in = text_height_in(names, fontsize=7, rotation=60) + 0.15  # the names, rotated, below their ticks
    fig, (ax,) = new_figure(1, width=max(5.0, 0.5 * len(fields) + 2.5), height=3.8, bottom_in=bottom_in, title_lines=2)
    x = np.arange(len(fields))
    for k, (label, values) in enumerate(
        (
            ("RMS", [c.rms_px for c in changes]),
            ("max", [c.max_px for c in changes]),
            ("RMS modulo H", [c.rms_mod_h_px for c in changes]),
            ("max modulo H", [c.max_mod_h_px for c in changes]),
        )
    ):
        ax.bar(x + (k - 1.5) * 0.2, values, 0.2, label=label)
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("Δ − Δref at the nodes (px)")
    ax.set_title(f"change of the correction with orientation\nsystem {system_name}", fontsize=10)
    ax.legend(fontsize=7)
    return save_figure(fig, path)


def _change_maps(path: Path, fields, changes, ref: int) -> Path:
    """Arrow maps of each orientation's difference from the reference modulo a homography, one scale for all."""
    from fluorocal.report import add_colorbar, image_axes, new_figure, save_figure

    shown = [i for i in range(len(fields)) if i != ref][:MAX_MAPS]
    fig, axes = new_figure(len(shown), width=4.2, height=4.0, n_cols=min(len(shown), 4), title_lines=2, colorbar=True)
    first = fields[ref].field
    xx, yy = np.meshgrid(first.x_nodes_px, first.y_nodes_px)
    extent = (first.x_nodes_px[0], first.x_nodes_px[-1], first.y_nodes_px[-1], first.y_nodes_px[0])
    vmax = max((np.nanmax(np.linalg.norm(changes[i].difference_mod_h_px, axis=-1), initial=0) for i in shown))
    vmax = vmax if np.isfinite(vmax) and vmax > 0 else 1.0
    step = max(len(first.x_nodes_px) // 24, 1)
    sel = (slice(None, None, step), slice(None, None, step))
    for ax, i in zip(axes, shown):
        d = changes[i].difference_mod_h_px
        im = ax.imshow(np.linalg.norm(d, axis=-1), extent=extent, cmap="magma", vmin=0, vmax=vmax)
        if vmax > 0:  # equal fields (scheme none) leave no arrow to scale
            ax.quiver(xx[sel], yy[sel], d[sel][..., 0], d[sel][..., 1], angles="xy", color="c", scale=vmax * 25)
        image_axes(
            ax,
            (first.width_px, first.height_px),
            f"{fields[i].describe()}\nRMS {changes[i].rms_mod_h_px:.3f} px modulo H",
        )
    add_colorbar(fig, im, axes, f"|Δ − Δref| modulo H (px), against {fields[ref].name}")
    return save_figure(fig, path)


def inspect_calibration(path: Path, out_dir: Path | None = None) -> list[str]:
    """Lines describing a calibration's systems and orientations; writes the orientation plots.

    ``fluorocal inspect calibration.json``: per system the image size and, per orientation, its
    angles and field summary; for a system with several orientations, :func:`orientation_report`'s
    table, its PNGs written into ``out_dir`` (default: ``overlays/`` beside the calibration).
    """
    from fluorocal.calibration import Calibration

    path = Path(path)
    cal = Calibration.load(path)
    out_dir = inside(path.parent, "overlays") if out_dir is None else Path(out_dir)
    lines = [f"{path}: {len(cal.system_names)} system(s), scheme {cal.meta.get('scheme', '?')}"]
    for name in cal.system_names:
        s = cal.systems[name]
        w, h = s.image_size_px
        listed = s.orientations
        lines.append(f"system {name}: {w}x{h} px, {len(listed) or 1} field(s)")
        for label, field in [(o.describe(), o.field) for o in listed] or [("one field, no named orientation", s.field)]:
            mag = np.linalg.norm(field.delta_px, axis=-1)[field.support]
            lines.append(f"  {label}: max |Δ| {mag.max(initial=0):.2f} px where supported")
        if len(listed) > 1:
            out_dir.mkdir(parents=True, exist_ok=True)
            paths, report = orientation_report(out_dir, name, listed)
            lines += [line for line in report if line.startswith("|")] + [f"plot: {p}" for p in paths]
    return lines
