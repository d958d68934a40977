"""``otr play RUN --video out.mp4``: a video of the policy tracking its reference.

Runs the single CPU-MuJoCo env (``gymnasium.make``) in evaluation mode (frame 0, no
randomisation or noise, the episode ends with the clip or a termination) with the policy's
mean action, and records the env's frames: the robot plus a translucent ghost of the reference
(for OTR-G1-BoxTrack-v0 also the box and the table, and a ghost of the reference box), on the
clip's terrain when the run gives it one (at the origin 0: the clip is played alone).
Offscreen rendering needs ``MUJOCO_GL=egl`` (GPU / EGL) or ``osmesa``; egl is the default here.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from agents import runs  # noqa: E402
from agents.evaluate import eval_env_overrides  # noqa: E402
from agents.policy import load_policy  # noqa: E402
from otr_gym.reference import InvalidReferenceError  # noqa: E402


def play(run_or_checkpoint, video: str | Path, reference: str | Path | None = None, seconds: float | None = None,
         width: int = 640, height: int = 480, clip: str | None = None) -> dict:
    """Record one evaluation episode to ``video`` (mp4, atomically) of the library's clip
    ``clip`` (a label, ``agents.library.clip_labels``; default the first); returns its outcome."""
    import imageio.v2 as imageio

    import otr_gym  # noqa: F401  (registers the environments)
    from agents.library import clip_labels, load_library, with_terrain
    from envs.config import load_env_config

    policy = load_policy(run_or_checkpoint, "cpu")
    overrides = eval_env_overrides(policy.train_cfg.env, randomize=False)
    library = load_library(reference or policy.run_config["reference"], policy.train_cfg.task, overrides)
    labels = clip_labels([r.source for r in library.references])
    if clip is not None and clip not in labels:
        raise ValueError(f"--clip {clip!r}: not a clip of the library (clips: {', '.join(labels)})")
    index = labels.index(clip) if clip is not None else 0
    chosen = library.references[index]
    cfg = load_env_config(policy.train_cfg.task, overrides=with_terrain(overrides, library, [chosen.source]))
    env = gymnasium.make(policy.train_cfg.task, reference=chosen, render_mode="rgb_array", cfg=cfg,
                         evaluation=True, width=width, height=height)
    fps = env.metadata["render_fps"]
    max_steps = None if seconds is None else int(round(seconds * fps))
    obs, _ = env.reset(seed=0)
    steps, terminated, truncated = 0, False, False
    with runs.atomic_path(video) as tmp:
        with imageio.get_writer(tmp, fps=fps, codec="libx264", macro_block_size=8, format="FFMPEG") as writer:
            writer.append_data(env.render())
            while not (terminated or truncated) and (max_steps is None or steps < max_steps):
                batch = TensorDict({k: torch.from_numpy(np.asarray(v))[None] for k, v in obs.items()}, batch_size=[1])
                action = policy.act(batch)[0].numpy()
                obs, _, terminated, truncated, _ = env.step(action)
                writer.append_data(env.render())
                steps += 1
    env.close()
    return {"video": str(video), "frames": steps + 1, "fps": fps, "terminated": terminated,
            "clip_completed": bool(truncated and not terminated), "clip": labels[index]}


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="run folder (its latest checkpoint) or a model_<it>.pt checkpoint")
    parser.add_argument("--video", required=True, help="output .mp4")
    parser.add_argument("--reference", nargs="+", metavar="REF", help="reference .npz files, folders or clip lists "
                        "(default: the run's own library)")
    parser.add_argument("--clip", help="which clip of the library to play, by label (default: the first)")
    parser.add_argument("--seconds", type=float, help="stop after this long (s; default: the whole clip)")
    parser.add_argument("--width", type=int, default=640, help="video width (pixels; default: %(default)s)")
    parser.add_argument("--height", type=int, default=480, help="video height (pixels; default: %(default)s)")


def main(args: argparse.Namespace) -> int:
    try:
        out = play(args.run, args.video, args.reference, args.seconds, args.width, args.height, args.clip)
    except (runs.RunError, InvalidReferenceError, ValueError, gymnasium.error.Error) as exc:
        print(f"otr play: {exc}", file=sys.stderr)
        return 2
    ending = "clip completed" if out["clip_completed"] else "terminated" if out["terminated"] else "stopped"
    print(f"wrote {out['video']}: {out['frames']} frames at {out['fps']} fps ({ending})")
    return 0
