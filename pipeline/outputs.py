"""Where ``fluorocal`` may write: sanitised names, paths kept inside their folder, outputs published as a set.

Every output file name is built from names that passed :func:`safe_name` and
joined with :func:`inside`, which refuses a path that resolves outside its
folder (``..``, an absolute name, a symbolic link pointing elsewhere).

:func:`publish` writes a run's outputs into a staging folder beside the
output folder and swaps it in: the previous set is renamed aside, the new one
renamed in, the previous one deleted. A reader sees the previous complete set
or the new one, never a mixture; a run killed midway leaves the previous set
(or, killed between the two renames, the previous set aside, which the next
run puts back). Entries of the output folder that are not part of a published
set (``overlays/`` of ``fluorocal inspect``, files a user put there) are
carried over into the new set. Folders left by a killed run, and only those
named as this module names them, are swept at the start of the next publish.

A published set names the project that wrote it (its config, in :data:`MANIFEST`):
:func:`check_output_dir` refuses a folder another project published into, so two
configs sharing one ``[output] dir`` never replace each other's calibration.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import secrets
import shutil
import stat
from collections.abc import Callable
from pathlib import Path

from fluorocal.stages.errors import InputError

try:  # POSIX
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None

log = logging.getLogger(__name__)

#: longest name :func:`safe_name` accepts (file systems allow 255 bytes; names get prefixes and suffixes)
MAX_NAME_LENGTH = 64
_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]*")
#: the file in a published set listing the set's own entries
MANIFEST = ".fluorocal-outputs.json"
_SIDE = re.compile(r"\.(?P<out>.+)\.fluorocal-(?P<kind>staging|old)-(?P<pid>[0-9]+)-[0-9a-f]{8}")


def safe_name(text, *, what: str = "name") -> str:
    """Return ``text`` if it can be part of a file name, else raise :class:`InputError`.

    A safe name is 1 to :data:`MAX_NAME_LENGTH` letters, digits, ``-``, ``_``
    and ``.``, not starting with ``.``: no separator, no ``..``, nothing hidden.
    System names are used in output file names (``field_<system>.npz``), so
    the config loader checks them with this rule.

    Examples
    --------
    >>> safe_name("A")
    'A'
    >>> safe_name("B/../../../escaped", what="system name")
    Traceback (most recent call last):
    ...
    fluorocal.stages.errors.InputError: system name 'B/../../../escaped' cannot be part of a file name: ...
    """
    if not isinstance(text, str) or len(text) > MAX_NAME_LENGTH or not _NAME.fullmatch(text):
        shown = text if not isinstance(text, str) or len(text) <= 80 else text[:80] + "..."
        raise InputError(
            f"{what} {shown!r} cannot be part of a file name: use 1 to {MAX_NAME_LENGTH} letters, digits, "
            "'-', '_' or '.', not starting with '.'"
        )
    return text


def inside(folder: str | os.PathLike, name: str) -> Path:
    """``folder / name``, refused with :class:`InputError` unless it resolves to an entry inside ``folder``.

    Examples
    --------
    >>> inside("out", "report.md").name
    'report.md'
    >>> inside("out", "../escaped.png")
    Traceback (most recent call last):
    ...
    fluorocal.stages.errors.InputError: '../escaped.png' resolves outside the folder ...
    """
    folder = Path(folder)
    root = folder.resolve()
    path = (folder / name).resolve()
    if Path(name).is_absolute() or path == root or root not in path.parents:
        raise InputError(f"{name!r} resolves outside the folder {root}; refusing to write or read it")
    return folder / name


# --- publishing a set -------------------------------------------------------------------------


def check_output_dir(
    out_dir: str | os.PathLike, *, keep_out: list[tuple[str, Path]], owner: str | os.PathLike | None = None
) -> Path:
    """Check before any work that ``out_dir`` can hold a published set; return it resolved.

    Parameters
    ----------
    out_dir : path
        The output folder (it may not exist yet).
    keep_out : list of (str, Path)
        What must not lie inside it, with what it is (``[("the config", path), ...]``):
        the folder is swapped as a whole, so it must not hold the project's inputs or cache.
    owner : path, optional
        The config of the project about to publish there: a set another project published is refused.

    Raises
    ------
    InputError
        ``out_dir`` is a file, holds one of ``keep_out``, holds another project's set, or its parent
        is not a writable folder.
    """
    out_dir = Path(out_dir).resolve()
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"output {out_dir} is a file; [output] dir must name a folder")
    for what, path in keep_out:
        path = Path(path).resolve()
        if path == out_dir or out_dir in path.parents:
            raise InputError(
                f"output folder {out_dir} holds {what} ({path}); its content is replaced as a whole by each run, "
                "choose an [output] dir of its own"
            )
    parent = next((p for p in out_dir.parents if p.exists()), None)
    if parent is None or not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"cannot write the output folder {out_dir}: {parent} is not a writable folder")
    previous = published_by(out_dir)
    if owner is not None and previous is not None and previous != owner_name(out_dir, owner):
        raise InputError(
            f"output folder {out_dir} holds the outputs of another project ({os.path.normpath(out_dir / previous)}); "
            "give this project an [output] dir of its own"
        )
    return out_dir


def owner_name(out_dir: str | os.PathLike, config: str | os.PathLike) -> str:
    """The config's path relative to the output folder: what names a set's project, moved along with it.

    Examples
    --------
    >>> owner_name("/p/out", "/p/fluorocal.toml")
    '../fluorocal.toml'
    """
    return os.path.relpath(Path(config).resolve(), Path(out_dir).resolve())


def published_by(out_dir: str | os.PathLike) -> str | None:
    """The config (relative to ``out_dir``) of the project whose set it holds (None: no set, or no owner)."""
    try:
        project = json.loads((Path(out_dir) / MANIFEST).read_text(encoding="utf-8")).get("project")
    except (OSError, ValueError, AttributeError, RecursionError):  # RecursionError: nested too deep to decode
        return None
    return project if isinstance(project, str) else None


def publish(
    out_dir: str | os.PathLike, write: Callable[[Path], list[Path]], *, owner: str | os.PathLike | None = None
) -> list[Path]:
    """Call ``write(staging)`` to write a set of outputs, then swap the set in as ``out_dir``.

    Parameters
    ----------
    out_dir : path
        The output folder.
    write : callable
        Writes the set into the folder it is given (with :func:`inside`) and
        returns the paths written there.
    owner : path, optional
        The config of the project publishing the set, recorded in its :data:`MANIFEST`.

    Returns
    -------
    list of Path
        The written paths, under ``out_dir``; when ``write`` writes nothing, ``out_dir`` is left as it is.
    """
    out_dir = Path(out_dir).resolve()
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    sweep(out_dir)
    staging = _side_folder(out_dir, "staging")
    staging.mkdir()
    if out_dir.is_dir():
        os.chmod(staging, stat.S_IMODE(out_dir.stat().st_mode))  # the new set keeps the folder's permissions
    try:
        written = write(staging)
        if not written:
            shutil.rmtree(staging)
            return []
        names = sorted({p.relative_to(staging).parts[0] for p in written})
        record = {"entries": names, "project": None if owner is None else owner_name(out_dir, owner)}
        (staging / MANIFEST).write_text(json.dumps(record, indent=1), encoding="utf-8")
        with _publishing(out_dir):  # runs finishing at once swap their sets in one after the other
            _swap(out_dir, staging)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return [out_dir / p.relative_to(staging) for p in written]


def sweep(out_dir: str | os.PathLike) -> None:
    """Remove what killed runs left beside ``out_dir``; put back a previous set a kill left aside.

    Under the publishing lock: runs starting together would otherwise remove the same dead run's folder at
    once, and each but the first fail on a file the others had just removed.
    """
    out_dir = Path(out_dir).resolve()
    if not out_dir.parent.is_dir():
        return
    with _publishing(out_dir):
        _sweep_unlocked(out_dir)


def _sweep_unlocked(out_dir: Path) -> None:
    for side in sorted(out_dir.parent.iterdir()):
        m = _SIDE.fullmatch(side.name)
        if m is None or m["out"] != out_dir.name or not side.is_dir() or _alive(int(m["pid"])):
            continue
        if m["kind"] == "old" and not out_dir.exists():
            log.warning("restoring the previous outputs %s left aside by an interrupted run", out_dir)
            os.rename(side, out_dir)
            continue
        if m["kind"] == "old":
            _carry_over(side, out_dir)
        log.info("removing %s, left by an interrupted run", side)
        shutil.rmtree(side)


@contextlib.contextmanager
def _publishing(out_dir: Path):
    """An exclusive lock on publishing into ``out_dir``'s parent (POSIX ``flock`` on the folder itself: no file)."""
    fd = os.open(out_dir.parent, os.O_RDONLY)
    try:
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing releases the lock


def _side_folder(out_dir: Path, kind: str) -> Path:
    return out_dir.parent / f".{out_dir.name}.fluorocal-{kind}-{os.getpid()}-{secrets.token_hex(4)}"


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return False  # this process has no publish in progress while it sweeps
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


def _swap(out_dir: Path, staging: Path) -> None:
    if not out_dir.exists():
        os.rename(staging, out_dir)
        return
    old = _side_folder(out_dir, "old")
    os.rename(out_dir, old)
    try:
        os.rename(staging, out_dir)
    except BaseException:
        os.rename(old, out_dir)
        raise
    _carry_over(old, out_dir)
    shutil.rmtree(old)


def _carry_over(old: Path, new: Path) -> None:
    """Move the entries of ``old`` that are not a published output (and not in ``new``) into ``new``."""
    try:
        published = set(json.loads((old / MANIFEST).read_text(encoding="utf-8"))["entries"])
    except (OSError, ValueError, KeyError, TypeError, RecursionError):  # RecursionError: nested too deep
        published = set()  # a folder written before sets were published: keep what the new set does not replace
    for entry in old.iterdir():
        if entry.name != MANIFEST and entry.name not in published and not (new / entry.name).exists():
            os.rename(entry, new / entry.name)
