"""Acquisition geometry: systems placed in the lab (system angle, misalignment, IOP) and turntable poses."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from fluorocal.stages.artifacts import freeze
from fluorocal.stages.errors import InputError
from fluorocal.stages.geometry import matrix_to_quat, quat_to_matrix
from fluorocal.stages.simulate.distortion import ImageDistortion, make_distortion
from fluorocal.stages.simulate.orientation import angle_codes, make_orientations
from fluorocal.stages.simulate.params import RNG_ACQ, RNG_WOBBLE, SYSTEM_NAMES, SimulateParams


@dataclass(frozen=True, eq=False)
class SystemTruth:
    """One imaging system's true geometry.

    Attributes
    ----------
    name : str
    iop_px : (3,) float64 ndarray, px
        ``(xp, yp, c)``.
    distortion : ImageDistortion
    lab_from_camera_q : (4,) float64 ndarray
        Quaternion rotating camera-frame vectors into the lab frame (z up).
    source_lab_mm : (3,) float64 ndarray, mm
        Source position in the lab frame (isocentre at the origin).
    source_image_distance_mm : float, mm
    """

    name: str
    iop_px: np.ndarray
    distortion: ImageDistortion
    lab_from_camera_q: np.ndarray
    source_lab_mm: np.ndarray
    source_image_distance_mm: float

    def __post_init__(self):
        freeze(self)


@dataclass(frozen=True, eq=False)
class Acquisition:
    """Systems and exposures: everything geometric except the phantom.

    Attributes
    ----------
    systems : tuple of SystemTruth
    turntable_angle_rad : (K,) float64 ndarray, rad
        Phantom rotation about the vertical lab axis at each exposure.
    turntable_translation_mm : (K, 3) float64 ndarray, mm
        Phantom origin in the lab frame at each exposure.
    lab_from_phantom_q : (K, 4) float64 ndarray
        Phantom orientation at each exposure (for a cube: the turntable rotation).
    q : (S, K, 4) float64 ndarray
        Camera pose rotation (object -> camera) of system s at exposure k.
    source_mm : (S, K, 3) float64 ndarray, mm
        X-ray source in object (phantom) coordinates.
    orientations : tuple of Orientation
        The C-arm orientations of a grid sequence (empty: every exposure at the centred orientation).
    exposure_orientation : (K,) int64 ndarray
        Index into ``orientations`` of each exposure; -1 without orientations.

    Notes
    -----
    With orientations, the plate rides on system A's intensifier:
    ``lab_from_phantom_q`` and ``turntable_translation_mm`` place it as if the
    C-arm stayed centred (what matters, its pose relative to the camera, is
    exact); the C-arm's turn is in the orientation's angles.
    """

    systems: tuple
    turntable_angle_rad: np.ndarray
    turntable_translation_mm: np.ndarray
    lab_from_phantom_q: np.ndarray
    q: np.ndarray
    source_mm: np.ndarray
    orientations: tuple = ()
    exposure_orientation: np.ndarray | None = None

    def __post_init__(self):
        if self.exposure_orientation is None:
            object.__setattr__(self, "exposure_orientation", np.full(len(self.turntable_angle_rad), -1, np.int64))
        freeze(self)

    def system_at(self, s: int, k: int) -> SystemTruth:
        """System ``s`` as it images exposure ``k``: with the distortion of that exposure's orientation."""
        o = int(self.exposure_orientation[k])
        if o < 0:
            return self.systems[s]
        return replace(self.systems[s], distortion=self.orientations[o].distortion)


