"""The deploy cycle log's file (``agents.deploy.log``): where it is written and how it reads back,
without DDS (the log API called directly)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from agents.deploy.controller import CycleInput, CycleOutput
from agents.deploy.log import CycleLog, DeployLog, log_file
from agents.deploy.safety import Stage, Transition
from otr_gym.io import NpzError

PERIOD_NS = 20_000_000


def short_log(path: Path, cycles: int = 3) -> Path:
    """A log of ``cycles`` cycles waiting for a LowState, saved at ``path``; returns where it went."""
    log = CycleLog(observation_dim=4, meta={"period_ns": PERIOD_NS, "domain_id": 0, "interface": "lo"})
    for i in range(cycles):
        out = CycleOutput(command=None, stage=Stage.WAIT, frame=-1, observation=None, action=None, tilt_rad=0.0,
                          mpjpe_m=float("nan"))
        log.append(CycleInput(t_s=i * PERIOD_NS / 1e9, state=None), out, deadline_ns=i * PERIOD_NS,
                   wake_ns=i * PERIOD_NS + 1000, publish_ns=i * PERIOD_NS + 5000)
    return log.save(path, [Transition(cycle=2, source=Stage.WAIT, target=Stage.DAMP, reason="test")])


@pytest.mark.parametrize(("asked", "written"), [("run", "run.npz"), ("run.npz", "run.npz"),
                                                 ("run.2024-06-01", "run.2024-06-01.npz")])
def test_a_log_path_without_the_npz_suffix_gets_it_appended(asked, written):
    assert log_file(Path("logs") / asked) == Path("logs") / written


def test_saving_to_a_path_without_a_suffix_writes_and_returns_the_npz(tmp_path):
    saved = short_log(tmp_path / "run")
    assert saved == tmp_path / "run.npz" and saved.is_file()
    assert not (tmp_path / "run").exists()
    log = DeployLog.load(saved)
    assert log.num_cycles == 3
    assert log.transitions()[0][1:] == ("WAIT", "DAMP", "test")


def test_loading_the_path_asked_for_finds_the_log_written_with_the_suffix(tmp_path):
    short_log(tmp_path / "run")
    assert DeployLog.load(tmp_path / "run").path == tmp_path / "run.npz"  # ``otr deploy --replay run``


def test_a_file_that_is_not_a_log_archive_is_named_with_its_problem(tmp_path):
    path = tmp_path / "run.npz"
    path.write_text("not a log\n")
    with pytest.raises(NpzError, match=rf"^{path}: not a NumPy .npz archive"):
        DeployLog.load(path)
    np.savez(path, wake_ns=np.zeros(3, np.int64))
    with pytest.raises(ValueError, match=rf"^{path}: not a readable deploy log \(its 'meta' JSON"):
        DeployLog.load(path)
