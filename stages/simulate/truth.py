"""Ground-truth records of a simulated data set and their JSON form (the ``truth.json`` schema)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.artifacts import Phantom, freeze
from fluorocal.stages.simulate.acquisition import Acquisition
from fluorocal.stages.simulate.params import VERSION, SimulateParams
from fluorocal.stages.simulate.projection import FrameTruth


@dataclass(frozen=True, eq=False)
class Truth:
    """Ground truth of a simulated data set.

    Attributes
    ----------
    true_xyz_mm : (N, 3) float64 ndarray, mm
        True bead (hole) centres in phantom coordinates, in ``phantom.ids`` order.
    reference_xyz_mm : (N, 3) float64 ndarray, mm
        Reference check points (true + survey noise).
    acquisition : Acquisition
        Systems (IOP, distortion, lab placement) and per-exposure poses.
    frames : tuple of tuple of FrameTruth
        ``frames[system][exposure]``.
    """

    true_xyz_mm: np.ndarray
    reference_xyz_mm: np.ndarray
    acquisition: Acquisition
    frames: tuple

    def __post_init__(self):
        freeze(self)

    @property
    def systems(self) -> tuple:
        return self.acquisition.systems


@dataclass(frozen=True, eq=False)
class SimulatedData:
    """A simulated acquisition: frames, nominal phantom and ground truth.

    Attributes
    ----------
    params : SimulateParams
    phantom : Phantom
        Nominal (design) phantom, as written to ``phantom.csv``.
    truth : Truth
    frames : tuple of tuple of Radiograph
        ``frames[system][exposure]``; empty tuples when simulated with ``render=False``.
    """

    params: SimulateParams
    phantom: Phantom
    truth: Truth
    frames: tuple

    @property
    def system_names(self) -> tuple:
        return tuple(s.name for s in self.truth.systems)


def truth_to_dict(data: SimulatedData, *, grid_step_px: float | None = None) -> dict:
    """JSON-serialisable ground truth (the content of ``truth.json``).

    Floats are kept at full precision (Python's ``json`` writes them exactly).
    The schema is documented in ``pipeline/cmd_simulate.py``.

    Parameters
    ----------
    data : SimulatedData
    grid_step_px : float, optional
        Spacing of the dense correction grid (default 16 px at 1024, scaled with the image, at least 8 px).
    """
    from dataclasses import asdict

    params = data.params
    step = grid_step_px or max(8.0, 16.0 * params.px_scale)
    acq = data.truth.acquisition
    systems = _systems_to_dicts(params, acq, step)
    exposures = [
        {
            "turntable_angle_rad": float(acq.turntable_angle_rad[k]),
            "turntable_translation_mm": acq.turntable_translation_mm[k].tolist(),
            "lab_from_phantom_q": acq.lab_from_phantom_q[k].tolist(),
        }
        for k in range(params.n_exposures)
    ]
    frames = []
    for s, per_system in enumerate(data.truth.frames):
        for ft in per_system:
            entry = {
                "system": acq.systems[s].name,
                "exposure": ft.exposure,
                "q": ft.q.tolist(),
                "source_mm": ft.source_mm.tolist(),
            }
            o = int(acq.exposure_orientation[ft.exposure])
            if o >= 0:
                orientation = acq.orientations[o]
                entry.update(
                    orientation=orientation.name, orbit_deg=orientation.orbit_deg, tilt_deg=orientation.tilt_deg
                )
            entry["beads"] = {name: getattr(ft, name).tolist() for name in FrameTruth.BEAD_FIELDS}
            frames.append(entry)
    return {
        "schema": "fluorocal-simulation-truth",
        "schema_version": 1,
        "simulator_version": VERSION,
        "params": asdict(params),
        "image_size_px": params.image_size_px,
        "fov": {"centre_xy_px": params.image_centre_xy_px.tolist(), "radius_px": params.fov_radius_px},
        "phantom": {
            "kind": params.phantom,
            "ids": data.phantom.ids.tolist(),
            "diameter_mm": data.phantom.diameter_mm.tolist(),
            "role": data.phantom.role.tolist(),
            "nominal_xyz_mm": data.phantom.xyz_mm.tolist(),
            "true_xyz_mm": data.truth.true_xyz_mm.tolist(),
            "reference_xyz_mm": data.truth.reference_xyz_mm.tolist(),
        },
        "systems": systems,
        "exposures": exposures,
        "frames": frames,
    }


def _systems_to_dicts(params: SimulateParams, acq: Acquisition, step_px: float) -> list:
    """``truth.json``'s ``systems``: geometry, distortion and correction grid, per orientation in a grid sequence."""
    systems = []
    for system in acq.systems:
        systems.append(
            {
                "name": system.name,
                "iop_px": system.iop_px.tolist(),
                "source_image_distance_mm": system.source_image_distance_mm,
                "pixel_pitch_mm": params.pixel_pitch_mm,
                "lab_from_camera_q": system.lab_from_camera_q.tolist(),
                "source_lab_mm": system.source_lab_mm.tolist(),
                "distortion": system.distortion.to_dict(),
                "correction_grid": _correction_grid(system.distortion, params.image_size_px, step_px),
            }
        )
    if acq.orientations:
        # the grid sequence's system A: its distortion at each orientation
        systems[0]["orientations"] = [
            {
                "name": o.name,
                "orbit_deg": o.orbit_deg,
                "tilt_deg": o.tilt_deg,
                "exposures": np.flatnonzero(acq.exposure_orientation == i).tolist(),
                "field_change": o.field_change.tolist(),
                "distortion": o.distortion.to_dict(),
                "correction_grid": _correction_grid(o.distortion, params.image_size_px, step_px),
            }
            for i, o in enumerate(acq.orientations)
        ]
    return systems


def _correction_grid(distortion, image_size_px: int, step_px: float) -> dict:
    """``{x_px, y_px, delta_px}``: the correction Δ on a regular grid of measured coordinates (JSON lists)."""
    gx, gy, delta = distortion.correction_grid(image_size_px, step_px)
    return {"x_px": gx.tolist(), "y_px": gy.tolist(), "delta_px": delta.tolist()}
