"""Uncertainty of the interior orientation and of the field, with the field estimated jointly (issue 14).

The adjustment's covariance holds the correction field fixed: conditional on
the field, its σ of the principal point and of ``c`` is far too small, since a
free field can trade a principal-point shift (and a change of ``c``) against
the poses. :func:`joint_uncertainty` gives the marginal covariance over the
joint problem instead, the IOP, the poses, the object points *and* the
gridded field, linearised at the solution:

- the field's node values ``v`` carry the gridded fit's smoothness prior
  ``|D v|² / τ²`` (:func:`fluorocal.stages.learn.grid.difference_operator`;
  the ``τ`` and order the cross-validation chose), so the covariance is the
  posterior one and includes the prior's smoothing, not only the noise;
- the field is held to the gauge the learning imposes
  (:mod:`fluorocal.stages.learn.gauge`): its least-squares component at the
  training observations along a principal-point shift, a scaling about the
  principal point and the three displacement fields of a common camera
  rotation is zero. This is the convention that makes the IOP identifiable:
  the reported IOP is the pinhole under it, and its error is measured against
  the true IOP expressed in the same convention (the true configuration moved
  by an IOP change and a common camera rotation until its correction has no
  gauge component, :func:`convention_truth`);
- the IOP's σ leaves the phantom's shape free, as the final adjustment that
  estimates the IOP does; the field's σ holds the phantom's five affine shape
  modes beyond a similarity at the design's when the refinement that learned
  the field held them (``LearnParams.affine_datum``).

The observations' weights are the adjustment's: the inverse of each centroid's covariance (its σx, σy
and x-y correlation ρ), times its t-weight over the adjustment's variance factor.
Each system is treated on its own with free poses per exposure: a biplanar
pair's ROP (which ties them) is not used, so its σ is slightly conservative.

Linear algebra: with ``S = A^T W A + D^T D / τ²`` (sparse, per component) and
the gauge ``C v = 0``, the field given the orientation has the constrained
inverse ``S_c^-1 = S^-1 - S^-1 C^T (C S^-1 C^T)^-1 C S^-1``; the orientation's
marginal normal matrix is ``J^T W J - M^T S_c^-1 M`` with ``M = A^T W J``
(the field eliminated), bordered by the 7 inner constraints of the free
network, and the field's marginal covariance is
``S_c^-1 + G Cov_θ G^T``, ``G = S_c^-1 M``. ``S`` is banded, so its solves and
the diagonal of ``S^-1`` are dense block work on a block-bidiagonal Cholesky
factor (:mod:`fluorocal.stages.learn.blocktri`); ``M`` is sparse (a bead's
columns touch only the nodes around its observations), so the forward substitutions
start each column at its first non-zero block, made dense a block of rows at a time.
``M^T S_c^-1 M`` is ``|Z|²`` with ``Z = Π L^-1 M`` (``S = L L^T``, ``Π`` the projector
of the gauge: ``S_c^-1 = L^-T Π L^-1``), one symmetric product; the orientation's
marginal normal matrix is inverted from Bunch-Kaufman ``L_H D L_H^T`` factors
(``P`` their permutation), and the field's variance from them: ``diag(G Cov_θ G^T)``,
``G = L^-T Z``, is each row's ``D^-1`` quadratic form of ``L^-T (Z P L_H^-T)``, a
triangular product and a backward substitution done in place in one array of
``Z``'s size. The work is three products of ``Z``'s size by its width (the symmetric
one, the triangular one, and the substitution's, by the bandwidth twice): the
sparsity of ``M`` is spent by then (``L^-1`` fills each column below its first row).

Numerics: ``J^T W J - M^T S_c^-1 M`` is nearly singular (Jacobi-scaled, its smallest
eigenvalues ~1e-15 and ~1e-12 of its largest on a 40-exposure set: a bead's
coordinates, and a common turn of the cameras, that the field nearly mimics), so the σ
are determined in float64 only to ~1e-4 relative (the same problem with its
parameters in another order gives σ that differ by 1e-5 to 1e-4), and it is
positive definite only to rounding: a Cholesky factor of it fails in some orders of
its parameters, the symmetric indefinite factors do not. Its data term must be
symmetric to the last bit: a symmetric factor reads one triangle, and the rounding
asymmetry of a general product ``M^T (S_c^-1 M)`` (~1e-12 of the scaled matrix) moved a
one-triangle inverse's IOP σ by a factor of two there.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from fluorocal.stages.adjust.collinearity import whiten, whitening
from fluorocal.stages.adjust.covariance import covariance_factor
from fluorocal.stages.artifacts import freeze
from fluorocal.stages.field import bilinear_design
from fluorocal.stages.learn.blocktri import block_cholesky
from fluorocal.stages.learn.gauge import gauge_basis
from fluorocal.stages.learn.grid import prior_normal
from fluorocal.stages.learn.network import linearised_network
from fluorocal.stages.learn.nogil import inverse_lower, trmm
from fluorocal.stages.learn.params import FieldGauge
from fluorocal.stages.learn.threads import each_system
from scipy.linalg import ldl
from scipy.sparse import bmat, csr_matrix, diags, identity, issparse, vstack

# rows of the field's dense work done at a time in place (no second array of its size)
_ROWS = 512


@dataclass(frozen=True)
class JointUncertainty:
    """One system's uncertainty with the field estimated jointly.

    Attributes
    ----------
    iop_cov_px2 : (3, 3) float64 ndarray, px²
        Covariance of ``(xp, yp, c)`` over the joint problem (IOP, poses, points, field).
    iop_std_px : (3,) float64 ndarray, px
    node_std_px : (H_g, W_g, 2) float64 ndarray, px
        Standard deviation of each node's ``(Δx, Δy)`` over the joint problem (the phantom's affine shape
        held when the refinement that learned the field held it).
    conditional_iop_std_px : (3,) float64 ndarray, px
        The same problem with the field held fixed (what the adjustment reports), for comparison.
    """

    iop_cov_px2: np.ndarray
    iop_std_px: np.ndarray
    node_std_px: np.ndarray
    conditional_iop_std_px: np.ndarray

    def __post_init__(self):
        freeze(self)

    @property
    def field_std_px(self) -> np.ndarray:
        """``(H_g, W_g)`` px: per node, the RMS of the two components' σ (the field file's ``sigma_px``)."""
        return np.sqrt(np.mean(self.node_std_px**2, axis=-1))


@dataclass(frozen=True)
class _Network:
    """One system's linearised orientation (:class:`Network`) and its observations' weight matrix."""

    J: csr_matrix
    w: np.ndarray  # shape (2n,): the diagonal of the weight matrix
    w_xy: np.ndarray  # shape (n,): its x-y entries (the centroids' correlation)
    datum: np.ndarray  # shape (n_theta, 7)
    affine: np.ndarray | None  # shape (n_theta, 5): the phantom's affine shape modes, or None


def _network(adj, observations, rows, system: int, shape_nominal_mm=None) -> _Network:
    """The Jacobian of system ``system``'s observations ``rows`` by ``(IOP, poses, points)`` at ``adj``, weighted."""
    net = linearised_network(adj, observations, rows, system, shape_nominal_mm)
    # each observation's weight matrix: the inverse of its (σx, σy, ρ) covariance, times its t-weight over the
    # adjustment's variance factor
    # W = L^-T L^-1 with L^-1 = [[l11, 0], [l21, l22]], the adjustment's whitening
    l11, l21, l22 = whitening(observations.sigma_px[rows]).T
    scale = adj.weight[rows] / variance_factor(adj, observations)
    w = np.concatenate([scale * (l11**2 + l21**2), scale * l22**2])
    return _Network(net.J, w, scale * l21 * l22, net.datum, net.affine)


