"""Shared test fixtures: the real radiographs in ../shared/data (skipped when absent)."""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data" / "arcadis"


@pytest.fixture(scope="session")
def arcadis_dir() -> Path:
    """Directory of the real ARCADIS frames; skips the test on machines without ../shared/data."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real radiographs not present at {SHARED_DATA} (they live only in ../shared/data)")
    return SHARED_DATA
