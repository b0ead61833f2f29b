"""The orientation of one or more systems linearised at an adjustment: the Jacobian by ``(IOP, poses, points)``.

Shared by the refinement's joint field step (:mod:`.joint`, every system at
once) and the joint uncertainty (:mod:`.uncertainty`, one system). The poses are
the adjustment's: each epoch's reference pose and each further system's ROP; one
system alone is linearised in its own poses. The systems share the beads.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.geometry import quat_to_matrix, similarity_fit
from scipy.sparse import csr_matrix


def camera_jacobians(iop_px, R, T_mm, xyz_mm):
    """Derivatives of ``x = xp + c p_x/p_z``, ``p = R (P - T)`` per observation, px per unit.

    ``iop_px`` ``(3,)`` or, per observation, ``(n, 3)``.

    Returns ``(J_iop (n, 2, 3), J_rot (n, 2, 3), J_src (n, 2, 3), J_point (n, 2, 3))``: by
    ``(xp, yp, c)``, by a small rotation ``φ`` of the camera (``R <- exp([φ]x) R``), by the
    source ``T`` (mm) and by the bead ``P`` (mm).
    """
    p = np.einsum("nij,nj->ni", R, xyz_mm - T_mm)
    u, v = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    c = np.asarray(iop_px, dtype=np.float64)[..., 2]  # one system's, or (n,) per observation
    D = np.zeros((len(p), 2, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 0, 2], D[:, 1, 2] = -u, -v
    D *= (c / p[:, 2])[:, None, None]
    J_iop = np.zeros((len(p), 2, 3))
    J_iop[:, 0, 0] = J_iop[:, 1, 1] = 1.0
    J_iop[:, 0, 2], J_iop[:, 1, 2] = u, v
    # dp = φ x p = -[p]x φ
    px = np.zeros((len(p), 3, 3))
    px[:, 0, 1], px[:, 0, 2], px[:, 1, 2] = -p[:, 2], p[:, 1], -p[:, 0]
    px = px - px.transpose(0, 2, 1)
    J_point = D @ R
    return J_iop, -D @ px, -J_point, J_point


def affine_shape_modes(points_mm: np.ndarray, nominal_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal directions ``B`` ``(3 n, 5)`` of the affine deformations beyond a similarity; ``B^T (P - P_nom)``.

    The deformations ``dP_i = E (P_i - mean P)`` with ``E`` symmetric and
    traceless (stretches and shears), less their components along a
    similarity's displacements (a translation, a rotation and a scaling about
    the centroid: for a point set that is not isotropic they are not
    orthogonal to the stretches), so that holding them never holds the
    similarity, the free network's datum. ``P_nom`` is the nominal design
    brought onto ``P`` by a 7-parameter similarity, so only shape differs.
    """
    c = points_mm - points_mm.mean(0)
    r3 = 1 / np.sqrt(3.0)
    mats = [np.diag([1.0, -1.0, 0.0]), np.diag([r3, r3, -2 * r3])]
    for i, j in ((0, 1), (0, 2), (1, 2)):
        e = np.zeros((3, 3))
        e[i, j] = e[j, i] = 1.0
        mats.append(e)
    similarity = [np.tile(np.eye(3)[a], len(c)) for a in range(3)]
    similarity += [np.cross(np.eye(3)[a], c).ravel() for a in range(3)] + [c.ravel()]
    S, _ = np.linalg.qr(np.column_stack(similarity))
    shapes = np.column_stack([(c @ e.T).ravel() for e in mats])
    B, _ = np.linalg.qr(shapes - S @ (S.T @ shapes))
    scale, R, t = similarity_fit(nominal_mm, points_mm)
    aligned = scale * nominal_mm @ R.T + t
    return B, B.T @ (points_mm - aligned).ravel()


def similarity_modes(R, T_mm, P_mm, n_theta: int, pose_col: int, point_col: int, baselines=None) -> np.ndarray:
    """The 7 directions ``(n_theta, 7)`` of a similarity of object space, under which nothing projects differently.

    ``baselines``: ``(col, b_mm (k, 3))``, the columns and values of the ROP's source offsets (in the reference
    camera's frame: a scaling of object space scales them, a rotation or a translation leaves them).
    """
    E = np.zeros((n_theta, 7))
    m, n = len(T_mm), len(P_mm)
    rot = np.arange(m)[:, None] * 6 + pose_col + np.arange(3)
    src = rot + 3
    pts = np.arange(n)[:, None] * 3 + point_col + np.arange(3)
    for a in range(3):
        e = np.eye(3)[a]
        E[src, a], E[pts, a] = e, e
        E[src, 3 + a] = np.cross(e, T_mm)
        E[pts, 3 + a] = np.cross(e, P_mm)
        E[rot, 3 + a] = -R @ e
    E[src, 6], E[pts, 6] = T_mm, P_mm
    if baselines is not None:
        col, b_mm = baselines
        E[np.arange(len(b_mm))[:, None] * 6 + col + 3 + np.arange(3), 6] = b_mm
    return E / np.linalg.norm(E, axis=0)


