"""``otr retarget``: configuration, batch behaviour (resume, failures, workers), bad inputs, and
the OMOMO large-box clip end to end."""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from otr_gym.reference import Reference
from retarget.checks.feasibility import check_feasibility
from retarget.cli.batch import SUMMARY_NAME
from retarget.cli.retarget import configure_parser, main
from retarget.clip import retarget_demonstration
from retarget.config import CONFIG_DIR, ConfigError, RetargetConfig, load_config

from clips import clip

EPS_COL = 3e-4


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    configure_parser(parser)
    return parser.parse_args(list(argv))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("demos")
    clip("walk", 40, 46).save(folder / "walk_a.npz")
    clip("walk", 60, 66).save(folder / "walk_b.npz")
    return folder


def test_default_yaml_mirrors_the_dataclass_defaults():
    assert load_config(CONFIG_DIR / "default.yaml") == RetargetConfig()


def test_unknown_config_key_is_named(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("solver:\n  iterationz: 3\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml\.solver': unknown keys \['iterationz'\]"):
        load_config(bad)


def test_unknown_link_grouping_is_named_with_the_choices(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("links_together: arms\n")
    with pytest.raises(ConfigError,
                       match=r"unknown links_together 'arms' \(choose from \['hand', 'none', 'shared_parts'\]\)"):
        load_config(bad)
    assert load_config(links_together="hand").links_together == "hand"


def test_link_clearances_are_checked_when_the_config_loads(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("solver:\n  link_clearance_m: {torso: 0.01}\n")
    with pytest.raises(ConfigError, match=r"unknown G1 link 'torso'"):
        load_config(bad)
    bad.write_text("solver:\n  link_clearance_m: {torso_link: -0.01}\n")
    with pytest.raises(ConfigError, match=r"'torso_link' must be a finite clearance >= 0 m, got -0.01"):
        load_config(bad)
    good = tmp_path / "good.yaml"
    good.write_text("solver:\n  link_clearance_m: {torso_link: 0.015}\n")
    assert load_config(good).solver.link_clearance_m == {"torso_link": 0.015}


def test_folder_is_retargeted_then_skipped_on_the_second_run(tiny, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(_args(str(tiny), "--out", str(out), "--mode", "robot-only")) == 0
    files = sorted(p.name for p in out.glob("*.npz"))
    assert files == ["walk_a.npz", "walk_b.npz"]
    ref = Reference.load(out / "walk_a.npz")
    assert ref.fps == 50.0 and ref.metadata["mode"] == "robot-only" and ref.metadata["scale"] == 1.0
    assert ref.metadata["config"]["interaction"]["robot_weights"] == [256.0, 625.0, 2500.0]
    assert ref.contacts.channel_names == ("ground",) and ref.contacts.distance.shape[1] == 30
    # the summary carries each clip's dynamic feasibility, as `otr verify` measures it on the file
    summary = json.loads((out / SUMMARY_NAME).read_text())
    clip = next(r for r in summary["results"] if r["output"].endswith("walk_a.npz"))
    report = check_feasibility(ref)
    assert clip["flagged_share"] == pytest.approx(report.flagged_share())
    brief = report.brief()
    assert clip["feasibility"]["verdict"] == brief["verdict"]
    assert clip["feasibility"]["frames_over"] == brief["frames_over"]
    assert clip["feasibility"]["torque_peak_ratio"] == pytest.approx(brief["torque_peak_ratio"])
    assert clip["feasibility"]["limb_jump_peak_m"] == pytest.approx(report.summary()["limb_jump"]["peak_m"])
    assert summary["feasible"] == sum(r["flagged_share"] == 0.0 for r in summary["results"])
    stamp = (out / "walk_a.npz").stat().st_mtime_ns
    capsys.readouterr()
    assert main(_args(str(tiny), "--out", str(out), "--mode", "robot-only")) == 0
    assert "2 of 2 outputs already exist: skipped" in capsys.readouterr().out
    assert (out / "walk_a.npz").stat().st_mtime_ns == stamp
    assert not list(out.glob("*.tmp"))


def test_a_failing_clip_is_reported_and_the_batch_goes_on_with_a_nonzero_exit(tiny, tmp_path, capsys):
    out = tmp_path / "out"
    missing = tmp_path / "nowhere.pt"
    unknown = tmp_path / "notes.txt"
    unknown.write_text("not a demonstration")
    code = main(_args(str(missing), str(unknown), str(tiny / "walk_a.npz"), "--out", str(out), "--mode", "robot-only"))
    err = capsys.readouterr().err
    assert code == 1
    assert f"{missing}: no such demonstration file" in err
    assert f"{unknown}: unknown demonstration format '.txt'" in err
    assert (out / "walk_a.npz").is_file() and not (out / "nowhere.npz").exists()


def test_two_workers_give_the_same_references_as_one(tiny, tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    assert main(_args(str(tiny), "--out", str(one), "--mode", "robot-only")) == 0
    assert main(_args(str(tiny), "--out", str(two), "--mode", "robot-only", "--workers", "2")) == 0
    # byte for byte: the portable ProxQP build makes a solve independent of the process's
    # allocation history (retarget/__init__.py; tests/test_determinism.py)
    for name in ("walk_a.npz", "walk_b.npz"):
        assert (one / name).read_bytes() == (two / name).read_bytes()


def test_scaled_mode_scales_the_human_and_pins_the_object():
    demo = clip("box_carry", 100, 104)
    ref = retarget_demonstration(demo, RetargetConfig(mode="scaled"))
    sc = 1.32 / demo.stature_m
    assert ref.metadata["scale"] == pytest.approx(sc) and ref.metadata["free_objects"] == []
    box = next(o for o in ref.objects if o.name == "box")
    src = next(o for o in demo.objects if o.name == "box")
    # pinned: horizontal track × sc, height scaled about the first frame's (a box resting on the
    # floor stays on it; OmniRetarget's convention); at 50 fps: first and last frames
    np.testing.assert_allclose(box.pos_w[[0, -1], :2], src.pos_w[[0, -1], :2] * sc, atol=1e-9)
    np.testing.assert_allclose(box.pos_w[0, 2], src.pos_w[0, 2], atol=1e-9)
    np.testing.assert_allclose(box.pos_w[-1, 2], src.pos_w[0, 2] + sc * (src.pos_w[-1, 2] - src.pos_w[0, 2]), atol=1e-9)


def test_omomo_clip_without_its_object_mesh_is_named(shared_data, tmp_path):
    clip_path = tmp_path / "sub3_largebox_003.pt"
    shutil.copy(shared_data / "omomo" / "sub3_largebox_003.pt", clip_path)
    code = main(_args(str(clip_path), "--out", str(tmp_path / "out")))
    assert code == 1
    wrong = tmp_path / "nothing.obj"
    code = main(_args(str(clip_path), "--out", str(tmp_path / "out"), "--object", str(wrong)))
    assert code == 1 and not (tmp_path / "out" / "sub3_largebox_003.npz").exists()


@pytest.mark.slow
def test_largebox_native_keeps_contacts_without_penetration_and_within_limits(shared_data, largebox_reference):
    """OMOMO sub3_largebox_003, box free, native scale (the figures quoted in the report)."""
    from otr_gym.reference import Reference
    from retarget.checks.verify import check_reference
    from retarget.inputs.readers import load_demonstration
    from retarget.solver.problem import resample_demonstration

    demo = load_demonstration(shared_data / "omomo" / "sub3_largebox_003.pt", shared_data / "objects" / "largebox.obj")
    ref = Reference.load(largebox_reference)
    checks = check_reference(ref, resample_demonstration(demo, ref.fps))
    print(dataclasses.asdict(checks), ref.metadata["solver"])
    assert ref.contacts.distance.min() >= -EPS_COL  # probes, every link and channel
    # exact, visual-mesh vertices vs the scanned box; the grasp pass squeezes the hands' collision
    # boxes 8 mm into the box's faces, which takes the hands' meshes below 1 mm into the scan
    assert ref.metadata["grasp"]["holds"] and not ref.metadata["grasp"]["holds"][0]["kept"]
    assert checks.object_penetration_mesh_m <= 1e-3
    assert checks.ground_penetration_mesh_m <= EPS_COL
    assert checks.joint_limit_excess_rad <= 1e-6 and checks.joint_speed_ratio <= 1.0 + 1e-6  # QP bounds to rounding
    assert checks.hand_contact_frames > 300 and checks.hand_hold >= 0.95
    assert checks.object_min_height_m >= -EPS_COL


def test_verify_cli_prints_the_checks_of_a_retargeted_walk(tiny, tmp_path, capsys):
    from otr_gym import cli

    out = tmp_path / "out"
    assert main(_args(str(tiny / "walk_a.npz"), "--out", str(out))) == 0
    capsys.readouterr()
    assert cli.main(["verify", str(out / "walk_a.npz"), "--demo", str(tiny / "walk_a.npz")]) == 0
    rows = dict(line.split(None, 1) for line in capsys.readouterr().out.splitlines())
    assert rows["ground_penetration_mesh_m"].split()[1] == "ok"
    assert float(rows["ground_penetration_mesh_m"].split()[0]) <= EPS_COL
    assert 0.0 < float(rows["joint_speed_ratio"]) <= 1.0
    assert int(rows["frames"]) == Reference.load(out / "walk_a.npz").num_frames
