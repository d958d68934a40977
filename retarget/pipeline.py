"""Demonstrations in, G1 references out: the retarget driver and the ``otr retarget`` command.

``retarget_demonstration(demo, cfg) -> Reference`` runs the whole method on one demonstration
(resampling, probes, correspondences, SQP, reference assembly). The command line runs it over
files and folders:

    otr retarget INPUT… --out DIR [--object MESH] [--mode native|scaled|robot-only]
                 [--workers N] [--fps 50] [--config YAML] [--overwrite]

Inputs are AMASS ``.npz`` (SMPL-X / SMPL-H parameters), OMOMO InterMimic ``.pt`` clips and our
demonstration ``.npz`` files, or folders of them (searched recursively). Every input becomes
``DIR/<name>.npz`` (folder inputs keep their sub-folders). A batch is resumable: finished
outputs are skipped (writes are atomic, so an existing file is complete), a failing clip is
reported with its file and error and the batch goes on; the exit code is 1 if any clip failed.

Output rate (our choice): the demonstration is resampled to ``--fps`` (default 50, what the
Holosoma / BeyondMimic trackers expect) *before* solving, so every stored frame is a solved,
constraint-checked frame (interpolating a solution would not keep its contacts).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import multiprocessing
import os
import sys
import time
import traceback
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from otr_gym.config import from_dict, load_yaml_mapping
from retarget.geometry import GeometryConfig
from retarget.problem import SolverConfig
from retarget.residuals import InteractionConfig
from retarget.stance import StanceConfig
from retarget.style import StyleConfig

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs" / "retarget"
INPUT_SUFFIXES = (".npz", ".pt")


@dataclass(frozen=True)
class RetargetConfig:
    """Everything ``retarget_demonstration`` needs; mirrored by configs/retarget/default.yaml."""

    #: native | scaled | robot-only (METHOD.md "Modes").
    mode: str = "native"
    #: Rate the demonstration is resampled to and solved at (Hz); None keeps the demonstration's.
    fps: float | None = 50.0
    #: Spacing of the convex-hull guard points on the robot links (m, ``retarget.probes``).
    guard_spacing_m: float = 0.008
    #: Cap on area probes per robot link (None: the paper's density everywhere).
    max_probes_per_link: int | None = None
    #: Seed of every probe sampling.
    seed: int = 0
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    interaction: InteractionConfig = field(default_factory=InteractionConfig)
    style: StyleConfig = field(default_factory=StyleConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    stance: StanceConfig = field(default_factory=StanceConfig)


class ConfigError(ValueError):
    """A configuration file or value that cannot be used; the message names it."""


def load_config(path: str | Path | None = None, **overrides) -> RetargetConfig:
    """The configuration of a YAML file (default: configs/retarget/default.yaml), with top-level
    ``overrides`` (e.g. mode, fps) applied. Problems raise ConfigError naming the file."""
    default = CONFIG_DIR / "default.yaml"
    try:
        data = load_yaml_mapping(path, default, "retarget")
        cfg = from_dict(RetargetConfig, data, str(path if path is not None else default))
    except (ValueError, FileNotFoundError, yaml.YAMLError) as exc:
        raise ConfigError(str(exc)) from exc
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if overrides:
        cfg = dataclasses.replace(cfg, **overrides)
    from retarget.problem import MODES

    if cfg.mode not in MODES:
        raise ConfigError(f"unknown mode '{cfg.mode}' (choose from {MODES})")
    if cfg.fps is not None and not cfg.fps > 0:
        raise ConfigError(f"fps must be > 0, got {cfg.fps}")
    return cfg


# ------------------------------------------------------------------ one demonstration


def retarget_demonstration(demo, cfg: RetargetConfig = RetargetConfig(), progress=None):
    """Retarget one Demonstration to a G1 ``Reference`` (see the module doc for the rate).

    ``progress(t)`` is called after each solved frame. The reference carries the free and fixed
    objects' tracks (with meshes), per-link contact annotations against every channel, and
    metadata (mode, scale, weights, source, solver statistics).
    """
    from otr_gym.reference import ContactAnnotations, ObjectTrack, Reference
    from otr_gym.robot import BODY_NAMES
    from otr_gym.rotations import (
        angular_velocity_from_quats,
        linear_velocity_from_positions,
        matrix_to_quat,
    )
    from retarget.problem import build_problem, mode_scale, resample_demonstration
    from retarget.solver import solve_sequence

    start = time.perf_counter()
    if cfg.fps is not None:
        demo = resample_demonstration(demo, cfg.fps)
    problem = build_problem(demo, cfg.mode, geometry=cfg.geometry, interaction=cfg.interaction, style=cfg.style,
                            solver=cfg.solver, guard_spacing_m=cfg.guard_spacing_m,
                            max_probes_per_link=cfg.max_probes_per_link, seed=cfg.seed, stance=cfg.stance)
    built = time.perf_counter()
    sol = solve_sequence(problem, progress)
    solved = time.perf_counter()

    dt = 1.0 / demo.fps
    meshes = {o.name: o for o in demo.objects}
    objects = []
    for track in problem.channels[1:]:
        free = [i for i, o in enumerate(problem.objects) if o.name == track.name]
        pos = sol.obj_pos[:, free[0]] if free else track.pos_w
        quat = matrix_to_quat(sol.obj_rot[:, free[0]] if free else track.rot_w)
        src = meshes[track.name]
        objects.append(ObjectTrack(track.name, pos, quat, linear_velocity_from_positions(pos, dt),
                                   angular_velocity_from_quats(quat, dt), src.vertices, src.faces))
    contacts = ContactAnnotations(BODY_NAMES, tuple(t.name for t in problem.channels), sol.contacts, sol.witness_c)
    iterations = np.array([s.iterations for s in sol.stats])
    rows = np.concatenate([s.qp_rows for s in sol.stats if s.qp_rows] or [np.zeros(1)])
    metadata = {
        "generator": "otr-gym retarget (OTRetarget)",
        "mode": cfg.mode, "scale": mode_scale(demo, cfg.mode), "fps": demo.fps,
        "source": {"name": demo.name, **{k: v for k, v in demo.source.items() if _jsonable(v)}},
        "config": dataclasses.asdict(cfg),
        "free_objects": [o.name for o in problem.objects],
        "solver": {
            "frames": len(iterations), "iterations_mean": float(iterations.mean()),
            "iterations_max": int(iterations.max()), "rejected_steps": int(sum(s.rejected for s in sol.stats)),
            "qp_rows_mean": float(rows.mean()), "qp_rows_max": int(rows.max()),
            "qp_variables": problem.num_variables, "qp_failures": sol.qp_failures,
            "min_distance_m": float(min(s.min_distance_m for s in sol.stats)),
            "min_self_distance_m": float(min(s.min_self_distance_m for s in sol.stats)),
            "setup_s": built - start, "solve_s": solved - built,
            "ms_per_frame": 1000.0 * (solved - built) / len(iterations),
        },
    }
    return Reference.from_qpos(sol.qpos, demo.fps, objects=objects, contacts=contacts, metadata=metadata)


def _jsonable(v) -> bool:
    return isinstance(v, (str, int, float, bool)) or v is None


# ------------------------------------------------------------------ batch


@dataclass(frozen=True)
class Job:
    source: Path
    output: Path


def collect_jobs(inputs: list[Path], out: Path) -> list[Job]:
    """One job per input file; folders contribute their .npz/.pt files (recursively, sorted)
    with their sub-folders kept under ``out``. Missing inputs still make a job (it fails with
    a clear message); two inputs mapping to one output are an error."""
    jobs: list[Job] = []
    for item in inputs:
        item = Path(item)
        if item.is_dir():
            files = sorted(p for p in item.rglob("*") if p.suffix in INPUT_SUFFIXES and p.is_file())
            jobs += [Job(p, out / p.relative_to(item).with_suffix(".npz")) for p in files]
        else:
            jobs.append(Job(item, out / f"{item.stem}.npz"))
    seen: dict[Path, Path] = {}
    for job in jobs:
        if job.output in seen:
            raise ConfigError(f"inputs {seen[job.output]} and {job.source} would both write {job.output}")
        seen[job.output] = job.source
    return jobs


def _one_thread_per_worker() -> None:
    """Spawned workers inherit this environment before importing NumPy: one BLAS/OpenMP thread
    each, since the QPs are small and the processes give the parallelism."""
    for key in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[key] = "1"


def run_job(job: Job, cfg: RetargetConfig, object_mesh: Path | None, frame_bar: bool = False) -> tuple[str, str]:
    """Retarget one file; returns (status, message) with status 'done' or 'failed' (never raises)."""
    try:
        from retarget.demos import load_demonstration

        demo = load_demonstration(job.source, object_mesh)
        progress = None
        if frame_bar:
            from tqdm import tqdm

            total = demo.num_frames if cfg.fps is None else int(np.floor((demo.num_frames - 1) / demo.fps * cfg.fps
                                                                            + 1e-9)) + 1
            bar = tqdm(total=total, desc=job.source.name, unit="frame", leave=False)

            def progress(_t: int) -> None:
                bar.update(1)
        reference = retarget_demonstration(demo, cfg, progress)
        if frame_bar:
            bar.close()
        reference.save(job.output)
        solver = reference.metadata["solver"]
        return "done", (f"{job.output} ({solver['frames']} frames, {solver['ms_per_frame']:.1f} ms/frame, "
                        f"min distance {1000 * solver['min_distance_m']:.2f} mm)")
    except Exception as exc:  # one clip's failure must not stop the batch
        detail = "" if isinstance(exc, (ValueError, FileNotFoundError)) else "\n" + traceback.format_exc()
        return "failed", f"{job.source}: {type(exc).__name__}: {exc}{detail}"


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("inputs", nargs="+", type=Path, metavar="INPUT",
                   help="demonstration files (AMASS .npz, OMOMO .pt, our .npz) or folders of them")
    p.add_argument("--out", type=Path, required=True, help="output folder for the references (.npz)")
    p.add_argument("--object", type=Path, default=None, metavar="MESH",
                   help="object mesh for OMOMO clips (default: looked up next to the clip)")
    p.add_argument("--mode", choices=("native", "scaled", "robot-only"), default=None,
                   help="native scene (default), scaled with the object fixed, or ground only")
    p.add_argument("--fps", type=float, default=None, help="output and solve rate in Hz (default: 50)")
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes (default: 1)")
    p.add_argument("--config", type=Path, default=None, help="YAML configuration (default: the built-in defaults)")
    p.add_argument("--overwrite", action="store_true", help="redo clips whose output already exists")


def main(args: argparse.Namespace) -> int:
    try:
        cfg = load_config(args.config, mode=args.mode, fps=args.fps)
        jobs = collect_jobs(list(args.inputs), Path(args.out))
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.workers < 1:
        print(f"error: --workers must be >= 1, got {args.workers}", file=sys.stderr)
        return 2
    todo = [j for j in jobs if args.overwrite or not j.output.is_file()]
    skipped = len(jobs) - len(todo)
    if skipped:
        print(f"{skipped} of {len(jobs)} outputs already exist: skipped (use --overwrite to redo them)")
    results = run_batch(todo, functools.partial(run_job, cfg=cfg, object_mesh=args.object), args.workers,
                        "retarget", "clip")
    failures = [message for _, status, message in results if status == "failed"]
    done = len(todo) - len(failures)
    print(f"retargeted {done}, skipped {skipped}, failed {len(failures)} (of {len(jobs)})")
    for message in failures:
        print(f"FAILED {message}", file=sys.stderr)
    return 1 if failures else 0


def run_batch(jobs: list, run: Callable[..., tuple[str, str]], workers: int, desc: str,
              unit: str) -> list[tuple[object, str, str]]:
    """Run ``run(job, frame_bar=…) -> (status, message)`` over ``jobs`` behind a progress bar:
    in this process with a per-job frame bar (one worker), else in ``workers`` spawned processes
    (``run`` and the jobs must pickle). ``run`` never raises: status 'failed' is reported and the
    batch goes on, 'warning' is reported as one, anything else as written. Returns
    (job, status, message) in completion order."""
    from tqdm import tqdm

    results: list[tuple[object, str, str]] = []
    bar = tqdm(total=len(jobs), desc=desc, unit=unit)
    if workers == 1 or len(jobs) <= 1:
        for job in jobs:
            status, message = run(job, frame_bar=True)
            _report(bar, status, message)
            results.append((job, status, message))
    else:
        _one_thread_per_worker()
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
            futures = {pool.submit(run, job): job for job in jobs}
            for fut in as_completed(futures):
                status, message = fut.result()
                _report(bar, status, message)
                results.append((futures[fut], status, message))
    bar.close()
    return results


def _report(bar, status: str, message: str) -> None:
    if status == "failed":
        bar.write(f"failed: {message.splitlines()[0]}")
    elif status == "warning":
        bar.write(f"warning: {message}")
    else:
        bar.write(f"wrote {message}")
    bar.update(1)
