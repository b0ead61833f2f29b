"""Robust (Student-t) homography per frame for grid plates, all frames solved together.

Each frame's plate-to-image mapping is ``x = (h1 X + h2 Y + h3) / d``,
``y = (h4 X + h5 Y + h6) / d``, ``d = h7 X + h8 Y + 1`` in normalised
coordinates (plate and image centred and scaled per frame, Hartley's
conditioning). Levenberg–Marquardt runs on every frame at once: per-frame
8 x 8 normal equations are segment sums over the observations, the damping and
the accept/reject decision are per frame, and the t-scale σ² is estimated per
frame, with the bundle adjustment's likelihood (:mod:`stages.adjust.robust`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from fluorocal.stages.adjust.collinearity import whiten, whitening
from fluorocal.stages.adjust.robust import ml_scales, t_rho, t_weights
from fluorocal.stages.errors import EstimationError


@dataclass(frozen=True)
class FrameFit:
    """Per-frame homographies and per-observation statistics (observations in frame-sorted order)."""

    H: np.ndarray  # (F, 3, 3) image px from plate mm
    scale2: np.ndarray  # (F,) ML variance factors
    residual_px: np.ndarray  # (N, 2)
    s: np.ndarray  # (N,) squared Mahalanobis residuals
    weight: np.ndarray  # (N,) final t-weights
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
    """Whitened ``∂e/∂h`` (N, 2, 8) of ``e = L^-1 (ideal - projection)`` and the projection.

    ``∂f/∂h`` has rows ``(X, Y, 1, 0, 0, 0, -u X, -u Y) / d`` and ``(0, 0, 0, X, Y, 1, -v X, -v Y) / d``;
    ``L^-1`` (lower triangular) is applied to their non-zero blocks only.
    """
    f, d = _project(h, plate_n, seg)
    X, Y = plate_n[:, 0] / d, plate_n[:, 1] / d
    u, v = f[:, 0], f[:, 1]
    row0 = np.column_stack([X, Y, 1.0 / d])  # columns 0-2 of the x row, 3-5 of the y row
    l11, l21, l22 = (-linv_n[:, i, None] for i in range(3))
    J = np.empty((len(X), 2, 8))
    J[:, 0, :3] = l11 * row0
    J[:, 0, 3:6] = 0.0
    J[:, 1, :3] = l21 * row0
    J[:, 1, 3:6] = l22 * row0
    ux, vx = np.column_stack([-u * X, -u * Y]), np.column_stack([-v * X, -v * Y])
    J[:, 0, 6:] = l11 * ux
    J[:, 1, 6:] = l21 * ux + l22 * vx
    return J, f


@dataclass(frozen=True)
class _Frames:
    """Observations sorted by frame, in each frame's normalised plate and image coordinates."""

    plate_n: np.ndarray  # (N, 2)
    image_n: np.ndarray  # (N, 2)
    linv_n: np.ndarray  # (N, 3) whitening in normalised image units
    seg: np.ndarray  # (N,) frame of each observation
    counts: np.ndarray  # (F,) observations per frame
    starts: np.ndarray  # (F,) first observation of each frame
    plate_centre: np.ndarray  # (F, 2) mm
    plate_scale: np.ndarray  # (F,) 1/mm
    image_centre: np.ndarray  # (F, 2) px
    image_scale: np.ndarray  # (F,) 1/px

    def cost(self, h: np.ndarray, scale2: np.ndarray, nu: float) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame cost (F,) (inf where a point maps through the horizon) and per-observation s (N,)."""
        n_frames = len(self.starts)
        f, d = _project(h, self.plate_n, self.seg)
        bad = np.bincount(self.seg, d <= 0, n_frames) > 0
        e = whiten(self.linv_n, self.image_n - f)
        s = (e * e).sum(1)
        per = np.bincount(self.seg, t_rho(s, nu, scale2[self.seg]), n_frames) + self.counts * np.log(scale2)
        return np.where(bad, np.inf, per), s

    def weighted_normal(self, h: np.ndarray, scale2: np.ndarray, nu: float):
        """``H = Σ w J^T J`` (F, 8, 8), ``b = -Σ w J^T e`` (F, 8) per frame; J (N, 2, 8), f, e (N, 2), w (N,)."""
        J, f = _jacobian(h, self.plate_n, self.seg, self.linv_n)
        e = whiten(self.linv_n, self.image_n - f)
        w = t_weights((e * e).sum(1), nu, scale2[self.seg])
        root = np.sqrt(w)
        Jw = (J * root[:, None, None]).reshape(-1, 8)  # two rows per observation
        ew = (e * root[:, None]).ravel()
        H = np.empty((len(self.starts), 8, 8))
        b = np.empty((len(self.starts), 8))
        for k, (lo, hi) in enumerate(zip(2 * self.starts, 2 * np.r_[self.starts[1:], len(e)])):
            H[k] = Jw[lo:hi].T @ Jw[lo:hi]
            b[k] = -(ew[lo:hi] @ Jw[lo:hi])
        return H, b, J, f, e, w


def _normalised(plate_mm, image_px, sigma_px, frame_starts) -> _Frames:
    n_frames = len(frame_starts)
    counts = np.diff(np.r_[frame_starts, len(plate_mm)])
    if np.any(counts < 5):
        raise EstimationError(f"every frame needs >= 5 observations for a homography; got {int(counts.min())}")
    seg = np.repeat(np.arange(n_frames), counts)
    pc, ps = _normaliser(plate_mm, frame_starts)
    ic, is_ = _normaliser(image_px, frame_starts)
    # whitening in normalised image units: σ scales by the frame's image scale
    sig_n = sigma_px * np.column_stack([is_[seg], is_[seg], np.ones(len(seg))])
    return _Frames(
        plate_n=(plate_mm - pc[seg]) * ps[seg, None],
        image_n=(image_px - ic[seg]) * is_[seg, None],
        linv_n=whitening(sig_n),
        seg=seg,
        counts=counts,
        starts=np.asarray(frame_starts),
        plate_centre=pc,
        plate_scale=ps,
        image_centre=ic,
        image_scale=is_,
    )


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
    nu, estimate_scale, max_iterations, function_tolerance
        As in :class:`stages.adjust.SolverOptions`.

    Raises
    ------
    EstimationError
        A frame with fewer than 5 observations, or whose layout admits no homography.
    """
    frames = _normalised(plate_mm, image_px, sigma_px, frame_starts)
    n_frames = len(frame_starts)
    h = _initial(frames.plate_n, frames.image_n, frame_starts)
    scale2 = np.ones(n_frames)
    cost, s = frames.cost(h, scale2, nu)
    if estimate_scale:
        scale2 = ml_scales(s, frames.seg, frames.counts, nu, scale2)
        cost, s = frames.cost(h, scale2, nu)
    history = [float(cost.sum())]
    mu = np.full(n_frames, 1e-4)
    done = np.zeros(n_frames, bool)
    it = 0
    while it < max_iterations and not done.all():
        it += 1
        H, b, _, _, _, _ = frames.weighted_normal(h, scale2, nu)
        diag = np.einsum("fii->fi", H)
        step = np.linalg.solve(H + (mu[:, None] * diag)[:, :, None] * np.eye(8), b[:, :, None])[:, :, 0]
        step[done] = 0.0
        trial = h + step
        new_cost, new_s = frames.cost(trial, scale2, nu)
        predicted = 0.5 * ((b * step).sum(1) + mu * (diag * step * step).sum(1)) / scale2
        actual = cost - new_cost
        ok = np.isfinite(new_cost) & (actual > 0) & (predicted > 0) & ~done
        rho = np.where(ok, actual / np.where(predicted > 0, predicted, 1.0), 0.0)
        h = np.where(ok[:, None], trial, h)
        mu = np.where(ok, np.maximum(mu * np.maximum(1 / 3, 1 - (2 * rho - 1) ** 3), 1e-12), mu * 4.0)
        cost_prev = cost.copy()
        # the cost at the new h: per frame the trial's or the last one's (a frame's cost is its observations' alone)
        cost = np.where(ok, new_cost, cost)
        s = np.where(ok[frames.seg], new_s, s)
        if estimate_scale:
            scale2 = ml_scales(s, frames.seg, frames.counts, nu, scale2)
            cost, s = frames.cost(h, scale2, nu)
        change = cost_prev - cost
        done |= (ok & (change <= function_tolerance)) | (~ok & (np.abs(actual) <= function_tolerance)) | (mu > 1e12)
        history.append(float(cost.sum()))
    return _frame_fit(frames, h, scale2, nu, it, done, tuple(history))


def _frame_fit(frames: _Frames, h, scale2, nu, iterations, done, history) -> FrameFit:
    """Homographies in px from plate mm, and the per-observation statistics, at the solution ``h`` (F, 8)."""
    n_frames = len(frames.starts)
    # back to pixels and plate mm: H_px = T_img^-1 H_n T_plate
    ps, pc, is_, ic = frames.plate_scale, frames.plate_centre, frames.image_scale, frames.image_centre
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
    H, _, J, f, e, w = frames.weighted_normal(h, scale2, nu)
    Q = np.linalg.inv(H)
    JQ = np.empty_like(J)
    for k, (lo, hi) in enumerate(zip(frames.starts, np.r_[frames.starts[1:], len(J)])):
        JQ[lo:hi] = J[lo:hi] @ Q[k]
    hat = np.einsum("nai,nbi->nab", JQ, J)
    return FrameFit(
        H=H_px,
        scale2=scale2,
        residual_px=(frames.image_n - f) / is_[frames.seg, None],
        s=(e * e).sum(1),
        weight=w,
        hat=hat,
        iterations=iterations,
        converged=done,
        cost_history=history,
    )
