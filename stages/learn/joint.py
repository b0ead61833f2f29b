"""The refinement's field step with the orientation eliminated: a Gauss-Newton step of the joint problem.

The alternation is slow along the field components that the orientation can
partly mimic: the IOP, the poses (a common rotation, the scale) and a
deformation of the (unknown, free-network) phantom. Each adjustment absorbs
part of the remaining field, and the next regression sees only what is left;
estimated alone, the field's update ignores that response and creeps. Here
the update is estimated with the response: :func:`fit_grids_jointly` solves
the linearised joint problem in every system's field *and* the IOP, every pose
and every bead, and keeps the fields' part (the next adjustment re-solves the
rest, non-linearly). Its fixed point is the alternation's; it is reached in a
few steps instead of dozens (beyond the paper). The systems of a biplanar set
are solved together: the beads they share tie their fields, and one system's
step at a time, the others held, would only approach the joint step by a slow
block iteration between them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from fluorocal.stages.errors import EstimationError, InputError
from fluorocal.stages.field import CorrectionField, bilinear_design
from fluorocal.stages.learn.gauge import gauge_basis
from fluorocal.stages.learn.grid import factor_sum, grid_result, scaled_prior
from fluorocal.stages.learn.network import Network
from fluorocal.stages.learn.nodes import DEFAULT_GRID, GridSpec
from scipy.linalg import LinAlgError, cho_factor, cho_solve
from scipy.linalg import block_diag as dense_block_diag
from scipy.sparse import csr_matrix, diags
from scipy.sparse.linalg import LinearOperator, cg

logger = logging.getLogger(__name__)

#: stiffness of the phantom's affine shape hold, relative to the largest diagonal term of the beads' coordinates in
#: the orientation's normal matrix: stiff enough to hold it to a small fraction of its data-determined change, yet
#: well conditioned
AFFINE_STIFFNESS = 1e2
#: ridge of the beads' coordinates in the orientation's Jacobi-scaled normal matrix (unit diagonal)
POINT_RIDGE = 1e-8


class Respond(StrEnum):
    """What responds to the fields' update in the joint step: the whole orientation, or the object points alone."""

    ORIENTATION = "orientation"
    POINTS = "points"


@dataclass(frozen=True)
class SystemStep:
    """One system's part of the joint field step: its observations, residuals, weights and field prior.

    Attributes
    ----------
    xy_px, residuals_px : (n, 2) float64 ndarray, px
        Measured coordinates (the observations the field learns from) and their residuals.
    weights : (n, 2) float64 ndarray, 1/px²
        Observation weights (inverse variances, times the t-weights).
    iop_px : (3,) array_like, px
        The system's ``(xp, yp, c)`` (for the gauge fields).
    image_size, tau_px, base, cv_rms_px, order
        As in :func:`fluorocal.stages.learn.grid.fit_grid_field` (``order``: the difference prior's).
    start : (H_g, W_g, 2) float64 ndarray, px, optional
        Node values to start the conjugate gradients from.
    """

    xy_px: np.ndarray
    residuals_px: np.ndarray
    weights: np.ndarray
    iop_px: np.ndarray
    image_size: tuple
    tau_px: float
    base: CorrectionField
    cv_rms_px: float
    order: int = 2
    start: np.ndarray | None = None


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
    respond: Respond = Respond.ORIENTATION,
) -> CorrectionField:
    """One system's gridded field update estimated jointly with the orientation's response (IOP, poses, points).

    :func:`fit_grids_jointly` of one system (its :class:`SystemStep` fields are the arguments of the same names).
    """
    step = SystemStep(xy_px, residuals_px, weights, iop_px, image_size, tau_px, base, cv_rms_px, order, start)
    options = dict(grid=grid, max_cg_iterations=max_cg_iterations, cg_tolerance=cg_tolerance, respond=respond)
    return fit_grids_jointly((step,), network, estimate_iop=estimate_iop, **options)[0]


