"""`fluorocal evaluate CONFIG`: the paper's protocol (section VI, TABLE I) on a project's own frames.

Half the epochs (exposures; a biplanar pair is one epoch) are held out. For each
training size and scheme the project is calibrated on that many of the other
epochs (evenly spaced) and scored:

  in-sample      reprojection RMS of the training adjustment (inliers, px)
  out-of-sample  the held-out epochs adjusted with the calibrated IOP and correction held fixed
                 (poses and object points free): reprojection RMS (inliers, px)
  check points   with --reference: the training and held-out object points against the surveyed
                 points after a rigid (6-parameter) and a similarity (7-parameter) fit, RMS mm
  two-ray        biplanar projects: each held-out pair's beads intersected from their two rays
                 (calibrated IOP, ROP, fields), fitted per epoch onto the check points (or, without
                 --reference, the nominal phantom) by a rigid transform: X, Y, Z RMSE, their
                 average and the mean 3D error, mm (TABLE I's columns)

Schemes (default: none, polynomial, the project's [calibration] scheme and, with --reference,
opencv): none (IOP + EOP only, no field), polynomial (global radial + decentring model in the
adjustment), knn, knn+iop, knn+smooth, knn+iop+smooth (the learned field), and opencv
(cv2.calibrateCamera, rational + thin-prism + tilted model, on the check points; needs --reference).

The labelling is taken from the project's cache (`fluorocal run` fills it; what is missing is
computed once), never repeated per training size. Outputs, published as one set into --out:
evaluation.csv (a row per scheme and size), evaluation.md (the table; a line for every figure
where a peer beats fluorocal's scheme), evaluation_errors.png (each figure against the training
size), evaluation_improvement.png (over none) and evaluation_residuals_<system>.png (held-out
residuals of each scheme at the largest size).

Grid plates ([phantom] lattice) are scored on held-out holes instead: for every frame (--holdout: the
frames scored; default all) and lattice-row parity, each scheme is fitted without that frame's holes on
those rows, and the held-out holes, corrected, are compared by a best-fitting homography with the plate's
layout as self-calibrated from the same training holes, and with the nominal lattice (RMS lengths, px).
A training size counts the frames the plate is self-calibrated from: the scored frame (its other rows)
and others evenly spaced (default: 5 sizes up to every frame of a system). Schemes: plate (fluorocal's:
a field per orientation and the plate's errors, with the project's [plate]; always run, its layout is
the reference), none (a homography of the nominal plate per frame) and polynomial (the radial +
decentring model of scheme polynomial per orientation, the plate nominal). The in-sample figure is the
same comparison on the scored frames' training rows. No opencv for a plate: calibrateCamera needs the
plate seen at several tilts to fix its intrinsics, and a plate on the intensifier is seen square on.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from fluorocal.cli_common import add_out, load_project, project_runner

log = logging.getLogger("fluorocal")

#: the schemes of stages.learn.SCHEMES and the OpenCV peer (listed here so that --help imports nothing)
SCHEME_NAMES = ("none", "knn", "knn+iop", "knn+smooth", "knn+iop+smooth", "polynomial", "opencv")


def add_parser(subparsers) -> None:
    """Register the ``evaluate`` subcommand."""
    p = subparsers.add_parser(
        "evaluate",
        help="the paper's held-out protocol on a project: schemes x training sizes, table and plots",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("config", type=Path, help="project TOML file")
    p.add_argument(
        "--holdout",
        action="append",
        metavar="RULE|FILE",
        help="held-out epochs: odd (every other one from the second; the default), even, random:SEED (half, "
        "drawn with SEED), or a frame file of the project (its epoch is held out in every system; repeat "
        "--holdout for several); for a grid plate the frames whose alternate rows are scored (default: every frame)",
    )
    p.add_argument(
        "--train-sizes",
        metavar="N,N,...",
        help="training epochs per calibration (default: 5 sizes evenly spaced up to all training epochs); for a "
        "grid plate, frames (default: 5 sizes up to every frame of a system)",
    )
    p.add_argument(
        "--schemes",
        metavar="a,b,...",
        help=f"comma-separated, of {', '.join(SCHEME_NAMES)} (default: none, polynomial, the project's scheme; "
        "opencv too with --reference); for a grid plate of none, polynomial, plate (default: all three)",
    )
    p.add_argument("--reference", type=Path, metavar="CSV", help="surveyed check points id,x,y,z mm (default: none)")
    add_out(p, "output folder (default: evaluation/ beside the config)")
    p.set_defaults(func=run)


def run(args) -> int:
    from fluorocal.stages.evaluate import evaluate

    config, runner = _project(args)
    out_dir = _check_out(args, config)
    if not config.phantom.kind.check_points:
        return _run_plate(args, config, runner, out_dir)
    args.holdout = args.holdout or ["odd"]
    reference = _reference(args.reference, runner) if args.reference else None
    schemes, ours = _schemes(args.schemes, config.scheme, reference is not None)
    _parsed_sizes(args.train_sizes)  # the syntax before any work; the range once the epochs are known
    runner.run()
    obs = _observations(runner)
    heldout = _heldout(args.holdout, runner, obs)
    setup = _setup(runner, reference)
    sizes = _sizes(args.train_sizes, obs, heldout, setup.selection)
    log.info(
        "evaluate: %d training + %d held-out epochs; sizes %s; schemes %s",
        len(set(obs.exposure.tolist()) - set(heldout.tolist())),
        len(heldout),
        ",".join(map(str, sizes)),
        ",".join(schemes),
    )
    t0 = time.perf_counter()
    result = evaluate(obs, heldout, sizes, schemes, setup, progress=_progress)
    notes = _notes(args, config, heldout, result.scores, ours, time.perf_counter() - t0)
    return _publish(out_dir, config, result, ours, notes, setup.image_size_px, t0)


def _run_plate(args, config, runner, out_dir: Path) -> int:
    """The grid plate's protocol (module docstring): held-out rows of each frame, per training size and scheme."""
    import numpy as np
    from fluorocal.stages.evaluate.plate import PlateSetup, evaluate_plate

    schemes = _plate_schemes(args.schemes)
    _plate_sizes(args.train_sizes, [sum(u.system == s for u in runner.units) for s in range(len(config.systems))])
    runner.run()
    obs = _observations(runner)
    scored = None if args.holdout is None else _heldout(args.holdout, runner, obs)
    sizes = _plate_sizes(
        args.train_sizes, [len(np.unique(obs.exposure[obs.system == s])) for s in range(len(config.systems))]
    )
    extras = _stage("learn").extras(config, runner.units)
    plan = extras["setup"]
    setup = PlateSetup(
        runner.get("phantom", None), plan.image_size_px, plan.orientations, extras["plate"], extras["solver"]
    )
    log.info("evaluate (grid plate): sizes %s frames; schemes %s", ",".join(map(str, sizes)), ",".join(schemes))
    t0 = time.perf_counter()
    bars = _SizeBars(runner.progress and sys.stderr.isatty())
    try:
        result = evaluate_plate(obs, sizes, schemes, setup, scored=scored, progress=_progress, step=bars)
    finally:
        bars.close()
    held = "every frame" if args.holdout is None else f"the frames of --holdout {' '.join(args.holdout)}"
    notes = [
        f"Project `{config.path.name}` (grid plate): {held} scored on alternate lattice rows, each row parity "
        "held out in turn; RMS lengths of the corrected holes after a best-fitting homography, px; the "
        "self-calibrated layout is fluorocal's (scheme plate) from the same training holes; % improvement is "
        "over `none`.",
        f"A training size counts the frames the plate is self-calibrated from (the scored one among them). "
        f"Wall time {time.perf_counter() - t0:.1f} s.",
        "Made by `fluorocal evaluate " + " ".join(_argv(args)) + "`.",
    ]
    return _publish(out_dir, config, result, "plate", notes, setup.image_size_px, t0)


