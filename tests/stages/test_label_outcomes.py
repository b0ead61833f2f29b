"""benchmarks/label_varied.py ``--outcomes``: full labellings grouped into the distinct labellings they reach.

The truth is constructed: a labelling found again with one label of ten changed is the same outcome (each gives 90 %
of its detections the other's bead, as the search merges them), the same detections slipped by one bead are another,
and a labelling that diverged (None) counts as a labelling that reaches nothing.
"""

from __future__ import annotations

import functools
import importlib.util
import sys
from pathlib import Path

import numpy as np

LABEL_VARIED = Path(__file__).parents[2] / "benchmarks" / "label_varied.py"


@functools.cache
def _label_varied():
    spec = importlib.util.spec_from_file_location("label_varied_under_test", LABEL_VARIED)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def _labelling(beads) -> dict:
    return {"det": np.arange(len(beads)), "bead": np.asarray(beads)}


def test_outcomes_group_labellings_found_again_and_tell_slips_apart():
    label_varied = _label_varied()
    truth = _labelling(range(10))
    again = _labelling([*range(9), 42])  # 9 of 10 labels the truth's
    slip = _labelling(range(1, 11))  # every detection one bead over
    calls = [("start", truth), ("start", again), ("rival", slip), ("rival", None), ("rival", truth)]
    counts = label_varied.outcome_counts(calls)
    assert counts["start labellings"] == 2
    assert counts["rival labellings"] == 3
    assert counts["distinct outcomes"] == 2


def test_outcomes_tell_apart_labellings_agreeing_on_less_than_nine_tenths():
    label_varied = _label_varied()
    calls = [("start", _labelling(range(10))), ("start", _labelling([*range(8), 42, 43]))]
    assert label_varied.outcome_counts(calls)["distinct outcomes"] == 2