@dataclass(frozen=True)
class Network:
    """The linearised orientation of one or more systems.

    Attributes
    ----------
    J : (2 n, n_theta) sparse csr_matrix, px per unit
        Derivatives of the observations' projections (x rows, then y rows) by ``θ``: each system's IOP
        ``(xp, yp, c)`` (columns ``3 s`` to ``3 s + 2``), each epoch's reference pose, its rotation and
        source (6 columns each, from ``3 n_systems``), with several systems each further system's
        relative orientation (ROP: its rotation and source offset, 6 columns each, system 0's being the
        reference), each bead's coordinates (3 columns each, from ``point_col``), once for every system
        that sees it. As the adjustment's parameters: system ``s``'s pose at epoch ``j`` is the ROP
        composed with the reference pose, ``R_s R_j`` and ``T_j + R_j^T b_s``.
    datum : (n_theta, 7) float64 ndarray
        The free network's similarity modes (unit columns), under which nothing projects differently.
    affine : (n_theta, 5) float64 ndarray or None
        The phantom's affine shape modes beyond a similarity (orthonormal, on the points' columns).
    affine_gap_mm : (5,) float64 ndarray or None
        The points' current shape along ``affine`` less the nominal design's.
    point_col : int
    beads : (n_beads,) int ndarray
        The beads of the point columns, in order (indices into the adjustment's ``bead_id``).
    n_systems : int
    """

    J: csr_matrix
    datum: np.ndarray
    affine: np.ndarray | None
    affine_gap_mm: np.ndarray | None
    point_col: int
    beads: np.ndarray
    n_systems: int = 1


def linearised_network(adj, observations, rows, system: int, shape_nominal_mm=None) -> Network:
    """The Jacobian of system ``system``'s observations ``rows`` by ``(IOP, poses, points)`` at ``adj``.

    ``shape_nominal_mm`` ``(n_beads, 3)``: the design coordinates of ``adj.bead_id``, for the affine modes.
    """
    return systems_network(adj, observations, (rows,), (system,), shape_nominal_mm)


