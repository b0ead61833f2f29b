"""Joint refinement of the gridded field and the object points (beyond the paper).

The alternation is slow along the field components that a deformation of the
(unknown, free-network) phantom can mimic: each adjustment moves the points to
absorb part of the remaining field, and the next regression sees only what is
left. :func:`fit_grid_with_points` estimates the field's update together with
a 3D shift of every bead from the linearised model, optionally holding the
phantom's affine shape at the design's (:func:`affine_shape_modes`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from fluorocal.stages.field import CorrectionField, bilinear_design
from fluorocal.stages.geometry import similarity_fit
from fluorocal.stages.learn.grid import difference_operator, factor_spd, grid_result
from fluorocal.stages.learn.nodes import DEFAULT_GRID, GridSpec
from scipy.sparse import block_diag, csr_matrix, diags, vstack
from scipy.sparse.linalg import LinearOperator, cg

logger = logging.getLogger(__name__)


def affine_shape_modes(points_mm: np.ndarray, nominal_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal directions ``B`` ``(3 n, 5)`` of the affine deformations beyond a similarity; ``B^T (P - P_nom)``.

    The deformations ``dP_i = E (P_i - mean P)`` with ``E`` symmetric and
    traceless (stretches and shears); ``P_nom`` is the nominal design brought
    onto ``P`` by a 7-parameter similarity, so only shape differs.
    """
    c = points_mm - points_mm.mean(0)
    r3 = 1 / np.sqrt(3.0)
    mats = [np.diag([1.0, -1.0, 0.0]), np.diag([r3, r3, -2 * r3])]
    for i, j in ((0, 1), (0, 2), (1, 2)):
        e = np.zeros((3, 3))
        e[i, j] = e[j, i] = 1.0
        mats.append(e)
    B, _ = np.linalg.qr(np.column_stack([(c @ e.T).ravel() for e in mats]))
    scale, R, t = similarity_fit(nominal_mm, points_mm)
    aligned = scale * nominal_mm @ R.T + t
    return B, B.T @ (points_mm - aligned).ravel()


def fit_grid_with_points(
    xy_px: np.ndarray,
    residuals_px: np.ndarray,
    weights: np.ndarray,
    bead_index: np.ndarray,
    point_jacobian: np.ndarray,
    *,
    image_size: tuple[int, int],
    tau_px: float,
    base: CorrectionField,
    cv_rms_px: float,
    grid: GridSpec = DEFAULT_GRID,
    shape_mm: tuple[np.ndarray, np.ndarray] | None = None,
    max_cg_iterations: int = 400,
    order: int = 2,
) -> CorrectionField:
    """Gridded field update estimated jointly with corrections to the object points (poses held).

    The alternation is slow along the field components that a deformation of
    the (unknown, free-network) phantom can mimic: each adjustment moves the
    points to absorb part of the remaining field, and the next regression sees
    only what is left. Here the update ``δ`` of the node values and a 3D shift
    ``dP`` of every bead are estimated together from the linearised model
    ``r ≈ A δ + J dP``, minimising ``Σ w (r - A δ - J dP)² + |D (base + δ)|² / τ²``;
    the shifts are eliminated bead by bead (3×3 blocks) and the reduced system
    in ``δ`` is solved by conjugate gradients preconditioned with the
    field-only normal matrix (a sparse LU).

    Parameters
    ----------
    xy_px : (n, 2) float64 ndarray, px
        Measured coordinates (inliers of one system).
    residuals_px : (n, 2) float64 ndarray, px
    weights : (n, 2) float64 ndarray, 1/px²
        Observation weights (inverse variances, times the t-weights).
    bead_index : (n,) int ndarray
        Bead of each observation (``0 .. n_beads - 1``).
    point_jacobian : (n, 2, 3) float64 ndarray, px/mm
        Derivative of the projection by the bead's coordinates.
    image_size, tau_px, base, cv_rms_px, grid
        As in :func:`fluorocal.stages.learn.grid.fit_grid_field`.
    shape_mm : ((n_beads, 3), (n_beads, 3)) float64 ndarrays, mm, optional
        Current and nominal bead coordinates. When given, the five affine
        deformations beyond a similarity (stretches and shears) of the
        shifted points ``P + dP`` are held at the nominal design's by a stiff
        penalty: the free network's similarity datum leaves them to weak
        perspective effects, and a field that mimics them (an image aspect
        ratio or shear) would otherwise stretch the reconstruction.
    max_cg_iterations : int
    order : int
        Order of the difference prior (default 2), as in :func:`fluorocal.stages.learn.grid.fit_grid_field`.

    Returns
    -------
    CorrectionField
        The update ``δ`` (not ``base + δ``).
    """
    xy, r, w = (np.asarray(a, dtype=np.float64) for a in (xy_px, residuals_px, weights))
    width, height = (int(s) for s in image_size)
    xn, yn = grid.nodes((width, height))
    A = bilinear_design(xn, yn, xy)
    D = difference_operator(len(yn), len(xn), int(order))
    Nvv, bv, AtW = _field_normal(A, w, r, (D.T @ D).tocsr() / tau_px**2, base.delta_px.reshape(-1, 2))
    n_beads = len(shape_mm[0]) if shape_mm is not None else (int(bead_index.max()) + 1 if len(xy) else 0)
    Nvp, points, bp = _point_normal(AtW, w, r, bead_index, point_jacobian, n_beads, shape_mm)
    v = _solve_reduced(Nvv, Nvp, points, bv, bp, np.array_equal(w[:, 0], w[:, 1]), max_cg_iterations)
    n_nodes = A.shape[1]
    return grid_result(xn, yn, np.column_stack([v[:n_nodes], v[n_nodes:]]), A, xy, cv_rms_px, grid, (width, height))


