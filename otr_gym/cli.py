"""The ``otr`` command line: one command per job.

Each job lives in its own module exposing ``configure_parser(parser)`` and ``main(args) -> int``;
modules are imported only when their command runs, so ``otr --help`` stays instant and a
job's heavy dependencies (mujoco_warp, torch, pinocchio) load only when needed.
``python -m otr_gym.cli COMMAND …`` is the same command line where the package is not installed
(from the repository root: the GPU machines of ``benchmarks/``).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys
from collections.abc import Callable

#: command -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("retarget.cli.demo", "run the whole pipeline on the embedded default (synthetic box carry)"),
    "inspect": ("agents.inspect", "summarise a demonstration, reference or deploy-log file"),
    "retarget": ("retarget.cli.retarget", "retarget demonstrations (AMASS, OMOMO, BVH, our .npz) to G1 references"),
    "score": ("retarget.cli.score", "score a reference against its demonstration (the paper's protocol; "
              "policies: otr evaluate)"),
    "verify": ("retarget.checks.verify", "check a reference: penetration, limits and holds against its demonstration; "
               "dynamic feasibility (on its terrain too)"),
    "clear-ground": ("retarget.checks.ground_clearance", "lift a reference's arms out of the ground or its terrain "
                     "(hands a reference put inside it)"),
    "variants": ("retarget.cli.variants", "one demonstration, many references: substitute shapes and sizes (Table IV)"),
    "view": ("retarget.cli.viewer", "web viewer (viser): references, objects, the person, contacts, metrics"),
    "kernels": ("retarget.cli.kernel_record", "record the numba kernels a first retarget compiles (--compile: "
                "compile the listed ones now)"),
    "procedural": ("agents.procedural", "write a procedural G1 reference: stand, walk or sway"),
    "train": ("agents.train", "train a tracking policy with rsl-rl PPO"),
    "evaluate": ("agents.evaluate", "evaluate a trained policy: success rate and MPJPE (references: otr score)"),
    "trace": ("agents.episode_trace", "one evaluation episode of a policy, frame by frame"),
    "failure-map": ("agents.failure_bins", "where in each clip a run's training episodes fail, and where its "
                    "starts go"),
    "plot": ("agents.plots", "training curves (PNG) and summary of a run, or several runs side by side"),
    "runs": ("agents.runs", "training run folders: the latest checkpoint, policy-only copies"),
    "export": ("agents.export", "export a policy to ONNX with metadata"),
    "play": ("agents.play", "render a policy tracking its reference to a video"),
    "reference-policy": ("agents.deploy.reference_policy", "write an ONNX stand-in policy that plays the reference "
                         "open loop (sim2sim before training)"),
    "deploy": ("agents.deploy.runner", "run an exported policy on a G1 over DDS (or replay a deploy log)"),
    "sim-robot": ("agents.deploy.sim_robot", "a MuJoCo G1 on the low-level DDS interface, for sim2sim"),
}

#: Commands that were renamed: the old name -> what to type instead (exit code 2, no alias).
RENAMED: dict[str, str] = {
    "eval": "otr eval was renamed: use otr score (references) or otr evaluate (policies)",
}


def int_at_least(low: int) -> Callable[[str], int]:
    """An argparse ``type``: an integer >= ``low``; a smaller one is refused as a usage error
    ("argument --every: must be >= 1, got 0", exit code 2)."""
    def parse(text: str) -> int:
        value = int(text)
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        return value

    parse.__name__ = "int"  # argparse's message for a non-integer: "invalid int value"
    return parse


def _available(module: str) -> bool:
    return importlib.util.find_spec(module) is not None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="otr", description="OTR-Gym: mocap -> G1 references -> tracking policies -> robot.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        if not _available(module):
            continue
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            importlib.import_module(module).configure_parser(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    if command in RENAMED:
        print(RENAMED[command], file=sys.stderr)
        return 2
    parser = build_parser(command if command in COMMANDS else None)
    args = parser.parse_args(argv)
    args.argv = argv  # the command line itself, for jobs that re-launch themselves (otr train --gpus)
    if args.command is None:
        parser.print_help()
        return 2
    return int(importlib.import_module(COMMANDS[args.command][0]).main(args) or 0)


if __name__ == "__main__":  # python -m otr_gym.cli COMMAND …: the same, without the installed `otr` script
    sys.exit(main())
