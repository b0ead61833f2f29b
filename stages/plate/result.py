"""What the grid-plate calibration returns (:class:`PlateCalibration`), one artifact for all systems."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.artifacts import SCHEMA_VERSION, freeze


@dataclass(frozen=True)
class PlateCalibration:
    """A grid plate's self-calibration: a field per orientation, the plate's layout, the per-frame fits.

    Orientations, frames and holes of every system are stacked; their ``*_system`` arrays say whose.

    Attributes
    ----------
    orientation_names : tuple of str
        Name of each orientation (``O``).
    orientation_system : (O,) int64 ndarray
    orientation_angles_deg : (O, 2) float64 ndarray, deg
        ``(orbit, tilt)``, NaN where unknown.
    fields : tuple of CorrectionField
        One per orientation: ``ideal = measured - Δ(measured)``, with no homography component (the datum).
    smoothness_order : (S, 2) int64 ndarray
    smoothness_tau_px : (S, 2) float64 ndarray, px
        Per system, the smoothness prior of the field common to its orientations and of each
        orientation's deviation from it, chosen by cross-validation.
    frame_system, frame_exposure, frame_orientation : (F,) int64 ndarray
        The frames fitted and their orientation (index into ``orientation_names``).
    homography : (F, 3, 3) float64 ndarray
        Ideal image px (homogeneous) from plate mm, ``H[2, 2] = 1``.
    hole_system, hole_id : (K,) int64 ndarray
        The holes (lattice ids, one layout per system).
    nominal_mm : (K, 2) float64 ndarray, mm
        Nominal lattice positions.
    plate_error_mm : (K, 2) float64 ndarray, mm
        Estimated manufacturing error: the self-calibrated layout is ``nominal_mm + plate_error_mm``.
    plate_error_std_mm : (K,) float64 ndarray, mm
        Standard uncertainty of each component of the error (0 where not estimated).
    plate_estimated : (K,) bool ndarray
        Holes seen in two frames or more (the others are taken as nominal).
    residual_px : (N, 2) float64 ndarray, px
        Per input observation: ``m - Δ(m) - H(n + e)``.
    initial_residual_px : (N, 2) float64 ndarray, px
        Per input observation: a homography of the nominal lattice, no correction (the "before").
    weight : (N,) float64 ndarray
        Student-t weight of each observation.
    inlier : (N,) bool ndarray
    iterations : int
    converged : bool
    stop_reason : str
    wall_time_s : float
    system_names : tuple of str
    scheme : str
        ``"plate"`` (the fields and the plate's errors), or ``"none"`` (homographies of the nominal plate only).
    """

    orientation_names: tuple
    orientation_system: np.ndarray
    orientation_angles_deg: np.ndarray
    fields: tuple
    smoothness_order: np.ndarray
    smoothness_tau_px: np.ndarray
    frame_system: np.ndarray
    frame_exposure: np.ndarray
    frame_orientation: np.ndarray
    homography: np.ndarray
    hole_system: np.ndarray
    hole_id: np.ndarray
    nominal_mm: np.ndarray
    plate_error_mm: np.ndarray
    plate_error_std_mm: np.ndarray
    plate_estimated: np.ndarray
    residual_px: np.ndarray
    initial_residual_px: np.ndarray
    weight: np.ndarray
    inlier: np.ndarray
    iterations: int
    converged: bool
    stop_reason: str
    wall_time_s: float
    system_names: tuple = ("A",)
    scheme: str = "plate"
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self):
        object.__setattr__(self, "orientation_names", tuple(self.orientation_names))
        object.__setattr__(self, "fields", tuple(self.fields))
        object.__setattr__(self, "system_names", tuple(self.system_names))
        freeze(self)

    def summary(self) -> str:
        """One line: frames, orientations, in-sample RMS before and after, the plate's estimated errors."""
        inl = self.inlier
        before = float(np.sqrt(np.mean(self.initial_residual_px[inl] ** 2))) if inl.any() else float("nan")
        after = float(np.sqrt(np.mean(self.residual_px[inl] ** 2))) if inl.any() else float("nan")
        est = self.plate_estimated
        rms_mm = float(np.sqrt(np.mean(self.plate_error_mm[est] ** 2))) if est.any() else 0.0
        plate = (
            f"plate errors {rms_mm:.4f} mm RMS over {int(est.sum())} holes"
            if est.any()
            else "plate taken as nominal (one frame per hole)"
        )
        return (
            f"grid plate: {len(self.frame_system)} frame(s), {len(self.orientation_names)} orientation(s), "
            f"in-sample RMS {before:.3f} -> {after:.3f} px per component, {plate}, {self.stop_reason}"
        )


__all__ = ["PlateCalibration"]
