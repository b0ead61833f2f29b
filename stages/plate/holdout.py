"""Held-out scoring of a plate calibration: each frame's alternate lattice rows left out in turn.

The issue's protocol: for frame ``f`` and row parity ``p``, the calibration is solved without frame
``f``'s holes on rows of parity ``p`` (every other frame complete); those holes are then corrected by
their orientation's field and compared, by a best-fitting homography, with the plate's self-calibrated
layout ``n + e`` (their ``e`` learned from the other frames). The figure is the RMS of that comparison's
residual over every held-out hole, px (per hole, the length of the 2-D residual).

Peers (:func:`holdout_scores`) are fitted on the same training holes of each split and scored the same
way, against the same layout: the one the self-calibration of that split found. A scheme is a function
``fit(training problem, scored frame) -> PlateFit``; :func:`solved` makes one of solve settings.
The same comparison on the scored frame's training holes (its other rows) is the in-sample figure.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial
from typing import Callable

import numpy as np
from fluorocal.stages.errors import EstimationError
from fluorocal.stages.geometry import homography_fit
from fluorocal.stages.plate.solve import PlateProblem, SolveSettings, solve_plate

#: the name under which :func:`holdout_score` runs its settings
_OURS = "plate"

#: fewest holes on either side of a frame's split: a homography (8 parameters) fitted to 4 leaves no residual
MIN_SPLIT_HOLES = 12


@dataclass(frozen=True)
class PlateFit:
    """What a scheme fitted on a split's training holes gives the scoring.

    Attributes
    ----------
    correct : callable
        Measured centres ``(M, 2)`` px of the scored frame -> corrected (ideal) centres ``(M, 2)`` px.
    plate_error_mm : (K, 2) float64 ndarray or None, mm
        The plate's estimated errors (the self-calibrated layout is ``nominal + error``); None: not estimated.
    """

    correct: Callable
    plate_error_mm: np.ndarray | None = None


@dataclass(frozen=True)
class HoldoutScore:
    """Held-out residuals of :func:`holdout_score`.

    Attributes
    ----------
    frame : (M,) int64 ndarray
        Frame of each held-out hole.
    residual_px : (M, 2) float64 ndarray, px
        Corrected centre less the homography image of the self-calibrated layout.
    nominal_residual_px : (M, 2) float64 ndarray, px
        The same against the nominal lattice (the plate's errors ignored), for comparison.
    xy_px : (M, 2) float64 ndarray, px
        The held-out holes' measured centres.
    in_sample_residual_px : (M', 2) float64 ndarray, px
        The same comparison as ``residual_px`` on the scored frames' training holes (in sample).
    fit_s : float
        Wall time of the scheme's fits, s.
    """

    frame: np.ndarray
    residual_px: np.ndarray
    nominal_residual_px: np.ndarray
    xy_px: np.ndarray
    in_sample_residual_px: np.ndarray
    fit_s: float = 0.0

    @staticmethod
    def rms(residual_px: np.ndarray) -> float:
        """RMS length of 2-D residuals, px."""
        return float(np.sqrt(np.mean(np.sum(residual_px**2, axis=1))))

    def per_frame(self) -> dict:
        """Frame -> (RMS against the self-calibrated layout, RMS against the nominal lattice), px."""
        return {
            int(f): (self.rms(self.residual_px[self.frame == f]), self.rms(self.nominal_residual_px[self.frame == f]))
            for f in np.unique(self.frame)
        }

    @classmethod
    def concatenate(cls, parts) -> "HoldoutScore":
        """One score of several (their holes stacked, their fit times summed)."""
        parts = list(parts)
        stacked = [np.concatenate([getattr(p, name) for p in parts]) for name in cls._ARRAYS]
        return cls(*stacked, fit_s=float(sum(p.fit_s for p in parts)))

    _ARRAYS = ("frame", "residual_px", "nominal_residual_px", "xy_px", "in_sample_residual_px")


def holdout_splits(problem: PlateProblem, row: np.ndarray, frames=None):
    """Each split ``(f, test)``: frame ``f``'s holes on lattice rows of one parity, a mask ``(N,)`` of the problem."""
    for f in range(problem.n_frames) if frames is None else frames:
        for parity in (0, 1):
            yield f, (problem.frame == f) & (row[problem.hole] % 2 == parity)


def holdout_score(problem: PlateProblem, settings: SolveSettings, row: np.ndarray, *, frames=None) -> HoldoutScore:
    """Solve once per (frame, row parity) with those holes left out and score them; see the module docstring.

    Parameters
    ----------
    problem : PlateProblem
    settings : SolveSettings
    row : (K,) int64 ndarray
        The lattice row of each hole (its parity splits the holes).
    frames : sequence of int, optional
        Frames to score (default all).
    """
    return holdout_scores(problem, {_OURS: solved(settings)}, row, layout=_OURS, frames=frames)[_OURS]


def holdout_scores(problem: PlateProblem, schemes: dict, row: np.ndarray, *, layout: str, frames=None) -> dict:
    """:func:`holdout_score` of every scheme on the same splits, against the layout scheme ``layout`` found.

    Parameters
    ----------
    problem : PlateProblem
    schemes : dict
        Name -> ``fit(training problem, scored frame) -> PlateFit``; the fit sees the training holes only
        (``problem.subset(~test)``, frame numbers kept).
    row : (K,) int64 ndarray
        The lattice row of each hole.
    layout : str
        The scheme whose ``plate_error_mm`` makes the self-calibrated layout of each split (one of ``schemes``).
    frames : sequence of int, optional
        Frames to score (default all).

    Returns
    -------
    dict
        Name -> :class:`HoldoutScore`.

    Raises
    ------
    EstimationError
        A split leaves fewer than ``MIN_SPLIT_HOLES`` holes on either side, or holes on one line (no
        homography to score them by with residuals left over).
    """
    parts = {name: [] for name in schemes}
    for f, test in holdout_splits(problem, row, frames):
        train_f = (problem.frame == f) & ~test
        if min(int(test.sum()), int(train_f.sum())) < MIN_SPLIT_HOLES:
            raise EstimationError(
                f"frame {f}: fewer than {MIN_SPLIT_HOLES} holes on alternate lattice rows; it cannot be scored"
            )
        train = problem.subset(~test)
        fits, seconds = {}, {}
        for name, fit in schemes.items():
            t0 = time.perf_counter()
            fits[name] = fit(train, f)
            seconds[name] = time.perf_counter() - t0
        error = fits[layout].plate_error_mm
        for name, fit in fits.items():
            held = [
                _homography_residual(t, fit.correct(problem.xy_px[test]), f) for t in _targets(problem, test, error)
            ]
            inside = _homography_residual(_targets(problem, train_f, error)[0], fit.correct(problem.xy_px[train_f]), f)
            frame = np.full(int(test.sum()), f)
            parts[name].append(HoldoutScore(frame, *held, problem.xy_px[test], inside, seconds[name]))
    return {name: HoldoutScore.concatenate(p) for name, p in parts.items()}


def _homography_residual(plate_mm: np.ndarray, xy_px: np.ndarray, frame: int) -> np.ndarray:
    """``xy_px`` less the best homography of ``plate_mm`` ``(M, 2)``; EstimationError when there is none."""
    fitted = homography_fit(plate_mm, xy_px)
    if fitted is None:
        raise EstimationError(f"frame {frame}: its holes on alternate lattice rows lie on a line; it cannot be scored")
    return fitted[1]


def _targets(problem: PlateProblem, mask: np.ndarray, error_mm) -> tuple[np.ndarray, np.ndarray]:
    """The self-calibrated layout and the nominal lattice ``(M, 2)`` mm of the holes of ``mask``."""
    nominal = problem.nominal_mm[problem.hole[mask]]
    return (nominal if error_mm is None else nominal + error_mm[problem.hole[mask]]), nominal


def solved(settings: SolveSettings) -> Callable:
    """A scheme of :func:`holdout_scores`: :func:`solve_plate` with ``settings``, the scored frame's field."""
    return partial(_solve_fit, settings)


def _solve_fit(settings: SolveSettings, train: PlateProblem, frame: int) -> PlateFit:
    solution = solve_plate(train, settings)
    field = solution.fields[train.orientation_of_frame[frame]]
    return PlateFit(field.undistort_points, solution.plate_error_mm)


__all__ = ["HoldoutScore", "PlateFit", "holdout_score", "holdout_scores", "holdout_splits", "solved"]
