"""``otr score REFERENCE… --demo DEMO``: score references against their demonstration (a trained
policy is evaluated by ``otr evaluate``).

References are files or folders of ``.npz`` (ours, Holosoma, BeyondMimic, mjlab layouts).
``--demo`` is one demonstration for every reference (methods compared on one clip), one per
reference (paired in order), or a folder in which each reference finds the demonstration whose
file name (without suffix) is the longest prefix of its own (``sub3_largebox_003.pt`` for
``sub3_largebox_003_mj_w_obj.npz``). The table follows the paper's Tables I–III; ``--json``
keeps every per-sequence value (with the reference's dynamic feasibility: the share of its
frames over a limit, ``retarget.checks.feasibility``) and is rewritten atomically after each sequence, so
``--resume`` continues a long batch where it stopped; it is written only once a reference was
scored (failures are listed in it beside the scores, never alone: a file of failures would read
as a result, and a previous file is left as it was).

A reference of ours records the demonstration it was made from (``metadata["source"]``,
``retarget.clip``); one scored against another demonstration (another name, format, subject or,
in the scaled mode, stature) is refused (``source_mismatch``) unless ``--allow-other-demo`` is
given. References without that record (Holosoma's, other tools') are not checked: a geometric
test would not tell two people doing the same motion apart from retargeting error.

Exit codes: 0 every reference scored; 1 some failed (unreadable, durations differ, …); 2 bad
arguments, or some reference was refused as made from another demonstration.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import asdict
from pathlib import Path

from retarget.evaluation.config import EvalConfig

DEMO_SUFFIXES = (".pt", ".npz", ".bvh")


def _scale_arg(text: str) -> float | None:
    if text == "auto":
        return None
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--scale must be 'auto' or a number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"--scale must be > 0, got {text!r}")
    return value


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("references", nargs="+", type=Path, metavar="REFERENCE",
                   help="reference .npz files or folders of them")
    p.add_argument("--demo", action="append", type=Path, required=True, metavar="DEMO",
                   help="demonstration (OMOMO .pt, AMASS .npz, BVH, our .npz): once for all references, once per "
                        "reference, or a folder matched by file name")
    p.add_argument("--object", type=Path, metavar="MESH", help="object mesh of the demonstration (OMOMO clips)")
    p.add_argument("--allow-other-demo", action="store_true",
                   help="score a reference of ours even when the source it records (name, format, subject, "
                        "stature) is not the given demonstration; references without that record "
                        "(Holosoma's, other tools') are never checked")
    from retarget.inputs.bvh import add_arguments

    add_arguments(p)
    p.add_argument("--scale", type=_scale_arg, default=None, metavar="auto|FLOAT",
                   help="world scale of the references: 'auto' (default) recovers it from their trajectories")
    p.add_argument("--contacts-world", choices=("native", "reference"), default="native",
                   help="world of the demonstrated contacts: as captured (default, the same set H for every "
                        "method) or the demonstration mapped into the reference's scaled world")
    p.add_argument("--eps-mm", type=float, default=20.0, help="interaction threshold ε_eval in mm (default 20)")
    p.add_argument("--json", type=Path, metavar="OUT", help="write every per-sequence value to this JSON file")
    p.add_argument("--resume", action="store_true",
                   help="reuse the sequences already in --json that were scored with the same settings")
    p.add_argument("--plots", type=Path, metavar="DIR", help="write contact timelines and metric distributions (PNG)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


class OtherDemonstrationError(ValueError):
    """A reference of ours scored against a demonstration other than the one it was made from."""


#: Fields of a demonstration's ``source`` (and its name) that identify the capture; our references
#: record them in ``metadata["source"]`` (``retarget.clip``). ``path`` is not one: the same file
#: moves between folders and machines.
SOURCE_IDENTITY = ("name", "format", "subject", "gender", "kind", "seed")
#: Statures closer than this (m) are the same body: the same file read again gives the same stature.
STATURE_TOLERANCE_M = 0.005


def source_mismatch(ref, demo) -> str | None:
    """How the demonstration ``ref`` (``otr_gym.reference.Reference``) records it was made from
    differs from ``demo``, e.g. "name 'sub2_x' vs 'sub3_x'; stature 1.62 m vs 1.94 m"; None when
    they agree or ``ref`` records no source (references of other tools are not checked).

    Compared: the identity fields both sides have (``SOURCE_IDENTITY``) and, for references made
    in the scaled mode, the stature their scale implies (G1 height / scale)."""
    from otr_gym import robot

    meta = ref.metadata if isinstance(ref.metadata, dict) else {}
    recorded = meta.get("source")
    if not isinstance(recorded, dict):
        return None
    current = {**demo.source, "name": demo.name}
    diffs = [f"{key} {recorded[key]!r} vs {current[key]!r}" for key in SOURCE_IDENTITY
             if key in recorded and key in current and recorded[key] != current[key]]
    mode = meta.get("mode", (meta.get("config") or {}).get("mode"))
    scale = meta.get("scale")
    if mode == "scaled" and isinstance(scale, (int, float)) and scale > 0:
        stature = robot.HEIGHT_M / scale
        if abs(stature - demo.stature_m) > STATURE_TOLERANCE_M:
            diffs.append(f"stature {stature:.3f} m vs {demo.stature_m:.3f} m")
    return "; ".join(diffs) or None


def pair_demonstrations(references: list[Path], demos: list[Path]) -> list[Path]:
    """The demonstration of each reference (see module docstring); raises ValueError on mismatch."""
    if len(demos) == 1 and demos[0].is_dir():
        candidates = sorted(p for p in demos[0].iterdir() if p.suffix in DEMO_SUFFIXES)
        out = []
        for ref in references:
            matches = [d for d in candidates if ref.stem.startswith(d.stem)]
            if not matches:
                raise ValueError(f"{ref}: no demonstration in {demos[0]} whose name starts the reference's name")
            out.append(max(matches, key=lambda d: len(d.stem)))
        return out
    if len(demos) == 1:
        return demos * len(references)
    if len(demos) == len(references):
        return list(demos)
    raise ValueError(f"--demo given {len(demos)} times for {len(references)} references: give it once, "
                     f"once per reference, or as a folder")


def main(args: argparse.Namespace) -> int:
    from otr_gym.io import write_json
    from otr_gym.reference import InvalidReferenceError, Reference, list_references
    from retarget.checks.feasibility import check_feasibility
    from retarget.evaluation.alignment import AlignmentError
    from retarget.evaluation.plots import plot_contact_timeline, plot_metric_distributions
    from retarget.evaluation.report import format_object_notes, format_scale_notes, format_table, read_json
    from retarget.evaluation.sequence import dataset_medians, evaluate_sequence
    from retarget.inputs.bvh import options_from_args
    from retarget.inputs.demonstration import InvalidDemonstrationError
    from retarget.inputs.meshes import InvalidMeshError
    from retarget.inputs.readers import load_demonstration

    expected = (InvalidReferenceError, InvalidDemonstrationError, AlignmentError, InvalidMeshError,
                FileNotFoundError, ValueError)
    try:
        cfg = EvalConfig(eps_eval_m=args.eps_mm / 1000.0, scale=args.scale, contacts_world=args.contacts_world)
        references = [f for p in args.references for f in list_references(p)]
        demos = pair_demonstrations(references, args.demo)
        previous = read_json(args.json) if args.resume and args.json and args.json.is_file() else None
    except expected as exc:
        print(f"otr score: error: {exc}", file=sys.stderr)
        return 2
    config = asdict(cfg)
    reusable = {}
    if previous is not None and previous.get("config") == config:
        reusable = {(r["reference"], r["demonstration_file"]): r for r in previous["sequences"]}

    progress = not args.no_progress and sys.stderr.isatty()
    records, failures, loaded, refused = [], [], {}, 0
    pairs = list(zip(references, demos))
    if progress and len(pairs) > 1:
        from tqdm import tqdm

        pairs = tqdm(pairs, desc="otr score", unit="seq")
    for ref_path, demo_path in pairs:
        key = (str(ref_path), str(demo_path))
        if key in reusable:
            records.append(reusable[key])
            continue
        start = time.perf_counter()
        try:
            ref = Reference.load(ref_path)
            if demo_path not in loaded:
                loaded = {demo_path: load_demonstration(demo_path, args.object,  # keep one in memory
                                                        bvh=options_from_args(args))}
            mismatch = None if args.allow_other_demo else source_mismatch(ref, loaded[demo_path])
            if mismatch:
                raise OtherDemonstrationError(
                    f"{ref_path} was made from another demonstration than {demo_path} ({mismatch}); pass "
                    f"--allow-other-demo to score it against {demo_path} anyway")
            result = evaluate_sequence(ref, loaded[demo_path], cfg, progress=progress, demo_source=str(demo_path))
        except expected as exc:
            print(f"otr score: error: {exc}", file=sys.stderr)
            failures.append({"reference": str(ref_path), "demonstration": str(demo_path), "error": str(exc)})
            refused += isinstance(exc, OtherDemonstrationError)
            continue
        record = result.as_dict()
        feasibility = check_feasibility(ref)  # the motion alone: what a policy on the G1 will find hard
        record["feasibility"] = feasibility.brief()
        record["demonstration_file"] = str(demo_path)
        record["seconds"] = time.perf_counter() - start
        records.append(record)
        if args.json:
            write_json(args.json, _payload(config, records, failures, dataset_medians))
    if args.json and records:  # a file of failures alone would read as a result: nothing scored, nothing written
        write_json(args.json, _payload(config, records, failures, dataset_medians))
    elif args.json:
        print(f"{args.json} not written: no reference was scored", file=sys.stderr)
    if records:
        print(format_table(records))
        print()
        print(format_scale_notes(records))
        notes = format_object_notes(records)
        if notes:
            print(notes)
        print("\n".join(f"{r['name']}: {r['frames']} frames in {r['seconds']:.1f} s" for r in records
                        if "seconds" in r))
        print("dynamic feasibility (otr verify for where and why):")
        print("\n".join(f"  {r['name']}: {r['feasibility']['verdict'].removeprefix('verdict: ')}" for r in records
                        if "feasibility" in r))
    if args.plots and records:
        for r in records:
            plot_contact_timeline(r, args.plots / f"{r['name']}_contacts.png")
        plot_metric_distributions(records, args.plots / "metric_distributions.png")
        print(f"plots in {args.plots}")
    if failures:
        print(f"otr score: {len(failures)} of {len(failures) + len(records)} sequences failed", file=sys.stderr)
        return 2 if refused else 1
    return 0


def _payload(config: dict, records: list[dict], failures: list[dict], medians) -> dict:
    from retarget.evaluation.sequence import json_safe

    return json_safe({"protocol": "OTRetarget paper Sec. IV-A (see retarget/evaluation)", "config": config,
                      "sequences": records, "median": medians([r["metrics"] for r in records]) if records else {},
                      "failures": failures})
