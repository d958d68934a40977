"""Throughput of OTR-G1-Track-v0 (or, with ``--task``, OTR-G1-BoxTrack-v0): env-steps/s vs
num_envs on MuJoCo-Warp, against the raw MuJoCo-Warp physics of the same model, plus the
single CPU env (MuJoCo). For the box task every size is also run on OTR-G1-Track-v0 with the
same reference (its robot motion; the objects ignored) and the ratio box/track is printed.

For every num_envs, one vector env (training configuration: randomisation and noise on) runs
random actions; three rates are measured on it, in env-steps/s (one env-step = 4 physics
steps at 200 Hz):

- ``env``: the full ``step`` (actions → PD → physics → rewards/terminations → resets → obs), on
  CUDA one replayed graph (``envs/step_graph.py``, switched on here whatever the config says; a
  failed capture is reported as ``graph_error`` and the step is then eager); ``env eager``: the
  same step with the MDP's torch work launched from Python between the physics graphs (the
  default, ``sim.cuda_graph: false``);
- ``backend``: the env's physics graph alone (physics + contact-force maxima + kinematics refresh);
- ``raw``: a graph of nothing but ``decimation`` × ``mujoco_warp.step`` on the same Model/Data
  (with the env's contact sensors); ``raw_bare``: the same on the G1 without contact sensors,
  standing keyframe, no resets (the setting of docs/environment.md §1).

``env/raw`` is the share of the raw physics ceiling the env keeps. Before timing, three checks run
on CUDA: no torch host synchronisation inside ``step`` (``torch.cuda.set_sync_debug_mode``),
torch reads of the state views see the graph's writes without an explicit synchronise, and the
graphed step gives the eager step's results (two evaluation envs of 512 worlds, same random
actions, 60 steps with falls and restarts: the largest observation difference and the first step
at which they part), beside a second eager env as the baseline (MuJoCo-Warp's atomics may part
two eager runs too).

Usage::

    python benchmarks/env_throughput.py --device cuda --num-envs 1024 2048 4096 8192 16384 --out out/env_throughput.json
    python benchmarks/env_throughput.py --device cpu --num-envs 4 8 --steps 20 --cpu-steps 200 --out /tmp/tp.json
    python benchmarks/env_throughput.py --task OTR-G1-BoxTrack-v0 --reference out/demo/box_carry.npz \
        --num-envs 8192 --out out/env_throughput_box.json

Writes the table to stdout, and the results to ``--out`` (JSON) and the same stem with ``.md``.
On a fresh GPU machine the first size also pays MuJoCo-Warp's kernel compilation (minutes;
cached in ~/.cache/warp): under a per-command time limit, warm the cache first with
``--num-envs 1024 --steps 10 --cpu-steps 0``.
"""

from __future__ import annotations

import argparse
import gc
import json
import platform
import sys
import time
import traceback
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing


def _sync(device: torch.device) -> None:
    import warp as wp

    wp.synchronize()
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _rate(fn, steps: int, num_envs: int, device: torch.device) -> tuple[float, float]:
    """(env-steps/s, ms per call) of ``fn`` called ``steps`` times."""
    _sync(device)
    start = time.perf_counter()
    for i in range(steps):
        fn(i)
    _sync(device)
    elapsed = time.perf_counter() - start
    return num_envs * steps / elapsed, 1e3 * elapsed / steps


def _checks(task, actions) -> dict:
    """CUDA only: sync-free step, and stream ordering between warp graphs and torch reads."""
    import warp as wp

    out = {}
    torch.cuda.set_sync_debug_mode("error")
    try:
        for i in range(5):
            task.step(actions[i % len(actions)])
        out["host_sync_in_step"] = False
    except RuntimeError as exc:
        out["host_sync_in_step"] = f"yes: {exc}".splitlines()[0]
    finally:
        torch.cuda.set_sync_debug_mode("default")
    mismatches = 0
    for i in range(5):
        task.step(actions[i % len(actions)])
        seen = task.backend.body_pos_w.clone()  # last written by a warp graph; torch read, no synchronise
        wp.synchronize()
        mismatches += int(not torch.equal(seen, task.backend.body_pos_w))
    out["stale_reads"] = mismatches
    return out