def _plate_schemes(text) -> list[str]:
    """A grid plate's schemes of ``--schemes`` (default none, polynomial, plate); plate always among them."""
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.evaluate.plate import PLATE_SCHEMES

    if text is None:
        return [*PLATE_SCHEMES[1:], PLATE_SCHEMES[0]]  # the peers, then fluorocal's
    names = list(dict.fromkeys(n.strip() for n in text.split(",") if n.strip()))
    unknown = [n for n in names if n not in PLATE_SCHEMES]
    if unknown or not names:
        why = (
            " (OpenCV's calibrateCamera needs the plate seen at several tilts; on the intensifier it is seen square on)"
            if "opencv" in unknown
            else ""
        )
        raise InputError(
            f"--schemes: a grid plate is evaluated with {', '.join(PLATE_SCHEMES)}; "
            f"got {unknown[0] if unknown else text!r}{why}"
        )
    return names + [PLATE_SCHEMES[0]] * (PLATE_SCHEMES[0] not in names)


def _plate_sizes(text, counts: list[int]) -> tuple[int, ...]:
    """A grid plate's training sizes (frames; default 5 up to the fewest frames of a system), checked."""
    from fluorocal.stages.evaluate import check_train_sizes, default_train_sizes

    n = min(counts)
    why = f"a system of the plate project has {n} frame(s), the scored one among its training frames"
    if text is None:
        return check_train_sizes(default_train_sizes(n, minimum=1), n, 1, why=why)
    return check_train_sizes(_parsed_sizes(text), n, 1, why=why)


