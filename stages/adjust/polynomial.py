"""The global polynomial distortion model: the adjustment's additional parameters (APs).

The classic photogrammetric self-calibration model (the "expert method" the
paper compares with): Brown's radial and decentring distortion and Fraser's
affinity, seven coefficients per imaging system, estimated in the bundle
adjustment (:class:`stages.adjust.FreeParameters` ``additional_parameters``).

Model
-----
For a measured (distorted) point ``(x, y)`` px of a system with principal
point ``(xp, yp)`` px and reference radius ``r0`` px::

    u = (x - xp) / r0,   v = (y - yp) / r0,   ρ² = u² + v²
    Δx = u (k1 ρ² + k2 ρ⁴ + k3 ρ⁶) + p1 (ρ² + 2 u²) + 2 p2 u v + b1 u + b2 v
    Δy = v (k1 ρ² + k2 ρ⁴ + k3 ρ⁶) + 2 p1 u v + p2 (ρ² + 2 v²)

and ``ideal = measured - Δ``, the sign of every correction in fluorocal
(docs/concepts.md, "Conventions"). The model acts on measured coordinates, like the
learned fields, and moves with the principal point.

Normalisation: ``r0`` is fixed during a solve (:func:`reference_radius`: half
the diagonal of the bounding box of the system's observations, for a fully
covered image half the image diagonal), so ``ρ <= ~1`` where there are
observations and all seven coefficients are in px, each the displacement its
term causes at ``ρ = 1``: the Jacobian columns are all of order one, like the
principal point's, which keeps the normal equations well conditioned.

The adjustment holds the affinity at zero unless asked
(:class:`stages.adjust.FreeParameters` ``fixed_additional_parameters``): in a
free network a stretch or shear of the phantom nearly mimics it.

In the classic unnormalised form ``ideal = x̄ + Δ_c`` with ``x̄ = x - xp`` px
and ``Δ_c = x̄ (K1 r² + K2 r⁴ + K3 r⁶) + P1 (r² + 2 x̄²) + 2 P2 x̄ ȳ + B1 x̄ + B2 ȳ``
(Fraser 1997), the coefficients are ``K1 = -k1 / r0³``, ``K2 = -k2 / r0⁵``,
``K3 = -k3 / r0⁷``, ``P_i = -p_i / r0²``, ``B_i = -b_i / r0``.

References
----------
.. [1] D. C. Brown, "Close-range camera calibration", Photogrammetric Engineering 37(8), 1971.
.. [2] C. S. Fraser, "Digital camera self-calibration", ISPRS J. Photogramm. Remote Sens. 52(4), 1997.
"""

from __future__ import annotations

import numpy as np

#: coefficient names in the order of the AP vector (all px at ρ = 1)
AP_NAMES = ("k1", "k2", "k3", "p1", "p2", "b1", "b2")
N_AP = len(AP_NAMES)
_DEGREES = np.array([3, 5, 7, 2, 2, 1, 1])  # of each term in (u, v)


def reference_radius(xy_px: np.ndarray) -> float:
    """Half the diagonal of the bounding box of ``xy_px`` ``(N, 2)`` px (1 for fewer than two distinct points)."""
    if len(xy_px) == 0:
        return 1.0
    extent = np.ptp(xy_px, axis=0)
    return float(np.hypot(*extent) / 2) or 1.0


def basis(xy_px: np.ndarray, pp_px: np.ndarray, radius_px, *, derivatives: bool = False):
    """The model's design matrix ``B`` with ``Δ = B @ ap``, optionally with ``∂B/∂u`` and ``∂B/∂v``.

    Parameters
    ----------
    xy_px : (N, 2) float64 ndarray, px
        Measured coordinates.
    pp_px : (2,) or (N, 2) float64 ndarray, px
        Principal point (per point, for several systems).
    radius_px : float or (N,) float64 ndarray, px
        Reference radius ``r0``.
    derivatives : bool
        Also return the derivatives with respect to ``u`` and ``v`` (for the
        chain rule through the principal point: ``∂Δ/∂xp = -(∂B/∂u @ ap) / r0``).

    Returns
    -------
    B : (N, 2, 7) float64 ndarray
        Columns ``k1, k2, k3, p1, p2, b1, b2``.
    dB_du, dB_dv : (N, 2, 7) float64 ndarray
        Only with ``derivatives``.
    """
    xy = np.asarray(xy_px, dtype=np.float64)
    r0 = np.asarray(radius_px, dtype=np.float64)
    uv = (xy - np.asarray(pp_px, dtype=np.float64)) / (r0[..., None] if r0.ndim else r0)
    u, v = uv[:, 0], uv[:, 1]
    uu, vv, uv_ = u * u, v * v, u * v
    r2 = uu + vv
    r4 = r2 * r2
    r6 = r4 * r2
    zero, one = np.zeros_like(u), np.ones_like(u)
    B = np.stack(
        [
            np.stack([u * r2, u * r4, u * r6, r2 + 2 * uu, 2 * uv_, u, v], 1),
            np.stack([v * r2, v * r4, v * r6, 2 * uv_, r2 + 2 * vv, zero, zero], 1),
        ],
        1,
    )
    if not derivatives:
        return B
    dB_du = np.stack(
        [
            np.stack([r2 + 2 * uu, r4 + 4 * uu * r2, r6 + 6 * uu * r4, 6 * u, 2 * v, one, zero], 1),
            np.stack([2 * uv_, 4 * uv_ * r2, 6 * uv_ * r4, 2 * v, 2 * u, zero, zero], 1),
        ],
        1,
    )
    dB_dv = np.stack(
        [
            np.stack([2 * uv_, 4 * uv_ * r2, 6 * uv_ * r4, 2 * v, 2 * u, zero, one], 1),
            np.stack([r2 + 2 * vv, r4 + 4 * vv * r2, r6 + 6 * vv * r4, 2 * u, 6 * v, zero, zero], 1),
        ],
        1,
    )
    return B, dB_du, dB_dv


def correction_at(xy_px: np.ndarray, pp_px: np.ndarray, radius_px, ap_px: np.ndarray) -> np.ndarray:
    """``Δ`` ``(N, 2)`` px of the model at measured ``xy_px`` ``(N, 2)`` px (``ap_px`` ``(7,)`` or ``(N, 7)``).

    Examples
    --------
    >>> ap = np.array([2.0, 0, 0, 0, 0, 0, 0])  # k1: 2 px outwards at the reference radius
    >>> correction_at(np.array([[612.0, 512.0]]), np.array([512.0, 512.0]), 100.0, ap)
    array([[2., 0.]])
    """
    B = basis(xy_px, pp_px, radius_px)
    ap = np.asarray(ap_px, dtype=np.float64)
    return B @ ap if ap.ndim == 1 else np.einsum("nij,nj->ni", B, ap)


def rescaled(ap_px: np.ndarray, radius_from_px: float, radius_to_px: float) -> np.ndarray:
    """The same model's coefficients ``(..., 7)`` px for another reference radius.

    A term of degree ``d`` in ``(u, v)`` scales as ``(r0' / r0)^d``: 3, 5, 7 for
    ``k1..k3``, 2 for ``p1, p2``, 1 for ``b1, b2``.
    """
    return np.asarray(ap_px, dtype=np.float64) * (radius_to_px / radius_from_px) ** _DEGREES
