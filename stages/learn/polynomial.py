"""Scheme ``polynomial``: the expert method the paper compares with, a global model estimated in the adjustment.

A radial + decentring (+ affinity) model per system (:mod:`fluorocal.stages.adjust.polynomial`),
sampled onto the same grid as the learned fields; no kNN loop.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from fluorocal.stages.adjust import FreeParameters, polynomial
from fluorocal.stages.field import CorrectionField
from fluorocal.stages.learn.adjuster import Adjuster, adjustment_outcome
from fluorocal.stages.learn.nodes import GridSpec
from fluorocal.stages.learn.result import IterationRecord, LearnResult

logger = logging.getLogger(__name__)


def calibrate_polynomial(
    observations, phantom, initial, sizes, spec: GridSpec, *, fixed: tuple, solver=None, selection=None
) -> LearnResult:
    """Scheme ``polynomial``: the adjustment estimates the IOP and each system's global polynomial model; no kNN loop.

    Iteration 0 is the plain adjustment (no correction: the "before" of the
    report, as in the other schemes); iteration 1 the adjustment with the
    model (:mod:`fluorocal.stages.adjust.polynomial`: the coefficients not in
    ``fixed``, by default all but the affinity ``b1, b2``), warm-started
    from it. Each system's model is sampled at the nodes of the usual grid
    (``spec.spacing_px``) relative to its estimated principal point;
    ``corrections_px`` is the model itself at every observation. Node
    ``sigma_px`` is the model's standard uncertainty there propagated from the
    coefficients' covariance, ``sqrt((σ²_Δx + σ²_Δy) / 2)`` with
    ``σ²_Δ = b C_ap b^T`` (``b`` the node's row of the design matrix; the
    principal point's own uncertainty is not included), and ``support`` marks
    nodes with ``spec.min_support`` used observations within
    ``spec.support_radius_px``, as for the learned fields.
    """
    t0 = time.perf_counter()
    xy = observations.xy_px
    options = {"solver": solver, "selection": selection}
    plain = Adjuster(observations, phantom, initial, free=FreeParameters(estimate_iop=True), fast=True, **options)
    terms = FreeParameters(estimate_iop=True, additional_parameters="polynomial", fixed_additional_parameters=fixed)
    model = Adjuster(observations, phantom, initial, free=terms, **options)
    zero = np.zeros((len(xy), 2))
    first = plain(zero, None, final=False)
    adj = model(zero, first)
    before, out = adjustment_outcome(first, observations.sigma_px), adjustment_outcome(adj, observations.sigma_px)
    corrections = np.zeros((len(xy), 2))
    fields = []
    for s, (w, h) in enumerate(sizes):
        rows = np.flatnonzero(observations.system == s)
        corrections[rows] = adj.polynomial_correction(s, xy[rows])
        grid = CorrectionField.constant(w, h, spacing_px=spec.spacing_px)
        nodes = grid.nodes_px
        B = polynomial.basis(nodes, adj.iop_px[s, :2], adj.ap_radius_px[s])
        var = np.einsum("nci,ij,ncj->n", B, adj.ap_cov_px2[s], B) / 2
        fields.append(
            grid.with_delta(
                adj.polynomial_correction(s, nodes).reshape(grid.delta_px.shape),
                sigma_px=np.sqrt(var).reshape(grid.sigma_px.shape),
                support=spec.support_mask(xy[rows[adj.used[rows]]], grid.x_nodes_px, grid.y_nodes_px).reshape(
                    grid.support.shape
                ),
            )
        )
    step = float(np.abs(corrections).max(initial=0.0))
    history = (
        IterationRecord(0, "adjust", before.cost, 0.0, before.cost, (), before.rms_px, 0.0),
        IterationRecord(1, "polynomial", out.cost, 0.0, out.cost, (), out.rms_px, step),
    )
    logger.info(
        "scheme polynomial: inlier RMS %.4f -> %.4f px, coefficients %s px",
        before.rms_px,
        out.rms_px,
        np.round(adj.ap_px, 4).tolist(),
    )
    stop = f"polynomial model estimated in the adjustment ({adj.stop_reason})"
    seconds = plain.seconds + model.seconds
    return LearnResult(
        "polynomial",
        tuple(fields),
        None,
        corrections,
        adj,
        history,
        (),
        adj.converged,
        stop,
        time.perf_counter() - t0,
        seconds,
        first.residual_px,
    )


__all__ = ["calibrate_polynomial"]
