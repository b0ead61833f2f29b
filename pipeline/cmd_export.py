"""`fluorocal export`: a calibration in the formats of other tools (OpenCV, DLTdv/XMALab, MayaCam, mrcal, the paper's).

FORMAT is one of:

  opencv   OpenCV FileStorage YAML per system (and orientation): camera matrix, image size and the
           float32 undistortion maps for cv2.remap, exact, as byte planes (the file says how to join them)
  dlt      the 11 DLT coefficients per training exposure, one column per system (XMALab, DLTdv),
           on undistorted coordinates, with their reprojection RMS (dlt_rms.csv)
  mayacam  XMALab / Autoscoper MayaCam 2.0 camera files per system and training exposure
  mrcal    mrcal .cameramodel per system (and orientation): a splined stereographic model fitted
           to the field, the fit error stated in the file
  paper    the paper's text files: .iop, .eop, .xyz and .pho (image frame x = column, y = -row)

docs/exports.md gives each format's frame and units. A grid plate's calibration has no
interior orientation or poses: only opencv exports it (the maps, with the nominal camera matrix).
"""

from __future__ import annotations

import argparse

from fluorocal.cli_common import add_calibration, add_out, add_overwrite

#: the formats, as fluorocal.exports.FORMATS has them (listed here so that --help imports nothing)
FORMAT_NAMES = ("opencv", "dlt", "mayacam", "mrcal", "paper")


def add_parser(subparsers) -> None:
    """Register the ``export`` subcommand."""
    p = subparsers.add_parser(
        "export",
        help="export a calibration for OpenCV, DLTdv/XMALab, MayaCam, mrcal or the paper's formats",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_calibration(p)
    p.add_argument("--format", required=True, choices=FORMAT_NAMES, metavar="FORMAT", help=", ".join(FORMAT_NAMES))
    add_out(p, "output folder (new or empty; required)", required=True)
    add_overwrite(p, "the files of a non-empty --out")
    p.set_defaults(func=run)


def run(args) -> int:
    from fluorocal.exports import export

    for line in export(args.calibration, args.format, args.out, overwrite=args.overwrite):
        print(line)
    return 0
