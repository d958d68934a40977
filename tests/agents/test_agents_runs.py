"""Run folders, checkpoints, atomic writes and device checks (no environment needed)."""

from __future__ import annotations

import os

import pytest
import torch

from agents import runs
from agents.devices import resolve_device


def _touch_checkpoints(folder, iterations):
    folder.mkdir(parents=True, exist_ok=True)
    for it in iterations:
        (folder / f"model_{it}.pt").write_bytes(b"x")


def test_checkpoints_are_sorted_by_iteration_number_not_by_name(tmp_path):
    _touch_checkpoints(tmp_path / "run", [100, 9, 20, 0])
    (tmp_path / "run" / "model_best.pt").write_bytes(b"x")  # not a checkpoint name
    assert [c.iteration for c in runs.checkpoints(tmp_path / "run")] == [0, 9, 20, 100]
    latest = runs.resolve_checkpoint(tmp_path / "run")
    assert latest.iteration == 100 and latest.path.name == "model_100.pt"


def test_a_checkpoint_file_resolves_to_itself(tmp_path):
    _touch_checkpoints(tmp_path / "run", [3, 7])
    ckpt = runs.resolve_checkpoint(tmp_path / "run" / "model_3.pt")
    assert ckpt.iteration == 3 and ckpt.run_dir == tmp_path / "run"


def test_missing_run_folder_is_named(tmp_path):
    with pytest.raises(runs.RunError, match="no_such_run"):
        runs.resolve_checkpoint(tmp_path / "no_such_run")


def test_run_folder_without_checkpoints_is_named(tmp_path):
    (tmp_path / "empty_run").mkdir()
    with pytest.raises(runs.RunError, match="empty_run.*no checkpoint"):
        runs.resolve_checkpoint(tmp_path / "empty_run")


def test_file_that_is_not_a_checkpoint_is_named(tmp_path):
    path = tmp_path / "weights.bin"
    path.write_bytes(b"x")
    with pytest.raises(runs.RunError, match="weights.bin.*not a checkpoint"):
        runs.resolve_checkpoint(path)


def test_run_folder_missing_its_config_is_named(tmp_path):
    _touch_checkpoints(tmp_path / "run", [0])
    with pytest.raises(runs.RunError, match="config.yaml"):
        runs.run_config(tmp_path / "run")


def test_failed_atomic_write_keeps_the_previous_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "model_1.pt"
    runs.atomic_write(target, lambda f: torch.save({"a": torch.ones(3)}, f))

    def crash(f):
        f.write(b"partial")
        raise RuntimeError("killed mid-write")

    with pytest.raises(RuntimeError):
        runs.atomic_write(target, crash)
    assert torch.equal(torch.load(target)["a"], torch.ones(3))
    assert os.listdir(tmp_path) == ["model_1.pt"]


def test_run_name_is_task_reference_stem_and_timestamp(tmp_path):
    clips = tmp_path / "walks"
    clips.mkdir()
    assert runs.run_name("OTR-G1-Track-v0", tmp_path / "walk_01.npz", "20260101-120000") == \
        "OTR-G1-Track-v0_walk_01_20260101-120000"
    assert runs.run_name("OTR-G1-Track-v0", clips, "20260101-120000") == "OTR-G1-Track-v0_walks_20260101-120000"


def test_two_runs_in_the_same_second_get_distinct_folders(tmp_path):
    a = runs.create_run_dir(tmp_path, "T", "ref.npz")
    b = runs.create_run_dir(tmp_path, "T", "ref.npz")
    assert a != b and a.is_dir() and b.is_dir()


def test_cuda_device_without_cuda_is_refused_with_a_clear_message(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="CUDA is not available"):
        resolve_device("cuda")
    assert resolve_device(None) == torch.device("cpu")
    with pytest.raises(ValueError, match="not a torch device"):
        resolve_device("gpu0")
