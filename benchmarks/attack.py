"""Hostile and careless input, faults and tampering, run through the command line as a user would (issue 13).

Builds one small simulated biplanar project (``fluorocal simulate --frames 4 --systems 2 --image-size 512 512``),
runs it once so its cache is warm, and then, per case, copies it into a folder of its own beside a
``sibling/`` folder (a user's other work), applies one hostile or careless change and runs the
``fluorocal`` command(s) a user would, each in a subprocess. Per case it records:

- the exit code, and whether stdout/stderr hold a Python traceback (``--debug`` is never passed);
- whether a refusal is one clear line (``fluorocal: error: ...``) naming the file, key or argument;
- whether any file outside the project's output and cache folders (and the command's own ``--out``) was
  created, modified or deleted: the whole case folder, the project's inputs and the sibling included, is
  snapshotted before and after (type, size, mtime, sha256, link target);
- whether code from data ran: payloads that would ``touch`` a canary file;
- for a case that exits 0, whether the result is right: each case states its correct outcome (``refuse``,
  ``ok`` with a check against the clean run's results or the simulator's truth, or ``either``).

Usage: ``python benchmarks/attack.py [--quick] [--only CLASS[,CLASS]] [--list] [--jobs N] [--keep DIR]``.
``--quick`` runs the first case of each class. Targets (issue 13): 0 tracebacks, 0 silent wrong results,
0 files written or deleted outside the output and cache folders, 0 code executed from data.
A full disk is a tmpfs mounted for the case when the process may mount one (root), else RLIMIT_FSIZE
(``EFBIG`` instead of ``ENOSPC``); the run says which.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import hashlib
import json
import os
import re
import resource
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

TRACEBACK = "Traceback (most recent call last)"
UNPRIVILEGED = [
    "setpriv",
    "--bounding-set",
    "-dac_override,-dac_read_search",
    "--inh-caps",
    "-dac_override,-dac_read_search",
]
CANARY = "CANARY"


def _env() -> dict:
    return {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def fluorocal(*args: str) -> list[str]:
    return [sys.executable, "-m", "fluorocal.cli", "--quiet", *map(str, args)]


# --- a case and its folder --------------------------------------------------------------------


@dataclasses.dataclass
class Ctx:
    """One case's folder: ``root/proj`` (the project), ``root/sibling`` (a user's other files)."""

    root: Path
    clean: Path  # the clean run's project (read only)

    @property
    def proj(self) -> Path:
        return self.root / "proj"

    @property
    def cfg(self) -> Path:
        return self.proj / "fluorocal.toml"

    @property
    def canary(self) -> Path:
        return self.root / CANARY

    @property
    def cal(self) -> Path:
        return self.proj / "out" / "calibration.json"

    def frames(self, system: str = "A") -> list[Path]:
        return sorted((self.proj / "frames" / system).glob("*.tif"))

    def edit_cfg(self, old: str, new: str, count: int = 1) -> None:
        text = self.cfg.read_text()
        assert old in text, old
        self.cfg.write_text(text.replace(old, new, count))

    def append_cfg(self, text: str) -> None:
        self.cfg.write_text(self.cfg.read_text() + "\n" + text + "\n")


@dataclasses.dataclass
class Case:
    name: str
    klass: str
    setup: Callable[[Ctx], None]
    commands: Callable[[Ctx], list[list[str]]]
    expect: str = "refuse"  # refuse | ok | either
    hints: tuple[str, ...] = ()  # a refusal must name one of these (file, key, argument)
    check: Callable[[Ctx], str | None] | None = None  # for exit 0: None if the result is right, else why not
    allow: tuple[str, ...] = ()  # further paths (relative to the case folder) the commands may write
    runner: Callable[[Ctx, list[list[str]]], list[tuple[int, str]]] | None = None
    as_nobody: bool = False
    note: str = ""


@dataclasses.dataclass
class Outcome:
    case: Case
    rc: int
    traceback: bool
    message: str
    clear: bool
    wrong: str | None
    outside: list[str]
    code_ran: bool
    seconds: float

    @property
    def weak(self) -> bool:
        return self.rc not in (0,) and not self.clear

    @property
    def failed(self) -> bool:
        return self.traceback or bool(self.wrong) or bool(self.outside) or self.code_ran


# --- snapshot ---------------------------------------------------------------------------------


def snapshot(root: Path) -> dict[str, tuple]:
    """Every entry under ``root`` (symbolic links not followed): kind, size, mtime, sha256 or link target."""
    snap = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = str(p.relative_to(root))
            try:
                st = p.lstat()
            except OSError:
                continue
            if stat.S_ISLNK(st.st_mode):
                snap[rel] = ("link", os.readlink(p))
            elif stat.S_ISDIR(st.st_mode):
                snap[rel] = ("dir",)
            elif not stat.S_ISREG(st.st_mode):  # a FIFO or device: never opened (it would block)
                snap[rel] = ("special", st.st_mode)
            else:
                try:
                    digest = hashlib.sha256(p.read_bytes()).hexdigest()
                except OSError:
                    digest = "unreadable"
                snap[rel] = ("file", st.st_size, st.st_mtime_ns, digest)
    return snap


def changed_outside(before: dict, after: dict, allowed: list[str]) -> list[str]:
    def ok(rel: str) -> bool:
        return any(
            rel == a or rel.startswith(a.rstrip("/") + "/") or (a.endswith("*") and rel.startswith(a[:-1]))
            for a in allowed
        )

    out = []
    for rel in sorted(set(before) | set(after)):
        if before.get(rel) != after.get(rel) and not ok(rel):
            kind = "created" if rel not in before else "deleted" if rel not in after else "modified"
            if kind == "modified" and before[rel][0] == after[rel][0] == "dir":
                continue
            out.append(f"{kind} {rel}")
    return out


# --- running a case ---------------------------------------------------------------------------


def _preexec(nobody: bool, fsize: int | None):
    def f():
        os.setsid()
        if fsize is not None:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))

    return f


def run_cmd(argv: list[str], cwd: Path, *, nobody=False, fsize=None, timeout=900) -> tuple[int, str]:
    if nobody and os.geteuid() == 0:  # root without the capabilities that override permissions: read-only is read-only
        argv = [*UNPRIVILEGED, *argv]
    p = subprocess.run(
        argv,
        cwd=cwd,
        env=_env(),
        capture_output=True,
        text=True,
        errors="replace",
        preexec_fn=_preexec(nobody, fsize),
        timeout=timeout,
    )
    return p.returncode, p.stdout + p.stderr


def default_runner(c: Ctx, commands: list[list[str]], nobody=False) -> list[tuple[int, str]]:
    return [run_cmd(argv, c.proj, nobody=nobody) for argv in commands]


ERROR_LINE = re.compile(r"fluorocal( [a-z]+)*: error: ")


def error_lines(text: str) -> list[str]:
    """The lines of a command's output that are not warnings nor argparse's usage lines."""
    lines, usage = [], False
    for ln in text.splitlines():
        usage = ln.startswith("usage:") or (usage and ln.startswith(" "))
        if ln.strip() and not usage and "warning" not in ln.lower()[:40]:
            lines.append(ln)
    return lines


def judge(case: Case, c: Ctx, results, before, after, seconds) -> Outcome:
    tb = any(TRACEBACK in out for _, out in results)
    rc, out = results[-1]
    lines = error_lines(out)
    message = lines[-1] if lines else ""
    if len(results) > 1:  # a fault, then what follows it: show how each command ended
        message = " / ".join(f"[{r}] {(error_lines(o) or [''])[-1][:90]}" for r, o in results)
    clear = (
        rc == 2
        and len([ln for ln in lines if ERROR_LINE.match(ln)]) == 1
        and ERROR_LINE.match(message) is not None
        and (not case.hints or any(h.lower() in message.lower() for h in case.hints))
    )
    wrong = None
    if rc == 0:
        if case.expect == "refuse":
            wrong = "accepted (exit 0) what must be refused"
        elif case.check is not None:
            wrong = case.check(c)
    elif case.expect == "ok":
        wrong = None  # a refusal of good input is not a silent wrong result; it shows as a weak/failed refusal
    allowed = ["proj/out", "proj/.fluorocal", "proj/.out.fluorocal-*", *case.allow]
    outside = changed_outside(before, after, allowed)
    code_ran = any(p.name.startswith(CANARY) for p in c.root.rglob("*")) or any(
        p.name.startswith(CANARY) for p in c.root.parent.glob("*")
    )
    return Outcome(case, rc, tb, message[:200], clear, wrong, outside, code_ran, seconds)


def run_case(case: Case, base: Path, work: Path, index: int) -> Outcome:
    root = work / f"{index:03d}_{case.name}"
    shutil.copytree(base, root, symlinks=True)
    c = Ctx(root, base / "proj")
    case.setup(c)
    if case.as_nobody:
        _readonly(case, c)
    before = snapshot(root)
    t = time.perf_counter()
    commands = case.commands(c)
    try:
        if case.runner is not None:
            results = case.runner(c, commands)
        else:
            results = default_runner(c, commands, nobody=case.as_nobody)
    except subprocess.TimeoutExpired:
        results = [(124, "timed out")]
    seconds = time.perf_counter() - t
    after = snapshot(root)
    return judge(case, c, results, before, after, seconds)


def _readonly(case: Case, c: Ctx) -> None:
    for rel in getattr(case, "_readonly", ()):
        p = c.root / rel
        mode = stat.S_IMODE(p.stat().st_mode)
        p.chmod(mode & ~0o222)


# --- result checks ----------------------------------------------------------------------------


def _csv_array(path: Path) -> np.ndarray:
    return np.genfromtxt(path, delimiter=",", skip_header=1)


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


def clean_and_no_leftovers(c: Ctx) -> str | None:
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


# --- building the project ---------------------------------------------------------------------


def make_base(work: Path) -> Path:
    base = work / "base"
    proj = base / "proj"
    subprocess.run(
        fluorocal("simulate", proj, "--frames", "4", "--systems", "2", "--image-size", "512", "512", "--seed", "3"),
        check=True,
        env=_env(),
        capture_output=True,
    )
    (proj / "montage.png").unlink()
    t = time.process_time()
    r = subprocess.run(fluorocal("run", proj / "fluorocal.toml"), env=_env(), capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(f"the clean run failed: {r.stderr}")
    cpu = resource.getrusage(resource.RUSAGE_CHILDREN)
    (base / "sibling" / "work").mkdir(parents=True)
    (base / "sibling" / "precious.txt").write_text("a user's file beside the project\n")
    (base / "sibling" / "work" / "notes.txt").write_text("more of the user's work\n")
    print(
        f"clean project: {proj} (cold run: {cpu.ru_utime + cpu.ru_stime:.1f} cpu-s in children, "
        f"{time.process_time() - t:.1f} s own)"
    )
    return base


def check_clean_against_truth(base: Path) -> str:
    truth = json.loads((base / "proj" / "truth.json").read_text())
    cal = json.loads((base / "proj" / "out" / "calibration.json").read_text())
    parts = []
    for s in truth["systems"]:
        iop = _find_iop(cal, s["name"])
        if iop is not None:
            parts.append(
                f"{s['name']}: principal point off truth by "
                f"{np.hypot(iop[0] - s['iop_px'][0], iop[1] - s['iop_px'][1]):.2f} px, "
                f"c by {abs(iop[2] - s['iop_px'][2]):.1f} px"
            )
    return "; ".join(parts) or "no IOP found in calibration.json"


def _find_iop(cal: dict, name: str):
    systems = cal.get("systems")
    items = systems.items() if isinstance(systems, dict) else ((s.get("name"), s) for s in systems or [])
    for n, s in items:
        if n == name:
            for key in ("iop_px", "iop"):
                if key in s:
                    v = s[key]
                    return [v[k] for k in ("xp", "yp", "c")] if isinstance(v, dict) else v
    return None


# --- the cases ----------------------------------------------------------------------------------


def run_cfg(c: Ctx) -> list[list[str]]:
    return [fluorocal("run", c.cfg)]


def _set_key(c: Ctx, key: str, value: str, system: int = 0) -> None:
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


def _phantom_rows(c: Ctx) -> list[list[str]]:
    return [ln.split(",") for ln in c.proj.joinpath("phantom.csv").read_text().splitlines()]


def _write_rows(c: Ctx, rows, name="phantom.csv") -> None:
    c.proj.joinpath(name).write_text("\n".join(",".join(r) for r in rows) + "\n")


def _scale_phantom(factor: float):
    def f(c: Ctx) -> None:
        rows = _phantom_rows(c)
        for r in rows[1:]:
            for j in (1, 2, 3, 4):
                r[j] = repr(float(r[j]) * factor)
        _write_rows(c, rows)

    return f


def _phantom_cell(row: int, col: int, value: str):
    def f(c: Ctx) -> None:
        rows = _phantom_rows(c)
        rows[row][col] = value
        _write_rows(c, rows)

    return f


def _write_bytes(rel: str, data: bytes):
    def f(c: Ctx) -> None:
        p = c.proj / rel
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)

    return f


def _make_dir(rel: str):
    def f(c: Ctx) -> None:
        p = c.proj / rel
        p.unlink()
        p.mkdir()

    return f


def _symlink(rel: str, target: str):
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


def _tiff(rel: str, arr: np.ndarray, **kw):
    def f(c: Ctx) -> None:
        import tifffile

        p = c.proj / rel
        if p.exists():
            p.unlink()
        tifffile.imwrite(p, arr, **kw)

    return f


def _chain(*fs):
    def f(c: Ctx) -> None:
        for g in fs:
            g(c)

    return f


def _cfg_edit(old: str, new: str):
    return lambda c: c.edit_cfg(old, new)


def _cfg_key(key: str, value: str, system: int = 0):
    return lambda c: _set_key(c, key, value, system)


def _cfg_append(text: str):
    return lambda c: c.append_cfg(text)


def _touch_cmd(c: Ctx) -> str:
    return f"touch {c.canary}"


# --- cache tampering helpers ------------------------------------------------------------------


def _entries(c: Ctx, stage: str) -> list[Path]:
    return sorted(p for p in (c.proj / ".fluorocal" / stage).iterdir() if p.is_dir() and not p.name.startswith("."))


def _rehash(entry: Path) -> None:
    """Recompute an entry's checksums, as an attacker who knows the format would."""
    m = json.loads((entry / "manifest.json").read_text())
    if (entry / "arrays.npz").is_file():
        m.setdefault("files", {})["arrays.npz"] = hashlib.sha256((entry / "arrays.npz").read_bytes()).hexdigest()
    text = json.dumps(m, indent=1)
    (entry / "manifest.json").write_text(text)
    (entry / "manifest.sha256").write_text(hashlib.sha256(text.encode()).hexdigest() + "\n")


