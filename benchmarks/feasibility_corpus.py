"""Dynamic feasibility of a corpus of references: one row per clip, medians, the worst clip, and
how many clips meet issue 52's targets.

    otr retarget CORPUS --out REFS --workers 2              # writes REFS/retarget_summary.json
    python benchmarks/feasibility_corpus.py REFS/retarget_summary.json [MORE.json ...] [--json OUT] [--markdown]
    python benchmarks/feasibility_corpus.py --references REFS [--json OUT] [--markdown]

The first form reads what ``otr retarget`` recorded per clip (``FeasibilityReport.brief``, in
``retarget_summary.json``); a clip that a resumed batch only lists as *skipped* is checked from its
``.npz``, and a clip named by several summaries takes its last entry. The second form runs
``retarget.checks.feasibility.check_feasibility`` on every ``.npz`` of the folder (~0.5-2 s a clip).
Every measure is ``otr verify``'s, at the tracking rate (50 fps):

* *flag %*: share of the frames over any limit; *limb*: the largest foot or hand jump off the line
  of its neighbours (cm), and frames over 3 cm; *pelvis*: frames with the pelvis over 1 cm off that line;
* *τ/eff*: the largest joint torque over its effort limit (contact-consistent inverse dynamics), and
  frames at or over 1×; *unsup.*: frames where the base force that the floor cannot supply reaches
  20 % of the weight; *slide*: frames with a stance foot sliding at 5 cm/s or more.

Targets (issue 52): flag ≤ 2 %, τ/eff ≤ 1.2 and no limb jump over 3 cm (no frame over the limb limit).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: issue 52's targets for a reference the G1 can execute
TARGET_FLAGGED_SHARE = 0.02
TARGET_TORQUE_RATIO = 1.2


@dataclass(frozen=True)
class ClipRow:
    """One clip's feasibility (lengths in metres, shares as fractions; frames at 50 fps)."""

    clip: str
    frames: int
    flagged_share: float
    limb_jump_peak_m: float
    limb_jump_frames: int  # frames with a foot or hand ≥ 3 cm off its neighbours' line
    pelvis_jump_frames: int  # frames with the pelvis ≥ 1 cm off its neighbours' line
    torque_peak_ratio: float  # largest |τ| / effort limit
    torque_frames: int  # frames with a torque at or over its effort limit
    unsupported_frames: int
    sliding_frames: int
    verdict: str

    @property
    def meets_targets(self) -> dict[str, bool]:
        return {"flagged": self.flagged_share <= TARGET_FLAGGED_SHARE,
                "torque": self.torque_peak_ratio <= TARGET_TORQUE_RATIO,
                "limb jump": self.limb_jump_frames == 0}


@dataclass(frozen=True)
class FailedClip:
    clip: str
    message: str  # the first line of the error


def row_from_brief(clip: str, frames: int, brief: dict) -> ClipRow:
    """A row from ``FeasibilityReport.brief()`` (what retarget_summary.json stores per clip)."""
    over = brief["frames_over"]
    return ClipRow(clip=clip, frames=int(frames), flagged_share=float(brief["flagged_share"]),
                   limb_jump_peak_m=float(brief["limb_jump_peak_m"]), limb_jump_frames=int(over["limb jump"]),
                   pelvis_jump_frames=int(over["jump"]), torque_peak_ratio=float(brief["torque_peak_ratio"]),
                   torque_frames=int(over["torque"]), unsupported_frames=int(over["unsupported"]),
                   sliding_frames=int(over["sliding"]), verdict=str(brief["verdict"]))


def check_reference(path: Path) -> ClipRow:
    """Run the feasibility check on one reference file."""
    from otr_gym.reference import Reference
    from retarget.checks.feasibility import check_feasibility

    report = check_feasibility(Reference.load(path))
    return row_from_brief(path.stem, report.num_frames, report.brief())


def rows_from_references(folder: Path) -> tuple[list[ClipRow], list[FailedClip]]:
    """Check every ``.npz`` of ``folder``; a file that does not load is a failed clip."""
    from otr_gym.reference import InvalidReferenceError, list_references

    rows, failed = [], []
    for path in list_references(folder):
        try:
            rows.append(check_reference(path))
        except InvalidReferenceError as exc:
            failed.append(FailedClip(path.stem, str(exc).splitlines()[0]))
    return rows, failed


