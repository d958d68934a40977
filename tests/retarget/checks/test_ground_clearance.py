"""Arms re-solved out of the ground (retarget.checks.ground_clearance): a standing G1 lowered until its
hanging hands are 4 cm in the floor, and Holosoma's crawl on its slope (shared data)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from otr_gym import cli, robot
from otr_gym.reference import Reference
from retarget.checks.feasibility import check_feasibility
from retarget.checks.ground import Ground
from retarget.checks.ground_clearance import ARM_BODIES, ARM_JOINTS, ClearanceCfg, clear_ground

from conftest import SHARED_DATA, load_benchmark, lowest_collision_reach

FPS = 50.0
CRAWL = SHARED_DATA / "references" / "holosoma" / "motion_crawl_slope.npz"
SLOPE = SHARED_DATA / "references" / "holosoma" / "terrain_slope.obj"


@pytest.fixture(scope="module")
def sunk_hands():
    """10 frames: the default pose, lowered 0.62 m on frames 3-6 (the hanging hands' lowest
    reach, 0.577 m up when standing, then 4.3 cm in the floor; the wrists' own capsules above it)."""
    qpos = np.tile(robot.default_qpos(), (10, 1))
    qpos[3:7, 2] -= 0.62
    reference = Reference.from_qpos(qpos, FPS)
    return reference, *clear_ground(reference)


def test_sunk_hands_are_lifted_to_the_clearance_by_the_arm_joints_alone(sunk_hands):
    reference, cleared, report = sunk_hands
    before, after = ([lowest_collision_reach(q, ARM_BODIES)[0] for q in r.qpos()] for r in (reference, cleared))
    before, after = np.array(before), np.array(after)
    assert before[3:7] == pytest.approx(-0.043, abs=2e-3)
    assert after.min() >= ClearanceCfg.clearance_m - 2e-4  # checked by MuJoCo, not the solver's own model
    np.testing.assert_allclose(report.depth_before_m[3:7], 0.043 + ClearanceCfg.clearance_m, atol=2e-3)
    assert report.depth_after_m.max() <= 2e-4 and report.qp_failures == 0
    # only the arm joints of the sunk frames moved; the clear frames are the input's exactly
    arm = np.isin(robot.JOINT_NAMES, ARM_JOINTS)
    q0, q1 = reference.qpos(), cleared.qpos()
    assert np.array_equal(q0[:, :7], q1[:, :7]) and np.array_equal(q0[:, 7:][:, ~arm], q1[:, 7:][:, ~arm])
    assert np.array_equal(np.delete(q0, np.s_[3:7], axis=0), np.delete(q1, np.s_[3:7], axis=0))
    assert report.frames_changed == 4 and np.all(report.joint_change_rad[3:7] > 0.05)
    # the cheapest joints do the work: every moved frame turns a wrist more than any shoulder
    change = np.abs(q1 - q0)[3:7, 7:]
    wrist = [robot.JOINT_NAMES.index(j) for j in ARM_JOINTS if "_wrist_" in j]
    shoulder = [robot.JOINT_NAMES.index(j) for j in ARM_JOINTS if "_shoulder_" in j]
    assert np.all(change[:, wrist].max(1) > change[:, shoulder].max(1))
    assert cleared.metadata["ground_clearance"]["frames_changed"] == 4


def test_the_surface_benchmark_sees_the_visual_hands_leave_the_floor(sunk_hands, tmp_path, capsys):
    """benchmarks/surface_on_ground.py on the same clip before and after: the visual meshes'
    hands (not the collision boxes the solve used) go from centimetres in the floor to out of it,
    and every other number is per frame of the same clip."""
    bench = load_benchmark("surface_on_ground")
    reference, cleared, _ = sunk_hands
    paths = [reference.save(tmp_path / "before" / "sunk.npz"), cleared.save(tmp_path / "after" / "sunk.npz")]
    assert bench.main([str(p) for p in paths] + ["--json", str(tmp_path / "s.json")]) == 0
    before, after = json.loads((tmp_path / "s.json").read_text())["rows"]
    assert before["hands_m"] > 0.03 and before["hand_frames_over_1cm"] == 4
    assert after["hands_m"] < 0.002 and after["hand_frames_over_1cm"] == 0
    assert before["frames"] == after["frames"] == 10
    out = capsys.readouterr().out
    assert "| before/sunk.npz | 10 |" in out and "| after/sunk.npz | 10 |" in out
    assert bench.main([str(tmp_path / "none.npz")]) == 2 and "none.npz" in capsys.readouterr().err


def test_a_joint_already_beyond_its_limit_is_not_pushed_farther():
    """The left wrist pitch 0.5 rad past its upper limit on the sunk frames: the solve still
    lifts the hands, and that joint ends no farther out than it began."""
    qpos = np.tile(robot.default_qpos(), (6, 1))
    qpos[2:4, 2] -= 0.62
    j = robot.JOINT_NAMES.index("left_wrist_pitch_joint")
    qpos[2:4, 7 + j] = robot.JOINT_UPPER[j] + 0.5  # farther out than one trust-region step (0.4)
    reference = Reference.from_qpos(qpos, FPS)
    cleared, report = clear_ground(reference)
    assert report.depth_before_m[2:4].min() > 0.02 and report.depth_after_m.max() <= 2e-4 and report.qp_failures == 0
    assert np.all(cleared.qpos()[2:4, 7 + j] <= reference.qpos()[2:4, 7 + j] + 1e-6)  # ProxQP eps 1e-7 per step


def test_the_command_names_a_missing_file_and_refuses_a_negative_clearance(tmp_path, capsys):
    assert cli.main(["clear-ground", str(tmp_path / "none.npz"), str(tmp_path / "out.npz")]) == 2
    assert "none.npz" in capsys.readouterr().err
    assert cli.main(["clear-ground", str(tmp_path / "none.npz"), str(tmp_path / "out.npz"), "--clearance-m", "-1"]) == 2
    assert "--clearance-m must be >= 0" in capsys.readouterr().err
    assert not (tmp_path / "out.npz").exists()


@pytest.mark.skipif(not CRAWL.exists(), reason=f"shared data absent: {CRAWL}")
def test_holosomas_crawl_keeps_its_hands_on_its_slope(tmp_path, capsys):
    """Holosoma's crawl puts the G1's hands up to 9 cm into its ramp and platform; cleared, none
    is more than 3 mm in (verify's measure) and no hand jumps between frames."""
    ground = Ground.from_mesh(SLOPE)
    original = check_feasibility(Reference.load(CRAWL), ground=ground)
    assert original.penetration_m.max() > 0.08 and original.summary()["penetration"]["frames_over"] > 100
    out = tmp_path / "crawl.npz"
    assert cli.main(["clear-ground", str(CRAWL), str(out), "--terrain", str(SLOPE)]) == 0
    assert "arm joints changed on" in capsys.readouterr().out
    cleared = check_feasibility(Reference.load(out), ground=ground)
    arm = np.isin(np.asarray(cleared.penetration_link), ARM_BODIES)
    assert cleared.penetration_m[arm].max(initial=0.0) < 0.003
    assert cleared.limb_jump_m[:, 2:].max() < 0.03  # the hands: no snap from the per-frame solves
