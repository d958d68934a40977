"""``otr evaluate RUN_OR_CHECKPOINT [--reference REF]``: success rate and MPJPE of a policy
(and, for OTR-G1-BoxTrack-v0, the object errors).

Protocol (docs/environment.md §5 success, paper Sec. IV-E MPJPE):

- env i plays clip i mod C from frame 0, without domain randomisation, observation or reset
  noise (the env's ``evaluation`` mode), and the episode ends with the clip, not a time-out;
- the policy's deterministic mean action (``--action-noise STD`` adds Gaussian noise to it: a
  diagnostic of what the policy's exploration noise costs, not part of the protocol);
- success: the clip reached its last frame without a tracking termination; per clip and
  overall, how many episodes each termination ended (``ended_by``; several may fire at once);
- MPJPE: root-relative over the 14 tracked bodies, every step an env is alive, including the
  step it terminates on; per clip and overall (frame-weighted), in mm; beside it, as a
  diagnostic, the same with the reference turned by the anchors' yaw difference
  (``mpjpe_heading_aligned_mm``: posture without heading drift);
- box task (``agents.metrics.ObjectEpisodeMetrics``): object position error (world, cm) mean
  and 95th percentile over the same frames, orientation error (deg), the error at the clip's
  last frame of successful episodes, and per support (ground, table) how often the object
  touches it inside its windows and at the clip's end (the box placed on the table).

Deterministic physics makes every env on one clip identical, so by default one env runs per
clip. ``--randomize`` keeps the training randomisation (friction, centre of mass, joint
offsets, observation noise; pushes off, start at frame 0 without reset noise), so N envs per
clip give a success *rate* that measures robustness.

Given a run folder, every checkpoint is evaluated (the env is built once) and ``--plot``
draws MPJPE and success against the checkpoint iteration; given a checkpoint file, only it.

A motion library (several clips) is reported per clip (a table) and overall: success over all
envs, MPJPE frame-weighted. Clips that fail to load are reported by name and skipped
(``agents.library``); a world whose physics diverges counts as a failure and its non-finite
frame is left out of the MPJPE.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gymnasium
import torch
from tensordict import TensorDict

from agents import runs
from agents.devices import resolve_device
from agents.library import clip_labels, load_library, with_terrain
from agents.metrics import EpisodeAccumulator, ObjectEpisodeMetrics, summarize
from agents.policy import TrainedPolicy, load_policy
from agents.vecenv import make_vec_env
from envs.mdp.metrics import mpjpe_root_relative, mpjpe_root_relative_heading_aligned
from envs.task import NON_FINITE
from otr_gym.reference import InvalidReferenceError

#: The evaluation episode ends with the clip (on_clip_end "truncate"), never by time-out first.
NO_TIMEOUT_S = 1.0e6
_RANDOMIZED = {"command": {"start": "zero", "on_clip_end": "truncate", "reset_noise_enabled": False},
               "randomization": {"push_lin_vel_mps": [0.0, 0.0, 0.0], "push_ang_vel_radps": [0.0, 0.0, 0.0]}}


def eval_env_overrides(train_env_overrides: dict, randomize: bool) -> dict:
    """The run's env overrides plus the evaluation protocol's."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in train_env_overrides.items()}
    extra = {"sim": {"episode_length_s": NO_TIMEOUT_S}, **(_RANDOMIZED if randomize else {})}
    for key, value in extra.items():
        out[key] = {**out.get(key, {}), **value}
    return out


def evaluation_library(policy: TrainedPolicy, reference: str | Path | None, randomize: bool):
    """(clip library, env overrides) of the evaluation protocol for ``policy``'s task and config;
    ``reference`` None: the run's own."""
    if reference is None:
        reference = policy.run_config["reference"]
    overrides = eval_env_overrides(policy.train_cfg.env, randomize)
    library = load_library(reference, policy.train_cfg.task, overrides)
    return library, with_terrain(overrides, library, [r.source for r in library.references])


