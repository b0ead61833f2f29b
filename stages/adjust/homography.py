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
from fluorocal.stages.adjust.collinearity import whitening
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


def _project(h: np.ndarray, plate_t: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projections ``u, v`` (N,) of the plate points ``plate_t`` (2, N) and their denominators ``d`` (N,)."""
    hs = np.repeat(h.T, counts, axis=1)  # (8, N): each observation's frame's h, one contiguous row per entry
    X, Y = plate_t
    d = hs[6] * X + hs[7] * Y + 1.0
    u = (hs[0] * X + hs[1] * Y + hs[2]) / d
    v = (hs[3] * X + hs[4] * Y + hs[5]) / d
    return u, v, d


def _jacobian_rows(u, v, d, plate_t, linv_t) -> np.ndarray:
    """Whitened ``∂e/∂h`` as rows ``(16, N)`` (x then y component, 8 entries each) of ``e = L^-1 (ideal - projection)``.

    ``∂f/∂h`` has rows ``(X, Y, 1, 0, 0, 0, -u X, -u Y) / d`` and ``(0, 0, 0, X, Y, 1, -v X, -v Y) / d``;
    ``L^-1`` (lower triangular) is applied to their non-zero blocks only.
    """
    X, Y, one = plate_t[0] / d, plate_t[1] / d, 1.0 / d
    l11, l21, l22 = -linv_t
    ux, uy, vx, vy = -u * X, -u * Y, -v * X, -v * Y
    rows = np.zeros((16, len(d)))
    rows[0], rows[1], rows[2], rows[6], rows[7] = l11 * X, l11 * Y, l11 * one, l11 * ux, l11 * uy
    rows[8], rows[9], rows[10] = l21 * X, l21 * Y, l21 * one
    rows[11], rows[12], rows[13] = l22 * X, l22 * Y, l22 * one
    rows[14], rows[15] = l21 * ux + l22 * vx, l21 * uy + l22 * vy
    return rows


@dataclass(frozen=True)
class _Frames:
    """Observations sorted by frame, in each frame's normalised plate and image coordinates.

    The per-observation arrays are also held transposed (``_t``, one contiguous row per coordinate).
    """

    plate_n: np.ndarray  # (N, 2)
    image_n: np.ndarray  # (N, 2)
    plate_t: np.ndarray  # (2, N)
    image_t: np.ndarray  # (2, N)
    linv_t: np.ndarray  # (3, N) whitening in normalised image units
    seg: np.ndarray  # (N,) frame of each observation
    counts: np.ndarray  # (F,) observations per frame
    starts: np.ndarray  # (F,) first observation of each frame
    plate_centre: np.ndarray  # (F, 2) mm
    plate_scale: np.ndarray  # (F,) 1/mm
    image_centre: np.ndarray  # (F, 2) px
    image_scale: np.ndarray  # (F,) 1/px

    def whitened(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """The whitened residuals ``e = L^-1 (ideal - (u, v))``, as two rows ``(N,)``."""
        rx, ry = self.image_t[0] - u, self.image_t[1] - v
        l11, l21, l22 = self.linv_t
        return l11 * rx, l21 * rx + l22 * ry

    def cost(self, h: np.ndarray, scale2: np.ndarray, nu: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-frame cost (F,) (inf where a point maps through the horizon), per-observation s (N,), that flag (F,)."""
        u, v, d = _project(h, self.plate_t, self.counts)
        bad = np.bincount(self.seg, d <= 0, len(self.starts)) > 0
        e0, e1 = self.whitened(u, v)
        s = e0 * e0 + e1 * e1
        return self.cost_of(s, bad, scale2, nu), s, bad

    def cost_of(self, s: np.ndarray, bad: np.ndarray, scale2: np.ndarray, nu: float) -> np.ndarray:
        """Per-frame cost (F,) of the squared residuals ``s`` (N,), inf where ``bad`` (F,)."""
        rho = t_rho(s, nu, np.repeat(scale2, self.counts))
        per = np.bincount(self.seg, rho, len(self.starts)) + self.counts * np.log(scale2)
        return np.where(bad, np.inf, per)

    def weighted_normal(self, h: np.ndarray, scale2: np.ndarray, nu: float):
        """``H = Σ w J^T J`` (F, 8, 8), ``b = -Σ w J^T e`` (F, 8) per frame; J as rows (16, N), u, v, e0, e1, w (N,)."""
        u, v, d = _project(h, self.plate_t, self.counts)
        rows = _jacobian_rows(u, v, d, self.plate_t, self.linv_t)
        e0, e1 = self.whitened(u, v)
        w = t_weights(e0 * e0 + e1 * e1, nu, np.repeat(scale2, self.counts))
        root = np.sqrt(w)
        Jw = np.ascontiguousarray((rows * root).T).reshape(-1, 8)  # two rows per observation
        ew = np.column_stack([e0 * root, e1 * root]).ravel()
        H = np.empty((len(self.starts), 8, 8))
        b = np.empty((len(self.starts), 8))
        for k, (lo, hi) in enumerate(zip(2 * self.starts, 2 * np.r_[self.starts[1:], len(w)])):
            H[k] = Jw[lo:hi].T @ Jw[lo:hi]
            b[k] = -(ew[lo:hi] @ Jw[lo:hi])
        return H, b, rows, (u, v), (e0, e1), w


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
    plate_n = (plate_mm - pc[seg]) * ps[seg, None]
    image_n = (image_px - ic[seg]) * is_[seg, None]
    return _Frames(
        plate_n=plate_n,
        image_n=image_n,
        plate_t=np.ascontiguousarray(plate_n.T),
        image_t=np.ascontiguousarray(image_n.T),
        linv_t=np.ascontiguousarray(whitening(sig_n).T),
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
    cost, s, bad = frames.cost(h, scale2, nu)
    if estimate_scale:
        scale2 = ml_scales(s, frames.counts, nu, scale2)
        cost = frames.cost_of(s, bad, scale2, nu)
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
        new_cost, new_s, _ = frames.cost(trial, scale2, nu)
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
        bad &= ~ok  # an accepted trial's cost is finite: none of its points maps through the horizon
        if estimate_scale:
            scale2 = ml_scales(s, frames.counts, nu, scale2)
            cost = frames.cost_of(s, bad, scale2, nu)  # the residuals at h are s: only the scale changed
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
    H, _, rows, (u, v), (e0, e1), w = frames.weighted_normal(h, scale2, nu)
    J = np.ascontiguousarray(rows.T).reshape(-1, 2, 8)
    Q = np.linalg.inv(H)
    JQ = np.empty_like(J)
    for k, (lo, hi) in enumerate(zip(frames.starts, np.r_[frames.starts[1:], len(J)])):
        JQ[lo:hi] = J[lo:hi] @ Q[k]
    hat = np.einsum("nai,nbi->nab", JQ, J)
    return FrameFit(
        H=H_px,
        scale2=scale2,
        residual_px=(frames.image_n - np.column_stack([u, v])) / is_[frames.seg, None],
        s=e0 * e0 + e1 * e1,
        weight=w,
        hat=hat,
        iterations=iterations,
        converged=done,
        cost_history=history,
    )
