"""The deployment's cycle log: every policy cycle's timing, inputs, observation, action,
command and stage, saved as one ``.npz`` (atomically) that ``otr inspect`` summarises and
``otr deploy --replay`` re-runs.

Arrays (C cycles; NaN where a quantity did not exist that cycle, e.g. no action before TRACK):

- timing (int64 ns from the runner's start, steady clock): ``deadline_ns`` (the cycle's slot on
  the absolute 50 Hz grid), ``wake_ns`` (loop woke), ``received_ns`` (the LowState taken,
  decoded and its CRC checked), ``decided_ns`` (the controller done), ``publish_ns`` (LowCmd
  written); ``policy_ns`` (the ONNX run's own duration, 0 when no policy ran); ``t_s`` (float64
  s, the controller's time input);
- inputs: ``fresh`` (a new LowState arrived), ``crc_ok``, ``keys`` (keyboard KEY_* bits),
  ``state_q``/``state_dq`` (C, 29), ``state_quat_wxyz`` (C, 4), ``state_gyro_b``,
  ``state_accel_b`` (C, 3), ``state_tick_ms``, ``state_mode_machine``, ``state_remote_keys``;
- outputs: ``stage`` (``safety.Stage``), ``frame`` (target frame, −1 when not tracking),
  ``observation`` (C, D) float32, ``action`` (C, 29) raw policy output, ``command`` (C, 5, 29)
  rows q, dq, kp, kd, τ, ``tilt_rad``, ``mpjpe_m``;
- motion capture (``otr deploy --mocap``; B bodies, ``meta["mocap"]["bodies"]``: the pelvis,
  then the reference's moving objects, by the reference's names): ``mocap_fresh`` (a new frame
  arrived), ``mocap_stamp_ns`` (its capture time), ``mocap_seq``, ``mocap_present`` (C, B) (the
  frame carried the body), ``mocap_pos`` (C, B, 3) m and ``mocap_quat`` (C, B, 4) wxyz as
  captured, ``object_error_m`` (C, B − 1): each object's distance from the aligned reference's
  (``controller.CycleOutput.object_error_m``);
- ``base_pos_w``, ``base_lin_vel_w`` (C, 3): the pelvis position (m) and velocity (m/s) the policy
  saw, from motion capture or the state estimator (``--state-estimator``), while tracking;
- ``transition_cycle``/``transition_from``/``transition_to``/``transition_reason``;
- ``meta``: JSON (policy and reference paths with SHA-256, configuration, machine; the message of
  a fault that damped, ``fault_detail``).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agents.deploy.controller import CycleInput, CycleOutput
from agents.deploy.messages import RobotState
from agents.deploy.mocap import MocapFrame, MocapTracker
from agents.deploy.safety import Stage, Transition
from otr_gym import robot
from otr_gym.io import load_npz, save_npz

FORMAT = "otr-gym-deploy-log/1"
NS = 1_000_000_000
#: Arrays that tell a deploy log from the other ``.npz`` files ``otr inspect`` reads.
LOG_KEYS = ("meta", "wake_ns")


def log_file(path: str | Path) -> Path:
    """Where a log asked for at ``path`` is written: ``path`` with ``.npz`` appended unless it
    already ends in it (``--log run`` writes ``run.npz``, as ``np.savez`` would), so that the
    suffix says what the file is to ``otr inspect`` and to a reader of the folder."""
    path = Path(path)
    return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")


def is_deploy_log(keys) -> bool:
    """Whether an .npz file's array names are those of a deploy log."""
    return all(k in keys for k in LOG_KEYS)


