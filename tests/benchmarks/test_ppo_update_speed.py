"""benchmarks/ppo_update_speed.py: every mode times real PPO updates under the setting it names,
and its table compares them against the first row."""

from __future__ import annotations

import math

import pytest

from conftest import load_benchmark

SMALL = {"device": "cpu", "num_envs": 64, "steps": 4, "epochs": 1, "mini_batches": 2, "updates": 1}


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("ppo_update_speed")


def test_float32_and_bfloat16_updates_are_timed_and_move_the_weights(bench):
    fp32, bf16 = bench.measure("fp32", **SMALL), bench.measure("bf16", **SMALL)
    assert fp32["settings"] == {"tf32_matmul": False, "use_mixed_precision": False, "compiled": False}
    assert bf16["settings"]["use_mixed_precision"] and not bf16["settings"]["compiled"]
    for row in (fp32, bf16):
        assert row["update_s"] > 0 and row["rollout_s"] > 0 and row["warmup_update_s"] > 0
        assert row["mini_batch_ms"] == pytest.approx(1e3 * row["update_s"] / 2)
        assert row["actor_weight_change"] > 0  # the timed update stepped Adam
        assert set(row["losses"]) >= {"value", "surrogate", "entropy"}
        assert all(math.isfinite(v) for v in row["losses"].values())
    lines = bench.table([fp32, bf16]).splitlines()
    assert lines[2].startswith("| fp32 |") and "| 1.00x |" in lines[2] and lines[3].startswith("| bf16 |")


def test_modes_map_onto_the_training_config(bench):
    assert bench.mode_config("tf32", 8, 24, 10, 4).tf32_matmul
    compiled = bench.mode_config("compile", 8, 24, 10, 4)
    assert compiled.torch_compile_mode == "default" and compiled.algorithm.num_learning_epochs == 10
    assert bench.mode_config("bf16", 8, 24, 5, 4).algorithm.use_mixed_precision
    with pytest.raises(KeyError, match="'fp16'"):
        bench.mode_config("fp16", 8, 24, 5, 4)
