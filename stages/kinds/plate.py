"""The grid plate: holes indexed on its lattice, one numbering across frames.

Calibrated by the plate's own solve: :func:`fluorocal.stages.kinds.learning.calibrate_grid_plate`.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class GridPlate:
    """A perforated grid plate (``[phantom] lattice``, ``pitch``): a :class:`~fluorocal.stages.kinds.base.PhantomKind`.

    One kind for every lattice: its geometry is the phantom's data (``lattice``, one of
    :data:`~fluorocal.stages.lattices.LATTICES`, and ``pitch_mm``). Each system is calibrated on its
    own (frames never paired), at any number of C-arm orientations (a field each), with the plate's errors
    estimated (no 3D geometry; :func:`~fluorocal.stages.kinds.learning.calibrate_grid_plate`): scheme
    ``knn+iop+smooth`` (the plate's solve) or ``none`` (homographies only).
    """

    name = "plate"
    noun = "a grid plate"
    calibrated_by = "by the plate's own solve (a field per orientation and the plate's errors)"
    section = "plate"
    needs_geometry = False
    pairs_frames = False
    several_orientations = True
    estimates_geometry = False
    check_points = False

    @property
    def schemes(self) -> tuple:
        from fluorocal.stages.learn import Scheme

        return (Scheme.KNN_IOP_SMOOTH, Scheme.NONE)

    def label_frame(self, centroids, phantom, params, prior_pose=None):
        from fluorocal.stages.label import label_plate_frame

        return label_plate_frame(centroids, phantom, params)

    def label_sequence(self, centroids_seq, phantom, params, seeds_by_frame=None) -> tuple:
        from fluorocal.stages.label import label_plate_sequence

        return label_plate_sequence(centroids_seq, phantom, params, seeds_by_frame)