def fit_grids_jointly(
    systems,
    network: Network,
    *,
    estimate_iop: bool,
    grid: GridSpec = DEFAULT_GRID,
    max_cg_iterations: int = 400,
    cg_tolerance: float = 1e-6,
    respond: Respond = Respond.ORIENTATION,
    with_response: bool = False,
) -> tuple[CorrectionField, ...]:
    """Every system's gridded field update, estimated jointly with the orientation's response.

    From the linearised model ``r_s ≈ A_s δ_s + J_s dθ`` of each system ``s``, minimises
    ``Σ_s [Σ w (r_s - A_s δ_s - J_s dθ)² + |D (base_s + δ_s)|² / τ_s²]`` (+ the holds below) over
    the node values' updates ``δ_s`` of every system and ``dθ``, every system's IOP and poses and
    the beads, which the systems share; ``dθ`` is eliminated (its normal matrix is small and dense:
    a Cholesky factor) and the reduced system in the stacked ``δ`` solved by conjugate gradients
    preconditioned with the field-only normal matrix (sparse factors per system), deflated by the
    smooth fields the orientation nearly reproduces (:func:`_deflated`). One system's
    step is the system's Gauss-Newton step, several systems' the whole problem's: the shared
    beads tie their fields, which one system's step at a time (the others' orientation held)
    could only approach by a slow block iteration. What no data fix is held: the network's
    similarity (``network.datum``), each field's gauge (the fields its IOP and a common rotation
    of its cameras reproduce exactly, :mod:`fluorocal.stages.learn.gauge`) and, when
    ``network.affine`` is given, the phantom's five affine shape modes beyond a similarity, at the
    nominal design's: the free network's datum leaves them to weak perspective effects, and a
    field that mimics them (an image aspect ratio or shear) would otherwise stretch the
    reconstruction.

    Parameters
    ----------
    systems : sequence of SystemStep
        Each system's observations, in the order of ``network``'s rows.
    network : Network
        The systems' orientation linearised at the adjustment, at the same observations
        (:func:`fluorocal.stages.learn.network.systems_network`).
    estimate_iop : bool
        Whether the adjustment estimates the IOP (then they respond, and their gauge fields are held).
    grid : GridSpec
    max_cg_iterations, cg_tolerance
        The conjugate gradients' cap and relative tolerance (of the residual, to the right-hand side).
    respond : Respond
        What responds to the fields' update: ``Respond.ORIENTATION`` (the IOP, the poses and the points, as
        above) or ``Respond.POINTS`` (the points alone, the IOP and the poses held: no datum and no gauge
        to hold then).
    with_response : bool
        Also return the orientation's response ``J_s dθ`` at each system's observations.

    Returns
    -------
    tuple of CorrectionField
        Each system's update ``δ_s`` (not ``base + δ_s``).
    tuple of (n_s, 2) float64 ndarray, px
        With ``with_response``: each system's ``J_s dθ``, so that ``r_s - A_s δ_s - J_s dθ`` is what the step
        leaves of its residuals (the in-sample cost of the step's fit is that of equation 3).
    """
    if respond not in tuple(Respond):
        raise InputError(f"respond must be 'orientation' or 'points'; got {respond!r}")
    respond = Respond(respond)
    parts = [_field_part(step, grid) for step in systems]
    matvec, rhs, response = _reduced_system(parts, network, estimate_iop, respond)
    starts = [step.start for step in systems]
    x0 = None if any(s is None for s in starts) else np.concatenate([_node_vector(s) for s in starts])
    v = _solve_reduced(parts, matvec, rhs, max_cg_iterations, cg_tolerance, x0)
    bounds = np.cumsum([0] + [2 * p.n_nodes for p in parts])
    updates = tuple(
        grid_result(p.xn, p.yn, v[a:b].reshape(2, -1).T, p.A, p.xy, step.cv_rms_px, grid, p.size)
        for p, step, a, b in zip(parts, systems, bounds[:-1], bounds[1:])
    )
    if not with_response:
        return updates
    rows = np.cumsum([0] + [len(p.xy) for p in parts])
    at_obs = response(v)
    return updates, tuple(at_obs[a:b] for a, b in zip(rows[:-1], rows[1:]))


