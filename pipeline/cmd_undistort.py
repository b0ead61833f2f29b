"""`fluorocal undistort`: remove a system's learned distortion from clinical or experimental frames.

Each INPUT (DICOM, TIFF, PNG or video) is resampled onto the ideal pinhole
image of the calibrated system and written to OUTDIR under the same name, in
the input's own format, bit depth and metadata (DICOM: a new SOP Instance
UID and a derivation note).

An image intensifier's distortion changes with the C-arm's orientation, so a
calibration may hold a field per orientation. --orientation chooses one by
name, or interpolates between calibrated ones at given angles
(--orientation orbit=15,tilt=0; never beyond them). Without it: the system's
one field, or the orientation named like each input's file stem.
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
        "--orientation",
        metavar="NAME",
        help="the C-arm orientation of the inputs: a calibrated orientation's name, or orbit=DEG,tilt=DEG to "
        "interpolate between calibrated ones (default: the system's one field, or with several the orientation "
        "named like each input's file stem)",
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
    from fluorocal.stages.undistort import UndistortParams, undistort_frame
    from tqdm import tqdm

    log = logging.getLogger("fluorocal")
    out_dir = _check_paths(args.inputs, args.out)  # every input and the output before any work
    cal = Calibration.load(args.calibration)
    system = cal.systems.get(args.system)
    if system is None:
        raise InputError(f"--system {args.system!r} is not in {args.calibration}; it has {', '.join(cal.system_names)}")
    chosen = None if args.orientation is None else parse_orientation(args.orientation)
    orientation_of = {path: _orientation_for(cal, args.system, path, chosen) for path in args.inputs}
    maps = {}  # orientation (hashable) -> remap maps, all checked before anything is written
    for orientation in orientation_of.values():
        key = _key(orientation)
        if key not in maps:
            maps[key] = _maps(cal, args, orientation)
    params = UndistortParams(interpolation=args.interpolation)
    for path in tqdm(args.inputs, desc="undistort", unit="file", disable=args.quiet or None):
        frames = read_frames(path)
        size = (frames[0].shape[1], frames[0].shape[0])
        if size != tuple(system.image_size_px):
            raise InputError(
                f"{path}: frame is {size[0]}x{size[1]} px; "
                f"system {args.system} was calibrated at {system.image_size_px[0]}x{system.image_size_px[1]}"
            )
        map_x, map_y = maps[_key(orientation_of[path])]
        corrected = [undistort_frame(f, map_x, map_y, params) for f in frames]
        out_dir.mkdir(parents=True, exist_ok=True)
        write_frames_like(path, corrected, out_dir / path.name)
        if orientation_of[path] is not None:
            log.debug("%s: orientation %s", path, orientation_of[path])
    log.info("wrote %d undistorted file(s) to %s", len(args.inputs), out_dir)
    return 0


def parse_orientation(text: str):
    """``--orientation``'s value: a name, or ``orbit=DEG,tilt=DEG`` as ``{"orbit": float, "tilt": float}``.

    Raises
    ------
    InputError
        ``key=value`` pairs that are not exactly orbit and tilt, each a number.

    Examples
    --------
    >>> parse_orientation("orbit30")
    'orbit30'
    >>> parse_orientation("orbit=15, tilt=-7.5")
    {'orbit': 15.0, 'tilt': -7.5}
    """
    from fluorocal.stages.errors import InputError

    if "=" not in text:
        return text
    values = {}
    for part in text.split(","):
        key, _, value = part.partition("=")
        try:
            values[key.strip()] = float(value)
        except ValueError:
            raise InputError(f"--orientation {text!r}: {key.strip()} must be a number of degrees") from None
    if set(values) != {"orbit", "tilt"} or text.count("=") != 2:
        raise InputError(f"--orientation {text!r}: expected a name, or orbit=DEG,tilt=DEG (both, nothing else)")
    return values


def _orientation_for(cal, system: str, path: Path, chosen):
    """The orientation to undistort ``path`` with: ``chosen``; else the one field; else the one named like the file."""
    from fluorocal.orientations import default_orientation_name
    from fluorocal.stages.errors import InputError

    names = cal.orientation_names(system)
    if chosen is not None or len(names) <= 1:
        return chosen
    stem = default_orientation_name(path)
    if stem in names:
        return stem
    raise InputError(
        f"{path}: system {system} is calibrated at {len(names)} orientations ({', '.join(names)}) and none is "
        f"named {stem!r} like this file; choose one with --orientation NAME, or --orientation orbit=DEG,tilt=DEG"
    )


def _key(orientation):
    return tuple(sorted(orientation.items())) if isinstance(orientation, dict) else orientation


def _maps(cal, args, orientation):
    """The checked remap maps of the system's field at ``orientation``."""
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.undistort import check_maps, check_shift

    system = cal.systems[args.system]
    where = f"{args.calibration}: system {args.system}" + (
        "" if orientation is None else f", orientation {orientation}"
    )
    try:
        field = cal.field(args.system, orientation)
        check_shift(field.delta_px, *system.image_size_px)  # the nodes first: a huge field overflows the maps
        map_x, map_y = field.remap_maps(*system.image_size_px)  # every input must have the calibrated size
        check_maps(map_x, map_y)
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from exc
    return map_x, map_y


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
