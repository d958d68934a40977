"""The CPU cost of one ``otr deploy`` cycle, in-process, without DDS or scheduling: the parts the
runner does each cycle on a real LowState of the sim robot, timed over many repetitions (median
and p99; minimum too, the least disturbed by other jobs on a shared machine).

    python benchmarks/deploy_cycle.py [--repeats 500]
    PYTHONPATH=OTHER_CHECKOUT python OTHER_CHECKOUT/benchmarks/deploy_cycle.py   # another version

Parts: *receive* (the LowState's bytes to a ``RobotState`` and its CRC check, as the runner reads
them: ``runner.read_low_state`` where the checkout has it, else CycloneDDS's ``LowState_``
deserialisation, ``robot_state`` and ``crc_ok``), *controller* (``Controller.step`` while
tracking: stages, kinematics, observation, ONNX), *send* (``low_cmd``, CRC, serialisation as the
DDS writer does it), and *track start* (the one cycle that goes BLEND → TRACK and turns the clip
to the robot's heading). Sway clip (64 s), the open-loop reference policy.
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def timed(fn, repeats: int) -> np.ndarray:
    fn()
    out = np.empty(repeats)
    for i in range(repeats):
        t = time.perf_counter_ns()
        fn()
        out[i] = (time.perf_counter_ns() - t) * 1e-6
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repeats", type=int, default=500)
    args = p.parse_args()
    import torch

    from agents.deploy import crc
    from agents.deploy.controller import ControllerCfg, CycleInput
    from agents.deploy.messages import LowState_, low_cmd, robot_state
    from agents.deploy.reference_policy import write_reference_policy
    from agents.deploy.runner import build_controller
    from agents.deploy.safety import SafetyCfg, Stage
    from agents.deploy.sim_robot import SimRobot, SimRobotCfg, initial_pose
    from agents.procedural import SwaySpec, sway_reference

    torch.set_num_threads(1)
    try:
        from agents.deploy.runner import read_low_state
    except ImportError:  # a checkout from before the runner read the bytes itself
        def read_low_state(data: bytes):
            msg = LowState_.deserialize(data)
            return robot_state(msg), crc.crc_ok(msg)

    out = Path(tempfile.mkdtemp(prefix="deploy_cycle_"))
    reference = sway_reference(SwaySpec(duration_s=64.0)).save(out / "sway.npz")
    policy = write_reference_policy(out / "reference_policy.onnx", reference)
    sim = SimRobot(SimRobotCfg(), initial_qpos=initial_pose(str(reference)))
    data = crc.with_crc(sim.low_state()).serialize()
    state, _ = read_low_state(data)

    def controller():
        return build_controller(policy, reference, ControllerCfg(safety=SafetyCfg(ramp_s=0.04, blend_s=0.04),
                                                                  auto_start=True))

    starts, c, t = [], None, 0.0
    for _ in range(5):  # the track-start cycle of fresh controllers
        c, t = controller(), 0.0
        while c.stage != Stage.TRACK:
            before = time.perf_counter_ns()
            c.step(CycleInput(t_s=t, state=state))
            if c.stage == Stage.TRACK:
                starts.append((time.perf_counter_ns() - before) * 1e-6)
            t += 0.02

    def step():
        nonlocal t
        t += 0.02
        return c.step(CycleInput(t_s=t, state=state))

    command = step().command
    rows = {
        "receive": timed(lambda: read_low_state(data), args.repeats),
        "controller (tracking)": timed(step, args.repeats),
        "send": timed(lambda: crc.with_crc(low_cmd(command, 0)).serialize(), args.repeats),
    }
    print(f"\n{platform.processor() or platform.machine()}, {time.strftime('%Y-%m-%d %H:%M')}, checkout {REPO}, "
          f"{args.repeats} repeats\n")
    print("| part | min | p50 | p99 (ms) |\n|---|---|---|---|")
    for k, v in rows.items():
        print(f"| {k} | {v.min():.3f} | {np.median(v):.3f} | {np.percentile(v, 99):.3f} |")
    total = sum(np.median(v) for v in rows.values())
    print(f"| cycle (sum of p50) | | {total:.3f} | |")
    print(f"| track start (BLEND → TRACK cycle, 5 starts) | {min(starts):.3f} | {np.median(starts):.3f} | "
          f"{max(starts):.3f} (max) |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
