"""The problem builder of the bundle adjustment: indices and whitening, free/fixed parameters, gauge, packing, sparsity.

:func:`build_problem` sorts the observations for the Schur complement (by
system, then kept block), maps every system's free IOP, ROP and AP
parameters to columns of the globals vector (:attr:`Problem.gcol`), and sets
the datum (the inner constraints of the object points at their nominal
coordinates). :func:`split_step` and :func:`apply_step` unpack a step of the
solver into the parameters' local updates (:mod:`stages.adjust.collinearity`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse
from fluorocal.stages.adjust import polynomial
from fluorocal.stages.adjust.collinearity import State, ap_values, whitening
from fluorocal.stages.adjust.selection import nominal_coordinates
from fluorocal.stages.geometry import quat_multiply, quat_normalize, rotvec_to_quat

N_GLOBAL_COLS = 9  # per observation: IOP (3) + ROP rotation (3) + ROP translation (3); the APs follow


@dataclass(frozen=True)
class Problem:
    """Everything about the problem that does not change during a solve.

    Observations are stored sorted by (system, kept block, eliminated block):
    the kept blocks' Gram matrices are products of contiguous runs of the
    Jacobian (no gathered copy per linearisation), and the reference system's
    observations, whose relative orientation is the identity, come first
    (:attr:`n_reference`). The eliminated blocks' sums go through ``e_order``
    (:attr:`es_summer`), in the same order as if the observations were sorted
    by eliminated block.

    Attributes
    ----------
    point_idx, pose_idx, sys_idx : (N,) int64 ndarray
    meas_px : (N, 2) float64 ndarray, px
        Measured coordinates minus the distortion correction (ideal coordinates).
    linv : (N, 3) float64 ndarray
        ``(l11, l21, l22)`` of the lower-triangular ``L^-1`` with ``C = L L^T``.
    n_points, n_poses, n_systems, n_globals : int
    gcol : (S, G_o) int64 ndarray
        Column of each per-observation global parameter in the globals vector, -1 if fixed:
        3 IOP, then 6 ROP with several systems, then 7 APs when estimated.
    datum : (n, 3, 7) float64 ndarray
        Inner-constraint directions (translation, rotation, scale) at the nominal points.
    eliminate : str
        ``"points"`` or ``"poses"``: the block type removed by the Schur complement.
    e_idx, k_idx : (N,) int64 ndarray
        Eliminated and kept block of each observation.
    e_order, es_starts, es_e, es_s : int64 ndarray
        Observation order sorted by (eliminated block, system, kept block), the segment starts of each
        (eliminated block, system) in it, and their block and system.
    ks_starts, ks_k, ks_s : int64 ndarray
        Segment starts of each (system, kept block) and their block and system.
    n_reference : int
        Number of observations of the reference system (system 0), the first ones.
    ap_xy_px : (N, 2) float64 ndarray or None, px
        Measured coordinates (before any correction), where the APs are evaluated; None without APs.
    ap_radius_px : (S,) float64 ndarray or None, px
        Reference radius ``r0`` of each system's AP model; None: no APs.
    """

    point_idx: np.ndarray
    pose_idx: np.ndarray
    sys_idx: np.ndarray
    meas_px: np.ndarray
    linv: np.ndarray
    n_points: int
    n_poses: int
    n_systems: int
    n_globals: int
    gcol: np.ndarray
    datum: np.ndarray
    eliminate: str
    # derived sort structures
    e_idx: np.ndarray
    k_idx: np.ndarray
    e_order: np.ndarray
    es_starts: np.ndarray
    es_e: np.ndarray
    es_s: np.ndarray
    ks_starts: np.ndarray
    ks_k: np.ndarray
    ks_s: np.ndarray
    n_reference: int
    ap_xy_px: np.ndarray | None = None
    ap_radius_px: np.ndarray | None = None

    @property
    def n_obs(self) -> int:
        return len(self.point_idx)

    @cached_property
    def es_summer(self) -> scipy.sparse.csr_matrix:
        """``(n_es, N)`` 0/1 matrix: ``es_summer @ X`` sums ``X (N, k)`` over each (eliminated block, system)."""
        return segment_summer(self.es_starts, self.n_obs, self.e_order)

    @cached_property
    def ks_summer(self) -> scipy.sparse.csr_matrix:
        """``(n_ks, N)`` 0/1 matrix: ``ks_summer @ X`` sums ``X (N, k)`` over each (system, kept block) run."""
        return segment_summer(self.ks_starts, self.n_obs)

    @cached_property
    def ks_by_block(self) -> np.ndarray:
        """The (system, kept block) segments in kept-block order (the systems of a block in turn), for :attr:`ks_k`."""
        return np.argsort(self.ks_k, kind="stable")

    @cached_property
    def coupling_index(self) -> np.ndarray:
        """``(N * be * bk,)`` flat index of each observation's ``be x bk`` coupling block in ``B`` ``(ne, be, r)``.

        In a system each (eliminated, kept) pair is seen at most once; with several
        systems a pair can be seen once in each, and the blocks add up.
        """
        be, bk = self.be, self.bk
        rows = self.e_idx[:, None, None] * be + np.arange(be)[None, :, None]
        return (rows * self.n_kept + self.k_idx[:, None, None] * bk + np.arange(bk)).reshape(-1)

    @property
    def n_ap(self) -> int:
        """Additional parameters per system (0 or 7)."""
        return 0 if self.ap_radius_px is None else polynomial.N_AP

    @property
    def ap_start(self) -> int:
        """First AP column of :attr:`gcol` (after the IOP and, with several systems, the ROP)."""
        return _ap_start(self.n_systems)

    @property
    def be(self) -> int:
        return 3 if self.eliminate == "points" else 6

    @property
    def bk(self) -> int:
        return 6 if self.eliminate == "points" else 3

    @property
    def ne(self) -> int:
        return self.n_points if self.eliminate == "points" else self.n_poses

    @property
    def nk(self) -> int:
        return self.n_poses if self.eliminate == "points" else self.n_points

    @property
    def n_kept(self) -> int:
        """Size of the reduced (kept) system without the 7 datum multipliers."""
        return self.nk * self.bk + self.n_globals

    @property
    def n_free(self) -> int:
        """Number of free parameters (before the 7 datum constraints)."""
        return 3 * self.n_points + 6 * self.n_poses + self.n_globals


def _ap_start(n_systems: int) -> int:
    """First AP column of :attr:`Problem.gcol`."""
    return N_GLOBAL_COLS if n_systems > 1 else 3


def datum_directions(nominal_mm: np.ndarray) -> np.ndarray:
    """Inner-constraint matrix rows ``(n, 3, 7)``: translation, rotation, scale at ``nominal_mm``.

    Columns are scaled to comparable magnitude (rotation and scale by the RMS
    radius) so that the bordered system is well conditioned.
    """
    centred = nominal_mm - nominal_mm.mean(0)
    radius = float(np.sqrt((centred**2).sum(1).mean())) or 1.0
    a = centred / radius
    n = len(a)
    d = np.zeros((n, 3, 7))
    d[:, [0, 1, 2], [0, 1, 2]] = 1.0
    # d(R P)/dω = -[P]x : columns of the rotation part
    x, y, z = a.T
    d[:, 0, 4], d[:, 0, 5] = z, -y
    d[:, 1, 3], d[:, 1, 5] = -z, x
    d[:, 2, 3], d[:, 2, 4] = y, -x
    d[:, :, 6] = a
    return d


def segment_starts(keys: np.ndarray) -> np.ndarray:
    """Start indices of runs of equal values in a sorted 1-D array."""
    if len(keys) == 0:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])


def segment_summer(starts: np.ndarray, n: int, order: np.ndarray | None = None) -> scipy.sparse.csr_matrix:
    """The 0/1 matrix ``(len(starts), n)`` that sums rows ``order[starts[i]:starts[i+1]]`` (default ``order`` identity).

    Its product with an ``(n, k)`` array is a segment sum in one pass, several
    times faster than ``np.add.reduceat`` over many short segments, and with
    ``order`` it needs no gathered copy of the array.
    """
    columns = np.arange(n) if order is None else order
    # 32-bit indices, as scipy keeps them (64-bit ones are checked and converted on every product)
    return scipy.sparse.csr_matrix(
        (np.ones(n), columns.astype(np.int32), np.r_[starts, n].astype(np.int32)), shape=(len(starts), n)
    )


def build_problem(
    point_idx: np.ndarray,
    pose_idx: np.ndarray,
    sys_idx: np.ndarray,
    meas_px: np.ndarray,
    sigma_px: np.ndarray,
    nominal_mm: np.ndarray,
    n_poses: int,
    n_systems: int,
    iop_free: np.ndarray,
    eliminate: str,
    *,
    xy_px: np.ndarray | None = None,
    ap_radius_px: np.ndarray | None = None,
    ap_free: np.ndarray | None = None,
) -> tuple[Problem, np.ndarray]:
    """Sort the observations and set up indices, whitening, parameter columns and the datum.

    ``ap_radius_px`` ``(S,)`` (px) adds every system's 7 APs to the globals,
    evaluated at the measured coordinates ``xy_px`` ``(N, 2)`` (default ``meas_px``);
    those where the mask ``ap_free`` ``(7,)`` is False are held at their state values.

    Returns
    -------
    problem : Problem
    perm : (N,) int64 ndarray
        ``problem`` arrays are the inputs taken at ``perm``.
    """
    n_points = len(nominal_mm)
    if eliminate == "auto":
        eliminate = "points" if 6 * n_poses < 3 * n_points else "poses"
    e_all, k_all = (point_idx, pose_idx) if eliminate == "points" else (pose_idx, point_idx)
    perm = np.lexsort((e_all, k_all, sys_idx))
    sys_idx = sys_idx[perm]
    order = _sort_structures(e_all[perm], k_all[perm], sys_idx)
    n_ap = 0 if ap_radius_px is None else polynomial.N_AP
    gcol, n_globals = _global_columns(n_systems, iop_free, n_ap, ap_free)
    problem = Problem(
        point_idx=point_idx[perm],
        pose_idx=pose_idx[perm],
        sys_idx=sys_idx,
        meas_px=meas_px[perm],
        linv=whitening(sigma_px[perm]),
        n_points=n_points,
        n_poses=n_poses,
        n_systems=n_systems,
        n_globals=n_globals,
        gcol=gcol,
        datum=datum_directions(nominal_mm),
        eliminate=eliminate,
        **order,
        ap_xy_px=None if n_ap == 0 else (meas_px if xy_px is None else xy_px)[perm],
        ap_radius_px=None if n_ap == 0 else np.asarray(ap_radius_px, dtype=np.float64).reshape(n_systems),
    )
    return problem, perm


def _sort_structures(e_idx: np.ndarray, k_idx: np.ndarray, sys_idx: np.ndarray) -> dict:
    """The segment starts and eliminated-block order of :class:`Problem` for observations sorted by (system, kept)."""
    ks_starts = segment_starts(sys_idx * (int(k_idx.max(initial=0)) + 1) + k_idx)
    # within an (eliminated block, system) by kept block, as the observations were ordered before
    e_order = np.lexsort((k_idx, sys_idx, e_idx))
    e_sorted = e_idx[e_order]
    es_starts = segment_starts(e_sorted * (int(sys_idx.max(initial=0)) + 1) + sys_idx[e_order])
    return {
        "e_idx": e_idx,
        "k_idx": k_idx,
        "e_order": e_order,
        "es_starts": es_starts,
        "es_e": e_sorted[es_starts],
        "es_s": sys_idx[e_order][es_starts],
        "ks_starts": ks_starts,
        "ks_k": k_idx[ks_starts],
        "ks_s": sys_idx[ks_starts],
        "n_reference": int(np.count_nonzero(sys_idx == 0)),
    }


def _global_columns(n_systems: int, iop_free: np.ndarray, n_ap: int, ap_free) -> tuple[np.ndarray, int]:
    """:attr:`Problem.gcol` ``(S, G_o)`` (-1 for fixed parameters) and the number of free globals."""
    ap_start = _ap_start(n_systems)
    gcol = -np.ones((n_systems, ap_start + n_ap), dtype=np.int64)
    n_globals = 0
    for s in range(n_systems):
        if iop_free[s]:
            gcol[s, :3] = np.arange(n_globals, n_globals + 3)
            n_globals += 3
        if s > 0:
            gcol[s, 3:N_GLOBAL_COLS] = np.arange(n_globals, n_globals + 6)
            n_globals += 6
        if n_ap:
            free = np.flatnonzero(np.ones(n_ap, bool) if ap_free is None else ap_free)
            gcol[s, ap_start + free] = np.arange(n_globals, n_globals + len(free))
            n_globals += len(free)
    return gcol, n_globals


def start_points(start, ids: np.ndarray, nominal_mm: np.ndarray) -> np.ndarray:
    """Start coordinates (n, 3): ``start`` where given, else nominal, projected onto ``D^T (P - P_nominal) = 0``.

    ``start`` is None or a table of :func:`stages.adjust.selection.nominal_coordinates`'s kinds.
    """
    points = nominal_mm.copy()
    if start is None:
        return points
    s_ids, s_xyz = nominal_coordinates(start)
    order = np.argsort(s_ids)
    pos = np.clip(np.searchsorted(s_ids[order], ids), 0, max(len(s_ids) - 1, 0))
    have = (s_ids[order][pos] == ids) if len(s_ids) else np.zeros(len(ids), bool)
    points[have] = s_xyz[order][pos[have]]
    D = datum_directions(nominal_mm).reshape(-1, 7)
    delta = (points - nominal_mm).ravel()
    delta -= D @ np.linalg.lstsq(D, delta, rcond=None)[0]
    return nominal_mm + delta.reshape(-1, 3)


def split_step(problem: Problem, de: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step as ``(δpoints (n, 3), δposes (m, 6), δglobals (G,))``."""
    nkb = problem.nk * problem.bk
    kept = dy[:nkb].reshape(problem.nk, problem.bk)
    if problem.eliminate == "points":
        return de, kept, dy[nkb:]
    return kept, de, dy[nkb:]


