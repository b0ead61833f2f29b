"""Hostile and careless input, faults and tampering, run through the command line as a user would (issue 13).

The battery itself (its harness and its 420 cases) lives in ``tests/attack`` and runs as tests under
``make check``; this script runs the same cases with a line per case and the totals, for the benchmark page.
Builds one small simulated biplanar project, runs it once so its cache is warm, then runs each case on its own
copy beside a ``sibling/`` folder (a user's other work); see ``tests/attack/__init__.py`` for what is recorded.

Usage: ``python benchmarks/attack.py [--quick] [--only CLASS[,CLASS]] [--list] [--jobs N] [--keep DIR]``.
``--quick`` runs the first case of each class. Targets (issue 13): 0 tracebacks, 0 silent wrong results,
0 files written or deleted outside the output and cache folders, 0 code executed from data.
A full disk is a tmpfs mounted for the case when the process may mount one (root), else RLIMIT_FSIZE
(``EFBIG`` instead of ``ENOSPC``).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.attack.cases import all_cases  # noqa: E402
from tests.attack.harness import Outcome, build_base, run_case  # noqa: E402


def check_clean_against_truth(base: Path) -> str:
    """How far the clean run's interior orientation is from the simulator's truth, per system."""
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


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="the first case of each class only")
    ap.add_argument("--only", help="comma-separated classes or case names")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--jobs", type=int, default=2, help="cases run at once (default: 2)")
    ap.add_argument("--keep", type=Path, help="work here (kept) instead of a temporary folder")
    return ap


def selected(args) -> list:
    """The cases ``--only`` and ``--quick`` select, in the battery's order."""
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
    return cases


def _clean_base(work: Path) -> Path:
    """The clean project under ``work/sandbox/base``: built, or reused from a finished earlier ``--keep`` run."""
    base = work / "sandbox" / "base"
    if not (base / "proj" / "out" / "calibration.json").is_file():
        shutil.rmtree(work / "sandbox", ignore_errors=True)
        try:
            print(build_base(base))
        except RuntimeError as e:
            raise SystemExit(str(e)) from None
    return base


def run_all(cases: list, base: Path, cases_dir: Path, jobs: int) -> list[Outcome]:
    """Run ``cases`` ``jobs`` at a time, printing each one's line as it ends; their outcomes in order."""
    with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        futures = {pool.submit(run_case, k, base, cases_dir / f"{i:03d}_{k.name}"): i for i, k in enumerate(cases)}
        done = {}
        for fut in concurrent.futures.as_completed(futures):
            i = futures[fut]
            done[i] = fut.result()
            print(f"{i:3d} {done[i].line()}", flush=True)
    return [done[i] for i in sorted(done)]


def totals(outcomes: list[Outcome], seconds: float) -> bool:
    """Print the totals; whether the targets are met."""
    tracebacks = sum(o.traceback for o in outcomes)
    wrong = sum(bool(o.wrong) for o in outcomes)
    outside = sum(bool(o.outside) for o in outcomes)
    code = sum(o.code_ran for o in outcomes)
    weak = sum(o.weak for o in outcomes)
    refused_good = sum(o.refused_good for o in outcomes)
    print(
        f"{len(outcomes)} cases in {len({o.case.klass for o in outcomes})} classes, {seconds:.0f} s "
        f"(load {os.getloadavg()[0]:.1f})"
    )
    print(
        f"tracebacks: {tracebacks}; silent wrong results: {wrong}; outside writes/deletes: {outside}; "
        f"code from data: {code}; weak messages: {weak}; good input refused: {refused_good}"
    )
    met = not any(o.problems for o in outcomes)  # what `make check` asserts case by case
    print(f"targets (every total 0, as the battery's tests assert): {'met' if met else 'NOT met'}")
    return met


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    cases = selected(args)
    if args.list:
        for k in cases:
            print(f"{k.klass:12s} {k.name:40s} expect {k.expect}")
        print(f"{len(cases)} cases")
        return 0
    work = args.keep or Path(tempfile.mkdtemp(prefix="fluorocal-attack-"))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    base = _clean_base(work)
    print(f"clean run against the simulator's truth: {check_clean_against_truth(base)}")
    cases_dir = work / "sandbox" / "cases"
    shutil.rmtree(cases_dir, ignore_errors=True)
    cases_dir.mkdir()
    met = totals(run_all(cases, base, cases_dir, args.jobs), time.perf_counter() - t0)
    if args.keep is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if met else 1


if __name__ == "__main__":
    import docpage

    sys.exit(docpage.run(__file__, main))
