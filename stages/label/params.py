"""The labelling's parameters and its per-detection status codes."""

from __future__ import annotations

from dataclasses import dataclass

from fluorocal.stages.errors import InputError

#: per-detection status codes in :attr:`Labels.detection_status`
STATUS_LABELLED, STATUS_AMBIGUOUS, STATUS_UNMATCHED, STATUS_REJECTED = 0, 1, 2, 3


@dataclass(frozen=True)
class LabelParams:
    """Parameters of :func:`fluorocal.stages.kinds.labelling.label_beads`.

    Distances given in bead diameters scale with each bead's apparent
    diameter in the frame (its projected diameter once a pose is known, the
    median detected diameter before), so the defaults hold for any bead size.

    Attributes
    ----------
    source_image_distance_mm : float
        Source-image distance of the system (mm, approximate); filled by the pipeline from the system config.
    pixel_pitch_mm : float
        Detector pixel pitch (mm, approximate); filled from the system config. The assumed principal
        distance is ``c = source_image_distance_mm / pixel_pitch_mm`` px.
    image_size_px : tuple of int
        ``(width, height)`` of the frame; the assumed principal point is its centre. ``()`` (default): from the
        centroids artifact when it carries the image shape, otherwise the centre of the detections' bounding box.
    seeds : tuple of (id, x_px, y_px)
        Manually identified beads in this frame (at least 3, ideally 4 or more spread out); when given they
        replace the markers and any prior pose. Default ``()``.
    gate_bead_diameters : float
        Assignment gate: a detection may be assigned to a bead only within this distance of its predicted
        position (default 0.5, half the ambiguity distance, so that an unambiguous bead's nearest rival is
        at least as far again).
    final_gate_bead_diameters : float
        A label is kept only if the detection lies within this distance of the final prediction
        (pose + correction; default 0.25).
    ambiguity_bead_diameters : float
        A bead is ambiguous when another bead's outline centre lies closer than this times the mean of their
        apparent diameters (default 1.0: the outlines touch). Centres are the measured ones where a bead was
        detected, the predicted ones elsewhere; diameters are projected from the pose, scaled by the local
        magnification of the correction. A bead so judged is labelled all the same when its own detection tells it
        apart (:func:`fluorocal.stages.label.assign.told_apart`).
    ransac_threshold_bead_diameters : float
        Inlier threshold of the RANSAC pose on the first, coarse assignment (default 0.3).
    ransac_iterations : int
        Iterations of the RANSAC pose (default 200).
    correction_degree : int
        Total degree (0-5) of the 2D polynomial correction fitted during labelling (default 3; 0 = pinhole
        only); it is reached over the first iterations, as the labelled set grows.
    max_iterations : int
        Cap on assignment/refinement iterations (default 15).
    marker_size_ratio : float
        Apparent size ratio of markers to ordinary beads; 0 (default) = from the phantom's diameters.
    max_marker_candidates : int
        At most this many of the largest detections are tried as markers (default 10).
    min_labelled : int
        A 3D-phantom frame with fewer labelled beads fails (default 12).
    min_labelled_fraction : float
        A frame fails when fewer than this fraction of its valid detections are labelled or ambiguous
        (default 0.7): most detections of a sound frame are beads of the phantom.
    max_axis_ratio : float
        3D phantoms: detections more elongated than this (major / minor axis) are merged blobs of overlapping
        beads, not labelled (default 1.3; a sphere's outline stays within a few % of round).
    max_rms_bead_diameters, max_rms_floor_px : float
        A frame fails when the labelled detections' RMS distance from the final prediction (pose + correction)
        exceeds ``max(max_rms_floor_px, max_rms_bead_diameters x diameter)`` (defaults 0.1 and 1.5 px): right
        labels leave centroid noise and unmodelled distortion (< 1 px), chance matches spread over the gate.
    lattice_tolerance_pitch : float
        Grid plates: a hole is accepted within this fraction of the local spacing of its predicted
        lattice position (default 0.3).
    lattice_max_gap : int
        Grid plates: the growth bridges up to this many consecutive missing holes (default 2).
    """

    source_image_distance_mm: float = 0.0
    pixel_pitch_mm: float = 0.0
    image_size_px: tuple[int, ...] = ()
    seeds: tuple[tuple[float, ...], ...] = ()
    gate_bead_diameters: float = 0.5
    final_gate_bead_diameters: float = 0.25
    ambiguity_bead_diameters: float = 1.0
    ransac_threshold_bead_diameters: float = 0.3
    ransac_iterations: int = 200
    correction_degree: int = 3
    max_iterations: int = 15
    marker_size_ratio: float = 0.0
    max_marker_candidates: int = 10
    min_labelled: int = 12
    min_labelled_fraction: float = 0.7
    max_axis_ratio: float = 1.3
    max_rms_bead_diameters: float = 0.1
    max_rms_floor_px: float = 1.5
    lattice_tolerance_pitch: float = 0.3
    lattice_max_gap: int = 2

    def __post_init__(self):
        positive = (
            "gate_bead_diameters",
            "final_gate_bead_diameters",
            "ambiguity_bead_diameters",
            "ransac_threshold_bead_diameters",
            "lattice_tolerance_pitch",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise InputError(f"{name} must be > 0; got {getattr(self, name)}")
        if self.source_image_distance_mm < 0 or self.pixel_pitch_mm < 0:
            raise InputError(
                "source_image_distance_mm and pixel_pitch_mm must be >= 0; "
                f"got {self.source_image_distance_mm}, {self.pixel_pitch_mm}"
            )
        if len(self.image_size_px) not in (0, 2):
            raise InputError(f"image_size_px must be () or (width, height); got {self.image_size_px}")
        if any(len(s) != 3 for s in self.seeds):
            raise InputError(f"seeds must be (id, x_px, y_px) triples; got {self.seeds}")
        if not 0 <= self.correction_degree <= 5:
            raise InputError(f"correction_degree must be in 0..5; got {self.correction_degree}")
