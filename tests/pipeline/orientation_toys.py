"""Toys for the orientation tests: a calibration with a field per C-arm orientation, small angled DICOMs."""

from __future__ import annotations

import numpy as np
from fluorocal.calibration import Calibration, SystemCalibration
from fluorocal.stages.field import CorrectionField
from fluorocal.stages.io import write_dicom
from fluorocal.stages.orientation import OrientationField

from tests.helpers import xa_dataset


def angled_dicom(path, *, angles=None, n_frames: int = 1, motion: str = "STATIC", empty_tags: bool = False):
    """A small XA DICOM of 32 x 32 px, with the C-arm angles as tags when given."""
    ds = xa_dataset(32, 32, PositionerMotion=motion)
    if angles is not None:
        ds.PositionerPrimaryAngle, ds.PositionerSecondaryAngle = angles
    elif empty_tags:  # as the real ARCADIS frames hold them: present, without a value
        ds.PositionerPrimaryAngle, ds.PositionerSecondaryAngle = None, None
    path.parent.mkdir(parents=True, exist_ok=True)
    write_dicom(path, ds, np.full((n_frames, 32, 32), 1000, np.uint16))
    return path


W, H = 64, 48


def constant_field(dx: float, dy: float) -> CorrectionField:
    """A field of one shift ``(dx, dy)`` px over a ``W`` x ``H`` frame."""
    return CorrectionField.constant(W, H, (dx, dy), spacing_px=16.0)


def toy_system(name="A", orientations=(), field=None) -> SystemCalibration:
    """A system of a ``W`` x ``H`` frame at the origin: one ``field``, or a field per orientation."""
    iop, pose = np.array([32.0, 24.0, 1000.0]), (np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3))
    return SystemCalibration(name, (W, H), iop, *pose, field, tuple(orientations))


def orientation_calibration() -> Calibration:
    """System A at three orientations (integer shifts, so undistortion moves pixels exactly), B with one field."""
    a = [
        OrientationField("o0", 0.0, 0.0, constant_field(2.0, 0.0)),
        OrientationField("o30", 30.0, 0.0, constant_field(0.0, 2.0)),
        OrientationField("named", None, None, constant_field(-2.0, 0.0)),
    ]
    return Calibration([toy_system("A", a), toy_system("B", field=constant_field(0.5, 0.5))], {}, {"scheme": "test"})
