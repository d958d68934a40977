"""One rank of the 2-process test of tests/test_distributed.py, started by torchrun:

    python -m torch.distributed.run --standalone --nproc-per-node=2 tests/distributed_worker.py OUT train ...

Runs ``otr train ...`` (gloo on the CPU) with two probes around rsl-rl, changing nothing:

- around ``PPO.reduce_parameters`` (the gradient all-reduce of every minibatch): this rank's
  gradient before, the result after, and every rank's gradient before (all-gathered), reduced
  to figures: the largest deviation of the result from the mean of the ranks' gradients, and
  how much the ranks' gradients differ (so that agreeing is not trivial);
- around ``TrackingRunner.learn``: the rank's parameters, normalisers and sampler statistics at
  the end (also when the run stops early), written to OUT/rank<r>.pt.
"""

from __future__ import annotations

import sys
from itertools import chain
from pathlib import Path

import torch
from rsl_rl.algorithms import PPO

from agents.runner import TrackingRunner
from otr_gym import cli


def main() -> int:
    out, argv = Path(sys.argv[1]), sys.argv[2:]
    records: list[dict] = []
    reduce_parameters, learn = PPO.reduce_parameters, TrackingRunner.learn

    def probed_reduce(self) -> None:
        params = [p for p in chain(self.actor.parameters(), self.critic.parameters()) if p.grad is not None]
        local = torch.cat([p.grad.reshape(-1) for p in params]).clone()
        reduce_parameters(self)
        reduced = torch.cat([p.grad.reshape(-1) for p in params])
        every = [torch.zeros_like(local) for _ in range(torch.distributed.get_world_size())]
        torch.distributed.all_gather(every, local)
        every = torch.stack(every)
        records.append({"deviation": float((reduced - every.mean(0)).abs().max()),
                        "rank_spread": float((every[0] - every[1]).abs().max()),
                        "scale": float(every.abs().max())})

    def probed_learn(self, *args, **kwargs):
        try:
            return learn(self, *args, **kwargs)
        finally:
            state = self.alg.save()
            torch.save({"actor": state["actor_state_dict"], "critic": state["critic_state_dict"],
                        "env": self.env.state_dict(), "records": records, "iteration": self.current_learning_iteration,
                        "rank": torch.distributed.get_rank(), "world_size": torch.distributed.get_world_size()},
                       out / f"rank{torch.distributed.get_rank()}.pt")

    PPO.reduce_parameters = probed_reduce
    TrackingRunner.learn = probed_learn
    return cli.main(argv)


if __name__ == "__main__":
    sys.exit(main())
