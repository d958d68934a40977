"""The whole env step in one CUDA graph: physics, rewards, terminations, resets, observations.

Why: profiled on an H200 at 8192 envs (docs/benchmarks.md, *Where the step's time goes*), the
step was host-bound: 8.96 ms of GPU kernels in a 17.3 ms step, the physics one captured warp
graph and the MDP ~700 small torch kernels launched one by one from Python, the GPU idle while
the host launched them. Replaying the step as one graph launches all of it with one call. (On an
H100, 2026-12-08, it gained only 3 %: the eager step was 3.2 ms over its own physics there; it
is off by default, docs/environment.md §1.)

How (``StepGraph``):

* **One stream, one graph.** torch captures the step on a side stream; the warp backend joins
  that capture (``PhysicsBackend.joined_capture``: warp on the same stream, the capture
  registered with warp as external) and launches its physics kernels eagerly into it instead of
  replaying its own graph (a graph cannot be launched into a capture).
* **State at fixed addresses.** The MDP keeps its state in tensor attributes that ``step``
  rebinds to new tensors (``self.frame = torch.where(...)``). A graph reads and writes the
  addresses it saw at capture, so at the end of the captured step every rebound attribute's new
  value is copied into the tensor the attribute held before the capture, and the attribute is
  bound back to it (``StateSlots``): the next replay reads what the last one wrote. Before each
  replay the same is done for attributes rebound outside the graph (an eager ``reset``, a
  trainer assigning ``episode_length_buf``), so eager calls between replays stay valid.
* **Fresh outputs.** A replay overwrites the graph's output buffers, so ``step`` returns clones
  (trainers keep a rollout's log tensors; rsl-rl averages them at the end).
* **Random numbers.** The task's generator is registered with the graph, so each replay draws
  new numbers (Philox offsets advance per replay) rather than the captured ones.
* **No host state.** A replay runs no Python: a step that changed a Python number or flag would
  not be replayed, so capture refuses one.

The first ``warmup`` calls run eagerly (warp modules load, torch initialises lazily); the next
call captures, then replays. Only the warp backend on a CUDA device is captured. A capture that
fails (a CUDA or driver limitation) leaves the state as before it, warns with the reason
(``StepGraph.error``) and the step runs eagerly from then on.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch

#: Attribute values a replay could not update: host state changed inside a captured step.
_HOST_TYPES = (bool, int, float, str)


@dataclass
class _Slot:
    owner: object
    name: str
    held: object  # the value the graph reads and writes (a tensor) or points to (an output object)


def _is_env_object(value: object) -> bool:
    """Objects of the environment's own classes (envs.*) whose attributes can hold MDP state:
    not frozen dataclasses (immutable: the tracking state, libraries of constants) nor this
    module's own."""
    cls = type(value)
    params = getattr(cls, "__dataclass_params__", None)
    return (hasattr(value, "__dict__") and not isinstance(value, type) and cls.__module__.startswith("envs.")
            and cls.__module__ != __name__ and not (params is not None and params.frozen))


def _env_objects(root: object) -> Iterator[object]:
    """``root`` and every environment object reachable through attributes, each once."""
    seen: set[int] = set()
    stack = [root]
    while stack:
        obj = stack.pop()
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        yield obj
        stack.extend(v for v in vars(obj).values() if _is_env_object(v))


