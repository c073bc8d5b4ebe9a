"""Samplers that give one process and many the same samples: evaluation in order, training by (seed, epoch).

Both are ``DistributedSampler`` subclasses, which Lightning keeps under DDP.
"""

from __future__ import annotations

from collections.abc import Iterator, Sized

import torch
from torch.utils.data import DistributedSampler

__all__ = ["ContiguousDistributedSampler", "EpochShuffleSampler", "contiguous_block"]


def contiguous_block(n: int, num_replicas: int, rank: int) -> range:
    """Indices of the ``rank``-th of ``num_replicas`` contiguous blocks of ``range(n)`` (the first ``n % num_replicas``
    blocks hold one more; blocks may be empty)."""
    if num_replicas < 1 or not 0 <= rank < num_replicas:
        raise ValueError(f"rank: expected 0 <= rank < num_replicas, got rank {rank} of {num_replicas}")
    base, extra = divmod(n, num_replicas)
    start = rank * base + min(rank, extra)
    return range(start, start + base + (1 if rank < extra else 0))


class ContiguousDistributedSampler(DistributedSampler):
    """Rank ``r`` sees the ``r``-th contiguous block of the dataset, each sample once, never shuffled, without
    padding: concatenated rank after rank, the blocks are the one-process order. For evaluation only."""

    def __init__(self, dataset: Sized, num_replicas: int | None = None, rank: int | None = None) -> None:
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=False, drop_last=False)
        self.block = contiguous_block(len(dataset), self.num_replicas, self.rank)
        self.num_samples = len(self.block)
        self.total_size = len(dataset)

    def __iter__(self) -> Iterator[int]:
        return iter(self.block)

    def __len__(self) -> int:
        return self.num_samples


class EpochShuffleSampler(DistributedSampler):
    """Training order shuffled by ``(seed, epoch)`` and dealt out over the processes; yields ``(index, epoch)``.

    The epoch travels with each index, so that a dataset can draw its per-sample randomness from ``(seed, index,
    epoch)``. The last round is padded by repeating samples. ``num_replicas``, ``rank``: the process group's, when one
    is initialised; else 1 and 0.
    """

    def __init__(self, dataset: Sized, seed: int = 0, num_replicas: int | None = None, rank: int | None = None) -> None:
        if num_replicas is None and not (torch.distributed.is_available() and torch.distributed.is_initialized()):
            num_replicas, rank = 1, 0
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=True, seed=seed, drop_last=False)

    def __iter__(self) -> Iterator[tuple[int, int]]:  # type: ignore[override]
        epoch = self.epoch
        return ((i, epoch) for i in super().__iter__())
