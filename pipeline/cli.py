"""fluorocal: calibrate X-ray fluoroscopes from radiographs of a bead phantom.

Commands:
  run CONFIG              detect, centroid, label, then adjust and learn; write the calibration
  inspect CONFIG [STAGE]  what each stage produced (cached / stale / missing), overlays;
                          inspect calibration.json: its systems and how the field changes with orientation
  cache clean CONFIG      delete the project's artifact cache
  undistort CALIBRATION INPUT...  undistort frames with a calibration, keeping format and bit depth
  check CALIBRATION FRAME...  check a calibration with new plate or phantom frames (QA: pass, or recalibrate)
  export CALIBRATION      the calibration for OpenCV, DLTdv/XMALab, MayaCam, mrcal or the paper's formats
  evaluate CONFIG         the paper's held-out protocol on a project: schemes x training sizes, table, plots
  simulate OUTDIR         write a synthetic data set with ground truth and a config
  detect FILE...          detect and centroid beads in single frames (debugging)
  label DETECTIONS.csv    label detections against a phantom (debugging)
  adjust                  the robust bundle adjustment alone, from CSV files (debugging)

Quick start: `fluorocal simulate demo && fluorocal run demo/fluorocal.toml`.

A project is a TOML file (see docs/config.md); paths in it are relative
to it. Artifacts are cached in .fluorocal/ beside the config: a second run
with nothing changed recomputes nothing.

Threads: one BLAS/OpenMP/OpenCV thread per process unless [compute] threads
or FLUOROCAL_THREADS says otherwise; the per-frame stages run on every core
(--jobs, [compute] jobs) or on a Dask cluster (--scheduler).

Exit codes: 0 success, 1 unexpected failure, 2 bad input (file, config key,
argument), 130 interrupted, 141 output pipe closed (as by `| head`). Add --debug for a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import importlib
import logging
import os
import sys
import warnings
from pathlib import Path

from fluorocal.cli_common import add_out, load_project, positive_int, project_runner

#: optional command modules: pipeline/cmd_<name>.py exposing add_parser(subparsers) and run(args); they share
#: options and helpers through fluorocal.cli_common (never this module), and get the common options
#: (--quiet, --debug) from the subparsers' class
COMMAND_MODULES = ("simulate", "detect", "label", "adjust", "undistort", "check", "export", "evaluate")

log = logging.getLogger("fluorocal")


def _command_modules():
    here = Path(__file__).parent
    for name in COMMAND_MODULES:
        if (here / f"cmd_{name}.py").is_file():
            yield importlib.import_module(f"fluorocal.cmd_{name}")


class _Parser(argparse.ArgumentParser):
    """Usage errors in one line like every other refusal; the usage is one ``--help`` away.

    No abbreviations: an option has one spelling (``--orient`` is not ``--orientation``).
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, allow_abbrev=False, **kwargs)

    def error(self, message: str):
        self.exit(2, f"fluorocal: error: {message} (see {self.prog} --help)\n")


def _add_common(parser: argparse.ArgumentParser, default) -> None:
    """The options every command takes, before or after the command's name."""
    parser.add_argument("--debug", action="store_true", default=default, help="show tracebacks and debug logging")
    parser.add_argument(
        "-q", "--quiet", action="store_true", default=default, help="no progress bars, warnings and errors only"
    )