@dataclass(frozen=True)
class _FieldPart:
    """One system's field block of the joint normal equations (:func:`_field_part`)."""

    xn: np.ndarray
    yn: np.ndarray
    A: object  # (n, n_nodes) sparse: the bilinear design at the observations
    xy: np.ndarray
    w: np.ndarray
    r: np.ndarray
    iop_px: np.ndarray
    size: tuple
    Nvv: tuple  # per component, (n_nodes, n_nodes) CSR: A^T W_c A + the prior + the ridge on the diagonal
    bv: np.ndarray
    AtW: list
    data: list  # per component, (n_nodes, n_nodes) sparse: A^T W_c A
    prior: object  # the prior's D^T D / τ² as factor_sum takes it
    ridge: float

    @property
    def n_nodes(self) -> int:
        return self.A.shape[1]


def _field_part(step: SystemStep, grid: GridSpec) -> _FieldPart:
    xy, r, w = (np.asarray(a, dtype=np.float64) for a in (step.xy_px, step.residuals_px, step.weights))
    size = tuple(int(s) for s in step.image_size)
    xn, yn = grid.nodes(size)
    A = bilinear_design(xn, yn, xy)
    prior = scaled_prior(len(yn), len(xn), int(step.order), step.tau_px)
    Nvv, bv, AtW, data, ridge = _field_normal(A, w, r, prior.reg, step.base.delta_px.reshape(-1, 2))
    iop = np.asarray(step.iop_px, dtype=np.float64)
    return _FieldPart(xn, yn, A, xy, w, r, iop, size, Nvv, bv, AtW, data, prior.term, ridge)


def _node_vector(values) -> np.ndarray:
    """Node values ``(H_g, W_g, 2)`` as the solve's vector: the x components, then the y components."""
    return np.asarray(values, dtype=np.float64).reshape(-1, 2).T.ravel()


def _reduced_system(parts, network: Network, estimate_iop: bool, respond: Respond):
    """The stacked node values' system with the responding parameters eliminated: its product and right side.

    And ``v -> J dθ(v)`` ``(n, 2)``: the responding parameters' step given the node values' and its effect at
    the observations.
    """
    iop_cols = 0 if estimate_iop else 3 * network.n_systems
    held = slice(network.point_col if respond is Respond.POINTS else iop_cols, None)
    J = network.J[:, held]
    w, r = (np.concatenate([getattr(p, a) for p in parts]) for a in ("w", "r"))
    Jt = J.T.tocsr()
    solve_theta, b_theta = _orientation_inverse(J, w, r, network, held, Jt)
    n_obs = len(w)
    Nvt, Ntv = _coupling(parts, J, Jt)
    Nvv = [M for p in parts for M in p.Nvv]  # the field blocks, in the node vector's order
    # the gauge is held only where the orientation, which could carry it, responds
    G = None
    if respond is Respond.ORIENTATION:
        G = dense_block_diag(
            *(np.sqrt(k) * g for g, k in (_gauge_penalty(p.A, p.xy, p.w, p.iop_px, estimate_iop) for p in parts))
        )

    def matvec(v):
        # unrefined: the refinement changes the product by parts in 1e-9, far below the conjugate gradients' tolerance
        reduced = _block_product(Nvv, v) - Nvt(solve_theta(Ntv(v), refine=False))
        return reduced if G is None else reduced + G.T @ (G @ v)

    def response(v):
        return (J @ solve_theta(b_theta - Ntv(v))).reshape(2, n_obs).T

    return matvec, np.concatenate([p.bv for p in parts]) - Nvt(solve_theta(b_theta)), response


