"""The refinement's field step with the orientation eliminated: a Gauss-Newton step of the joint problem.

The alternation is slow along the field components that the orientation can
partly mimic: the IOP, the poses (a common rotation, the scale) and a
deformation of the (unknown, free-network) phantom. Each adjustment absorbs
part of the remaining field, and the next regression sees only what is left;
estimated alone, the field's update ignores that response and creeps. Here
the update is estimated with the response: :func:`fit_grid_jointly` solves
the linearised joint problem in the field *and* the IOP, every pose and every
bead, and keeps the field's part (the next adjustment re-solves the rest,
non-linearly). Its fixed point is the alternation's; it is reached in a few
steps instead of dozens (beyond the paper).
"""

from __future__ import annotations

import logging

import numpy as np
from fluorocal.stages.errors import EstimationError, InputError
from fluorocal.stages.field import CorrectionField, bilinear_design
from fluorocal.stages.learn.gauge import gauge_basis
from fluorocal.stages.learn.grid import factor_spd, grid_result, prior_normal
from fluorocal.stages.learn.network import Network
from fluorocal.stages.learn.nodes import DEFAULT_GRID, GridSpec
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse import block_diag, diags, vstack
from scipy.sparse.linalg import LinearOperator, cg

logger = logging.getLogger(__name__)

#: stiffness of the phantom's affine shape hold, relative to the largest diagonal term of the beads' coordinates in
#: the orientation's normal matrix: stiff enough to hold it to a small fraction of its data-determined change, yet
#: well conditioned
AFFINE_STIFFNESS = 1e2
#: ridge of the beads' coordinates in the orientation's Jacobi-scaled normal matrix (unit diagonal)
POINT_RIDGE = 1e-8


def fit_grid_jointly(
    xy_px: np.ndarray,
    residuals_px: np.ndarray,
    weights: np.ndarray,
    network: Network,
    *,
    iop_px,
    estimate_iop: bool,
    image_size: tuple[int, int],
    tau_px: float,
    base: CorrectionField,
    cv_rms_px: float,
    grid: GridSpec = DEFAULT_GRID,
    max_cg_iterations: int = 400,
    cg_tolerance: float = 1e-6,
    order: int = 2,
    start: np.ndarray | None = None,
    point_information: np.ndarray | None = None,
    respond: str = "orientation",
) -> CorrectionField:
    """Gridded field update estimated jointly with the orientation's response (IOP, poses, points).

    From the linearised model ``r ≈ A δ + J dθ``, minimises
    ``Σ w (r - A δ - J dθ)² + |D (base + δ)|² / τ²`` (+ the holds below) over
    the node values' update ``δ`` and ``dθ``; ``dθ`` is eliminated (its normal
    matrix is small and dense: a Cholesky factor) and the reduced system in
    ``δ`` solved by conjugate gradients preconditioned with the field-only
    normal matrix (a sparse LU). What no data fix is held: the free network's
    similarity (``network.datum``), the field's gauge (the fields the IOP and a
    common camera rotation reproduce exactly, :mod:`fluorocal.stages.learn.gauge`)
    and, when ``network.affine`` is given, the phantom's five affine shape modes
    beyond a similarity, at the nominal design's: the free network's datum
    leaves them to weak perspective effects, and a field that mimics them (an
    image aspect ratio or shear) would otherwise stretch the reconstruction.

    Parameters
    ----------
    xy_px, residuals_px : (n, 2) float64 ndarray, px
        Measured coordinates (inliers of one system) and their residuals.
    weights : (n, 2) float64 ndarray, 1/px²
        Observation weights (inverse variances, times the t-weights).
    network : Network
        The system's orientation linearised at the adjustment, at the same observations
        (:func:`fluorocal.stages.learn.network.linearised_network`).
    iop_px, estimate_iop : (3,) array_like px, bool
        The system's ``(xp, yp, c)`` (for the gauge fields); whether the adjustment estimates it.
    image_size, tau_px, base, cv_rms_px, grid, order
        As in :func:`fluorocal.stages.learn.grid.fit_grid_field` (``order``: the difference prior's, default 2).
    max_cg_iterations, cg_tolerance, start
        The conjugate gradients' cap, relative tolerance and start (node values ``(H_g, W_g, 2)`` px, optional).
    point_information : (n_beads, 3, 3) float64 ndarray, 1/mm², optional
        What other systems' observations tell of ``network.beads`` (their orientation held,
        :func:`fluorocal.stages.learn.network.point_information`): the beads a biplanar set
        shares are not free for this system's field step to move.
    respond : str
        What responds to the field's update: ``"orientation"`` (the IOP, the poses and the points, as
        above) or ``"points"`` (the points alone, the IOP and the poses held: no datum and no gauge
        to hold then).

    Returns
    -------
    CorrectionField
        The update ``δ`` (not ``base + δ``).
    """
    if respond not in ("orientation", "points"):
        raise InputError(f"respond must be 'orientation' or 'points'; got {respond!r}")
    xy, r, w = (np.asarray(a, dtype=np.float64) for a in (xy_px, residuals_px, weights))
    width, height = (int(s) for s in image_size)
    xn, yn = grid.nodes((width, height))
    A = bilinear_design(xn, yn, xy)
    reg = prior_normal(len(yn), len(xn), int(order)) / tau_px**2
    Nvv, bv, AtW = _field_normal(A, w, r, reg, base.delta_px.reshape(-1, 2))
    matvec, rhs = _reduced_system(A, xy, w, r, Nvv, bv, AtW, network, iop_px, estimate_iop, respond, point_information)
    x0 = None if start is None else np.asarray(start, dtype=np.float64).reshape(-1, 2).T.ravel()
    v = _solve_reduced(Nvv, matvec, rhs, np.array_equal(w[:, 0], w[:, 1]), max_cg_iterations, cg_tolerance, x0)
    n_nodes = A.shape[1]
    return grid_result(xn, yn, np.column_stack([v[:n_nodes], v[n_nodes:]]), A, xy, cv_rms_px, grid, (width, height))


