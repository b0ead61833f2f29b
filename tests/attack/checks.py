"""The attack battery's result checks: for a case that exits 0, None if its result is right, else why not."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tests.attack.harness import Ctx


def _csv_array(path: Path) -> np.ndarray:
    return np.genfromtxt(path, delimiter=",", skip_header=1)


def _fields_differ(ref: Path, out: Path) -> str | None:
    """The first of the clean run's field files (in ``ref``) missing from ``out`` or different there (1e-6)."""
    for f in sorted(ref.glob("field_*.npz")):
        g = out / f.name
        if not g.is_file():
            return f"{f.name} missing"
        with np.load(f) as x, np.load(g) as y:
            for k in x.files:
                if (
                    k not in y.files
                    or x[k].shape != y[k].shape
                    or not np.allclose(x[k], y[k], atol=1e-6, equal_nan=True)
                ):
                    return f"{f.name}[{k}] differs from the clean run's"
    return None


def same_as_clean(c: Ctx, tol_mm: float = 1e-6, renamed: dict | None = None) -> str | None:
    """object_points.csv and every field file as the clean run's (numerically, within ``tol_mm``).

    ``renamed`` maps a bead id the case gave to the clean run's id of that bead (the rows are compared in id order).
    """
    out, ref = c.proj / "out", c.clean / "out"
    if not (out / "object_points.csv").is_file():
        return "exit 0 but no object_points.csv"
    a, b = _csv_array(out / "object_points.csv"), _csv_array(ref / "object_points.csv")
    if renamed and a.ndim == 2:
        a[:, 0] = [renamed.get(int(i), i) for i in a[:, 0]]
        a = a[np.argsort(a[:, 0], kind="stable")]
    if a.shape != b.shape or not np.allclose(a[:, :4], b[:, :4], atol=tol_mm, rtol=0):
        d = np.abs(a[:, :4] - b[:, :4]).max() if a.shape == b.shape else "shape"
        return f"object points differ from the clean run's ({d})"
    return _fields_differ(ref, out)


def clean_and_no_leftovers(c: Ctx) -> str | None:
    """The clean run's results (:func:`same_as_clean`), and no temporary, staging or old folder left behind."""
    why = same_as_clean(c)
    if why:
        return why
    left = [
        str(p.relative_to(c.root))
        for p in c.root.rglob("*")
        if ".tmp-" in p.name
        or ".fluorocal-staging" in p.name
        or ".fluorocal-old" in p.name
        or p.name.startswith(".label.")
    ]
    return f"left behind: {left[:3]}" if left else None


def sibling_intact(c: Ctx) -> str | None:
    """The user's files beside the project are still there."""
    for rel in ("sibling/precious.txt", "sibling/work/notes.txt"):
        if not (c.root / rel).is_file():
            return f"{rel} gone"
    return None


def undistorted_ok(out_dir: str, n: int | None = None):
    """The undistort outputs: present, finite, not all black."""

    def check(c: Ctx) -> str | None:
        import OpenImageIO as oiio

        files = sorted((c.root / out_dir).glob("*.tif"))
        if not files or (n is not None and len(files) != n):
            return f"{len(files)} undistorted files, expected {n}"
        for f in files:
            img = oiio.ImageBuf(str(f)).get_pixels(oiio.FLOAT)
            if img is None or not np.isfinite(img).all() or img.max() <= 0:
                return f"{f.name}: all black or not finite"
        return None

    return check


def accepted(c: Ctx) -> None:
    """Any result of exit 0 is right: the case is about how the command ends, not what it computes."""
    return None
