"""The learning's parameters, its schemes and its two presets (``recommended``, the default, and ``paper``)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from fluorocal.stages.errors import InputError
from fluorocal.stages.learn.grid import DEFAULT_TAU_GRID_PX, DIFFERENCE_STENCILS
from fluorocal.stages.learn.knn import DEFAULT_K_GRID
from fluorocal.stages.learn.nodes import GridSpec


class Scheme(StrEnum):
    """A calibration scheme: the adjustment alone, the paper's four, or the global polynomial model.

    Its text (``[calibration] scheme``) is parsed once, by :meth:`parse`; what the scheme does is read
    from its properties, never from its spelling. As a ``str`` it is its spelling (logs, artifacts, keys).

    Examples
    --------
    >>> s = Scheme.parse("knn+iop")
    >>> s.learn_field, s.estimate_iop, s.smooth, s.polynomial, s.corrects
    (True, True, False, False, True)
    >>> str(Scheme.parse("none")), Scheme.parse("none").corrects
    ('none', False)
    """

    NONE = "none"
    KNN = "knn"
    KNN_IOP = "knn+iop"
    KNN_SMOOTH = "knn+smooth"
    KNN_IOP_SMOOTH = "knn+iop+smooth"
    POLYNOMIAL = "polynomial"

    @classmethod
    def parse(cls, text, *, where: str = "scheme") -> Scheme:
        """The scheme spelled ``text`` (a :class:`Scheme` is returned as it is).

        Raises
        ------
        InputError
            ``text`` is not a scheme's spelling; the message starts with ``where``.
        """
        if isinstance(text, str) and text in SCHEMES:
            return cls(text)
        raise InputError(f"{where}: expected one of {', '.join(SCHEMES)}; got {text!r}")

    @property
    def learn_field(self) -> bool:
        """The kNN loop learns a field (the four ``knn`` schemes)."""
        return self._parts[0] == "knn"

    @property
    def estimate_iop(self) -> bool:
        """The adjustment estimates the interior orientation (all but ``knn`` and ``knn+smooth``)."""
        return not self.learn_field or "iop" in self._parts

    @property
    def smooth(self) -> bool:
        """The learned field is the smoothed (gridded) one (``+smooth``; true where no kNN field is learned)."""
        return not self.learn_field or "smooth" in self._parts

    @property
    def polynomial(self) -> bool:
        """The adjustment estimates the global polynomial model instead of a kNN loop."""
        return self is Scheme.POLYNOMIAL

    @property
    def corrects(self) -> bool:
        """The calibration corrects the image at all (all but ``none``, the adjustment alone)."""
        return self is not Scheme.NONE

    @property
    def _parts(self) -> tuple[str, ...]:
        return tuple(self.value.split("+"))


#: the schemes' spellings
SCHEMES = tuple(s.value for s in Scheme)


class Acceleration(StrEnum):
    """How the kNN phase's fixed-point iteration is stepped (``[learn] acceleration``)."""

    NONE = "none"
    OVERRELAX = "overrelax"
    ANDERSON = "anderson"


class Refine(StrEnum):
    """What follows the kNN phase (``[learn] refine``): nothing, the gridded field, or it jointly with the points."""

    NONE = "none"
    GRID = "grid"
    GRID_POINTS = "grid+points"


class Training(StrEnum):
    """Which observations each regression learns from (``[learn] training``)."""

    INLIERS = "inliers"
    LOCAL = "local"


class FieldGauge(StrEnum):
    """What is removed from the fields after every update (``[learn] field_gauge``)."""

    NONE = "none"
    ORIENTATION = "orientation"


#: the learning's switches: each field of :class:`LearnParams` that takes one of an enumeration's values
SWITCHES = {"acceleration": Acceleration, "refine": Refine, "training": Training, "field_gauge": FieldGauge}


