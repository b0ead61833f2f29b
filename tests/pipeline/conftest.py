"""Fixtures shared by the pipeline tests of the undistortion maps."""

from __future__ import annotations

import pytest

from tests.pipeline.synthetic_calibration import synthetic_calibration


@pytest.fixture()
def saved(tmp_path):
    """The synthetic calibration (:func:`synthetic_calibration`) saved in its own folder; its path."""
    path = tmp_path / "cal" / "calibration.json"
    path.parent.mkdir()
    synthetic_calibration().save(path)
    return path
