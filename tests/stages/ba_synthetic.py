"""Synthetic bundle-adjustment problems and a scipy reference solver (shared by tests and benchmarks/adjust.py).

Geometry: beads on four vertical faces of a cube (edge ``cube_mm``), seen by
a fluoroscope with the source ``distance_mm`` from the cube's centre, principal
distance ``c = 4400 px`` (SID 1100 mm at 0.25 mm pixels), a 1024 x 1024 image.
The phantom turns on a turntable (angle about the vertical object y axis) and
is tilted by up to ``tilt_deg`` about the horizontal axis and shifted by a few
mm between exposures: pure turntable motion (all rotations about one axis) is
a critical motion for self-calibration (the principal point's y and the tilt
are then inseparable), which the real acquisition avoided by moving the cube.
A second system (biplanar) views the same epochs from ``rop_deg`` around the
vertical axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.adjust import Orientation
from fluorocal.stages.artifacts import Observations
from fluorocal.stages.geometry import (
    matrix_to_quat,
    project,
    quat_multiply,
    quat_normalize,
    quat_to_matrix,
    rotvec_to_quat,
)
from fluorocal.stages.simulate import SimulateParams, simulate

IMAGE_PX = 1024
#: the centroid noise of :func:`simulated_set`'s noisy observations, px
NOISE_PX = 0.05
#: the adjustment tests' two standard problems (test_adjust.py, test_adjust_model.py): one system, and two
MONO = dict(n_beads=200, n_exposures=14, seed=1)
BIPLANAR = dict(n_beads=160, n_exposures=10, n_systems=2, seed=2)


@dataclass(frozen=True)
class Synthetic:
    """A synthetic acquisition: truth, noisy observations and a perturbed start."""

    observations: Observations
    ids: np.ndarray
    xyz_true_mm: np.ndarray
    nominal_mm: np.ndarray
    truth: Orientation
    initial: Orientation
    ideal_px: np.ndarray  # noise-free projections, (N, 2)


def _rot_quat(rotvec) -> np.ndarray:
    return rotvec_to_quat(np.asarray(rotvec, dtype=np.float64))


def cube_phantom(n_beads: int, rng: np.random.Generator, cube_mm: float = 120.0) -> np.ndarray:
    """``(n_beads, 3)`` mm: beads on the four faces x = ±h and z = ±h, |other| < 0.9 h."""
    h = cube_mm / 2
    face = np.arange(n_beads) % 4
    a = rng.uniform(-0.9 * h, 0.9 * h, n_beads)
    b = rng.uniform(-0.9 * h, 0.9 * h, n_beads)
    sign = np.where(face % 2 == 0, 1.0, -1.0) * h
    x = np.where(face < 2, sign, a)
    z = np.where(face < 2, a, sign)
    return np.column_stack([x, b, z])


def make_problem(
    *,
    n_beads: int = 200,
    n_exposures: int = 12,
    n_systems: int = 1,
    noise_px: float = 0.05,
    visible_fraction: float = 1.0,
    tilt_deg: float = 15.0,
    distance_mm: float = 950.0,
    iop_px=(512.0, 512.0, 4400.0),
    rop_deg: float = 90.0,
    nominal_error_mm: float = 0.3,
    start_error: float = 1.0,
    seed: int = 0,
) -> Synthetic:
    """A seeded synthetic problem; ``start_error`` scales the perturbation of the start values."""
    rng = np.random.default_rng(seed)
    xyz = cube_phantom(n_beads, rng)
    ids = np.arange(100, 100 + n_beads, dtype=np.int64)
    q, src = _turntable_ring(n_exposures, tilt_deg, distance_mm, rng)
    rig = _rig(n_systems, iop_px, rop_deg, distance_mm)
    truth = _orientation(q, src, *rig)
    obs, ideal = _observed(truth, xyz, ids, noise_px, visible_fraction, rng)
    initial = _orientation(*_perturbed(q, src, *rig, start_error, rng))
    nominal = xyz + rng.normal(0, nominal_error_mm, xyz.shape)
    return Synthetic(obs, ids, xyz, nominal, truth, initial, ideal)


def _turntable_ring(n_exposures, tilt_deg, distance_mm, rng) -> tuple[np.ndarray, np.ndarray]:
    """Poses ``(q_cam_from_obj (M, 4), source_mm (M, 3))``: a turntable ring, tilted and shifted a few mm."""
    angles = np.linspace(0, 2 * np.pi, n_exposures, endpoint=False) + rng.uniform(-0.05, 0.05, n_exposures)
    tilts = np.deg2rad(tilt_deg) * np.sin(np.arange(n_exposures) * 2.4 + 0.3)
    q = np.array([quat_multiply(_rot_quat([t, 0, 0]), _rot_quat([0, a, 0])) for t, a in zip(tilts, angles)])
    offset = np.column_stack(
        [
            rng.uniform(-10, 10, n_exposures),
            rng.uniform(-15, 15, n_exposures),
            distance_mm + rng.uniform(-20, 20, n_exposures),
        ]
    )
    R = quat_to_matrix(q)
    return q, -np.einsum("mji,mj->mi", R, offset)


def _rig(n_systems, iop_px, rop_deg, distance_mm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(iop_px, rop_q, rop_source_mm)`` per system: system B ``rop_deg`` around the vertical, its IOP a little off."""
    iop = np.tile(np.asarray(iop_px, dtype=np.float64), (n_systems, 1))
    rop_q = np.tile([1.0, 0, 0, 0], (n_systems, 1))
    rop_t = np.zeros((n_systems, 3))
    for s in range(1, n_systems):
        iop[s] += [6.0, -4.0, 30.0]
        rop_q[s] = quat_multiply(_rot_quat([0.02, 0, 0.01]), _rot_quat([0, np.deg2rad(rop_deg), 0]))
        Rr = quat_to_matrix(rop_q[s])
        centre = np.array([0.0, 0.0, distance_mm])
        rop_t[s] = centre - Rr.T @ (centre + [3.0, -2.0, 40.0])
    return iop, rop_q, rop_t


