"""Samplers that give one process and many the same samples: evaluation in order, training by (seed, epoch).

Lightning replaces a plain sampler by :class:`torch.utils.data.DistributedSampler` when it runs more than one
process. For training that is right; for evaluation it is not: the distributed sampler pads the dataset to a
multiple of the process count by repeating samples (an object scored twice changes Hungarian accuracy and
few-shot accuracy), and deals samples out round-robin (the metrics' ``"cat"`` states are gathered rank after
rank, so the objects reach ``compute()`` in another order than in one process, and order-seeded choices, such as
few-shot's shots, change). :class:`ContiguousDistributedSampler` gives rank ``r`` the ``r``-th contiguous block of
the dataset, without padding: concatenated rank after rank, the blocks are the one-process order. Lightning keeps a
sampler that already is a ``DistributedSampler``.
"""

from __future__ import annotations

from collections.abc import Iterator, Sized

import torch
from torch.utils.data import DistributedSampler

__all__ = ["ContiguousDistributedSampler", "EpochShuffleSampler", "contiguous_block"]


def contiguous_block(n: int, num_replicas: int, rank: int) -> range:
    """Indices of the ``rank``-th of ``num_replicas`` contiguous blocks of ``range(n)``.

    The first ``n % num_replicas`` blocks hold one sample more than the others; blocks may be empty
    (``n < num_replicas``). Concatenated over ranks ``0..num_replicas-1`` they are ``range(n)``.
    """
    if num_replicas < 1 or not 0 <= rank < num_replicas:
        raise ValueError(f"rank: expected 0 <= rank < num_replicas, got rank {rank} of {num_replicas}")
    base, extra = divmod(n, num_replicas)
    start = rank * base + min(rank, extra)
    return range(start, start + base + (1 if rank < extra else 0))


class ContiguousDistributedSampler(DistributedSampler):
    """Rank ``r`` sees the ``r``-th contiguous block of the dataset, each sample exactly once, never shuffled.

    For evaluation only: ranks may run different numbers of batches, which a training step's gradient all-reduce
    would not survive (Lightning's evaluation loops do no collective per batch).
    """

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

    The epoch travels with each index, so that a dataset can draw its per-sample randomness (which views of a
    scene are the inputs) from ``(seed, index, epoch)`` instead of the process's global generator: a sample then
    looks the same whichever process, worker or position draws it, in one process or under DDP (the quantizer's
    bank is the same both ways). Lightning calls :meth:`set_epoch` every epoch, and keeps this sampler under DDP
    (it already is a ``DistributedSampler``; like Lightning's, it pads the last round by repeating samples).

    Args:
        dataset: the training dataset (sized).
        seed: seed of the shuffle.
        num_replicas, rank: the process group's, when one is initialised; else 1 and 0.
    """

    def __init__(self, dataset: Sized, seed: int = 0, num_replicas: int | None = None, rank: int | None = None) -> None:
        if num_replicas is None and not (torch.distributed.is_available() and torch.distributed.is_initialized()):
            num_replicas, rank = 1, 0
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=True, seed=seed, drop_last=False)

    def __iter__(self) -> Iterator[tuple[int, int]]:  # type: ignore[override]
        epoch = self.epoch
        return ((i, epoch) for i in super().__iter__())
