"""A 3D phantom labelled from a predicted pose (a neighbouring frame's): a search over small turns and shifts.

Between the frames of a sequence the phantom turns (a turntable step, its axis wobbling) and moves by
several bead rows. The predicted orientation is taken as roughly right, within a search radius, and the
position not at all: every small rotation of it on a grid (any axis, :func:`_ball_starts`) is scored by the
shift vote (:mod:`.votes`) at a few depths, the best distinct rotations get their vote's peaks as starts,
and several starts are labelled; of the acceptable labellings the one with the most :func:`evidence` is
checked against its rivals (:func:`~fluorocal.stages.label.rivals.settle`). Without an acceptable
labelling near the prediction, turns about the sequence's turntable axis over the full circle are tried
(a large step). A frame is never labelled by a guess: it fails when a rival explains it as well.
"""

from __future__ import annotations

import functools
import itertools

import numpy as np
from fluorocal.stages.label.cube_frame import CubeFrame, coarse_evidence, with_camera
from fluorocal.stages.label.iterate import acceptable, agreement, iterate
from fluorocal.stages.label.motion import OrientationPrior
from fluorocal.stages.label.rivals import evidence, explains_most, polish, settle, stands_alone
from fluorocal.stages.label.symmetry import turn_angle
from fluorocal.stages.label.votes import (
    N_DEPTH_DETECTIONS,
    N_PEAKS,
    rays_of,
    shift_peaks,
    shift_starts,
    shift_strengths,
    shift_votes,
)

# the rotation grid: spacing that moves the beads farthest from the phantom's centre by this many gates ...
_GRID_GATES = 1.6
# ... within these many standard deviations of the prediction in turn (a wider search when the narrower
# finds nothing), and at most this far (deg) about any axis
_SEARCH_SIGMAS = (3.0, 6.0)
_MAX_SEARCH_DEG = 16.0
_MAX_GRID_STEPS = 12
# the phantom's distance from the source: levels this fraction of it apart, covering this many sigmas of
# its prediction (by default this fraction of it)
_DEPTH_SPACING = 0.02
_DEPTH_SIGMAS = 2.5
_DEFAULT_SIGMA_DEPTH = 0.025
# distinct rotations (at least two grid steps apart) whose vote peaks are kept as starts, peaks per rotation
_N_ROTATIONS = 16
# rotations that polish to within this angle (deg) of one another share their slips
_SAME_ORIENTATION_DEG = 0.5
# starts labelled in full (best coarse score first)
_MAX_STARTS = 16
# turns about the turntable axis: detections voting, turns searched in full, candidates re-scored
_N_TURN_DETECTIONS = 120
_N_TURNS = 4
_N_TURN_CANDIDATES = 12