def _manifest_payload(stage: str, payload: Callable[[Ctx], dict], rehash: bool = True, which: int = 0):
    def f(c: Ctx) -> None:
        entry = _entries(c, stage)[which]
        m = json.loads((entry / "manifest.json").read_text())
        m["artifact"] = payload(c)
        (entry / "manifest.json").write_text(json.dumps(m, indent=1))
        if rehash:
            _rehash(entry)

    return f


def _pickle_npz(stage: str):
    """arrays.npz replaced by one holding a pickled object whose unpickling would touch the canary."""

    def f(c: Ctx) -> None:
        entry = _entries(c, stage)[0]
        with np.load(entry / "arrays.npz") as z:
            arrays = {k: z[k] for k in z.files}
        key = next(iter(arrays))
        obj = np.empty(1, dtype=object)
        obj[0] = _Payload(_touch_cmd(c))
        arrays[key] = obj
        np.savez(entry / "arrays.npz", **arrays)
        _rehash(entry)

    return f


class _Payload:
    def __init__(self, cmd: str):
        self.cmd = cmd

    def __reduce__(self):
        return (os.system, (self.cmd,))


def _entry_edit(stage: str, fn: Callable[[Path], None], which: int = 0):
    def f(c: Ctx) -> None:
        fn(_entries(c, stage)[which])

    return f


def _flip_byte(name: str, offset_frac: float = 0.5):
    def fn(entry: Path) -> None:
        p = entry / name
        b = bytearray(p.read_bytes())
        b[int(len(b) * offset_frac)] ^= 0x40
        p.write_bytes(bytes(b))

    return fn


def _truncate(name: str, frac: float = 0.5):
    def fn(entry: Path) -> None:
        p = entry / name
        p.write_bytes(p.read_bytes()[: int(p.stat().st_size * frac)])

    return fn


def _edit_array(entry: Path) -> None:
    """An array value changed and every checksum recomputed: a forger who knows the format."""
    with np.load(entry / "arrays.npz") as z:
        arrays = {k: z[k] for k in z.files}
    k = next(k for k in arrays if arrays[k].dtype.kind == "f" and arrays[k].size)
    arrays[k] = arrays[k] + 1.0
    np.savez(entry / "arrays.npz", **arrays)
    _rehash(entry)


def _edit_summary(entry: Path) -> None:
    m = json.loads((entry / "manifest.json").read_text())
    m["summary"] = "edited by hand"
    (entry / "manifest.json").write_text(json.dumps(m, indent=1))


# --- runners for faults -------------------------------------------------------------------------


def kill_when(pattern: str, delay: float = 0.0, timeout: float = 600.0):
    """Start the first command, SIGKILL it when ``pattern`` (a glob under the project) appears, then run the rest."""

    def runner(c: Ctx, commands):
        p = subprocess.Popen(
            commands[0],
            cwd=c.proj,
            env=_env(),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=os.setsid,
        )
        t = time.perf_counter()
        while p.poll() is None and time.perf_counter() - t < timeout:
            if pattern == "" or any(c.proj.glob(pattern)):
                time.sleep(delay)
                break
            time.sleep(0.01)
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        return [run_cmd(argv, c.proj) for argv in commands[1:]]

    return runner


def kill_after(seconds: float):
    def runner(c: Ctx, commands):
        p = subprocess.Popen(
            commands[0],
            cwd=c.proj,
            env=_env(),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=os.setsid,
        )
        try:
            p.wait(seconds)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        return [run_cmd(argv, c.proj) for argv in commands[1:]]

    return runner