def _coupling(parts, J, Jt=None):
    """The products ``y -> N_vθ y`` and ``v -> N_θv v`` of the fields' coupling to the orientation, ``Σ A^T W J``.

    Through ``J`` and each system's ``A^T W`` per component, never formed: the coupling matrix has a row per node
    and component with a column for every pose and bead its observations see (2.6 times the nonzeros of ``J`` and
    the ``A^T W`` together, measured on 40 exposures), so its products cost about twice the factors' and its
    assembly more than the conjugate gradients' products with it. ``J``'s rows are the observations' x rows, then
    their y rows, system by system in each; the node vector is each system's x components, then its y ones.
    ``Jt``: ``J^T`` in CSR, when at hand.
    """
    n_obs = J.shape[0] // 2
    Jt = J.T.tocsr() if Jt is None else Jt
    bounds = np.cumsum([0] + [len(p.xy) for p in parts])
    # (rows of J, rows of the node vector, A^T W, W A) per system and component, in the node vector's order
    blocks, start = [], 0
    for p, a, b in zip(parts, bounds[:-1], bounds[1:]):
        for c in (0, 1):
            rows, nodes = slice(c * n_obs + a, c * n_obs + b), slice(start, start + p.n_nodes)
            blocks.append((rows, nodes, p.AtW[c], p.AtW[c].T))
            start += p.n_nodes

    def to_fields(y):
        Jy = J @ y
        return np.concatenate([AtW @ Jy[rows] for rows, _, AtW, _ in blocks], axis=0)

    def to_orientation(v):
        z = np.empty((J.shape[0],) + v.shape[1:])
        for rows, nodes, _, WA in blocks:
            z[rows] = WA @ v[nodes]
        return Jt @ z

    return to_fields, to_orientation


def _block_product(blocks, v: np.ndarray) -> np.ndarray:
    """The block-diagonal matrix of the square CSR ``blocks`` times ``v`` ``(n, ...)``, block by block.

    Each row sums its entries in their stored order, as the block-diagonal matrix's product would: the same numbers
    without assembling it.
    """
    bounds = np.cumsum([0] + [M.shape[0] for M in blocks])
    return np.concatenate([M @ v[a:b] for M, a, b in zip(blocks, bounds[:-1], bounds[1:])], axis=0)


def _sorted(M) -> csr_matrix:
    """``M`` in CSR with each row's entries in increasing columns (as a conversion from CSC would leave them)."""
    M = M.tocsr()
    M.sort_indices()
    return M


def _field_normal(A, w, r, reg, base_v):
    """The field's block of the joint normal equations, its right-hand side, ``A^T W`` and ``A^T W A`` per component.

    And the ridge: ``reg`` is the prior's ``D^T D / τ²``; a tiny ridge keeps nodes far from all data determined.
    """
    n_nodes = A.shape[1]
    ridge = 1e-10 * max(float(w.max()), 1.0)
    AtW = [A.T.multiply(w[:, c]).tocsr() for c in range(2)]
    data = [AtW[c] @ A for c in range(2)]
    Nvv = tuple(_sorted(data[c] + reg + diags(np.full(n_nodes, ridge), format="csr")) for c in range(2))
    bv = np.concatenate([AtW[c] @ r[:, c] - reg @ base_v[:, c] for c in range(2)])
    return Nvv, bv, AtW, data, ridge


def _orientation_inverse(J, w, r, network: Network, held: slice, Jt=None):
    """``(x, refine) -> N_θθ^-1 x`` (``refine``: with a step of iterative refinement) and ``J^T W r``.

    ``N_θθ = J^T W J`` plus the datum (a unit curvature along each similarity mode, in the
    Jacobi-scaled problem: the data's gradient along them is nil, so they stay put) and
    the affine hold ``κ |B^T (P + dP) - B^T P_nominal|²``.
    With the points alone responding, ``N_θθ`` is the beads' 3x3 blocks and the hold's rank-5 term
    (:func:`_points_inverse`). ``Jt``: ``J^T`` in CSR, when at hand.
    """
    Jt = J.T.tocsr() if Jt is None else Jt
    if held.start == network.point_col:
        return _points_inverse(J, Jt, w, r, network)
    wf, rf = w.T.ravel(), r.T.ravel()
    JW = _row_scaled(J, wf)
    N = _normal_matrix(Jt, JW)
    b = JW.T @ rf
    # the Jacobi scaling of the data's normal matrix (the stiff affine hold would swamp the points' diagonal)
    d = np.sqrt(np.maximum(N.diagonal(), 1e-300))
    if network.affine is not None:
        kappa = AFFINE_STIFFNESS * float(np.max(N.diagonal()[network.point_col - held.start :]))
        F = network.affine[held]
        b = b - kappa * F @ network.affine_gap_mm
    E = d[:, None] * network.datum[held]
    E = E / np.linalg.norm(E, axis=0)
    # the low-rank terms of the Jacobi-scaled matrix: the datum, and the affine hold (on the beads' columns)
    U = E if network.affine is None else np.hstack([E, np.sqrt(kappa) * F / d[:, None]])
    solve = _bordered_inverse(_jacobi_scaled(N, 1.0 / d), U, network.point_col - held.start)

    def solve_theta(x, refine=True):
        scale = d.reshape(d.shape + (1,) * (np.ndim(x) - 1))
        return solve(x / scale, refine) / scale

    return solve_theta, b


