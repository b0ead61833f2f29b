"""The shift vote: where across the beam a pose must move to put many beads on the frame's detections.

Every pair of a detection and a bead votes for the shift of the phantom across the beam (at the bead's
depth) that puts the bead on the detection's ray. With the orientation about right, the true shift
gathers a vote from nearly every detection, while a wrong one gathers only chance coincidences; a
periodic bead layout adds peaks one period apart, which must all be labelled to be told apart.
"""

from __future__ import annotations

import numpy as np
from fluorocal.stages.label.cube_frame import CubeFrame

# peaks of the shift vote kept as starts, sought among this many of the strongest bins
N_PEAKS = 8
_N_PEAK_BINS = 300
# the phantom's distance from the source may change by this fraction between neighbouring frames
_MAX_DEPTH_CHANGE = 0.05
# detections voting (evenly thinned) when depths are compared
N_DEPTH_DETECTIONS = 80
# poses whose strengths are found together (their beads' coordinates at once; then one pose at a time)
_N_BATCH = 64


def rays_of(frame: CubeFrame, xy: np.ndarray) -> np.ndarray:
    """``(x, y) / z`` in camera coordinates of the rays through image points ``xy`` (pinhole)."""
    return (xy - frame.iop[:2]) / frame.iop[2]


def depth_steps(frame: CubeFrame, depth_mm: float) -> np.ndarray:
    """Changes of the phantom's distance from the source (mm) to try: up to ``_MAX_DEPTH_CHANGE`` of it.

    The steps move the detection farthest from the principal point by one assignment gate.
    """
    r_max = float(np.max(np.linalg.norm(frame.det_xy - frame.iop[:2], axis=1), initial=1.0))
    step = frame.params.gate_bead_diameters * frame.diam_ref_px * depth_mm / max(r_max, 1.0)
    n = int(np.ceil(_MAX_DEPTH_CHANGE * depth_mm / step))
    return np.arange(-n, n + 1) * step


def shift_starts(frame: CubeFrame, R: np.ndarray, T: np.ndarray, rays: np.ndarray, n_keep: int = 0) -> list:
    """Start poses ``[(R, T, votes)]``: the pose moved to where many beads meet detections, best first.

    Each of :func:`depth_steps` is tried; at each, every pair of a detection and a bead votes for the
    shift across the beam that puts the bead on the detection's ray (:func:`shift_votes`). The depth
    whose strongest peak gathers the most votes of a thinned set of detections (``N_DEPTH_DETECTIONS``)
    is kept, and the vote of all detections there gives its peaks (``n_keep``, default
    ``N_PEAKS``): the peaks of a periodic layout, one period apart, must all be labelled to be told
    apart.
    """
    depth = float(np.median((frame.phantom.xyz_mm - T) @ R[2]))
    thin = (
        rays[np.linspace(0, len(rays) - 1, N_DEPTH_DETECTIONS).astype(int)] if len(rays) > N_DEPTH_DETECTIONS else rays
    )
    steps = depth_steps(frame, depth)
    best_dz = steps[
        int(np.argmax(shift_strengths(frame, np.repeat(R[None], len(steps), 0), T - steps[:, None] * R[2], thin)))
    ]
    return shift_peaks(frame, R, T - best_dz * R[2], rays, n_keep or N_PEAKS)