class _SizeBars:
    """A progress bar for each training size of a plate's evaluation (its scored frames' fits), on stderr.

    Shown on a terminal unless ``--quiet``, as the stages' bars are; closed before the size's scores are logged.
    """

    def __init__(self, shown: bool):
        self.shown = shown
        self.bar = None

    def __call__(self, size: int, done: int, total: int) -> None:
        from tqdm import tqdm

        if done == 0:
            self.bar = tqdm(
                total=total, desc=f"evaluate, training size {size}", unit="frame", leave=False, disable=not self.shown
            )
            return
        self.bar.update(1)
        if done == total:
            self.close()

    def close(self) -> None:
        """Close the open bar, if any (at the end of a size, or when the evaluation stops with an error)."""
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _progress(score) -> None:
    log.info(
        "  %s, %d: out-of-sample RMS %.4f px (%.1f s)", score.scheme, score.n_train, score.out_rms_px, score.wall_s
    )


def _publish(out_dir: Path, config, result, ours: str, notes: list[str], image_size_px, t0: float) -> int:
    """Write the evaluation's files, print its table and the headline line."""
    from fluorocal.evaluation import headline, publish_evaluation

    names = tuple(s.name for s in config.systems)
    written = publish_evaluation(
        out_dir, result, ours, notes, systems=names, image_size_px=image_size_px, owner=config.path
    )
    md = next(p for p in written if p.name == "evaluation.md")
    lines = md.read_text(encoding="utf-8").splitlines()
    print("\n".join(line for line in lines if line.startswith(("|", "- ", "No peer"))))
    key = headline(result.scores)
    print(f"headline figure: {key}; wall {time.perf_counter() - t0:.1f} s; wrote {len(written)} file(s) to {out_dir}")
    return 0


def _project(args):
    from fluorocal.stages.errors import InputError

    config = load_project(args.config)
    if args.reference and not config.phantom.kind.check_points:
        raise InputError(f"--reference: {config.phantom.kind.noun} has no check points (scored on held-out rows)")
    return config, project_runner(args, config, until="label")


def _check_out(args, config) -> Path:
    from fluorocal.export import check_outputs

    out = args.out if args.out is not None else config.path.parent / "evaluation"
    return check_outputs(config, out_dir=out)


def _reference(path: Path, runner):
    """``(ids, xyz_mm)`` of the check points CSV, refused in one line before any work.

    Refused: unreadable, a cell not finite, an id given twice, or no id among the phantom's beads.
    """
    import numpy as np
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.io import PHANTOM, read_table

    try:
        table = read_table(path, PHANTOM)
    except OSError as exc:
        raise InputError(f"--reference {path}: cannot read ({exc.strerror or exc})") from None
    except InputError as exc:
        raise InputError(f"--reference: {exc}") from None
    ids, xyz = table["id"].astype(np.int64), np.column_stack([table["x"], table["y"], table["z"]])
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise InputError(f"--reference {path}:{int(np.argmax(bad)) + 2}: coordinates must be finite numbers")
    values, counts = np.unique(ids, return_counts=True)
    if (counts > 1).any():
        raise InputError(f"--reference {path}: id {int(values[counts > 1][0])} is given more than once")
    if not np.isin(ids, runner.get("phantom", None).ids).any():
        raise InputError(f"--reference {path}: no id matches a bead of the project's phantom")
    return ids, xyz