def _bordered_inverse(B: np.ndarray, U: np.ndarray, k: int):
    """``(x, refine) -> (B + diag(ridge) + U U^T)^-1 x``, the beads eliminated first (as in the adjustment's Schur).

    ``refine``: with a step of iterative refinement.

    ``B`` ``(n, n)`` the Jacobi-scaled normal matrix, whose beads' block (from column ``k``) is block diagonal in 3x3
    (each observation sees one bead); the ridge ``POINT_RIDGE`` on that block, for what no data fix beyond the datum:
    the depth of a bead one exposure saw (the data's gradient along it is nil too). Not on the poses and the IOP:
    their weakest combinations, which the field trades against, sit far below any ridge that would make a difference.
    ``U`` ``(n, m)`` the datum and the affine hold. The beads' block with its part of ``U U^T`` is inverted by
    Woodbury's identity on the 3x3 blocks, which leaves a dense Cholesky factor of the poses and the IOP alone (a
    Cholesky factor of the whole in another order): a few percent of the whole's, and each solve a fraction.
    """
    blocks = _bead_blocks(B[k:, k:])
    blocks[:, np.arange(3), np.arange(3)] += POINT_RIDGE
    ridge = np.where(np.arange(B.shape[0]) >= k, POINT_RIDGE, 0.0)
    try:
        blocks_inv = np.linalg.inv(blocks)
    except np.linalg.LinAlgError as exc:
        raise _singular_orientation() from exc

    block_solve = _block_solver(blocks_inv)
    U_p = U[k:]
    BiU = block_solve(U_p)
    try:
        core = cho_factor(np.eye(U.shape[1]) + U_p.T @ BiU)
        C = B[:k, k:].toarray() + U[:k] @ U_p.T

        def beads_solve(y):
            return block_solve(y) - BiU @ cho_solve(core, BiU.T @ y, check_finite=False)

        PiCt = beads_solve(C.T)
        factor = cho_factor(B[:k, :k].toarray() + U[:k] @ U[:k].T - C @ PiCt)
    except np.linalg.LinAlgError as exc:
        raise _singular_orientation() from exc

    def solve_once(y):
        t = beads_solve(y[k:])
        x_c = cho_solve(factor, y[:k] - C @ t, check_finite=False)
        return np.concatenate([x_c, t - PiCt @ x_c])

    def solve(y, refine=True):
        # one step of iterative refinement against the sparse matrix: Woodbury's identity on the stiff hold loses
        # digits that a Cholesky factor of the whole keeps
        x = solve_once(y)
        if not refine:
            return x
        r = y - (B @ x + (ridge * x.T).T + U @ (U.T @ x))
        return x + solve_once(r)

    return solve


def _singular_orientation() -> EstimationError:
    return EstimationError(
        "the refinement's field step: the orientation's normal matrix is singular (an exposure with too few "
        "observations left?); raise [adjust] min_beads_per_exposure to leave such exposures out"
    )


