r"""`fluorocal undistort`: remove a system's learned distortion from clinical or experimental frames.

Each INPUT (DICOM, TIFF, PNG or video; a file of one or many frames, or a
folder of them) is resampled onto the ideal pinhole image of the calibrated
system and written to --out under the same name, in the input's own format,
bit depth and metadata. DICOM outputs form a derived series: a new Series
Instance UID per source series and run, a new SOP Instance UID per file,
ImageType DERIVED\SECONDARY, a Source Image Sequence naming the original and
a Derivation Description naming the calibration (file and content SHA-256),
the system and the orientation. An existing output file is refused, before
anything is read or written, unless --overwrite.
Frames stream: one is read while another is remapped and a third written, so
memory holds a few frames however many there are. The undistortion maps are
computed once per orientation and cached beside the calibration
(calibration.maps/).

An image intensifier's distortion changes with the C-arm's orientation, so a
calibration may hold a field per orientation. --orientation chooses one by
name, or interpolates between calibrated ones at given angles
(--orientation orbit=15,tilt=0; never beyond them). Without it: the system's
one field, or the orientation named like each input's file stem.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from fluorocal.cli_common import add_calibration, add_out, add_overwrite, parse_orientation

if TYPE_CHECKING:  # imported when run: `fluorocal undistort --help` loads neither OpenCV nor OpenImageIO
    from fluorocal.stages.io import Derivation, StoredFrames
    from fluorocal.stages.undistort import UndistortParams


def add_parser(subparsers) -> None:
    """Register the ``undistort`` subcommand."""
    p = subparsers.add_parser(
        "undistort",
        help="undistort frames with a calibration",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_calibration(p)
    p.add_argument(
        "inputs",
        nargs="+",
        type=Path,
        metavar="INPUT",
        help="frame files (single or multi-frame) or folders of them (their frame files, sorted by name)",
    )
    p.add_argument(
        "--system",
        required=True,
        metavar="NAME",
        help="the imaging system the frames come from (a name in the calibration)",
    )
    p.add_argument(
        "--orientation",
        metavar="NAME|orbit=DEG,tilt=DEG",
        help="the C-arm orientation of the inputs: a calibrated orientation's name, or orbit=DEG,tilt=DEG to "
        "interpolate between calibrated ones (default: the system's one field, or with several the orientation "
        "named like each input's file stem)",
    )
    add_out(p, "output folder (default: ./undistorted)", default=Path("undistorted"))
    p.add_argument(
        "--interpolation",
        choices=("linear", "cubic", "lanczos", "nearest"),
        default="linear",
        help="resampling kernel (default: linear)",
    )
    add_overwrite(p, "output files that already exist")
    p.set_defaults(func=run)


def run(args) -> int:
    import logging
    import time

    from fluorocal.calibration import Calibration
    from fluorocal.stages.errors import InputError
    from fluorocal.streaming import stream
    from tqdm import tqdm

    log = logging.getLogger("fluorocal")
    inputs = _expand(args.inputs)
    out_dir = _check_paths(inputs, args.out, overwrite=args.overwrite)  # every input and output before any work
    cal = Calibration.load(args.calibration)
    if args.system not in cal.systems:
        raise InputError(f"--system {args.system!r} is not in {args.calibration}; it has {', '.join(cal.system_names)}")
    chosen = None if args.orientation is None else parse_orientation(args.orientation)
    series = _derived_series(inputs)  # every DICOM input's references checked, a new series per source series

    def jobs():
        for path in inputs:
            orientation = _orientation_for(cal, args.system, path, chosen)
            derivation = _derivation(cal, args, orientation, series[path])
            yield _job(cal, args, path, out_dir / path.name, orientation, derivation)

    # every orientation's maps and every file's size checked before anything is written; the jobs themselves
    # (open readers, headers) are made again as the frames stream, so memory does not grow with the file count
    n_frames = sum(job.n_frames for job in jobs())
    out_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with tqdm(total=n_frames, desc="undistort", unit="frame", disable=args.quiet or None) as bar:

        def transform(item):
            job, frame = item
            bar.update()
            return job, job.remap(frame)

        stream(_frames(jobs()), transform, _write_all)
    seconds = time.perf_counter() - start
    log.info(
        "undistorted %d frame(s) of %d file(s) in %.2f s (%.1f frames/s) into %s",
        n_frames,
        len(inputs),
        seconds,
        n_frames / max(seconds, 1e-9),
        out_dir,
    )
    return 0


@dataclass(frozen=True, eq=False)
class _Job:
    """One input file: where it goes, its maps, and its frames as stored (None: read and written as radiographs)."""

    path: Path
    out: Path
    maps: tuple  # (map_x, map_y)
    params: UndistortParams
    n_frames: int
    derivation: Derivation
    stored: StoredFrames | None = None

    def remap(self, frame):
        from fluorocal.stages.undistort import remap_image, undistort_frame

        if self.stored is None:
            return undistort_frame(frame, *self.maps, self.params)
        return remap_image(frame, *self.maps, self.params)


def _job(cal, args, path: Path, out: Path, orientation, derivation: Derivation) -> _Job:
    """The checked job of one input: its frames' size against the calibration's, and its maps."""
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import open_stored, probe_frames
    from fluorocal.stages.undistort import UndistortParams

    system = cal.systems[args.system]
    stored = open_stored(path)
    n_frames, size = (stored.n_frames, stored.size_px) if stored is not None else probe_frames(path)
    if tuple(size) != tuple(system.image_size_px):
        raise InputError(
            f"{path}: frame is {size[0]}x{size[1]} px; "
            f"system {args.system} was calibrated at {system.image_size_px[0]}x{system.image_size_px[1]}"
        )
    maps = cal.remap_maps(args.system, orientation=orientation)
    border = 0.0 if stored is None else stored.black  # the dark outside of the field, in stored units
    return _Job(path, out, maps, UndistortParams(args.interpolation, border), n_frames, derivation, stored)


def _frames(jobs):
    """``(job, frame)`` for every frame of every job, read as they are asked for."""
    from fluorocal.stages.io import read_frames

    for job in jobs:
        for frame in read_frames(job.path) if job.stored is None else job.stored.frames:
            yield job, frame


def _write_all(items) -> None:
    """Write the ``(job, frame)`` items, file by file as they come: streamed where stored, else per file."""
    from itertools import groupby
    from operator import itemgetter

    from fluorocal.stages.io import write_frames_like, write_stored_like

    for job, group in groupby(items, key=itemgetter(0)):  # jobs compare by identity
        frames = (frame for _, frame in group)
        if job.stored is None:
            write_frames_like(job.path, list(frames), job.out, derivation=job.derivation)
        else:
            write_stored_like(job.path, frames, job.out, job.n_frames, derivation=job.derivation)


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


def _expand(inputs: list[Path]) -> list[Path]:
    """The input files: each file given, and each folder's frame files (sorted by name; not its sub-folders).

    Raises
    ------
    InputError
        A missing input, or a folder holding no file that a frame format claims.
    """
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import frame_format

    files = []
    for path in inputs:
        if not path.is_dir():
            files.append(path)
            continue
        found = []
        for entry in sorted(path.iterdir()):
            if entry.is_file() and not entry.name.startswith("."):
                try:
                    frame_format(entry)
                except InputError:
                    continue  # a folder of frames may hold notes, DICOMDIR indexes, ...
                found.append(entry)
        if not found:
            raise InputError(f"{path}: folder holds no frame file fluorocal reads")
        files.extend(found)
    return files


def _check_paths(inputs: list[Path], out: Path, *, overwrite: bool = False) -> Path:
    """The resolved output folder, after refusing a file as ``--out``, missing inputs and outputs that would clash.

    Output names are the inputs' file names; two inputs whose names differ only in case are refused
    too, as they would overwrite each other on a case-insensitive file system. An output that already
    exists is refused unless ``overwrite`` (a folder in its place always), whatever the format.
    """
    from fluorocal.stages.errors import InputError

    out_dir = out.resolve()
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out} is a file; give a folder for the undistorted frames")
    seen: dict[str, Path] = {}
    for path in inputs:
        if not path.is_file():
            raise InputError(f"{path}: no such file")
        if path.resolve().parent == out_dir:
            raise InputError(f"{path}: input lies in the output directory {out_dir}; choose another --out")
        other = seen.setdefault(path.name.casefold(), path)
        if other is not path:
            raise InputError(
                f"inputs {other} and {path} would both be written as {out_dir / path.name}; "
                "undistort them in separate runs with separate --out folders"
            )
        target = out_dir / path.name
        if target.is_dir():
            raise InputError(f"{target}: is a folder, where the undistorted {path.name} would go; choose another --out")
        if (target.exists() or target.is_symlink()) and not overwrite:
            raise InputError(f"{target}: already exists; add --overwrite to replace it, or choose another --out")
    return out_dir


def _derived_series(inputs: list[Path]) -> dict[Path, str | None]:
    """A new Series Instance UID for each input of a format with series (DICOM), one per source series; else None."""
    from fluorocal.stages.io import series_of
    from pydicom.uid import generate_uid

    found = {path: series_of(path) for path in inputs}
    new = {key: generate_uid() for key in dict.fromkeys(found.values()) if key is not None}
    return {path: new.get(key) for path, key in found.items()}


def _derivation(cal, args, orientation, series_uid: str | None) -> Derivation:
    """What one input's output records of its making: the calibration by name and content, system, orientation."""
    from importlib.metadata import PackageNotFoundError, version

    from fluorocal.stages.io import Derivation

    try:
        by = f"fluorocal {version('fluorocal')}"
    except PackageNotFoundError:
        by = "fluorocal"
    if isinstance(orientation, dict):
        where = f"orientation interpolated at orbit {orientation['orbit']:g} deg, tilt {orientation['tilt']:g} deg"
    else:
        names = cal.orientation_names(args.system)
        name = orientation if orientation is not None else (names[0] if len(names) == 1 else None)
        where = "the system's one field" if name is None else f"orientation {name}"
    digest = "" if cal.content_sha256 is None else f" (content sha256 {cal.content_sha256[:16]})"
    text = (
        f"geometric distortion corrected by {by} with calibration {Path(args.calibration).name}{digest}, "
        f"system {args.system}, {where}, {args.interpolation} interpolation"
    )
    return Derivation(text[:1024], series_uid)