def label_from_prior(
    frame: CubeFrame,
    prior: OrientationPrior,
    p_centre: np.ndarray,
    *,
    turn_search: bool = False,
    also: list = (),
    camera: dict | None = None,
    decide: bool = True,
) -> tuple[dict | None, str]:
    """Label a frame from a predicted orientation ``prior`` and the phantom centre's place ``p_centre``.

    ``p_centre`` (camera frame, mm) is where a neighbouring frame saw the phantom's centre: its depth
    starts the search, its position across the beam does not matter (the shift is searched).

    Returns ``(result, "")`` or ``(None, reason)``. The prediction itself is tried first (its vote's
    best slip, then its other slips), then (with ``turn_search``, if nothing was found) turns about the
    prior's axis; then rotations of the prediction within each of ``_SEARCH_SIGMAS`` of its uncertainty in
    turn are searched with the phantom's position free (:func:`_ball_starts`), at the depth of the first
    labelling found if any (the labellings of a frame share its magnification). After each search the
    labellings found so far are settled against each other and their rivals, the prior deciding between
    those that the frame itself cannot tell apart; a winner must lie in the region searched, and a wider
    region's winner replaces the narrower's (a hinge of the truth near the prediction gives way to the
    truth a few sigmas out); a narrower region's winner that the settling of everything found no longer
    picks (a wider region's labelling ties it, the prior unable to tell them apart either, or beats it) is
    dropped: the frame is then ambiguous. The search ends early once a winner stands alone
    (:func:`~fluorocal.stages.label.rivals.stands_alone`: nothing found later could beat it). With
    ``turn_search`` and no winner, turns about the prior's axis over the full circle close the search
    (:func:`_turn_starts`). Labellings found otherwise (``also``: the frame's markers') compete with them
    on their evidence alone, wherever they lie. ``decide=False``: the prior does not decide between
    labellings the frame cannot tell apart (a prior centred on a suspect pose would favour it).

    ``camera`` (a neighbouring frame's: its ``iop`` and polynomial ``corr``, the system's distortion)
    sharpens the search: the detections vote corrected, and the starts are ranked by their
    :func:`~fluorocal.stages.label.rivals.evidence` under it; without it, by the pinhole's
    :func:`~fluorocal.stages.label.cube_frame.coarse_evidence`.
    """
    view = _Search(frame, camera)
    reason = "no pose near the neighbouring frame's brings beads onto the detections"
    settled = False
    tried: list = []
    found: list = [*also]
    winner = None
    for within, search in _searches(view, prior, p_centre, turn_search, found):
        if within is None and winner is not None:
            break  # the full circle only when nothing near the prediction stands
        starts = [s for s in search() if not any(_near(s, t) for t in tried)]
        tried += starts
        new, why = _label_starts(view, starts)
        # a labelling found again (from a start a little off one tried before) is not its own rival: of the
        # two, the one with more evidence stays (in place: the searches ask whether anything is found yet)
        found[:] = _merged(frame, found, new)
        if found:
            # every region is searched: a labelling found in a narrower one may be a hinge or slip of the
            # truth, which lies a few sigmas out when the axis wobbles; the wider search replaces the narrower's
            # winner only with a labelling that stands against everything found
            best, why = settle(frame, found, prior if decide else None, None if also else within)
            if best is not None:
                winner = best
                if view.depth_mm is None and explains_most(frame, best):
                    # the labellings that explain a frame share its depth (hinges and slips of the truth
                    # alike): the rotations of the wider searches are scored at it alone
                    view.depth_mm = view.depth_of(best)
                if stands_alone(frame, best, prior):
                    # a labelling found later could not beat it by a margin, nor lie much nearer the
                    # prediction: the search is over (one about as good, a few sigmas out, would have left
                    # the frame ambiguous; the early stop takes that risk)
                    break
            else:
                # a labelling found but not singled out says more than the failures of the other starts; a narrower
                # region's winner that the settling of everything found does not pick stands no more
                winner, reason, settled = None, why, True
        elif not settled:
            reason = why or reason
    return (winner, "") if winner is not None else (None, reason)


def _merged(frame: CubeFrame, found: list, new: list) -> list:
    """``found`` with the ``new`` labellings added.

    One that agrees with a found one on 90 % of its labels is that one found again, not its rival: it
    replaces it (in its place) if it has more evidence, else it is dropped.
    """
    out = list(found)
    for f in new:
        same = [i for i, g in enumerate(out) if agreement(f, g) >= 0.9]
        if not same:
            out.append(f)
        elif evidence(frame, f) > max(evidence(frame, out[i]) for i in same):
            # in the place of the first it replaces: the order found decides ties
            out = [f if i == same[0] else g for i, g in enumerate(out) if i == same[0] or i not in same]
    return out


def _searches(view: "_Search", prior: OrientationPrior, p_centre: np.ndarray, turn_search: bool, found: list):
    """The searches of :func:`label_from_prior` in order: ``[(region, starts)]``.

    ``region``: the region searched in the prior's standard deviations (None: the full circle);
    ``starts()`` its start poses. First the cheap ones: the prediction itself, and when nothing is
    ``found`` yet (with ``turn_search``) the turns about the axis; then the rotations
    around the prediction (a wider region that the cap leaves as the narrower one is not searched again);
    with ``turn_search``, the full circle last.
    """
    sizes = [_semi_axes(prior, k) for k in _SEARCH_SIGMAS]
    turns = functools.cache(lambda: _turn_starts(view, prior.R, p_centre, prior.axis))

    def ball(k_sigma):
        return _ball_starts(view, prior, p_centre, k_sigma)

    searches = [(_SEARCH_SIGMAS[0], lambda: ball(0.0))]
    if turn_search:
        searches.append((_SEARCH_SIGMAS[-1], lambda: [] if found else turns()))
    searches += [(k, lambda k=k: ball(k)) for i, k in enumerate(_SEARCH_SIGMAS) if i == 0 or sizes[i] != sizes[i - 1]]
    if turn_search:
        searches.append((None, turns))
    return searches


