"""Demonstrations in, G1 references out: the retarget driver and the ``otr retarget`` command.

``retarget_demonstration(demo, cfg) -> Reference`` runs the whole method on one demonstration
(resampling, probes, correspondences, SQP, reference assembly). The command line runs it over
files and folders:

    otr retarget INPUT… --out DIR [--object MESH] [--mode native|scaled|robot-only]
                 [--workers N] [--ray [ADDRESS]] [--fps 50] [--config YAML] [--overwrite]
                 [--skeleton-map YAML] [--units UNIT] [--up AXIS]

Inputs are AMASS ``.npz`` (SMPL-X / SMPL-H parameters), OMOMO InterMimic ``.pt`` clips, BVH
files and our demonstration ``.npz`` files, or folders of them (searched recursively). Every
input becomes ``DIR/<name>.npz`` (folder inputs keep their sub-folders). A batch is resumable:
finished outputs are skipped (writes are atomic, so an existing file is complete), a failing
clip is reported with its file and error and the batch goes on; the exit code is 1 if any clip
failed. ``DIR/retarget_summary.json`` lists every clip (status, frames, ms/frame, worker).

Where clips run (executors, one interface): in this process (default), ``--workers N`` local
processes, or ``--ray [ADDRESS]`` Ray tasks on a cluster. All three produce the same bytes
(``retarget_bytes``; .npz members carry no time stamp, the metadata no wall-clock time).

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
import socket
import sys
import time
import traceback
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from otr_gym.config import from_dict, load_yaml_mapping
from retarget.flight import FlightConfig
from retarget.geometry import GeometryConfig
from retarget.problem import SolverConfig
from retarget.residuals import InteractionConfig
from retarget.stance import StanceConfig
from retarget.style import StyleConfig

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs" / "retarget"
INPUT_SUFFIXES = (".npz", ".pt", ".bvh")


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
    #: Which G1 links share one OT plan with their human parts (``retarget.human.LINK_GROUPINGS``:
    #: none | hand | shared_parts); "none" matches each link alone, as the references were made.
    links_together: str = "none"
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    interaction: InteractionConfig = field(default_factory=InteractionConfig)
    style: StyleConfig = field(default_factory=StyleConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    stance: StanceConfig = field(default_factory=StanceConfig)
    flight: FlightConfig = field(default_factory=FlightConfig)


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
    from retarget.problem import MODES, link_clearance

    if cfg.mode not in MODES:
        raise ConfigError(f"unknown mode '{cfg.mode}' (choose from {MODES})")
    from retarget.human import link_grouping

    try:
        link_grouping(cfg.links_together)
        link_clearance(cfg.solver.link_clearance_m)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    if cfg.fps is not None and not cfg.fps > 0:
        raise ConfigError(f"fps must be > 0, got {cfg.fps}")
    return cfg


# ------------------------------------------------------------------ one demonstration


def retarget_demonstration(demo, cfg: RetargetConfig = RetargetConfig(), progress=None):
    """Retarget one Demonstration to a G1 ``Reference`` (see the module doc for the rate).

    ``progress(t)`` is called after each solved frame (of both passes when ``cfg.flight`` solves
    the clip twice). The reference carries the free and fixed
    objects' tracks (with meshes), per-link contact annotations against every channel, and
    metadata (mode, scale, weights, source, solver statistics). Wall-clock times are not in
    it (``retarget_timed`` returns them), so the same clip always gives the same file.
    """
    return retarget_timed(demo, cfg, progress)[0]


@dataclass(frozen=True)
class Timing:
    """Where one clip's time went (s), and the solve time per output frame (ms)."""

    setup_s: float
    solve_s: float
    frames: int

    @property
    def ms_per_frame(self) -> float:
        return 1000.0 * self.solve_s / max(self.frames, 1)


def problem_from_config(demo, cfg: RetargetConfig):
    """``retarget.problem.build_problem`` of ``demo`` (at its own fps) with every setting of ``cfg``."""
    from retarget.problem import build_problem

    return build_problem(demo, cfg.mode, geometry=cfg.geometry, interaction=cfg.interaction, style=cfg.style,
                         solver=cfg.solver, guard_spacing_m=cfg.guard_spacing_m,
                         max_probes_per_link=cfg.max_probes_per_link, seed=cfg.seed, stance=cfg.stance,
                         links_together=cfg.links_together)


