"""The labelling's artifact: the labelled detections of one frame."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from fluorocal.stages.artifacts import SCHEMA_VERSION, as_arrays, check_shape, freeze
from fluorocal.stages.label.params import STATUS_REJECTED, STATUS_UNMATCHED

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Labels:
    """The labelled detections of one frame.

    Attributes
    ----------
    det_index : (N,) int64 ndarray
        Index of each labelled detection into the centroids artifact.
    bead_id : (N,) int64 ndarray
        Phantom bead id (grid plates: :func:`lattice_id` of the hole's lattice indices).
    xy_px : (N, 2) float64 ndarray, px
        Measured (distorted) centre of each labelled detection.
    sigma_px : (N, 3) float64 ndarray
        ``(sigma_x px, sigma_y px, rho)`` of each centre, from the centroid stage.
    object_xyz_mm : (N, 3) float64 ndarray, mm
        Nominal object coordinates of each labelled bead (grid plates: lattice coordinates x pitch, z = 0).
    detection_status : (M,) int8 ndarray
        For every detection of the centroids artifact: ``STATUS_LABELLED`` (0), ``STATUS_AMBIGUOUS`` (1, assigned
        to a bead whose projection overlaps another's), ``STATUS_UNMATCHED`` (2) or ``STATUS_REJECTED`` (3, not a
        usable centroid: failed fit, or too elongated for one bead).
    q : (4,) float64 ndarray
        Approximate pose rotation ``(w, x, y, z)``, object to camera (NaN when the frame failed).
    source_mm : (3,) float64 ndarray, mm
        Approximate X-ray source position in object space (NaN when the frame failed).
    iop : (3,) float64 ndarray, px
        The interior orientation ``(xp, yp, c)`` of the labelling: the principal point assumed at the image
        centre, ``c`` from the configured source-image distance and pixel pitch, refined during the labelling of
        a 3D phantom when its beads span enough depth (approximate: the adjustment estimates the IOP).
    n_labelled, n_ambiguous, n_unmatched : int
        Valid detections labelled / left out as ambiguous / matching no bead.
    rms_px : float
        Reprojection RMS of the labelled detections under the pinhole pose and the assumed IOP (px, in-sample;
        includes the uncorrected distortion). NaN for a grid plate labelled without the geometry.
    rms_corrected_px : float
        The same after the low-order polynomial correction fitted during labelling (px, in-sample; for a grid
        plate, of a homography plus that correction, so it is available without the geometry).
    ok : bool
        False when the frame's labelling failed; then nothing is labelled.
    reason : str
        Why it failed ("" when ok).
    pose_source : str
        ``"markers"``, ``"seeds"``, ``"prior"``, ``"lattice"`` or ``""``.
    explains_most : bool
        The labelling explains most of the frame's usable detections (a 3D phantom:
        :func:`~fluorocal.stages.label.rivals.explains_most`). One that does not may have converged from a
        start a few degrees off with its polynomial correction bent to fit;
        :func:`~fluorocal.stages.label.label_bead_sequence` checks such a frame against its neighbours.
    """

    det_index: np.ndarray
    bead_id: np.ndarray
    xy_px: np.ndarray
    sigma_px: np.ndarray
    object_xyz_mm: np.ndarray
    detection_status: np.ndarray
    q: np.ndarray
    source_mm: np.ndarray
    iop: np.ndarray
    n_labelled: int = 0
    n_ambiguous: int = 0
    n_unmatched: int = 0
    rms_px: float = float("nan")
    rms_corrected_px: float = float("nan")
    ok: bool = True
    reason: str = ""
    pose_source: str = ""
    explains_most: bool = True
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self):
        as_arrays(self, np.int64, "det_index", "bead_id")
        as_arrays(self, np.float64, "xy_px", shape=(-1, 2))
        as_arrays(self, np.float64, "sigma_px", "object_xyz_mm", shape=(-1, 3))
        as_arrays(self, np.int8, "detection_status")
        as_arrays(self, np.float64, "q", shape=(4,))
        as_arrays(self, np.float64, "source_mm", "iop", shape=(3,))
        n = len(self.det_index)
        check_shape("bead_id", self.bead_id, (n,))
        check_shape("xy_px", self.xy_px, (n, 2))
        check_shape("sigma_px", self.sigma_px, (n, 3))
        check_shape("object_xyz_mm", self.object_xyz_mm, (n, 3))
        for name in ("n_labelled", "n_ambiguous", "n_unmatched"):
            object.__setattr__(self, name, int(getattr(self, name)))
        for name in ("ok", "explains_most"):
            object.__setattr__(self, name, bool(getattr(self, name)))
        freeze(self)

    def __len__(self) -> int:
        return len(self.det_index)

    def to_table(self) -> tuple[list[str], list[list]]:
        """The labelled detections as ``(header, rows)`` with columns ``id,x,y,sigma_x,sigma_y,rho``."""
        header = ["id", "x", "y", "sigma_x", "sigma_y", "rho"]
        rows = [
            [int(i), float(x), float(y), float(sx), float(sy), float(r)]
            for i, (x, y), (sx, sy, r) in zip(self.bead_id, self.xy_px, self.sigma_px)
        ]
        return header, rows

    def summary(self) -> str:
        """One line: counts, pose source and RMS, or the failure reason."""
        if not self.ok:
            return f"labelling failed: {self.reason}"
        return (
            f"{self.n_labelled} labelled, {self.n_ambiguous} ambiguous, {self.n_unmatched} unmatched; "
            f"pose from {self.pose_source}, "
            f"RMS {self.rms_px:.2f} px pinhole, {self.rms_corrected_px:.2f} px corrected"
        )


def failed_labels(valid: np.ndarray, iop: np.ndarray, reason: str, pose_source: str = "") -> Labels:
    """The Labels of a frame whose labelling failed: nothing labelled, ``valid`` detections unmatched.

    Parameters
    ----------
    valid : (M,) bool ndarray
        Usable detections (the others get ``STATUS_REJECTED``).
    iop : (3,) float64 ndarray, px
    reason : str
    pose_source : str, optional
    """
    log.debug("labelling failed: %s", reason)  # a sequence may label the frame from its neighbours yet
    status = np.where(valid, STATUS_UNMATCHED, STATUS_REJECTED)
    empty = np.empty((0,))
    return Labels(
        empty,
        empty,
        np.empty((0, 2)),
        np.empty((0, 3)),
        np.empty((0, 3)),
        status,
        np.full(4, np.nan),
        np.full(3, np.nan),
        iop,
        0,
        0,
        int(np.sum(valid)),
        ok=False,
        reason=reason,
        pose_source=pose_source,
        explains_most=False,
    )
