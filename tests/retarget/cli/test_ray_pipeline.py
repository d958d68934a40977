"""``otr retarget --ray``: a local Ray cluster gives the serial path's references byte for byte,
reports a failing clip while the others finish, retries a clip whose worker dies, and writes the
summary JSON.

Byte for byte: both paths serialise through ``retarget_bytes`` (no time stamps, tested below),
and a clip's reference does not depend on the process that computed it nor on the clips it
computed before (``tests/test_determinism.py``)."""

from __future__ import annotations

import argparse
import json
import os
import signal
import zipfile
from pathlib import Path

import numpy as np
import pytest

from otr_gym.io import npz_bytes
from retarget.cli.batch import SUMMARY_NAME, Job, Task
from retarget.cli.executors import RayExecutor
from retarget.cli.retarget import configure_parser, main
from retarget.config import load_config

from clips import clip

ray = pytest.importorskip("ray", reason="ray is not installed (pip install 'otr-gym[cluster]')")


def assert_same_reference(a: Path, b: Path) -> None:
    """The same file, byte for byte."""
    x, y = a.read_bytes(), b.read_bytes()
    assert x == y, f"{a} and {b} differ ({len(x)} and {len(y)} bytes)"
    with np.load(a) as loaded:
        assert loaded["joint_pos"].shape[1] == 36


def test_npz_bytes_are_reproducible_and_carry_no_time_stamp():
    arrays = {"a": np.arange(6.0).reshape(2, 3), "names": np.array(["x", "yz"])}
    first, second = npz_bytes(arrays), npz_bytes({k: v.copy() for k, v in arrays.items()})
    assert first == second
    import io

    with zipfile.ZipFile(io.BytesIO(first)) as archive:
        assert {i.date_time for i in archive.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    with np.load(io.BytesIO(first)) as loaded:
        assert np.array_equal(loaded["a"], arrays["a"]) and list(loaded["names"]) == ["x", "yz"]


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    configure_parser(parser)
    return parser.parse_args(list(argv))


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Path:
    """Three short synthetic walks (10 frames at 30 fps each) as demonstration files."""
    folder = tmp_path_factory.mktemp("corpus")
    for i, start in enumerate((40, 55, 70)):
        clip("walk", start, start + 10).save(folder / f"walk_{i}.npz")
    return folder


@pytest.fixture(scope="module")
def serial_out(corpus, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("serial")
    assert main(_args(str(corpus), "--out", str(out), "--mode", "robot-only")) == 0
    return out


def test_local_ray_writes_the_serial_paths_references_and_a_summary(corpus, serial_out, tmp_path):
    out = tmp_path / "ray"
    assert main(_args(str(corpus), "--out", str(out), "--mode", "robot-only", "--ray", "--workers", "2")) == 0
    names = sorted(p.name for p in serial_out.glob("*.npz"))
    assert names == ["walk_0.npz", "walk_1.npz", "walk_2.npz"]
    for name in names:
        assert_same_reference(out / name, serial_out / name)
    summary = json.loads((out / SUMMARY_NAME).read_text())
    assert summary["executor"].startswith("Ray (local") and summary["done"] == 3 and summary["failed"] == 0
    for record in summary["results"]:
        assert record["status"] == "done" and record["frames"] == 16  # 10 frames at 30 fps -> 16 at 50 fps
        assert record["ms_per_frame"] > 0 and record["worker"].count(":") >= 1
    assert not list(out.glob(".*.tmp*"))


def test_a_raising_clip_is_reported_by_name_and_the_others_finish(corpus, tmp_path, capsys):
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    for p in corpus.glob("walk_[01].npz"):
        (inputs / p.name).write_bytes(p.read_bytes())
    broken = inputs / "broken.npz"
    broken.write_bytes(b"PK\x03\x04 not really a zip file")
    out = tmp_path / "ray"
    code = main(_args(str(inputs), "--out", str(out), "--mode", "robot-only", "--ray", "--workers", "2"))
    assert code == 1
    assert f"{broken}: InvalidDemonstrationError" in capsys.readouterr().err
    assert sorted(p.name for p in out.glob("*.npz")) == ["walk_0.npz", "walk_1.npz"]
    summary = json.loads((out / SUMMARY_NAME).read_text())
    status = {Path(r["source"]).name: r["status"] for r in summary["results"]}
    assert status == {"broken.npz": "failed", "walk_0.npz": "done", "walk_1.npz": "done"}
    # a second run skips the finished clips and retries only the broken one
    code = main(_args(str(inputs), "--out", str(out), "--mode", "robot-only", "--ray", "--workers", "1"))
    summary = json.loads((out / SUMMARY_NAME).read_text())
    assert code == 1 and summary["skipped"] == 2 and summary["failed"] == 1


def test_a_clip_whose_worker_dies_is_retried_once(corpus, serial_out, tmp_path):
    marker = tmp_path / "killed_once"

    def dies_on_first_attempt(job, task):
        from retarget.cli.batch import retarget_bytes

        if job.source.name == "walk_0.npz" and not marker.exists():
            marker.touch()
            os.kill(os.getpid(), signal.SIGKILL)
        return retarget_bytes(job, task)

    def always_dies(job, task):
        os.kill(os.getpid(), signal.SIGKILL)

    task = Task(load_config(mode="robot-only"))
    jobs = [Job(corpus / "walk_0.npz", tmp_path / "out" / "walk_0.npz")]
    executor = RayExecutor(None, workers=1)
    try:
        results = list(executor.run(jobs, task, task_fn=dies_on_first_attempt))
        assert marker.exists() and [r.status for r in results] == ["done"]
        assert_same_reference(tmp_path / "out" / "walk_0.npz", serial_out / "walk_0.npz")
        jobs = [Job(corpus / "walk_1.npz", tmp_path / "out" / "walk_1.npz")]
        results = list(executor.run(jobs, task, task_fn=always_dies))
        assert [r.status for r in results] == ["failed"] and "worker lost twice" in results[0].message
        assert not (tmp_path / "out" / "walk_1.npz").exists()
    finally:
        executor.close()