def shift_votes(
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
    z, a, lo, shape, bin_mm = _vote_grids(frame, p_cam[None], rays, bin_gates)
    shape = tuple(int(n) for n in shape[0])
    buf = np.empty((len(rays), len(p_cam)))
    ix, iy = np.empty_like(buf, np.int64), np.empty_like(buf, np.int64)
    _pair_bins(rays, z[0], a[0], lo[0], ix, iy, buf)
    # the histogram with box // 2 empty bins before and box - 1 - box // 2 after each axis (for the box sums)
    before = box // 2
    full = (shape[0] + box - 1, shape[1] + box - 1)
    ix += before
    ix *= full[1]
    ix += iy
    ix += before
    padded = np.bincount(ix.ravel(), minlength=full[0] * full[1]).reshape(full)
    hist = padded[before : before + shape[0], before : before + shape[1]]
    # separable box sum
    rows = padded[: shape[0]].copy()
    for a in range(1, box):
        rows += padded[a : a + shape[0]]
    votes = rows[:, : shape[1]].copy()
    for b in range(1, box):
        votes += rows[:, b : b + shape[1]]
    return hist, votes, lo[0], float(bin_mm[0])


def shift_strength(frame: CubeFrame, R: np.ndarray, T: np.ndarray, rays: np.ndarray) -> float:
    """Votes of the strongest peak of :func:`shift_votes` on a coarser grid; 0 without one.

    The grid has bins of a gate and 2 x 2 sums: for comparing depths and turns, 4x faster.
    """
    return float(shift_strengths(frame, R[None], T[None], rays)[0])


def shift_strengths(frame: CubeFrame, R: np.ndarray, T: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """:func:`shift_strength` of each of the poses ``R`` (K, 3, 3), ``T`` (K, 3): a (K,) float64 ndarray.

    The strength is ``shift_votes(..., bin_gates=1.0, box=2)``'s largest sum, found without its padding:
    the largest 2 x 2 sum is the same wherever the sums start, as long as each window that touches the
    grid lies inside one that is summed.
    """
    out = np.zeros(len(R))
    for i in range(0, len(R), _N_BATCH):
        out[i : i + _N_BATCH] = _strengths(frame, R[i : i + _N_BATCH], T[i : i + _N_BATCH], rays)
    return out


def _strengths(frame: CubeFrame, R: np.ndarray, T: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """:func:`shift_strengths` of a batch of poses."""
    # shape (K, B, 3): the beads in each pose's camera frame
    p_cam = (frame.phantom.xyz_mm - T[:, None, :]) @ np.swapaxes(R, 1, 2)
    out = np.zeros(len(p_cam))
    in_front = p_cam[:, :, 2] > 0
    every = in_front.all(1)
    # the poses with beads behind the source: those in front vote (a pose's own number of beads)
    groups = [(np.flatnonzero(every), p_cam[every])]
    groups += [(np.array([k]), p_cam[k][in_front[k]][None]) for k in np.flatnonzero(~every)]
    for ks, p in groups:
        if p.shape[1] < 4 or not len(rays) or not len(ks):
            continue
        z, a, lo, shape, _ = _vote_grids(frame, p, rays, 1.0)
        # one empty bin after each axis (the 2 x 2 sums starting at every bin); small grids count in int32
        n_bins = (shape[:, 0] + 1) * (shape[:, 1] + 1)
        buf = np.empty((len(rays), p.shape[1]))
        dtype = np.int32 if n_bins.max() < 2**31 else np.int64
        ix, iy = np.empty_like(buf, dtype), np.empty_like(buf, dtype)
        for i, k in enumerate(ks):
            _pair_bins(rays, z[i], a[i], lo[i], ix, iy, buf)
            width = int(shape[i, 1]) + 1
            ix *= width
            ix += iy
            hist = np.bincount(ix.ravel(), minlength=int(n_bins[i]))
            # the sums over 2 rows, then 2 columns, of the flattened histogram: a sum that wraps from the empty
            # last column to the next row's first is part of one that does not (it cannot be the largest)
            rows = hist[:-width] + hist[width:]
            out[k] = (rows[:-1] + rows[1:]).max()
    return out


def _vote_grids(frame: CubeFrame, p_cam: np.ndarray, rays: np.ndarray, bin_gates: float) -> tuple:
    """The bins of the votes (:func:`shift_votes`) of K poses whose beads ``p_cam`` (K, B, 3) are in front.

    Returns
    -------
    z : (K, B) float64 ndarray
        The beads' depths, in bins.
    a : (K, 2, B) float64 ndarray
        The beads' x and y, in bins.
    lo : (K, 2) float64 ndarray
        Index of bin ``[0, 0]`` (shift / bin size, floored).
    shape : (K, 2) int64 ndarray
        Bins along x and y that hold a vote.
    bin_mm : (K,) float64 ndarray
    """
    n_beads = p_cam.shape[1]
    half = n_beads // 2
    z_mid = np.partition(p_cam[:, :, 2], (half - 1, half) if n_beads % 2 == 0 else half, axis=1)
    # the median depth (np.median's value, without its overhead: this runs for every pose searched)
    median = 0.5 * (z_mid[:, half - 1] + z_mid[:, half]) if n_beads % 2 == 0 else z_mid[:, half]
    bin_mm = bin_gates * frame.params.gate_bead_diameters * frame.diam_ref_px * median / frame.iop[2]
    z = p_cam[:, :, 2] / bin_mm[:, None]
    a = np.ascontiguousarray(np.swapaxes(p_cam[:, :, :2], 1, 2)) / bin_mm[:, None, None]
    # for each bead the shift is monotonic in the ray (rounding is too, and z > 0): its extremes over the
    # detections are those at the rays' extremes, shape (K, 2, 2, B): found without a pass over every pair
    ends = np.stack([rays.min(0), rays.max(0)])[None, :, :, None] * z[:, None, None, :] - a[:, None]
    lo = np.floor(ends.min(axis=(1, 3)))
    shape = (ends.max(axis=(1, 3)) - lo).astype(np.int64) + 1
    return z, a, lo, shape, bin_mm


def _pair_bins(rays: np.ndarray, z: np.ndarray, a: np.ndarray, lo: np.ndarray, ix, iy, buf) -> None:
    """Write the bins of every pair's vote in one pose (:func:`_vote_grids`) to ``ix`` and ``iy``.

    ``ix``, ``iy`` : (D, B) integer ndarrays; ``buf`` : (D, B) float64 ndarray, overwritten.
    """
    for c, out in ((0, ix), (1, iy)):
        # shape (D, B): the shift (bins) that moves bead b onto detection d's ray, at b's depth
        np.multiply(rays[:, c : c + 1], z, out=buf)
        buf -= a[c]
        buf -= lo[c]
        # truncated: floored, as buf >= 0
        np.copyto(out, buf, casting="unsafe")


def shift_peaks(frame: CubeFrame, R: np.ndarray, T: np.ndarray, rays: np.ndarray, n_keep: int) -> list:
    """The ``n_keep`` strongest peaks ``[(R, T, votes)]`` of :func:`shift_votes`, at least 3 bins apart.

    Each is located at the vote-weighted mean of its 3 x 3 bins.
    """
    vote = shift_votes(frame, R, T, rays)
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