def _graph_matches_eager(task_id: str, reference, device: str, num_envs: int = 512, steps: int = 60) -> dict:
    """CUDA only: the same evaluation env (deterministic: no randomisation, noise or random
    starts) stepped as a graph and eagerly with the same actions, and a second eager env beside
    them: MuJoCo-Warp's contact solver accumulates with atomics, so two eager runs may part too.
    For both pairs, the largest observation and reward differences and the first step at which an
    observation differs by more than 1e-4 (None: never); and the envs that ended (so the restart
    path ran). The graph agrees with the eager step as well as the eager step agrees with itself
    when its pair parts no earlier than the eager pair."""
    from envs.config import BOX_TASK, load_env_config

    if task_id == BOX_TASK:
        from envs.box import make_box_task as make_task
    else:
        from envs.tracking import make_task
    tasks = []
    for graph in (True, False, False):
        cfg = load_env_config(task_id)
        cfg.sim.cuda_graph = graph
        tasks.append(make_task(reference, num_envs, "warp", device, cfg=cfg, evaluation=True, seed=0))
    graphed, eager, again = tasks
    if graphed.step_graph is None:
        return {"graph_check": "no graph on this device"}
    gen = torch.Generator(device=graphed.device).manual_seed(1)
    diff = {"graph": [0.0, 0.0, None], "eager": [0.0, 0.0, None]}  # obs, reward, first parting step
    ended = 0
    for i in range(steps):
        a = 2.0 * torch.randn(num_envs, 29, device=graphed.device, generator=gen)
        og, rg, tg, ug, _ = graphed.step(a)
        oe, re, te, ue, _ = eager.step(a)
        oa, ra, _, _, _ = again.step(a)
        for name, (o, r) in (("graph", (og, rg)), ("eager", (oa, ra))):
            obs = max(float((o[k] - oe[k]).abs().max()) for k in o)
            d = diff[name]
            d[0], d[1] = max(d[0], obs), max(d[1], float((r - re).abs().max()))
            if d[2] is None and obs > 1e-4:
                d[2] = i
        ended += int((te | ue).sum())
    if graphed.step_graph.error is not None:
        return {"graph_error": graphed.step_graph.error}
    return {"graph_obs_max_diff": diff["graph"][0], "graph_reward_max_diff": diff["graph"][1],
            "graph_parts_at_step": diff["graph"][2], "eager_obs_max_diff": diff["eager"][0],
            "eager_reward_max_diff": diff["eager"][1], "eager_parts_at_step": diff["eager"][2],
            "graph_check_ended": ended, "graph_replays": graphed.step_graph.calls - graphed.step_graph.warmup}


def _capture_steps(model, data, decimation: int, device):
    """A graph of ``decimation`` bare ``mujoco_warp.step`` calls."""
    import mujoco_warp as mjw
    import warp as wp

    with wp.ScopedDevice(device):
        with wp.ScopedCapture(device=device) as capture:
            for _ in range(decimation):
                mjw.step(model, data)
    return capture.graph


def _bare_world(num_envs: int, device, nconmax: int, njmax: int):
    """(Model, Data) of the G1 + ground without contact sensors: the setting of docs/environment.md §1."""
    import mujoco
    import mujoco_warp as mjw
    import warp as wp

    from envs.backends import build_sim_model

    model = build_sim_model(())
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    with wp.ScopedDevice(device):
        m = mjw.put_model(model)
        m.opt.warn_overflow &= ~(mjw.OverflowType.ITERATIONS | mjw.OverflowType.LS_ITERATIONS)
        d = mjw.put_data(model, data, nworld=num_envs, nconmax=nconmax, njmax=njmax)
    return m, d


