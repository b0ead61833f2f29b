"""The undistortion maps of a calibration, computed once and cached beside it.

:meth:`fluorocal.Calibration.remap_maps` costs about a second per call at 1024² px (the field is
inverted at every pixel), so each map pair is stored on disk, in a folder beside the
calibration named like it (``calibration.json`` -> ``calibration.maps/``):

- one file per (calibration content, system, orientation, output size), named
  ``<key>.<digest>.npy``: ``key`` is the SHA-256 of the canonical JSON of those four and of the
  digest of the code that computes the maps (:func:`maps_code_digest`: the syntax trees of
  :data:`MAP_MODULES` and of every fluorocal module they import, as the stage cache keys its
  artifacts). The calibration's content is the hash of its JSON and field files, so an edited or
  re-run calibration never meets its old maps, and a change of the code never meets the maps of
  the code before it; ``digest`` is a BLAKE2b of the array's bytes, so a changed bit is noticed;
- the file is a ``(2, H, W)`` float32 ``.npy`` (``map_x``, ``map_y``): data only, read with
  ``np.load(allow_pickle=False)``, written atomically;
- an unreadable or corrupt entry is a miss: warned about (:class:`MapCacheWarning`), deleted and
  recomputed; a folder that cannot be written costs only the cache (warned about too).

Warnings name the caller of :meth:`~fluorocal.Calibration.remap_maps` (``stacklevel=4``).
Entries of earlier calibration contents are not removed: delete the folder to reclaim the space.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from collections.abc import Mapping
from functools import cache
from pathlib import Path

import numpy as np
from fluorocal.stages.io import atomic_write

#: the modules whose code computes the maps: the calibration's field choice and remap, the field, its interpolation
MAP_MODULES = ("fluorocal.calibration", "fluorocal.stages.field", "fluorocal.stages.orientation")


class MapCacheWarning(UserWarning):
    """A cached map pair was unreadable or corrupt (and is recomputed), or could not be stored."""


def maps_folder(calibration_path: str | Path) -> Path:
    """The cache folder beside a calibration file: ``calibration.json`` -> ``calibration.maps``."""
    path = Path(calibration_path)
    return path.with_name(path.stem + ".maps")


def orientation_key(orientation):
    """A JSON-able, canonical form of an orientation: None, a name, or ``{"orbit": deg, "tilt": deg}`` as floats."""
    if isinstance(orientation, Mapping):
        return {k: float(orientation[k]) for k in sorted(orientation)}
    return orientation


def map_key(content_sha256: str, system: str, orientation, size_px: tuple[int, int]) -> str:
    """The cache key of one map pair: SHA-256 of the canonical JSON of what determines it.

    Examples
    --------
    >>> a = map_key("0" * 64, "A", {"tilt": 0, "orbit": 15}, (64, 48))
    >>> a == map_key("0" * 64, "A", {"orbit": 15.0, "tilt": 0.0}, (64, 48)), a == map_key("0" * 64, "A", None, (64, 48))
    (True, False)
    """
    doc = {
        "calibration": content_sha256,
        "system": system,
        "orientation": orientation_key(orientation),
        "size_px": [int(size_px[0]), int(size_px[1])],
        "code": maps_code_digest(),
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


@cache
def maps_code_digest() -> str:
    """The digest of the code that computes the maps (:data:`MAP_MODULES` and their imports), once per process."""
    from fluorocal.codehash import code_digest

    return code_digest(MAP_MODULES)


def cached_maps(calibration_path, content_sha256, system: str, orientation, size_px, compute) -> np.ndarray:
    """The read-only ``(2, H, W)`` float32 maps: from the cache beside ``calibration_path``, else computed and stored.

    Without a ``calibration_path`` (a calibration built in memory), the maps are computed and not stored.
    """
    if calibration_path is None:
        maps = compute()
    else:
        folder, key = maps_folder(calibration_path), map_key(content_sha256, system, orientation, size_px)
        maps = load_maps(folder, key, size_px)
        if maps is None:
            maps = compute()
            store_maps(folder, key, maps)
    maps.flags.writeable = False
    return maps


def _digest(maps: np.ndarray) -> str:
    return hashlib.blake2b(np.ascontiguousarray(maps).data, digest_size=16).hexdigest()


def load_maps(folder: Path, key: str, size_px: tuple[int, int]) -> np.ndarray | None:
    """The cached ``(2, H, W)`` float32 maps under ``key``, or None on a miss (a corrupt entry: warned, deleted)."""
    w, h = size_px
    for file in sorted(folder.glob(f"{key}.*.npy")):
        try:
            maps = np.load(file, allow_pickle=False)
            if maps.dtype != np.float32 or maps.shape != (2, h, w):
                raise ValueError(f"expected a (2, {h}, {w}) float32 array; got {maps.shape} {maps.dtype}")
            if file.name != f"{key}.{_digest(maps)}.npy":
                raise ValueError("its content does not match the digest in its name")
            return maps
        except (OSError, ValueError, EOFError) as exc:
            warnings.warn(
                f"{file}: corrupt cached undistortion maps ({exc}); recomputing", MapCacheWarning, stacklevel=4
            )
            try:
                file.unlink(missing_ok=True)
            except OSError:  # a folder that cannot be written only loses the cache
                pass
    return None


def store_maps(folder: Path, key: str, maps: np.ndarray) -> None:
    """Store ``(2, H, W)`` float32 maps under ``key`` atomically; a failure is warned about, not raised."""
    file = folder / f"{key}.{_digest(maps)}.npy"
    try:
        atomic_write(file, lambda tmp: np.save(tmp, maps, allow_pickle=False))
    except OSError as exc:
        warnings.warn(
            f"{file}: cannot cache the undistortion maps ({exc}); they are recomputed on every run",
            MapCacheWarning,
            stacklevel=4,
        )
