"""One calibration for the same observations in any order: the learning's rows in a canonical order.

Everything downstream of the stage's entry depends on the order of the observation rows: the
cross-validation's shuffled folds draw from the rows' positions, KD-tree queries break distance ties
by position, floating-point sums accumulate in row order, the local screen keeps the first of equals.
Each is harmless alone, yet the alternation amplifies them: the same observations listed in another
order gave another calibration (issue 30). :func:`canonical_order` sorts the rows by system, exposure
and the measured coordinates (then by bead id, so that even duplicated coordinates have one order),
the learning runs on the sorted rows, and :func:`unpermuted_result` hands every per-observation
array back in the caller's order. The bead ids are names, not data: sorted by them, a phantom whose
beads were numbered otherwise (one bead renamed) gave other rows, and the loop another stopping point
(object points 0.01 mm apart); sorted by where the beads were seen, it gives the same calibration. The
systems keep their order: it is meaningful (the first system is the biplanar reference that the others'
relative orientation is to).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from fluorocal.stages.artifacts import Observations

#: the per-observation arrays of an adjustment (rows of the observations)
_ADJUSTMENT_ROWS = ("residual_px", "standardized_residual", "redundancy", "weight", "inlier", "used")


def canonical_order(observations: Observations) -> np.ndarray:
    """The permutation ``(N,)`` that sorts the rows by system, exposure, x and y, then bead id.

    Examples
    --------
    >>> xy = np.array([[5.0, 1.0], [2.0, 0.0], [2.0, 0.0]])
    >>> obs = Observations([0, 0, 0], [2, 1, 1], [5, 9, 3], xy, np.ones((3, 3)))
    >>> canonical_order(obs).tolist()
    [2, 1, 0]
    """
    keys = (observations.bead_id, observations.xy_px[:, 1], observations.xy_px[:, 0], observations.exposure)
    return np.lexsort((*keys, observations.system))


def taken(observations: Observations, order: np.ndarray) -> Observations:
    """The observations' rows in ``order``."""
    o = observations
    return Observations(
        o.system[order], o.exposure[order], o.bead_id[order], o.xy_px[order], o.sigma_px[order], o.system_names
    )


def _restored(array, inverse: np.ndarray):
    return None if array is None else np.asarray(array)[inverse]


def unpermuted_result(result, order: np.ndarray):
    """A :class:`~fluorocal.stages.learn.result.LearnResult` of the rows in ``order``, back in the caller's order."""
    inverse = np.argsort(order)
    if np.array_equal(order, np.arange(len(order))):
        return result
    adj = result.adjustment
    adj = replace(adj, **{name: _restored(getattr(adj, name), inverse) for name in _ADJUSTMENT_ROWS})
    rows = ("corrections_px", "initial_residual_px", "trained")
    return replace(result, adjustment=adj, **{name: _restored(getattr(result, name), inverse) for name in rows})


__all__ = ["canonical_order", "taken", "unpermuted_result"]
