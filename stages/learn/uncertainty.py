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
  the true IOP expressed in the same convention (the true distortion with its
  gauge component moved into the IOP, :func:`convention_truth`);
- the IOP's σ leaves the phantom's shape free, as the final adjustment that
  estimates the IOP does; the field's σ holds the phantom's five affine shape
  modes beyond a similarity at the design's when the refinement that learned
  the field held them (``LearnParams.affine_datum``).

The observations' weights are the adjustment's (t-weight over ``σ²``, times its variance factor).
Each system is treated on its own with free poses per exposure: a biplanar
pair's ROP (which ties them) is not used, so its σ is slightly conservative.

Linear algebra: with ``S = A^T W A + D^T D / τ²`` (sparse, per component) and
the gauge ``C v = 0``, the field given the orientation has the constrained
inverse ``S_c^-1 = S^-1 - S^-1 C^T (C S^-1 C^T)^-1 C S^-1``; the orientation's
marginal normal matrix is ``J^T W J - M^T S_c^-1 M`` with ``M = A^T W J``
(the field eliminated), bordered by the 7 inner constraints of the free
network, and the field's marginal covariance is
``S_c^-1 + G Cov_θ G^T``, ``G = S_c^-1 M``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.adjust.covariance import covariance_factor
from fluorocal.stages.artifacts import freeze
from fluorocal.stages.field import bilinear_design
from fluorocal.stages.learn.gauge import gauge_basis
from fluorocal.stages.learn.grid import difference_operator, factor_spd
from fluorocal.stages.learn.network import linearised_network
from scipy.sparse import csr_matrix, identity

#: columns of the identity solved at once for the diagonal of the field's inverse (bounds memory)
_CHUNK = 512


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
    """One system's linearised orientation (:class:`Network`) and its observations' weights ``(2n,)``."""

    J: csr_matrix
    w: np.ndarray  # shape (2n,)
    datum: np.ndarray  # shape (n_theta, 7)
    affine: np.ndarray | None  # shape (n_theta, 5): the phantom's affine shape modes, or None


def _network(adj, observations, rows, system: int, shape_nominal_mm=None) -> _Network:
    """The Jacobian of system ``system``'s observations ``rows`` by ``(IOP, poses, points)`` at ``adj``, weighted."""
    net = linearised_network(adj, observations, rows, system, shape_nominal_mm)
    sig = observations.sigma_px[rows, :2]
    w = (adj.weight[rows, None] / sig**2 / variance_factor(adj, observations)).T.ravel()
    return _Network(net.J, w, net.datum, net.affine)


def variance_factor(adj, observations) -> float:
    """The adjustment's factor of its cofactors (Huber's sandwich for the t, :func:`covariance_factor`).

    Recomputed from its residuals, t-weights and scale, so that the field held fixed gives the
    adjustment's own σ.
    """
    used = adj.used
    r = adj.residual_px[used]
    sx, sy, rho = observations.sigma_px[used].T
    # squared Mahalanobis norm of each residual under (σx, σy, ρ)
    s = ((r[:, 0] / sx) ** 2 - 2 * rho * r[:, 0] * r[:, 1] / (sx * sy) + (r[:, 1] / sy) ** 2) / (1 - rho**2)
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
    n, n_nodes = len(rows), A.shape[1]
    DtD = difference_operator(len(yn), len(xn), int(order))
    DtD = (DtD.T @ DtD).tocsr() / float(tau_px) ** 2
    lus = _field_factors(A, net.w.reshape(2, n), DtD)

    def s_inv(X):  # S^-1 X for X (2 n_nodes, k), the two components' blocks apart
        return np.concatenate(
            [lus[c].solve(np.ascontiguousarray(X[c * n_nodes : (c + 1) * n_nodes])) for c in range(2)]
        )

    JW = net.J.multiply(net.w[:, None]).tocsr()
    M = np.concatenate([(A.T @ JW[c * n : (c + 1) * n]).toarray() for c in range(2)])  # (2 n_nodes, n_theta)
    # the gauge C v = 0: the field's components at the observations along the gauge fields, (K, 2 n_nodes)
    B = gauge_basis(xy, adj.iop_px[system], True)
    C = np.concatenate([(A.T @ B[:, c, :]).T for c in range(2)], axis=1)
    C /= np.linalg.norm(C, axis=1, keepdims=True)
    Y = s_inv(C.T)
    CY_inv = np.linalg.inv(C @ Y)
    G = s_inv(M)
    G -= Y @ (CY_inv @ (C @ G))
    H_cond = (net.J.T @ JW).toarray()
    scale = float(np.mean(np.diag(H_cond)))
    border = scale * net.datum @ net.datum.T
    H_joint = H_cond - M.T @ G
    # the IOP as the final adjustment estimates it: the phantom's shape free
    cov = _sym_inv(H_joint + border)
    # the field as the refinement learned it: with the phantom's affine shape held, if it was
    # (the Gaussian conditioned on F^T θ = 0: cov - cov F (F^T cov F)^-1 F^T cov)
    cov_field = cov
    if net.affine is not None:
        cF = cov @ net.affine
        cov_field = cov - cF @ np.linalg.solve(net.affine.T @ cF, cF.T)
    node_var = _diag_s_inv(lus, n_nodes) - np.sum((Y @ CY_inv) * Y, axis=1)
    node_var += np.sum((G @ cov_field) * G, axis=1)
    cov_cond = _sym_inv(H_cond + border)
    shape = (len(yn), len(xn))
    node_std = _std(node_var).reshape(2, *shape).transpose(1, 2, 0)
    return JointUncertainty(cov[:3, :3], _std(np.diag(cov)[:3]), node_std, _std(np.diag(cov_cond)[:3]))