def _near(a: tuple, b: tuple) -> bool:
    """Starts ``(R, T, votes)`` within a degree and a millimetre of each other (tried already)."""
    return 0.5 * (np.trace(a[0].T @ b[0]) - 1.0) > np.cos(np.radians(1.0)) and np.linalg.norm(a[1] - b[1]) < 1.0


def _label_starts(search: "_Search", starts: list) -> tuple[list, str]:
    """Distinct labellings from the best of ``starts`` (by coarse evidence), and the last failure's reason.

    Those acceptable but for the beads' sizes are kept too (``eligible`` False): a start one slip off
    the truth puts markers on ordinary beads, and the truth is among its slips.
    """
    if not starts:
        return [], ""
    # the starts were found with the search's camera: the labellings start from it too
    frame = search.vote_frame
    scores = np.array([search.score(R, T) for R, T, _ in starts])
    found: list = []
    reason = ""
    for k in np.argsort(-scores, kind="stable")[:_MAX_STARTS]:
        result = iterate(frame, *starts[k][:2])
        ok, why = (False, "the labelling diverged") if result is None else acceptable(frame, result)
        if not ok:
            reason = f"from the neighbouring frame's pose, moved: {why}"
            if result is None or not acceptable(frame, {**result, "sizes_consistent": True})[0]:
                continue
        result["eligible"] = ok
        if all(agreement(result, f) < 0.9 for f in found):
            found.append(result)
    return found, reason


def _ball_starts(search: "_Search", prior: OrientationPrior, p_centre: np.ndarray, k_sigma: float) -> list:
    """Start poses ``[(R, T, votes)]`` from rotations of the prediction within ``k_sigma`` of its uncertainty.

    The rotations (about the phantom's centre) lie on a cubic grid of rotation vectors whose spacing
    moves the beads farthest from the centre by ``_GRID_GATES`` assignment gates, within the ellipsoid of
    ``k_sigma`` times the prior's turn and tilt uncertainties (each at most ``_MAX_SEARCH_DEG``; the
    prediction itself always). Each is scored by the strongest peak of its shift vote
    (:func:`~fluorocal.stages.label.votes.shift_strength`, a thinned set of detections) at the depths the
    prior allows (:func:`_depth_levels`). For each of the ``_N_ROTATIONS`` best rotations at least two grid
    steps apart, the strongest peak of its full vote (:func:`~fluorocal.stages.label.votes.shift_peaks`) is
    polished: whichever slip it is, its orientation is then its basin's, where the vote is sharp and its
    peaks are the slips; the one that explains the frame best (:meth:`_Search.score`) is the basin's start.
    Rotations that polish to one orientation share a start.
    """
    from scipy.spatial.transform import Rotation

    frame, rays = search.vote_frame, search.rays
    xyz = frame.phantom.xyz_mm
    centre = xyz.mean(0)
    R0 = prior.R
    extent = float(np.max(np.linalg.norm(xyz - centre, axis=1)))
    if not p_centre[2] > 0:
        return []
    gate_mm = frame.params.gate_bead_diameters * frame.diam_ref_px * p_centre[2] / frame.iop[2]
    # a phantom large for its beads would need a fine grid: at most _MAX_GRID_STEPS steps out to the cap
    step = max(_GRID_GATES * gate_mm / extent, np.radians(_MAX_SEARCH_DEG) / _MAX_GRID_STEPS)
    a_turn, a_tilt = _semi_axes(prior, k_sigma)
    n = int(np.floor(max(a_turn, a_tilt) / step))
    g = np.arange(-n, n + 1) * step
    # shape (G, 3): the grid's rotation vectors within the ellipsoid
    vecs = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    if n:
        turn = vecs @ prior.axis
        tilt = np.linalg.norm(vecs - np.outer(turn, prior.axis), axis=1)
        vecs = vecs[(turn / a_turn) ** 2 + (tilt / a_tilt) ** 2 <= 1 + 1e-9]
    turns = Rotation.from_rotvec(vecs).as_matrix()
    thin = (
        rays[np.linspace(0, len(rays) - 1, N_DEPTH_DETECTIONS).astype(int)] if len(rays) > N_DEPTH_DETECTIONS else rays
    )
    # the depths the prior allows, or the one a labelling of the frame found
    depths = _depth_levels(prior, p_centre[2]) if search.depth_mm is None else [search.depth_mm - p_centre[2]]

    def pose(k, dz):
        R = turns[k] @ R0
        return R, centre - R.T @ (p_centre + [0.0, 0.0, dz])

    # the grid's points by their steps from the prediction: the regions share them, and their scores
    cells = [tuple(c) for c in np.rint(vecs / step).astype(int).tolist()]
    grid = list(itertools.product(range(len(vecs)), depths))

    def strengths(indices):
        R, T = (np.array(x) for x in zip(*(pose(*grid[i]) for i in indices)))
        return shift_strengths(frame, R, T, thin).tolist()

    # shape (G, L): strength of each rotation at each depth (those not scored yet, in one pass)
    strength = np.array(search.memo_all([("strength", cells[k], dz) for k, dz in grid], strengths))
    strength = strength.reshape(len(vecs), len(depths))
    best = strength.max(1)
    kept: list[int] = []
    for k in np.argsort(-best, kind="stable"):
        if len(kept) == _N_ROTATIONS:
            break
        if all(np.max(np.abs(vecs[k] - vecs[j])) > 1.5 * step for j in kept):
            kept.append(int(k))
    starts: list = []
    for k in kept:
        dz = depths[int(np.argmax(strength[k]))]
        start = search.memo(("start", cells[k], dz), _basin_start, search, *pose(k, dz))
        if start is None or any(turn_angle(start[0], s[0]) < np.radians(_SAME_ORIENTATION_DEG) for s in starts):
            continue
        starts.append(start)
    return starts