def bench_vector(task_id: str, reference, num_envs: int, device: str, steps: int, warmup: int, final_obs: bool,
                 seed: int) -> dict:
    import warp as wp

    from envs.config import BOX_TASK, load_env_config

    free_before = torch.cuda.mem_get_info()[0] if device.startswith("cuda") else None
    cfg = load_env_config(task_id)
    cfg.final_obs = final_obs
    cfg.sim.cuda_graph = True  # timed as a graph (off by default until measured) and eagerly, below
    if task_id == BOX_TASK:
        from envs.box import make_box_task as make_task
    else:
        from envs.tracking import make_task
    t0 = time.perf_counter()
    task = make_task(reference, num_envs, "warp", device, cfg=cfg, seed=seed)
    build_s = time.perf_counter() - t0
    dev = task.device
    gen = torch.Generator(device=dev).manual_seed(seed)
    actions = [0.5 * torch.randn(num_envs, 29, device=dev, generator=gen) for _ in range(16)]
    t0 = time.perf_counter()
    task.step(actions[0])
    _sync(dev)
    first_step_s = time.perf_counter() - t0
    for i in range(warmup):
        task.step(actions[i % 16])
    row = {"task": task_id, "num_envs": num_envs, "build_s": round(build_s, 2), "first_step_s": round(first_step_s, 2)}
    if dev.type == "cuda":
        row.update(_checks(task, actions))
        row.update(_graph_matches_eager(task_id, reference, device))
    row["env_steps_per_s"], row["env_ms_per_step"] = _rate(lambda i: task.step(actions[i % 16]), steps, num_envs, dev)
    if task.step_graph is not None and task.step_graph.error is not None:
        row["graph_error"] = task.step_graph.error
    if task.step_graph is not None:  # the same env, its step eager (the graph's state is pinned back after)
        row["env_eager_steps_per_s"], _ = _rate(lambda i: task._step(actions[i % 16]), steps, num_envs, dev)
    if free_before is not None:
        _sync(dev)
        row["device_mem_gib"] = (free_before - torch.cuda.mem_get_info()[0]) / 2**30

    # Physics alone, from the standing start every 50 steps (as the env's resets keep robots up).
    backend = task.backend
    wp_device = wp.get_device(str(dev))
    everyone = torch.ones(num_envs, dtype=torch.bool, device=dev)
    qpos0, qvel0 = task.start_state(noise=False)
    ctrl = task.default_joint_pos.clone()

    def physics(launch):
        def run(i):
            if i % 50 == 0:
                backend.reset(everyone, qpos0, qvel0)
            launch()
        return run

    row["backend_steps_per_s"], row["backend_ms_per_step"] = _rate(
        physics(lambda: backend.step(ctrl)), steps, num_envs, dev)
    raw = _capture_steps(backend.warp_model, backend.warp_data, backend.decimation, wp_device)
    row["raw_steps_per_s"], row["raw_ms_per_step"] = _rate(
        physics(lambda: wp.capture_launch(raw)), steps, num_envs, dev)
    row["env_over_raw"] = row["env_steps_per_s"] / row["raw_steps_per_s"]
    row["contacts_per_world"] = float(backend.warp_data.nacon.numpy()[0]) / num_envs

    # The same without contact sensors, standing keyframe, no resets: comparable to docs/environment.md §1.
    bare_m, bare_d = _bare_world(num_envs, wp_device, cfg.sim.nconmax, cfg.sim.njmax)
    bare = _capture_steps(bare_m, bare_d, backend.decimation, wp_device)
    row["raw_bare_steps_per_s"], _ = _rate(lambda i: wp.capture_launch(bare), steps, num_envs, dev)
    return row


def bench_cpu_single(task_id: str, reference, steps: int, seed: int) -> dict:
    """gymnasium.make single env (CPU MuJoCo), random actions, reset on episode end."""
    import gymnasium

    import otr_gym  # noqa: F401  (registers the environment)

    env = gymnasium.make(task_id, reference=reference)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    actions = (0.5 * rng.standard_normal((16, 29))).astype(np.float32)
    episodes = 0
    start = time.perf_counter()
    for i in range(steps):
        _, _, terminated, truncated, _ = env.step(actions[i % 16])
        if terminated or truncated:
            env.reset()
            episodes += 1
    elapsed = time.perf_counter() - start
    env.close()
    return {"steps": steps, "env_steps_per_s": steps / elapsed, "ms_per_step": 1e3 * elapsed / steps,
            "episodes": episodes}


def _table(rows: list[dict]) -> str:
    head = ("task", "num_envs", "env steps/s", "env eager steps/s", "backend steps/s", "raw steps/s", "env/raw",
            "raw bare steps/s", "env/raw bare", "env ms/step", "mem GiB", "contacts/world",
            "obs diff graph/eager (parts at step)", "obs diff eager/eager (parts at step)")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['task']} | {r['num_envs']} | error: {r['error']} |")
            continue
        mem = f"{r['device_mem_gib']:.2f}" if "device_mem_gib" in r else "-"
        eager = f"{r['env_eager_steps_per_s']:,.0f}" if "env_eager_steps_per_s" in r else "-"
        check = (f"{r['graph_obs_max_diff']:.1e} ({r['graph_parts_at_step']})" if "graph_obs_max_diff" in r else "-")
        baseline = (f"{r['eager_obs_max_diff']:.1e} ({r['eager_parts_at_step']})" if "eager_obs_max_diff" in r
                    else "-")
        lines.append(f"| {r['task']} | {r['num_envs']} | {r['env_steps_per_s']:,.0f} | {eager} | "
                     f"{r['backend_steps_per_s']:,.0f} | "
                     f"{r['raw_steps_per_s']:,.0f} | {r['env_over_raw']:.0%} | {r['raw_bare_steps_per_s']:,.0f} | "
                     f"{r['env_steps_per_s'] / r['raw_bare_steps_per_s']:.0%} | "
                     f"{r['env_ms_per_step']:.2f} | {mem} | "
                     f"{r['contacts_per_world']:.1f} | {check} | {baseline} |")
    return "\n".join(lines)