def rows_from_summaries(paths: list[Path]) -> tuple[list[ClipRow], list[FailedClip]]:
    """Rows of the clips in ``retarget_summary.json`` files (later files win for a clip listed twice)."""
    from otr_gym.reference import InvalidReferenceError

    entries: dict[str, dict] = {}
    for path in paths:
        try:
            results = json.loads(path.read_text())["results"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise SystemExit(f"{path}: not a retarget_summary.json ({type(exc).__name__}: {exc})") from exc
        for entry in results:
            # a skipped entry (the file existed when the batch resumed) must not hide an earlier 'done'
            if entry["status"] != "skipped" or entry["output"] not in entries:
                entries[entry["output"]] = entry
    rows, failed = [], []
    for output, entry in entries.items():
        clip = Path(entry["source"]).stem
        if entry["status"] == "done" and entry.get("feasibility"):
            rows.append(row_from_brief(clip, entry["frames"], entry["feasibility"]))
        elif entry["status"] == "failed":
            failed.append(FailedClip(clip, entry["message"].splitlines()[0]))
        elif Path(output).is_file():  # skipped, or written before the summary carried feasibility
            try:
                rows.append(check_reference(Path(output)))
            except InvalidReferenceError as exc:
                failed.append(FailedClip(clip, str(exc).splitlines()[0]))
        else:
            failed.append(FailedClip(clip, f"{entry['status']} and {output} is missing"))
    return rows, failed


def corpus_summary(rows: list[ClipRow]) -> dict:
    """Medians and worst clips of flag %, limb jump and torque, and how many clips meet each target."""
    if not rows:
        return {"clips": 0}
    out: dict = {"clips": len(rows)}
    for key in ("flagged_share", "limb_jump_peak_m", "torque_peak_ratio"):
        values = [getattr(r, key) for r in rows]
        worst = max(rows, key=lambda r: getattr(r, key))
        out[key] = {"median": statistics.median(values), "worst": getattr(worst, key), "worst_clip": worst.clip}
    meets = [r.meets_targets for r in rows]
    out["meeting"] = {target: sum(m[target] for m in meets) for target in meets[0]}
    out["meeting"]["all"] = sum(all(m.values()) for m in meets)
    return out


HEADERS = ("clip", "frames", "flag %", "limb peak cm", "limb > 3 cm", "pelvis > 1 cm", "τ/eff peak",
           "τ over", "unsup.", "slide")


def _cells(r: ClipRow) -> tuple[str, ...]:
    return (r.clip, str(r.frames), f"{100 * r.flagged_share:.1f}", f"{100 * r.limb_jump_peak_m:.1f}",
            str(r.limb_jump_frames), str(r.pelvis_jump_frames), f"{r.torque_peak_ratio:.2f}", str(r.torque_frames),
            str(r.unsupported_frames), str(r.sliding_frames))


def format_table(rows: list[ClipRow], markdown: bool = False) -> str:
    """The per-clip table: aligned text, or a markdown table for the docs."""
    body = [_cells(r) for r in rows]
    if markdown:
        lines = ["| " + " | ".join(HEADERS) + " |", "|" + "---|" * len(HEADERS)]
        return "\n".join(lines + ["| " + " | ".join(c) + " |" for c in body])
    widths = [max(len(h), *(len(c[i]) for c in body)) for i, h in enumerate(HEADERS)]
    return "\n".join("  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))
                     for cells in [HEADERS, *body])


def format_summary(summary: dict, failed: list[FailedClip]) -> str:
    """Median / worst line, the targets line, and the failed clips."""
    lines = []
    if summary["clips"]:
        f, limb, tau = summary["flagged_share"], summary["limb_jump_peak_m"], summary["torque_peak_ratio"]
        lines.append(f"{summary['clips']} clips: flag % median {100 * f['median']:.1f} (worst {100 * f['worst']:.1f}, "
                     f"{f['worst_clip']}); limb jump peak median {100 * limb['median']:.1f} cm (worst "
                     f"{100 * limb['worst']:.1f}, {limb['worst_clip']}); τ/eff peak median {tau['median']:.2f} "
                     f"(worst {tau['worst']:.2f}, {tau['worst_clip']})")
        m, n = summary["meeting"], summary["clips"]
        lines.append(f"meeting issue 52's targets: flag ≤ {100 * TARGET_FLAGGED_SHARE:.0f} % {m['flagged']}/{n}, "
                     f"τ/eff ≤ {TARGET_TORQUE_RATIO} {m['torque']}/{n}, no limb jump over 3 cm {m['limb jump']}/{n}; "
                     f"all three {m['all']}/{n}")
    lines += [f"failed: {c.clip}: {c.message}" for c in failed]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("summaries", nargs="*", type=Path, help="retarget_summary.json files of `otr retarget`")
    parser.add_argument("--references", type=Path, help="check every .npz of this folder instead")
    parser.add_argument("--json", type=Path, help="write the rows, failures and summary here")
    parser.add_argument("--markdown", action="store_true", help="print the table as markdown")
    args = parser.parse_args(argv)
    if bool(args.summaries) == (args.references is not None):
        parser.error("give retarget_summary.json files or --references DIR (one of the two)")
    from otr_gym.reference import InvalidReferenceError

    try:
        rows, failed = (rows_from_references(args.references) if args.references
                        else rows_from_summaries(args.summaries))
    except InvalidReferenceError as exc:  # an empty or missing folder, named by the message
        raise SystemExit(str(exc)) from exc
    rows.sort(key=lambda r: r.clip)
    summary = corpus_summary(rows)
    print(format_table(rows, args.markdown))
    print()
    print(format_summary(summary, failed))
    if args.json:
        from otr_gym.io import write_json

        write_json(args.json, {"rows": [asdict(r) | {"meets_targets": r.meets_targets} for r in rows],
                               "failed": [asdict(c) for c in failed], "summary": summary}, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
