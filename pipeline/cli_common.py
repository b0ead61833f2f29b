"""What the command modules share: the one spelling of each shared option, its parser, project loading.

:mod:`fluorocal.cli` and every ``cmd_<name>`` module import from here, never from each other, so the
command line has no import cycle. Each option that more than one command takes is added by one
function below, so that it is spelled, parsed and documented once:

==================  =====================================================================
concept             spelling
==================  =====================================================================
existing outputs    ``--overwrite`` (:func:`add_overwrite`)
recompute a stage   ``--force STAGE`` (``run`` only)
C-arm angles        ``orbit=DEG,tilt=DEG`` (:func:`parse_orientation`), the config's keys
image size          ``--image-size W H`` (:func:`add_image_size`)
output              ``--out DIR``: always a folder
calibration file    the positional ``CALIBRATION``
rough geometry      ``--source-image-distance MM``, ``--pixel-pitch MM``: the config's keys
==================  =====================================================================

Nothing here imports more than the standard library at import time, so ``--help`` stays instant.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path


def positive_int(text: str) -> int:
    """An argparse type: a positive integer (``--jobs``, ``--image-size``).

    Examples
    --------
    >>> positive_int("512")
    512
    >>> positive_int("-1")
    Traceback (most recent call last):
    argparse.ArgumentTypeError: expected a positive integer; got '-1'
    """
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer; got {text!r}")
    return int(text)


def length_mm(text: str) -> float:
    """An argparse type: a finite length in mm, >= 0 (``--source-image-distance``, ``--pixel-pitch``; 0: not given).

    Examples
    --------
    >>> length_mm("1100")
    1100.0
    >>> length_mm("nan")
    Traceback (most recent call last):
    argparse.ArgumentTypeError: expected a finite length in mm, >= 0; got 'nan'
    """
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected a finite length in mm, >= 0; got {text!r}")
    return value


def add_overwrite(parser: argparse.ArgumentParser, what: str) -> None:
    """``--overwrite``: replace ``what`` (outputs that already exist) instead of refusing them before any work."""
    parser.add_argument("--overwrite", action="store_true", help=f"replace {what} (default: refuse before any work)")


def add_image_size(parser: argparse.ArgumentParser, note: str, default: tuple[int, int] | None = None) -> None:
    """``--image-size W H`` in px, each a positive integer; ``note`` says what it is for and its default."""
    parser.add_argument(
        "--image-size",
        type=positive_int,
        nargs=2,
        default=default,
        metavar=("W", "H"),
        help=f"frame size in px; {note}",
    )


def add_out(parser: argparse.ArgumentParser, help: str, **kw) -> None:
    """``--out DIR``: the folder a command writes into (``help`` says what goes there and the default)."""
    parser.add_argument("--out", type=Path, metavar="DIR", help=help, **kw)


def add_calibration(parser: argparse.ArgumentParser) -> None:
    """The positional ``CALIBRATION``: a calibration.json written by ``fluorocal run``."""
    parser.add_argument(
        "calibration", type=Path, metavar="CALIBRATION", help="calibration.json written by `fluorocal run`"
    )


def add_geometry(parser: argparse.ArgumentParser, default_mm: tuple[float, float] | None = None) -> None:
    """``--source-image-distance MM`` and ``--pixel-pitch MM``, named as a system's keys in the project config.

    Without ``default_mm`` both default to 0 (not given).
    """
    for flag, what, default in zip(
        ("--source-image-distance", "--pixel-pitch"),
        ("source-image distance", "detector pixel pitch"),
        default_mm or (0.0, 0.0),
    ):
        tail = f"default: {default:g}" if default_mm else "required for a 3D phantom"
        parser.add_argument(
            flag, type=length_mm, default=default, metavar="MM", help=f"{what} in mm, approximate ({tail})"
        )


def parse_orientation(text: str):
    """A C-arm orientation as typed: a calibrated orientation's name, or ``orbit=DEG,tilt=DEG``.

    The angles are spelled as the keys of a system's ``orientations`` in the project config.

    Returns
    -------
    str or dict
        The name, or ``{"orbit": float, "tilt": float}`` in degrees.

    Raises
    ------
    InputError
        ``key=value`` pairs that are not exactly orbit and tilt, each a finite number.

    Examples
    --------
    >>> parse_orientation("orbit30")
    'orbit30'
    >>> parse_orientation("orbit=15, tilt=-7.5")
    {'orbit': 15.0, 'tilt': -7.5}
    """
    import math

    from fluorocal.stages.errors import InputError

    if "=" not in text:
        return text
    values = {}
    for part in text.split(","):
        key, _, value = part.partition("=")
        try:
            values[key.strip()] = float(value)
        except ValueError:
            raise InputError(f"--orientation {text!r}: {key.strip()} must be a number of degrees") from None
        if not math.isfinite(values[key.strip()]):
            raise InputError(f"--orientation {text!r}: {key.strip()} must be a finite number of degrees")
    if set(values) != {"orbit", "tilt"} or text.count("=") != 2:
        raise InputError(f"--orientation {text!r}: expected a name, or orbit=DEG,tilt=DEG (both, nothing else)")
    return values


def load_project(config_path: Path, *, writable: bool = True):
    """The project config at ``config_path``, checked against the stages' parameters (see ``config.load_config``)."""
    from fluorocal.config import load_config
    from fluorocal.graph import stage_params_classes

    return load_config(config_path, stage_params_allowed=stage_params_classes(), writable=writable)


def project_runner(args: argparse.Namespace, config=None, **kw):
    """A :class:`fluorocal.run.Runner` of the project (``args.config`` unless ``config``), placed by ``--jobs`` etc.

    ``--jobs``, ``--scheduler`` or ``FLUOROCAL_SCHEDULER`` go over the config's ``[compute]``; ``kw`` goes to
    the runner (``force``, ``until``).
    """
    from fluorocal.cache import ArtifactCache
    from fluorocal.compute import where_to_run
    from fluorocal.graph import default_stages
    from fluorocal.run import Runner

    config = load_project(args.config) if config is None else config
    compute = where_to_run(config.compute, getattr(args, "jobs", None), getattr(args, "scheduler", None))
    return Runner(
        config, default_stages(), ArtifactCache(config.cache_dir), progress=not args.quiet, compute=compute, **kw
    )


def refuse_existing(paths, *, overwrite: bool) -> None:
    """Refuse, before any work, an existing output file unless ``--overwrite`` (a folder in its place always).

    Raises
    ------
    InputError
        The first such path, with what to do.
    """
    from fluorocal.stages.errors import InputError

    for path in paths:
        if Path(path).is_dir():
            raise InputError(f"{path}: is a folder, where an output file goes; choose another --out")
        if Path(path).exists() and not overwrite:
            raise InputError(f"{path}: already exists; add --overwrite to replace it, or choose another --out")
