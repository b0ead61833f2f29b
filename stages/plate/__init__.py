"""Grid-plate calibration: the plate's own errors estimated with one correction field per C-arm orientation.

A perforated grid plate on the image intensifier is planar, so it fixes no interior orientation: what it
calibrates is the distortion, modulo a homography of the image (which the undistorted image is free to
carry). The plate's holes are not where the drawing puts them either (rows displaced, alternate rows
offset by a fraction of a pixel): a method that trusts the nominal lattice learns those errors as
distortion. Here the holes' positions are unknowns shared by every frame, with a datum on the nominal
lattice, estimated jointly with a smooth correction field per orientation and a homography per frame
(:mod:`.solve`); held-out scoring by alternate lattice rows is in :mod:`.holdout`.

From one frame the plate is taken as nominal (its errors cannot be told from the distortion); every
further frame in which the plate sits elsewhere on the image (another orientation, or the plate moved)
separates the two.

Modules: :mod:`.homography` (normalisation, the homography modes of the datum), :mod:`.problem`
(observations indexed per system), :mod:`.solve` (the alternation), :mod:`.holdout` (the held-out
score), :mod:`.polynomial` (the evaluation's polynomial peer), :mod:`.result` (:class:`PlateCalibration`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from fluorocal.stages.errors import InputError
from fluorocal.stages.label.lattice import check_lattice
from fluorocal.stages.learn.nodes import GridSpec
from fluorocal.stages.plate.problem import frame_orientations, plate_problem, stacked
from fluorocal.stages.plate.result import PlateCalibration
from fluorocal.stages.plate.solve import PlateProblem, PlateSolution, SolveSettings, solve_plate

#: each setting's allowed range: node spacings from a few px to a quarter of a 1024-px frame (a field needs a few
#: nodes a side), the plate prior from a ten-thousandth of a pitch to a pitch, the tolerance below a pixel
_RANGES = (
    ("spacing_px", 4.0, 256.0),
    ("orientation_spacing_px", 4.0, 256.0),
    ("plate_sigma_pitch", 1e-4, 1.0),
    ("tolerance_px", 1e-9, 1.0),
)


@dataclass(frozen=True)
class PlateParams:
    """Parameters of the grid-plate calibration (config section ``[plate]``).

    Attributes
    ----------
    spacing_px : float
        Node spacing of each orientation's field, px (default 16: about one hole pitch of a 1024² frame).
    orientation_spacing_px : float
        Node spacing of each orientation's deviation from the field common to all orientations, px
        (default 64: the change with orientation is smooth, the earth's field acting on the intensifier).
    smoothness_orders : tuple of int
        Candidate orders of the fields' difference prior (default ``(3,)``); with the weights
        ``tau_grid_px``, chosen by 5-fold cross-validation (a hole's observations in one fold), once for
        the field common to the orientations and once for their deviations.
    tau_grid_px : tuple of float
        Candidate prior standard deviations, px (default 0.03, 0.1, 0.3, 1).
    plate_sigma_pitch : float
        Prior standard deviation of a hole's manufacturing error, in pitches (default 0.01: a drilled
        plate is good to a few hundredths of a millimetre at a pitch of a few millimetres; the real
        ARCADIS plate's errors are about 0.012 pitch). It decides what the frames determine only
        weakly, the plate's smooth deformations, which it leaves to the fields; a looser prior lets
        them drift into the layout (``benchmarks/plate.py --plate plate_sigma_pitch=0.02`` shows it).
    max_iterations : int
        Cap on the alternation (default 30).
    tolerance_px : float
        The alternation stops when the corrections and the plate errors (seen in the image) change by
        less than this RMS, px (default 0.001).
    """

    spacing_px: float = 16.0
    orientation_spacing_px: float = 64.0
    smoothness_orders: tuple[int, ...] = (3,)
    tau_grid_px: tuple[float, ...] = (0.03, 0.1, 0.3, 1.0)
    plate_sigma_pitch: float = 0.01
    max_iterations: int = 30
    tolerance_px: float = 1e-3

    def __post_init__(self):
        object.__setattr__(self, "smoothness_orders", tuple(int(o) for o in self.smoothness_orders))
        object.__setattr__(self, "tau_grid_px", tuple(float(t) for t in self.tau_grid_px))
        for name, low, high in _RANGES:
            value = getattr(self, name)
            if not (np.isfinite(value) and low <= value <= high):
                raise InputError(f"{name} must lie in [{low:g}, {high:g}]; got {value}")
        if self.orientation_spacing_px < self.spacing_px:
            raise InputError(
                f"orientation_spacing_px ({self.orientation_spacing_px:g}) must be >= spacing_px ({self.spacing_px:g})"
            )
        if not self.tau_grid_px or not all(np.isfinite(t) and t > 0 for t in self.tau_grid_px):
            raise InputError(f"tau_grid_px must be finite values > 0; got {self.tau_grid_px}")
        if not self.smoothness_orders or not set(self.smoothness_orders) <= {1, 2, 3, 4}:
            raise InputError(f"smoothness_orders must be among 1, 2, 3, 4; got {self.smoothness_orders}")
        if int(self.max_iterations) < 1:
            raise InputError(f"max_iterations must be >= 1; got {self.max_iterations}")

    def settings(self, pitch_mm: float, estimate_plate: bool, *, learn_fields: bool = True, solver=None):
        """The solve's :class:`SolveSettings` for a plate of ``pitch_mm`` (no field at all unless ``learn_fields``).

        ``solver``: the adjustment's :class:`~fluorocal.stages.adjust.SolverOptions` (``[adjust]``: the
        Student-t ``nu``, the homographies' iterations and tolerance, the scale's estimation; default
        ``SolverOptions()``).
        """
        from fluorocal.stages.adjust import SolverOptions

        return SolveSettings(
            grid=GridSpec(spacing_px=self.spacing_px, support_radius_px=2 * self.spacing_px),
            orders=self.smoothness_orders,
            tau_grid_px=self.tau_grid_px,
            start_smoothness=(max(self.smoothness_orders), float(np.median(self.tau_grid_px))),
            deviation_spacing_px=self.orientation_spacing_px,
            plate_sigma_mm=self.plate_sigma_pitch * pitch_mm,
            estimate_plate=estimate_plate and learn_fields,
            solver=SolverOptions() if solver is None else solver,
            max_iterations=int(self.max_iterations) if learn_fields else 0,
            tolerance_px=self.tolerance_px,
        )


def calibrate_plate(
    observations, phantom, params: PlateParams, *, image_size_px, orientations, learn_fields: bool = True, solver=None
) -> PlateCalibration:
    """Self-calibrate a grid plate and one correction field per orientation, per system.

    Parameters
    ----------
    observations : Observations
        The labelled hole centres (lattice ids, consistent across a system's frames).
    phantom : Phantom
        The plate (``lattice``, ``pitch_mm``).
    params : PlateParams
    image_size_px : tuple of (int, int)
        ``(width, height)`` per system.
    orientations : tuple of (int, int, str, float or None, float or None)
        ``(system, exposure, orientation name, orbit_deg, tilt_deg)`` of every frame.
    learn_fields : bool
        False: homographies of the nominal plate only, no field and no plate errors (scheme ``none``).
    solver : SolverOptions, optional
        The adjustment's likelihood (``nu``) and outlier rule (``outlier_weight``), from ``[adjust]``.

    Returns
    -------
    PlateCalibration

    Raises
    ------
    InputError
        Not a grid plate, or a frame without an orientation.
    EstimationError
        A frame admits no homography.
    """
    check_lattice(phantom.lattice, "calibrate_plate")
    from fluorocal.stages.adjust import SolverOptions

    solver = SolverOptions() if solver is None else solver
    t0 = time.perf_counter()
    groups = frame_orientations(observations, orientations)
    parts = []
    for s in range(len(observations.system_names)):
        problem, index = plate_problem(observations, phantom, s, groups, image_size_px[s])
        estimate = learn_fields and len(np.unique(problem.frame)) > 1
        settings = params.settings(phantom.pitch_mm, estimate, learn_fields=learn_fields, solver=solver)
        parts.append((problem, index, solve_plate(problem, settings)))
    calibration = stacked(observations, groups, parts, time.perf_counter() - t0, solver.outlier_weight)
    return replace(calibration, scheme="plate" if learn_fields else "none")


__all__ = [
    "PlateCalibration",
    "PlateParams",
    "PlateProblem",
    "PlateSolution",
    "SolveSettings",
    "calibrate_plate",
    "solve_plate",
]
