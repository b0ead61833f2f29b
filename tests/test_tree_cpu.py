"""benchmarks/tree_cpu.py counts a fork server's pool workers, which the caller's RUSAGE_CHILDREN misses.

The truth: each worker's own ``process_time`` when its task ends (what the kernel charges it until
then), reported back with its result; a worker's exit after that costs a few clock ticks.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

TREE_CPU = Path(__file__).parents[1] / "benchmarks" / "tree_cpu.py"

POOL = """
import json, multiprocessing, os, sys, time
from concurrent.futures import ProcessPoolExecutor

def burn(seconds):
    t0 = time.process_time()
    while time.process_time() - t0 < seconds:
        pass
    return os.getpid(), time.process_time()

if __name__ == "__main__":
    context = multiprocessing.get_context("forkserver")
    with ProcessPoolExecutor(2, mp_context=context) as pool:
        done = list(pool.map(burn, [0.4, 0.4, 0.4]))
    last = {pid: max(t for p, t in done if p == pid) for pid, _ in done}  # a worker's CPU only grows
    json.dump({"workers_s": sum(last.values()), "main_s": time.process_time()}, open(sys.argv[1], "w"))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_CHILD_SUBREAPER is Linux only")
def test_workers_of_a_fork_server_are_counted(tmp_path):
    script = tmp_path / "pool.py"
    script.write_text(POOL)
    measured, truth = tmp_path / "cpu.json", tmp_path / "truth.json"
    proc = subprocess.run([sys.executable, str(TREE_CPU), str(measured), sys.executable, str(script), str(truth)])
    assert proc.returncode == 0
    cpu, true = json.loads(measured.read_text()), json.loads(truth.read_text())
    assert true["workers_s"] >= 1.2  # the three burns, whichever worker ran them
    # clock ticks (10 ms) and each worker's exit after its last task
    assert true["workers_s"] - 0.05 <= cpu["orphans_children_s"] <= true["workers_s"] + 0.3
    # the main process alone: it burnt nothing; its figure is what RUSAGE_CHILDREN alone would say
    assert cpu["main_s"] >= true["main_s"] - 0.05
    assert cpu["main_s"] < 1.0


def test_exit_status_passes_through(tmp_path):
    measured = tmp_path / "cpu.json"
    proc = subprocess.run([sys.executable, str(TREE_CPU), str(measured), sys.executable, "-c", "raise SystemExit(3)"])
    assert proc.returncode == 3
    assert json.loads(measured.read_text())["orphans_children_s"] == 0.0
