"""Near-symmetries of a 3D phantom: the turns that map its bead layout (almost) onto itself.

A cube of identical walls looks alike after a quarter turn about its vertical axis (up to a shift of half
a row) and after a half turn; a frame that shows no marker cannot tell such poses apart. The turns are
measured from the phantom's own coordinates, once per phantom.
"""

from __future__ import annotations

import functools

import numpy as np

# a turn is a near-symmetry when this fraction of the beads land within _TOLERANCE of a bead
_MIN_ALIKE = 0.8
# ... in typical bead spacings (median nearest-neighbour distance); the shift that realigns the turned
# layout is sought within one spacing (a larger one is a periodic slip, which the shift search checks)
_TOLERANCE = 0.25
# turns tried about each principal axis (degrees)
_STEP_DEG = 2.0
# the offsets' bins (within +-1 / _TOLERANCE of 0) encoded as one integer: digits of this base, shifted positive
_KEY_BASE = 16
_KEY_OFFSET = 8
_KEY_WEIGHTS = np.array([_KEY_BASE**2, _KEY_BASE, 1])


def phantom_symmetries(xyz_mm: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray, float], ...]:
    """The rigid motions ``x -> Rg (x - centre) + centre + t`` that map the bead layout nearly onto itself.

    Turns about each principal axis of the layout (through its centroid), every ``_STEP_DEG``, are each
    given the shift (within one typical bead spacing) that lands most turned beads on beads; a turn is
    kept when ``_MIN_ALIKE`` of them land within ``_TOLERANCE`` spacings of one, and it is the best of its
    neighbours over the angle. The identity is left out.

    Parameters
    ----------
    xyz_mm : (B, 3) float64 ndarray, mm
        The phantom's bead coordinates.

    Returns
    -------
    tuple of (Rg, t, fraction)
        ``Rg`` (3, 3) the turn, ``t`` (3,) mm the shift after it, ``fraction`` of beads landing on beads.
    """
    xyz = np.ascontiguousarray(xyz_mm, dtype=np.float64)
    return _symmetries(xyz.tobytes(), xyz.shape)


@functools.lru_cache(maxsize=8)
def _symmetries(buffer: bytes, shape: tuple) -> tuple:
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    xyz = np.frombuffer(buffer, dtype=np.float64).reshape(shape)
    if len(xyz) < 4:
        return ()
    tree = cKDTree(xyz)
    spacing = float(np.median(tree.query(xyz, k=2)[0][:, 1]))
    tol = _TOLERANCE * spacing
    centre = xyz.mean(0)
    axes = np.linalg.eigh(np.cov((xyz - centre).T))[1].T
    angles = np.radians(np.arange(_STEP_DEG, 360.0 - 0.5 * _STEP_DEG, _STEP_DEG))
    out = []
    for axis in axes:
        fits = [_alike(xyz, tree, centre, Rotation.from_rotvec(axis * a).as_matrix(), spacing, tol) for a in angles]
        scores = np.array([f for f, _ in fits])
        peak = (scores >= np.roll(scores, 1)) & (scores >= np.roll(scores, -1)) & (scores >= _MIN_ALIKE)
        for k in np.flatnonzero(peak):
            out.append((Rotation.from_rotvec(axis * angles[k]).as_matrix(), fits[k][1], float(scores[k])))
    # products of two (a quarter turn about one axis after a half turn about another) are tried too: the
    # principal axes of a layout with two equal extents are any two in their plane
    for Ra, _, _ in list(out):
        for Rb, _, _ in list(out):
            fraction, t = _alike(xyz, tree, centre, Ra @ Rb, spacing, tol)
            if fraction >= _MIN_ALIKE and Rotation.from_matrix(Ra @ Rb).magnitude() > np.radians(_STEP_DEG):
                out.append((Ra @ Rb, t, fraction))
    return tuple(_distinct(out))


def _alike(xyz, tree, centre, Rg, spacing, tol) -> tuple[float, np.ndarray]:
    """Fraction of beads turned by ``Rg`` (about ``centre``) and shifted that land on a bead, and the shift.

    The shift is the mode of the offsets from turned beads to beads within one ``spacing`` (bins of
    ``tol``), refined by the mean offset of the pairs in its bin.
    """
    from scipy.spatial import cKDTree

    turned = (xyz - centre) @ Rg.T + centre
    pairs = cKDTree(turned).sparse_distance_matrix(tree, spacing, output_type="ndarray")
    if not len(pairs):
        return 0.0, np.zeros(3)
    offsets = xyz[pairs["j"]] - turned[pairs["i"]]
    # shape (P, 3): the offsets' bins, within +-spacing / tol = +-4 of 0; one integer key each, ordered as the
    # bins are lexicographically (the first of the most common bins wins ties)
    bins = np.floor(offsets / tol).astype(np.int64)
    keys = (bins + _KEY_OFFSET) @ _KEY_WEIGHTS
    best = np.array(divmod(int(np.argmax(np.bincount(keys))), _KEY_BASE**2))
    best = np.array([best[0], *divmod(int(best[1]), _KEY_BASE)]) - _KEY_OFFSET
    # the bin and its neighbours: the mode's offsets straddle bin edges
    near = np.all(np.abs(bins - best) <= 1, axis=1)
    t = offsets[near].mean(0)
    d, _ = tree.query(turned + t, distance_upper_bound=tol)
    return float(np.isfinite(d).mean()), t


def _distinct(symmetries: list) -> list:
    """The symmetries without repeats (the same turn found about two axes), best first."""
    from scipy.spatial.transform import Rotation

    kept: list = []
    for s in sorted(symmetries, key=lambda s: -s[2]):
        if all(Rotation.from_matrix(s[0] @ k[0].T).magnitude() > np.radians(_STEP_DEG) for k in kept):
            kept.append(s)
    return kept


def turn_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The angle (radians) of the rotation that takes orientation ``Rb`` to ``Ra``."""
    cos = 0.5 * (float(np.trace(Ra @ Rb.T)) - 1.0)
    return float(np.arccos(np.clip(cos, -1.0, 1.0)))
