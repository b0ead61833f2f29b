"""The attack battery's setups: the hostile or careless change a case makes to its copy of the project.

Each function here returns a setup (``Ctx -> None``) or is one; the cache's tampering is in
:mod:`tests.attack.tampering`.
"""

from __future__ import annotations

import os
import shutil
import warnings
from pathlib import Path

import numpy as np

from tests.attack.harness import Ctx


def nothing(c: Ctx) -> None:
    """No change: the case is in its commands or its runner."""


# --- the config -----------------------------------------------------------------------------------


def set_key(c: Ctx, key: str, value: str, system: int = 0) -> None:
    """Set ``key = value`` in the ``system``-th [[systems]] table (0: A) of the simulator's config."""
    lines = c.cfg.read_text().splitlines()
    seen = -1
    for i, ln in enumerate(lines):
        if ln.strip() == "[[systems]]":
            seen += 1
        if seen == system and ln.split("=")[0].strip() == key:
            lines[i] = f"{key} = {value}"
            break
    else:
        raise AssertionError(key)
    c.cfg.write_text("\n".join(lines) + "\n")


def cfg_edit(old: str, new: str):
    """Replace the first ``old`` in the config (which must hold it) by ``new``."""

    def f(c: Ctx) -> None:
        c.edit_cfg(old, new)

    return f


def cfg_key(key: str, value: str, system: int = 0):
    """:func:`set_key` as a setup."""

    def f(c: Ctx) -> None:
        set_key(c, key, value, system)

    return f


def cfg_append(text: str):
    """Append ``text`` to the config."""

    def f(c: Ctx) -> None:
        c.append_cfg(text)

    return f


def cfg_replace(old: str, new: str):
    """Replace every ``old`` in the config by ``new`` (none there: no change)."""

    def f(c: Ctx) -> None:
        c.cfg.write_text(c.cfg.read_text().replace(old, new))

    return f


# --- the phantom table ----------------------------------------------------------------------------


def phantom_rows(c: Ctx) -> list[list[str]]:
    """phantom.csv's rows, header first, each split at its commas."""
    return [ln.split(",") for ln in c.proj.joinpath("phantom.csv").read_text().splitlines()]


def write_rows(c: Ctx, rows, name="phantom.csv") -> None:
    """Write ``rows`` (lists of cells) as the project's ``name``."""
    c.proj.joinpath(name).write_text("\n".join(",".join(r) for r in rows) + "\n")


def scale_phantom(factor: float):
    """Every bead's x, y, z and diameter times ``factor`` (another unit)."""

    def f(c: Ctx) -> None:
        rows = phantom_rows(c)
        for r in rows[1:]:
            for j in (1, 2, 3, 4):
                r[j] = repr(float(r[j]) * factor)
        write_rows(c, rows)

    return f


def phantom_cell(row: int, col: int, value: str):
    """One cell of phantom.csv (``row`` 0 is the header) set to ``value``."""

    def f(c: Ctx) -> None:
        rows = phantom_rows(c)
        rows[row][col] = value
        write_rows(c, rows)

    return f


# --- files ----------------------------------------------------------------------------------------


def write_bytes(rel: str, data: bytes):
    """``proj/rel`` (whatever it was: file, folder or link) replaced by a file holding ``data``."""

    def f(c: Ctx) -> None:
        p = c.proj / rel
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)

    return f


def make_dir(rel: str):
    """The file ``proj/rel`` replaced by an empty folder."""

    def f(c: Ctx) -> None:
        p = c.proj / rel
        p.unlink()
        p.mkdir()

    return f


def symlink(rel: str, target: str):
    """Replace ``proj/rel`` by a symbolic link to ``target`` (relative to the case folder, or absolute)."""

    def f(c: Ctx) -> None:
        p = c.proj / rel
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()
        t = Path(target) if os.path.isabs(target) else c.root / target
        p.symlink_to(t)

    return f


def chain(*fs):
    """The setups ``fs`` one after the other."""

    def f(c: Ctx) -> None:
        for g in fs:
            g(c)

    return f


# --- frames ---------------------------------------------------------------------------------------


def tiff(rel: str, arr: np.ndarray, **kw):
    """``proj/rel`` written as a TIFF of ``arr`` (tifffile's options ``kw``)."""

    def f(c: Ctx) -> None:
        import tifffile

        p = c.proj / rel
        if p.exists():
            p.unlink()
        with warnings.catch_warnings():  # a frame of zero size is written on purpose
            warnings.filterwarnings("ignore", ".*writing zero-size array to nonconformant TIFF", UserWarning)
            tifffile.imwrite(p, arr, **kw)

    return f


def read_frame(p: Path) -> np.ndarray:
    import tifffile

    return tifffile.imread(p)


def with_inf(c: Ctx) -> np.ndarray:
    """Frame A's second as float32, with a 10-px square of +inf."""
    a = read_frame(c.frames("A")[1]).astype(np.float32)
    a[10:20, 10:20] = np.inf
    return a


def png(p: Path) -> None:
    """The frame at ``p`` rewritten as a PNG under its own name."""
    import cv2

    a = read_frame(p)
    ok, buf = cv2.imencode(".png", a)
    p.write_bytes(buf.tobytes())


def huge_header_tiff(p: Path) -> None:
    """A TIFF whose header claims 2**31-1 x 2**31-1 pixels, with a few bytes of data."""
    import tifffile

    tifffile.imwrite(p, np.zeros((4, 4), np.uint16))
    b = bytearray(p.read_bytes())
    with tifffile.TiffFile(p) as t:
        page = t.pages[0]
        for tag in (256, 257):
            off = page.tags[tag].valueoffset
            size = 2 if page.tags[tag].dtype == 3 else 4
            b[off : off + size] = (0xFFFF if size == 2 else 0x7FFFFFFF).to_bytes(size, "little")
    p.write_bytes(bytes(b))


# --- the calibration's files ------------------------------------------------------------------------


def field_npz(fn, name="field_A.npz"):
    """The published field file ``name``'s arrays changed in place by ``fn`` (a dict of arrays), then saved."""

    def f(c: Ctx) -> None:
        p = c.proj / "out" / name
        with np.load(p) as z:
            arrays = {k: z[k] for k in z.files}
        fn(arrays)
        np.savez(p, **arrays)

    return f
