"""Parameters of the simulator (:class:`SimulateParams`) and its constants: version, system names, seed streams."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from fluorocal.stages.errors import InputError

VERSION = 1
SYSTEM_NAMES = ("A", "B")
#: points on each outline used for the distorted outline centre and apparent diameter
N_OUTLINE = 256
#: Fibonacci numbers allowed as sub-sample counts of edge pixels
FIBONACCI = (5, 8, 13, 21, 34, 55, 89, 144)

# seed-sequence tags, so each random quantity has its own stream and the
# geometry does not depend on whether frames were rendered
RNG_PHANTOM, RNG_ACQ, RNG_DIST, RNG_NOISE = 1, 2, 3, 4
# streams of the optional motion and marker variations (their own, so the defaults draw what they always drew)
RNG_WOBBLE, RNG_MARKERS, RNG_HIDDEN = 5, 6, 7
#: marker layouts of the cube: the design's fixed slots, or beads drawn at random
MARKER_LAYOUTS = ("fixed", "random")


@dataclass(frozen=True)
class SimulateParams:
    """Parameters of a simulated acquisition (defaults give ARCADIS-like 1024² frames).

    Lengths in mm are physical (detector plane or object space); px values
    derived from them scale with ``image_size_px``. Distortion amplitudes are
    quoted in px for a 1024-px image and scale with the image size.

    Attributes
    ----------
    n_frames : int, default 12
        Exposures per system.
    n_systems : int, default 1
        1 (monoplanar) or 2 (biplanar, synchronised exposures).
    image_size_px : int, default 1024
        Square image side.
    detector_size_mm : float, default 256.0
        Detector side at the image plane; pixel pitch = detector_size_mm / image_size_px.
    source_image_distance_mm : float, default 1100.0
    magnification : float, default 1.35
        At the isocentre (source–isocentre distance = SID / magnification).
    system_angle_deg : float, default 75.0
        Azimuth of system B from system A (biplanar only).
    phantom : str, default "cube"
        ``"cube"`` (3D bead phantom) or ``"grid"`` (perforated hex plate, monoplanar only).
    distortion : str, default "strong"
        ``"none"``, ``"mild"`` (radial ~5 px at the field edge) or ``"strong"`` (~15 px).
    noise_scale : float, default 1.0
        Multiplies quantum and electronic noise; 0 gives noise-free frames.
    seed : int, default 0
    cube_side_mm, wall_thickness_mm : float, default 120.0, 5.0
        Acrylic box; bead centres lie in the walls' mid-planes.
    bead_diameter_mm, marker_diameter_mm : float, default 3.5, 5.0
    bead_row_pitch_mm, bead_column_pitch_mm : float, default 12.0, 9.0
        Bead grid on each wall (9 or 10 rows × 13 columns on the default cube,
        494 beads); neighbouring walls' rows are offset by half a row pitch.
    grid_pitch_mm, grid_hole_diameter_mm, grid_thickness_mm : float, default 3.6, 1.8, 1.0
    grid_size_mm : float, default 250.0
        Diameter of the perforated region of the plate.
    grid_magnification : float, default 1.05
        The plate sits near the detector face.
    fabrication_error_mm : float, default 0.1
        3D RMS of true - nominal bead positions.
    reference_error_mm : float, default 0.025
        3D RMS of reference - true (survey noise of the check points).
    turntable_translation_mm, turntable_height_mm : float, default 10.0, 15.0
        Half-ranges of the horizontal shifts and height changes of the turntable.
    min_face_angle_deg : float, default 30.0
        Turntable angles keep every system at least this far from viewing a wall edge-on.
    turntable_step_deg : float, default 0.0
        Turn of the turntable between consecutive exposures. 0: the exposures are spread evenly over the
        angles that respect ``min_face_angle_deg``; otherwise exposure k is at ``k * turntable_step_deg``
        from the first such angle, and later exposures may view walls edge-on.
    turntable_wobble_deg : float, default 0.0
        At each exposure the turntable's axis is tilted from the vertical by up to this angle (uniform), in
        a uniformly random direction, independently of the other exposures.
    marker_layout : str, default "fixed"
        Cube markers: ``"fixed"`` (the first ``n_markers`` of eight fixed slots, two per wall near its
        centre, placed asymmetrically) or ``"random"`` (``n_markers`` beads drawn at random, seeded).
    n_markers : int, default 8
        Number of marker beads (at most 8 with ``"fixed"``; 0 gives a phantom without markers).
    hidden_marker_fraction : float, default 0.0
        Fraction of frames (drawn per frame) in which 1 to all of the visible markers are hidden: left out
        of the rendered frame and of its truth, as if occluded or missed by detection.
    system_misalignment_deg : float, default 1.0
        Random tilt of each system from its nominal orientation.
    principal_point_offset_px : float, default 6.0
        Half-range of the principal point's offset from the image centre (at 1024 px).
    fov_radius_frac : float, default 0.47
        Radius of the round field of view as a fraction of the image side.
    overlap_margin_px : float, default 2.0
        Outlines closer than this (about half a blurred edge) count as overlapping.
    mu_steel_per_mm, mu_acrylic_per_mm : float, default 0.9, 0.015
        Effective linear attenuation coefficients (~60 keV).
    open_field_dn : float, default 2000.0
        Unattenuated signal at the field centre.
    dark_dn : float, default 8.0
        Signal outside the field of view.
    focal_spot_mm : float, default 0.6
        FWHM of the focal spot; blurs by ``focal_spot_mm * (M - 1)`` at the detector.
    intensifier_blur_mm : float, default 0.32
        Gaussian sigma of the intensifier + camera blur at the detector.
    glare_fraction : float, default 0.06
    glare_sigma_mm : float, default 30.0
        Veiling glare: this fraction of the signal is spread by a Gaussian of this sigma.
    vignetting : float, default 0.2
        Relative fall-off of the signal from the field centre to its rim.
    heel : float, default 0.04
        Relative fluence gradient (heel effect) from the field centre to the rim along y.
    gain_dn_per_quantum : float, default 0.14
        Quantum noise variance = gain * signal (DN²).
    electronic_noise_dn : float, default 4.0
    supersample : int, default 21
        Sub-samples per pixel on bead edges, on a Fibonacci lattice (a Fibonacci number: 5, 8, 13, 21, 34, 55, ...).
    bit_depth : int, default 12
    """

    n_frames: int = 12
    n_systems: int = 1
    image_size_px: int = 1024
    detector_size_mm: float = 256.0
    source_image_distance_mm: float = 1100.0
    magnification: float = 1.35
    system_angle_deg: float = 75.0
    phantom: str = "cube"
    distortion: str = "strong"
    noise_scale: float = 1.0
    seed: int = 0
    cube_side_mm: float = 120.0
    wall_thickness_mm: float = 5.0
    bead_diameter_mm: float = 3.5
    marker_diameter_mm: float = 5.0
    bead_row_pitch_mm: float = 12.0
    bead_column_pitch_mm: float = 9.0
    grid_pitch_mm: float = 3.6
    grid_hole_diameter_mm: float = 1.8
    grid_thickness_mm: float = 1.0
    grid_size_mm: float = 250.0
    grid_magnification: float = 1.05
    fabrication_error_mm: float = 0.1
    reference_error_mm: float = 0.025
    turntable_translation_mm: float = 10.0
    turntable_height_mm: float = 15.0
    min_face_angle_deg: float = 30.0
    system_misalignment_deg: float = 1.0
    principal_point_offset_px: float = 6.0
    fov_radius_frac: float = 0.47
    overlap_margin_px: float = 2.0
    mu_steel_per_mm: float = 0.9
    mu_acrylic_per_mm: float = 0.015
    open_field_dn: float = 2000.0
    dark_dn: float = 8.0
    focal_spot_mm: float = 0.6
    intensifier_blur_mm: float = 0.32
    glare_fraction: float = 0.06
    glare_sigma_mm: float = 30.0
    vignetting: float = 0.2
    heel: float = 0.04
    gain_dn_per_quantum: float = 0.14
    electronic_noise_dn: float = 4.0
    supersample: int = 21
    bit_depth: int = 12
    turntable_step_deg: float = 0.0
    turntable_wobble_deg: float = 0.0
    marker_layout: str = "fixed"
    n_markers: int = 8
    hidden_marker_fraction: float = 0.0

    def __post_init__(self):
        choices = (("phantom", ("cube", "grid")), ("distortion", ("none", "mild", "strong")))
        for name, allowed in (*choices, ("marker_layout", MARKER_LAYOUTS)):
            if getattr(self, name) not in allowed:
                raise InputError(f"{name} must be one of {', '.join(allowed)}; got {getattr(self, name)!r}")
        if self.n_systems not in (1, 2):
            raise InputError(f"n_systems must be 1 or 2; got {self.n_systems}")
        if self.phantom == "grid" and self.n_systems != 1:
            raise InputError("n_systems must be 1 for phantom='grid' (the plate sits on one detector)")
        if self.supersample not in FIBONACCI:
            raise InputError(f"supersample must be one of {', '.join(map(str, FIBONACCI))}; got {self.supersample}")
        for name in ("n_frames", "image_size_px"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name} must be >= 1; got {getattr(self, name)}")
        if self.image_size_px < 16:
            raise InputError(f"image_size_px must be >= 16; got {self.image_size_px}")
        if not 1.0 < self.magnification < 3.0:
            raise InputError(f"magnification must lie in (1, 3); got {self.magnification}")
        if not 0 < self.fov_radius_frac <= 0.75:
            raise InputError(f"fov_radius_frac must lie in (0, 0.75]; got {self.fov_radius_frac}")
        if not 0 < self.bit_depth <= 16:
            raise InputError(f"bit_depth must lie in 1..16; got {self.bit_depth}")
        if self.n_markers < 0 or (self.marker_layout == "fixed" and self.n_markers > 8):
            raise InputError(
                f"n_markers must lie in 0..8 for the fixed marker layout, >= 0 otherwise; got {self.n_markers}"
            )
        if not 0 <= self.hidden_marker_fraction <= 1:
            raise InputError(f"hidden_marker_fraction must lie in [0, 1]; got {self.hidden_marker_fraction}")
        if not self.turntable_wobble_deg < 45:
            raise InputError(f"turntable_wobble_deg must be < 45; got {self.turntable_wobble_deg}")
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not (np.isfinite(value) and value >= 0):
                raise InputError(f"{f.name} must be a finite number >= 0; got {value}")

    @property
    def pixel_pitch_mm(self) -> float:
        """Detector pixel pitch (mm)."""
        return self.detector_size_mm / self.image_size_px

    @property
    def px_scale(self) -> float:
        """Image size relative to 1024 px (px amplitudes are quoted for 1024)."""
        return self.image_size_px / 1024.0

    @property
    def fov_radius_px(self) -> float:
        return self.fov_radius_frac * self.image_size_px

    @property
    def image_centre_xy_px(self) -> np.ndarray:
        return np.full(2, (self.image_size_px - 1) / 2.0)
