"""From the pipeline's tables to the plate solve and back: orientation groups, per-system problems, the artifact."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.errors import InputError
from fluorocal.stages.label.lattice import lattice_index, lattice_xyz_mm
from fluorocal.stages.plate.result import PlateCalibration
from fluorocal.stages.plate.solve import PlateProblem


@dataclass(frozen=True)
class Groups:
    """The orientations of every system: names, systems, angles, and the orientation of each frame."""

    names: tuple  # (O,) orientation names
    system: np.ndarray  # (O,) system of each orientation
    angles_deg: np.ndarray  # (O, 2) (orbit, tilt), NaN where unknown
    of_frame: dict  # (system, exposure) -> orientation index


def frame_orientations(observations, orientations) -> Groups:
    """Group the labelled frames into orientations, numbered in order of first appearance.

    An orientation none of whose frames was labelled gets no field (its frames are reported as failed).

    Raises
    ------
    InputError
        A frame with observations but no orientation, or one orientation named with two sets of angles.
    """
    names, systems, angles, of_frame = [], [], [], {}
    index: dict[tuple[int, str], int] = {}
    frames = set(zip(observations.system.tolist(), observations.exposure.tolist()))
    for system, exposure, name, orbit, tilt in orientations:
        if (int(system), int(exposure)) not in frames:
            continue
        key = (int(system), str(name))
        pair = (np.nan if orbit is None else float(orbit), np.nan if tilt is None else float(tilt))
        if key not in index:
            index[key] = len(names)
            names.append(str(name))
            systems.append(int(system))
            angles.append(pair)
        elif not np.allclose(angles[index[key]], pair, equal_nan=True):
            raise InputError(f"orientation {name!r} is given two sets of angles: {angles[index[key]]} and {pair}")
        of_frame[(int(system), int(exposure))] = index[key]
    missing = sorted(frames - set(of_frame))
    if missing:
        raise InputError(f"frames (system, exposure) {missing[:5]} have no orientation")
    return Groups(tuple(names), np.array(systems, np.int64), np.array(angles, float).reshape(-1, 2), of_frame)


def plate_problem(observations, phantom, system: int, groups: Groups, image_size) -> tuple[PlateProblem, dict]:
    """The plate problem of one system, sorted by frame, and how its rows map back.

    Returns
    -------
    problem : PlateProblem
        Orientations numbered within the system.
    index : dict
        ``rows`` (N,) the observations' rows in ``observations``; ``exposures`` (F,) each frame's exposure;
        ``hole_ids`` (K,) each hole's lattice id; ``orientations`` (O_s,) the global orientation indices.
    """
    rows = np.flatnonzero(observations.system == system)
    if not len(rows):
        raise InputError(f"system {observations.system_names[system]} has no labelled hole")
    rows = rows[np.argsort(observations.exposure[rows], kind="stable")]
    exposures, frame = np.unique(observations.exposure[rows], return_inverse=True)
    hole_ids, hole = np.unique(observations.bead_id[rows], return_inverse=True)
    global_orient = np.array([groups.of_frame[(system, int(e))] for e in exposures])
    orientations, local = np.unique(global_orient, return_inverse=True)
    nominal = lattice_xyz_mm(lattice_index(hole_ids), phantom.lattice, phantom.pitch_mm)[:, :2]
    problem = PlateProblem(
        frame.astype(np.int64),
        local.astype(np.int64),
        hole.astype(np.int64),
        nominal,
        observations.xy_px[rows],
        observations.sigma_px[rows],
        tuple(int(v) for v in image_size),
    )
    return problem, {"rows": rows, "exposures": exposures, "hole_ids": hole_ids, "orientations": orientations}


def stacked(observations, groups: Groups, parts, wall_time_s: float, outlier_weight: float) -> PlateCalibration:
    """One :class:`PlateCalibration` of the systems' ``(problem, index, solution)``, rows in input order.

    An observation is an outlier when its Student-t weight is below ``outlier_weight`` (the adjustment's rule).
    """
    n = len(observations.system)
    residual, initial, weight = np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n)
    fields = [None] * len(groups.names)
    n_sys = len(parts)
    order, tau = np.zeros((n_sys, 2), np.int64), np.zeros((n_sys, 2))
    frames, holes = [], []
    for s, (problem, index, sol) in enumerate(parts):
        rows = index["rows"]
        residual[rows], initial[rows], weight[rows] = sol.residual_px, sol.initial_residual_px, sol.weight
        for local, o in enumerate(index["orientations"]):
            fields[o] = sol.fields[local]
        (order[s, 0], tau[s, 0]), (order[s, 1], tau[s, 1]) = sol.smoothness
        frames.append(
            (
                np.full(problem.n_frames, s),
                index["exposures"],
                index["orientations"][problem.orientation_of_frame],
                sol.homography,
            )
        )
        holes.append(
            (
                np.full(len(index["hole_ids"]), s),
                index["hole_ids"],
                problem.nominal_mm,
                sol.plate_error_mm,
                sol.plate_error_std_mm,
                sol.plate_estimated,
            )
        )
    inlier = weight >= outlier_weight
    f_sys, f_exp, f_or, H = (np.concatenate(c) for c in zip(*frames))
    h_sys, h_id, nominal, err, err_std, est = (np.concatenate(c) for c in zip(*holes))
    converged = all(sol.converged for _, _, sol in parts)
    iterations = max(sol.iterations for _, _, sol in parts)
    return PlateCalibration(
        groups.names,
        groups.system,
        groups.angles_deg,
        tuple(fields),
        order,
        tau,
        f_sys,
        f_exp,
        f_or,
        H,
        h_sys,
        h_id,
        nominal,
        err,
        err_std,
        est,
        residual,
        initial,
        weight,
        inlier,
        iterations,
        converged,
        "; ".join(f"{observations.system_names[s]}: {sol.stop_reason}" for s, (_, _, sol) in enumerate(parts)),
        float(wall_time_s),
        tuple(observations.system_names),
    )
