"""The motion of a sequence: a frame's orientation predicted from its labelled neighbours, and how well.

A turntable turns the phantom about an axis fixed in the lab, hence fixed in each system's camera frame,
by a roughly regular step; the axis may wobble (tilt) from frame to frame, and the phantom moves across
the floor. The orientation of an unlabelled frame is predicted between the nearest labelled frames on
either side (or from one side and the sequence's mean rotation per frame), and the prediction's error is
measured on the labelled frames themselves (each predicted from its own neighbours), separately for the
turn about the axis and the tilt across it: a regular step predicts the turn much better than the tilt.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# the turntable axis is estimated from the sequence once its labelled frames span this turn
_MIN_AXIS_TURN_DEG = 3.0
# the mean motion per frame is taken from labelled frames at most this many frames apart
_MAX_MOTION_GAP = 3
# the prediction's error (1 sigma, deg) assumed before the sequence shows it, and its floor
_DEFAULT_SIGMA_DEG = 4.0
_MIN_SIGMA_DEG = 0.5
# prediction errors measured on at least this many labelled frames replace the default
_MIN_RESIDUALS = 3


@dataclass(frozen=True)
class OrientationPrior:
    """A predicted orientation with its uncertainty: ``sigma_turn_rad`` about ``axis``, ``sigma_tilt_rad`` across it.

    Attributes
    ----------
    R : (3, 3) float64 ndarray
        Predicted rotation, object to camera.
    axis : (3,) float64 ndarray
        Unit turntable axis in the camera frame.
    sigma_turn_rad, sigma_tilt_rad : float
        1-sigma error of the prediction about the axis and across it (rad).
    """

    R: np.ndarray
    axis: np.ndarray
    sigma_turn_rad: float
    sigma_tilt_rad: float

    @classmethod
    def isotropic(cls, R: np.ndarray, sigma_rad: float) -> "OrientationPrior":
        """A prior with one uncertainty about every axis."""
        return cls(np.asarray(R, dtype=np.float64), np.array([0.0, 1.0, 0.0]), sigma_rad, sigma_rad)

    def distance(self, R: np.ndarray) -> float:
        """The rotation from the prediction to ``R`` in standard deviations (turn and tilt combined)."""
        from scipy.spatial.transform import Rotation

        v = Rotation.from_matrix(R @ self.R.T).as_rotvec()
        turn = float(v @ self.axis)
        tilt = float(np.linalg.norm(v - turn * self.axis))
        return float(np.hypot(turn / self.sigma_turn_rad, tilt / self.sigma_tilt_rad))


def predict(i: int, rotations: dict) -> tuple[OrientationPrior, int, bool] | None:
    """The orientation prior of frame ``i`` from the labelled frames' ``rotations`` (frame -> R), or None.

    Returns the prior, the nearest labelled frame, and whether the motion is known (labelled frames on
    both sides, or the sequence's mean rotation per frame); without it the prediction is that frame's
    orientation with the default uncertainty.
    """
    nb = neighbours(i, rotations)
    if nb == (None, None):
        return None
    axis = turntable_axis(list(rotations.values()))
    R, near, known = _predicted_rotation(i, nb, rotations, _mean_step(rotations))
    both = None not in nb
    sigmas = _prediction_sigmas(rotations, axis, both)
    return OrientationPrior(R, axis, *sigmas), near, known


def neighbours(i: int, rotations: dict) -> tuple:
    """The nearest labelled frames before and after frame ``i`` (None where there is none)."""
    before = [j for j in rotations if j < i]
    after = [j for j in rotations if j > i]
    return (max(before) if before else None, min(after) if after else None)


def _predicted_rotation(i: int, nb: tuple, rotations: dict, step: np.ndarray | None):
    """``(R, nearest labelled frame, motion known)``: interpolated between both sides, else moved on by ``step``."""
    from scipy.spatial.transform import Rotation, Slerp

    a, b = nb
    near = a if b is None or (a is not None and i - a <= b - i) else b
    if a is not None and b is not None:
        rot = Slerp([a, b], Rotation.from_matrix([rotations[a], rotations[b]]))([i])[0]
        return rot.as_matrix(), near, True
    if step is None:
        return rotations[near], near, False
    return Rotation.from_rotvec(step * (i - near)).as_matrix() @ rotations[near], near, True


def _mean_step(rotations: dict) -> np.ndarray | None:
    """The median rotation per frame (rotation vector, camera frame) between labelled frames a few frames apart."""
    from scipy.spatial.transform import Rotation

    frames = sorted(rotations)
    steps = [
        Rotation.from_matrix(rotations[k] @ rotations[j].T).as_rotvec() / (k - j)
        for j, k in zip(frames, frames[1:])
        if k - j <= _MAX_MOTION_GAP
    ]
    return np.median(steps, axis=0) if steps else None


def _prediction_sigmas(rotations: dict, axis: np.ndarray, both_sides: bool) -> tuple[float, float]:
    """1-sigma errors (rad) of the prediction about ``axis`` and across it, measured on the labelled frames.

    Each labelled frame with labelled frames near it (on both sides, or before it, as the prediction
    will be made) is predicted from them; the robust standard deviations of the misses about the axis
    (1.4826 x the median absolute turn) and across it (per component: the median tilt / 1.1774, the
    median of a 2D normal's length in its sigmas), floored at ``_MIN_SIGMA_DEG``. ``_DEFAULT_SIGMA_DEG``
    until ``_MIN_RESIDUALS`` frames show them.
    """
    from scipy.spatial.transform import Rotation

    misses = []
    for j in rotations:
        others = {k: R for k, R in rotations.items() if k != j and abs(k - j) <= _MAX_MOTION_GAP}
        nb = neighbours(j, others)
        if (both_sides and None in nb) or nb[0] is None:
            continue
        R, _, known = _predicted_rotation(j, nb if both_sides else (nb[0], None), others, _mean_step(others))
        if known:
            misses.append(Rotation.from_matrix(rotations[j] @ R.T).as_rotvec())
    if len(misses) < _MIN_RESIDUALS:
        return np.radians(_DEFAULT_SIGMA_DEG), np.radians(_DEFAULT_SIGMA_DEG)
    misses = np.asarray(misses)
    turn = misses @ axis
    tilt = np.linalg.norm(misses - np.outer(turn, axis), axis=1)
    floor = np.radians(_MIN_SIGMA_DEG)
    return max(floor, 1.4826 * float(np.median(np.abs(turn)))), max(floor, float(np.median(tilt)) / 1.1774)


def turntable_axis(rotations: list) -> np.ndarray:
    """The axis (camera frame) about which the phantom turns between the labelled frames of a sequence.

    A turntable turns the phantom about an axis fixed in the lab, hence in the camera frame of a
    system: ``R_j R_i^T`` is a turn about it. The axis is the principal direction of the rotation
    vectors of every labelled frame relative to the first, once they span at least
    ``_MIN_AXIS_TURN_DEG``; before that, the image's vertical axis (a turntable seen by a horizontal
    beam, the usual setup).
    """
    from scipy.spatial.transform import Rotation

    Rs = np.asarray(rotations)
    rotvecs = Rotation.from_matrix(Rs @ Rs[0].T).as_rotvec()
    if np.degrees(np.linalg.norm(rotvecs, axis=1).max()) < _MIN_AXIS_TURN_DEG:
        return np.array([0.0, 1.0, 0.0])
    return np.linalg.eigh(rotvecs.T @ rotvecs)[1][:, -1]