def _meta(device: str) -> dict:
    import mujoco
    import mujoco_warp
    import warp as wp

    if device.startswith("cuda"):
        name = torch.cuda.get_device_name(torch.device(device))
    else:
        name = platform.processor() or "cpu"
    return {"date": datetime.now(UTC).isoformat(timespec="seconds"), "device": device, "device_name": name,
            "torch": torch.__version__, "warp": wp.__version__, "mujoco": mujoco.__version__,
            "mujoco_warp": mujoco_warp.__version__, "python": platform.python_version()}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="OTR-G1-Track-v0", choices=("OTR-G1-Track-v0", "OTR-G1-BoxTrack-v0"),
                        help="environment; the box task is also compared with OTR-G1-Track-v0 at every size")
    parser.add_argument("--device", default="cuda", help="warp device for the vector env: cuda, cuda:K or cpu")
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1024, 2048, 4096, 8192, 16384])
    parser.add_argument("--steps", type=int, default=200, help="timed env steps per num_envs")
    parser.add_argument("--warmup", type=int, default=20, help="untimed env steps after the first one")
    parser.add_argument("--cpu-steps", type=int, default=1000, help="steps of the single CPU env (0: skip)")
    parser.add_argument("--reference", default=None,
                        help="reference .npz or folder (default: a generated 11 s walk, agents.procedural; the box "
                        "task needs a reference with objects, e.g. out/demo/box_carry.npz from `otr demo`)")
    parser.add_argument("--final-obs", action="store_true",
                        help="also compute info['final_obs'] (off, as the rsl-rl adapter runs it)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("env_throughput.json"),
                        help="JSON path; the markdown table is written beside it (.md)")
    args = parser.parse_args(argv)

    from agents.procedural import WalkSpec, walking_reference
    from envs.backends.warp_backend import quiet_warp

    quiet_warp()  # the bare-G1 ceiling below uses Warp before any environment does
    box = args.task == "OTR-G1-BoxTrack-v0"
    if box and args.reference is None:
        parser.error("--task OTR-G1-BoxTrack-v0 needs --reference with objects (e.g. out/demo/box_carry.npz)")
    reference = args.reference or walking_reference(WalkSpec(steps=20))
    tasks = [args.task, "OTR-G1-Track-v0"] if box else [args.task]
    results = {"meta": _meta(args.device), "args": {k: str(v) for k, v in vars(args).items()}, "vector": []}
    print(f"# {args.task} throughput on {results['meta']['device_name']} ({args.device})", flush=True)
    for n in args.num_envs:
        for task_id in tasks:
            print(f"{task_id} num_envs={n} ...", flush=True)
            try:
                row = bench_vector(task_id, reference, n, args.device, args.steps, args.warmup, args.final_obs,
                                   args.seed)
            except Exception as exc:  # keep going: report OOM or a failing size in the table
                traceback.print_exc()
                row = {"task": task_id, "num_envs": n, "error": f"{type(exc).__name__}: {exc}".splitlines()[0][:200]}
            gc.collect()  # free this size's env (and its device memory) before the next one
            if args.device.startswith("cuda"):
                torch.cuda.empty_cache()
            print("   ", {k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
            results["vector"].append(row)
    ratios = {}
    if box:
        for n in args.num_envs:
            pair = {r["task"]: r for r in results["vector"] if r["num_envs"] == n and "error" not in r}
            if len(pair) == 2:
                ratios[n] = pair[args.task]["env_steps_per_s"] / pair["OTR-G1-Track-v0"]["env_steps_per_s"]
        results["box_over_track"] = ratios
    if args.cpu_steps > 0:
        results["cpu_single_env"] = bench_cpu_single(args.task, reference, args.cpu_steps, args.seed)

    table = _table(results["vector"])
    if ratios:
        table += "\n\nOTR-G1-BoxTrack-v0 / OTR-G1-Track-v0 (same reference, same run): " + ", ".join(
            f"{n} envs: {r:.2f}" for n, r in ratios.items())
    cpu = results.get("cpu_single_env")
    cpu_line = (f"\nSingle env, CPU MuJoCo (gymnasium.make): {cpu['env_steps_per_s']:,.0f} env-steps/s "
                f"({cpu['ms_per_step']:.2f} ms/step, {cpu['episodes']} resets)") if cpu else ""
    meta = results["meta"]
    checks = "".join(f"\n{r['task']} num_envs={r['num_envs']}: host sync in step: {r['host_sync_in_step']}, "
                     f"stale torch reads: {r['stale_reads']}" for r in results["vector"] if "stale_reads" in r)
    markdown = (f"# {args.task} throughput\n\n{meta['device_name']} ({meta['device']}), {meta['date']}; "
                f"torch {meta['torch']}, warp {meta['warp']}, mujoco {meta['mujoco']}, "
                f"mujoco_warp {meta['mujoco_warp']}\n\n"
                f"env-steps/s (1 env-step = 4 physics steps, 50 Hz policy); {args.steps} timed steps per size.\n\n"
                f"{table}\n{cpu_line}\n{checks}\n")
    print("\n" + markdown, flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2))
    args.out.with_suffix(".md").write_text(markdown)
    return results


if __name__ == "__main__":
    main()
