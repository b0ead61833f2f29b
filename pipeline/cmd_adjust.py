"""`fluorocal adjust`: run the robust bundle adjustment alone on labelled observations (debugging).

Input: an observations CSV as written by `fluorocal label`, or the
observations.csv or label.csv of `fluorocal run` (file,id,x,y,sigma_x,sigma_y,
rho; px, x right, y down, top-left pixel centre at 0,0), optionally with
`frame` (default 0), `system` (names; default "A"), `exposure` and
`delta_x`,`delta_y` distortion corrections (px, ideal = measured - correction;
`dx`,`dy` accepted). Without an exposure column, frames of each system are
numbered in sorted (file, frame) order; frames of different systems with the
same exposure are one epoch (a biplanar pair). A phantom CSV
id,x,y,z (mm) gives the nominal bead coordinates.

Start values: each frame is resected (OpenCV solvePnP) with c =
--source-image-distance / --pixel-pitch and the principal point at the image
centre (--image-size).

Outputs in DIR: object_points.csv (id,x,y,z,sx,sy,sz; mm, in the nominal
frame), observations.csv (the input rows plus system,exposure,residual_x,
residual_y in px, standardized wx,wy, redundancy numbers redx,redy, t-weight,
inlier, used) and orientation.json (IOP with standard deviations, poses, ROP,
sigma0, iterations, stop reason, usable).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fluorocal.cli_common import add_geometry, add_image_size, add_out, add_overwrite, refuse_existing

#: what ``--out`` receives
OUTPUTS = ("object_points.csv", "observations.csv", "orientation.json")


def add_parser(subparsers) -> None:
    """Register the ``adjust`` subcommand."""
    p = subparsers.add_parser(
        "adjust",
        help="robust bundle adjustment of labelled observations (debugging)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--observations", type=Path, required=True, metavar="CSV", help="labelled observations (from `fluorocal label`)"
    )
    p.add_argument(
        "--phantom", type=Path, required=True, metavar="CSV", help="phantom CSV id,x,y,z[,diameter][,role] (mm)"
    )
    add_geometry(p, (1100.0, 0.25))
    add_image_size(p, "the principal point starts at its centre (default: 1024 1024)", (1024, 1024))
    p.add_argument(
        "--nu", type=float, default=4.0, help="Student-t degrees of freedom; inf for least squares (default 4)"
    )
    p.add_argument(
        "--fixed-iop", action="store_true", help="hold (xp, yp, c) at the start values (default: estimate them)"
    )
    add_out(p, "output folder (created; required)", required=True)
    add_overwrite(p, f"existing {', '.join(OUTPUTS)}")
    p.set_defaults(func=run)


def _read_observations(path: Path):
    """Observations, the table as read (:data:`~fluorocal.stages.io.OBSERVATIONS`) and the corrections (N, 2) px."""
    import numpy as np
    from fluorocal.stages.artifacts import Observations
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import OBSERVATIONS, check_finite, read_table

    table = read_table(path, OBSERVATIONS)
    if not len(table["id"]):
        raise InputError(f"{path}: no observations")
    check_finite(path, {c: table[c] for c in ("x", "y", "sigma_x", "sigma_y", "rho")})
    names = tuple(sorted(set(table["system"].tolist())))
    system = np.searchsorted(np.array(names), table["system"])
    exposure = table.get("exposure")
    if exposure is None:  # number each system's frames in sorted (file, frame) order
        exposure = np.empty(len(system), dtype=np.int64)
        keys = list(zip(table["file"].tolist(), table["frame"].tolist()))
        for s in range(len(names)):
            number = {f: i for i, f in enumerate(sorted({k for k, sy in zip(keys, system) if sy == s}))}
            exposure[system == s] = [number[k] for k, sy in zip(keys, system) if sy == s]
    obs = Observations(
        system=system,
        exposure=exposure,
        bead_id=table["id"],
        xy_px=np.stack([table["x"], table["y"]], axis=1),
        sigma_px=np.stack([table["sigma_x"], table["sigma_y"], table["rho"]], axis=1),
        system_names=names,
    )
    return obs, table, np.stack([table["delta_x"], table["delta_y"]], axis=1)


def run(args) -> int:
    """Read, adjust and write the outputs; return the exit code."""
    import logging
    import math

    from fluorocal.stages.adjust import FreeParameters, SolverOptions, adjust_bundle, initial_orientation
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.geometry import iop_guess
    from fluorocal.stages.io import read_phantom

    log = logging.getLogger("fluorocal")
    sid, pitch = args.source_image_distance, args.pixel_pitch
    if not (0 < sid < math.inf and 0 < pitch < math.inf):  # NaN and inf fail too
        raise InputError(f"--source-image-distance and --pixel-pitch must be finite and > 0; got {sid}, {pitch}")
    out = Path(args.out)
    refuse_existing([out / name for name in OUTPUTS], overwrite=args.overwrite)
    phantom = read_phantom(args.phantom)
    obs, rows, corrections = _read_observations(args.observations)
    w, h = args.image_size
    iop = iop_guess((w, h), sid, pitch)
    start = initial_orientation(obs, phantom, iop)
    # the flags own the choice of free parameters; the solver keeps its defaults but for ν
    free = FreeParameters(estimate_iop=not args.fixed_iop)
    res = adjust_bundle(obs, phantom, start, corrections, free=free, solver=SolverOptions(nu=args.nu))

    out.mkdir(parents=True, exist_ok=True)
    _write_tables(out, obs, rows, res)
    summary = _summary(res)
    _write_json(out / "orientation.json", summary)
    log.info(
        "adjusted %d observations (%d outliers, %d unused): σ0 %.3g, %d iterations (%s), usable %s -> %s",
        len(obs),
        summary["outliers"],
        summary["unused"],
        res.sigma0,
        res.iterations,
        res.stop_reason,
        res.usable,
        out,
    )
    if not res.usable:  # said in one line even with --quiet, not a bare exit code
        from fluorocal.stages.errors import EstimationError

        raise EstimationError(
            f"the adjustment of {args.observations} is not usable (σ0 {res.sigma0:.3g}, {res.stop_reason}); "
            f"its tables are in {out}; check --source-image-distance, --pixel-pitch and --image-size against the frames"
        )
    return 0


def _write_tables(out: Path, obs, table: dict, res) -> None:
    """``object_points.csv`` and ``observations.csv`` (the input rows with the adjustment's statistics)."""
    from fluorocal.export_tables import write_object_points
    from fluorocal.stages.io import OBSERVATIONS, write_table

    write_object_points(out / "object_points.csv", res.bead_id, res.xyz_mm, res.xyz_std_mm)
    columns = {name: table[name] for name in ("system", "file", "frame", "id", "x", "y", "sigma_x", "sigma_y", "rho")}
    columns.update(exposure=obs.exposure, delta_x=table["delta_x"], delta_y=table["delta_y"])
    columns.update(residual_x=res.residual_px[:, 0], residual_y=res.residual_px[:, 1])
    columns.update(wx=res.standardized_residual[:, 0], wy=res.standardized_residual[:, 1])
    columns.update(redx=res.redundancy[:, 0], redy=res.redundancy[:, 1], weight=res.weight)
    columns.update(inlier=res.inlier, used=res.used)
    write_table(out / "observations.csv", OBSERVATIONS, columns)


def _summary(res) -> dict:
    """The orientation and the solve's statistics, JSON-ready."""
    import math

    return {
        "system_names": list(res.system_names),
        "iop_px": res.iop_px.tolist(),
        "iop_std_px": res.iop_std_px.tolist(),
        "exposure": res.exposure.tolist(),
        "q_cam_from_obj": res.q_cam_from_obj.tolist(),
        "source_mm": res.source_mm.tolist(),
        "pose_std": res.pose_std.tolist(),
        "rop_q": res.rop_q.tolist(),
        "rop_source_mm": res.rop_source_mm.tolist(),
        "rop_std": res.rop_std.tolist(),
        "sigma0": res.sigma0,
        "t_scale": res.t_scale,
        "nu": res.nu if math.isfinite(res.nu) else "inf",
        "dof": res.dof,
        "n_parameters": res.n_parameters,
        "iterations": res.iterations,
        "stop_reason": res.stop_reason,
        "converged": res.converged,
        "usable": res.usable,
        "cost_history": list(res.cost_history),
        "outliers": int((~res.inlier & res.used).sum()),
        "unused": int((~res.used).sum()),
    }


def _write_json(path: Path, data: dict) -> None:
    import json

    from fluorocal.stages.io import atomic_write

    def _write(tmp):
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(data, fh, indent=1)

    atomic_write(path, _write)
