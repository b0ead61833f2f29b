"""The pipeline's share of a grid plate: its outputs, its evaluation and what its later frames are checked by.

A :class:`PlatePart`, looked up by :func:`fluorocal.kinds.part_of` for a
:class:`~fluorocal.stages.kinds.GridPlate`.
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

from fluorocal import evaluate_common as common

log = logging.getLogger("fluorocal")

#: a grid plate's figures (:func:`fluorocal.stages.evaluate.plate.evaluate_plate`): RMS lengths after a homography
FIGURES = {
    "out_rms_px": "held-out holes vs self-calibrated layout, RMS length (px)",
    "out_nominal_rms_px": "held-out holes vs nominal lattice, RMS length (px)",
    "in_rms_px": "in-sample holes vs self-calibrated layout, RMS length (px)",
}


class PlatePart:
    """A grid plate's outputs (:mod:`fluorocal.export_plate`), evaluation and check (:mod:`fluorocal.kinds`)."""

    scored_on = "held-out rows of each frame"
    figures = FIGURES
    rms_columns = {name: FIGURES[name] for name in ("in_rms_px", "out_rms_px", "out_nominal_rms_px")}
    trained_on = "frames"

    def export(self, runner, result, obs, excluded, out_dir: Path, figures) -> list[Path]:
        """``calibration.json`` (no geometry), the layout, observations, report (:mod:`fluorocal.export_plate`)."""
        from fluorocal.export_plate import export_plate

        return export_plate(runner, result, obs, excluded, out_dir, figures)

    def evaluate(self, args, config, runner, out_dir: Path) -> int:
        """The grid plate's protocol (:mod:`fluorocal.cmd_evaluate`): held-out rows of each frame, by size, scheme."""
        import numpy as np
        from fluorocal.stages.evaluate.plate import PlateSetup, evaluate_plate

        schemes = _plate_schemes(args.schemes)
        _plate_sizes(args.train_sizes, [sum(u.system == s for u in runner.units) for s in range(len(config.systems))])
        runner.run()
        obs = common.observations(runner)
        scored = None if args.holdout is None else common.heldout(args.holdout, runner, obs)
        sizes = _plate_sizes(
            args.train_sizes, [len(np.unique(obs.exposure[obs.system == s])) for s in range(len(config.systems))]
        )
        extras = common.registered_stage("learn").extras(config, runner.units)
        plan = extras["setup"]
        setup = PlateSetup(
            runner.get("phantom", None), plan.image_size_px, plan.orientations, extras["plate"], extras["solver"]
        )
        log.info("evaluate (grid plate): sizes %s frames; schemes %s", ",".join(map(str, sizes)), ",".join(schemes))
        t0 = time.perf_counter()
        bars = SizeBars(runner.progress and sys.stderr.isatty())
        try:
            result = evaluate_plate(obs, sizes, schemes, setup, scored=scored, progress=common.progress, step=bars)
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
            "Made by `fluorocal evaluate " + " ".join(common.argv(args)) + "`.",
        ]
        return common.publish(out_dir, config, self, result, "plate", notes, setup.image_size_px, t0)

    def check_setup(self, tables, config, table):
        """The plate's lattice and its layout as self-calibrated (``table``: its object points)."""
        import numpy as np
        from fluorocal.check_setups import PlateSetup
        from fluorocal.stages.label.lattice import lattice_index

        ph = config.phantom
        layout = np.column_stack([table["x"], table["y"]])
        return PlateSetup(tables, ph.lattice, ph.pitch_mm, lattice_index(np.asarray(table["id"], np.int64)), layout)


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
    return check_train_sizes(common.parsed_sizes(text), n, 1, why=why)


class SizeBars:
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
