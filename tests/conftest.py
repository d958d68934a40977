"""Shared fixtures. Real data lives in ../shared/data (not part of the project): tests that
need it skip with a reason when it is absent; the core suite uses generated data only."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED_DATA = Path(os.environ.get("OTR_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not (SHARED_DATA / "README.md").is_file():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (set OTR_SHARED_DATA to use it)")
    return SHARED_DATA
