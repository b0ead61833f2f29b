"""Run a command; write the CPU time of its main process and of the processes it left behind (Linux only).

``fluorocal run`` computes its per-frame stages on a pool whose workers are children of a
multiprocessing fork server, itself a child of the main process that never waits for it: the
fork server outlives the main process by a moment, is re-parented, and its CPU and its workers'
never reach the caller's ``RUSAGE_CHILDREN`` (nor ``time``'s). This process makes itself a child
subreaper (``prctl(PR_SET_CHILD_SUBREAPER)``, Linux >= 3.4) so that such orphans are re-parented to
it, waits for the command, then for every orphan, reading each one's CPU from ``/proc/<pid>/stat``
while it is a zombie: its own, and its reaped children's (a fork server's workers).

Usage: ``python benchmarks/tree_cpu.py OUT.json COMMAND [ARG ...]``: the command's output and exit
status pass through; OUT.json gets ``main_s`` (the main process, with any children it waited for),
``orphans_own_s`` (the orphans' own: the fork server's imports, and multiprocessing's resource tracker)
and ``orphans_children_s`` (what they reaped: the workers), in CPU seconds, user + system.
"""

from __future__ import annotations

import ctypes
import json
import os
import sys
from pathlib import Path

PR_SET_CHILD_SUBREAPER = 36  # linux/prctl.h


def become_subreaper() -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER) failed (Linux only)")


def zombie_cpu(pid: int) -> tuple[float, float]:
    """CPU seconds of an exited, not yet reaped process: its own, and its reaped children's."""
    stat = Path(f"/proc/{pid}/stat").read_text()
    fields = stat[stat.rindex(")") + 2 :].split()  # after the command name, which may hold spaces
    utime, stime, cutime, cstime = (int(f) for f in fields[11:15])  # proc(5) fields 14-17
    tick = os.sysconf("SC_CLK_TCK")
    return (utime + stime) / tick, (cutime + cstime) / tick


def run(command: list[str]) -> tuple[int, dict]:
    """(the command's exit code, its CPU seconds: ``main_s``, ``orphans_own_s``, ``orphans_children_s``)."""
    become_subreaper()
    pid = os.posix_spawnp(command[0], command, os.environ)
    _, status, usage = os.wait4(pid, 0)
    cpu = {"main_s": usage.ru_utime + usage.ru_stime, "orphans_own_s": 0.0, "orphans_children_s": 0.0}
    while True:  # the orphans: each fork server exits once the main process is gone
        try:
            orphan = os.waitid(os.P_ALL, 0, os.WEXITED | os.WNOWAIT).si_pid
        except ChildProcessError:
            break
        own, children = zombie_cpu(orphan)
        cpu["orphans_own_s"] += own
        cpu["orphans_children_s"] += children
        os.waitpid(orphan, 0)
    return os.waitstatus_to_exitcode(status), cpu


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        raise SystemExit("usage: tree_cpu.py OUT.json COMMAND [ARG ...]")
    code, cpu = run(argv[1:])
    Path(argv[0]).write_text(json.dumps(cpu))
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
