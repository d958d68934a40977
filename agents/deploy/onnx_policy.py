"""An exported policy (``otr export --onnx``) run with onnxruntime for one observation at a time.

One thread, sequential execution: a 50 Hz loop wants a steady few-hundred-µs inference, not a
thread pool waking up on a 2-core computer that also runs the robot simulation.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from agents.deploy.observation import PolicySpec, PolicySpecError
from otr_gym import robot


class OnnxPolicy:
    """``policy(obs (D,) float32) -> action (29,) float32``; ``last_ns``: how long the last run took."""

    def __init__(self, path: str | Path, spec: PolicySpec):
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        self.path = Path(path)
        self.last_ns = 0
        self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        inputs = {i.name: i.shape for i in self.session.get_inputs()}
        outputs = {o.name: o.shape for o in self.session.get_outputs()}
        if "obs" not in inputs or "actions" not in outputs:
            raise PolicySpecError(f"{path}: expects input 'obs' and output 'actions', has {list(inputs)} -> "
                                  f"{list(outputs)}")
        dim, acts = inputs["obs"][-1], outputs["actions"][-1]
        if isinstance(dim, int) and dim != spec.observation_dim:
            raise PolicySpecError(f"{path}: input 'obs' has {dim} values, the metadata's layout {spec.observation_dim}")
        if isinstance(acts, int) and acts != robot.NUM_JOINTS:
            raise PolicySpecError(f"{path}: output 'actions' has {acts} values, the G1 has {robot.NUM_JOINTS} joints")

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        start = time.perf_counter_ns()
        x = np.ascontiguousarray(obs, dtype=np.float32)[None]
        action = self.session.run(["actions"], {"obs": x})[0][0]
        self.last_ns = time.perf_counter_ns() - start
        return action
