"""The 3D bead phantom: beads labelled from their markers, seeds or neighbours.

Calibrated by the learning loop: :func:`fluorocal.stages.kinds.learning.calibrate_beads`.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class BeadPhantom:
    """A 3D bead phantom (a cube; ``[phantom] file``): see :class:`~fluorocal.stages.kinds.base.PhantomKind`.

    Its frames of two systems pair into epochs; a system is one C-arm orientation (the phantom moves);
    every scheme applies; its calibration (:func:`~fluorocal.stages.kinds.learning.calibrate_beads`)
    estimates the beads' positions, so check points can score it.
    """

    name = "beads"
    noun = "a 3D bead phantom"
    calibrated_by = "by the learning loop (a bundle adjustment alternating with a learned field)"
    section = "learn"
    needs_geometry = True
    pairs_frames = True
    several_orientations = False
    estimates_geometry = True
    check_points = True

    @property
    def schemes(self) -> tuple:
        from fluorocal.stages.learn import Scheme

        return tuple(Scheme)

    def label_frame(self, centroids, phantom, params, prior_pose=None):
        from fluorocal.stages.label import label_bead_frame

        return label_bead_frame(centroids, phantom, params, prior_pose)

    def label_sequence(self, centroids_seq, phantom, params, seeds_by_frame=None) -> tuple:
        from fluorocal.stages.label import label_bead_sequence

        return label_bead_sequence(centroids_seq, phantom, params, seeds_by_frame)