@torch.inference_mode()
def run_episodes(vec, policy: TrainedPolicy, seed: int = 0, action_noise: float = 0.0) -> dict:
    """One episode per env from the env's (re)start with ``policy.act(obs TensorDict) -> actions``,
    plus zero-mean Gaussian noise of std ``action_noise`` (action units, every joint; drawn from
    a generator seeded with ``seed``) when positive; returns the ``summarize`` dict."""
    obs, _ = vec.reset(seed=seed)
    n = vec.num_envs
    noise = torch.Generator(device=vec.device).manual_seed(seed) if action_noise > 0.0 else None
    clip_ids = vec.command.clip.cpu().numpy()
    acc = EpisodeAccumulator(n, vec.device)
    objects = None
    if vec.tracking_state.objects is not None:
        objects = ObjectEpisodeMetrics(n, vec.tracking_state.objects.support_names, vec.device)
    max_steps = int(vec.motion.clip_length.max()) + 1
    for _ in range(max_steps):
        actions = policy.act(TensorDict(dict(obs), batch_size=[n], device=vec.device))
        if noise is not None:
            actions = actions + action_noise * torch.randn(actions.shape, device=actions.device, generator=noise)
        obs, _, terminated, truncated, info = vec.step(actions)
        alive = ~acc.finished
        state = vec.tracking_state
        acc.add_frame(mpjpe_root_relative(state), ~info["terminations"][NON_FINITE],
                      mpjpe_root_relative_heading_aligned(state))
        if objects is not None:
            objects.add_frame(vec.tracking_state, alive)
            objects.end_step(vec.tracking_state, alive & truncated & ~terminated)
        acc.end_step(terminated, truncated, info["terminations"])
        if acc.all_finished:
            break
    return summarize(acc.per_env(), clip_ids, clip_labels(list(vec.motion.names)), objects,
                     vec.motion.clip_length.tolist())


def evaluate(run_or_checkpoint: str | Path, reference: str | Path | None = None, num_envs: int | None = None,
             device: str | None = None, randomize: bool = False, seed: int = 0, last_only: bool = False,
             action_noise: float = 0.0, every: int | None = None) -> dict:
    """Results of one checkpoint, or of every checkpoint of a run folder (oldest first; only
    the latest with ``last_only``; with ``every``, those at multiples of it and the latest);
    ``action_noise``: see ``run_episodes``."""
    if not 0.0 <= action_noise < float("inf"):  # NaN fails too
        raise ValueError(f"--action-noise must be a finite std >= 0, got {action_noise}")
    target = Path(run_or_checkpoint)
    ckpts = runs.checkpoints(target) if target.is_dir() and not last_only else [runs.resolve_checkpoint(target)]
    if every is not None:
        ckpts = runs.every_nth(ckpts, every) + ckpts[-1:]
    torch_device = resolve_device(device)
    first = load_policy(ckpts[-1], torch_device)
    library, overrides = evaluation_library(first, reference, randomize)
    if num_envs is None:
        num_envs = len(library.references) * (256 if randomize else 1)
    if num_envs < 1:
        raise ValueError(f"--num-envs must be >= 1, got {num_envs}")
    env = make_vec_env(first.train_cfg.task, list(library.references), num_envs, str(torch_device), overrides,
                       evaluation=not randomize, seed=seed)
    vec = env.unwrapped
    results = []
    for ckpt in ckpts:
        policy = first if ckpt == first.checkpoint else load_policy(ckpt, torch_device)
        result = {"checkpoint": str(ckpt.path), "iteration": ckpt.iteration,
                  **run_episodes(vec, policy, seed, action_noise)}
        results.append(result)
        line = (f"iteration {ckpt.iteration:>6}: success {100 * result['success_rate']:5.1f} %  "
                f"MPJPE {result['mpjpe_mm']:7.1f} mm (heading-aligned {result['mpjpe_heading_aligned_mm']:5.1f})")
        if result.get("object_pos_error_cm") is not None:
            line += (f"  object {result['object_pos_error_cm']:5.1f} cm "
                     f"(p95 {result['object_pos_error_p95_cm']:5.1f}), "
                     f"{result['object_ori_error_deg']:5.1f} deg")
        line += ended_by_text(result)
        print(f"{line}  ({result['envs']} envs, {result['frames']} frames)")
        if len(result["clips"]) > 1:
            print(format_clip_table(result["clips"]))
    env.close()
    return {
        "run": ckpts[-1].run_dir.name,
        "reference": {"name": library.name, "path": library.source,
                      "skipped": [{"clip": c.path, "error": c.error} for c in library.skipped]},
        "protocol": {"randomize": randomize, "num_envs": num_envs, "seed": seed, "device": str(torch_device),
                     "start_frame": 0,
                     "action": "deterministic mean"
                               + (f" + Gaussian noise std {action_noise:g}" if action_noise else ""),
                     "mpjpe": "root-relative, 14 bodies, mm",
                     "mpjpe_heading_aligned": "diagnostic: the same after turning the reference by the anchors' "
                                              "yaw difference (heading drift not charged)",
                     "objects": "position error world cm (mean over moving objects), orientation deg; "
                                "support contact: force > 1 N inside the object-support windows"},
        "final": results[-1],
        "checkpoints": results,
    }


