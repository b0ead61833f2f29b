r"""`fluorocal check CALIBRATION FRAME...`: does last month's calibration still hold? A grid-plate quality check.

The routine it serves: weekly, and after any service of the C-arm (a new
intensifier, a moved detector, a software update), take a frame of the
calibration's grid plate at each orientation in use and check it. Each FRAME
(a file of one or many frames, or a folder of them) is detected and labelled
like a calibration frame, renumbered onto the calibration's plate by the
plate's own manufacturing errors (its fingerprint), and its hole centres are
corrected with the calibration's field at the frame's orientation (the C-arm
angles it records, else --orientation, else the orientation named like the
file, as `fluorocal undistort` chooses). The corrected centres are compared
with the calibration's self-calibrated plate layout (object_points.csv beside
the calibration: the nominal lattice plus the plate's estimated errors) by the
best homography (the plate's pose); what remains is the residual distortion,
per hole, in px and in mm at the detector (the config's pixel_pitch).
Scored: the holes where the field is supported.

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
(another plate, or a frame of another C-arm), or when fewer than 100 of its
holes lie where the field is supported. Each frame's row is appended to the
QA record (--record, default qa_record.csv beside the calibration) and the
record's trend is drawn beside it (qa_trend.png; for a record X.csv, X_trend.png). Exit 0 when every frame
passes, 1 when one fails, 2 on bad input (nothing appended).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: the default tolerances, px (the module docstring gives their reasons)
TOLERANCES_PX = {"rms": 0.1, "p95": 0.25, "max": 1.0}
#: fewer scored holes than this and the check says nothing
MIN_HOLES = 100
#: a frame's plate is the calibration's when its fingerprint correlates at least this well, and by this margin
#: over any other numbering (stages.label.lattice_sequence's own thresholds for renumbering a frame)
MIN_CORRELATION, MIN_MARGIN = 0.3, 0.1
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
    "n_holes",
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


def add_parser(subparsers) -> None:
    """Register the ``check`` subcommand."""
    p = subparsers.add_parser(
        "check",
        help="check a calibration with new grid-plate frames (QA)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("calibration", type=Path, metavar="CALIBRATION", help="calibration.json of a grid-plate run")
    p.add_argument("frames", nargs="+", type=Path, metavar="FRAME", help="grid-plate frame files or folders of them")
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
    plate = plate_setup(cal, Path(args.calibration), system)
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
            result = check_frame(frame, cal, system, orientation, plate, tolerances)
            rows.append(_row(now, args.calibration, cal, system, path, index, orientation, result, plate, tolerances))
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


@dataclass(frozen=True)
class PlateSetup:
    """What a frame is checked against: the plate (lattice, pitch), its self-calibrated layout, the geometry.

    Attributes
    ----------
    lattice : str
        ``"hex"`` or ``"square"``.
    pitch_mm : float
    pixel_pitch_mm : float
        At the detector (the config's ``pixel_pitch``): px -> mm.
    source_image_distance_mm : float
    ij : (N, 2) int64 ndarray
        Lattice index of each layout hole.
    layout_mm : (N, 2) float64 ndarray, mm
        The plate's holes as calibrated: nominal + estimated error.
    """

    lattice: str
    pitch_mm: float
    pixel_pitch_mm: float
    source_image_distance_mm: float
    ij: np.ndarray
    layout_mm: np.ndarray


def plate_setup(cal, calibration: Path, system: str) -> PlateSetup:
    """The plate a calibration was made with: its config's lattice and geometry, its layout (object_points.csv).

    Raises
    ------
    InputError
        Not a grid-plate calibration, or its config or layout cannot be read (naming the file).
    """
    from fluorocal.config import ConfigError, load_config
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import OBJECT_POINTS, read_table
    from fluorocal.stages.label.lattice import lattice_index

    if cal.meta.get("scheme") != "plate":
        raise InputError(
            f"{calibration}: not a grid-plate calibration (scheme {cal.meta.get('scheme')!r}); "
            "fluorocal check needs the plate's self-calibrated layout"
        )
    config_path = Path(str(cal.meta.get("config", "")))
    try:
        config = load_config(config_path, writable=False)
    except (ConfigError, OSError) as exc:
        raise InputError(f"{calibration}: cannot read its project config {config_path} for the plate ({exc})") from None
    layout_path = calibration.with_name("object_points.csv")
    if not layout_path.is_file():
        raise InputError(
            f"{layout_path}: missing; the plate's layout is written beside the calibration by fluorocal run"
        )
    table = read_table(layout_path, OBJECT_POINTS)
    geometry = next((s for s in config.systems if s.name == system), None)
    if geometry is None:
        raise InputError(f"{config_path}: has no system {system!r}, which {calibration} was calibrated with")
    return PlateSetup(
        config.phantom.lattice,
        config.phantom.pitch_mm,
        geometry.pixel_pitch_mm,
        geometry.source_image_distance_mm,
        lattice_index(np.asarray(table["id"], np.int64)),
        np.column_stack([table["x"], table["y"]]),
    )


@dataclass(frozen=True)
class CheckResult:
    """One frame's check: residual figures (px; NaN when not measured), the verdict and why."""

    n_holes: int
    rms_px: float
    p95_px: float
    max_px: float
    passed: bool
    reason: str

    def summary(self) -> str:
        figures = f"{self.n_holes} holes, RMS {self.rms_px:.3f} px, P95 {self.p95_px:.3f} px, max {self.max_px:.3f} px"
        return (
            ("pass: " if self.passed else "FAIL: ")
            + (figures if self.n_holes else "")
            + (f" ({self.reason})" if self.reason and self.n_holes else self.reason)
        )


def check_frame(frame, cal, system: str, orientation, plate: PlateSetup, tolerances: dict) -> CheckResult:
    """Detect, label and renumber a frame's holes; correct them; the residual against the layout, judged."""
    from fluorocal.stages.geometry import homography_fit

    labels = _labels(frame, plate)
    if not labels.ok:
        return _failed(f"no grid plate found: {labels.reason}")
    matched = _on_layout(labels, plate)
    if isinstance(matched, str):
        return _failed(matched)
    xy, layout = matched
    field = cal.field(system, orientation)
    supported = field.support_at(xy)
    if supported.sum() < MIN_HOLES:
        return _failed(f"only {int(supported.sum())} holes where the field is supported (at least {MIN_HOLES})")
    residual = homography_fit(layout[supported], field.undistort_points(xy[supported]))[1]
    length = np.linalg.norm(residual, axis=1)
    figures = {
        "rms": float(np.sqrt(np.mean(residual**2))),
        "p95": float(np.percentile(length, 95)),
        "max": float(length.max()),
    }
    over = [f"{k.upper()} {v:.3f} px > {tolerances[k]:g} px" for k, v in figures.items() if not v <= tolerances[k]]
    reason = "; ".join(over) + ("" if not over else ": the field no longer holds at this orientation")
    return CheckResult(int(supported.sum()), figures["rms"], figures["p95"], figures["max"], not over, reason)


def _failed(reason: str) -> CheckResult:
    nan = float("nan")
    return CheckResult(0, nan, nan, nan, False, reason)


def _labels(frame, plate: PlateSetup):
    """The frame's holes, detected, centroided and labelled as a calibration frame's are."""
    from fluorocal.stages.artifacts import Phantom
    from fluorocal.stages.centroid import CentroidParams, centroid_beads
    from fluorocal.stages.detect import DetectParams, detect_beads, estimate_appearance
    from fluorocal.stages.label import LabelParams, label_sequence

    detect = estimate_appearance([frame], DetectParams())
    centroids = centroid_beads(frame, detect_beads(frame, detect), CentroidParams())
    phantom = Phantom(
        np.empty(0, np.int64), np.empty((0, 3)), np.empty(0), np.empty(0, str), plate.lattice, plate.pitch_mm
    )
    size = (frame.image.shape[1], frame.image.shape[0])
    params = LabelParams(
        source_image_distance_mm=plate.source_image_distance_mm, pixel_pitch_mm=plate.pixel_pitch_mm, image_size_px=size
    )
    return label_sequence([centroids], phantom, params)[0]


def _on_layout(labels, plate: PlateSetup):
    """``(xy_px, layout_mm)`` of the frame's holes renumbered onto the layout by the plate's fingerprint, or why not."""
    from fluorocal.stages.label.lattice import lattice_index, lattice_xyz_mm
    from fluorocal.stages.label.lattice_sequence import Fingerprint, fingerprint, match_fingerprints

    nominal = lattice_xyz_mm(plate.ij, plate.lattice, plate.pitch_mm)[:, :2]
    reference = Fingerprint(plate.ij, (plate.layout_mm - nominal) / plate.pitch_mm)
    M, t, corr, margin = match_fingerprints(fingerprint(labels, plate.lattice), reference, plate.lattice)[:4]
    if not (corr >= MIN_CORRELATION and margin >= MIN_MARGIN):
        return (
            f"the plate is not the calibration's (fingerprint correlation {corr:.2f}, margin {margin:.2f}; "
            f"at least {MIN_CORRELATION} and {MIN_MARGIN} needed): another plate, or another C-arm's frame"
        )
    where = {tuple(v): k for k, v in enumerate(plate.ij)}
    ij = lattice_index(labels.bead_id) @ np.asarray(M).T + np.asarray(t)
    pairs = [(i, where[key]) for i, key in enumerate(map(tuple, ij)) if key in where]
    if len(pairs) < MIN_HOLES:
        return f"only {len(pairs)} of the frame's holes are in the calibration's layout (at least {MIN_HOLES})"
    mine, theirs = np.array(pairs).T
    return labels.xy_px[mine], plate.layout_mm[theirs]


# --- the record ---------------------------------------------------------------------------------------------


def _row(now, calibration, cal, system, path, index, orientation, result, plate, tolerances) -> list:
    angles = orientation if isinstance(orientation, dict) else {}
    found = next((o for o in cal.systems[system].orientations if o.name == orientation), None)
    orbit = angles.get("orbit", getattr(found, "orbit_deg", None))
    tilt = angles.get("tilt", getattr(found, "tilt_deg", None))
    mm = plate.pixel_pitch_mm
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
        result.n_holes,
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
    """Append ``rows`` to the QA record CSV (created with its header), atomically; refuse a file of other columns."""
    import csv

    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import write_csv

    old = []
    if path.exists():
        with open(path, newline="", encoding="utf-8") as fh:
            old = list(csv.reader(fh))
        if old and old[0] != RECORD_COLUMNS:
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