def variance_factor(adj, observations) -> float:
    """The adjustment's factor of its cofactors (Huber's sandwich for the t, :func:`covariance_factor`).

    Recomputed from its residuals, t-weights and scale, so that the field held fixed gives the
    adjustment's own σ.
    """
    used = adj.used
    r = adj.residual_px[used]
    # squared Mahalanobis norm of each residual under (σx, σy, ρ)
    s = np.sum(whiten(whitening(observations.sigma_px[used]), r) ** 2, axis=1)
    return covariance_factor(s, adj.weight[used], adj.nu, adj.t_scale**2, adj.n_parameters - 7, adj.dof)


def joint_uncertainty(
    adj,
    observations,
    rows: np.ndarray,
    system: int,
    field,
    *,
    tau_px: float,
    order: int,
    shape_nominal_mm: np.ndarray | None = None,
) -> JointUncertainty:
    """The IOP's and the field's covariance over the joint problem (module docstring).

    Parameters
    ----------
    adj : Adjustment
        The final adjustment (the field held at ``field``).
    observations : Observations
    rows : (n,) int ndarray
        The observations of ``system`` the field was learned from (used by the adjustment).
    system : int
    field : CorrectionField
        The learned gridded field of ``system`` (its nodes).
    tau_px, order : float, int
        The smoothness prior of the gridded fit (``GridCvReport.tau_px``, ``.order``).
    shape_nominal_mm : (n_beads, 3) float64 ndarray, mm, optional
        The design coordinates of ``adj.bead_id``: the field's σ then holds the phantom's affine shape
        at the design's (as the refinement with ``affine_datum`` does); the IOP's never does.

    Notes
    -----
    The IOP must have been estimated (it is a parameter here, and the gauge includes its fields).

    Returns
    -------
    JointUncertainty
    """
    net = _network(adj, observations, rows, system, shape_nominal_mm)
    xy = observations.xy_px[rows]
    xn, yn = field.x_nodes_px, field.y_nodes_px
    A = bilinear_design(xn, yn, xy)
    n = len(rows)
    DtD = prior_normal(len(yn), len(xn), int(order)) / float(tau_px) ** 2
    s_inv = _field_inverse(A, net.w.reshape(2, n), net.w_xy, DtD)
    W = diags(net.w) + diags([net.w_xy, net.w_xy], [n, -n])  # (2n, 2n): x rows then y rows
    JW = (W @ net.J).tocsr()
    # (2 n_nodes, n_theta), sparse: a bead's columns touch only the nodes around its observations
    M = vstack([A.T @ JW[c * n : (c + 1) * n] for c in range(2)]).tocsr()
    theta = _by_first_node(M, A.shape[1])
    net = replace(
        net, J=net.J[:, theta], datum=net.datum[theta], affine=None if net.affine is None else net.affine[theta]
    )
    JW, M = JW[:, theta], M[:, theta]
    # the gauge C v = 0: the field's components at the observations along the gauge fields, (K, 2 n_nodes)
    B = gauge_basis(xy, adj.iop_px[system], True)
    C = np.concatenate([(A.T @ B[:, c, :]).T for c in range(2)], axis=1)
    C /= np.linalg.norm(C, axis=1, keepdims=True)
    # S_c^-1 = L^-T Π L^-1 with Π = I - V (V^T V)^-1 V^T, V = L^-1 C^T: M^T S_c^-1 M = |Π L^-1 M|², symmetric
    V = s_inv.forward(C.T)
    CY_inv = np.linalg.inv(V.T @ V)
    Z = _projected(s_inv.forward(M), V, CY_inv)
    H_cond = (net.J.T @ JW).toarray()
    scale = float(np.mean(np.diag(H_cond)))
    border = scale * net.datum @ net.datum.T
    # the IOP as the final adjustment estimates it: the phantom's shape free
    cov = _symmetric_inverse(H_cond - Z.T @ Z + border)
    iop_cov = cov.quadratic(np.eye(len(H_cond), 3))
    # the field as the refinement learned it: with the phantom's affine shape held, if it was (the Gaussian
    # conditioned on F^T θ = 0: cov - cov F (F^T cov F)^-1 F^T cov), by rows of G = S_c^-1 M = L^-T Z:
    # diag(G cov G^T) less that term; with cov = P L_H^-T D^-1 L_H^-1 P^T, each row's D^-1 form of L^-T Z P L_H^-T
    node_var = -_held_affine_variance(cov, s_inv, Z, net.affine) if net.affine is not None else np.zeros(len(Z))
    node_var += s_inv.backward_quadratic(cov.right_half(Z, overwrite=True), cov.D_inv)  # Z overwritten
    Y = s_inv.backward(V)  # S^-1 C^T (V overwritten)
    node_var += s_inv.diagonal() - np.sum((Y @ CY_inv) * Y, axis=1)
    # the IOP's block of the conditional covariance (the field held): three columns of the inverse
    cov_cond = np.linalg.solve(H_cond + border, np.eye(len(H_cond), 3))[:3]
    shape = (len(yn), len(xn))
    node_std = _std(node_var).reshape(2, *shape).transpose(1, 2, 0)
    return JointUncertainty(iop_cov, _std(np.diag(iop_cov)), node_std, _std(np.diag(cov_cond)))


