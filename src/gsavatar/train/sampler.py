"""Deterministic per-step batches: the batch of step ``s`` depends only on (seed, s).

That makes resuming trivial (start at the checkpoint's step) and makes N ranks see
exactly the global batch one process would: rank r takes positions r, r+N, ... of it.
"""

from __future__ import annotations

import torch
from torch.utils.data import Sampler

_STEP_MIX = 1_000_003


def step_generator(seed: int, step: int, item: int = -1) -> torch.Generator:
    """A generator seeded by (seed, step[, global item position])."""
    g = torch.Generator()
    g.manual_seed((seed * _STEP_MIX + step) * 4099 + item + 1)
    return g


def global_batch(n: int, batch_size: int, seed: int, step: int) -> list[int]:
    """Dataset indices of step ``step``'s global batch (with replacement across steps)."""
    return torch.randint(n, (batch_size,), generator=step_generator(seed, step)).tolist()


class StepBatchSampler(Sampler[list[int]]):
    """Yields this rank's slice of every step's global batch, from ``start_step`` to ``steps``."""

    def __init__(
        self, n: int, batch_size: int, seed: int, start_step: int, steps: int, rank: int = 0, world: int = 1
    ) -> None:
        if batch_size % world:
            raise ValueError(f"batch_size ({batch_size}) must be divisible by the number of ranks ({world})")
        self.n, self.batch_size, self.seed = n, batch_size, seed
        self.start_step, self.steps, self.rank, self.world = start_step, steps, rank, world

    def positions(self) -> list[int]:
        """Positions of this rank's items inside the global batch."""
        return list(range(self.rank, self.batch_size, self.world))

    def __iter__(self):
        for step in range(self.start_step, self.steps):
            yield global_batch(self.n, self.batch_size, self.seed, step)[self.rank :: self.world]

    def __len__(self) -> int:
        return max(0, self.steps - self.start_step)