def retarget_timed(demo, cfg: RetargetConfig = RetargetConfig(), progress=None):
    """``retarget_demonstration`` that also returns its ``Timing``."""
    from otr_gym.reference import ContactAnnotations, ObjectTrack, Reference
    from otr_gym.robot import BODY_NAMES
    from otr_gym.rotations import (
        angular_velocity_from_quats,
        linear_velocity_from_positions,
        matrix_to_quat,
    )
    from retarget.kernel_warmup import finish_warmup
    from retarget.flight import ballistic_problem
    from retarget.problem import mode_scale, resample_demonstration
    from retarget.solver import solve_sequence

    start = time.perf_counter()
    if cfg.fps is not None:
        demo = resample_demonstration(demo, cfg.fps)
    problem = problem_from_config(demo, cfg)
    finish_warmup()  # the kernels a first run's command line began compiling beside the grids
    built = time.perf_counter()
    sol = solve_sequence(problem, progress)
    # a clip that leaves the ground is solved again with its flights thrown (retarget.flight)
    thrown = ballistic_problem(problem, sol, cfg.flight) if cfg.flight.enabled else None
    flight = {"passes": 1}
    if thrown is not None:
        problem, stats = thrown
        sol = solve_sequence(problem, progress)
        flight = {"passes": 2, **stats}
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
        },
        "flight": flight,
    }
    reference = Reference.from_qpos(sol.qpos, demo.fps, objects=objects, contacts=contacts, metadata=metadata)
    return reference, Timing(built - start, solved - built, len(iterations))


def _jsonable(v) -> bool:
    return isinstance(v, (str, int, float, bool)) or v is None


# ------------------------------------------------------------------ batch


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


def _one_thread_per_worker() -> None:
    """Spawned workers inherit this environment before importing NumPy: one BLAS/OpenMP thread
    each, since the QPs are small and the processes give the parallelism."""
    for key in ONE_THREAD:
        os.environ[key] = "1"


ONE_THREAD = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


@dataclass(frozen=True)
class Task:
    """What every worker needs besides the job: the same for the whole batch."""

    cfg: RetargetConfig
    object_mesh: Path | None = None
    bvh: object = None  # retarget.bvh.BvhOptions


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


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def retarget_bytes(job: Job, task: Task, frame_bar: bool = False) -> tuple[ClipResult, bytes | None]:
    """Retarget one file to the bytes of its reference ``.npz`` (never raises: a failure is a
    'failed' result naming the file). Every executor goes through here, so their outputs are
    the same bytes."""
    start = time.perf_counter()
    try:
        from otr_gym.io import npz_bytes
        from retarget.demos import load_demonstration

        demo = load_demonstration(job.source, task.object_mesh, bvh=task.bvh)
        progress, bar = None, None
        if frame_bar:
            from tqdm import tqdm

            cfg = task.cfg
            total = demo.num_frames if cfg.fps is None else int(np.floor((demo.num_frames - 1) / demo.fps * cfg.fps
                                                                            + 1e-9)) + 1
            bar = tqdm(total=total, desc=job.source.name, unit="frame", leave=False)

            def progress(_t: int) -> None:
                if bar.n == bar.total:  # the ballistic second pass (retarget.flight) starts over
                    bar.total += total
                    bar.set_description(f"{job.source.name} (ballistic pass)")
                bar.update(1)
        reference, timing = retarget_timed(demo, task.cfg, progress)
        if bar is not None:
            bar.close()
        reference.validate()
        data = npz_bytes(reference.to_arrays())
        solver = reference.metadata["solver"]
        message = (f"{job.output} ({timing.frames} frames, {timing.ms_per_frame:.1f} ms/frame, "
                   f"min distance {1000 * solver['min_distance_m']:.2f} mm)")
        return ClipResult(str(job.source), str(job.output), "done", message, timing.frames, timing.ms_per_frame,
                          time.perf_counter() - start, worker_name()), data
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


# ------------------------------------------------------------------ executors: where the clips run


class SerialExecutor:
    """Clips one after the other in this process, with a per-frame bar."""

    name = "serial"

    def map(self, fn: Callable, jobs: list) -> Iterator[tuple[object, object]]:
        """(job, fn(job, frame_bar=True)) for every job, in order."""
        for job in jobs:
            yield job, fn(job, frame_bar=True)

    def run(self, jobs: list[Job], task: Task) -> Iterator[ClipResult]:
        for _, result in self.map(functools.partial(run_job, task=task), jobs):
            yield result

    def close(self) -> None:
        pass


