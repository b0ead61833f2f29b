"""`fluorocal simulate OUTDIR`: write a synthetic data set with its ground truth and a ready-to-run config.

Layout of OUTDIR::

    frames/A/frame_000.tif ...   16-bit TIFF holding 12-bit values (0-4095), or frame_000.dcm (DICOM XA,
                                 BitsStored 12) with --format dicom; with --orientation (grid plate)
                                 frame_000_centred.dcm, frame_001_tilt15.dcm, ...: exposure, then the
                                 C-arm orientation's name (DICOM PositionerPrimaryAngle = orbit,
                                 PositionerSecondaryAngle = tilt, degrees)
    frames/B/...                 second system (--systems 2); frames pair with A's in sorted order
    phantom.csv                  id,x,y,z,diameter,role: the nominal (design) phantom, mm
    reference.csv                id,x,y,z: reference check points (true + survey noise), mm
    truth.json                   ground truth (schema below)
    fluorocal.toml               project config: `fluorocal run OUTDIR/fluorocal.toml`
    montage.png                  a few frames side by side, downscaled

truth.json schema (version 1; px = pixels with the top-left pixel centre at
(0, 0), x right, y down; mm in phantom coordinates; quaternions (w, x, y, z)
rotate phantom vectors into the camera frame, ``p = R(q) (P - T)``)::

    schema              "fluorocal-simulation-truth"
    schema_version      1
    simulator_version   int (stages.simulate.VERSION)
    params              every SimulateParams field (defaults filled in)
    image_size_px       int
    fov                 {centre_xy_px: [x, y], radius_px}: round field of view
    phantom             {kind: "cube"|"grid", ids[N], diameter_mm[N], role[N],
                         nominal_xyz_mm[N][3], true_xyz_mm[N][3], reference_xyz_mm[N][3]}
    systems[S]          {name, iop_px: [xp, yp, c], source_image_distance_mm, pixel_pitch_mm,
                         lab_from_camera_q[4], source_lab_mm[3]  (lab: z up, isocentre at 0),
                         distortion: forward model ideal -> distorted, the parameters of
                             stages.simulate.ImageDistortion {model, centre_xy_px, scale_px,
                             k1, k2, s_rad, p1, p2, field_spacing_px, field_origin_xy_px,
                             field_coeffs_px[2][ny][nx], poly_coeffs_px[2][10] (only when not
                             zero: a cubic displacement, see ImageDistortion)},
                         correction_grid: {x_px[nx], y_px[ny], delta_px[ny][nx][2]}:
                             DESIGN's correction Δ on measured (distorted) coordinates,
                             ideal = measured - Δ(measured),
                         orientations[O] (grid with --orientation only; the distortion above is
                             the centred one): {name, orbit_deg, tilt_deg, exposures[] (its
                             exposure indices), field_change[3] (change of the unit earth field in
                             the intensifier's frame), distortion, correction_grid (as above, at
                             this orientation)}}
    exposures[K]        {turntable_angle_rad, turntable_translation_mm[3], lab_from_phantom_q[4]}
                        (grid with --orientation: the plate's turn about its normal and its
                        place as if the C-arm stayed centred; its pose to the camera is q, source_mm)
    frames[S*K]         {system: name, exposure: k, q[4], source_mm[3] (pose (q, T) in phantom coordinates),
                         orientation, orbit_deg, tilt_deg (grid with --orientation only: the
                             exposure's orientation's name and C-arm angles, degrees),
                         beads: per bead whose outline meets the field of view (id order):
                           ids[n], ideal_xy_px[n][2] (pinhole projection of the centre),
                           distorted_xy_px[n][2] (that, distorted),
                           outline_ideal_xy_px[n][2] (centre of the ideal outline ellipse),
                           outline_xy_px[n][2] (area centroid of the distorted outline: what an
                               ideal centroid of the bead's silhouette measures),
                           diameter_px[n] (equal-area diameter of the distorted outline),
                           overlap[n] (outline within overlap_margin_px of another bead's),
                           field_edge[n] (outline within overlap_margin_px of the field rim or image border)}

Frame files are named frame_<exposure>.tif (frame_<exposure>_<orientation>.tif with
--orientation), so sorted names follow the exposures; ``frames`` lists system A's
exposures first, then B's. With --orientation, fluorocal.toml names each
orientation's frames and angles in the system's ``orientations`` list.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fluorocal.cli_common import add_image_size, add_overwrite, parse_orientation

FORMATS = {"tiff": ".tif", "dicom": ".dcm"}


def add_parser(subparsers) -> None:
    """Register the ``simulate`` subcommand."""
    p = subparsers.add_parser(
        "simulate",
        help="write a synthetic data set with ground truth and a config",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "outdir", type=Path, metavar="OUTDIR", help="output directory (must be empty or absent unless --overwrite)"
    )
    p.add_argument(
        "--frames", type=int, default=12, metavar="N", help="exposures per system, or per orientation (default: 12)"
    )
    p.add_argument("--systems", type=int, choices=(1, 2), default=1, help="1 = monoplanar, 2 = biplanar (default: 1)")
    p.add_argument("--seed", type=int, default=0, help="random seed; same seed, same bytes (default: 0)")
    add_image_size(p, "square (W = H); the detector stays 256 mm wide (default: 1024 1024)", (1024, 1024))
    p.add_argument(
        "--distortion",
        choices=("none", "mild", "strong"),
        default="strong",
        help="image-intensifier distortion (default: strong, ~15 px at the field edge)",
    )
    p.add_argument(
        "--phantom",
        choices=("cube", "grid"),
        default="cube",
        help="cube: 494 steel beads on an acrylic box; grid: perforated hex plate, 1 system only (default: cube)",
    )
    p.add_argument(
        "--orientation",
        action="append",
        default=[],
        metavar="orbit=DEG,tilt=DEG",
        help="grid plate only: a C-arm orientation to expose at, repeated for each (e.g. --orientation orbit=0,tilt=0"
        " --orientation orbit=0,tilt=15); --frames is then per orientation (default: none, every frame centred"
        " with the plate moved by hand between frames)",
    )
    p.add_argument(
        "--plate-error",
        type=float,
        default=None,
        metavar="MM",
        help="grid plate only: RMS of the holes' manufacturing errors in mm (default: 0.02)",
    )
    p.add_argument(
        "--format", choices=tuple(FORMATS), default="tiff", help="frame files: 16-bit TIFF or DICOM XA (default: tiff)"
    )
    p.add_argument(
        "--noise", type=float, default=1.0, metavar="SCALE", help="noise scale, 0 for noise-free frames (default: 1.0)"
    )
    add_overwrite(p, "the files of a non-empty OUTDIR (earlier frames)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Simulate and write the data set; return the exit code."""
    import logging

    from fluorocal.stages.errors import InputError
    from fluorocal.stages.simulate import SimulateParams, simulate

    log = logging.getLogger("fluorocal")
    outdir = Path(args.outdir)
    if outdir.exists() and not outdir.is_dir():
        raise InputError(f"OUTDIR {outdir} exists and is not a directory")
    if outdir.is_dir() and any(outdir.iterdir()) and not args.overwrite:
        raise InputError(f"OUTDIR {outdir} is not empty; pass --overwrite to write into it")
    grid_only = {"--orientation": args.orientation, "--plate-error": args.plate_error}
    for option, value in grid_only.items():
        if value not in ([], None) and args.phantom != "grid":
            raise InputError(f"{option} is for the grid plate; add --phantom grid")
    width, height = args.image_size
    if width != height:
        raise InputError(f"--image-size: simulated frames are square; got {width} {height} (give W = H)")
    by_option = {  # option -> (SimulateParams field, value)
        "--frames": ("n_frames", args.frames),
        "--seed": ("seed", args.seed),
        "--image-size": ("image_size_px", width),
        "--noise": ("noise_scale", args.noise),
        "--orientation": ("orientations_deg", orientation_angles(args.orientation)),
    }
    if args.plate_error is not None:
        by_option["--plate-error"] = ("plate_error_mm", args.plate_error)
    values = dict(by_option.values())
    try:
        params = SimulateParams(n_systems=args.systems, distortion=args.distortion, phantom=args.phantom, **values)
    except InputError as exc:  # name the option the user typed, not the parameter behind it
        option = next((o for o, (name, _) in by_option.items() if str(exc).startswith(name)), None)
        raise InputError(f"{option}: {exc}" if option else str(exc)) from None
    from tqdm import tqdm

    quiet = bool(getattr(args, "quiet", False))
    with tqdm(
        total=params.n_exposures * params.n_systems, desc="simulate", unit="frame", disable=True if quiet else None
    ) as bar:
        data = simulate(params, on_frame=lambda s, k: bar.update())
    written = write_dataset(data, outdir, fmt=args.format, replace=args.overwrite)
    log.info("wrote %d files to %s (run: fluorocal run %s)", len(written), outdir, outdir / "fluorocal.toml")
    return 0


