"""``otr deploy``: run an exported policy on a G1 (or ``otr sim-robot``) over the low-level DDS
interface, and ``otr deploy --replay LOG`` to re-run a recorded session offline.

Each cycle, on an absolute 50 Hz grid (``DeadlineClock``): take the newest ``rt/lowstate``,
let the ``Controller`` decide (stages, safety, observation, ONNX), write ``rt/lowcmd`` with its
CRC, log the cycle; with ``--mocap TOPIC`` also take the newest motion-capture frame
(``agents.deploy.mocap``), which feeds the terms that need it and is logged. Operator: Enter or
``s`` (or the remote's Start) starts tracking from HOLD;
space, ``e`` or Esc (or the remote's Select) is the e-stop; Ctrl-C stops (damping) and a
second Ctrl-C quits at once. After entering DAMP the runner keeps sending damping for
``--damp-s`` seconds and exits; the log is written on every exit path.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import os
import platform
import select
import signal
import sys
import time
from pathlib import Path

import numpy as np

from agents.deploy import crc
from agents.deploy.controller import KEY_ESTOP, KEY_START, KEY_STOP, Controller, ControllerCfg, CycleInput
from agents.deploy.log import NS, CycleLog, DeployLog, file_sha256, log_file
from agents.deploy.messages import LowState_, RobotState, is_low_state_xcdr1, low_cmd, robot_state, robot_state_from_cdr
from agents.deploy.mocap import TOPIC_MOCAP, MocapFault, mocap_frame, name_map
from agents.deploy.observation import ESTIMATOR, MOCAP, ObservationBuilder, PolicySpec, PolicySpecError
from agents.deploy.onnx_policy import OnnxPolicy
from agents.deploy.safety import SafetyCfg, Stage

REPLAY_TOL = 1e-6
MOCAP_FAULTS = (MocapFault.STALE, MocapFault.NAN, MocapFault.MISSING_BODY)


class DeadlineClock:
    """Wake-ups on an absolute grid t0 + k·period (no drift): sleep until ``spin_ns`` before the
    slot, then spin on the steady clock. A wake-up later than a whole period skips the missed
    slots (they are counted by the log's timing summary as missed deadlines)."""

    def __init__(self, period_ns: int, spin_ns: int = 500_000):
        self.period_ns, self.spin_ns = period_ns, spin_ns
        self.t0 = time.perf_counter_ns()
        self.deadline = self.t0

    def wait(self) -> tuple[int, int]:
        """(deadline, wake) in ns since the clock started."""
        now = time.perf_counter_ns()
        if now - self.deadline >= self.period_ns:  # overran: jump to the latest slot already due
            self.deadline += (now - self.deadline) // self.period_ns * self.period_ns
        remaining = self.deadline - now - self.spin_ns
        if remaining > 0:
            time.sleep(remaining * 1e-9)
        while (now := time.perf_counter_ns()) < self.deadline:
            pass
        deadline = self.deadline
        self.deadline += self.period_ns
        return deadline - self.t0, now - self.t0


def read_low_state(data: bytes) -> tuple[RobotState, bool]:
    """A LowState sample's robot state and whether its CRC matches, from its bytes: straight from
    the XCDR1 little-endian layout the G1 and ``otr sim-robot`` send (~0.03 ms), else through
    ``LowState_`` (~0.2 ms). The same values either way (``tests/agents/deploy/test_deploy_messages.py``)."""
    if is_low_state_xcdr1(data):
        return robot_state_from_cdr(data), crc.low_state_crc_ok_cdr(data)
    msg = LowState_.deserialize(data)
    return robot_state(msg), crc.crc_ok(msg)


def set_realtime_priority(priority: int) -> None:
    """SCHED_FIFO at ``priority`` (1..99) for the calling thread: the loop then wakes on time
    even when other processes load the CPU. Needs root or CAP_SYS_NICE (``ulimit -r``)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError) as exc:
        raise PermissionError(f"real-time priority {priority} refused ({exc}); run as root, grant CAP_SYS_NICE "
                              "or raise `ulimit -r`, or leave --rt-priority out") from exc


class Keyboard:
    """Non-blocking single keys from a terminal (nothing when stdin is not a TTY)."""

    START_KEYS, ESTOP_KEYS = ("\n", "\r", "s"), (" ", "e", "\x1b")

    def __enter__(self) -> Keyboard:
        self._saved = None
        if sys.stdin.isatty():
            import termios
            import tty

            self._saved = termios.tcgetattr(sys.stdin)
            tty.setcbreak(sys.stdin.fileno())
        return self

    def __exit__(self, *exc) -> None:
        if self._saved is not None:
            import termios

            termios.tcsetattr(sys.stdin, termios.TCSADRAIN, self._saved)

    def keys(self) -> int:
        if self._saved is None:
            return 0
        out = 0
        while select.select([sys.stdin], [], [], 0)[0]:
            ch = os.read(sys.stdin.fileno(), 1).decode(errors="ignore").lower()
            out |= KEY_START if ch in self.START_KEYS else KEY_ESTOP if ch in self.ESTOP_KEYS else 0
        return out


def build_controller(policy_path: str | Path, reference, cfg: ControllerCfg) -> Controller:
    """The controller of ``policy_path`` on ``reference``; a policy that reads what ``cfg``'s
    sources (motion capture) cannot give is refused (``PolicySpecError`` naming terms and flags)."""
    spec = PolicySpec.from_onnx(policy_path)
    sources = frozenset({MOCAP} if cfg.mocap_names is not None else set()) | (
        frozenset({ESTIMATOR}) if cfg.state_estimator else frozenset())
    builder = ObservationBuilder(spec, reference, sources)
    return Controller(spec, builder, OnnxPolicy(policy_path, spec), cfg)


def _controller_cfg_dict(cfg: ControllerCfg) -> dict:
    d = dataclasses.asdict(cfg)
    d["safety"]["damping_kd"] = np.asarray(cfg.safety.damping_kd).tolist()
    return d


def _controller_cfg_from_dict(d: dict) -> ControllerCfg:
    # logs written before the hold → track blend and the end hold had neither: replay them without
    safety = {"blend_s": 0.0, "end_hold_s": 0.0, **d["safety"]}
    return ControllerCfg(safety=SafetyCfg(**safety), auto_start=d["auto_start"], duration_s=d["duration_s"],
                         mocap_names=d.get("mocap_names"), state_estimator=d.get("state_estimator", False))


class Runner:
    def __init__(self, controller: Controller, policy_path: Path, reference: str, domain_id: int,
                 interface: str | None, damp_s: float, spin_us: float, wait_timeout_s: float,
                 mocap_topic: str | None = None):
        self.controller, self.damp_s, self.wait_timeout_s = controller, damp_s, wait_timeout_s
        self.period_ns = int(round(controller.spec.policy_dt * NS))
        self.spin_ns = int(spin_us * 1000)
        self.meta = {
            "policy": {"path": str(policy_path), "sha256": file_sha256(policy_path)},
            "reference": {"path": str(reference), "sha256": file_sha256(reference)},
            "controller": _controller_cfg_dict(controller.cfg),
            "period_ns": self.period_ns, "spin_ns": self.spin_ns, "interface": interface, "domain_id": domain_id,
            "host": platform.node(), "cpus": os.cpu_count(), "python": platform.python_version(),
            "started_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        }
        if mocap_topic is not None:
            self.meta["mocap"] = {"topic": mocap_topic}
        self.log = CycleLog(controller.spec.observation_dim, self.meta, controller.mocap)
        from agents.deploy.dds import G1Domain

        self.dds = G1Domain(domain_id, interface)
        self.reader = self.dds.latest_reader(self.dds.lowstate_topic)
        self.writer = self.dds.writer(self.dds.lowcmd_topic)
        self.mocap_reader = (None if mocap_topic is None or controller.mocap is None
                             else self.dds.latest_reader(self.dds.mocap_topic(mocap_topic)))
        self._sigints = 0

    def _on_sigint(self, *_) -> None:
        self._sigints += 1
        if self._sigints > 1:
            raise KeyboardInterrupt

    def run(self) -> int:
        from agents.deploy.dds import take_latest, take_latest_bytes

        c = self.controller
        # A full collection walks the ~400k objects torch, MuJoCo and onnxruntime set up (100-300 ms
        # here, at whatever allocation triggers it): freeze them out of the collector, and collect
        # what the loop makes only in a cycle's slack (``_collect_garbage``).
        gc_enabled = gc.isenabled()
        gc.collect()
        gc.freeze()
        gc.disable()
        clock = DeadlineClock(self.period_ns, self.spin_ns)
        damp_since: float | None = None
        previous = signal.signal(signal.SIGINT, self._on_sigint)
        signal.signal(signal.SIGTERM, self._on_sigint)
        status = 0
        try:
            with Keyboard() as keyboard:
                while True:
                    deadline, wake = clock.wait()
                    t_s = wake / NS
                    data = take_latest_bytes(self.reader)
                    state, crc_ok = (None, True) if data is None else read_low_state(data)
                    mocap = None if self.mocap_reader is None else take_latest(self.mocap_reader)
                    keys = keyboard.keys() | (KEY_STOP if self._sigints else 0)
                    inp = CycleInput(t_s=t_s, state=state, crc_ok=crc_ok, keys=keys,
                                     mocap=None if mocap is None else mocap_frame(mocap))
                    received = time.perf_counter_ns() - clock.t0
                    stage_before = c.stage
                    out = c.step(inp)
                    decided = time.perf_counter_ns() - clock.t0
                    if out.command is not None:
                        self.writer.write(crc.with_crc(low_cmd(out.command, c.state.mode_machine if c.state else 0)))
                    publish = time.perf_counter_ns() - clock.t0
                    policy_ns = getattr(c.policy, "last_ns", 0) if out.action is not None else 0
                    self.log.append(inp, out, deadline, wake, publish, received, decided, policy_ns)
                    if out.stage != stage_before:
                        print(f"[{t_s:7.2f} s] {stage_before.name} -> {out.stage.name} "
                              f"({c.stages.transitions[-1].reason})", flush=True)
                        if out.stage == Stage.DAMP and c.fault_detail:
                            print(f"otr deploy: {c.fault_detail}", file=sys.stderr, flush=True)
                    if out.stage == Stage.DAMP:
                        damp_since = t_s if damp_since is None else damp_since
                        if t_s - damp_since >= self.damp_s:
                            break
                    elif out.stage == Stage.WAIT and t_s > self.wait_timeout_s:
                        print(f"otr deploy: no LowState on {self.dds.interface or '(auto)'} domain "
                              f"{self.dds.domain_id} within {self.wait_timeout_s:g} s", file=sys.stderr)
                        status = 3
                        break
                    self._collect_garbage(clock)
        except KeyboardInterrupt:
            status = 130
        finally:
            signal.signal(signal.SIGINT, previous)
            gc.unfreeze()
            if gc_enabled:
                gc.enable()
        return status

    #: Collect garbage only with this much time left before the next slot; a full collection
    #: (of what the loop itself made: microseconds) every this many cycles, the youngest otherwise.
    GC_SLACK_NS, GC_FULL_EVERY = 5_000_000, 250

    def _collect_garbage(self, clock: DeadlineClock) -> None:
        if clock.deadline - time.perf_counter_ns() > self.GC_SLACK_NS:
            gc.collect(2 if self.log.n % self.GC_FULL_EVERY == 0 else 0)


def replay(log_path: str | Path, policy: str | Path | None = None, reference: str | Path | None = None) -> dict:
    """Re-run a log's inputs through a fresh controller; compare actions and stages."""
    log = DeployLog.load(log_path)
    policy = Path(policy or log.meta["policy"]["path"])
    reference = Path(reference or log.meta["reference"]["path"])
    for what, path in (("policy", policy), ("reference", reference)):
        if not path.is_file():
            raise FileNotFoundError(f"{path}: the {what} of {log.path} not found (pass --{what})")
        if file_sha256(path) != log.meta[what]["sha256"]:
            raise ValueError(f"{path}: differs from the {what} the log was recorded with (SHA-256 mismatch)")
    controller = build_controller(policy, reference, _controller_cfg_from_dict(log.meta["controller"]))
    actions = np.full_like(log.arrays["action"], np.nan)
    stages = np.zeros_like(log.arrays["stage"])
    for i, inp in enumerate(log.inputs()):
        out = controller.step(inp)
        stages[i] = out.stage
        if out.action is not None:
            actions[i] = out.action
    recorded = log.arrays["action"]
    both = np.isfinite(recorded) & np.isfinite(actions)
    return {
        "cycles": log.num_cycles,
        "tracking_cycles": int((log.arrays["stage"] == Stage.TRACK).sum()),
        "max_action_diff": float(np.abs(recorded[both] - actions[both]).max()) if both.any() else 0.0,
        "nan_pattern_equal": bool(np.array_equal(np.isnan(recorded), np.isnan(actions))),
        "stages_equal": bool(np.array_equal(stages, log.arrays["stage"])),
        "actions": actions,
    }


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--policy", type=Path, help="exported policy (.onnx from `otr export --onnx`)")
    p.add_argument("--reference", help="reference clip to track (default: the one in the policy's metadata)")
    p.add_argument("--interface", default=None,
                   help="network interface to the robot (e.g. eth0; lo for sim2sim with `otr sim-robot`); "
                        "default: CycloneDDS picks one")
    p.add_argument("--domain-id", type=int, default=0, help="DDS domain id (the G1 uses 0; default: %(default)s)")
    p.add_argument("--log", type=Path, default=None,
                   help="cycle log .npz (default deploy_logs/<policy>_<time>.npz); see `otr inspect`")
    p.add_argument("--auto-start", action="store_true", help="track as soon as the ramp ends (no operator)")
    p.add_argument("--duration", type=float, default=None,
                   help="stop tracking (damp) after this many seconds (default: no limit)")
    p.add_argument("--ramp", type=float, default=SafetyCfg.ramp_s,
                   help="start-up ramp to the default pose (s; default: %(default)s)")
    p.add_argument("--blend", type=float, default=SafetyCfg.blend_s,
                   help="on start: targets from the default pose to the reference's first frame and gains from "
                        "the start-up ones to the policy's over this long (s; 0: none; default: %(default)s)")
    p.add_argument("--end-hold", type=float, default=SafetyCfg.end_hold_s,
                   help="at the clip's end: hold its last frame this long, then damp (s; 0: damp at once; "
                        "default: %(default)s)")
    p.add_argument("--tilt-limit", type=float, default=float(np.degrees(SafetyCfg.tilt_limit_rad)),
                   help="damp when the torso tilts more than this from vertical (degrees; default: %(default).1f)")
    p.add_argument("--stale-cycles", type=int, default=SafetyCfg.stale_cycles,
                   help="damp after this many control cycles without a new LowState (default: %(default)s)")
    p.add_argument("--soft-limit-factor", type=float, default=SafetyCfg.soft_limit_factor,
                   help="joint targets clamped to this fraction of each joint's range (default: %(default)s)")
    p.add_argument("--damp-s", type=float, default=2.0,
                   help="keep sending damping this long, then exit (s; default: %(default)s)")
    p.add_argument("--spin-us", type=float, default=500.0,
                   help="spin (instead of sleep) this long before a deadline (µs; default: %(default)s)")
    p.add_argument("--rt-priority", type=int, default=0,
                   help="run the loop at this SCHED_FIFO priority (1-99; 0 = normal scheduling; default: %(default)s)")
    p.add_argument("--wait-timeout", type=float, default=30.0,
                   help="give up when no LowState arrives in this time (s; default: %(default)s)")
    p.add_argument("--mocap", nargs="?", const=TOPIC_MOCAP, default=None, metavar="TOPIC",
                   help="subscribe to a motion-capture pose stream (agents/deploy/idl/otr_mocap.idl; default topic "
                        f"{TOPIC_MOCAP}): it feeds the observation terms that need the robot's world pose or the "
                        "objects' and is logged (otr sim-robot --publish-mocap publishes one)")
    p.add_argument("--mocap-name", action="append", default=None, metavar="POLICY=STREAM",
                   help="the stream's name of a body the reference names otherwise (e.g. largebox=box_1; the "
                        "robot's base is 'pelvis')")
    p.add_argument("--state-estimator", action="store_true",
                   help="estimate the robot's world position and velocity from the IMU and the legs' kinematics "
                        "(agents/deploy/estimator.py) for the terms that need them, where --mocap does not give them")
    p.add_argument("--replay", type=Path, default=None,
                   help="re-run this log offline through the same controller and compare the actions")


def _main_replay(args: argparse.Namespace) -> int:
    try:
        r = replay(args.replay, args.policy, args.reference)
    except (FileNotFoundError, ValueError, PolicySpecError) as exc:
        print(f"otr deploy --replay: {exc}", file=sys.stderr)
        return 2
    ok = r["max_action_diff"] <= REPLAY_TOL and r["nan_pattern_equal"] and r["stages_equal"]
    print(f"replayed {r['cycles']} cycles ({r['tracking_cycles']} tracking): max |Δaction| {r['max_action_diff']:.3g}, "
          f"stages {'equal' if r['stages_equal'] else 'DIFFER'} -> {'reproduced' if ok else 'NOT reproduced'}")
    return 0 if ok else 1


def main(args: argparse.Namespace) -> int:
    if args.replay is not None:
        return _main_replay(args)
    if args.policy is None:
        print("otr deploy: --policy is required (or --replay LOG)", file=sys.stderr)
        return 2
    import torch

    from agents.deploy.dds import TransportError

    torch.set_num_threads(1)
    try:
        spec_ref = PolicySpec.from_onnx(args.policy)
        reference = args.reference
        if reference is None:
            from agents.export import read_metadata

            reference = (read_metadata(args.policy).get("reference") or {}).get("path")
            if not reference or not Path(reference).is_file():
                raise FileNotFoundError(f"{args.policy}: no --reference given and the metadata's reference "
                                        f"{reference!r} is not a file")
        safety = SafetyCfg(stale_cycles=args.stale_cycles, tilt_limit_rad=float(np.radians(args.tilt_limit)),
                           soft_limit_factor=args.soft_limit_factor, ramp_s=args.ramp, blend_s=args.blend,
                           end_hold_s=args.end_hold)
        cfg = ControllerCfg(safety=safety, auto_start=args.auto_start, duration_s=args.duration,
                            mocap_names=None if args.mocap is None else name_map(args.mocap_name),
                            state_estimator=args.state_estimator)
        controller = build_controller(args.policy, reference, cfg)
        runner = Runner(controller, args.policy, reference, args.domain_id, args.interface, args.damp_s, args.spin_us,
                        args.wait_timeout, args.mocap)
        if args.rt_priority:
            set_realtime_priority(args.rt_priority)  # after the DDS threads exist: only this loop is real-time
            runner.log.meta["rt_priority"] = args.rt_priority
    except (FileNotFoundError, ValueError, PolicySpecError, TransportError, PermissionError) as exc:
        print(f"otr deploy: {exc}", file=sys.stderr)
        return 2
    log_path = log_file(args.log or Path("deploy_logs") / f"{args.policy.stem}_{time.strftime('%Y%m%d-%H%M%S')}.npz")
    if args.log is not None and log_path != args.log:
        print(f"deploy: the log goes to {log_path} (.npz appended to --log {args.log})", flush=True)
    print(f"deploy: {args.policy} on {args.interface or '(auto)'} domain {args.domain_id}, "
          f"{1.0 / spec_ref.policy_dt:g} Hz, {controller.builder.num_frames} reference frames; "
          f"{'auto start' if args.auto_start else 'Enter/s or remote Start to track, space/e or Select = e-stop'}",
          flush=True)
    try:
        status = runner.run()
    finally:
        runner.log.save(log_path, controller.stages.transitions, controller.fault_detail)
        print(f"log: {log_path} ({runner.log.n} cycles)")
    reason = controller.stages.damp_reason
    if reason in ("stale_state", "bad_crc", "nan_state", "nan_action", "tilt", "estop", *MOCAP_FAULTS) and status == 0:
        status = 1
    print(f"deploy: ended in {controller.stage.name}" + (f" ({reason})" if reason else ""))
    return status
