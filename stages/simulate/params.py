"""Parameters of the simulator (:class:`SimulateParams`) and its constants: version, system names, seed streams."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from fluorocal.stages.errors import InputError

VERSION = 2
SYSTEM_NAMES = ("A", "B")
#: points on each outline used for the distorted outline centre and apparent diameter
N_OUTLINE = 256
#: Fibonacci numbers allowed as sub-sample counts of edge pixels
FIBONACCI = (5, 8, 13, 21, 34, 55, 89, 144)

#: noise correlation (px) of the real frames (default for the grid; the cube keeps white noise)
_GRID_NOISE_CORRELATION_PX = 0.72

# seed-sequence tags, so each random quantity has its own stream and the
# geometry does not depend on whether frames were rendered
RNG_PHANTOM, RNG_ACQ, RNG_DIST, RNG_NOISE = 1, 2, 3, 4
# streams of the optional motion and marker variations (their own, so the defaults draw what they always drew)
RNG_WOBBLE, RNG_MARKERS, RNG_HIDDEN = 5, 6, 7
#: marker layouts of the cube: the design's fixed slots, or beads drawn at random
MARKER_LAYOUTS = ("fixed", "random")


#: largest simulated image side (px): a 16-bit frame of 16384 px is 512 MB, rendered supersampled
MAX_IMAGE_SIZE_PX = 16384


@dataclass(frozen=True)
class SimulateParams:
    """Parameters of a simulated acquisition (defaults give ARCADIS-like 1024² frames).

    Lengths in mm are physical (detector plane or object space); px values
    derived from them scale with ``image_size_px``. Distortion amplitudes are
    quoted in px for a 1024-px image and scale with the image size.

    Attributes
    ----------
    n_frames : int, default 12
        Exposures per system; with ``orientations_deg``, exposures per orientation.
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
    grid_pitch_mm, grid_hole_diameter_mm, grid_thickness_mm : float, default 3.6, 2.0, 0.9
        With ``grid_magnification`` they give the real ARCADIS frames' look: holes ~15.4 px apart and
        ~8 px wide (FWHM), the plate ~0.48 of a hole's level.
    grid_size_mm : float, default 250.0
        Diameter of the perforated region of the plate.
    grid_magnification : float, default 1.07
        The plate sits near the detector face.
    grid_exposure_gain : float, default 1.6
        Dose factor of the automatic brightness control with the plate in the beam (it absorbs
        about half the field): real grid frames' holes reach ~2900 DN where a bead frame's open
        field is ~1600 DN.
    fabrication_error_mm : float, default 0.1
        3D RMS of true - nominal bead positions (cube).
    plate_error_mm : float, default 0.02
        2D RMS of true - nominal hole positions (grid), structured like a drilled plate's errors:
        a displacement per lattice row, alternate rows offset along the rows, and per-hole jitter
        (see :func:`make_phantom`).
    orientations_deg : tuple of (float, float), default ()
        C-arm orientations ``(orbit, tilt)`` in degrees (grid only), each exposed ``n_frames``
        times with the plate riding on the intensifier (it moves by ``plate_play_mm`` /
        ``plate_play_deg`` between orientations) and the distortion changed by the earth's field
        (:mod:`.orientation`). Empty: every exposure at the centred orientation, the plate
        repositioned by hand between exposures (random turn, tilt up to 5 degrees, shift up to 5 mm).
    plate_play_mm, plate_play_deg : float, default 0.6, 0.2
        Half-ranges of the plate's shift (per axis) and turn on the intensifier between orientations.
    earth_field_inclination_deg, earth_field_heading_deg : float, default 65.0, 315.0
        Direction of the earth's magnetic field: its dip below the horizontal and the direction
        of its horizontal part in image coordinates at the centred orientation (from +x toward +y).
    orientation_distortion_px : float, default 0.96
        Sensitivity of the distortion to the earth's field (px at 1024): RMS over the field of
        view, modulo a homography, of the change per unit change of the field across the
        intensifier's axis (:mod:`.orientation`). The defaults give the real C-arm's figures:
        the centred correction leaves 0.20 px at 15 degrees, 0.37-0.39 px at 30, 0.52-0.54 at 45,
        0.62-0.66 at 60 (orbit or tilt). 0 turns it off.
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
    noise_correlation_px : float, optional
        Sigma (px) of the Gaussian that correlates neighbouring pixels' noise (the per-pixel
        spread is kept). The real frames' noise, after removing a sigma = 3 px Gaussian
        background, correlates 0.54 at one pixel; 0.72 px gives 0.53. Default (None): 0.72 for
        the grid, 0 (white) for the cube, whose frames are kept as earlier versions rendered them.
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
    grid_hole_diameter_mm: float = 2.0
    grid_thickness_mm: float = 0.9
    grid_size_mm: float = 250.0
    grid_magnification: float = 1.07
    grid_exposure_gain: float = 1.6
    fabrication_error_mm: float = 0.1
    plate_error_mm: float = 0.02
    orientations_deg: tuple = ()
    plate_play_mm: float = 0.6
    plate_play_deg: float = 0.2
    earth_field_inclination_deg: float = 65.0
    earth_field_heading_deg: float = 315.0
    orientation_distortion_px: float = 0.96
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
    noise_correlation_px: float | None = None
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
        if not 16 <= self.image_size_px <= MAX_IMAGE_SIZE_PX:  # beyond it the frames' arrays exhaust memory
            raise InputError(f"image_size_px must lie in 16..{MAX_IMAGE_SIZE_PX}; got {self.image_size_px}")
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
        object.__setattr__(self, "orientations_deg", _check_orientations(self.orientations_deg, self.phantom))

    @property
    def noise_sigma_px(self) -> float:
        """``noise_correlation_px``, or its default for the phantom when None."""
        if self.noise_correlation_px is not None:
            return float(self.noise_correlation_px)
        return _GRID_NOISE_CORRELATION_PX if self.phantom == "grid" else 0.0

    @property
    def n_exposures(self) -> int:
        """Exposures per system: ``n_frames`` per orientation (one orientation if none are given)."""
        return self.n_frames * max(1, len(self.orientations_deg))

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


def _check_orientations(value, phantom: str) -> tuple:
    """``orientations_deg`` as a tuple of distinct ``(orbit, tilt)`` float pairs within ±90 degrees."""
    try:
        pairs = tuple((float(o), float(t)) for o, t in value)
    except (TypeError, ValueError):
        raise InputError(f"orientations_deg must be (orbit, tilt) pairs in degrees; got {value!r}") from None
    if pairs and phantom != "grid":
        raise InputError("orientations_deg needs phantom='grid' (the cube turns on a turntable, the C-arm stays)")
    for pair in pairs:
        if not all(np.isfinite(a) and abs(a) <= 90 for a in pair):
            raise InputError(f"orientations_deg angles must be finite and within ±90 degrees; got {pair}")
    if len(set(pairs)) != len(pairs):
        raise InputError(f"orientations_deg must not repeat an orientation; got {pairs}")
    return pairs
