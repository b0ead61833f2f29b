r"""`fluorocal check CALIBRATION FRAME...`: does last month's calibration still hold? A quality check.

The routine it serves: weekly, and after any service of the C-arm (a new
intensifier, a moved detector, a software update), take a frame of the
calibration's grid plate (or bead phantom) at each orientation in use and check
it. Each FRAME (a file of one or many frames, or a folder of them) is detected
and labelled like a calibration frame, with the project's [detect], [centroid]
and [label] tables (a bead phantom from its markers: the project's seeds name
its own frames, not later ones), and its centres are corrected with the calibration's field at
the frame's orientation (the C-arm angles it records, else --orientation, else
the orientation named like the file, as `fluorocal undistort` chooses). What
the corrected centres are compared with is the calibration's own object
(object_points.csv beside the calibration):

  grid plate    the holes, renumbered onto the calibration's plate by the
                plate's own manufacturing errors (its fingerprint), against
                the self-calibrated layout (the nominal lattice plus the
                plate's estimated errors) by the best homography (the plate's
                pose);
  bead phantom  the labelled beads against their adjusted positions by the
                best pose of the phantom (a resection with the calibration's
                principal point and distance held).

What remains is the residual distortion, per hole or bead, in px and in mm at
the detector (the config's pixel_pitch). Scored: the holes or beads where the
field is supported.

Tolerances (a frame fails when any is exceeded; override with the options):

  --tol-rms 0.1 px    RMS per component. A calibrated orientation leaves about
                      0.02 px on its own frame (centroid noise), a field
                      interpolated to a held-out orientation 0.07-0.08 px,
                      while the field 15 degrees away leaves 0.12 px or more.
  --tol-p95 0.25 px   95th percentile of the residual's length: a change
                      confined to part of the field (a rim) shows here first.
  --tol-max 1 px      largest residual: a few mis-centred holes reach some
                      tenths of a px; a changed field reaches a px at the rim.

A frame also fails when its plate is not recognised as the calibration's
(another plate, or a frame of another C-arm), when its phantom is not found,
or when fewer than 100 of its holes (30 of its beads) lie where the field is
supported. Each frame's row is appended to the
QA record (--record, default qa_record.csv beside the calibration) and the
record's trend is drawn beside it (qa_trend.png; for a record X.csv, X_trend.png). Exit 0 when every frame
passes, 1 when one fails, 2 on bad input (nothing appended).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

#: the default tolerances, px (the module docstring gives their reasons)
TOLERANCES_PX = {"rms": 0.1, "p95": 0.25, "max": 1.0}
#: the QA record's columns
RECORD_COLUMNS = [
    "checked_at",
    "calibration",
    "calibration_sha256",
    "system",
    "file",
    "frame",
    "orientation",
    "orbit_deg",
    "tilt_deg",
    "n_points",
    "rms_px",
    "p95_px",
    "max_px",
    "rms_mm",
    "p95_mm",
    "max_mm",
    "tol_rms_px",
    "tol_p95_px",
    "tol_max_px",
    "result",
    "reason",
]
#: the record's columns as the grid-plate check first wrote them
FIRST_RECORD_COLUMNS = [("n_holes" if c == "n_points" else c) for c in RECORD_COLUMNS]


def add_parser(subparsers) -> None:
    """Register the ``check`` subcommand."""
    p = subparsers.add_parser(
        "check",
        help="check a calibration with new grid-plate or bead-phantom frames (QA)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("calibration", type=Path, metavar="CALIBRATION", help="calibration.json of a fluorocal run")
    p.add_argument(
        "frames", nargs="+", type=Path, metavar="FRAME", help="frame files (or folders of them) of the plate or phantom"
    )
    p.add_argument("--system", metavar="NAME", help="the system the frames come from (default: the only one)")
    p.add_argument(
        "--orientation",
        metavar="NAME|orbit=DEG,tilt=DEG",
        help="check against this orientation (a name, or orbit=DEG,tilt=DEG) instead of each frame's own "
        "(default: the angles each frame records, else the orientation named like the file)",
    )
    p.add_argument(
        "--record",
        type=Path,
        metavar="CSV",
        help="the QA record a row per frame is appended to (default: qa_record.csv beside the calibration)",
    )
    for name, value in TOLERANCES_PX.items():
        p.add_argument(
            f"--tol-{name}", type=float, default=value, metavar="PX", help=f"tolerance, px (default: {value})"
        )
    p.set_defaults(func=run)


def run(args) -> int:
    """Check every frame; append the record, draw the trend; 0 all pass, 1 one fails."""
    import logging
    from datetime import datetime

    from fluorocal.calibration import Calibration
    from fluorocal.cli_common import parse_orientation
    from fluorocal.cmd_undistort import expand_inputs, input_orientations
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import probe_frames

    log = logging.getLogger("fluorocal")
    tolerances = {name: getattr(args, f"tol_{name}") for name in TOLERANCES_PX}
    if not all(v > 0 for v in tolerances.values()):
        raise InputError(f"tolerances must be > 0 px; got {tolerances}")
    cal = Calibration.load(args.calibration)
    system = _system(cal, args.system, args.calibration)
    setup = reference_setup(cal, Path(args.calibration), system)
    chosen = None if args.orientation is None else parse_orientation(args.orientation)
    files = expand_inputs(args.frames)
    plan = []  # (file, per-frame orientations): every input checked before any frame is measured
    for path in files:
        n_frames, size = probe_frames(path)
        w, h = cal.systems[system].image_size_px
        if tuple(size) != (w, h):
            raise InputError(f"{path}: frame is {size[0]}x{size[1]} px; system {system} was calibrated at {w}x{h}")
        orientations, _ = input_orientations(cal, system, path, chosen, n_frames)
        for orientation in {_describe(o): o for o in orientations}.values():
            cal.field(system, orientation)  # an unknown orientation, or angles beyond the calibrated: refused here
        plan.append((path, orientations))
    now = datetime.now().isoformat(timespec="seconds")
    rows = []
    for path, orientations in plan:
        for index, (frame, orientation) in enumerate(zip(_read(path), orientations)):
            result = check_frame(frame, cal, system, orientation, setup, tolerances)
            rows.append(_row(now, args.calibration, cal, system, path, index, orientation, result, setup, tolerances))
            (log.info if result.passed else log.warning)("%s[%d]: %s", path.name, index, result.summary())
    record = args.record or Path(args.calibration).with_name("qa_record.csv")
    append_record(record, rows)
    stem = record.stem.replace("record", "trend") if "record" in record.stem else record.stem + "_trend"
    trend = draw_trend(record, record.with_name(stem + ".png"))
    log.info("appended %d row(s) to %s; trend: %s", len(rows), record, trend)
    return 0 if all(r[RECORD_COLUMNS.index("result")] == "pass" for r in rows) else 1


def _system(cal, name: str | None, path) -> str:
    from fluorocal.stages.errors import InputError

    if name is None:
        if len(cal.system_names) != 1:
            raise InputError(f"{path} holds systems {', '.join(cal.system_names)}; choose one with --system")
        return cal.system_names[0]
    if name not in cal.systems:
        raise InputError(f"--system {name!r} is not in {path}; it has {', '.join(cal.system_names)}")
    return name


def _read(path: Path):
    from fluorocal.stages.io import read_frames

    return read_frames(path)


def _describe(orientation) -> str:
    if isinstance(orientation, dict):
        return f"orbit={orientation['orbit']:g},tilt={orientation['tilt']:g}"
    return "" if orientation is None else str(orientation)


# --- the measurement ---------------------------------------------------------------------------------------


def reference_setup(cal, calibration: Path, system: str):
    """What ``system``'s later frames are checked against, as its phantom kind says (:mod:`fluorocal.check_setups`).

    The kind is the calibration's own (a plate's estimates no geometry); the rest is read from its project
    config (the phantom and the [detect]/[centroid]/[label] tables, the system's geometry) and the object
    points written beside the calibration.

    Raises
    ------
    InputError
        A calibration that corrects nothing, a config that no longer names the calibration's kind of object, or a
        config or object points that cannot be read (naming the file).
    """
    import numpy as np
    from fluorocal.check_setups import Tables
    from fluorocal.cli_common import load_project
    from fluorocal.config import ConfigError, params_from_dict
    from fluorocal.kinds import part_of
    from fluorocal.stages.centroid import CentroidParams
    from fluorocal.stages.detect import DetectParams
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import OBJECT_POINTS, read_table
    from fluorocal.stages.label import LabelParams

    s = cal.systems[system]
    if not any(np.any(f.delta_px) for f in [s.field] + [o.field for o in s.orientations] if f is not None):
        raise InputError(f"{calibration}: system {system} holds no correction (scheme none); nothing to check")
    config_path = Path(str(cal.meta.get("config", "")))
    try:
        config = load_project(config_path, writable=False)
    except (ConfigError, OSError) as exc:
        raise InputError(f"{calibration}: cannot read its project config {config_path} ({exc})") from None
    made = made_with(cal, calibration)
    if config.phantom.kind not in made:
        nouns = " or ".join(kind.noun for kind in made) or f"a kind of object named {cal.meta['phantom_kind']!r}"
        now = config.phantom.kind.noun
        raise InputError(f"{calibration}: made with {nouns}, but its config {config_path} now names {now}")
    points_path = calibration.with_name("object_points.csv")
    if not points_path.is_file():
        raise InputError(f"{points_path}: missing; fluorocal run writes the object points beside the calibration")
    table = read_table(points_path, OBJECT_POINTS)
    geometry = next((s for s in config.systems if s.name == system), None)
    if geometry is None:
        raise InputError(f"{config_path}: has no system {system!r}, which {calibration} was calibrated with")
    where = f"{config_path.name}: "
    params = [
        params_from_dict(cls, config.stage_params.get(section, {}), where=f"{where}[{section}] ")
        for cls, section in ((DetectParams, "detect"), (CentroidParams, "centroid"), (LabelParams, "label"))
    ]
    tables = Tables(*params, geometry.pixel_pitch_mm, geometry.source_image_distance_mm)
    return part_of(config.phantom.kind).check_setup(tables, config, table)


def made_with(cal, calibration: Path) -> list:
    """The kinds of object (:data:`~fluorocal.stages.kinds.KINDS`) the calibration ``cal`` can have been made with.

    The one its ``phantom_kind`` names; in a calibration written before it named one, each kind whose
    estimating the geometry or not is the calibration's (``geometry_estimated``).

    Raises
    ------
    InputError
        ``phantom_kind`` names a kind that estimates the geometry where the calibration did not, or the
        reverse: one of the two keys was edited (the message names both, and the file ``calibration``).
    """
    from fluorocal.exports.common import has_geometry
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.kinds import KINDS

    kinds = list(dict.fromkeys(KINDS.values()))  # a kind of several spellings once
    estimated = has_geometry(cal)
    if "phantom_kind" not in cal.meta:
        return [kind for kind in kinds if kind.estimates_geometry == estimated]
    named = [kind for kind in kinds if kind.name == cal.meta["phantom_kind"]]
    if any(kind.estimates_geometry != estimated for kind in named):
        raise InputError(
            f"{calibration}: its phantom_kind {cal.meta['phantom_kind']!r} contradicts its geometry_estimated "
            f"{str(estimated).lower()}; one of them was edited"
        )
    return named


@dataclass(frozen=True)
class CheckResult:
    """One frame's check: residual figures (px; NaN when not measured), the verdict and why."""

    n_points: int
    rms_px: float
    p95_px: float
    max_px: float
    passed: bool
    reason: str
    noun: str = "holes"

    def summary(self) -> str:
        figures = (
            f"{self.n_points} {self.noun}, RMS {self.rms_px:.3f} px, P95 {self.p95_px:.3f} px, max {self.max_px:.3f} px"
        )
        return (
            ("pass: " if self.passed else "FAIL: ")
            + (figures if self.n_points else "")
            + (f" ({self.reason})" if self.reason and self.n_points else self.reason)
        )


def check_frame(frame, cal, system: str, orientation, setup, tolerances: dict) -> CheckResult:
    """Detect and label a frame's holes or beads, match them to the calibration's; correct; the residual, judged."""
    import numpy as np

    labels = setup.labels(frame)
    if not labels.ok:
        return _failed(f"{setup.not_found}: {labels.reason}")
    matched = setup.matched(labels)
    if isinstance(matched, str):
        return _failed(matched)
    xy, reference = matched
    field = cal.field(system, orientation)
    supported = field.support_at(xy)
    n = int(supported.sum())
    if n < setup.min_points:
        return _failed(f"only {n} {setup.noun} where the field is supported (at least {setup.min_points})")
    ideal = field.undistort_points(xy[supported])
    residual = setup.residual(reference[supported], ideal, cal.systems[system].iop_px)
    if residual is None:
        return _failed(f"no pose of the {setup.thing} fits its {setup.noun}")
    length = np.linalg.norm(residual, axis=1)
    figures = {
        "rms": float(np.sqrt(np.mean(residual**2))),
        "p95": float(np.percentile(length, 95)),
        "max": float(length.max()),
    }
    over = [f"{k.upper()} {v:.3f} px > {tolerances[k]:g} px" for k, v in figures.items() if not v <= tolerances[k]]
    reason = "; ".join(over) + ("" if not over else ": the field no longer holds at this orientation")
    return CheckResult(n, figures["rms"], figures["p95"], figures["max"], not over, reason, setup.noun)


def _failed(reason: str) -> CheckResult:
    nan = float("nan")
    return CheckResult(0, nan, nan, nan, False, reason)


# --- the record ---------------------------------------------------------------------------------------------


def _row(now, calibration, cal, system, path, index, orientation, result, setup, tolerances) -> list:
    angles = orientation if isinstance(orientation, dict) else {}
    found = next((o for o in cal.systems[system].orientations if o.name == orientation), None)
    orbit = angles.get("orbit", getattr(found, "orbit_deg", None))
    tilt = angles.get("tilt", getattr(found, "tilt_deg", None))
    mm = setup.tables.pixel_pitch_mm
    return [
        now,
        Path(calibration).name,
        (cal.content_sha256 or "")[:16],
        system,
        Path(path).name,
        index,
        _describe(orientation) or "the one field",
        "" if orbit is None else orbit,
        "" if tilt is None else tilt,
        result.n_points,
        result.rms_px,
        result.p95_px,
        result.max_px,
        result.rms_px * mm,
        result.p95_px * mm,
        result.max_px * mm,
        tolerances["rms"],
        tolerances["p95"],
        tolerances["max"],
        "pass" if result.passed else "fail",
        result.reason,
    ]


def append_record(path: Path, rows: list) -> None:
    """Append ``rows`` to the QA record CSV (created with its header), atomically; refuse a file of other columns.

    A record of the grid-plate check's first columns (``n_holes`` where ``n_points`` is) is continued under today's.
    """
    import csv

    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import write_csv

    old = []
    if path.exists():
        with open(path, newline="", encoding="utf-8") as fh:
            old = list(csv.reader(fh))
        if old and old[0] not in (RECORD_COLUMNS, FIRST_RECORD_COLUMNS):
            raise InputError(f"{path}: not a fluorocal QA record (columns {old[0][:4]}...); choose another --record")
    write_csv(path, RECORD_COLUMNS, old[1:] + rows)


def draw_trend(record: Path, png: Path) -> Path:
    """The QA record's RMS, P95 and largest residual per check, one line per (system, orientation), and tolerances."""
    import csv

    from fluorocal.report import new_figure, save_figure, text_height_in

    with open(record, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    bottom_in = text_height_in({r["checked_at"] for r in rows}, fontsize=6, rotation=60) + 0.15  # rotated dates
    fig, axes = new_figure(3, width=4.6, height=3.6, bottom_in=bottom_in)
    for ax, key in zip(axes, ("rms", "p95", "max")):
        series: dict = {}
        for r in rows:
            series.setdefault((r["system"], r["orientation"]), []).append((r["checked_at"], float(r[f"{key}_px"])))
        for (system, orientation), points in series.items():
            ax.plot([p[0] for p in points], [p[1] for p in points], "o-", ms=3, label=f"{system} {orientation}")
        ax.axhline(float(rows[-1][f"tol_{key}_px"]), color="r", ls="--", lw=1, label="tolerance")
        ax.set_title(f"{key.upper()} residual (px)", fontsize=9)
        ax.tick_params(axis="x", labelrotation=60, labelsize=6)
    axes[0].legend(fontsize=6)
    return save_figure(fig, png)