class ProcessExecutor:
    """``--workers N``: N spawned processes on this machine."""

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self.name = f"{workers} local processes"

    def map(self, fn: Callable, jobs: list) -> Iterator[tuple[object, object]]:
        """(job, fn(job)) for every job, in completion order (``fn`` and the jobs must pickle)."""
        _one_thread_per_worker()
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=self.workers, mp_context=context) as pool:
            futures = {pool.submit(fn, job): job for job in jobs}
            for fut in as_completed(futures):
                yield futures[fut], fut.result()

    def run(self, jobs: list[Job], task: Task) -> Iterator[ClipResult]:
        for _, result in self.map(functools.partial(run_job, task=task), jobs):
            yield result

    def close(self) -> None:
        pass


class RayExecutor:
    """``--ray [ADDRESS]``: one Ray task per clip on a Ray cluster (a local one without ADDRESS).

    Workers return the reference's bytes and this process writes them (atomically), so only
    the inputs must be readable on every node (a shared file system); the output folder is
    this machine's. A task whose worker dies (killed, out of memory, node lost) is retried
    once (``max_retries=1``); a clip that raises is a 'failed' result, not a retry. At most
    ``workers`` tasks are in flight (default: the cluster's CPUs).
    """

    def __init__(self, address: str | None, workers: int | None = None) -> None:
        import ray

        self._ray = ray
        env = {"env_vars": {key: "1" for key in ONE_THREAD}}
        if address:
            ray.init(address=address, runtime_env=env, log_to_driver=False, ignore_reinit_error=True)
        else:
            ray.init(num_cpus=workers or os.cpu_count(), runtime_env=env, include_dashboard=False,
                     log_to_driver=False, ignore_reinit_error=True)
        self.slots = max(1, workers or int(ray.cluster_resources().get("CPU", 1)))
        self.name = f"Ray ({'cluster ' + address if address else 'local'}, {self.slots} at a time)"
        self._remote = ray.remote(num_cpus=1, max_retries=1)(_ray_task)

    def run(self, jobs: list[Job], task: Task, task_fn=None) -> Iterator[ClipResult]:
        """``task_fn`` replaces ``retarget_bytes`` (tests: a worker that dies)."""
        ray = self._ray
        remote = self._remote if task_fn is None else ray.remote(num_cpus=1, max_retries=1)(task_fn)
        task_ref = ray.put(task)
        pending: dict = {}
        queue = list(jobs)
        while queue or pending:
            while queue and len(pending) < self.slots:
                job = queue.pop(0)
                pending[remote.remote(job, task_ref)] = job
            ready, _ = ray.wait(list(pending), num_returns=1)
            job = pending.pop(ready[0])
            try:
                result, data = ray.get(ready[0])
            except ray.exceptions.RayError as exc:  # the worker died on both attempts
                yield ClipResult(str(job.source), str(job.output), "failed",
                                 f"{job.source}: worker lost twice ({type(exc).__name__}: "
                                 f"{str(exc).splitlines()[0]})")
                continue
            if data is not None:
                from otr_gym.io import atomic_write

                atomic_write(job.output, lambda f, data=data: f.write(data))
            yield result

    def close(self) -> None:
        self._ray.shutdown()


def _ray_task(job: Job, task: Task) -> tuple[ClipResult, bytes | None]:
    import ray

    result, data = retarget_bytes(job, task)
    ctx = ray.get_runtime_context()
    result.worker = f"{ray.util.get_node_ip_address()}:{os.getpid()} (node {ctx.get_node_id()[:8]})"
    return result, data


# ------------------------------------------------------------------ the command


SUMMARY_NAME = "retarget_summary.json"


def configure_parser(p: argparse.ArgumentParser) -> None:
    from retarget.bvh import add_arguments

    p.add_argument("inputs", nargs="+", type=Path, metavar="INPUT",
                   help="demonstration files (AMASS .npz, OMOMO .pt, BVH .bvh, our .npz) or folders of them")
    p.add_argument("--out", type=Path, required=True, help="output folder for the references (.npz)")
    p.add_argument("--object", type=Path, default=None, metavar="MESH",
                   help="object mesh for OMOMO clips (default: looked up next to the clip)")
    p.add_argument("--mode", choices=("native", "scaled", "robot-only"), default=None,
                   help="native scene (default), scaled with the object fixed, or ground only")
    p.add_argument("--fps", type=float, default=None, help="output and solve rate in Hz (default: 50)")
    p.add_argument("--workers", type=int, default=None,
                   help="parallel worker processes (default: 1); with --ray, tasks in flight (default: the "
                        "cluster's CPUs)")
    p.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="run the clips as Ray tasks: on the cluster at ADDRESS (e.g. 10.0.0.1:6379, 'auto'), "
                        "or on a local Ray started for this run when no address is given")
    p.add_argument("--config", type=Path, default=None, help="YAML configuration (default: the built-in defaults)")
    p.add_argument("--overwrite", action="store_true", help="redo clips whose output already exists")
    add_arguments(p)


