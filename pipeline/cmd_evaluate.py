"""`fluorocal evaluate CONFIG`: the paper's protocol (section VI, TABLE I) on a project's own frames.

Half the epochs (exposures; a biplanar pair is one epoch) are held out. For each
training size and scheme the project is calibrated on that many of the other
epochs (evenly spaced) and scored:

  in-sample      reprojection RMS of the training adjustment (inliers, px)
  out-of-sample  the held-out epochs adjusted with the calibrated IOP and correction held fixed
                 (poses and object points free): reprojection RMS (inliers, px)
  check points   with --reference: the training and held-out object points against the surveyed
                 points after a rigid (6-parameter) and a similarity (7-parameter) fit, RMS mm
  two-ray        biplanar projects: each held-out pair's beads intersected from their two rays
                 (calibrated IOP, ROP, fields), fitted per epoch onto the check points (or, without
                 --reference, the nominal phantom) by a rigid transform: X, Y, Z RMSE, their
                 average and the mean 3D error, mm (TABLE I's columns)

Schemes (default: none, polynomial, the project's [calibration] scheme and, with --reference,
opencv): none (IOP + EOP only, no field), polynomial (global radial + decentring model in the
adjustment), knn, knn+iop, knn+smooth, knn+iop+smooth (the learned field), and opencv
(cv2.calibrateCamera, rational + thin-prism + tilted model, on the check points; needs --reference).

The labelling is taken from the project's cache (`fluorocal run` fills it; what is missing is
computed once), never repeated per training size. Outputs, published as one set into --out:
evaluation.csv (a row per scheme and size), evaluation.md (the table; a line for every figure
where a peer beats fluorocal's scheme), evaluation_errors.png (each figure against the training
size), evaluation_improvement.png (over none) and evaluation_residuals_<system>.png (held-out
residuals of each scheme at the largest size).

Grid plates ([phantom] lattice) are scored on held-out holes instead: for every frame (--holdout: the
frames scored; default all) and lattice-row parity, each scheme is fitted without that frame's holes on
those rows, and the held-out holes, corrected, are compared by a best-fitting homography with the plate's
layout as self-calibrated from the same training holes, and with the nominal lattice (RMS lengths, px).
A training size counts the frames the plate is self-calibrated from: the scored frame (its other rows)
and others evenly spaced (default: 5 sizes up to every frame of a system). Schemes: plate (fluorocal's:
a field per orientation and the plate's errors, with the project's [plate]; always run, its layout is
the reference), none (a homography of the nominal plate per frame) and polynomial (the radial +
decentring model of scheme polynomial per orientation, the plate nominal). The in-sample figure is the
same comparison on the scored frames' training rows. No opencv for a plate: calibrateCamera needs the
plate seen at several tilts to fix its intrinsics, and a plate on the intensifier is seen square on.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fluorocal.cli_common import add_out, load_project, project_runner
from fluorocal.evaluate_common import SCHEME_NAMES


def add_parser(subparsers) -> None:
    """Register the ``evaluate`` subcommand."""
    p = subparsers.add_parser(
        "evaluate",
        help="the paper's held-out protocol on a project: schemes x training sizes, table and plots",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("config", type=Path, help="project TOML file")
    p.add_argument(
        "--holdout",
        action="append",
        metavar="RULE|FILE",
        help="held-out epochs: odd (every other one from the second; the default), even, random:SEED (half, "
        "drawn with SEED), or a frame file of the project (its epoch is held out in every system; repeat "
        "--holdout for several); for a grid plate the frames whose alternate rows are scored (default: every frame)",
    )
    p.add_argument(
        "--train-sizes",
        metavar="N,N,...",
        help="training epochs per calibration (default: 5 sizes evenly spaced up to all training epochs); for a "
        "grid plate, frames (default: 5 sizes up to every frame of a system)",
    )
    p.add_argument(
        "--schemes",
        metavar="a,b,...",
        help=f"comma-separated, of {', '.join(SCHEME_NAMES)} (default: none, polynomial, the project's scheme; "
        "opencv too with --reference); for a grid plate of none, polynomial, plate (default: all three)",
    )
    p.add_argument("--reference", type=Path, metavar="CSV", help="surveyed check points id,x,y,z mm (default: none)")
    add_out(p, "output folder (default: evaluation/ beside the config)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Evaluate the project as its phantom kind is evaluated (:meth:`fluorocal.kinds.KindPart.evaluate`)."""
    from fluorocal.kinds import part_of

    config, runner = _project(args)
    out_dir = _check_out(args, config)
    return part_of(config.phantom.kind).evaluate(args, config, runner, out_dir)


def _project(args):
    from fluorocal.kinds import part_of
    from fluorocal.stages.errors import InputError

    config = load_project(args.config)
    kind = config.phantom.kind
    if args.reference and not kind.check_points:
        raise InputError(f"--reference: {kind.noun} has no check points (scored on {part_of(kind).scored_on})")
    return config, project_runner(args, config, until="label")


def _check_out(args, config) -> Path:
    from fluorocal.export import check_outputs

    out = args.out if args.out is not None else config.path.parent / "evaluation"
    return check_outputs(config, out_dir=out)
