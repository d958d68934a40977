"""Run folders and checkpoints.

A training run is one folder ``<log_dir>/<task>_<reference stem>_<YYYYmmdd-HHMMSS>/``::

    config.yaml          resolved training config + how the run was started (reference, device)
    env_spec.json        the environment's specification (joint order, gains, observation layout, fps)
    model_<it>.pt        rsl-rl checkpoints after iteration <it> (written atomically)
    events.out.tfevents.*  TensorBoard scalars (rewards per term, episode length, success, MPJPE, FPS)
    git/                 code state of the checkout (rsl-rl's logger)

Every file is written to a temporary name in the same folder and renamed, so an interrupted
write never leaves a truncated file under the final name.

``otr runs latest RUN`` prints a run's latest checkpoint, for the shell recipes that carry a run
to another machine (``benchmarks/train_box.sh carry``, ``train_box_gpus.sh pack``); ``otr runs
policy-only RUN --every N --out DIR`` writes policy-only copies of its checkpoints.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import yaml

# the one atomic-output implementation, re-exported for the agents' writers
from otr_gym.io import atomic_path, atomic_write, write_json  # noqa: F401

CONFIG_FILE = "config.yaml"
ENV_SPEC_FILE = "env_spec.json"
_CHECKPOINT = re.compile(r"^model_(\d+)\.pt$")


class RunError(FileNotFoundError):
    """A run folder or checkpoint that cannot be used; the message names the path and the problem."""


@dataclass(frozen=True)
class Checkpoint:
    path: Path
    iteration: int

    @property
    def run_dir(self) -> Path:
        return self.path.parent


def run_name(task: str, reference: str | Path, stamp: str | None = None) -> str:
    """``<task>_<reference stem>_<timestamp>``; a reference folder contributes its own name."""
    ref = Path(reference)
    stem = ref.name if ref.is_dir() else ref.stem
    return f"{task}_{stem}_{stamp or time.strftime('%Y%m%d-%H%M%S')}"


def create_run_dir(log_dir: str | Path, task: str, reference: str | Path) -> Path:
    """A new, empty run folder (a numeric suffix avoids collisions within the same second)."""
    base = Path(log_dir) / run_name(task, reference)
    path, k = base, 1
    while path.exists():
        path, k = base.with_name(f"{base.name}-{k}"), k + 1
    path.mkdir(parents=True)
    return path


def write_yaml(path: str | Path, data: dict) -> Path:
    return atomic_write(path, lambda f: yaml.safe_dump(data, f, sort_keys=False), binary=False)


def read_yaml(path: Path) -> dict:
    if not path.is_file():
        raise RunError(f"{path}: missing (is {path.parent} a training run folder?)")
    data = yaml.safe_load(path.read_text())
    if not isinstance(data, dict):
        raise RunError(f"{path}: expected a YAML mapping")
    return data


def read_env_spec(run_dir: Path) -> dict:
    path = Path(run_dir) / ENV_SPEC_FILE
    if not path.is_file():
        raise RunError(f"{path}: missing (is {run_dir} a training run folder?)")
    return json.loads(path.read_text())


def checkpoints(run_dir: str | Path) -> list[Checkpoint]:
    """The run's checkpoints sorted by iteration; a missing or empty folder raises RunError."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunError(f"{run_dir}: no such run folder")
    found = sorted((Checkpoint(p, int(m.group(1))) for p in run_dir.iterdir()
                    if (m := _CHECKPOINT.match(p.name))), key=lambda c: c.iteration)
    if not found:
        raise RunError(f"{run_dir}: run folder holds no checkpoint (model_<iteration>.pt)")
    return found


def resolve_checkpoint(run_or_checkpoint: str | Path) -> Checkpoint:
    """A checkpoint file as given, or the latest checkpoint of a run folder."""
    path = Path(run_or_checkpoint)
    if path.is_dir():
        return checkpoints(path)[-1]
    if not path.is_file():
        raise RunError(f"{path}: no such run folder or checkpoint file")
    m = _CHECKPOINT.match(path.name)
    if m is None:
        raise RunError(f"{path}: not a checkpoint (expected a run folder or model_<iteration>.pt)")
    return Checkpoint(path, int(m.group(1)))