def _orientation(q, src, iop, rop_q, rop_t) -> Orientation:
    return Orientation(
        iop_px=iop,
        exposure=np.arange(len(q)),
        q_cam_from_obj=q,
        source_mm=src,
        rop_q=rop_q,
        rop_source_mm=rop_t,
        system_names=tuple("AB"[: len(iop)]),
    )


def _perturbed(q, src, iop, rop_q, rop_t, f: float, rng) -> tuple[np.ndarray, ...]:
    """The start values: rotations ~0.005 f rad, sources ~3 f mm off, the IOP by a fixed offset times f."""
    n_systems = len(iop)
    q0 = np.array([quat_multiply(_rot_quat(rng.normal(0, f * 0.005, 3)), qq) for qq in q])
    src0 = src + rng.normal(0, f * 3.0, src.shape)
    rop_q0 = np.array(
        [quat_multiply(_rot_quat(rng.normal(0, f * 0.005, 3)), qq) if s else qq for s, qq in enumerate(rop_q)]
    )
    rop_t0 = rop_t + (np.arange(n_systems) > 0)[:, None] * rng.normal(0, f * 3.0, (n_systems, 3))
    return q0, src0, iop + f * np.array([8.0, -6.0, -60.0]), rop_q0, rop_t0


def _observed(truth: Orientation, xyz, ids, noise_px, visible_fraction, rng) -> tuple[Observations, np.ndarray]:
    """Every bead projected inside the image (a ``visible_fraction`` of them) plus noise; and the noise-free points."""
    rows = []
    for s in range(len(truth.iop_px)):
        qs, Ts = truth.poses(s)
        for j in range(len(truth.exposure)):
            xy = project(xyz, qs[j], Ts[j], truth.iop_px[s])
            inside = np.all((xy > 5) & (xy < IMAGE_PX - 6), axis=1) & (rng.random(len(ids)) < visible_fraction)
            k = np.flatnonzero(inside)
            rows.append((np.full(len(k), s), np.full(len(k), j), ids[k], xy[k]))
    system, exposure, bead, ideal = (np.concatenate(c) for c in zip(*rows))
    n = len(system)
    xy = ideal + rng.normal(0, noise_px, (n, 2))
    obs = Observations(
        system=system,
        exposure=exposure,
        bead_id=bead,
        xy_px=xy,
        sigma_px=np.tile([noise_px, noise_px, 0.0], (n, 1)),
        system_names=truth.system_names,
    )
    return obs, ideal