class _CommandParser(_Parser):
    """A command's parser: it takes the common options too (after the command), and its subcommands theirs.

    Their default is suppressed, so that an option given before the command is not reset by the command's parser.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        _add_common(self, argparse.SUPPRESS)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("fluorocal")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown"


class _VersionAction(argparse.Action):
    """``--version``: the installed version, looked up only when asked (importing importlib.metadata takes ~30 ms)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest, nargs=0, default=default, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"fluorocal {_version()}")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="fluorocal", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action=_VersionAction, help="show program's version number and exit")
    _add_common(parser, False)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=_CommandParser)

    p = sub.add_parser(
        "run",
        help="run the calibration pipeline of a project",
        description="Run every stage of a project (cached stages are not recomputed) and write its outputs.",
    )
    p.add_argument("config", type=Path, help="project TOML file")
    p.add_argument(
        "--force",
        action="append",
        default=[],
        metavar="STAGE",
        help="recompute STAGE and everything downstream (repeatable)",
    )
    p.add_argument(
        "--until",
        metavar="STAGE",
        help="stop after STAGE; its tables go to <output dir>/until-STAGE/, the published outputs stay "
        "(default: run all stages)",
    )
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--jobs",
        type=positive_int,
        metavar="N",
        help="worker processes for the per-frame stages; 1: serial (default: [compute] jobs, else every core)",
    )
    where.add_argument(
        "--scheduler",
        metavar="tcp://HOST:PORT",
        help="run the per-frame stages on this Dask scheduler's cluster (default: $FLUOROCAL_SCHEDULER, else none)",
    )
    p.set_defaults(func=cmd_run)

    p = sub.add_parser(
        "inspect",
        help="show what each stage produced, or what a calibration holds",
        description=(
            "Table of stages: key, status (cached / stale / missing), size and summary; "
            "with STAGE, that stage's artifacts. Given a calibration.json instead of a project: its systems, "
            "their orientations and how the field changes with orientation (table and plots)."
        ),
    )
    p.add_argument("config", type=Path, help="project TOML file, or a calibration.json")
    p.add_argument("stage", nargs="?", help="a stage name (default: all stages)")
    p.add_argument(
        "--frame",
        type=int,
        metavar="N",
        help="with STAGE: write the debug overlay of frame N (0-based, over all systems)",
    )
    add_out(p, "with a calibration.json: folder for the orientation plots (default: overlays/ beside the calibration)")
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("cache", help="manage the artifact cache", description="Manage a project's artifact cache.")
    cache_sub = p.add_subparsers(dest="cache_command", metavar="ACTION", required=True)
    c = cache_sub.add_parser(
        "clean",
        help="delete a project's cache",
        description=(
            "Delete the project's artifact cache (or, with --stale, only entries the current config no longer uses). "
            "Only what the cache wrote is deleted, and only in a folder holding the cache's marker file."
        ),
    )
    c.add_argument("config", type=Path, help="project TOML file")
    c.add_argument("--stale", action="store_true", help="keep entries the current config uses (default: delete all)")
    c.set_defaults(func=cmd_cache_clean)

    for module in _command_modules():
        module.add_parser(sub)
    return parser


def cmd_run(args) -> int:
    from fluorocal.export import check_outputs, export_outputs

    config = load_project(args.config)
    out_dir = check_outputs(config)  # before any work: names, the output folder, leftovers of a killed run
    runner = project_runner(args, config, force=args.force, until=args.until, start_pool=True)
    report = runner.run()
    if "label" in report.outcomes:
        from fluorocal.gather import labelling_line

        log.info("label: %s", labelling_line([runner.get("label", u) for u in range(len(runner.units))]))
    written = export_outputs(runner)
    log.info("wrote %d file(s) to %s", len(written), written[0].parent if written else out_dir)
    if written and "learn" not in runner.by_name:
        print(f"partial results (--until {args.until}): {written[0].parent}; the outputs in {out_dir} are unchanged")
    report_md = out_dir / "report.md"
    if report_md in written:
        table = [line for line in report_md.read_text(encoding="utf-8").splitlines() if line.startswith("|")]
        print("\n".join(table))
        print(f"report: {report_md}")
    return 0


def cmd_inspect(args) -> int:
    from fluorocal.stages.errors import InputError

    if args.config.suffix.lower() == ".json":
        from fluorocal.orientations import inspect_calibration

        if args.stage or args.frame is not None:
            raise InputError(f"{args.config} is a calibration: STAGE and --frame apply to a project TOML file")
        print("\n".join(inspect_calibration(args.config, args.out)))
        return 0
    if args.out is not None:
        raise InputError("--out applies to a calibration.json; a project's overlays go to its output folder")
    runner = project_runner(
        args, load_project(args.config, writable=args.frame is not None)
    )  # only an overlay is written
    if args.stage:
        return _inspect_stage(runner, args.stage, args.frame)
    from fluorocal.inspect import stage_summary

    print(f"{'stage':<10} {'key':<12} {'status':<8} {'entries':>9} {'size':>10}  summary")
    for r in runner.status():
        summary = stage_summary(runner, r["stage"]) if runner.by_name[r["stage"]].per_frame else r["summary"]
        print(
            f"{r['stage']:<10} {r['key']:<12} {r['status']:<8} {r['cached']:>4}/{r['n']:<4} "
            f"{_human(r['bytes']):>10}  {summary}"
        )
    return 0