def _reduced_system(A, xy, w, r, Nvv, bv, AtW, network, iop_px, estimate_iop, respond, point_information):
    """The node values' system with the responding parameters eliminated: its matrix-vector product and right side."""
    held = slice(network.point_col if respond == "points" else 0 if estimate_iop else 3, None)
    J = network.J[:, held]
    solve_theta, b_theta = _orientation_inverse(J, w, r, network, held, point_information)
    Nvt = vstack([AtW[c] @ J[c * len(xy) : (c + 1) * len(xy)] for c in range(2)]).tocsr()
    # the gauge is held only where the orientation, which could carry it, responds
    G, k_gauge = _gauge_penalty(A, xy, w, iop_px, estimate_iop) if respond == "orientation" else (None, 0.0)
    Ntv = Nvt.T.tocsr()

    def matvec(v):
        reduced = Nvv @ v - Nvt @ solve_theta(Ntv @ v)
        return reduced if G is None else reduced + k_gauge * (G.T @ (G @ v))

    return matvec, bv - Nvt @ solve_theta(b_theta)


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


def _orientation_inverse(J, w, r, network: Network, held: slice, point_information=None):
    """``x -> N_θθ^-1 x`` for the orientation's normal matrix with its holds, and the right-hand side ``J^T W r``.

    ``N_θθ = J^T W J`` plus the datum (a unit curvature along each similarity mode, in the
    Jacobi-scaled problem: the data's gradient along them is nil, so they stay put) and
    the affine hold ``κ |B^T (P + dP) - B^T P_nominal|²``; ``point_information`` is added to the beads' blocks.
    With the points alone responding, ``N_θθ`` is the beads' 3x3 blocks and the hold's rank-5 term
    (:func:`_points_inverse`).
    """
    if held.start == network.point_col:
        return _points_inverse(J, w, r, network, point_information)
    wf, rf = w.T.ravel(), r.T.ravel()
    JW = J.multiply(wf[:, None]).tocsr()
    N = (J.T @ JW).toarray()
    b = JW.T @ rf
    if point_information is not None:
        p0 = network.point_col - held.start
        idx = p0 + 3 * np.arange(len(point_information))[:, None] + np.arange(3)
        N[idx[:, :, None], idx[:, None, :]] += point_information
    # the Jacobi scaling of the data's normal matrix (the stiff affine hold would swamp the points' diagonal)
    d = np.sqrt(np.maximum(np.diag(N), 1e-300))
    if network.affine is not None:
        kappa = AFFINE_STIFFNESS * float(np.max(np.diag(N)[network.point_col - held.start :]))
        F = network.affine[held]
        N += kappa * F @ F.T
        b = b - kappa * F @ network.affine_gap_mm
    E = d[:, None] * network.datum[held]
    # the similarity is a datum only when nothing else fixes it: not when other systems' views of the beads, their
    # orientation held, pin them
    E = E / np.linalg.norm(E, axis=0) if point_information is None else np.zeros((len(d), 0))
    # a ridge on the beads' coordinates, in the Jacobi-scaled problem, for what no data fix beyond the datum: the
    # depth of a bead one exposure saw (the data's gradient along it is nil too). Not on the poses and the IOP: their
    # weakest combinations, which the field trades against, sit far below any ridge that would make a difference
    ridge = np.zeros(len(d))
    ridge[network.point_col - held.start :] = POINT_RIDGE
    try:
        factor = cho_factor(N / d[:, None] / d[None, :] + E @ E.T + np.diag(ridge))
    except np.linalg.LinAlgError as exc:
        raise EstimationError(
            "the refinement's field step: the orientation's normal matrix is singular (an exposure with too few "
            'observations left?); set [learn] orientation_response = "no" to move the beads alone'
        ) from exc
    # the factor is finite (checked by cho_factor): no check of it at every one of the CG's solves
    return (lambda x: cho_solve(factor, x / d, check_finite=False) / d), b


