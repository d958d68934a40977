"""``otr train``: PPO (rsl-rl-lib's OnPolicyRunner) on OTR-G1-Track-v0 or (``--task``) OTR-G1-BoxTrack-v0.

config (configs/agents/ppo_track.yaml + CLI) -> vector env -> VecEnv adapter -> runner.

``--reference`` takes one or more reference files, folders of them or clip-list files
(``.txt``: one path per line): all their clips form one motion library, trained by one policy
with adaptive start sampling over (clip, time bin) (``envs.mdp.commands``). A clip that cannot
be loaded is reported by name and skipped (``agents.library``); per-clip success, MPJPE and
segment length go to TensorBoard as ``clip/<label>/…``.

A new run gets a folder ``<log-dir>/<task>_<reference name>_<timestamp>/`` (see agents.runs);
``--resume RUN`` continues a run in its own folder from its latest checkpoint (or the given
``model_<it>.pt``): same iteration counter, optimiser, normalisers, adaptive-sampling
statistics. ``--iterations N`` runs N more iterations; without it training runs up to the
config's ``max_iterations`` in total. ``--max-minutes M`` stops after the first iteration that
ends past M minutes of learning (the clock starts with the first rollout: environment build
and compilation are not charged). Ctrl-C, like the budget, stops between two iterations and
writes a checkpoint first.

Several GPUs: ``torchrun --nproc-per-node N -m otr_gym.cli train …`` or ``otr train --gpus N``
(``agents.distributed``): N ranks of ``--num-envs`` worlds each, gradients averaged by rsl-rl,
rank 0 writing the run; stopping (budget, Ctrl-C) and resuming work the same.

``--set KEY=VALUE`` (repeatable) overrides any key of the training config by its dotted path,
the environment's under ``env.`` (the task's configs/env YAML layout); values are YAML, e.g.
``--set env.rewards.hand_contact.weight=0`` (an ablation) or
``--set env.objects.overrides.largebox.mesh=largebox.obj`` (a reference without embedded mesh)
or ``--set env.terrain.meshes.motion_crawl_slope=terrain_slope.obj`` (a clip recorded on
terrain, ``envs.terrain``; clip lists can say ``crawl.npz terrain=slope.obj``). They are stored
in the run (terrain mesh paths made absolute), so evaluation, export and play use them too.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import random
import subprocess
import sys
import time
from pathlib import Path

import gymnasium
import numpy as np
import torch

from agents import distributed, runs
from agents.config import TrainCfg, load_train_config, train_config_from_dict
from agents.library import ClipLibrary, prepare_library, with_terrain
from agents.runner import TrackingRunner
from agents.stopping import StopConditions, TrainingStopped
from agents.vecenv import RslRlVecEnv, make_vec_env
from envs.config import TrackEnvCfg, load_env_config
from envs.config.box import BOX_DEFAULT_ACTOR
from envs.config.tasks import BOX_TASK
from otr_gym.config import merge, parse_sets
from otr_gym.reference import InvalidReferenceError

PROJECT_ROOT = Path(__file__).resolve().parents[1]


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--task", default=None, help="environment id (default: the config's, OTR-G1-Track-v0)")
    parser.add_argument("--reference", nargs="+", metavar="REF",
                        help="reference .npz files, folders of them or clip lists (.txt, one path per line): "
                        "one policy for all their clips (required unless --resume)")
    parser.add_argument("--num-envs", type=int, help="parallel environments per GPU (default: config, 4096)")
    parser.add_argument("--device", help="torch/warp device: cuda, cuda:K or cpu (default: cuda if available; "
                        "under torchrun every rank uses cuda:LOCAL_RANK)")
    parser.add_argument("--gpus", type=int, default=1, help="GPUs of this host to train on: N > 1 re-launches "
                        "through torchrun, one rank per GPU (with --device cpu: N CPU processes, gloo)")
    parser.add_argument("--iterations", type=int, help="PPO iterations to run now (default: up to the "
                        "config's max_iterations in total)")
    parser.add_argument("--max-minutes", type=float, help="wall-clock budget of the learning loop, minutes")
    parser.add_argument("--log-dir", default="runs", help="parent folder of new run folders (default: runs/)")
    parser.add_argument("--resume", metavar="RUN", help="run folder (latest checkpoint) or model_<it>.pt to continue")
    parser.add_argument("--seed", type=int, help="random seed (default: config, 42)")
    parser.add_argument("--save-interval", type=int, help="checkpoint every N iterations (default: config, 500)")
    parser.add_argument("--config", help="training YAML (default: configs/agents/ppo_track.yaml)")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config key by dotted path (YAML value), e.g. "
                        "env.rewards.hand_contact.weight=0; repeatable")


def _overrides(args: argparse.Namespace) -> dict:
    keys = {"task": args.task, "num_envs": args.num_envs, "seed": args.seed, "save_interval": args.save_interval}
    return merge(parse_sets(getattr(args, "sets", []) or []), {k: v for k, v in keys.items() if v is not None})


@dataclasses.dataclass
class TrainSetup:
    """Everything ``otr train`` settles before the (slow) environment is built, each read once:
    the training config, the task's env config, the clip library (clip lists parsed, clips
    loaded and prepared), which the environment takes as they are."""

    cfg: TrainCfg  # its ``env`` overrides as the run records them (``with_terrain``: clip-list meshes added)
    env_cfg: TrackEnvCfg  # the task's env config under the given overrides; clip-list meshes ride with the clips
    library: ClipLibrary
    run_dir: Path | None  # None: a new run (its folder is made once the environment stands)
    ckpt: runs.Checkpoint | None  # the checkpoint to resume
    record: dict  # the run record (config.yaml)


def _setup(args: argparse.Namespace) -> TrainSetup:
    """Read and check the configs, the references and the run to resume."""
    if args.iterations is not None and args.iterations < 1:
        raise ValueError(f"--iterations must be >= 1, got {args.iterations}")
    if args.resume:
        ckpt = runs.resolve_checkpoint(args.resume)
        if runs.load_checkpoint(ckpt).get("policy_only"):
            raise ValueError(f"{ckpt.path}: a policy-only checkpoint (no critic or optimizer state, carried for "
                             "evaluation) cannot resume training; resume from the run's full checkpoint")
        record = runs.run_config(ckpt.run_dir)
        cfg = train_config_from_dict(merge(record["train"], _overrides(args)))
        reference = args.reference or record["reference"]
        run_dir = ckpt.run_dir
        if args.iterations is None and ckpt.iteration + 1 >= cfg.max_iterations:
            raise ValueError(f"{ckpt.path}: the run already completed max_iterations {cfg.max_iterations} "
                             "(pass --iterations N to train further)")
    else:
        if not args.reference:
            raise ValueError("--reference is required for a new run (or give --resume RUN)")
        ckpt, record = None, {}
        cfg = load_train_config(args.config, _overrides(args))
        reference = args.reference
        run_dir = None
    if cfg.task == BOX_TASK and not {"actor", "policy"} & set((cfg.env or {}).get("observations") or {}):
        # the run records its actor by name, so that a later change of the default does not
        # change what its checkpoints are evaluated, played and resumed with
        observations = {**((cfg.env or {}).get("observations") or {}), "actor": BOX_DEFAULT_ACTOR}
        cfg = dataclasses.replace(cfg, env={**(cfg.env or {}), "observations": observations})
    env_cfg = load_env_config(cfg.task, overrides=cfg.env or None)
    library = prepare_library(reference, env_cfg.command, report=int(os.environ.get("RANK", "0")) == 0)
    cfg = dataclasses.replace(cfg, env=with_terrain(cfg.env, library))
    record.update(train=cfg.to_dict(), reference=library.source, reference_info=library.info())
    record.setdefault("sessions", []).append({
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "args": {k: v for k, v in vars(args).items() if v is not None and not callable(v) and k != "argv"},
        "resumed_from": str(ckpt.path) if ckpt else None})
    return TrainSetup(cfg, env_cfg, library, run_dir, ckpt, record)


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def train(args: argparse.Namespace) -> int:
    ctx = distributed.setup(args.device)
    try:
        return _train(args, ctx)
    finally:
        distributed.shutdown(ctx)


def _train(args: argparse.Namespace, ctx: distributed.Context) -> int:
    device = ctx.device
    setup = _setup(args)
    cfg, library, run_dir, ckpt, record = setup.cfg, setup.library, setup.run_dir, setup.ckpt, setup.record
    seed = cfg.seed + ctx.rank  # ranks explore differently
    record["device"] = str(device)
    record["world_size"] = ctx.world_size
    record["sessions"][-1]["world_size"] = ctx.world_size
    _seed_everything(seed)
    # process-wide, like the seed: the networks' float32 matmuls (the MDP's maths is element-wise)
    torch.backends.cuda.matmul.allow_tf32 = cfg.tf32_matmul

    env = make_vec_env(cfg.task, library.clips, cfg.num_envs, str(device), setup.env_cfg, seed=seed)
    stop = StopConditions(args.max_minutes)
    vec = RslRlVecEnv(env, cfg.num_steps_per_env, seed=seed, stop=stop)
    if ctx.is_main:
        if run_dir is None:
            run_dir = runs.create_run_dir(args.log_dir, cfg.task, library.name)
        print(f"run folder: {run_dir}")
        runs.write_yaml(run_dir / runs.CONFIG_FILE, record)
        runs.write_json(run_dir / runs.ENV_SPEC_FILE, {
            "task": cfg.task, "num_actions": vec.num_actions, "observation_dims": vec.vec.obs_dims,
            "policy_metadata": vec.vec.policy_metadata(), "clips": vec.clip_labels})
        if len(vec.clip_labels) > 1 or library.skipped:
            print(f"motion library: {len(vec.clip_labels)} clip(s): {', '.join(vec.clip_labels)}"
                  + (f"; {len(library.skipped)} skipped" if library.skipped else ""))
    run_dir = distributed.broadcast_object(run_dir, ctx)

    runner = TrackingRunner(vec, cfg.to_rsl_rl(), log_dir=str(run_dir) if ctx.is_main else None, device=str(device))
    runner.add_git_repo_to_log(str(PROJECT_ROOT))
    if ckpt is not None:
        runner.load(str(ckpt.path), map_location=str(device))
        if ctx.is_main:
            print(f"resumed from {ckpt.path} at iteration {runner.current_learning_iteration}")
    iterations = args.iterations or cfg.max_iterations - runner.current_learning_iteration
    status = 0
    with stop:
        try:
            runner.learn(iterations, init_at_random_ep_len=cfg.init_at_random_ep_len and ckpt is None)
        except TrainingStopped as stopped:
            if ctx.is_main:
                print(f"training stopped: {stopped.reason} after {stopped.completed} iteration(s) of this session")
            if stopped.completed > 0:
                runner.save(str(run_dir / f"model_{runner.current_learning_iteration}.pt"))
            status = 130 if stop.interrupted else 0
        finally:
            if runner.logger.writer is not None:
                runner.logger.writer.close()
    if ctx.is_main:
        try:
            latest = runs.checkpoints(run_dir)[-1]
            print(f"latest checkpoint: {latest.path} (iteration {latest.iteration})")
        except runs.RunError:
            print("no checkpoint written (stopped before the first iteration completed)")
    return status


def main(args: argparse.Namespace) -> int:
    if args.gpus < 1:
        print(f"otr train: --gpus must be >= 1, got {args.gpus}", file=sys.stderr)
        return 2
    if args.gpus > 1 and not distributed.launched_by_torchrun():
        command = distributed.torchrun_command(args.gpus, list(getattr(args, "argv", sys.argv[1:])))
        print("+ " + " ".join(command), flush=True)
        return subprocess.call(command)
    try:
        return train(args)
    except (runs.RunError, InvalidReferenceError, ValueError, FileNotFoundError, gymnasium.error.Error) as exc:
        print(f"otr train: {exc}", file=sys.stderr)
        return 2
