"""One system's orientation linearised at an adjustment: the Jacobian by ``(IOP, poses, points)`` and its datum.

Shared by the refinement's joint field step (:mod:`.joint`) and the joint
uncertainty (:mod:`.uncertainty`). Each system is taken on its own with a free
pose per exposure (a biplanar pair's ROP, which ties them, is not used).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.geometry import quat_to_matrix, similarity_fit
from scipy.sparse import csr_matrix, vstack


def camera_jacobians(iop_px, R, T_mm, xyz_mm):
    """Derivatives of ``x = xp + c p_x/p_z``, ``p = R (P - T)`` per observation, px per unit.

    Returns ``(J_iop (n, 2, 3), J_rot (n, 2, 3), J_src (n, 2, 3), J_point (n, 2, 3))``: by
    ``(xp, yp, c)``, by a small rotation ``φ`` of the camera (``R <- exp([φ]x) R``), by the
    source ``T`` (mm) and by the bead ``P`` (mm).
    """
    p = np.einsum("nij,nj->ni", R, xyz_mm - T_mm)
    u, v = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    c = float(iop_px[2])
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


def similarity_modes(R, T_mm, P_mm, n_theta: int, pose_col: int, point_col: int) -> np.ndarray:
    """The 7 directions ``(n_theta, 7)`` of a similarity of object space, under which nothing projects differently."""
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
    return E / np.linalg.norm(E, axis=0)


@dataclass(frozen=True)
class Network:
    """One system's linearised orientation.

    Attributes
    ----------
    J : (2 n, n_theta) sparse csr_matrix, px per unit
        Derivatives of the observations' projections (x rows, then y rows) by ``θ``: the IOP
        ``(xp, yp, c)`` (columns 0-2), each exposure's rotation and source (6 columns each), each
        bead's coordinates (3 columns each, from ``point_col``).
    datum : (n_theta, 7) float64 ndarray
        The free network's similarity modes (unit columns), under which nothing projects differently.
    affine : (n_theta, 5) float64 ndarray or None
        The phantom's affine shape modes beyond a similarity (orthonormal, on the points' columns).
    affine_gap_mm : (5,) float64 ndarray or None
        The points' current shape along ``affine`` less the nominal design's.
    point_col : int
    beads : (n_beads,) int ndarray
        The beads of the point columns, in order (indices into the adjustment's ``bead_id``).
    """

    J: csr_matrix
    datum: np.ndarray
    affine: np.ndarray | None
    affine_gap_mm: np.ndarray | None
    point_col: int
    beads: np.ndarray


def linearised_network(adj, observations, rows, system: int, shape_nominal_mm=None) -> Network:
    """The Jacobian of system ``system``'s observations ``rows`` by ``(IOP, poses, points)`` at ``adj``.

    ``shape_nominal_mm`` ``(n_beads, 3)``: the design coordinates of ``adj.bead_id``, for the affine modes.
    """
    epochs, e_of = np.unique(np.searchsorted(adj.exposure, observations.exposure[rows]), return_inverse=True)
    beads, b_of = np.unique(_bead_index(adj, observations, rows), return_inverse=True)
    q_s, T_s = adj.orientation.poses(system)
    R_e, T_e, P_b = quat_to_matrix(q_s[epochs]), T_s[epochs], adj.xyz_mm[beads]
    J_iop, J_rot, J_src, J_pt = camera_jacobians(adj.iop_px[system], R_e[e_of], T_e[e_of], P_b[b_of])
    n, m, nb = len(rows), len(epochs), len(beads)
    pose_col, point_col = 3, 3 + 6 * m
    n_theta = point_col + 3 * nb
    cols = np.concatenate(
        [
            np.tile(np.arange(3), (n, 1)),
            pose_col + 6 * e_of[:, None] + np.arange(6),
            point_col + 3 * b_of[:, None] + np.arange(3),
        ],
        axis=1,
    )
    blocks = []
    for comp in range(2):
        vals = np.concatenate([J_iop[:, comp], J_rot[:, comp], J_src[:, comp], J_pt[:, comp]], axis=1)
        blocks.append(csr_matrix((vals.ravel(), (np.repeat(np.arange(n), 12), cols.ravel())), shape=(n, n_theta)))
    datum = similarity_modes(R_e, T_e, P_b, n_theta, pose_col, point_col)
    affine = gap = None
    if shape_nominal_mm is not None:
        B, gap = affine_shape_modes(P_b, shape_nominal_mm[beads])
        affine = np.zeros((n_theta, B.shape[1]))
        affine[point_col:] = B
    return Network(vstack(blocks).tocsr(), datum, affine, gap, point_col, beads)


def point_information(adj, observations, rows, weights, beads) -> np.ndarray:
    """``(len(beads), 3, 3)``: what observations ``rows`` (any systems) tell of the beads ``beads``, orientation held.

    ``Σ J_P^T W J_P`` per bead over the rows that observe it (``weights`` ``(n, 2)``, 1/px²), with
    ``J_P`` the projection's derivative by the bead's coordinates at ``adj``. The other systems'
    information on the beads a system's joint field step shares with them: in a biplanar set the
    points are pinned by both views, not free for one system's field to push.
    """
    info = np.zeros((len(beads), 3, 3))
    bead = _bead_index(adj, observations, rows)
    where = np.searchsorted(beads, bead)
    seen = (where < len(beads)) & (beads[np.minimum(where, len(beads) - 1)] == bead)
    epoch = np.searchsorted(adj.exposure, observations.exposure[rows])
    for system in np.unique(observations.system[rows]):
        at = seen & (observations.system[rows] == system)
        q_s, T_s = adj.orientation.poses(int(system))
        *_, J_pt = camera_jacobians(adj.iop_px[system], quat_to_matrix(q_s[epoch[at]]), T_s[epoch[at]],
                                    adj.xyz_mm[bead[at]])  # fmt: skip
        np.add.at(info, where[at], np.einsum("nci,nc,ncj->nij", J_pt, weights[at], J_pt))
    return info


def _bead_index(adj, observations, rows) -> np.ndarray:
    """Index into ``adj.bead_id`` of each observation ``rows``."""
    order = np.argsort(adj.bead_id)
    return order[np.searchsorted(adj.bead_id, observations.bead_id[rows], sorter=order)]


__all__ = [
    "Network",
    "affine_shape_modes",
    "camera_jacobians",
    "linearised_network",
    "point_information",
    "similarity_modes",
]
