"""benchmarks/feasibility_corpus.py: its table carries check_feasibility's numbers per clip, from a
folder of references or from the summary that ``otr retarget`` writes, and counts the clips that
meet issue 52's targets."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from otr_gym import robot
from otr_gym.reference import Reference
from retarget.checks.feasibility import check_feasibility
from retarget.cli.batch import ClipResult, summary

from conftest import load_benchmark

FPS = 50.0


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("feasibility_corpus")


@pytest.fixture(scope="module")
def references(tmp_path_factory):
    """Two 30-frame references: the robot standing still, and the same with the whole robot
    teleported 6 cm sideways for one frame (pelvis, feet and hands jump)."""
    folder = tmp_path_factory.mktemp("refs")
    stand = np.tile(robot.default_qpos(), (30, 1))
    teleport = stand.copy()
    teleport[15, 1] += 0.06
    paths = {}
    for name, qpos in (("stand", stand), ("teleport", teleport)):
        paths[name] = Reference.from_qpos(qpos, FPS).save(folder / f"{name}.npz")
    return folder, paths


@pytest.fixture(scope="module")
def reports(references):
    _, paths = references
    return {name: check_feasibility(Reference.load(path)) for name, path in paths.items()}


def _expected(report) -> dict:
    over = report.frames_over()
    return {"frames": report.num_frames, "flagged_share": report.flagged_share(),
            "limb_jump_peak_m": report.limb_jump_m.max(), "limb_jump_frames": over["limb jump"],
            "pelvis_jump_frames": over["jump"], "torque_peak_ratio": report.torque_ratio.max(),
            "torque_frames": over["torque"], "unsupported_frames": over["unsupported"],
            "sliding_frames": over["sliding"]}


def _measures(row) -> dict:
    return {key: value for key, value in dataclasses.asdict(row).items() if key not in ("clip", "verdict")}


def test_a_folder_of_references_gives_check_feasibilitys_numbers_per_clip(bench, references, reports):
    folder, _ = references
    rows, failed = bench.rows_from_references(folder)
    assert failed == [] and [r.clip for r in rows] == ["stand", "teleport"]
    for row in rows:
        assert _measures(row) == pytest.approx(_expected(reports[row.clip]))
    teleport = rows[1]
    assert teleport.limb_jump_peak_m == pytest.approx(0.06, abs=0.005)  # the jump is measured, not a zero row
    assert teleport.pelvis_jump_frames > 0 and teleport.limb_jump_frames > 0


def test_a_retarget_summary_gives_the_same_rows_and_names_the_failed_clips(bench, references, reports, tmp_path):
    _, paths = references
    stand = reports["stand"]
    results = [
        ClipResult("corpus/stand.pt", str(paths["stand"]), "done", frames=stand.num_frames,
                   flagged_share=stand.flagged_share(), feasibility=stand.brief()),
        # a resumed batch lists a finished clip as skipped: its reference is checked from the file
        ClipResult("corpus/teleport.pt", str(paths["teleport"]), "skipped"),
        ClipResult("corpus/sub8_monitor_000.pt", str(tmp_path / "sub8_monitor_000.npz"), "failed",
                   "corpus/sub8_monitor_000.pt: DemonstrationFileNotFoundError: object mesh not found\ntraceback"),
    ]
    path = tmp_path / "retarget_summary.json"
    path.write_text(json.dumps(summary(results, "serial", 1.0)))
    rows, failed = bench.rows_from_summaries([path])
    assert [r.clip for r in rows] == ["stand", "teleport"]
    for row in rows:
        assert _measures(row) == pytest.approx(_expected(reports[row.clip]))
    assert failed == [bench.FailedClip("sub8_monitor_000",
                                       "corpus/sub8_monitor_000.pt: DemonstrationFileNotFoundError: "
                                       "object mesh not found")]


def test_the_summary_counts_the_clips_meeting_each_target(bench, references):
    folder, _ = references
    rows, _ = bench.rows_from_references(folder)
    stand, teleport = rows
    assert stand.meets_targets == {"flagged": True, "torque": True, "limb jump": True}
    assert not teleport.meets_targets["limb jump"] and not teleport.meets_targets["flagged"]
    result = bench.corpus_summary(rows)
    assert result["meeting"] == {"flagged": 1, "torque": 2, "limb jump": 1, "all": 1}
    assert result["limb_jump_peak_m"]["worst_clip"] == "teleport"
    assert result["flagged_share"]["median"] == pytest.approx((stand.flagged_share + teleport.flagged_share) / 2)


def test_the_markdown_table_and_the_json_carry_the_rows(bench, references, tmp_path, capsys):
    folder, _ = references
    out = tmp_path / "corpus.json"
    assert bench.main(["--references", str(folder), "--markdown", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    data = json.loads(out.read_text())
    teleport = next(r for r in data["rows"] if r["clip"] == "teleport")
    line = next(line for line in printed.splitlines() if line.startswith("| teleport |"))
    assert line.split(" | ")[3] == f"{100 * teleport['limb_jump_peak_m']:.1f}"
    assert printed.splitlines()[0].startswith("| clip | frames | flag % |")
    assert "all three 1/2" in printed
    assert data["summary"]["clips"] == 2 and data["failed"] == []


def test_a_folder_without_references_is_a_clear_error(bench, tmp_path):
    with pytest.raises(SystemExit, match="holds no .npz references"):
        bench.main(["--references", str(tmp_path)])
