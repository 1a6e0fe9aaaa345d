"""Shared fixtures. Real data lives in ../shared/data beside the checkout; tests that need it
skip with a clear message where it is absent."""
from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA} (the shared/ folder beside the repo)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def lego_dir(shared_data) -> Path:
    p = shared_data / "nerf_synthetic_lego_400"
    if not p.is_dir():
        pytest.skip(f"{p} not found")
    return p
