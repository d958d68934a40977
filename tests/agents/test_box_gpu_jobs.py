"""benchmarks/train_box_gpus.sh: the _q0 / _xy suffixes compose with every base job, every job's
--set overrides load into the box config (a typo would only surface on the GPU), and `pack` returns
each resumable run's checkpoint in a file of its own."""
import os
import subprocess
import tarfile
from pathlib import Path

import pytest

from agents.config import load_train_config
from agents.train import parse_sets
from envs.config import load_env_config
from otr_gym.config import merge

from conftest import REPO_ROOT

SCRIPT = REPO_ROOT / "benchmarks" / "train_box_gpus.sh"


def script(tmp_path: Path, *args: str, **env: str) -> subprocess.CompletedProcess:
    """The script in ``tmp_path`` (its working folder), the caller's knobs dropped, ``env`` added."""
    base = {k: v for k, v in os.environ.items() if k not in ("SETS", "XY_M", "IN")}
    return subprocess.run(["bash", str(SCRIPT), *args], cwd=tmp_path, capture_output=True, text=True,
                          env={**base, **env}, timeout=60)


def parse_show(stdout: str) -> dict[str, dict[str, str]]:
    jobs: dict[str, dict[str, str]] = {}
    for line in stdout.splitlines():
        if not line.startswith("  "):
            job = jobs.setdefault(line, {})
        else:
            key, _, value = line.strip().partition(": ")
            job[key.rstrip(":")] = value
    return jobs


def box_env(sets: str):
    """The environment config `otr train --task OTR-G1-BoxTrack-v0 --set …` builds (as agents.vecenv)."""
    train = load_train_config(None, merge(parse_sets(sets.split()), {"task": "OTR-G1-BoxTrack-v0"}))
    return load_env_config(train.task, overrides=train.env or None)


def test_suffixes_compose_and_load_into_the_box_config(tmp_path):
    names = ["ours", "ours_q0", "ours_q0_xy", "holo_q0", "no_contact_q0", "demo_q0_xy"]
    result = script(tmp_path, "show", *names, XY_M="0.3")
    assert result.returncode == 0, result.stderr
    jobs = parse_show(result.stdout)
    assert list(jobs) == names

    assert jobs["ours"]["reference"] == "out/gin/sub3_largebox_003.npz"
    assert jobs["holo_q0"]["reference"] == "out/gin/sub3_largebox_003_mj_w_obj.npz"
    assert jobs["holo_q0"]["knobs"] == "OBJECT_MESH=largebox=out/gin/largebox.obj"
    assert jobs["no_contact_q0"]["knobs"] == "ABLATION=no_contact"
    assert jobs["demo_q0_xy"]["reference"] == "out/gin/demo_box_carry.npz"

    default = box_env(jobs["ours"]["sets"])
    assert default.objects.grasp_fit_quantile == pytest.approx(0.75)
    assert "anchor_xy" not in default.terminations
    for job in ("ours_q0", "ours_q0_xy", "holo_q0", "no_contact_q0", "demo_q0_xy"):
        assert box_env(jobs[job]["sets"]).objects.grasp_fit_quantile == 0.0, job
    for job in ("ours_q0_xy", "demo_q0_xy"):
        term = box_env(jobs[job]["sets"]).terminations["anchor_xy"]
        assert term.fn == "anchor_horizontal_error" and term.params == {"threshold_m": 0.3}, job
    assert "anchor_xy" not in box_env(jobs["ours_q0"]["sets"]).terminations


def test_unknown_jobs_are_refused_by_name(tmp_path):
    for job in ("bogus", "bogus_q0", "throughput_q0"):
        result = script(tmp_path, "show", job)
        assert result.returncode == 2
        assert f"'{job}'" in result.stderr


