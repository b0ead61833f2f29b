"""What ``fluorocal check`` measures a later frame against, per kind of phantom (:mod:`fluorocal.cmd_check`).

:class:`Tables` detect, centroid and label a frame as the calibration's own frames were; a grid plate's
frame is checked against its self-calibrated layout (:class:`PlateSetup`), a bead phantom's against its
adjusted beads (:class:`PhantomSetup`). Which one is the phantom kind's choice
(:meth:`fluorocal.kinds.KindPart.check_setup`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: fewer scored holes than this and the check says nothing
MIN_HOLES = 100
#: fewer scored beads than this and the check says nothing: five times the pose's six parameters (the simulator's
#: 512 px cube frames show about 250)
MIN_BEADS = 30
#: a frame's plate is the calibration's when its fingerprint correlates at least this well, and by this margin
#: over any other numbering (stages.label.lattice_sequence's own thresholds for renumbering a frame)
MIN_CORRELATION, MIN_MARGIN = 0.3, 0.1


@dataclass(frozen=True)
class Tables:
    """The project's ``[detect]``, ``[centroid]`` and ``[label]`` tables as parameters, and the system's geometry.

    A later frame is detected, centroided and labelled as the calibration's own frames were.
    """

    detect: object
    centroid: object
    label: object
    pixel_pitch_mm: float
    source_image_distance_mm: float

    def labels(self, frame, phantom):
        """The frame's labelled beads or holes (:class:`~fluorocal.stages.label.Labels`)."""
        from dataclasses import replace

        from fluorocal.stages.centroid import centroid_beads
        from fluorocal.stages.detect import detect_beads, estimate_appearance
        from fluorocal.stages.kinds.labelling import label_sequence

        detect = estimate_appearance([frame], self.detect)
        centroids = centroid_beads(frame, detect_beads(frame, detect), self.centroid)
        size = (frame.image.shape[1], frame.image.shape[0])
        params = replace(
            self.label,
            source_image_distance_mm=self.source_image_distance_mm,
            pixel_pitch_mm=self.pixel_pitch_mm,
            image_size_px=size,
        )
        return label_sequence([centroids], phantom, params)[0]


@dataclass(frozen=True)
class PlateSetup:
    """What a grid-plate frame is checked against: the plate (lattice, pitch), its self-calibrated layout.

    Its residual is what the best homography (the plate's pose) leaves of the corrected centres.

    Attributes
    ----------
    tables : Tables
    lattice : str
        ``"hex"`` or ``"square"``.
    pitch_mm : float
    ij : (N, 2) int64 ndarray
        Lattice index of each layout hole.
    layout_mm : (N, 2) float64 ndarray, mm
        The plate's holes as calibrated: nominal + estimated error.
    """

    tables: Tables
    lattice: str
    pitch_mm: float
    ij: np.ndarray
    layout_mm: np.ndarray

    noun, thing = "holes", "plate"
    min_points = MIN_HOLES
    not_found = "no grid plate found"

    def labels(self, frame):
        from fluorocal.stages.artifacts import Phantom

        empty = np.empty(0, np.int64), np.empty((0, 3)), np.empty(0), np.empty(0, str)
        return self.tables.labels(frame, Phantom(*empty, self.lattice, self.pitch_mm))

    def matched(self, labels):
        """``(xy_px, layout_mm)`` of the holes renumbered onto the layout by the plate's fingerprint, or why not."""
        from fluorocal.stages.label.lattice import lattice_index, lattice_xyz_mm
        from fluorocal.stages.label.lattice_sequence import Fingerprint, fingerprint, match_fingerprints

        nominal = lattice_xyz_mm(self.ij, self.lattice, self.pitch_mm)[:, :2]
        reference = Fingerprint(self.ij, (self.layout_mm - nominal) / self.pitch_mm)
        M, t, corr, margin = match_fingerprints(fingerprint(labels, self.lattice), reference, self.lattice)[:4]
        if not (corr >= MIN_CORRELATION and margin >= MIN_MARGIN):
            return (
                f"the plate is not the calibration's (fingerprint correlation {corr:.2f}, margin {margin:.2f}; "
                f"at least {MIN_CORRELATION} and {MIN_MARGIN} needed): another plate, or another C-arm's frame"
            )
        where = {tuple(v): k for k, v in enumerate(self.ij)}
        ij = lattice_index(labels.bead_id) @ np.asarray(M).T + np.asarray(t)
        pairs = [(i, where[key]) for i, key in enumerate(map(tuple, ij)) if key in where]
        if len(pairs) < MIN_HOLES:
            return f"only {len(pairs)} of the frame's holes are in the calibration's layout (at least {MIN_HOLES})"
        mine, theirs = np.array(pairs).T
        return labels.xy_px[mine], self.layout_mm[theirs]

    def residual(self, layout_mm: np.ndarray, ideal_px: np.ndarray, iop_px) -> np.ndarray | None:
        """What the best homography from the layout leaves of the corrected centres ``(n, 2)``, px; None without one."""
        from fluorocal.stages.geometry import homography_fit

        fit = homography_fit(layout_mm, ideal_px)
        return None if fit is None else fit[1]


