"""benchmarks/box_sim2sim.py on a tiny case: the open-loop reference player with the box task's
``mocap`` actor on the generated box clip (the robot stands, the box stays on the floor), one
run over loopback DDS. The table's fields must come from the two processes' files (the sim
robot's stats and trace, the runner's log), not be carried boxes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from agents.deploy.log import DeployLog, log_timing, start_tilt_error_deg
from agents.deploy.reference_policy import write_reference_policy
from agents.deploy.safety import Stage
from tests.deploy_support import domain_id

from conftest import load_benchmark

pytestmark = pytest.mark.timeout(180)
SHORT = ["--deploy-arg=--ramp=0.5", "--deploy-arg=--blend=0.2", "--deploy-arg=--end-hold=0.2"]


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("box_sim2sim")


@pytest.fixture(scope="module")
def batch(bench, box_reference, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("box_sim2sim")
    policy = write_reference_policy(tmp / "box_mocap.onnx", box_reference, "OTR-G1-BoxTrack-v0",
                                    {"observations": {"actor": "mocap"}})
    out = tmp / "runs"
    args = ["--policy", str(policy), "--reference", str(box_reference), "--runs", "1", "--seed", "5",
            "--out", str(out), "--domain-id", str(domain_id(11)), *SHORT]
    assert bench.main(args) == 0
    return bench, args, out, policy


def test_a_run_draws_the_box_and_its_row_comes_from_the_logs(batch, box_reference):
    bench, _, out, _ = batch
    run = out / "run_00"
    done = json.loads((run / "done.json").read_text())
    assert done["draw_seed"] == 5 and done["mocap"] and done["deploy_rc"] == 0  # the actor needs motion capture
    stats = json.loads((run / "sim.json").read_text())
    log = DeployLog.load(run / "run.npz")
    trace = np.load(run / "trace.npz")
    (row,) = json.loads((out / "results.json").read_text())["runs"]
    assert row == bench.run_metrics(run, box_reference)
    # the sim robot drew the box as the training env would with seed 5, and the row reports that
    from agents.deploy.sim_robot import object_properties, sim_objects

    drawn = object_properties(sim_objects(str(box_reference))[0], draw_seed=5)["box"]
    box = stats["objects"]["box"]
    assert (row["mass_kg"], row["friction"]) == (box["mass_kg"], box["friction"]) == (drawn.mass_kg, drawn.friction)
    assert stats["object_draw"]["seed"] == 5 and box["properties"] == "drawn"
    # the clip's end: the simulated time of the LowState the runner went TRACK -> END on
    ((cycle, _),) = [(c, r) for c, f, t, r in zip(log.arrays["transition_cycle"], log.arrays["transition_from"],
                                                  log.arrays["transition_to"], log.arrays["transition_reason"])
                     if f == Stage.TRACK and t == Stage.END]
    assert row["ended"] == "clip_end" and row["end_sim_s"] == log.arrays["state_tick_ms"][cycle] / 1000.0
    assert abs(row["end_trace_sim_s"] - row["end_sim_s"]) <= 0.011  # the 50 Hz trace's nearest sample
    i = int(np.argmin(np.abs(trace["sim_s"] - row["end_sim_s"])))
    np.testing.assert_array_equal(row["end_pose"], trace["object_pose"][i, 0])
    assert row["end_error_m"] == pytest.approx(np.linalg.norm(np.subtract(row["end_pose"][:3], box["goal"][:3])))
    # the runner's captured box at that cycle is the simulated one (the stream is the sim's, 0 ms late)
    seen = np.flatnonzero(log.arrays["mocap_fresh"][: cycle + 1])[-1]
    np.testing.assert_allclose(log.arrays["mocap_pos"][seen, 1], row["end_pose"][:3], atol=0.01)
    assert abs(log.arrays["object_error_m"][seen, 0] - row["end_error_m"]) < 0.02
    # the robot stood: the box stayed on the floor, not lifted, not carried, not on the table
    assert not row["lifted"] and row["max_rise_m"] == pytest.approx(max(trace["object_pose"][:i + 1, 0, 2]) - 0.1)
    assert row["carried"] is False and row["end_error_m"] > 0.5 and not row["within"]
    assert box["end_contacts"] == ["ground"] and row["on_table"] is False and not row["passed"]
    assert row["start_tilt_deg"] == start_tilt_error_deg(log) < 10.0 and row["tilt_ok"]
    track = log.arrays["stage"] == Stage.TRACK
    assert row["mpjpe_mm"] == pytest.approx(np.nanmean(log.arrays["mpjpe_m"][track]) * 1e3)
    assert row["missed_deadlines"] == log_timing(log)["missed_deadlines"] and row["load_1min"] == done["load_1min"]


def test_the_batch_resumes_skipping_finished_runs_and_refuses_another_configuration(batch, capsys):
    bench, args, out, _ = batch
    files = {p: p.stat().st_mtime_ns for p in (out / "run_00").iterdir()}
    capsys.readouterr()
    assert bench.main(args) == 0  # the one run is finished: nothing runs again
    assert {p: p.stat().st_mtime_ns for p in (out / "run_00").iterdir()} == files
    text = capsys.readouterr().out
    assert "| run_00 | 5 |" in text and "**0 / 1 runs pass**" in text and "on table" in text
    assert "| clip_end | " in text
    assert (out / "table.md").read_text().endswith(text.split("\n\n", 1)[1])
    other = [a if a != "5" else "6" for a in args]
    assert bench.main(other) == 2
    assert "seed differ" in capsys.readouterr().err


def test_a_policy_trained_with_another_box_is_refused_naming_the_difference(batch, box_reference, capsys):
    bench, args, _, policy = batch
    assert bench.box_mismatch(policy, box_reference) == []
    assert bench.box_mismatch(policy, box_reference, ["objects.mass_kg=2"]) == \
        ["box: nominal mass 2 kg, trained with 1"]
    capsys.readouterr()
    assert bench.main([*args, "--env-set", "objects.mass_kg=2"]) == 2
    assert "box: nominal mass 2 kg, trained with 1" in capsys.readouterr().err
