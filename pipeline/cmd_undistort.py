r"""`fluorocal undistort`: remove a system's learned distortion from clinical or experimental frames.

Each INPUT (DICOM, TIFF, PNG or video; a file of one or many frames, or a
folder of them) is resampled onto the ideal pinhole image of the calibrated
system and written to --out under the same name, in the input's own format,
pixel type (sample type, channels, photometric) and metadata; a file
whose samples cannot be written back so is refused before anything is
written. DICOM outputs form a derived series: a new Series
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
(--orientation orbit=15,tilt=0; never beyond them). Without it, for a system
calibrated at orientations with C-arm angles, each frame's recorded angles
choose or interpolate its field: a file's PositionerPrimaryAngle (orbit) and
PositionerSecondaryAngle (tilt), or, for a rotational run (PositionerMotion
DYNAMIC), each frame's from the per-frame functional groups or from
PositionerPrimary/SecondaryAngleIncrement (one value: the change per frame;
one per frame: each frame's offset from the start angles, as DICOM PS3.3
C.8.7.5.1.3 says); the Derivation Description records
the angles used, and a frame beyond the calibrated angles is refused, naming
the frame and the calibrated range. A file without angles: the system's one
field, or the orientation named like the file's stem.
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
        "interpolate between calibrated ones (default: the C-arm angles each frame records, else the system's one "
        "field, or with several the orientation named like each input's file stem)",
    )
    add_out(p, "output folder (default: ./undistorted)", default=Path("undistorted"))
    p.add_argument(
        "--interpolation",
        choices=("linear", "cubic", "lanczos", "nearest"),
        default="linear",
        help="resampling kernel (default: linear)",
    )
    p.add_argument(
        "--outside",
        choices=("background", "keep"),
        default="background",
        help="output pixels whose source lies outside the field's support (where the calibration saw no bead or "
        "hole) or outside the frame's collimated area: set to the frame's background, or kept as remapped "
        "(default: background)",
    )
    add_overwrite(p, "output files that already exist")
    p.set_defaults(func=run)


def run(args) -> int:
    import logging
    import time
    from datetime import datetime

    from fluorocal.calibration import Calibration
    from fluorocal.stages.errors import InputError
    from fluorocal.streaming import stream
    from tqdm import tqdm

    log = logging.getLogger("fluorocal")
    inputs = expand_inputs(args.inputs)
    out_dir = _check_paths(inputs, args.out, overwrite=args.overwrite)  # every input and output before any work
    cal = Calibration.load(args.calibration)
    if args.system not in cal.systems:
        raise InputError(f"--system {args.system!r} is not in {args.calibration}; it has {', '.join(cal.system_names)}")
    chosen = None if args.orientation is None else parse_orientation(args.orientation)
    series = _derived_series(inputs)  # every DICOM input's references checked, a new series per source series

    when = datetime.now()  # the derivation's ContentDate and ContentTime, one for the run
    views: dict = {}  # orientation key -> (maps, where the field is supported), made once per orientation

    def jobs():
        for path in inputs:
            yield _job(cal, args, path, out_dir / path.name, chosen, (series[path], when), views)

    # every orientation's maps and every file's size checked before anything is written; the jobs themselves
    # (open readers, headers) are made again as the frames stream, so memory does not grow with the file count
    n_frames = sum(job.n_frames for job in jobs())
    out_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with tqdm(total=n_frames, desc="undistort", unit="frame", disable=args.quiet or None) as bar:

        def transform(item):
            job, index, frame = item
            bar.update()
            return job, job.remap(frame, index)

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
    """One input file: where it goes, each frame's orientation, and its frames as stored (written back as such)."""

    path: Path
    out: Path
    keys: tuple  # per frame, the key of its orientation in views
    views: dict  # orientation key -> ((map_x, map_y), (H, W) bool where the output's source is supported)
    params: UndistortParams
    n_frames: int
    derivation: Derivation
    stored: StoredFrames

    def remap(self, frame, index: int):
        import numpy as np
        from fluorocal.stages.undistort import clear_outside, remap_stored

        maps, supported = self.views[self.keys[index]]
        out = remap_stored(frame, *maps, self.params)
        if frame.ndim == 2:
            return clear_outside(frame, out, *maps, self.params, supported)
        # each colour channel as remap_stored resamples it: its own collimated area and background; an alpha
        # channel (the last of grey+alpha and RGBA) is no intensity and stays as remapped
        n_colour = out.shape[2] - (out.shape[2] in (2, 4))
        cleared = [clear_outside(frame[..., c], out[..., c], *maps, self.params, supported) for c in range(n_colour)]
        return np.stack(cleared + [out[..., c] for c in range(n_colour, out.shape[2])], axis=-1)


