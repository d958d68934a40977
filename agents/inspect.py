"""``otr inspect FILE…``: what is in a demonstration, reference or deploy-log file.

References (Holosoma / BeyondMimic / mjlab / ours .npz) report frames, fps, duration, bodies,
objects, velocity consistency and contact statistics from their annotations; anything else is
read as a demonstration (AMASS, OMOMO .pt, BVH, our demonstration .npz) and reports its parts,
objects, stature and ground/object contact statistics of the posed human surface. Deploy logs
(``otr deploy --log``) report cycle timing, missed deadlines, stage changes and tracking error.

An ``.npz`` archive is recognised by the arrays it holds, whatever its suffix (a deploy log
written as ``run`` is still a deploy log). A file that cannot be read gets one line naming it
and the problem; the next files are still inspected and the exit code is 1.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from otr_gym.io import NpzError, npz_keys
from otr_gym.reference import Reference
from otr_gym.reference_summary import has_reference_keys, reference_summary

#: Suffixes read by a demonstration reader of their own, never as an .npz archive.
OTHER_FORMATS = (".pt", ".bvh")


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("files", nargs="+", type=Path, help="demonstration or reference files")
    p.add_argument("--object", type=Path, help="object mesh for demonstrations that need one (OMOMO)")
    from retarget.inputs.bvh import add_arguments

    add_arguments(p)


def file_kind(path: Path) -> str:
    """'reference', 'deploy log' or 'demonstration' (the demonstration readers name any other
    format); NpzError naming the file when an ``.npz`` file is not a readable archive."""
    if path.suffix.lower() in OTHER_FORMATS or not path.is_file():
        return "demonstration"
    try:
        keys = npz_keys(path)
    except (NpzError, OSError):
        if path.suffix == ".npz":
            raise
        return "demonstration"  # not an archive: its suffix decides (and the reader names it)
    if has_reference_keys(keys):
        return "reference"
    if "meta" in keys:  # maybe a deploy log: only then import its reader (torch)
        from agents.deploy.log import is_deploy_log

        if is_deploy_log(keys):
            return "deploy log"
    return "demonstration"


def inspect_rows(path: Path, args: argparse.Namespace) -> list[tuple[str, str]]:
    """The (key, value) rows `otr inspect` prints for one file (``file_kind`` decides which summary)."""
    kind = file_kind(path)
    if kind == "reference":
        return reference_summary(Reference.load(path))
    if kind == "deploy log":
        from agents.deploy.log import DeployLog, summary_rows

        return summary_rows(DeployLog.load(path))
    from retarget.inputs.bvh import options_from_args
    from retarget.inputs.summary import demonstration_summary

    return demonstration_summary(path, args.object, options_from_args(args))


def main(args: argparse.Namespace) -> int:
    status = 0
    for path in args.files:
        try:
            rows = inspect_rows(path, args)
        except (ValueError, OSError) as exc:  # InvalidReferenceError, InvalidDemonstrationError, NpzError, …
            problem = str(exc).removeprefix(f"{path}: ")  # our messages name the file already
            print(f"{path}: error: {problem}")
            status = 1
            continue
        print(path)
        width = max(len(k) for k, _ in rows)
        for key, value in rows:
            print(f"  {key:<{width}}  {value}")
    return status
