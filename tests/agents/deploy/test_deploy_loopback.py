"""End to end on real CycloneDDS over the loopback interface: ``otr sim-robot`` and
``otr deploy`` as two processes, exactly as a user runs sim2sim (no transport mocks)."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from agents.deploy import crc
from agents.deploy.log import DeployLog, start_tilt_error_deg
from agents.deploy.messages import JointCommand, low_cmd
from agents.deploy.reference_policy import reference_policy_model, training_metadata
from agents.deploy.safety import STARTUP_KD, STARTUP_KP, Stage
from agents.procedural import SwaySpec, sway_reference
from otr_gym import cli, robot
from otr_gym.reference import Reference
from tests.deploy_support import REPO, domain_id, feedback_policy, finish, nan_policy, otr, save_with_metadata

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def sway(tmp_path_factory):
    return sway_reference(SwaySpec(duration_s=16.0)).save(tmp_path_factory.mktemp("deploy") / "sway.npz")


@pytest.fixture(scope="module")
def meta(sway):
    m = training_metadata(sway)
    m["joint_stiffness"], m["joint_damping"] = STARTUP_KP.tolist(), STARTUP_KD.tolist()  # open loop needs them
    return m


def sim2sim(tmp, policy, reference, domain, sim_args=(), deploy_args=(), sim_s=20.0):
    """Run the sim robot and the runner side by side; (runner rc, output, log, sim stats). The
    sim robot exits 1 s after the runner's last LowCmd (``sim_s`` is only an upper bound)."""
    stats, log = tmp / f"sim_{domain}.json", tmp / f"run_{domain}.npz"
    sim = otr("sim-robot", "--interface", "lo", "--domain-id", str(domain), "--reference", str(reference),
              "--duration", str(sim_s), "--idle-exit", "1", "--stats", str(stats), *sim_args)
    run = otr("deploy", "--policy", str(policy), "--reference", str(reference), "--interface", "lo",
              "--domain-id", str(domain), "--auto-start", "--ramp", "0.5", "--damp-s", "0.5", "--log", str(log),
              *deploy_args)
    rc, out = finish(run, sim_s + 30)
    sim_rc, sim_out = finish(sim, sim_s + 30)
    assert sim_rc == 0, sim_out
    return rc, out, DeployLog.load(log), json.loads(stats.read_text())


@pytest.fixture(scope="module")
def tracked_run(tmp_path_factory, meta, sway):
    tmp = tmp_path_factory.mktemp("sim2sim")
    policy = feedback_policy(meta, tmp / "feedback.onnx")
    return (policy,) + sim2sim(tmp, policy, sway, domain_id(0), deploy_args=("--duration", "10"), sim_s=60.0)


def test_runner_and_sim_robot_keep_the_g1_upright_for_10_s_of_tracking(tracked_run):
    _, rc, out, log, stats = tracked_run
    assert rc == 0, out
    stage = log.arrays["stage"]
    # 10 s of tracking on the runner's 50 Hz grid; a loaded 2-core CI machine may skip a few slots
    # (the clock jumps to the latest due slot), which the log counts as missed deadlines
    track_slots = np.diff(log.arrays["deadline_ns"][stage == Stage.TRACK][[0, -1]])[0] // log.meta["period_ns"] + 1
    assert track_slots >= 500, track_slots
    assert (stage == Stage.TRACK).sum() >= 0.95 * track_slots, ((stage == Stage.TRACK).sum(), track_slots)
    assert log.transitions()[-1][1:] == ("TRACK", "DAMP", "duration")
    assert stats["upright"], stats  # pelvis above 0.5 m and tilt below 60° until damping
    assert stats["min_pelvis_z_m"] > 0.6
    assert stats["accepted"] >= 500 and stats["dropped_bad_crc"] == 0
    mpjpe = log.arrays["mpjpe_m"][stage == Stage.TRACK]
    assert np.nanmean(mpjpe) < 0.04, np.nanmean(mpjpe)  # open loop + small feedback: centimetres


