"""The field's gauge: what the orientation parameters reproduce exactly, removed from a learned field.

A common rotation of every pose, and with the IOP estimated a principal-point
shift and a principal-distance scaling, displace the image by fields a
correction field can equally carry; left in the field they let the
alternation's fixed point, and the IOP, drift (``LearnParams.field_gauge``).
"""

from __future__ import annotations

import numpy as np
from fluorocal.stages.field import CorrectionField


def gauge_basis(xy_px, iop_px, with_iop: bool) -> np.ndarray:
    """Image displacement fields ``(n, 2, K)`` px the orientation parameters reproduce exactly (to first order).

    A common rotation of every pose about the camera axes (absorbed, in a
    biplanar set, by the ROP) displaces the image by ``c ω × ...``: a rotation
    about the principal point and two "keystone" fields
    ``(c + x'²/c, x'y'/c)``, ``(x'y'/c, c + y'²/c)`` (``x' = x - xp``). With
    the IOP estimated, a shift of the principal point (the two translations)
    and of the principal distance (a scaling about the principal point) too.
    """
    xp, yp, c = (float(v) for v in iop_px)
    u, v = xy_px[:, 0] - xp, xy_px[:, 1] - yp
    cols = [np.stack([-v, u], 1), np.stack([c + u * u / c, u * v / c], 1), np.stack([u * v / c, c + v * v / c], 1)]
    if with_iop:
        one, zero = np.ones_like(u), np.zeros_like(u)
        cols += [np.stack([one, zero], 1), np.stack([zero, one], 1), np.stack([u, v], 1)]
    return np.stack(cols, 2)


def gauge_fixed(field: CorrectionField, xy_px: np.ndarray, iop_px, with_iop: bool) -> CorrectionField:
    """The field less its least-squares component (at the observations) that the orientation reproduces.

    These components trade exactly against the adjustment's parameters (see
    :func:`gauge_basis`): left in the field they make the alternation's
    fixed point, and the IOP, drift; removed, the adjustment carries them.
    """
    B = gauge_basis(xy_px, iop_px, with_iop)
    scale = np.sqrt(np.mean(B**2, axis=(0, 1)))
    A = (B / scale).reshape(-1, B.shape[2])
    coef, *_ = np.linalg.lstsq(A, field.correction_at(xy_px).reshape(-1), rcond=None)
    nodes = field.nodes_px
    at_nodes = (gauge_basis(nodes, iop_px, with_iop) / scale).reshape(-1, B.shape[2]) @ coef
    return field.with_delta(field.delta_px - at_nodes.reshape(field.delta_px.shape))


__all__ = ["gauge_basis", "gauge_fixed"]