def with_xy(obs: Observations, xy: np.ndarray, bead_id=None) -> Observations:
    """``obs`` with the coordinates ``xy`` (and the ids ``bead_id`` if given)."""
    return Observations(
        obs.system, obs.exposure, obs.bead_id if bead_id is None else bead_id, xy, obs.sigma_px, obs.system_names
    )


def rms(a) -> float:
    """Root mean square of all the entries of ``a``."""
    return float(np.sqrt(np.mean(np.square(a))))


def aligned_error_mm(estimate_mm: np.ndarray, truth_mm: np.ndarray) -> np.ndarray:
    """Per point 3D error (mm) after the least-squares 7-parameter similarity of the estimate onto the truth."""
    from fluorocal.stages.geometry import similarity_fit

    s, R, t = similarity_fit(estimate_mm, truth_mm)
    return np.linalg.norm(s * estimate_mm @ R.T + t - truth_mm, axis=1)


# --------------------------------------------------------------------------- scipy reference


class ScipyProblem:
    """The same model for ``scipy.optimize.least_squares``: rotation vectors, whitened residuals, datum rows.

    Parameters ``x = [points (3n), per epoch (rotvec (3), T (3)), IOP (3 per system, if free), per system >= 1
    (ROP rotvec (3), b (3))]``. Rotations are ``R = exp(ω) R_start``. The 7 datum rows
    ``D^T (P - P_nominal)`` are exact at the optimum (they act only in the gauge directions).
    """

    def __init__(self, syn: Synthetic, estimate_iop: bool = True, corrections_px=None):
        from fluorocal.stages.adjust.problem import datum_directions

        obs = syn.observations
        self.n, self.m, self.S = len(syn.ids), len(syn.initial.exposure), syn.initial.n_systems
        self.pt = np.searchsorted(syn.ids, obs.bead_id)
        self.ep = np.searchsorted(syn.initial.exposure, obs.exposure)
        self.sy = obs.system
        corr = np.zeros((len(obs), 2)) if corrections_px is None else corrections_px
        self.meas = obs.xy_px - corr
        self.sig = obs.sigma_px[:, :2]
        self.nominal = syn.nominal_mm
        self.datum = datum_directions(syn.nominal_mm).reshape(-1, 7)
        self.estimate_iop = estimate_iop
        self.init = syn.initial
        self.R0 = quat_to_matrix(syn.initial.q_cam_from_obj)
        self.Rr0 = quat_to_matrix(syn.initial.rop_q)
        self.n_iop = 3 * self.S if estimate_iop else 0

    def x0(self) -> np.ndarray:
        i = self.init
        poses = np.column_stack([np.zeros((self.m, 3)), i.source_mm])
        parts = [self.nominal.ravel(), poses.ravel()]
        if self.estimate_iop:
            parts.append(i.iop_px.ravel())
        parts.append(np.column_stack([np.zeros((self.S - 1, 3)), i.rop_source_mm[1:]]).ravel())
        return np.concatenate(parts)

    def unpack(self, x):
        from scipy.spatial.transform import Rotation

        n3, m6 = 3 * self.n, 6 * self.m
        P = x[:n3].reshape(-1, 3)
        poses = x[n3 : n3 + m6].reshape(-1, 6)
        R = Rotation.from_rotvec(poses[:, :3]).as_matrix() @ self.R0
        iop = x[n3 + m6 : n3 + m6 + self.n_iop].reshape(-1, 3) if self.estimate_iop else self.init.iop_px
        rop = x[n3 + m6 + self.n_iop :].reshape(-1, 6)
        Rr = (
            np.concatenate([np.eye(3)[None], Rotation.from_rotvec(rop[:, :3]).as_matrix() @ self.Rr0[1:]])
            if self.S > 1
            else np.eye(3)[None]
        )
        b = np.concatenate([np.zeros((1, 3)), rop[:, 3:]])
        return P, R, poses[:, 3:], iop, Rr, b

    def residuals(self, x, datum_weight: float = 1.0):
        P, R, T, iop, Rr, b = self.unpack(x)
        pa = np.einsum("nij,nj->ni", R[self.ep], P[self.pt] - T[self.ep])
        p = np.einsum("nij,nj->ni", Rr[self.sy], pa - b[self.sy])
        f = iop[self.sy, :2] + iop[self.sy, 2:] * p[:, :2] / p[:, 2:]
        e = ((self.meas - f) / self.sig).ravel()
        return np.concatenate([e, datum_weight * self.datum.T @ (P - self.nominal).ravel()])

    def sparsity(self):
        from scipy.sparse import lil_matrix

        N = len(self.pt)
        nx = len(self.x0())
        A = lil_matrix((2 * N + 7, nx), dtype=np.int8)
        rows = np.arange(N)
        n3, m6 = 3 * self.n, 6 * self.m
        for k in range(2):
            r = 2 * rows + k
            for a in range(3):
                A[r, 3 * self.pt + a] = 1
            for a in range(6):
                A[r, n3 + 6 * self.ep + a] = 1
            if self.estimate_iop:
                for a in range(3):
                    A[r, n3 + m6 + 3 * self.sy + a] = 1
            sel = self.sy > 0
            for a in range(6):
                A[r[sel], n3 + m6 + self.n_iop + 6 * (self.sy[sel] - 1) + a] = 1
        A[2 * N :, :n3] = 1
        return A.tocsr()


