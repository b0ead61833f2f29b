"""The report's figures, drawn again only when what they show changed.

A figure is a product of its content: the function that plots it, the arguments it is given (arrays,
titles, sizes), the code of the function's module and all it imports (:func:`fluorocal.codehash.code_digest`)
and matplotlib's version: :func:`figure_key` hashes them all. ``fluorocal run`` publishes its outputs as a
whole set each time (:func:`fluorocal.outputs.publish`); :class:`Figures` copies into the new set each figure
the previous set holds under the same key instead of drawing it again.

Every figure is drawn under matplotlib's default settings and the report's own (:data:`STYLE`, in the key through
the plots' code: :func:`_default_style`), whatever the process's ``rcParams`` (a ``matplotlibrc`` in the working
folder, ``$MATPLOTLIBRC``, the user's, or code that changed them): the process' settings are no input of a
figure, so its key need not hold them and a report is the same on every machine with the same versions.

A published set records each figure's key and the sha256 of its PNG (:data:`RECORD`). A figure is taken
over only when that record gives the same key and the previous set's file still has the recorded checksum:
a figure edited, truncated or removed, or swapped by a run publishing at the same time, is drawn anew. The
copy is written into the set being staged like a drawn one, so the set is published whole or not at all.
"""

from __future__ import annotations

import dataclasses
import enum
import gc
import hashlib
import json
import logging
import os
import re
import stat
from pathlib import Path

import numpy as np
from fluorocal.outputs import inside
from fluorocal.stages.errors import InputError
from fluorocal.stages.io import atomic_write, write_png

log = logging.getLogger(__name__)

#: the report's settings over matplotlib's defaults. Text unhinted: FreeType's hinting (the font's own
#: instructions, run again each time matplotlib 3.11 sets a glyph's size) cost a third of the figures' text time;
#: unhinted letters are as legible at the report's sizes, their shapes a little softer
STYLE = {"text.hinting": "no_hinting"}
#: the file of a published set that records its figures: name -> {"key": ..., "sha256": ...}
RECORD = ".fluorocal-figures.json"
_HEX = re.compile(r"[0-9a-f]{64}")


class Figures:
    """Draws the figures of a set being written, or copies those of ``previous`` made from the same content.

    Parameters
    ----------
    previous : path, optional
        The folder of the published set (absent or without a :data:`RECORD`: every figure is drawn).
    memo : fluorocal.codehash.AnalysisMemo, optional
        Analyses of the code digests kept between runs.
    """

    def __init__(self, previous=None, memo=None):
        self.previous = None if previous is None else Path(previous)
        self.old = {} if previous is None else _read_record(_read_own(self.previous, RECORD))
        self.memo = memo
        self.new: dict[str, dict[str, str]] = {}
        self.drawn: list[str] = []
        self.copied: list[str] = []
        self._codes: dict[str, str] = {}

    def draw(self, path: Path, plot, *args) -> Path:
        """``plot(path, *args)``, or the previous set's figure of the same name and key written to ``path``.

        Raises
        ------
        InputError
            A figure of this report was already written under that name (a system named ``sigma_x`` beside
            one named ``x``: ``field_sigma_x.png`` is both): one would silently replace the other.
        """
        if path.name in self.new:
            raise InputError(
                f"two of the report's figures would both be written as {path.name}: rename a system or an "
                "orientation so that their file names differ"
            )
        key = figure_key(plot, args, self._code(plot.__module__))
        data = self._previous_png(path.name, key)
        if data is None:
            from fluorocal.compute import no_collection

            with _default_style(), no_collection():
                plot(path, *args)
            # a figure is thousands of objects in reference cycles, made with the collector paused: all in its
            # youngest generation, collected by a pass over them alone (not over the whole process, ~60 ms a pass)
            gc.collect(0)
            data = Path(path).read_bytes()
            self.drawn.append(path.name)
        else:
            write_png(path, data)
            self.copied.append(path.name)
        self.new[path.name] = {"key": key, "sha256": hashlib.sha256(data).hexdigest()}
        return path

    def write_record(self, folder: Path) -> Path:
        """Write :data:`RECORD` of the figures drawn or copied into ``folder``; return its path."""
        path = inside(folder, RECORD)
        text = json.dumps(self.new, indent=1, sort_keys=True)
        atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
        if self.copied:
            log.info("figures: %d drawn, %d unchanged and copied", len(self.drawn), len(self.copied))
        return path

    def _previous_png(self, name: str, key: str) -> bytes | None:
        old = self.old.get(name)
        if self.previous is None or old is None or old["key"] != key:
            return None
        data = _read_own(self.previous, name)
        return data if data is not None and hashlib.sha256(data).hexdigest() == old["sha256"] else None

    def _code(self, module: str) -> str:
        if module not in self._codes:
            from importlib.metadata import version

            from fluorocal.codehash import code_digest

            digest = code_digest([module], self.memo)
            self._codes[module] = f"{digest} matplotlib=={version('matplotlib')} style={sorted(STYLE.items())}"
        return self._codes[module]


