"""Typed configuration of the tracking environments, one module per concept:
``tracking`` (the MDP of OTR-G1-Track-v0, shared by both tasks), ``box`` (OTR-G1-BoxTrack-v0's
objects on top) and ``tasks`` (``load_env_config``: the config of a task id). Defaults are the
numbers of docs/environment.md; ``configs/env/track.yaml`` and ``box.yaml`` mirror them."""

from envs.config.box import (
    BOX_CONFIG,
    BoxEnvCfg,
    ObjectOverrideCfg,
    ObjectRandomizationCfg,
    ObjectsCfg,
    load_box_config,
)
from envs.config.tasks import BOX_TASK, TRACK_TASK, load_env_config
from envs.config.tracking import (
    DEFAULT_CONFIG,
    ActionCfg,
    CommandCfg,
    ObservationCfg,
    ObsTermCfg,
    RandomizationCfg,
    ResetNoiseCfg,
    RewardTermCfg,
    SimCfg,
    TerminationTermCfg,
    TerrainCfg,
    TrackEnvCfg,
    load_track_config,
)

__all__ = ["BOX_CONFIG", "BOX_TASK", "DEFAULT_CONFIG", "TRACK_TASK", "ActionCfg", "BoxEnvCfg", "CommandCfg",
           "ObjectOverrideCfg", "ObjectRandomizationCfg", "ObjectsCfg", "ObsTermCfg", "ObservationCfg",
           "RandomizationCfg", "ResetNoiseCfg", "RewardTermCfg", "SimCfg", "TerminationTermCfg", "TerrainCfg",
           "TrackEnvCfg", "load_box_config", "load_env_config", "load_track_config"]