def _inspect_stage(runner, stage: str, frame: int | None) -> int:
    from fluorocal.gather import frame_description
    from fluorocal.stages.errors import InputError

    if stage not in runner.by_name:
        raise InputError(f"unknown stage {stage!r}; stages are {', '.join(runner.by_name)}")
    per_frame = runner.by_name[stage].per_frame
    units = range(len(runner.units)) if per_frame else [None]
    if frame is not None:
        if not per_frame:
            frame_stages = ", ".join(s.name for s in runner.stages if s.per_frame)
            raise InputError(f"--frame: stage {stage!r} has one artifact per project; --frame is for {frame_stages}")
        if not 0 <= frame < len(runner.units):
            raise InputError(f"--frame must be in 0..{len(runner.units) - 1} (the frames of every system, in order)")
        units = [frame]
    for u in units:
        key = runner.keys[(stage, u)]
        where = frame_description(runner.units[u], runner.config) if u is not None else "project"
        manifest = runner.cache.manifest(stage, key)
        if manifest is None:
            print(f"{where}: missing (run `fluorocal run` first)")
            continue
        entry = runner.cache.entry_dir(stage, key)
        files = ", ".join(str(entry / f) for f in manifest["files"] if not f.endswith(".npz"))
        print(f"{where}: {manifest['summary']}  [{entry}]" + (f"  {files}" if files else ""))
    if frame is not None:
        from fluorocal.inspect import write_stage_overlay

        path = write_stage_overlay(runner, stage, frame)
        print(f"overlay: {path}")
    return 0


def cmd_cache_clean(args) -> int:
    from fluorocal.cache import ArtifactCache

    config = load_project(args.config)
    cache = ArtifactCache(config.cache_dir)
    if args.stale:
        runner = project_runner(args)
        keep = {(stage, key) for (stage, _), key in runner.keys.items()}
        removed = cache.clean(keep=keep, project=config.path)
    else:
        removed = cache.clean(project=config.path)  # another project's entries are kept
    log.info("removed %d cache entries from %s", removed, config.cache_dir)
    return 0


def _human(n: int) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"fluorocal: warning: {message}", file=sys.stderr)


def os_error_message(exc: OSError) -> str:
    """One line for an error of the file system, naming the path and what to do.

    Examples
    --------
    >>> import errno
    >>> os_error_message(OSError(errno.ENOSPC, "No space left on device", "out/report.md"))
    'no space left on device writing out/report.md; free some space and run again (finished stages are cached)'
    >>> os_error_message(PermissionError(errno.EACCES, "Permission denied", "out"))
    'permission denied: out; fix its permissions or choose another folder'
    """
    path = exc.filename if exc.filename is not None else "a file"
    if exc.errno == errno.ENOSPC:
        return f"no space left on device writing {path}; free some space and run again (finished stages are cached)"
    what = (exc.strerror or type(exc).__name__).lower()
    if isinstance(exc, PermissionError):
        return f"{what}: {path}; fix its permissions or choose another folder"
    if isinstance(exc, (IsADirectoryError, NotADirectoryError, FileExistsError)):
        return f"{what}: {path}; a file and a folder are in each other's place"
    return f"{what}: {path}"


def _degrade_output() -> None:
    """Print what the terminal's encoding cannot show as escapes (``Δ`` as a backslash escape under ``LC_ALL=C``)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.reconfigure(errors="backslashreplace")
        except (AttributeError, ValueError, OSError):  # not a text stream of the io module: left as it is
            pass


def main(argv=None) -> int:
    _degrade_output()
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.debug else (logging.WARNING if args.quiet else logging.INFO), format="%(message)s"
    )
    for noisy in ("PIL", "matplotlib"):  # their debug lines are not fluorocal's
        logging.getLogger(noisy).setLevel(logging.WARNING)
    if not args.debug:
        warnings.showwarning = _show_warning
    from fluorocal.compute import config_threads, limit_threads
    from fluorocal.stages.errors import CalibError

    try:
        limit_threads(config_threads(getattr(args, "config", None)))  # before numpy, OpenCV and BLAS load
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's own flush at exit
        return code
    except BrokenPipeError:  # `fluorocal inspect ... | head`: the reader has what it wanted
        with contextlib.suppress(OSError, ValueError):  # no more writes to the pipe, at exit neither
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, as a shell reports a command that a closed pipe ended
    except CalibError as exc:
        if args.debug:
            raise
        print(f"fluorocal: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # permissions, a full disk, a folder where a file belongs, ...: name the path
        if args.debug:
            raise
        print(f"fluorocal: error: {os_error_message(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("fluorocal: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
