"""Held-out scoring of a plate calibration: each frame's alternate lattice rows left out in turn.

The issue's protocol: for frame ``f`` and row parity ``p``, the calibration is solved without frame
``f``'s holes on rows of parity ``p`` (every other frame complete); those holes are then corrected by
their orientation's field and compared, by a best-fitting homography, with the plate's self-calibrated
layout ``n + e`` (their ``e`` learned from the other frames). The figure is the RMS of that comparison's
residual over every held-out hole, px (per hole, the length of the 2-D residual).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.geometry import homography_fit
from fluorocal.stages.plate.solve import PlateProblem, SolveSettings, solve_plate


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
    """

    frame: np.ndarray
    residual_px: np.ndarray
    nominal_residual_px: np.ndarray

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
    out_frame, out_res, out_nom = [], [], []
    for f in range(problem.n_frames) if frames is None else frames:
        for parity in (0, 1):
            test = (problem.frame == f) & (row[problem.hole] % 2 == parity)
            solution = solve_plate(problem.subset(~test), settings)
            field = solution.fields[problem.orientation_of_frame[f]]
            corrected = field.undistort_points(problem.xy_px[test])
            for layout, out in ((solution.plate_error_mm, out_res), (0.0, out_nom)):
                target = problem.nominal_mm[problem.hole[test]] + (layout[problem.hole[test]] if np.ndim(layout) else 0)
                out.append(homography_fit(target, corrected)[1])
            out_frame.append(np.full(int(test.sum()), f))
    return HoldoutScore(np.concatenate(out_frame), np.vstack(out_res), np.vstack(out_nom))
