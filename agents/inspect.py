"""``otr inspect FILE…``: what is in a demonstration, reference or deploy-log file.

References (Holosoma / BeyondMimic / mjlab / ours .npz) report frames, fps, duration, bodies,
objects, velocity consistency and contact statistics from their annotations; anything else is
read as a demonstration (AMASS, OMOMO .pt, BVH, our demonstration .npz) and reports its parts,
objects, stature and ground/object contact statistics of the posed human surface. Deploy logs
(``otr deploy --log``) report cycle timing, missed deadlines, stage changes and tracking error.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from otr_gym.reference import InvalidReferenceError, Reference
from otr_gym.reference_summary import is_reference_file, reference_summary


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("files", nargs="+", type=Path, help="demonstration or reference files")
    p.add_argument("--object", type=Path, help="object mesh for demonstrations that need one (OMOMO)")
    from retarget.inputs.bvh import add_arguments

    add_arguments(p)


def _is_deploy_log(path: Path) -> bool:
    if path.suffix != ".npz":
        return False
    try:
        with np.load(path, allow_pickle=False) as npz:
            return "meta" in npz.files and "wake_ns" in npz.files
    except (OSError, ValueError):
        return False


def main(args: argparse.Namespace) -> int:
    status = 0
    for path in args.files:
        try:
            if is_reference_file(path):
                rows = reference_summary(Reference.load(path))
            elif _is_deploy_log(path):
                from agents.deploy.log import DeployLog, summary_rows

                rows = summary_rows(DeployLog.load(path))
            else:
                from retarget.inputs.bvh import options_from_args

                from retarget.inputs.summary import demonstration_summary

                rows = demonstration_summary(path, args.object, options_from_args(args))
        except (InvalidReferenceError, ValueError, FileNotFoundError) as exc:
            print(f"{path}: error: {exc}")
            status = 1
            continue
        print(path)
        width = max(len(k) for k, _ in rows)
        for key, value in rows:
            print(f"  {key:<{width}}  {value}")
    return status