def make_executor(args: argparse.Namespace):
    if args.ray is not None:
        return RayExecutor(args.ray or None, args.workers)
    workers = args.workers or 1
    return SerialExecutor() if workers == 1 else ProcessExecutor(workers)


def main(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from otr_gym.io import write_json
    from retarget.bvh import options_from_args
    from retarget.kernel_warmup import start_warmup, stop_warmup

    try:
        cfg = load_config(args.config, mode=args.mode, fps=args.fps)
        jobs = collect_jobs(list(args.inputs), Path(args.out))
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.workers is not None and args.workers < 1:
        print(f"error: --workers must be >= 1, got {args.workers}", file=sys.stderr)
        return 2
    task = Task(cfg, args.object, options_from_args(args))
    todo = [j for j in jobs if args.overwrite or not j.output.is_file()]
    done_before = [j for j in jobs if j not in todo]
    if done_before:
        print(f"{len(done_before)} of {len(jobs)} outputs already exist: skipped (use --overwrite to redo them)")
    results = [ClipResult(str(j.source), str(j.output), "skipped", "output exists") for j in done_before]
    summary_path = Path(args.out) / SUMMARY_NAME
    executor = make_executor(args) if todo else SerialExecutor()
    if todo and isinstance(executor, SerialExecutor):  # a pool's processes keep every core busy already
        start_warmup()  # a first run compiles the solver's kernels beside its grids (retarget.kernel_warmup)
    start = time.perf_counter()
    bar = tqdm(total=len(todo), desc="retarget", unit="clip")
    try:
        for result in executor.run(todo, task):
            results.append(result)
            _report(bar, result)
            write_json(summary_path, _summary(results, executor.name, time.perf_counter() - start))
    finally:
        bar.close()
        executor.close()
        stop_warmup()
    write_json(summary_path, _summary(results, executor.name, time.perf_counter() - start))
    failures = [r for r in results if r.status == "failed"]
    print(f"retargeted {len(todo) - len(failures)}, skipped {len(done_before)}, failed {len(failures)} "
          f"(of {len(jobs)}); summary {summary_path}")
    for r in failures:
        print(f"FAILED {r.message}", file=sys.stderr)
    return 1 if failures else 0


def run_batch(jobs: list, run: Callable[..., tuple[str, str]], workers: int, desc: str,
              unit: str) -> list[tuple[object, str, str]]:
    """Any batch besides ``otr retarget``'s (``otr variants``): ``run(job, frame_bar=…) ->
    (status, message)`` over ``jobs`` behind a progress bar, here (one worker, with a per-job
    frame bar) or in ``workers`` spawned processes. ``run`` never raises: status 'failed' is
    reported and the batch goes on, 'warning' is reported as one. Returns (job, status,
    message) in completion order."""
    from tqdm import tqdm

    executor = SerialExecutor() if workers == 1 or len(jobs) <= 1 else ProcessExecutor(workers)
    results: list[tuple[object, str, str]] = []
    bar = tqdm(total=len(jobs), desc=desc, unit=unit)
    try:
        for job, (status, message) in executor.map(run, jobs):
            if status in ("failed", "warning"):
                bar.write(f"{status}: {message.splitlines()[0] if status == 'failed' else message}")
            bar.update(1)
            results.append((job, status, message))
    finally:
        bar.close()
    return results


def _summary(results: list[ClipResult], executor: str, seconds: float) -> dict:
    done = [r for r in results if r.status == "done"]
    frames = sum(r.frames or 0 for r in done)
    return {"executor": executor, "wall_s": seconds, "clips": len(results),
            "done": len(done), "failed": sum(r.status == "failed" for r in results),
            "skipped": sum(r.status == "skipped" for r in results), "frames": frames,
            "clips_per_minute": 60.0 * len(done) / seconds if seconds > 0 else None,
            "results": [dataclasses.asdict(r) for r in results]}


def _report(bar, result: ClipResult) -> None:
    if result.status == "failed":
        bar.write(f"failed: {result.message.splitlines()[0]}")
    else:
        bar.write(f"wrote {result.message}")
    bar.update(1)
