"""Content-addressed artifact store.

An artifact lives in ``<cache>/<stage>/<key>/``: ``manifest.json`` (key,
stage, provenance, the artifact's structure and the sha256 of every file),
``manifest.sha256`` (the manifest's own checksum), ``arrays.npz`` (its numpy
arrays), and, where the artifact offers them, ``table.csv`` and
``overlay.png`` for people. The key is a hash of the stage name, the digest
of the code that computes it (:mod:`fluorocal.codehash`), its parameters and
its input keys (:func:`artifact_key`).

The cache stores data, never references to code: an entry decodes only into
the registered artifact classes (:mod:`fluorocal.artifact_codec`); nothing
a manifest names is imported or called. A read checks the manifest's
checksum, then every file's; a missing, truncated, edited or corrupt entry,
or one naming an unregistered type, is a miss (with a :class:`CacheWarning`),
recomputed and replaced, never an error and never used. (The checksums catch
corruption and hand edits; they are no signature. A forged entry can at most
hold wrong numbers, which whoever hands over a project folder could put in its
frames as well.)

Writes are atomic: everything is written into a hidden temporary directory
``.tmp-<key>-*`` beside the final one, which is renamed into place last, so an
interrupted write never leaves a directory a later run would trust, and a
reader sees a whole entry or none. Processes sharing a cache hold a lock per
entry (``.locks/<stage>.<key>.lock``, ``fcntl.flock``) while computing and
writing it, so an entry is computed once; an entry another process published
first is accepted. :meth:`ArtifactCache.sweep` removes temporaries no live
writer holds. The cache folder carries a marker (:data:`MARKER`), and
:meth:`ArtifactCache.clean` deletes only what the cache writes, in a folder
with that marker.

Projects may share a cache. Each run records the entries its project uses
(:meth:`ArtifactCache.record_use`, ``.projects/<hash of the config path>.json``);
``clean(project=...)`` removes only entries no other project records, and an
entry no project records only when no other project uses the cache.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import hashlib
import io
import json
import logging
import os
import platform
import re
import shutil
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from fluorocal.artifact_codec import UntrustedData, artifact_types, decode, encode, named_types
from fluorocal.stages.errors import InputError
from fluorocal.steady import file_sha256

try:
    import fcntl
except ImportError:  # not POSIX: no inter-process locks
    fcntl = None

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
CHECKSUM = "manifest.sha256"
ARRAYS = "arrays.npz"
TABLE = "table.csv"
OVERLAY = "overlay.png"
#: the files a manifest may list (the data files of an entry)
DATA_FILES = frozenset({ARRAYS, TABLE, OVERLAY})
FORMAT_VERSION = 2
#: the file at the cache root that says the folder is a fluorocal cache
MARKER = ".fluorocal-cache"
MARKER_CONTENT = {"format": "fluorocal-cache", "version": FORMAT_VERSION}
LOCKS = ".locks"
#: the folder of the records of which entries each project uses
PROJECTS = ".projects"
#: the folder of the code analyses kept between runs (:class:`fluorocal.codehash.AnalysisMemo`)
CODE = ".code"

_STAGE = re.compile(r"[a-z][a-z0-9_]*")
_KEY = re.compile(r"[0-9a-f]{64}")
_TMP = re.compile(r"\.tmp-([0-9a-f]{64})-[a-z0-9_]+")
_LEGACY_TMP = re.compile(r"\.tmp-[0-9a-f]{12}-[a-z0-9_]+")
_LOCK = re.compile(r"[a-z][a-z0-9_]*\.[0-9a-f]{64}\.lock")
_HELD: dict[str, int] = {}  # lock file -> depth, of the locks this process holds


class CacheWarning(UserWarning):
    """A cache entry was unreadable and will be recomputed."""


def canonical_json(obj) -> str:
    """JSON with sorted keys and no whitespace: the hashing form of parameters."""
    return json.dumps(_jsonable(obj), sort_keys=True, separators=(",", ":"))


def _jsonable(obj):
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def artifact_key(stage: str, code: str, params, input_keys: list[str]) -> str:
    """sha256 of ``{stage, code digest, params, input keys}`` in canonical JSON."""
    payload = canonical_json({"stage": stage, "code": code, "params": params, "inputs": list(input_keys)})
    return hashlib.sha256(payload.encode()).hexdigest()


def _summary(artifact) -> str:
    if hasattr(artifact, "summary"):
        return str(artifact.summary())
    parts = []
    for f in dataclasses.fields(artifact) if dataclasses.is_dataclass(artifact) else ():
        v = getattr(artifact, f.name)
        if isinstance(v, np.ndarray):
            parts.append(f"{f.name}{list(v.shape)}")
    return ", ".join(parts)


class ArtifactCache:
    """The on-disk store under ``root`` (default ``.fluorocal/`` beside the config).

    Parameters
    ----------
    root : path
        The cache folder: created with a marker file (:data:`MARKER`) on first use.
    types : dict of str to type, optional
        Registry of the artifact classes entries may decode into (:func:`artifact_types`);
        by default the project's stages' own. :meth:`register` adds a runner's stages'.
    """

    def __init__(self, root: str | os.PathLike, types: dict[str, type] | None = None):
        self.root = Path(root)
        self._types = dict(types) if types is not None else None
        self._kinds: dict[str, type] = {}

    # --- names and the registry ----------------------------------------------------------------

    @property
    def types(self) -> dict[str, type]:
        """The registry entries decode into."""
        if self._types is None:
            from fluorocal.graph import default_stages

            self._types = artifact_types(default_stages())
        return self._types

    def register(self, types: dict[str, type], kinds: dict[str, type] | None = None) -> None:
        """Trust ``types`` (a runner's stages' artifact classes) as well; ``kinds``: what each stage's entries hold.

        An entry whose artifact decodes into a registered type other than its stage's kind (a manifest edited
        to hold a plain dict, or another stage's artifact) is a miss like any other tampered entry.
        """
        self._types = {**(self._types or {}), **types}
        self._kinds.update(kinds or {})

    def entry_dir(self, stage: str, key: str) -> Path:
        """``<root>/<stage>/<key>``; raises ValueError for a name the cache would not write."""
        if not _STAGE.fullmatch(stage) or not _KEY.fullmatch(key):
            raise ValueError(f"not a cache entry name: {stage!r}/{key!r} (stage [a-z][a-z0-9_]*, key 64 hex digits)")
        return self.root / stage / key

    # --- reading ---------------------------------------------------------------------------------

    def has(self, stage: str, key: str) -> bool:
        """Whether an entry is present (not whether it is intact: see :meth:`verify`)."""
        return (self.entry_dir(stage, key) / MANIFEST).is_file()

    def verify(self, stage: str, key: str, *, warn: bool = True) -> bool:
        """Whether the entry is present and intact (every checksum, every type it names registered)."""
        return self._read(stage, key, warn=warn) is not None

    def load(self, stage: str, key: str, *, warn: bool = True):
        """The artifact stored at ``(stage, key)``, or ``None`` on a miss.

        A corrupt, truncated or tampered entry, or one naming a type outside the
        registry, warns (:class:`CacheWarning`, unless ``warn`` is False) and counts
        as a miss; the next :meth:`store` of that key replaces it.
        """
        manifest = self._read(stage, key, warn=warn)
        if manifest is None:
            return None
        try:
            with np.load(self.entry_dir(stage, key) / ARRAYS, allow_pickle=False) as npz:
                arrays = {k: npz[k] for k in npz.files}
            return decode(manifest["artifact"], arrays, self.types)
        except Exception as exc:  # any failure to read is a miss, never fatal
            if warn:
                _warn_unreadable(stage, key, exc)
            return None

    def manifest(self, stage: str, key: str) -> dict | None:
        """The entry's verified manifest (``None`` if missing or not intact); nothing is decoded."""
        return self._read(stage, key, warn=False)

    def _read(self, stage: str, key: str, *, warn: bool) -> dict | None:
        entry = self.entry_dir(stage, key)
        if not entry.is_dir():
            if warn and (entry.exists() or entry.is_symlink()):
                _warn_unreadable(stage, key, ValueError("not a directory"))
            return None
        try:
            raw = (entry / MANIFEST).read_bytes()
            if not (entry / CHECKSUM).exists() and _older_format(raw):
                log.debug("cache entry %s/%s has an older format; recomputing", stage, key[:12])
                return None  # a plain miss: the previous format had no manifest checksum
            if hashlib.sha256(raw).hexdigest() != (entry / CHECKSUM).read_text().strip():
                raise ValueError(f"{MANIFEST} does not match {CHECKSUM}")
            manifest = json.loads(raw)
            _check_manifest(manifest, stage, key)
            for name, digest in manifest["files"].items():
                if file_sha256(entry / name) != digest:
                    raise ValueError(f"checksum mismatch in {name}")
            unknown = named_types(manifest["artifact"]) - set(self.types)
            if unknown:
                raise UntrustedData(f"names unregistered type(s) {', '.join(map(repr, sorted(unknown)))}")
            self._check_kind(stage, manifest["artifact"])
            return manifest
        except Exception as exc:
            if warn and entry.exists():  # an entry that vanished meanwhile (replaced, cleaned) is a plain miss
                _warn_unreadable(stage, key, exc)
            return None

    def _check_kind(self, stage: str, tree) -> None:
        """Raise UntrustedData unless ``tree`` encodes the stage's registered kind (checked before any decoding)."""
        kind = self._kinds.get(stage)
        if kind is None:
            return
        name = tree.get("__dataclass__") if isinstance(tree, dict) else None
        cls = self.types.get(name) if isinstance(name, str) else None
        if not (isinstance(cls, type) and issubclass(cls, kind)):
            raise UntrustedData(f"holds a {name or type(tree).__name__}, not the stage's {kind.__name__}")

    def keys(self, stage: str) -> list[str]:
        """Keys of the entries of ``stage`` (not checked)."""
        d = self.root / stage
        return sorted(p.name for p in d.iterdir() if _KEY.fullmatch(p.name)) if d.is_dir() else []

    def size_bytes(self, stage: str, key: str) -> int:
        entry = self.entry_dir(stage, key)
        return sum(p.stat().st_size for p in entry.iterdir()) if entry.is_dir() else 0

    # --- writing ---------------------------------------------------------------------------------

    def store(
        self, stage: str, key: str, artifact, *, provenance: dict | None = None, overlay: bytes | None = None
    ) -> Path:
        """Write ``artifact`` atomically and return its directory.

        If another process published the same entry meanwhile, that entry is kept
        and ours dropped (both are computed from the same inputs).
        """
        final = self.entry_dir(stage, key)
        self.prepare_root()
        final.parent.mkdir(exist_ok=True)
        with self.lock(stage, key):
            tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{key}-", dir=final.parent))
            try:
                self._write(tmp, stage, key, artifact, provenance, overlay)
                self._publish(tmp, final, stage, key)
            except OSError as exc:
                shutil.rmtree(tmp, ignore_errors=True)
                if exc.filename is None:  # numpy and pathlib leave it out: name the entry (a full disk, say)
                    raise OSError(exc.errno, exc.strerror, str(final)) from exc
                raise
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)
                raise
        return final

    def _write(self, tmp: Path, stage: str, key: str, artifact, provenance, overlay) -> None:
        arrays: dict[str, np.ndarray] = {}
        tree = encode(artifact, arrays, "artifact", self.types)
        buffer = io.BytesIO()  # each file's bytes made in memory: written once, hashed there
        np.savez(buffer, **arrays)
        files = {ARRAYS: buffer.getvalue()}
        if hasattr(artifact, "to_table"):
            from fluorocal.stages.io import csv_text

            files[TABLE] = csv_text(*artifact.to_table()).encode("utf-8")
        if overlay is not None:
            files[OVERLAY] = bytes(overlay)
        for name, data in files.items():
            (tmp / name).write_bytes(data)
        manifest = {
            "format_version": FORMAT_VERSION,
            "key": key,
            "stage": stage,
            "summary": _summary(artifact),
            "provenance": {**_environment(), **(provenance or {})},
            "files": {name: hashlib.sha256(files[name]).hexdigest() for name in sorted(files)},
            "artifact": tree,
        }
        # the manifest and its checksum are written last: an entry without them is never trusted
        raw = json.dumps(manifest, indent=1).encode()
        (tmp / MANIFEST).write_bytes(raw)
        (tmp / CHECKSUM).write_text(hashlib.sha256(raw).hexdigest() + "\n")

    def _publish(self, tmp: Path, final: Path, stage: str, key: str) -> None:
        """Rename ``tmp`` to ``final``; an intact entry already there wins, a broken one is displaced."""
        try:
            os.replace(tmp, final)
            return
        except OSError as exc:
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR):
                raise
        if self._read(stage, key, warn=False) is not None:
            shutil.rmtree(tmp, ignore_errors=True)
            return
        trash = Path(tempfile.mkdtemp(prefix=f".tmp-{key}-", dir=final.parent))
        # a folder goes over the empty one, a file or link in its place into it: readers see the old entry or none
        os.replace(final, trash if final.is_dir() and not final.is_symlink() else trash / "entry")
        os.replace(tmp, final)
        shutil.rmtree(trash, ignore_errors=True)

    # --- the cache folder ------------------------------------------------------------------------

    def prepare_root(self) -> None:
        """Create the cache folder and its marker, or check an existing one is a cache.

        Raises
        ------
        InputError
            ``root`` is a file, or a folder holding anything but cache entries and no marker.
        """
        marker = self.root / MARKER
        if _is_marker(marker):
            return
        if self.root.exists() and not self.root.is_dir():
            raise InputError(f"cache dir {self.root} is a file, not a folder")
        # the marker looked for again after the listing: another process may have made the cache meanwhile
        if self.root.is_dir() and not _only_cache_files(self.root) and not _is_marker(marker):
            raise InputError(
                f"cache dir {self.root} holds files that are not a fluorocal cache (no {MARKER}); "
                "choose a new or empty folder"
            )
        self.root.mkdir(parents=True, exist_ok=True)
        with contextlib.suppress(FileExistsError):  # another process made it meanwhile
            with open(marker, "x") as fh:
                fh.write(json.dumps(MARKER_CONTENT) + "\n")

    def sweep(self) -> int:
        """Delete temporaries left by interrupted writes (none a live writer holds); return the count."""
        removed = 0
        for stage_dir, entry in self._own_children():
            m = _TMP.fullmatch(entry.name)
            if m is None:
                continue
            with self.lock(stage_dir.name, m.group(1), blocking=False) as held:
                if held:
                    shutil.rmtree(entry, ignore_errors=True)
                    removed += 1
        if removed:
            log.info("removed %d leftover temporar%s from %s", removed, "y" if removed == 1 else "ies", self.root)
        return removed

    def clean(self, *, keep: set[tuple[str, str]] | None = None, project: str | os.PathLike | None = None) -> int:
        """Delete every entry (or every one not in ``keep``) and leftover temporaries; return the count.

        Only what the cache writes is deleted: ``<stage>/<key>`` entries, ``.tmp-*``
        temporaries and lock files; the folder itself only if nothing else is left in it.
        With ``project`` (its config path), entries another project's record lists are kept,
        and so are entries no record lists (and live temporaries) when another project uses the cache.

        Raises
        ------
        InputError
            ``root`` has no marker: it is not a folder the cache created.
        """
        if not self.root.exists():
            return 0
        self._check_marker()
        uses = self._uses()
        own = uses.pop(self._project_id(project), set()) if project is not None else set()
        others = set().union(*uses.values()) if project is not None else set()
        shared = bool(uses) and project is not None
        removed, deleted = 0, set()
        for stage_dir, entry in self._own_children():
            slot = (stage_dir.name, entry.name)
            if _TMP.fullmatch(entry.name) and shared:
                continue  # left to the lock-aware sweep below: another project's writer may hold it
            if _KEY.fullmatch(entry.name) and (
                (keep is not None and slot in keep) or slot in others or (shared and slot not in own)
            ):
                continue
            trash = Path(tempfile.mkdtemp(prefix=f".tmp-{'0' * 64}-", dir=stage_dir))
            os.replace(entry, trash)  # readers see the entry or none
            shutil.rmtree(trash, ignore_errors=True)
            removed += 1
            deleted.add(slot)
        if shared:
            removed += self.sweep()
        if project is not None:
            self._write_use(project, own - deleted)
        if keep is None and not uses:
            self._remove_skeleton()
        return removed

    # --- which project uses which entries ----------------------------------------------------------

    def record_use(self, project: str | os.PathLike, entries) -> None:
        """Add ``entries`` ((stage, key) pairs) to those ``project`` (its config path) is recorded to use."""
        with self.lock("projects", self._project_id(project)):
            self._write_use(project, self._uses().get(self._project_id(project), set()) | set(entries))

    def _write_use(self, project, entries: set[tuple[str, str]]) -> None:
        folder = self.root / PROJECTS
        path = folder / f"{self._project_id(project)}.json"
        if not entries:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
            return
        folder.mkdir(exist_ok=True)
        config = os.path.relpath(Path(project).resolve(), self.root.resolve())
        record = {"config": config, "entries": sorted(f"{s}/{k}" for s, k in entries)}
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=folder)
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(record, fh)
        os.replace(tmp, path)

    def _project_id(self, project: str | os.PathLike) -> str:
        """A project's record name: the sha256 of its config's path relative to the cache (moved along with it)."""
        return hashlib.sha256(os.path.relpath(Path(project).resolve(), self.root.resolve()).encode()).hexdigest()

    def _uses(self) -> dict[str, set[tuple[str, str]]]:
        """Per recorded project (its id): the entries it uses. An unreadable record uses nothing it can show."""
        folder = self.root / PROJECTS
        uses = {}
        for path in sorted(folder.glob("*.json")) if folder.is_dir() and not folder.is_symlink() else ():
            try:
                entries = json.loads(path.read_text(encoding="utf-8"))["entries"]
                uses[path.stem] = {tuple(e.split("/", 1)) for e in entries if isinstance(e, str) and "/" in e}
            except (OSError, ValueError, KeyError, TypeError, RecursionError):  # RecursionError: nested too deep
                uses[path.stem] = set()  # still a project using the cache: its entries are not taken as orphans
        return uses

    def _check_marker(self) -> None:
        try:
            content = json.loads((self.root / MARKER).read_text()) if _is_marker(self.root / MARKER) else None
        except (OSError, ValueError, RecursionError):  # RecursionError: nested too deep to decode
            content = None
        if not isinstance(content, dict) or content.get("format") != MARKER_CONTENT["format"]:
            raise InputError(f"{self.root} is not a fluorocal cache (no valid {MARKER} in it); nothing deleted")

    def _own_children(self):
        """``(stage folder, child)`` of every entry or temporary the cache wrote (no symlinks followed)."""
        for stage_dir in sorted(self.root.iterdir()) if self.root.is_dir() else ():
            if stage_dir.is_symlink() or not stage_dir.is_dir() or not _STAGE.fullmatch(stage_dir.name):
                continue
            for entry in sorted(stage_dir.iterdir()):
                if (
                    not entry.is_symlink()
                    and entry.is_dir()
                    and (_KEY.fullmatch(entry.name) or _TMP.fullmatch(entry.name))
                ):
                    yield stage_dir, entry

    def code_memo(self):
        """The analyses of the code digests kept in this cache (:class:`fluorocal.codehash.AnalysisMemo`)."""
        from fluorocal.codehash import AnalysisMemo

        return AnalysisMemo(self.root / CODE / "analyses.json")

    def _remove_skeleton(self) -> None:
        """After a full clean: empty stage folders, lock files, the code memo, the root if only the marker is left."""
        if (self.root / CODE).is_dir() and not (self.root / CODE).is_symlink():
            shutil.rmtree(self.root / CODE, ignore_errors=True)
        locks = self.root / LOCKS
        if locks.is_dir() and not locks.is_symlink():
            for path in locks.iterdir():
                if _LOCK.fullmatch(path.name) and path.is_file():
                    path.unlink()
            with contextlib.suppress(OSError):
                locks.rmdir()
        for stage_dir in self.root.iterdir():
            if stage_dir.name == PROJECTS and stage_dir.is_dir() and not stage_dir.is_symlink():
                with contextlib.suppress(OSError):  # a record left: a project still uses the cache
                    stage_dir.rmdir()
            if _STAGE.fullmatch(stage_dir.name) and stage_dir.is_dir() and not stage_dir.is_symlink():
                with contextlib.suppress(OSError):  # not empty: something else lives there
                    stage_dir.rmdir()
        if [p.name for p in self.root.iterdir()] == [MARKER]:
            (self.root / MARKER).unlink()
            self.root.rmdir()

    # --- locks -----------------------------------------------------------------------------------

    @contextlib.contextmanager
    def lock(self, stage: str, key: str, *, blocking: bool = True):
        """Hold the entry's lock (``fcntl.flock`` on ``<root>/.locks/<stage>.<key>.lock``); reentrant in a process.

        Yields whether the lock is held (always True when ``blocking``; False without
        ``blocking`` when another process, or this one, holds it). Without ``fcntl``
        (not POSIX) this holds nothing between processes.
        """
        self.entry_dir(stage, key)  # checks the names
        path = os.path.abspath(self.root / LOCKS / f"{stage}.{key}.lock")
        if _HELD.get(path) and not blocking:  # held by this process: a live writer
            yield False
            return
        if fcntl is None or _HELD.get(path):
            _HELD[path] = _HELD.get(path, 0) + 1
            try:
                yield True
            finally:
                _HELD[path] -= 1
            return
        os.makedirs(os.path.dirname(path), exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
            except BlockingIOError:
                yield False
                return
            _HELD[path] = 1
            try:
                yield True
            finally:
                del _HELD[path]
                fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)