def ended_by_text(result: dict) -> str:
    """"  ended by ee_height 3, anchor_height 1" for a result (overall or one clip) whose
    episodes some termination ended; "" otherwise."""
    counts = result.get("ended_by") or {}
    return "  ended by " + ", ".join(f"{name} {n}" for name, n in counts.items()) if counts else ""


def format_clip_table(clips: list[dict]) -> str:
    """One line per clip: success, MPJPE, envs, frames (and the object error for the box task),
    then the terminations that ended its episodes."""
    width = max(len(c["clip"]) for c in clips)
    lines = [f"    {'clip':<{width}}  success    MPJPE (mm)  envs  frames"]
    for c in clips:
        line = (f"    {c['clip']:<{width}}  {100 * c['success_rate']:6.1f} %  {c['mpjpe_mm']:9.1f}  "
                f"{c['envs']:>5} {c['frames']:>7}")
        if c.get("object_pos_error_cm") is not None:
            line += f"  object {c['object_pos_error_cm']:.1f} cm"
        lines.append(line + ended_by_text(c))
    return "\n".join(lines)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="run folder (every checkpoint) or a model_<it>.pt checkpoint")
    parser.add_argument("--reference", nargs="+", metavar="REF", help="reference .npz files, folders or clip lists "
                        "(default: the run's own library)")
    parser.add_argument("--num-envs", type=int, help="parallel envs, env i plays clip i mod C (default: one per "
                        "clip; 256 per clip with --randomize)")
    parser.add_argument("--device", help="cuda, cuda:K or cpu (default: cuda if available)")
    parser.add_argument("--randomize", action="store_true", help="keep domain randomisation and observation "
                        "noise (pushes off) to measure robustness")
    parser.add_argument("--last", action="store_true", help="of a run folder, only the latest checkpoint")
    parser.add_argument("--every", type=int, metavar="N", help="of a run folder, only the checkpoints at multiples "
                        "of N iterations and the latest")
    parser.add_argument("--seed", type=int, default=0, help="seed of the envs' resets and of --action-noise "
                        "(default: %(default)s)")
    parser.add_argument("--action-noise", type=float, default=0.0, metavar="STD",
                        help="add zero-mean Gaussian noise of this std to every action (action units, e.g. the "
                             "policy's learned std, to see what its exploration costs; default 0)")
    parser.add_argument("--json", help="write the results here (atomically)")
    parser.add_argument("--plot", help="PNG of MPJPE and success against the checkpoint iteration")


def main(args: argparse.Namespace) -> int:
    try:
        results = evaluate(args.run, args.reference, args.num_envs, args.device, args.randomize, args.seed,
                           args.last, args.action_noise, args.every)
    except (runs.RunError, InvalidReferenceError, ValueError, gymnasium.error.Error) as exc:
        print(f"otr evaluate: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(f"wrote {runs.write_json(args.json, results)}")
    if args.plot:
        from agents.plots import plot_evaluation

        print(f"wrote {plot_evaluation(results, args.plot)}")
    return 0
