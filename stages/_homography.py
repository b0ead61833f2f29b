"""Robust (Student-t) homography per frame for grid plates, all frames solved together.

Each frame's plate-to-image mapping is ``x = (h1 X + h2 Y + h3) / d``,
``y = (h4 X + h5 Y + h6) / d``, ``d = h7 X + h8 Y + 1`` in normalised
coordinates (plate and image centred and scaled per frame, Hartley's
conditioning). Levenberg–Marquardt runs on every frame at once: per-frame
8 x 8 normal equations are segment sums over the observations, the damping and
the accept/reject decision are per frame, and the t-scale σ² is estimated per
frame, exactly as in :mod:`stages._ba`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from fluorocal.stages._ba import t_weights, whiten, whitening
from fluorocal.stages.errors import EstimationError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameFit:
    """Per-frame homographies and per-observation statistics (observations in frame-sorted order)."""

    H: np.ndarray  # (F, 3, 3) image px from plate mm
    scale2: np.ndarray  # (F,) ML variance factors
    residual_px: np.ndarray  # (N, 2)
    s: np.ndarray  # (N,) squared Mahalanobis residuals
    hat: np.ndarray  # (N, 2, 2) J Q J^T with the whitened Jacobian, Q = (J^T W J)^-1 of its frame
    iterations: int
    converged: np.ndarray  # (F,) bool
    cost_history: tuple


def _normaliser(points: np.ndarray, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-segment centre (F, 2) and scale (F,) making the mean distance from the centre sqrt(2)."""
    counts = np.diff(np.r_[starts, len(points)])
    centre = np.add.reduceat(points, starts, axis=0) / counts[:, None]
    seg = np.repeat(np.arange(len(starts)), counts)
    dist = np.linalg.norm(points - centre[seg], axis=1)
    scale = math.sqrt(2) / np.maximum(np.add.reduceat(dist, starts) / counts, 1e-12)
    return centre, scale


