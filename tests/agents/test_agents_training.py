"""Training, resuming, stopping, evaluation, export and play on the real vector env
(MuJoCo-Warp on the CPU, 16 envs, generated references). One short run is shared by the
module; every later test reads or extends it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch
from tensordict import TensorDict

from agents import runs
from agents.config import train_config_from_dict
from agents.evaluate import eval_env_overrides, run_episodes
from agents.export import check_parity, export_onnx, read_metadata, typical_observations
from agents.plots import read_scalars
from agents.policy import load_policy
from agents.procedural import WalkSpec, standing_reference, walking_reference
from agents.runner import TrackingRunner
from agents.vecenv import RslRlVecEnv, make_vec_env
from otr_gym import cli, robot

NUM_ENVS = 16
UPDATES_PER_ITERATION = 5 * 4  # docs/environment.md §7: 5 epochs x 4 minibatches, one Adam step each
SAMPLES_PER_ITERATION = NUM_ENVS * 24


@pytest.fixture(scope="module", autouse=True)
def single_torch_thread():
    """One intra-op thread for this module: on a small shared CPU, OpenMP threads waiting for
    each other make PPO's small minibatch updates ~10x slower (measured: 0.16 s vs 2-9 s)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="module")
def walk_ref(tmp_path_factory) -> Path:
    return walking_reference(WalkSpec(steps=4)).save(tmp_path_factory.mktemp("refs") / "walk.npz")


@pytest.fixture(scope="module")
def run_dir(walk_ref, tmp_path_factory) -> Path:
    """One PPO iteration (checkpoint model_0)."""
    log_dir = tmp_path_factory.mktemp("runs")
    rc = cli.main(["train", "--reference", str(walk_ref), "--num-envs", str(NUM_ENVS), "--device", "cpu",
                   "--iterations", "1", "--save-interval", "1", "--log-dir", str(log_dir)])
    assert rc == 0
    (run,) = log_dir.iterdir()
    return run


@pytest.fixture(scope="module")
def resumed_run(run_dir) -> Path:
    """The same run continued under a budget far below one iteration: exactly one more, with
    TF32 matmuls switched on by ``--set`` (a CUDA flag; it changes nothing on the CPU)."""
    previous = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = False
    try:
        rc = cli.main(["train", "--resume", str(run_dir), "--iterations", "50", "--max-minutes", "0.001",
                       "--set", "tf32_matmul=true"])
        assert torch.backends.cuda.matmul.allow_tf32, "tf32_matmul=true did not reach torch"
    finally:
        torch.backends.cuda.matmul.allow_tf32 = previous
    assert rc == 0
    return run_dir


