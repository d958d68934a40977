"""``otr train --task OTR-G1-BoxTrack-v0`` through evaluation and export (MuJoCo-Warp on the CPU,
8 envs, the generated box clip of conftest)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from agents import runs
from agents.config import train_config_from_dict
from agents.episode_trace import CLIP_END, EpisodeTrace, trace_episode
from agents.evaluate import evaluate
from agents.export import export_onnx, read_metadata
from agents.plots import read_scalars
from agents.train import parse_sets
from otr_gym import cli, robot
from otr_gym.reference import Reference


@pytest.fixture(scope="module")
def box_run(box_reference, tmp_path_factory):
    """One PPO iteration with the object velocity terms switched off by --set (an ablation)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    log_dir = tmp_path_factory.mktemp("runs")
    try:
        rc = cli.main(["train", "--task", "OTR-G1-BoxTrack-v0", "--reference", str(box_reference), "--num-envs", "8",
                       "--device", "cpu", "--iterations", "1", "--save-interval", "1", "--log-dir", str(log_dir),
                       "--set", "env.rewards.object_lin_vel.weight=0", "--set", "env.rewards.object_ang_vel.weight=0"])
    finally:
        torch.set_num_threads(previous)
    assert rc == 0
    (run,) = log_dir.iterdir()
    return run


def test_set_overrides_parse_dotted_keys_into_nested_yaml_values():
    assert parse_sets(["env.rewards.hand_contact.weight=0", "env.objects.overrides.box.mesh=a b.obj", "seed=7"]) == {
        "env": {"rewards": {"hand_contact": {"weight": 0}}, "objects": {"overrides": {"box": {"mesh": "a b.obj"}}}},
        "seed": 7}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        parse_sets(["env.rewards"])


def test_box_training_logs_object_terms_and_keeps_the_ablation_in_the_run(box_run):
    cfg = train_config_from_dict(runs.run_config(box_run)["train"])
    assert cfg.task == "OTR-G1-BoxTrack-v0"
    assert cfg.env["rewards"]["object_lin_vel"]["weight"] == 0 and cfg.env["rewards"]["object_ang_vel"]["weight"] == 0
    scalars = read_scalars(box_run)
    assert scalars["reward/object_lin_vel"][1] == [0.0] and scalars["reward/object_ang_vel"][1] == [0.0]
    assert scalars["reward/hand_contact"][1][0] > 0.0  # 1·dt per step outside windows, more inside
    assert 0.0 <= scalars["metric/object_pos_error_m"][1][0] < 0.5
    assert "termination/object_pos" in scalars and "metric/success_rate" in scalars
    spec = runs.read_env_spec(box_run)
    assert spec["observation_dims"]["policy"] == 154 + 15 + 4  # the perception-free actor: §3's 154 + the box's
    assert cfg.env["observations"]["actor"] == "perception_free"  # recorded by name with the run


def test_a_box_run_from_before_the_perception_free_default_is_read_with_its_mocap_actor(tmp_path):
    old = {"train": {"task": "OTR-G1-BoxTrack-v0", "env": {"rewards": {"object_lin_vel": {"weight": 0}}}}}
    runs.write_yaml(tmp_path / runs.CONFIG_FILE, old)
    env = runs.run_config(tmp_path)["train"]["env"]
    assert env["observations"] == {"actor": "mocap"} and env["rewards"] == old["train"]["env"]["rewards"]
    track = {"train": {"task": "OTR-G1-Track-v0", "env": {}}}
    runs.write_yaml(tmp_path / runs.CONFIG_FILE, track)
    assert runs.run_config(tmp_path) == track


def test_box_evaluation_reports_object_errors_and_export_names_the_object_observations(box_run, box_reference,
                                                                                       tmp_path):
    assert cli.main(["evaluate", str(box_run), "--device", "cpu", "--json", str(tmp_path / "eval.json")]) == 0
    final = json.loads((tmp_path / "eval.json").read_text())["final"]
    assert final["object_pos_error_cm"] >= 0.0 and final["object_pos_error_p95_cm"] >= 0.0
    assert final["object_ori_error_deg"] >= 0.0
    assert set(final["support_contact"]) == {"ground", "table"}
    # the clip starts with the box resting on the floor: its window is open and the box touches it
    assert final["support_contact"]["ground"]["contact_rate"] == 1.0
    meta = read_metadata(export_onnx(box_run, tmp_path / "policy.onnx"))
    names = [t["name"] for t in meta["observation_layout"]]
    assert names[:2] == ["command", "anchor_ori_b"] and "base_lin_vel_b" not in names
    assert names[6:] == ["object_command", "contact_schedule"]
    assert meta["observation_dim"] == 173 and meta["objects"]["moving"] == ["box"]
    assert meta["objects"]["supports"] == ["ground", "table"]