def test_pack_writes_one_checkpoint_tar_per_resumable_run(tmp_path):
    """Each run that learned to the deadline gets its own tar with only its latest checkpoint (a
    device command returns files of at most 16 MiB: one tar of four checkpoints did not come back)."""
    for job, resumable, iterations in (("ours_q0", True, (25, 100, 75)), ("holo_q0", False, (250,)),
                                       ("ours_q0_xy", True, (50,)), ("ours", True, ())):
        run = tmp_path / "runs" / "gpus" / job / "RUN"
        run.mkdir(parents=True)
        for it in iterations:
            (run / f"model_{it}.pt").write_bytes(b"x" * it)
        (run.parent / "LATEST_RUN").write_text(f"runs/gpus/{job}/RUN\n")
        if resumable:
            (run.parent / "RESUMABLE").touch()
        (tmp_path / "out" / "gpus" / job).mkdir(parents=True)
        (tmp_path / "out" / "gpus" / job / "summary.md").write_text(f"# {job}\n")
    result = script(tmp_path, "pack", "packed/results.tgz")
    assert result.returncode == 0, result.stderr
    assert "# ours_q0_xy" in result.stdout
    assert "pack: no checkpoint in runs/gpus/ours/RUN" in result.stderr  # reported, the others still packed

    packed = sorted(p.name for p in (tmp_path / "packed").iterdir())
    assert packed == ["results.tgz", "results_checkpoint_ours_q0.tar", "results_checkpoint_ours_q0_xy.tar"]
    with tarfile.open(tmp_path / "packed" / "results_checkpoint_ours_q0.tar") as tar:
        assert tar.getnames() == ["runs/gpus/ours_q0/RUN/model_100.pt"]
    with tarfile.open(tmp_path / "packed" / "results.tgz") as tar:
        names = tar.getnames()
    assert "out/gpus/holo_q0/summary.md" in names and "runs/gpus/ours_q0/LATEST_RUN" in names
    assert not [n for n in names if n.endswith(".pt")]


@pytest.mark.parametrize("script, args", [("train_box.sh", ["out", "ref.npz"]), ("train_library.sh", ["out"])])
def test_carry_packs_the_latest_run_with_only_its_latest_checkpoint(tmp_path, script, args):
    """`carry` (both recipes, through carry_run.sh) writes what resuming on another machine needs:
    RUNS_DIR's LATEST_RUN and the run folder with its highest-numbered checkpoint (by number: 1250
    after 975, which a sort of the names would pick), its config and event files, no other
    checkpoint. The box recipe's `prune` keeps the same latest checkpoint; a run without
    checkpoints is refused by name."""
    carry = REPO_ROOT / "benchmarks" / script
    run = tmp_path / "runs" / "x" / "OTR-G1-BoxTrack-v0_sub3_largebox_003_20261127-022526"
    run.mkdir(parents=True)
    for it in (25, 975, 1250):
        (run / f"model_{it}.pt").write_bytes(b"x" * it)
    (run / "config.yaml").write_text("train: {}\n")
    (run / "events.out.tfevents.1").write_bytes(b"e")
    (run.parent / "LATEST_RUN").write_text(f"runs/x/{run.name}\n")

    def stage(name: str) -> subprocess.CompletedProcess:
        return subprocess.run(["bash", str(carry), name, *args], cwd=tmp_path, capture_output=True,
                              text=True, env={**os.environ, "RUNS_DIR": "runs/x"}, timeout=60)

    result = stage("carry")
    assert result.returncode == 0, result.stderr
    assert "checkpoint model_1250.pt" in result.stdout
    packed = tmp_path / "out" / "run.tar.gz"
    assert packed.read_bytes()[:2] == b"\x1f\x8b"  # gzipped: the event files grow with the run
    with tarfile.open(packed) as tar:
        files = sorted(m.name for m in tar.getmembers() if m.isfile())
    folder = f"runs/x/{run.name}"
    assert files == ["runs/x/LATEST_RUN", f"{folder}/config.yaml", f"{folder}/events.out.tfevents.1",
                     f"{folder}/model_1250.pt"]

    assert "extract in the repository root" in result.stdout  # RUNS_DIR is relative here

    if script == "train_box.sh":
        (run / "model_499.pt").write_bytes(b"x")
        assert stage("prune").returncode == 0  # keeps the latest checkpoint and every 500th
        assert sorted(p.name for p in run.glob("model_*.pt")) == ["model_1250.pt", "model_499.pt"]
    for f in run.glob("model_*.pt"):
        f.unlink()
    result = stage("carry")
    assert result.returncode == 1 and "holds no checkpoint" in result.stderr and run.name in result.stderr


