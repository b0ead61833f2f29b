"""What the phantom kinds' evaluations share (``fluorocal evaluate``, :mod:`fluorocal.cmd_evaluate`).

The observations and held-out frames of a project, the training sizes' syntax, the progress line, the
published outputs and the command line they were made by. Imports nothing at module level but the standard
library, so that ``--help`` stays instant.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

log = logging.getLogger("fluorocal")

#: the schemes of stages.learn.SCHEMES and the OpenCV peer (listed here so that --help imports nothing)
SCHEME_NAMES = ("none", "knn", "knn+iop", "knn+smooth", "knn+iop+smooth", "polynomial", "opencv")


def observations(runner):
    """The project's labelled observations (the runner's labels, gathered as the learning stage takes them)."""
    from fluorocal.gather import observations_from_labels

    labels = [runner.get("label", u) for u in range(len(runner.units))]
    return observations_from_labels(runner.units, labels, runner.config)


def heldout(values: list[str], runner, obs):
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


def parsed_sizes(text) -> list[int] | None:
    """``--train-sizes`` as integers (None when not given).

    Examples
    --------
    >>> parsed_sizes("2, 4,8"), parsed_sizes(None)
    ([2, 4, 8], None)
    """
    from fluorocal.stages.errors import InputError

    if text is None:
        return None
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--train-sizes must be comma-separated integers; got {text!r}") from None


def registered_stage(name: str):
    """The registered stage ``name`` (the runner may stop before it)."""
    from fluorocal.graph import default_stages

    return next(s for s in default_stages() if s.name == name)


def progress(score) -> None:
    """Log one score as it is made."""
    log.info(
        "  %s, %d: out-of-sample RMS %.4f px (%.1f s)", score.scheme, score.n_train, score.out_rms_px, score.wall_s
    )


def publish(out_dir: Path, config, part, result, ours: str, notes: list[str], image_size_px, t0: float) -> int:
    """Write the evaluation's files, print its table and the headline line; ``part``: the kind's, scoring it."""
    from fluorocal.evaluation import headline, publish_evaluation

    names = tuple(s.name for s in config.systems)
    written = publish_evaluation(
        out_dir, result, ours, notes, part=part, systems=names, image_size_px=image_size_px, owner=config.path
    )
    md = next(p for p in written if p.name == "evaluation.md")
    lines = md.read_text(encoding="utf-8").splitlines()
    print("\n".join(line for line in lines if line.startswith(("|", "- ", "No peer"))))
    key = headline(result.scores)
    print(f"headline figure: {key}; wall {time.perf_counter() - t0:.1f} s; wrote {len(written)} file(s) to {out_dir}")
    return 0


def argv(args) -> list[str]:
    """The command's arguments as given (``--holdout`` only when given: a plate's default is every frame)."""
    out = [str(args.config), *(word for value in args.holdout or () for word in ("--holdout", value))]
    for flag, value in (("--train-sizes", args.train_sizes), ("--schemes", args.schemes)):
        if value:
            out += [flag, value]
    if args.reference:
        out += ["--reference", str(args.reference)]
    return out