def test_an_episode_trace_agrees_with_the_evaluation_frame_by_frame(box_run, tmp_path, capsys):
    final = evaluate(box_run, device="cpu")["final"]
    trace = trace_episode(box_run, device="cpu")
    # the same protocol and loop: the per-step values average to the evaluation's figures
    assert trace.steps == final["frames"]
    assert trace.frame == list(range(1, trace.steps + 1))  # from frame 0's state on, one frame a step
    assert sum(trace.mpjpe_mm) / trace.steps == pytest.approx(final["mpjpe_mm"], rel=1e-5)
    assert sum(trace.object_pos_error_cm) / trace.steps == pytest.approx(final["object_pos_error_cm"], rel=1e-5)
    assert sum(trace.object_ori_error_deg) / trace.steps == pytest.approx(final["object_ori_error_deg"], rel=1e-5)
    assert all(abs(h) <= p + 1e-6 for h, p in zip(trace.object_height_error_cm, trace.object_pos_error_cm, strict=True))
    assert trace.success == (final["success_rate"] == 1.0)
    assert trace.ended_by  # a termination's name, or the clip's end
    assert (trace.ended_by == [CLIP_END]) == trace.success
    assert trace.object_termination_cm == pytest.approx(25.0)
    # the anchor's offset in the reference's heading frame is the lag, split into ahead and left
    offsets = np.asarray(trace.anchor_offset_cm)
    assert offsets.shape == (trace.steps, 2)
    np.testing.assert_allclose(np.linalg.norm(offsets, axis=1), trace.anchor_lag_cm, rtol=1e-4, atol=1e-4)
    # the box's (one moving object): its error without the height part
    box = np.linalg.norm(np.asarray(trace.object_offset_cm), axis=1)
    whole = np.asarray(trace.object_pos_error_cm)
    np.testing.assert_allclose(box, np.sqrt(np.maximum(whole**2 - np.asarray(trace.object_height_error_cm) ** 2, 0)),
                               rtol=1e-3, atol=1e-3)
    assert [p[0] for p in trace.ahead_by_phase()] == [p[0] for p in trace.object_phases()]
    # the per-body errors are the MPJPE's parts: 14 tracked bodies, the root (pelvis) at zero
    bodies = np.asarray(trace.body_error_mm)
    assert bodies.shape == (trace.steps, 14) and len(trace.body_names) == 14
    np.testing.assert_allclose(bodies.mean(1), trace.mpjpe_mm, rtol=1e-5)
    assert np.all(bodies[:, trace.body_names.index("pelvis")] == 0.0)
    means = trace.body_means_mm()
    assert [m for _, m in means] == sorted((m for _, m in means), reverse=True)
    assert np.mean([m for _, m in means]) == pytest.approx(final["mpjpe_mm"], rel=1e-5)
    # the end effectors' heights are the ee_height termination's quantity: inside its band while
    # the episode runs, outside it where that term ended it
    heights = np.abs(np.asarray(trace.ee_height_cm))
    assert trace.end_effector_names == ["left_ankle_roll_link", "right_ankle_roll_link", "left_wrist_yaw_link",
                                        "right_wrist_yaw_link"]
    assert trace.ee_height_threshold_cm == pytest.approx(25.0)
    assert np.all(heights[:-1] <= 25.0 + 1e-4)
    assert ("ee_height" in trace.ended_by) == bool(heights[-1].max() > 25.0)
    # joints: q − q_ref per joint; torques within the effort limits, not all idle
    error, effort = np.asarray(trace.joint_error_rad), np.asarray(trace.effort_fraction)
    assert error.shape == effort.shape == (trace.steps, 29)
    assert np.all(effort <= 1.0 + 1e-4) and effort.mean() > 0.01
    joints = trace.joints_off_reference(last_steps=5)
    assert len(joints) == 3 and abs(joints[0][1]) >= abs(joints[1][1]) >= abs(joints[2][1])
    j = robot.JOINT_NAMES.index(joints[0][0])
    assert joints[0][1] == pytest.approx(error[-5:, j].mean()) and joints[0][3] == pytest.approx(effort[-5:, j].max())
    assert cli.main(["trace", str(box_run), "--every", "5", "--json", str(tmp_path / "t.json"),
                     "--png", str(tmp_path / "t.png")]) == 0
    out = capsys.readouterr().out
    ee, cm = trace.worst_end_effector(4)
    assert f"| {ee} {cm:+.1f} |" in out  # the fifth step's row
    assert "end effectors' height off their reference at the last step" in out and "; the termination at ±25" in out
    assert f"{trace.steps} steps" in out and out.count("\n| ") >= 2
    assert f"{means[0][0]} {means[0][1]:.1f}" in out  # the per-body line, largest first
    assert f"mean over the episode): {offsets[:, 0].mean():+.1f} / {offsets[:, 1].mean():+.1f}" in out
    saved = json.loads((tmp_path / "t.json").read_text())
    assert saved["mpjpe_mm"] == trace.mpjpe_mm and saved["steps"] == trace.steps
    assert (tmp_path / "t.png").read_bytes()[:4] == b"\x89PNG"