def concurrently(n_first: int):
    """The first ``n_first`` commands at once; then the rest one by one. All must exit 0."""

    def runner(c: Ctx, commands):
        procs = [
            subprocess.Popen(a, cwd=c.proj, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            for a in commands[:n_first]
        ]
        results = []
        for p in procs:
            out, _ = p.communicate()
            results.append((p.returncode, out))
        bad = [r for r in results if r[0] != 0]
        results += [run_cmd(a, c.proj) for a in commands[n_first:]]
        return bad + results[-1:] if bad else results

    return runner


def _can_mount() -> bool:
    if os.geteuid() != 0 or not shutil.which("mount"):
        return False
    with tempfile.TemporaryDirectory() as d:
        ok = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", d], capture_output=True).returncode == 0
        if ok:
            subprocess.run(["umount", d], check=True)
    return ok


CAN_MOUNT = _can_mount()


def full_disk(free_kb: int):
    """The project on a tmpfs with ``free_kb`` free: the first command fills it; the disk grown, the rest run.

    Without mount rights: RLIMIT_FSIZE of ``free_kb`` on the first command (EFBIG rather than ENOSPC).
    """

    def runner(c: Ctx, commands):
        if not CAN_MOUNT:
            first = [run_cmd(commands[0], c.proj, fsize=free_kb * 1024)]
            return first + [run_cmd(a, c.proj) for a in commands[1:]]
        keep = c.root / "proj.keep"
        os.rename(c.proj, keep)
        c.proj.mkdir()
        subprocess.run(["mount", "-t", "tmpfs", "-o", "size=400m", "tmpfs", c.proj], check=True)
        try:
            for p in keep.iterdir():
                shutil.move(p, c.proj / p.name)
            keep.rmdir()
            st = os.statvfs(c.proj)
            used_kb = (st.f_blocks - st.f_bfree) * st.f_frsize // 1024
            subprocess.run(["mount", "-o", f"remount,size={used_kb + free_kb}k", c.proj], check=True)
            first = run_cmd(commands[0], c.proj)
            subprocess.run(["mount", "-o", "remount,size=400m", c.proj], check=True)
            rest = [run_cmd(a, c.proj) for a in commands[1:]]
            # copied off the tmpfs before unmounting, so the snapshot and the result check see what the runs left
            shutil.copytree(c.proj, keep, symlinks=True)
        finally:
            subprocess.run(["umount", "-l", c.proj])
        c.proj.rmdir()
        os.rename(keep, c.proj)
        return [first] + rest

    return runner


def first_refused_clearly(hints: tuple[str, ...]):
    """For a fault then a rerun: the fault's command must fail with a clear line; the rerun's result is checked."""

    def check(c: Ctx) -> str | None:
        return clean_and_no_leftovers(c)

    return check


# --- the catalogue --------------------------------------------------------------------------------


def all_cases() -> list[Case]:
    K: list[Case] = []

    def add(name, klass, setup, commands=run_cfg, expect="refuse", hints=(), check=None, allow=(), **kw):
        if expect in ("ok", "either") and check is None:
            check = same_as_clean
        K.append(Case(name, klass, setup, commands, expect, tuple(hints), check, tuple(allow), **kw))

    nothing = lambda c: None  # noqa: E731

    # ---- config (fluorocal run) ----
    add("config_missing", "config", nothing, lambda c: [fluorocal("run", c.proj / "nope.toml")], hints=("nope.toml",))
    add("config_empty", "config", _write_bytes("fluorocal.toml", b""), hints=("phantom",))
    add("config_binary", "config", _write_bytes("fluorocal.toml", bytes(range(256)) * 8), hints=("fluorocal.toml",))
    add(
        "config_latin1",
        "config",
        lambda c: c.cfg.write_bytes(c.cfg.read_bytes() + "# café\n".encode("latin-1")),
        hints=("fluorocal.toml", "UTF-8"),
    )
    add(
        "config_utf16",
        "config",
        lambda c: c.cfg.write_bytes(c.cfg.read_text().encode("utf-16")),
        hints=("fluorocal.toml",),
    )
    add("config_bom", "config", lambda c: c.cfg.write_bytes(b"\xef\xbb\xbf" + c.cfg.read_bytes()), expect="ok")
    add("config_crlf", "config", lambda c: c.cfg.write_bytes(c.cfg.read_bytes().replace(b"\n", b"\r\n")), expect="ok")
    add("config_is_directory", "config", _make_dir("fluorocal.toml"), hints=("fluorocal.toml",))
    add("config_toml_syntax", "config", _cfg_append("[output\ndir = "), hints=("fluorocal.toml", "TOML"))
    add(
        "config_huge",
        "config",
        lambda c: c.cfg.write_text(c.cfg.read_text() + "# " + "x" * 20_000_000 + "\n"),
        expect="ok",
        note="a 20 MB comment is still a valid config",
    )
    add("config_deep_nesting", "config", _cfg_append("x = " + "[" * 5000 + "]" * 5000), hints=("fluorocal.toml",))
    add(
        "config_nul_byte",
        "config",
        lambda c: c.cfg.write_bytes(c.cfg.read_bytes() + b"\x00\n"),
        hints=("fluorocal.toml",),
    )
    add(
        "config_symlink_outside",
        "config",
        _chain(
            lambda c: shutil.copy(c.cfg, c.root / "sibling" / "elsewhere.toml"),
            _symlink("fluorocal.toml", "sibling/elsewhere.toml"),
        ),
        hints=("phantom",),
        note="the config's folder is where the link points: its relative paths resolve there",
    )
    add(
        "no_phantom_table",
        "config",
        lambda c: c.cfg.write_text(c.cfg.read_text().replace("[phantom]", "[phantomx]")),
        hints=("phantom",),
    )
    add("unknown_top_key", "config", _cfg_append("[outputs]\ndir = 'x'"), hints=("outputs",))
    add(
        "unknown_system_key",
        "config",
        _cfg_key("source_image_distance", "1100\npixelpitch = 0.5"),
        hints=("pixelpitch",),
    )
    add(
        "systems_not_table",
        "config",
        lambda c: c.cfg.write_text(c.cfg.read_text().split("[[systems]]")[0] + "systems = 3\n[output]\ndir = 'out'\n"),
        hints=("systems",),
    )
    add(
        "three_systems",
        "config",
        lambda c: c.cfg.write_text(
            c.cfg.read_text().replace(
                "[calibration]",
                "[[systems]]\nname = 'C'\nframes = 'frames/A/*.tif'\n"
                "source_image_distance = 1100\npixel_pitch = 0.5\n\n[calibration]",
            )
        ),
        hints=("systems",),
    )
    for key in ("source_image_distance", "pixel_pitch"):
        for label, value in (
            ("nan", "nan"),
            ("inf", "inf"),
            ("neg_inf", "-inf"),
            ("negative", "-1.0"),
            ("zero", "0"),
            ("huge", "1e300"),
            ("string", '"1mm"'),
            ("bool", "true"),
            ("array", "[1, 2]"),
            ("missing", None),
        ):
            if value is None:
                setup = (
                    _cfg_key(key, "1", 0)
                    if False
                    else (
                        lambda c, key=key: c.cfg.write_text(
                            "\n".join(
                                ln
                                for ln in c.cfg.read_text().splitlines()
                                if not ln.startswith(key + " ") or 'name = "B"' in ln
                            )
                            + "\n"
                        )
                    )
                )
            else:
                setup = _cfg_key(key, value)
            add(f"{key}_{label}", "config", setup, hints=(key,))
    add("pixel_pitch_tiny", "config", _cfg_key("pixel_pitch", "0.0005"), hints=("pixel_pitch",))
    add("sid_in_metres", "config", _cfg_key("source_image_distance", "1.1"), hints=("source_image_distance",))
    for label, value in (
        ("missing_file", '"nope.csv"'),
        ("directory", '"frames"'),
        ("int", "3"),
        ("absolute_etc", '"/etc/passwd"'),
        ("outside", '"../sibling/precious.txt"'),
        ("empty_string", '""'),
        ("nul", '"phan\\u0000tom.csv"'),
    ):
        add(
            f"phantom_file_{label}",
            "config",
            _cfg_edit('file = "phantom.csv"', f"file = {value}"),
            hints=("phantom", "file"),
        )
    add(
        "lattice_bad",
        "config",
        _cfg_append("").__class__ and _cfg_edit('file = "phantom.csv"', 'lattice = "tri"\npitch = 5'),
        hints=("lattice",),
    )
    add("pitch_nan", "config", _cfg_edit('file = "phantom.csv"', 'lattice = "hex"\npitch = nan'), hints=("pitch",))
    for label, value in (
        ("no_match", '"frames/A/*.dcm"'),
        ("matches_folder", '"frames/*"'),
        ("empty_list", "[]"),
        ("list_missing", '["frames/A/nope.tif"]'),
        ("list_folder", '["frames/A"]'),
        ("int", "7"),
        ("etc", '"/etc/host*"'),
        ("nul", '"frames/A/\\u0000*.tif"'),
        ("list_of_int", "[1, 2]"),
    ):
        add(f"frames_{label}", "config", _cfg_key("frames", value), hints=("frames", "/etc/"))
    add(
        "frames_outside_project",
        "config",
        _chain(
            lambda c: shutil.copytree(c.proj / "frames" / "A", c.root / "sibling" / "A"),
            _cfg_key("frames", '"../sibling/A/*.tif"'),
        ),
        expect="ok",
        note="reading frames from anywhere is the user's choice; nothing may be written there",
    )
    for label, value in (
        ("traversal", '"B/../../../escaped"'),
        ("absolute", '"/tmp/escaped"'),
        ("dotdot", '".."'),
        ("empty", '""'),
        ("slash", '"a/b"'),
        ("long", '"' + "a" * 300 + '"'),
        ("int", "1"),
        ("hidden", '".hidden"'),
        ("nul", '"A\\u0000"'),
        ("backslash", '"..\\\\..\\\\x"'),
        ("newline", '"A\\nB"'),
    ):
        add(f"system_name_{label}", "names", _cfg_key("name", value, 1), hints=("name",))
    add("system_name_duplicate", "names", _cfg_key("name", '"A"', 1), hints=("name",))
    add(
        "system_name_unicode",
        "names",
        _cfg_key("name", '"Ä"', 1),
        expect="either",
        check=lambda c: None if (c.proj / "out" / "field_Ä.npz").is_file() else "no field_Ä.npz",
        hints=("name",),
        note="either refused as not a safe file name or calibrated under that name",
    )
    for label, value in (
        ("dot", '"."'),
        ("dotdot", '".."'),
        ("file", '"phantom.csv"'),
        ("frames", '"frames"'),
        ("cache", '".fluorocal"'),
        ("int", "1"),
        ("nul", '"out\\u0000"'),
        ("etc_file", '"/etc/passwd"'),
        ("proc", '"/proc/self"'),
    ):
        add(
            f"output_dir_{label}",
            "config",
            _cfg_append(f"[output]\ndir = {value}")
            if False
            else (lambda c, v=value: c.cfg.write_text(c.cfg.read_text().replace('dir = "out"', f"dir = {v}"))),
            hints=("output", "dir", "phantom.csv", "folder"),
        )
    add(
        "output_dir_sibling",
        "config",
        lambda c: c.cfg.write_text(c.cfg.read_text().replace('dir = "out"', 'dir = "../sibling"')),
        expect="either",
        allow=("sibling",),
        hints=("output",),
        check=lambda c: (
            sibling_intact(c) or (None if (c.root / "sibling" / "calibration.json").is_file() else "no calibration")
        ),
        note="an [output] dir outside the project is the user's choice; the sibling's own files must survive",
    )
    for label, value in (
        ("dot", '"."'),
        ("dotdot", '".."'),
        ("file", '"phantom.csv"'),
        ("frames", '"frames"'),
        ("out", '"out"'),
        ("sibling", '"../sibling"'),
        ("int", "1"),
        ("nul", '"c\\u0000"'),
        ("etc", '"/etc"'),
    ):
        add(f"cache_dir_{label}", "config", _cfg_append(f"[cache]\ndir = {value}"), hints=("cache", "dir", "folder"))
    add("scheme_unknown", "config", _cfg_edit('scheme = "knn+iop+smooth"', 'scheme = "magic"'), hints=("scheme",))
    add("scheme_int", "config", _cfg_edit('scheme = "knn+iop+smooth"', "scheme = 3"), hints=("scheme",))
    add("compute_scheduler", "config", _cfg_append("[compute]\nscheduler = 'tcp://evil:8786'"), hints=("scheduler",))
    for label, value in (("neg", "-1"), ("zero", "0"), ("str", '"x"'), ("float", "1.5")):
        add(f"compute_jobs_{label}", "config", _cfg_append(f"[compute]\njobs = {value}"), hints=("jobs",))
    add(
        "compute_jobs_huge",
        "config",
        _cfg_append("[compute]\njobs = 100000000"),
        expect="either",
        note="DEBATABLE: accepted; the pool starts min(jobs, frames to compute) workers, so the number is bounded "
        "by the work, not refused",
    )
    add("compute_threads_zero", "config", _cfg_append("[compute]\nthreads = 0"), hints=("threads",))
    add("stage_unknown_key", "config", _cfg_append("[detect]\nbogus = 1"), hints=("bogus",))
    add("stage_owned_key", "config", _cfg_append("[learn]\nsmooth = true"), hints=("smooth",))
    add("stage_owned_label_pitch", "config", _cfg_append("[label]\npixel_pitch_mm = 0.5"), hints=("pixel_pitch_mm",))
    add("stage_param_wrong_type", "config", _cfg_append("[adjust]\nnu = 'four'"), hints=("nu",))
    add("stage_param_nan", "config", _cfg_append("[adjust]\nnu = nan"), hints=("nu",))
    add("stage_param_negative", "config", _cfg_append("[adjust]\nnu = -4"), hints=("nu",))
    add("stage_table_not_table", "config", _cfg_append("detect = 3"), hints=("detect",))
    add(
        "orientations_wrong_type",
        "config",
        _cfg_key("frames", '"frames/A/*.tif"\norientations = 5'),
        hints=("orientations",),
    )
    add(
        "orientations_traversal_name",
        "names",
        _cfg_key(
            "frames",
            '"frames/A/*.tif"\norientations = [{name = "../../x", frames = "frames/A/*.tif", orbit = 0, tilt = 0}]',
        ),
        hints=("orientation", "name"),
    )
    add("seeds_missing", "config", _cfg_key("frames", '"frames/A/*.tif"\nseeds = "nope.csv"'), hints=("seeds",))
    add(
        "seeds_binary",
        "config",
        _chain(
            _write_bytes("seeds.csv", os.urandom(3000)), _cfg_key("frames", '"frames/A/*.tif"\nseeds = "seeds.csv"')
        ),
        hints=("seeds",),
    )

    # ---- read-only / permissions (as the unprivileged user 'nobody') ----
    def ro(name, rel, expect="refuse", hints=(), commands=run_cfg, **kw):
        add(name, "permissions", nothing, commands, expect=expect, hints=hints, as_nobody=True, **kw)
        K[-1]._readonly = rel

    ro("readonly_project", ("proj",), hints=("not writable", "permission", "proj"))
    ro("readonly_output", ("proj/out",), hints=("out",), expect="either")
    ro("readonly_cache", ("proj/.fluorocal",), hints=(".fluorocal", "cache"))
    ro("readonly_cache_stage", ("proj/.fluorocal/label",), hints=("label", "permission"), expect="either")
    ro("readonly_frame", (), hints=("frame_000",))
    K[-1].setup = lambda c: (c.frames("A")[0]).chmod(0)
    ro("unreadable_phantom", (), hints=("phantom",))
    K[-1].setup = lambda c: (c.proj / "phantom.csv").chmod(0)
    ro("unreadable_config", (), hints=("fluorocal.toml",))
    K[-1].setup = lambda c: c.cfg.chmod(0)
    ro("unreadable_cache_entry", (), expect="either")
    K[-1].setup = lambda c: (_entries(c, "label")[0] / "manifest.json").chmod(0)
    ro(
        "readonly_inspect",
        ("proj", "proj/.fluorocal"),
        expect="ok",
        commands=lambda c: [fluorocal("inspect", c.cfg)],
        check=lambda c: None,
    )
    ro(
        "readonly_undistort_out",
        ("proj",),
        hints=("und", "permission", "writable"),
        commands=lambda c: [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "und", c.frames("A")[0])],
    )

    # ---- phantom CSV ----
    P = "phantom"
    add("phantom_empty", P, _write_bytes("phantom.csv", b""), hints=("phantom.csv",))
    add("phantom_header_only", P, _write_bytes("phantom.csv", b"id,x,y,z,diameter,role\n"), hints=("phantom.csv",))
    add("phantom_binary", P, _write_bytes("phantom.csv", os.urandom(5000)), hints=("phantom.csv",))
    add(
        "phantom_latin1",
        P,
        lambda c: (c.proj / "phantom.csv").write_bytes(
            (c.proj / "phantom.csv").read_bytes() + "999,1,2,3,3.5,é\n".encode("latin-1")
        ),
        hints=("phantom.csv",),
    )
    add(
        "phantom_bom",
        P,
        lambda c: (c.proj / "phantom.csv").write_bytes(b"\xef\xbb\xbf" + (c.proj / "phantom.csv").read_bytes()),
        expect="ok",
    )
    add(
        "phantom_crlf",
        P,
        lambda c: (c.proj / "phantom.csv").write_bytes((c.proj / "phantom.csv").read_bytes().replace(b"\n", b"\r\n")),
        expect="ok",
    )
    add("phantom_metres", P, _scale_phantom(0.001), hints=("metres", "phantom.csv"))
    add("phantom_inches", P, _scale_phantom(1 / 25.4), hints=("inches", "phantom.csv"))
    add(
        "phantom_cm",
        P,
        _scale_phantom(0.1),
        hints=("phantom.csv", "cm", "centimetres"),
        note="a cube of 12 instead of 120: no unit of the three named, but as wrong",
    )
    add("phantom_x1000", P, _scale_phantom(1000.0), hints=("phantom.csv",))
    for label, value, col in (
        ("nan_x", "nan", 1),
        ("inf_y", "inf", 2),
        ("neginf_z", "-inf", 3),
        ("text_x", "abc", 1),
        ("empty_z", "", 3),
        ("neg_diameter", "-3.5", 4),
        ("zero_diameter", "0", 4),
        ("nan_diameter", "nan", 4),
        ("huge_x", "1e300", 1),
        ("id_text", "bead", 0),
        ("id_float", "1.5", 0),
        ("id_negative", "-1", 0),
        ("id_huge", "99999999999999999999999", 0),
        ("role_garbage", "evil", 5),
    ):
        add(
            f"phantom_{label}",
            P,
            _phantom_cell(3, col, value),
            hints=("phantom.csv",),
            **({"expect": "either"} if label in ("id_negative", "role_garbage") else {}),
            **(
                {
                    "expect": "either",
                    "check": lambda c: same_as_clean(c, tol_mm=0.05),
                    "note": "DEBATABLE: 'nan' reads as an empty cell, a diameter not given (the column is optional)",
                }
                if label == "nan_diameter"
                else {}
            ),
            # the bead of id 2 (data row 3) renamed -1: the same points, listed first
            **({"check": lambda c: same_as_clean(c, renamed={-1: 2})} if label == "id_negative" else {}),
        )
    add(
        "phantom_missing_column",
        P,
        lambda c: _write_rows(c, [r[:3] + r[4:] for r in _phantom_rows(c)]),
        hints=("phantom.csv", "z"),
    )
    add(
        "phantom_extra_column",
        P,
        lambda c: _write_rows(c, [r + (["extra"] if i == 0 else ["1"]) for i, r in enumerate(_phantom_rows(c))]),
        expect="either",
    )
    add(
        "phantom_short_row",
        P,
        lambda c: _write_rows(c, [r if i != 5 else r[:2] for i, r in enumerate(_phantom_rows(c))]),
        hints=("phantom.csv",),
    )
    add("phantom_duplicate_id", P, _phantom_cell(4, 0, "2"), hints=("phantom.csv", "id"))
    add(
        "phantom_duplicate_point",
        P,
        lambda c: _write_rows(c, (lambda r: r[:4] + [[r[4][0]] + r[3][1:]] + r[5:])(_phantom_rows(c))),
        hints=("phantom.csv",),
    )
    add("phantom_one_bead", P, lambda c: _write_rows(c, _phantom_rows(c)[:2]), hints=("phantom.csv",))
    add(
        "phantom_semicolons",
        P,
        lambda c: (c.proj / "phantom.csv").write_text((c.proj / "phantom.csv").read_text().replace(",", ";")),
        hints=("phantom.csv",),
    )
    add(
        "phantom_huge_rows",
        P,
        lambda c: (c.proj / "phantom.csv").write_text(
            "id,x,y,z,diameter,role\n" + "".join(f"{i},{i % 1000}.5,{i // 1000}.25,0,3.5,\n" for i in range(2_000_000))
        ),
        hints=("phantom.csv",),
    )
    add(
        "phantom_long_line",
        P,
        lambda c: (c.proj / "phantom.csv").write_text(
            (c.proj / "phantom.csv").read_text() + "1," + "9" * 10_000_000 + ",0,0,3.5,\n"
        ),
        hints=("phantom.csv",),
    )
    add("phantom_directory", P, _make_dir("phantom.csv"), hints=("phantom",))
    add("phantom_symlink_etc", P, _symlink("phantom.csv", "/etc/passwd"), hints=("phantom",))
    add(
        "phantom_symlink_loop",
        P,
        lambda c: ((c.proj / "phantom.csv").unlink(), (c.proj / "phantom.csv").symlink_to(c.proj / "phantom.csv")),
        hints=("phantom",),
    )
    add(
        "phantom_fifo",
        P,
        lambda c: ((c.proj / "phantom.csv").unlink(), os.mkfifo(c.proj / "phantom.csv")),
        hints=("phantom",),
    )
    add(
        "phantom_quoted",
        P,
        lambda c: _write_rows(c, [[f'"{v}"' for v in r] for r in _phantom_rows(c)]),
        expect="either",
    )
    add(
        "phantom_formula_injection",
        P,
        _phantom_cell(3, 5, "=cmd|' /C calc'!A0"),
        expect="either",
        hints=("phantom.csv", "role"),
    )

    # ---- frames ----
    F = "frames"
    rng = np.random.default_rng(0)
    add("frame_empty_file", F, _write_bytes("frames/A/frame_001.tif", b""), hints=("frame_001",))
    add(
        "frame_truncated",
        F,
        lambda c: c.frames("A")[1].write_bytes(c.frames("A")[1].read_bytes()[:3000]),
        hints=("frame_001",),
    )
    add("frame_random_bytes", F, _write_bytes("frames/A/frame_001.tif", os.urandom(80_000)), hints=("frame_001",))
    add(
        "frame_bitflip_header",
        F,
        lambda c: c.frames("A")[1].write_bytes(b"II*\x00\xff\xff\xff\x7f" + c.frames("A")[1].read_bytes()[8:]),
        hints=("frame_001",),
    )
    add("frame_1x1", F, _tiff("frames/A/frame_001.tif", np.full((1, 1), 1000, np.uint16)), hints=("frame_001",))
    add("frame_3x3", F, _tiff("frames/A/frame_001.tif", np.full((3, 3), 1000, np.uint16)), hints=("frame_001",))
    add(
        "frame_other_size",
        F,
        _tiff("frames/A/frame_001.tif", np.full((300, 400), 1000, np.uint16)),
        hints=("frame_001", "size"),
    )
    add(
        "frame_all_black",
        F,
        _tiff("frames/A/frame_001.tif", np.zeros((512, 512), np.uint16)),
        expect="either",
        check=lambda c: None,
        hints=("frame_001", "label"),
        note="a blank frame: excluded with its reason or refused",
    )
    add(
        "frame_all_white",
        F,
        _tiff("frames/A/frame_001.tif", np.full((512, 512), 65535, np.uint16)),
        expect="either",
        check=lambda c: None,
        hints=("frame_001", "label"),
    )
    add(
        "frame_noise",
        F,
        _tiff("frames/A/frame_001.tif", rng.integers(0, 4096, (512, 512)).astype(np.uint16)),
        expect="either",
        check=lambda c: None,
        hints=("frame_001", "label"),
    )
    add(
        "frame_float_nan",
        F,
        _tiff("frames/A/frame_001.tif", np.full((512, 512), np.nan, np.float32)),
        hints=("frame_001",),
    )
    add(
        "frame_float_inf",
        F,
        lambda c: _tiff("frames/A/frame_001.tif", _with_inf(c))(c),
        hints=("frame_001",),
        expect="either",
        check=lambda c: None,
    )
    add(
        "frame_rgb",
        F,
        lambda c: _tiff("frames/A/frame_001.tif", np.repeat(_read_frame(c.frames("A")[1])[..., None], 3, 2))(c),
        expect="either",
        check=lambda c: None,
        hints=("frame_001",),
    )
    add(
        "frame_8bit",
        F,
        lambda c: _tiff("frames/A/frame_001.tif", (_read_frame(c.frames("A")[1]) // 16).astype(np.uint8))(c),
        expect="either",
        check=lambda c: None,
    )
    add(
        "frame_multipage_in_B",
        "pairing",
        lambda c: _tiff("frames/B/frame_001.tif", np.stack([_read_frame(c.frames("B")[1])] * 2))(c),
        hints=("frame", "B"),
    )
    add("frame_missing_in_B", "pairing", lambda c: c.frames("B")[1].unlink(), hints=("frame", "B"))
    add(
        "frame_extra_in_A",
        "pairing",
        lambda c: shutil.copy(c.frames("A")[1], c.proj / "frames" / "A" / "frame_004.tif"),
        hints=("frame", "A"),
    )
    add(
        "frame_missing_in_B_and_extra",
        "pairing",
        _chain(
            lambda c: c.frames("B")[0].unlink(),
            lambda c: shutil.copy(c.frames("B")[1], c.proj / "frames" / "B" / "frame_009.tif"),
        ),
        expect="either",
        check=lambda c: None,
        note="equal counts with the names shifted: pairing is by sorted order (README); debatable",
    )
    add("frame_B_all_missing", "pairing", lambda c: [p.unlink() for p in c.frames("B")], hints=("frames", "B"))
    add("frame_directory", F, _make_dir("frames/A/frame_001.tif"), hints=("frame",))
    add(
        "frame_symlink_outside",
        F,
        lambda c: (
            shutil.copy(c.frames("A")[1], c.root / "sibling" / "f.tif"),
            _symlink("frames/A/frame_001.tif", "sibling/f.tif")(c),
        ),
        expect="ok",
        note="a frame linked from elsewhere is read, nothing written there",
    )
    add("frame_symlink_dangling", F, _symlink("frames/A/frame_001.tif", "sibling/nope.tif"), hints=("frame_001",))
    add("frame_symlink_devzero", F, _symlink("frames/A/frame_001.tif", "/dev/zero"), hints=("frame_001",))
    add(
        "frame_duplicate_content",
        F,
        lambda c: shutil.copy(c.frames("A")[0], c.frames("A")[1]),
        expect="either",
        check=lambda c: None,
        hints=("frame",),
    )
    add("frame_png_named_tif", F, lambda c: _png(c.frames("A")[1]), expect="either", check=same_as_clean)
    add(
        "frame_decompression_bomb",
        F,
        _tiff("frames/A/frame_001.tif", np.zeros((20000, 20000), np.uint16), compression="zlib"),
        hints=("frame_001", "size"),
    )
    add("frame_huge_header", F, lambda c: _huge_header_tiff(c.frames("A")[1]), hints=("frame_001",))
    add("frame_zero_width", F, _tiff("frames/A/frame_001.tif", np.zeros((0, 512), np.uint16)), hints=("frame_001",))
    add(
        "frame_name_spaces_unicode",
        F,
        lambda c: [p.rename(p.with_name(f"ä b {p.name}")) for p in c.frames("A")],
        expect="ok",
        note="names with spaces and umlauts are fine",
    )

    # ---- calibration files (undistort / inspect / export) ----
    C = "calibration"

    def und(*extra, out="und", system="A"):
        return lambda c: [
            fluorocal("undistort", c.cal, "--system", system, "--out", c.proj / out, *extra, c.frames("A")[0])
        ]

    def on_cal(cmd):
        if cmd == "undistort":
            return und()
        if cmd == "inspect":
            return lambda c: [fluorocal("inspect", c.cal, "--out", c.proj / "insp")]
        return lambda c: [fluorocal("export", "--format", "opencv", "--out", c.proj / "exp", c.cal)]

    cal_allow = ("proj/und", "proj/insp", "proj/exp")

    def cal_json(fn):
        def f(c: Ctx) -> None:
            d = json.loads(c.cal.read_text())
            r = fn(d, c)
            c.cal.write_text(json.dumps(d if r is None else r))

        return f

    def field_npz(fn, name="field_A.npz"):
        def f(c: Ctx) -> None:
            p = c.proj / "out" / name
            with np.load(p) as z:
                arrays = {k: z[k] for k in z.files}
            fn(arrays)
            np.savez(p, **arrays)

        return f

    def set_sys(key, value):
        def fn(d, c):
            d["systems"][0][key] = value

        return fn

    cal_bad = [
        ("list", cal_json(lambda d, c: [d])),
        ("empty", lambda c: c.cal.write_bytes(b"")),
        ("binary", lambda c: c.cal.write_bytes(os.urandom(4000))),
        ("latin1", lambda c: c.cal.write_bytes(c.cal.read_bytes().replace(b'"A"', '"\xc4"'.encode("latin-1"), 1))),
        ("not_json", lambda c: c.cal.write_text("{'systems': [}")),
        ("deep_nesting", lambda c: c.cal.write_text("[" * 100_000 + "]" * 100_000)),
        ("missing_systems", cal_json(lambda d, c: d.pop("systems"))),
        ("systems_not_list", cal_json(lambda d, c: d.__setitem__("systems", "A"))),
        ("schema_wrong", cal_json(lambda d, c: d.__setitem__("schema", "other"))),
        ("version_future", cal_json(lambda d, c: d.__setitem__("schema_version", 99))),
        ("image_size_negative", cal_json(set_sys("image_size_px", [-512, 512]))),
        ("image_size_huge", cal_json(set_sys("image_size_px", [10**9, 10**9]))),
        ("image_size_nan", cal_json(lambda d, c: d["systems"][0].__setitem__("image_size_px", [float("nan"), 512]))),
        ("image_size_string", cal_json(set_sys("image_size_px", "512x512"))),
        ("iop_nan", cal_json(lambda d, c: d["systems"][0]["iop_px"].__setitem__("c", float("nan")))),
        ("iop_negative_c", cal_json(lambda d, c: d["systems"][0]["iop_px"].__setitem__("c", -2000.0))),
        ("iop_missing", cal_json(lambda d, c: d["systems"][0].pop("iop_px"))),
        (
            "field_file_absolute",
            cal_json(lambda d, c: d["systems"][0]["field"].__setitem__("file", str(c.proj / "out" / "field_B.npz"))),
        ),
        (
            "field_file_dotdot",
            cal_json(lambda d, c: d["systems"][0]["field"].__setitem__("file", "../out/field_B.npz")),
        ),
        ("field_file_etc", cal_json(lambda d, c: d["systems"][0]["field"].__setitem__("file", "/etc/passwd"))),
        ("field_file_int", cal_json(lambda d, c: d["systems"][0]["field"].__setitem__("file", 5))),
        ("field_file_missing", lambda c: (c.proj / "out" / "field_A.npz").unlink()),
        (
            "field_file_directory",
            lambda c: ((c.proj / "out" / "field_A.npz").unlink(), (c.proj / "out" / "field_A.npz").mkdir()),
        ),
        ("field_npz_truncated", lambda c: _truncate("field_A.npz")(c.proj / "out")),
        ("field_npz_bitflip", lambda c: _flip_byte("field_A.npz", 0.6)(c.proj / "out")),
        ("field_npz_empty", lambda c: (c.proj / "out" / "field_A.npz").write_bytes(b"")),
        ("field_npz_not_zip", lambda c: (c.proj / "out" / "field_A.npz").write_bytes(os.urandom(3000))),
        ("field_npz_missing_array", field_npz(lambda a: a.pop("delta_px"))),
        ("field_npz_wrong_shape", field_npz(lambda a: a.__setitem__("delta_px", a["delta_px"][:5, :7]))),
        ("field_npz_nan", field_npz(lambda a: a["delta_px"].__setitem__((3, 3, 0), np.nan))),
        ("field_npz_1e30", field_npz(lambda a: a.__setitem__("delta_px", a["delta_px"] * 1e30))),
        ("field_npz_nodes_unsorted", field_npz(lambda a: a.__setitem__("x_nodes_px", a["x_nodes_px"][::-1].copy()))),
        ("field_npz_string_array", field_npz(lambda a: a.__setitem__("delta_px", np.array(["x"] * 4)))),
        ("field_npz_pickled", lambda c: _pickle_field(c)),
        (
            "field_npz_symlink_other",
            lambda c: (
                (c.proj / "out" / "field_A.npz").unlink(),
                (c.proj / "out" / "field_A.npz").symlink_to(c.root / "sibling" / "precious.txt"),
            ),
        ),
        ("duplicate_system", cal_json(lambda d, c: d["systems"].append(dict(d["systems"][0])))),
        ("system_name_traversal", cal_json(lambda d, c: d["systems"][0].__setitem__("name", "../../x"))),
    ]
    for label, setup in cal_bad:
        cmds = (
            ("undistort", "inspect", "export")
            if label
            in (
                "list",
                "binary",
                "deep_nesting",
                "image_size_negative",
                "field_file_absolute",
                "field_npz_truncated",
                "field_npz_bitflip",
                "field_npz_pickled",
                "latin1",
                "system_name_traversal",
            )
            else ("undistort",)
        )
        for cmd in cmds:
            hints = ("calibration.json", "field_A.npz", "field", "image_size", "passwd", "precious")
            add(
                f"cal_{label}_{cmd}",
                C,
                setup,
                on_cal(cmd),
                hints=hints,
                allow=cal_allow,
                **(
                    {"expect": "either", "check": lambda c: None}
                    if label in ("version_future", "field_npz_nodes_unsorted")
                    else {}
                ),
            )

    # ---- undistort ----
    U = "undistort"
    add("undistort_ok", U, nothing, und(), expect="ok", check=undistorted_ok("proj/und", 1), allow=("proj/und",))
    add(
        "undistort_field_1e30",
        U,
        field_npz(lambda a: a.__setitem__("delta_px", a["delta_px"] * 1e30)),
        und(),
        hints=("field", "calibration"),
        allow=("proj/und",),
    )
    add(
        "undistort_field_200px",
        U,
        field_npz(lambda a: a.__setitem__("delta_px", a["delta_px"] + 600.0)),
        und(),
        hints=("field", "calibration"),
        allow=("proj/und",),
        note="a field moving every pixel out of the image",
    )
    add(
        "undistort_same_names",
        U,
        lambda c: (
            (c.root / "sibling" / "A").mkdir()
            or shutil.copy(c.frames("B")[0], c.root / "sibling" / "A" / "frame_000.tif")
        ),
        lambda c: [
            fluorocal(
                "undistort",
                c.cal,
                "--system",
                "A",
                "--out",
                c.proj / "und",
                c.frames("A")[0],
                c.root / "sibling" / "A" / "frame_000.tif",
            )
        ],
        hints=("frame_000",),
        allow=("proj/und",),
    )
    add(
        "undistort_out_is_file",
        U,
        lambda c: (c.proj / "und").write_text("x"),
        und(),
        hints=("und",),
        allow=("proj/und",),
    )
    add(
        "undistort_out_is_input_folder",
        U,
        nothing,
        lambda c: [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "frames" / "A", c.frames("A")[0])],
        hints=("frame_000", "exists"),
    )
    add(
        "undistort_overwrite_inputs",
        U,
        nothing,
        lambda c: [
            fluorocal(
                "undistort",
                c.cal,
                "--system",
                "A",
                "--out",
                c.proj / "frames" / "A",
                "--overwrite",
                c.frames("A")[0],
            )
        ],
        hints=("frame_000", "input"),
        note="--overwrite onto its own input: refusing is right (reading and writing one file); debatable",
    )
    add(
        "undistort_existing_output",
        U,
        lambda c: (c.proj / "und").mkdir() or (c.proj / "und" / "frame_000.tif").write_text("x"),
        und(),
        hints=("frame_000",),
        allow=(),
    )
    add(
        "undistort_input_missing",
        U,
        nothing,
        lambda c: [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "und", c.proj / "nope.tif")],
        hints=("nope.tif",),
        allow=("proj/und",),
    )
    add(
        "undistort_input_empty_folder",
        U,
        lambda c: (c.proj / "empty").mkdir(),
        lambda c: [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "und", c.proj / "empty")],
        hints=("empty",),
        allow=("proj/und", "proj/empty"),
    )
    add(
        "undistort_input_binary",
        U,
        _write_bytes("bad.tif", os.urandom(5000)),
        lambda c: [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "und", c.proj / "bad.tif")],
        hints=("bad.tif",),
        allow=("proj/und",),
    )
    add(
        "undistort_input_other_size",
        U,
        _tiff("small.tif", np.full((100, 100), 1000, np.uint16)),
        lambda c: [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "und", c.proj / "small.tif")],
        hints=("small.tif", "size"),
        allow=("proj/und",),
    )
    add(
        "undistort_input_1x1",
        U,
        _tiff("one.tif", np.full((1, 1), 1000, np.uint16)),
        lambda c: [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "und", c.proj / "one.tif")],
        hints=("one.tif", "size"),
        allow=("proj/und",),
    )
    add("undistort_system_unknown", U, nothing, und(system="Z"), hints=("Z",), allow=("proj/und",))
    add("undistort_system_traversal", U, nothing, und(system="../../etc"), hints=("etc", "system"), allow=("proj/und",))
    add(
        "undistort_orientation_garbage",
        U,
        nothing,
        und("--orientation", "orbit=abc,tilt=0"),
        hints=("orientation",),
        allow=("proj/und",),
    )
    add(
        "undistort_orientation_nan",
        U,
        nothing,
        und("--orientation", "orbit=nan,tilt=0"),
        hints=("orientation",),
        allow=("proj/und",),
    )
    add(
        "undistort_calibration_missing",
        U,
        lambda c: c.cal.unlink(),
        und(),
        hints=("calibration.json",),
        allow=("proj/und",),
    )
    add(
        "undistort_calibration_is_dir",
        U,
        lambda c: (c.cal.unlink(), c.cal.mkdir()),
        und(),
        hints=("calibration.json",),
        allow=("proj/und",),
    )
    add(
        "undistort_two_frames_folder",
        U,
        nothing,
        lambda c: [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "und", c.proj / "frames" / "A")],
        expect="ok",
        check=undistorted_ok("proj/und", 4),
        allow=("proj/und",),
    )
    add(
        "undistort_input_is_calibration_npz",
        U,
        nothing,
        lambda c: [
            fluorocal(
                "undistort",
                c.cal,
                "--system",
                "A",
                "--out",
                c.proj / "und",
                c.proj / "out" / "field_A.npz",
            )
        ],
        hints=("field_A.npz",),
        allow=("proj/und",),
    )
    add(
        "undistort_out_symlink_outside",
        U,
        lambda c: (c.proj / "und").symlink_to(c.root / "sibling"),
        und(),
        expect="either",
        allow=("sibling/frame_000.tif", "proj/und"),
        check=lambda c: sibling_intact(c),
        note="an --out that is the user's own link: writing through it is the user's choice; nothing else touched",
    )

    # ---- cache tampering (run, inspect) ----
    T = "cache"

    def code_ref(ref):
        return lambda c: {"__dataclass__": ref, "fields": {"command": _touch_cmd(c), "args": [_touch_cmd(c)]}}

    for stage in ("label", "learn"):
        refs = ("os:system", "subprocess:getoutput", "builtins:eval", "posix:system", "pty:spawn")
        for ref in refs if stage == "label" else refs[:1]:  # a learn entry recomputed costs a learning run
            for cmd in ("run", "inspect"):
                add(
                    f"manifest_{ref.replace(':', '_')}_{stage}_{cmd}",
                    T,
                    _manifest_payload(stage, code_ref(ref)),
                    (lambda c, cmd=cmd: [fluorocal(cmd, c.cfg)]),
                    expect="ok",
                    check=same_as_clean if cmd == "run" else (lambda c: None),
                )
    add("manifest_code_ref_no_rehash", T, _manifest_payload("label", code_ref("os:system"), rehash=False), expect="ok")
    add(
        "manifest_array_ref_traversal",
        T,
        _manifest_payload("label", lambda c: {"__array__": "../../../sibling/precious.txt"}),
        expect="ok",
    )
    add(
        "manifest_nested_code_ref",
        T,
        _manifest_payload(
            "label",
            lambda c: {
                "__dataclass__": "fluorocal.stages.label:Labels",
                "fields": {"x": {"__dataclass__": "os:system", "fields": {"command": _touch_cmd(c)}}},
            },
        ),
        expect="ok",
    )
    add(
        "manifest_dict_payload",
        T,
        _manifest_payload("label", lambda c: {"__dict__": {"__reduce__": _touch_cmd(c)}}),
        expect="ok",
    )
    add("arrays_npz_pickled_label", T, _pickle_npz("label"), expect="ok")
    add("arrays_npz_pickled_learn", T, _pickle_npz("learn"), expect="ok")
    add(
        "arrays_npz_pickled_inspect",
        T,
        _pickle_npz("label"),
        lambda c: [fluorocal("inspect", c.cfg, "label")],
        expect="ok",
        check=lambda c: None,
    )
    for stage in ("detect", "label"):
        add(f"{stage}_arrays_bitflip", T, _entry_edit(stage, _flip_byte("arrays.npz")), expect="ok")
        add(f"{stage}_arrays_truncated", T, _entry_edit(stage, _truncate("arrays.npz")), expect="ok")
        add(f"{stage}_manifest_edited", T, _entry_edit(stage, _edit_summary), expect="ok")
        add(f"{stage}_manifest_deleted", T, _entry_edit(stage, lambda e: (e / "manifest.json").unlink()), expect="ok")
        add(f"{stage}_checksum_deleted", T, _entry_edit(stage, lambda e: (e / "manifest.sha256").unlink()), expect="ok")
        add(
            f"{stage}_manifest_garbage",
            T,
            _entry_edit(stage, lambda e: (e / "manifest.json").write_bytes(os.urandom(900))),
            expect="ok",
        )
        add(
            f"{stage}_manifest_is_dir",
            T,
            _entry_edit(stage, lambda e: ((e / "manifest.json").unlink(), (e / "manifest.json").mkdir())),
            expect="ok",
        )
        add(
            f"{stage}_entry_is_file",
            T,
            _entry_edit(stage, lambda e: (shutil.rmtree(e), e.write_text("x"))),
            expect="ok",
        )
        add(
            f"{stage}_arrays_symlink_etc",
            T,
            _entry_edit(stage, lambda e: ((e / "arrays.npz").unlink(), (e / "arrays.npz").symlink_to("/etc/passwd"))),
            expect="ok",
        )
    add("learn_manifest_edited", T, _entry_edit("learn", _edit_summary), expect="ok")
    add(
        "learn_arrays_forged_rehashed",
        T,
        _entry_edit("learn", _edit_array),
        expect="either",
        check=lambda c: None,
        note="DEBATABLE: a forger who rewrites the data and every checksum is indistinguishable from the cache's "
        "own writer (the checksum guards faults, not forgery); the run must not crash or run code; its "
        "result is the forged one",
    )
    add(
        "stage_folder_symlink_sibling",
        T,
        lambda c: (
            shutil.rmtree(c.proj / ".fluorocal" / "label"),
            (c.proj / ".fluorocal" / "label").symlink_to(c.root / "sibling"),
        ),
        expect="either",
        hints=("label", "link", "cache"),
        allow=("sibling",),
        check=lambda c: sibling_intact(c) or same_as_clean(c),
        note="a stage folder linked out of the cache: recomputing into it writes where it points",
    )
    add(
        "entry_symlink_sibling",
        T,
        _entry_edit("label", lambda e: (shutil.rmtree(e), e.symlink_to(e.parents[3] / "sibling"))),
        expect="either",
        hints=("label", "link", "cache"),
        check=lambda c: sibling_intact(c) or same_as_clean(c),
    )
    add(
        "cache_marker_deleted",
        T,
        lambda c: (c.proj / ".fluorocal" / ".fluorocal-cache").unlink(),
        expect="either",
        hints=("cache",),
    )
    add(
        "cache_marker_garbage",
        T,
        lambda c: (c.proj / ".fluorocal" / ".fluorocal-cache").write_bytes(os.urandom(50)),
        expect="either",
        hints=("cache",),
    )
    add(
        "cache_tmp_leftovers",
        T,
        lambda c: [
            (c.proj / ".fluorocal" / "label" / f".tmp-{'a' * 64}-xyz1").mkdir(),
            (c.proj / ".fluorocal" / "label" / f".tmp-{'a' * 64}-xyz1" / "x").write_text("x"),
        ],
        expect="ok",
        check=clean_and_no_leftovers,
    )
    add(
        "out_staging_leftovers",
        T,
        lambda c: [
            (c.proj / ".out.fluorocal-staging-999999-abcdef01").mkdir(),
            (c.proj / ".out.fluorocal-staging-999999-abcdef01" / "calibration.json").write_text("{}"),
        ],
        expect="ok",
        check=clean_and_no_leftovers,
    )
    add(
        "out_manifest_lists_user_file",
        T,
        lambda c: (
            (c.proj / "out" / "mine.txt").write_text("user"),
            (c.proj / "out" / ".fluorocal-outputs.json").write_text(
                json.dumps({"entries": ["mine.txt", "../phantom.csv"]})
            ),
        ),
        expect="ok",
        check=lambda c: same_as_clean(c),
        note="a hand-edited outputs manifest may at most lose files inside the output folder",
    )
    add(
        "out_is_symlink_sibling",
        T,
        lambda c: (shutil.rmtree(c.proj / "out"), (c.proj / "out").symlink_to(c.root / "sibling")),
        expect="either",
        hints=("out",),
        allow=("sibling", "proj/out"),
        check=lambda c: sibling_intact(c),
        note="DEBATABLE: the output folder is a link to the user's other folder",
    )
    add(
        "cache_is_symlink_sibling",
        T,
        lambda c: (shutil.rmtree(c.proj / ".fluorocal"), (c.proj / ".fluorocal").symlink_to(c.root / "sibling")),
        expect="either",
        hints=("cache", ".fluorocal", "sibling"),
        allow=(),
        check=lambda c: sibling_intact(c),
    )
    add(
        "inspect_frame_overlay_huge_index",
        T,
        nothing,
        lambda c: [fluorocal("inspect", c.cfg, "detect", "--frame", "999")],
        hints=("frame", "999"),
    )
    add(
        "inspect_frame_negative",
        T,
        nothing,
        lambda c: [fluorocal("inspect", c.cfg, "detect", "--frame", "-1")],
        hints=("frame",),
    )
    add("inspect_stage_unknown", T, nothing, lambda c: [fluorocal("inspect", c.cfg, "bogus")], hints=("bogus",))
    add(
        "inspect_stage_traversal",
        T,
        nothing,
        lambda c: [fluorocal("inspect", c.cfg, "../../sibling")],
        hints=("sibling", "stage"),
    )

    # ---- cache clean ----
    CL = "clean"

    def clean_case(name, setup, expect="refuse", hints=("cache",), check=None, allow=(), extra=(), note=""):
        add(
            name,
            CL,
            setup,
            lambda c: [fluorocal("cache", "clean", c.cfg, *extra)],
            expect=expect,
            hints=hints,
            check=check or (lambda c: None),
            allow=allow,
            note=note,
        )

    for label, value in (
        ("dot", '"."'),
        ("dotdot", '".."'),
        ("sibling", '"../sibling"'),
        ("frames", '"frames"'),
        ("out", '"out"'),
        ("phantom_file", '"phantom.csv"'),
        ("absolute_sibling", None),
        ("nonexistent", '"nothing_here"'),
    ):
        setup = (
            _cfg_append(f"[cache]\ndir = {value}")
            if value
            else (lambda c: c.append_cfg(f'[cache]\ndir = "{c.root / "sibling"}"'))
        )
        clean_case(
            f"clean_dir_{label}",
            setup,
            expect="either" if label == "nonexistent" else "refuse",
            hints=("cache", "dir", "marker", "fluorocal-cache"),
        )
    clean_case(
        "clean_forged_marker_sibling",
        lambda c: (
            c.append_cfg('[cache]\ndir = "../sibling"'),
            (c.root / "sibling" / ".fluorocal-cache").write_text(
                json.dumps({"format": "fluorocal-cache", "version": 2})
            ),
        ),
        expect="either",
        allow=("sibling/.fluorocal-cache",),
        check=sibling_intact,
        note="a marker forged into a folder: clean may delete only entries it writes, none of the user's",
    )
    clean_case(
        "clean_forged_marker_key_named",
        lambda c: (
            c.append_cfg('[cache]\ndir = "../sibling"'),
            (c.root / "sibling" / ".fluorocal-cache").write_text(
                json.dumps({"format": "fluorocal-cache", "version": 2})
            ),
            (c.root / "sibling" / "work" / ("b" * 64)).mkdir(),
            (c.root / "sibling" / "work" / ("b" * 64) / "data.txt").write_text("mine"),
        ),
        expect="either",
        allow=("sibling/.fluorocal-cache", "sibling/work/" + "b" * 64),
        check=sibling_intact,
        note="DEBATABLE: a folder named like a key inside a forged cache is the cache's by its own rules",
    )
    clean_case(
        "clean_entry_symlink_outside",
        _entry_edit("label", lambda e: (shutil.rmtree(e), e.symlink_to(e.parents[3] / "sibling"))),
        expect="ok",
        check=sibling_intact,
    )
    clean_case(
        "clean_stage_symlink_outside",
        lambda c: (
            shutil.rmtree(c.proj / ".fluorocal" / "label"),
            (c.proj / ".fluorocal" / "label").symlink_to(c.root / "sibling"),
        ),
        expect="either",
        check=sibling_intact,
    )
    clean_case(
        "clean_user_file_in_cache",
        lambda c: (c.proj / ".fluorocal" / "my_notes.txt").write_text("mine"),
        expect="ok",
        check=lambda c: None if (c.proj / ".fluorocal" / "my_notes.txt").is_file() else "user file deleted",
        allow=("proj/.fluorocal",),
    )
    clean_case(
        "clean_ok",
        nothing,
        expect="ok",
        check=lambda c: None if not any((c.proj / ".fluorocal").glob("*/*")) else "entries left",
    )
    clean_case(
        "clean_stale",
        nothing,
        expect="ok",
        extra=("--stale",),
        check=lambda c: None if len(_entries(c, "learn")) == 1 else "entries lost",
    )
    clean_case("clean_config_broken", _write_bytes("fluorocal.toml", b"[[[["), hints=("fluorocal.toml",))

    # ---- other commands' inputs ----
    CMD = "commands"
    det = lambda *a: lambda c: [fluorocal("detect", *a, "--out", c.proj / "det", c.frames("A")[0])]  # noqa: E731
    add(
        "detect_ok",
        CMD,
        nothing,
        det(),
        expect="ok",
        allow=("proj/det",),
        check=lambda c: (
            None if len((c.proj / "det" / "detections.csv").read_text().splitlines()) > 50 else "few detections"
        ),
    )
    add(
        "detect_missing_file",
        CMD,
        nothing,
        lambda c: [fluorocal("detect", "--out", c.proj / "det", c.proj / "no.tif")],
        hints=("no.tif",),
        allow=("proj/det",),
    )
    add(
        "detect_binary_file",
        CMD,
        _write_bytes("bad.tif", os.urandom(999)),
        lambda c: [fluorocal("detect", "--out", c.proj / "det", c.proj / "bad.tif")],
        hints=("bad.tif",),
        allow=("proj/det",),
    )
    add(
        "detect_out_is_dir",
        CMD,
        lambda c: (c.proj / "det" / "detections.csv").mkdir(parents=True),
        det(),
        hints=("detections.csv",),
        allow=("proj/det",),
    )
    add("detect_diameter_garbage", CMD, nothing, det("--diameter", "a:b"), hints=("diameter",), allow=("proj/det",))
    add(
        "detect_diameter_negative",
        CMD,
        nothing,
        det("--diameter", "-5:3"),
        hints=("diameter",),
        allow=("proj/det",),
    )
    add("detect_diameter_nan", CMD, nothing, det("--diameter", "nan:inf"), hints=("diameter",), allow=("proj/det",))
    add(
        "detect_overlay_traversal",
        CMD,
        nothing,
        det("--overlay", "../../sibling_overlay"),
        expect="either",
        allow=("proj/det", "sibling_overlay"),
        check=lambda c: None,
        note="--overlay names the user's own folder",
    )
    add(
        "detect_1x1",
        CMD,
        _tiff("one.tif", np.full((1, 1), 5, np.uint16)),
        lambda c: [fluorocal("detect", "--out", c.proj / "det", c.proj / "one.tif")],
        hints=("one.tif",),
        allow=("proj/det",),
        expect="either",
        check=lambda c: (
            None if len((c.proj / "det" / "detections.csv").read_text().splitlines()) <= 1 else "beads in a 1x1 frame"
        ),
        note="DEBATABLE: the debugging command reports the frame (no field of view, no candidates), writes no row",
    )

    def det_csv(text):
        return _write_bytes("det.csv", text.encode() if isinstance(text, str) else text)

    lab = lambda *a: (  # noqa: E731
        lambda c: [
            fluorocal(
                "label",
                c.proj / "det.csv",
                "--phantom",
                c.proj / "phantom.csv",  # noqa: E731
                "--source-image-distance",
                "1100",
                "--pixel-pitch",
                "0.5",
                "--image-size",
                "512",
                "512",
                "--out",
                c.proj / "lab",
                *a,
            )
        ]
    )
    head = "file,frame,x,y,sigma_x,sigma_y,rho,major,minor\n"
    for label, text in (
        ("empty", ""),
        ("header_only", head),
        ("binary", os.urandom(2000)),
        ("missing_column", "file,frame,x,y\nf.tif,0,1,2\n"),
        ("nan_x", head + "f.tif,0,nan,2,0.1,0.1,0,5,5\n"),
        ("text_y", head + "f.tif,0,1,abc,0.1,0.1,0,5,5\n"),
        ("inf_sigma", head + "f.tif,0,1,2,inf,0.1,0,5,5\n"),
        ("negative_frame", head + "f.tif,-1,1,2,0.1,0.1,0,5,5\n"),
    ):
        documented = label in ("nan_x", "inf_sigma", "negative_frame")
        add(
            f"label_detections_{label}",
            CMD,
            det_csv(text),
            lab(),
            hints=("det.csv",),
            allow=("proj/lab",),
            expect="either" if documented else "refuse",
            check=lambda c: (
                None if len((c.proj / "lab" / "labels.csv").read_text().splitlines()) <= 1 else "labels from nothing"
            ),
            note="DEBATABLE: a non-finite detection is a failed fit by the CSV's definition (README); the frame's "
            "labelling fails with its reason, no label is written"
            if documented
            else "",
        )
    add(
        "label_sid_nan",
        CMD,
        det_csv(head),
        lab("--source-image-distance", "nan"),
        hints=("source-image-distance",),
        allow=("proj/lab",),
    )
    add(
        "label_image_size_negative",
        CMD,
        det_csv(head),
        lab("--image-size", "-1", "-1"),
        hints=("image-size", "image size"),
        allow=("proj/lab",),
    )
    add(
        "label_phantom_metres",
        CMD,
        _chain(det_csv(head), _scale_phantom(0.001)),
        lab(),
        hints=("phantom", "metres"),
        allow=("proj/lab",),
    )
    adj = lambda *a: (  # noqa: E731
        lambda c: [
            fluorocal(
                "adjust",
                "--observations",
                c.proj / "obs.csv",
                "--phantom",  # noqa: E731
                c.proj / "phantom.csv",
                "--out",
                c.proj / "adj",
                *a,
            )
        ]
    )

    def obs(fn):
        def f(c: Ctx) -> None:
            lines = (c.proj / "out" / "observations.csv").read_text().splitlines()
            (c.proj / "obs.csv").write_text("\n".join(fn(lines)) + "\n")

        return f

    add("adjust_obs_empty", CMD, _write_bytes("obs.csv", b""), adj(), hints=("obs.csv",), allow=("proj/adj",))
    add(
        "adjust_obs_binary",
        CMD,
        _write_bytes("obs.csv", os.urandom(3000)),
        adj(),
        hints=("obs.csv",),
        allow=("proj/adj",),
    )
    add(
        "adjust_obs_nan",
        CMD,
        obs(lambda ls: ls[:5] + [ls[5].replace(ls[5].split(",")[4], "nan", 1)] + ls[6:]),
        adj(),
        hints=("obs.csv",),
        allow=("proj/adj",),
    )
    add(
        "adjust_obs_latin1",
        CMD,
        lambda c: (c.proj / "obs.csv").write_bytes(
            (c.proj / "out" / "observations.csv").read_bytes().replace(b",A,", ",\xc4,".encode("latin-1"), 1)
        ),
        adj(),
        hints=("obs.csv",),
        allow=("proj/adj",),
    )
    add("adjust_nu_nan", CMD, obs(lambda ls: ls), adj("--nu", "nan"), hints=("nu",), allow=("proj/adj",))
    add("adjust_nu_negative", CMD, obs(lambda ls: ls), adj("--nu", "-2"), hints=("nu",), allow=("proj/adj",))
    add(
        "adjust_sid_inf",
        CMD,
        obs(lambda ls: ls),
        adj("--source-image-distance", "inf"),
        hints=("source-image-distance",),
        allow=("proj/adj",),
    )
    add(
        "adjust_out_is_file",
        CMD,
        _chain(obs(lambda ls: ls), lambda c: (c.proj / "adj").write_text("x")),
        adj(),
        hints=("adj",),
        allow=("proj/adj",),
    )
    add(
        "adjust_phantom_nan",
        CMD,
        _chain(obs(lambda ls: ls), _phantom_cell(3, 1, "nan")),
        adj(),
        hints=("phantom.csv",),
        allow=("proj/adj",),
    )
    exp = lambda fmt, out="exp", *a: lambda c: [fluorocal("export", "--format", fmt, "--out", c.proj / out, *a, c.cal)]  # noqa: E731
    add("export_format_unknown", CMD, nothing, exp("evil"), hints=("format",), allow=("proj/exp",))
    add(
        "export_out_is_file",
        CMD,
        lambda c: (c.proj / "exp").write_text("x"),
        exp("opencv"),
        hints=("exp",),
        allow=("proj/exp",),
    )
    add(
        "export_out_in_frames_overwrite",
        CMD,
        nothing,
        exp("opencv", "frames/A", "--overwrite"),
        expect="either",
        allow=("proj/frames/A/*",),
        check=lambda c: None if len(c.frames("A")) == 4 else "frames lost",
        note="export into the frames' folder: only new files, the frames stay",
    )
    ev = lambda *a: lambda c: [fluorocal("evaluate", c.cfg, "--out", c.proj / "ev", *a)]  # noqa: E731
    for label, a in (
        ("holdout_garbage", ("--holdout", "sometimes")),
        ("holdout_missing_file", ("--holdout", "nope.tif")),
        ("train_sizes_negative", ("--train-sizes", "-1")),
        ("train_sizes_zero", ("--train-sizes", "0")),
        ("train_sizes_text", ("--train-sizes", "abc")),
        ("train_sizes_huge", ("--train-sizes", "99")),
        ("schemes_unknown", ("--schemes", "magic")),
        ("reference_missing", ("--reference", "nope.csv")),
        ("reference_binary", ("--reference", "phantom_bin.csv")),
        ("random_seed_text", ("--holdout", "random:x")),
    ):
        add(
            f"evaluate_{label}",
            CMD,
            _write_bytes("phantom_bin.csv", os.urandom(500)),
            ev(*a),
            hints=("holdout", "train", "schemes", "reference", "nope", "phantom_bin", "random"),
            allow=("proj/ev",),
        )
    add(
        "simulate_into_project",
        CMD,
        nothing,
        lambda c: [fluorocal("simulate", c.proj, "--frames", "2")],
        hints=("simulate", "exists", "force", str("proj")),
        note="simulate over an existing project refuses without --overwrite",
    )
    add(
        "simulate_frames_negative",
        CMD,
        nothing,
        lambda c: [fluorocal("simulate", c.proj / "sim2", "--frames", "-3")],
        hints=("frames",),
        allow=("proj/sim2",),
    )
    add(
        "simulate_image_size_huge",
        CMD,
        nothing,
        lambda c: [fluorocal("simulate", c.proj / "sim2", "--image-size", "10000000", "10000000")],
        hints=("image-size", "image size"),
        allow=("proj/sim2",),
    )

    # ---- SIGKILL in every stage, then a rerun ----
    KL = "kill"
    rerun = lambda *force: lambda c: [fluorocal("run", c.cfg, *force), fluorocal("run", c.cfg)]  # noqa: E731
    for stage in ("detect", "centroid", "label"):
        add(
            f"kill_during_{stage}_store",
            KL,
            nothing,
            rerun("--force", stage),
            expect="ok",
            check=clean_and_no_leftovers,
            runner=kill_when(f".fluorocal/{stage}/.tmp-*"),
        )
    add(
        "kill_during_learn_store",
        KL,
        nothing,
        rerun("--force", "learn"),
        expect="ok",
        check=clean_and_no_leftovers,
        runner=kill_when(".fluorocal/learn/.tmp-*"),
    )
    add(
        "kill_during_publish",
        KL,
        nothing,
        rerun(),
        expect="ok",
        check=clean_and_no_leftovers,
        runner=kill_when(".out.fluorocal-staging-*"),
    )
    add(
        "kill_during_publish_late",
        KL,
        nothing,
        rerun(),
        expect="ok",
        check=clean_and_no_leftovers,
        runner=kill_when(".out.fluorocal-staging-*/report.md"),
    )
    for t in (1.5, 3.0, 6.0):
        add(
            f"kill_after_{t:g}s",
            KL,
            nothing,
            rerun("--force", "detect"),
            expect="ok",
            check=clean_and_no_leftovers,
            runner=kill_after(t),
        )
    add(
        "kill_during_clean",
        KL,
        nothing,
        lambda c: [
            fluorocal("cache", "clean", c.cfg),
            fluorocal("run", c.cfg, "--until", "label"),
            fluorocal("run", c.cfg),
        ],
        expect="ok",
        check=clean_and_no_leftovers,
        runner=kill_after(1.2),
    )

    # ---- concurrent runs ----
    CC = "concurrency"
    add(
        "concurrent_4_warm_runs",
        CC,
        nothing,
        lambda c: [fluorocal("run", c.cfg)] * 4 + [fluorocal("run", c.cfg)],
        expect="ok",
        check=clean_and_no_leftovers,
        runner=concurrently(4),
    )
    add(
        "concurrent_3_force_label",
        CC,
        nothing,
        lambda c: [fluorocal("run", c.cfg, "--force", "label", "--until", "label")] * 3 + [fluorocal("run", c.cfg)],
        expect="ok",
        check=clean_and_no_leftovers,
        runner=concurrently(3),
    )
    add(
        "concurrent_run_and_inspect",
        CC,
        nothing,
        lambda c: [fluorocal("run", c.cfg), fluorocal("inspect", c.cfg), fluorocal("run", c.cfg)],
        expect="ok",
        check=clean_and_no_leftovers,
        runner=concurrently(2),
    )
    add(
        "concurrent_undistort_same_out",
        CC,
        nothing,
        lambda c: (
            [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "und", c.frames("A")[0])] * 2
            + [fluorocal("inspect", c.cal, "--out", c.proj / "insp")]
        ),
        expect="either",
        check=undistorted_ok("proj/und", 1),
        allow=("proj/und", "proj/insp"),
        runner=_one_of_two_ok,
        note="two undistorts into one folder at once: one writes, the other refuses the existing file",
    )

    # ---- full disk ----
    D = "disk"
    # (name, the run's arguments, the disk's free space in kB)
    for name, args, free in (
        ("full_disk_cache", ("--force", "label"), 40),
        ("full_disk_outputs", (), 200),
        ("full_disk_outputs_tiny", (), 8),
    ):
        add(
            name,
            D,
            nothing,
            rerun(*args),
            expect="ok",
            check=clean_and_no_leftovers,
            runner=full_disk(free),
            hints=("space", "too large"),
        )
    add(
        "full_disk_undistort",
        D,
        nothing,
        lambda c: [
            fluorocal(
                "undistort",
                c.cal,
                "--system",
                "A",
                "--out",
                c.proj / "out" / "und",
                c.proj / "frames" / "A",
            ),
            fluorocal(
                "undistort",
                c.cal,
                "--system",
                "A",
                "--out",
                c.proj / "out" / "und2",
                c.proj / "frames" / "A",
            ),
        ],
        expect="ok",
        check=undistorted_ok("proj/out/und2", 4),
        runner=full_disk(300),
        hints=("space", "too large"),
    )
    issue28_cases(add, nothing)
    return K


