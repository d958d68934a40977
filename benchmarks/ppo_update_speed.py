"""Time of rsl-rl's PPO on the Track recipe's networks, without a simulator: the rollout's policy
and value passes and the update, in float32 and in the faster numeric modes ``otr train`` offers.

    python benchmarks/ppo_update_speed.py [--device cuda] [--num-envs 8192] [--steps 24]
        [--epochs 10] [--mini-batches 4] [--updates 5] [--actor-obs 160] [--critic-obs 286]
        [--modes fp32 tf32 bf16 compile] [--json out.json]

Why: on one H200 an iteration of the precise-tracking recipe (8192 envs, 10 epochs × 4
mini-batches) spends about 0.35 s in the update against 0.6 s collecting, so the update decides
how many iterations fit into a 20-minute budget. Each mode builds a fresh PPO from
``agents.config.TrainCfg`` (same seed), fills its rollout storage with random observations,
rewards and 1 % resets (``--steps`` policy and value passes, timed as "rollout"), and times
``--updates`` updates after one untimed warm-up update (which pays ``torch.compile``'s
compilation; its time is printed apart). Modes, each the ``otr train --set`` it stands for:

- ``fp32``: float32, every run in README;
- ``tf32``: ``tf32_matmul`` (float32 matmuls on TF32 tensor cores; CUDA only);
- ``bf16``: ``algorithm.use_mixed_precision`` (rsl-rl's bfloat16 autocast of the update);
- ``compile``: ``torch_compile_mode="default"``.

The rollout column is the networks' share of collection only; the simulator's is
``benchmarks/env_throughput.py``'s. The mean losses of the last update are printed as a sanity
check (same order of magnitude across modes), not as a quality measure: whether a mode learns
as well is a training run's question.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import time
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: mode -> the ``otr train --set`` overrides it stands for
MODES = {
    "fp32": [],
    "tf32": ["tf32_matmul=true"],
    "bf16": ["algorithm.use_mixed_precision=true"],
    "compile": ["torch_compile_mode=default"],
}


def mode_config(mode: str, num_envs: int, steps: int, epochs: int, mini_batches: int):
    """The TrainCfg that ``otr train`` would build for ``mode``'s overrides and these sizes
    (KeyError names an unknown mode)."""
    from agents.config import load_train_config
    from agents.train import parse_sets
    from otr_gym.config import merge

    if mode not in MODES:
        raise KeyError(f"mode {mode!r}: one of {', '.join(MODES)}")
    sizes = {"num_envs": num_envs, "num_steps_per_env": steps,
             "algorithm": {"num_learning_epochs": epochs, "num_mini_batches": mini_batches}}
    return load_train_config(overrides=merge(sizes, parse_sets(MODES[mode])))


def _sync(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize(device)


def measure(mode: str, *, device: str = "cuda", num_envs: int = 8192, steps: int = 24, epochs: int = 10,
            mini_batches: int = 4, updates: int = 5, actor_obs: int = 160, critic_obs: int = 286,
            num_actions: int = 29, seed: int = 0) -> dict:
    """One mode's timings: rollout (the ``steps`` act + store passes, s), warm-up update (s),
    update (s, mean of ``updates``), per mini-batch (ms), the last update's losses, how far
    the timed updates moved the actor's weights (L2, so a no-op update cannot pass unnoticed)
    and the settings rsl-rl ran with (``settings``)."""
    import torch
    from rsl_rl.algorithms import PPO
    from tensordict import TensorDict

    cfg = mode_config(mode, num_envs, steps, epochs, mini_batches)
    previous_tf32 = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = cfg.tf32_matmul
    try:
        torch.manual_seed(seed)
        gen = torch.Generator(device=device).manual_seed(seed)

        def observations() -> TensorDict:
            return TensorDict({"policy": torch.randn(num_envs, actor_obs, device=device, generator=gen),
                               "critic": torch.randn(num_envs, critic_obs, device=device, generator=gen)},
                              batch_size=[num_envs], device=device)

        train_cfg = cfg.to_rsl_rl()
        train_cfg["multi_gpu"] = None
        with contextlib.redirect_stdout(io.StringIO()):  # rsl-rl prints both models
            alg = PPO.construct_algorithm(observations(), SimpleNamespace(num_envs=num_envs, num_actions=num_actions),
                                          train_cfg, device)
        settings = {"tf32_matmul": torch.backends.cuda.matmul.allow_tf32,
                    "use_mixed_precision": alg.use_mixed_precision, "compiled": alg.actor is not alg._raw_actor}

        def rollout() -> float:
            _sync(device)
            start = time.perf_counter()
            with torch.inference_mode():
                for _ in range(steps):
                    obs = observations()
                    alg.act(obs)
                    rewards = torch.rand(num_envs, device=device, generator=gen)
                    dones = torch.rand(num_envs, device=device, generator=gen) < 0.01
                    alg.process_env_step(obs, rewards, dones, {})
                alg.compute_returns(observations())
            _sync(device)
            return time.perf_counter() - start

        def update() -> tuple[float, dict]:
            _sync(device)
            start = time.perf_counter()
            losses = alg.update()
            _sync(device)
            return time.perf_counter() - start, losses

        rollout()
        warmup, _ = update()
        before = torch.cat([p.detach().flatten().clone() for p in alg.actor.parameters()])
        rollout_s, update_s, losses = [], [], {}
        for _ in range(updates):
            rollout_s.append(rollout())
            seconds, losses = update()
            update_s.append(seconds)
        after = torch.cat([p.detach().flatten() for p in alg.actor.parameters()])
    finally:
        torch.backends.cuda.matmul.allow_tf32 = previous_tf32
    update_mean = sum(update_s) / len(update_s)
    return {"mode": mode, "device": device, "num_envs": num_envs, "steps": steps, "epochs": epochs,
            "mini_batches": mini_batches, "updates": updates,
            "rollout_s": sum(rollout_s) / len(rollout_s), "warmup_update_s": warmup, "update_s": update_mean,
            "mini_batch_ms": 1e3 * update_mean / (epochs * mini_batches),
            "actor_weight_change": float(torch.linalg.norm(after - before)), "settings": settings,
            "losses": {k: float(v) for k, v in losses.items()}}


def table(rows: list[dict]) -> str:
    """Markdown table of ``measure`` rows, speed-ups against the first row."""
    base = rows[0]
    lines = ["| mode | rollout networks s | update s | per mini-batch ms | update speed-up | warm-up update s "
             "| value loss | surrogate loss |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['mode']} | {r['rollout_s']:.3f} | {r['update_s']:.3f} | {r['mini_batch_ms']:.2f} "
                     f"| {base['update_s'] / r['update_s']:.2f}x | {r['warmup_update_s']:.2f} "
                     f"| {r['losses']['value']:.3g} | {r['losses']['surrogate']:.3g} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--num-envs", type=int, default=8192)
    parser.add_argument("--steps", type=int, default=24, help="rollout steps per iteration (default: 24)")
    parser.add_argument("--epochs", type=int, default=10, help="PPO epochs (default: 10, the precise recipe)")
    parser.add_argument("--mini-batches", type=int, default=4)
    parser.add_argument("--updates", type=int, default=5, help="timed updates per mode (default: 5)")
    parser.add_argument("--actor-obs", type=int, default=160, help="actor observation size (default: 160, "
                        "the state-estimation actor)")
    parser.add_argument("--critic-obs", type=int, default=286)
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    parser.add_argument("--json", type=Path, help="write the rows here")
    args = parser.parse_args(argv)

    from agents.devices import resolve_device

    device = str(resolve_device(args.device))
    if device == "cpu" and "tf32" in args.modes:
        print("tf32: CUDA only; measured as float32 on the CPU", file=sys.stderr)
    rows = []
    for mode in args.modes:
        rows.append(measure(mode, device=device, num_envs=args.num_envs, steps=args.steps, epochs=args.epochs,
                            mini_batches=args.mini_batches, updates=args.updates, actor_obs=args.actor_obs,
                            critic_obs=args.critic_obs))
        print(f"{mode}: update {rows[-1]['update_s']:.3f} s", file=sys.stderr)
    import torch

    name = torch.cuda.get_device_name(device) if device.startswith("cuda") else "cpu"
    print(f"PPO update on {name}, torch {torch.__version__}: {args.num_envs} envs × {args.steps} steps, "
          f"{args.epochs} epochs × {args.mini_batches} mini-batches")
    print(table(rows))
    if args.json:
        from otr_gym.io import write_json

        write_json(args.json, {"device_name": name, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