# --------------------------------------------------------------------------- pycolmap (benchmark only)


def pycolmap_reconstruction(syn: Synthetic, xy_px: np.ndarray):
    """The same observations as a pycolmap Reconstruction (one SIMPLE_PINHOLE camera per system; monoplanar only).

    COLMAP puts the top-left pixel's corner at (0, 0), so 0.5 px is added to the
    image coordinates and the principal point.
    """
    import pycolmap

    obs = syn.observations
    init = syn.initial
    rec = pycolmap.Reconstruction()
    xp, yp, c = init.iop_px[0]
    cam = pycolmap.Camera(
        camera_id=1, model="SIMPLE_PINHOLE", width=IMAGE_PX, height=IMAGE_PX, params=[c, xp + 0.5, yp + 0.5]
    )
    rec.add_camera_with_trivial_rig(cam)
    point_ids = {}
    for i, b in enumerate(syn.ids):
        point_ids[int(b)] = rec.add_point3D(syn.nominal_mm[i], pycolmap.Track())
    R = quat_to_matrix(init.q_cam_from_obj)
    for j, e in enumerate(init.exposure):
        sel = np.flatnonzero(obs.exposure == e)
        pts = pycolmap.Point2DList([pycolmap.Point2D(xy_px[k] + 0.5) for k in sel])
        image = pycolmap.Image(name=f"{e}", points2D=pts, camera_id=1, image_id=j + 1)
        t = -R[j] @ init.source_mm[j]
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(np.column_stack([R[j], t])))
        for n, k in enumerate(sel):
            rec.add_observation(point_ids[int(obs.bead_id[k])], pycolmap.TrackElement(j + 1, n))
    return rec