@dataclass(frozen=True)
class PhantomSetup:
    """What a bead-phantom frame is checked against: the phantom's beads as the calibration adjusted them.

    Its residual is what the best pose of the phantom (a resection, the calibration's IOP held) leaves of the
    corrected centres: a 3D phantom's beads at their calibrated positions fix the pose with 6 parameters, where a
    plate's homography takes 8.

    Attributes
    ----------
    tables : Tables
    phantom : Phantom
        The design (markers and beads) the frames are labelled with.
    ids : (N,) int64 ndarray
        Bead ids of the calibrated beads (object_points.csv).
    xyz_mm : (N, 3) float64 ndarray, mm
        Their adjusted positions.
    """

    tables: Tables
    phantom: object
    ids: np.ndarray
    xyz_mm: np.ndarray

    noun, thing = "beads", "phantom"
    min_points = MIN_BEADS
    not_found = "no phantom found"

    def labels(self, frame):
        return self.tables.labels(frame, self.phantom)

    def matched(self, labels):
        """``(xy_px, xyz_mm)`` of the frame's labelled beads that the calibration adjusted, or why not."""
        where = {int(b): k for k, b in enumerate(self.ids)}
        pairs = [(i, where[int(b)]) for i, b in enumerate(labels.bead_id) if int(b) in where]
        if len(pairs) < MIN_BEADS:
            return f"only {len(pairs)} of the frame's beads are among the calibration's (at least {MIN_BEADS})"
        mine, theirs = np.array(pairs).T
        return labels.xy_px[mine], self.xyz_mm[theirs]

    def residual(self, xyz_mm: np.ndarray, ideal_px: np.ndarray, iop_px) -> np.ndarray | None:
        """What the best pose leaves of the corrected centres ``(n, 2)``, px: OpenCV's resection, IOP held."""
        return resection_residual(xyz_mm, ideal_px, iop_px)


def resection_residual(xyz_mm: np.ndarray, ideal_px: np.ndarray, iop_px) -> np.ndarray | None:
    """``ideal - projection`` ``(n, 2)`` px at the least-squares pose of points ``xyz_mm`` seen at ``ideal_px``.

    The pinhole of ``iop_px`` ``(xp, yp, c)`` is held; the pose starts from OpenCV's SQPnP and is refined by
    Levenberg-Marquardt (``cv2.solvePnPRefineLM``) on the reprojection error. None when SQPnP finds no pose.

    Examples
    --------
    >>> from fluorocal.stages.geometry import project
    >>> rng = np.random.default_rng(0)
    >>> xyz = rng.uniform(-50, 50, (40, 3))
    >>> q, source, iop = np.array([0.99, 0.1, -0.05, 0.02]), np.array([5.0, -3.0, -900.0]), (256.0, 250.0, 2200.0)
    >>> seen = project(xyz, q / np.linalg.norm(q), source, np.array(iop))
    >>> float(np.abs(resection_residual(xyz, seen, iop)).max()) < 1e-6
    True
    """
    import cv2
    from fluorocal.stages.geometry import camera_matrix

    obj, img = np.ascontiguousarray(xyz_mm, np.float64), np.ascontiguousarray(ideal_px, np.float64)
    K = camera_matrix(iop_px)
    found, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_SQPNP)
    if not found:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec)
    return img - cv2.projectPoints(obj, rvec, tvec, K, None)[0].reshape(-1, 2)
