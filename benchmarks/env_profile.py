"""Where the time of one ``OTR-G1-Track-v0`` (or ``OTR-G1-BoxTrack-v0``) step goes on the GPU.

Runs the vector env with random actions under ``torch.profiler`` (CUPTI: every CUDA kernel,
torch's and MuJoCo-Warp's, graph-launched ones included) and attributes each kernel to the MDP
phase whose Python call launched it (the phases are the task's own methods, wrapped in
``record_function`` by this script only: the environment carries no profiling code). Prints

- per phase: kernels per step, GPU ms per step (sum of kernel durations), host ms per step
  (wall time of the Python call that launches the work);
- the 25 kernels with the most GPU time;
- the step's wall time with and without the profiler, and the GPU's busy share.

Usage::

    python benchmarks/env_profile.py --num-envs 8192 --steps 30 --out out/env_profile
    python benchmarks/env_profile.py --task OTR-G1-BoxTrack-v0 --reference box.npz --num-envs 8192

Writes ``OUT/profile.md``, ``OUT/profile.json`` and the Chrome trace ``OUT/trace.json.gz`` (open
it in https://ui.perfetto.dev).
"""

from __future__ import annotations

import argparse
import bisect
import functools
import gzip
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing

_PREFIX = "otr/"


def _wrap(obj, name: str, label: str) -> None:
    fn = getattr(obj, name)

    @functools.wraps(fn)
    def wrapped(*a, **k):
        with torch.profiler.record_function(_PREFIX + label):
            return fn(*a, **k)

    setattr(obj, name, wrapped)


def instrument(task) -> None:
    """Wrap the task's phases (instance attributes only; the classes are untouched)."""
    _wrap(task, "step", "step")
    _wrap(task.backend, "step", "physics")
    _wrap(task.backend, "reset", "backend.reset")
    _wrap(task, "_build_state", "build_state")
    _wrap(task, "_restart", "restart")
    _wrap(task, "_clear_episode", "clear_episode")
    _wrap(task, "_log", "log")
    _wrap(task, "_finite_observations", "observations")
    for name in ("resample", "start_state", "advance", "record_failures", "update_failure_rate"):
        _wrap(task.command, name, "command." + name)
    if task.randomizer is not None:
        _wrap(task.randomizer, "push", "randomizer.push")
        _wrap(task.randomizer, "reset", "randomizer.reset")

    def labelled(kind, entries):
        out = []
        for entry in entries:
            name, fn = entry[0], entry[1]

            def call(*a, _fn=fn, _label=f"{kind}/{name}", **k):
                with torch.profiler.record_function(_PREFIX + _label):
                    return _fn(*a, **k)
            out.append((name, call, *entry[2:]))
        return out

    task._rewards = labelled("reward", task._rewards)
    task._terminations = labelled("termination", task._terminations)


