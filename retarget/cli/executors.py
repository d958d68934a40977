"""Where a batch's clips run, behind one interface: this process, local processes or Ray.

All three produce the same bytes (``retarget.cli.batch.retarget_bytes``; .npz members carry no
time stamp, the metadata no wall-clock time).
"""

from __future__ import annotations

import argparse
import functools
import multiprocessing
import os
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed

from retarget.cli.batch import ClipResult, Job, Task, retarget_bytes, run_job

ONE_THREAD = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")

def _one_thread_per_worker() -> None:
    """Spawned workers inherit this environment before importing NumPy: one BLAS/OpenMP thread
    each, since the QPs are small and the processes give the parallelism."""
    for key in ONE_THREAD:
        os.environ[key] = "1"

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

def make_executor(args: argparse.Namespace):
    if args.ray is not None:
        return RayExecutor(args.ray or None, args.workers)
    workers = args.workers or 1
    return SerialExecutor() if workers == 1 else ProcessExecutor(workers)

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