def _schemes(text, project_scheme, have_reference: bool) -> tuple[list[str], str]:
    """The schemes to run and fluorocal's own (the project's learned scheme, else the recommended one)."""
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.learn.params import SCHEMES, Scheme

    ours = project_scheme if project_scheme.learn_field else Scheme.KNN_IOP_SMOOTH
    if text is None:
        names = ["none", "polynomial", ours] + (["opencv"] if have_reference else [])
    else:
        names = list(dict.fromkeys(n.strip() for n in text.split(",") if n.strip()))
        unknown = [n for n in names if n not in SCHEME_NAMES]
        if unknown or not names:
            raise InputError(
                f"--schemes: unknown scheme {unknown[0] if unknown else text!r}; known: {', '.join(SCHEME_NAMES)}"
            )
        if "opencv" in names and not have_reference:
            raise InputError("--schemes: opencv needs --reference (OpenCV calibrates against known 3D points)")
        learned = [n for n in names if n in SCHEMES and Scheme(n).learn_field]
        ours = ours if ours in names or not learned else learned[0]
    return names, ours


def _observations(runner):
    from fluorocal.gather import observations_from_labels

    labels = [runner.get("label", u) for u in range(len(runner.units))]
    return observations_from_labels(runner.units, labels, runner.config)


def _heldout(values: list[str], runner, obs):
    """The held-out epochs of ``--holdout``: a keyword rule, or the epochs of the frame files named."""
    import numpy as np
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.evaluate import heldout_epochs

    epochs = np.unique(obs.exposure)
    rule = values[0] in ("odd", "even") or values[0].startswith("random:") or not Path(values[0]).exists()
    if len(values) == 1 and rule:  # a keyword, or no file: the rule's error lists the keywords
        return heldout_epochs(epochs, values[0])
    by_path = {}
    for unit in runner.units:
        by_path.setdefault(unit.path.resolve(), []).append(unit.exposure)
    held = []
    for value in values:
        found = by_path.get(Path(value).resolve())
        if found is None:
            raise InputError(f"--holdout {value}: not a frame file of this project (see [[systems]] frames)")
        held += found
    return np.unique(np.asarray(held, dtype=np.int64))


def _sizes(text, obs, heldout, selection):
    """The training sizes of ``--train-sizes`` (default: 5 evenly spaced), refused outside what the project allows."""
    import numpy as np
    from fluorocal.stages.adjust import DataSelection
    from fluorocal.stages.evaluate import check_train_sizes, default_train_sizes, min_train_epochs

    n_train = len(np.setdiff1d(np.unique(obs.exposure), heldout))
    selection = DataSelection() if selection is None else selection
    minimum = min_train_epochs(len(obs.system_names), selection.min_exposures)
    if text is None:
        text = ",".join(map(str, default_train_sizes(n_train, minimum=minimum)))
    return check_train_sizes(_parsed_sizes(text), n_train, minimum)


def _parsed_sizes(text) -> list[int] | None:
    """``--train-sizes`` as integers (None when not given)."""
    from fluorocal.stages.errors import InputError

    if text is None:
        return None
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--train-sizes must be comma-separated integers; got {text!r}") from None


def _setup(runner, reference):
    from fluorocal.run import stage_params
    from fluorocal.stages.evaluate import EvaluationSetup

    learn = _stage("learn")
    params = stage_params(learn, runner.config, None, runner.units)
    extras = learn.extras(runner.config, runner.units)
    setup = extras["setup"]
    return EvaluationSetup(
        runner.get("phantom", None),
        setup.image_size_px,
        setup.iop_guess_px,
        params,
        extras["solver"],
        extras["selection"],
        reference,
    )


def _stage(name: str):
    """The registered stage ``name`` (the runner may stop before it)."""
    from fluorocal.graph import default_stages

    return next(s for s in default_stages() if s.name == name)


def _notes(args, config, heldout, scores, ours: str, seconds: float) -> list[str]:
    from fluorocal.evaluation import FIGURES, headline

    key = headline(scores)
    where = "check points" if args.reference else "the nominal phantom (no --reference)"
    return [
        f"Project `{config.path.name}`; held out ({' '.join(args.holdout)}): {len(heldout)} epochs; "
        f"fluorocal's scheme: {ours}; % improvement is over `none` on {FIGURES[key]}.",
        f"Two-ray points (biplanar) are fitted per epoch onto {where}. Wall time {seconds:.1f} s.",
        "Made by `fluorocal evaluate " + " ".join(_argv(args)) + "`.",
    ]


def _argv(args) -> list[str]:
    """The command's arguments as given (``--holdout`` only when given: a plate's default is every frame)."""
    out = [str(args.config), *(word for value in args.holdout or () for word in ("--holdout", value))]
    for flag, value in (("--train-sizes", args.train_sizes), ("--schemes", args.schemes)):
        if value:
            out += [flag, value]
    if args.reference:
        out += ["--reference", str(args.reference)]
    return out