def _job(cal, args, path: Path, out: Path, chosen, made, views: dict) -> _Job:
    """The checked job of one input: its frames' size against the calibration's, each frame's orientation and maps.

    ``made`` is ``(series_uid, when)`` of its derivation; ``views`` is filled with the maps of each orientation.
    """
    import json

    from fluorocal.maps import orientation_key
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import open_stored
    from fluorocal.stages.undistort import UndistortParams, supported_output

    system = cal.systems[args.system]
    stored = open_stored(path)  # refuses, naming the file, what cannot be written back as stored
    n_frames, size = stored.n_frames, stored.size_px
    if tuple(size) != tuple(system.image_size_px):
        raise InputError(
            f"{path}: frame is {size[0]}x{size[1]} px; "
            f"system {args.system} was calibrated at {system.image_size_px[0]}x{system.image_size_px[1]}"
        )
    orientations, recorded = input_orientations(cal, args.system, path, chosen, n_frames)
    keys = []
    for i, orientation in enumerate(orientations):
        keys.append(json.dumps(orientation_key(orientation)))
        if keys[-1] in views:
            continue
        try:
            maps = cal.remap_maps(args.system, orientation=orientation)
        except InputError as exc:
            if not recorded:
                raise
            raise InputError(f"{path}, frame {i}: at the C-arm angles it records: {exc}") from None
        views[keys[-1]] = maps, supported_output(cal.field(args.system, orientation), *maps)
    border = stored.black  # the dark outside of the field, in stored units
    params = UndistortParams(args.interpolation, border, outside=args.outside)
    derivation = _derivation(cal, args, orientations, recorded, *made)
    return _Job(path, out, tuple(keys), views, params, n_frames, derivation, stored)


def _frames(jobs):
    """``(job, index, frame)`` for every frame of every job, read as they are asked for."""
    for job in jobs:
        for index, frame in enumerate(job.stored.frames):
            yield job, index, frame


def _write_all(items) -> None:
    """Write the ``(job, frame)`` items, file by file as they come, each file's frames streamed."""
    from itertools import groupby
    from operator import itemgetter

    from fluorocal.stages.io import write_stored_like

    for job, group in groupby(items, key=itemgetter(0)):  # jobs compare by identity
        frames = (frame for _, frame in group)
        write_stored_like(job.path, frames, job.out, job.n_frames, derivation=job.derivation)


def input_orientations(cal, system: str, path: Path, chosen, n_frames: int) -> tuple[tuple, bool]:
    """Each frame's orientation, and whether they are the angles the file records.

    ``chosen`` (``--orientation``) for every frame; else, for a system calibrated at orientations with
    C-arm angles, the angles each frame records (:func:`fluorocal.stages.io.dicom.frame_angles_deg`) when
    every frame records them; else the one field; else the orientation named like the file.
    """
    from fluorocal.orientations import default_orientation_name
    from fluorocal.stages.errors import InputError

    if chosen is not None:
        return (chosen,) * n_frames, False
    if any(o.has_angles for o in cal.systems[system].orientations):
        recorded = _recorded_angles(path, n_frames)
        if all(a is not None for a in recorded):
            return tuple({"orbit": orbit, "tilt": tilt} for orbit, tilt in recorded), True
    names = cal.orientation_names(system)
    if len(names) <= 1:
        return (None,) * n_frames, False
    stem = default_orientation_name(path)
    if stem in names:
        return (stem,) * n_frames, False
    raise InputError(
        f"{path}: system {system} is calibrated at {len(names)} orientations ({', '.join(names)}) and none is "
        f"named {stem!r} like this file, which records no C-arm angles; choose one with --orientation NAME, or "
        "--orientation orbit=DEG,tilt=DEG"
    )


def _recorded_angles(path: Path, n_frames: int) -> tuple:
    """Each frame's recorded ``(orbit, tilt)`` deg or None (formats other than DICOM record none)."""
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import dicom, frame_format

    if frame_format(path).name != dicom.NAME:
        return (None,) * n_frames
    angles = dicom.frame_angles_deg(path)
    if len(angles) != n_frames:
        raise InputError(f"{path}: the header gives C-arm angles for {len(angles)} frame(s); it holds {n_frames}")
    return angles


def expand_inputs(inputs: list[Path]) -> list[Path]:
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


def _derivation(cal, args, orientations: tuple, recorded: bool, series_uid: str | None, when=None) -> Derivation:
    """What one input's output records of its making: the calibration by name and content, system, orientation(s)."""
    from importlib.metadata import PackageNotFoundError, version

    from fluorocal.stages.io import Derivation

    try:
        by = f"fluorocal {version('fluorocal')}"
    except PackageNotFoundError:
        by = "fluorocal"
    where = _where(cal, args.system, orientations, recorded)
    digest = "" if cal.content_sha256 is None else f" (content sha256 {cal.content_sha256[:16]})"
    edges = " (outside the field's support and the collimated area: background)" if args.outside == "background" else ""
    head = f"geometric distortion corrected{edges} by {by} with calibration {Path(args.calibration).name}{digest}, "
    tail = f", {args.interpolation} interpolation"
    room = 1024 - len(head) - len(tail)
    if len(where) > room:  # a long rotational run: as many frames' angles as fit
        where = where[: room - 4].rsplit(",", 1)[0] + ", ..."
    return Derivation(f"{head}system {args.system}, {where}{tail}", series_uid, when)


def _where(cal, system: str, orientations: tuple, recorded: bool) -> str:
    """The orientation(s) used, as the Derivation Description names them."""
    first = orientations[0] if orientations else None
    if recorded and any(o != first for o in orientations):
        angles = ", ".join(f"{o['orbit']:g}/{o['tilt']:g}" for o in orientations)
        return f"per frame the field at the C-arm angles it records (orbit/tilt deg, frame by frame: {angles})"
    if isinstance(first, dict):
        source = " (the C-arm angles the file records)" if recorded else ""
        return f"orientation interpolated at orbit {first['orbit']:g} deg, tilt {first['tilt']:g} deg{source}"
    names = cal.orientation_names(system)
    name = first if first is not None else (names[0] if len(names) == 1 else None)
    return "the system's one field" if name is None else f"orientation {name}"
