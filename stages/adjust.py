"""Robust bundle adjustment: Student-t maximum likelihood, free network, interior orientation, biplanar constraint.

The model is the collinearity equation (paper section IV, eq. 1; conventions
in :mod:`stages._geometry`)::

    ideal_o = xy_o - Δ_o = (xp_s, yp_s) + c_s * (p_x, p_y) / p_z,
    p = R_s (R_j (P_i - T_j) - b_s)

for observation ``o`` of bead ``i`` in epoch ``j`` by system ``s``. The
unknowns are every observed bead's coordinates ``P_i`` (the nominal
coordinates only start them), the reference system's pose ``(q_j, T_j)`` per
epoch, per system the IOP ``(xp, yp, c)`` (estimated or held fixed: the paper's
"kNN + IOP" versus "kNN" schemes) and, for systems ``s >= 1``, one relative
orientation (ROP) ``(R_s, b_s)`` for the whole acquisition: frames of
different systems with the same ``exposure`` index share the phantom's pose
(biplanar). System 0 has ``R_0 = I``, ``b_0 = 0``. The corrections ``Δ`` are
constants of a solve (the learning stage updates them between solves).
Optionally (``additional_parameters="polynomial"``) each system's global
polynomial distortion model (:mod:`stages._polynomial`: radial ``k1..k3``,
decentring ``p1, p2``, affinity ``b1, b2``) is estimated with everything else:
``ideal_o = xy_o - Δ_o - Δ_AP(xy_o; xp_s, yp_s)``.

Estimation maximises the likelihood of a 2-D Student-t of every observation
with covariance ``σ² C_o`` (eq. 2), ``C_o`` from the centroid stage's
``(σx, σy, ρ)`` and ``σ²`` a variance factor estimated with the parameters
(``estimate_scale``), by Levenberg–Marquardt with analytic Jacobians: the
exact gradient, and the IRLS Hessian with weights
``w = (ν + 2) / (ν + r^T C^-1 r / σ²)`` (with Triggs' curvature correction
once σ² has settled, which shortens the IRLS tail). The datum is the inner
constraints of the object points relative to their nominal coordinates
(translation, rotation, scale: the results are in mm in the nominal frame),
solved as a bordered system. Each step eliminates either the points or the
poses by a Schur complement, whichever leaves the smaller dense system (with
a fixed phantom and many exposures: the poses, so the cost grows linearly in
the number of exposures). Numerics live in :mod:`stages._ba`.

What cannot be estimated is dropped with a logged message (beads seen in
fewer than two epochs or along nearly one direction, epochs with too few
beads, duplicate labels); too few frames raise :class:`InputError`, all frames
from one pose or a singular network :class:`EstimationError`. A pure
turntable (every rotation about one axis) is a critical motion for the
principal point: tilt the phantom between exposures or fix the IOP.

Also here: :func:`initial_orientation` (start values by per-frame resection)
and :func:`adjust_plate` (a robust homography per frame for grid plates, with
the same per-observation outputs).

Examples
--------
>>> import numpy as np
>>> from fluorocal.stages._geometry import project, quat_to_matrix, rotvec_to_quat
>>> from fluorocal.stages.artifacts import Observations
>>> rng = np.random.default_rng(0)
>>> xyz = rng.uniform(-50, 50, (40, 3))
>>> angles = np.deg2rad(np.arange(0, 360, 40))
>>> q = np.array([rotvec_to_quat([0.3 * (-1) ** k, a, 0.0]) for k, a in enumerate(angles)])  # tilted: not all about one axis
>>> src = -np.einsum("mji,j->mi", quat_to_matrix(q), [0.0, 0.0, 700.0])
>>> iop = np.array([512.0, 512.0, 4400.0])
>>> xy = np.concatenate([project(xyz, q[j], src[j], iop) for j in range(len(q))])
>>> obs = Observations(system=np.zeros(len(xy)), exposure=np.repeat(np.arange(len(q)), 40),
...                    bead_id=np.tile(np.arange(40), len(q)), xy_px=xy, sigma_px=np.tile([0.05, 0.05, 0.0], (len(xy), 1)))
>>> start = Orientation(iop_px=[[510.0, 515.0, 4300.0]], exposure=np.arange(len(q)), q_cam_from_obj=q, source_mm=src + 1.0)
>>> result = adjust_bundle(obs, (np.arange(40), xyz), start)
>>> bool(result.usable), bool(np.allclose(result.iop_px, iop, atol=1e-6))
(True, True)
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, fields

import numpy as np
from fluorocal.stages import _ba, _polynomial
from fluorocal.stages._geometry import quat_multiply, quat_normalize, quat_to_matrix
from fluorocal.stages.artifacts import SCHEMA_VERSION, Observations, Phantom, check_shape, freeze
from fluorocal.stages.errors import EstimationError, InputError, ShapeError

log = logging.getLogger(__name__)

VERSION = 1


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class AdjustParams:
    """Options of :func:`adjust_bundle`.

    Attributes
    ----------
    nu : float
        Student-t degrees of freedom (default 4, the paper's choice); ``math.inf``
        gives least squares.
    estimate_nu : bool
        Estimate ν by maximum likelihood along with the parameters (default False).
    nu_bounds : tuple of float
        Search interval for ν when estimated (default (1, 1000)).
    estimate_scale : bool
        Estimate the variance factor σ² of the observation covariances by maximum
        likelihood (default True). Without it the t-weights trust ``sigma_px``
        absolutely, which flags everything while distortion is still unmodelled.
    estimate_iop : bool
        Estimate each system's ``(xp, yp, c)`` (default True: "kNN + IOP");
        False holds them at the initial values ("kNN").
    outlier_weight : float
        Observations whose final t-weight ``w = (ν+2)/(ν+r²)`` is below this are
        flagged as outliers (default 0.2, i.e. ``r² > 26`` at ν = 4: a 2-D Gaussian
        exceeds it with probability 2e-6).
    max_iterations : int
        Levenberg–Marquardt iteration cap (default 100).
    function_tolerance : float
        Stop when an accepted step lowers the negative log-likelihood by less
        than this (absolute; default 1e-5). A step of δ in a parameter of
        standard deviation σ changes it by about ½ (δ/σ)², so the stopping
        error is about ``sqrt(2 tol)`` σ.
    parameter_tolerance : float
        Stop when the step norm is below this times the parameter norm (default 1e-10).
    initial_damping : float
        Initial Marquardt damping μ of ``H + μ diag(H)`` (default 1e-6: the
        Gauss–Newton step is usually good from labelling's start values; a
        rejected step raises μ).
    min_exposures : int
        Fewest frames (system, exposure) the adjustment accepts (default 3).
    min_beads_per_exposure : int
        Epochs with fewer distinct beads are dropped (default 6; 3 determine a pose).
    min_exposures_per_bead : int
        Beads seen in fewer epochs are dropped (default 2; one ray cannot fix a point).
    min_ray_angle_deg : float
        Beads whose rays (at the initial orientation) span a smaller angle are
        dropped, as their depth is undetermined (default 1.0 degree).
    schur : str
        ``"auto"`` (default: eliminate points or poses, whichever leaves the smaller
        reduced system), ``"points"`` or ``"poses"``.
    min_inlier_fraction : float
        ``usable`` requires at least this fraction of inliers (default 0.5).
    compute_covariance : bool
        Compute the parameters' covariance and the observations' redundancy
        numbers (default True). False skips the dense inverse (about two
        thirds of a warm-started solve): standard deviations are then zero and
        every observation gets the mean redundancy ``dof / 2N`` (the learning
        loop's intermediate solves use this).
    additional_parameters : str
        ``"none"`` (default) or ``"polynomial"``: estimate per system the 7
        coefficients of the global polynomial distortion model of
        :mod:`stages._polynomial` (px at its reference radius), on top of any
        ``corrections_px``.
    fixed_additional_parameters : tuple of str
        Names among ``k1, k2, k3, p1, p2, b1, b2`` held at zero when
        ``additional_parameters="polynomial"`` (default ``("b1", "b2")``: Brown's
        radial and decentring model). In a free network the affinity is
        determined only through perspective, since a stretch or shear of the
        phantom nearly mimics it: on the simulator's turntable (75 exposures,
        c = 4400 px) estimating it drives ``c`` from 4370 to 2490 px and ``b1`` to
        270 px, with 19 mm 3D error out of sample (0.28 mm with it held). Pass
        ``()`` to estimate all seven where the network determines them (varied
        tilts, a deep phantom, or a near source).
    """

    nu: float = 4.0
    estimate_nu: bool = False
    nu_bounds: tuple = (1.0, 1000.0)
    estimate_scale: bool = True
    estimate_iop: bool = True
    outlier_weight: float = 0.2
    max_iterations: int = 100
    function_tolerance: float = 1e-5
    parameter_tolerance: float = 1e-10
    initial_damping: float = 1e-6
    min_exposures: int = 3
    min_beads_per_exposure: int = 6
    min_exposures_per_bead: int = 2
    min_ray_angle_deg: float = 1.0
    schur: str = "auto"
    min_inlier_fraction: float = 0.5
    compute_covariance: bool = True
    additional_parameters: str = "none"
    fixed_additional_parameters: tuple = ("b1", "b2")

    def __post_init__(self):
        object.__setattr__(self, "nu_bounds", tuple(float(b) for b in self.nu_bounds))
        object.__setattr__(self, "fixed_additional_parameters", tuple(str(n) for n in self.fixed_additional_parameters))
        if not self.nu > 0:
            raise InputError(f"nu must be > 0 (math.inf for least squares); got {self.nu}")
        lo, hi = self.nu_bounds
        if not 0 < lo < hi < math.inf:
            raise InputError(f"nu_bounds must satisfy 0 < low < high < inf; got {self.nu_bounds}")
        if not 0 <= self.outlier_weight <= 1:
            raise InputError(f"outlier_weight must lie in [0, 1]; got {self.outlier_weight}")
        if self.max_iterations < 1:
            raise InputError(f"max_iterations must be >= 1; got {self.max_iterations}")
        if self.schur not in ("auto", "points", "poses"):
            raise InputError(f"schur must be 'auto', 'points' or 'poses'; got {self.schur!r}")
        if self.additional_parameters not in ("none", "polynomial"):
            raise InputError(
                f"additional_parameters must be 'none' or 'polynomial'; got {self.additional_parameters!r}"
            )
        unknown = set(self.fixed_additional_parameters) - set(_polynomial.AP_NAMES)
        if unknown:
            raise InputError(
                f"fixed_additional_parameters must name some of {', '.join(_polynomial.AP_NAMES)}; got {sorted(unknown)}"
            )
        if self.min_exposures < 2 or self.min_beads_per_exposure < 3 or self.min_exposures_per_bead < 2:
            raise InputError(
                "min_exposures >= 2, min_beads_per_exposure >= 3 and min_exposures_per_bead >= 2 are required; got "
                f"{self.min_exposures}, {self.min_beads_per_exposure}, {self.min_exposures_per_bead}"
            )
        for name in ("function_tolerance", "parameter_tolerance", "initial_damping", "min_ray_angle_deg"):
            if not getattr(self, name) >= 0:
                raise InputError(f"{name} must be >= 0; got {getattr(self, name)}")


# --------------------------------------------------------------------------- orientation


@dataclass(frozen=True)
class Orientation:
    """Exterior, interior and relative orientation of an acquisition.

    Attributes
    ----------
    iop_px : (S, 3) float64 ndarray, px
        ``(xp, yp, c)`` per system.
    exposure : (M,) int64 ndarray
        Epoch indices (``Observations.exposure`` values), sorted, unique.
    q_cam_from_obj : (M, 4) float64 ndarray
        Unit quaternion ``(w, x, y, z)`` of the reference system's (system 0)
        rotation, object -> camera, per epoch.
    source_mm : (M, 3) float64 ndarray, mm
        Reference system's X-ray source in object space per epoch.
    rop_q : (S, 4) float64 ndarray
        System ``s`` camera from system 0 camera (identity for ``s = 0``).
    rop_source_mm : (S, 3) float64 ndarray, mm
        System ``s``'s source in system 0's camera frame (zero for ``s = 0``).
    system_names : tuple of str
    """

    iop_px: np.ndarray
    exposure: np.ndarray
    q_cam_from_obj: np.ndarray
    source_mm: np.ndarray
    rop_q: np.ndarray | None = None
    rop_source_mm: np.ndarray | None = None
    system_names: tuple = ("A",)
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self):
        iop = np.asarray(self.iop_px, dtype=np.float64).reshape(-1, 3)
        n_sys = len(iop)
        set_ = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731
        set_("iop_px", iop)
        set_("exposure", np.asarray(self.exposure, dtype=np.int64).reshape(-1))
        m = len(self.exposure)
        set_("q_cam_from_obj", quat_normalize(np.asarray(self.q_cam_from_obj, dtype=np.float64).reshape(-1, 4)))
        set_("source_mm", np.asarray(self.source_mm, dtype=np.float64).reshape(-1, 3))
        rop_q = np.tile([1.0, 0, 0, 0], (n_sys, 1)) if self.rop_q is None else self.rop_q
        rop_t = np.zeros((n_sys, 3)) if self.rop_source_mm is None else self.rop_source_mm
        set_("rop_q", quat_normalize(np.asarray(rop_q, dtype=np.float64).reshape(-1, 4)))
        set_("rop_source_mm", np.asarray(rop_t, dtype=np.float64).reshape(-1, 3))
        names = tuple(self.system_names)
        if len(names) != n_sys:
            names = names + tuple(chr(ord("A") + i) for i in range(len(names), n_sys))
        set_("system_names", names[:n_sys])
        check_shape("q_cam_from_obj", self.q_cam_from_obj, (m, 4))
        check_shape("source_mm", self.source_mm, (m, 3))
        check_shape("rop_q", self.rop_q, (n_sys, 4))
        check_shape("rop_source_mm", self.rop_source_mm, (n_sys, 3))
        if m and np.any(np.diff(self.exposure) <= 0):
            raise InputError(f"exposure must be sorted and unique; got {self.exposure.tolist()[:10]}...")
        for name in ("iop_px", "q_cam_from_obj", "source_mm", "rop_q", "rop_source_mm"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise InputError(f"{name} holds non-finite values")
        freeze(self)

    @property
    def n_systems(self) -> int:
        return len(self.iop_px)

    def poses(self, system: int) -> tuple[np.ndarray, np.ndarray]:
        """Every epoch's pose of ``system``: ``q (M, 4)`` object -> camera and source ``T (M, 3)`` mm.

        ``R_s R_j`` and ``T_j + R_j^T b_s``: the ROP composed with the reference pose.
        """
        q_s = quat_normalize(quat_multiply(self.rop_q[system], self.q_cam_from_obj))
        T_s = self.source_mm + np.einsum("mji,j->mi", quat_to_matrix(self.q_cam_from_obj), self.rop_source_mm[system])
        return q_s, T_s


# --------------------------------------------------------------------------- result


@dataclass(frozen=True)
class Adjustment:
    """Result of :func:`adjust_bundle`.

    Per-observation arrays have one row per input observation, in input order;
    observations that did not enter the adjustment (``used`` False) have zero
    residuals, weight 0 and ``inlier`` False.

    Attributes
    ----------
    bead_id : (n,) int64 ndarray
        Estimated beads.
    xyz_mm : (n, 3) float64 ndarray, mm
        In the nominal frame (inner constraints: no translation, rotation or
        scale relative to the nominal coordinates).
    xyz_std_mm : (n, 3) float64 ndarray, mm
    xyz_cov_mm2 : (n, 3, 3) float64 ndarray, mm²
        Per bead covariance (inner-constraint datum).
    iop_px, iop_std_px : (S, 3) float64 ndarray, px
        Std 0 where the IOP were held fixed.
    iop_cov_px2 : (S, 3, 3) float64 ndarray, px²
    exposure : (M,) int64 ndarray
    q_cam_from_obj : (M, 4) float64 ndarray
    source_mm : (M, 3) float64 ndarray, mm
    pose_std : (M, 6) float64 ndarray
        Rotation std (rad, about the camera axes) and source std (mm).
    rop_q : (S, 4) float64 ndarray
    rop_source_mm : (S, 3) float64 ndarray, mm
    rop_std : (S, 6) float64 ndarray
        Rotation std (rad) and source std (mm); zero for system 0.
    residual_px : (N, 2) float64 ndarray, px
        ``(xy - Δ - Δ_AP) - projection`` (``Δ_AP`` the polynomial model, if estimated).
    standardized_residual : (N, 2) float64 ndarray
        ``v / (σ0 σ sqrt(r))`` per coordinate (Baarda's w).
    redundancy : (N, 2) float64 ndarray
        Diagonal of ``Q_vv P`` per coordinate; sums to ``dof``.
    weight : (N,) float64 ndarray
        Final t-weight ``(ν+2)/(ν+r²/σ²)``.
    inlier : (N,) bool ndarray
    used : (N,) bool ndarray
    sigma0 : float
        A posteriori standard deviation of unit weight from the inliers.
    t_scale : float
        Maximum-likelihood scale σ of the t relative to ``sigma_px``.
    nu : float
    dof : int
        ``2 N_used - (n_free - 7)``.
    n_parameters : int
        Free parameters (before the 7 datum constraints).
    cost_history : tuple of float
        Negative log-likelihood (up to a constant) after each accepted step.
    iterations : int
    stop_reason : str
    converged : bool
    usable : bool
        Converged, finite, and at least ``min_inlier_fraction`` inliers.
    system_names : tuple of str
    additional_parameters : str
        ``"none"`` or ``"polynomial"`` (:class:`AdjustParams`).
    ap_px, ap_std_px : (S, 7) float64 ndarray, px
        Coefficients ``k1, k2, k3, p1, p2, b1, b2`` (:data:`stages._polynomial.AP_NAMES`)
        of each system's polynomial distortion model and their standard
        deviations; zero when not estimated.
    ap_cov_px2 : (S, 7, 7) float64 ndarray, px²
    ap_radius_px : (S,) float64 ndarray, px
        The model's reference radius ``r0`` per system (1 when not estimated).
    """

    bead_id: np.ndarray
    xyz_mm: np.ndarray
    xyz_std_mm: np.ndarray
    xyz_cov_mm2: np.ndarray
    iop_px: np.ndarray
    iop_std_px: np.ndarray
    iop_cov_px2: np.ndarray
    exposure: np.ndarray
    q_cam_from_obj: np.ndarray
    source_mm: np.ndarray
    pose_std: np.ndarray
    rop_q: np.ndarray
    rop_source_mm: np.ndarray
    rop_std: np.ndarray
    residual_px: np.ndarray
    standardized_residual: np.ndarray
    redundancy: np.ndarray
    weight: np.ndarray
    inlier: np.ndarray
    used: np.ndarray
    sigma0: float
    t_scale: float
    nu: float
    dof: int
    n_parameters: int
    cost_history: tuple
    iterations: int
    stop_reason: str
    converged: bool
    usable: bool
    system_names: tuple = ("A",)
    additional_parameters: str = "none"
    ap_px: np.ndarray | None = None
    ap_std_px: np.ndarray | None = None
    ap_cov_px2: np.ndarray | None = None
    ap_radius_px: np.ndarray | None = None
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self):
        n_sys, n_ap = len(np.asarray(self.iop_px).reshape(-1, 3)), _polynomial.N_AP
        for name, shape, fill in (
            ("ap_px", (n_sys, n_ap), 0.0),
            ("ap_std_px", (n_sys, n_ap), 0.0),
            ("ap_cov_px2", (n_sys, n_ap, n_ap), 0.0),
            ("ap_radius_px", (n_sys,), 1.0),
        ):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(shape, fill))
        _check_finite_and_freeze(self)

    def polynomial_correction(self, system: int, xy_px: np.ndarray) -> np.ndarray:
        """``Δ_AP`` ``(N, 2)`` px of ``system``'s estimated polynomial model at measured ``xy_px`` ``(N, 2)`` px (zero without it)."""
        return _polynomial.correction(xy_px, self.iop_px[system, :2], self.ap_radius_px[system], self.ap_px[system])

    @property
    def orientation(self) -> Orientation:
        """The estimated orientation (for example to start the next solve of the learning loop)."""
        return Orientation(
            iop_px=self.iop_px,
            exposure=self.exposure,
            q_cam_from_obj=self.q_cam_from_obj,
            source_mm=self.source_mm,
            rop_q=self.rop_q,
            rop_source_mm=self.rop_source_mm,
            system_names=self.system_names,
        )


def _check_finite_and_freeze(result) -> None:
    """Raise :class:`EstimationError` if a float array of an adjustment result is not finite; freeze it."""
    for f in fields(result):
        value = getattr(result, f.name)
        if isinstance(value, np.ndarray) and value.dtype.kind == "f" and not np.all(np.isfinite(value)):
            raise EstimationError(f"adjustment output {f.name} holds non-finite values")
    freeze(result)


# --------------------------------------------------------------------------- start values


def initial_orientation(observations: Observations, nominal, iop_px: np.ndarray, *, min_beads: int = 6) -> Orientation:
    """Start values by resection of every frame (OpenCV ``solvePnP``) at the given IOP.

    Parameters
    ----------
    observations : Observations
    nominal : Phantom or dict or (ids, xyz_mm)
        Nominal bead coordinates (mm).
    iop_px : (S, 3) or (3,) float64 ndarray, px
        Approximate ``(xp, yp, c)`` per system (for example the image centre and
        source-image distance / pixel pitch).
    min_beads : int
        Frames with fewer labelled beads are not resected (default 6).

    Returns
    -------
    Orientation
        Per epoch the pose of system 0 (or, where system 0 has no frame, of the
        first system that has one, carried over by the ROP); per system ``s >= 1``
        the ROP as the rotation-averaged ``R_s R_0^T`` and mean ``R_0 (T_s - T_0)``
        over the epochs both systems resected.

    Raises
    ------
    EstimationError
        No frame could be resected, or a system shares no epoch with system 0.
    """
    import cv2
    from fluorocal.stages._geometry import matrix_to_quat

    ids, xyz = _nominal_table(nominal)
    n_sys = len(observations.system_names)
    iop_px = np.broadcast_to(np.asarray(iop_px, dtype=np.float64).reshape(-1, 3), (n_sys, 3)).copy()
    point = _lookup(observations.bead_id, ids, "observations.bead_id not in the nominal coordinates")
    epochs = np.unique(observations.exposure)
    R = np.full((n_sys, len(epochs), 3, 3), np.nan)
    T = np.full((n_sys, len(epochs), 3), np.nan)
    for s in range(n_sys):
        K = np.array([[iop_px[s, 2], 0, iop_px[s, 0]], [0, iop_px[s, 2], iop_px[s, 1]], [0, 0, 1.0]])
        for j, ep in enumerate(epochs):
            sel = (observations.system == s) & (observations.exposure == ep)
            if sel.sum() < min_beads:
                continue
            ok, rvec, tvec = cv2.solvePnP(xyz[point[sel]], observations.xy_px[sel], K, None, flags=cv2.SOLVEPNP_SQPNP)
            if not ok:
                log.info("resection of system %d exposure %d failed", s, ep)
                continue
            Rj = cv2.Rodrigues(rvec)[0]
            R[s, j], T[s, j] = Rj, -Rj.T @ tvec.ravel()
    rop_q = np.tile([1.0, 0, 0, 0], (n_sys, 1))
    rop_t = np.zeros((n_sys, 3))
    for s in range(1, n_sys):
        both = np.isfinite(T[0, :, 0]) & np.isfinite(T[s, :, 0])
        if not both.any():
            raise EstimationError(
                f"system {observations.system_names[s]} shares no resected exposure with system {observations.system_names[0]}"
            )
        q_rel = matrix_to_quat(R[s, both] @ R[0, both].transpose(0, 2, 1))
        q_rel *= np.sign(q_rel @ q_rel[0])[:, None]
        rop_q[s] = quat_normalize(q_rel.mean(0))
        rop_t[s] = np.einsum("nij,nj->ni", R[0, both], T[s, both] - T[0, both]).mean(0)
    # the reference pose of each epoch, from system 0 or through another system's ROP
    q0 = np.full((len(epochs), 4), np.nan)
    T0 = np.full((len(epochs), 3), np.nan)
    for s in range(n_sys - 1, -1, -1):
        have = np.isfinite(T[s, :, 0])
        if not have.any():
            continue
        Rr = quat_to_matrix(rop_q[s])
        R_ref = Rr.T @ R[s, have]  # R_s = R_r R_0
        q0[have] = matrix_to_quat(R_ref)
        T0[have] = T[s, have] - np.einsum("nji,j->ni", R_ref, rop_t[s])  # T_s = T_0 + R_0^T b_s
    found = np.isfinite(T0[:, 0])
    if not found.any():
        raise EstimationError(f"no frame could be resected (each needs >= {min_beads} labelled beads)")
    if not found.all():
        log.warning("%d exposure(s) could not be resected and are left out", int((~found).sum()))
    return Orientation(
        iop_px=iop_px,
        exposure=epochs[found],
        q_cam_from_obj=q0[found],
        source_mm=T0[found],
        rop_q=rop_q,
        rop_source_mm=rop_t,
        system_names=observations.system_names,
    )


# --------------------------------------------------------------------------- input checks


def _nominal_table(nominal) -> tuple[np.ndarray, np.ndarray]:
    """``(ids (n,), xyz_mm (n, 3))`` from a Phantom, a mapping id -> xyz or a pair ``(ids, xyz)``."""
    if isinstance(nominal, Phantom):
        return nominal.ids, nominal.xyz_mm
    if isinstance(nominal, dict):
        ids = np.fromiter(nominal.keys(), dtype=np.int64, count=len(nominal))
        xyz = np.asarray(list(nominal.values()), dtype=np.float64).reshape(-1, 3)
        return ids, xyz
    ids, xyz = nominal
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    xyz = np.asarray(xyz, dtype=np.float64)
    check_shape("nominal xyz_mm", xyz, (len(ids), 3))
    if not np.all(np.isfinite(xyz)):
        raise InputError("nominal xyz_mm holds non-finite values")
    return ids, xyz


def _lookup(keys: np.ndarray, table: np.ndarray, what: str) -> np.ndarray:
    """Index of every ``keys`` value in ``table``; InputError naming the missing ones."""
    order = np.argsort(table, kind="stable")
    pos = np.searchsorted(table[order], keys)
    pos = np.minimum(pos, len(table) - 1) if len(table) else pos
    found = len(table) > 0
    ok = np.zeros(len(keys), bool) if not found else table[order][pos] == keys
    if not np.all(ok):
        missing = np.unique(keys[~ok])
        raise InputError(f"{what}: {len(missing)} value(s) not found, e.g. {missing[:5].tolist()}")
    return order[pos]


def _ray_spread_deg(points_mm, sources_mm, point_idx, n_points) -> np.ndarray:
    """Per point, twice the largest angle (deg) between an observing ray and the mean ray."""
    rays = points_mm[point_idx] - sources_mm
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    mean = np.stack([np.bincount(point_idx, rays[:, k], n_points) for k in range(3)], 1).astype(np.float64)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-300)
    cosang = np.clip((rays * mean[point_idx]).sum(1), -1.0, 1.0)
    worst = np.full(n_points, 1.0)
    np.minimum.at(worst, point_idx, cosang)
    return 2.0 * np.degrees(np.arccos(worst))


def _select_observations(obs, point_idx, epoch_idx, n_points, n_epochs, initial, nominal_xyz, params) -> np.ndarray:
    """Mask of observations that can be estimated; logs what is dropped and why."""
    used = np.ones(len(obs), bool)
    key = (obs.system * (n_epochs + 1) + epoch_idx) * (n_points + 1) + point_idx
    _, first = np.unique(key, return_index=True)
    dup = np.ones(len(obs), bool)
    dup[first] = False
    if dup.any():
        log.warning("dropping %d duplicate observation(s) of a bead in one frame (kept the first)", int(dup.sum()))
        used &= ~dup
    # every observation's own source, for the ray-angle test
    sources = np.empty((len(obs), 3))
    for s in range(initial.n_systems):
        sel = obs.system == s
        sources[sel] = initial.poses(s)[1][epoch_idx[sel]]
    spread = _ray_spread_deg(nominal_xyz, sources, point_idx, n_points)
    for _ in range(100):
        before = used.sum()
        pts_epochs = np.zeros(n_points, np.int64)
        pe = np.unique(point_idx[used] * (n_epochs + 1) + epoch_idx[used])
        np.add.at(pts_epochs, pe // (n_epochs + 1), 1)
        weak_bead = pts_epochs < params.min_exposures_per_bead
        if used.any():
            spread = _ray_spread_deg(nominal_xyz, sources[used], point_idx[used], n_points)
        narrow = (spread < params.min_ray_angle_deg) & ~weak_bead & (pts_epochs > 0)
        drop = (weak_bead | narrow)[point_idx] & used
        if drop.any():
            log.info(
                "dropping %d observation(s) of %d bead(s) seen in fewer than %d epochs or by rays within %.3g deg",
                int(drop.sum()),
                int(len(np.unique(point_idx[drop]))),
                params.min_exposures_per_bead,
                params.min_ray_angle_deg,
            )
            used &= ~drop
        epoch_beads = np.bincount(
            np.unique(epoch_idx[used] * (n_points + 1) + point_idx[used]) // (n_points + 1), minlength=n_epochs
        )
        weak_epoch = (epoch_beads < params.min_beads_per_exposure)[epoch_idx] & used
        if weak_epoch.any():
            log.info(
                "dropping %d observation(s) of epochs with fewer than %d beads",
                int(weak_epoch.sum()),
                params.min_beads_per_exposure,
            )
            used &= ~weak_epoch
        if used.sum() == before:
            break
    if not used.any() and len(obs) and (spread[point_idx] < params.min_ray_angle_deg).all():
        raise EstimationError(
            "every bead is seen along (nearly) one direction: all exposures share one pose "
            f"(ray angles < min_ray_angle_deg = {params.min_ray_angle_deg}); the points' depth is undetermined"
        )
    return used


def _start_points(start, ids: np.ndarray, nominal_mm: np.ndarray) -> np.ndarray:
    """Start coordinates (n, 3): ``start`` where given, else nominal, projected onto ``D^T (P - P_nominal) = 0``."""
    points = nominal_mm.copy()
    if start is None:
        return points
    s_ids, s_xyz = _nominal_table(start)
    order = np.argsort(s_ids)
    pos = np.clip(np.searchsorted(s_ids[order], ids), 0, max(len(s_ids) - 1, 0))
    have = (s_ids[order][pos] == ids) if len(s_ids) else np.zeros(len(ids), bool)
    points[have] = s_xyz[order][pos[have]]
    D = _ba.datum_directions(nominal_mm).reshape(-1, 7)
    delta = (points - nominal_mm).ravel()
    delta -= D @ np.linalg.lstsq(D, delta, rcond=None)[0]
    return nominal_mm + delta.reshape(-1, 3)


# --------------------------------------------------------------------------- the stage


def adjust_bundle(
    observations: Observations,
    nominal,
    initial: Orientation,
    corrections_px: np.ndarray | None = None,
    params: AdjustParams = AdjustParams(),
    *,
    start_points=None,
) -> Adjustment:
    """Robust (Student-t) free-network bundle adjustment of labelled bead observations.

    Parameters
    ----------
    observations : Observations
        ``N`` labelled observations (``xy_px`` measured, ``sigma_px`` from the centroid stage).
    nominal : Phantom or dict or (ids, xyz_mm)
        Nominal bead coordinates (mm) by bead id: the start values and the datum.
    initial : Orientation
        Start values of IOP, poses (every observed epoch) and ROP.
    corrections_px : (N, 2) float64 ndarray, px, optional
        Distortion corrections Δ held constant: ideal = ``xy_px - Δ`` (default 0).
    params : AdjustParams
    start_points : dict or (ids, xyz_mm), optional
        Start values of the bead coordinates (for example a previous
        :class:`Adjustment`'s ``(bead_id, xyz_mm)`` in the learning loop); beads
        not given start at their nominal coordinates. The datum stays the
        nominal one: the start is projected onto the inner constraints.

    Returns
    -------
    Adjustment

    Raises
    ------
    InputError
        Inconsistent inputs (unknown bead ids or epochs, wrong shapes, system
        count mismatch) or fewer than ``min_exposures`` usable frames.
    EstimationError
        Degenerate geometry (all exposures from one pose, singular normal
        equations) or an initial orientation with points behind a source.

    Notes
    -----
    Model and datum: see the module docstring. Uncertainties are
    ``c (J^T W J)^-1`` under the inner constraints with Huber's sandwich
    factor ``c = K² [Σ w² s / dof] mean(w) / mean(a)²``, ``a = w ν/(ν + s/σ²)``
    the averaged ψ', ``K = 1 + (u / 2N) var(a) / mean(a)²`` his small-sample
    correction (``s`` squared Mahalanobis residuals, ``u`` free parameters less 7);
    it reduces to σ̂0² for least squares [1]_. The
    redundancy numbers are the diagonal of ``Q_vv P`` with
    ``P = w C^-1``; ``σ0² = Σ_inliers s / Σ_inliers r``.

    References
    ----------
    .. [1] P. J. Huber, Robust Statistics, Wiley 1981, section 7.6.
    """
    prepared = _prepare(observations, nominal, initial, corrections_px, params, start_points)
    solved = _ba.solve(prepared.state, prepared.problem, prepared.options)
    return _summarise(observations, prepared, solved, initial, params)


@dataclass(frozen=True)
class _Prepared:
    """The numerical problem behind one :func:`adjust_bundle` call (tests use it to probe the cost)."""

    problem: _ba.Problem
    perm: np.ndarray
    state: _ba.State
    options: _ba.SolverOptions
    used: np.ndarray
    beads_used: np.ndarray
    ids: np.ndarray
    epochs_used: np.ndarray


def _prepare(observations, nominal, initial, corrections_px, params, start_points=None) -> _Prepared:
    """Check the inputs, drop what cannot be estimated and build the problem and start state."""
    if not isinstance(observations, Observations):
        raise InputError(f"observations must be an Observations artifact; got {type(observations).__name__}")
    n_obs = len(observations)
    if corrections_px is None:
        corrections_px = np.zeros((n_obs, 2))
    corrections_px = np.asarray(corrections_px, dtype=np.float64)
    if corrections_px.shape != (n_obs, 2):
        raise ShapeError(
            f"corrections_px must have shape ({n_obs}, 2) like the observations; got {corrections_px.shape}"
        )
    if not np.all(np.isfinite(corrections_px)):
        raise InputError("corrections_px holds non-finite values")
    if initial.n_systems != len(observations.system_names):
        raise InputError(
            f"initial orientation has {initial.n_systems} system(s); observations name {len(observations.system_names)}: "
            f"{observations.system_names}"
        )
    if np.any(observations.sigma_px[:, :2] <= 0) or np.any(np.abs(observations.sigma_px[:, 2]) >= 1):
        raise InputError("sigma_px must have σx, σy > 0 and |ρ| < 1")
    ids, nominal_xyz = _nominal_table(nominal)
    point_all = _lookup(observations.bead_id, ids, "observations.bead_id not in the nominal coordinates")
    epoch_all = _lookup(observations.exposure, initial.exposure, "observations.exposure not in initial.exposure")

    used = _select_observations(
        observations, point_all, epoch_all, len(ids), len(initial.exposure), initial, nominal_xyz, params
    )
    n_frames = len(np.unique(observations.system[used] * (len(initial.exposure) + 1) + epoch_all[used]))
    if n_frames < params.min_exposures:
        raise InputError(
            f"observations must leave at least min_exposures = {params.min_exposures} frames with "
            f">= {params.min_beads_per_exposure} beads seen in >= {params.min_exposures_per_bead} epochs; got {n_frames}"
        )

    beads_used, point_idx = np.unique(point_all[used], return_inverse=True)
    epochs_used, pose_idx = np.unique(epoch_all[used], return_inverse=True)
    sys_idx = observations.system[used]
    n_sys = initial.n_systems
    iop_free = np.full(n_sys, bool(params.estimate_iop))
    ap_radius = None
    if params.additional_parameters == "polynomial":
        ap_radius = np.array(
            [_polynomial.reference_radius(observations.xy_px[used][sys_idx == s]) for s in range(n_sys)]
        )
    problem, perm = _ba.build_problem(
        point_idx.astype(np.int64),
        pose_idx.astype(np.int64),
        sys_idx,
        observations.xy_px[used] - corrections_px[used],
        observations.sigma_px[used],
        nominal_xyz[beads_used],
        len(epochs_used),
        n_sys,
        iop_free,
        params.schur,
        xy_px=observations.xy_px[used],
        ap_radius_px=ap_radius,
        ap_free=np.array([name not in params.fixed_additional_parameters for name in _polynomial.AP_NAMES]),
    )
    state = _ba.State(
        points_mm=_start_points(start_points, ids[beads_used], nominal_xyz[beads_used]),
        q=initial.q_cam_from_obj[epochs_used].copy(),
        source_mm=initial.source_mm[epochs_used].copy(),
        iop_px=initial.iop_px.copy(),
        rop_q=initial.rop_q.copy(),
        rop_source_mm=initial.rop_source_mm.copy(),
        ap_px=np.zeros((n_sys, problem.n_ap)),
    )
    options = _ba.SolverOptions(
        nu=float(params.nu),
        estimate_nu=params.estimate_nu,
        nu_bounds=params.nu_bounds,
        estimate_scale=params.estimate_scale,
        max_iterations=params.max_iterations,
        function_tolerance=params.function_tolerance,
        parameter_tolerance=params.parameter_tolerance,
        initial_damping=params.initial_damping,
    )
    log.info(
        "adjusting %d observations: %d beads, %d epochs, %d systems, %d free parameters, eliminating %s",
        problem.n_obs,
        problem.n_points,
        problem.n_poses,
        n_sys,
        problem.n_free,
        problem.eliminate,
    )
    return _Prepared(problem, perm, state, options, used, beads_used, ids, epochs_used)


def _summarise(observations, prepared: _Prepared, solved, initial, params) -> Adjustment:
    """Statistics of the solution and the per-observation outputs in input order."""
    problem, perm, used = prepared.problem, prepared.perm, prepared.used
    beads_used, ids, epochs_used = prepared.beads_used, prepared.ids, prepared.epochs_used
    state = solved.state
    r_px, e = _ba.residuals(state, problem)
    s = (e * e).sum(1)
    w = _ba.t_weights(s, solved.nu, solved.scale2)
    n_used = problem.n_obs
    u = problem.n_free - 7
    dof = 2 * n_used - u
    if dof <= 0:
        raise EstimationError(f"no redundancy: {2 * n_used} observations for {u} parameters")
    if params.compute_covariance:
        cov = _ba.covariance(state, problem, w)
        hat = cov.hat
    else:
        # no inverse: zero cofactors, and the mean redundancy for every observation (hat = (1 - r̄)/w I)
        ng = problem.n_globals
        cov = _ba.Covariance(
            np.zeros((problem.n_points, 3, 3)), np.zeros((problem.n_poses, 6, 6)), np.zeros((ng, ng)), None
        )
        hat = ((1.0 - dof / (2.0 * n_used)) / w)[:, None, None] * np.eye(2)

    red, std_res, sigma0, inlier = _observation_statistics(r_px, s, w, hat, problem.linv, params.outlier_weight)

    if math.isinf(solved.nu):
        c_h = float(s.sum() / dof)
    else:
        # Huber's sandwich for an M-estimator: ψ'-average a = w ν/(ν + t) per observation,
        # with his small-sample factor K = 1 + (u / 2N) var(a) / mean(a)²
        a = w * solved.nu / (solved.nu + s / solved.scale2)
        a_bar = float(np.mean(a))
        K = 1.0 + u / (2.0 * n_used) * float(np.var(a)) / a_bar**2
        c_h = K * K * float((w * w * s).sum() / dof) * float(np.mean(w)) / a_bar**2

    def std(c):
        return np.sqrt(np.clip(c_h * np.einsum("...ii->...i", c), 0.0, None))

    n_sys = problem.n_systems
    iop_std = np.zeros((n_sys, 3))
    iop_cov = np.zeros((n_sys, 3, 3))
    rop_std = np.zeros((n_sys, 6))
    n_ap = problem.n_ap
    ap_std = np.zeros((n_sys, n_ap))
    ap_cov = np.zeros((n_sys, n_ap, n_ap))
    g_std = std(cov.globals_) if problem.n_globals else np.zeros(0)
    for s_ in range(n_sys):
        cols = problem.gcol[s_]
        if cols[0] >= 0:
            iop_std[s_] = g_std[cols[:3]]
            iop_cov[s_] = c_h * cov.globals_[np.ix_(cols[:3], cols[:3])]
        if n_sys > 1 and cols[3] >= 0:
            rop_std[s_] = g_std[cols[3:9]]
        if n_ap:
            free = np.flatnonzero(cols[problem.ap_start :] >= 0)
            ap_cols = cols[problem.ap_start + free]
            ap_std[s_, free] = g_std[ap_cols]
            ap_cov[s_][np.ix_(free, free)] = c_h * cov.globals_[np.ix_(ap_cols, ap_cols)]

    # back to input order
    where = np.flatnonzero(used)[perm]

    def scatter(values, fill=0.0):
        return _scatter(values, where, len(observations), fill)

    finite = all(np.all(np.isfinite(arr)) for arr in (state.points_mm, state.q, state.source_mm, state.iop_px, r_px))
    inlier_fraction = float(inlier.mean()) if n_used else 0.0
    usable = bool(solved.converged and finite and inlier_fraction >= params.min_inlier_fraction)
    if not usable:
        # the result says so (``usable``, ``stop_reason``); callers decide whether it concerns the user
        log.info(
            "adjustment not usable: %s, %.1f %% inliers (minimum %.1f %%)",
            solved.stop_reason,
            100 * inlier_fraction,
            100 * params.min_inlier_fraction,
        )
    log.info(
        "adjustment: %d iterations (%s), σ0 %.3g, %.2f %% outliers, dof %d",
        solved.iterations,
        solved.stop_reason,
        sigma0,
        100 * (1 - inlier_fraction),
        dof,
    )
    return Adjustment(
        bead_id=ids[beads_used],
        xyz_mm=state.points_mm,
        xyz_std_mm=std(cov.points),
        xyz_cov_mm2=c_h * cov.points,
        iop_px=state.iop_px,
        iop_std_px=iop_std,
        iop_cov_px2=iop_cov,
        exposure=initial.exposure[epochs_used],
        q_cam_from_obj=state.q,
        source_mm=state.source_mm,
        pose_std=std(cov.poses),
        rop_q=state.rop_q,
        rop_source_mm=state.rop_source_mm,
        rop_std=rop_std,
        residual_px=scatter(r_px),
        standardized_residual=scatter(std_res),
        redundancy=scatter(red),
        weight=scatter(w),
        inlier=scatter(inlier, False),
        used=used.copy(),
        sigma0=float(sigma0),
        t_scale=float(math.sqrt(solved.scale2)),
        nu=float(solved.nu),
        dof=int(dof),
        n_parameters=int(problem.n_free),
        cost_history=tuple(float(c) for c in solved.cost_history),
        iterations=int(solved.iterations),
        stop_reason=solved.stop_reason,
        converged=bool(solved.converged),
        usable=usable,
        system_names=tuple(observations.system_names),
        additional_parameters=params.additional_parameters,
        ap_px=state.ap_px if n_ap else None,
        ap_std_px=ap_std if n_ap else None,
        ap_cov_px2=ap_cov if n_ap else None,
        ap_radius_px=problem.ap_radius_px,
    )


# --------------------------------------------------------------------------- grid plates


@dataclass(frozen=True)
class PlateAdjustment:
    """Result of :func:`adjust_plate`: one robust homography per frame, per-observation outputs like :class:`Adjustment`.

    Attributes
    ----------
    frame_system, frame_exposure : (F,) int64 ndarray
        The frames fitted.
    homography : (F, 3, 3) float64 ndarray
        Image px (homogeneous) from plate ``(x, y, 1)`` mm, ``H[2, 2] = 1``.
    t_scale : (F,) float64 ndarray
        Maximum-likelihood t scale per frame, relative to ``sigma_px``.
    residual_px, standardized_residual, redundancy, weight, inlier, used
        As in :class:`Adjustment` (one row per input observation).
    sigma0, nu, dof, iterations, stop_reason, converged, usable, cost_history, system_names
        As in :class:`Adjustment`; ``dof = 2 N_used - 8 F``.
    """

    frame_system: np.ndarray
    frame_exposure: np.ndarray
    homography: np.ndarray
    t_scale: np.ndarray
    residual_px: np.ndarray
    standardized_residual: np.ndarray
    redundancy: np.ndarray
    weight: np.ndarray
    inlier: np.ndarray
    used: np.ndarray
    sigma0: float
    nu: float
    dof: int
    iterations: int
    stop_reason: str
    converged: bool
    usable: bool
    cost_history: tuple
    system_names: tuple = ("A",)
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self):
        _check_finite_and_freeze(self)


def adjust_plate(
    observations: Observations,
    nominal,
    corrections_px: np.ndarray | None = None,
    params: AdjustParams = AdjustParams(),
) -> PlateAdjustment:
    """Robust (Student-t) homography of each frame of a planar grid plate.

    The plate's nominal ``(x, y)`` (mm; ``z`` is ignored) map to the ideal image
    coordinates ``xy_px - Δ`` by one homography per frame (system, exposure),
    estimated by maximum likelihood under the same 2-D Student-t as
    :func:`adjust_bundle` (``nu``, ``estimate_scale``, ``outlier_weight``,
    ``max_iterations``, ``function_tolerance``, ``min_beads_per_exposure`` of
    ``params`` apply). Frames with fewer beads are left out (``used`` False).

    Parameters
    ----------
    observations : Observations
    nominal : Phantom or dict or (ids, xyz_mm)
    corrections_px : (N, 2) float64 ndarray, px, optional
    params : AdjustParams

    Returns
    -------
    PlateAdjustment

    Raises
    ------
    InputError
        Unknown bead ids, wrong shapes, or no frame with enough observations.
    EstimationError
        A frame's observations admit no homography (for example all on a line).
    """
    from fluorocal.stages import _homography

    if not isinstance(observations, Observations):
        raise InputError(f"observations must be an Observations artifact; got {type(observations).__name__}")
    n_obs = len(observations)
    corrections_px = np.zeros((n_obs, 2)) if corrections_px is None else np.asarray(corrections_px, dtype=np.float64)
    if corrections_px.shape != (n_obs, 2):
        raise ShapeError(
            f"corrections_px must have shape ({n_obs}, 2) like the observations; got {corrections_px.shape}"
        )
    ids, xyz = _nominal_table(nominal)
    point = _lookup(observations.bead_id, ids, "observations.bead_id not in the nominal coordinates")
    frame_key = observations.system * (int(observations.exposure.max(initial=0)) + 1) + observations.exposure
    keys, frame_idx, counts = np.unique(frame_key, return_inverse=True, return_counts=True)
    used = counts[frame_idx] >= max(params.min_beads_per_exposure, 5)
    if (~used).any():
        log.info(
            "leaving out %d frame(s) with fewer than %d beads",
            int((counts < max(params.min_beads_per_exposure, 5)).sum()),
            max(params.min_beads_per_exposure, 5),
        )
    if not used.any():
        raise InputError(
            f"no frame has >= {max(params.min_beads_per_exposure, 5)} observations; got at most {int(counts.max(initial=0))}"
        )
    order = np.flatnonzero(used)[np.argsort(frame_idx[used], kind="stable")]
    fr = frame_idx[order]
    starts = np.flatnonzero(np.r_[True, fr[1:] != fr[:-1]])
    fit = _homography.fit_homographies(
        xyz[point[order], :2],
        observations.xy_px[order] - corrections_px[order],
        observations.sigma_px[order],
        starts,
        nu=float(params.nu),
        estimate_scale=params.estimate_scale,
        max_iterations=params.max_iterations,
        function_tolerance=params.function_tolerance,
    )
    seg = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(order)]))
    w = (
        _ba.t_weights(fit.s, float(params.nu), 1.0)
        if math.isinf(params.nu)
        else (params.nu + 2) / (params.nu + fit.s / fit.scale2[seg])
    )
    linv = _ba.whitening(observations.sigma_px[order])
    red, std_res, sigma0, inlier = _observation_statistics(
        fit.residual_px, fit.s, w, fit.hat, linv, params.outlier_weight
    )
    dof = 2 * len(order) - 8 * len(starts)

    def scatter(values, fill=0.0):
        return _scatter(values, order, n_obs, fill)

    converged = bool(fit.converged.all())
    inlier_fraction = float(inlier.mean())
    usable = converged and inlier_fraction >= params.min_inlier_fraction
    first = order[starts]
    return PlateAdjustment(
        frame_system=observations.system[first],
        frame_exposure=observations.exposure[first],
        homography=fit.H,
        t_scale=np.sqrt(fit.scale2),
        residual_px=scatter(fit.residual_px),
        standardized_residual=scatter(std_res),
        redundancy=scatter(red),
        weight=scatter(w),
        inlier=scatter(inlier, False),
        used=used,
        sigma0=float(sigma0),
        nu=float(params.nu),
        dof=int(dof),
        iterations=int(fit.iterations),
        stop_reason="converged in every frame"
        if converged
        else f"{int((~fit.converged).sum())} frame(s) hit max_iterations",
        converged=converged,
        usable=bool(usable),
        cost_history=fit.cost_history,
        system_names=tuple(observations.system_names),
    )