class StateSlots:
    """The attributes of ``root``'s environment objects, pinned to the values a graph uses.

    ``snapshot`` before a capture records every attribute; ``pin_rebound`` at the end of the
    captured region copies each rebound tensor attribute into the tensor it held (inside the
    graph) and binds the attribute back, and keeps the rebound non-tensor attributes (per-step
    output objects such as the tracking state) as the graph's; ``restore`` before a replay does
    the same for attributes rebound since, outside the graph.
    """

    def __init__(self, root: object):
        self.root = root
        self._before: dict[tuple[int, str], _Slot] = {}
        self.slots: list[_Slot] = []

    def snapshot(self) -> None:
        self._before = {(id(o), n): _Slot(o, n, v) for o in _env_objects(self.root) for n, v in vars(o).items()}

    def pin_rebound(self) -> None:
        """Called inside the capture, after the step: see the class docstring."""
        now = [(s, getattr(s.owner, s.name)) for s in self._before.values()]
        rebound = [(s, new) for s, new in now if new is not s.held]
        host = [f"{type(s.owner).__name__}.{s.name}" for s, new in rebound if isinstance(new, _HOST_TYPES)]
        if host:
            raise RuntimeError(f"the env step changes host state a CUDA graph replay would not: {host}; "
                               "keep per-step state in tensors updated on the device")
        held_storage = {s.held.untyped_storage().data_ptr() for s in self._before.values()
                        if isinstance(s.held, torch.Tensor)}
        # A new value may alias another slot's held tensor (``last_action = action``): take all
        # such values before the first copy overwrites what they alias.
        copies = []
        for s, new in rebound:
            if isinstance(s.held, torch.Tensor) and isinstance(new, torch.Tensor):
                if new.untyped_storage().data_ptr() in held_storage:
                    new = new.clone()
                copies.append((s, new))
        for s, new in copies:
            if new.shape != s.held.shape or new.dtype != s.held.dtype:
                raise RuntimeError(f"{type(s.owner).__name__}.{s.name} changes shape or dtype in the step "
                                   f"({tuple(s.held.shape)} {s.held.dtype} -> {tuple(new.shape)} {new.dtype})")
            s.held.copy_(new)
            setattr(s.owner, s.name, s.held)
        tensor_rebound = {id(s) for s, _ in copies}
        self.slots = [s for s in self._before.values() if isinstance(s.held, torch.Tensor)]
        # output objects (new each step, e.g. the TrackingState): the graph's are kept
        self.slots += [_Slot(s.owner, s.name, new) for s, new in rebound if id(s) not in tensor_rebound]

    def rewind(self) -> None:
        """After a failed capture: every attribute back to its value before it. Nothing captured
        ran, so those values are the state before the step."""
        for s in self._before.values():
            setattr(s.owner, s.name, s.held)

    def restore(self) -> None:
        """Before a replay: attributes rebound outside the graph back onto the graph's values."""
        for s in self.slots:
            value = getattr(s.owner, s.name)
            if value is s.held:
                continue
            if isinstance(s.held, torch.Tensor):
                value = torch.as_tensor(value, device=s.held.device)
                if value.shape != s.held.shape:
                    raise ValueError(f"{type(s.owner).__name__}.{s.name}: assigned shape {tuple(value.shape)}, "
                                     f"the env's is {tuple(s.held.shape)}")
                s.held.copy_(value)
            setattr(s.owner, s.name, s.held)


def clone_outputs(tree):
    """Tensors of a nested dict/tuple/list structure cloned; everything else as is."""
    if isinstance(tree, torch.Tensor):
        return tree.clone()
    if isinstance(tree, dict):
        return {k: clone_outputs(v) for k, v in tree.items()}
    if isinstance(tree, (tuple, list)):
        return type(tree)(clone_outputs(v) for v in tree)
    return tree


class StepGraph:
    """``step(actions)`` of ``task`` as one replayed CUDA graph (see the module docstring).

    ``task`` provides ``backend`` (with ``joined_capture``), ``device``, ``generator`` and
    ``num_envs``/``num_actions``; ``eager_step`` is the step to capture.
    """

    def __init__(self, task, eager_step: Callable, warmup: int = 2):
        self.task, self.eager_step, self.warmup = task, eager_step, warmup
        self.calls = 0
        self.error: str | None = None  # why the capture failed (the step then runs eagerly)
        self.graph: torch.cuda.CUDAGraph | None = None
        self._actions: torch.Tensor | None = None
        self._outputs = None
        self._slots = StateSlots(task)

    def __call__(self, actions: torch.Tensor):
        self.calls += 1
        if self.error is not None or (self.graph is None and self.calls <= self.warmup):
            return self.eager_step(actions)
        if self.graph is None:
            try:
                self._capture(actions)
            except (RuntimeError, NotImplementedError) as exc:  # torch.AcceleratorError is a RuntimeError
                self.error = f"{type(exc).__name__}: {exc}".splitlines()[0]
                self._slots.rewind()
                warnings.warn(f"the env step could not be captured as a CUDA graph and runs eagerly from now "
                              f"on ({self.error}); sim.cuda_graph: false skips the attempt", RuntimeWarning,
                              stacklevel=2)
                return self.eager_step(actions)
        else:
            self._slots.restore()
            self._actions.copy_(actions)
        self.graph.replay()
        return clone_outputs(self._outputs)

    def _capture(self, actions: torch.Tensor) -> None:
        task = self.task
        self._actions = torch.as_tensor(actions, dtype=torch.float32, device=task.device).clone()
        torch.cuda.synchronize(task.device)
        graph = torch.cuda.CUDAGraph()
        if hasattr(graph, "register_generator_state"):
            graph.register_generator_state(task.generator)
        stream = torch.cuda.Stream(device=task.device)
        stream.wait_stream(torch.cuda.current_stream(task.device))
        self._slots.snapshot()
        with torch.cuda.graph(graph, stream=stream, capture_error_mode="thread_local"):
            with task.backend.joined_capture():
                outputs = self.eager_step(self._actions)
            self._slots.pin_rebound()
        torch.cuda.current_stream(task.device).wait_stream(stream)
        self.graph, self._outputs = graph, outputs
