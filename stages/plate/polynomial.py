"""Peer ``polynomial`` of a grid plate's evaluation: the global model of scheme ``polynomial``, the plate nominal.

The classic calibration with a plate: the plate taken as drawn, each frame's homography of it and one
radial + decentring model per orientation (:mod:`fluorocal.stages.adjust.polynomial`, the model scheme
``polynomial`` estimates in the adjustment: ``k1, k2, k3, p1, p2``, about the image centre, the affinity
held at zero as the adjustment holds it, a homography carrying it), fitted together to the training holes
of the scored frame's orientation by robust least squares (scipy's soft-L1 loss on the residuals in units
of their stated σ, bending at 3σ: a wrongly labelled hole does not pull the model).
"""

from __future__ import annotations

from functools import partial

import numpy as np
from fluorocal.stages.adjust import polynomial
from fluorocal.stages.errors import EstimationError
from fluorocal.stages.geometry import homography_fit
from fluorocal.stages.plate.holdout import PlateFit
from fluorocal.stages.plate.homography import Normaliser
from fluorocal.stages.plate.solve import PlateProblem

#: the model's coefficients fitted (k1, k2, k3, p1, p2; the affinity b1, b2 held at zero)
_FREE = 5
#: the soft-L1 loss's bend, in stated σ
_LOSS_SCALE = 3.0


def fit_polynomial(train: PlateProblem, frame: int) -> PlateFit:
    """Fit the model of ``frame``'s orientation and its frames' homographies on ``train``; see the module docstring.

    Raises
    ------
    EstimationError
        A frame of the orientation admits no homography, or the fit does not converge.
    """
    from scipy.optimize import least_squares

    sel = train.orientation == train.orientation_of_frame[frame]
    xy = train.xy_px[sel]
    plate = Normaliser.of(train.nominal_mm[train.hole[sel]])
    plate_n = plate.forward(train.nominal_mm[train.hole[sel]])
    frames, of = np.unique(train.frame[sel], return_inverse=True)
    centre = (np.asarray(train.image_size, dtype=np.float64) - 1) / 2
    radius = polynomial.reference_radius(xy)
    B = polynomial.basis(xy, centre, radius)[:, :, :_FREE]  # shape (N, 2, 5)
    weight = 1.0 / np.sqrt(np.mean(train.sigma_px[sel, :2] ** 2, axis=1))
    start = [np.zeros(_FREE)]
    for g in range(len(frames)):
        fit = homography_fit(plate_n[of == g], xy[of == g])
        if fit is None:
            raise EstimationError(f"frame {int(frames[g])}: its holes admit no homography")
        start.append((fit[0] / fit[0][2, 2]).ravel()[:8])

    def residual(x):
        H = np.column_stack([x[_FREE:].reshape(-1, 8), np.ones(len(frames))]).reshape(-1, 3, 3)[of]
        p = np.einsum("nij,nj->ni", H, np.column_stack([plate_n, np.ones(len(xy))]))
        ideal = xy - np.einsum("nij,j->ni", B, x[:_FREE])
        return ((ideal - p[:, :2] / p[:, 2:3]) * weight[:, None]).ravel()

    solution = least_squares(residual, np.concatenate(start), loss="soft_l1", f_scale=_LOSS_SCALE, x_scale="jac")
    if solution.status <= 0 or not np.all(np.isfinite(solution.x)):
        raise EstimationError(f"the polynomial model's fit did not converge: {solution.message}")
    coefficients = np.zeros(polynomial.N_AP)
    coefficients[:_FREE] = solution.x[:_FREE]
    return PlateFit(partial(_corrected, centre, radius, coefficients))


def _corrected(centre: np.ndarray, radius: float, coefficients: np.ndarray, xy_px: np.ndarray) -> np.ndarray:
    """``xy - Δ(xy)`` of the model, px."""
    return xy_px - polynomial.correction_at(xy_px, centre, radius, coefficients)


__all__ = ["fit_polynomial"]
