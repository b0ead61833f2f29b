"""Fixtures shared by the pipeline tests of the undistortion maps."""

from __future__ import annotations

import pytest
from fluorocal.stages.field import CorrectionField


@pytest.fixture()
def saved(tmp_path):
    """The synthetic calibration of ``test_undistort_api`` saved in its own folder; its path."""
    from tests.pipeline.test_undistort_api import _calibration  # here: that module imports this one

    path = tmp_path / "cal" / "calibration.json"
    path.parent.mkdir()
    _calibration().save(path)
    return path


def count_map_computations(monkeypatch) -> list:
    """The calls of :meth:`CorrectionField.remap_maps` from now on (the maps computed, not read from the cache)."""
    calls = []
    original = CorrectionField.remap_maps

    def counted(self, *args):
        calls.append(args)
        return original(self, *args)

    monkeypatch.setattr(CorrectionField, "remap_maps", counted)
    return calls
