"""The map cache's key follows the code that computes the maps: no hand-kept version number to forget.

The code is changed here without touching a file: the source text that :mod:`fluorocal.codehash`
reads for one module is monkeypatched, as an edit of that module would change it.
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal import codehash
from fluorocal.calibration import Calibration
from fluorocal.maps import map_key, maps_code_digest, maps_folder

from tests.pipeline.synthetic_calibration import count_map_computations


@pytest.fixture()
def fresh_digest():
    """The digest computed anew in the test, and anew after it (the monkeypatched source gone)."""
    maps_code_digest.cache_clear()
    yield
    maps_code_digest.cache_clear()


def _edit(monkeypatch, module: str, appended: str) -> None:
    """Make ``module``'s source, as the code digest reads it, end with ``appended``."""
    original = codehash._module_source

    def edited(name):
        found = original(name)
        if name == module and found is not None:
            return found[0], found[1] + appended
        return found

    monkeypatch.setattr(codehash, "_module_source", edited)
    maps_code_digest.cache_clear()


def test_unchanged_code_reuses_the_entry_and_changed_code_recomputes(saved, monkeypatch, fresh_digest):
    calls = count_map_computations(monkeypatch)
    first = np.stack(Calibration.load(saved).remap_maps("B"))
    again = np.stack(Calibration.load(saved).remap_maps("B"))  # a new process, in effect: only the disk is shared
    assert len(calls) == 1 and len(list(maps_folder(saved).glob("*.npy"))) == 1
    np.testing.assert_array_equal(again, first)
    key = map_key("0" * 64, "B", None, (96, 64))
    # a comment is no change of the code: same key, the entry reused
    _edit(monkeypatch, "fluorocal.stages.field", "\n# a comment\n")
    assert map_key("0" * 64, "B", None, (96, 64)) == key
    Calibration.load(saved).remap_maps("B")
    assert len(calls) == 1
    # a change of the code that computes the maps: another key, the maps computed anew beside the old entry
    _edit(monkeypatch, "fluorocal.stages.field", "\n\ndef _new_helper():\n    return 1\n")
    assert map_key("0" * 64, "B", None, (96, 64)) != key
    recomputed = np.stack(Calibration.load(saved).remap_maps("B"))
    assert len(calls) == 2 and len(list(maps_folder(saved).glob("*.npy"))) == 2
    np.testing.assert_array_equal(recomputed, first)  # the edit changed no value: the same maps


@pytest.mark.parametrize(
    "module", ["fluorocal.calibration", "fluorocal.stages.orientation", "fluorocal.stages.undistort"]
)
def test_every_module_on_the_maps_path_is_in_the_key(monkeypatch, fresh_digest, module):
    # the calibration chooses and remaps the field, orientation interpolates it, undistort checks the maps
    # (reached through the calibration's imports)
    key = map_key("0" * 64, "A", {"orbit": 15, "tilt": 0}, (96, 64))
    _edit(monkeypatch, module, "\n\n_CHANGED = 1\n")
    assert map_key("0" * 64, "A", {"orbit": 15, "tilt": 0}, (96, 64)) != key
