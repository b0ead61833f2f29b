"""A project's frames as the units of work of the per-frame stages, counted and checked before any stage runs.

Every frame of every system (a multi-page TIFF or a DICOM cine holds several) becomes a
:class:`FrameUnit` keyed by its file's content hash and its index; what cannot make a calibration
(files without frames, frames too small or of two sizes in one system, biplanar systems of unequal
length, a file holding another's content) is refused here, naming the files.
"""

from __future__ import annotations

import hashlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from fluorocal.cache import file_sha256
from fluorocal.config import Config
from fluorocal.stages.errors import InputError


@dataclass(frozen=True)
class FrameUnit:
    """One frame of one system: the unit per-frame stages run on."""

    system: int
    exposure: int
    path: Path
    index: int
    key: str
    file_sha256: str
    size_px: tuple[int, int] = (0, 0)

    @property
    def label(self) -> str:
        return f"{self.path.name}" + (f"[{self.index}]" if self.index else "")


#: smallest frame side (px) that can hold a bead image with background around it
MIN_FRAME_PX = 8


def frame_units(config: Config) -> list[FrameUnit]:
    r"""Every frame of every system, in sorted file order; the key is the file's content hash and frame index.

    Frames are counted (a multi-page TIFF or a DICOM cine holds several), not files.

    Raises
    ------
    InputError
        A frame file cannot be read or holds no frame; a frame is smaller than
        :data:`MIN_FRAME_PX` on a side; the frames of one system differ in size; or
        the two systems of a biplanar project hold different numbers of frames (they pair
        by position, so a missing frame would pair every later one with the wrong partner); or a file
        holds the content of another file of the project.

    Examples
    --------
    >>> import tempfile
    >>> import numpy as np
    >>> from fluorocal.config import load_config
    >>> from fluorocal.stages.io.still import write_still
    >>> with tempfile.TemporaryDirectory() as d:
    ...     root = Path(d)
    ...     _ = (root / "phantom.csv").write_text("id,x,y,z\n1,0,0,0\n2,10,0,0\n3,0,10,0\n4,0,0,10\n")
    ...     for i in range(2):
    ...         write_still(root / f"f{i}.tif", np.full((32, 48), 1000 + i, np.uint16))
    ...     system = 'name = "A"\nframes = "f*.tif"\nsource_image_distance = 1100\npixel_pitch = 0.5\n'
    ...     _ = (root / "p.toml").write_text(f'[phantom]\nfile = "phantom.csv"\n[[systems]]\n{system}')
    ...     units = frame_units(load_config(root / "p.toml", writable=False))
    >>> [(u.exposure, u.path.name, u.size_px) for u in units]
    [(0, 'f0.tif', (48, 32)), (1, 'f1.tif', (48, 32))]
    """
    from fluorocal.stages.io import probe_frames

    units = []
    for s, system in enumerate(config.systems):
        exposure = 0
        for path in system.frames:
            try:
                digest = file_sha256(path)
            except OSError as exc:
                raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
            n_frames, size = probe_frames(path)
            _check_frame_size(path, n_frames, size, next((u for u in units if u.system == s), None))
            for i in range(n_frames):
                key = hashlib.sha256(f"{digest}:{i}".encode()).hexdigest()
                units.append(FrameUnit(s, exposure, Path(path), i, key, digest, size))
                exposure += 1
    _check_pairing(config, units)
    _check_distinct(config, units)
    return units


def _check_distinct(config: Config, units: list[FrameUnit]) -> None:
    """Refuse a frame file whose content another file of the project holds: a copied file, not an exposure.

    Found here, before any work; at learn the copy makes a rig that is no rig, and the adjustment's normal
    equations turn singular, or not, by rounding.
    """
    first: dict[tuple[int, str], Path] = {}
    for u in units:
        other = first.setdefault((u.system, u.file_sha256), u.path)
        if other != u.path:
            raise InputError(f"{u.path}: the same content as {other} (a copied file?); each exposure has its own frame")
    twin = next((u for u in units if u.system and (0, u.file_sha256) in first), None)
    if twin is not None:  # the same content: the adjustment's normal equations turn singular, found only at learn
        raise InputError(f"{twin.path}: holds a frame of system {config.systems[0].name}; give each system its own")


def _check_frame_size(path: Path, n_frames: int, size: tuple[int, int], first) -> None:
    """Refuse a file without frames, frames too small for a bead, or a size unlike the system's first frame's."""
    if n_frames < 1:
        raise InputError(f"{path}: holds no frame")
    width, height = size
    if min(width, height) < MIN_FRAME_PX:
        raise InputError(
            f"{path}: frame of {width}x{height} px is too small to hold a bead (at least {MIN_FRAME_PX} px a side)"
        )
    if first is not None and first.size_px != size:
        w0, h0 = first.size_px
        raise InputError(
            f"frames of one system differ in size: {first.path} is {w0}x{h0} px, {path} is {width}x{height} px; "
            "a system's frames must come from one detector mode"
        )


def _check_pairing(config: Config, units: list[FrameUnit]) -> None:
    """Refuse biplanar systems whose frame counts differ, naming the counts and the frames left unpaired.

    A kind whose systems are calibrated each on its own (a grid plate: frames never paired) takes any counts.
    """
    if len(config.systems) < 2 or not config.phantom.kind.pairs_frames:
        return
    per_system = [[u for u in units if u.system == s] for s in range(len(config.systems))]
    counts = [len(p) for p in per_system]
    if len(set(counts)) == 1:
        return
    n = min(counts)
    longer = max(range(len(counts)), key=counts.__getitem__)
    unpaired = [u.label for u in per_system[longer][n:]]
    shown = ", ".join(unpaired[:5]) + (f" and {len(unpaired) - 5} more" if len(unpaired) > 5 else "")
    frames_in = Counter(u.path for u in units)  # a file holding several frames shifts the pairing too
    multi = [f"{path.name} holds {k} frames" for path, k in frames_in.items() if k > 1]
    counted = ", ".join(f"{system.name}: {k}" for system, k in zip(config.systems, counts))
    raise InputError(
        f"biplanar systems must hold the same number of frames (they pair by position); frames counted {counted}"
        + (f" ({'; '.join(multi[:3])})" if multi else "")
        + f"; past frame {n}, system {config.systems[longer].name}'s {shown} "
        f"{'has' if len(unpaired) == 1 else 'have'} no partner in system {config.systems[1 - longer].name}; "
        "add the missing frames or remove the extra ones"
    )