def parse_switch(name: str, value) -> StrEnum:
    """``value`` (an enumeration member or its spelling) as the member of switch ``name``'s enumeration.

    Raises
    ------
    InputError
        ``value`` is none of the enumeration's spellings; the message names ``name`` and lists them.

    Examples
    --------
    >>> parse_switch("refine", "grid+points") is Refine.GRID_POINTS
    True
    >>> parse_switch("training", "all")
    Traceback (most recent call last):
    ...
    fluorocal.stages.errors.InputError: training must be one of 'inliers', 'local'; got 'all'
    """
    kind = SWITCHES[name]
    if isinstance(value, str) and value in kind._value2member_map_:
        return kind(value)
    raise InputError(f"{name} must be one of {', '.join(repr(m.value) for m in kind)}; got {value!r}")


#: the values a preset gives the fields left unset (None); explicit values always win
PRESETS = {
    # the accelerated loop: a few kNN steps, then the gridded field refined jointly with the points
    # (its smoothness prior's order and weight chosen by cross-validation), stopped once the field stops moving
    "recommended": {
        "acceleration": Acceleration.ANDERSON,
        "refine": Refine.GRID_POINTS,
        "orientation_response": True,
        "affine_datum": True,
        "smoothness_orders": (2, 3, 4),
        "max_iterations": 3,
        "step_tolerance": 0.05,
        "field_tolerance": 0.1,
        "stall_tolerance": 1e-3,
        "training": Training.LOCAL,
        "field_gauge": FieldGauge.ORIENTATION,
        "fast_intermediate": True,
    },
    # Chow et al.'s loop as written: learn from the inliers, plain fixed-point steps, every solve in full
    "paper": {
        "acceleration": Acceleration.NONE,
        "refine": Refine.NONE,
        "orientation_response": False,
        "affine_datum": False,
        "smoothness_orders": (2,),
        "max_iterations": 30,
        "step_tolerance": 0.0,
        "field_tolerance": 0.0,
        "stall_tolerance": 0.0,
        "training": Training.INLIERS,
        "field_gauge": FieldGauge.NONE,
        "fast_intermediate": False,
    },
}


