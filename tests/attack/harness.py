"""The attack battery's harness: a case, its folder, how its commands run and how its outcome is judged.

A case runs on its own copy of the clean project (:func:`build_base`): ``root/proj`` beside ``root/sibling``
(a user's other work). The case applies one hostile or careless change (its setup) and runs the ``fluorocal``
command(s) a user would, each in a subprocess; :func:`judge` reads what they printed and what changed on disk.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import re
import resource
import shutil
import signal
import stat
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

TRACEBACK = "Traceback (most recent call last)"
UNPRIVILEGED = [
    "setpriv",
    "--bounding-set",
    "-dac_override,-dac_read_search",
    "--inh-caps",
    "-dac_override,-dac_read_search",
]
CANARY = "CANARY"
#: what a command may write without it counting as outside: the output and cache folders, the publish staging
OWN_FOLDERS = ("proj/out", "proj/.fluorocal", "proj/.out.fluorocal-*")
ERROR_LINE = re.compile(r"fluorocal( [a-z]+)*: error: ")


def env() -> dict:
    """The environment of every command: the caller's, with one BLAS/OpenMP thread."""
    return {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def fluorocal(*args: str) -> list[str]:
    """The command line of ``fluorocal --quiet ARGS`` (the installed package, this interpreter)."""
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


def run_cfg(c: Ctx) -> list[list[str]]:
    """``fluorocal run`` of the case's project: the commands of a case that names none."""
    return [fluorocal("run", c.cfg)]


def undistort_first(*extra: str, out: str = "und", system: str = "A"):
    """The commands: ``fluorocal undistort`` of frame A's first with the project's calibration into ``proj/out``."""

    def commands(c: Ctx) -> list[list[str]]:
        return [fluorocal("undistort", c.cal, "--system", system, "--out", c.proj / out, *extra, c.frames("A")[0])]

    return commands


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
    readonly: tuple[str, ...] = ()  # with as_nobody: paths (relative to the case folder) made read-only first
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

    @property
    def refused_good(self) -> bool:
        """Good input (a case that expects ``ok``) that the commands did not accept."""
        return self.rc != 0 and self.case.expect == "ok"

    @property
    def flags(self) -> list[str]:
        """What is wrong with the outcome, as the battery's per-case line shows it (empty: nothing)."""
        return [
            f
            for f, on in (
                ("TRACEBACK", self.traceback),
                ("WRONG: " + str(self.wrong), self.wrong),
                ("OUTSIDE: " + "; ".join(self.outside[:3]), self.outside),
                ("CODE RAN", self.code_ran),
                ("weak message", self.weak),
            )
            if on
        ]

    @property
    def problems(self) -> list[str]:
        """What makes the outcome fail the battery's targets (empty: it passes): its flags, and good input refused."""
        return self.flags + (["good input refused"] if self.refused_good else [])

    def line(self) -> str:
        """The case's class, name, expectation, exit code, verdict, flags, message and seconds on one line."""
        return (
            f"{self.case.klass:11s} {self.case.name:38s} expect {self.case.expect:6s} exit {self.rc:3d} "
            f"{'ok ' if not (self.failed or self.weak) else 'BAD'} {', '.join(self.flags)} | {self.message[:110]} "
            f"({self.seconds:.0f} s)"
        )


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


def _allowed(rel: str, allowed: list[str]) -> bool:
    """``rel`` is one of ``allowed``, under one, or starts like one ending in ``*``."""
    return any(
        rel == a or rel.startswith(a.rstrip("/") + "/") or (a.endswith("*") and rel.startswith(a[:-1])) for a in allowed
    )


def changed_outside(before: dict, after: dict, allowed: list[str]) -> list[str]:
    """The entries created, deleted or modified between two snapshots but the ``allowed`` ones (folders' mtimes)."""
    out = []
    for rel in sorted(set(before) | set(after)):
        if before.get(rel) != after.get(rel) and not _allowed(rel, allowed):
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
    """Run one command in its own session: its exit code and what it printed (stdout, then stderr)."""
    if nobody and os.geteuid() == 0:  # root without the capabilities that override permissions: read-only is read-only
        argv = [*UNPRIVILEGED, *argv]
    p = subprocess.run(
        argv,
        cwd=cwd,
        env=env(),
        capture_output=True,
        text=True,
        errors="replace",
        preexec_fn=_preexec(nobody, fsize),
        timeout=timeout,
    )
    return p.returncode, p.stdout + p.stderr


def default_runner(c: Ctx, commands: list[list[str]], nobody=False) -> list[tuple[int, str]]:
    """The commands one after the other in the project's folder."""
    return [run_cmd(argv, c.proj, nobody=nobody) for argv in commands]


def error_lines(text: str) -> list[str]:
    """The lines of a command's output that are not warnings nor argparse's usage lines."""
    lines, usage = [], False
    for ln in text.splitlines():
        usage = ln.startswith("usage:") or (usage and ln.startswith(" "))
        if ln.strip() and not usage and "warning" not in ln.lower()[:40]:
            lines.append(ln)
    return lines


def _message(results: list[tuple[int, str]]) -> tuple[str, list[str]]:
    """The line that tells how the commands ended, and the last command's error lines."""
    lines = error_lines(results[-1][1])
    message = lines[-1] if lines else ""
    if len(results) > 1:  # a fault, then what follows it: show how each command ended
        message = " / ".join(f"[{r}] {(error_lines(o) or [''])[-1][:90]}" for r, o in results)
    return message, lines


def judge(case: Case, c: Ctx, results, before, after, seconds) -> Outcome:
    """The outcome of ``case``: its commands' ``results`` and the case folder's snapshots ``before`` and ``after``."""
    tb = any(TRACEBACK in out for _, out in results)
    rc = results[-1][0]
    message, lines = _message(results)
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
    # a refusal of good input (expect "ok") is not a silent wrong result; it shows as a weak/failed refusal
    outside = changed_outside(before, after, [*OWN_FOLDERS, *case.allow])
    code_ran = any(p.name.startswith(CANARY) for p in c.root.rglob("*")) or any(
        p.name.startswith(CANARY) for p in c.root.parent.glob("*")
    )
    return Outcome(case, rc, tb, message[:200], clear, wrong, outside, code_ran, seconds)


def run_case(case: Case, base: Path, root: Path) -> Outcome:
    """Copy the clean project's folder ``base`` to ``root`` (new), apply the case there, run it and judge it."""
    shutil.copytree(base, root, symlinks=True)
    c = Ctx(root, base / "proj")
    case.setup(c)
    if case.as_nobody:
        for rel in case.readonly:
            p = c.root / rel
            p.chmod(stat.S_IMODE(p.stat().st_mode) & ~0o222)
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


# --- building the project ---------------------------------------------------------------------


def build_base(base: Path) -> str:
    """The clean project every case copies: ``base/proj`` simulated and run once, ``base/sibling`` beside it.

    ``fluorocal simulate --frames 4 --systems 2 --image-size 512 512 --seed 3`` (its montage removed), then
    ``fluorocal run`` so its cache and outputs are warm. Returns a line saying where it is and what the run cost.
    """
    proj = base / "proj"
    subprocess.run(
        fluorocal("simulate", proj, "--frames", "4", "--systems", "2", "--image-size", "512", "512", "--seed", "3"),
        check=True,
        env=env(),
        capture_output=True,
    )
    (proj / "montage.png").unlink()
    t = time.process_time()
    r = subprocess.run(fluorocal("run", proj / "fluorocal.toml"), env=env(), capture_output=True, text=True)
    if r.returncode:
        raise RuntimeError(f"the clean run failed: {r.stderr}")
    cpu = resource.getrusage(resource.RUSAGE_CHILDREN)
    (base / "sibling" / "work").mkdir(parents=True)
    (base / "sibling" / "precious.txt").write_text("a user's file beside the project\n")
    (base / "sibling" / "work" / "notes.txt").write_text("more of the user's work\n")
    return (
        f"clean project: {proj} (cold run: {cpu.ru_utime + cpu.ru_stime:.1f} cpu-s in children, "
        f"{time.process_time() - t:.1f} s own)"
    )
