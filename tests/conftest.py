"""Shared fixtures. Real data lives in ../shared/data (not part of the project): tests that
need it skip with a reason when it is absent; the core suite uses generated data only."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

SHARED_DATA = Path(os.environ.get("OTR_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))

# Headless rendering in tests: EGL unless the caller chose a GL backend (must precede `import mujoco`).
if sys.platform.startswith("linux"):
    os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not (SHARED_DATA / "README.md").is_file():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (set OTR_SHARED_DATA to use it)")
    return SHARED_DATA


# ------------------------------------------------------------------ generated G1 references
@pytest.fixture(scope="session")
def standing_reference(tmp_path_factory) -> Path:
    """A 4 s standing clip (default pose, Reference.from_qpos) saved as our npz."""
    from agents.procedural import standing_reference as stand

    return stand(duration_s=4.0).save(tmp_path_factory.mktemp("refs") / "stand.npz")


@pytest.fixture(scope="session")
def walking_reference(tmp_path_factory) -> Path:
    """A 3 s procedural walk (4 footsteps) at 30 fps, so that loading resamples it to 50 fps."""
    from agents.procedural import WalkSpec
    from agents.procedural import walking_reference as walk

    return walk(WalkSpec(steps=4, fps=30.0)).save(tmp_path_factory.mktemp("refs") / "walk.npz")
