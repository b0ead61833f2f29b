"""`fluorocal detect FILE...`: detect and centroid beads in single frames, outside any project (debugging).

Every frame of every FILE (DICOM, TIFF, PNG or video) goes through the detect
and centroid stages with default parameters (plus --polarity and --diameter).
One row of --out's detections.csv per successfully fitted bead:

    file,frame,x,y,sigma_x,sigma_y,rho,major,minor,angle,fit_rmse,score

x, y: ellipse centre in px (x right, y down, top-left pixel centre at 0,0);
sigma_x, sigma_y (px), rho: the centre's standard deviations and correlation;
major, minor: semi-axes in px; angle: major axis in radians from +x toward +y;
fit_rmse: RMS distance of the edge points from the ellipse, px; score:
detection contrast over noise.

With --overlay DIR, a PNG per frame shows the accepted ellipses (green),
failed fits (orange) and rejected candidates (red) with their reason.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fluorocal.cli_common import add_out, add_overwrite, refuse_existing

#: the columns written, in order (the table's schema is :data:`fluorocal.stages.io.DETECTIONS`)
COLUMNS = ["file", "frame", "x", "y", "sigma_x", "sigma_y", "rho", "major", "minor", "angle", "fit_rmse", "score"]


def _diameter_range(text: str) -> tuple[float, float]:
    """Parse ``MIN:MAX`` (px) for --diameter."""
    try:
        low, high = (float(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--diameter must be MIN:MAX in px, e.g. 12:30; got {text!r}") from None
    if not 0 < low <= high:
        raise argparse.ArgumentTypeError(f"--diameter must satisfy 0 < MIN <= MAX; got {text!r}")
    return low, high


def add_parser(subparsers) -> None:
    """Register the ``detect`` subcommand."""
    p = subparsers.add_parser(
        "detect",
        help="detect and centroid beads in single frames (debugging)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("files", nargs="+", type=Path, metavar="FILE", help="frames: DICOM, TIFF, PNG or video")
    p.add_argument(
        "--polarity",
        choices=("auto", "dark", "bright"),
        default="auto",
        help="dark beads (steel) or bright (grid holes) (default: auto, decided per frame)",
    )
    p.add_argument(
        "--diameter",
        type=_diameter_range,
        metavar="MIN:MAX",
        help="expected bead diameter range in px (default: estimated per frame)",
    )
    add_out(p, "folder for detections.csv (required; written atomically)", required=True)
    add_overwrite(p, "an existing detections.csv")
    p.add_argument(
        "--overlay", type=Path, metavar="DIR", help="also write a PNG overlay per frame into DIR (default: none)"
    )
    p.set_defaults(func=run)


def run(args) -> int:
    """Detect, centroid and write the table (and overlays); return the exit code."""
    import logging
    import sys
    import warnings

    from fluorocal.stages.centroid import CentroidParams, centroid_beads
    from fluorocal.stages.detect import DetectParams, detect_beads
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import DETECTIONS, columns_of, read_frames, write_table
    from tqdm import tqdm

    log = logging.getLogger("fluorocal")
    for path in args.files:
        if not Path(path).is_file():
            raise InputError(f"{path}: no such file")
    table = args.out / "detections.csv"
    refuse_existing([table], overwrite=args.overwrite)
    low, high = args.diameter or (0.0, 0.0)
    detect_params = DetectParams(polarity=args.polarity, min_diameter_px=low, max_diameter_px=high)
    centroid_params = CentroidParams()
    quiet = bool(getattr(args, "quiet", False))
    rows, n_frames = [], 0
    for path in tqdm(args.files, desc="detect", unit="file", disable=quiet or not sys.stderr.isatty()):
        for frame in read_frames(path):
            n_frames += 1
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                candidates = detect_beads(frame, detect_params)
                beads = centroid_beads(frame, candidates, centroid_params)
            for w in caught:
                log.warning("%s", w.message)
            rows.extend(_rows(str(path), frame.frame_index, beads))
            if args.overlay is not None:
                _write_overlay(
                    Path(args.overlay) / f"{Path(path).stem}_f{frame.frame_index:04d}.png", frame, candidates, beads
                )
            log.debug(
                "%s[%d]: %d candidates, %d accepted, %d fitted",
                path,
                frame.frame_index,
                len(candidates),
                candidates.n_accepted,
                int(beads.ok.sum()),
            )
    write_table(table, DETECTIONS, columns_of(COLUMNS, rows))
    log.info("%d beads in %d frames of %d files -> %s", len(rows), n_frames, len(args.files), table)
    return 0


def _rows(file: str, frame_index: int, beads) -> list[list]:
    """CSV rows (see :data:`COLUMNS`) of the successfully fitted beads of one frame."""
    out = []
    for i in beads.ok.nonzero()[0]:
        x, y = beads.xy_px[i]
        out.append(
            [
                file,
                frame_index,
                float(x),
                float(y),
                float(beads.sigma_x[i]),
                float(beads.sigma_y[i]),
                float(beads.rho[i]),
                float(beads.major_px[i]),
                float(beads.minor_px[i]),
                float(beads.angle_rad[i]),
                float(beads.fit_rmse_px[i]),
                float(beads.score[i]),
            ]
        )
    return out


def _write_overlay(path: Path, frame, candidates, beads) -> None:
    from fluorocal.overlay import render_overlay
    from fluorocal.stages.io import write_png

    write_png(path, render_overlay(frame, candidates, beads))
