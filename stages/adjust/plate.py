"""The grid-plate adjustment: a robust homography per frame (:func:`adjust_plate`), outputs like the bundle's.

A planar grid plate determines no depth, so each frame (system, exposure) is
fitted alone by a homography (:mod:`stages.adjust.homography`), under the
bundle adjustment's Student-t likelihood and with its per-observation
statistics (:func:`stages.adjust.covariance.observation_statistics`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from fluorocal.stages.adjust.collinearity import whitening
from fluorocal.stages.adjust.covariance import observation_statistics
from fluorocal.stages.adjust.homography import fit_homographies
from fluorocal.stages.adjust.options import DataSelection, SolverOptions
from fluorocal.stages.adjust.result import check_finite_and_freeze, scatter
from fluorocal.stages.adjust.selection import checked_corrections, index_of, nominal_coordinates
from fluorocal.stages.artifacts import SCHEMA_VERSION, Observations
from fluorocal.stages.errors import InputError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PlateAdjustment:
    """Result of :func:`adjust_plate`: a robust homography per frame, per-observation outputs as in an Adjustment.

    Attributes
    ----------
    frame_system, frame_exposure : (F,) int64 ndarray
        The frames fitted.
    homography : (F, 3, 3) float64 ndarray
        Image px (homogeneous) from plate ``(x, y, 1)`` mm, ``H[2, 2] = 1``.
    t_scale : (F,) float64 ndarray
        Maximum-likelihood t scale per frame, relative to ``sigma_px``.
    residual_px, standardized_residual, redundancy, weight, inlier, used
        As in :class:`stages.adjust.Adjustment` (one row per input observation).
    sigma0, nu, dof, iterations, stop_reason, converged, usable, cost_history, system_names
        As in :class:`stages.adjust.Adjustment`; ``dof = 2 N_used - 8 F``.
    """

    frame_system: np.ndarray
    frame_exposure: np.ndarray
    homography: np.ndarray
    t_scale: np.ndarray
    residual_px: np.ndarray
    standardized_residual: np.ndarray
    redundancy: np.ndarray
    weight: np.ndarray
    inlier: np.ndarray
    used: np.ndarray
    sigma0: float
    nu: float
    dof: int
    iterations: int
    stop_reason: str
    converged: bool
    usable: bool
    cost_history: tuple
    system_names: tuple = ("A",)
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self):
        check_finite_and_freeze(self)


def adjust_plate(
    observations: Observations,
    nominal,
    corrections_px: np.ndarray | None = None,
    *,
    solver: SolverOptions | None = None,
    selection: DataSelection | None = None,
) -> PlateAdjustment:
    """Robust (Student-t) homography of each frame of a planar grid plate.

    The plate's nominal ``(x, y)`` (mm; ``z`` is ignored) map to the ideal image
    coordinates ``xy_px - Δ`` by one homography per frame (system, exposure),
    estimated by maximum likelihood under the same 2-D Student-t as
    :func:`stages.adjust.adjust_bundle`.

    Parameters
    ----------
    observations : Observations
    nominal : Phantom or dict or (ids, xyz_mm)
    corrections_px : (N, 2) float64 ndarray, px, optional
    solver : SolverOptions, optional
        ``nu``, ``estimate_scale``, ``outlier_weight``, ``max_iterations``,
        ``function_tolerance`` and ``min_inlier_fraction`` apply (default ``SolverOptions()``).
    selection : DataSelection, optional
        Frames with fewer than ``min_beads_per_exposure`` (at least 5) beads
        are left out, ``used`` False (default ``DataSelection()``).

    Returns
    -------
    PlateAdjustment

    Raises
    ------
    InputError
        Unknown bead ids, wrong shapes, or no frame with enough observations.
    EstimationError
        A frame's observations admit no homography (for example all on a line).
    """
    solver = SolverOptions() if solver is None else solver
    selection = DataSelection() if selection is None else selection
    corrections_px = checked_corrections(observations, corrections_px)
    n_obs = len(observations)
    ids, xyz = nominal_coordinates(nominal)
    point = index_of(observations.bead_id, ids, "observations.bead_id not in the nominal coordinates")
    used, order, starts = _frames(observations, max(selection.min_beads_per_exposure, 5))
    ideal_px = observations.xy_px[order] - corrections_px[order]
    fit = _fit(xyz[point[order], :2], ideal_px, observations.sigma_px[order], starts, solver)
    linv = whitening(observations.sigma_px[order])
    red, std_res, sigma0, inlier = observation_statistics(
        fit.residual_px, fit.s, fit.weight, fit.hat, linv, solver.outlier_weight
    )
    converged = bool(fit.converged.all())
    usable = converged and float(inlier.mean()) >= solver.min_inlier_fraction
    stop = "converged in every frame" if converged else f"{int((~fit.converged).sum())} frame(s) hit max_iterations"
    first = order[starts]
    return PlateAdjustment(
        frame_system=observations.system[first],
        frame_exposure=observations.exposure[first],
        homography=fit.H,
        t_scale=np.sqrt(fit.scale2),
        residual_px=scatter(fit.residual_px, order, n_obs),
        standardized_residual=scatter(std_res, order, n_obs),
        redundancy=scatter(red, order, n_obs),
        weight=scatter(fit.weight, order, n_obs),
        inlier=scatter(inlier, order, n_obs, False),
        used=used,
        sigma0=float(sigma0),
        nu=float(solver.nu),
        dof=int(2 * len(order) - 8 * len(starts)),
        iterations=int(fit.iterations),
        stop_reason=stop,
        converged=converged,
        usable=bool(usable),
        cost_history=fit.cost_history,
        system_names=tuple(observations.system_names),
    )


def _fit(plate_mm, ideal_px, sigma_px, starts, solver: SolverOptions):
    return fit_homographies(
        plate_mm,
        ideal_px,
        sigma_px,
        starts,
        nu=float(solver.nu),
        estimate_scale=solver.estimate_scale,
        max_iterations=solver.max_iterations,
        function_tolerance=solver.function_tolerance,
    )


def _frames(observations: Observations, min_beads: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Used observations ``(N,)`` (frames with >= ``min_beads``), their order by frame, and each frame's start in it."""
    frame_key = observations.system * (int(observations.exposure.max(initial=0)) + 1) + observations.exposure
    keys, frame_idx, counts = np.unique(frame_key, return_inverse=True, return_counts=True)
    used = counts[frame_idx] >= min_beads
    if (~used).any():
        log.debug("leaving out %d frame(s) with fewer than %d beads", int((counts < min_beads).sum()), min_beads)
    if not used.any():
        raise InputError(f"no frame has >= {min_beads} observations; got at most {int(counts.max(initial=0))}")
    order = np.flatnonzero(used)[np.argsort(frame_idx[used], kind="stable")]
    fr = frame_idx[order]
    starts = np.flatnonzero(np.r_[True, fr[1:] != fr[:-1]])
    return used, order, starts
