"""``otr inspect`` (``agents.inspect``): one clear line for a file it cannot read, the next files
still inspected, and files recognised by what they hold."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from otr_gym import robot
from otr_gym.cli import main
from otr_gym.reference import Reference


def deploy_log(path: Path) -> Path:
    """A two-cycle deploy log written by the log API at ``path``; returns where it went."""
    from agents.deploy.controller import CycleInput, CycleOutput
    from agents.deploy.log import CycleLog
    from agents.deploy.safety import Stage

    log = CycleLog(observation_dim=4, meta={"period_ns": 20_000_000})
    for i in range(2):
        out = CycleOutput(command=None, stage=Stage.WAIT, frame=-1, observation=None, action=None, tilt_rad=0.0,
                          mpjpe_m=float("nan"))
        log.append(CycleInput(t_s=0.02 * i, state=None), out, deadline_ns=20_000_000 * i,
                   wake_ns=20_000_000 * i + 1000, publish_ns=20_000_000 * i + 5000)
    return log.save(path, [])


@pytest.fixture
def reference(tmp_path):
    return Reference.from_qpos(np.tile(robot.default_qpos(), (11, 1)), fps=50).save(tmp_path / "walk.npz")


def inspect(capsys, *paths) -> tuple[int, list[str]]:
    rc = main(["inspect", *map(str, paths)])
    return rc, capsys.readouterr().out.splitlines()


def test_a_truncated_npz_is_one_error_line_and_the_next_file_is_still_inspected(tmp_path, reference, capsys):
    cut = tmp_path / "cut.npz"
    cut.write_bytes(reference.read_bytes()[:200])
    rc, lines = inspect(capsys, cut, reference)
    assert rc == 1
    assert lines[0].startswith(f"{cut}: error: not a NumPy .npz archive (truncated or not a zip archive")
    assert lines[1] == str(reference) and "11 @ 50 fps" in "\n".join(lines[2:])


def test_an_empty_npz_is_one_error_line(tmp_path, reference, capsys):
    empty = tmp_path / "empty.npz"
    empty.touch()
    rc, lines = inspect(capsys, empty, reference)
    assert rc == 1
    assert lines[0] == f"{empty}: error: empty file (0 bytes), not a NumPy .npz archive"
    assert lines[1] == str(reference)


def test_a_text_file_named_npz_is_not_an_archive_and_unpickling_is_never_suggested(tmp_path, capsys):
    text = tmp_path / "notes.npz"
    text.write_text("hello\n")
    rc, lines = inspect(capsys, text)
    assert rc == 1
    assert lines == [f"{text}: error: not a NumPy .npz archive (starts with the text 'hello')"]


def test_a_deploy_log_saved_without_the_suffix_is_inspected_as_a_deploy_log(tmp_path, capsys):
    saved = deploy_log(tmp_path / "run")
    rc, lines = inspect(capsys, saved)
    assert rc == 0
    assert any(line.split()[:3] == ["kind", "deploy", "log"] for line in lines), lines


def test_a_deploy_log_renamed_without_the_suffix_is_still_recognised_by_its_arrays(tmp_path, capsys):
    renamed = deploy_log(tmp_path / "run.npz").rename(tmp_path / "run")
    rc, lines = inspect(capsys, renamed)
    assert rc == 0
    assert any(line.split()[:3] == ["kind", "deploy", "log"] for line in lines), lines