def _default_style():
    """A context drawing under matplotlib's defaults (``rcParamsDefault``, none of its rc files) and :data:`STYLE`."""
    import matplotlib.style

    return matplotlib.style.context(["default", STYLE])


def figure_key(plot, args, code: str) -> str:
    """sha256 of the plotting function's name, ``code`` (the digest of its code) and its arguments' content.

    Examples
    --------
    >>> a = figure_key(print, (np.arange(3.0), "title"), "code")
    >>> same, other_dtype = (np.arange(3.0), "title"), (np.arange(3), "title")
    >>> a == figure_key(print, same, "code"), a == figure_key(print, other_dtype, "code")
    (True, False)
    """
    h = hashlib.sha256(f"{plot.__module__}.{plot.__qualname__}\n{code}\n".encode())
    _feed(h, args)
    return h.hexdigest()


def _feed(h, value) -> None:
    """Hash ``value``'s content: its type, and its arrays' dtype, shape and bytes; refuse what it cannot hash."""
    if isinstance(value, (np.ndarray, np.void)):
        if type(value) is not np.ndarray or value.dtype.hasobject or value.dtype.fields is not None:
            # a subclass' own state (a masked array's mask) and a structured dtype's fields are not in the bytes
            raise TypeError(
                f"a figure's arrays must be plain arrays of numbers, not {type(value).__qualname__} {value.dtype}"
            )
        h.update(f"ndarray {value.dtype.str} {value.shape}\n".encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, enum.Enum):
        h.update(f"{type(value).__qualname__} {value.value!r}\n".encode())
    elif value is None or isinstance(value, (str, bytes, int, float, complex, np.generic)):
        h.update(f"{type(value).__qualname__} {value!r}\n".encode())
    elif isinstance(value, dict):
        h.update(f"dict {len(value)}\n".encode())
        for k in sorted(value, key=repr):
            _feed(h, k)
            _feed(h, value[k])
    elif isinstance(value, (list, tuple)):
        h.update(f"{type(value).__qualname__} {len(value)}\n".encode())
        for item in value:
            _feed(h, item)
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = dataclasses.fields(value)
        h.update(f"{type(value).__module__}.{type(value).__qualname__} {len(fields)}\n".encode())
        for f in fields:
            h.update(f"{f.name}\n".encode())
            _feed(h, getattr(value, f.name))
    else:
        raise TypeError(f"cannot hash a figure's argument of type {type(value).__qualname__}")


def _read_own(folder: Path, name: str) -> bytes | None:
    """The bytes of the regular file ``name`` of ``folder``; None if unreadable, or not the folder's own (a symlink)."""
    try:
        fd = os.open(inside(folder, name), os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except (OSError, ValueError):  # ValueError: InputError, a name resolving outside the folder
        return None
    with os.fdopen(fd, "rb") as fh:
        try:
            return fh.read() if stat.S_ISREG(os.fstat(fd).st_mode) else None
        except OSError:
            return None


def _read_record(data: bytes | None) -> dict[str, dict[str, str]]:
    """The figures a set's record ``data`` lists (no record, an unreadable one, or entry, records none)."""
    if data is None:
        return {}
    try:
        raw = json.loads(data.decode("utf-8"))
    except (ValueError, RecursionError):  # not UTF-8, not JSON, or nested too deep to decode
        return {}
    if not isinstance(raw, dict):
        return {}
    return {
        name: {"key": e["key"], "sha256": e["sha256"]}
        for name, e in raw.items()
        if isinstance(name, str)
        and isinstance(e, dict)
        and all(isinstance(e.get(k), str) and _HEX.fullmatch(e[k]) for k in ("key", "sha256"))
    }
