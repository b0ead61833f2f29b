"""`fluorocal label DETECTIONS.csv`: give detected beads their phantom ids, outside any project (debugging).

Input: the CSV written by `fluorocal detect` (columns
file,frame,x,y,sigma_x,sigma_y,rho,major,minor[,angle,fit_rmse,score][,ok]; px,
x right, y down, top-left pixel centre at 0,0; major/minor are semi-axes).
Frames are labelled in sorted (file, frame) order; a frame whose labelling fails
is reported on stderr and left out of the output.

A 3D phantom needs --phantom (CSV id,x,y,z[,diameter][,role], mm) and the rough
geometry --source-image-distance and --pixel-pitch; the pose comes from the marker beads (role
"marker", larger than the others), from --seeds, or from the previous frame.
A grid plate needs --lattice and --pitch instead; its ids encode the lattice
indices, id = (i + 5000) * 10000 + (j + 5000).

Seeds CSV: id,x,y[,file,frame] (px): a few beads identified by hand. Without
file/frame columns they apply to the first frame.

Output, --out's labels.csv: file,frame,id,x,y,sigma_x,sigma_y,rho (one row per labelled
detection). With --overlay DIR, a PNG per frame (read from the detections'
file column) with each detection drawn by status: labelled green with its id,
ambiguous orange, unmatched red, rejected grey.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from fluorocal.cli_common import add_geometry, add_image_size, add_out, add_overwrite, refuse_existing
from fluorocal.stages.kinds import LATTICE_SPELLINGS

log = logging.getLogger(__name__)

#: the columns written, in order: file and frame, then those of ``Labels.to_table`` (schema ``stages.io.LABELS``)
COLUMNS = ["file", "frame", "id", "x", "y", "sigma_x", "sigma_y", "rho"]


def add_parser(subparsers) -> None:
    """Register the ``label`` subcommand."""
    p = subparsers.add_parser(
        "label",
        help="label detections with phantom bead ids (debugging)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("detections", type=Path, metavar="DETECTIONS.csv", help="detections from `fluorocal detect`")
    p.add_argument(
        "--phantom",
        type=Path,
        metavar="CSV",
        help="phantom CSV id,x,y,z[,diameter][,role] (mm); required unless --lattice",
    )
    p.add_argument(
        "--lattice",
        choices=LATTICE_SPELLINGS,
        default="",
        help="grid plate lattice instead of a phantom CSV (default: none)",
    )
    p.add_argument(
        "--pitch",
        type=float,
        default=0.0,
        metavar="MM",
        help="grid plate hole pitch in mm (default: 0, required with --lattice)",
    )
    add_geometry(p)
    add_image_size(p, "the principal point is its centre (default: the centre of the detections)")
    p.add_argument("--seeds", type=Path, metavar="CSV", help="seeds id,x,y[,file,frame] (default: none)")
    add_out(p, "folder for labels.csv (required)", required=True)
    add_overwrite(p, "an existing labels.csv")
    p.add_argument(
        "--overlay", type=Path, metavar="DIR", help="write a PNG per frame with the ids drawn (default: none)"
    )
    p.set_defaults(func=run)


def run(args) -> int:
    """Label every frame of the detections file; return the exit code."""
    from fluorocal.stages.artifacts import Phantom
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import LABELS, columns_of, read_frames, read_phantom, write_table
    from fluorocal.stages.kinds import phantom_kind
    from fluorocal.stages.kinds.labelling import label_sequence
    from fluorocal.stages.label import LabelParams

    table = args.out / "labels.csv"
    refuse_existing([table], overwrite=args.overwrite)
    frames = _read_detections(args.detections)
    kind = phantom_kind(args.lattice)
    if not kind.needs_geometry:  # a grid plate: its lattice and pitch are the whole phantom
        if not args.pitch > 0:
            raise InputError("--pitch must be > 0 mm with --lattice")
        phantom = Phantom([], [], [], [], args.lattice, args.pitch)
    elif args.phantom is None:
        raise InputError("give --phantom CSV (3D phantom) or --lattice and --pitch (grid plate)")
    else:
        phantom = read_phantom(args.phantom)
        if not (args.source_image_distance > 0 and args.pixel_pitch > 0):
            raise InputError(f"--source-image-distance and --pixel-pitch (mm, > 0) are needed to label {kind.noun}")
    keys = sorted(frames)
    seeds = _read_seeds(args.seeds, keys) if args.seeds else {}
    params = LabelParams(
        source_image_distance_mm=args.source_image_distance,
        pixel_pitch_mm=args.pixel_pitch,
        image_size_px=tuple(args.image_size or ()),
    )
    by_file: dict[str, list] = {}
    for key in keys:
        by_file.setdefault(key[0], []).append(key)
    rows, n_failed = [], 0
    for file, file_keys in by_file.items():
        labels = label_sequence(
            [frames[k] for k in file_keys],
            phantom,
            params,
            {i: seeds[k] for i, k in enumerate(file_keys) if k in seeds},
        )
        images = read_frames(file) if args.overlay else None  # decoded once per file, not per frame
        for (f, frame), lab in zip(file_keys, labels):
            where = f"{f}[{frame}]"
            if images is not None:
                _write_overlay(
                    args.overlay / f"{Path(f).stem}_{frame:03d}_labels.png", f, frame, images, frames[(f, frame)], lab
                )
            if not lab.ok:
                n_failed += 1
                log.warning("%s: %s", where, lab.summary())
                continue
            log.info("%s: %s", where, lab.summary())
            rows.extend([f, frame, *r] for r in lab.to_table()[1])
    write_table(table, LABELS, columns_of(COLUMNS, rows))
    log.info("wrote %d labels from %d of %d frames to %s", len(rows), len(keys) - n_failed, len(keys), table)
    return 0


def _read_detections(path: Path) -> dict:
    """``{(file, frame): Centroids}`` from a detections CSV (:data:`~fluorocal.stages.io.DETECTIONS`).

    A detection is ok unless its ``ok`` cell is false (no ``ok`` column: every one is) or one of its
    x, y, sigma_x, sigma_y, rho, major, minor is not finite.
    """
    import numpy as np
    from fluorocal.stages.centroid import Centroids
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import DETECTIONS, read_table

    t = read_table(path, DETECTIONS)
    if not len(t["file"]):
        raise InputError(f"{path}: detections CSV has no rows")
    # shape (N, 7): x, y, sigma_x, sigma_y, rho, major, minor
    values = np.stack([t[c] for c in ("x", "y", "sigma_x", "sigma_y", "rho", "major", "minor")], axis=1)
    ok = t["ok"] & np.all(np.isfinite(values), axis=1)
    keys = list(zip(t["file"].tolist(), t["frame"].tolist()))
    rows: dict = {}
    for i, key in enumerate(keys):
        rows.setdefault(key, []).append(i)
    out = {}
    for key, idx in rows.items():
        a, k, n = values[idx], ok[idx], len(idx)
        out[key] = Centroids(
            a[:, 0:2],
            a[:, 2],
            a[:, 3],
            a[:, 4],
            a[:, 5],
            a[:, 6],
            np.zeros(n),
            np.zeros(n),
            np.zeros(n, np.int64),
            np.zeros(n),
            k,
            np.where(k, "", "input"),
            np.arange(n),
            key[0],
            key[1],
        )
    return out


def _read_seeds(path: Path, keys: list) -> dict:
    """``{(file, frame): ((id, x, y), ...)}``; rows without file/frame go to the first frame."""
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import read_seeds

    by_name = {(Path(f).name, i): (f, i) for f, i in keys}
    out = {}
    for key, seeds in read_seeds(path).items():
        key = keys[0] if key == ("", 0) else by_name.get(key)
        if key is None:
            raise InputError(f"{path}: a seeded frame is not in the detections")
        out[key] = out.get(key, ()) + seeds
    return out


def _write_overlay(path: Path, file: str, frame_index: int, frames, centroids, labels) -> None:
    from fluorocal.overlay import render_label_overlay
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import write_png

    if not 0 <= frame_index < len(frames):
        raise InputError(f"{file}: has no frame {frame_index} for the overlay")
    write_png(path, render_label_overlay(frames[frame_index], centroids, labels))