def load_checkpoint(ckpt: Checkpoint) -> dict:
    """The saved mapping of a checkpoint (on the CPU); a truncated or foreign file raises
    RunError naming it."""
    import pickle

    import torch

    try:
        saved = torch.load(ckpt.path, map_location="cpu", weights_only=False)
    except (RuntimeError, EOFError, OSError, pickle.UnpicklingError) as exc:
        raise RunError(f"{ckpt.path}: not a readable checkpoint ({exc})") from exc
    if not isinstance(saved, dict):
        raise RunError(f"{ckpt.path}: not a checkpoint of this package (a {type(saved).__name__}, not a mapping)")
    return saved


#: What a policy-only checkpoint keeps: the actor (evaluate, play, export, episode_trace), the
#: iteration and the training state the failure map reads; not the critic or the optimizer.
POLICY_ONLY_KEYS = ("actor_state_dict", "iter", "infos")


def write_policy_only(ckpt: Checkpoint, out: str | Path) -> Path:
    """Write ``ckpt`` without its critic and optimizer state to ``out`` (atomically; about a
    sixth of the size, so that a run's intermediate checkpoints can travel back from a GPU
    machine and be evaluated). It is marked ``policy_only``: training cannot resume from it."""
    import torch

    saved = load_checkpoint(ckpt)
    if "actor_state_dict" not in saved:
        raise RunError(f"{ckpt.path}: holds no actor_state_dict")
    slim = {key: saved[key] for key in POLICY_ONLY_KEYS if key in saved}
    slim["policy_only"] = True
    return atomic_write(out, lambda f: torch.save(slim, f))


def every_nth(found: list[Checkpoint], every: int) -> list[Checkpoint]:
    """Of ``found`` (oldest first), those at multiples of ``every`` iterations, the latest left
    out (the caller adds or packs it whole)."""
    if every < 1:
        raise ValueError(f"--every must be >= 1, got {every}")
    return [c for c in found[:-1] if c.iteration % every == 0]


def policy_only_copies(run_dir: str | Path, every: int, out_dir: str | Path) -> list[Path]:
    """Policy-only copies (``write_policy_only``) in ``out_dir`` of the run's checkpoints at
    multiples of ``every`` iterations, all but the latest (which travels whole), same names."""
    chosen = every_nth(checkpoints(run_dir), every)
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    return [write_policy_only(c, Path(out_dir) / c.path.name) for c in chosen]


def run_config(run_dir: str | Path) -> dict:
    """The ``config.yaml`` of a run: {"train": …, "reference": …, "device": …, …}. A box run
    records its actor (``env.observations.actor`` or ``policy``); one that records neither was
    trained before the perception-free actor became the default, with the ``mocap`` actor."""
    config = read_yaml(Path(run_dir) / CONFIG_FILE)
    train = config.get("train") or {}
    if train.get("task") == "OTR-G1-BoxTrack-v0":
        observations = ((train.get("env") or {}).get("observations") or {})
        if "actor" not in observations and "policy" not in observations:
            env = dict(train.get("env") or {})
            env["observations"] = {**observations, "actor": "mocap"}
            config["train"] = {**train, "env": env}
    return config


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """``otr runs``'s sub-commands: ``latest`` and ``policy-only``."""
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    latest = sub.add_parser("latest", help="print the latest checkpoint of a run folder",
                            description="print the latest checkpoint (by iteration) of a run folder")
    latest.add_argument("run", help="run folder")
    slim = sub.add_parser("policy-only", help="policy-only copies of a run's checkpoints every N iterations "
                          "(all but the latest), to evaluate elsewhere",
                          description="policy-only copies (the actor, no critic or optimizer) of a run's checkpoints "
                          "every N iterations, all but the latest (which travels whole)")
    slim.add_argument("run", help="run folder")
    slim.add_argument("--every", type=int, required=True, help="iterations between the copies (the checkpoints at "
                      "multiples of it)")
    slim.add_argument("--out", required=True, help="folder to write them to (same file names)")


def main(args: argparse.Namespace) -> int:
    """``otr runs latest|policy-only``: one path per line on stdout; a folder without checkpoints or
    a bad ``--every``: the message on stderr, exit code 1."""
    try:
        if args.action == "latest":
            print(resolve_checkpoint(args.run).path)
        else:
            for path in policy_only_copies(args.run, args.every, args.out):
                print(path)
    except (RunError, ValueError) as exc:
        print(f"otr runs {args.action}: {exc}", file=sys.stderr)
        return 1
    return 0
