"""Orientation of an acquisition (:class:`Orientation`) and its start values by resection (:func:`initial_orientation`).

Conventions (:mod:`stages.geometry`): the reference system's (system 0)
pose of epoch ``j`` is ``p_0 = R_j (P - T_j)``; system ``s`` sees
``p_s = R_s (p_0 - b_s)`` with its relative orientation (ROP) ``(R_s, b_s)``,
the same for the whole acquisition (biplanar: frames of different systems
with the same ``exposure`` share the phantom's pose).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from fluorocal.stages.adjust.selection import index_of, nominal_coordinates
from fluorocal.stages.artifacts import SCHEMA_VERSION, Observations, check_shape, freeze
from fluorocal.stages.errors import EstimationError, InputError
from fluorocal.stages.geometry import camera_matrix, matrix_to_quat, quat_multiply, quat_normalize, quat_to_matrix

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Orientation:
    """Exterior, interior and relative orientation of an acquisition.

    Attributes
    ----------
    iop_px : (S, 3) float64 ndarray, px
        ``(xp, yp, c)`` per system.
    exposure : (M,) int64 ndarray
        Epoch indices (``Observations.exposure`` values), sorted, unique.
    q_cam_from_obj : (M, 4) float64 ndarray
        Unit quaternion ``(w, x, y, z)`` of the reference system's (system 0)
        rotation, object -> camera, per epoch.
    source_mm : (M, 3) float64 ndarray, mm
        Reference system's X-ray source in object space per epoch.
    rop_q : (S, 4) float64 ndarray
        System ``s`` camera from system 0 camera (identity for ``s = 0``).
    rop_source_mm : (S, 3) float64 ndarray, mm
        System ``s``'s source in system 0's camera frame (zero for ``s = 0``).
    system_names : tuple of str
    """

    iop_px: np.ndarray
    exposure: np.ndarray
    q_cam_from_obj: np.ndarray
    source_mm: np.ndarray
    rop_q: np.ndarray | None = None
    rop_source_mm: np.ndarray | None = None
    system_names: tuple = ("A",)
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self):
        iop = np.asarray(self.iop_px, dtype=np.float64).reshape(-1, 3)
        n_sys = len(iop)
        set_ = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731
        set_("iop_px", iop)
        set_("exposure", np.asarray(self.exposure, dtype=np.int64).reshape(-1))
        m = len(self.exposure)
        set_("q_cam_from_obj", quat_normalize(np.asarray(self.q_cam_from_obj, dtype=np.float64).reshape(-1, 4)))
        set_("source_mm", np.asarray(self.source_mm, dtype=np.float64).reshape(-1, 3))
        rop_q = np.tile([1.0, 0, 0, 0], (n_sys, 1)) if self.rop_q is None else self.rop_q
        rop_t = np.zeros((n_sys, 3)) if self.rop_source_mm is None else self.rop_source_mm
        set_("rop_q", quat_normalize(np.asarray(rop_q, dtype=np.float64).reshape(-1, 4)))
        set_("rop_source_mm", np.asarray(rop_t, dtype=np.float64).reshape(-1, 3))
        names = tuple(self.system_names)
        if len(names) != n_sys:
            names = names + tuple(chr(ord("A") + i) for i in range(len(names), n_sys))
        set_("system_names", names[:n_sys])
        check_shape("q_cam_from_obj", self.q_cam_from_obj, (m, 4))
        check_shape("source_mm", self.source_mm, (m, 3))
        check_shape("rop_q", self.rop_q, (n_sys, 4))
        check_shape("rop_source_mm", self.rop_source_mm, (n_sys, 3))
        if m and np.any(np.diff(self.exposure) <= 0):
            raise InputError(f"exposure must be sorted and unique; got {self.exposure.tolist()[:10]}...")
        for name in ("iop_px", "q_cam_from_obj", "source_mm", "rop_q", "rop_source_mm"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise InputError(f"{name} holds non-finite values")
        freeze(self)

    @property
    def n_systems(self) -> int:
        return len(self.iop_px)

    def poses(self, system: int) -> tuple[np.ndarray, np.ndarray]:
        """Every epoch's pose of ``system``: ``q (M, 4)`` object -> camera and source ``T (M, 3)`` mm.

        ``R_s R_j`` and ``T_j + R_j^T b_s``: the ROP composed with the reference pose.
        """
        q_s = quat_normalize(quat_multiply(self.rop_q[system], self.q_cam_from_obj))
        T_s = self.source_mm + np.einsum("mji,j->mi", quat_to_matrix(self.q_cam_from_obj), self.rop_source_mm[system])
        return q_s, T_s


def initial_orientation(observations: Observations, nominal, iop_px: np.ndarray, *, min_beads: int = 6) -> Orientation:
    """Start values by resection of every frame (OpenCV ``solvePnP``) at the given IOP.

    Parameters
    ----------
    observations : Observations
    nominal : Phantom or dict or (ids, xyz_mm)
        Nominal bead coordinates (mm).
    iop_px : (S, 3) or (3,) float64 ndarray, px
        Approximate ``(xp, yp, c)`` per system (for example the image centre and
        source-image distance / pixel pitch).
    min_beads : int
        Frames with fewer labelled beads are not resected (default 6).

    Returns
    -------
    Orientation
        Per epoch the pose of system 0 (or, where system 0 has no frame, of the
        first system that has one, carried over by the ROP); per system ``s >= 1``
        the ROP as the rotation-averaged ``R_s R_0^T`` and mean ``R_0 (T_s - T_0)``
        over the epochs both systems resected.

    Raises
    ------
    EstimationError
        No frame could be resected, or a system shares no epoch with system 0.
    """
    n_sys = len(observations.system_names)
    iop_px = np.broadcast_to(np.asarray(iop_px, dtype=np.float64).reshape(-1, 3), (n_sys, 3)).copy()
    epochs = np.unique(observations.exposure)
    R, T = _resect_frames(observations, nominal, iop_px, epochs, min_beads)
    rop_q, rop_t = _relative_orientations(R, T, observations.system_names)
    q0, T0 = _reference_poses(R, T, rop_q, rop_t)
    found = np.isfinite(T0[:, 0])
    if not found.any():
        raise EstimationError(f"no frame could be resected (each needs >= {min_beads} labelled beads)")
    if not found.all():
        log.warning("%d exposure(s) could not be resected and are left out", int((~found).sum()))
    return Orientation(
        iop_px=iop_px,
        exposure=epochs[found],
        q_cam_from_obj=q0[found],
        source_mm=T0[found],
        rop_q=rop_q,
        rop_source_mm=rop_t,
        system_names=observations.system_names,
    )


def _resect_frames(observations, nominal, iop_px, epochs, min_beads) -> tuple[np.ndarray, np.ndarray]:
    """Per system and epoch the resected rotation ``R (S, M, 3, 3)`` and source ``T (S, M, 3)`` mm (NaN: none)."""
    import cv2

    ids, xyz = nominal_coordinates(nominal)
    n_sys = len(iop_px)
    point = index_of(observations.bead_id, ids, "observations.bead_id not in the nominal coordinates")
    R = np.full((n_sys, len(epochs), 3, 3), np.nan)
    T = np.full((n_sys, len(epochs), 3), np.nan)
    for s in range(n_sys):
        K = camera_matrix(iop_px[s])
        for j, ep in enumerate(epochs):
            sel = (observations.system == s) & (observations.exposure == ep)
            if sel.sum() < min_beads:
                continue
            ok, rvec, tvec = cv2.solvePnP(xyz[point[sel]], observations.xy_px[sel], K, None, flags=cv2.SOLVEPNP_SQPNP)
            if not ok:
                log.info("resection of system %d exposure %d failed", s, ep)
                continue
            Rj = cv2.Rodrigues(rvec)[0]
            R[s, j], T[s, j] = Rj, -Rj.T @ tvec.ravel()
    return R, T


def _relative_orientations(R, T, system_names) -> tuple[np.ndarray, np.ndarray]:
    """ROP (S, 4), (S, 3) mm: rotation-averaged ``R_s R_0^T`` and mean ``R_0 (T_s - T_0)`` over shared epochs."""
    n_sys = len(R)
    rop_q = np.tile([1.0, 0, 0, 0], (n_sys, 1))
    rop_t = np.zeros((n_sys, 3))
    for s in range(1, n_sys):
        both = np.isfinite(T[0, :, 0]) & np.isfinite(T[s, :, 0])
        if not both.any():
            raise EstimationError(f"system {system_names[s]} shares no resected exposure with system {system_names[0]}")
        q_rel = matrix_to_quat(R[s, both] @ R[0, both].transpose(0, 2, 1))
        q_rel *= np.sign(q_rel @ q_rel[0])[:, None]
        rop_q[s] = quat_normalize(q_rel.mean(0))
        rop_t[s] = np.einsum("nij,nj->ni", R[0, both], T[s, both] - T[0, both]).mean(0)
    return rop_q, rop_t


def _reference_poses(R, T, rop_q, rop_t) -> tuple[np.ndarray, np.ndarray]:
    """The reference pose ``q (M, 4)``, ``T (M, 3)`` mm of each epoch, from system 0 or through another system's ROP."""
    n_sys, n_epochs = T.shape[:2]
    q0 = np.full((n_epochs, 4), np.nan)
    T0 = np.full((n_epochs, 3), np.nan)
    for s in range(n_sys - 1, -1, -1):
        have = np.isfinite(T[s, :, 0])
        if not have.any():
            continue
        Rr = quat_to_matrix(rop_q[s])
        R_ref = Rr.T @ R[s, have]  # R_s = R_r R_0
        q0[have] = matrix_to_quat(R_ref)
        T0[have] = T[s, have] - np.einsum("nji,j->ni", R_ref, rop_t[s])  # T_s = T_0 + R_0^T b_s
    return q0, T0
