"""Shared test fixtures: paths to ../shared data (skipped with a reason when absent)."""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
SHARED_DATA = SHARED / "data"


@pytest.fixture(scope="session")
def shared_data():
    """Path to ../shared/data; skips the test when the folder is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def rinex_path(shared_data):
    p = shared_data / "rinex" / "brdc0010.22n"
    if not p.is_file():
        pytest.skip(f"RINEX file not found at {p}")
    return p
