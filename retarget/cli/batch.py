"""A batch of ``otr retarget``: files to jobs, one clip to the bytes of its reference, the summary.

Every input becomes ``OUT/<name>.npz`` (folder inputs keep their sub-folders). A failing clip
is a 'failed' result naming its file, never an exception, so a batch goes on; outputs are
written atomically, so an existing file is complete and a batch resumes by skipping it. A
skipped clip keeps the figures its earlier run recorded (``skipped_result``), so the summary
of a resumed batch still describes every clip and the clip list filters all of them.
"""

from __future__ import annotations

import dataclasses
import os
import socket
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from retarget.clip import retarget_timed
from retarget.config import ConfigError, RetargetConfig

INPUT_SUFFIXES = (".npz", ".pt", ".bvh")

@dataclass(frozen=True)
class Job:
    source: Path
    output: Path

def collect_jobs(inputs: list[Path], out: Path) -> list[Job]:
    """One job per input file; folders contribute their .npz/.pt/.bvh files (recursively, sorted)
    with their sub-folders kept under ``out``. Missing inputs still make a job (it fails with
    a clear message); two inputs mapping to one output are an error."""
    jobs: list[Job] = []
    for item in inputs:
        item = Path(item)
        if item.is_dir():
            files = sorted(p for p in item.rglob("*") if p.suffix.lower() in INPUT_SUFFIXES and p.is_file())
            jobs += [Job(p, out / p.relative_to(item).with_suffix(".npz")) for p in files]
        else:
            jobs.append(Job(item, out / f"{item.stem}.npz"))
    seen: dict[Path, Path] = {}
    for job in jobs:
        if job.output in seen:
            raise ConfigError(f"inputs {seen[job.output]} and {job.source} would both write {job.output}")
        seen[job.output] = job.source
    return jobs

@dataclass(frozen=True)
class Task:
    """What every worker needs besides the job: the same for the whole batch."""

    cfg: RetargetConfig
    object_mesh: Path | None = None
    bvh: object = None  # retarget.inputs.bvh.BvhOptions

@dataclass
class ClipResult:
    """One clip of a batch, as the summary JSON lists it."""

    source: str
    output: str
    status: str  # done | failed | skipped
    message: str = ""
    frames: int | None = None
    ms_per_frame: float | None = None
    seconds: float | None = None
    worker: str = ""
    #: share of the reference's frames over a dynamic-feasibility limit (``retarget.checks.feasibility``:
    #: torques, jumps, support, sliding, …), so a corpus run shows which clips need care
    flagged_share: float | None = None
    #: frames over each limit, the peaks and the one-line verdict (``FeasibilityReport.brief``)
    feasibility: dict | None = None
    #: the contacts as the solve left them (``contact_figures``): penetration, contact shares
    fidelity: dict | None = None


def contact_figures(reference) -> dict:
    """The clip's contacts as the solve already measured them (no extra evaluation):

    * ``min_distance_m``: the smallest signed distance of any robot probe or guard to a
      collidable channel (ground, objects) over the clip; negative is penetration;
    * ``penetration_m``: max(0, −min_distance_m);
    * ``min_self_distance_m``: the smallest distance between links that must not touch;
    * ``qp_failures``: QPs whose rows conflicted and were re-solved in elastic mode;
    * ``contact_share``: per channel, the share of frames in which some G1 contact unit is within
      20 mm of it (``ContactAnnotations.in_contact``, the evaluation's ε): 0 on an object the
      demonstration carries means the robot never touched it.

    A distance the solver never measured (no collidable pair) is None: JSON has no infinity."""
    solver = reference.metadata["solver"]
    finite = {key: float(solver[key]) if np.isfinite(solver[key]) else None
              for key in ("min_distance_m", "min_self_distance_m")}
    touching = reference.contacts.in_contact().any(axis=1)  # (T, C)
    return {**finite, "penetration_m": max(0.0, -(finite["min_distance_m"] or 0.0)),
            "qp_failures": int(solver["qp_failures"]),
            "contact_share": {name: float(touching[:, c].mean())
                              for c, name in enumerate(reference.contacts.channel_names)}}

def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"

def retarget_bytes(job: Job, task: Task, frame_bar: bool = False) -> tuple[ClipResult, bytes | None]:
    """Retarget one file to the bytes of its reference ``.npz`` (never raises: a failure is a
    'failed' result naming the file). Every executor goes through here, so their outputs are
    the same bytes."""
    start = time.perf_counter()
    try:
        from otr_gym.io import npz_bytes
        from retarget.checks.feasibility import check_feasibility
        from retarget.inputs.readers import load_demonstration

        demo = load_demonstration(job.source, task.object_mesh, bvh=task.bvh)
        progress, bar = None, None
        if frame_bar:
            from tqdm import tqdm

            cfg = task.cfg
            total = demo.num_frames if cfg.fps is None else int(np.floor((demo.num_frames - 1) / demo.fps * cfg.fps
                                                                            + 1e-9)) + 1
            bar = tqdm(total=total, desc=job.source.name, unit="frame", leave=False)

            def progress(_t: int) -> None:
                if bar.n == bar.total:  # the ballistic second pass (retarget.solver.flight) starts over
                    bar.total += total
                    bar.set_description(f"{job.source.name} (ballistic pass)")
                bar.update(1)
        reference, timing = retarget_timed(demo, task.cfg, progress)
        if bar is not None:
            bar.close()
        reference.validate()
        data = npz_bytes(reference.to_arrays())
        solver = reference.metadata["solver"]
        feasibility = check_feasibility(reference)  # ~0.5 s a clip: the solve takes 10-100x that
        message = (f"{job.output} ({timing.frames} frames, {timing.ms_per_frame:.1f} ms/frame, "
                   f"min distance {1000 * solver['min_distance_m']:.2f} mm, "
                   f"{100 * feasibility.flagged_share():.1f} % of frames over a feasibility limit)")
        return ClipResult(str(job.source), str(job.output), "done", message, timing.frames, timing.ms_per_frame,
                          time.perf_counter() - start, worker_name(), feasibility.flagged_share(),
                          feasibility.brief(), contact_figures(reference)), data
    except Exception as exc:  # one clip's failure must not stop the batch
        detail = "" if isinstance(exc, (ValueError, FileNotFoundError)) else "\n" + traceback.format_exc()
        return ClipResult(str(job.source), str(job.output), "failed", f"{job.source}: {type(exc).__name__}: {exc}"
                          f"{detail}", seconds=time.perf_counter() - start, worker=worker_name()), None