def test_carry_with_every_packs_policy_only_checkpoints_beside_the_run(tmp_path):
    """EVERY=N: a second archive holds policy-only copies of the checkpoints at multiples of N
    (not the latest, which run.tar.gz holds whole) under the run's own paths."""
    import torch

    carry = REPO_ROOT / "benchmarks" / "train_library.sh"
    run = tmp_path / "runs" / "x" / "OTR-G1-Track-v0_librefs_20261129-102510"
    run.mkdir(parents=True)
    for it in (250, 499, 500, 750):
        torch.save({"actor_state_dict": {"w": torch.full((3,), float(it))}, "critic_state_dict": {"w": torch.ones(50)},
                    "optimizer_state_dict": {"m": torch.ones(100)}, "iter": it, "infos": {}}, run / f"model_{it}.pt")
    (run / "config.yaml").write_text("train: {}\n")
    (run.parent / "LATEST_RUN").write_text(f"runs/x/{run.name}\n")

    def carry_every(every: str) -> subprocess.CompletedProcess:
        return subprocess.run(["bash", str(carry), "carry", "out"], cwd=tmp_path, capture_output=True, text=True,
                              env={**os.environ, "RUNS_DIR": "runs/x", "EVERY": every}, timeout=60)

    result = carry_every("250")
    assert result.returncode == 0, result.stderr
    assert "2 policy-only checkpoints every 250 iterations" in result.stdout
    with tarfile.open(tmp_path / "out" / "run_policies.tar.gz") as tar:
        assert sorted(tar.getnames()) == [f"runs/x/{run.name}/model_250.pt", f"runs/x/{run.name}/model_500.pt"]
        tar.extractall(tmp_path / "back")
    slim = torch.load(tmp_path / "back" / "runs" / "x" / run.name / "model_500.pt", weights_only=False)
    assert slim["policy_only"] and slim["iter"] == 500 and "critic_state_dict" not in slim
    assert slim["actor_state_dict"]["w"].tolist() == [500.0] * 3
    with tarfile.open(tmp_path / "out" / "run.tar.gz") as tar:
        assert [n for n in tar.getnames() if n.endswith(".pt")] == [f"runs/x/{run.name}/model_750.pt"]
    (tmp_path / "out" / "run_policies.tar.gz").unlink()
    result = carry_every("1000")  # nothing but the latest at a multiple: said, no archive
    assert result.returncode == 0 and "no checkpoint but the latest" in result.stderr
    assert not (tmp_path / "out" / "run_policies.tar.gz").exists()


@pytest.mark.parametrize("script, args", [("train_box.sh", ["out", "ref.npz"]), ("train_library.sh", ["out"])])
def test_carry_packs_a_run_that_is_still_training(tmp_path, script, args):
    """While the train stage's process runs there is no LATEST_RUN yet (it is written when the
    process ends), and a detached run on a machine that may be lost is what `carry` is for: it
    takes the run folder from OUT_DIR/train.log's last `run folder:` line, refuses it by name
    while it holds no checkpoint, and once it has one writes LATEST_RUN (which the train stage
    resumes) and packs both."""
    carry = REPO_ROOT / "benchmarks" / script
    old = tmp_path / "runs" / "x" / "OTR-G1-Track-v0_walk_20261128-010101"
    run = tmp_path / "runs" / "x" / "OTR-G1-Track-v0_smplh_walk_jog_turn_20261129-091220"
    for folder in (old, run):
        folder.mkdir(parents=True)
        (folder / "config.yaml").write_text("train: {}\n")
    (old / "model_50.pt").write_bytes(b"o")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "train.log").write_text(
        f"run folder: runs/x/{old.name}\nLearning iteration 50/100\nrun folder: runs/x/{run.name}\n")

    def stage() -> subprocess.CompletedProcess:
        return subprocess.run(["bash", str(carry), "carry", *args], cwd=tmp_path, capture_output=True,
                              text=True, env={**os.environ, "RUNS_DIR": "runs/x"}, timeout=60)

    result = stage()  # the new run has not saved its first checkpoint yet
    assert result.returncode == 1 and "holds no checkpoint" in result.stderr and run.name in result.stderr
    assert not (tmp_path / "runs" / "x" / "LATEST_RUN").exists()

    (run / "model_25.pt").write_bytes(b"x" * 25)
    result = stage()
    assert result.returncode == 0, result.stderr
    assert "checkpoint model_25.pt" in result.stdout
    assert (tmp_path / "runs" / "x" / "LATEST_RUN").read_text().strip() == f"runs/x/{run.name}"
    with tarfile.open(tmp_path / "out" / "run.tar.gz") as tar:
        files = sorted(m.name for m in tar.getmembers() if m.isfile())
    assert files == ["runs/x/LATEST_RUN", f"runs/x/{run.name}/config.yaml", f"runs/x/{run.name}/model_25.pt"]

    (tmp_path / "out" / "train.log").unlink()
    (tmp_path / "runs" / "x" / "LATEST_RUN").unlink()
    result = stage()  # neither a finished run nor a log
    assert result.returncode == 1 and "no trained run" in result.stderr
