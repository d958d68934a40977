"""The environment config of a task id: ``load_env_config`` picks OTR-G1-Track-v0's
(``envs.config.tracking``) or OTR-G1-BoxTrack-v0's (``envs.config.box``)."""

from __future__ import annotations

from pathlib import Path

from envs.config.box import load_box_config
from envs.config.tracking import TrackEnvCfg, load_track_config

TRACK_TASK = "OTR-G1-Track-v0"
BOX_TASK = "OTR-G1-BoxTrack-v0"


def load_env_config(task: str, path: str | Path | None = None, overrides: dict | None = None) -> TrackEnvCfg:
    """The environment config of ``task`` (its YAML, or ``path``) with ``overrides``."""
    if task == BOX_TASK:
        return load_box_config(path, overrides)
    if task == TRACK_TASK:
        return load_track_config(path, overrides)
    raise ValueError(f"unknown task '{task}' (expected {TRACK_TASK} or {BOX_TASK})")
