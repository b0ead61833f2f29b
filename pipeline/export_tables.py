"""What both exports write: a bead phantom's (:mod:`fluorocal.export`) and a plate's (:mod:`fluorocal.export_plate`).

``object_points.csv`` and ``observations.csv`` (the schemas :data:`fluorocal.stages.io.OBJECT_POINTS` and
:data:`fluorocal.stages.io.OBSERVATIONS`), and the version stamped into ``calibration.json``.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
from fluorocal.stages.io import OBJECT_POINTS, OBSERVATIONS, write_table

__all__ = ["fluorocal_version", "write_object_points", "write_observations"]


def fluorocal_version() -> str:
    """The installed fluorocal's version, or ``"unknown"`` (run from a source tree without installing)."""
    try:
        return version("fluorocal")
    except PackageNotFoundError:
        return "unknown"


def write_object_points(path: Path, bead_id, xyz_mm, xyz_std_mm) -> None:
    """``object_points.csv``: adjusted bead centres and their standard deviations, mm (:data:`OBJECT_POINTS`)."""
    xyz_mm, xyz_std_mm = np.asarray(xyz_mm), np.asarray(xyz_std_mm)
    columns = {"id": bead_id, "x": xyz_mm[:, 0], "y": xyz_mm[:, 1], "z": xyz_mm[:, 2]}
    columns.update(sx=xyz_std_mm[:, 0], sy=xyz_std_mm[:, 1], sz=xyz_std_mm[:, 2])
    write_table(path, OBJECT_POINTS, columns)


def write_observations(path: Path, obs, *, files: dict, corrections_px, residual_px, inlier) -> None:
    """``observations.csv`` (:data:`~fluorocal.stages.io.OBSERVATIONS`; ``fluorocal adjust`` reads it).

    Parameters
    ----------
    path : Path
        The file to write.
    obs : fluorocal.stages.artifacts.Observations
        The labelled bead centres, px, and their covariances.
    files : dict
        ``(system index, exposure) -> file name`` of each frame.
    corrections_px : (N, 2) float ndarray, px
        The learned correction Δ at each observation (ideal = measured - Δ).
    residual_px : (N, 2) float ndarray, px
        The final residuals.
    inlier : (N,) bool ndarray
        Whether the robust adjustment kept each observation.
    """
    columns = {
        "system": [obs.system_names[s] for s in obs.system],
        "file": [files[(s, e)] for s, e in zip(obs.system.tolist(), obs.exposure.tolist())],
        "exposure": obs.exposure,
        "id": obs.bead_id,
        "x": obs.xy_px[:, 0],
        "y": obs.xy_px[:, 1],
        "sigma_x": obs.sigma_px[:, 0],
        "sigma_y": obs.sigma_px[:, 1],
        "rho": obs.sigma_px[:, 2],
        "delta_x": corrections_px[:, 0],
        "delta_y": corrections_px[:, 1],
        "residual_x": residual_px[:, 0],
        "residual_y": residual_px[:, 1],
        "inlier": inlier,
    }
    write_table(path, OBSERVATIONS, columns)
