"""A batch of ``otr retarget``: files to jobs, one clip to the bytes of its reference, the summary.

Every input becomes ``OUT/<name>.npz`` (folder inputs keep their sub-folders). A failing clip
is a 'failed' result naming its file, never an exception, so a batch goes on; outputs are
written atomically, so an existing file is complete and a batch resumes by skipping it.
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
                          feasibility.brief()), data
    except Exception as exc:  # one clip's failure must not stop the batch
        detail = "" if isinstance(exc, (ValueError, FileNotFoundError)) else "\n" + traceback.format_exc()
        return ClipResult(str(job.source), str(job.output), "failed", f"{job.source}: {type(exc).__name__}: {exc}"
                          f"{detail}", seconds=time.perf_counter() - start, worker=worker_name()), None

def run_job(job: Job, task: Task, frame_bar: bool = False) -> ClipResult:
    """Retarget one file and write its reference atomically (the serial and process-pool path)."""
    result, data = retarget_bytes(job, task, frame_bar)
    if data is not None:
        from otr_gym.io import atomic_write

        atomic_write(job.output, lambda f: f.write(data))
    return result

SUMMARY_NAME = "retarget_summary.json"

def summary(results: list[ClipResult], executor: str, seconds: float) -> dict:
    done = [r for r in results if r.status == "done"]
    frames = sum(r.frames or 0 for r in done)
    return {"executor": executor, "wall_s": seconds, "clips": len(results),
            "done": len(done), "failed": sum(r.status == "failed" for r in results),
            "skipped": sum(r.status == "skipped" for r in results), "frames": frames,
            "clips_per_minute": 60.0 * len(done) / seconds if seconds > 0 else None,
            "feasible": sum(r.flagged_share == 0.0 for r in done),
            "results": [dataclasses.asdict(r) for r in results]}


def report(bar, result: ClipResult) -> None:
    if result.status == "failed":
        bar.write(f"failed: {result.message.splitlines()[0]}")
    else:
        bar.write(f"wrote {result.message}")
    bar.update(1)