def file_sha256(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


class CycleLog:
    """Rows appended per cycle into growing preallocated arrays (no allocation per cycle
    except when a chunk fills)."""

    CHUNK = 4096

    def __init__(self, observation_dim: int, meta: dict, mocap: MocapTracker | None = None):
        self.meta = dict(meta, format=FORMAT)
        self.mocap = mocap
        B = 0 if mocap is None else len(mocap.cfg.bodies)
        if mocap is not None:
            self.meta["mocap"] = dict(self.meta.get("mocap", {}), bodies=list(mocap.cfg.bodies),
                                      names=dict(mocap.cfg.names))
        self.n = 0
        J = robot.NUM_JOINTS
        self._shapes = {
            "deadline_ns": ((), np.int64), "wake_ns": ((), np.int64), "publish_ns": ((), np.int64),
            "received_ns": ((), np.int64), "decided_ns": ((), np.int64), "policy_ns": ((), np.int64),
            "t_s": ((), np.float64), "fresh": ((), bool), "crc_ok": ((), bool), "keys": ((), np.int8),
            "state_q": ((J,), np.float64), "state_dq": ((J,), np.float64), "state_quat_wxyz": ((4,), np.float64),
            "state_gyro_b": ((3,), np.float64), "state_accel_b": ((3,), np.float64),
            "state_tick_ms": ((), np.int64), "state_mode_machine": ((), np.int16), "state_remote_keys": ((), np.int32),
            "stage": ((), np.int8), "frame": ((), np.int32), "observation": ((observation_dim,), np.float32),
            "action": ((J,), np.float64), "command": ((5, J), np.float64), "tilt_rad": ((), np.float64),
            "mpjpe_m": ((), np.float64), "ref_tilt_rad": ((), np.float64),
            "mocap_fresh": ((), bool), "mocap_stamp_ns": ((), np.int64), "mocap_seq": ((), np.int64),
            "mocap_present": ((B,), bool), "mocap_pos": ((B, 3), np.float64), "mocap_quat": ((B, 4), np.float64),
            "object_error_m": ((max(B - 1, 0),), np.float64),
            "base_pos_w": ((3,), np.float64), "base_lin_vel_w": ((3,), np.float64),
        }
        self._arrays = {k: self._empty(k, self.CHUNK) for k in self._shapes}

    def _empty(self, key: str, rows: int) -> np.ndarray:
        shape, dtype = self._shapes[key]
        fill = np.nan if np.issubdtype(dtype, np.floating) else 0
        return np.full((rows, *shape), fill, dtype=dtype)

    def append(self, inp: CycleInput, out: CycleOutput, deadline_ns: int, wake_ns: int, publish_ns: int,
               received_ns: int = 0, decided_ns: int = 0, policy_ns: int = 0) -> None:
        if self.n == len(self._arrays["t_s"]):
            self._arrays = {k: np.concatenate([a, self._empty(k, self.CHUNK)]) for k, a in self._arrays.items()}
        a, i = self._arrays, self.n
        a["deadline_ns"][i], a["wake_ns"][i], a["publish_ns"][i] = deadline_ns, wake_ns, publish_ns
        a["received_ns"][i], a["decided_ns"][i], a["policy_ns"][i] = received_ns, decided_ns, policy_ns
        a["t_s"][i], a["fresh"][i] = inp.t_s, inp.state is not None
        a["crc_ok"][i], a["keys"][i] = inp.crc_ok, inp.keys
        s = inp.state
        if s is not None:
            a["state_q"][i], a["state_dq"][i], a["state_quat_wxyz"][i] = s.joint_pos, s.joint_vel, s.quat_wxyz
            a["state_gyro_b"][i], a["state_accel_b"][i] = s.gyro_b, s.accel_b
            a["state_tick_ms"][i], a["state_mode_machine"][i] = s.tick_ms, s.mode_machine
            a["state_remote_keys"][i] = s.remote_keys
        a["stage"][i], a["frame"][i] = out.stage, out.frame
        a["tilt_rad"][i], a["mpjpe_m"][i], a["ref_tilt_rad"][i] = out.tilt_rad, out.mpjpe_m, out.ref_tilt_rad
        if out.observation is not None:
            a["observation"][i] = out.observation
        if out.action is not None:
            a["action"][i] = out.action
        if out.command is not None:
            a["command"][i] = out.command.as_array()
        if inp.mocap is not None and self.mocap is not None:
            a["mocap_fresh"][i], a["mocap_stamp_ns"][i], a["mocap_seq"][i] = True, inp.mocap.stamp_ns, inp.mocap.seq
            a["mocap_pos"][i], a["mocap_quat"][i] = self.mocap.rows(inp.mocap)
            a["mocap_present"][i] = [self.mocap.stream_name(b) in inp.mocap.names for b in self.mocap.cfg.bodies]
        if out.object_error_m is not None:
            a["object_error_m"][i] = out.object_error_m
        if out.base is not None:
            a["base_pos_w"][i], a["base_lin_vel_w"][i] = out.base.pos_w, out.base.lin_vel_w
        self.n += 1

    def save(self, path: str | Path, transitions: list[Transition], fault_detail: str = "") -> Path:
        """Write the log atomically to ``log_file(path)`` (``.npz`` appended when missing), with
        the message of the fault that damped (``Controller.fault_detail``); returns where."""
        if fault_detail:
            self.meta["fault_detail"] = fault_detail
        arrays = {k: v[: self.n] for k, v in self._arrays.items()}
        arrays["transition_cycle"] = np.array([t.cycle for t in transitions], dtype=np.int64)
        arrays["transition_from"] = np.array([int(t.source) for t in transitions], dtype=np.int8)
        arrays["transition_to"] = np.array([int(t.target) for t in transitions], dtype=np.int8)
        arrays["transition_reason"] = np.array([t.reason for t in transitions], dtype=str)
        arrays["meta"] = np.array(json.dumps(self.meta))
        return save_npz(log_file(path), arrays)


@dataclass
class DeployLog:
    path: Path
    arrays: dict[str, np.ndarray]
    meta: dict

    @classmethod
    def load(cls, path: str | Path) -> DeployLog:
        path = Path(path)
        if not path.is_file() and log_file(path).is_file():  # ``--log run`` wrote run.npz
            path = log_file(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: deploy log not found")
        try:
            arrays = load_npz(path)  # NpzError (a ValueError) names the file and the problem
        except OSError as exc:
            raise ValueError(f"{path}: not a readable deploy log ({exc})") from exc
        try:
            meta = json.loads(str(arrays.pop("meta")))
        except (KeyError, ValueError) as exc:
            raise ValueError(f"{path}: not a readable deploy log (its 'meta' JSON: {exc})") from exc
        if meta.get("format") != FORMAT:
            raise ValueError(f"{path}: format {meta.get('format')!r}, expected {FORMAT!r}")
        return cls(path, arrays, meta)

    @property
    def num_cycles(self) -> int:
        return len(self.arrays["t_s"])

    def inputs(self) -> list[CycleInput]:
        """The controller inputs of every cycle, as recorded."""
        a = self.arrays
        mocap = self.meta.get("mocap")
        out = []
        for i in range(self.num_cycles):
            state = None
            if a["fresh"][i]:
                state = RobotState(joint_pos=a["state_q"][i], joint_vel=a["state_dq"][i],
                                   quat_wxyz=a["state_quat_wxyz"][i], gyro_b=a["state_gyro_b"][i],
                                   accel_b=a["state_accel_b"][i], tick_ms=int(a["state_tick_ms"][i]),
                                   mode_machine=int(a["state_mode_machine"][i]),
                                   remote_keys=int(a["state_remote_keys"][i]))
            frame = None
            if mocap is not None and a["mocap_fresh"][i]:
                present = a["mocap_present"][i]
                names = tuple(mocap["names"].get(b, b) for b, p in zip(mocap["bodies"], present, strict=True) if p)
                frame = MocapFrame(int(a["mocap_stamp_ns"][i]), int(a["mocap_seq"][i]), names,
                                   a["mocap_pos"][i][present], a["mocap_quat"][i][present])
            out.append(CycleInput(t_s=float(a["t_s"][i]), state=state, crc_ok=bool(a["crc_ok"][i]),
                                  keys=int(a["keys"][i]), mocap=frame))
        return out

    def transitions(self) -> list[tuple[float, str, str, str]]:
        """(time s, from, to, reason) of every stage change."""
        a = self.arrays
        t = a["t_s"]
        return [(float(t[c]) if c < len(t) else float("nan"), Stage(f).name, Stage(to).name, str(r))
                for c, f, to, r in zip(a["transition_cycle"], a["transition_from"], a["transition_to"],
                                       a["transition_reason"], strict=True)]


def timing_stats(deadline_ns: np.ndarray, wake_ns: np.ndarray, publish_ns: np.ndarray, period_ns: int) -> dict:
    """Loop timing in ms: period (wake to wake), its error against the nominal period,
    wake lateness (wake − deadline), compute (publish − wake), and missed deadlines (a cycle
    whose command went out after the next cycle's slot, plus grid slots skipped)."""
    ms = 1e-6
    period = np.diff(wake_ns) * ms
    error = np.abs(period - period_ns * ms)
    late = (wake_ns - deadline_ns) * ms
    compute = (publish_ns - wake_ns) * ms
    skipped = int(np.maximum(np.diff(deadline_ns) // period_ns - 1, 0).sum())
    overran = int((publish_ns > deadline_ns + period_ns).sum())

    def pct(x: np.ndarray) -> dict:
        if x.size == 0:
            return {"p50": float("nan"), "p95": float("nan"), "p99": float("nan"), "max": float("nan")}
        p50, p95, p99 = np.percentile(x, [50, 95, 99])
        return {"p50": float(p50), "p95": float(p95), "p99": float(p99), "max": float(x.max())}

    return {
        "cycles": int(len(wake_ns)),
        "period_ms": pct(period), "period_error_ms": pct(error),
        "jitter_ms": float(period.std()) if period.size else float("nan"),
        "lateness_ms": pct(late), "compute_ms": pct(compute),
        "missed_deadlines": skipped + overran,
    }


def log_timing(log: DeployLog) -> dict:
    a = log.arrays
    return timing_stats(a["deadline_ns"], a["wake_ns"], a["publish_ns"], int(log.meta["period_ns"]))


#: The parts of a cycle's compute (``cycle_split_ms``): take, decode and CRC-check the LowState;
#: the controller without the ONNX run (stages, kinematics, observation); the ONNX run; build,
#: CRC, serialise and write the LowCmd, and the log row's bookkeeping before ``publish_ns``.
SPLIT = ("receive", "controller", "policy", "send")


def cycle_split_ms(log: DeployLog, cycles: np.ndarray | None = None) -> dict[str, np.ndarray] | None:
    """Each cycle's compute in ms by part (``SPLIT``) over ``cycles`` (a mask or indices; all by
    default); None for a log written before the runner recorded the parts."""
    a = log.arrays
    if "received_ns" not in a:
        return None
    sel = slice(None) if cycles is None else cycles
    wake, received, decided, publish = (a[k][sel] for k in ("wake_ns", "received_ns", "decided_ns", "publish_ns"))
    policy = a["policy_ns"][sel]
    return {"receive": (received - wake) * 1e-6, "controller": (decided - received - policy) * 1e-6,
            "policy": policy * 1e-6, "send": (publish - decided) * 1e-6}


def summary_rows(log: DeployLog) -> list[tuple[str, str]]:
    """``otr inspect`` rows for a deploy log."""
    a, m = log.arrays, log.meta
    stage = a["stage"]
    track = stage == Stage.TRACK
    tm = log_timing(log)
    rows = [
        ("kind", f"deploy log ({'replayable' if m.get('policy') else 'no policy'})"),
        ("cycles", f"{log.num_cycles} @ {1e9 / m['period_ns']:g} Hz ({log.num_cycles * m['period_ns'] / NS:.1f} s), "
                   f"{int(track.sum())} tracking"),
        ("policy", f"{m.get('policy', {}).get('path', '?')}"),
        ("reference", f"{m.get('reference', {}).get('path', '?')}"),
        ("transport", f"interface {m.get('interface') or '(auto)'}, domain {m.get('domain_id')}"),
    ]
    for t, src, dst, reason in log.transitions():
        rows.append(("stage", f"{t:8.3f} s  {src} → {dst} ({reason})"))
    p, e, late, comp = tm["period_ms"], tm["period_error_ms"], tm["lateness_ms"], tm["compute_ms"]
    rows += [
        ("cycle period", f"p50 {p['p50']:.3f} / p99 {p['p99']:.3f} / max {p['max']:.3f} ms, jitter (std) "
                         f"{tm['jitter_ms']:.3f} ms"),
        ("period error", f"p99 {e['p99']:.3f} / max {e['max']:.3f} ms"),
        ("wake lateness", f"p50 {late['p50']:.3f} / p99 {late['p99']:.3f} / max {late['max']:.3f} ms"),
        ("compute", f"p50 {comp['p50']:.3f} / p99 {comp['p99']:.3f} / max {comp['max']:.3f} ms"),
        ("missed deadlines", str(tm["missed_deadlines"])),
        ("LowState", f"{a['fresh'].mean():.1%} of cycles fresh, {int((~a['crc_ok']).sum())} bad CRC"),
    ]
    if track.any():
        rows.append(("MPJPE", f"{np.nanmean(a['mpjpe_m'][track]) * 1e3:.1f} mm mean over tracking "
                              f"(max {np.nanmax(a['mpjpe_m'][track]) * 1e3:.1f} mm)"))
        rows.append(("torso tilt", f"max {np.degrees(np.nanmax(a['tilt_rad'][track])):.1f}° while tracking"))
        if (start := start_tilt_error_deg(log)) is not None:
            rows.append(("start", f"torso tilt within {start:.1f}° of the reference's in the first "
                                  f"{START_WINDOW_S:g} s of tracking"))
    rows += mocap_rows(log)
    if m.get("fault_detail"):
        rows.append(("fault", m["fault_detail"]))
    return rows


def mocap_rows(log: DeployLog) -> list[tuple[str, str]]:
    """``otr inspect`` rows of the motion-capture stream and of the objects it followed: the box
    error over tracking and where each object ended, from its reference's last frame."""
    a, mocap = log.arrays, log.meta.get("mocap")
    if not mocap or "mocap_fresh" not in a:
        return []
    fresh = a["mocap_fresh"]
    rows = [("mocap", f"{mocap.get('topic', '?')}: {fresh.mean():.1%} of cycles fresh, bodies "
                      f"{', '.join(mocap['bodies'])}")]
    track = a["stage"] == Stage.TRACK
    for k, name in enumerate(mocap["bodies"][1:]):
        error = a["object_error_m"][:, k]
        seen = np.flatnonzero(np.isfinite(error))
        if not seen.size:
            continue
        during = error[track & np.isfinite(error)]
        last = seen[-1]
        where = a["mocap_pos"][last, k + 1]
        on = "last frame" if a["frame"][last] < 0 else f"frame {a['frame'][last] - 1}"
        rows.append((name, (f"error {np.mean(during) * 100:.1f} cm mean / {np.max(during) * 100:.1f} cm max over "
                            "tracking; " if during.size else "")
                     + f"ended at ({where[0]:.2f}, {where[1]:.2f}, {where[2]:.2f}) m, {error[last] * 100:.1f} cm "
                       f"from the reference's {on}"))
    return rows


#: The window after the start of tracking in which ``start_tilt_error_deg`` looks for a lurch (s).
START_WINDOW_S = 1.0


def start_tilt_error_deg(log: DeployLog) -> float | None:
    """Largest |torso tilt − the reference's| (deg) over the first ``START_WINDOW_S`` of tracking;
    None for a log without tracking or without the reference's tilt (logs before it was recorded)."""
    a = log.arrays
    track = np.flatnonzero(a["stage"] == Stage.TRACK)
    if "ref_tilt_rad" not in a or not track.size:
        return None
    first = track[a["t_s"][track] - a["t_s"][track[0]] < START_WINDOW_S]
    error = np.abs(a["tilt_rad"][first] - a["ref_tilt_rad"][first])
    return float(np.degrees(np.nanmax(error))) if np.isfinite(error).any() else None