def _check_manifest(manifest, stage: str, key: str) -> None:
    if not isinstance(manifest, dict):
        raise ValueError("manifest is not a JSON object")
    if manifest.get("key") != key or manifest.get("stage") != stage:
        raise ValueError("manifest does not match its stage and key")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"format {manifest.get('format_version')!r}, not {FORMAT_VERSION}")
    files = manifest.get("files")
    if not isinstance(files, dict) or ARRAYS not in files or not set(files) <= DATA_FILES:
        raise ValueError(f"manifest lists files other than {', '.join(sorted(DATA_FILES))}")


def _older_format(raw: bytes) -> bool:
    """Whether a manifest says it is of an earlier format (read as data only, never decoded)."""
    try:
        version = json.loads(raw).get("format_version")
    except (ValueError, AttributeError, RecursionError):  # RecursionError: nested too deep to decode
        return False
    return isinstance(version, int) and not isinstance(version, bool) and version < FORMAT_VERSION


def _is_marker(path: Path) -> bool:
    """Whether ``path`` is a marker file the cache can have written: a file, not a link (which may lead anywhere)."""
    return path.is_file() and not path.is_symlink()


def _only_cache_files(root: Path) -> bool:
    """Whether ``root`` holds only what a cache (of this or the previous format) writes."""
    for child in root.iterdir():
        if child.is_symlink():  # may lead out of the cache
            return False
        if (child.name in (LOCKS, PROJECTS, CODE) and child.is_dir()) or (child.name == MARKER and child.is_file()):
            continue
        if not child.is_dir() or not _STAGE.fullmatch(child.name):
            return False
        if any(
            not (_KEY.fullmatch(p.name) or _TMP.fullmatch(p.name) or _LEGACY_TMP.fullmatch(p.name))
            for p in child.iterdir()
        ):
            return False
    return True


def _warn_unreadable(stage: str, key: str, exc: Exception) -> None:
    warnings.warn(f"cache entry {stage}/{key[:12]} unreadable ({exc}); recomputing", CacheWarning, stacklevel=4)


def _environment() -> dict:
    import cv2  # noqa: F401  (version recorded for provenance)
    import OpenImageIO

    return {
        "written_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "openimageio": OpenImageIO.__version__,
    }