def _projected(Z: np.ndarray, V: np.ndarray, CY_inv: np.ndarray, rows: int = _ROWS) -> np.ndarray:
    """``Π Z = Z - V (V^T V)^-1 V^T Z`` in place, a block of ``rows`` at a time (no second array of ``Z``'s size)."""
    T = CY_inv @ (V.T @ Z)
    for lo in range(0, len(Z), rows):
        Z[lo : lo + rows] -= V[lo : lo + rows] @ T
    return Z


def _held_affine_variance(cov, s_inv, Z: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """``diag(G cov F (F^T cov F)^-1 F^T cov G^T)`` with ``G = L^-T Z``: what holding ``F^T θ = 0`` takes."""
    cF = cov.solve(affine)
    GcF = s_inv.backward(Z @ cF)
    return np.sum(GcF * np.linalg.solve(affine.T @ cF, GcF.T).T, axis=1)


def _by_first_node(M, n_nodes: int) -> np.ndarray:
    """The orientation's parameters ``(n_theta,)`` in the order of the first node their columns of ``M`` touch.

    The IOP's three stay first (where they are reported). The field's solves start each column at its first non-zero
    block (:meth:`fluorocal.stages.learn.blocktri.BlockCholesky.forward`) and take the columns in this order without
    copying them: a node's row is ``2 i + c`` in the coupled factor's order, ``i`` in a component's.
    """
    Mc = M.tocsc()
    first = np.full(Mc.shape[1], n_nodes)
    touched = np.diff(Mc.indptr) > 0
    first[touched] = np.minimum.reduceat(Mc.indices % n_nodes, Mc.indptr[:-1][touched])
    first[:3] = -1
    return np.argsort(first, kind="stable")


def _std(var: np.ndarray) -> np.ndarray:
    """Standard deviations of variances ``var``.

    NaN (never 0, a claim of certainty) where rounding left one below zero: a parameter the data barely determine.
    """
    return np.where(var >= 0, np.sqrt(np.abs(var)), np.nan)


@dataclass(frozen=True)
class _FieldInverse:
    """``S^-1`` of the node values ``[x nodes; y nodes]`` from block Cholesky factors (:func:`_field_inverse`)."""

    factors: tuple  # of BlockCholesky: per component (one, twice, when equal), or one of both, interleaved
    n_nodes: int

    def _interleaved(self) -> np.ndarray | None:
        """The coupled factor's order of the node values (:func:`_interleaving`), None for per-component factors."""
        return _interleaving(self.n_nodes) if len(self.factors) == 1 else None

    def forward(self, X) -> np.ndarray:
        """``L^-1 X`` for ``X`` ``(2 n_nodes, k)``, dense or sparse, with ``S = L L^T`` in the factors' order of rows.

        ``S^-1 = L^-T L^-1``: ``X^T S^-1 X`` is ``|L^-1 X|²`` whatever that order.
        """
        n, order = self.n_nodes, self._interleaved()
        if order is None:
            return np.concatenate([f.forward(X[c * n : (c + 1) * n]) for c, f in enumerate(self.factors)])
        return self.factors[0].forward(X.tocsr()[order] if issparse(X) else X[order])

    def backward(self, Y: np.ndarray) -> np.ndarray:
        """``L^-T Y`` for ``Y`` ``(2 n_nodes, k)`` in the factors' order of rows (overwritten), in node order."""
        n, order = self.n_nodes, self._interleaved()
        if order is None:
            return np.concatenate(
                [f.backward(Y[c * n : (c + 1) * n], overwrite=True) for c, f in enumerate(self.factors)]
            )
        out = np.empty(Y.shape)
        out[order] = self.factors[0].backward(Y, overwrite=True)
        return out

    def backward_quadratic(self, Y: np.ndarray, B) -> np.ndarray:
        """Each row's ``g B g^T`` ``(2 n_nodes,)`` of ``L^-T Y`` (``Y`` in the factors' order, overwritten), node order.

        ``B``: a :class:`_BlockDiagonal`. In place: no array of ``Y``'s size is made (the field's variance of a
        40-exposure set: ``(8450, 1716)``, 116 MB).
        """
        n, order = self.n_nodes, self._interleaved()
        if order is None:
            for c, f in enumerate(self.factors):
                f.backward(Y[c * n : (c + 1) * n], overwrite=True)
        else:
            Y = self.factors[0].backward(Y, overwrite=True)
        values = B.row_quadratics(Y)
        if order is None:
            return values
        out = np.empty(len(Y))
        out[order] = values
        return out

    def diagonal(self) -> np.ndarray:
        """The diagonal ``(2 n_nodes,)`` of ``S^-1`` (once when the components share a factor)."""
        order = self._interleaved()
        if order is not None:
            out = np.empty(2 * self.n_nodes)
            out[order] = self.factors[0].diag_inverse()
            return out
        first = self.factors[0].diag_inverse()
        return np.concatenate([first, first if self.factors[1] is self.factors[0] else self.factors[1].diag_inverse()])


def _interleaving(n_nodes: int) -> np.ndarray:
    """Indices into ``[x nodes; y nodes]`` putting each node's two components side by side (``2 i + c``)."""
    return np.arange(2 * n_nodes).reshape(2, -1).T.ravel()


def _field_inverse(A, w: np.ndarray, w_xy: np.ndarray, DtD) -> _FieldInverse:
    """``S = A^T W A + D^T D / τ²`` over both components, factored in dense blocks of its bandwidth.

    ``w`` ``(2, n)`` the weight matrix's diagonal, ``w_xy`` ``(n,)`` its x-y entries. ``S`` is banded (row-major
    nodes, :mod:`fluorocal.stages.learn.blocktri`): per component when ``w_xy`` is zero (one factor when the
    components weigh alike), else the pair coupled, each node's two components adjacent.
    """
    n_nodes = A.shape[1]
    ridge = 1e-10 * max(float(w.max()), 1.0)  # as the gridded fit's: nodes far from all data stay determined
    same = np.array_equal(w[0], w[1])
    S = [A.T.multiply(w[c]) @ A + DtD + ridge * identity(n_nodes) for c in range(2 - same)] * (1 + same)
    if np.any(w_xy):
        cross = A.T.multiply(w_xy) @ A
        order = _interleaving(n_nodes)
        return _FieldInverse((block_cholesky(bmat([[S[0], cross], [cross, S[1]]]).tocsr()[order][:, order]),), n_nodes)
    factors = [block_cholesky(S[c]) for c in range(2 - same)]
    return _FieldInverse(tuple(factors * (1 + same)), n_nodes)


@dataclass(frozen=True)
class _BlockDiagonal:
    """A symmetric block diagonal matrix ``B`` of 1x1 and 2x2 blocks (the inverse of the ``D`` of ``ldl``).

    A quadratic form's diagonal in it is one pass over the operand, without the product ``G B`` (a second
    array of the operand's size: ``(8450, 1716)``, 116 MB, for the field's variance on a 40-frame set).
    """

    diagonal: np.ndarray  # (n,)
    first: np.ndarray  # (m,) the first row of each 2x2 block
    off: np.ndarray  # (m,) the off-diagonal entry of each 2x2 block

    def __matmul__(self, X: np.ndarray) -> np.ndarray:
        """The product with a 2-D ``X`` ``(n, k)``."""
        out = self.diagonal[:, None] * X
        out[self.first] += self.off[:, None] * X[self.first + 1]
        out[self.first + 1] += self.off[:, None] * X[self.first]
        return out

    def row_quadratics(self, G: np.ndarray) -> np.ndarray:
        """Each row's ``g B g^T`` ``(k,)`` of ``G`` ``(k, n)``: the diagonal of ``G B G^T``."""
        out = np.einsum("j,ij,ij->i", self.diagonal, G, G)
        return out + 2.0 * np.einsum("j,ij,ij->i", self.off, G[:, self.first], G[:, self.first + 1])


@dataclass(frozen=True)
class _SymmetricInverse:
    """``H^-1`` of a symmetric ``(n, n)`` ``H`` from its Bunch-Kaufman factors ``H = P L D L^T P^T``.

    ``H^-1 = P L^-T D^-1 L^-1 P^T``: a quadratic form ``X H^-1 X^T`` is ``E D^-1 E^T`` with ``E = X P L^-T``,
    a product by a triangular matrix, and ``D`` block diagonal (1x1 and 2x2 blocks). A factor and a triangular
    inverse cost a third of a general inverse.
    """

    L_inv: np.ndarray  # (n, n) unit lower-triangular: the inverse of L
    D_inv: _BlockDiagonal  # the inverse of D
    perm: np.ndarray  # (n,) P^T X is X[perm]

    def right_half(self, X: np.ndarray, *, overwrite: bool = False) -> np.ndarray:
        """``X P L^-T`` ``(k, n)`` for ``X`` ``(k, n)``: ``X H^-1 X^T`` is its ``D^-1`` quadratic form.

        BLAS trmm in place in ``X P`` (C order), on its Fortran view: ``(X P L^-T)^T = L^-1 (X P)^T``. With
        ``overwrite``, ``X`` (C order) holds ``X P`` and then the result: its columns permuted a block of rows at
        a time.
        """
        if overwrite:
            E = X
            for lo in range(0, len(E), _ROWS):
                E[lo : lo + _ROWS] = np.take(E[lo : lo + _ROWS], self.perm, axis=1)
        else:
            E = np.take(np.asarray(X, dtype=np.float64), self.perm, axis=1)
        return trmm(self.L_inv, E.T, side=0, lower=1, trans_a=0, diag=1).T

    def quadratic(self, X: np.ndarray) -> np.ndarray:
        """``X^T H^-1 X`` ``(k, k)`` for ``X`` ``(n, k)``, symmetric."""
        E = self.right_half(X.T)
        Q = E @ (self.D_inv @ E.T)
        return 0.5 * (Q + Q.T)

    def row_quadratics(self, X: np.ndarray) -> np.ndarray:
        """The diagonal ``(k,)`` of ``X H^-1 X^T`` for ``X`` ``(k, n)``."""
        return self.D_inv.row_quadratics(self.right_half(X))

    def solve(self, X: np.ndarray) -> np.ndarray:
        """``H^-1 X`` for ``X`` ``(n, k)``."""
        out = np.empty(X.shape)
        out[self.perm] = self.L_inv.T @ (self.D_inv @ self.right_half(X.T).T)
        return out


def _symmetric_inverse(H: np.ndarray) -> _SymmetricInverse:
    """:class:`_SymmetricInverse` of a symmetric ``H``."""
    lu, d, perm = ldl(H, lower=True)
    L_inv = inverse_lower(lu[perm], unit=True)  # lu[perm] is unit lower triangular
    return _SymmetricInverse(np.asfortranarray(L_inv), _block_diagonal_inverse(d), perm)


def _block_diagonal_inverse(d: np.ndarray) -> _BlockDiagonal:
    """The inverse of a block diagonal ``d`` ``(n, n)`` of 1x1 and 2x2 blocks (the ``D`` of ``ldl``).

    A 2x2 block's diagonal may be zero (a Bunch-Kaufman pivot of an indefinite matrix): only the 1x1 blocks
    are inverted entry by entry.
    """
    n = len(d)
    first = np.flatnonzero(np.diag(d, -1))  # the first row of each 2x2 block
    single = np.setdiff1d(np.arange(n), np.concatenate([first, first + 1]))
    a, b, c = d[first, first], d[first + 1, first], d[first + 1, first + 1]
    det = a * c - b * b
    diagonal = np.empty(n)
    diagonal[single] = 1.0 / d[single, single]
    diagonal[first], diagonal[first + 1] = c / det, a / det
    return _BlockDiagonal(diagonal, first, -b / det)


def learned_uncertainty(
    adj, observations, rows, trained, grids, memory, params, *, estimate_iop: bool, nominal_shape_mm, workers: int = 1
) -> tuple | None:
    """Each system's :class:`JointUncertainty` after the learning's gridded refinement, or None where undefined.

    Defined when the fields are gauge-fixed (``params.field_gauge`` ``FieldGauge.ORIENTATION``) and the IOP
    estimated: the recommended loop. ``rows`` per system, ``trained`` ``(N,)`` the observations the
    fields learned from, ``memory`` per system the loop's regression memory (the smoothness prior's
    ``tau_px`` and ``cv.order``); ``nominal_shape_mm`` the design coordinates of ``adj.bead_id``
    (used when ``params.affine_datum`` held the phantom's affine shape). The systems side by side in up to
    ``workers`` threads (:func:`~fluorocal.stages.learn.threads.each_system`).
    """
    if params.field_gauge is not FieldGauge.ORIENTATION or not estimate_iop or any(m.tau_px is None for m in memory):
        return None
    used = trained & adj.used
    shape = nominal_shape_mm if params.affine_datum else None

    def system(s: int) -> JointUncertainty:
        r, m = rows[s], memory[s]
        return joint_uncertainty(
            adj, observations, r[used[r]], s, grids[s], tau_px=m.tau_px, order=m.cv.order, shape_nominal_mm=shape
        )

    return each_system(system, len(rows), workers)


def with_field_std(field, uncertainty: JointUncertainty):
    """``field`` with its node σ (``sigma_px``) replaced by the joint one (RMS of the components)."""
    return field.with_delta(field.delta_px, sigma_px=uncertainty.field_std_px)


def _moved_ideal(ideal_px, iop_px, change) -> np.ndarray:
    """Ideal points ``(m, 2)`` px of the same rays under the IOP ``iop + change[:3]``, every camera rotated alike.

    ``change[3:]`` is the common camera rotation as a rotation vector times ``c`` (px, so that all six
    are of one scale): ``p <- R p`` for every camera ray ``p``, exactly, not to first order.
    """
    from scipy.spatial.transform import Rotation

    xp, yp, c = (float(v) for v in iop_px)
    rays = np.column_stack([(ideal_px[:, 0] - xp) / c, (ideal_px[:, 1] - yp) / c, np.ones(len(ideal_px))])
    rays = rays @ Rotation.from_rotvec(np.asarray(change[3:]) / c).as_matrix().T
    new = np.asarray(iop_px, dtype=np.float64) + change[:3]
    return new[:2] + new[2] * rays[:, :2] / rays[:, 2:3]


def convention_truth(xy_px, true_correction, true_iop_px):
    """A known IOP and correction expressed in the gauge convention, exactly: ``(iop (3,) px, component)``.

    The true configuration moved along the gauge: the IOP changed and every camera rotated alike by the
    six parameters that leave the moved correction ``Δ'(x) = x - ideal'(x)`` no least-squares component,
    at ``xy_px``, along the gauge fields at the moved IOP (:func:`fluorocal.stages.learn.gauge.gauge_basis`),
    as the learning's gauge requires of its field. It reproduces the projections exactly: the IOP change
    and the rotation act on the *ideal* point ``x - Δ(x)`` of each ray (a projective map), which the gauge's
    first-order fields at the measured point only approximate; moving that approximation into the IOP by
    an adjustment leaves a systematic misfit (a few hundredths of a pixel at a strong distortion) that
    shifts the IOP along the weakly determined principal point by tens of pixels.

    Parameters
    ----------
    xy_px : (n, 2) float64 ndarray, px
        The distorted points the gauge is taken at (the training observations the field learned from).
    true_correction : callable
        ``xy (m, 2) -> Δ(xy) (m, 2)`` px, the true correction (distorted minus ideal).
    true_iop_px : (3,) array_like, px

    Returns
    -------
    iop_px : (3,) float64 ndarray, px
        The IOP in the convention.
    component : callable
        ``xy (m, 2) -> (m, 2)`` px, what the convention moves out of the correction: the true field in the
        convention at ``xy`` is ``Δ(xy) - component(xy)`` and the true ideal point ``ideal + component(xy)``.
    """
    from fluorocal.stages.errors import EstimationError
    from scipy.optimize import root

    xy = np.asarray(xy_px, dtype=np.float64)
    iop = np.asarray(true_iop_px, dtype=np.float64)
    ideal = xy - true_correction(xy)

    def gauge_coefficients(change):
        B = gauge_basis(xy, iop + change[:3], True)
        B = B / np.sqrt(np.mean(B**2, axis=(0, 1)))
        moved = xy - _moved_ideal(ideal, iop, change)
        return np.linalg.lstsq(B.reshape(-1, B.shape[2]), moved.reshape(-1), rcond=None)[0]

    sol = root(gauge_coefficients, np.zeros(6), method="hybr", options={"xtol": 1e-12})
    if not sol.success:
        raise EstimationError(f"the gauge convention's truth was not found: {sol.message}")
    change = sol.x

    def component(q):
        ideal_q = np.asarray(q, dtype=np.float64) - true_correction(q)
        return _moved_ideal(ideal_q, iop, change) - ideal_q

    return iop + change[:3], component


__all__ = [
    "JointUncertainty",
    "convention_truth",
    "joint_uncertainty",
    "learned_uncertainty",
    "with_field_std",
]