def _points_inverse(J, w, r, network: Network, point_information=None):
    """:func:`_orientation_inverse` when the points alone respond: their 3x3 blocks, less a Woodbury term.

    Each observation sees one bead, so ``J^T W J`` (and ``point_information``) is block diagonal;
    the affine hold adds ``κ F F^T`` (rank 5), inverted by Woodbury's identity. The same matrix as
    the dense path's, the ridge ``POINT_RIDGE`` on the Jacobi-scaled diagonal included (no datum:
    the points move the image), at a cost linear in the beads instead of a dense Cholesky.
    """
    wf, rf = w.T.ravel(), r.T.ravel()
    JW = J.multiply(wf[:, None]).tocsr()
    b = JW.T @ rf
    n_beads = J.shape[1] // 3
    coo = (J.T @ JW).tocoo()
    blocks = np.zeros((n_beads, 3, 3))
    np.add.at(blocks, (coo.row // 3, coo.row % 3, coo.col % 3), coo.data)
    if point_information is not None:
        blocks += point_information
    diag = np.einsum("bii->bi", blocks)
    d2 = np.maximum(diag, 1e-300)
    kappa = AFFINE_STIFFNESS * float(np.max(diag)) if network.affine is not None else 0.0
    blocks[:, np.arange(3), np.arange(3)] += POINT_RIDGE * d2
    try:
        blocks_inv = np.linalg.inv(blocks)
    except np.linalg.LinAlgError as exc:
        raise EstimationError("the refinement's field step: a bead's normal block is singular") from exc

    def block_solve(x):
        return np.einsum("bij,bj...->bi...", blocks_inv, x.reshape(n_beads, 3, *x.shape[1:])).reshape(x.shape)

    if network.affine is None:
        return block_solve, b
    F = network.affine[network.point_col :]
    b = b - kappa * F @ network.affine_gap_mm
    NiF = block_solve(F)
    core = np.linalg.inv(np.eye(F.shape[1]) / kappa + F.T @ NiF)
    return (lambda x: block_solve(x) - NiF @ (core @ (NiF.T @ x))), b


def _gauge_penalty(A, xy, w, iop_px, with_iop: bool):
    """``G`` ``(K, 2 n_nodes)``: the field's components at the observations along the gauge fields, and its weight.

    The weight makes each gauge mode about as stiff as the data would make it, were it not
    reproduced by the orientation.
    """
    B = gauge_basis(xy, iop_px, with_iop)
    B = B / np.sqrt(np.mean(B**2, axis=(0, 1)))
    G = np.concatenate([(A.T @ B[:, c, :]).T for c in range(2)], axis=1)
    return G, float(np.mean(w)) / max(len(xy), 1)


def _solve_reduced(Nvv, matvec, rhs, same_weights: bool, max_cg_iterations: int, cg_tolerance: float, x0=None):
    """The node values of the reduced system, by CG preconditioned with the field block's LU."""
    n_nodes = Nvv.shape[0] // 2
    op = LinearOperator((2 * n_nodes, 2 * n_nodes), matvec=matvec, dtype=np.float64)
    # the preconditioner, block by block: one factorisation when both components weigh alike
    blocks = [Nvv[:n_nodes, :n_nodes]] if same_weights else [Nvv[:n_nodes, :n_nodes], Nvv[n_nodes:, n_nodes:]]
    lus = [factor_spd(blk) for blk in blocks]

    def precondition(v):
        return np.concatenate([lus[0].solve(v[:n_nodes]), lus[-1].solve(v[n_nodes:])])

    pre = LinearOperator((2 * n_nodes, 2 * n_nodes), matvec=precondition, dtype=np.float64)
    v, info = cg(op, rhs, x0=x0, rtol=cg_tolerance, maxiter=max_cg_iterations, M=pre)
    if info > 0:
        logger.info("joint field step: CG stopped after %d iterations short of its tolerance", info)
    return v


__all__ = ["fit_grid_jointly"]
