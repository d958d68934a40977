"""The multi-GPU code path run as two CPU processes (torch.distributed with gloo, MuJoCo-Warp on
warp's CPU device, 8 envs per rank): what a 2-GPU ``torchrun`` run does, checked on values.

One run (module fixture) under a time budget that stops it after its first iteration; each rank
dumps its final state through tests/distributed_worker.py."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from agents import distributed, runs
from agents.plots import read_scalars
from otr_gym import cli

from conftest import REPO_ROOT

NUM_ENVS = 8
ROOT = REPO_ROOT


@pytest.fixture(scope="module")
def two_rank_run(tmp_path_factory, walking_reference, standing_reference):
    out = tmp_path_factory.mktemp("ranks")
    log_dir = tmp_path_factory.mktemp("runs")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node=2",
           str(ROOT / "tests" / "distributed_worker.py"), str(out),
           "train", "--reference", str(walking_reference), str(standing_reference), "--num-envs", str(NUM_ENVS),
           "--device", "cpu", "--iterations", "5", "--max-minutes", "0.0001", "--log-dir", str(log_dir)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600, check=False)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    (run,) = log_dir.iterdir()
    ranks = [torch.load(out / f"rank{r}.pt", weights_only=False) for r in (0, 1)]
    return run, ranks, proc.stdout + proc.stderr


def test_gradients_are_averaged_over_the_ranks_at_every_minibatch(two_rank_run):
    _, ranks, _ = two_rank_run
    for state in ranks:
        records = state["records"]
        assert len(records) == 5 * 4  # one iteration: 5 epochs x 4 minibatches
        for r in records:
            # the ranks saw different data (seed + rank), so their gradients differ ...
            assert r["rank_spread"] > 1e-3 * r["scale"]
            # ... and what rsl-rl applies is their mean (all-reduce sum / world size)
            assert r["deviation"] <= 1e-6 * r["scale"]


def test_every_rank_ends_with_the_same_parameters_and_pooled_normalisers(two_rank_run):
    run, (a, b), _ = two_rank_run
    assert a["world_size"] == b["world_size"] == 2
    for key in ("actor", "critic"):
        assert a[key].keys() == b[key].keys()
        for name, tensor in a[key].items():
            assert torch.equal(tensor, b[key][name]), f"{key}.{name}"
    # normalisers pool both ranks' samples: 2 ranks x 8 envs x 24 steps
    assert int(a["actor"]["obs_normalizer.count"]) == 2 * NUM_ENVS * 24
    # the adaptive sampler's statistics are merged, so both ranks sample starts alike
    assert torch.equal(a["env"]["failure_rate"], b["env"]["failure_rate"])
    # rank 0's checkpoint holds exactly these parameters
    ckpt = torch.load(run / "model_0.pt", map_location="cpu", weights_only=False)
    for name, tensor in a["actor"].items():
        assert torch.equal(ckpt["actor_state_dict"][name], tensor)


def test_the_budget_stops_both_ranks_together_and_rank_0_alone_writes_the_run(two_rank_run):
    run, (a, b), log = two_rank_run
    assert a["iteration"] == b["iteration"] == 0
    assert log.count("training stopped: wall-clock budget reached after 1 iteration(s)") == 1  # rank 0 reports
    assert [c.iteration for c in runs.checkpoints(run)] == [0]
    assert len(list(run.glob("events.out.tfevents.*"))) == 1
    record = runs.run_config(run)
    assert record["world_size"] == 2 and record["device"] == "cpu"
    scalars = read_scalars(run)
    # the logger counts both ranks' samples
    assert scalars["Perf/total_fps"][0] == [0]
    assert "clip/walk/mpjpe_mm" in scalars and "clip/stand/mpjpe_mm" in scalars


def test_a_two_rank_checkpoint_resumes_in_one_process(two_rank_run):
    run, _, _ = two_rank_run
    torch.set_num_threads(1)
    assert cli.main(["train", "--resume", str(run), "--iterations", "1", "--device", "cpu"]) == 0
    ckpt = torch.load(run / "model_1.pt", map_location="cpu", weights_only=False)
    assert ckpt["iter"] == 1
    # one more iteration of one process's 8 envs on top of the pooled statistics
    assert int(ckpt["actor_state_dict"]["obs_normalizer.count"]) == 2 * NUM_ENVS * 24 + NUM_ENVS * 24
    assert runs.run_config(run)["sessions"][-1]["world_size"] == 1


def test_gpus_option_relaunches_itself_through_torchrun():
    argv = ["train", "--reference", "a.npz", "--gpus", "2", "--num-envs", "4096"]
    cmd = distributed.torchrun_command(2, argv)
    assert cmd[1:6] == ["-m", "torch.distributed.run", "--standalone", "--nproc-per-node=2", "-m"]
    assert cmd[6:] == ["otr_gym.cli", "train", "--reference", "a.npz", "--num-envs", "4096"]
    assert distributed.torchrun_command(4, ["train", "--gpus=4", "--device", "cuda"])[-3:] == ["train", "--device",
                                                                                            "cuda"]