@dataclass(frozen=True)
class LearnParams:
    """Parameters of the kNN regression and of the alternation.

    Fields marked *(preset)* default to None, "the preset's value": construction
    fills them from :data:`PRESETS` ``[preset]``, so an instance (and the
    cache key hashed from it) always holds the resolved values, and a value
    given explicitly always wins over the preset's. ``dataclasses.replace``
    keeps the resolved values: replacing ``preset`` alone changes nothing else.
    Whether the kNN field is smoothed (gridded) is not a parameter here: the
    scheme decides it (``[calibration] scheme``, ``knn+smooth`` and
    ``knn+iop+smooth``).

    Attributes
    ----------
    preset : str
        ``"recommended"`` (default): Anderson acceleration, then the gridded
        field refined jointly with the object points with the affine datum and
        a smoothness prior whose order and weight are chosen by
        cross-validation, stopped once the field stops moving. ``"paper"``:
        Chow et al.'s loop as written (plain fixed-point steps, learning from
        the adjustment's inliers, no field gauge, every solve in full, up to 30
        iterations), for comparison.
    k_grid : tuple of int
        Candidate neighbourhood sizes for the cross-validation (default
        1, 2, 3, 4, 6, ..., 181, 256: roughly ``sqrt(2)`` steps). Candidates larger
        than a training fold are dropped.
    n_folds : int
        Folds of the cross-validation (default 10, as in the paper).
    grid_spacing_px : float
        Largest spacing between grid nodes (default 16 px); the nodes are
        spread evenly over ``[-0.5, W - 0.5]`` and ``[-0.5, H - 0.5]``.
    seed : int
        Seed of the fold shuffling (default 0).
    support_radius_px : float or None
        Radius within which a node counts observations for the support mask
        (default None: twice ``grid_spacing_px``).
    min_support : int
        Observations needed within ``support_radius_px`` of a node for it to be
        supported (default 3).
    max_iterations : int *(preset)*
        Cap on the kNN alternation's outer iterations (recommended 3: kNN steps
        before the refinement; paper 30, its typical count).
    tolerance : float
        Stop when the combined cost changes by less than ``tolerance`` per
        observation between iterations (default 1e-4).
    step_tolerance : float *(preset)*
        Also stop when the largest change of the correction at any observation
        falls below this fraction of the inlier residual RMS (recommended 0.05;
        paper 0: off, its criterion alone). Inexact inner solves leave the
        combined cost a little noisy near the fixed point; the step still shows
        that the field has stopped moving.
    field_tolerance : float *(preset)*
        Smoothed schemes: the change of the gridded field that counts as none, as a fraction of each
        supported node's own uncertainty in the loop (its ``sigma_px``, the cross-validated residual RMS over
        the square root of the node's bilinear weight; recommended 0.1; paper 0: off). That σ is about 2.5
        times the result's, the joint uncertainty's (median 0.126 against 0.051 px on the 8-exposure set of
        ``tests/stages/test_learn_order.py``), so 0.1 of it is about 0.25 of the σ a user reads. A change of
        ``t σ`` independent of the field's error raises that error by ``sqrt(1 + t²) - 1``: 0.5 % at 0.1,
        3 % at 0.25. The refinement ends (a) when its steps (the largest over the nodes) have shrunk twice
        running and their geometric tail, the last step ``s`` times ``ρ / (1 - ρ)`` with ``ρ`` its ratio to
        the step before, is below this, while the tail of the adjustment's cost's falls, estimated alike, is
        below the cost's own noise, ``1/sqrt(n)`` of it for ``n`` observations. The tail is an estimate, and
        an optimistic one where the contraction slows near the fixed point: on ``benchmarks/run_speed.py``'s
        40-frame set the rule ends the refinement at its third iteration with 0.039 σ estimated still to go
        where the later steps add up to 0.20 σ (biplanar 75 + 75: 0.046 against 0.39 σ), and the field
        against the truth is the same as after 11 more iterations (0.01636 px; biplanar 0.01541 against
        0.01544 px). Or (b) when at two refinement iterations running no node moved by this much with the
        adjustment's cost stopped falling (not below the phase's best so far by ``tolerance`` per
        observation): on rendered frames the inexact inner solves and the centroids' correlated errors leave
        the steps wandering at a few hundredths of a pixel, which the ``step_tolerance`` rule, tied to the
        residual RMS, never reaches.
    stall_tolerance : float *(preset)*
        The refinement also ends at the first iteration whose adjustment cost (equation 2) is not
        below the refinement's best by this fraction of itself (recommended 1e-3; paper 0: off); the
        loop keeps its best iterate, never the last, so one such iteration is enough (issue 31). Each
        joint step is a Gauss-Newton step of the joint problem, so once the cost stops falling the
        field has reached the steps' fixed point: on the 8-exposure 384 px set of
        ``tests/stages/test_learn_order.py``, run until this rule ended it, one more step from the kept
        iterate moved the field by less than 1 % of its σ (the ``field_tolerance`` rule now ends it two
        iterations before, at 8 %). The cost's last changes, a few hundredths of a percent, come from
        inexact inner solves; a weighted sum of squares of ``2n`` residuals fluctuates by about
        ``1/sqrt(n)`` of itself from sample to sample (3 % at 1 000 observations), far above 1e-3. On a
        refinement whose steps wander rather than contract, this rule is the one that ends it.
    acceleration : Acceleration *(preset)*
        ``"none"`` (the paper's plain fixed-point loop), ``"overrelax"``
        (``Δ += relaxation δ``) or ``"anderson"`` (recommended: Anderson
        acceleration of the kNN phase's fixed-point iteration of the gridded field;
        the refinement's Gauss-Newton steps are taken as they are; the
        unsmoothed schemes run it as ``"none"``).
    relaxation : float
        Step factor of ``"overrelax"`` (default 1.5; 1 is the plain loop).
    anderson_depth : int
        Past iterates Anderson acceleration combines (default 10).
    refine : Refine *(preset)*
        ``"none"`` (paper: the kNN only), ``"grid"``: once the kNN
        alternation has converged, continue alternating with the gridded
        least-squares field of :func:`~fluorocal.stages.learn.grid.fit_grid_field`,
        or ``"grid+points"`` (recommended): the same with each field step
        estimated jointly with the orientation's response, the IOP, every pose
        and every object point (:func:`~fluorocal.stages.learn.joint.fit_grids_jointly`:
        a Gauss-Newton step of the joint problem, so the alternation converges
        in a few steps). The unsmoothed schemes run without a refinement.
    orientation_response : bool *(preset)*
        With ``refine="grid+points"``, what the fields' step is estimated jointly with: true
        (recommended): the IOP, every pose (each epoch's reference pose and each further system's ROP)
        and every object point (a Gauss-Newton step of the joint problem); false: the object points
        alone, the IOP and the poses held. Either way every system's field is solved in the same step,
        the beads the systems share tying them (:func:`~fluorocal.stages.learn.joint.fit_grids_jointly`).
        With one system the
        beads-alone step creeps along the principal point / field direction: on the 40 + 40-exposure
        1024 px sets of ``benchmarks/robust.py`` (seeds 0-2) it took 12 iterations to the joint
        step's 7-8, to the same out-of-sample 3D error or a larger one (0.0089 / 0.0069 / 0.0066
        against 0.0088 / 0.0067 / 0.0066 mm), and under gross errors it stopped in a lull of that
        creep (seed 2: 1.58x the clean run's 3D error, against 1.005x with the joint step).
    tau_grid_px : tuple of float
        Candidate smoothness priors (px, standard deviation of a node's
        difference of the prior's order) for the refinement, chosen by
        cross-validation (default 0.03, 0.1, 0.3, 1, 3 px; the prior acts on
        the total field, whose strong radial part has second differences of
        ~0.1 px at a 16 px spacing near the rim of a 1024 px image, so smaller
        values bias it).
    smoothness_folds : int
        Folds of that cross-validation (default 5: it runs once per system and
        each fold costs a sparse factorisation per candidate).
    smoothness_orders : tuple of int *(preset)*
        Candidate orders ``m`` of the difference prior (recommended
        ``(2, 3, 4)``; paper ``(2,)``: the thin-plate energy, second
        differences). The prior penalises the discrete ``m``-th order energy
        ``Σ_a C(m, a) (∂^m Δ / ∂x^(m-a) ∂y^a)²`` (null space: the polynomials
        of degree below ``m``); a higher order assumes a smoother field and
        biases its large-scale, strong part (the radial distortion) less, so it
        can smooth the noise harder. With several candidates the
        cross-validation chooses the order together with ``τ`` (each order
        costs ``len(tau_grid_px)`` candidates more).
    refine_iterations : int
        Cap on the alternation's iterations with the gridded least-squares field (default 100;
        the convergence tests end it before). The beads-alone step converges linearly: on a rendered
        40-frame 1024 px set it took 25 refinement iterations (32 before Anderson's history outlived the
        regression cost's wandering: :mod:`fluorocal.stages.learn.loop`), and a cap of 15 left the field 0.066 px
        from the truth (modulo a homography) against 0.016 px converged; the joint step on a weak
        biplanar set (4 + 4 frames of 512 px) took 74 when each system's step was solved alone.
    affine_datum : bool *(preset)*
        With ``refine="grid+points"``: hold the phantom's affine shape beyond a
        similarity (stretches and shears: 5 degrees of freedom) at the nominal
        design's while refining (recommended True, paper False: its inner
        constraints only; left unset it is False whenever ``refine`` is not
        ``"grid+points"``). In a free network these deformations trade off
        against an image aspect ratio or shear of the field through weak
        perspective effects only; see
        :func:`~fluorocal.stages.learn.joint.fit_grids_jointly`. If a real
        phantom is stretched or sheared as a whole, that error passes into
        the result: set it False then.
    training : Training *(preset)*
        Which observations each regression learns from. ``"inliers"``: the
        adjustment's inliers (paper). ``"local"`` (recommended): every
        observation the adjustment used, less those the fitted field itself
        cannot explain (squared standardised misfit above ``outlier_chi2``
        times its median / ln 4, the robust scale of a 2-D Gaussian), refitted
        without them. While the distortion is still unmodelled the
        adjustment's t-weights flag the strongly distorted rim of the field as
        outliers, so an inlier-only regression never learns the rim and the
        loop stalls; gross errors (mislabels), unlike distortion, are not
        shared by their neighbours, which is what the local test uses. With
        ``"local"`` the joint refinement also weights observations by their
        variances only, not their t-weights.
    field_gauge : FieldGauge *(preset)*
        ``"orientation"`` (recommended): after every update, remove from each
        system's field its least-squares component (over the observations)
        that the orientation parameters reproduce exactly: an image rotation
        and the two "keystone" fields of a common rotation of every pose
        (absorbed, biplanar, by the ROP), and, when the IOP are estimated, a
        principal-point shift and a principal-distance scaling. These trade
        one for one between field and adjustment; left free they let the
        IOP (and the alternation's fixed point) drift without bound, as on a
        turntable set. The IOP then are the best pinhole over the observed
        area, and the field the departure from it. ``"none"`` (paper): the
        field keeps whatever the loop leaves in it.
    outlier_chi2 : float
        Threshold of the local outlier test of ``training="local"`` (default
        23: a 2-D Gaussian exceeds it with probability 1e-5).
    screen_chi2 : float
        Threshold, in the same units, of the screen that runs before that
        test (``training="local"``): each observation against the median
        residual of its 16 nearest neighbours
        (:func:`~fluorocal.stages.learn.robust.local_screen`); those beyond
        it are left out of the cross-validation and the first fit, and every
        observation's out-of-fold cost is bounded at it, so that gross errors
        (a bead moved by a few px, a label swapped with a neighbour's) decide
        neither ``k`` nor the smoothness (default 368, sixteen times
        ``outlier_chi2``: four times the distance, about 1 px at 0.05 px
        noise, still far below a 3 px gross error). The neighbours' median is
        a rougher local estimate than the fitted field (one-sided at the rim
        of the covered area, biased by the unmodelled distortion's curvature
        early on), and a clean observation left out of the cross-validation
        costs accuracy where the field is strongest: measured, 23 changed
        the clean run's choices on ``benchmarks/robust.py``'s set, 92 still
        those of a 14-exposure 512 px set, 368 neither.
    fast_intermediate : bool *(preset)*
        Solve the loop's intermediate adjustments without the covariance and
        redundancy numbers (each observation gets the mean redundancy), with
        ``function_tolerance`` at least 1e-3 and at most 10 iterations (they
        are warm-started), and only the final solve in full (recommended
        True). False (paper): every solve with the ``[adjust]`` solver options, in full.
    polynomial_fixed : tuple of str
        Scheme ``polynomial`` only: its coefficients held at zero (default
        ``("b1", "b2")``, the affinity; ``()`` estimates all of k1-k3, p1, p2,
        b1, b2). The scheme owns the adjustment's additional parameters, so
        this is where they are chosen.

    Examples
    --------
    >>> str(LearnParams().refine), str(LearnParams(preset="paper").refine)
    ('grid+points', 'none')
    >>> p = LearnParams(preset="paper", max_iterations=5)
    >>> p.max_iterations, p.training is Training.INLIERS
    (5, True)
    >>> LearnParams(refine="grid").affine_datum
    False
    """

    preset: str = "recommended"
    k_grid: tuple = DEFAULT_K_GRID
    n_folds: int = 10
    grid_spacing_px: float = 16.0
    seed: int = 0
    support_radius_px: float | None = None
    min_support: int = 3
    max_iterations: int | None = None
    tolerance: float = 1e-4
    step_tolerance: float | None = None
    field_tolerance: float | None = None
    stall_tolerance: float | None = None
    acceleration: Acceleration | None = None
    relaxation: float = 1.5
    anderson_depth: int = 10
    refine: Refine | None = None
    orientation_response: bool | None = None
    tau_grid_px: tuple = DEFAULT_TAU_GRID_PX
    smoothness_folds: int = 5
    smoothness_orders: tuple[int, ...] | None = None
    refine_iterations: int = 100
    affine_datum: bool | None = None
    training: Training | None = None
    field_gauge: FieldGauge | None = None
    outlier_chi2: float = 23.0
    screen_chi2: float = 368.0
    fast_intermediate: bool | None = None
    polynomial_fixed: tuple[str, ...] = ("b1", "b2")

    def __post_init__(self):
        self._resolve_preset()
        self._check_choices()
        self._check_numbers()

    def _resolve_preset(self):
        if self.preset not in PRESETS:
            raise InputError(f"preset must be one of {', '.join(PRESETS)}; got {self.preset!r}")
        values = PRESETS[self.preset]
        for name in SWITCHES:  # a switch given by its spelling is held as its enumeration's member
            if getattr(self, name) is not None:
                object.__setattr__(self, name, parse_switch(name, getattr(self, name)))
        refine = self.refine if self.refine is not None else values["refine"]
        for name, value in values.items():
            if getattr(self, name) is None:
                # the affine datum constrains the joint refinement's point shifts: unset, it follows refine
                value = value and refine is Refine.GRID_POINTS if name == "affine_datum" else value
                object.__setattr__(self, name, value)

    def _check_choices(self):
        if not isinstance(self.orientation_response, bool):
            raise InputError(
                f"orientation_response must be true or false (unquoted); got {self.orientation_response!r}"
            )
        if self.affine_datum and self.refine is not Refine.GRID_POINTS:
            raise InputError(
                "affine_datum needs refine='grid+points' (it constrains the point shifts); "
                f"got refine={self.refine.value!r}"
            )
        object.__setattr__(self, "smoothness_orders", tuple(sorted({int(m) for m in self.smoothness_orders})))
        if not self.smoothness_orders or not set(self.smoothness_orders) <= set(DIFFERENCE_STENCILS):
            raise InputError(
                f"smoothness_orders must hold orders among {tuple(DIFFERENCE_STENCILS)}; got {self.smoothness_orders}"
            )

    def _check_numbers(self):
        object.__setattr__(self, "k_grid", tuple(sorted({int(k) for k in self.k_grid})))
        if not self.k_grid or self.k_grid[0] < 1:
            raise InputError(f"k_grid must hold positive integers; got {self.k_grid}")
        if self.n_folds < 2:
            raise InputError(f"n_folds must be >= 2; got {self.n_folds}")
        if not self.grid_spacing_px > 0:
            raise InputError(f"grid_spacing_px must be > 0; got {self.grid_spacing_px}")
        object.__setattr__(self, "tau_grid_px", tuple(float(t) for t in self.tau_grid_px))
        if not self.tau_grid_px or min(self.tau_grid_px) <= 0:
            raise InputError(f"tau_grid_px must hold positive values; got {self.tau_grid_px}")
        if not 0 < self.relaxation < 2:
            raise InputError(f"relaxation must lie in (0, 2); got {self.relaxation}")
        if self.max_iterations < 1:
            raise InputError(f"max_iterations must be >= 1; got {self.max_iterations}")
        for name in ("step_tolerance", "field_tolerance", "stall_tolerance"):
            if not getattr(self, name) >= 0:
                raise InputError(f"{name} must be >= 0; got {getattr(self, name)}")
        if not self.outlier_chi2 > 0:
            raise InputError(f"outlier_chi2 must be > 0; got {self.outlier_chi2}")
        if not self.screen_chi2 > 0:
            raise InputError(f"screen_chi2 must be > 0; got {self.screen_chi2}")

    @property
    def support_radius(self) -> float:
        """Support radius in px (``support_radius_px`` or twice the grid spacing)."""
        return float(self.support_radius_px if self.support_radius_px is not None else 2 * self.grid_spacing_px)

    @property
    def grid(self) -> GridSpec:
        """The node grid and support rule of the learned fields."""
        return GridSpec(self.grid_spacing_px, self.support_radius, self.min_support)