def _basin_start(search: "_Search", R: np.ndarray, T: np.ndarray) -> tuple | None:
    """The start ``(R, T, votes)`` of the basin that pose ``(R, T)``'s vote leads to; None without a peak.

    The strongest peak of its full vote (:func:`~fluorocal.stages.label.votes.shift_peaks`) is polished:
    whichever slip it is, its orientation is then its basin's, where the vote is sharp and its peaks are the
    slips; the one that explains the frame best (:meth:`_Search.score`) is the basin's start.
    """
    frame, rays = search.vote_frame, search.rays
    peaks = shift_peaks(frame, R, T, rays, N_PEAKS)
    if not peaks:
        return None
    R, T = search.polish(*peaks[0][:2])
    slips = [(R, T, peaks[0][2]), *shift_peaks(frame, R, T, rays, N_PEAKS)]
    return max(slips, key=lambda s: search.score(s[0], s[1]))


def _depth_levels(prior: OrientationPrior, depth_mm: float) -> np.ndarray:
    """Moves (mm) of the phantom's centre along the beam scored at each rotation: its predicted depth's spread.

    Levels ``_DEPTH_SPACING`` of the depth apart (the vote holds about half of that either way) cover
    ``_DEPTH_SIGMAS`` of the prediction's error (``_DEFAULT_SIGMA_DEPTH`` of the depth when not given).
    """
    sigma = prior.sigma_depth_mm if prior.sigma_depth_mm is not None else _DEFAULT_SIGMA_DEPTH * depth_mm
    spacing = _DEPTH_SPACING * depth_mm
    n = int(np.ceil(max(_DEPTH_SIGMAS * sigma - 0.5 * spacing, 0.0) / spacing))
    return np.arange(-n, n + 1) * spacing


def _semi_axes(prior: OrientationPrior, k_sigma: float) -> tuple[float, float]:
    """Semi-axes (rad) about and across the turntable axis of the region within ``k_sigma`` of the prior."""
    cap = np.radians(_MAX_SEARCH_DEG)
    return min(k_sigma * prior.sigma_turn_rad, cap), min(k_sigma * prior.sigma_tilt_rad, cap)


