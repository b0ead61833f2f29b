"""`fluorocal adjust`: run the robust bundle adjustment alone on labelled observations (debugging).

Input: an observations CSV as written by `fluorocal label`
(file,frame,id,x,y,sigma_x,sigma_y,rho; px, x right, y down, top-left pixel
centre at 0,0), optionally with a `system` column (names; default "A") and
`dx`,`dy` distortion corrections (px, ideal = measured - correction). Frames
of each system are numbered in sorted (file, frame) order; frames of different
systems with the same number are one epoch (a biplanar pair). A phantom CSV
id,x,y,z (mm) gives the nominal bead coordinates.

Start values: each frame is resected (OpenCV solvePnP) with c = SID / pixel
pitch and the principal point at the image centre (--image-size).

Outputs in DIR: object_points.csv (id,x,y,z,sx,sy,sz; mm, in the nominal
frame), observations.csv (the input rows plus system,exposure,rx,ry residuals
in px, standardized wx,wy, redundancy numbers redx,redy, t-weight, inlier,
used) and orientation.json (IOP with standard deviations, poses, ROP,
sigma0, iterations, stop reason, usable).
"""

from __future__ import annotations

import argparse
from pathlib import Path


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
    p.add_argument(
        "--sid", type=float, default=1100.0, metavar="MM", help="source-image distance, approximate (default 1100)"
    )
    p.add_argument(
        "--pixel-pitch", type=float, default=0.25, metavar="MM", help="detector pixel pitch, approximate (default 0.25)"
    )
    p.add_argument(
        "--image-size",
        type=int,
        nargs=2,
        default=(1024, 1024),
        metavar=("W", "H"),
        help="image size in px (default 1024 1024)",
    )
    p.add_argument(
        "--nu", type=float, default=4.0, help="Student-t degrees of freedom; inf for least squares (default 4)"
    )
    p.add_argument(
        "--fixed-iop", action="store_true", help="hold (xp, yp, c) at the start values (default: estimate them)"
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output directory (created)")
    p.set_defaults(func=run)


def _read_observations(path: Path):
    """Observations, the (file, frame, row) keys in input order, and the corrections (N, 2)."""
    import csv

    import numpy as np
    from fluorocal.stages.artifacts import Observations
    from fluorocal.stages.errors import InputError

    if not path.is_file():
        raise InputError(f"{path}: observations file not found")
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        header = [h.strip() for h in (reader.fieldnames or [])]
        need = ["file", "frame", "id", "x", "y", "sigma_x", "sigma_y", "rho"]
        missing = [c for c in need if c not in header]
        if missing:
            raise InputError(f"{path}: observations CSV needs columns {','.join(need)}; missing {','.join(missing)}")
        rows = []
        for line_no, row in enumerate(reader, start=2):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k is not None}
            try:
                rows.append(
                    (
                        row.get("system") or "A",
                        row["file"],
                        int(row["frame"]),
                        int(row["id"]),
                        *(float(row[c]) for c in ("x", "y", "sigma_x", "sigma_y", "rho")),
                        float(row.get("dx") or 0.0),
                        float(row.get("dy") or 0.0),
                    )
                )
            except ValueError as exc:
                raise InputError(f"{path}:{line_no}: not a number ({exc})") from exc
    if not rows:
        raise InputError(f"{path}: no observations")
    names = tuple(sorted({r[0] for r in rows}))
    system = np.array([names.index(r[0]) for r in rows])
    exposure = np.empty(len(rows), dtype=np.int64)
    for s in range(len(names)):
        frames = sorted({(r[1], r[2]) for r, sy in zip(rows, system) if sy == s})
        number = {f: i for i, f in enumerate(frames)}
        for k, (r, sy) in enumerate(zip(rows, system)):
            if sy == s:
                exposure[k] = number[(r[1], r[2])]
    table = np.array([r[4:] for r in rows], dtype=np.float64)
    obs = Observations(
        system=system,
        exposure=exposure,
        bead_id=np.array([r[3] for r in rows]),
        xy_px=table[:, 0:2],
        sigma_px=table[:, 2:5],
        system_names=names,
    )
    return obs, rows, table[:, 5:7]


def run(args) -> int:
    """Read, adjust and write the outputs; return the exit code."""
    import logging

    import numpy as np
    from fluorocal.stages.adjust import FreeParameters, SolverOptions, adjust_bundle, initial_orientation
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import read_phantom

    log = logging.getLogger("fluorocal")
    if args.sid <= 0 or args.pixel_pitch <= 0:
        raise InputError(f"--sid and --pixel-pitch must be > 0; got {args.sid}, {args.pixel_pitch}")
    phantom = read_phantom(args.phantom)
    obs, rows, corrections = _read_observations(args.observations)
    w, h = args.image_size
    iop = np.array([(w - 1) / 2, (h - 1) / 2, args.sid / args.pixel_pitch])
    start = initial_orientation(obs, phantom, iop)
    # the flags own the choice of free parameters; the solver keeps its defaults but for ν
    free = FreeParameters(estimate_iop=not args.fixed_iop)
    res = adjust_bundle(obs, phantom, start, corrections, free=free, solver=SolverOptions(nu=args.nu))

    out = Path(args.out)
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
    return 0 if res.usable else 1


_OBSERVATION_COLUMNS = [
    "file",
    "frame",
    "system",
    "exposure",
    "id",
    "x",
    "y",
    "sigma_x",
    "sigma_y",
    "rho",
    "dx",
    "dy",
    "rx",
    "ry",
    "wx",
    "wy",
    "redx",
    "redy",
    "weight",
    "inlier",
    "used",
]


def _write_tables(out: Path, obs, rows, res) -> None:
    """object_points.csv and observations.csv (the input rows with the adjustment's per-observation outputs)."""
    from fluorocal.stages.io import write_csv

    write_csv(
        out / "object_points.csv",
        ["id", "x", "y", "z", "sx", "sy", "sz"],
        [[int(i), *map(float, p), *map(float, sd)] for i, p, sd in zip(res.bead_id, res.xyz_mm, res.xyz_std_mm)],
    )
    table = []
    for k, r in enumerate(rows):
        table.append(
            [
                r[1],
                r[2],
                r[0],
                int(obs.exposure[k]),
                r[3],
                *r[4:11],
                *map(float, res.residual_px[k]),
                *map(float, res.standardized_residual[k]),
                *map(float, res.redundancy[k]),
                float(res.weight[k]),
                int(res.inlier[k]),
                int(res.used[k]),
            ]
        )
    write_csv(out / "observations.csv", _OBSERVATION_COLUMNS, table)


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
        with open(tmp, "w") as fh:
            json.dump(data, fh, indent=1)

    atomic_write(path, _write)