def _points_inverse(J, Jt, w, r, network: Network):
    """:func:`_orientation_inverse` when the points alone respond: their 3x3 blocks, less a Woodbury term.

    Each observation sees one bead, so ``J^T W J`` is block diagonal;
    the affine hold adds ``κ F F^T`` (rank 5), inverted by Woodbury's identity. The same matrix as
    the dense path's, the ridge ``POINT_RIDGE`` on the Jacobi-scaled diagonal included (no datum:
    the points move the image), at a cost linear in the beads instead of a dense Cholesky.
    """
    wf, rf = w.T.ravel(), r.T.ravel()
    JW = _row_scaled(J, wf)
    b = JW.T @ rf
    blocks = _bead_blocks(Jt @ JW)
    diag = np.einsum("bii->bi", blocks)
    d2 = np.maximum(diag, 1e-300)
    kappa = AFFINE_STIFFNESS * float(np.max(diag)) if network.affine is not None else 0.0
    blocks[:, np.arange(3), np.arange(3)] += POINT_RIDGE * d2
    try:
        blocks_inv = np.linalg.inv(blocks)
    except np.linalg.LinAlgError as exc:
        raise EstimationError("the refinement's field step: a bead's normal block is singular") from exc

    block_solve = _block_solver(blocks_inv)
    if network.affine is None:
        return (lambda x, refine=True: block_solve(x)), b
    F = network.affine[network.point_col :]
    b = b - kappa * F @ network.affine_gap_mm
    NiF = block_solve(F)
    core = np.linalg.inv(np.eye(F.shape[1]) / kappa + F.T @ NiF)
    return (lambda x, refine=True: block_solve(x) - NiF @ (core @ (NiF.T @ x))), b


def _row_scaled(M, s: np.ndarray) -> csr_matrix:
    """``diag(s) M`` of a CSR ``M``: the numbers and layout of ``M.multiply(s[:, None]).tocsr()``, unconverted."""
    return csr_matrix((M.data * s[_row_of_entries(M)], M.indices, M.indptr), shape=M.shape)


def _normal_matrix(Jt, JW) -> csr_matrix:
    """``J^T W J`` from ``J^T`` and ``W J`` in CSR, with sorted indices: the same matrix as ``(J.T @ JW).tocsr()``.

    Each entry sums its products over the observations in the same order; a CSR product skips converting ``JW`` to
    CSC, and its unsorted rows are sorted as the CSC product's conversion would have them.
    """
    N = Jt @ JW
    N.sort_indices()
    return N


def _jacobi_scaled(N, s: np.ndarray) -> csr_matrix:
    """``diag(s) N diag(s)`` of a CSR ``N`` with sorted indices: the numbers and layout of the two sparse products.

    Each entry ``(s_i N_ij) s_j``, rounded as the products round it, in ``N``'s layout (the second product restores
    the order the first reversed).
    """
    return csr_matrix(((s[_row_of_entries(N)] * N.data) * s[N.indices], N.indices, N.indptr), shape=N.shape)


def _row_of_entries(M) -> np.ndarray:
    return np.repeat(np.arange(M.shape[0]), np.diff(M.indptr))