# ---- issue 28: outputs that survive every option, files that prove what they are, any locale ----


def _with_env(**extra):
    """Run the commands one by one with ``extra`` in the environment (a locale, FLUOROCAL_THREADS)."""

    def runner(c: Ctx, commands):
        env = {**_env(), **extra}
        done = [
            subprocess.run(a, cwd=c.proj, env=env, capture_output=True, text=True, errors="replace") for a in commands
        ]
        return [(p.returncode, p.stdout + p.stderr) for p in done]

    return runner


def _published_kept(c: Ctx) -> str | None:
    """``--until``: the published set (calibration, fields, report) is the clean run's; the partial tables beside."""
    missing = [n for n in ("calibration.json", "report.md", "field_A.npz") if not (c.proj / "out" / n).is_file()]
    if missing:
        return f"--until deleted {', '.join(missing)}"
    if not (c.proj / "out" / "until-label" / "label.csv").is_file():
        return "no partial label.csv in out/until-label"
    return same_as_clean(c)


def _other_project(out: str, extra: str = ""):
    def f(c: Ctx) -> None:
        text = c.cfg.read_text().replace('dir = "out"', f'dir = "{out}"')
        (c.proj / "other.toml").write_text(text + extra)

    return f


def _cache_kept(c: Ctx) -> str | None:
    learn = list((c.proj / ".fluorocal" / "learn").glob("*/manifest.json"))
    return None if learn else "cache clean of another project removed this project's learn entry"


