"""The retargeter's configuration: one typed dataclass tree, read from YAML.

``load_config()`` gives ``configs/retarget/default.yaml`` (the paper's numbers, see
``docs/method.md``); a user's YAML overrides any key, and top-level keyword overrides (mode,
fps) are applied last. Every problem raises ``ConfigError`` naming the file or value.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from otr_gym.config import from_dict, load_yaml_mapping
from retarget.geometry.channels import GeometryConfig
from retarget.solver.balance import BalanceConfig
from retarget.solver.flight import FlightConfig
from retarget.solver.grasp import GraspCfg
from retarget.solver.problem import SolverConfig
from retarget.solver.residuals import InteractionConfig
from retarget.solver.stance import StanceConfig
from retarget.solver.style import StyleConfig
from retarget.solver.trajectory import TrajectoryCfg

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs" / "retarget"

@dataclass(frozen=True)
class RetargetConfig:
    """Everything ``retarget.clip.retarget_demonstration`` needs; mirrored by configs/retarget/default.yaml."""

    #: native | scaled | robot-only (docs/method.md "Modes").
    mode: str = "native"
    #: Rate the demonstration is resampled to and solved at (Hz); None keeps the demonstration's.
    fps: float | None = 50.0
    #: Spacing of the convex-hull guard points on the robot links (m, ``retarget.solver.probes``).
    guard_spacing_m: float = 0.008
    #: Cap on area probes per robot link (None: the paper's density everywhere).
    max_probes_per_link: int | None = None
    #: Seed of every probe sampling.
    seed: int = 0
    #: Which G1 links share one OT plan with their human parts (``retarget.inputs.human.LINK_GROUPINGS``:
    #: none | hand | shared_parts); "none" matches each link alone, as the references were made.
    links_together: str = "none"
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    interaction: InteractionConfig = field(default_factory=InteractionConfig)
    style: StyleConfig = field(default_factory=StyleConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    stance: StanceConfig = field(default_factory=StanceConfig)
    balance: BalanceConfig = field(default_factory=BalanceConfig)
    flight: FlightConfig = field(default_factory=FlightConfig)
    trajectory: TrajectoryCfg = field(default_factory=TrajectoryCfg)
    grasp: GraspCfg = field(default_factory=GraspCfg)

class ConfigError(ValueError):
    """A configuration file or value that cannot be used; the message names it."""

def load_config(path: str | Path | None = None, **overrides) -> RetargetConfig:
    """The configuration of a YAML file (default: configs/retarget/default.yaml), with top-level
    ``overrides`` (e.g. mode, fps) applied. Problems raise ConfigError naming the file."""
    default = CONFIG_DIR / "default.yaml"
    try:
        data = load_yaml_mapping(path, default, "retarget")
        cfg = from_dict(RetargetConfig, data, str(path if path is not None else default))
    except (ValueError, FileNotFoundError, yaml.YAMLError) as exc:
        raise ConfigError(str(exc)) from exc
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if overrides:
        cfg = dataclasses.replace(cfg, **overrides)
    from retarget.solver.problem import MODES, link_clearance

    if cfg.mode not in MODES:
        raise ConfigError(f"unknown mode '{cfg.mode}' (choose from {MODES})")
    from retarget.inputs.human import link_grouping

    try:
        link_grouping(cfg.links_together)
        link_clearance(cfg.solver.link_clearance_m)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    if cfg.fps is not None and not cfg.fps > 0:
        raise ConfigError(f"fps must be > 0, got {cfg.fps}")
    return cfg
