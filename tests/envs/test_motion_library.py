"""Motion libraries: one policy trained on several clips (``otr train --reference A B DIR LIST``).

Generated clips only: a standing clip, a procedural walk at 30 fps (resampled at load), a
clip whose reference floats 0.6 m above the floor (the robot falls: terminations at known
times), and a file that is not a reference."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch

from agents import runs
from agents.failure_bins import clip_failures
from agents.library import clip_labels, load_library
from agents.metrics import ClipRolloutStats
from agents.plots import plot_clip_curves, read_scalars
from agents.procedural import WalkSpec, standing_reference, walking_reference
from envs.config import CommandCfg, load_env_config
from envs.mdp.commands import MotionCommand
from envs.mdp.motion import MotionLibrary
from otr_gym import cli, robot
from otr_gym.reference import InvalidReferenceError, Reference

TRACK = "OTR-G1-Track-v0"
BOX = "OTR-G1-BoxTrack-v0"


@pytest.fixture(scope="module", autouse=True)
def single_torch_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def _hover(seconds: float = 1.5) -> Reference:
    qpos = np.tile(robot.default_qpos(), (int(seconds * 50) + 1, 1))
    qpos[:, 2] += 0.6
    return Reference.from_qpos(qpos, 50.0)


@pytest.fixture(scope="module")
def library_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("library")
    standing_reference(duration_s=2.0).save(d / "stand.npz")
    _hover(3.0).save(d / "hover.npz")
    (d / "broken.npz").write_bytes(b"not a reference")
    return d


@pytest.fixture(scope="module")
def library_run(library_dir, tmp_path_factory):
    """Two iterations on the folder (two good clips, one broken), random initial episode
    lengths off so that only clip ends and terminations end segments."""
    log_dir = tmp_path_factory.mktemp("runs")
    rc = cli.main(["train", "--reference", str(library_dir), "--num-envs", "16", "--device", "cpu",
                   "--iterations", "2", "--log-dir", str(log_dir), "--set", "init_at_random_ep_len=false"])
    assert rc == 0
    (run,) = log_dir.iterdir()
    return run


def test_a_two_clip_library_trains_with_per_clip_metrics(library_run, library_dir):
    info = runs.run_config(library_run)["reference_info"]
    assert info["labels"] == ["hover", "stand"]
    # the broken file is reported by name, with why, and left out
    assert [s["clip"] for s in info["skipped"]] == [str(library_dir / "broken.npz")]
    assert "not a NumPy .npz archive" in info["skipped"][0]["error"]
    scalars = read_scalars(library_run)
    for clip in ("hover", "stand"):
        for name in ("mpjpe_mm", "success_rate", "episode_length_s", "start_probability"):
            assert scalars[f"clip/{clip}/{name}"][0] == [0, 1], (clip, name)
    for it in (0, 1):
        total = scalars["clip/hover/start_probability"][1][it] + scalars["clip/stand/start_probability"][1][it]
        assert total == pytest.approx(1.0, abs=1e-6)
    # the floating reference: the robot falls 0.25 m below its anchor within ~0.25 s, so a
    # segment there succeeds only when it starts in the clip's last 0.25 s (the exact figures
    # are checked in test_clip_statistics_of_a_rollout_are_exact)
    hover, stand = (scalars[f"clip/{c}/episode_length_s"][1] for c in ("hover", "stand"))
    assert max(hover) < 0.4 and min(stand) > max(hover)
    assert sum(scalars["clip/hover/success_rate"][1]) < sum(scalars["clip/stand/success_rate"][1])
    # falls are failures: the sampler moved probability towards the floating clip
    assert scalars["clip/hover/start_probability"][1][1] > 0.5


def test_evaluation_reports_every_clip_and_the_overall_figures(library_run, tmp_path, capsys):
    out = tmp_path / "eval.json"
    assert cli.main(["evaluate", str(library_run), "--device", "cpu", "--last", "--json", str(out)]) == 0
    printed = capsys.readouterr()
    table = printed.out[printed.out.index("MPJPE (mm)  envs"):]
    assert "hover" in table and "stand" in table
    assert "broken.npz" in printed.err  # skipped again, by name
    final = json.loads(out.read_text())["final"]
    clips = {c["clip"]: c for c in final["clips"]}
    assert set(clips) == {"hover", "stand"}
    assert clips["hover"]["success_rate"] == 0.0 and clips["hover"]["frames"] < 20
    frames = sum(c["frames"] for c in clips.values())
    assert final["frames"] == frames
    assert final["mpjpe_mm"] == pytest.approx(sum(c["mpjpe_mm"] * c["frames"] for c in clips.values()) / frames)
    assert final["success_rate"] == pytest.approx(np.mean([c["success_rate"] for c in clips.values()]))


def test_per_clip_curves_are_drawn(library_run, tmp_path):
    png = plot_clip_curves(library_run, tmp_path / "clips.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_clip_failure_bins_cover_each_clip_with_the_samplers_bins():
    # 151 frames in 1 s bins: 4 bins of ⌊f·4/151⌋; 101 frames: 3 bins
    rate = np.arange(7, dtype=float)
    cfg = CommandCfg(fps=50.0, bin_duration_s=1.0, adaptive_floor="relative", adaptive_uniform_ratio=0.5,
                     adaptive_kernel_size=1, library_clip_floor=0.5)
    hover, stand = clip_failures(rate, [151, 101], ["hover", "stand"], cfg)
    assert hover.first_frame.tolist() == [0, 38, 76, 114] and hover.last_frame.tolist() == [37, 75, 113, 150]
    assert stand.first_frame.tolist() == [0, 34, 68] and stand.last_frame.tolist() == [33, 67, 100]
    assert hover.rate.tolist() == [0, 1, 2, 3] and stand.rate.tolist() == [4, 5, 6]
    assert stand.worst(2) == [2, 1] and hover.worst(5) == [3, 2, 1]  # bins without failures are not listed
    # the starts, written out: relative floor r/n_c·F_c per bin (hover F 6, stand F 15), clip
    # mass (1 + r)·F_c, clip share β/2 + (1 − β)·m_c/Σm, split over the bins by weight
    hover_w = np.array([0, 1, 2, 3]) + 0.5 / 4 * 6
    stand_w = np.array([4, 5, 6]) + 0.5 / 3 * 15
    share = 0.25 + 0.5 * np.array([hover_w.sum(), stand_w.sum()]) / (hover_w.sum() + stand_w.sum())
    np.testing.assert_allclose(hover.start, hover_w / hover_w.sum() * share[0], rtol=1e-12)
    np.testing.assert_allclose(stand.start, stand_w / stand_w.sum() * share[1], rtol=1e-12)
    assert hover.start_share + stand.start_share == pytest.approx(1.0)
    assert hover.describe_bin(3).endswith(f"50 %, {100 * hover.start[3]:.1f} % of starts")
    with pytest.raises(ValueError, match="not this run's library"):
        clip_failures(rate, [151], ["hover"], cfg)


def test_the_failure_maps_starts_are_the_samplers():
    """The starts that otr failure-map shows are the distribution MotionCommand draws from,
    for the same failure rates, under either floor rule and a start kernel."""
    refs = [standing_reference(duration_s=99 / 50), standing_reference(duration_s=249 / 50)]
    motion = MotionLibrary.from_references(refs, robot.TRACKED_BODIES, 50.0)
    rate = torch.tensor([0.0, 2.0, 0.3, 0.0, 0.0, 0.1, 0.0, 4.0, 0.5])
    for cfg in (CommandCfg(), CommandCfg(adaptive_floor="absolute", adaptive_kernel_size=3, library_clip_floor=0.2)):
        cmd = MotionCommand(motion, 8, cfg, torch.Generator().manual_seed(0))
        cmd.failure_rate.copy_(rate)
        clips = clip_failures(rate.numpy(), [100, 250], ["short", "long"], cfg)
        np.testing.assert_allclose(np.concatenate([c.start for c in clips]), cmd.sampling_probabilities().numpy(),
                                   rtol=1e-6)
        np.testing.assert_allclose([c.start_share for c in clips], cmd.clip_probabilities().numpy(), rtol=1e-6)


def test_a_runs_failure_map_names_the_clip_and_seconds_that_fail(library_run, library_dir, tmp_path, capsys):
    from agents import failure_bins

    ckpt, clips, _ = failure_bins.load_clip_failures(library_run)
    saved = torch.load(ckpt.path, map_location="cpu", weights_only=False)
    rate = saved["infos"]["training_state"]["env"]["failure_rate"]
    assert [c.clip for c in clips] == ["hover", "stand"]
    assert [c.frames for c in clips] == [151, 101]
    assert np.concatenate([c.rate for c in clips]).tolist() == pytest.approx(rate.tolist())
    assert clips[0].total > clips[1].total  # the floating clip is where the robot falls
    # a checkpoint whose failures all sit in the floating clip's third second
    one_hot = torch.zeros_like(rate)
    one_hot[2] = 0.5
    saved["infos"]["training_state"]["env"]["failure_rate"] = one_hot
    run = shutil.copytree(library_run, tmp_path / library_run.name)
    torch.save(saved, run / ckpt.path.name)
    png, out = tmp_path / "bins.png", tmp_path / "bins.json"
    assert cli.main(["failure-map", str(run / ckpt.path.name), "--png", str(png), "--json", str(out)]) == 0
    table = capsys.readouterr().out
    hover_line = next(line for line in table.splitlines() if line.startswith("hover"))
    # starts under the run's rule (relative floor r, clip floor β): hover's failure mass is
    # under 1, so each clip's floor is r/n_c per bin; hover weighs r + 0.5, stand r
    cfg = load_env_config(TRACK).command
    r, beta = cfg.adaptive_uniform_ratio, cfg.library_clip_floor
    assert cfg.adaptive_floor == "relative" and cfg.adaptive_kernel_size == 1
    hover_share = beta / 2 + (1 - beta) * (r + 0.5) / (2 * r + 0.5)
    third_bin = (r / 4 + 0.5) / (r + 0.5) * hover_share
    assert f"100 %  {100 * hover_share:5.1f} %  1.5–2.3 s (frames 76–113) 100 %, {100 * third_bin:.1f} % of starts" \
        in hover_line
    assert next(line for line in table.splitlines() if line.startswith("stand")).endswith("–")
    assert "starts under library_clip_floor 0.5" in table
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    saved_map = json.loads(out.read_text())
    bins = saved_map["clips"][0]["bins"]
    assert [b["failures_per_step"] for b in bins] == [0.0, 0.0, 0.5, 0.0]
    assert bins[2]["start_share"] == pytest.approx(third_bin) and saved_map["library_clip_floor"] == beta
    # another floor, the same failures: with β = 0 the clips share by their mass alone
    assert cli.main(["failure-map", str(run), "--clip-floor", "0", "--json", str(out)]) == 0
    assert "starts under library_clip_floor 0 (--clip-floor)" in capsys.readouterr().out
    what_if = json.loads(out.read_text())["clips"]
    assert what_if[0]["start_share"] == pytest.approx((r + 0.5) / (2 * r + 0.5))
    assert what_if[0]["bins"][2]["failures_per_step"] == 0.5  # the failures are the run's
    assert cli.main(["failure-map", str(run), "--clip-floor", "1.5"]) == 2
    assert "--clip-floor must lie in [0, 1], got 1.5" in capsys.readouterr().err
    # clips of another library do not fit the checkpoint's bins: refused, nothing written
    assert cli.main(["failure-map", str(run), "--reference", str(library_dir / "stand.npz")]) == 2
    assert "not this run's library" in capsys.readouterr().err
    # a truncated checkpoint is named, not a traceback
    broken = run / "model_9.pt"
    broken.write_bytes((run / ckpt.path.name).read_bytes()[:100])
    assert cli.main(["failure-map", str(broken)]) == 2
    assert f"{broken}: not a readable checkpoint" in capsys.readouterr().err


def test_clip_statistics_of_a_rollout_are_exact():
    stats = ClipRolloutStats(["a", "b"], step_dt=0.02, device="cpu")
    clip = torch.tensor([0, 0, 1, 1])
    ok = torch.ones(4, dtype=torch.bool)
    # step 1: env 1 (clip a) fails after 10 frames; env 3 (clip b) ends its clip after 30 frames
    stats.add_step(clip, torch.tensor([0.01, 0.03, 0.02, 0.04]), ok, torch.tensor([False, True, False, True]),
                   torch.tensor([False, True, False, False]), torch.tensor([5, 10, 7, 30]))
    # step 2: env 2's physics diverged (not valid, failed); its MPJPE must not count
    stats.add_step(clip, torch.tensor([0.01, 0.01, float("nan"), 0.02]), ok & torch.tensor([1, 1, 0, 1]).bool(),
                   torch.tensor([False, False, True, False]), torch.tensor([False, False, True, False]),
                   torch.tensor([6, 1, 8, 1]))
    out = stats.flush(torch.tensor([0.25, 0.75]))
    assert out["clip/a/mpjpe_mm"] == pytest.approx(1000 * (0.01 + 0.03 + 0.01 + 0.01) / 4)
    assert out["clip/b/mpjpe_mm"] == pytest.approx(1000 * (0.02 + 0.04 + 0.02) / 3)
    assert out["clip/a/success_rate"] == 0.0 and out["clip/b/success_rate"] == 0.5
    assert out["clip/a/episode_length_s"] == pytest.approx(10 * 0.02)
    assert out["clip/b/episode_length_s"] == pytest.approx((30 + 8) / 2 * 0.02)
    assert out["clip/b/start_probability"] == 0.75
    assert stats.flush() == {}  # sums cleared


@pytest.mark.parametrize("floor", [0.0, 0.5])
def test_sampler_bins_follow_injected_failures(floor):
    """Two clips of 100 and 250 frames (3 and 6 bins). Failures injected in bin 4 of the second
    clip for 200 steps: the EMA, the start distribution and the sampled starts follow exactly
    (the clip first, with ``floor`` of the starts spread evenly over the clips, then the bin)."""
    refs = [standing_reference(duration_s=99 / 50), standing_reference(duration_s=249 / 50)]
    motion = MotionLibrary.from_references(refs, robot.TRACKED_BODIES, 50.0)
    cfg = CommandCfg(reset_noise_enabled=False, library_clip_floor=floor, adaptive_floor="absolute",
                     adaptive_uniform_ratio=0.1)  # §2's floor, whose arithmetic is written out below
    n = 4000
    cmd = MotionCommand(motion, n, cfg, torch.Generator().manual_seed(0))
    assert cmd.bin_count.tolist() == [3, 6]
    before = cmd.sampling_probabilities()
    torch.testing.assert_close(before[:3], torch.full((3,), 0.5 / 3))  # each clip the same mass r, split evenly
    torch.testing.assert_close(before[3:], torch.full((6,), 0.5 / 6))

    cmd.clip = torch.ones(n, dtype=torch.long)
    cmd.frame = torch.full((n,), 180)  # bin ⌊180·6/250⌋ = 4 of clip 1, global bin 3 + 4 = 7
    failing = torch.zeros(n, dtype=torch.bool)
    failing[:5] = True  # 5 failures per step
    steps = 200
    for _ in range(steps):
        cmd.record_failures(failing)
        cmd.update_failure_rate()
    f = 5.0 * (1.0 - (1.0 - cfg.adaptive_alpha) ** steps)
    expected = torch.tensor([0.1 / 3] * 3 + [0.1 / 6] * 6)
    expected[7] += f
    mass = torch.stack([expected[:3].sum(), expected[3:].sum()])
    share = floor / 2 + (1 - floor) * mass / mass.sum()
    expected[:3] *= share[0] / mass[0]
    expected[3:] *= share[1] / mass[1]
    torch.testing.assert_close(cmd.failure_rate[7], torch.tensor(f), rtol=1e-5, atol=0)
    torch.testing.assert_close(cmd.sampling_probabilities(), expected, rtol=1e-5, atol=0)
    torch.testing.assert_close(cmd.clip_probabilities(), torch.stack([expected[:3].sum(), expected[3:].sum()]),
                               rtol=1e-5, atol=0)

    cmd.resample(torch.ones(n, dtype=torch.bool))
    in_bin = (cmd.clip == 1) & (cmd.start_frame * 6 // 248 == 4)
    p = float(expected[7])
    assert abs(in_bin.float().mean().item() - p) < 4 * np.sqrt(p * (1 - p) / n)


def test_a_clip_that_always_fails_keeps_the_others_sampled():
    """Three clips; five envs fail on clip 0 at every step for 5 000 steps (a clip the policy
    cannot track). With the default floor of 0.5 the other two clips keep at least a third of
    the starts between them; with floor 0 (one distribution over all bins) clip 0 takes over
    95 % (the bins under §2's absolute floor)."""
    refs = [standing_reference(duration_s=99 / 50) for _ in range(3)]
    motion = MotionLibrary.from_references(refs, robot.TRACKED_BODIES, 50.0)
    shares = {}
    for floor in (0.5, 0.0):
        cfg = CommandCfg(reset_noise_enabled=False, library_clip_floor=floor, adaptive_floor="absolute",
                         adaptive_uniform_ratio=0.1)
        cmd = MotionCommand(motion, 300, cfg, torch.Generator().manual_seed(0))
        failing = (cmd.clip == 0) & (torch.arange(300) < 15)
        for _ in range(5000):
            cmd.record_failures(failing)
            cmd.update_failure_rate()
        shares[floor] = cmd.clip_probabilities()
    assert shares[0.5][1:].sum() >= 0.5 * 2 / 3 and shares[0.5][0] < 0.66
    assert shares[0.0][0] > 0.95


def test_clips_of_different_rates_and_lengths_mix_at_50_fps(tmp_path):
    walk = walking_reference(WalkSpec(steps=4, fps=30.0)).save(tmp_path / "walk30.npz")
    stand = standing_reference(duration_s=1.0).save(tmp_path / "stand50.npz")
    lib = load_library([walk, stand], TRACK)
    raw = Reference.load(walk)
    assert [r.fps for r in lib.references] == [50.0, 50.0]
    assert lib.references[0].num_frames == int(np.floor((raw.num_frames - 1) / 30.0 * 50.0 + 1e-9)) + 1
    assert lib.references[1].num_frames == 51
    assert lib.name == "walk30+1"


def test_a_clip_list_names_clips_relative_to_itself(tmp_path, library_dir):
    (tmp_path / "sub").mkdir()
    standing_reference(duration_s=1.0).save(tmp_path / "sub" / "a.npz")
    listing = tmp_path / "clips.txt"
    listing.write_text(f"# my library\nsub/a.npz\n\n{library_dir / 'hover.npz'}  # absolute\n")
    lib = load_library(listing, TRACK, report=False)
    assert [r.source for r in lib.references] == [str(tmp_path / "sub" / "a.npz"), str(library_dir / "hover.npz")]
    listing.write_text("sub/missing.npz\n")
    with pytest.raises(InvalidReferenceError, match=r"clips.txt, line 1: .*missing.npz"):
        load_library(listing, TRACK)


def test_a_library_without_a_loadable_clip_is_refused_by_name(tmp_path, capsys):
    (tmp_path / "bad.npz").write_bytes(b"nope")
    assert cli.main(["train", "--reference", str(tmp_path), "--device", "cpu", "--log-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "bad.npz" in err and "no clip of" in err


def test_duplicate_clip_stems_get_unique_labels():
    assert clip_labels(["x/walk.npz", "y/walk.npz", "y/run.npz"]) == ["x/walk", "y/walk", "run"]
    assert clip_labels(["x/walk.npz", "x/walk.npz"]) == ["x/walk#1", "x/walk#2"]


def test_box_library_shares_one_object_set_or_is_refused(box_reference, box_reference_geometry, tmp_path, capsys):
    import gymnasium

    import otr_gym  # noqa: F401
    from agents.vecenv import RslRlVecEnv

    env = gymnasium.make_vec(BOX, num_envs=4, vectorization_mode="vector_entry_point", device="cpu",
                             reference=[box_reference, box_reference_geometry], seed=0)
    vec = RslRlVecEnv(env, num_steps_per_env=2, seed=0)
    assert vec.clip_labels == ["box_annotated", "box_plain"]
    log = {}
    for _ in range(2):
        log = vec.step(torch.zeros(4, env.unwrapped.num_actions))[3]["log"]
    assert {"clip/box_annotated/mpjpe_mm", "clip/box_plain/mpjpe_mm"} <= set(log)
    env.close()

    ref = Reference.load(box_reference)
    renamed = replace(ref, objects=[replace(o, name="crate" if o.name == "box" else o.name) for o in ref.objects])
    other = renamed.save(tmp_path / "crate.npz")
    rc = cli.main(["train", "--task", BOX, "--reference", str(box_reference), str(other), "--device", "cpu",
                   "--num-envs", "2", "--iterations", "1", "--log-dir", str(tmp_path)])
    assert rc == 2
    err = capsys.readouterr().err
    assert "crate.npz" in err and "one object set per clip library" in err


def test_a_library_run_resumes_with_its_clips_and_sampler(library_run, tmp_path):
    run = shutil.copytree(library_run, tmp_path / library_run.name)
    saved = torch.load(run / "model_1.pt", map_location="cpu", weights_only=False)
    assert cli.main(["train", "--resume", str(run), "--iterations", "1", "--device", "cpu"]) == 0
    scalars = read_scalars(run)
    assert scalars["clip/hover/mpjpe_mm"][0] == [0, 1, 2]
    record = runs.run_config(run)
    assert record["reference_info"]["labels"] == ["hover", "stand"] and len(record["sessions"]) == 2
    # the resumed sampler started from the saved failure statistics, not from zero
    rate = saved["infos"]["training_state"]["env"]["failure_rate"]
    assert rate.sum() > 0
    resumed = torch.load(run / "model_2.pt", map_location="cpu", weights_only=False)
    after = resumed["infos"]["training_state"]["env"]["failure_rate"]
    # every bin at least its saved rate decayed over the 24 new steps (from zero it would hold only new failures)
    assert torch.all(after >= (1 - 0.001) ** 24 * rate - 1e-7)


def test_evaluating_a_library_runs_checkpoints_draws_each_clips_progress(library_run, tmp_path):
    """``otr evaluate RUN --plot`` over every checkpoint: each clip's length is reported, the
    share of it the episodes tracked follows from the frames they lived, and the x axis is the
    run's learning minutes at each checkpoint."""
    from agents.plots import checkpoint_minutes, learning_minutes, tracked_share

    out, png = tmp_path / "eval.json", tmp_path / "eval.png"
    assert cli.main(["evaluate", str(library_run), "--device", "cpu", "--json", str(out), "--plot", str(png)]) == 0
    results = json.loads(out.read_text())
    assert [e["iteration"] for e in results["checkpoints"]] == [c.iteration for c in runs.checkpoints(library_run)]
    final = {c["clip"]: c for c in results["final"]["clips"]}
    assert final["hover"]["clip_frames"] == 151 and final["stand"]["clip_frames"] == 101
    hover = final["hover"]  # the floating clip: the robot falls within ~0.25 s
    assert (tracked_share(hover) == pytest.approx(hover["frames"] / (hover["envs"] * 150))
            and tracked_share(hover) < 0.15)
    its, minutes = learning_minutes(read_scalars(library_run))
    assert checkpoint_minutes(results) == [minutes[its.index(e["iteration"])] for e in results["checkpoints"]]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # --every N: the checkpoints at multiples of N, and the latest whatever its number
    shutil.copy(runs.checkpoints(library_run)[-1].path, tmp_path / "model_7.pt")
    run = shutil.copytree(library_run, tmp_path / "every")
    shutil.copy(tmp_path / "model_7.pt", run / "model_7.pt")
    assert cli.main(["evaluate", str(run), "--every", "2", "--device", "cpu", "--json", str(out)]) == 0
    expected = [c.iteration for c in runs.checkpoints(run)[:-1] if c.iteration % 2 == 0] + [7]
    assert [e["iteration"] for e in json.loads(out.read_text())["checkpoints"]] == expected
    assert cli.main(["evaluate", str(run), "--every", "0", "--device", "cpu"]) == 2


def test_policy_only_checkpoints_evaluate_like_the_full_ones_and_refuse_to_resume(library_run, tmp_path, capsys):
    """A run's intermediate checkpoints travel back from a GPU machine without critic and
    optimizer (``carry`` with EVERY): the copy keeps the actor, the iteration and the sampler
    statistics, evaluates to exactly the full checkpoint's figures, and cannot resume training."""
    run = shutil.copytree(library_run, tmp_path / library_run.name)
    full = run / "model_1.pt"
    shutil.copy(full, run / "model_4.pt")  # the latest, which carry packs whole
    copies = runs.policy_only_copies(run, 1, tmp_path / "slim")
    assert [p.name for p in copies] == [c.path.name for c in runs.checkpoints(run)[:-1]]  # not model_4
    slim_path = tmp_path / "slim" / "model_1.pt"
    slim = torch.load(slim_path, map_location="cpu", weights_only=False)
    saved = torch.load(full, map_location="cpu", weights_only=False)
    assert slim["policy_only"] is True and set(slim) == {"actor_state_dict", "iter", "infos", "policy_only"}
    assert all(torch.equal(slim["actor_state_dict"][k], v) for k, v in saved["actor_state_dict"].items())
    assert slim["infos"]["training_state"]["env"]["failure_rate"].tolist() == \
        saved["infos"]["training_state"]["env"]["failure_rate"].tolist()
    assert slim_path.stat().st_size < full.stat().st_size / 2
    shutil.copy(slim_path, full)
    out_full, out_slim = tmp_path / "full.json", tmp_path / "slim.json"
    assert cli.main(["evaluate", str(run / "model_4.pt"), "--device", "cpu", "--json", str(out_full)]) == 0
    assert cli.main(["evaluate", str(full), "--device", "cpu", "--json", str(out_slim)]) == 0
    a, b = (json.loads(p.read_text())["final"] for p in (out_full, out_slim))
    assert (a["success_rate"], a["mpjpe_mm"], a["frames"]) == (b["success_rate"], b["mpjpe_mm"], b["frames"])
    capsys.readouterr()
    assert cli.main(["train", "--resume", str(full), "--iterations", "1", "--device", "cpu"]) == 2
    assert f"{full}: a policy-only checkpoint" in capsys.readouterr().err
    assert cli.main(["runs", "policy-only", str(run), "--every", "0", "--out", str(tmp_path / "x")]) == 1


def test_play_records_the_chosen_clip_of_a_library(library_run, tmp_path):
    from agents.play import play

    out = play(library_run, tmp_path / "hover.mp4", seconds=0.1, width=96, height=64, clip="hover")
    assert out["clip"] == "hover" and (tmp_path / "hover.mp4").stat().st_size > 0
    with pytest.raises(ValueError, match="not a clip of the library"):
        play(library_run, tmp_path / "x.mp4", clip="nope")