def simulated_set(seed: int, n_train: int, size: int):
    """Training observations (noisy and exact), held-out ones with their true ideal points, start values, truth."""
    data = simulate(
        SimulateParams(n_frames=2 * n_train, n_systems=1, seed=seed, image_size_px=size, distortion="strong"),
        render=False,
    )
    rng = np.random.default_rng([seed, 3])
    sets = []
    for part in (0, 1):
        frames = [f for f in data.truth.frames[0] if f.exposure % 2 == part]
        keep = [f.visible for f in frames]
        exposure = np.concatenate([np.full(k.sum(), f.exposure // 2) for f, k in zip(frames, keep)])
        ids = np.concatenate([f.ids[k] for f, k in zip(frames, keep)])
        exact = np.concatenate([f.distorted_xy_px[k] for f, k in zip(frames, keep)])
        ideal = np.concatenate([f.ideal_xy_px[k] for f, k in zip(frames, keep)])
        sigma = np.tile([NOISE_PX, NOISE_PX, 0.0], (len(exact), 1))
        noisy = exact + rng.normal(0, NOISE_PX, exact.shape)
        system = np.zeros(len(exact), np.int64)
        sets.append([Observations(system, exposure, ids, v, sigma) for v in (noisy, exact)] + [ideal])
    acq = data.truth.acquisition
    true_sys = acq.systems[0]
    epochs = np.arange(0, 2 * n_train, 2)
    # start values: the true poses, the IOP 1 % and the image centre off (as from the nominal geometry)
    iop0 = np.array([[(size - 1) / 2, (size - 1) / 2, true_sys.iop_px[2] * 1.01]])
    initial = Orientation(iop0, np.arange(n_train), acq.q[0, epochs], acq.source_mm[0, epochs], system_names=("A",))
    return sets, initial, data.phantom, true_sys


def simulated_sets(n_train: int, n_systems: int, size: int, seed: int):
    """Training and held-out observation sets, the nominal phantom, initial orientations and the truth."""
    p = SimulateParams(n_frames=2 * n_train, n_systems=n_systems, seed=seed, image_size_px=size, distortion="strong")
    data = simulate(p, render=False)
    acq = data.truth.acquisition
    rng = np.random.default_rng([seed, 7])
    sets = []
    for part in (0, 1):
        # the paper's uniform split: even exposures train, odd ones are held out
        obs = truth_observations(data, rng, lambda f, part=part: f.exposure % 2 == part, lambda e: e // 2)
        sets.append((obs, rough_start(acq, np.arange(part, p.n_frames, 2), size, rng)))
    return sets, data.phantom, data.truth.true_xyz_mm, acq, p


def truth_observations(data, rng, use=lambda frame: True, epoch=lambda exposure: exposure) -> Observations:
    """Observations of the simulator's frames where ``use(frame)``: true outline centres + ``NOISE_PX`` noise.

    Beads near another's outline or the field's rim are left out (labelling would not keep them
    reliably); ``epoch(exposure)`` numbers the epochs.
    """
    frames = [f for per_system in data.truth.frames for f in per_system if use(f)]
    keep = [~(f.overlap | f.field_edge) for f in frames]
    system = np.concatenate([np.full(k.sum(), f.system) for f, k in zip(frames, keep)])
    exposure = np.concatenate([np.full(k.sum(), epoch(f.exposure)) for f, k in zip(frames, keep)])
    ids = np.concatenate([f.ids[k] for f, k in zip(frames, keep)])
    xy = np.concatenate([f.outline_xy_px[k] for f, k in zip(frames, keep)])
    xy = xy + rng.normal(0, NOISE_PX, xy.shape)
    sigma = np.tile([NOISE_PX, NOISE_PX, 0.0], (len(xy), 1))
    return Observations(system, exposure, ids, xy, sigma, system_names=data.system_names)


def rough_start(acq, epochs, size, rng, source_sigma_mm: float = 5.0) -> Orientation:
    """Rough start values, as labelling would give: poses within ~0.6 deg and ``source_sigma_mm``, IOP nominal."""
    n = len(epochs)
    dq = np.array([rotvec_to_quat(v) for v in rng.normal(0, 0.01, (n, 3))])
    q = quat_normalize(quat_multiply(dq, acq.q[0, epochs]))
    src = acq.source_mm[0, epochs] + rng.normal(0, source_sigma_mm, (n, 3))
    iop = np.array([[(size - 1) / 2, (size - 1) / 2, s.iop_px[2] * 1.01] for s in acq.systems])
    rop_q = np.tile([1.0, 0, 0, 0], (len(acq.systems), 1))
    rop_t = np.zeros((len(acq.systems), 3))
    R0 = quat_to_matrix(acq.q[0, 0])
    for s in range(1, len(acq.systems)):
        rop_q[s] = matrix_to_quat(quat_to_matrix(acq.q[s, 0]) @ R0.T)
        rop_t[s] = R0 @ (acq.source_mm[s, 0] - acq.source_mm[0, 0])
    return Orientation(iop, np.arange(n), q, src, rop_q, rop_t, tuple(s.name for s in acq.systems))


def true_rig(acq) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The simulator's IOP ``(S, 3)`` px, ROP rotations ``(S, 4)`` and sources in A's camera frame ``(S, 3)`` mm.

    The rig is rigid (``stages.simulate.make_acquisition``), so epoch 0 gives the ROP.
    """
    R0 = quat_to_matrix(acq.q[0, 0])
    rop_q = np.array([matrix_to_quat(quat_to_matrix(acq.q[s, 0]) @ R0.T) for s in range(len(acq.systems))])
    rop_source = np.array([R0 @ (acq.source_mm[s, 0] - acq.source_mm[0, 0]) for s in range(len(acq.systems))])
    return np.array([s.iop_px for s in acq.systems]), rop_q, rop_source