def _bead_blocks(N) -> np.ndarray:
    """The 3x3 diagonal blocks ``(n_beads, 3, 3)`` of the beads' block of a normal matrix (sparse, block diagonal)."""
    coo = N.tocoo()
    blocks = np.zeros((N.shape[0] // 3, 3, 3))
    np.add.at(blocks, (coo.row // 3, coo.row % 3, coo.col % 3), coo.data)
    return blocks


def _block_solver(blocks_inv: np.ndarray):
    """``x -> diag(blocks_inv) x`` for ``x`` ``(3 n_beads, ...)``: each bead's 3x3 inverse applied to its rows."""
    n_beads = len(blocks_inv)

    def block_solve(x):
        return np.einsum("bij,bj...->bi...", blocks_inv, x.reshape(n_beads, 3, *x.shape[1:])).reshape(x.shape)

    return block_solve


def _gauge_penalty(A, xy, w, iop_px, with_iop: bool):
    """``G`` ``(K, 2 n_nodes)``: the field's components at the observations along the gauge fields, and its weight.

    The weight makes each gauge mode about as stiff as the data would make it, were it not
    reproduced by the orientation.
    """
    B = gauge_basis(xy, iop_px, with_iop)
    B = B / np.sqrt(np.mean(B**2, axis=(0, 1)))
    G = np.concatenate([(A.T @ B[:, c, :]).T for c in range(2)], axis=1)
    return G, float(np.mean(w)) / max(len(xy), 1)


def _solve_reduced(parts, matvec, rhs, max_cg_iterations: int, cg_tolerance: float, x0=None):
    """The stacked node values of the reduced system, by CG preconditioned with each field block's factor, deflated.

    The product's gauge penalty is not in the preconditioner: its fields (:mod:`fluorocal.stages.learn.gauge`) are
    of degree <= 2 about the principal point, which the deflation (:func:`_deflated`) solves outright; added by
    Woodbury's identity, it left the iterations as they were.
    """
    # one factorisation per system, of the mean of its components' data terms (their weights differ by the
    # centroids' σx / σy alone: the mean preconditions both about as well as each its own, at half the factorisations)
    blocks, start = [], 0
    for p in parts:
        n = p.n_nodes
        blocks.append((slice(start, start + 2 * n), factor_sum(((p.data[0] + p.data[1]) * 0.5, p.prior), p.ridge)))
        start += 2 * n

    def field_solve(v):
        return np.concatenate([_solve_components(lu, v[at]) for at, lu in blocks], axis=0)

    precondition = _deflated(field_solve, matvec, _coarse_space(parts))
    op = LinearOperator((start, start), matvec=matvec, dtype=np.float64)
    pre = LinearOperator((start, start), matvec=precondition, dtype=np.float64)
    v, info = cg(op, rhs, x0=x0, rtol=cg_tolerance, maxiter=max_cg_iterations, M=pre)
    if info > 0:
        logger.debug("joint field step: CG stopped after %d iterations short of its tolerance", info)
    return v


def _coarse_space(parts) -> np.ndarray:
    """Orthonormal columns ``(2 n_nodes total, 12 per system)``: each system's fields of degree <= 2 in each component.

    Over the nodes, in ``((x - xp) / c, (y - yp) / c)``; zero on the other systems' nodes.
    """
    blocks = []
    for p in parts:
        xp, yp, c = p.iop_px
        x, y = np.meshgrid((p.xn - xp) / c, (p.yn - yp) / c)
        x, y = x.ravel(), y.ravel()
        monomials = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
        zero = np.zeros_like(monomials)
        blocks.append(np.block([[monomials, zero], [zero, monomials]]))
    W, _ = np.linalg.qr(dense_block_diag(*blocks))
    return W


def _deflated(precondition, matvec, W: np.ndarray):
    """The two-level preconditioner: ``precondition`` with the span of ``W`` solved exactly (BNN, Tang et al. [1]).

    ``x -> Q x + (I - Q A) M (I - A Q) x``, ``Q = W (W^T A W)^-1 W^T``, ``M`` = ``precondition``: symmetric positive
    definite, as the conjugate gradients need from any start (the one-sided A-DEF2, ``Q + (I - Q A) M``, is not; it
    needs a start of its own, and the loop's steps start from the last one's). The joint step's
    slowest modes are fields the orientation nearly reproduces and the prior does not see: smooth, of degree 2 over
    the image (the projective terms of a tilt, measured: eigenvalues of the preconditioned system 1e-4 of the
    others'). Left to the conjugate gradients, each stalled them for a dozen iterations; in the coarse space their
    part is solved outright, and the iterations halve.

    References
    ----------
    .. [1] Tang, Nabben, Vuik, Erlangga, "Comparison of two-level preconditioners derived from deflation, domain
       decomposition and multigrid methods", J. Sci. Comput. 39 (2009).
    """
    AW = matvec(W)
    try:
        coarse = cho_factor(W.T @ AW)
    except LinAlgError:  # not positive definite to rounding: the conjugate gradients without the coarse solve
        return precondition

    def apply(x):
        y = precondition(x - AW @ cho_solve(coarse, W.T @ x, check_finite=False))
        return y + W @ cho_solve(coarse, W.T @ x - AW.T @ y, check_finite=False)

    return apply


def _solve_components(lu, v: np.ndarray) -> np.ndarray:
    """``lu``'s solve of both components of ``v`` ``(2 n, ...)`` (the x components, then the y ones) at once."""
    n = v.shape[0] // 2
    columns = v.reshape(2, n, -1).transpose(1, 0, 2).reshape(n, -1)  # shape (n, 2 k)
    return lu.solve(columns).reshape(n, 2, -1).transpose(1, 0, 2).reshape(v.shape)


__all__ = ["SystemStep", "fit_grid_jointly", "fit_grids_jointly"]
