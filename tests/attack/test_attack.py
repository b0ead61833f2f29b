"""The attack battery (issue 13) as tests: each case one test, named by the case, run on its own copy.

Per case: no traceback, no silent wrong result, nothing written or deleted outside the output and cache folders,
no code run from data, a refusal one clear line naming its file, key or argument, and good input not refused
(:mod:`tests.attack`). The cases are split into test classes of similar running time, so that
``--dist loadscope`` (which keeps a class on one worker) spreads them over the workers.
"""

from __future__ import annotations

import pytest

from tests.attack.cases import (
    cache,
    calibration,
    clean,
    commands,
    config,
    faults,
    frames,
    issue28,
    permissions,
    phantom,
    undistort,
)
from tests.attack.harness import run_case

pytestmark = pytest.mark.check


def _each_case_of(*tables):
    """Parametrise ``case`` over the cases of ``tables``, each test named by its case."""
    cases = [case for table in tables for case in table.cases()]
    return pytest.mark.parametrize("case", cases, ids=[case.name for case in cases])


def _passes(case, attack_base, tmp_path) -> None:
    outcome = run_case(case, attack_base, tmp_path / case.name)
    found = outcome.problems
    assert not found, f"{', '.join(found)}: {outcome.line()}\nmessage: {outcome.message}\nnote: {case.note}"


class TestFilesAndArguments:
    """The project file, permissions, calibration files, undistort and the other commands (~220 s of cases)."""

    @_each_case_of(config, permissions, calibration, undistort, commands)
    def test_case(self, case, attack_base, tmp_path):
        _passes(case, attack_base, tmp_path)


class TestPhantomAndFrames:
    """The phantom table, the frames and their pairing (~230 s)."""

    @_each_case_of(phantom, frames)
    def test_case(self, case, attack_base, tmp_path):
        _passes(case, attack_base, tmp_path)


class TestCache:
    """The cache tampered with, and ``cache clean`` (~225 s)."""

    @_each_case_of(cache, clean)
    def test_case(self, case, attack_base, tmp_path):
        _passes(case, attack_base, tmp_path)


class TestFaults:
    """SIGKILL, concurrent runs, a full disk, and the cases of issue 28 (~195 s)."""

    @_each_case_of(faults, issue28)
    def test_case(self, case, attack_base, tmp_path):
        _passes(case, attack_base, tmp_path)