def test_a_replayed_log_reproduces_the_recorded_actions_to_1e_6(tracked_run, capsys):
    policy, _, _, log, _ = tracked_run
    assert cli.main(["deploy", "--replay", str(log.path), "--policy", str(policy)]) == 0
    assert "reproduced" in capsys.readouterr().out
    from agents.deploy.runner import replay

    r = replay(log.path)
    assert r["tracking_cycles"] == (log.arrays["stage"] == Stage.TRACK).sum() >= 475  # every logged cycle
    assert r["max_action_diff"] <= 1e-6 and r["stages_equal"] and r["nan_pattern_equal"]
    # the feedback term makes actions depend on the state: a replay with different states would differ
    track = log.arrays["stage"] == Stage.TRACK
    assert np.ptp(log.arrays["observation"][track, 67:96], axis=0).max() > 1e-3


def test_inspect_summarises_timing_stages_and_tracking_error(tracked_run, capsys):
    _, _, _, log, _ = tracked_run
    assert cli.main(["inspect", str(log.path)]) == 0
    text = capsys.readouterr().out
    for needle in ("cycle period", "missed deadlines", "TRACK → DAMP (duration)", "MPJPE"):
        assert needle in text, text


def test_bridge_stops_publishing_then_the_runner_damps_within_3_cycles(tmp_path, meta, sway):
    policy = feedback_policy(meta, tmp_path / "p.onnx")
    rc, out, log, stats = sim2sim(tmp_path, policy, sway, domain_id(1), sim_args=("--mute-after", "2"), sim_s=60.0)
    assert rc == 1, out  # a fault ended the run
    (damp,) = [t for t in log.transitions() if t[2] == "DAMP"]
    assert damp[1:] == ("TRACK", "DAMP", "stale_state")
    a = log.arrays
    damp_cycle = int(np.argmax(a["stage"] == Stage.DAMP))
    last_fresh = int(np.nonzero(a["fresh"][:damp_cycle])[0].max())
    assert damp_cycle - last_fresh <= 3
    assert (a["command"][damp_cycle:, 2] == 0).all()  # kp = 0 from then on: damping
    assert stats["first_damping_wall_s"] is not None and stats["last_command_kp_mean"] == 0.0


def test_a_nan_action_sends_the_robot_to_damping(tmp_path, meta, sway):
    policy = nan_policy(meta, tmp_path / "nan.onnx")
    rc, out, log, stats = sim2sim(tmp_path, policy, sway, domain_id(2), sim_s=60.0)
    assert rc == 1, out
    a = log.arrays
    first_track = int(np.argmax(a["stage"] == Stage.TRACK)) if (a["stage"] == Stage.TRACK).any() else None
    (damp,) = [t for t in log.transitions() if t[2] == "DAMP"]
    assert damp[1:] == ("TRACK", "DAMP", "nan_action")
    assert first_track is None  # damped in the very cycle tracking began, no NaN command went out
    assert np.isfinite(a["command"][np.isfinite(a["command"][:, 0, 0])]).all()
    assert stats["first_damping_wall_s"] is not None and stats["upright"]


