"""The grid plate: holes indexed on its lattice, one numbering across frames; calibrated by the plate's own solve."""

from __future__ import annotations

from dataclasses import dataclass

from fluorocal.stages.kinds.base import CalibrationSetup
from fluorocal.stages.label import label_plate_frame, label_plate_sequence
from fluorocal.stages.learn import Scheme
from fluorocal.stages.plate import PlateCalibration, PlateParams, calibrate_plate


@dataclass(frozen=True)
class GridPlate:
    """A perforated grid plate (``[phantom] lattice``, ``pitch``): a :class:`~fluorocal.stages.kinds.base.PhantomKind`.

    Its geometry is data: ``lattice`` (``"hex"`` or ``"square"``, :mod:`fluorocal.stages.label.lattice`);
    the pitch comes with the phantom. Each system is calibrated on its own (frames never paired), at any
    number of C-arm orientations (a field each), with the plate's errors estimated (no 3D geometry):
    scheme ``knn+iop+smooth`` (the plate's solve) or ``none`` (homographies only).
    """

    lattice: str

    name = "plate"
    noun = "a grid plate"
    calibrated_by = "by the plate's own solve (a field per orientation and the plate's errors)"
    section = "plate"
    schemes = (Scheme.KNN_IOP_SMOOTH, Scheme.NONE)
    needs_geometry = False
    pairs_frames = False
    several_orientations = True
    estimates_geometry = False
    check_points = False

    def label_frame(self, centroids, phantom, params, prior_pose=None):
        return label_plate_frame(centroids, phantom, params)

    def label_sequence(self, centroids_seq, phantom, params, seeds_by_frame=None) -> tuple:
        return label_plate_sequence(centroids_seq, phantom, params, seeds_by_frame)

    def calibrate(
        self, observations, phantom, params, *, setup: CalibrationSetup, solver=None, selection=None, plate=None
    ) -> PlateCalibration:
        """:func:`fluorocal.stages.plate.calibrate_plate` with ``plate`` (default ``PlateParams()``).

        A field per orientation and the plate's errors; scheme ``none`` fits homographies only (no field).
        ``params`` and ``selection`` (the learning's) are not read.
        """
        return calibrate_plate(
            observations,
            phantom,
            PlateParams() if plate is None else plate,
            image_size_px=setup.image_size_px,
            orientations=setup.orientations,
            learn_fields=setup.scheme.corrects,
            solver=solver,
        )