def _scatter(values: np.ndarray, where: np.ndarray, n: int, fill=0.0) -> np.ndarray:
    """Rows ``values`` placed at ``where`` of an ``n``-row array filled with ``fill``."""
    out = np.full((n,) + values.shape[1:], fill, dtype=values.dtype)
    out[where] = values
    return out


def _observation_statistics(r_px, s, w, hat, linv, outlier_weight):
    """Redundancy numbers, standardised residuals, σ0 and inlier flags from ``J Q J^T`` per observation.

    Returns
    -------
    redundancy : (N, 2) float64 ndarray
        ``diag(L (I - w J Q J^T) L^-1)``: the diagonal of ``Q_vv P`` with ``P = w C^-1``.
    standardized : (N, 2) float64 ndarray
        ``v / (σ0 σ sqrt(r))`` (Baarda's w).
    sigma0 : float
        ``sqrt(Σ_inliers s / Σ_inliers r)``.
    inlier : (N,) bool ndarray
    """
    n = len(s)
    l11, l21, l22 = linv.T
    L = np.zeros((n, 2, 2))
    L[:, 0, 0] = 1.0 / l11
    L[:, 1, 0] = -l21 / (l11 * l22)
    L[:, 1, 1] = 1.0 / l22
    Linv = np.zeros((n, 2, 2))
    Linv[:, 0, 0], Linv[:, 1, 0], Linv[:, 1, 1] = l11, l21, l22
    red = np.einsum("nii->ni", L @ (np.eye(2) - w[:, None, None] * hat) @ Linv)
    inlier = w >= outlier_weight
    red_in = red[inlier].sum()
    sigma0 = math.sqrt(s[inlier].sum() / red_in) if red_in > 0 else math.sqrt(s.mean() / 2)
    sig_xy = np.sqrt(np.einsum("nij,nij->ni", L, L))  # diag of C = L L^T
    denom = sigma0 * sig_xy * np.sqrt(np.clip(red, 0.0, None))
    std_res = np.divide(r_px, denom, out=np.zeros_like(r_px), where=denom > 1e-12 * sig_xy)
    return red, std_res, sigma0, inlier


__all__ = [
    "VERSION",
    "AdjustParams",
    "Orientation",
    "Adjustment",
    "adjust_bundle",
    "initial_orientation",
    "PlateAdjustment",
    "adjust_plate",
]
