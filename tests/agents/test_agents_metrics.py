"""Evaluation bookkeeping on hand-made numbers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agents.evaluate import format_clip_table
from agents.metrics import EpisodeAccumulator, summarize


def test_frames_after_an_envs_first_episode_end_are_ignored():
    acc = EpisodeAccumulator(3)
    false, true = torch.zeros(3, dtype=torch.bool), torch.ones(3, dtype=torch.bool)
    acc.add_frame(torch.tensor([0.010, 0.020, 0.030]))
    acc.end_step(terminated=torch.tensor([True, False, False]), truncated=false)  # env 0 falls
    acc.add_frame(torch.tensor([9.0, 0.040, 0.050]))  # env 0 is resetting: its 9 m must not count
    acc.end_step(terminated=false, truncated=torch.tensor([False, True, False]))  # env 1 completes its clip
    acc.add_frame(torch.tensor([9.0, 9.0, 0.070]))
    acc.end_step(terminated=true, truncated=false)  # later ends of envs 0, 1 do not count; env 2 falls
    out = acc.per_env()
    assert out["frames"].tolist() == [1, 2, 3]
    np.testing.assert_allclose(out["mpjpe_mm"], [10.0, 30.0, 50.0])
    assert out["success"].tolist() == [False, True, False]
    assert acc.all_finished


def test_an_env_still_running_when_evaluation_stops_is_not_a_success():
    acc = EpisodeAccumulator(1)
    acc.add_frame(torch.tensor([0.01]))
    assert not acc.all_finished
    assert acc.per_env()["success"].tolist() == [False]


def test_summary_is_frame_weighted_per_clip_and_overall():
    per_env = {"success": np.array([True, False, True]), "mpjpe_mm": np.array([10.0, 100.0, 20.0]),
               "frames": np.array([300, 100, 100])}
    out = summarize(per_env, clip_ids=np.array([0, 0, 1]), clip_names=["walk", "run"])
    walk, run = out["clips"]
    assert walk["clip"] == "walk" and walk["envs"] == 2 and walk["success_rate"] == 0.5
    assert walk["mpjpe_mm"] == pytest.approx((10 * 300 + 100 * 100) / 400)
    assert run["mpjpe_mm"] == pytest.approx(20.0) and run["success_rate"] == 1.0
    assert out["success_rate"] == pytest.approx(2 / 3)
    assert out["mpjpe_mm"] == pytest.approx((10 * 300 + 100 * 100 + 20 * 100) / 500)
    assert out["frames"] == 500 and out["envs"] == 3


def test_heading_aligned_diagnostic_is_accumulated_and_frame_weighted_beside_mpjpe():
    acc = EpisodeAccumulator(2)
    acc.add_frame(torch.tensor([0.05, 0.02]), heading_aligned_m=torch.tensor([0.03, 0.02]))
    acc.add_frame(torch.tensor([0.07, 0.02]), heading_aligned_m=torch.tensor([0.05, 0.02]))
    out = acc.per_env()
    np.testing.assert_allclose(out["mpjpe_mm"], [60.0, 20.0])
    np.testing.assert_allclose(out["mpjpe_heading_aligned_mm"], [40.0, 20.0])
    summary = summarize(out, clip_ids=np.array([0, 0]), clip_names=["jog"])
    assert summary["mpjpe_heading_aligned_mm"] == pytest.approx(30.0)
    assert summary["clips"][0]["mpjpe_heading_aligned_mm"] == pytest.approx(30.0)
    assert summary["mpjpe_mm"] == pytest.approx(40.0)


def test_the_terminations_that_end_each_episode_are_counted_per_clip():
    acc = EpisodeAccumulator(4)
    no = torch.zeros(4, dtype=torch.bool)
    acc.add_frame(torch.full((4,), 0.01))
    fired = {"anchor_height": torch.tensor([True, False, False, False]),
             "ee_height": torch.tensor([True, True, False, False])}
    acc.end_step(terminated=torch.tensor([True, True, False, False]), truncated=no, fired=fired)
    acc.add_frame(torch.full((4,), 0.01))
    # envs 0 and 1 already ended: their later terminations must not count; env 2 completes the clip
    later = {"anchor_height": torch.tensor([True, True, False, True]),
             "ee_height": torch.tensor([True, True, False, True])}
    acc.end_step(terminated=torch.tensor([True, True, False, True]),
                 truncated=torch.tensor([False, False, True, False]), fired=later)
    out = acc.per_env()
    assert out["ended_by"]["anchor_height"].tolist() == [True, False, False, True]
    assert out["ended_by"]["ee_height"].tolist() == [True, True, False, True]
    summary = summarize(out, clip_ids=np.array([0, 0, 1, 1]), clip_names=["jog", "squat"])
    jog, squat = summary["clips"]
    assert jog["ended_by"] == {"anchor_height": 1, "ee_height": 2}
    assert squat["ended_by"] == {"anchor_height": 1, "ee_height": 1}
    assert summary["ended_by"] == {"anchor_height": 2, "ee_height": 3}
    assert out["success"].tolist() == [False, False, True, False]
    table = format_clip_table(summary["clips"]).splitlines()
    assert table[1].endswith("ended by anchor_height 1, ee_height 2") and "ended by" in table[2]
