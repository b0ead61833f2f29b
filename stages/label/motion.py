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
# the depth's prediction error (1 sigma, fraction of the depth) assumed before the sequence shows it, and its floor
_DEFAULT_SIGMA_DEPTH = 0.025
_MIN_SIGMA_DEPTH = 0.003


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
    depth_mm, sigma_depth_mm : float or None
        The phantom centre's predicted distance from the source along the beam (mm, in the frame's
        assumed camera) and its 1-sigma error; None: unknown (a neighbour's, with a default error).
    """

    R: np.ndarray
    axis: np.ndarray
    sigma_turn_rad: float
    sigma_tilt_rad: float
    depth_mm: float | None = None
    sigma_depth_mm: float | None = None

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


@dataclass(frozen=True)
class Motion:
    """What the labelled frames of a sequence say about its motion, computed once for a set of them.

    Attributes
    ----------
    axis : (3,) float64 ndarray
        The turntable axis, camera frame (:func:`turntable_axis`).
    step : (3,) float64 ndarray or None
        The median rotation per frame (rotation vector), None without labelled frames close enough.
    sigmas_both, sigmas_one : tuple of float
        ``(turn, tilt)`` 1-sigma errors (rad) of a prediction between labelled frames, and beside them.
    depths : dict
        Frame -> the phantom centre's distance from the source (mm) of the labelled frames.
    depth_from_neighbours : bool
        The depth is predicted from the nearest labelled frames (smooth motion), else as the median of all
        (a turntable moved at random between exposures), whichever misses less on the labelled frames.
    sigma_depth_mm : float
        1-sigma error of that prediction.
    """

    axis: np.ndarray
    step: np.ndarray | None
    sigmas_both: tuple
    sigmas_one: tuple
    depths: dict
    depth_from_neighbours: bool
    sigma_depth_mm: float

    @classmethod
    def of(cls, rotations: dict, depths: dict | None = None) -> "Motion":
        """The motion of the labelled frames' ``rotations`` (frame -> R, object to camera) and ``depths`` (mm)."""
        axis = turntable_axis(list(rotations.values()))
        depths = dict(depths or {})
        from_neighbours, sigma = _depth_model(depths)
        turn = _turns(rotations)
        return cls(
            axis,
            _mean_step(rotations, turn),
            _prediction_sigmas(rotations, axis, True, turn),
            _prediction_sigmas(rotations, axis, False, turn),
            depths,
            from_neighbours,
            sigma,
        )


def predict(i: int, rotations: dict, motion: Motion | None = None) -> tuple[OrientationPrior, int, bool] | None:
    """The orientation prior of frame ``i`` from the labelled frames' ``rotations`` (frame -> R), or None.

    Returns the prior, the nearest labelled frame, and whether the motion is known (labelled frames on
    both sides, or the sequence's mean rotation per frame); without it the prediction is that frame's
    orientation with the default uncertainty. ``motion`` (default: that of ``rotations``) may come from a
    larger set of frames, e.g. with frame ``i`` itself; with its ``depths``, the prior predicts the depth.
    """
    others = {j: R for j, R in rotations.items() if j != i}
    nb = neighbours(i, others)
    if nb == (None, None):
        return None
    motion = motion or Motion.of(others)
    R, near, known = _predicted_rotation(i, nb, others, motion.step)
    sigmas = motion.sigmas_both if None not in nb else motion.sigmas_one
    depths = {j: z for j, z in motion.depths.items() if j != i}
    depth = _predicted_depth(i, depths, motion.depth_from_neighbours) if depths else None
    return (
        OrientationPrior(R, motion.axis, *sigmas, depth, motion.sigma_depth_mm if depth is not None else None),
        near,
        known,
    )


def _predicted_depth(i: int, depths: dict, from_neighbours: bool) -> float:
    """Frame ``i``'s depth: interpolated between (or from) the nearest labelled frames, or the median of all."""
    if not from_neighbours:
        return float(np.median(list(depths.values())))
    a, b = neighbours(i, depths)
    if a is None or b is None:
        return float(depths[a if b is None else b])
    return float(depths[a] + (depths[b] - depths[a]) * (i - a) / (b - a))


def _depth_model(depths: dict) -> tuple[bool, float]:
    """Whether the depth is better predicted from the neighbours than as the median, and that prediction's sigma.

    Each labelled frame's depth is predicted from the others both ways (leave one out); the robust
    standard deviation (1.4826 x median absolute miss) of each, floored at ``_MIN_SIGMA_DEPTH`` of the
    depth; the default (``_DEFAULT_SIGMA_DEPTH`` of it, from the neighbours) until ``_MIN_RESIDUALS``
    frames show it.
    """
    if len(depths) <= _MIN_RESIDUALS:
        scale = float(np.median(list(depths.values()))) if depths else 0.0
        return True, _DEFAULT_SIGMA_DEPTH * scale
    misses = {True: [], False: []}
    for j, z in depths.items():
        others = {k: v for k, v in depths.items() if k != j}
        for way in misses:
            misses[way].append(_predicted_depth(j, others, way) - z)
    sigma = {way: 1.4826 * float(np.median(np.abs(m))) for way, m in misses.items()}
    way = sigma[True] <= sigma[False]
    return way, max(sigma[way], _MIN_SIGMA_DEPTH * float(np.median(list(depths.values()))))


def neighbours(i: int, rotations: dict) -> tuple:
    """The nearest labelled frames before and after frame ``i`` (None where there is none)."""
    before = [j for j in rotations if j < i]
    after = [j for j in rotations if j > i]
    return (max(before) if before else None, min(after) if after else None)


def _predicted_rotation(i: int, nb: tuple, rotations: dict, step: np.ndarray | None):
    """``(R, nearest labelled frame, motion known)``: interpolated between both sides, else moved on by ``step``.

    Between both sides the turn from one to the other is taken the way ``step`` goes (:func:`_lifted`): a
    turn of more than half a circle across a gap (e.g. three 90 deg steps) is otherwise taken the short way
    back, and the frames between are predicted turned the wrong way. A frame a fraction ``s`` of the way is
    turned by ``s`` of the rest, then by ``s`` of the whole turns (about the step's axis): at ``s = 1`` the
    whole turns vanish and the prediction is the far side's rotation.
    """
    from scipy.spatial.transform import Rotation

    a, b = nb
    near = a if b is None or (a is not None and i - a <= b - i) else b
    if a is not None and b is not None:
        turn = Rotation.from_matrix(rotations[b] @ rotations[a].T).as_rotvec()
        whole, rest = _lifted(turn, step * (b - a)) if step is not None else (np.zeros(3), turn)
        s = (i - a) / (b - a)
        R = Rotation.from_rotvec(rest * s).as_matrix() @ rotations[a]
        return (Rotation.from_rotvec(whole * s).as_matrix() @ R if whole.any() else R), near, True
    if step is None:
        return rotations[near], near, False
    return Rotation.from_rotvec(step * (i - near)).as_matrix() @ rotations[near], near, True


def _unwrapped(turn: np.ndarray, guess: np.ndarray) -> np.ndarray:
    """The rotation vector of the same rotation as ``turn`` (angle in [0, pi]) nearest ``guess``: whole turns added.

    A rotation by ``theta`` about ``u`` is also one by ``theta + 2 pi k``; over several frames of a large step
    the turn made is the one the step predicts, which the rotation alone cannot tell.
    """
    theta = float(np.linalg.norm(turn))
    norm = float(np.linalg.norm(guess))
    if norm == 0.0:
        return turn
    u = turn / theta if theta > 1e-12 else guess / norm
    k = np.rint((float(guess @ u) - theta) / (2 * np.pi))
    return u * (theta + 2 * np.pi * k)


def _lifted(turn: np.ndarray, guess: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(whole, rest)``: ``turn`` taken the way ``guess`` goes, as whole turns about ``guess``'s axis and the rest.

    ``whole`` is the whole turns of ``guess`` (rotation vector of angle ``2 pi n``, n the nearest integer to
    ``|guess| / 2 pi``; zero when n is 0), ``rest`` the rotation vector of ``turn`` nearest ``guess - whole``
    (:func:`_unwrapped`). Across a gap whose turn is near whole turns, ``turn`` is near the identity and its
    axis is noise: the whole turns are then taken about the step's axis, not about that of ``turn``. Without
    whole turns this is :func:`_unwrapped` itself.
    """
    norm = float(np.linalg.norm(guess))
    n = np.rint(norm / (2 * np.pi))
    if n == 0:
        return np.zeros(3), _unwrapped(turn, guess)
    whole = guess * (2 * np.pi * n / norm)
    return whole, _unwrapped(turn, guess - whole)


def _turns(rotations: dict):
    """``turn(j, k)``: the rotation from frame ``j`` to frame ``k`` of ``rotations`` (rotation vector, camera frame).

    Each pair converted once: the leave-one-out predictions of :func:`_prediction_sigmas` take the mean
    step of overlapping windows of frames, and scipy's conversion costs ~0.1 ms a call.
    """
    from scipy.spatial.transform import Rotation

    memo = {}

    def turn(j: int, k: int) -> np.ndarray:
        if (j, k) not in memo:
            memo[(j, k)] = Rotation.from_matrix(rotations[k] @ rotations[j].T).as_rotvec()
        return memo[(j, k)]

    return turn


def _mean_step(rotations: dict, turn=None, guess: np.ndarray | None = None) -> np.ndarray | None:
    """The median rotation per frame (rotation vector, camera frame) between labelled frames a few frames apart.

    ``turn``: :func:`_turns` of ``rotations`` or of a set holding them (default: made here). The turn between
    frames more than one apart is taken the way ``guess`` (a step) goes, by default the median step between
    consecutive frames (:func:`_lifted`): three 90 deg steps make a turn of 270 deg, not one of -90 deg, and
    three 120 deg steps a whole turn about the step's axis, not about the noise of a near-identity rotation.
    """
    turn = turn or _turns(rotations)
    frames = sorted(rotations)
    pairs = [(j, k) for j, k in zip(frames, frames[1:]) if k - j <= _MAX_MOTION_GAP]
    if guess is None:
        consecutive = [turn(j, k) for j, k in pairs if k - j == 1]
        guess = np.median(consecutive, axis=0) if consecutive else None
    lifted = [turn(j, k) if guess is None else np.add(*_lifted(turn(j, k), guess * (k - j))) for j, k in pairs]
    steps = [t / (k - j) for t, (j, k) in zip(lifted, pairs)]
    return np.median(steps, axis=0) if steps else None


def _prediction_sigmas(rotations: dict, axis: np.ndarray, both_sides: bool, turn=None) -> tuple[float, float]:
    """1-sigma errors (rad) of the prediction about ``axis`` and across it, measured on the labelled frames.

    Each labelled frame with labelled frames near it is predicted from them as the prediction will be
    made: between both sides, or from one side (each side it has: a frame before the sequence's first
    labelled one is predicted from after it); the robust standard deviations of the misses about the axis
    (1.4826 x the median absolute turn) and across it (per component: the median tilt / 1.1774, the
    median of a 2D normal's length in its sigmas), floored at ``_MIN_SIGMA_DEG``. ``_DEFAULT_SIGMA_DEG``
    until ``_MIN_RESIDUALS`` predictions show them. ``turn``: :func:`_turns` of ``rotations`` (default: made
    here). The turns across gaps go the way of the step of all ``rotations`` (:func:`_mean_step`).
    """
    from scipy.spatial.transform import Rotation

    turn = turn or _turns(rotations)
    guess = _mean_step(rotations, turn)
    misses = []
    for j in rotations:
        others = {k: R for k, R in rotations.items() if k != j and abs(k - j) <= _MAX_MOTION_GAP}
        a, b = neighbours(j, others)
        if both_sides:
            ways = [] if a is None or b is None else [(a, b)]
        else:
            ways = [w for w in ((a, None), (None, b)) if w != (None, None)]
        step = _mean_step(others, turn, guess) if ways else None
        for way in ways:
            R, _, known = _predicted_rotation(j, way, others, step)
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