def test_the_bridge_drops_lowcmds_with_a_wrong_crc_and_counts_them(tmp_path):
    from agents.deploy.dds import G1Domain, take_latest

    domain, stats_path = domain_id(3), tmp_path / "sim.json"
    sim = otr("sim-robot", "--interface", "lo", "--domain-id", str(domain), "--duration", "5",
              "--stats", str(stats_path))
    dds = G1Domain(domain, "lo")
    reader, writer = dds.latest_reader(dds.lowstate_topic), dds.writer(dds.lowcmd_topic)
    deadline = time.monotonic() + 20
    while take_latest(reader) is None:  # discovery done: the robot's LowState reaches us
        assert time.monotonic() < deadline, "no LowState from the sim robot"
        time.sleep(0.01)
    time.sleep(0.2)  # and our writer is matched by its reader
    squat = robot.DEFAULT_JOINT_POS + 0.5
    cmd = JointCommand(q=squat, dq=np.zeros(29), kp=STARTUP_KP, kd=STARTUP_KD, tau=np.zeros(29))
    for _ in range(20):
        msg = crc.with_crc(low_cmd(cmd, 5))
        msg.crc ^= 0x1  # one bit off
        writer.write(msg)
        time.sleep(0.02)
    time.sleep(0.2)
    for _ in range(5):  # the same command with its CRC right is applied
        writer.write(crc.with_crc(low_cmd(cmd, 5)))
        time.sleep(0.02)
    rc, out = finish(sim, 30)
    assert rc == 0, out
    stats = json.loads(stats_path.read_text())
    assert stats["dropped_bad_crc"] == 20, stats
    # only the five with a right CRC were accepted, and only they started the physics
    assert stats["accepted"] == 5 and stats["steps"] > 0


def test_with_the_gantry_the_ramp_happens_hanging_and_the_robot_is_lowered_onto_its_feet(tmp_path, meta, sway):
    policy = feedback_policy(meta, tmp_path / "p.onnx")
    trace = tmp_path / "trace.npz"
    rc, out, log, stats = sim2sim(tmp_path, policy, sway, domain_id(4),
                                  sim_args=("--gantry", "--gantry-release", "2.5", "--trace", str(trace)),
                                  deploy_args=("--duration", "3", "--ramp", "2"), sim_s=60.0)
    assert rc == 0, out
    assert (log.arrays["stage"] == Stage.RAMP).sum() >= 95 and (log.arrays["stage"] == Stage.TRACK).sum() >= 145
    t = np.load(trace)
    since_command = t["wall_s"] - stats["first_command_wall_s"]
    pelvis_z = t["qpos"][:, 2]
    hanging = pelvis_z[(since_command > 0) & (since_command < 2.5)]  # the ramp, in the gantry
    standing = pelvis_z[(since_command > 3.6) & (since_command < 5.0)]  # lowered, tracking
    assert hanging.min() > 0.79  # default stance 0.76 m + the gantry's 5 cm, less its sag
    assert 0.70 < standing.min() and standing.max() < 0.78
    assert stats["upright"], stats


def _start_steps(log: DeployLog) -> tuple[float, float]:
    """(largest per-cycle change of the joint targets, of the kp gains) from the end of the ramp
    to one second into tracking."""
    a = log.arrays
    ramp_end = log.transitions()[1][0]  # RAMP → HOLD
    track = a["t_s"][a["stage"] == Stage.TRACK]
    window = (a["t_s"] >= ramp_end - 0.1) & (a["t_s"] <= track[0] + 1.0) & np.isfinite(a["command"][:, 0, 0])
    command = a["command"][window]
    return float(np.abs(np.diff(command[:, 0], axis=0)).max()), float(np.abs(np.diff(command[:, 2], axis=0)).max())


@pytest.mark.parametrize("blend", ["1.0", "0"])
def test_the_start_blends_into_the_clip_without_a_target_jump(tmp_path, meta, blend):
    """A clip that starts away from the default pose (the sway from t = 2.5 s: squatting, arms
    0.4 rad up): with the blend (the default) the targets reach its first frame over a second;
    without it they jump there on the start cycle (measured 0.399 rad at the shoulders)."""
    sway = sway_reference(SwaySpec(duration_s=8.0))
    midway = Reference.from_qpos(sway.qpos()[125:], sway.fps).save(tmp_path / "midway.npz")
    policy = feedback_policy(meta, tmp_path / "p.onnx")
    rc, out, log, stats = sim2sim(tmp_path, policy, midway, domain_id(5 if blend == "0" else 6),
                                  deploy_args=("--duration", "2", "--blend", blend), sim_s=60.0)
    assert rc == 0, out
    stages = [t[1:] for t in log.transitions()]
    q_step, _ = _start_steps(log)
    if blend == "0":
        assert ("HOLD", "TRACK", "auto_start") in stages and q_step > 0.3, (stages, q_step)
        return
    assert ("HOLD", "BLEND", "auto_start") in stages and ("BLEND", "TRACK", "blend_done") in stages
    times = {t[1:3]: t[0] for t in log.transitions()}
    assert 0.95 <= times[("BLEND", "TRACK")] - times[("HOLD", "BLEND")] <= 1.1
    assert q_step < 0.05, q_step  # the clip's own motion per 20 ms, no jump
    assert start_tilt_error_deg(log) < 10.0  # the bound on the first second of tracking
    assert stats["upright"], stats
    assert cli.main(["inspect", str(log.path)]) == 0


