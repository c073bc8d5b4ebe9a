"""Momentum contrast (MoCo, He et al., CVPR 2020): a momentum key encoder and a ring-buffer queue of negatives.

:class:`MomentumContrast` holds the query encoder (trained by back-propagation), the key encoder (an exponential
moving average of it) and a queue of past keys used as negatives by
:func:`threedq.contrastive.infonce.info_nce_streamed`. One training step::

    q = F.normalize(moco.encoder_q(x_q), dim=1)               # [N, D], with grad
    with torch.no_grad():
        moco._momentum_update_key_encoder()
        k = F.normalize(moco.encoder_k(x_k), dim=1)           # [N, D], no grad
    loss = moco.loss(q, k)                                    # InfoNCE against the current queue
    keys = self.all_gather(k).reshape(-1, k.shape[-1])        # Lightning, under DDP
    moco._dequeue_and_enqueue(keys)

Under DDP the caller gathers the keys of every process (in the same order) so that all replicas keep identical
queues. The queue and its pointer are registered buffers.

Convention:
    Rows are samples: queries and keys are ``[N, D]``, the queue ``[Q, D]``; vectors are expected to be
    L2-normalised by the caller (the queue is initialised with random unit rows).
"""

from __future__ import annotations

import copy

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from threedq.contrastive.infonce import info_nce_streamed
from threedq.geometry.grid import _desc

__all__ = ["MomentumContrast"]


class MomentumContrast(nn.Module):
    """MoCo key encoder + negative queue (names as in He et al.: ``encoder_q``, ``encoder_k``, ``queue``).

    Args:
        encoder_q: the query encoder (kept as is, trained by the caller's optimiser).
        dim: feature size ``D`` of the keys in the queue.
        queue_size: number of negatives ``Q`` kept.
        momentum: ``m`` in ``param_k = m * param_k + (1 - m) * param_q``, in ``[0, 1]``.
        temperature: ``T > 0`` of the InfoNCE logits.

    Attributes:
        encoder_k: deep copy of ``encoder_q`` with ``requires_grad_(False)``.
        queue: buffer ``[Q, D]``, random unit rows at initialisation (torch's global RNG).
        queue_ptr: buffer, long ``[1]``: the row the next key is written to.

    Convention:
        Rows are samples; vectors are expected to be L2-normalised by the caller.
    """

    queue: Tensor
    queue_ptr: Tensor

    def __init__(self, encoder_q: nn.Module, dim: int = 32, queue_size: int = 100_000, momentum: float = 0.999,
                 temperature: float = 0.07) -> None:
        super().__init__()
        if not isinstance(encoder_q, nn.Module):
            raise ValueError(f"encoder_q must be an nn.Module, got {type(encoder_q).__name__}")
        for name, v in (("dim", dim), ("queue_size", queue_size)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        if isinstance(momentum, bool) or not isinstance(momentum, (int, float)) or not 0.0 <= momentum <= 1.0:
            raise ValueError(f"momentum must be in [0, 1], got {momentum!r}")
        if isinstance(temperature, bool) or not isinstance(temperature, (int, float)) or not temperature > 0:
            raise ValueError(f"temperature must be a positive number, got {temperature!r}")
        self.dim, self.queue_size = dim, queue_size
        self.momentum, self.temperature = float(momentum), float(temperature)
        self.encoder_q = encoder_q
        self.encoder_k = copy.deepcopy(encoder_q)
        self.encoder_k.requires_grad_(False)
        self.register_buffer("queue", F.normalize(torch.randn(queue_size, dim), dim=1))
        self.register_buffer("queue_ptr", torch.zeros(1, dtype=torch.long))

    @torch.no_grad()
    def _momentum_update_key_encoder(self) -> None:
        """``param_k = m * param_k + (1 - m) * param_q`` for every parameter; buffers (e.g. BatchNorm running
        statistics) are copied from ``encoder_q`` to ``encoder_k``."""
        params_q = list(self.encoder_q.parameters())
        params_k = list(self.encoder_k.parameters())
        if len(params_q) != len(params_k):
            raise ValueError("encoder_k no longer matches encoder_q (different number of parameters)")
        m = self.momentum
        for pk, pq in zip(params_k, params_q):
            pk.mul_(m).add_(pq.detach(), alpha=1.0 - m)
        for bk, bq in zip(self.encoder_k.buffers(), self.encoder_q.buffers()):
            bk.copy_(bq)

    @torch.no_grad()
    def _dequeue_and_enqueue(self, keys: Tensor) -> None:
        """Write ``keys`` ``[N, D]`` into the ring buffer: key ``i`` lands in row ``(ptr + i) % Q`` (with ``N > Q`` only
        the last ``Q`` keys survive) and the pointer becomes ``(ptr + N) % Q``."""
        if not isinstance(keys, Tensor) or keys.dim() != 2 or keys.shape[1] != self.queue.shape[1]:
            raise ValueError(f"keys must have shape [N, {self.queue.shape[1]}], got {_desc(keys)}")
        n = keys.shape[0]
        if n == 0:
            return
        size = self.queue.shape[0]
        ptr = int(self.queue_ptr[0])
        keys = keys.detach().to(device=self.queue.device, dtype=self.queue.dtype)
        first = max(0, n - size)  # the keys before it would be overwritten within this call
        rows = (ptr + first + torch.arange(n - first, device=self.queue.device)) % size
        self.queue[rows] = keys[first:]
        self.queue_ptr[0] = (ptr + n) % size

    def loss(self, q: Tensor, k: Tensor, chunk: int = 1024) -> Tensor:
        """InfoNCE (:func:`info_nce_streamed`) of queries ``q`` ``[N, D]`` against their keys ``k`` ``[N, D]``
        (detached) and the current queue. Call :meth:`_dequeue_and_enqueue` afterwards."""
        if not isinstance(q, Tensor) or q.dim() != 2 or q.shape[1] != self.queue.shape[1]:
            raise ValueError(f"q must have shape [N, {self.queue.shape[1]}], got {_desc(q)}")
        if not isinstance(k, Tensor):
            raise ValueError(f"k must be a tensor [N, {self.queue.shape[1]}], got {type(k).__name__}")
        return info_nce_streamed(q, k.detach(), self.queue, self.temperature, chunk)
