"""Benchmark of the field per C-arm orientation (issue 12): interpolation to a held-out orientation.

Target (issue 12): calibrated at three orientations 30° apart, a held-out orientation in between gets
<= 0.10 px through interpolation (transfer from the nearest calibrated one: 0.16-0.40 px).

Protocol (``tests/pipeline/plate_orientation.py``), on the real ARCADIS grid frames
(``../shared/data/arcadis/grid_centered_0.dcm``, ``grid_tilt_15/30/45/60.dcm``; their angles given in the
config, the DICOMs record none) and on a simulated sequence (``fluorocal simulate OUT --phantom grid
--orientation orbit=0,tilt=0 ... --orientation orbit=0,tilt=60`` (tilts 0, 15, 30, 45, 60)
``--frames 1 --format dicom``, seed 0, 1024 px):

1. every frame is detected, centroided and labelled by the pipeline (``fluorocal run --until label``),
   one lattice numbering across the sequence;
2. the plate is calibrated (``calibrate_plate``, default ``[plate]`` unless ``--plate`` says otherwise)
   from the tilt 0, 30 and 60° frames only;
3. each held-out frame (tilt 15°, tilt 45°) is corrected by the field interpolated at its angles
   (``Calibration.field(system, orientation={"orbit": 0, "tilt": 15})``: the parabola through the three
   calibrated fields), by each of its two nearest calibrated orientations' fields (transfer), by the
   piecewise-linear interpolation between those two (a peer), and by none; the corrected hole centres
   are compared with the plate's self-calibrated layout (nominal + estimated plate errors, as in
   ``object_points.csv``) by the least-squares homography. Figure: RMS of the residual's length per
   hole, px, out-of-sample (the frame took no part in the calibration); per component = that / sqrt 2.
   Scored: the frame's holes whose plate error was estimated and where every calibrated field is
   supported, the same holes for every field;
4. for reference, each calibrated orientation's own held-out figure (its frame's even, then odd,
   lattice rows left out of the calibration in turn, the left-out holes scored as in 3).

On the simulated sequence, each field is also compared with the simulator's true correction at the
held-out orientation, modulo a homography (``tests/stages/plate_truth.py`` ``field_error_px``: RMS per
component over the field of view, px), and the interpolation is applied to the true fields of the
calibrated orientations too (the interpolant's own error).

Usage: ``OPENBLAS_NUM_THREADS=1 python benchmarks/orientation.py [--workdir DIR] [--skip-real]
[--skip-sim] [--no-own] [--plate KEY=VALUE ...]`` (``--workdir`` keeps the projects, their caches and the
simulated set for the next run; ``--plate`` sets ``PlateParams`` fields, e.g. ``orientation_spacing_px=32``).
"""

from __future__ import annotations

import argparse
import ast
import json
import math
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.pipeline.plate_orientation import (  # noqa: E402
    CALIBRATED,
    HELD_OUT,
    calibrate,
    held_out_frame,
    labelled_sequence,
    nearest,
    own_holdout_px,
    true_fields,
    write_real_project,
)

REAL_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "arcadis"
SIM_ANGLES = [f"orbit=0,tilt={tilt}" for tilt in (0, 15, 30, 45, 60)]
SIM_ARGS = [
    "--phantom",
    "grid",
    *(w for a in SIM_ANGLES for w in ("--orientation", a)),
    "--frames",
    "1",
    "--format",
    "dicom",
]


def linear_between(a, b, angles_deg):
    """The field linearly interpolated between orientations ``a`` and ``b`` at ``angles_deg`` (a peer)."""
    span = math.hypot(b.orbit_deg - a.orbit_deg, b.tilt_deg - a.tilt_deg)
    w = math.hypot(angles_deg[0] - a.orbit_deg, angles_deg[1] - a.tilt_deg) / span
    return a.field.with_delta((1 - w) * a.field.delta_px + w * b.field.delta_px)


def simulated_project(root: Path) -> Path:
    """The simulated sequence at ``root`` (reused when ``root`` holds the one this simulator writes)."""
    from fluorocal.cli import main
    from fluorocal.cmd_simulate import orientation_angles
    from fluorocal.stages.simulate import VERSION, SimulateParams

    truth_path = root / "truth.json"
    expected = SimulateParams(phantom="grid", n_frames=1, orientations_deg=orientation_angles(SIM_ANGLES))
    if truth_path.is_file():
        truth = json.loads(truth_path.read_text())
        params = json.loads(json.dumps(asdict(expected)))  # as truth.json spells them (tuples as lists)
        if truth.get("simulator_version") == VERSION and truth.get("params") == params:
            return root / "fluorocal.toml"
    if main(["--quiet", "simulate", str(root), *SIM_ARGS, "--overwrite"]) != 0:
        raise SystemExit("fluorocal simulate failed")
    return root / "fluorocal.toml"