def _scale_field(factor: float):
    def f(c: Ctx) -> None:
        p = c.proj / "out" / "field_A.npz"
        with np.load(p) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["x_nodes_px"] = arrays["x_nodes_px"] * factor
        arrays["y_nodes_px"] = arrays["y_nodes_px"] * factor
        np.savez(p, **arrays)

    return f


def _cal_edit(change):
    def f(c: Ctx) -> None:
        doc = json.loads(c.cal.read_text())
        change(doc)
        c.cal.write_text(json.dumps(doc))

    return f


def issue28_cases(add, nothing) -> None:
    """The classes of issue 28, each case as a careless user or a hostile file would try it."""
    K = "issue28"
    run = lambda *a: lambda c: [fluorocal("run", c.cfg, *a)]  # noqa: E731
    add("until_keeps_published", K, nothing, run("--until", "label"), expect="ok", check=_published_kept)
    add("second_project_same_out", K, _other_project("out"), lambda c: [fluorocal("run", c.proj / "other.toml")],
        hints=("another project",))  # fmt: skip
    add("shared_cache_clean", K, _other_project("out2", "\n[detect]\nmin_snr = 7.5\n"),
        lambda c: [fluorocal("cache", "clean", "--stale", c.proj / "other.toml"),
                   fluorocal("cache", "clean", c.proj / "other.toml")],
        expect="ok", check=_cache_kept)  # fmt: skip
    undistort = lambda c: [fluorocal("undistort", c.cal, "--system", "A",  # noqa: E731
                                     "--out", c.proj / "und", c.frames("A")[0])]  # fmt: skip
    for factor in (2.0, 0.5):
        add(f"field_nodes_x{factor:g}", K, _scale_field(factor), undistort, hints=("field_A.npz",))
    export = lambda c: [fluorocal("export", c.cal, "--format", "dlt", "--out", c.proj / "exp")]  # noqa: E731
    for name, q in (("rop_q_nan", [float("nan"), 0, 0, 0]), ("rop_q_zero", [0, 0, 0, 0]), ("rop_q_three", [1, 0, 0])):
        add(name, K, _cal_edit(lambda d, q=q: d["systems"][1]["rop"].update(q_cam_from_ref=q)), export,
            hints=("q_cam_from_ref",))  # fmt: skip
    add("exposure_source_nan", K, _cal_edit(lambda d: d["exposures"][0].update(source_mm=[0, float("nan"), 0])),
        export, hints=("source_mm",))  # fmt: skip
    seven = ["999", "1", "2", "3", "4", "", "x"]  # under the six columns id,x,y,z,diameter,role
    add("phantom_row_extra_value", K, lambda c: _write_rows(c, _phantom_rows(c) + [seven]),
        hints=("phantom.csv",))  # fmt: skip
    upper = lambda c: _write_rows(c, [(rs := _phantom_rows(c))[0]] + [[*r[:5], r[5].upper()] for r in rs[1:]])  # noqa: E731
    add("phantom_role_upper", K, upper,
        expect="ok")  # fmt: skip
    add("system_b_given_a_frames", K, _cfg_edit('frames = "frames/B/*.tif"', 'frames = "frames/A/*.tif"'),
        hints=("frames",))  # fmt: skip
    for name, text, key in (("n_arcs_1e21", "[centroid]\nn_arcs = " + str(10**21), "n_arcs"),
                            ("seed_negative", "[learn]\nseed = -1", "seed"),
                            ("int_5000_digits", "[learn]\nseed = " + "9" * 5000, "seed"),
                            ("float_1e400", "[detect]\nmin_snr = 1e400", "min_snr")):  # fmt: skip
        add(name, K, _cfg_append(text), hints=(key,))
    add("threads_env_huge", K, nothing, runner=_with_env(FLUOROCAL_THREADS="99999999999999999999"),
        hints=("FLUOROCAL_THREADS",))  # fmt: skip
    ascii_locale = {"LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONIOENCODING": "ascii"}
    add("locale_c_ascii_run", K, nothing, run("--force", "learn"), expect="ok", runner=_with_env(**ascii_locale))
    und = lambda name: lambda c: [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "und",  # noqa: E731
                                            c.proj / "frames" / name)]  # fmt: skip
    for name in ("lossy.jpg", "mjpeg.avi"):  # re-encoded lossily: refused (a frame comes back exactly or not at all)
        add(f"undistort_{name.replace('.', '_')}", K, _frame_copy(name), und(name), hints=(name,))
    greek = "fr\u00e4me_\u0394.tif"  # read and written under the C locale (OpenImageIO refused the name)
    add("undistort_non_ascii_name_c_locale", K, _frame_copy(greek), und(greek), expect="ok",
        check=undistorted_ok("proj/und", 1), allow=("proj/und",), runner=_with_env(**ascii_locale))  # fmt: skip