def _field_normal(A, w, r, reg, base_v):
    """The field's block of the joint normal equations, its right-hand side and ``A^T W`` per component.

    ``reg`` is the prior's ``D^T D / τ²``; a tiny ridge keeps nodes far from all data determined.
    """
    n_nodes = A.shape[1]
    ridge = 1e-10 * max(float(w.max()), 1.0)
    AtW = [A.T.multiply(w[:, c]).tocsr() for c in range(2)]
    Nvv = block_diag([AtW[0] @ A + reg, AtW[1] @ A + reg], format="csc") + diags(np.full(2 * n_nodes, ridge))
    bv = np.concatenate([AtW[c] @ r[:, c] - reg @ base_v[:, c] for c in range(2)])
    return Nvv, bv, AtW


@dataclass(frozen=True)
class _PointInverse:
    """The inverse of the points' normal matrix: per-bead 3x3 blocks, less a rank-5 Woodbury term (affine datum)."""

    blocks_inv: np.ndarray  # shape (n_beads, 3, 3)
    NiB: np.ndarray | None = None
    core: np.ndarray | None = None

    def block_inverse(self, x: np.ndarray) -> np.ndarray:
        return np.einsum("bij,bj->bi", self.blocks_inv, x.reshape(-1, 3)).ravel()

    def apply(self, x: np.ndarray) -> np.ndarray:
        if self.NiB is None:
            return self.block_inverse(x)
        return self.block_inverse(x) - self.NiB @ (self.core @ (self.NiB.T @ x))


def _point_normal(AtW, w, r, bead_index, point_jacobian, n_beads: int, shape_mm):
    """The coupling ``N_vp`` (sparse), the points' inverse normal matrix and right-hand side ``(n_beads, 3)``."""
    n = len(r)
    cols = (3 * bead_index[:, None] + np.arange(3)).ravel()
    # J_c as sparse (n, 3 n_beads): row o holds d proj_c / d P of its bead
    Jc = [
        csr_matrix((point_jacobian[:, c, :].ravel(), (np.repeat(np.arange(n), 3), cols)), shape=(n, 3 * n_beads))
        for c in range(2)
    ]
    Nvp = vstack([AtW[c] @ Jc[c] for c in range(2)]).tocsr()
    # per-bead 3x3 blocks sum_o J^T W J, inverted
    Npp = np.zeros((n_beads, 3, 3))
    np.add.at(Npp, bead_index, np.einsum("nci,nc,ncj->nij", point_jacobian, w, point_jacobian))
    trace = np.trace(Npp, axis1=1, axis2=2)
    # beads without observations here (seen only by another system) get a unit-scale block
    Npp += np.maximum(1e-9 * trace, 1e-6 * max(float(trace.max(initial=0.0)), 1e-300))[:, None, None] * np.eye(3)
    points = _PointInverse(np.linalg.inv(Npp))
    bp = np.zeros((n_beads, 3))
    np.add.at(bp, bead_index, np.einsum("nci,nc->ni", point_jacobian, w * r))
    if shape_mm is not None:
        B, gap = affine_shape_modes(*shape_mm)
        kappa = 1e2 * float(np.max(trace))
        # penalty kappa |B^T (P + dP) - B^T P_nominal|^2: rank-5 term, inverted by Woodbury
        bp = bp - kappa * (B @ gap).reshape(-1, 3)
        NiB = np.column_stack([points.block_inverse(b) for b in B.T])
        points = _PointInverse(points.blocks_inv, NiB, np.linalg.inv(np.eye(B.shape[1]) / kappa + B.T @ NiB))
    return Nvp, points, bp


def _solve_reduced(Nvv, Nvp, points: _PointInverse, bv, bp, same_weights: bool, max_cg_iterations: int):
    """The node values of the system with the points eliminated, by CG preconditioned with the field block's LU."""
    n_nodes = Nvv.shape[0] // 2
    Npv = Nvp.T.tocsr()
    rhs = bv - Nvp @ points.apply(bp.ravel())
    op = LinearOperator(
        (2 * n_nodes, 2 * n_nodes), matvec=lambda v: Nvv @ v - Nvp @ points.apply(Npv @ v), dtype=np.float64
    )
    # the preconditioner, block by block: one factorisation when both components weigh alike
    blocks = [Nvv[:n_nodes, :n_nodes]] if same_weights else [Nvv[:n_nodes, :n_nodes], Nvv[n_nodes:, n_nodes:]]
    lus = [factor_spd(blk) for blk in blocks]

    def precondition(v):
        return np.concatenate([lus[0].solve(v[:n_nodes]), lus[-1].solve(v[n_nodes:])])

    pre = LinearOperator((2 * n_nodes, 2 * n_nodes), matvec=precondition, dtype=np.float64)
    v, info = cg(op, rhs, rtol=1e-6, maxiter=max_cg_iterations, M=pre)
    if info > 0:
        logger.info("joint field-and-points step: CG stopped after %d iterations short of its tolerance", info)
    return v


__all__ = ["affine_shape_modes", "fit_grid_with_points"]
