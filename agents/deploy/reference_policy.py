"""A stand-in policy for sim2sim before a trained one is at hand: it plays the reference.

``otr reference-policy policy.onnx`` writes an ONNX graph with the same
input, output and metadata as ``otr export --onnx`` (the observation layout of the training
env's default actor, built by that env), whose action is the reference's joint targets read
from the observation's ``command`` term: a = (q_ref − q_default) / action_scale. It therefore
flows through the deployment runner unchanged (observation rebuild, clip, soft limits, DDS).

It is open loop: nothing in it balances. With the training gains (kp = J·ω², ω = 2π·10 rad/s)
an open-loop pose topples in about 1.3 s (``tests/test_env_tracking.py``), so its metadata
carries the stiff start-up gains of docs/environment.md §9 instead; with them the G1 follows references
that keep both feet on the ground (``otr procedural sway``), not a walk.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper

from agents.deploy.safety import STARTUP_KD, STARTUP_KP
from agents.export import FORMAT, OPSET
from otr_gym import robot
from otr_gym.io import atomic_path


def training_metadata(reference, task_id: str = "OTR-G1-Track-v0", env: dict | None = None) -> dict:
    """The metadata ``otr export`` would write for a policy trained on ``task_id``'s env (its
    default config with the ``env`` overrides; without the checkpoint fields), taken from the
    env itself."""
    from envs.config import BOX_TASK, load_env_config

    cfg = load_env_config(task_id, overrides=env)
    if task_id == BOX_TASK:
        from envs.box import make_box_task

        task = make_box_task(reference, 1, "mujoco", "cpu", cfg=cfg, evaluation=True)
    else:
        from envs.tracking import make_task

        task = make_task(reference, 1, "mujoco", "cpu", cfg=cfg, evaluation=True)
    meta = task.policy_metadata()
    names, dims = meta.pop("observation_names")["policy"], meta.pop("observation_dims")["policy"]
    starts = np.cumsum([0, *dims[:-1]]).tolist()
    return {"format": FORMAT, "task": task_id, **meta, "observation_group": "policy",
            "observation_dim": int(sum(dims)),
            "observation_layout": [{"name": n, "dim": d, "start": s}
                                   for n, d, s in zip(names, dims, starts, strict=True)],
            "action_dim": robot.NUM_JOINTS}


def reference_policy_model(meta: dict) -> onnx.ModelProto:
    """obs (batch, D) -> actions (batch, 29) = (obs[:, cmd:cmd+29] − default) / scale."""
    layout = {t["name"]: t for t in meta["observation_layout"]}
    if "command" not in layout:
        raise ValueError("the observation layout has no 'command' term to read the reference from")
    start = int(layout["command"]["start"])
    default = np.asarray(meta["default_joint_pos"], np.float32)
    scale = np.asarray(meta["action_scale"], np.float32)
    inits = [
        helper.make_tensor("starts", TensorProto.INT64, [1], [start]),
        helper.make_tensor("ends", TensorProto.INT64, [1], [start + robot.NUM_JOINTS]),
        helper.make_tensor("axes", TensorProto.INT64, [1], [1]),
        helper.make_tensor("default", TensorProto.FLOAT, [robot.NUM_JOINTS], default.tolist()),
        helper.make_tensor("scale", TensorProto.FLOAT, [robot.NUM_JOINTS], scale.tolist()),
    ]
    nodes = [helper.make_node("Slice", ["obs", "starts", "ends", "axes"], ["q_ref"]),
             helper.make_node("Sub", ["q_ref", "default"], ["offset"]),
             helper.make_node("Div", ["offset", "scale"], ["actions"])]
    graph = helper.make_graph(
        nodes, "reference_policy",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", int(meta["observation_dim"])])],
        [helper.make_tensor_value_info("actions", TensorProto.FLOAT, ["batch", robot.NUM_JOINTS])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="otr-gym reference policy")
    onnx.checker.check_model(model)
    return model


def write_reference_policy(out: str | Path, reference, task_id: str = "OTR-G1-Track-v0",
                           env: dict | None = None) -> Path:
    """The reference player for ``task_id``'s default actor (``env``: config overrides, e.g.
    {"observations": {"actor": "mocap"}} for the box task's motion-capture actor), at ``out``."""
    meta = training_metadata(reference, task_id, env)
    meta.update({
        "joint_stiffness": STARTUP_KP.tolist(), "joint_damping": STARTUP_KD.tolist(),
        "reference": {"path": str(reference)},
        "checkpoint": {"file": None, "iteration": None, "run": "reference-policy (open loop, start-up gains)"},
        "exported_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    })
    model = reference_policy_model(meta)
    for key, value in meta.items():
        model.metadata_props.add(key=key, value=json.dumps(value))
    with atomic_path(out) as tmp:
        tmp.write_bytes(model.SerializeToString())
    return Path(out)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """``otr reference-policy``'s arguments."""
    parser.add_argument("out", help="output .onnx (written atomically)")
    parser.add_argument("--reference", default=None,
                        help="reference whose env builds the observation layout (default: a generated standing clip)")
    parser.add_argument("--task", default="OTR-G1-Track-v0", choices=("OTR-G1-Track-v0", "OTR-G1-BoxTrack-v0"),
                        help="the env whose actor's observation layout the graph takes (the box task needs a "
                             "--reference with objects; default: %(default)s)")
    parser.add_argument("--box-actor", default=None, choices=("perception_free", "mocap"),
                        help="with the box task: its actor (default: configs/env/box.yaml's, perception_free)")


def main(args: argparse.Namespace) -> int:
    """``otr reference-policy OUT``: write the stand-in policy; a reference that cannot be read or an
    output that cannot be written: a message naming it, exit code 2."""
    reference = args.reference
    if reference is None:
        from agents.procedural import standing_reference

        reference = standing_reference()
    env = None if args.box_actor is None else {"observations": {"actor": args.box_actor}}
    if env is not None and args.task != "OTR-G1-BoxTrack-v0":
        print("otr reference-policy: --box-actor needs --task OTR-G1-BoxTrack-v0", file=sys.stderr)
        return 2
    try:
        path = write_reference_policy(args.out, reference, args.task, env)
    except (OSError, ValueError) as exc:
        print(f"otr reference-policy: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {path}: obs -> (q_ref − q_default)/scale, start-up gains")
    return 0
