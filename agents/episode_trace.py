"""One evaluation episode, frame by frame: where a policy loses its clip or its object.

``otr evaluate`` gives means over episodes; this follows the single env of the evaluation
protocol (frame 0, no randomisation, mean action; the same loop as ``agents.evaluate``) and
records after every step the reference frame, the root-relative MPJPE and each tracked body's
share of it (which bodies carry the error, and when), how far the robot's anchor (torso) is from
the reference anchor horizontally, split into ahead/behind and left/right of the reference
anchor's heading (a robot that trails its reference from one that runs ahead of it), and for
the moving objects (box task) the position error, its horizontal part split the same way, the
height offset from the reference (negative: below it) and the orientation error, each a mean
over the moving objects, and whether a robot–object proximity window of the reference is open
(the gates of the contact rewards: a hand near an object, from the reach to the release). The
object error is then also split into the phases before the first window, in a window, between
windows and after the last one, which tells a policy that carries well but sets the object down
off its mark from one that loses it in the hands. Per step it also keeps each end effector's
height off its reference (the quantity of the ``ee_height`` termination, which ends most
failed episodes), each joint's distance from its reference angle and the torque its actuator
applied as a share of the joint's effort limit: a joint far from its reference at a small share
of its effort is one the policy did not drive there (a learning gap), one pinned at its limit one
the robot could not (a capability gap). It names what ended the episode: the termination terms
that fired, or the clip's end.
``--start-frame K`` starts the episode on the reference's frame K instead (the clip cut there,
``Reference.subclip``): whether a failure comes from drift carried from the start or from the
passage itself.

    otr trace RUN_OR_CHECKPOINT [--reference REF] [--start-frame K] \\
        [--device cpu] [--every 10] [--png trace.png] [--json trace.json]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from agents import runs
from agents.devices import resolve_device
from agents.evaluate import evaluation_library
from agents.policy import load_policy
from agents.vecenv import make_vec_env
from envs.mdp.metrics import (
    anchor_horizontal_error_m,
    anchor_offset_heading_m,
    body_position_error_root_relative,
    end_effector_height_offset_m,
    object_offset_heading_m,
    object_orientation_error_rad,
    object_position_error_m,
)
from otr_gym import robot
from otr_gym.cli import int_at_least
from otr_gym.flags import true_intervals
from otr_gym.io import save_figure, write_json

#: What ``ended_by`` says for an episode that reached its clip's last frame.
CLIP_END = "clip end"


@dataclass
class EpisodeTrace:
    """Per-step values of one episode (lists of equal length, one entry per env step)."""

    checkpoint: str
    reference: str
    clip_frames: int  # of the whole clip
    frame: list[int]  # reference frame the step's state is compared with (50 Hz clips: 20 ms each)
    mpjpe_mm: list[float]  # root-relative, 14 bodies (the evaluation's metric)
    anchor_lag_cm: list[float]  # ‖xy of the reference anchor − xy of the robot's anchor‖, world
    object_pos_error_cm: list[float] | None  # moving objects only; None on a task without objects
    object_height_error_cm: list[float] | None  # z of the object − z of its reference, world
    object_ori_error_deg: list[float] | None
    ended_by: list[str]  # the termination terms that fired at the last step, or [CLIP_END]
    success: bool
    object_termination_cm: float | None = None  # the run's object position termination, if any
    body_names: list[str] | None = None  # the tracked bodies, in the order of body_error_mm's rows
    body_error_mm: list[list[float]] | None = None  # per step, per body: root-relative error (mm)
    start_frame: int = 0  # the reference frame the episode started on
    object_in_window: list[bool] | None = None  # per step: a robot–object window of the reference is open
    # per step: (ahead, left) of the robot's anchor from the reference's, cm, the reference's heading frame
    anchor_offset_cm: list[list[float]] | None = None
    object_offset_cm: list[list[float]] | None = None  # the same for the moving objects (their mean), cm
    end_effector_names: list[str] | None = None  # the ee_height termination's bodies (ankles, wrists)
    ee_height_cm: list[list[float]] | None = None  # per step, per end effector: z − reference z (cm, aligned)
    ee_height_threshold_cm: float | None = None  # the run's ee_height termination, if any
    joint_error_rad: list[list[float]] | None = None  # per step, per joint (robot.JOINT_NAMES): q − q_ref
    effort_fraction: list[list[float]] | None = None  # per step, per joint: |actuator torque| / effort limit

    @property
    def steps(self) -> int:
        return len(self.frame)

    def body_means_mm(self) -> list[tuple[str, float]]:
        """(body, mean root-relative error over the episode, mm), largest first; the MPJPE is
        their mean."""
        if not self.body_error_mm:
            return []
        means = np.asarray(self.body_error_mm).mean(0)
        return sorted(zip(self.body_names, means.tolist()), key=lambda kv: -kv[1])

    def worst_end_effector(self, step: int) -> tuple[str, float]:
        """(end effector, its height off the reference in cm) with the largest |offset| at ``step``."""
        heights = self.ee_height_cm[step]
        k = int(np.argmax(np.abs(heights)))
        return self.end_effector_names[k], float(heights[k])

    def joints_off_reference(self, last_steps: int = 25, count: int = 3) -> list[tuple[str, float, float, float]]:
        """(joint, mean q − q_ref in rad, mean and peak share of its effort limit) over the
        episode's last ``last_steps`` steps, for the ``count`` joints with the largest mean
        |q − q_ref| there, largest first. Empty when the joints were not recorded."""
        if not self.joint_error_rad:
            return []
        error = np.asarray(self.joint_error_rad)[-last_steps:]
        effort = np.asarray(self.effort_fraction)[-last_steps:]
        order = np.argsort(-np.abs(error).mean(0))[:count]
        return [(robot.JOINT_NAMES[j], float(error[:, j].mean()), float(effort[:, j].mean()), float(effort[:, j].max()))
                for j in order]

    #: the object phases, in clip order
    PHASES = ("before", "in window", "between windows", "after")

    def _phase_labels(self) -> np.ndarray | None:
        """Per step, its phase (``PHASES``); None on a task without objects."""
        if self.object_pos_error_cm is None or self.object_in_window is None:
            return None
        inside = np.asarray(self.object_in_window, dtype=bool)
        phase = np.full(inside.shape, "in window", dtype=object)
        if inside.any():
            first, last = np.flatnonzero(inside)[[0, -1]]
            index = np.arange(inside.size)
            phase[~inside & (index < first)] = "before"
            phase[~inside & (index > last)] = "after"
            phase[~inside & (index > first) & (index < last)] = "between windows"
        else:
            phase[:] = "before"
        return phase

    def object_phases(self) -> list[tuple[str, int, float, float]]:
        """(phase, steps, mean object error cm, share of the episode's summed error) for the
        phases present, in clip order: ``before`` (the reference's first robot–object window),
        ``in window``, ``between windows``, ``after`` (its last window: the object set down).
        Empty on a task without objects."""
        phase = self._phase_labels()
        if phase is None:
            return []
        error = np.asarray(self.object_pos_error_cm)
        total = float(error.sum()) or 1.0
        return [(name, int((phase == name).sum()), float(error[phase == name].mean()),
                 float(error[phase == name].sum()) / total)
                for name in self.PHASES if (phase == name).any()]

    def ahead_by_phase(self) -> list[tuple[str, float, float | None]]:
        """(phase, mean cm the anchor is ahead of its reference, mean cm the objects are ahead of
        theirs) for the object phases present, both along the reference anchor's heading
        (negative: behind). Empty on a task without objects or without the offsets."""
        phase = self._phase_labels()
        if phase is None or self.anchor_offset_cm is None:
            return []
        anchor = np.asarray(self.anchor_offset_cm)[:, 0]
        objects = None if self.object_offset_cm is None else np.asarray(self.object_offset_cm)[:, 0]
        return [(name, float(anchor[phase == name].mean()),
                 None if objects is None else float(objects[phase == name].mean()))
                for name in self.PHASES if (phase == name).any()]

    def rows(self, every: int = 10) -> list[str]:
        """A Markdown table: every ``every``-th step and the last."""
        objects = self.object_pos_error_cm is not None
        offsets = self.anchor_offset_cm is not None
        object_offsets = objects and self.object_offset_cm is not None
        limbs = bool(self.ee_height_cm) and bool(self.joint_error_rad)
        head = ("| frame | MPJPE mm | anchor lag cm |" + (" anchor ahead / left cm |" if offsets else "")
                + (" end effector farthest in height, cm | joint farthest, rad (share of effort) |" if limbs else "")
                + (" object error cm | object height cm | object orientation deg |" if objects else "")
                + (" object ahead / left cm |" if object_offsets else ""))
        out = [head, "|" + "---|" * (head.count("|") - 1)]
        picks = sorted(set(range(every - 1, self.steps, every)) | {self.steps - 1})
        for i in picks:
            row = f"| {self.frame[i]} | {self.mpjpe_mm[i]:.1f} | {self.anchor_lag_cm[i]:.1f} |"
            if offsets:
                row += f" {self.anchor_offset_cm[i][0]:+.1f} / {self.anchor_offset_cm[i][1]:+.1f} |"
            if limbs:
                ee, cm = self.worst_end_effector(i)
                j = int(np.argmax(np.abs(self.joint_error_rad[i])))
                row += (f" {ee} {cm:+.1f} | {robot.JOINT_NAMES[j]} {self.joint_error_rad[i][j]:+.2f}"
                        f" ({100 * self.effort_fraction[i][j]:.0f} %) |")
            if objects:
                row += (f" {self.object_pos_error_cm[i]:.1f} | {self.object_height_error_cm[i]:+.1f} |"
                        f" {self.object_ori_error_deg[i]:.1f} |")
            if object_offsets:
                row += f" {self.object_offset_cm[i][0]:+.1f} / {self.object_offset_cm[i][1]:+.1f} |"
            out.append(row)
        return out


def _termination_cm(cfg, name: str) -> float | None:
    """The distance (cm) of the run's termination term ``name``; None when the run has none."""
    term = cfg.terminations.get(name)
    threshold = None if term is None else term.params.get("threshold_m")
    return None if threshold is None else 100.0 * float(threshold)


@torch.inference_mode()
def trace_episode(run_or_checkpoint: str | Path, reference: str | Path | None = None, device: str = "cpu",
                  seed: int = 0, start_frame: int = 0) -> EpisodeTrace:
    """Run one evaluation episode of a checkpoint (a run folder: its latest) on one clip, from
    its frame ``start_frame``; frames are reported in the whole clip's numbering."""
    ckpt = runs.resolve_checkpoint(Path(run_or_checkpoint))
    torch_device = resolve_device(device)
    policy = load_policy(ckpt, torch_device)
    library, overrides = evaluation_library(policy, reference, randomize=False)
    reference = library.source
    if len(library.references) != 1:
        raise ValueError(f"{reference}: {len(library.references)} clips; trace one clip at a time "
                         "(pass --reference CLIP)")
    clip = library.references[0]
    clip_frames = clip.num_frames
    if start_frame:
        clip = clip.subclip(start_frame)
    env = make_vec_env(policy.train_cfg.task, [clip], 1, str(torch_device), overrides, evaluation=True, seed=seed)
    vec = env.unwrapped
    obs, _ = vec.reset(seed=seed)
    has_objects = vec.tracking_state.objects is not None
    ee = vec.tracking_state.end_effectors
    effort = torch.as_tensor(robot.EFFORT_LIMIT, dtype=torch.float32, device=vec.device)
    names = ("frame", "mpjpe", "bodies", "lag", "offset", "pos", "height", "ori", "window", "obj_offset",
             "ee", "joint", "effort")
    cols: dict[str, list] = {k: [] for k in names}
    ended_by, success = [], False
    try:
        for _ in range(int(vec.motion.clip_length.max()) + 1):
            actions = policy.act(TensorDict(dict(obs), batch_size=[1], device=vec.device))
            frame = start_frame + int(vec.command.frame[0])  # the step's state is compared with it, then it advances
            obs, _, terminated, truncated, info = vec.step(actions)
            s = vec.tracking_state
            cols["frame"].append(frame)
            bodies_mm = 1000.0 * body_position_error_root_relative(s)[0]
            cols["mpjpe"].append(float(bodies_mm.mean()))
            cols["bodies"].append(bodies_mm.tolist())
            cols["lag"].append(100.0 * float(anchor_horizontal_error_m(s)[0]))
            cols["offset"].append((100.0 * anchor_offset_heading_m(s)[0]).tolist())
            cols["ee"].append((100.0 * end_effector_height_offset_m(s)[0]).tolist())
            cols["joint"].append((s.joint_pos[0] - s.ref_joint_pos[0]).tolist())
            cols["effort"].append((vec.task.backend.joint_torque_nm[0].abs() / effort).tolist())
            if has_objects:
                o = s.objects
                cols["pos"].append(100.0 * float(object_position_error_m(s)[0].mean()))
                cols["height"].append(100.0 * float((o.pos_w[0, :, 2] - o.ref_pos_w[0, :, 2]).mean()))
                cols["ori"].append(float(torch.rad2deg(object_orientation_error_rad(s)[0]).mean()))
                cols["window"].append(bool((o.hand_gate[0] > 0).any()))
                cols["obj_offset"].append((100.0 * object_offset_heading_m(s)[0].mean(0)).tolist())
            if bool(terminated[0]) or bool(truncated[0]):
                ended_by = [k for k, v in info["terminations"].items() if bool(v[0])]
                success = bool(info["success"][0])
                if not ended_by:
                    ended_by = [CLIP_END]
                break
    finally:
        env.close()
    return EpisodeTrace(
        checkpoint=str(ckpt.path), reference=str(reference), clip_frames=clip_frames, start_frame=start_frame,
        frame=cols["frame"], mpjpe_mm=cols["mpjpe"], anchor_lag_cm=cols["lag"],
        object_pos_error_cm=cols["pos"] if has_objects else None,
        object_height_error_cm=cols["height"] if has_objects else None,
        object_ori_error_deg=cols["ori"] if has_objects else None,
        object_in_window=cols["window"] if has_objects else None,
        object_offset_cm=cols["obj_offset"] if has_objects else None,
        anchor_offset_cm=cols["offset"], ended_by=ended_by, success=success,
        object_termination_cm=_termination_cm(vec.task.cfg, "object_pos"),
        body_names=list(vec.tracking_state.body_names), body_error_mm=cols["bodies"],
        end_effector_names=[vec.tracking_state.body_names[k] for k in ee.tolist()], ee_height_cm=cols["ee"],
        ee_height_threshold_cm=_termination_cm(vec.task.cfg, "ee_height"),
        joint_error_rad=cols["joint"], effort_fraction=cols["effort"])


def plot_trace(trace: EpisodeTrace, out_png: str | Path) -> Path:
    """Panels against the reference frame: MPJPE, the three bodies with the largest mean error,
    the anchor lag and how far the anchor is ahead of its reference; for objects, the position
    error and its parts ahead, to the left (the reference anchor's heading frame) and up, with the
    object termination's distance and the reference's robot–object windows shaded; orientation
    error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    objects = trace.object_pos_error_cm is not None
    limbs = bool(trace.ee_height_cm) and bool(trace.joint_error_rad)
    panels = 1 + 2 * limbs + 2 * objects
    fig, axes = plt.subplots(1, panels, figsize=(5.2 * panels, 3.6), squeeze=False)
    axes = list(axes[0])
    frames = np.asarray(trace.frame)
    axes[0].plot(frames, trace.mpjpe_mm, lw=1.1, label="MPJPE (mm)")
    if trace.body_error_mm:
        bodies = np.asarray(trace.body_error_mm)
        for name, _ in trace.body_means_mm()[:3]:
            axes[0].plot(frames, bodies[:, trace.body_names.index(name)], lw=0.7, ls=":", label=f"{name} (mm)")
    axes[0].plot(frames, np.asarray(trace.anchor_lag_cm) * 10.0, lw=1.1, label="anchor lag (mm)")
    if trace.anchor_offset_cm:
        ahead = np.asarray(trace.anchor_offset_cm)[:, 0] * 10.0
        axes[0].plot(frames, ahead, lw=1.0, ls="--", label="anchor ahead (+) / behind (−) (mm)")
        axes[0].axhline(0.0, color="k", lw=0.5)
    axes[0].set_title("tracking", fontsize=9)
    if limbs:
        ee_ax, joint_ax = axes.pop(1), axes.pop(1)
        for name, column in zip(trace.end_effector_names, np.asarray(trace.ee_height_cm).T, strict=True):
            ee_ax.plot(frames, column, lw=1.0, label=name)
        if trace.ee_height_threshold_cm is not None:
            for sign in (1, -1):
                ee_ax.axhline(sign * trace.ee_height_threshold_cm, color="k", lw=0.8, ls="--",
                              label="ee_height termination" if sign > 0 else None)
        ee_ax.set_title("end effectors: height − reference (cm)", fontsize=9)
        effort_ax = joint_ax.twinx()
        error, effort = np.asarray(trace.joint_error_rad), np.asarray(trace.effort_fraction)
        for k, (name, *_) in enumerate(trace.joints_off_reference()):
            j = robot.JOINT_NAMES.index(name)
            joint_ax.plot(frames, error[:, j], lw=1.1, color=f"C{k}", label=f"{name} q − q_ref (rad)")
            effort_ax.plot(frames, effort[:, j], lw=0.8, ls=":", color=f"C{k}")
        effort_ax.set_ylim(0.0, 1.05)
        effort_ax.set_ylabel("torque / effort limit (dotted)", fontsize=8)
        joint_ax.set_title("joints farthest from their reference at the end", fontsize=9)
        axes += [ee_ax, joint_ax]
    if objects:
        axes[1].plot(frames, trace.object_pos_error_cm, lw=1.1, label="position error")
        axes[1].plot(frames, trace.object_height_error_cm, lw=1.1, label="height (object − reference)")
        if trace.object_offset_cm:
            offset = np.asarray(trace.object_offset_cm)
            axes[1].plot(frames, offset[:, 0], lw=0.9, ls="--", label="ahead (+) / behind (−)")
            axes[1].plot(frames, offset[:, 1], lw=0.9, ls=":", label="left (+) / right (−)")
        if trace.object_termination_cm is not None:
            axes[1].axhline(trace.object_termination_cm, color="k", lw=0.8, ls="--", label="object termination")
        for k, (a, b) in enumerate(true_intervals(trace.object_in_window or [])):  # the windows, shaded
            axes[1].axvspan(frames[a] - 0.5, frames[b - 1] + 0.5, color="0.85", zorder=0,
                            label="robot–object window" if k == 0 else None)
        axes[1].set_title("object (cm)", fontsize=9)
        axes[2].plot(frames, trace.object_ori_error_deg, lw=1.1)
        axes[2].set_title("object orientation error (deg)", fontsize=9)
    for ax in axes:
        ax.set_xlabel(f"reference frame (of {trace.clip_frames})")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    end = "success" if trace.success else "ended by " + ", ".join(trace.ended_by)
    start = f", started at frame {trace.start_frame}" if trace.start_frame else ""
    fig.suptitle(f"{Path(trace.checkpoint).parent.name}/{Path(trace.checkpoint).name}: {end} at frame "
                 f"{trace.frame[-1]}{start}", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, out_png)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """``otr trace``'s arguments."""
    parser.add_argument("run_or_checkpoint", help="run folder (its latest checkpoint) or model_<it>.pt")
    parser.add_argument("--reference", help="clip to trace (default: the run's reference)")
    parser.add_argument("--start-frame", type=int_at_least(0), default=0,
                        help="start on this reference frame, the clip cut there (frame index; default: %(default)s)")
    parser.add_argument("--device", default="cpu", help="torch/warp device (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the env's reset (default: %(default)s)")
    parser.add_argument("--every", type=int_at_least(1), default=10,
                        help="print every N-th step (steps; default: %(default)s)")
    parser.add_argument("--png", help="write the per-frame curves here (PNG)")
    parser.add_argument("--json", help="write the per-frame values here (JSON)")


def main(args: argparse.Namespace) -> int:
    """``otr trace RUN_OR_CHECKPOINT``: print the episode's rows and summaries; a run, checkpoint or
    clip that cannot be used (or a start frame beyond the clip): a message naming it, exit code 2."""
    try:
        trace = trace_episode(args.run_or_checkpoint, args.reference, args.device, args.seed, args.start_frame)
    except (runs.RunError, ValueError) as exc:  # a library given for one clip, a start frame beyond the clip
        print(f"otr trace: {exc}", file=sys.stderr)
        return 2
    print("\n".join(trace.rows(args.every)))
    end = "success" if trace.success else "ended by " + ", ".join(trace.ended_by)
    print(f"{trace.steps} steps, {end} at frame {trace.frame[-1]} of {trace.clip_frames}")
    print("root-relative error per body, mean over the episode (mm): "
          + ", ".join(f"{name} {mm:.1f}" for name, mm in trace.body_means_mm()))
    if trace.ee_height_cm:
        limit = ("" if trace.ee_height_threshold_cm is None
                 else f"; the termination at ±{trace.ee_height_threshold_cm:.0f}")
        print(f"end effectors' height off their reference at the last step (cm, robot − reference{limit}): "
              + ", ".join(f"{name} {cm:+.1f}" for name, cm in zip(trace.end_effector_names, trace.ee_height_cm[-1],
                                                                  strict=True)))
    joints = trace.joints_off_reference()
    if joints:
        print(f"joints farthest from their reference over the last {min(25, trace.steps)} steps "
              "(mean q − q_ref in rad; mean / peak torque as a share of the joint's effort limit): "
              + ", ".join(f"{name} {rad:+.2f} ({100 * mean:.0f} / {100 * peak:.0f} %)"
                          for name, rad, mean, peak in joints))
    phases = trace.object_phases()
    if phases:
        print("object error by the reference's robot–object windows (cm, steps, share of the error): "
              + ", ".join(f"{name} {cm:.1f} ({n} steps, {100 * share:.0f} %)" for name, n, cm, share in phases))
    if trace.anchor_offset_cm:
        offset = np.asarray(trace.anchor_offset_cm)
        print(f"torso ahead / left of its reference (cm, mean over the episode): {offset[:, 0].mean():+.1f} / "
              f"{offset[:, 1].mean():+.1f} (ahead in {100 * (offset[:, 0] > 0).mean():.0f} % of the steps)")
    ahead = trace.ahead_by_phase()
    if ahead:
        print("ahead of the reference along its heading (cm; negative: behind), anchor / object, by the same phases: "
              + ", ".join(f"{name} {a:+.1f} / {o:+.1f}" for name, a, o in ahead))
    if args.png:
        print(f"wrote {plot_trace(trace, args.png)}")
    if args.json:
        print(f"wrote {write_json(args.json, {**asdict(trace), 'steps': trace.steps})}")
    return 0
