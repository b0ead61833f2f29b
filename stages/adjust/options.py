"""The adjustment's parameters, one owner each: solver options, free parameters, data selection.

- :class:`SolverOptions`: how the likelihood is maximised (the robust model,
  Levenberg–Marquardt's settings, the Schur ordering, what counts as usable).
  Set by the user (config section ``[adjust]``).
- :class:`FreeParameters`: which parameters the network estimates (the IOP,
  the polynomial additional parameters). Set by the caller that owns that
  choice: the learning loop's scheme, or ``fluorocal adjust``'s flags; never
  by ``[adjust]``.
- :class:`DataSelection`: which observations can enter the solve (config
  section ``[adjust]``).

The last switch, whether to compute the covariance, is the keyword
``compute_covariance`` of :func:`stages.adjust.adjust_bundle`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fluorocal.stages.adjust import polynomial
from fluorocal.stages.errors import InputError


@dataclass(frozen=True)
class SolverOptions:
    """How :func:`stages.adjust.adjust_bundle` and :func:`stages.adjust.adjust_plate` solve.

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
    schur : str
        ``"auto"`` (default: eliminate points or poses, whichever leaves the smaller
        reduced system), ``"points"`` or ``"poses"``.
    min_inlier_fraction : float
        ``usable`` requires at least this fraction of inliers (default 0.5).
    """

    nu: float = 4.0
    estimate_nu: bool = False
    nu_bounds: tuple = (1.0, 1000.0)
    estimate_scale: bool = True
    outlier_weight: float = 0.2
    max_iterations: int = 100
    function_tolerance: float = 1e-5
    parameter_tolerance: float = 1e-10
    initial_damping: float = 1e-6
    schur: str = "auto"
    min_inlier_fraction: float = 0.5

    def __post_init__(self):
        object.__setattr__(self, "nu_bounds", tuple(float(b) for b in self.nu_bounds))
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
        for name in ("function_tolerance", "parameter_tolerance", "initial_damping"):
            if not getattr(self, name) >= 0:
                raise InputError(f"{name} must be >= 0; got {getattr(self, name)}")


@dataclass(frozen=True)
class FreeParameters:
    """Which parameters :func:`stages.adjust.adjust_bundle` estimates (points, poses and ROP always are).

    Attributes
    ----------
    estimate_iop : bool
        Estimate each system's ``(xp, yp, c)`` (default True: "kNN + IOP");
        False holds them at the initial values ("kNN").
    additional_parameters : str
        ``"none"`` (default) or ``"polynomial"``: estimate per system the 7
        coefficients of the global polynomial distortion model of
        :mod:`stages.adjust.polynomial` (px at its reference radius), on top of any
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

    estimate_iop: bool = True
    additional_parameters: str = "none"
    fixed_additional_parameters: tuple = ("b1", "b2")

    def __post_init__(self):
        object.__setattr__(self, "fixed_additional_parameters", tuple(str(n) for n in self.fixed_additional_parameters))
        if self.additional_parameters not in ("none", "polynomial"):
            raise InputError(
                f"additional_parameters must be 'none' or 'polynomial'; got {self.additional_parameters!r}"
            )
        unknown = set(self.fixed_additional_parameters) - set(polynomial.AP_NAMES)
        if unknown:
            raise InputError(
                f"fixed_additional_parameters must name some of {', '.join(polynomial.AP_NAMES)}; got {sorted(unknown)}"
            )

    @property
    def ap_free(self) -> tuple[bool, ...]:
        """Per coefficient of :data:`stages.adjust.polynomial.AP_NAMES`: estimated (True) or held at zero."""
        return tuple(name not in self.fixed_additional_parameters for name in polynomial.AP_NAMES)


@dataclass(frozen=True)
class DataSelection:
    """Which observations can enter a solve; the rest are dropped (``used`` False) with a debug message.

    Attributes
    ----------
    min_exposures : int
        Fewest frames (system, exposure) the adjustment accepts (default 3).
    min_beads_per_exposure : int
        Epochs with fewer distinct beads are dropped (default 6; 3 determine a pose).
        :func:`stages.adjust.adjust_plate` leaves out frames with fewer (at least 5).
    min_exposures_per_bead : int
        Beads seen in fewer epochs are dropped (default 2; one ray cannot fix a point).
    min_ray_angle_deg : float
        Beads whose rays (at the initial orientation) span a smaller angle are
        dropped, as their depth is undetermined (default 1.0 degree).
    """

    min_exposures: int = 3
    min_beads_per_exposure: int = 6
    min_exposures_per_bead: int = 2
    min_ray_angle_deg: float = 1.0

    def __post_init__(self):
        if self.min_exposures < 2 or self.min_beads_per_exposure < 3 or self.min_exposures_per_bead < 2:
            raise InputError(
                "min_exposures >= 2, min_beads_per_exposure >= 3 and min_exposures_per_bead >= 2 are required; got "
                f"{self.min_exposures}, {self.min_beads_per_exposure}, {self.min_exposures_per_bead}"
            )
        if not self.min_ray_angle_deg >= 0:
            raise InputError(f"min_ray_angle_deg must be >= 0; got {self.min_ray_angle_deg}")
