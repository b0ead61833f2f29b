"""A small synthetic two-system calibration and frame, for the tests of the undistortion maps and of `undistort`.

The field is a smooth pincushion-like correction of a few px (not a constant shift), so the maps are sub-pixel
everywhere and equalities of resampled frames test the resampling, not integer moves.
"""

from __future__ import annotations

import numpy as np
from fluorocal.calibration import Calibration, SystemCalibration
from fluorocal.stages.field import CorrectionField, grid_nodes
from fluorocal.stages.orientation import OrientationField

W, H = 96, 64


def smooth_field(scale: float) -> CorrectionField:
    """A radial correction of up to about ``scale`` px on a 16 px grid of the W x H frame."""
    x, y = grid_nodes(W, H, 16.0)
    yy, xx = np.meshgrid(y, x, indexing="ij")
    r2 = ((xx - W / 2) ** 2 + (yy - H / 2) ** 2) / (W / 2) ** 2
    delta = scale * np.stack([(xx - W / 2) * r2, (yy - H / 2) * r2], axis=-1) / 10  # up to ~scale px
    ones = np.ones(xx.shape)
    return CorrectionField(x, y, delta, 0.01 * ones, ones.astype(bool), W, H)


def synthetic_calibration() -> Calibration:
    """System A with two orientations' fields (0 and 30 degrees of orbit), system B with one field."""
    orientations = (
        OrientationField("o0", 0.0, 0.0, smooth_field(2.0)),
        OrientationField("o30", 30.0, 0.0, smooth_field(-2.0)),
    )
    iop = np.array([W / 2, H / 2, 1000.0])
    a = SystemCalibration("A", (W, H), iop, np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3), None, orientations)
    b = SystemCalibration("B", (W, H), iop, np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3), smooth_field(1.5))
    return Calibration([a, b], {}, {"scheme": "test"})


def textured_frame(seed=0) -> np.ndarray:
    """A 12-bit frame with smooth structure and noise, as uint16."""
    yy, xx = np.mgrid[0:H, 0:W]
    noise = np.random.default_rng(seed).normal(0, 30, (H, W))
    return np.clip(2000 + 1500 * np.sin(xx / 6.0) * np.cos(yy / 8.0) + noise, 0, 4095).astype(np.uint16)


def count_map_computations(monkeypatch) -> list:
    """The calls of :meth:`CorrectionField.remap_maps` from now on (the maps computed, not read from the cache)."""
    calls = []
    original = CorrectionField.remap_maps

    def counted(self, *args):
        calls.append(args)
        return original(self, *args)

    monkeypatch.setattr(CorrectionField, "remap_maps", counted)
    return calls
