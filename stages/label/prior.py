"""A 3D phantom labelled from another frame's pose: a global search over the phantom's shift (and turn).

The neighbouring frame's pose fixes the orientation roughly but not the position: every detection-bead
pair votes for the shift of the phantom across the beam that would put the bead on the detection, over
the whole image and a few depths; the peaks of the vote are labelled, and the best labelling is kept only
if no distinct one (a periodic layout one row off) explains the frame about as well. A frame that still
fails is searched over turns about the sequence's turntable axis. A labelling found so is kept only if
no pose the phantom's near-symmetries allow (a cube half turned) explains the frame as well, unless the
beads' sizes or a much nearer prior orientation rule it out: a frame is never labelled by a guess.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from fluorocal.stages.label.cube_frame import CubeFrame, coarse_score, visible
from fluorocal.stages.label.iterate import acceptable, agreement, iterate, rivals, sizes_consistent
from fluorocal.stages.label.symmetry import phantom_symmetries, turn_angle

# from another frame's pose: peaks of the shift vote kept as starts, sought among this many of the strongest bins
_N_PEAKS = 8
_N_PEAK_BINS = 300
# ... starts labelled (best coarse score first) until one is acceptable
_MAX_STARTS = 6
# ... and another start is labelled in full when its screen count reaches this fraction of the labelling's
_SCREEN_RIVAL = 0.85
# the phantom's distance from the source may change by this fraction between neighbouring frames
_MAX_DEPTH_CHANGE = 0.05
# detections voting (evenly thinned) when depths or turns are compared, and turns searched in full
_N_DEPTH_DETECTIONS = 80
_N_TURN_DETECTIONS = 120
_N_TURNS = 4
_N_TURN_CANDIDATES = 12
# symmetric rivals: sizes that fit markers by this many more rule a rival out; else the prior decides, when
# every other is this many times as far from it as the nearest
_SIZE_MARGIN = 2
_PRIOR_MARGIN = 3.0


def label_from_prior(
    frame: CubeFrame, R0: np.ndarray, T0: np.ndarray, axis: np.ndarray | None
) -> tuple[dict | None, str]:
    """Label a frame from a neighbouring frame's pose ``(R0, T0)``; ``(result, "")`` or ``(None, reason)``.

    The neighbouring pose fixes the orientation roughly (a turntable step) but not the position: the
    phantom may have moved by several bead rows across the beam and by a few % of its distance along
    it, and a start one row off converges to a labelling one row off that fits about as well. So the
    position is searched over the whole image (:func:`_shift_starts`), the best peaks are labelled, and
    the best labelling is kept only if no distinct one explains the frame about as well
    (:func:`_best_start`). When that fails and the sequence's turntable ``axis`` (camera frame) is
    known, the search is repeated over turns of the phantom about that axis (:func:`_turn_starts`).
    Last, a phantom that looks alike after a turn (a cube of identical walls) allows the found pose's
    symmetric rivals, which a frame without markers cannot tell from it: the labelling is kept only if
    the beads' sizes or, failing them, the prior's orientation single it out (:func:`resolve_symmetry`).
    """
    rays = _rays(frame, frame.det_xy)
    best, why = _best_start(frame, _shift_starts(frame, R0, T0, rays))
    if best is None and axis is not None:
        best, why = _best_start(frame, _turn_starts(frame, R0, T0, axis))
    if best is None:
        return best, why
    return resolve_symmetry(frame, best, R0)


def _rays(frame: CubeFrame, xy: np.ndarray) -> np.ndarray:
    """``(x, y) / z`` in camera coordinates of the rays through image points ``xy`` (pinhole)."""
    return (xy - frame.iop[:2]) / frame.iop[2]


def _depth_steps(frame: CubeFrame, depth_mm: float) -> np.ndarray:
    """Changes of the phantom's distance from the source (mm) to try: up to ``_MAX_DEPTH_CHANGE`` of it.

    The steps move the detection farthest from the principal point by one assignment gate.
    """
    r_max = float(np.max(np.linalg.norm(frame.det_xy - frame.iop[:2], axis=1), initial=1.0))
    step = frame.params.gate_bead_diameters * frame.diam_ref_px * depth_mm / max(r_max, 1.0)
    n = int(np.ceil(_MAX_DEPTH_CHANGE * depth_mm / step))
    return np.arange(-n, n + 1) * step


def _shift_starts(frame: CubeFrame, R: np.ndarray, T: np.ndarray, rays: np.ndarray, n_keep: int = 0) -> list:
    """Start poses ``[(R, T, votes)]``: the pose moved to where many beads meet detections, best first.

    Each of :func:`_depth_steps` is tried; at each, every pair of a detection and a bead votes for the
    shift across the beam that puts the bead on the detection's ray (:func:`_shift_votes`). The depth
    whose strongest peak gathers the most votes of a thinned set of detections (``_N_DEPTH_DETECTIONS``)
    is kept, and the vote of all detections there gives its peaks (``n_keep``, default
    ``_N_PEAKS``): the peaks of a periodic layout, one period apart, must all be labelled to be told
    apart.
    """
    depth = float(np.median((frame.phantom.xyz_mm - T) @ R[2]))
    thin = (
        rays[np.linspace(0, len(rays) - 1, _N_DEPTH_DETECTIONS).astype(int)]
        if len(rays) > _N_DEPTH_DETECTIONS
        else rays
    )
    steps = _depth_steps(frame, depth)
    best_dz = steps[int(np.argmax([_shift_strength(frame, R, T - dz * R[2], thin) for dz in steps]))]
    return _shift_peaks(frame, R, T - best_dz * R[2], rays, n_keep or _N_PEAKS)


def _shift_votes(
    frame: CubeFrame, R: np.ndarray, T: np.ndarray, rays: np.ndarray, *, bin_gates: float = 0.5, box: int = 3
):
    """The vote for shifts of pose ``(R, T)`` across the beam; None without beads in front of the source.

    Every pair of a detection (``rays``) and a bead votes for the shift (camera x, y at the bead's depth,
    mm) that puts the bead on the detection's ray. Votes are binned at ``bin_gates`` assignment gates.

    Returns
    -------
    hist : (H, W) int64 ndarray
        Votes per bin.
    votes : (H, W) int64 ndarray
        Votes summed over ``box`` x ``box`` bins (starting at the bin, or for an odd box, centred on it).
    lo : (2,) float64 ndarray
        Index of bin ``[0, 0]`` (shift / bin size, floored).
    bin_mm : float
    """
    p_cam = (frame.phantom.xyz_mm - T) @ R.T
    p_cam = p_cam[p_cam[:, 2] > 0]
    if len(p_cam) < 4 or not len(rays):
        return None
    bin_mm = (
        bin_gates * frame.params.gate_bead_diameters * frame.diam_ref_px * float(np.median(p_cam[:, 2])) / frame.iop[2]
    )
    # shape (D, B) each: the shift (in bins) that moves bead b onto detection d's ray, at b's depth
    z = p_cam[:, 2] / bin_mm
    fx = rays[:, 0:1] * z - p_cam[:, 0] / bin_mm
    fy = rays[:, 1:2] * z - p_cam[:, 1] / bin_mm
    lo = np.floor([fx.min(), fy.min()])
    ix, iy = (fx - lo[0]).astype(np.int64), (fy - lo[1]).astype(np.int64)
    shape = (int(ix.max()) + 1, int(iy.max()) + 1)
    ix *= shape[1]
    ix += iy
    hist = np.bincount(ix.ravel(), minlength=shape[0] * shape[1]).reshape(shape)
    padded = np.pad(hist, ((box // 2, box - 1 - box // 2),) * 2)
    # separable box sum
    rows = sum(padded[a : a + shape[0]] for a in range(box))
    votes = sum(rows[:, b : b + shape[1]] for b in range(box))
    return hist, votes, lo, bin_mm


def _shift_strength(frame: CubeFrame, R: np.ndarray, T: np.ndarray, rays: np.ndarray) -> float:
    """Votes of the strongest peak of :func:`_shift_votes` on a coarser grid; 0 without one.

    The grid has bins of a gate and 2 x 2 sums: for comparing depths and turns, 4x faster.
    """
    vote = _shift_votes(frame, R, T, rays, bin_gates=1.0, box=2)
    return 0.0 if vote is None else float(vote[1].max())


def _shift_peaks(frame: CubeFrame, R: np.ndarray, T: np.ndarray, rays: np.ndarray, n_keep: int) -> list:
    """The ``n_keep`` strongest peaks ``[(R, T, votes)]`` of :func:`_shift_votes`, at least 3 bins apart.

    Each is located at the vote-weighted mean of its 3 x 3 bins.
    """
    vote = _shift_votes(frame, R, T, rays)
    if vote is None:
        return []
    hist, votes, lo, bin_mm = vote
    shape = votes.shape
    votes = votes.ravel()
    # greedy non-maximum suppression among the strongest bins
    top = np.argpartition(-votes, min(_N_PEAK_BINS, len(votes) - 1))[:_N_PEAK_BINS]
    top = top[np.argsort(-votes[top], kind="stable")]
    kept: list[tuple[int, int]] = []
    out = []
    for k in top:
        if votes[k] <= 0 or len(kept) == n_keep:
            break
        i, j = divmod(int(k), shape[1])
        if any(abs(i - a) <= 2 and abs(j - b) <= 2 for a, b in kept):
            continue
        kept.append((i, j))
        i0, j0 = max(i - 1, 0), max(j - 1, 0)
        win = hist[i0 : i + 2, j0 : j + 2].astype(np.float64)
        ii, jj = np.meshgrid(np.arange(i0, i0 + win.shape[0]), np.arange(j0, j0 + win.shape[1]), indexing="ij")
        centre = (np.array([(ii * win).sum(), (jj * win).sum()]) / win.sum() + lo + 0.5) * bin_mm
        out.append((R, T - R.T @ np.array([centre[0], centre[1], 0.0]), float(votes[k])))
    return out


def _turn_starts(frame: CubeFrame, R0: np.ndarray, T0: np.ndarray, axis: np.ndarray) -> list:
    """Start poses ``[(R, T, votes)]`` turned about ``axis`` (camera frame) over the full circle.

    The phantom is turned about the axis through its centre, in steps that move the beads farthest
    from the axis by two assignment gates. Each turn is scored by the strongest peak of its shift vote
    on a coarse grid and a thinned set of detections (:func:`_shift_strength`, the prior's depth); the
    ``_N_TURN_CANDIDATES`` best local maxima over the angle are re-scored on the fine grid with all
    detections (:func:`_shift_votes`) at half-step offsets, and the ``_N_TURNS`` best get the full search of
    :func:`_shift_starts`. All their peaks are returned, best first: a phantom that looks alike after
    a turn (a cube after a quarter turn) must show both.
    """
    import cv2

    xyz = frame.phantom.xyz_mm
    centre = xyz.mean(0)
    p_centre = R0 @ (centre - T0)
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    rel = (xyz - centre) @ R0.T
    radius = float(np.max(np.linalg.norm(rel - np.outer(rel @ axis, axis), axis=1)))
    gate_mm = frame.params.gate_bead_diameters * frame.diam_ref_px * p_centre[2] / frame.iop[2]
    n_steps = int(np.clip(np.ceil(np.pi * radius / gate_mm), 8, 360))
    step = 2 * np.pi / n_steps
    rays = _rays(frame, frame.det_xy)

    def turned(angle):
        turn, _ = cv2.Rodrigues(axis * angle)
        R = turn @ R0
        return R, centre - R.T @ p_centre

    def strength(angle):
        vote = _shift_votes(frame, *turned(angle), rays)
        return 0.0 if vote is None else float(vote[1].max())

    thin = (
        rays[np.linspace(0, len(rays) - 1, _N_TURN_DETECTIONS).astype(int)] if len(rays) > _N_TURN_DETECTIONS else rays
    )
    scan = np.array([_shift_strength(frame, *turned(a), thin) for a in np.arange(n_steps) * step])
    local = np.flatnonzero((scan >= np.roll(scan, 1)) & (scan >= np.roll(scan, -1)))
    refined = []
    for k in local[np.argsort(-scan[local], kind="stable")][:_N_TURN_CANDIDATES]:
        angles = (k + np.array([-0.5, 0.0, 0.5])) * step
        scores = [strength(a) for a in angles]
        refined.append((max(scores), angles[int(np.argmax(scores))]))
    refined.sort(key=lambda s: -s[0])
    starts = [s for _, a in refined[:_N_TURNS] for s in _shift_starts(frame, *turned(a), rays)]
    return sorted(starts, key=lambda s: -s[2])


def _best_start(frame: CubeFrame, starts: list) -> tuple[dict | None, str]:
    """Label from the starts, best coarse score first; the best labelling, unless a rival matches it.

    Starts are labelled until one is acceptable. A periodic layout gives a start one period off almost
    the same coarse score, so every other start is then checked: moved as that labelling moved from its
    start, and re-aligned by the median offset of its matches, it is counted with the labelling's model
    (pose, ``c``, correction) and the final gate (:func:`screen`); those that reach
    ``_SCREEN_RIVAL`` of the labelling's own count, with detection sizes that fit the beads (a slip
    that puts markers on ordinary beads is no rival), are labelled in full, and the best labelling is kept
    only if no distinct acceptable one comes within ``_RIVAL_LABELS`` of it.
    """
    if not starts:
        return None, "no shift of the previous frame's pose brings beads onto the detections"
    scores = np.array([coarse_score(frame, R, T) for R, T, _ in starts])
    order = np.argsort(-scores, kind="stable")
    reason = "no shift of the previous frame's pose gives an acceptable labelling"
    best, k_best = None, -1
    for k in order[:_MAX_STARTS]:
        result = iterate(frame, starts[k][0], starts[k][1])
        ok, why = (False, "the labelling diverged") if result is None else acceptable(frame, result)
        if ok:
            best, k_best = result, k
            break
        reason = f"from the previous frame's pose, shifted: {why}"
    if best is None:
        return None, reason
    # the rigid motion that took the start to the labelling's pose, in camera coordinates: p -> A p + b
    R0, T0, _ = starts[k_best]
    A = best["R"] @ R0.T
    b = best["R"] @ (T0 - best["T"])
    own, _ = screen(frame, best, best["R"], best["T"])
    accepted = [best]
    for k in order:
        if k == k_best:
            continue
        R = A @ starts[k][0]
        T = starts[k][1] - R.T @ b
        n, sizes_ok = screen(frame, best, R, T, _SCREEN_RIVAL * own)
        if n < _SCREEN_RIVAL * own or not sizes_ok:
            continue
        result = iterate(frame, *starts[k][:2])
        if result is None or not acceptable(frame, result)[0]:
            continue
        if all(agreement(result, other) < 0.9 for other in accepted):
            accepted.append(result)
    accepted.sort(key=lambda r: -r["n_labelled"])
    best = accepted[0]
    for other in accepted[1:]:
        if rivals(best, other):
            return None, (
                f"pose from the neighbouring frame is ambiguous: two shifts of it explain the frame about equally well "
                f"({best['n_labelled']} vs {other['n_labelled']} labels)"
            )
    return best, ""


def screen(frame: CubeFrame, result: dict, R: np.ndarray, T: np.ndarray, min_count: float = 0.0) -> tuple[int, bool]:
    """Beads that pose ``(R, T)`` puts within the final gate of a detection, under ``result``'s model.

    Returns the count and whether their detections' sizes fit them (:func:`sizes_consistent`; checked
    only for ``min_count`` beads or more, True below).

    The pose is first moved across the image by the median offset of the detections within the
    assignment gate of its predictions (twice), so that a start a little off its peak counts in full.
    """
    p = frame.params
    sub = replace(frame, iop=result["iop"])
    vis, ideal, diam = visible(sub, R, T)
    if not len(vis):
        return 0, True
    pred = result["corr"].distort_points(ideal[vis])
    for _ in range(2):
        d, j = frame.det_tree.query(pred, distance_upper_bound=p.gate_bead_diameters * frame.diam_ref_px)
        hit = np.isfinite(d)
        if hit.sum() < 3:
            return int(hit.sum()), True
        pred = pred + np.median(frame.det_xy[j[hit]] - pred[hit], axis=0)
    d, j = frame.det_tree.query(pred)
    close = d <= p.final_gate_bead_diameters * diam[vis]
    n = int(close.sum())
    return n, n < min_count or sizes_consistent(sub, R, T, vis[close], j[close])


def resolve_symmetry(frame: CubeFrame, best: dict, R_prior: np.ndarray) -> tuple[dict | None, str]:
    """The labelling from a prior pose among those the phantom's near-symmetries allow; ``(None, reason)`` if unsure.

    A frame without markers shows a phantom that looks alike after a symmetry ``g`` (a cube turned by a
    quarter or half turn, :func:`~fluorocal.stages.label.symmetry.phantom_symmetries`) as it shows the
    phantom itself, so the labelling ``best`` found near the prior pose has rivals: ``best``'s pose moved
    by each ``g``. Each rival that screens about as well (:func:`screen`) is labelled in full; those that
    are acceptable and label about as many detections with other ids (:func:`rivals`) are candidates
    with ``best``. Then, in turn:

    1. the sizes: a candidate whose labelled markers fit their detections' sizes by ``_SIZE_MARGIN`` more
       (fits minus misfits, :func:`~fluorocal.stages.label.iterate.size_evidence`) than another's rules
       that other out;
    2. the prior: of the candidates left, the one nearest the prior pose is kept if every other is at
       least ``_PRIOR_MARGIN`` times as far from it (rotation angles). The neighbour's pose is close to
       the frame's when the sequence steps by small turns, and then the found pose is much nearer the
       prior than any symmetric rival; a step comparable with the symmetry's angle leaves both at
       similar distances, and the prior does not say which;
    3. otherwise the frame fails: "pose from the neighbouring frame is ambiguous: ...".

    A rival that the prior rules out is not labelled when no labelled bead of ``best``'s is off its size
    (it could not win on sizes either).
    """
    xyz = frame.phantom.xyz_mm
    centre = xyz.mean(0)
    own, _ = screen(frame, best, best["R"], best["T"])
    found = [(best, None)]
    a_best = turn_angle(best["R"], R_prior)
    clean = best["size_evidence"] is None or best["size_evidence"][1] == 0
    for Rg, t, _ in phantom_symmetries(xyz):
        # the pose that shows the phantom moved by g: x -> Rg (x - centre) + centre + t
        R = best["R"] @ Rg
        T = centre - Rg.T @ (centre + t - best["T"])
        if clean and a_best * _PRIOR_MARGIN <= turn_angle(R, R_prior):
            # the prior rules this rival out, and its sizes could not: no bead of best's is off its size, so
            # the rival, the same detections relabelled, cannot fit more markers by _SIZE_MARGIN
            continue
        n, sizes_ok = screen(frame, best, R, T, _SCREEN_RIVAL * own)
        if n < _SCREEN_RIVAL * own or not sizes_ok:
            continue
        other = iterate(frame, R, T)
        if other is not None and acceptable(frame, other)[0] and rivals(best, other):
            if all(agreement(other, f) < 0.9 for f, _ in found):
                found.append((other, Rg))
    if len(found) == 1:
        return best, ""
    fit = [0 if f["size_evidence"] is None else f["size_evidence"][0] - f["size_evidence"][1] for f, _ in found]
    found = [f for f, s in zip(found, fit) if s > max(fit) - _SIZE_MARGIN]
    angles = np.degrees([turn_angle(f["R"], R_prior) for f, _ in found])
    order = np.argsort(angles)
    if len(found) == 1 or angles[order[0]] * _PRIOR_MARGIN <= angles[order[1]]:
        return found[order[0]][0], ""
    near, far = order[:2]
    g = found[far][1] if found[far][1] is not None else found[near][1]
    return None, (
        f"pose from the neighbouring frame is ambiguous: the phantom looks alike turned by "
        f"{np.degrees(turn_angle(g, np.eye(3))):.0f} deg, and two such poses label the frame about as well "
        f"({found[near][0]['n_labelled']} and {found[far][0]['n_labelled']} labels), "
        f"{angles[near]:.0f} and {angles[far]:.0f} deg from the neighbour's"
    )