def systems_network(adj, observations, rows_by_system, systems, shape_nominal_mm=None) -> Network:
    """The Jacobian of the observations ``rows_by_system[k]`` of each system ``systems[k]``, at ``adj``.

    The observations in that order (system by system); the beads once, whichever systems see them;
    the poses as the adjustment's, the epochs' reference poses and the systems' ROP (:class:`Network`).
    The datum is the similarity of the whole network; the affine modes are the shape's of all the
    beads seen (one phantom).
    """
    rows = np.concatenate(rows_by_system)
    s_of = np.repeat(np.arange(len(systems)), [len(r) for r in rows_by_system])
    epochs, e_of = np.unique(np.searchsorted(adj.exposure, observations.exposure[rows]), return_inverse=True)
    beads, b_of = np.unique(_bead_index(adj, observations, rows), return_inverse=True)
    ori, n, m, nb, n_sys = adj.orientation, len(rows), len(epochs), len(beads), len(systems)
    R_pose, T_pose = np.zeros((n, 3, 3)), np.zeros((n, 3))
    for k, system in enumerate(systems):
        q_s, T_s = ori.poses(int(system))
        at = epochs[e_of[s_of == k]]
        R_pose[s_of == k], T_pose[s_of == k] = quat_to_matrix(q_s[at]), T_s[at]
    R_ref, T_ref, P_b = quat_to_matrix(ori.q_cam_from_obj[epochs]), ori.source_mm[epochs], adj.xyz_mm[beads]
    iop = np.asarray(adj.iop_px, dtype=np.float64)[np.asarray(systems)][s_of]
    J_iop, J_rot, J_src, J_pt = camera_jacobians(iop, R_pose, T_pose, P_b[b_of])
    R_rop, b_rop = quat_to_matrix(ori.rop_q[np.asarray(systems)]), ori.rop_source_mm[np.asarray(systems)]
    if n_sys == 1:
        # one system alone: its own poses are the reference (no ROP), so that a similarity scales its sources too
        first = np.unique(e_of, return_index=True)[1]  # an observation of each epoch
        R_ref, T_ref = R_pose[first], T_pose[first]
        R_rop, b_rop = np.eye(3)[None], np.zeros((1, 3))
    # by the reference pose (ψ_j, T_j): φ = R_s ψ, δT = δT_j + R_j^T [b_s]x ψ; by the ROP (χ_s, b_s): φ = χ,
    # δT = R_j^T δb
    J_src_ref = J_src @ R_ref[e_of].transpose(0, 2, 1)
    J_psi = J_rot @ R_rop[s_of] + J_src_ref @ _cross_matrix(b_rop[s_of])
    pose_col = 3 * n_sys
    rop_col = pose_col + 6 * m
    point_col = rop_col + 6 * (n_sys - 1)
    values = [J_iop, J_psi, J_src, J_pt, J_rot, J_src_ref]
    cols = [
        3 * s_of[:, None] + np.arange(3),
        pose_col + 6 * e_of[:, None] + np.arange(6),
        point_col + 3 * b_of[:, None] + np.arange(3),
        rop_col + 6 * (s_of[:, None] - 1) + np.arange(6),
    ]
    J = _sparse_jacobian(values, cols, s_of > 0, point_col + 3 * nb)
    datum = similarity_modes(R_ref, T_ref, P_b, J.shape[1], pose_col, point_col, (rop_col, b_rop[1:]))
    affine = gap = None
    if shape_nominal_mm is not None:
        B, gap = affine_shape_modes(P_b, shape_nominal_mm[beads])
        affine = np.zeros((J.shape[1], B.shape[1]))
        affine[point_col:] = B
    return Network(J, datum, affine, gap, point_col, beads, n_sys)


def _cross_matrix(v: np.ndarray) -> np.ndarray:
    """``[v]x`` ``(n, 3, 3)`` of vectors ``v`` ``(n, 3)``: ``[v]x u = v x u``."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    return out - out.transpose(0, 2, 1)


def _sparse_jacobian(values, cols, with_rop: np.ndarray, n_theta: int) -> csr_matrix:
    """``J`` (x rows, then y rows) from the per-observation blocks ``(n, 2, 3)`` and their columns.

    ``values``: by the IOP, the reference rotation and source, the point, then (rows ``with_rop``) the ROP's
    rotation and offset; ``cols``: the IOP's, the reference pose's, the point's and the ROP's. Laid out in CSR
    directly, each row's entries in increasing columns (the IOP's, the pose's, the ROP's, the point's): the
    matrix a COO of the blocks converts to, without the conversion's sort.
    """
    n = len(with_rop)
    iop, psi, src, point, rot, src_ref = values
    groups = [(iop, cols[0]), (np.concatenate([psi, src], axis=2), cols[1]), (point, cols[2])]
    if with_rop.any():
        groups.insert(2, (np.concatenate([rot, src_ref], axis=2), cols[3]))
    data = [np.concatenate([v[:, c] for v, _ in groups], axis=1) for c in range(2)]
    row_cols = np.concatenate([c for _, c in groups], axis=1)
    if with_rop.any() and not with_rop.all():
        # the rows without an ROP (the reference system's) leave out its 6 entries
        keep = np.ones(row_cols.shape, bool)
        keep[~with_rop, 9:15] = False
        data, row_cols = [d[keep] for d in data], row_cols[keep]
    ends = np.cumsum(np.where(with_rop, 18, 12))
    dtype = np.int32 if max(n_theta, 2 * row_cols.size) < 2**31 else np.int64
    indptr = np.concatenate([[0], ends, ends[-1:] + ends]).astype(dtype)
    indices = np.concatenate([row_cols.ravel()] * 2).astype(dtype)
    return csr_matrix((np.concatenate([d.ravel() for d in data]), indices, indptr), shape=(2 * n, n_theta))


def _bead_index(adj, observations, rows) -> np.ndarray:
    """Index into ``adj.bead_id`` of each observation ``rows``."""
    order = np.argsort(adj.bead_id)
    return order[np.searchsorted(adj.bead_id, observations.bead_id[rows], sorter=order)]


__all__ = [
    "Network",
    "affine_shape_modes",
    "camera_jacobians",
    "linearised_network",
    "similarity_modes",
    "systems_network",
]
