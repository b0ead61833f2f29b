"""`fluorocal undistort`: remove a system's learned distortion from clinical or experimental frames.

Each INPUT (DICOM, TIFF, PNG or video) is resampled onto the ideal pinhole
image of the calibrated system and written to OUTDIR under the same name, in
the input's own format, bit depth and metadata (DICOM: a new SOP Instance
UID and a derivation note). The calibration must come from the same C-arm
orientation: an image intensifier's distortion changes with it.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(subparsers) -> None:
    """Register the ``undistort`` subcommand."""
    p = subparsers.add_parser(
        "undistort",
        help="undistort frames with a calibration",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("inputs", nargs="+", type=Path, metavar="INPUT", help="frames to undistort")
    p.add_argument("--calibration", type=Path, required=True, help="calibration.json written by `fluorocal run`")
    p.add_argument(
        "--system",
        required=True,
        metavar="NAME",
        help="the imaging system the frames come from (a name in the calibration)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=Path("undistorted"),
        metavar="OUTDIR",
        help="output directory (default: ./undistorted)",
    )
    p.add_argument(
        "--interpolation",
        choices=("linear", "cubic", "lanczos", "nearest"),
        default="linear",
        help="resampling kernel (default: linear)",
    )
    p.set_defaults(func=run)


def run(args) -> int:
    import logging

    from fluorocal.calibration import Calibration
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import read_frames, write_frames_like
    from fluorocal.stages.undistort import UndistortParams, check_maps, check_shift, undistort_frame
    from tqdm import tqdm

    out_dir = _check_paths(args.inputs, args.out)  # every input and the output before any work
    cal = Calibration.load(args.calibration)
    field = cal.systems.get(args.system)
    if field is None:
        raise InputError(f"--system {args.system!r} is not in {args.calibration}; it has {', '.join(cal.system_names)}")
    params = UndistortParams(interpolation=args.interpolation)
    try:
        check_shift(field.field.delta_px, *field.image_size_px)  # the nodes first: a huge field overflows the maps
        map_x, map_y = field.field.remap_maps(*field.image_size_px)  # every input must have the calibrated size
        check_maps(map_x, map_y)
    except InputError as exc:
        raise InputError(f"{args.calibration}: system {args.system}: {exc}") from exc
    for path in tqdm(args.inputs, desc="undistort", unit="file", disable=args.quiet or None):
        frames = read_frames(path)
        size = (frames[0].shape[1], frames[0].shape[0])
        if size != tuple(field.image_size_px):
            raise InputError(
                f"{path}: frame is {size[0]}x{size[1]} px; "
                f"system {args.system} was calibrated at {field.image_size_px[0]}x{field.image_size_px[1]}"
            )
        corrected = [undistort_frame(f, map_x, map_y, params) for f in frames]
        out_dir.mkdir(parents=True, exist_ok=True)
        write_frames_like(path, corrected, out_dir / path.name)
    logging.getLogger("fluorocal").info("wrote %d undistorted file(s) to %s", len(args.inputs), out_dir)
    return 0


def _check_paths(inputs: list[Path], out: Path) -> Path:
    """The resolved output folder, after refusing a file as ``--out``, missing inputs and colliding output names.

    Output names are the inputs' file names; two inputs whose names differ only in case are refused
    too, as they would overwrite each other on a case-insensitive file system.
    """
    from fluorocal.stages.errors import InputError

    out_dir = out.resolve()
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out} is a file; give a folder for the undistorted frames")
    seen: dict[str, Path] = {}
    for path in inputs:
        if not path.is_file():
            raise InputError(f"{path}: no such file" + (" (a folder)" if path.is_dir() else ""))
        if path.resolve().parent == out_dir:
            raise InputError(f"{path}: input lies in the output directory {out_dir}; choose another --out")
        other = seen.setdefault(path.name.casefold(), path)
        if other is not path:
            raise InputError(
                f"inputs {other} and {path} would both be written as {out_dir / path.name}; "
                "undistort them in separate runs with separate --out folders"
            )
    return out_dir
