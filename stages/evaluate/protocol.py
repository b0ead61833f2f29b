"""The paper's protocol on labelled observations: calibrate on training epochs, score in and out of sample.

Every scheme ends as an :class:`Interior` per project: each system's IOP, its
correction ``Δ`` as a function of measured coordinates, the relative
orientation of the rig, and the training adjustment. The held-out epochs are
then scored the same way whatever produced it (:func:`score_interior`):
their poses and object points re-estimated by the robust adjustment with the
IOP and the correction held fixed, its inlier reprojection RMS, its object
points against check points; and for a biplanar rig the two-ray intersection
of the held-out pairs with the training calibration's IOP, ROP and fields.

The peer ``opencv`` (:func:`opencv_interior`) is OpenCV's ``calibrateCamera``
with the rational, thin-prism and tilted models on the check points (it needs
known 3D points), followed by the same training adjustment at its IOP and
correction (for the ROP and the in-sample figures).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from fluorocal.stages.adjust import FreeParameters, adjust_bundle
from fluorocal.stages.errors import CalibError, InputError
from fluorocal.stages.evaluate.metrics import (
    biplanar_errors,
    check_point_errors,
    ideal_points,
    inlier_rms_px,
    select,
    summarise,
    with_xy,
)
from fluorocal.stages.evaluate.split import training_subset
from fluorocal.stages.kinds.learning import CalibrationSetup, learn_calibration
from fluorocal.stages.learn import LearnParams, start_orientation

log = logging.getLogger(__name__)

#: the peer that needs check points
OPENCV = "opencv"

#: fewest check points a frame needs to enter OpenCV's calibration
OPENCV_MIN_POINTS = 10

#: OpenCV's stopping rule: its default 30 iterations, but stopping once the parameters change by less than 1e-9
#: (relative). Its default (machine epsilon) took 6x the CPU time on 30 simulated views of 1024 px (17 s against
#: 2.9 s) and ended at f = 3590 px, cx = 250 px (in-sample RMS 0.68 px) against the true 4370, 507 px; this rule at
#: f = 4323, cx = 511 px (0.91 px): the narrow-angle network leaves OpenCV's 18 intrinsics ill-determined either way
OPENCV_CRITERIA = (3, 30, 1e-9)  # cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS


@dataclass(frozen=True)
class EvaluationSetup:
    """What every calibration of one evaluation shares.

    Attributes
    ----------
    phantom : Phantom
        Nominal bead coordinates (the adjustment's datum).
    image_size_px : tuple of (int, int)
        ``(width, height)`` per system.
    iop_guess_px : tuple of (float, float, float)
        Start ``(xp, yp, c)`` per system.
    learn : LearnParams
    solver, selection : SolverOptions, DataSelection or None
        The project's ``[adjust]``.
    reference : tuple of ((R,) int64, (R, 3) float64 mm) or None
        Surveyed check points ``(ids, xyz)``; None: none given.
    """

    phantom: object
    image_size_px: tuple
    iop_guess_px: tuple
    learn: LearnParams = field(default_factory=LearnParams)
    solver: object = None
    selection: object = None
    reference: tuple | None = None


@dataclass(frozen=True)
class Interior:
    """A calibrated rig: per system IOP ``(S, 3)`` px and correction callables, the ROP and the training adjustment."""

    iop_px: np.ndarray
    corrections: tuple
    rop_q: np.ndarray
    rop_source_mm: np.ndarray
    training: object
    wall_s: float


@dataclass(frozen=True)
class Score:
    """One row of the evaluation: a scheme calibrated on ``n_train`` epochs, scored on ``n_heldout``.

    Lengths mm, reprojection px; NaN where a figure does not apply (no check points, one system).
    A grid plate's rows (:func:`~fluorocal.stages.evaluate.plate.evaluate_plate`): ``n_train`` frames,
    ``n_heldout`` held-out holes, ``in_rms_px`` / ``out_rms_px`` the training / held-out holes against the
    self-calibrated layout and ``out_nominal_rms_px`` the held-out holes against the nominal lattice (RMS
    lengths after a homography). ``tworay_*`` are the held-out pairs' two-ray intersections after a
    per-epoch rigid fit onto ``tworay_reference`` (``"check points"`` or ``"nominal phantom"``);
    ``in_3d_*`` / ``out_3d_*`` the training / held-out adjustment's object points against the check points.
    """

    scheme: str
    n_train: int
    n_heldout: int
    in_rms_px: float
    out_rms_px: float
    in_3d_rigid_mm: float = float("nan")
    in_3d_similarity_mm: float = float("nan")
    out_3d_rigid_mm: float = float("nan")
    out_3d_similarity_mm: float = float("nan")
    tworay_pairs: int = 0
    tworay_x_rmse_mm: float = float("nan")
    tworay_y_rmse_mm: float = float("nan")
    tworay_z_rmse_mm: float = float("nan")
    tworay_avg_rmse_mm: float = float("nan")
    tworay_mean_mm: float = float("nan")
    tworay_reference: str = ""
    out_nominal_rms_px: float = float("nan")
    wall_s: float = 0.0


def learned_interior(train_obs, scheme: str, setup: EvaluationSetup) -> Interior:
    """Calibrate ``train_obs`` with ``scheme`` as ``fluorocal run`` does (:func:`.learn_calibration`)."""
    t0 = time.perf_counter()
    plan = CalibrationSetup(scheme=scheme, image_size_px=setup.image_size_px, iop_guess_px=setup.iop_guess_px)
    res = learn_calibration(
        train_obs, setup.phantom, setup.learn, setup=plan, solver=setup.solver, selection=setup.selection
    )
    adj = res.adjustment
    corrections = tuple(res.field(s).correction_at for s in range(len(train_obs.system_names)))
    return Interior(adj.iop_px, corrections, adj.rop_q, adj.rop_source_mm, adj, time.perf_counter() - t0)


def opencv_interior(train_obs, setup: EvaluationSetup) -> Interior:
    """OpenCV's ``calibrateCamera`` (rational + thin prism + tilted) per system on the check points.

    Each system's interior becomes ``(cx, cy, f)`` with ``f`` the mean of ``fx, fy`` and the correction
    ``xy - undistort(xy)`` (``cv2.undistortPoints`` iterated to 1e-10, re-projected with that ``f``: exact for
    OpenCV's model); the training adjustment at them (IOP fixed) gives the ROP.

    Raises
    ------
    InputError
        No check points given, or a system has no training frame with :data:`OPENCV_MIN_POINTS` of them.
    """
    import cv2

    if setup.reference is None:
        raise InputError(f"scheme {OPENCV} needs --reference (OpenCV calibrates against known 3D points)")
    t0 = time.perf_counter()
    ref_ids, ref_xyz = setup.reference
    order = np.argsort(ref_ids)
    iop, corrections = [], []
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_THIN_PRISM_MODEL
    flags |= cv2.CALIB_TILTED_MODEL
    for s, name in enumerate(train_obs.system_names):
        obj, img = [], []
        for e in np.unique(train_obs.exposure[train_obs.system == s]):
            rows = np.flatnonzero((train_obs.system == s) & (train_obs.exposure == e))
            rows = rows[np.isin(train_obs.bead_id[rows], ref_ids)]
            if len(rows) >= OPENCV_MIN_POINTS:
                at = order[np.searchsorted(ref_ids, train_obs.bead_id[rows], sorter=order)]
                obj.append(ref_xyz[at].astype(np.float32))
                img.append(train_obs.xy_px[rows].astype(np.float32))
        if not obj:
            raise InputError(
                f"scheme {OPENCV}: no training frame of system {name} shows {OPENCV_MIN_POINTS} check points"
            )
        xp, yp, c = setup.iop_guess_px[s]
        K0 = np.array([[c, 0, xp], [0, c, yp], [0, 0, 1]], dtype=np.float64)
        size = tuple(setup.image_size_px[s])
        _, K, dist, _, _ = cv2.calibrateCamera(obj, img, size, K0, np.zeros(14), flags=flags, criteria=OPENCV_CRITERIA)
        f = (K[0, 0] + K[1, 1]) / 2
        iop.append((K[0, 2], K[1, 2], f))
        P = np.array([[f, 0, K[0, 2]], [0, f, K[1, 2]], [0, 0, 1]])
        corrections.append(partial(_opencv_correction, K, dist.ravel(), P))
    iop = np.array(iop)
    adj, _ = _adjust_fixed(train_obs, setup, iop, tuple(corrections))
    return Interior(iop, tuple(corrections), adj.rop_q, adj.rop_source_mm, adj, time.perf_counter() - t0)


def _opencv_correction(K, dist, P, xy_px: np.ndarray) -> np.ndarray:
    """``Δ = xy - ideal`` of OpenCV's model, ideal points projected with ``P``."""
    import cv2

    if not len(xy_px):
        return np.zeros((0, 2))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    src = np.ascontiguousarray(xy_px, dtype=np.float64).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(src, K, dist, R=None, P=P, criteria=criteria).reshape(-1, 2)
    return xy_px - ideal


def _adjust_fixed(obs, setup: EvaluationSetup, iop_px: np.ndarray, corrections: tuple):
    """The robust adjustment of ``obs`` with the IOP and the corrections held: poses, points and ROP free.

    Observations where a correction is not finite (a peer's model that does not invert there) are left out.
    """
    ideal = ideal_points(obs, corrections)
    finite = np.isfinite(ideal).all(axis=1)
    if not finite.all():
        log.warning("%d observation(s) left out: their correction is not finite", int((~finite).sum()))
        obs, ideal = select(obs, finite), ideal[finite]
    initial = start_orientation(with_xy(obs, ideal), setup.phantom, iop_px)
    return adjust_bundle(
        obs,
        setup.phantom,
        initial,
        obs.xy_px - ideal,
        free=FreeParameters(estimate_iop=False),
        solver=setup.solver,
        selection=setup.selection,
    ), obs


@dataclass(frozen=True)
class HeldOutResiduals:
    """The held-out adjustment's inlier residuals of one scheme: ``system (N,)``, ``xy_px``, ``residual_px (N, 2)``."""

    scheme: str
    n_train: int
    system: np.ndarray
    xy_px: np.ndarray
    residual_px: np.ndarray


@dataclass(frozen=True)
class Evaluation:
    """:func:`evaluate`'s result: a :class:`Score` per scheme and size, residuals at the largest size per scheme."""

    scores: tuple
    residuals: tuple


def score_interior(interior: Interior, scheme: str, n_train: int, test_obs, setup: EvaluationSetup) -> Score:
    """Score a calibrated rig in sample (its training adjustment) and on the held-out observations ``test_obs``."""
    return _score(interior, scheme, n_train, test_obs, setup)[0]


def _score(interior: Interior, scheme: str, n_train: int, test_obs, setup: EvaluationSetup):
    """:func:`score_interior`, with the held-out adjustment's inlier residuals."""
    held, used = _adjust_fixed(test_obs, setup, interior.iop_px, interior.corrections)
    keep = held.inlier & held.used
    residuals = HeldOutResiduals(scheme, n_train, used.system[keep], used.xy_px[keep], held.residual_px[keep])
    figures = {}
    if setup.reference is not None:
        ids, xyz = setup.reference
        for where, adj in (("in", interior.training), ("out", held)):
            for fit, with_scale in (("rigid", False), ("similarity", True)):
                dist = check_point_errors(adj.bead_id, adj.xyz_mm, ids, xyz, with_scale=with_scale)
                figures[f"{where}_3d_{fit}_mm"] = float(np.sqrt(np.mean(dist**2)))
    if len(test_obs.system_names) == 2:
        ids, xyz = setup.reference if setup.reference is not None else (setup.phantom.ids, setup.phantom.xyz_mm)
        ideal = ideal_points(test_obs, interior.corrections)
        err = biplanar_errors(test_obs, ideal, interior.iop_px, interior.rop_q, interior.rop_source_mm, ids, xyz)
        st = summarise(err)
        x, y, z = st["axes"]
        figures.update(
            tworay_pairs=st["n"],
            tworay_x_rmse_mm=float(x),
            tworay_y_rmse_mm=float(y),
            tworay_z_rmse_mm=float(z),
            tworay_avg_rmse_mm=st["avg_rmse"],
            tworay_mean_mm=st["mean"],
            tworay_reference="check points" if setup.reference is not None else "nominal phantom",
        )
    score = Score(
        scheme,
        n_train,
        len(np.unique(test_obs.exposure)),
        inlier_rms_px(interior.training),
        inlier_rms_px(held),
        wall_s=interior.wall_s,
        **figures,
    )
    return score, residuals


def evaluate(obs, heldout, sizes, schemes, setup: EvaluationSetup, *, progress=None) -> Evaluation:
    """The protocol: per training size and scheme, calibrate on a training subset and score it.

    Parameters
    ----------
    obs : Observations
        Every labelled observation of the project.
    heldout : (H,) int64 array_like
        Held-out epochs; every other epoch of ``obs`` trains.
    sizes : sequence of int
        Training sizes (epochs), each at most the number of training epochs
        (:func:`~fluorocal.stages.evaluate.split.training_subset` picks them evenly spaced).
    schemes : sequence of str
        Schemes of :func:`fluorocal.stages.learn.calibrate` and/or :data:`OPENCV`.
    setup : EvaluationSetup
    progress : callable, optional
        Called with each :class:`Score` as it is computed.

    Returns
    -------
    Evaluation
        The scores in the order computed (size, then scheme), and the held-out residuals of each
        scheme at the largest size.

    Raises
    ------
    InputError
        No held-out or no training observation.
    CalibError
        A calibration failed as a whole (its scheme and size named; the class of the failure kept).
    """
    held_mask = np.isin(obs.exposure, np.asarray(heldout, dtype=np.int64))
    if not held_mask.any() or held_mask.all():
        raise InputError("the holdout must leave at least one held-out and one training epoch with observations")
    test_obs = select(obs, held_mask)
    train_epochs = np.unique(obs.exposure[~held_mask])
    scores, residuals = [], []
    for size in sizes:
        train_obs = select(obs, np.isin(obs.exposure, training_subset(train_epochs, size)))
        for scheme in schemes:
            try:
                if scheme == OPENCV:
                    interior = opencv_interior(train_obs, setup)
                else:
                    interior = learned_interior(train_obs, scheme, setup)
                score, held = _score(interior, scheme, size, test_obs, setup)
            except CalibError as exc:
                raise type(exc)(f"scheme {scheme}, {size} training epochs: {exc}") from exc
            scores.append(score)
            if size == max(sizes):
                residuals.append(held)
            if progress is not None:
                progress(score)
    return Evaluation(tuple(scores), tuple(residuals))


__all__ = [
    "OPENCV",
    "EvaluationSetup",
    "Interior",
    "Score",
    "HeldOutResiduals",
    "Evaluation",
    "learned_interior",
    "opencv_interior",
    "score_interior",
    "evaluate",
]
