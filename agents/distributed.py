"""Several processes training one policy: torch.distributed as rsl-rl-lib 5.x expects it.

``torchrun --nproc-per-node N -m otr_gym.cli train …`` (or ``otr train --gpus N``, which
re-launches itself through torchrun) starts N processes with WORLD_SIZE/RANK/LOCAL_RANK set.
Each process (rank):

- steps its own MuJoCo-Warp worlds (``--num-envs`` per rank) on its own GPU, ``cuda:LOCAL_RANK``
  (``--device cpu``: on the CPU, for tests);
- seeds its environment and torch with ``seed + rank``, so ranks explore differently;
- runs rsl-rl's PPO, whose distributed mode broadcasts rank 0's parameters at the start,
  averages every minibatch's gradients (all-reduce, then ÷ world size), averages the KL of the
  adaptive learning rate and pools the observation normalisers' statistics;
- and rank 0 alone writes the run folder: config, checkpoints, TensorBoard.

The process group is created here, before the environment is built (NCCL for CUDA, gloo for
the CPU), so that the ranks can agree on the run folder; ``agents.runner.TrackingRunner`` then
hands it to rsl-rl. The same command without torchrun is an ordinary one-GPU run.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass

import torch

from agents.devices import resolve_device


@dataclass(frozen=True)
class Context:
    world_size: int
    rank: int
    local_rank: int
    device: torch.device

    @property
    def is_distributed(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def launched_by_torchrun() -> bool:
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def setup(device: str | None) -> Context:
    """The process's rank and device; in a torchrun launch also the process group."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size <= 1:
        return Context(1, 0, 0, resolve_device(device))
    rank, local_rank = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    wanted = resolve_device(device)
    if wanted.type == "cuda":
        if wanted.index not in (None, local_rank):
            raise ValueError(f"--device {device}: under torchrun every rank uses cuda:LOCAL_RANK "
                             f"(this is rank {rank}, LOCAL_RANK {local_rank}); pass --device cuda")
        if local_rank >= torch.cuda.device_count():
            raise ValueError(f"LOCAL_RANK {local_rank}: only {torch.cuda.device_count()} CUDA device(s) on this host "
                             "(--nproc-per-node must not exceed the GPU count)")
        torch.cuda.set_device(local_rank)
        wanted, backend = torch.device("cuda", local_rank), "nccl"
    else:
        backend = "gloo"
    if not torch.distributed.is_initialized():
        torch.distributed.init_process_group(backend=backend, rank=rank, world_size=world_size,
                                             device_id=wanted if backend == "nccl" else None)
    return Context(world_size, rank, local_rank, wanted)


def broadcast_object(value, ctx: Context):
    """Rank 0's ``value`` on every rank."""
    if not ctx.is_distributed:
        return value
    box = [value]
    torch.distributed.broadcast_object_list(box, src=0)
    return box[0]


def shutdown(ctx: Context) -> None:
    if ctx.is_distributed and torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()


def torchrun_command(gpus: int, argv: list[str]) -> list[str]:
    """The torchrun command that runs ``otr train`` with ``argv`` (``--gpus`` removed) on
    ``gpus`` processes of this host."""
    rest, skip = [], False
    for arg in argv:
        if skip:
            skip = False
            continue
        if arg == "--gpus":
            skip = True
            continue
        if arg.startswith("--gpus="):
            continue
        rest.append(arg)
    return [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={gpus}",
            "-m", "otr_gym.cli", *rest]
