"""The pipeline's share of a 3D bead phantom: its outputs, its evaluation and what its later frames are checked by.

A :class:`BeadPart`, looked up by :func:`fluorocal.kinds.part_of` for a
:class:`~fluorocal.stages.kinds.BeadPhantom`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from fluorocal import evaluate_common as common

log = logging.getLogger("fluorocal")

#: the figures compared between fluorocal and its peers (all: lower is better), with their table headings
FIGURES = {
    "tworay_mean_mm": "two-ray mean 3D (mm)",
    "tworay_avg_rmse_mm": "two-ray avg RMSE (mm)",
    "out_3d_rigid_mm": "out-of-sample 3D, rigid (mm)",
    "out_3d_similarity_mm": "out-of-sample 3D, similarity (mm)",
    "out_rms_px": "out-of-sample reprojection RMS (px)",
    "in_rms_px": "in-sample reprojection RMS (px)",
}


class BeadPart:
    """A bead phantom's outputs (:mod:`fluorocal.export_beads`), evaluation and check (:mod:`fluorocal.kinds`)."""

    scored_on = "held-out epochs, and check points with --reference"
    figures = FIGURES
    rms_columns = {"in_rms_px": "in-sample RMS (px)", "out_rms_px": "out-of-sample RMS (px)"}
    trained_on = "epochs"

    def export(self, runner, result, obs, excluded, out_dir: Path, figures) -> list[Path]:
        """``calibration.json``, object points, observations, report (:func:`~fluorocal.export_beads.export_beads`)."""
        from fluorocal.export_beads import export_beads

        return export_beads(runner, result, obs, excluded, out_dir, figures)

    def evaluate(self, args, config, runner, out_dir: Path) -> int:
        """The paper's protocol (:mod:`fluorocal.cmd_evaluate`): held-out epochs, per training size and scheme."""
        from fluorocal.stages.evaluate import evaluate

        args.holdout = args.holdout or ["odd"]
        reference = _reference(args.reference, runner) if args.reference else None
        schemes, ours = _schemes(args.schemes, config.scheme, reference is not None)
        common.parsed_sizes(args.train_sizes)  # the syntax before any work; the range once the epochs are known
        runner.run()
        obs = common.observations(runner)
        heldout = common.heldout(args.holdout, runner, obs)
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
        result = evaluate(obs, heldout, sizes, schemes, setup, progress=common.progress)
        notes = _notes(args, config, heldout, result.scores, ours, time.perf_counter() - t0)
        return common.publish(out_dir, config, self, result, ours, notes, setup.image_size_px, t0)

    def check_setup(self, tables, config, table):
        """The phantom's beads as the calibration adjusted them (``table``: its object points)."""
        import numpy as np
        from fluorocal.check_setups import PhantomSetup
        from fluorocal.stages.io import read_phantom

        xyz = np.column_stack([table["x"], table["y"], table["z"]])
        return PhantomSetup(tables, read_phantom(config.phantom.file), np.asarray(table["id"], np.int64), xyz)


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
        unknown = [n for n in names if n not in common.SCHEME_NAMES]
        if unknown or not names:
            raise InputError(
                f"--schemes: unknown scheme {unknown[0] if unknown else text!r}; "
                f"known: {', '.join(common.SCHEME_NAMES)}"
            )
        if "opencv" in names and not have_reference:
            raise InputError("--schemes: opencv needs --reference (OpenCV calibrates against known 3D points)")
        learned = [n for n in names if n in SCHEMES and Scheme(n).learn_field]
        ours = ours if ours in names or not learned else learned[0]
    return names, ours


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
    return check_train_sizes(common.parsed_sizes(text), n_train, minimum)


def _setup(runner, reference):
    from fluorocal.run import stage_params
    from fluorocal.stages.evaluate import EvaluationSetup

    learn = common.registered_stage("learn")
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


def _notes(args, config, heldout, scores, ours: str, seconds: float) -> list[str]:
    from fluorocal.evaluation import headline

    key = headline(scores)
    where = "check points" if args.reference else "the nominal phantom (no --reference)"
    return [
        f"Project `{config.path.name}`; held out ({' '.join(args.holdout)}): {len(heldout)} epochs; "
        f"fluorocal's scheme: {ours}; % improvement is over `none` on {FIGURES[key]}.",
        f"Two-ray points (biplanar) are fitted per epoch onto {where}. Wall time {seconds:.1f} s.",
        "Made by `fluorocal evaluate " + " ".join(common.argv(args)) + "`.",
    ]
