"""The attack battery's tampering: cache entries and field files edited, forged, truncated or made to run code.

A payload that ran would ``touch`` the case's canary file (:attr:`Ctx.canary`), which :func:`judge` looks for.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

from tests.attack.harness import Ctx


def touch_cmd(c: Ctx) -> str:
    """The shell command a payload runs: it creates the case's canary."""
    return f"touch {c.canary}"


class Payload:
    """An object whose unpickling runs ``cmd`` in a shell."""

    def __init__(self, cmd: str):
        self.cmd = cmd

    def __reduce__(self):
        return (os.system, (self.cmd,))


def entries(c: Ctx, stage: str) -> list[Path]:
    """The cache entries (folders) of ``stage``, sorted by key."""
    return sorted(p for p in (c.proj / ".fluorocal" / stage).iterdir() if p.is_dir() and not p.name.startswith("."))


def rehash(entry: Path) -> None:
    """Recompute an entry's checksums, as an attacker who knows the format would."""
    m = json.loads((entry / "manifest.json").read_text())
    if (entry / "arrays.npz").is_file():
        m.setdefault("files", {})["arrays.npz"] = hashlib.sha256((entry / "arrays.npz").read_bytes()).hexdigest()
    text = json.dumps(m, indent=1)
    (entry / "manifest.json").write_text(text)
    (entry / "manifest.sha256").write_text(hashlib.sha256(text.encode()).hexdigest() + "\n")


def manifest_payload(stage: str, payload: Callable[[Ctx], dict], rehash_it: bool = True, which: int = 0):
    """The ``which``-th entry of ``stage``: its manifest's artifact replaced by ``payload(c)`` (checksums redone)."""

    def f(c: Ctx) -> None:
        entry = entries(c, stage)[which]
        m = json.loads((entry / "manifest.json").read_text())
        m["artifact"] = payload(c)
        (entry / "manifest.json").write_text(json.dumps(m, indent=1))
        if rehash_it:
            rehash(entry)

    return f


def code_ref(ref: str):
    """A manifest artifact naming the callable ``ref`` (``module:name``) as its class, with the canary's command."""

    def payload(c: Ctx) -> dict:
        return {"__dataclass__": ref, "fields": {"command": touch_cmd(c), "args": [touch_cmd(c)]}}

    return payload


def pickle_npz(stage: str):
    """arrays.npz replaced by one holding a pickled object whose unpickling would touch the canary."""

    def f(c: Ctx) -> None:
        entry = entries(c, stage)[0]
        with np.load(entry / "arrays.npz") as z:
            arrays = {k: z[k] for k in z.files}
        key = next(iter(arrays))
        obj = np.empty(1, dtype=object)
        obj[0] = Payload(touch_cmd(c))
        arrays[key] = obj
        np.savez(entry / "arrays.npz", **arrays)
        rehash(entry)

    return f


def pickle_field(c: Ctx) -> None:
    """field_A.npz's displacements replaced by a pickled object whose unpickling would touch the canary."""
    p = c.proj / "out" / "field_A.npz"
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files}
    obj = np.empty(1, dtype=object)
    obj[0] = Payload(touch_cmd(c))
    arrays["delta_px"] = obj
    np.savez(p, **arrays)


def entry_edit(stage: str, fn: Callable[[Path], None], which: int = 0):
    """The ``which``-th entry of ``stage`` changed by ``fn`` (given the entry's folder)."""

    def f(c: Ctx) -> None:
        fn(entries(c, stage)[which])

    return f


def flip_byte(name: str, offset_frac: float = 0.5):
    """One bit of the file ``name`` (in the folder given) flipped at ``offset_frac`` of its length."""

    def fn(entry: Path) -> None:
        p = entry / name
        b = bytearray(p.read_bytes())
        b[int(len(b) * offset_frac)] ^= 0x40
        p.write_bytes(bytes(b))

    return fn


def truncate(name: str, frac: float = 0.5):
    """The file ``name`` (in the folder given) cut to ``frac`` of its length."""

    def fn(entry: Path) -> None:
        p = entry / name
        p.write_bytes(p.read_bytes()[: int(p.stat().st_size * frac)])

    return fn


def edit_array(entry: Path) -> None:
    """An array value changed and every checksum recomputed: a forger who knows the format."""
    with np.load(entry / "arrays.npz") as z:
        arrays = {k: z[k] for k in z.files}
    k = next(k for k in arrays if arrays[k].dtype.kind == "f" and arrays[k].size)
    arrays[k] = arrays[k] + 1.0
    np.savez(entry / "arrays.npz", **arrays)
    rehash(entry)


def edit_summary(entry: Path) -> None:
    """The manifest's summary edited by hand (checksums left as they were)."""
    m = json.loads((entry / "manifest.json").read_text())
    m["summary"] = "edited by hand"
    (entry / "manifest.json").write_text(json.dumps(m, indent=1))


def entry_links_to_sibling(e: Path) -> None:
    """The entry replaced by a link to the case folder's ``sibling`` (``e`` is ``proj/.fluorocal/STAGE/KEY``)."""
    shutil.rmtree(e)
    e.symlink_to(e.parents[3] / "sibling")


def stage_links_to_sibling(c: Ctx) -> None:
    """The cache's label folder replaced by a link to the user's ``sibling`` folder."""
    shutil.rmtree(c.proj / ".fluorocal" / "label")
    (c.proj / ".fluorocal" / "label").symlink_to(c.root / "sibling")