def write_output(job: Job, result: ClipResult, data: bytes | None) -> ClipResult:
    """Write a clip's reference atomically; a write that fails (disk full, no permission) makes
    the clip 'failed', naming the output file and the error."""
    if data is None:
        return result
    from otr_gym.io import atomic_write

    try:
        atomic_write(job.output, lambda f: f.write(data))
    except OSError as exc:
        return dataclasses.replace(result, status="failed",
                                   message=f"{job.source}: could not write {job.output}: {exc}")
    return result

def run_job(job: Job, task: Task, frame_bar: bool = False) -> ClipResult:
    """Retarget one file and write its reference (the serial and process-pool path)."""
    return write_output(job, *retarget_bytes(job, task, frame_bar))

def lost_result(job: Job, why: str) -> ClipResult:
    """The 'failed' result of a clip that gave no result at all (its worker died, its task errored)."""
    return ClipResult(str(job.source), str(job.output), "failed", f"{job.source}: {why}")

def skipped_result(job: Job, earlier: dict | None) -> ClipResult:
    """A clip whose output exists: its figures from the summary that wrote it (``earlier``: that
    record), else measured on the output file itself (``check_feasibility``, ~0.5 s). An output
    that cannot be read is 'failed', naming the file and the problem (``--overwrite`` redoes it)."""
    if earlier is not None and earlier.get("feasibility") and earlier.get("fidelity"):
        return ClipResult(str(job.source), str(job.output), "skipped", "output exists", earlier.get("frames"),
                          earlier.get("ms_per_frame"), earlier.get("seconds"), earlier.get("worker") or "",
                          earlier["flagged_share"], earlier["feasibility"], earlier["fidelity"])
    from otr_gym.reference import InvalidReferenceError, Reference
    from retarget.checks.feasibility import check_feasibility

    try:
        reference = Reference.load(job.output)
        feasibility = check_feasibility(reference)
        fidelity = contact_figures(reference)
    except (InvalidReferenceError, KeyError, AttributeError) as exc:  # not ours: no solver metadata, no contacts
        return ClipResult(str(job.source), str(job.output), "failed",
                          f"{job.source}: its output {job.output} exists but cannot be read "
                          f"({type(exc).__name__}: {exc}); --overwrite redoes it")
    return ClipResult(str(job.source), str(job.output), "skipped", "output exists (figures measured on it)",
                      reference.num_frames, flagged_share=feasibility.flagged_share(),
                      feasibility=feasibility.brief(), fidelity=fidelity)

def earlier_records(summary_path: Path) -> dict[Path, dict]:
    """The records of an earlier ``retarget_summary.json`` by output file (resolved); {} when
    there is none or it is unreadable (a skipped clip then measures its output)."""
    import json

    try:
        results = json.loads(summary_path.read_text())["results"]
        return {Path(r["output"]).resolve(): r for r in results}
    except (OSError, ValueError, KeyError, TypeError):
        return {}

SUMMARY_NAME = "retarget_summary.json"

def summary(results: list[ClipResult], executor: str, seconds: float) -> dict:
    """``retarget_summary.json``: counts, this run's throughput (clips retargeted per minute of
    wall time), and every clip's record; ``feasible`` counts the clips of this run with no frame
    over a feasibility limit."""
    done = [r for r in results if r.status == "done"]
    frames = sum(r.frames or 0 for r in done)
    return {"executor": executor, "wall_s": seconds, "clips": len(results),
            "done": len(done), "failed": sum(r.status == "failed" for r in results),
            "skipped": sum(r.status == "skipped" for r in results), "frames": frames,
            "clips_per_minute": 60.0 * len(done) / seconds if seconds > 0 else None,
            "feasible": sum(r.flagged_share == 0.0 for r in done),
            "results": [dataclasses.asdict(r) for r in results]}


def progress_bar(total: int):
    """The batch's bar: clips finished of ``total``, the time so far, tqdm's ETA and clips
    retargeted per minute (``report`` updates it), whichever executor runs them."""
    from tqdm import tqdm

    return tqdm(total=total, desc="retarget", unit="clip",
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} clips "
                           "[{elapsed} elapsed, ETA {remaining}{postfix}]")


def report(bar, result: ClipResult, retargeted: int) -> None:
    """Print one clip's line above the bar and move the bar; ``retargeted``: clips done so far
    (failures take no solve: counting them would inflate the rate)."""
    if result.status == "failed":
        bar.write(f"failed: {result.message.splitlines()[0]}")
    else:
        bar.write(f"wrote {result.message}")
    elapsed_s = bar.format_dict["elapsed"]
    if retargeted and elapsed_s > 0:
        bar.set_postfix_str(f"{60.0 * retargeted / elapsed_s:.1f} clips/min", refresh=False)
    bar.update(1)
