"""Where a batch's clips run, behind one interface: this process, local processes or Ray.

All three produce the same bytes (``retarget.cli.batch.retarget_bytes``; .npz members carry no
time stamp, the metadata no wall-clock time), and every clip gives exactly one result: a clip
whose worker process dies or whose task errors is a 'failed' result naming its file
(``retarget.cli.batch.lost_result``), never a lost clip or a stopped batch.
"""

from __future__ import annotations

import argparse
import functools
import multiprocessing
import os
import signal
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from retarget.cli.batch import ClipResult, Job, Task, lost_result, retarget_bytes, run_job, write_output

ONE_THREAD = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
#: ``lost(job, why)``: the result standing for a job that gave none (``retarget.cli.batch.lost_result``)
Lost = Callable[[Any, str], Any]
#: fresh interpreters, which import NumPy under ``ONE_THREAD``'s settings (a fork would copy this process's threads)
_SPAWN = multiprocessing.get_context("spawn")

def _one_thread_per_worker() -> None:
    """Spawned workers inherit this environment before importing NumPy: one BLAS/OpenMP thread
    each, since the QPs are small and the processes give the parallelism."""
    for key in ONE_THREAD:
        os.environ[key] = "1"

class SerialExecutor:
    """Clips one after the other in this process, with a per-frame bar."""

    name = "serial"

    def map(self, fn: Callable, jobs: list, lost: Lost) -> Iterator[tuple[Any, Any]]:
        """(job, fn(job, frame_bar=True)) for every job, in order, or (job, lost(job, why)) where
        ``fn`` raised. A job that kills this process ends the batch (its summary so far is written)."""
        for job in jobs:
            try:
                outcome = fn(job, frame_bar=True)
            except Exception as exc:
                outcome = lost(job, f"{type(exc).__name__}: {exc}")
            yield job, outcome

    def run(self, jobs: list[Job], task: Task) -> Iterator[ClipResult]:
        for _, result in self.map(functools.partial(run_job, task=task), jobs, lost_result):
            yield result

    def close(self) -> None:
        pass

class ProcessExecutor:
    """``--workers N``: N spawned processes on this machine.

    At most N jobs are in flight, so when a worker process dies (killed, out of memory, a crash
    in native code; the pool then fails every job in it) the jobs it may have been running are
    known: each runs once more alone in a fresh process, and the rest go on in a new pool. A job
    that kills its lone process too is lost, naming the signal or exit code.
    """

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self.name = f"{workers} local processes"

    def map(self, fn: Callable, jobs: list, lost: Lost) -> Iterator[tuple[Any, Any]]:
        """(job, fn(job)) for every job, in completion order (``fn`` and the jobs must pickle), or
        (job, lost(job, why)) where ``fn`` raised or its process died twice."""
        _one_thread_per_worker()
        queue = list(jobs)
        while queue:
            suspects: list = []
            yield from self._pool_round(fn, queue, lost, suspects)
            for job in suspects:
                yield job, _alone(fn, job, lost)

    def _pool_round(self, fn: Callable, queue: list, lost: Lost, suspects: list) -> Iterator[tuple[Any, Any]]:
        """Jobs from ``queue`` (consumed) in one pool until it is empty or a worker dies; the jobs
        in flight when one died are appended to ``suspects``."""
        with ProcessPoolExecutor(max_workers=self.workers, mp_context=_SPAWN) as pool:
            running: dict[Future, Any] = {}
            while (queue and not suspects) or running:
                while queue and not suspects and len(running) < self.workers:
                    job = queue.pop(0)
                    running[pool.submit(fn, job)] = job
                finished, _ = wait(running, return_when=FIRST_COMPLETED)
                for fut in finished:
                    job = running.pop(fut)
                    exc = fut.exception()
                    if isinstance(exc, BrokenProcessPool):
                        suspects.append(job)
                    else:
                        yield job, (fut.result() if exc is None else lost(job, f"{type(exc).__name__}: {exc}"))

    def run(self, jobs: list[Job], task: Task, task_fn: Callable | None = None) -> Iterator[ClipResult]:
        """``task_fn(job, task)`` replaces ``run_job`` (tests: a worker that dies)."""
        fn = functools.partial(task_fn or run_job, task=task)
        for _, result in self.map(fn, jobs, lost_result):
            yield result

    def close(self) -> None:
        pass

def _alone(fn: Callable, job: Any, lost: Lost) -> Any:
    """``fn(job)`` in a fresh spawned process of its own: its result, or ``lost(job, why)`` when
    ``fn`` raises or the process dies."""
    receive, send = _SPAWN.Pipe(duplex=False)
    process = _SPAWN.Process(target=_send_outcome, args=(fn, job, send), daemon=True)
    process.start()
    send.close()  # the child holds the only writer: recv() ends with EOFError if it dies
    try:
        ok, value = receive.recv()
    except EOFError:
        process.join()
        code = process.exitcode or 0
        how = f"signal {_signal_name(-code)}" if code < 0 else f"exit code {code}"
        return lost(job, f"its worker process died ({how}; killed, out of memory or a crash in native code), "
                         "in the pool and again alone")
    process.join()
    return value if ok else lost(job, value)

def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:  # a real-time signal has no name
        return str(number)

def _send_outcome(fn: Callable, job: object, send) -> None:
    try:
        outcome = (True, fn(job))
    except Exception as exc:
        outcome = (False, f"{type(exc).__name__}: {exc}")
    send.send(outcome)

class RayExecutor:
    """``--ray [ADDRESS]``: one Ray task per clip on a Ray cluster (a local one without ADDRESS).

    Workers return the reference's bytes and this process writes them (atomically), so only
    the inputs must be readable on every node (a shared file system); the output folder is
    this machine's. A task whose worker dies (killed, out of memory, node lost) is retried
    once (``max_retries=1``); a clip that raises is a 'failed' result, not a retry, and so is a
    task that errors outside the clip. At most ``workers`` tasks are in flight (default: the
    cluster's CPUs).
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
            except ray.exceptions.RayTaskError as exc:  # the task raised outside retarget_bytes's guard
                yield lost_result(job, f"its Ray task raised {str(exc).splitlines()[0]}")
                continue
            except ray.exceptions.RayError as exc:  # the worker died on both attempts
                yield lost_result(job, f"worker lost twice ({type(exc).__name__}: {str(exc).splitlines()[0]})")
                continue
            yield write_output(job, result, data)

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
    reported and the batch goes on, 'warning' is reported as one; a job whose worker process
    dies is 'failed', named by its ``output``. Returns (job, status, message) in completion order."""
    from tqdm import tqdm

    executor = SerialExecutor() if workers == 1 or len(jobs) <= 1 else ProcessExecutor(workers)
    results: list[tuple[object, str, str]] = []
    bar = tqdm(total=len(jobs), desc=desc, unit=unit)
    try:
        for job, (status, message) in executor.map(run, jobs, _lost_variant):
            if status in ("failed", "warning"):
                bar.write(f"{status}: {message.splitlines()[0] if status == 'failed' else message}")
            bar.update(1)
            results.append((job, status, message))
    finally:
        bar.close()
    return results

def _lost_variant(job, why: str) -> tuple[str, str]:
    return "failed", f"{job.output}: {why}"
