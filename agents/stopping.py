"""When to stop training early: Ctrl-C (SIGINT) or a wall-clock budget.

Neither stops the process where it stands. The first SIGINT only raises a flag; the VecEnv
adapter polls ``reason()`` at the start of each rollout, i.e. between two PPO iterations, where
weights, optimiser and normaliser all belong to the last completed iteration, so the
checkpoint written then is exactly resumable. A second SIGINT interrupts at once (no save).
"""

from __future__ import annotations

import signal
import sys
import time


class TrainingStopped(Exception):
    """Raised by the adapter between iterations; ``completed`` iterations ran in this session."""

    def __init__(self, reason: str, completed: int):
        super().__init__(reason)
        self.reason = reason
        self.completed = completed


class StopConditions:
    """Context manager: installs the SIGINT handler on enter, restores the previous one on exit."""

    def __init__(self, max_minutes: float | None = None):
        if max_minutes is not None and max_minutes <= 0:
            raise ValueError(f"--max-minutes must be > 0, got {max_minutes}")
        self.budget_s = None if max_minutes is None else 60.0 * max_minutes
        self.deadline: float | None = None
        self.interrupted = False
        self._previous = None

    def reason(self) -> str | None:
        """Why to stop now, or None. The budget's clock starts at the first call (the first
        rollout), so building and compiling the environment is not charged to it."""
        if self.interrupted:
            return "interrupted (SIGINT)"
        now = time.monotonic()
        if self.budget_s is not None and self.deadline is None:
            self.deadline = now + self.budget_s
        if self.deadline is not None and now >= self.deadline:
            return "wall-clock budget reached"
        return None

    def _on_sigint(self, signum, frame) -> None:
        if self.interrupted:
            raise KeyboardInterrupt
        self.interrupted = True
        print("\nSIGINT: stopping after this iteration and saving a checkpoint "
              "(press Ctrl-C again to abort without saving)", file=sys.stderr, flush=True)

    def __enter__(self) -> StopConditions:
        self._previous = signal.signal(signal.SIGINT, self._on_sigint)
        return self

    def __exit__(self, *exc) -> None:
        signal.signal(signal.SIGINT, self._previous)