def test_a_trace_from_a_later_frame_is_the_trace_of_the_clip_cut_there(box_run, box_reference, tmp_path, capsys):
    k = 12
    whole = Reference.load(box_reference)
    later = trace_episode(box_run, device="cpu", start_frame=k)
    on_cut = trace_episode(box_run, reference=whole.subclip(k).save(tmp_path / "cut.npz"), device="cpu")
    assert later.start_frame == k and later.clip_frames == whole.num_frames
    assert later.frame == [k + f for f in on_cut.frame] and later.frame[0] == k + 1  # the whole clip's numbering
    assert later.mpjpe_mm == pytest.approx(on_cut.mpjpe_mm, rel=1e-6)
    assert later.object_pos_error_cm == pytest.approx(on_cut.object_pos_error_cm, rel=1e-6)
    assert later.ended_by == on_cut.ended_by and later.success == on_cut.success
    with pytest.raises(SystemExit):  # a usage error
        cli.main(["trace", str(box_run), "--start-frame", "-1"])
    assert "argument --start-frame: must be >= 0" in capsys.readouterr().err
    assert cli.main(["trace", str(box_run), "--start-frame", str(whole.num_frames - 1)]) == 2
    err = capsys.readouterr().err  # names the clip's file and the range
    assert Path(box_reference).name in err and f"frames {whole.num_frames - 1}:{whole.num_frames} are not" in err


def test_a_trace_marks_the_robot_object_windows_and_splits_the_object_error_by_them(box_run, tmp_path, capsys):
    """From frame 55 of the test clip the episode runs into its left-hand window [60, 100) (the
    annotations'): steps before frame 60 are 'before', later ones 'in window', until the falling
    box ends the episode; the phase means partition the episode's object error."""
    trace = trace_episode(box_run, device="cpu", start_frame=55)
    frames = np.asarray(trace.frame)
    assert frames[0] < 60 < frames[-1], frames
    assert trace.object_in_window == [60 <= f < 100 for f in trace.frame]
    phases = trace.object_phases()
    assert [name for name, *_ in phases] == ["before", "in window"]
    error = np.asarray(trace.object_pos_error_cm)
    (_, n_before, before_cm, before_share), (_, n_in, in_cm, in_share) = phases
    assert n_before == int((frames < 60).sum()) and n_before + n_in == trace.steps
    assert before_cm == pytest.approx(error[frames < 60].mean()) and in_cm == pytest.approx(error[frames >= 60].mean())
    assert before_share + in_share == pytest.approx(1.0)
    assert cli.main(["trace", str(box_run), "--start-frame", "55", "--png", str(tmp_path / "t.png")]) == 0
    out = capsys.readouterr().out
    assert f"before {before_cm:.1f} ({n_before} steps" in out and f"in window {in_cm:.1f} ({n_in} steps" in out
    assert (tmp_path / "t.png").read_bytes()[:4] == b"\x89PNG"


def test_object_phases_name_every_stretch_in_clip_order():
    inside = [False, True, True, False, True, False, False]
    error = [1.0, 2.0, 4.0, 6.0, 2.0, 10.0, 12.0]
    trace = EpisodeTrace(checkpoint="c", reference="r", clip_frames=8, frame=list(range(1, 8)), mpjpe_mm=[0.0] * 7,
                         anchor_lag_cm=[0.0] * 7, object_pos_error_cm=error, object_height_error_cm=[0.0] * 7,
                         object_ori_error_deg=[0.0] * 7, ended_by=[CLIP_END], success=True, object_in_window=inside)
    assert trace.object_phases() == [("before", 1, 1.0, pytest.approx(1 / 37)),
                                     ("in window", 3, pytest.approx(8 / 3), pytest.approx(8 / 37)),
                                     ("between windows", 1, 6.0, pytest.approx(6 / 37)),
                                     ("after", 2, 11.0, pytest.approx(22 / 37))]
    assert trace.ahead_by_phase() == []  # no offsets recorded
    trace.anchor_offset_cm = [[float(k), 1.0] for k in range(7)]  # (ahead, left)
    trace.object_offset_cm = [[-2.0 * k, 0.0] for k in range(7)]
    assert trace.ahead_by_phase() == [("before", 0.0, 0.0), ("in window", pytest.approx(7 / 3), pytest.approx(-14 / 3)),
                                      ("between windows", 3.0, -6.0), ("after", 5.5, -11.0)]
    trace.object_in_window = [False] * 7  # no window at all: one phase
    assert [p[:2] for p in trace.object_phases()] == [("before", 7)]
    trace.object_pos_error_cm = trace.object_in_window = None  # no objects
    assert trace.object_phases() == []
