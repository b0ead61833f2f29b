"""The plate's self-calibration: per-frame homographies, a correction field per orientation, the plate's errors.

Each observation of hole ``k`` in frame ``f`` (orientation ``o``) obeys

    m_fk - Δ_o(m_fk) = H_f(n_k + e_k)

with ``m`` the measured centre (px), ``Δ_o`` the orientation's correction field (bilinear on a node
grid, :class:`fluorocal.stages.field.CorrectionField`), ``H_f`` the frame's plate-to-image homography
and ``n_k + e_k`` the hole's true plate position: the nominal lattice plus its manufacturing error, an
unknown shared by every frame (the paper's self-calibration applied to a plate). The three blocks are
solved in turn until nothing moves, as the paper alternates its adjustment and its regression:

1. the homographies, by the bundle adjustment's Student-t maximum likelihood
   (:func:`fluorocal.stages.adjust.homography.fit_homographies`) on the corrected centres;
2. each orientation's field, by the gridded least squares of the learning
   (:func:`fluorocal.stages.learn.grid.fit_grid_field`) on what the homographies leave, its
   smoothness prior's order and weight chosen by cross-validation
   (:func:`fluorocal.stages.learn.grid.cross_validate_smoothness`);
3. the plate's errors: per hole, the mean over frames of where the corrected centre maps back onto
   the plate, shrunk by an independent prior of ``plate_sigma_mm`` per hole.

The field is smooth and the plate errors are independent from hole to hole, so what is smooth over the
image goes to the fields and what moves with the plate from frame to frame goes to the plate. The
datum: neither the fields nor the plate errors carry a homography (eight modes each, removed by least
squares after each update), since every frame's homography absorbs one; the undistorted image is thus
as close to the measured one as a homography allows, the same convention at every orientation, so
fields of different orientations can be compared and interpolated. A hole seen in one frame only
keeps its nominal position: its error cannot be told from the noise.

What the plate's motion does not separate stays in the fields: with the plate riding on the intensifier
(a few px between orientations) its errors smoother than about a node spacing are explained as well by
the fields as by the plate, and the truth fits the data no better than the estimate
(``benchmarks/plate_motion.py``); turned between the frames, the plate's errors are recovered.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from fluorocal.stages.adjust.homography import fit_homographies
from fluorocal.stages.adjust.robust import t_weights
from fluorocal.stages.errors import EstimationError, InputError
from fluorocal.stages.field import CorrectionField
from fluorocal.stages.learn.grid import cross_validate_smoothness, fit_grid_field
from fluorocal.stages.learn.nodes import GridSpec
from fluorocal.stages.plate.homography import Normaliser, homography_modes

log = logging.getLogger(__name__)

#: the alternation's iteration at which the fields' smoothness is cross-validated (before it: the start value)
_CV_ITERATION = 3
#: iterations without a smaller change after which the alternation stops at its best state
_PATIENCE = 3
#: a hole's error is estimated only if the plate carried it this far across the image between its frames, px
_MIN_MOVE_PX = 1.0


@dataclass(frozen=True)
class PlateProblem:
    """The observations of a grid plate, indexed for the solve, sorted by frame.

    Attributes
    ----------
    frame : (N,) int64 ndarray
        Frame of each observation, ``0 .. F-1``, non-decreasing.
    orientation_of_frame : (F,) int64 ndarray
        Orientation (field) of each frame, ``0 .. O-1``.
    hole : (N,) int64 ndarray
        Hole of each observation, ``0 .. K-1``.
    nominal_mm : (K, 2) float64 ndarray, mm
        The holes' nominal lattice positions.
    xy_px : (N, 2) float64 ndarray, px
        Measured centres.
    sigma_px : (N, 3) float64 ndarray
        ``(σx, σy, ρ)`` of each centre, px.
    image_size : (int, int)
        ``(width, height)`` of the frames, px.
    """

    frame: np.ndarray
    orientation_of_frame: np.ndarray
    hole: np.ndarray
    nominal_mm: np.ndarray
    xy_px: np.ndarray
    sigma_px: np.ndarray
    image_size: tuple

    def __post_init__(self):
        if np.any(np.diff(self.frame) < 0):
            raise InputError("the plate's observations must be sorted by frame")

    @property
    def n_frames(self) -> int:
        return len(self.orientation_of_frame)

    @property
    def n_orientations(self) -> int:
        return int(self.orientation_of_frame.max()) + 1

    @property
    def orientation(self) -> np.ndarray:
        """Orientation of each observation ``(N,)``."""
        return self.orientation_of_frame[self.frame]

    def subset(self, keep: np.ndarray) -> "PlateProblem":
        """The same problem with only the observations ``keep`` (holes, frames and orientations keep their indices)."""
        return PlateProblem(
            self.frame[keep],
            self.orientation_of_frame,
            self.hole[keep],
            self.nominal_mm,
            self.xy_px[keep],
            self.sigma_px[keep],
            self.image_size,
        )

    def of_frames(self, frames) -> tuple["PlateProblem", np.ndarray]:
        """The problem of ``frames`` alone, frames and orientations numbered afresh (holes keep theirs).

        Returns the problem and each new frame's index in this one ``(F',)`` (sorted).
        """
        frames = np.unique(np.asarray(frames, dtype=np.int64))
        keep = np.isin(self.frame, frames)
        _, local = np.unique(self.orientation_of_frame[frames], return_inverse=True)
        sub = PlateProblem(
            np.searchsorted(frames, self.frame[keep]),
            local.astype(np.int64),
            self.hole[keep],
            self.nominal_mm,
            self.xy_px[keep],
            self.sigma_px[keep],
            self.image_size,
        )
        return sub, frames


@dataclass(frozen=True)
class SolveSettings:
    """How :func:`solve_plate` models the plate and the fields (from :class:`~fluorocal.stages.plate.PlateParams`)."""

    grid: GridSpec
    orders: tuple
    tau_grid_px: tuple
    start_smoothness: tuple
    deviation_spacing_px: float
    plate_sigma_mm: float
    estimate_plate: bool
    solver: object  # SolverOptions: nu, max_iterations, function_tolerance, estimate_scale of the homographies
    max_iterations: int  # 0: homographies of the nominal plate only, no field
    tolerance_px: float


@dataclass(frozen=True)
class PlateSolution:
    """What :func:`solve_plate` found.

    Attributes
    ----------
    fields : tuple of CorrectionField
        One per orientation, on one node grid (``ideal = measured - Δ``).
    plate_error_mm : (K, 2) float64 ndarray, mm
        Estimated ``e_k`` (zero where not estimated).
    plate_error_std_mm : (K,) float64 ndarray, mm
        Standard uncertainty of each component of ``e_k`` (0 where not estimated).
    plate_estimated : (K,) bool ndarray
        Holes whose error was estimated (seen in two frames or more).
    homography : (F, 3, 3) float64 ndarray
        Image px (homogeneous) from plate mm, ``H[2, 2] = 1``.
    residual_px : (N, 2) float64 ndarray, px
        ``m - Δ(m) - H(n + e)``.
    initial_residual_px : (N, 2) float64 ndarray, px
        A homography of the nominal lattice, no correction: the "before".
    weight : (N,) float64 ndarray
        The homographies' final Student-t weights.
    smoothness : tuple of (int, float)
        Order and ``τ`` (px) of the common field's prior and of the orientations' deviations', from the
        cross-validation.
    iterations : int
    converged : bool
    stop_reason : str
    """

    fields: tuple
    plate_error_mm: np.ndarray
    plate_error_std_mm: np.ndarray
    plate_estimated: np.ndarray
    homography: np.ndarray
    residual_px: np.ndarray
    initial_residual_px: np.ndarray
    weight: np.ndarray
    smoothness: tuple
    iterations: int
    converged: bool
    stop_reason: str = ""

    def corrected(self, problem: PlateProblem) -> np.ndarray:
        """The problem's centres corrected by their orientation's field, ``m - Δ_o(m)`` ``(N, 2)`` px."""
        return _corrected(problem, self.fields)


def solve_plate(problem: PlateProblem, settings: SolveSettings) -> PlateSolution:
    """Alternate homographies, fields and plate errors until the largest change is below ``tolerance_px``.

    Raises
    ------
    EstimationError
        A frame admits no homography (fewer than 5 holes, or all on a line).
    """
    estimated = _estimable_holes(problem) if settings.estimate_plate else np.zeros(len(problem.nominal_mm), bool)
    plate_norm = Normaliser.of(problem.nominal_mm[np.unique(problem.hole)])
    error_mm = np.zeros_like(problem.nominal_mm)
    error_std_mm = np.zeros(len(problem.nominal_mm))
    base = CorrectionField.constant(*problem.image_size, spacing_px=settings.grid.spacing_px)
    devs = _zero_deviations(problem, settings)
    supports = _supports(problem, settings)
    fields = _combined(base, devs)
    corrected = _corrected(problem, fields)  # the centres corrected by ``fields``, found once per state
    smoothness = (settings.start_smoothness, settings.start_smoothness)
    converged = settings.max_iterations == 0
    stop = "no field: homographies only" if converged else f"{settings.max_iterations} iterations"
    iteration = 0
    initial = None
    best = None  # (change, iteration, fields, corrected, error_mm, error_std_mm): the state nearest a fixed point
    for iteration in range(1, settings.max_iterations + 1):
        fit = _homographies(problem, corrected, error_mm, settings.solver)
        if iteration == 1:
            initial = problem.xy_px - _apply(fit.H[problem.frame], problem.nominal_mm[problem.hole])
            estimated &= _moved_holes(problem, fit.H)
        target, var = _targets(problem, fit, error_mm)
        if iteration == _CV_ITERATION:  # chosen once the plate's errors are mostly out of the residuals
            smoothness = _smoothness(problem, target, var, base, devs, settings)
        base = _base_field(problem, target - _at(problem, devs), var, settings, smoothness[0], devs, supports)
        devs = _deviations(
            problem, target - base.correction_at(problem.xy_px), var, settings, smoothness[1], base, supports
        )
        new_fields = _combined(base, devs)
        new_corrected = _corrected(problem, new_fields)
        new_error, new_std = _plate_errors(problem, new_corrected, fit, estimated, settings.plate_sigma_mm, plate_norm)
        moved = _largest_change_px(problem, corrected, new_corrected, error_mm, new_error, fit.H)
        fields, corrected, error_mm, error_std_mm = new_fields, new_corrected, new_error, new_std
        log.debug("plate iteration %d: largest change %.2e px", iteration, moved)
        if iteration <= _CV_ITERATION:
            continue
        if best is None or moved < best[0]:
            best = (moved, iteration, fields, corrected, error_mm, error_std_mm)
        if moved < settings.tolerance_px:
            converged = True
            stop = f"converged in {iteration} iterations (change {moved:.1e} px)"
            break
        if iteration - best[1] >= _PATIENCE or iteration == settings.max_iterations:
            # the change has stopped falling (or the cap is reached): robust weights and a thinly supported
            # field feeding each other can make the alternation wander off; the state nearest a fixed point is kept
            stop = (
                f"kept iteration {best[1]} of {iteration}, nearest a fixed point (change {best[0]:.1e} px)"
                if best[1] < iteration
                else f"{iteration} iterations, still moving (change {moved:.1e} px)"
            )
            _, iteration, fields, corrected, error_mm, error_std_mm = best
            break
    fit = _homographies(problem, corrected, error_mm, settings.solver)
    if initial is None:
        initial = problem.xy_px - _apply(fit.H[problem.frame], problem.nominal_mm[problem.hole])
    layout = problem.nominal_mm[problem.hole] + error_mm[problem.hole]
    residual = corrected - _apply(fit.H[problem.frame], layout)
    return PlateSolution(
        fields,
        error_mm,
        error_std_mm,
        estimated,
        fit.H,
        residual,
        initial,
        fit.weight,
        tuple(smoothness),
        iteration,
        converged,
        stop,
    )


def _moved_holes(problem: PlateProblem, H: np.ndarray) -> np.ndarray:
    """Holes the plate carried across the image by at least :data:`_MIN_MOVE_PX` between their frames.

    A hole that stays put (the plate still, whatever the C-arm did) shows its error at one place of the
    image, where the field common to the orientations can take it as well: only the plate's motion
    tells the two apart.
    """
    at = _apply(H[problem.frame], problem.nominal_mm[problem.hole])
    n = len(problem.nominal_mm)
    lo = np.full((n, 2), np.inf)
    hi = np.full((n, 2), -np.inf)
    np.minimum.at(lo, problem.hole, at)
    np.maximum.at(hi, problem.hole, at)
    return np.hypot(*(hi - lo).T) >= _MIN_MOVE_PX


def _estimable_holes(problem: PlateProblem) -> np.ndarray:
    """Holes seen in two frames or more: only there can a plate error be told from the noise."""
    frames_per_hole = np.zeros(len(problem.nominal_mm), int)
    pairs = np.unique(np.column_stack([problem.hole, problem.frame]), axis=0)
    np.add.at(frames_per_hole, pairs[:, 0], 1)
    return frames_per_hole >= 2


def _corrected(problem: PlateProblem, fields) -> np.ndarray:
    """Each observation corrected by its orientation's field, ``m - Δ_o(m)`` ``(N, 2)`` px."""
    return problem.xy_px - _at(problem, fields)