def _load(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


def _adam_steps(ckpt: dict) -> set[int]:
    return {int(s["step"]) for s in ckpt["optimizer_state_dict"]["state"].values()}


def test_training_writes_a_run_folder_with_config_checkpoints_and_curves(run_dir, walk_ref):
    assert run_dir.name.startswith("OTR-G1-Track-v0_walk_")
    record = runs.run_config(run_dir)
    assert record["reference"] == str(walk_ref.resolve()) and record["device"] == "cpu"
    assert train_config_from_dict(record["train"]).num_steps_per_env == 24
    spec = runs.read_env_spec(run_dir)
    assert spec["observation_dims"] == {"policy": 154, "critic": 286} and spec["num_actions"] == 29
    assert [c.iteration for c in runs.checkpoints(run_dir)][0] == 0
    ckpt = _load(run_dir / "model_0.pt")
    assert ckpt["iter"] == 0
    assert _adam_steps(ckpt) == {UPDATES_PER_ITERATION}
    scalars = read_scalars(run_dir)
    for tag in ("Train/mean_episode_length", "Perf/total_fps", "metric/mpjpe_mm", "reward/body_pos",
                "reward/action_rate", "termination/anchor_height", "Loss/learning_rate"):
        assert scalars[tag][0][0] == 0, tag
    # an untrained policy started on the reference drifts off it by centimetres, not by metres
    # (measured 80-100 mm over the first iterations); 0 would mean the error is not measured
    assert all(20.0 < v < 300.0 for v in scalars["metric/mpjpe_mm"][1])
    # 384 samples per iteration on this CPU: a few hundred env steps/s (measured 420-580)
    assert all(20.0 < v < 20_000.0 for v in scalars["Perf/total_fps"][1])


def test_resume_continues_counter_optimizer_normalizer_and_curves(resumed_run):
    assert [c.iteration for c in runs.checkpoints(resumed_run)] == [0, 1]
    before, after = _load(resumed_run / "model_0.pt"), _load(resumed_run / "model_1.pt")
    assert after["iter"] == 1
    # Adam and the empirical normalisers kept counting across the restart
    assert _adam_steps(after) == {2 * UPDATES_PER_ITERATION}
    norm = "obs_normalizer.count"
    assert int(before["actor_state_dict"][norm]) == SAMPLES_PER_ITERATION
    assert int(after["actor_state_dict"][norm]) == 2 * SAMPLES_PER_ITERATION
    assert int(after["critic_state_dict"][norm]) == 2 * SAMPLES_PER_ITERATION
    logger_before = before["infos"]["training_state"]["logger"]["tot_timesteps"]
    assert after["infos"]["training_state"]["logger"]["tot_timesteps"] == logger_before + SAMPLES_PER_ITERATION
    # one curve, no repeated iteration
    assert read_scalars(resumed_run)["Perf/total_fps"][0] == [0, 1]
    record = runs.run_config(resumed_run)
    assert len(record["sessions"]) == 2
    # the override is recorded with the run, so the next resume keeps it
    assert record["train"]["tf32_matmul"] is True and record["train"]["torch_compile_mode"] is None


def test_loading_a_checkpoint_restores_the_exact_training_state(resumed_run, walk_ref):
    saved = _load(resumed_run / "model_1.pt")
    cfg = train_config_from_dict(runs.run_config(resumed_run)["train"])
    env = make_vec_env(cfg.task, walk_ref, NUM_ENVS, "cpu", cfg.env, seed=cfg.seed)
    vec = RslRlVecEnv(env, cfg.num_steps_per_env, seed=cfg.seed)
    runner = TrackingRunner(vec, cfg.to_rsl_rl(), log_dir=None, device="cpu")
    fresh = runner.alg.save()
    assert not torch.equal(fresh["actor_state_dict"]["mlp.0.weight"], saved["actor_state_dict"]["mlp.0.weight"])

    runner.load(str(resumed_run / "model_1.pt"))
    assert runner.current_learning_iteration == 2  # the next iteration to run
    state = runner.alg.save()
    for key in ("actor_state_dict", "critic_state_dict"):
        assert state[key].keys() == saved[key].keys()
        for name, tensor in saved[key].items():
            assert torch.equal(state[key][name], tensor), f"{key}.{name}"
    for pid, moments in saved["optimizer_state_dict"]["state"].items():
        for name, tensor in moments.items():
            assert torch.equal(state["optimizer_state_dict"]["state"][pid][name], tensor)
    assert runner.alg.learning_rate == saved["optimizer_state_dict"]["param_groups"][0]["lr"]
    assert torch.equal(vec.vec.command.failure_rate, saved["infos"]["training_state"]["env"]["failure_rate"])
    assert runner.logger.tot_timesteps == saved["infos"]["training_state"]["logger"]["tot_timesteps"]
    env.close()


def test_ctrl_c_stops_between_iterations_with_a_resumable_checkpoint(walk_ref, tmp_path):
    cmd = [sys.executable, "-m", "otr_gym.cli", "train", "--reference", str(walk_ref), "--num-envs", str(NUM_ENVS),
           "--device", "cpu", "--iterations", "100", "--save-interval", "1000", "--log-dir", str(tmp_path)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"})
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if "Learning iteration 0/" in line:
            proc.send_signal(signal.SIGINT)
            break
    lines += proc.stdout.readlines()
    rc = proc.wait(timeout=300)
    out = "".join(lines)
    assert rc == 130, out[-3000:]
    assert "training stopped: interrupted (SIGINT)" in out
    (run,) = tmp_path.iterdir()
    latest = runs.resolve_checkpoint(run)
    assert _load(latest.path)["iter"] == latest.iteration
    completed = int(out.split("interrupted (SIGINT) after ")[1].split()[0])
    assert latest.iteration == completed - 1
    assert load_policy(run).checkpoint == latest


def test_onnx_export_matches_torch_within_1e_5_and_carries_the_robot_spec(resumed_run, tmp_path):
    path = export_onnx(resumed_run, tmp_path / "policy.onnx")
    policy = load_policy(resumed_run)
    module = policy.actor.as_onnx(verbose=False).eval()
    assert check_parity(path, module, 154, batch=256, seed=7) <= 1e-5
    # the normaliser is inside the graph: raw observations in, the actor's mean action out
    obs = typical_observations(module, 154, batch=5, seed=1)
    got = ort.InferenceSession(str(path)).run(["actions"], {"obs": obs})[0]
    want = policy.act(TensorDict({"policy": torch.from_numpy(obs)}, batch_size=[5])).numpy()
    np.testing.assert_allclose(got, want, atol=1e-5, rtol=0)
    meta = read_metadata(path)
    assert meta["joint_names"] == list(robot.JOINT_NAMES)
    np.testing.assert_allclose(meta["joint_stiffness"], robot.KP)
    np.testing.assert_allclose(meta["joint_damping"], robot.KD)
    np.testing.assert_allclose(meta["action_scale"], robot.ACTION_SCALE)
    np.testing.assert_allclose(meta["default_joint_pos"], robot.DEFAULT_JOINT_POS)
    assert [t["name"] for t in meta["observation_layout"]] == [
        "command", "anchor_ori_b", "base_ang_vel_b", "joint_pos_rel", "joint_vel", "last_action"]
    assert sum(t["dim"] for t in meta["observation_layout"]) == meta["observation_dim"] == 154
    assert meta["observation_clip"] == 100.0 and meta["fps"] == 50.0
    assert meta["reference"]["name"] == "walk"
    assert meta["checkpoint"]["iteration"] == 1 and meta["checkpoint"]["run"] == resumed_run.name


def test_evaluating_a_run_scores_every_checkpoint_and_plots(resumed_run, walk_ref, tmp_path):
    rc = cli.main(["evaluate", str(resumed_run), "--reference", str(walk_ref), "--device", "cpu",
                   "--json", str(tmp_path / "eval.json"), "--plot", str(tmp_path / "eval.png")])
    assert rc == 0
    results = json.loads((tmp_path / "eval.json").read_text())
    assert [c["iteration"] for c in results["checkpoints"]] == [0, 1]
    final = results["final"]
    assert final["envs"] == 1 and final["clips"][0]["clip"] == "walk"
    assert 0 < final["frames"] <= 150  # the 151-frame clip has 150 steps
    assert 5.0 < final["mpjpe_mm"] < 300.0  # deterministic, two iterations in: centimetres off the clip
    assert (tmp_path / "eval.png").stat().st_size > 10_000


class ReplayReference:
    """The hand-made policy: PD targets = the reference joints of the target frame, read from
    the observation's command term, i.e. a = (q_ref − q_default) / scale."""

    def __init__(self):
        self.default = torch.as_tensor(robot.DEFAULT_JOINT_POS, dtype=torch.float32)
        self.scale = torch.as_tensor(robot.ACTION_SCALE, dtype=torch.float32)

    def act(self, obs: TensorDict) -> torch.Tensor:
        return (obs["policy"][:, :29] - self.default) / self.scale


def test_replaying_reference_joint_targets_on_a_standing_clip_succeeds_within_30mm(tmp_path):
    """Bound: the robot starts exactly on the reference and the PD targets equal it, so the
    error is only the PD's static sag under gravity, Δq ≈ τ/kp. The knees carry about half the
    weight at a few centimetres of lever arm: τ ≈ 15 N·m at kp ≈ 99 N·m/rad, i.e. ≈ 0.15 rad,
    which lowers the pelvis ≈ 2.5 cm over the ≈ 0.3 m shank and moves the legs and the upper
    body relative to the pelvis by up to a few centimetres; averaged over the 14 bodies and the
    25 steps of a 0.5 s clip (the sag builds up over ≈ 0.2 s) that is ≈ 15-20 mm (18.6 mm
    measured), so 30 mm bounds it with margin. The clip is short because open-loop PD cannot
    balance: the robot tips over after ≈ 1.2 s."""
    ref = standing_reference(duration_s=0.5).save(tmp_path / "stand.npz")
    env = make_vec_env("OTR-G1-Track-v0", ref, 2, "cpu", eval_env_overrides({}, randomize=False), evaluation=True)
    result = run_episodes(env.unwrapped, ReplayReference())
    # --action-noise: Gaussian noise on the same actions, reproducible from the seed; the
    # replay's error can only grow with it (0.5 action units ≈ 0.1-0.2 rad of PD target noise)
    quiet = run_episodes(env.unwrapped, ReplayReference(), action_noise=0.0)
    noisy = [run_episodes(env.unwrapped, ReplayReference(), seed=3, action_noise=0.5) for _ in range(2)]
    env.close()
    assert result["success_rate"] == 1.0
    assert result["frames"] == 2 * 25
    assert 1.0 < result["mpjpe_mm"] < 30.0
    assert quiet["mpjpe_mm"] == result["mpjpe_mm"]
    assert noisy[0]["mpjpe_mm"] == noisy[1]["mpjpe_mm"] > result["mpjpe_mm"] + 1.0


def test_play_renders_an_mp4_of_the_policy(resumed_run, walk_ref, tmp_path):
    import imageio.v2 as imageio

    from agents.play import play

    out = play(resumed_run, tmp_path / "play.mp4", walk_ref, seconds=0.2, width=160, height=128)
    assert out["frames"] == 11 and out["fps"] == 50
    with imageio.get_reader(str(tmp_path / "play.mp4"), format="FFMPEG") as reader:
        frames = list(reader.iter_data())  # list(reader) asks len() = inf of an mp4 stream
    assert len(frames) == 11 and frames[0].shape == (128, 160, 3)
    assert frames[0].std() > 10  # a rendered scene, not a blank frame


@pytest.mark.parametrize("argv, message", [
    (["train", "--reference", "missing_walk.npz", "--device", "cpu"], "missing_walk.npz"),
    (["train", "--resume", "no_such_run", "--device", "cpu"], "no_such_run"),
    (["train", "--device", "cpu"], "--reference is required"),
    (["evaluate", "no_such_run", "--reference", "x.npz"], "no_such_run"),
    (["evaluate", "no_such_run", "--action-noise", "-0.1"], "--action-noise must be a finite std >= 0, got -0.1"),
    (["evaluate", "no_such_run", "--action-noise", "nan"], "--action-noise must be a finite std >= 0, got nan"),
    (["export", "no_such_run", "--onnx", "p.onnx"], "no_such_run"),
    (["play", "no_such_run", "--video", "v.mp4"], "no_such_run"),
])
def test_bad_inputs_exit_2_naming_the_problem(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.main(argv) == 2
    assert message in capsys.readouterr().err


def test_cuda_requested_without_cuda_exits_2(walk_ref, capsys, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert cli.main(["train", "--reference", str(walk_ref), "--device", "cuda"]) == 2
    assert "CUDA is not available" in capsys.readouterr().err


def test_corrupt_checkpoint_is_named(resumed_run, tmp_path, capsys):
    run = tmp_path / "copy"
    run.mkdir()
    for name in (runs.CONFIG_FILE, runs.ENV_SPEC_FILE):
        (run / name).write_bytes((resumed_run / name).read_bytes())
    (run / "model_5.pt").write_bytes((resumed_run / "model_1.pt").read_bytes()[:1000])
    assert cli.main(["export", str(run), "--onnx", str(tmp_path / "p.onnx")]) == 2
    assert "model_5.pt" in capsys.readouterr().err
    assert not (tmp_path / "p.onnx").exists()


def test_invalid_reference_is_named_by_evaluate(resumed_run, tmp_path, capsys):
    bad = tmp_path / "not_a_reference.npz"
    np.savez(bad, fps=np.array([50]))
    assert cli.main(["evaluate", str(resumed_run / "model_1.pt"), "--reference", str(bad), "--device", "cpu"]) == 2
    assert "not_a_reference.npz" in capsys.readouterr().err
