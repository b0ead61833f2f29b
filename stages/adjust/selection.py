"""Data selection of the bundle adjustment: the nominal table, id look-ups, and what can be estimated.

:func:`select_observations` drops what a solve cannot determine (duplicate
labels, beads seen in too few epochs or along nearly one direction, epochs
with too few beads; :class:`stages.adjust.options.DataSelection`), each with
a debug message, and raises :class:`EstimationError` when every exposure
shares one pose.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
from fluorocal.stages.artifacts import Observations, Phantom, check_shape
from fluorocal.stages.errors import EstimationError, InputError, ShapeError

if TYPE_CHECKING:
    from fluorocal.stages.adjust.options import DataSelection
    from fluorocal.stages.adjust.orientation import Orientation

log = logging.getLogger(__name__)


def nominal_coordinates(nominal) -> tuple[np.ndarray, np.ndarray]:
    """The nominal bead table ``(ids, xyz_mm)`` from any of the forms the adjustment accepts.

    Parameters
    ----------
    nominal : Phantom or dict or (ids, xyz_mm)
        A :class:`stages.artifacts.Phantom`, a mapping id -> xyz (mm) or a pair ``(ids, xyz)``.

    Returns
    -------
    ids : (n,) int64 ndarray
    xyz_mm : (n, 3) float64 ndarray, mm

    Raises
    ------
    InputError
        A pair whose coordinates are not ``(len(ids), 3)`` or not finite.

    Examples
    --------
    >>> ids, xyz = nominal_coordinates({7: (0.0, 1.0, 2.0), 3: (1.0, 1.0, 1.0)})
    >>> ids.tolist(), xyz.shape
    ([7, 3], (2, 3))
    """
    if isinstance(nominal, Phantom):
        return nominal.ids, nominal.xyz_mm
    if isinstance(nominal, dict):
        ids = np.fromiter(nominal.keys(), dtype=np.int64, count=len(nominal))
        xyz = np.asarray(list(nominal.values()), dtype=np.float64).reshape(-1, 3)
        return ids, xyz
    ids, xyz = nominal
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    xyz = np.asarray(xyz, dtype=np.float64)
    check_shape("nominal xyz_mm", xyz, (len(ids), 3))
    if not np.all(np.isfinite(xyz)):
        raise InputError("nominal xyz_mm holds non-finite values")
    return ids, xyz


def index_of(keys: np.ndarray, table: np.ndarray, what: str) -> np.ndarray:
    """Index in ``table`` of every value of ``keys`` (for example bead ids in the nominal table).

    Parameters
    ----------
    keys : (N,) int ndarray
    table : (n,) int ndarray
        Unique values, in any order.
    what : str
        Start of the error message (what is looked up where).

    Returns
    -------
    (N,) int64 ndarray
        ``table[index_of(keys, table, ...)] == keys``.

    Raises
    ------
    InputError
        Some keys are not in ``table`` (the message counts them and names the first five).

    Examples
    --------
    >>> index_of(np.array([30, 10]), np.array([10, 20, 30]), "bead ids").tolist()
    [2, 0]
    """
    order = np.argsort(table, kind="stable")
    pos = np.searchsorted(table[order], keys)
    pos = np.minimum(pos, len(table) - 1) if len(table) else pos
    found = len(table) > 0
    ok = np.zeros(len(keys), bool) if not found else table[order][pos] == keys
    if not np.all(ok):
        missing = np.unique(keys[~ok])
        raise InputError(f"{what}: {len(missing)} value(s) not found, e.g. {missing[:5].tolist()}")
    return order[pos]


def checked_corrections(observations, corrections_px) -> np.ndarray:
    """The corrections Δ ``(N, 2)`` px (zero if None) after checking them and the observations' type.

    Raises
    ------
    InputError
        ``observations`` is not an :class:`stages.artifacts.Observations`.
    ShapeError
        ``corrections_px`` is not ``(N, 2)``.
    """
    if not isinstance(observations, Observations):
        raise InputError(f"observations must be an Observations artifact; got {type(observations).__name__}")
    n_obs = len(observations)
    corrections_px = np.zeros((n_obs, 2)) if corrections_px is None else np.asarray(corrections_px, dtype=np.float64)
    if corrections_px.shape != (n_obs, 2):
        raise ShapeError(
            f"corrections_px must have shape ({n_obs}, 2) like the observations; got {corrections_px.shape}"
        )
    return corrections_px


def _ray_spread_deg(points_mm, sources_mm, point_idx, n_points) -> np.ndarray:
    """Per point, twice the largest angle (deg) between an observing ray and the mean ray."""
    rays = points_mm[point_idx] - sources_mm
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    mean = np.stack([np.bincount(point_idx, rays[:, k], n_points) for k in range(3)], 1).astype(np.float64)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-300)
    cosang = np.clip((rays * mean[point_idx]).sum(1), -1.0, 1.0)
    worst = np.full(n_points, 1.0)
    np.minimum.at(worst, point_idx, cosang)
    return 2.0 * np.degrees(np.arccos(worst))


def epochs_per_bead(point_idx, epoch_idx, n_points: int, n_epochs: int) -> np.ndarray:
    """Number of distinct epochs ``(n_points,)`` in which each bead is observed.

    Examples
    --------
    >>> epochs_per_bead(np.array([0, 0, 0, 1]), np.array([0, 0, 1, 1]), 3, 2).tolist()
    [2, 1, 0]
    """
    pe = np.unique(np.asarray(point_idx) * (n_epochs + 1) + np.asarray(epoch_idx))
    return np.bincount(pe // (n_epochs + 1), minlength=n_points)


def select_observations(
    obs,
    point_idx,
    epoch_idx,
    n_points: int,
    n_epochs: int,
    initial: Orientation,
    nominal_xyz,
    selection: DataSelection,
    left_out=None,
) -> np.ndarray:
    """Mask ``(N,)`` of the observations that can be estimated; logs (debug) what is dropped and why.

    ``point_idx`` and ``epoch_idx`` ``(N,)`` index each observation's bead in
    ``nominal_xyz`` ``(n_points, 3)`` mm and its epoch in ``initial.exposure``;
    ``left_out`` ``(N,)`` bool, optional, marks observations dropped beforehand.
    """
    used = np.ones(len(obs), bool) if left_out is None else ~np.asarray(left_out, bool)
    key = (obs.system * (n_epochs + 1) + epoch_idx) * (n_points + 1) + point_idx
    _, first = np.unique(key, return_index=True)
    dup = np.ones(len(obs), bool)
    dup[first] = False
    if dup.any():
        log.warning("dropping %d duplicate observation(s) of a bead in one frame (kept the first)", int(dup.sum()))
        used &= ~dup
    # every observation's own source, for the ray-angle test
    sources = np.empty((len(obs), 3))
    for s in range(initial.n_systems):
        sel = obs.system == s
        sources[sel] = initial.poses(s)[1][epoch_idx[sel]]
    spread = _ray_spread_deg(nominal_xyz, sources, point_idx, n_points)
    for _ in range(100):
        before = used.sum()
        pts_epochs = epochs_per_bead(point_idx[used], epoch_idx[used], n_points, n_epochs)
        weak_bead = pts_epochs < selection.min_exposures_per_bead
        if used.any():
            spread = _ray_spread_deg(nominal_xyz, sources[used], point_idx[used], n_points)
        narrow = (spread < selection.min_ray_angle_deg) & ~weak_bead & (pts_epochs > 0)
        drop = (weak_bead | narrow)[point_idx] & used
        if drop.any():
            log.debug(
                "dropping %d observation(s) of %d bead(s) seen in fewer than %d epochs or by rays within %.3g deg",
                int(drop.sum()),
                int(len(np.unique(point_idx[drop]))),
                selection.min_exposures_per_bead,
                selection.min_ray_angle_deg,
            )
            used &= ~drop
        epoch_beads = np.bincount(
            np.unique(epoch_idx[used] * (n_points + 1) + point_idx[used]) // (n_points + 1), minlength=n_epochs
        )
        weak_epoch = (epoch_beads < selection.min_beads_per_exposure)[epoch_idx] & used
        if weak_epoch.any():
            log.debug(
                "dropping %d observation(s) of epochs with fewer than %d beads",
                int(weak_epoch.sum()),
                selection.min_beads_per_exposure,
            )
            used &= ~weak_epoch
        if used.sum() == before:
            break
    if not used.any() and len(obs) and (spread[point_idx] < selection.min_ray_angle_deg).all():
        raise EstimationError(
            "every bead is seen along (nearly) one direction: all exposures share one pose "
            f"(ray angles < min_ray_angle_deg = {selection.min_ray_angle_deg}); the points' depth is undetermined"
        )
    return used
