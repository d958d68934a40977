"""Helpers for the deployment tests: policies written as ONNX with the export's metadata, and
the two processes of a loopback sim2sim run (``otr sim-robot`` and ``otr deploy``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper

from agents.deploy.reference_policy import reference_policy_model

REPO = Path(__file__).resolve().parents[1]


def domain_id(k: int) -> int:
    """A DDS domain per test (k < 12) and per pytest process, so that concurrent runs on one
    machine never share a loopback domain (CycloneDDS accepts ids up to 232)."""
    if not 0 <= k < 12:
        raise ValueError(f"domain_id: k must be in [0, 12), got {k}")
    return 1 + (os.getpid() % 19) * 12 + k


def save_with_metadata(model: onnx.ModelProto, meta: dict, path: Path) -> Path:
    for key, value in meta.items():
        model.metadata_props.add(key=key, value=json.dumps(value))
    onnx.checker.check_model(model)
    path.write_bytes(model.SerializeToString())
    return path


def feedback_policy(meta: dict, path: Path, gain: float = 0.05, seed: int = 0) -> Path:
    """The reference policy plus a small term of every observation value,
    a = (q_ref − q_default)/scale + gain·tanh(W·obs), W ~ N(0, 1/D): stays near the reference
    (stiff gains keep the G1 up) but its action depends on the whole observation, so a
    replay must rebuild every observation exactly to reproduce it."""
    base = reference_policy_model(meta)
    D = int(meta["observation_dim"])
    W = np.random.default_rng(seed).standard_normal((D, 29)).astype(np.float32) / np.sqrt(D)
    g = base.graph
    g.output[0].name = "reference_actions"
    g.node[-1].output[0] = "reference_actions"
    g.initializer.extend([helper.make_tensor("W", TensorProto.FLOAT, [D, 29], W.ravel().tolist()),
                          helper.make_tensor("gain", TensorProto.FLOAT, [], [gain])])
    g.node.extend([helper.make_node("MatMul", ["obs", "W"], ["mixed"]),
                   helper.make_node("Tanh", ["mixed"], ["squashed"]),
                   helper.make_node("Mul", ["squashed", "gain"], ["feedback"]),
                   helper.make_node("Add", ["reference_actions", "feedback"], ["actions"])])
    del g.output[:]
    g.output.append(helper.make_tensor_value_info("actions", TensorProto.FLOAT, ["batch", 29]))
    return save_with_metadata(base, meta, path)


def nan_policy(meta: dict, path: Path) -> Path:
    """actions = obs[:, :29] · NaN: NaN from the first call."""
    D = int(meta["observation_dim"])
    graph = helper.make_graph(
        [helper.make_node("Slice", ["obs", "s", "e", "a"], ["head"]),
         helper.make_node("Mul", ["head", "nan"], ["actions"])],
        "nan_policy", [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", D])],
        [helper.make_tensor_value_info("actions", TensorProto.FLOAT, ["batch", 29])],
        [helper.make_tensor("s", TensorProto.INT64, [1], [0]), helper.make_tensor("e", TensorProto.INT64, [1], [29]),
         helper.make_tensor("a", TensorProto.INT64, [1], [1]),
         helper.make_tensor("nan", TensorProto.FLOAT, [], [np.nan])])
    return save_with_metadata(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)]), meta, path)


def otr(*args: str, **kwargs) -> subprocess.Popen:
    """``python -m otr_gym.cli ARGS`` in a child process (this checkout's code)."""
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-m", "otr_gym.cli", *args], env=env, cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kwargs)


def finish(proc: subprocess.Popen, timeout: float) -> tuple[int, str]:
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        raise AssertionError(f"{proc.args} did not finish in {timeout} s:\n{out}") from None
    return proc.returncode, out
