"""The ``otr`` command line: help, inspect and the demo job."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np

from otr_gym import robot
from otr_gym.cli import main
from otr_gym.reference import Reference
from retarget.inputs.demonstration import Demonstration


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
