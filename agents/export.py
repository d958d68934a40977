"""``otr export RUN --onnx policy.onnx``: the policy alone (obs -> action) as ONNX, with metadata.

The graph is rsl-rl's own export module (``MLPModel.as_onnx``): empirical normaliser, MLP and
the Gaussian mean, one input ``obs`` (batch, D) and one output ``actions`` (batch, 29), opset
18. The reference is *not* baked in (docs/environment.md §8): the deployment runner owns the clip and
builds the command part of the observation itself, so one policy file serves many clips.

``metadata_props`` holds one entry per field, each value JSON-encoded (``read_metadata``
decodes them): joint order, default pose, kp/kd, action scale, observation layout
(names, dims, clip), control rate, the training reference and the checkpoint.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np
import onnx
import torch
from rsl_rl.modules import EmpiricalNormalization

from agents import runs
from agents.policy import TrainedPolicy, load_policy

OPSET = 18  # as rsl-rl's own ONNX export (docs/environment.md §8, MJ column)
PARITY_TOL = 1e-5
FORMAT = "otr-gym-policy/1"


def onnx_metadata(policy: TrainedPolicy) -> dict:
    """Everything a deployment runner needs besides the weights (plain JSON types): the env's
    policy metadata, with the observation layout reduced to the actor's input."""
    spec = policy.env_spec
    group = policy.obs_group
    env_meta = dict(spec["policy_metadata"])
    names = env_meta.pop("observation_names")[group]
    dims = env_meta.pop("observation_dims")[group]
    starts = np.cumsum([0, *dims[:-1]]).tolist()
    ckpt = policy.checkpoint
    return {
        "format": FORMAT,
        "task": spec["task"],
        **env_meta,
        "observation_group": group,
        "observation_dim": int(sum(dims)),
        "observation_layout": [{"name": n, "dim": d, "start": s}
                               for n, d, s in zip(names, dims, starts, strict=True)],
        "action_dim": spec["num_actions"],
        "reference": policy.run_config.get("reference_info", {"path": policy.run_config.get("reference")}),
        "checkpoint": {"file": ckpt.path.name, "iteration": ckpt.iteration, "run": ckpt.run_dir.name,
                       "sha256": hashlib.sha256(ckpt.path.read_bytes()).hexdigest()},
        "exported_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def export_onnx(run_or_checkpoint, onnx_path: str | Path) -> Path:
    """Write the ONNX policy atomically and check onnxruntime against torch (≤ PARITY_TOL)."""
    policy = load_policy(run_or_checkpoint, "cpu")
    module = policy.actor.as_onnx(verbose=False).eval()
    dim = policy.env_spec["observation_dims"][policy.obs_group]
    if dim != sum(policy.env_spec["policy_metadata"]["observation_dims"][policy.obs_group]):
        raise runs.RunError(f"{policy.checkpoint.run_dir / runs.ENV_SPEC_FILE}: observation layout does not add "
                            f"up to the {dim}-dim '{policy.obs_group}' group")
    program = torch.onnx.export(module, (torch.zeros(1, dim),), input_names=["obs"], output_names=["actions"],
                                opset_version=OPSET, dynamo=True, verbose=False,
                                dynamic_shapes=({0: torch.export.Dim("batch")},))
    model = program.model_proto
    for key, value in onnx_metadata(policy).items():
        model.metadata_props.add(key=key, value=json.dumps(value))
    onnx.checker.check_model(model)
    with runs.atomic_path(onnx_path) as tmp:  # a file failing the parity check never gets the final name
        tmp.write_bytes(model.SerializeToString())
        check_parity(tmp, module, dim)
    return Path(onnx_path)


def read_metadata(onnx_path: str | Path) -> dict:
    """The metadata of an exported policy, values decoded from JSON."""
    model = onnx.load(str(onnx_path), load_external_data=False)
    return {p.key: json.loads(p.value) for p in model.metadata_props}


def typical_observations(module: torch.nn.Module, dim: int, batch: int, seed: int = 0) -> np.ndarray:
    """Raw observations spread like the training data: the normaliser's mean ± 2 std per
    dimension (standard normal without a normaliser). Far outside that range (e.g. ±3 on a
    dimension that never moved in training) the float32 outputs grow to hundreds and the two
    runtimes differ by float32 rounding of those large numbers, not by the graph."""
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((batch, dim))
    norm = getattr(module, "obs_normalizer", None)
    if isinstance(norm, EmpiricalNormalization):
        noise = norm.mean.numpy() + 2.0 * norm.std.numpy() * noise
    return noise.astype(np.float32)


@torch.no_grad()
def check_parity(onnx_path: Path, module: torch.nn.Module, dim: int, batch: int = 64, seed: int = 0) -> float:
    """Max |onnxruntime − torch| over typical observations (raises above PARITY_TOL)."""
    import onnxruntime as ort

    obs = typical_observations(module, dim, batch, seed)
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    got = session.run(["actions"], {"obs": obs})[0]
    want = module(torch.from_numpy(obs)).numpy()
    err = float(np.abs(got - want).max())
    if not err <= PARITY_TOL:
        raise RuntimeError(f"{onnx_path}: onnxruntime differs from torch by {err:.2e} (> {PARITY_TOL:g})")
    return err


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="run folder (its latest checkpoint) or a model_<it>.pt checkpoint")
    parser.add_argument("--onnx", required=True, help="output .onnx file (written atomically)")


def main(args: argparse.Namespace) -> int:
    try:
        path = export_onnx(args.run, args.onnx)
    except (runs.RunError, ValueError) as exc:
        print(f"otr export: {exc}", file=sys.stderr)
        return 2
    meta = read_metadata(path)
    print(f"wrote {path}: obs ({meta['observation_dim']},) -> actions ({meta['action_dim']},), "
          f"checkpoint iteration {meta['checkpoint']['iteration']}")
    return 0
