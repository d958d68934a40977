"""benchmarks/reference_seeds.py: seeds parsed or refused by name, and a short box clip retargeted
with two probe seeds, played back under object draws, ranked, resumed without re-solving."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from otr_gym.reference import Reference
from retarget.solver.problem import resample_demonstration

from clips import clip
from conftest import load_benchmark


@pytest.fixture(scope="module")
def seeds_module():
    return load_benchmark("reference_seeds")


def test_seed_ranges_are_parsed_or_refused(seeds_module):
    assert seeds_module.seed_range("0:3") == [0, 1, 2]
    assert seeds_module.seed_range("4,1") == [4, 1] and seeds_module.seed_range("7") == [7]
    for bad in ("a:b", "3:3", "1,,2"):
        with pytest.raises(argparse.ArgumentTypeError, match="--seeds"):
            seeds_module.seed_range(bad)


def test_two_seeds_are_retargeted_ranked_and_resumed(seeds_module, tmp_path, capsys):
    demo_path = resample_demonstration(clip("box_carry", 130, 150), 50.0).save(tmp_path / "lift.npz")
    out = tmp_path / "seeds"
    assert seeds_module.main([str(demo_path), "--seeds", "0,1", "--draws", "2", "--out", str(out)]) == 0
    summary = json.loads((out / "seeds.json").read_text())
    rows = summary["seeds"]
    assert sorted(r["seed"] for r in rows) == [0, 1] and all(r["runs"] == 2 for r in rows)
    assert all(isinstance(r["overlaps"], list) for r in rows)
    # best first: most runs carried, then the smaller mean error
    assert ([(-r["carried"], r["error_cm_mean"]) for r in rows]
            == sorted((-r["carried"], r["error_cm_mean"]) for r in rows))
    files = [Path(r["reference"]) for r in rows]
    a, b = (Reference.load(f) for f in sorted(files))
    assert not np.array_equal(a.joint_pos, b.joint_pos)  # the probe seed changes the solution
    table = capsys.readouterr().out
    assert "| seed 0 |" in table and "| seed 1 |" in table
    stamps = {f: f.stat().st_mtime_ns for f in files}
    assert seeds_module.main([str(demo_path), "--seeds", "0,1", "--draws", "1", "--out", str(out)]) == 0
    assert {f: f.stat().st_mtime_ns for f in files} == stamps  # present references are not solved again
