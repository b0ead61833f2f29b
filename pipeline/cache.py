"""Content-addressed artifact store.

An artifact lives in ``<cache>/<stage>/<key>/``: ``manifest.json`` (key,
stage, provenance, the artifact's structure and the sha256 of every file),
``arrays.npz`` (its numpy arrays), and, where the artifact offers them,
``table.csv`` and ``overlay.png`` for people. The key is a hash of the stage
name, the digest of the code that computes it (:mod:`fluorocal.codehash`),
its parameters and its input keys (:func:`artifact_key`).

Writes are atomic: everything is written into a hidden temporary directory
beside the final one, which is renamed into place last, so an interrupted
write never leaves a directory a later run would trust. A read checks every
checksum; a missing, truncated or corrupt entry is a miss (with a warning and
the entry deleted), never an error.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import logging
import os
import platform
import shutil
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
ARRAYS = "arrays.npz"
TABLE = "table.csv"
OVERLAY = "overlay.png"
FORMAT_VERSION = 1


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


def file_sha256(path: str | os.PathLike) -> str:
    """Content hash of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# --- generic (de)serialisation of frozen artifact dataclasses -------------------------------


def _encode(obj, arrays: dict, path: str):
    if isinstance(obj, np.ndarray):
        if obj.dtype == object:
            raise TypeError(f"artifact field {path} is an object array; use a typed array")
        arrays[path] = obj
        return {"__array__": path}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        cls = type(obj)
        return {
            "__dataclass__": f"{cls.__module__}:{cls.__qualname__}",
            "fields": {
                f.name: _encode(getattr(obj, f.name), arrays, f"{path}.{f.name}") for f in dataclasses.fields(obj)
            },
        }
    if isinstance(obj, (list, tuple)):
        return {"__tuple__": [_encode(v, arrays, f"{path}.{i}") for i, v in enumerate(obj)]}
    if isinstance(obj, dict):
        return {"__dict__": {str(k): _encode(v, arrays, f"{path}.{k}") for k, v in obj.items()}}
    if isinstance(obj, np.generic):
        return obj.item()
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    raise TypeError(f"artifact field {path} has unsupported type {type(obj).__name__}")


def _decode(node, arrays):
    if isinstance(node, dict):
        if "__array__" in node:
            return arrays[node["__array__"]]
        if "__dataclass__" in node:
            module, qualname = node["__dataclass__"].split(":")
            cls = importlib.import_module(module)
            for part in qualname.split("."):
                cls = getattr(cls, part)
            return cls(**{k: _decode(v, arrays) for k, v in node["fields"].items()})
        if "__tuple__" in node:
            return tuple(_decode(v, arrays) for v in node["__tuple__"])
        if "__dict__" in node:
            return {k: _decode(v, arrays) for k, v in node["__dict__"].items()}
    return node


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
    """The on-disk store under ``root`` (default ``.fluorocal/`` beside the config)."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def entry_dir(self, stage: str, key: str) -> Path:
        return self.root / stage / key

    def has(self, stage: str, key: str) -> bool:
        return (self.entry_dir(stage, key) / MANIFEST).is_file()

    def load(self, stage: str, key: str):
        """The artifact stored at ``(stage, key)``, or ``None`` on a miss.

        A corrupt or truncated entry warns (:class:`CacheWarning`), is deleted
        and counts as a miss.
        """
        entry = self.entry_dir(stage, key)
        if not entry.exists():
            return None
        try:
            manifest = json.loads((entry / MANIFEST).read_text())
            if manifest.get("key") != key or manifest.get("format_version") != FORMAT_VERSION:
                raise ValueError("manifest does not match its key or format")
            for name, digest in manifest["files"].items():
                if file_sha256(entry / name) != digest:
                    raise ValueError(f"checksum mismatch in {name}")
            with np.load(entry / ARRAYS, allow_pickle=False) as npz:
                arrays = {k: npz[k] for k in npz.files}
            return _decode(manifest["artifact"], arrays)
        except Exception as exc:  # any failure to read is a miss, never fatal
            warnings.warn(f"cache entry {stage}/{key[:12]} unreadable ({exc}); recomputing", CacheWarning, stacklevel=2)
            shutil.rmtree(entry, ignore_errors=True)
            return None

    def store(
        self, stage: str, key: str, artifact, *, provenance: dict | None = None, overlay: bytes | None = None
    ) -> Path:
        """Write ``artifact`` atomically and return its directory."""
        final = self.entry_dir(stage, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{key[:12]}-", dir=final.parent))
        try:
            arrays: dict[str, np.ndarray] = {}
            tree = _encode(artifact, arrays, "artifact")
            np.savez(tmp / ARRAYS, **arrays)
            if hasattr(artifact, "to_table"):
                _write_table(tmp / TABLE, *artifact.to_table())
            if overlay is not None:
                (tmp / OVERLAY).write_bytes(overlay)
            files = {p.name: file_sha256(p) for p in sorted(tmp.iterdir())}
            manifest = {
                "format_version": FORMAT_VERSION,
                "key": key,
                "stage": stage,
                "summary": _summary(artifact),
                "provenance": {**_environment(), **(provenance or {})},
                "files": files,
                "artifact": tree,
            }
            # the manifest is written last: an entry without one is never trusted
            (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1))
            if final.exists():
                shutil.rmtree(final)
            os.replace(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return final

    def manifest(self, stage: str, key: str) -> dict | None:
        try:
            return json.loads((self.entry_dir(stage, key) / MANIFEST).read_text())
        except (OSError, ValueError):
            return None

    def keys(self, stage: str) -> list[str]:
        d = self.root / stage
        return sorted(p.name for p in d.iterdir() if not p.name.startswith(".")) if d.is_dir() else []

    def size_bytes(self, stage: str, key: str) -> int:
        entry = self.entry_dir(stage, key)
        return sum(p.stat().st_size for p in entry.iterdir()) if entry.is_dir() else 0

    def clean(self, *, keep: set[tuple[str, str]] | None = None) -> int:
        """Delete every entry (or every one not in ``keep``) and leftover temporaries; return the count."""
        removed = 0
        if not self.root.is_dir():
            return 0
        for stage_dir in self.root.iterdir():
            if not stage_dir.is_dir():
                continue
            for entry in stage_dir.iterdir():
                if keep is None or entry.name.startswith(".") or (stage_dir.name, entry.name) not in keep:
                    shutil.rmtree(entry, ignore_errors=True)
                    removed += 1
        if keep is None:
            shutil.rmtree(self.root, ignore_errors=True)
        return removed


def _write_table(path: Path, header: list[str], rows) -> None:
    from fluorocal.stages.io import write_csv

    write_csv(path, header, rows)


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