def _apply(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Per-point homographies ``(N, 3, 3)`` applied to points ``(N, 2)``."""
    p = np.einsum("nij,nj->ni", H, np.column_stack([points, np.ones(len(points))]))
    return p[:, :2] / p[:, 2:3]


@dataclass(frozen=True)
class _Fit:
    """The frames' homographies, with one Student-t scale for all frames and the weights under it."""

    H: np.ndarray  # (F, 3, 3)
    scale2: float
    weight: np.ndarray  # (N,)


def _homographies(problem: PlateProblem, corrected, error_mm, solver) -> _Fit:
    """The frames' homographies, their Student-t weights recomputed under one scale pooled over the frames.

    The fit estimates a scale per frame; fed back through the plate's errors, a frame that fits a
    little better draws every hole's error to itself, fits better still, and its scale shrinks toward
    zero. One pooled scale keeps the frames on an equal footing.
    """
    fit = _frame_homographies(problem, corrected, error_mm, solver)
    counts = np.bincount(problem.frame, minlength=problem.n_frames)
    scale2 = float(np.sum(fit.scale2 * counts) / counts.sum())
    weight = t_weights(fit.s, float(solver.nu), scale2)
    return _Fit(fit.H, scale2, weight)


def _frame_homographies(problem: PlateProblem, corrected, error_mm, solver):
    starts = np.flatnonzero(np.r_[True, problem.frame[1:] != problem.frame[:-1]])
    if len(starts) != problem.n_frames:
        raise EstimationError(f"{problem.n_frames - len(starts)} frame(s) of the plate have no observation")
    return fit_homographies(
        problem.nominal_mm[problem.hole] + error_mm[problem.hole],
        corrected,
        problem.sigma_px,
        starts,
        nu=float(solver.nu),
        estimate_scale=solver.estimate_scale,
        max_iterations=solver.max_iterations,
        function_tolerance=solver.function_tolerance,
    )


def _targets(problem: PlateProblem, fit, error_mm):
    """What the fields are to fit, ``m - H(n + e)`` ``(N, 2)`` px, and its variance per observation ``(N,)`` px²."""
    layout = problem.nominal_mm[problem.hole] + error_mm[problem.hole]
    target = problem.xy_px - _apply(fit.H[problem.frame], layout)
    # one variance for both components: one factorisation serves both in the grid fit
    var = np.mean(problem.sigma_px[:, :2] ** 2, axis=1) * fit.scale2 / np.maximum(fit.weight, 1e-6)
    return target, var


def _deviation_grid(settings: SolveSettings) -> GridSpec:
    spacing = settings.deviation_spacing_px
    return GridSpec(spacing_px=spacing, support_radius_px=spacing, min_support=settings.grid.min_support)


def _zero_deviations(problem: PlateProblem, settings: SolveSettings) -> tuple:
    spacing = settings.deviation_spacing_px
    return tuple(
        CorrectionField.constant(*problem.image_size, spacing_px=spacing) for _ in range(problem.n_orientations)
    )


def _at(problem: PlateProblem, fields) -> np.ndarray:
    """Each observation's value ``(N, 2)`` px of its orientation's field (one per orientation)."""
    out = np.zeros_like(problem.xy_px)
    for o, field in enumerate(fields):
        sel = problem.orientation == o
        out[sel] = field.correction_at(problem.xy_px[sel])
    return out


def _combined(base: CorrectionField, devs) -> tuple:
    """Each orientation's field on the base grid: the base plus the orientation's deviation at its nodes.

    Supported where the base is and where the orientation's own frames support its deviation: elsewhere
    the deviation is the prior's extrapolation.
    """
    nodes = base.nodes_px
    return tuple(
        base.with_delta(
            base.delta_px + dev.correction_at(nodes).reshape(base.delta_px.shape),
            support=base.support & dev.support_at(nodes).reshape(base.support.shape),
        )
        for dev in devs
    )


def _smoothness(problem, target, var, base, devs, settings: SolveSettings) -> tuple:
    """Order and ``τ`` of the base field's prior and of the deviations', by shuffled 5-fold cross-validation."""

    def cv(xy, values, variance, grid):
        report = cross_validate_smoothness(
            xy,
            values,
            variance,
            image_size=problem.image_size,
            grid=grid,
            tau_grid_px=settings.tau_grid_px,
            orders=settings.orders,
            groups=problem.hole,
        )
        return report.order, report.tau_px

    chosen_base = cv(problem.xy_px, target - _at(problem, devs), var, settings.grid)
    if problem.n_orientations == 1:
        return chosen_base, settings.start_smoothness
    # one prior for every orientation's deviation: each is a smooth effect of the same cause
    return chosen_base, cv(problem.xy_px, target - base.correction_at(problem.xy_px), var, _deviation_grid(settings))


def _supports(problem: PlateProblem, settings: SolveSettings) -> tuple:
    """The support masks of the base field's nodes (every centre) and of each orientation's deviation (its centres).

    The centres do not move in the alternation: the masks are found once, not at every field fit.
    """
    base = settings.grid.support_mask(problem.xy_px, *settings.grid.nodes(problem.image_size))
    if problem.n_orientations == 1:
        return base, ()  # no deviation is fitted
    grid = _deviation_grid(settings)
    nodes = grid.nodes(problem.image_size)
    return base, tuple(
        grid.support_mask(problem.xy_px[problem.orientation == o], *nodes) for o in range(problem.n_orientations)
    )


def _base_field(problem, target, var, settings: SolveSettings, smoothness, devs, supports) -> CorrectionField:
    """The field common to every orientation, fitted to all frames, less its homography (the datum)."""
    order, tau = smoothness
    field = fit_grid_field(
        problem.xy_px,
        target,
        var,
        image_size=problem.image_size,
        tau_px=tau,
        grid=settings.grid,
        order=order,
        support=supports[0],
    )
    mean_dev = np.mean([dev.delta_px for dev in devs], axis=0)
    rest = devs[0].with_delta(mean_dev).correction_at  # the orientations' mean deviation
    return _without_homography(field, problem.xy_px, rest)


def _deviations(problem, target, var, settings: SolveSettings, smoothness, base: CorrectionField, supports) -> tuple:
    """Each orientation's smooth deviation from the base field, less its homography; zero with one orientation."""
    if problem.n_orientations == 1:
        return _zero_deviations(problem, settings)
    order, tau = smoothness
    grid = _deviation_grid(settings)
    out = []
    for o in range(problem.n_orientations):
        sel = problem.orientation == o
        field = fit_grid_field(
            problem.xy_px[sel],
            target[sel],
            var[sel],
            image_size=problem.image_size,
            tau_px=tau,
            grid=grid,
            order=order,
            support=supports[1][o],
        )
        out.append(_without_homography(field, problem.xy_px[sel], base.correction_at))
    return tuple(out)


def _without_homography(field: CorrectionField, xy_px: np.ndarray, rest) -> CorrectionField:
    """The field less its least-squares homography component at ``xy_px`` (the datum).

    What a frame's homography absorbs is a homography of the *ideal* image, ``m - Δ(m)``: the modes
    are evaluated there, ``Δ`` being this field plus ``rest(xy)`` (the rest of the orientation's
    correction). At the measured points instead, a distortion of many pixels would leave part of the
    gauge free, and the alternation would drift along it into the plate's errors.
    """
    at = field.correction_at(xy_px)
    ideal = xy_px - at - rest(xy_px)
    nodes = field.nodes_px
    ideal_nodes = nodes - field.correction_at(nodes) - rest(nodes)
    norm = Normaliser.of(ideal)
    B = homography_modes(norm.forward(ideal)).reshape(-1, 8)
    coef, *_ = np.linalg.lstsq(B, at.ravel(), rcond=None)
    at_nodes = homography_modes(norm.forward(ideal_nodes)).reshape(-1, 8) @ coef
    return field.with_delta(field.delta_px - at_nodes.reshape(field.delta_px.shape))


def _plate_errors(problem, corrected, fit, estimated, plate_sigma_mm, plate_norm) -> tuple[np.ndarray, np.ndarray]:
    """Per hole, the shrunk mean offset of its corrected centres mapped back onto the plate, less a homography.

    Returns the errors ``(K, 2)`` mm and their standard uncertainty per component ``(K,)`` mm.
    """
    n_holes = len(problem.nominal_mm)
    error = np.zeros((n_holes, 2))
    if not estimated.any():
        return error, np.zeros(n_holes)
    on_plate = _apply(np.linalg.inv(fit.H)[problem.frame], corrected)
    offset = on_plate - problem.nominal_mm[problem.hole]
    # the centre's variance in plate mm: px variance over the frame's scale (px per mm)² (the homography's local scale)
    px_per_mm = np.sqrt(np.abs(np.linalg.det(fit.H[:, :2, :2])))[problem.frame]
    var_mm = np.mean(problem.sigma_px[:, :2] ** 2, axis=1) * fit.scale2 / px_per_mm**2
    w = fit.weight / var_mm
    total_w = np.bincount(problem.hole, w, n_holes)
    for c in range(2):
        error[:, c] = np.bincount(problem.hole, w * offset[:, c], n_holes) / (total_w + 1.0 / plate_sigma_mm**2)
    error[~estimated] = 0.0
    B = homography_modes(plate_norm.forward(problem.nominal_mm[estimated]))
    coef, *_ = np.linalg.lstsq(B.reshape(-1, 8), error[estimated].ravel(), rcond=None)
    error[estimated] -= (B.reshape(-1, 8) @ coef).reshape(-1, 2)
    return error, np.where(estimated, 1.0 / np.sqrt(total_w + 1.0 / plate_sigma_mm**2), 0.0)


def _largest_change_px(problem, corrected, new_corrected, error_mm, new_error, H) -> float:
    """RMS change of the corrections at the centres or of the plate errors seen in the image, the larger (px)."""
    change = corrected - new_corrected
    px_per_mm = float(np.sqrt(np.abs(np.linalg.det(H[:, :2, :2]))).mean())
    plate = (new_error - error_mm) * px_per_mm
    return max(float(np.sqrt(np.mean(change**2))), float(np.sqrt(np.mean(plate**2))))
