"""The clip list of a corpus: the references a batch made or kept whose share of frames over a
feasibility limit is at most a bound, as a file ``otr train --reference`` reads
(``otr_gym.reference.clip_entries``: one path a line, relative to the list's folder; ``#``
lines are comments).

    otr retarget CORPUS/ --out DIR --max-flagged 0.02   # also writes DIR/clips_passing.txt
    otr train --reference DIR/clips_passing.txt
"""

from __future__ import annotations

import os
from pathlib import Path

from retarget.cli.batch import SUMMARY_NAME, ClipResult

PASSING_NAME = "clips_passing.txt"


def passing(results: list[ClipResult], max_flagged: float) -> list[ClipResult]:
    """The clips with a reference (done now or before) and ``flagged_share`` ≤ ``max_flagged``
    (a share in [0, 1]), in output order."""
    kept = [r for r in results if r.status in ("done", "skipped") and r.flagged_share is not None
            and r.flagged_share <= max_flagged]
    return sorted(kept, key=lambda r: r.output)


def write_clip_list(results: list[ClipResult], out_dir: Path, max_flagged: float) -> tuple[Path, int]:
    """Write ``out_dir/clips_passing.txt`` (atomically) and return its path and how many clips
    it names. Paths are relative to ``out_dir``, so the folder can move with its list."""
    from otr_gym.io import atomic_write

    kept = passing(results, max_flagged)
    with_reference = sum(r.status in ("done", "skipped") for r in results)
    lines = [f"# {len(kept)} of the {with_reference} references in {SUMMARY_NAME} with at most "
             f"{100 * max_flagged:g} % of their frames over a feasibility limit (otr retarget --max-flagged "
             f"{max_flagged:g})",
             f"# otr train --reference {out_dir / PASSING_NAME}",
             *(Path(os.path.relpath(r.output, out_dir)).as_posix() for r in kept)]
    path = out_dir / PASSING_NAME
    atomic_write(path, lambda f: f.write("\n".join(lines) + "\n"), binary=False)
    return path, len(kept)