def test_a_box_actor_runs_over_dds_against_a_sim_robot_that_simulates_the_box(tmp_path, box_reference):
    """The reference player with OTR-G1-BoxTrack-v0's default (perception-free) observation layout:
    the runner builds the object command and contact schedule from the clip, the sim robot
    simulates the clip's box (on the floor) and table; the box stays where it is (the robot stands
    still), which the stats report against the reference's end (on the table)."""
    meta = training_metadata(box_reference, "OTR-G1-BoxTrack-v0")
    meta["joint_stiffness"], meta["joint_damping"] = STARTUP_KP.tolist(), STARTUP_KD.tolist()
    assert [t["name"] for t in meta["observation_layout"]][-2:] == ["object_command", "contact_schedule"]
    policy = save_with_metadata(reference_policy_model(meta), meta, tmp_path / "box.onnx")
    rc, out, log, stats = sim2sim(tmp_path, policy, box_reference, domain_id(7), sim_s=60.0,
                                  deploy_args=("--blend", "0.2", "--end-hold", "0.2"))
    assert rc == 0, out
    stages = [t[1:] for t in log.transitions()]
    assert ("TRACK", "END", "clip_end") in stages and stages[-1] == ("END", "DAMP", "clip_end")
    frames = log.arrays["frame"][log.arrays["stage"] == Stage.TRACK]
    assert frames.max() == 150  # the whole clip
    box = stats["objects"]["box"]
    np.testing.assert_allclose(box["start"][:3], [0.6, 0.0, 0.1], atol=1e-6)
    assert abs(box["end"][2] - 0.1) < 0.01 and box["end_error_m"] > 0.5  # on the floor, not on the table
    assert stats["upright"], stats


def test_a_mocap_box_actor_is_refused_without_a_stream_and_tracks_with_the_sim_robots(tmp_path, box_reference,
                                                                                       capsys):
    """OTR-G1-BoxTrack-v0's ``mocap`` actor (the robot's world position, the box's pose): refused
    without ``--mocap``, naming the terms and the flag; with the sim robot publishing a stream
    (10 ms late, 1 mm of noise) it tracks the whole clip, the log records the box as captured, a
    replay reproduces the actions (the observation depends on the captured poses) and
    ``otr inspect`` reports where the box ended."""
    meta = training_metadata(box_reference, "OTR-G1-BoxTrack-v0", {"observations": {"actor": "mocap"}})
    meta["joint_stiffness"], meta["joint_damping"] = STARTUP_KP.tolist(), STARTUP_KD.tolist()
    policy = feedback_policy(meta, tmp_path / "mocap_box.onnx", gain=0.02)
    rc, out = finish(otr("deploy", "--policy", str(policy), "--reference", str(box_reference), "--interface", "lo",
                         "--domain-id", str(domain_id(8))), 60)
    assert rc == 2 and "anchor_pos_b, base_lin_vel_b, object_pos_b" in out and "--mocap TOPIC" in out, out
    topic = "rt/test/mocap"
    rc, out, log, stats = sim2sim(
        tmp_path, policy, box_reference, domain_id(9), sim_s=60.0,
        sim_args=("--publish-mocap", topic, "--mocap-latency-ms", "10", "--mocap-noise-m", "0.001"),
        deploy_args=("--mocap", topic, "--blend", "0.2", "--end-hold", "0.2"))
    assert rc == 0, out
    a = log.arrays
    track = a["stage"] == Stage.TRACK
    assert a["frame"][track].max() == 150 and stats["upright"], stats  # the whole clip
    assert log.meta["mocap"]["bodies"] == ["pelvis", "box"] and a["mocap_fresh"][track].mean() > 0.9
    # the captured box is the simulated one: it stays on the floor where it started
    box = stats["objects"]["box"]
    last = np.flatnonzero(a["mocap_fresh"])[-1]
    np.testing.assert_allclose(a["mocap_pos"][last, 1], box["end"][:3], atol=0.01)
    assert abs(a["object_error_m"][last, 0] - box["end_error_m"]) < 0.02
    assert stats["mocap_published"] > 0
    replayed = cli.main(["deploy", "--replay", str(log.path)])
    assert replayed == 0, capsys.readouterr().out
    capsys.readouterr()
    assert cli.main(["inspect", str(log.path)]) == 0
    text = capsys.readouterr().out
    assert f"{topic}: " in text and "box" in text and "from the reference's last frame" in text