def run(config: Path, plate, own: bool, truth: dict | None) -> None:
    """Measure and print one sequence's figures."""
    from fluorocal.stages.orientation import interpolate_field

    t0 = time.perf_counter()
    seq = labelled_sequence(config)
    t1 = time.perf_counter()
    cal, fields = calibrate(seq, CALIBRATED, plate)
    t2 = time.perf_counter()
    if seq.failed:
        print(f"  labelling failed on: {'; '.join(seq.failed)}")
    used = ", ".join(CALIBRATED)
    print(f"  labelled {len(seq.orientations)} frames in {t1 - t0:.1f} s; calibrated from {used} in {t2 - t1:.1f} s")
    print(f"  {cal.summary()}")
    truths = true_fields(truth) if truth else {}
    header = f"  {'held out':>8} {'holes':>5}  {'field':<34} {'RMS length px':>13} {'per comp. px':>12}"
    print(header + ("  vs truth px (per comp., mod H)" if truth else ""))
    for name in HELD_OUT:
        frame = held_out_frame(seq, cal, fields, name)
        a, b = nearest(fields, frame.angles_deg)
        rows = [
            ("interpolated (fluorocal)", interpolate_field(fields, *frame.angles_deg)),
            (f"linear {a.name}-{b.name} (peer)", linear_between(a, b, frame.angles_deg)),
            (f"transfer from {a.name}", a.field),
            (f"transfer from {b.name}", b.field),
            ("none", None),
        ]
        for label, field in rows:
            rms = frame.rms_px(field)
            line = f"  {name:>8} {frame.n_holes:>5}  {label:<34} {rms:>13.4f} {rms / math.sqrt(2):>12.4f}"
            if truth:
                line += f"  {_truth_error(field, truths[name], truth):.4f}"
            print(line)
    if truth:
        from fluorocal.stages.orientation import OrientationField

        exact = [OrientationField(f.name, f.orbit_deg, f.tilt_deg, truths[f.name]) for f in fields]
        for name in HELD_OUT:
            error = _truth_error(interpolate_field(exact, *seq.angles_of(name)), truths[name], truth)
            print(f"  {name:>8} interpolant on the true calibrated fields: {error:.4f} px vs truth (per comp., mod H)")
        for f in fields:
            error = _truth_error(f.field, truths[f.name], truth)
            print(f"  calibrated {f.name}: its field vs truth {error:.4f} px (per comp., mod H)")
    if own:
        for name in CALIBRATED:
            t = time.perf_counter()
            rms = own_holdout_px(seq, CALIBRATED, name, plate)
            took = time.perf_counter() - t
            print(
                f"  own held-out at calibrated {name}: {rms:.4f} px RMS length, {rms / math.sqrt(2):.4f} per component"
                f" (its frame's alternate rows left out in turn; {took:.1f} s)"
            )


def _truth_error(field, true, truth) -> float:
    from fluorocal.stages.field import CorrectionField

    from tests.stages.plate_truth import field_error_px

    if field is None:
        field = CorrectionField.constant(true.width_px, true.height_px)
    return field_error_px(field, true, truth["fov"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workdir", type=Path, help="keep the projects here (default: a temporary folder)")
    parser.add_argument("--skip-real", action="store_true", help="leave out the real frames")
    parser.add_argument("--skip-sim", action="store_true", help="leave out the simulated sequence")
    parser.add_argument("--no-own", action="store_true", help="leave out the own held-out figures (6 solves each)")
    parser.add_argument("--plate", nargs="*", default=[], metavar="KEY=VALUE", help="PlateParams fields")
    args = parser.parse_args()
    from fluorocal.stages.plate import PlateParams

    plate = PlateParams(**{k: ast.literal_eval(v) for k, v in (kv.split("=", 1) for kv in args.plate)})
    print(f"[plate] {plate}")
    with tempfile.TemporaryDirectory() as tmp:
        work = args.workdir or Path(tmp)
        if not args.skip_real:
            if REAL_DATA.is_dir():
                print(f"real ARCADIS frames ({REAL_DATA}):")
                run(write_real_project(work / "real", REAL_DATA), plate, not args.no_own, None)
            else:
                print(f"real frames: skipped, {REAL_DATA} is absent")
        if not args.skip_sim:
            config = simulated_project(work / "sim")
            print(f"simulated: fluorocal simulate {work / 'sim'} {' '.join(SIM_ARGS)}")
            run(config, plate, not args.no_own, json.loads((config.parent / "truth.json").read_text()))


if __name__ == "__main__":
    import docpage

    docpage.run(__file__, main)
