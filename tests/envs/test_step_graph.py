"""The env step as one CUDA graph (envs.step_graph): what can be checked without a GPU.

A replayed graph reads and writes the addresses it saw at capture. ``StateSlots`` makes the
MDP's rebound tensor attributes keep those addresses; here every step of a real env (tracking
and box, CPU MuJoCo) is followed by the same pinning the capture does, and must give exactly
the results of plain steps while its state tensors stay the same objects. The replay itself is
checked on the GPU by ``benchmarks/env_throughput.py`` (graphed against eager, same actions).
"""

from __future__ import annotations

import pytest
import torch

from envs.box import make_box_task
from envs.step_graph import StateSlots, clone_outputs
from envs.tracking import make_task


class _Toy:
    """A step that rebinds its state, one attribute aliasing another's old value."""

    __module__ = "envs.toy"

    def __init__(self):
        self.cur = torch.tensor([1.0, 2.0])
        self.last = torch.zeros(2)
        self.count = 0

    def step(self, a: torch.Tensor) -> torch.Tensor:
        self.last = self.cur
        self.cur = self.cur + a
        return self.cur * 10


def test_pinning_copies_rebound_state_into_the_held_tensors_in_alias_safe_order():
    toy = _Toy()
    cur, last = toy.cur, toy.last
    slots = StateSlots(toy)
    slots.snapshot()
    toy.step(torch.tensor([0.5, 0.5]))
    slots.pin_rebound()
    assert toy.cur is cur and toy.last is last  # the attributes are the tensors the graph saw
    assert torch.equal(cur, torch.tensor([1.5, 2.5]))
    assert torch.equal(last, torch.tensor([1.0, 2.0]))  # the old value, not the just-copied new one


def test_restore_copies_an_assignment_made_outside_the_graph_and_rejects_a_wrong_shape():
    toy = _Toy()
    cur = toy.cur
    slots = StateSlots(toy)
    slots.snapshot()
    toy.step(torch.zeros(2))
    slots.pin_rebound()
    toy.cur = torch.tensor([7.0, 8.0])  # e.g. a trainer setting episode_length_buf
    slots.restore()
    assert toy.cur is cur and torch.equal(cur, torch.tensor([7.0, 8.0]))
    toy.cur = torch.zeros(3)
    with pytest.raises(ValueError, match="cur: assigned shape"):
        slots.restore()


def test_a_step_that_changes_host_state_is_refused():
    toy = _Toy()
    slots = StateSlots(toy)
    slots.snapshot()
    toy.step(torch.zeros(2))
    toy.count += 1  # a replay runs no Python: this would never happen again
    with pytest.raises(RuntimeError, match=r"_Toy.count"):
        slots.pin_rebound()


def test_outputs_are_cloned_through_nested_containers():
    x = torch.ones(2)
    out = clone_outputs((x, {"log": {"a": x}}, [x], 3))
    assert not any(t is x for t in (out[0], out[1]["log"]["a"], out[2][0])) and out[3] == 3
    assert torch.equal(out[1]["log"]["a"], x)


def _tensors(tree) -> list[torch.Tensor]:
    if isinstance(tree, torch.Tensor):
        return [tree]
    if isinstance(tree, dict):
        return [t for v in tree.values() for t in _tensors(v)]
    if isinstance(tree, (tuple, list)):
        return [t for v in tree for t in _tensors(v)]
    return []


@pytest.mark.parametrize("kind", ["track", "box"])
def test_pinned_steps_of_the_real_mdp_equal_plain_steps(kind, walking_reference, box_reference):
    """Training configuration (randomisation, noise, resets): 60 steps of random actions, with
    pushes, terminations and restarts, pinned after every step as the capture pins."""
    make, ref = (make_task, walking_reference) if kind == "track" else (make_box_task, box_reference)
    plain, pinned = (make(ref, 6, "mujoco", "cpu", seed=3) for _ in range(2))
    slots = StateSlots(pinned)
    slots.snapshot()
    held = {(id(s.owner), s.name): s.held for s in slots._before.values() if isinstance(s.held, torch.Tensor)}
    gen = torch.Generator().manual_seed(0)
    ended = 0
    for _ in range(60):
        a = 3.0 * torch.randn(6, 29, generator=gen)
        expected = plain.step(a)
        slots.snapshot()
        got = pinned._step(a)
        slots.pin_rebound()
        for e, g in zip(_tensors(expected), _tensors(got), strict=True):
            assert torch.equal(e, g)
        ended += int((expected[2] | expected[3]).sum())
        for s in slots._before.values():
            if (id(s.owner), s.name) in held:
                assert getattr(s.owner, s.name) is held[(id(s.owner), s.name)], s.name
    assert ended > 0  # the restart path ran
    assert pinned.step_graph is None  # CPU: no graph