def test_the_state_estimation_actor_runs_on_the_estimator_without_motion_capture(tmp_path, sway):
    """The precise recipe's actor (``benchmarks/state_estimation.sets``: the reference torso's
    position in the robot's frame, the pelvis velocity) is refused without a source, naming both
    flags; with ``--state-estimator`` the estimator feeds it from the IMU and the legs. Against
    the simulator's truth (its 50 Hz trace, interpolated at the LowState's tick): the pelvis position
    within 2 cm, the velocity within 0.05 m/s RMS over 6 s of the sway (measured 2026-12-07:
    8 mm and 0.009 m/s, while the robot itself strays 5 cm from the clip)."""
    line = (REPO / "benchmarks" / "state_estimation.sets").read_text().strip()
    key, _, value = line.partition("=")
    assert key == "env.observations.policy"
    meta = training_metadata(sway, env={"observations": {"policy": json.loads(value)}})
    meta["joint_stiffness"], meta["joint_damping"] = STARTUP_KP.tolist(), STARTUP_KD.tolist()
    policy = feedback_policy(meta, tmp_path / "state_estimation.onnx", gain=0.02)
    rc, out = finish(otr("deploy", "--policy", str(policy), "--reference", str(sway), "--interface", "lo",
                         "--domain-id", str(domain_id(10))), 60)
    assert rc == 2 and "anchor_pos_b, base_lin_vel_b need" in out and "--mocap TOPIC" in out \
        and "or --state-estimator" in out, out
    trace_path = tmp_path / "trace.npz"
    rc, out, log, stats = sim2sim(tmp_path, policy, sway, domain_id(11), sim_s=40.0,
                                  sim_args=("--trace", str(trace_path)),
                                  deploy_args=("--state-estimator", "--duration", "6"))
    assert rc == 0 and stats["upright"], out
    a, trace = log.arrays, np.load(trace_path)
    track = np.flatnonzero(a["stage"] == Stage.TRACK)
    assert track.size >= 290 and np.isfinite(a["base_pos_w"][track]).all()
    sim_s = a["state_tick_ms"][track] / 1000.0  # the LowState's tick: the simulated time, ms
    assert trace["sim_s"][0] <= sim_s[0] and sim_s[-1] <= trace["sim_s"][-1]
    truth = np.stack([np.interp(sim_s, trace["sim_s"], trace["qpos"][:, k]) for k in range(3)], axis=-1)
    assert np.linalg.norm(a["base_pos_w"][track] - truth, axis=-1).max() < 0.02
    velocity = np.gradient(truth, sim_s, axis=0)
    assert np.sqrt(np.mean(np.sum((a["base_lin_vel_w"][track] - velocity) ** 2, axis=-1))) < 0.05
    assert cli.main(["deploy", "--replay", str(log.path)]) == 0
