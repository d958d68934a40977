"""The ``otr`` command line: help, inspect, the demo job, run folders and procedural clips."""

from __future__ import annotations

import json
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest

from otr_gym import robot
from otr_gym.cli import main
from otr_gym.reference import Reference
from retarget.inputs.demonstration import Demonstration

from conftest import REPO_ROOT


def test_help_lists_every_available_command(capsys):
    assert main([]) == 2
    out = capsys.readouterr().out
    for command in ("demo", "inspect"):
        assert command in out


def test_inspect_summarises_a_reference_with_its_numbers(tmp_path, capsys):
    q = np.tile(robot.default_qpos(), (101, 1))
    q[:, 0] = np.linspace(0.0, 2.0, 101)
    path = Reference.from_qpos(q, fps=50).save(tmp_path / "walk.npz")
    assert main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert "101 @ 50 fps (2.00 s)" in out
    assert "root path          2.00 m" in out


def test_inspect_reports_a_bad_file_and_fails(tmp_path, capsys):
    bad = tmp_path / "broken.npz"
    np.savez(bad, joint_pos=np.zeros((3, 36)), body_pos_w=np.zeros((3, 30, 3)))
    assert main(["inspect", str(bad)]) == 1
    assert "broken.npz" in capsys.readouterr().out


def test_demo_retargets_pictures_and_scores_the_embedded_walk(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--kind", "walk"]) == 0
    demo = Demonstration.load(tmp_path / "walk_demo.npz")
    ref = Reference.load(tmp_path / "walk.npz")
    assert ref.fps == 50 and abs(ref.duration_s - demo.duration_s) < 0.05
    picture = iio.imread(tmp_path / "walk.png")
    assert picture.shape[0] >= 700 and picture.shape[1] > 2 * picture.shape[0]  # two rows of six
    assert picture.std() > 10  # an actual rendering, not a blank canvas
    record = json.loads((tmp_path / "walk_eval.json").read_text())
    assert record["metrics"]["ground_jaccard"] > 0.9  # the feet keep the demonstrated floor contacts
    assert (tmp_path / "walk_contacts.png").stat().st_size > 10_000
    assert "walk" in capsys.readouterr().out.splitlines()[-1]  # the table's row


def test_otr_runs_latest_prints_the_checkpoint_of_the_highest_iteration(tmp_path, capsys):
    for name in ("model_975.pt", "model_1204.pt", "model_50.pt"):  # a plain sort would pick model_975
        (tmp_path / name).write_bytes(b"")
    assert main(["runs", "latest", str(tmp_path)]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "model_1204.pt")


def test_otr_runs_latest_of_a_folder_without_checkpoints_fails_naming_it(tmp_path, capsys):
    assert main(["runs", "latest", str(tmp_path)]) == 1
    assert str(tmp_path) in capsys.readouterr().err


def test_python_m_otr_gym_cli_is_the_otr_command_where_nothing_is_installed(tmp_path):
    """The GPU machines of benchmarks/ run ``python -m otr_gym.cli COMMAND`` from the repository root."""
    (tmp_path / "model_7.pt").write_bytes(b"")
    done = subprocess.run([sys.executable, "-m", "otr_gym.cli", "runs", "latest", str(tmp_path)], cwd=REPO_ROOT,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(tmp_path / "model_7.pt")


def test_otr_procedural_writes_a_standing_clip_of_the_duration_asked(tmp_path, capsys):
    assert main(["procedural", "stand", str(tmp_path / "stand.npz"), "--duration", "1"]) == 0
    ref = Reference.load(tmp_path / "stand.npz")
    assert ref.num_frames == 51 and ref.fps == 50
    assert np.ptp(ref.joint_pos, axis=0).max() == 0.0  # held still
    assert "51 frames at 50 fps" in capsys.readouterr().out


def test_a_count_below_its_minimum_is_a_usage_error_naming_the_option(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["trace", str(tmp_path), "--every", "0"])
    assert exit_.value.code == 2
    assert "argument --every: must be >= 1, got 0" in capsys.readouterr().err
