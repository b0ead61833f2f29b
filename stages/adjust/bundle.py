"""The bundle adjustment's entry :func:`adjust_bundle`: check, select, build, solve, summarise.

Model and method: :mod:`stages.adjust`. :func:`prepare` is the first half
(inputs checked, what cannot be estimated dropped, the problem and its start
state built); tests use it to probe the cost and the Jacobians. A bead the
solution's inliers leave seen in fewer than ``min_exposures_per_bead`` epochs
is dropped and the problem solved again (:func:`_beads_without_inliers`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from fluorocal.stages.adjust import polynomial
from fluorocal.stages.adjust.collinearity import State
from fluorocal.stages.adjust.options import DataSelection, FreeParameters, SolverOptions
from fluorocal.stages.adjust.orientation import Orientation
from fluorocal.stages.adjust.problem import Problem, build_problem
from fluorocal.stages.adjust.problem import start_points as projected_start
from fluorocal.stages.adjust.result import Adjustment, solution_weights, summarise
from fluorocal.stages.adjust.selection import (
    checked_corrections,
    epochs_per_bead,
    index_of,
    nominal_coordinates,
    select_observations,
)
from fluorocal.stages.adjust.solver import solve
from fluorocal.stages.artifacts import Observations
from fluorocal.stages.errors import InputError

log = logging.getLogger(__name__)

#: how often :func:`adjust_bundle` solves again without the beads its inliers no longer determine
MAX_RESELECTIONS = 2


def adjust_bundle(
    observations: Observations,
    nominal,
    initial: Orientation,
    corrections_px: np.ndarray | None = None,
    *,
    free: FreeParameters | None = None,
    solver: SolverOptions | None = None,
    selection: DataSelection | None = None,
    start_points=None,
    compute_covariance: bool = True,
) -> Adjustment:
    """Robust (Student-t) free-network bundle adjustment of labelled bead observations.

    Parameters
    ----------
    observations : Observations
        ``N`` labelled observations (``xy_px`` measured, ``sigma_px`` from the centroid stage).
    nominal : Phantom or dict or (ids, xyz_mm)
        Nominal bead coordinates (mm) by bead id: the start values and the datum.
    initial : Orientation
        Start values of IOP, poses (every observed epoch) and ROP.
    corrections_px : (N, 2) float64 ndarray, px, optional
        Distortion corrections Δ held constant: ideal = ``xy_px - Δ`` (default 0).
    free : FreeParameters, optional
        Which parameters are estimated (default ``FreeParameters()``: the IOP,
        no additional parameters). Set by the caller that owns the choice (the
        learning loop's scheme, ``fluorocal adjust``'s flags), not by configuration.
    solver : SolverOptions, optional
        The robust model and Levenberg–Marquardt's settings (default ``SolverOptions()``).
    selection : DataSelection, optional
        What can enter the solve (default ``DataSelection()``).
    start_points : dict or (ids, xyz_mm), optional
        Start values of the bead coordinates (for example a previous
        :class:`Adjustment`'s ``(bead_id, xyz_mm)`` in the learning loop); beads
        not given start at their nominal coordinates. The datum stays the
        nominal one: the start is projected onto the inner constraints.
    compute_covariance : bool
        Compute the covariance and the redundancy numbers (default True).
        False skips the dense inverse (two thirds of a warm-started solve; the
        learning loop's intermediate solves): standard deviations are then
        zero and every observation gets the mean redundancy ``dof / 2N``.

    Returns
    -------
    Adjustment
        ``usable`` False (see ``stop_reason``): not converged or too many
        outliers; the caller decides whether that concerns the user.

    Raises
    ------
    InputError
        Inconsistent inputs (unknown bead ids or epochs, wrong shapes, system
        count mismatch) or fewer than ``min_exposures`` usable frames.
    EstimationError
        Degenerate geometry (all exposures from one pose, singular normal
        equations) or an initial orientation with points behind a source.

    Notes
    -----
    Model and datum: see :mod:`stages.adjust`. Uncertainties are ``c (J^T W J)^-1``
    under the inner constraints, ``c`` Huber's sandwich factor (:func:`stages.adjust.covariance.covariance_factor`).
    Redundancy numbers: the diagonal of ``Q_vv P``, ``P = w C^-1``; ``σ0² = Σ_inliers s / Σ_inliers r``.
    """
    free = FreeParameters() if free is None else free
    solver = SolverOptions() if solver is None else solver
    selection = DataSelection() if selection is None else selection
    prepared, solved = _solve_determined(
        observations,
        nominal,
        initial,
        corrections_px,
        free=free,
        solver=solver,
        selection=selection,
        start_points=start_points,
    )
    return summarise(observations, prepared, solved, solver, free.additional_parameters, compute_covariance)


def _solve_determined(observations, nominal, initial, corrections_px, **settings) -> tuple[Prepared, object]:
    """Prepare and solve; again without the beads the solution's inliers leave undetermined (up to twice more)."""
    solver, selection = settings["solver"], settings["selection"]
    left_out = np.zeros(len(observations), bool)
    for attempt in range(MAX_RESELECTIONS + 1):
        prepared = prepare(observations, nominal, initial, corrections_px, left_out=left_out, **settings)
        solved = solve(prepared.state, prepared.problem, solver)
        weak = _beads_without_inliers(prepared, solved, solver.outlier_weight, selection.min_exposures_per_bead)
        if not weak.any() or attempt == MAX_RESELECTIONS:
            return prepared, solved
        log.debug(  # the report counts what was left out; a normal run stays quiet
            "%d bead(s) left with inliers in fewer than %d epochs (a gross error among too few observations): "
            "solving again without them",
            int(weak.sum()),
            selection.min_exposures_per_bead,
        )
        left_out[np.flatnonzero(prepared.used)[prepared.perm[weak[prepared.problem.point_idx]]]] = True


def _beads_without_inliers(prepared: Prepared, solved, outlier_weight: float, min_epochs: int) -> np.ndarray:
    """Mask ``(n_points,)`` of the problem's beads whose inliers are seen in fewer than ``min_epochs`` epochs.

    With two rays and one of them a gross error, the t-likelihood is highest
    with the point on the good ray, wherever along it the bad one pulls: the
    point is undetermined (its depth, and the covariance, singular), as if
    seen once. Such a bead cannot be estimated from these observations.
    """
    problem = prepared.problem
    inlier = solution_weights(solved, problem)[2] >= outlier_weight
    counts = epochs_per_bead(problem.point_idx[inlier], problem.pose_idx[inlier], problem.n_points, problem.n_poses)
    return counts < min_epochs


@dataclass(frozen=True)
class Prepared:
    """The numerical problem behind one :func:`adjust_bundle` call.

    Attributes
    ----------
    problem : Problem
    perm : (N_used,) int64 ndarray
        The problem's observations are the used ones taken at ``perm``.
    state : State
        Start values.
    used : (N,) bool ndarray
        Observations that entered the problem.
    beads_used : (n,) int64 ndarray
        Rows of the nominal table ``ids`` that entered (the problem's points).
    ids : (n_nominal,) int64 ndarray
        The nominal table's bead ids.
    exposure : (m,) int64 ndarray
        Epochs that entered (the problem's poses).
    """

    problem: Problem
    perm: np.ndarray
    state: State
    used: np.ndarray
    beads_used: np.ndarray
    ids: np.ndarray
    exposure: np.ndarray


def prepare(
    observations,
    nominal,
    initial: Orientation,
    corrections_px=None,
    *,
    free: FreeParameters | None = None,
    solver: SolverOptions | None = None,
    selection: DataSelection | None = None,
    start_points=None,
    left_out=None,
) -> Prepared:
    """Check the inputs, drop what cannot be estimated, build the problem and its start state.

    Arguments as :func:`adjust_bundle`; ``left_out`` ``(N,)`` bool, optional, marks observations dropped beforehand.
    """
    free = FreeParameters() if free is None else free
    solver = SolverOptions() if solver is None else solver
    selection = DataSelection() if selection is None else selection
    corrections_px = _checked_inputs(observations, initial, corrections_px)
    ids, nominal_xyz = nominal_coordinates(nominal)
    point_all = index_of(observations.bead_id, ids, "observations.bead_id not in the nominal coordinates")
    epoch_all = index_of(observations.exposure, initial.exposure, "observations.exposure not in initial.exposure")
    n_epochs = len(initial.exposure)
    used = select_observations(
        observations, point_all, epoch_all, len(ids), n_epochs, initial, nominal_xyz, selection, left_out
    )
    n_frames = len(np.unique(observations.system[used] * (n_epochs + 1) + epoch_all[used]))
    if n_frames < selection.min_exposures:
        raise InputError(
            f"observations must leave at least min_exposures = {selection.min_exposures} frames with "
            f">= {selection.min_beads_per_exposure} beads seen in >= {selection.min_exposures_per_bead} epochs; "
            f"got {n_frames}"
        )
    beads_used, point_idx = np.unique(point_all[used], return_inverse=True)
    epochs_used, pose_idx = np.unique(epoch_all[used], return_inverse=True)
    sys_idx = observations.system[used]
    n_sys = initial.n_systems
    ap_radius = None
    if free.additional_parameters == "polynomial":
        ap_radius = np.array(
            [polynomial.reference_radius(observations.xy_px[used][sys_idx == s]) for s in range(n_sys)]
        )
    problem, perm = build_problem(
        point_idx.astype(np.int64),
        pose_idx.astype(np.int64),
        sys_idx,
        observations.xy_px[used] - corrections_px[used],
        observations.sigma_px[used],
        nominal_xyz[beads_used],
        len(epochs_used),
        n_sys,
        np.full(n_sys, bool(free.estimate_iop)),
        solver.schur,
        xy_px=observations.xy_px[used],
        ap_radius_px=ap_radius,
        ap_free=np.array(free.ap_free),
    )
    state = State(
        points_mm=projected_start(start_points, ids[beads_used], nominal_xyz[beads_used]),
        q=initial.q_cam_from_obj[epochs_used].copy(),
        source_mm=initial.source_mm[epochs_used].copy(),
        iop_px=initial.iop_px.copy(),
        rop_q=initial.rop_q.copy(),
        rop_source_mm=initial.rop_source_mm.copy(),
        ap_px=np.zeros((n_sys, problem.n_ap)),
    )
    log.debug(
        "adjusting %d observations: %d beads, %d epochs, %d systems, %d free parameters, eliminating %s",
        problem.n_obs,
        problem.n_points,
        problem.n_poses,
        n_sys,
        problem.n_free,
        problem.eliminate,
    )
    return Prepared(problem, perm, state, used, beads_used, ids, initial.exposure[epochs_used])


def _checked_inputs(observations, initial: Orientation, corrections_px) -> np.ndarray:
    """The corrections ``(N, 2)`` (zero if None) after checking the observations, corrections and systems."""
    corrections_px = checked_corrections(observations, corrections_px)
    if not np.all(np.isfinite(corrections_px)):
        raise InputError("corrections_px holds non-finite values")
    if initial.n_systems != len(observations.system_names):
        raise InputError(
            f"initial orientation has {initial.n_systems} system(s); "
            f"observations name {len(observations.system_names)}: {observations.system_names}"
        )
    if not (np.array_equal(np.abs(initial.rop_q[0]), [1.0, 0, 0, 0]) and not np.any(initial.rop_source_mm[0])):
        # the model takes system 0's camera as the reference frame (its observations skip the ROP)
        raise InputError(
            f"initial.rop_q[0] must be the identity and rop_source_mm[0] zero (system 0 is the reference); "
            f"got {initial.rop_q[0].tolist()}, {initial.rop_source_mm[0].tolist()}"
        )
    if np.any(observations.sigma_px[:, :2] <= 0) or np.any(np.abs(observations.sigma_px[:, 2]) >= 1):
        raise InputError("sigma_px must have σx, σy > 0 and |ρ| < 1")
    return corrections_px