def orientation_angles(values: list[str]) -> tuple:
    """The repeated ``--orientation orbit=DEG,tilt=DEG`` as ``((orbit, tilt), ...)`` in degrees.

    Raises
    ------
    InputError
        A value that is not ``orbit=DEG,tilt=DEG`` (a name too: a simulation has no calibrated orientations).

    Examples
    --------
    >>> orientation_angles(["orbit=0,tilt=0", "orbit=-30, tilt=7.5"])
    ((0.0, 0.0), (-30.0, 7.5))
    """
    from fluorocal.stages.errors import InputError

    pairs = []
    for text in values:
        angles = parse_orientation(text)
        if isinstance(angles, str):
            raise InputError(f"--orientation {text!r}: a simulation needs the angles, orbit=DEG,tilt=DEG")
        pairs.append((angles["orbit"], angles["tilt"]))
    return tuple(pairs)


def frame_name(data, exposure: int) -> str:
    """File stem of an exposure: ``frame_003``, or ``frame_003_tilt15`` in a sequence of orientations."""
    o = int(data.truth.acquisition.exposure_orientation[exposure])
    suffix = f"_{data.truth.acquisition.orientations[o].name}" if o >= 0 else ""
    return f"frame_{exposure:03d}{suffix}"


def write_dataset(data, outdir: Path, *, fmt: str = "tiff", replace: bool = False) -> list[Path]:
    """Write a :class:`stages.simulate.SimulatedData` as a project directory (layout in the module docstring).

    Every file is written atomically. With ``replace``, frame files of an
    earlier data set in ``outdir/frames`` are removed first, so the config's
    globs see only the new frames.

    Returns
    -------
    list of Path
        The files written.
    """
    import json

    import numpy as np
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import PHANTOM, write_dicom, write_png, write_still, write_table
    from fluorocal.stages.simulate import truth_to_dict

    if fmt not in FORMATS:
        raise InputError(f"fmt must be one of {', '.join(FORMATS)}; got {fmt!r}")
    outdir = Path(outdir)
    if replace and (outdir / "frames").is_dir():
        for old in (outdir / "frames").glob("*/frame_*"):
            if old.suffix in FORMATS.values():
                old.unlink()
    written = []
    suffix = FORMATS[fmt]
    for s, frames in enumerate(data.frames):
        for k, frame in enumerate(frames):
            path = outdir / "frames" / data.system_names[s] / f"{frame_name(data, k)}{suffix}"
            pixels = frame.image.astype(np.uint16)
            if fmt == "tiff":
                write_still(path, pixels, attributes={"DateTime": _TIFF_DATETIME, "compression": "zip"})
            else:
                write_dicom(path, _dicom_dataset(data, s, k, pixels), pixels)
            written.append(path)

    phantom = data.phantom
    xyz, ref = phantom.xyz_mm, data.truth.reference_xyz_mm
    nominal = {"id": phantom.ids, "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    write_table(outdir / "phantom.csv", PHANTOM, {**nominal, "diameter": phantom.diameter_mm, "role": phantom.role})
    write_table(outdir / "reference.csv", PHANTOM, {"id": phantom.ids, "x": ref[:, 0], "y": ref[:, 1], "z": ref[:, 2]})
    written += [outdir / "phantom.csv", outdir / "reference.csv"]

    truth_text = json.dumps(truth_to_dict(data), separators=(",", ":"))
    written.append(_write_text(outdir / "truth.json", truth_text + "\n"))
    written.append(_write_text(outdir / "fluorocal.toml", _config_text(data, suffix)))
    if any(data.frames):
        write_png(outdir / "montage.png", montage(data), compression=9)
        written.append(outdir / "montage.png")
    return written


#: TIFF DateTime written into every frame, so that the same seed gives the same bytes
_TIFF_DATETIME = "2026:01:01 12:00:00"


def _write_text(path: Path, text: str) -> Path:
    from fluorocal.stages.io import atomic_write

    atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
    return path


def _config_text(data, suffix: str) -> str:
    """The project TOML (DESIGN.md format) for the written data set."""
    p = data.params
    orientations = "".join(f" --orientation orbit={o:g},tilt={t:g}" for o, t in p.orientations_deg)
    lines = [
        "# fluorocal project for a simulated data set: fluorocal simulate "
        f"--seed {p.seed} --frames {p.n_frames} --systems {p.n_systems}",
        f"#   --image-size {p.image_size_px} {p.image_size_px} --distortion {p.distortion} --phantom {p.phantom}"
        + orientations
        + ". Ground truth: truth.json.",
        "",
        "[phantom]",
        'file = "phantom.csv"',
    ]
    if p.phantom == "grid":
        lines += ['lattice = "hex"', f"pitch = {p.grid_pitch_mm}               # mm between neighbouring holes"]
    for name in data.system_names:
        lines += [
            "",
            "[[systems]]",
            f'name = "{name}"',
            f'frames = "frames/{name}/*{suffix}"',
            f"source_image_distance = {p.source_image_distance_mm:g}   "
            "# mm, approximate (nominal; the truth differs by up to 1 %)",
            f"pixel_pitch = {p.pixel_pitch_mm:g}              # mm at the detector",
        ]
        lines += _orientation_lines(data, name, suffix)
    lines += [
        "",
        "[calibration]",
        'scheme = "knn+iop+smooth"',
        "",
        "[output]",
        'dir = "out"',
        "",
    ]
    return "\n".join(lines)


def _orientation_lines(data, system: str, suffix: str) -> list[str]:
    """The system's ``orientations`` list (TOML): each orientation's name, frames and C-arm angles (degrees)."""
    import numpy as np

    acq = data.truth.acquisition
    if not acq.orientations:
        if data.params.phantom != "grid":
            return []
        # a plate moved by hand between frames at one C-arm position: the frames share one field
        return [
            'orientations = [{name = "centred", frames = "frames/' + system + "/*" + suffix + '", orbit = 0, tilt = 0}]'
        ]
    lines = ["orientations = ["]
    for i, o in enumerate(acq.orientations):
        files = ", ".join(
            f'"frames/{system}/{frame_name(data, k)}{suffix}"' for k in np.flatnonzero(acq.exposure_orientation == i)
        )
        lines.append(f'  {{name = "{o.name}", frames = [{files}], orbit = {o.orbit_deg:g}, tilt = {o.tilt_deg:g}}},')
    return lines + ["]"]


def montage(data, *, n_max: int = 4, tile_px: int = 256):
    """Up to ``n_max`` frames side by side (8-bit, each ``tile_px`` square); both systems when biplanar."""
    picks = []
    n_sys = len(data.frames)
    per_system = max(1, n_max // n_sys)
    for k in range(per_system):
        for s in range(n_sys):
            frames = data.frames[s]
            if frames:
                picks.append(frames[(k * len(frames)) // per_system])
    return tile_row(picks[:n_max], tile_px=tile_px)


def tile_row(frames, *, tile_px: int = 256):
    """Frames side by side as one 8-bit image, each downscaled to ``tile_px`` square and contrast-stretched."""
    import cv2
    import numpy as np

    tiles = []
    for frame in frames:
        img = frame.image
        lo, hi = np.percentile(img, [1, 99.5])
        tile = cv2.resize(img, (tile_px, tile_px), interpolation=cv2.INTER_AREA)
        tiles.append(np.clip((tile - lo) * 255.0 / max(hi - lo, 1.0), 0, 255).astype(np.uint8))
    gap = np.zeros((tile_px, 4), np.uint8)
    row = [t for tile in tiles for t in (tile, gap)][:-1]
    return np.hstack(row)


def _dicom_dataset(data, system: int, exposure: int, pixels):
    """A DICOM XA dataset with realistic tags for one frame (UIDs derived from the seed)."""
    import numpy as np
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, XRayAngiographicImageStorage, generate_uid

    p = data.params
    sys_truth = data.truth.systems[system]
    seed = f"fluorocal-sim-{p.seed}"
    study_uid = generate_uid(entropy_srcs=[seed, "study"])
    series_uid = generate_uid(entropy_srcs=[seed, "series", sys_truth.name])
    sop_uid = generate_uid(entropy_srcs=[seed, "image", sys_truth.name, str(exposure)])

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = XRayAngiographicImageStorage
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian

    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = XRayAngiographicImageStorage
    ds.SOPInstanceUID = sop_uid
    ds.StudyInstanceUID = study_uid
    ds.SeriesInstanceUID = series_uid
    ds.FrameOfReferenceUID = generate_uid(entropy_srcs=[seed, "frame-of-reference"])
    ds.Modality = "XA"
    ds.Manufacturer = "fluorocal"
    ds.ManufacturerModelName = "simulator"
    ds.SoftwareVersions = "fluorocal simulate"
    ds.ImageType = ["ORIGINAL", "PRIMARY", "BIPLANE " + sys_truth.name if len(data.frames) > 1 else "SINGLE PLANE"]
    ds.PatientName = f"PHANTOM^{p.phantom.upper()}"
    ds.PatientID = f"SIM{p.seed}"
    ds.StudyDate = ds.SeriesDate = ds.ContentDate = "20260101"
    ds.StudyTime = ds.SeriesTime = "120000"
    ds.ContentTime = f"12{exposure // 60:02d}{exposure % 60:02d}"
    ds.StudyID = "1"
    ds.SeriesNumber = system + 1
    ds.InstanceNumber = exposure + 1
    ds.AcquisitionNumber = exposure + 1
    ds.PositionerMotion = "STATIC"
    acq = data.truth.acquisition
    o = int(acq.exposure_orientation[exposure])
    if o >= 0:  # a grid sequence: the C-arm's orbit and tilt
        ds.PositionerPrimaryAngle = round(acq.orientations[o].orbit_deg, 3)
        ds.PositionerSecondaryAngle = round(acq.orientations[o].tilt_deg, 3)
    else:
        ds.PositionerPrimaryAngle = round(system * p.system_angle_deg, 3)
        ds.PositionerSecondaryAngle = 0
    ds.KVP = 70
    ds.XRayTubeCurrent = 5
    ds.ExposureTime = 10
    ds.FocalSpots = p.focal_spot_mm
    ds.DistanceSourceToDetector = round(sys_truth.source_image_distance_mm, 3)
    ds.DistanceSourceToPatient = round(p.source_image_distance_mm / p.magnification, 3)
    ds.EstimatedRadiographicMagnificationFactor = p.magnification
    ds.ImagerPixelSpacing = [p.pixel_pitch_mm, p.pixel_pitch_mm]
    ds.FieldOfViewShape = "ROUND"
    ds.FieldOfViewDimensions = [int(round(2 * p.fov_radius_px * p.pixel_pitch_mm))]
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = pixels.shape
    ds.BitsAllocated = 16
    ds.BitsStored = p.bit_depth
    ds.HighBit = p.bit_depth - 1
    ds.PixelRepresentation = 0
    ds.PixelIntensityRelationship = "LIN"
    ds.PixelData = np.ascontiguousarray(pixels, dtype="<u2").tobytes()
    return ds