def _std(var: np.ndarray) -> np.ndarray:
    """Standard deviations of variances ``var``.

    NaN (never 0, a claim of certainty) where rounding left one below zero: a parameter the data barely determine.
    """
    return np.where(var >= 0, np.sqrt(np.abs(var)), np.nan)


def _field_factors(A, w: np.ndarray, DtD) -> list:
    """Sparse LU of ``S = A^T W A + D^T D / τ²`` per component (``w`` ``(2, n)``; one shared when equal)."""
    n_nodes = A.shape[1]
    ridge = 1e-10 * max(float(w.max()), 1.0)  # as the gridded fit's: nodes far from all data stay determined
    same = np.array_equal(w[0], w[1])
    lus = [factor_spd((A.T.multiply(w[c]) @ A + DtD + ridge * identity(n_nodes)).tocsc()) for c in range(2 - same)]
    return lus * (1 + same)


def _sym_inv(H: np.ndarray) -> np.ndarray:
    inv = np.linalg.inv(H)
    return 0.5 * (inv + inv.T)


def _diag_s_inv(lus, n_nodes: int) -> np.ndarray:
    """The diagonal ``(2 n_nodes,)`` of ``S^-1``, solved a chunk of identity columns at a time (once if shared)."""
    diags = []
    for c, lu in enumerate(lus):
        if c and lu is lus[0]:
            diags.append(diags[0])
            continue
        d = np.empty(n_nodes)
        for lo in range(0, n_nodes, _CHUNK):
            hi = min(lo + _CHUNK, n_nodes)
            E = np.zeros((n_nodes, hi - lo))
            E[np.arange(lo, hi), np.arange(hi - lo)] = 1.0
            d[lo:hi] = lu.solve(E)[np.arange(lo, hi), np.arange(hi - lo)]
        diags.append(d)
    return np.concatenate(diags)


def learned_uncertainty(
    adj, observations, rows, trained, grids, memory, params, *, estimate_iop: bool, nominal_shape_mm
) -> tuple | None:
    """Each system's :class:`JointUncertainty` after the learning's gridded refinement, or None where undefined.

    Defined when the fields are gauge-fixed (``params.field_gauge == "orientation"``) and the IOP
    estimated: the recommended loop. ``rows`` per system, ``trained`` ``(N,)`` the observations the
    fields learned from, ``memory`` per system the loop's regression memory (the smoothness prior's
    ``tau_px`` and ``cv.order``); ``nominal_shape_mm`` the design coordinates of ``adj.bead_id``
    (used when ``params.affine_datum`` held the phantom's affine shape).
    """
    if params.field_gauge != "orientation" or not estimate_iop or any(m.tau_px is None for m in memory):
        return None
    used = trained & adj.used
    shape = nominal_shape_mm if params.affine_datum else None
    return tuple(
        joint_uncertainty(
            adj,
            observations,
            r[used[r]],
            s,
            grid,
            tau_px=m.tau_px,
            order=m.cv.order,
            shape_nominal_mm=shape,
        )
        for s, (r, grid, m) in enumerate(zip(rows, grids, memory))
    )


def with_field_std(field, uncertainty: JointUncertainty):
    """``field`` with its node σ (``sigma_px``) replaced by the joint one (RMS of the components)."""
    return field.with_delta(field.delta_px, sigma_px=uncertainty.field_std_px)


def gauge_component(xy_px, correction_px, iop_px, with_iop: bool = True):
    """The least-squares gauge component of a correction at ``xy_px``, as a field: ``xy (m, 2) -> (m, 2)`` px."""
    B = gauge_basis(xy_px, iop_px, with_iop)
    coef, *_ = np.linalg.lstsq(B.reshape(-1, B.shape[2]), np.asarray(correction_px).reshape(-1), rcond=None)
    return lambda xy: (gauge_basis(xy, iop_px, with_iop).reshape(-1, B.shape[2]) @ coef).reshape(-1, 2)


def convention_truth(observations, rows, phantom, initial, true_iop_px, true_correction_px, *, n_rounds: int = 3):
    """A known IOP and correction expressed in the gauge convention: ``(iop (3,) px, gauge component)``.

    The IOP an adjustment of ``observations`` (one system; its exact, noise-free projections)
    estimates with the true correction less its gauge component at ``rows`` held, the gauge
    recomputed at that IOP ``n_rounds`` times. What the convention moves out of the correction,
    ``gauge component(xy)``, is what the field under the convention lacks: its true value at
    ``xy`` is ``true correction - component`` and the true ideal point ``ideal + component``.
    Exact, unlike a first-order reading of the gauge coefficients, since a principal-point
    shift and a camera rotation differ only in the quadratic terms of the keystone fields.
    """
    from fluorocal.stages.adjust import FreeParameters, Orientation, adjust_bundle

    xy, corr = observations.xy_px, np.asarray(true_correction_px, dtype=np.float64)
    iop = np.asarray(true_iop_px, dtype=np.float64)
    for _ in range(n_rounds):
        component = gauge_component(xy[rows], corr[rows], iop)
        start = Orientation(
            iop[None], initial.exposure, initial.q_cam_from_obj, initial.source_mm, system_names=initial.system_names
        )
        free = FreeParameters(estimate_iop=True)
        oracle = adjust_bundle(observations, phantom, start, corr - component(xy), free=free, compute_covariance=False)
        iop = oracle.iop_px[0]
    return iop, gauge_component(xy[rows], corr[rows], iop)


__all__ = [
    "JointUncertainty",
    "convention_truth",
    "gauge_component",
    "joint_uncertainty",
    "learned_uncertainty",
    "with_field_std",
]