def _frame_copy(name: str):
    """Frame A's first, as ``frames/NAME``: an 8-bit JPEG, a 2-frame MJPEG AVI, or the TIFF itself (other names)."""

    def f(c: Ctx) -> None:
        import cv2

        source, target = c.frames("A")[0], c.proj / "frames" / name
        eight = (_read_frame(source) >> 4).astype(np.uint8)
        if name.endswith(".jpg"):
            cv2.imwrite(str(target), eight, [cv2.IMWRITE_JPEG_QUALITY, 95])
        elif name.endswith(".avi"):
            writer = cv2.VideoWriter(str(target), cv2.VideoWriter_fourcc(*"MJPG"), 10, eight.shape[::-1], False)
            for _ in range(2):
                writer.write(eight)
            writer.release()
        else:
            shutil.copyfile(source, target)

    return f


def _one_of_two_ok(c: Ctx, commands):
    res = concurrently(2)(c, commands)
    codes = [r[0] for r in res[:-1]]
    return [(0 if 0 in codes else 1, "\n".join(r[1] for r in res[:-1]))]


def _read_frame(p: Path) -> np.ndarray:
    import tifffile

    return tifffile.imread(p)


def _with_inf(c: Ctx) -> np.ndarray:
    a = _read_frame(c.frames("A")[1]).astype(np.float32)
    a[10:20, 10:20] = np.inf
    return a