def _turn_starts(search: "_Search", R0: np.ndarray, p_centre: np.ndarray, axis: np.ndarray) -> list:
    """Start poses ``[(R, T, votes)]`` turned about ``axis`` (camera frame) over the full circle.

    The phantom is turned about the axis through its centre, in steps that move the beads farthest
    from the axis by two assignment gates. Each turn is scored by the strongest peak of its shift vote
    on a coarse grid and a thinned set of detections (the prior's depth); the ``_N_TURN_CANDIDATES`` best
    local maxima over the angle are re-scored on the fine grid with all detections at half-step
    offsets, and the ``_N_TURNS`` best get the full shift search. All their peaks are returned, best first:
    a phantom that looks alike after a turn (a cube after a quarter turn) must show both.
    """
    import cv2

    if not p_centre[2] > 0:
        return []
    frame, rays = search.vote_frame, search.rays
    xyz = frame.phantom.xyz_mm
    centre = xyz.mean(0)
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    rel = (xyz - centre) @ R0.T
    radius = float(np.max(np.linalg.norm(rel - np.outer(rel @ axis, axis), axis=1)))
    gate_mm = frame.params.gate_bead_diameters * frame.diam_ref_px * p_centre[2] / frame.iop[2]
    n_steps = int(np.clip(np.ceil(np.pi * radius / gate_mm), 8, 360))
    step = 2 * np.pi / n_steps

    def turned(angle):
        turn, _ = cv2.Rodrigues(axis * angle)
        R = turn @ R0
        return R, centre - R.T @ p_centre

    def strength(angle):
        vote = shift_votes(frame, *turned(angle), rays)
        return 0.0 if vote is None else float(vote[1].max())

    thin = (
        rays[np.linspace(0, len(rays) - 1, _N_TURN_DETECTIONS).astype(int)] if len(rays) > _N_TURN_DETECTIONS else rays
    )
    R, T = (np.array(x) for x in zip(*(turned(a) for a in np.arange(n_steps) * step)))
    scan = shift_strengths(frame, R, T, thin)
    local = np.flatnonzero((scan >= np.roll(scan, 1)) & (scan >= np.roll(scan, -1)))
    refined = []
    for k in local[np.argsort(-scan[local], kind="stable")][:_N_TURN_CANDIDATES]:
        angles = (k + np.array([-0.5, 0.0, 0.5])) * step
        scores = [strength(a) for a in angles]
        refined.append((max(scores), angles[int(np.argmax(scores))]))
    refined.sort(key=lambda s: -s[0])
    starts = [s for _, a in refined[:_N_TURNS] for s in shift_starts(frame, *turned(a), rays)]
    return sorted(starts, key=lambda s: -s[2])


class _Search:
    """The frame as the search sees it: the camera its votes use, the detections' rays, how starts are ranked.

    With a neighbour's ``camera`` (``iop`` and polynomial ``corr``), the detections are corrected by it
    before they vote and the starts are ranked by their evidence under it (the final gate, the phantom's
    ends); without, the assumed pinhole and its coarse evidence (the assignment gate).
    """

    def __init__(self, frame: CubeFrame, camera: dict | None):
        from fluorocal.stages.label.correction import Correction

        self.frame, self.camera = frame, camera
        scale = 0.5 * float(np.hypot(frame.width, frame.height))
        self.model = camera or {"iop": frame.iop, "corr": Correction(frame.iop[:2].copy(), scale)}
        if camera is None:
            self.vote_frame, ideal = frame, frame.det_xy
        else:
            iop = camera["iop"]
            self.vote_frame = with_camera(frame, iop)
            ideal = frame.det_xy
            for _ in range(2):
                ideal = camera["corr"].undistort_points(frame.det_xy, ideal)
        self.rays = rays_of(self.vote_frame, ideal)
        self._memo: dict = {}
        # the phantom centre's distance from the source (mm, the vote camera) once a labelling has found it
        self.depth_mm: float | None = None

    def depth_of(self, result: dict) -> float:
        """The phantom centre's distance from the source in labelling ``result``, as the vote camera sees it."""
        z = float(result["R"][2] @ (self.frame.phantom.xyz_mm.mean(0) - result["T"]))
        return z * float(self.vote_frame.iop[2]) / float(result["iop"][2])

    def memo(self, key: tuple, compute, *args):
        """``compute(*args)``, once per ``key``: the search regions share the grid points at their centre."""
        if key not in self._memo:
            self._memo[key] = compute(*args)
        return self._memo[key]

    def memo_all(self, keys: list, compute) -> list:
        """The values of ``keys``, those not computed yet by one call ``compute(indices)`` (indices in ``keys``)."""
        missing = [i for i, key in enumerate(keys) if key not in self._memo]
        if missing:
            self._memo.update(zip((keys[i] for i in missing), compute(missing)))
        return [self._memo[key] for key in keys]

    def polish(self, R: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pose ``(R, T)`` refined on the detections nearest its beads (under the camera, or the pinhole)."""
        return polish(self.frame, self.model, R, T)

    def score(self, R: np.ndarray, T: np.ndarray) -> float:
        """How well pose ``(R, T)`` explains the frame (higher is better), once per pose (starts are scored twice)."""
        return self.memo(("score", R.tobytes(), T.tobytes()), self._score, R, T)

    def _score(self, R: np.ndarray, T: np.ndarray) -> float:
        if self.camera is None:
            return float(coarse_evidence(self.frame, R, T))
        return evidence(self.frame, self.camera, R, T)
