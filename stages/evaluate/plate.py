"""The held-out protocol on a grid plate: each frame's alternate lattice rows scored, per training size and scheme.

A plate is planar and fixes no interior orientation, so a plate's calibration is scored on held-out holes
(:mod:`fluorocal.stages.plate.holdout`): for every scored frame and row parity, each scheme is fitted
without that frame's holes on those rows, and the held-out holes, corrected by the scheme, are compared
by a best-fitting homography with the plate's layout as self-calibrated from the same training holes
(and with the nominal lattice). A training size is the number of frames the plate is self-calibrated
from: the scored frame (its other rows) and ``size - 1`` of the system's other frames, evenly spaced
(:func:`~fluorocal.stages.evaluate.split.training_subset`); the held-out holes are the same at every size.

Schemes (:data:`PLATE_SCHEMES`): ``plate`` (fluorocal: the fields per orientation and the plate's errors,
:func:`fluorocal.stages.plate.calibrate_plate`'s solve with the project's ``[plate]``), ``none`` (each
frame's homography of the nominal plate, no correction) and ``polynomial``
(:func:`fluorocal.stages.plate.polynomial.fit_polynomial`). ``plate`` is always solved: its layout is
what every scheme is scored against.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from fluorocal.stages.errors import EstimationError, InputError
from fluorocal.stages.evaluate.protocol import Evaluation, HeldOutResiduals, Score
from fluorocal.stages.evaluate.split import training_subset

#: the schemes of a grid plate's evaluation; the first is fluorocal's own
PLATE_SCHEMES = ("plate", "none", "polynomial")


@dataclass(frozen=True)
class PlateSetup:
    """What every fit of a plate's evaluation shares.

    Attributes
    ----------
    phantom : Phantom
        The plate (``lattice``, ``pitch_mm``).
    image_size_px : tuple of (int, int)
        ``(width, height)`` per system.
    orientations : tuple
        ``(system, exposure, orientation name, orbit_deg, tilt_deg)`` of every frame.
    plate : PlateParams
        The project's ``[plate]``.
    solver : SolverOptions or None
        The project's ``[adjust]``.
    """

    phantom: object
    image_size_px: tuple
    orientations: tuple
    plate: object
    solver: object = None


def plate_fits(setup: PlateSetup) -> dict:
    """Scheme name -> its ``fit(training problem, scored frame)`` (as ``stages.plate.holdout.holdout_scores`` takes)."""
    from fluorocal.stages.plate.holdout import solved
    from fluorocal.stages.plate.polynomial import fit_polynomial

    return {
        "plate": solved(setup.plate.settings(setup.phantom.pitch_mm, True, solver=setup.solver)),
        "none": uncorrected,
        "polynomial": fit_polynomial,
    }


def uncorrected(train, frame: int):
    """Scheme ``none``: the centres as measured, the plate nominal.

    Its homography of the nominal plate per frame is the one the scoring fits
    (:func:`fluorocal.stages.plate.holdout.holdout_scores`): a solve of it here would
    change nothing scored (a frame that admits no homography fails scheme ``plate`` first).
    """
    from fluorocal.stages.plate.holdout import PlateFit

    return PlateFit(np.array, np.zeros_like(train.nominal_mm))


def plate_frames(observations, setup: PlateSetup) -> list:
    """Per system, its plate problem, its frames' exposures ``(F,)`` and each hole's lattice row ``(K,)``."""
    from fluorocal.stages.label.lattice import lattice_index
    from fluorocal.stages.plate.problem import frame_orientations, plate_problem

    groups = frame_orientations(observations, setup.orientations)
    out = []
    for s in range(len(observations.system_names)):
        problem, index = plate_problem(observations, setup.phantom, s, groups, setup.image_size_px[s])
        out.append((problem, index["exposures"], lattice_index(index["hole_ids"])[:, 1]))
    return out


def training_frames(n_frames: int, frame: int, size: int) -> np.ndarray:
    """The frames of a training size: ``frame`` and ``size - 1`` of the others, evenly spaced (sorted).

    Examples
    --------
    >>> training_frames(6, 2, 3).tolist()
    [0, 2, 5]
    """
    if not 1 <= size <= n_frames:
        raise InputError(f"training size {size} is outside 1..{n_frames} frames")
    others = np.delete(np.arange(n_frames), frame)
    chosen = training_subset(others, size - 1) if size > 1 else np.empty(0, np.int64)
    return np.sort(np.append(chosen, frame))


def _frame_scores(system, frame: int, size: int, fits: dict) -> dict:
    """Scheme -> the :class:`HoldoutScore` of ``frame`` of ``system`` (as :func:`plate_frames` gives it) at ``size``."""
    from fluorocal.stages.plate.holdout import holdout_scores

    problem, _, row = system
    sub, back = problem.of_frames(training_frames(problem.n_frames, frame, size))
    held = holdout_scores(sub, fits, row, layout=PLATE_SCHEMES[0], frames=[int(np.searchsorted(back, frame))])
    return {name: dataclasses.replace(score, frame=back[score.frame]) for name, score in held.items()}


def evaluate_plate(
    observations, sizes, schemes, setup: PlateSetup, *, scored=None, progress=None, step=None
) -> Evaluation:
    """The protocol of the module docstring on a plate's labelled holes.

    Parameters
    ----------
    observations : Observations
        The labelled holes of every frame.
    sizes : sequence of int
        Training sizes (frames), each within ``1 ..`` the frames of every system.
    schemes : sequence of str
        Of :data:`PLATE_SCHEMES`.
    setup : PlateSetup
    scored : array_like of int, optional
        Exposures whose frames are scored (default every frame).
    progress : callable, optional
        Called with each :class:`Score` as it is computed.
    step : callable, optional
        Called as ``step(size, done, total)`` when a training size starts (``done = 0``) and after each of its
        ``total`` scored frames' fits (every scheme on both row parities), before that size's scores.

    Returns
    -------
    Evaluation
        A :class:`Score` per size and scheme (all systems' holes pooled), and each scheme's held-out
        residuals at the largest size.

    Raises
    ------
    InputError
        An unknown scheme, a size outside a system's frames, or no frame to score.
    """
    from fluorocal.stages.plate.holdout import HoldoutScore

    unknown = [s for s in schemes if s not in PLATE_SCHEMES]
    if unknown:
        raise InputError(f"a grid plate is evaluated with the schemes {', '.join(PLATE_SCHEMES)}; got {unknown[0]!r}")
    fits = {name: fit for name, fit in plate_fits(setup).items() if name == PLATE_SCHEMES[0] or name in schemes}
    systems = plate_frames(observations, setup)
    chosen = [[f for f, e in enumerate(exposures) if scored is None or e in set(scored)] for _, exposures, _ in systems]
    if not any(chosen):
        raise InputError("no frame of the plate is to be scored")
    scores, residuals = [], []
    todo = [(s, f) for s, frames in enumerate(chosen) for f in frames]
    for size in sizes:
        parts = {name: [] for name in fits}
        if step is not None:
            step(size, 0, len(todo))
        for done, (s, f) in enumerate(todo, 1):
            try:
                held = _frame_scores(systems[s], f, size, fits)
            except EstimationError as exc:
                where = f"system {observations.system_names[s]}, exposure {systems[s][1][f]}"
                raise EstimationError(f"{where} (training size {size}): {exc}") from None
            for name, score in held.items():
                parts[name].append((s, score))
            if step is not None:
                step(size, done, len(todo))
        for name in schemes:
            pooled = HoldoutScore.concatenate(p for _, p in parts[name])
            system = np.concatenate([np.full(len(p.frame), s) for s, p in parts[name]])
            score = Score(
                name,
                size,
                len(pooled.frame),
                pooled.rms(pooled.in_sample_residual_px),
                pooled.rms(pooled.residual_px),
                out_nominal_rms_px=pooled.rms(pooled.nominal_residual_px),
                wall_s=pooled.fit_s,
            )
            scores.append(score)
            if size == max(sizes):
                residuals.append(HeldOutResiduals(name, size, system, pooled.xy_px, pooled.residual_px))
            if progress is not None:
                progress(score)
    return Evaluation(tuple(scores), tuple(residuals))


__all__ = [
    "PLATE_SCHEMES",
    "PlateSetup",
    "evaluate_plate",
    "plate_fits",
    "plate_frames",
    "training_frames",
    "uncorrected",
]
