"""A cube labelling against its rivals: the same frame explained by the phantom slipped by a period, or turned.

A bead phantom is periodic: moved across the beam by a bead row or column (a *slip*), or turned a little
about a wall seen face-on (a *hinge*: the far wall moves by a column while the near one barely changes),
the phantom puts most of its beads on detections again, and a labelling found from a rough pose may be
such a rival. The frame tells them apart only at the phantom's ends (a row of detections left unexplained
on one side, a row of beads predicted where nothing was detected on the other), in the overlap of near
and far walls, and through the markers' sizes: :func:`evidence` counts all of these. So every labelling
is weighed against its slips (found by the shift vote at the labelling's own, accurate, orientation), the
poses the phantom's near-symmetries allow, and the other starts of the search that found it; a rival is
screened with the labelling's own model (its principal distance and polynomial correction) and the pose
polished on it (:func:`polish`), and labelled in full only if it comes close. The labelling stands only
if it is clearly the best, or, between symmetric poses, much the nearest a prior orientation.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from fluorocal.stages.label.assign import ambiguous, gate_bound
from fluorocal.stages.label.cube_frame import CubeFrame, inside_hull, visible, with_camera, within_gates
from fluorocal.stages.label.iterate import (
    acceptable,
    agreement,
    iterate,
    size_evidence,
    solve_pose,
)
from fluorocal.stages.label.motion import OrientationPrior
from fluorocal.stages.label.symmetry import phantom_symmetries, turn_angle
from fluorocal.stages.label.votes import N_PEAKS, shift_peaks

# a marker put on an ordinary bead's detection (or the reverse) weighs as much as this many beads
_SIZE_WEIGHT = 3.0
# a rival whose evidence comes within this many beads of the best's leaves the frame ambiguous ...
_EVIDENCE_MARGIN = 6.0
# ... unless the prior orientation is nearer one of them, by this factor (in the prior's standard deviations)
_PRIOR_MARGIN = 3.0
# ... and no labelling this many margins short of that one's evidence lies that much nearer still
_NEAR_MARGINS = 2.0
# a rival pose is polished when its screened evidence, and labelled in full when its polished evidence,
# comes within this many margins of the best's
_SCREEN_MARGINS = 4.0
_POLISH_MARGINS = 2.0
# slips: peaks of the shift vote with this fraction of the strongest one's votes
_SLIP_VOTES = 0.3
# pose refinements of a polish
_POLISH_ROUNDS = 3
# labellings whose rivals are sought: every one found and this many rivals, one per orientation (within
# _BASIN_DEG), when their evidence is within this many margins of the best's (a slip of the truth that
# misplaces markers scores several margins below it)
_MAX_EXPANSIONS = 4
_EXPAND_MARGINS = 8.0
_BASIN_DEG = 1.0
# a labelling whose evidence falls short of the usable detections by at most this fraction explains most of
# the frame (a right one misses dropouts and spurious blobs: 1-9 % of them), not counting as many again of its
# missing beads that nearly touch another (explains_most)
_MOST_DEFICIT = 0.1
# beads whose projections lie within this many times their mean diameter may merge into one blob, or into a shape
# the detector refuses (those within LabelParams.ambiguity_bead_diameters are ambiguous already); measured on a
# rendered face-on frame: the undetected beads lie 1.02-1.25 diameters from another
_MERGE_BEAD_DIAMETERS = 1.5
# polished poses whose sources lie closer than this (mm; the source is ~1 m away, so 0.5 deg moves it
# ~9 mm) lead to the labelling already found
_SAME_SOURCE_MM = 5.0


def evidence(
    frame: CubeFrame,
    model: dict,
    R: np.ndarray | None = None,
    T: np.ndarray | None = None,
    *,
    bound: float | None = None,
) -> float:
    """How well pose ``(R, T)`` (default: the model's own) explains the frame under ``model``'s camera.

    ``explained - unexplained - missing - _SIZE_WEIGHT x size_off``: *explained* counts the usable
    detections within the final gate of a predicted bead, *unexplained* the others, *missing* the beads
    predicted clear of others and well inside the detections' convex hull without a detection within the
    final gate, and *size_off* the detections whose size misfits their bead's (markers on ordinary beads).
    A right labelling misses only the detector's dropouts and leaves only spurious blobs unexplained; one
    slipped by a row misses a row at one end and leaves one unexplained at the other.

    Parameters
    ----------
    frame : CubeFrame
    model : dict
        A labelling of :func:`~fluorocal.stages.label.iterate.iterate`: its ``iop`` and ``corr`` predict the
        beads, its ``R``, ``T`` are the default pose.
    bound : float, optional
        Only whether the evidence exceeds ``bound`` matters: when ``explained - unexplained`` (an upper
        bound of the evidence) does not, that is returned, without the costlier missing beads and sizes.
    """
    p = frame.params
    R = model["R"] if R is None else R
    T = model["T"] if T is None else T
    sub = replace(frame, iop=model["iop"])
    vis, pred, app = _predicted(sub, model, R, T)
    if len(vis) < 2:
        return -float(len(frame.det_xy))
    gate = p.final_gate_bead_diameters * app
    from scipy.spatial import cKDTree

    tree = cKDTree(pred)
    explained = within_gates(tree, frame.det_xy, gate)
    if bound is not None and 2 * explained.sum() - len(explained) <= bound:
        return float(2 * explained.sum() - len(explained))
    clear = ~ambiguous(pred, app, p.ambiguity_bead_diameters, tree)
    # nothing beyond the widest gate is found: the query stops there (j of a point not found is not used)
    d_pred, j = frame.det_tree.query(pred, distance_upper_bound=gate_bound(gate))
    found = d_pred <= gate
    missing = int(np.sum(_missing(frame, pred, app, clear, found)))
    pairs = clear & found
    sizes = size_evidence(sub, R, T, vis[pairs], j[pairs])
    off = 0 if sizes is None else sizes[1]
    return float(2 * explained.sum() - len(explained) - missing - _SIZE_WEIGHT * off)


def stands_alone(frame: CubeFrame, model: dict, prior: OrientationPrior) -> bool:
    """True if no labelling found after ``model`` could displace it in :func:`settle`.

    :func:`evidence` is at most the number of usable detections (each explained, no bead missing, no
    size misfit), and ``model``'s comes within ``_EVIDENCE_MARGIN`` of that: another labelling could at
    most tie with it, never beat it; and it lies within ``_PRIOR_MARGIN`` standard deviations of the
    ``prior`` orientation, so that no tie could be ``_PRIOR_MARGIN`` times nearer. The detector's
    dropouts, a spurious blob and merged blobs keep the right labelling a few beads below the bound.
    """
    top = model_evidence(frame, model) > len(frame.det_xy) - _EVIDENCE_MARGIN
    return top and prior.distance(model["R"]) < _PRIOR_MARGIN


def _predicted(frame: CubeFrame, model: dict, R: np.ndarray, T: np.ndarray):
    """The beads visible at pose ``(R, T)`` under ``model``'s camera (``frame`` with its ``iop``).

    Returns their indices, predicted centres ``(V, 2)`` px and pinhole diameters ``(V,)`` px (the correction's
    local magnification changes them by a few % only).
    """
    vis, ideal, diam = visible(frame, R, T)
    return vis, model["corr"].distort_points(ideal[vis]), diam[vis]


def _missing(frame: CubeFrame, pred: np.ndarray, app: np.ndarray, clear: np.ndarray, found: np.ndarray) -> np.ndarray:
    """The beads :func:`evidence` counts missing: predicted ``clear`` of others, not ``found``, amid the detections."""
    return clear & ~found & inside_hull(frame, pred, app)


def _merged_missing(frame: CubeFrame, model: dict) -> int:
    """How many beads :func:`evidence` counts missing under ``model`` lie within ``_MERGE_BEAD_DIAMETERS`` of others."""
    p = frame.params
    vis, pred, app = _predicted(replace(frame, iop=model["iop"]), model, model["R"], model["T"])
    if len(vis) < 2:
        return 0
    found = frame.det_tree.query(pred)[0] <= p.final_gate_bead_diameters * app
    missing = _missing(frame, pred, app, ~ambiguous(pred, app, p.ambiguity_bead_diameters), found)
    return int(np.sum(missing & ambiguous(pred, app, _MERGE_BEAD_DIAMETERS)))


def explains_most(frame: CubeFrame, model: dict) -> bool:
    """True if ``model``'s evidence, less its missing beads that nearly touch another, comes near the most possible.

    That is, within ``_MOST_DEFICIT`` of the usable detections. A labelling found from a wrong start may still
    pass :func:`~fluorocal.stages.label.iterate.acceptable` with its polynomial correction bent to fit (its
    depth and camera then wrong); one that explains the frame this well has the phantom's magnification, hence
    its depth, right. Up to ``_MOST_DEFICIT`` of the detections, the missing beads that nearly touch another
    (:func:`_merged_missing`) are not held against it: near a face-on view the phantom's near and far walls'
    beads pair up so, and the detector sees each pair as one blob or none, whatever the labelling. On a rendered
    face-on frame, all 35 beads the right labelling leaves undetected are such; a labelling started 6 deg off
    that passes ``acceptable`` falls short by 212, a slip by a row by 65.
    """
    n = len(frame.det_xy)
    forgiven = min(_merged_missing(frame, model), _MOST_DEFICIT * n)
    return n - model_evidence(frame, model) - forgiven <= _MOST_DEFICIT * n


def settle(
    frame: CubeFrame, found: list, prior: OrientationPrior | None = None, within: float | None = None
) -> tuple[dict | None, str]:
    """The labelling that the frame singles out among ``found`` and their rivals; ``(None, reason)`` if none.

    Each labelling found (from a marker pose or a search's start) brings its rivals: its slips and its
    symmetric poses (:func:`_close_rivals`, screened with that labelling's own model); a rival that comes
    close is labelled in full and brings its own. The acceptable labelling of the highest
    :func:`evidence` wins when every other scores at least ``_EVIDENCE_MARGIN`` less. Otherwise, with a
    prior orientation (a neighbouring frame's, predicted), the one nearest it wins among the close ones
    if each other is at least ``_PRIOR_MARGIN`` times as far from it in the prior's standard deviations,
    a distance of one counting as one (a symmetric rival is turned by a quarter or half turn, a hinge by a
    few degrees about the turntable axis, which a regular step predicts well; a slip has the same
    orientation, and the prior cannot tell it), and no labelling within ``_NEAR_MARGINS`` margins of its
    evidence lies that many times nearer still (two hinges of a truth the search missed); else the frame
    fails. With ``within``, the winner must lie within that many of the prior's standard deviations (the
    region searched): a pose far from the neighbours' that explains the frame better is not taken on the
    frame's word.
    """

    def in_region(c):
        return within is None or prior.distance(c["R"]) <= within

    # best first: the first of an orientation is expanded, the others there are its slips
    scored = sorted(((model_evidence(frame, f), i) for i, f in enumerate(found)), key=lambda e: -e[0])
    candidates = [found[i] for _, i in scored]
    scores = [sc for sc, _ in scored]
    inside = [in_region(c) for c in candidates]
    expanded: list = []
    k = 0
    while k < len(candidates) and len(expanded) < len(found) + _MAX_EXPANSIONS:
        level = max((sc for sc, i in zip(scores, inside) if i), default=max(scores))
        # one labelling per orientation (the best there: its slips are the others'), a fair way below the best
        if scores[k] > level - _EXPAND_MARGINS * _EVIDENCE_MARGIN and not any(
            turn_angle(candidates[k]["R"], e["R"]) < np.radians(_BASIN_DEG) for e in expanded
        ):
            expanded.append(candidates[k])
            for result in _close_rivals(frame, candidates[k], level, candidates):
                if all(agreement(result, c) < 0.9 for c in candidates):
                    candidates.append(result)
                    scores.append(model_evidence(frame, result))
                    inside.append(in_region(result))
        k += 1
    # only fully acceptable labellings compete; the others only brought rivals
    eligible = [k for k, c in enumerate(candidates) if c.get("eligible", True)]
    if not eligible:
        return None, "no labelling of the frame is acceptable (markers misplaced in every one)"
    winner, why = _choose(frame, [candidates[k] for k in eligible], np.array([scores[k] for k in eligible]), prior)
    if winner is not None and not in_region(winner):
        return None, (
            f"the labelling that explains the frame best lies {prior.distance(winner['R']):.0f} standard deviations "
            f"from the orientation predicted by its neighbours (searched within {within:.0f})"
        )
    return winner, why


def _choose(frame: CubeFrame, candidates: list, scores: np.ndarray, prior) -> tuple[dict | None, str]:
    """The candidate of clearly the highest evidence, else the one much the nearest the prior; else none."""
    order = np.argsort(-scores, kind="stable")
    top = order[0]
    close = [k for k in order[1:] if scores[k] > scores[top] - _EVIDENCE_MARGIN]
    if not close:
        return candidates[top], ""
    contenders = [top, *close]
    if prior is not None:
        dist = np.array([prior.distance(c["R"]) for c in candidates])
        near = sorted(contenders, key=lambda k: dist[k])
        w = near[0]
        # a labelling only a little short of the winner's evidence that the prior would pick instead: the search
        # missed the labelling between them (a hinge of the truth each), and the prior cannot decide
        nearer = [k for k in order if scores[k] > scores[w] - _NEAR_MARGINS * _EVIDENCE_MARGIN and k != w]
        nearer = [k for k in nearer if _PRIOR_MARGIN * max(dist[k], 1.0) <= dist[w]]
        if dist[near[1]] >= _PRIOR_MARGIN * max(dist[w], 1.0):
            if not nearer:
                return candidates[w], ""
            top, close = w, nearer
    a, b = candidates[top], candidates[close[0]]
    return None, (
        f"ambiguous: two poses explain the frame about equally well ({a['n_labelled']} and {b['n_labelled']} labels, "
        f"evidence {scores[top]:.0f} and {scores[close[0]]:.0f}), "
        f"{np.degrees(turn_angle(a['R'], b['R'])):.0f} deg and {np.linalg.norm(a['T'] - b['T']):.0f} mm apart"
    )


def _close_rivals(frame: CubeFrame, model: dict, level: float, known: list) -> list:
    """Labellings from ``model``'s rival poses whose evidence under its camera comes close to ``level``.

    The rival poses are ``model``'s slips, its symmetric poses, and their slips when they themselves come
    close. Each is screened as it is, polished if it comes within ``_SCREEN_MARGINS`` margins of
    ``level``, and labelled in full if it then comes within ``_POLISH_MARGINS`` and is not the pose of a
    ``known`` labelling; the acceptable labellings are returned.
    """
    screen = level - _SCREEN_MARGINS * _EVIDENCE_MARGIN
    symmetric = _symmetric_poses(frame, model)
    near_sym = [(R, T) for R, T in symmetric if model_evidence(frame, model, R, T, bound=screen) > screen]
    rivals = list(near_sym)
    for R, T in [(model["R"], model["T"]), *near_sym]:
        rivals += _memo(model, "slips", (R, T), _slip_poses, frame, model, R, T)
    out: list = []
    close = level - _POLISH_MARGINS * _EVIDENCE_MARGIN
    for R, T in rivals:
        if model_evidence(frame, model, R, T, bound=screen) <= screen:
            continue
        R, T = _memo(model, "polish", (R, T), polish, frame, model, R, T)
        if model_evidence(frame, model, R, T, bound=close) <= close:
            continue
        if any(_same_pose(R, T, c["R"], c["T"]) for c in [*known, *out]):
            continue
        # the pose was found with the model's principal distance: the labelling starts from it too
        result = _memo(model, "labelling", (R, T), _labelling, frame, model["iop"], R, T)
        if result is not None:
            out.append(result)
    return out


def _labelling(frame: CubeFrame, iop: np.ndarray, R: np.ndarray, T: np.ndarray) -> dict | None:
    """The acceptable labelling from pose ``(R, T)`` seen with ``iop``, or None."""
    result = iterate(with_camera(frame, iop), R, T)
    return result if result is not None and acceptable(frame, result)[0] else None


def _memo(model: dict, kind: str, pose: tuple, compute, *args):
    """``compute(*args)`` for pose ``(R, T)`` once per labelling ``model`` (a frame is settled several times)."""
    cache = model.setdefault("memo", {})
    key = (kind, pose[0].tobytes(), pose[1].tobytes())
    if key not in cache:
        cache[key] = compute(*args)
    return cache[key]


def model_evidence(
    frame: CubeFrame, model: dict, R: np.ndarray | None = None, T: np.ndarray | None = None, *, bound=None
) -> float:
    """:func:`evidence`, computed once per pose for labelling ``model`` (an upper bound kept while it suffices)."""
    cache = model.setdefault("memo", {})
    key = ("evidence", *(model["R"] if R is None else R, model["T"] if T is None else T))
    key = (key[0], key[1].tobytes(), key[2].tobytes())
    value, exact = cache.get(key, (None, False))
    if value is not None and (exact or (bound is not None and value <= bound)):
        return value
    value = evidence(frame, model, R, T, bound=bound)
    # below the bound it may be the upper bound only (see evidence)
    cache[key] = (value, bound is None or value > bound)
    return value


def _same_pose(R1: np.ndarray, T1: np.ndarray, R2: np.ndarray, T2: np.ndarray) -> bool:
    """Poses within half a degree and a few millimetres (at the source) of each other label alike."""
    return turn_angle(R1, R2) < np.radians(0.5) and float(np.linalg.norm(T1 - T2)) < _SAME_SOURCE_MM


def polish(frame: CubeFrame, model: dict, R: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose ``(R, T)`` refined on the detections nearest its beads under ``model``'s camera (a few rounds)."""
    p = frame.params
    corr = model["corr"]
    sub = with_camera(frame, model["iop"])
    xyz = frame.phantom.xyz_mm
    for _ in range(_POLISH_ROUNDS):
        vis, ideal, diam = visible(sub, R, T)
        if len(vis) < 6:
            break
        pred = corr.distort_points(ideal[vis])
        d, j = frame.det_tree.query(pred, distance_upper_bound=p.gate_bead_diameters * frame.diam_ref_px)
        hit = np.isfinite(d)
        if hit.sum() < 6:
            break
        img = corr.undistort_points(frame.det_xy[j[hit]], ideal[vis[hit]])
        R, T = solve_pose(sub, xyz[vis[hit]], img, R, T)
    return R, T


def _symmetric_poses(frame: CubeFrame, result: dict) -> list:
    """The poses ``[(R, T)]`` that show the phantom moved by each of its near-symmetries as ``result`` shows it."""
    xyz = frame.phantom.xyz_mm
    centre = xyz.mean(0)
    out = []
    for Rg, t, _ in phantom_symmetries(xyz):
        # the pose that shows the phantom moved by g: x -> Rg (x - centre) + centre + t
        out.append((result["R"] @ Rg, centre - Rg.T @ (centre + t - result["T"])))
    return out


def _slip_poses(frame: CubeFrame, model: dict, R: np.ndarray, T: np.ndarray) -> list:
    """Pose ``(R, T)`` moved across the beam to the other strong peaks of its shift vote: ``[(R, T)]``.

    The vote uses ``model``'s camera: its principal distance, and the detections corrected by its
    polynomial, so that its peaks are sharp; peaks with ``_SLIP_VOTES`` of the strongest one's votes are
    kept, except the pose's own (within a gate of no shift).
    """
    iop, corr = model["iop"], model["corr"]
    ideal = frame.det_xy
    for _ in range(2):
        ideal = corr.undistort_points(frame.det_xy, ideal)
    sub = replace(frame, iop=iop)
    peaks = shift_peaks(sub, R, T, (ideal - iop[:2]) / iop[2], N_PEAKS)
    if not peaks:
        return []
    depth = float(np.median((frame.phantom.xyz_mm - T) @ R[2]))
    own_mm = frame.params.gate_bead_diameters * frame.diam_ref_px * depth / iop[2]
    strongest = max(v for _, _, v in peaks)
    return [(Rp, Tp) for Rp, Tp, v in peaks if v >= _SLIP_VOTES * strongest and np.linalg.norm(Tp - T) > own_mm]