def attribute(trace: dict, steps: int) -> tuple[list[dict], list[dict], float]:
    """(phases, top kernels, GPU busy ms per step) from a Chrome trace of ``steps`` env steps."""
    events = trace["traceEvents"]
    ranges = [e for e in events if e.get("ph") == "X" and e.get("cat") == "user_annotation"
              and str(e.get("name", "")).startswith(_PREFIX)]
    launches = {}
    for e in events:
        launched = e.get("cat") in ("cuda_runtime", "cuda_driver") and "correlation" in e.get("args", {})
        if e.get("ph") == "X" and launched:
            launches[e["args"]["correlation"]] = e
    kernels = [e for e in events if e.get("ph") == "X" and e.get("cat") in ("kernel", "gpu_memset", "gpu_memcpy")]
    # innermost annotation containing a time stamp, per thread: sort by start, scan candidates
    by_tid = defaultdict(list)
    for r in ranges:
        by_tid[r["tid"]].append(r)
    for rs in by_tid.values():
        rs.sort(key=lambda r: r["ts"])
    starts = {tid: [r["ts"] for r in rs] for tid, rs in by_tid.items()}

    def innermost(tid, ts) -> str:
        rs = by_tid.get(tid, [])
        i = bisect.bisect_right(starts.get(tid, []), ts)
        best = None
        for r in reversed(rs[:i]):
            if r["ts"] <= ts <= r["ts"] + r["dur"]:
                if best is None or r["dur"] < best["dur"]:
                    best = r
            if ts - r["ts"] > 5e5:  # annotations are shorter than 0.5 s
                break
        return best["name"][len(_PREFIX):] if best else "(outside the step)"

    gpu = defaultdict(float)
    count = defaultdict(int)
    per_kernel = defaultdict(lambda: [0.0, 0])
    busy = 0.0
    for k in kernels:
        launch = launches.get(k.get("args", {}).get("correlation"))
        phase = innermost(launch["tid"], launch["ts"]) if launch else "(no launch record)"
        gpu[phase] += k["dur"]
        count[phase] += 1
        busy += k["dur"]
        pk = per_kernel[str(k["name"])[:90]]
        pk[0] += k["dur"]
        pk[1] += 1
    host = defaultdict(float)
    for r in ranges:
        host[r["name"][len(_PREFIX):]] += r["dur"]
    phases = sorted(set(gpu) | set(host), key=lambda p: -gpu.get(p, 0.0))
    table = [{"phase": p, "kernels_per_step": count.get(p, 0) / steps, "gpu_ms_per_step": gpu.get(p, 0.0) / steps / 1e3,
              "host_ms_per_step": host.get(p, 0.0) / steps / 1e3} for p in phases]
    top = sorted(({"kernel": n, "gpu_ms_per_step": v[0] / steps / 1e3, "launches_per_step": v[1] / steps}
                  for n, v in per_kernel.items()), key=lambda r: -r["gpu_ms_per_step"])[:25]
    return table, top, busy / steps / 1e3


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="OTR-G1-Track-v0", choices=("OTR-G1-Track-v0", "OTR-G1-BoxTrack-v0"))
    p.add_argument("--reference", default=None, help="reference .npz (default: a generated walk)")
    p.add_argument("--num-envs", type=int, default=8192)
    p.add_argument("--device", default="cuda")
    p.add_argument("--steps", type=int, default=30, help="profiled env steps")
    p.add_argument("--warmup", type=int, default=30)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("out/env_profile"))
    args = p.parse_args(argv)

    import warp as wp
    from torch.profiler import ProfilerActivity, profile

    from agents.procedural import WalkSpec, walking_reference
    from envs.backends.warp_backend import quiet_warp
    from envs.config import BOX_TASK, load_env_config

    quiet_warp()
    reference = args.reference or walking_reference(WalkSpec(steps=20))
    cfg = load_env_config(args.task)
    # Per-phase attribution needs the MDP's kernels launched from Python: profile the eager step
    # (the default step replays one CUDA graph, envs/step_graph.py, a single launch to the profiler).
    cfg.sim.cuda_graph = False
    if args.task == BOX_TASK:
        from envs.box import make_box_task as make_task
    else:
        from envs.tracking import make_task
    task = make_task(reference, args.num_envs, "warp", args.device, cfg=cfg, seed=args.seed)
    dev = task.device
    gen = torch.Generator(device=dev).manual_seed(args.seed)
    actions = [0.5 * torch.randn(args.num_envs, 29, device=dev, generator=gen) for _ in range(16)]

    def sync():
        wp.synchronize()
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    for i in range(args.warmup):
        task.step(actions[i % 16])
    sync()
    t0 = time.perf_counter()
    for i in range(args.steps):
        task.step(actions[i % 16])
    sync()
    plain_ms = 1e3 * (time.perf_counter() - t0) / args.steps

    instrument(task)
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    with profile(activities=activities) as prof:
        t0 = time.perf_counter()
        for i in range(args.steps):
            task.step(actions[i % 16])
        sync()
        profiled_ms = 1e3 * (time.perf_counter() - t0) / args.steps
    args.out.mkdir(parents=True, exist_ok=True)
    raw = args.out / "trace.json"
    prof.export_chrome_trace(str(raw))
    trace = json.loads(raw.read_text())
    with gzip.open(args.out / "trace.json.gz", "wt") as f:
        json.dump(trace, f)
    raw.unlink()
    phases, top, busy_ms = attribute(trace, args.steps)

    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu"
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    lines = [f"# {args.task} step profile: {args.num_envs} envs, {name}, {stamp}",
             "", f"step wall time: {plain_ms:.2f} ms ({args.num_envs / plain_ms * 1e3:,.0f} env-steps/s) without the "
             f"profiler, {profiled_ms:.2f} ms with it; GPU busy (sum of kernel times) {busy_ms:.2f} ms per step "
             f"({busy_ms / profiled_ms:.0%} of the profiled step)", "",
             "| phase | kernels / step | GPU ms / step | host ms / step |", "|---|---|---|---|"]
    lines += [f"| {r['phase']} | {r['kernels_per_step']:.0f} | {r['gpu_ms_per_step']:.3f} | "
              f"{r['host_ms_per_step']:.3f} |" for r in phases]
    lines += ["", "| kernel | launches / step | GPU ms / step |", "|---|---|---|"]
    lines += [f"| `{r['kernel']}` | {r['launches_per_step']:.1f} | {r['gpu_ms_per_step']:.3f} |" for r in top]
    text = "\n".join(lines) + "\n"
    print(text, flush=True)
    (args.out / "profile.md").write_text(text)
    result = {"task": args.task, "num_envs": args.num_envs, "device": name, "plain_ms": plain_ms,
              "profiled_ms": profiled_ms, "gpu_busy_ms": busy_ms, "phases": phases, "top_kernels": top}
    (args.out / "profile.json").write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
