"""``otr retarget`` over a corpus folder: six short clips (three walks, a truncated file, one with
a NaN, a BVH of an unknown skeleton) give three references and three failures named with their
file and problem; a resumed batch leaves the three alone and keeps their figures; the filter
writes the list ``otr train --reference`` reads; a clip that kills its worker process is a
named failure while the others finish."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest

from otr_gym.reference import Reference, list_references
from retarget.cli.batch import SUMMARY_NAME, Job, Task, run_job
from retarget.cli.clip_list import PASSING_NAME
from retarget.cli.executors import ProcessExecutor
from retarget.cli.retarget import configure_parser, main
from retarget.config import load_config

from clips import clip

WALKS = ("walk_0.npz", "walk_1.npz", "walk_2.npz")
#: the bad files and a piece of the problem their failure must name
BAD = {"truncated.npz": "not a NumPy .npz archive", "nan.npz": "part_pos_w contains NaN/inf",
       "unknown.bvh": "skeleton not recognised (joints: bone_0, bone_1)"}

UNKNOWN_SKELETON_BVH = """HIERARCHY
ROOT bone_0
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT bone_1
  {
    OFFSET 0 10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 10 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.033333
0 90 0 0 0 0 0 0 0
0 90 0 0 0 0 0 0 0
"""


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    configure_parser(parser)
    return parser.parse_args(list(argv))


def _run(*argv: str) -> tuple[int, str, str]:
    """``otr retarget`` in this process: exit code, stdout, stderr (the bars and the failures)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(_args(*argv, "--mode", "robot-only"))
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Path:
    """Three 10-frame walks (30 fps) and three bad files, built here."""
    folder = tmp_path_factory.mktemp("corpus")
    for name, start in zip(WALKS, (40, 55, 70)):
        clip("walk", start, start + 10).save(folder / name)
    whole = (folder / "walk_0.npz").read_bytes()
    (folder / "truncated.npz").write_bytes(whole[: len(whole) // 2])  # a download cut short
    with np.load(folder / "walk_0.npz") as walk:
        arrays = {key: walk[key] for key in walk.files}
    arrays["part_pos_w"] = arrays["part_pos_w"].copy()
    arrays["part_pos_w"][3, 5, 2] = np.nan
    np.savez(folder / "nan.npz", **arrays)
    (folder / "unknown.bvh").write_text(UNKNOWN_SKELETON_BVH)
    return folder


@pytest.fixture(scope="module")
def first_run(corpus, tmp_path_factory) -> tuple[Path, int, str, dict]:
    """The corpus retargeted once: output folder, exit code, stderr and the summary as written then."""
    out = tmp_path_factory.mktemp("refs")
    code, _, err = _run(str(corpus), "--out", str(out))
    return out, code, err, json.loads((out / SUMMARY_NAME).read_text())


def _by_name(summary: dict) -> dict[str, dict]:
    return {Path(r["source"]).name: r for r in summary["results"]}


def test_a_corpus_gives_the_three_references_and_names_the_three_failures(corpus, first_run):
    out, code, err, summary = first_run
    assert code == 1
    assert sorted(p.name for p in out.glob("*.npz")) == list(WALKS)
    assert (summary["clips"], summary["done"], summary["failed"], summary["skipped"]) == (6, 3, 3, 0)
    records = _by_name(summary)
    for name, problem in BAD.items():
        assert records[name]["status"] == "failed"
        assert records[name]["message"].startswith(f"{corpus / name}: ") and problem in records[name]["message"]
        assert f"FAILED {corpus / name}: " in err
    assert not list(out.glob(".*.tmp*"))  # atomic writes leave no partial file


def test_the_summary_carries_each_clips_feasibility_and_contact_figures(first_run):
    out, _, _, summary = first_run
    for name in WALKS:
        record = _by_name(summary)[name]
        reference = Reference.load(out / name)
        solver = reference.metadata["solver"]
        assert record["status"] == "done" and 0.0 <= record["flagged_share"] <= 1.0
        assert record["feasibility"]["flagged_share"] == record["flagged_share"]
        assert record["feasibility"]["limb_jump_peak_m"] >= 0.0 and record["feasibility"]["torque_peak_ratio"] > 0.0
        fidelity = record["fidelity"]
        assert fidelity["min_distance_m"] == solver["min_distance_m"]
        assert fidelity["penetration_m"] == max(0.0, -solver["min_distance_m"])
        assert fidelity["qp_failures"] == solver["qp_failures"]
        on_ground = (reference.contacts.distance[:, :, 0] < 0.02).any(axis=1).mean()
        assert fidelity["contact_share"] == {"ground": pytest.approx(on_ground)}


def test_the_bar_shows_clips_per_minute_and_the_eta(first_run):
    err = first_run[2]
    assert "clips/min" in err and "ETA" in err and "6/6 clips" in err


def test_a_resumed_corpus_skips_the_three_untouched_and_keeps_their_figures(corpus, first_run):
    out, _, _, before = first_run
    stamps = {name: ((out / name).stat().st_mtime_ns, (out / name).read_bytes()) for name in WALKS}
    code, stdout, _ = _run(str(corpus), "--out", str(out))
    summary = json.loads((out / SUMMARY_NAME).read_text())
    assert code == 1 and "3 of 6 outputs already exist: skipped" in stdout
    assert (summary["done"], summary["failed"], summary["skipped"]) == (0, 3, 3)
    for name in WALKS:
        record, earlier = _by_name(summary)[name], _by_name(before)[name]
        assert record["status"] == "skipped"
        assert (out / name).stat().st_mtime_ns == stamps[name][0] and (out / name).read_bytes() == stamps[name][1]
        for key in ("frames", "flagged_share", "feasibility", "fidelity"):
            assert record[key] == earlier[key], key


def test_without_its_summary_a_resume_measures_the_figures_on_the_references(first_run, corpus, tmp_path):
    out, _, _, before = first_run
    for name in WALKS:
        shutil.copy2(out / name, tmp_path / name)
    _run(str(corpus), "--out", str(tmp_path))
    records = _by_name(json.loads((tmp_path / SUMMARY_NAME).read_text()))
    for name in WALKS:
        assert records[name]["status"] == "skipped"
        assert records[name]["flagged_share"] == _by_name(before)[name]["flagged_share"]
        assert records[name]["fidelity"]["contact_share"] == _by_name(before)[name]["fidelity"]["contact_share"]


def test_the_filter_lists_the_references_under_the_bound_for_otr_train(corpus, first_run):
    out, _, _, before = first_run
    shares = sorted((_by_name(before)[name]["flagged_share"], name) for name in WALKS)
    assert shares[0][0] < shares[1][0] < shares[2][0]  # the bound below splits them
    bound = shares[1][0]
    code, stdout, _ = _run(str(corpus), "--out", str(out), "--max-flagged", str(bound))
    assert code == 1 and f"2 of 6 clips pass --max-flagged {bound:g}" in stdout
    expected = sorted(out / name for _, name in shares[:2])
    assert list_references(out / PASSING_NAME) == expected  # what `otr train --reference LIST` reads
    _run(str(corpus), "--out", str(out), "--max-flagged", "0")
    assert not [line for line in (out / PASSING_NAME).read_text().splitlines() if not line.startswith("#")]


def test_a_share_outside_zero_to_one_is_refused(corpus, tmp_path, capsys):
    assert main(_args(str(corpus), "--out", str(tmp_path), "--max-flagged", "2")) == 2
    assert "--max-flagged is a share of frames in [0, 1], got 2.0" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_clips_an_executor_leaves_when_it_breaks_are_named_failed(corpus, tmp_path, monkeypatch):
    class LostCluster:
        name = "Ray (cluster 10.0.0.1:6379)"

        def run(self, jobs, task):
            raise ConnectionError("lost the head node")
            yield

        def close(self) -> None:
            pass

    monkeypatch.setattr("retarget.cli.retarget.make_executor", lambda args: LostCluster())
    code, _, err = _run(str(corpus / "walk_0.npz"), str(corpus / "walk_1.npz"), "--out", str(tmp_path), "--ray")
    records = _by_name(json.loads((tmp_path / SUMMARY_NAME).read_text()))
    assert code == 1 and set(records) == {"walk_0.npz", "walk_1.npz"}
    for name, record in records.items():
        assert record["status"] == "failed"
        assert record["message"] == (f"{corpus / name}: not retargeted: Ray (cluster 10.0.0.1:6379) stopped "
                                     "(ConnectionError: lost the head node)")


def _dies_on_crash_clips(job: Job, task: Task, frame_bar: bool = False):
    """``run_job``, except that a clip named crash* kills its worker process (as the OOM killer would)."""
    if job.source.name.startswith("crash"):
        os.kill(os.getpid(), signal.SIGKILL)
    return run_job(job, task)


def test_a_clip_that_kills_its_worker_is_failed_by_name_and_the_others_finish(corpus, tmp_path):
    crash = tmp_path / "crash.npz"
    shutil.copy(corpus / "walk_0.npz", crash)
    jobs = [Job(crash, tmp_path / "out" / "crash.npz"), Job(corpus / "walk_1.npz", tmp_path / "out" / "walk_1.npz"),
            Job(corpus / "walk_2.npz", tmp_path / "out" / "walk_2.npz")]
    results = list(ProcessExecutor(2).run(jobs, Task(load_config(mode="robot-only")), task_fn=_dies_on_crash_clips))
    status = {Path(r.source).name: r.status for r in results}
    assert status == {"crash.npz": "failed", "walk_1.npz": "done", "walk_2.npz": "done"}
    lost = next(r for r in results if r.status == "failed")
    assert lost.message.startswith(f"{crash}: its worker process died (signal SIGKILL")
    assert sorted(p.name for p in (tmp_path / "out").glob("*.npz")) == ["walk_1.npz", "walk_2.npz"]
