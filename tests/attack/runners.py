"""The attack battery's runners for faults: a case's commands killed, run at once, on a full disk, in a locale.

A runner takes the case's folder and its commands and returns each (or the telling) command's exit code and output.
A full disk is a tmpfs mounted for the case when the process may mount one (root), else RLIMIT_FSIZE
(``EFBIG`` instead of ``ENOSPC``).
"""

from __future__ import annotations

import functools
import os
import shutil
import signal
import subprocess
import tempfile
import time

from tests.attack.harness import Ctx, env, run_cmd


def _started(argv: list[str], c: Ctx) -> subprocess.Popen:
    """``argv`` started in the project's folder in a session of its own, its output dropped."""
    return subprocess.Popen(
        argv,
        cwd=c.proj,
        env=env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        preexec_fn=os.setsid,
    )


def kill_when(pattern: str, delay: float = 0.0, timeout: float = 600.0):
    """Start the first command, SIGKILL it when ``pattern`` (a glob under the project) appears, then run the rest."""

    def runner(c: Ctx, commands):
        p = _started(commands[0], c)
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
    """Start the first command, SIGKILL it after ``seconds`` unless it ended, then run the rest."""

    def runner(c: Ctx, commands):
        p = _started(commands[0], c)
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
            subprocess.Popen(a, cwd=c.proj, env=env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
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


def one_of_two_ok(c: Ctx, commands):
    """The first two commands at once, then the rest: exit 0 if either of the two did, with both outputs."""
    res = concurrently(2)(c, commands)
    codes = [r[0] for r in res[:-1]]
    return [(0 if 0 in codes else 1, "\n".join(r[1] for r in res[:-1]))]


@functools.cache
def can_mount() -> bool:
    """Whether this process may mount a tmpfs (root with ``mount``); tried once."""
    if os.geteuid() != 0 or not shutil.which("mount"):
        return False
    with tempfile.TemporaryDirectory() as d:
        ok = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", d], capture_output=True).returncode == 0
        if ok:
            subprocess.run(["umount", d], check=True)
    return ok


def _on_tmpfs(c: Ctx, commands, free_kb: int):
    """The first command on a tmpfs holding the project with ``free_kb`` free; the rest once it has 400 MB."""
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


def full_disk(free_kb: int):
    """The project on a tmpfs with ``free_kb`` free: the first command fills it; the disk grown, the rest run.

    Without mount rights: RLIMIT_FSIZE of ``free_kb`` on the first command (EFBIG rather than ENOSPC).
    """

    def runner(c: Ctx, commands):
        if not can_mount():
            first = [run_cmd(commands[0], c.proj, fsize=free_kb * 1024)]
            return first + [run_cmd(a, c.proj) for a in commands[1:]]
        return _on_tmpfs(c, commands, free_kb)

    return runner


def with_env(**extra):
    """Run the commands one by one with ``extra`` in the environment (a locale, FLUOROCAL_THREADS)."""

    def runner(c: Ctx, commands):
        environ = {**env(), **extra}
        done = [
            subprocess.run(a, cwd=c.proj, env=environ, capture_output=True, text=True, errors="replace")
            for a in commands
        ]
        return [(p.returncode, p.stdout + p.stderr) for p in done]

    return runner