def _initial(plate_n: np.ndarray, image_n: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Per-frame robust start ``(F, 8)`` from OpenCV (LMedS) in normalised coordinates."""
    import cv2

    ends = np.r_[starts[1:], len(plate_n)]
    h = np.zeros((len(starts), 8))
    for f, (a, b) in enumerate(zip(starts, ends)):
        H, _ = cv2.findHomography(plate_n[a:b], image_n[a:b], cv2.LMEDS)
        if H is None or not np.all(np.isfinite(H)) or abs(H[2, 2]) < 1e-12:
            raise EstimationError(f"frame {f}: no homography fits its {b - a} observations (degenerate layout)")
        h[f] = (H / H[2, 2]).ravel()[:8]
    return h


def _project(h: np.ndarray, plate_n: np.ndarray, seg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    hs = h[seg]
    X, Y = plate_n[:, 0], plate_n[:, 1]
    d = hs[:, 6] * X + hs[:, 7] * Y + 1.0
    u = (hs[:, 0] * X + hs[:, 1] * Y + hs[:, 2]) / d
    v = (hs[:, 3] * X + hs[:, 4] * Y + hs[:, 5]) / d
    return np.column_stack([u, v]), d


def _jacobian(h, plate_n, seg, linv_n) -> tuple[np.ndarray, np.ndarray]:
    """Whitened ``∂e/∂h`` (N, 2, 8) of ``e = L^-1 (ideal - projection)`` and the projection."""
    f, d = _project(h, plate_n, seg)
    X, Y = plate_n[:, 0] / d, plate_n[:, 1] / d
    zero = np.zeros_like(X)
    one_d = 1.0 / d
    u, v = f[:, 0], f[:, 1]
    dfdh = np.stack(
        [
            np.stack([X, Y, one_d, zero, zero, zero, -u * X, -u * Y], -1),
            np.stack([zero, zero, zero, X, Y, one_d, -v * X, -v * Y], -1),
        ],
        1,
    )
    return -whiten(linv_n, dfdh), f


def fit_homographies(
    plate_mm, image_px, sigma_px, frame_starts, *, nu, estimate_scale, max_iterations, function_tolerance
) -> FrameFit:
    """Student-t maximum-likelihood homography of every frame (observations sorted by frame).

    Parameters
    ----------
    plate_mm : (N, 2) float64 ndarray, mm
    image_px : (N, 2) float64 ndarray, px
        Ideal (distortion-corrected) coordinates.
    sigma_px : (N, 3) float64 ndarray
        ``(σx px, σy px, ρ)``.
    frame_starts : (F,) int64 ndarray
        First observation of each frame.
    """
    n_frames = len(frame_starts)
    counts = np.diff(np.r_[frame_starts, len(plate_mm)])
    if np.any(counts < 5):
        raise EstimationError(f"every frame needs >= 5 observations for a homography; got {int(counts.min())}")
    seg = np.repeat(np.arange(n_frames), counts)
    pc, ps = _normaliser(plate_mm, frame_starts)
    ic, is_ = _normaliser(image_px, frame_starts)
    plate_n = (plate_mm - pc[seg]) * ps[seg, None]
    image_n = (image_px - ic[seg]) * is_[seg, None]
    # whitening in normalised image units: σ scales by the frame's image scale
    sig_n = sigma_px * np.column_stack([is_[seg], is_[seg], np.ones(len(seg))])
    linv_n = whitening(sig_n)
    h = _initial(plate_n, image_n, frame_starts)

    def frame_cost(hh, scale2):
        """Per-frame cost (F,) (inf where a point maps through the horizon) and per-observation s (N,)."""
        f, d = _project(hh, plate_n, seg)
        bad = np.bincount(seg, d <= 0, n_frames) > 0
        e = whiten(linv_n, image_n - f)
        s = (e * e).sum(1)
        s2 = scale2[seg]
        rho = 0.5 * s / s2 if math.isinf(nu) else 0.5 * (nu + 2.0) * np.log1p(s / (nu * s2))
        per = np.bincount(seg, rho, n_frames) + counts * np.log(scale2)
        return np.where(bad, np.inf, per), s

    scale2 = np.ones(n_frames)
    cost, s = frame_cost(h, scale2)
    if estimate_scale:
        scale2 = _ml_scales(s, seg, counts, nu, scale2)
        cost, s = frame_cost(h, scale2)
    history = [float(cost.sum())]
    mu = np.full(n_frames, 1e-4)
    done = np.zeros(n_frames, bool)
    it = 0
    while it < max_iterations and not done.all():
        it += 1
        J, f = _jacobian(h, plate_n, seg, linv_n)
        e = whiten(linv_n, image_n - f)
        w = t_weights((e * e).sum(1), nu, 1.0) if math.isinf(nu) else (nu + 2.0) / (nu + (e * e).sum(1) / scale2[seg])
        Jw = J * np.sqrt(w)[:, None, None]
        H = np.add.reduceat(np.matmul(Jw.transpose(0, 2, 1), Jw), frame_starts, axis=0)
        b = -np.add.reduceat(np.einsum("nki,nk->ni", Jw, e * np.sqrt(w)[:, None]), frame_starts, axis=0)
        diag = np.einsum("fii->fi", H)
        step = np.linalg.solve(H + (mu[:, None] * diag)[:, :, None] * np.eye(8), b[:, :, None])[:, :, 0]
        step[done] = 0.0
        trial = h + step
        new_cost, s_new = frame_cost(trial, scale2)
        predicted = 0.5 * ((b * step).sum(1) + mu * (diag * step * step).sum(1)) / scale2
        actual = cost - new_cost
        ok = np.isfinite(new_cost) & (actual > 0) & (predicted > 0) & ~done
        rho = np.where(ok, actual / np.where(predicted > 0, predicted, 1.0), 0.0)
        h = np.where(ok[:, None], trial, h)
        mu = np.where(ok, np.maximum(mu * np.maximum(1 / 3, 1 - (2 * rho - 1) ** 3), 1e-12), mu * 4.0)
        cost_prev = cost.copy()
        cost, s = frame_cost(h, scale2)
        if estimate_scale:
            scale2 = _ml_scales(s, seg, counts, nu, scale2)
            cost, s = frame_cost(h, scale2)
        change = cost_prev - cost
        done |= (ok & (change <= function_tolerance)) | (~ok & (np.abs(actual) <= function_tolerance)) | (mu > 1e12)
        history.append(float(cost.sum()))
    # back to pixels and plate mm: H_px = T_img^-1 H_n T_plate
    Hn = np.concatenate([h, np.ones((n_frames, 1))], axis=1).reshape(-1, 3, 3)
    T_plate = np.zeros((n_frames, 3, 3))
    T_plate[:, 0, 0] = T_plate[:, 1, 1] = ps
    T_plate[:, :2, 2] = -pc * ps[:, None]
    T_plate[:, 2, 2] = 1
    T_img_inv = np.zeros((n_frames, 3, 3))
    T_img_inv[:, 0, 0] = T_img_inv[:, 1, 1] = 1 / is_
    T_img_inv[:, :2, 2] = ic
    T_img_inv[:, 2, 2] = 1
    H_px = T_img_inv @ Hn @ T_plate
    H_px /= H_px[:, 2:3, 2:3]
    J, f = _jacobian(h, plate_n, seg, linv_n)
    e = whiten(linv_n, image_n - f)
    s = (e * e).sum(1)
    w = t_weights(s, nu, 1.0) if math.isinf(nu) else (nu + 2.0) / (nu + s / scale2[seg])
    Jw = J * np.sqrt(w)[:, None, None]
    Q = np.linalg.inv(np.add.reduceat(np.matmul(Jw.transpose(0, 2, 1), Jw), frame_starts, axis=0))
    hat = np.einsum("nai,nij,nbj->nab", J, Q[seg], J)
    residual_px = (image_n - f) / is_[seg, None]
    return FrameFit(
        H=H_px,
        scale2=scale2,
        residual_px=residual_px,
        s=s,
        hat=hat,
        iterations=it,
        converged=done,
        cost_history=tuple(history),
    )


def _ml_scales(s, seg, counts, nu, scale2) -> np.ndarray:
    """Per-frame ML variance factors (vectorised EM fixed point of :func:`stages._ba.ml_scale`)."""
    for _ in range(100):
        w = t_weights(s, nu, 1.0) if math.isinf(nu) else (nu + 2.0) / (nu + s / scale2[seg])
        new = np.maximum(np.bincount(seg, w * s, len(counts)) / (2.0 * counts), 1e-300)
        if np.all(np.abs(new - scale2) <= 1e-10 * new):
            return new
        scale2 = new
    return scale2