def apply_step(state: State, problem: Problem, d_points, d_poses, d_glob) -> State:
    """The state after a step, with the quaternions updated multiplicatively."""
    iop = state.iop_px.copy()
    rop_q = state.rop_q.copy()
    rop_t = state.rop_source_mm.copy()
    ap = ap_values(state, problem).copy() if problem.n_ap else state.ap_px
    g = np.r_[d_glob, 0.0]  # fixed globals (-1) read the trailing zero
    for s in range(problem.n_systems):
        cols = problem.gcol[s]
        if cols[0] >= 0:
            iop[s] += g[cols[:3]]
        if problem.n_systems > 1 and cols[3] >= 0:
            rop_q[s] = quat_normalize(quat_multiply(rotvec_to_quat(g[cols[3:6]]), rop_q[s]))
            rop_t[s] += g[cols[6:9]]
        if problem.n_ap:
            ap[s] += g[cols[problem.ap_start :]]
    return State(
        points_mm=state.points_mm + d_points,
        q=quat_normalize(quat_multiply(rotvec_to_quat(d_poses[:, :3]), state.q)),
        source_mm=state.source_mm + d_poses[:, 3:],
        iop_px=iop,
        rop_q=rop_q,
        rop_source_mm=rop_t,
        ap_px=ap,
    )
