"""``otr score`` (``retarget.cli.score``): what it refuses and what it writes when a reference and
its demonstration do not belong together."""

from __future__ import annotations

from argparse import ArgumentParser

import numpy as np
import pytest

from otr_gym import robot
from otr_gym.reference import Reference
from retarget.cli.score import configure_parser, main, source_mismatch
from retarget.inputs.demonstration import Demonstration

from clips import tpose

FRAMES_50HZ = 16  # 0.3 s, the demonstration's duration


def _parse(argv):
    p = ArgumentParser()
    configure_parser(p)
    return p.parse_args(argv)


@pytest.fixture(scope="module")
def tpose_demo() -> Demonstration:
    """The human standing still in the T-pose for 0.3 s at 30 fps (``clips.tpose``)."""
    return tpose({"format": "synthetic", "path": "tpose-demo"})


def g1_tpose(frames: int = FRAMES_50HZ, metadata: dict | None = None) -> Reference:
    """The G1 standing still in its T-pose at 50 fps, with the given metadata."""
    from retarget.inputs.human import g1_tpose_qpos

    return Reference.from_qpos(np.tile(g1_tpose_qpos(), (frames, 1)), fps=50.0, metadata=metadata or {})


def made_from(name: str, **source) -> dict:
    """Metadata of a reference of ours made from the demonstration ``name`` (``retarget.clip``)."""
    return {"mode": "native", "scale": 1.0, "source": {"name": name, "format": "synthetic", **source}}


# ------------------------------------------------------------------ durations and the JSON


def test_another_duration_fails_naming_both_files_and_durations_and_writes_no_json(tmp_path, tpose_demo, capsys):
    demo = tpose_demo.save(tmp_path / "tpose.npz")
    long = g1_tpose(frames=100).save(tmp_path / "long.npz")
    out = tmp_path / "score.json"
    assert main(_parse([str(long), "--demo", str(demo), "--json", str(out), "--no-progress"])) == 1
    err = capsys.readouterr().err
    assert "long.npz" in err and "tpose.npz" in err
    assert "1.980 s" in err and "0.300 s" in err
    assert not out.exists()
    assert f"{out} not written" in err


def test_a_failure_beside_a_score_is_kept_in_the_json(tmp_path, tpose_demo):
    import json

    demo = tpose_demo.save(tmp_path / "tpose.npz")
    good = g1_tpose().save(tmp_path / "good.npz")
    long = g1_tpose(frames=100).save(tmp_path / "long.npz")
    out = tmp_path / "score.json"
    assert main(_parse([str(good), str(long), "--demo", str(demo), "--scale", "1", "--json", str(out),
                        "--no-progress"])) == 1
    payload = json.loads(out.read_text())
    assert [s["reference"] for s in payload["sequences"]] == [str(good)]
    assert [f["reference"] for f in payload["failures"]] == [str(long)]


# ------------------------------------------------------------------ the demonstration a reference was made from


def test_a_reference_of_another_demonstration_is_refused_naming_both(tmp_path, tpose_demo, capsys):
    demo = tpose_demo.save(tmp_path / "tpose.npz")
    ref = g1_tpose(metadata=made_from("someone_else")).save(tmp_path / "someone_else_g1.npz")
    out = tmp_path / "score.json"
    assert main(_parse([str(ref), "--demo", str(demo), "--scale", "1", "--json", str(out), "--no-progress"])) == 2
    err = capsys.readouterr().err
    assert f"{ref} was made from another demonstration than {demo}" in err
    assert "name 'someone_else' vs 'tpose'" in err and "--allow-other-demo" in err
    assert not out.exists()


def test_the_override_scores_a_reference_of_another_demonstration(tmp_path, tpose_demo):
    demo = tpose_demo.save(tmp_path / "tpose.npz")
    ref = g1_tpose(metadata=made_from("someone_else")).save(tmp_path / "someone_else_g1.npz")
    assert main(_parse([str(ref), "--demo", str(demo), "--scale", "1", "--allow-other-demo", "--no-progress"])) == 0


def test_a_reference_of_this_demonstration_is_scored(tmp_path, tpose_demo):
    demo = tpose_demo.save(tmp_path / "tpose.npz")
    ref = g1_tpose(metadata=made_from("tpose")).save(tmp_path / "tpose_g1.npz")
    assert main(_parse([str(ref), "--demo", str(demo), "--scale", "1", "--no-progress"])) == 0


def test_a_scaled_reference_of_another_stature_is_a_mismatch(tpose_demo):
    taller = tpose_demo.stature_m + 0.04
    ref = g1_tpose(metadata={**made_from("tpose"), "mode": "scaled", "scale": robot.HEIGHT_M / taller})
    assert source_mismatch(ref, tpose_demo) == f"stature {taller:.3f} m vs {tpose_demo.stature_m:.3f} m"
    same = g1_tpose(metadata={**made_from("tpose"), "mode": "scaled", "scale": robot.HEIGHT_M / tpose_demo.stature_m})
    assert source_mismatch(same, tpose_demo) is None


def test_another_format_is_a_mismatch_and_another_path_is_not(tpose_demo):
    assert source_mismatch(g1_tpose(metadata=made_from("tpose", format="bvh")), tpose_demo) == \
        "format 'bvh' vs 'synthetic'"
    assert source_mismatch(g1_tpose(metadata=made_from("tpose", path="/elsewhere/tpose.npz")), tpose_demo) is None


def test_a_reference_without_a_recorded_source_is_not_checked(tpose_demo):
    assert source_mismatch(g1_tpose(), tpose_demo) is None


# ------------------------------------------------------------------ dynamic feasibility beside the scores


def test_each_scored_reference_carries_its_flagged_frame_share(tmp_path, tpose_demo, capsys):
    """A G1 standing still is feasible; the same reference gliding sideways at 1 m/s slides its
    stance feet on every frame: the JSON and the printed verdicts say so per reference."""
    import json

    from retarget.checks.feasibility import check_feasibility

    demo = tpose_demo.save(tmp_path / "tpose.npz")
    still = g1_tpose().save(tmp_path / "still.npz")
    qpos = g1_tpose().qpos()
    qpos[:, 1] += 1.0 * np.arange(len(qpos)) / 50.0
    glide = Reference.from_qpos(qpos, fps=50.0).save(tmp_path / "glide.npz")
    out = tmp_path / "score.json"
    assert main(_parse([str(still), str(glide), "--demo", str(demo), "--scale", "1", "--json", str(out),
                        "--no-progress"])) == 0
    records = {s["name"]: s["feasibility"] for s in json.loads(out.read_text())["sequences"]}
    assert records["still"]["flagged_share"] == 0.0 and records["still"]["verdict"].startswith("verdict: feasible")
    expected = check_feasibility(Reference.load(glide))
    assert expected.flagged_share() > 0.5
    assert records["glide"]["flagged_share"] == pytest.approx(expected.flagged_share())
    assert records["glide"]["frames_over"]["sliding"] == expected.frames_over()["sliding"] > 0
    printed = capsys.readouterr().out
    assert f"glide: {expected.verdict().removeprefix('verdict: ')}" in printed and "still: feasible" in printed
