"""Sim2sim of a box policy on loopback DDS: RUNS runs of ``otr sim-robot`` + ``otr deploy``, the
box's mass, friction and inertia drawn per run as the box environment draws them in training,
then a Markdown table per run and the count of runs that pass.

    python benchmarks/box_sim2sim.py --policy P.onnx --reference R.npz [--runs 10] [--seed 0] [--mocap]
                                     [--out DIR] [--domain-id 150] [--sim-arg=ARG ...] [--deploy-arg=ARG ...]

Run k draws with seed SEED + k (``otr sim-robot --object-draw``: ``objects.randomization`` of
``configs/env/box.yaml``). The sim robot starts standing in the default pose at the reference's
first-frame position and heading (``--start-pose default``, as a G1 stands after its gantry
start-up; ``--start-pose reference`` starts it frozen on the first frame, which topples during
the runner's ramp where that frame does not balance open loop, e.g. ``otr demo``'s carry); the
runner uses its defaults (ramp 2 s, blend 1 s, end hold 1 s) with ``--auto-start``. A policy
whose observation needs motion capture (its ONNX metadata: ``PolicySpec.needs``, e.g. the box
task's ``mocap`` actor) runs with ``otr sim-robot --publish-mocap`` and ``otr deploy --mocap``;
``--mocap`` does so for any policy (the deploy log then records the box as captured).
``--env-set KEY=VALUE`` gives the sim robot the box config the policy was trained with (a training
run's ``--set env.KEY=VALUE``, e.g. ``objects.grasp_fit_quantile=0``); before the first run the
box the sim robot would build is checked against the policy's metadata (its collision method,
grasp-fit narrowing and nominal mass), and a mismatch is refused naming the fields.
``--sim-arg``/``--deploy-arg`` pass more options to either process (``--deploy-arg=--ramp=0.5``).
Each run's files go to ``OUT/run_KK/``: the sim robot's ``sim.json`` (``--stats``) and
``trace.npz`` (``--trace``), the deploy log ``run.npz``, both processes' output, and
``done.json`` once it finished; invoked again with the same ``--out`` (and the same policy,
reference, seed and options) it skips the finished runs and runs the rest, then prints the
table of all of them.

Per run (``run_metrics``; the moving object is the reference's first):

- *mass, friction*: what the sim robot simulated (its stats);
- *lifted*: the box's centre rose more than ``LIFT_M`` above its start (the sim robot's 50 Hz
  trace up to the clip's end);
- *carried*: while lifted, the box got at least ``CARRY_FRACTION`` of the reference's horizontal
  start-to-end distance towards its end ("—" when the reference moves it less than ``WITHIN_M``);
- *end error*: distance (cm) and yaw difference (deg) of the box from the reference's last-frame
  pose at the clip's end: the sim trace's sample at the simulated time of the LowState on which
  the runner's log went TRACK → END (if it damped earlier: of its last tracking cycle, or of its
  last cycle when it never tracked);
- *≤ 10 cm*: the end error within ``WITHIN_M``;
- *on table* (references with a static object): at the sim robot's end (after the runner damped
  and stopped) the box touches a static object and not the ground (``end_contacts`` in its stats);
- *start tilt Δ*: the largest |torso tilt − the reference's| over the first second of tracking
  (``agents.deploy.log.start_tilt_error_deg``; the issue's bound: 10°);
- *MPJPE*: mean over tracking (root-relative, 14 bodies; the runner's log);
- *ended*: the runner's last stage change (``clip_end`` when it tracked the whole clip);
- *missed / load*: the runner's missed 50 Hz deadlines (``agents.deploy.log.log_timing``) and the
  machine's 1-min load average when the run started (loopback DDS timing is sensitive to load).

A run passes when it lifted, carried and set the box within 10 cm (and, with a table, left it on
the table).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

LIFT_M = 0.05  # lifted: the box's centre this far above its start
CARRY_FRACTION = 0.5  # carried: this fraction of the reference's horizontal travel made while lifted
WITHIN_M = 0.10  # the bound on the box's end error
TILT_DEG = 10.0  # the bound on the torso tilt's difference over the first second
SIM_FILES = ("sim.json", "trace.npz", "run.npz", "sim.out", "deploy.out", "done.json")


def yaw_rad(q: np.ndarray) -> float:
    w, x, y, z = q
    return float(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def needs_mocap(policy: Path) -> bool:
    """Whether the policy's observation reads what only a motion-capture stream gives the runner
    here (its metadata's terms beyond the LowState: ``PolicySpec.needs``)."""
    from agents.deploy.observation import MOCAP, PolicySpec

    return any(MOCAP in sources for _, sources in PolicySpec.from_onnx(policy).needs().values())


def clip_seconds(reference: Path) -> float:
    from otr_gym.reference import Reference

    ref = Reference.load(reference)
    return ref.num_frames / ref.fps


def box_mismatch(policy: Path, reference: Path, env_sets: list[str] = ()) -> list[str]:
    """How the box the sim robot builds from ``reference`` with ``env_sets`` differs from the one
    the policy was trained with (its metadata's ``objects``: collision method, grasp-fit
    narrowing, nominal mass); empty when they agree or the metadata does not say."""
    from agents.deploy.sim_robot import sim_box_config, sim_objects
    from agents.export import read_metadata

    trained = read_metadata(policy).get("objects")
    if not trained:
        return []
    scene, _, _ = sim_objects(str(reference), cfg=sim_box_config(None, list(env_sets)))
    out = []
    for o in scene.objects if scene is not None else ():
        method = trained.get("collision", {}).get(o.name)
        if method is not None and method != o.method:
            out.append(f"{o.name}: collision {o.method}, trained with {method}")
        shrink = trained.get("grasp_shrink_m", {}).get(o.name)
        mine = None if o.grasp_shrink_m is None else o.grasp_shrink_m.tolist()
        if "grasp_shrink_m" in trained and (shrink is None) != (mine is None) or (
                shrink is not None and mine is not None and not np.allclose(shrink, mine, atol=1e-6)):
            out.append(f"{o.name}: grasp-fit narrowing {mine} m, trained with {shrink}")
        mass = trained.get("mass_kg", {}).get(o.name)
        if not o.static and mass is not None and abs(mass - o.mass_kg) > 1e-9:
            out.append(f"{o.name}: nominal mass {o.mass_kg:g} kg, trained with {mass:g}")
    return out


def run_once(policy: Path, reference: Path, folder: Path, draw_seed: int, domain: int, mocap: bool,
             sim_args: list[str] = (), deploy_args: list[str] = (), start_pose: str = "default") -> dict:
    """One sim2sim run into ``folder``; returns what ``done.json`` records (exit codes, times)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in SIM_FILES:  # an unfinished run's files go
        (folder / name).unlink(missing_ok=True)
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    cli = [sys.executable, "-m", "otr_gym.cli"]
    common = ["--interface", "lo", "--domain-id", str(domain), "--reference", str(reference)]
    bound = clip_seconds(reference) + 60.0  # ramp, blend, end hold, damping and start-up, generously
    topic = ["--publish-mocap"] if mocap else []
    start, load = time.time(), os.getloadavg()[0]
    with open(folder / "sim.out", "w") as sim_out, open(folder / "deploy.out", "w") as deploy_out:
        sim = subprocess.Popen([*cli, "sim-robot", *common, "--duration", str(bound), "--idle-exit", "1",
                                "--start-pose", start_pose, "--object-draw", str(draw_seed),
                                "--stats", str(folder / "sim.json"), "--trace", str(folder / "trace.npz"),
                                *topic, *sim_args],
                               env=env, cwd=REPO, stdout=sim_out, stderr=subprocess.STDOUT)
        deploy = subprocess.Popen([*cli, "deploy", *common, "--policy", str(policy), "--auto-start",
                                   "--damp-s", "1", "--log", str(folder / "run.npz"), *(["--mocap"] if mocap else []),
                                   *deploy_args], env=env, cwd=REPO, stdout=deploy_out, stderr=subprocess.STDOUT)
        deploy_rc = sim_rc = None  # None: killed after the time bound
        try:
            deploy_rc = deploy.wait(timeout=bound + 60.0)
            sim_rc = sim.wait(timeout=60.0)
        except subprocess.TimeoutExpired:
            pass
        finally:
            for p in (deploy, sim):
                if p.poll() is None:
                    p.kill()
                    p.wait()
    return {"draw_seed": draw_seed, "domain_id": domain, "mocap": mocap, "deploy_rc": deploy_rc, "sim_rc": sim_rc,
            "load_1min": load,
            "started_at": time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(start)),
            "wall_s": time.time() - start}


def static_objects(reference: Path) -> list[str]:
    """The reference's objects that the box environment (and the sim robot) makes fixed bodies."""
    from envs.config import load_box_config
    from envs.objects import is_static
    from otr_gym.reference import Reference

    cfg = load_box_config().objects
    return [t.name for t in Reference.load(reference).objects if is_static(t, cfg)]


def run_metrics(folder: Path, reference: Path, tables: list[str] | None = None) -> dict:
    """The table's row of one finished run, from its files (see the module docstring)."""
    from agents.deploy.log import DeployLog, log_timing, start_tilt_error_deg
    from agents.deploy.safety import Stage

    stats = json.loads((folder / "sim.json").read_text())
    trace = np.load(folder / "trace.npz")
    log = DeployLog.load(folder / "run.npz")
    done = json.loads((folder / "done.json").read_text())
    tables = static_objects(reference) if tables is None else tables
    name, box = next(iter(stats["objects"].items()))
    k = list(stats["objects"]).index(name)
    a = log.arrays
    track = np.flatnonzero(a["stage"] == Stage.TRACK)
    transitions = log.transitions()
    last = transitions[-1] if transitions else None
    ended = "none" if last is None else last[3] if last[1] in ("TRACK", "END") else f"{last[3]} in {last[1]}"
    row = {"run": folder.name, "draw_seed": done["draw_seed"], "object": name, "mass_kg": box["mass_kg"],
           "friction": box["friction"], "inertia_scale": box.get("inertia_scale", 1.0),
           "ended": ended, "deploy_rc": done["deploy_rc"],
           "tracking_s": float(len(track) * log.meta["period_ns"] * 1e-9), "upright": stats["upright"],
           "missed_deadlines": log_timing(log)["missed_deadlines"], "load_1min": done.get("load_1min")}
    # the clip's end: the LowState the runner went TRACK -> END on, or its last tracking cycle, or
    # (it never tracked) its last cycle with a LowState
    end_cycle = next((int(c) for c, f, to in zip(a["transition_cycle"], a["transition_from"], a["transition_to"],
                                                   strict=True) if f == Stage.TRACK and to == Stage.END), None)
    if end_cycle is None and track.size:
        end_cycle = int(track[-1])
    if end_cycle is None and a["fresh"].any():
        end_cycle = int(np.flatnonzero(a["fresh"])[-1])
    sim_s, poses = trace["sim_s"], trace["object_pose"][:, k]
    start = np.asarray(box["start"])
    goal = np.asarray(box["goal"]) if "goal" in box else None
    if end_cycle is None or goal is None:
        row.update(end_sim_s=None, end_pose=None, lifted=False, max_rise_m=None, carried=False, end_error_m=None,
                   yaw_error_deg=None, within=False)
    else:
        fresh = np.flatnonzero(a["fresh"][: end_cycle + 1])
        end_sim_s = float(a["state_tick_ms"][fresh[-1]]) / 1000.0
        upto = sim_s <= end_sim_s + 1e-9
        i_end = int(np.argmin(np.abs(sim_s - end_sim_s)))
        pose = poses[i_end]
        rise = poses[upto, 2] - start[2]
        lifted_rows = upto & (poses[:, 2] - start[2] > LIFT_M)
        travel = goal[:2] - start[:2]
        distance = float(np.linalg.norm(travel))
        if distance < WITHIN_M:
            carried = None  # the reference does not carry it
        else:
            progress = (poses[lifted_rows, :2] - start[:2]) @ (travel / distance)
            carried = bool(progress.size and progress.max() >= CARRY_FRACTION * distance)
        error = float(np.linalg.norm(pose[:3] - goal[:3]))
        yaw = (yaw_rad(pose[3:]) - yaw_rad(goal[3:]) + math.pi) % (2 * math.pi) - math.pi
        row.update(end_sim_s=end_sim_s, end_trace_sim_s=float(sim_s[i_end]), end_pose=pose.tolist(),
                   max_rise_m=float(rise.max()) if rise.size else None, lifted=bool(rise.size and rise.max() > LIFT_M),
                   carried=carried, reference_travel_m=distance, end_error_m=error,
                   yaw_error_deg=float(abs(math.degrees(yaw))), within=error <= WITHIN_M)
    contacts = box.get("end_contacts", [])
    moving = set(stats["objects"])
    if tables:
        row["on_table"] = bool(any(c in tables for c in contacts) and "ground" not in contacts)
    else:
        row["on_table"] = None
    row["end_contacts"] = [c for c in contacts if c not in moving or c == name]
    tilt = start_tilt_error_deg(log)
    row["start_tilt_deg"] = tilt
    row["mpjpe_mm"] = float(np.nanmean(a["mpjpe_m"][track]) * 1e3) if track.size else None
    row["passed"] = bool(row["lifted"] and row["carried"] is not False and row["within"]
                         and row["on_table"] is not False)
    row["tilt_ok"] = tilt is not None and tilt <= TILT_DEG
    return row


def _yes(x) -> str:
    return "—" if x is None else ("yes" if x else "no")


def _num(x, fmt: str) -> str:
    return "—" if x is None else format(x, fmt)


def table(rows: list[dict]) -> str:
    """The Markdown table of ``rows`` (``run_metrics``) and the counts of passing runs."""
    has_table = any(r["on_table"] is not None for r in rows)
    head = ["run", "draw seed", "mass (kg)", "friction", "lifted (rise cm)", "carried", "end error (cm)",
            "yaw error (°)", f"≤ {WITHIN_M * 100:g} cm", *(["on table"] if has_table else []),
            "start tilt Δ (°)", "MPJPE (mm)", "ended", "missed / load", "pass"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        rise = None if r["max_rise_m"] is None else r["max_rise_m"] * 100
        cells = [r["run"], str(r["draw_seed"]), f"{r['mass_kg']:.2f}", f"{r['friction']:.2f}",
                 f"{_yes(r['lifted'])} ({_num(rise, '.1f')})", _yes(r["carried"]),
                 _num(None if r["end_error_m"] is None else r["end_error_m"] * 100, ".1f"),
                 _num(r["yaw_error_deg"], ".1f"), _yes(r["within"]), *([_yes(r["on_table"])] if has_table else []),
                 _num(r["start_tilt_deg"], ".1f"), _num(r["mpjpe_mm"], ".1f"), r["ended"],
                 f"{r['missed_deadlines']} / {_num(r['load_1min'], '.1f')}", "**yes**" if r["passed"] else "no"]
        lines.append("| " + " | ".join(cells) + " |")
    n = len(rows)
    passed, tilt = sum(r["passed"] for r in rows), sum(r["tilt_ok"] for r in rows)
    lines += ["", f"**{passed} / {n} runs pass** (lifted > {LIFT_M * 100:g} cm, carried, within {WITHIN_M * 100:g} cm "
                  f"of the reference's final box pose{', left on the table' if has_table else ''}); "
                  f"torso tilt within {TILT_DEG:g}° of the reference's over the first second: {tilt} / {n}."]
    return "\n".join(lines)


def file_sha256(path: Path) -> str:
    from agents.deploy.log import file_sha256 as sha

    return sha(path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--policy", type=Path, required=True, help="exported box policy (.onnx, `otr export --onnx`)")
    p.add_argument("--reference", type=Path, required=True, help="the box reference it tracks")
    p.add_argument("--runs", type=int, default=10)
    p.add_argument("--seed", type=int, default=0, help="run k draws the box's properties with seed SEED + k")
    p.add_argument("--mocap", action="store_true", help="publish and subscribe motion capture even where the "
                   "policy does not need it (the deploy log then records the box)")
    p.add_argument("--out", type=Path, default=None, help="folder of the runs (default: a temp folder); the same "
                   "folder again resumes")
    p.add_argument("--start-pose", choices=("default", "reference"), default="default",
                   help="otr sim-robot --start-pose: standing in the default pose, or on the reference's first frame")
    p.add_argument("--domain-id", type=int, default=150, help="DDS domain of the runs (one run at a time)")
    p.add_argument("--env-set", action="append", default=[], metavar="KEY=VALUE",
                   help="a box config key the policy was trained with (otr sim-robot --env-set; e.g. "
                        "objects.grasp_fit_quantile=0)")
    p.add_argument("--sim-arg", action="append", default=[], help="one more argument to otr sim-robot")
    p.add_argument("--deploy-arg", action="append", default=[], help="one more argument to otr deploy")
    args = p.parse_args(argv)
    if args.runs < 1:
        p.error("--runs must be >= 1")
    for what, path in (("policy", args.policy), ("reference", args.reference)):
        if not path.is_file():
            p.error(f"--{what} {path}: not a file")
    import tempfile

    out = args.out or Path(tempfile.mkdtemp(prefix="box_sim2sim_"))
    out.mkdir(parents=True, exist_ok=True)
    mocap = args.mocap or needs_mocap(args.policy)
    config = {"policy": str(args.policy), "policy_sha256": file_sha256(args.policy),
              "reference": str(args.reference), "reference_sha256": file_sha256(args.reference), "seed": args.seed,
              "mocap": mocap, "start_pose": args.start_pose, "env_set": args.env_set, "sim_args": args.sim_arg,
              "deploy_args": args.deploy_arg}
    mismatch = box_mismatch(args.policy, args.reference, args.env_set)
    if mismatch:
        print(f"box_sim2sim: the sim robot's objects differ from those {args.policy} was trained with: "
              f"{'; '.join(mismatch)}. Pass the training run's box settings as --env-set KEY=VALUE (its "
              "--set env.KEY=VALUE; docs/box.md: the demo carry was learned with objects.grasp_fit_quantile=0)",
              file=sys.stderr)
        return 2
    config_file = out / "config.json"
    if config_file.is_file():
        before = json.loads(config_file.read_text())
        differ = sorted(k for k in config if k not in ("policy", "reference") and before.get(k) != config[k])
        if differ:
            print(f"box_sim2sim: {out} holds runs of another configuration ({', '.join(differ)} differ): "
                  "use another --out", file=sys.stderr)
            return 2
    config_file.write_text(json.dumps(config, indent=1))
    tables = static_objects(args.reference)
    print(f"box_sim2sim: {args.runs} runs of {args.policy.name} on {args.reference.name} into {out}"
          f"{' with motion capture' if mocap else ''}, the robot starting on the {args.start_pose} pose", flush=True)
    for k in range(args.runs):
        folder = out / f"run_{k:02d}"
        if (folder / "done.json").is_file():
            continue
        sim_args = [a for item in args.env_set for a in ("--env-set", item)] + args.sim_arg
        done = run_once(args.policy, args.reference, folder, args.seed + k, args.domain_id, mocap, sim_args,
                        args.deploy_arg, args.start_pose)
        if done["sim_rc"] != 0 or done["deploy_rc"] not in (0, 1) or not (folder / "run.npz").is_file():
            tail = "".join((folder / f).read_text()[-2000:] for f in ("sim.out", "deploy.out") if (folder / f).exists())
            print(f"box_sim2sim: {folder.name} failed (sim-robot exit {done['sim_rc']}, deploy exit "
                  f"{done['deploy_rc']}); it runs again when re-invoked:\n{tail}", file=sys.stderr)
            return 1
        (folder / "done.json").write_text(json.dumps(done, indent=1))
        row = run_metrics(folder, args.reference, tables)
        print(f"  {folder.name}: seed {row['draw_seed']}, {row['mass_kg']:.2f} kg, friction {row['friction']:.2f}: "
              f"ended {row['ended']}, end error {_num(row['end_error_m'], '.3f')} m, "
              f"{'pass' if row['passed'] else 'fail'} ({done['wall_s']:.0f} s)", flush=True)
    rows = [run_metrics(out / f"run_{k:02d}", args.reference, tables) for k in range(args.runs)]
    text = table(rows)
    header = (f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, {time.strftime('%Y-%m-%d')}; "
              f"policy {args.policy.name} (sha256 {config['policy_sha256'][:12]}), reference {args.reference.name}, "
              f"{'motion capture, ' if mocap else ''}draw seeds {args.seed}..{args.seed + args.runs - 1}; "
              f"files in {out}")
    (out / "table.md").write_text(header + "\n\n" + text + "\n")
    (out / "results.json").write_text(json.dumps({"config": config, "runs": rows}, indent=1))
    print(f"\n{header}\n\n{text}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