def _png(p: Path) -> None:
    import cv2

    a = _read_frame(p)
    ok, buf = cv2.imencode(".png", a)
    p.write_bytes(buf.tobytes())


def _huge_header_tiff(p: Path) -> None:
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


def _pickle_field(c: Ctx) -> None:
    p = c.proj / "out" / "field_A.npz"
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files}
    obj = np.empty(1, dtype=object)
    obj[0] = _Payload(_touch_cmd(c))
    arrays["delta_px"] = obj
    np.savez(p, **arrays)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="the first case of each class only")
    ap.add_argument("--only", help="comma-separated classes or case names")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--jobs", type=int, default=2, help="cases run at once (default: 2)")
    ap.add_argument("--keep", type=Path, help="work here (kept) instead of a temporary folder")
    args = ap.parse_args(argv)
    cases = all_cases()
    if args.only:
        wanted = set(args.only.split(","))
        cases = [k for k in cases if k.klass in wanted or k.name in wanted]
    if args.quick:
        seen, quick = set(), []
        for k in cases:
            if k.klass not in seen:
                seen.add(k.klass)
                quick.append(k)
        cases = quick
    if args.list:
        for k in cases:
            print(f"{k.klass:12s} {k.name:40s} expect {k.expect}")
        print(f"{len(cases)} cases")
        return 0
    work = args.keep or Path(tempfile.mkdtemp(prefix="fluorocal-attack-"))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    base = work / "sandbox" / "base"
    if not (base / "proj" / "out" / "calibration.json").is_file():  # --keep DIR reuses a finished clean project
        shutil.rmtree(work / "sandbox", ignore_errors=True)
        base = make_base(work / "sandbox")
    print(f"clean run against the simulator's truth: {check_clean_against_truth(base)}")
    cases_dir = work / "sandbox" / "cases"
    shutil.rmtree(cases_dir, ignore_errors=True)
    cases_dir.mkdir()
    outcomes: list[Outcome] = []
    with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = {pool.submit(run_case, k, base, cases_dir, i): i for i, k in enumerate(cases)}
        done = {}
        for fut in concurrent.futures.as_completed(futures):
            i = futures[fut]
            done[i] = fut.result()
            o = done[i]
            flags = [
                f
                for f, on in (
                    ("TRACEBACK", o.traceback),
                    ("WRONG: " + str(o.wrong), o.wrong),
                    ("OUTSIDE: " + "; ".join(o.outside[:3]), o.outside),
                    ("CODE RAN", o.code_ran),
                    ("weak message", o.weak),
                )
                if on
            ]
            print(
                f"{i:3d} {o.case.klass:11s} {o.case.name:38s} expect {o.case.expect:6s} exit {o.rc:3d} "
                f"{'ok ' if not (o.failed or o.weak) else 'BAD'} {', '.join(flags)} | {o.message[:110]} "
                f"({o.seconds:.0f} s)",
                flush=True,
            )
        outcomes = [done[i] for i in sorted(done)]
    n = len(outcomes)
    tracebacks = sum(o.traceback for o in outcomes)
    wrong = sum(bool(o.wrong) for o in outcomes)
    outside = sum(bool(o.outside) for o in outcomes)
    code = sum(o.code_ran for o in outcomes)
    weak = sum(o.weak for o in outcomes)
    refused_good = sum(o.rc != 0 and o.case.expect == "ok" for o in outcomes)
    print(
        f"{n} cases in {len({o.case.klass for o in outcomes})} classes, {time.perf_counter() - t0:.0f} s "
        f"(load {os.getloadavg()[0]:.1f})"
    )
    print(
        f"tracebacks: {tracebacks}; silent wrong results: {wrong}; outside writes/deletes: {outside}; "
        f"code from data: {code}; weak messages: {weak}; good input refused: {refused_good}"
    )
    met = tracebacks == wrong == outside == code == 0
    print(f"targets (0 tracebacks, 0 silent wrong, 0 outside writes, 0 code from data): {'met' if met else 'NOT met'}")
    if args.keep is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if met else 1


if __name__ == "__main__":
    import docpage

    sys.exit(docpage.run(__file__, main))