def _rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _small_rotation(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    return quat_to_matrix(np.concatenate([[1.0], np.radians(rng.uniform(-max_deg, max_deg, 3)) / 2]))


def _turntable_angles(params: SimulateParams) -> np.ndarray:
    """``n_frames`` angles spread evenly over those that keep every system off edge-on walls.

    With ``turntable_step_deg``, the angles step by it from the first of those instead.
    """
    candidates = np.radians(np.arange(0.0, 360.0, 0.25))
    ok = np.ones(candidates.shape, dtype=bool)
    for s in range(params.n_systems):
        rel = np.degrees(np.radians(s * params.system_angle_deg) - candidates) % 90.0
        ok &= np.minimum(rel, 90.0 - rel) >= params.min_face_angle_deg
    allowed = candidates[ok]
    if allowed.size == 0:
        raise InputError(
            f"min_face_angle_deg={params.min_face_angle_deg} leaves no turntable angle"
            f" for system_angle_deg={params.system_angle_deg}"
        )
    if params.turntable_step_deg > 0:
        return allowed[0] + np.radians(params.turntable_step_deg) * np.arange(params.n_frames)
    idx = ((np.arange(params.n_frames) + 0.5) * allowed.size / params.n_frames).astype(int)
    return allowed[idx]


def _wobble(params: SimulateParams) -> np.ndarray:
    """``(n_frames, 3, 3)`` tilts of the turntable's axis: up to ``turntable_wobble_deg`` in a random direction."""
    k = params.n_frames
    if not params.turntable_wobble_deg > 0:
        return np.broadcast_to(np.eye(3), (k, 3, 3))
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng([params.seed, RNG_WOBBLE])
    tilt = np.radians(rng.uniform(0.0, params.turntable_wobble_deg, k))
    direction = rng.uniform(0.0, 2 * np.pi, k)
    # a rotation about a horizontal lab axis tilts the vertical axis
    return Rotation.from_rotvec(
        tilt[:, None] * np.column_stack([np.cos(direction), np.sin(direction), np.zeros(k)])
    ).as_matrix()


def make_acquisition(params: SimulateParams) -> Acquisition:
    """Place the systems in the lab and the phantom on the turntable for every exposure.

    Lab frame: z up, isocentre at the origin. System s looks horizontally
    along azimuth ``s * system_angle_deg``; camera y points down (image rows).
    """
    rng = np.random.default_rng([params.seed, RNG_ACQ])
    sod_mm = params.source_image_distance_mm / params.magnification
    systems = []
    for s in range(params.n_systems):
        phi = np.radians(s * params.system_angle_deg)
        view = np.array([np.cos(phi), np.sin(phi), 0.0])
        down = np.array([0.0, 0.0, -1.0])
        # rows: camera x, y, z expressed in lab coordinates (camera_from_lab)
        nominal = np.stack([np.cross(down, view), down, view])
        camera_from_lab = _small_rotation(rng, params.system_misalignment_deg) @ nominal
        sid = params.source_image_distance_mm * rng.uniform(0.99, 1.01)
        offset = rng.uniform(-1, 1, 2) * params.principal_point_offset_px * params.px_scale
        iop = np.array([*(params.image_centre_xy_px + offset), sid / params.pixel_pitch_mm])
        systems.append(
            SystemTruth(
                SYSTEM_NAMES[s],
                iop,
                make_distortion(params, s),
                matrix_to_quat(camera_from_lab.T),
                -sod_mm * view,
                float(sid),
            )
        )
    k = params.n_exposures
    orientations, exposure_orientation = (), None
    if params.orientations_deg:
        orientations = make_orientations(params, systems[0].distortion)
        exposure_orientation = np.repeat(np.arange(len(orientations)), params.n_frames)
        angles, lab_from_phantom, translation = _plate_on_intensifier(params, rng, systems[0], orientations)
    elif params.phantom == "cube":
        angles = _turntable_angles(params)
        heights = np.linspace(-1, 1, k) if k > 1 else np.zeros(1)
        heights = rng.permutation(heights) * params.turntable_height_mm
        shifts = rng.uniform(-1, 1, (k, 2)) * params.turntable_translation_mm
        translation = np.column_stack([shifts, heights])
        lab_from_phantom = np.stack([tilt @ _rot_z(a) for tilt, a in zip(_wobble(params), angles)])
    else:
        # plate on system A's detector face, normal along the beam, small tilts and shifts
        angles = rng.uniform(0, 2 * np.pi, k)
        view = quat_to_matrix(systems[0].lab_from_camera_q)
        lab_from_phantom = np.stack([view @ _small_rotation(rng, 5.0) @ _rot_z(a) for a in angles])
        depth = params.source_image_distance_mm / params.grid_magnification
        # shifts in camera coordinates: up to 5 mm across the beam, 1 mm along it
        shifts = (rng.uniform(-5, 5, (k, 3)) * [1.0, 1.0, 0.2]) @ view.T
        translation = systems[0].source_lab_mm + depth * view[:, 2] + shifts
    q = np.empty((params.n_systems, k, 4))
    source = np.empty((params.n_systems, k, 3))
    for s, system in enumerate(systems):
        camera_from_lab = quat_to_matrix(system.lab_from_camera_q).T
        for i in range(k):
            # p_cam = C (R_k P + t_k - S) = (C R_k) (P - R_kᵀ (S - t_k))
            q[s, i] = matrix_to_quat(camera_from_lab @ lab_from_phantom[i])
            source[s, i] = lab_from_phantom[i].T @ (system.source_lab_mm - translation[i])
    return Acquisition(
        tuple(systems),
        np.asarray(angles, dtype=np.float64),
        translation,
        matrix_to_quat(lab_from_phantom),
        q,
        source,
        orientations,
        exposure_orientation,
    )


def _plate_on_intensifier(params: SimulateParams, rng: np.random.Generator, system: SystemTruth, orientations: tuple):
    """Plate poses of a grid sequence: mounted on the intensifier, moving a little between orientations.

    The mount (drawn from ``rng``): rows within 2 degrees of the image rows,
    the plate within 0.5 degree of square to the beam, its centre within 2 mm
    of the axis. Each orientation adds its own play (up to ``plate_play_mm``
    per axis across the beam and ``plate_play_deg`` about it), seeded by the
    orientation's angles, so an orientation looks the same whichever others
    are simulated with it. Every exposure of an orientation has its pose.

    Returns
    -------
    angles : (K,) float64 ndarray, rad
        The plate's turn about its normal.
    lab_from_phantom : (K, 3, 3) float64 ndarray
    translation : (K, 3) float64 ndarray, mm
    """
    view = quat_to_matrix(system.lab_from_camera_q)
    mount_angle = np.radians(rng.uniform(-2.0, 2.0))
    mount = _small_rotation(rng, 0.5) @ _rot_z(mount_angle)
    mount_shift = np.append(rng.uniform(-2.0, 2.0, 2), 0.0)
    depth = params.source_image_distance_mm / params.grid_magnification
    angles, poses, shifts = [], [], []
    for o in orientations:
        play = np.random.default_rng([params.seed, RNG_ACQ, *angle_codes(o.orbit_deg, o.tilt_deg)])
        turn = np.radians(play.uniform(-1.0, 1.0) * params.plate_play_deg)
        shift = mount_shift + np.append(play.uniform(-1.0, 1.0, 2) * params.plate_play_mm, 0.0)
        angles += [mount_angle + turn] * params.n_frames
        poses += [view @ _rot_z(turn) @ mount] * params.n_frames
        shifts += [system.source_lab_mm + depth * view[:, 2] + view @ shift] * params.n_frames
    return np.array(angles), np.stack(poses), np.array(shifts)
