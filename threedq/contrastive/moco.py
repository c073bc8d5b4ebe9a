"""Momentum contrast (MoCo, He et al., CVPR 2020): a momentum key encoder and a ring-buffer queue of negatives.

:class:`MomentumContrast` holds the query encoder (the given module, trained by back-propagation), the key
encoder (a deep copy, updated only as an exponential moving average of the query encoder) and a queue of past
keys used as negatives by :func:`threedq.contrastive.infonce.info_nce_streamed`. One training step::

    q = F.normalize(moco.encoder_q(x_q), dim=1)               # [N, D], with grad
    with torch.no_grad():
        moco._momentum_update_key_encoder()
        k = F.normalize(moco.encoder_k(x_k), dim=1)           # [N, D], no grad
    loss = moco.loss(q, k)                                    # InfoNCE against the current queue
    keys = self.all_gather(k).reshape(-1, k.shape[-1])        # Lightning, under DDP (see below)
    moco._dequeue_and_enqueue(keys)

Distributed training: the queue must receive the keys of every process, in the same order, so that all
replicas keep identical queues. Gathering them is the caller's job: in a ``LightningModule``,
``self.all_gather(k)`` (``[world, N, D]``, or ``[N, D]`` on a single process) followed by
``.reshape(-1, D)``. This module never needs a process group and never picks a device itself: the queue and its
pointer are registered buffers, so they move with ``.to(device)`` and are saved in (and restored from)
checkpoints.

The queue may be modified by :meth:`MomentumContrast._dequeue_and_enqueue` before ``loss.backward()``: when
the queue needs no gradient, :func:`info_nce_streamed` keeps no reference to it for backward.

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
        if isinstance(dim, bool) or not isinstance(dim, int) or dim < 1:
            raise ValueError(f"dim must be a positive int, got {dim!r}")
        if isinstance(queue_size, bool) or not isinstance(queue_size, int) or queue_size < 1:
            raise ValueError(f"queue_size must be a positive int, got {queue_size!r}")
        if isinstance(momentum, bool) or not isinstance(momentum, (int, float)) or not 0.0 <= momentum <= 1.0:
            raise ValueError(f"momentum must be in [0, 1], got {momentum!r}")
        if isinstance(temperature, bool) or not isinstance(temperature, (int, float)) or not temperature > 0:
            raise ValueError(f"temperature must be a positive number, got {temperature!r}")
        self.dim = dim
        self.queue_size = queue_size
        self.momentum = float(momentum)
        self.temperature = float(temperature)
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
        """Write ``keys`` ``[N, D]`` into the ring buffer at ``queue_ptr``, wrapping around; advance the pointer.

        The result is that of writing the keys one by one: key ``i`` lands in row ``(ptr + i) % Q`` and the
        pointer becomes ``(ptr + N) % Q``. With ``N > Q`` only the last ``Q`` keys survive. Keys from other
        DDP processes must already be gathered by the caller (see the module docstring).
        """
        if not isinstance(keys, Tensor) or keys.dim() != 2 or keys.shape[1] != self.queue.shape[1]:
            got = tuple(keys.shape) if isinstance(keys, Tensor) else type(keys).__name__
            raise ValueError(f"keys must have shape [N, {self.queue.shape[1]}], got {got}")
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
        """InfoNCE of queries ``q`` ``[N, D]`` against their keys ``k`` ``[N, D]`` and the current queue.

        ``k`` is detached (keys carry no gradient in MoCo); the loss is streamed over the queue
        (:func:`info_nce_streamed`, ``[N, chunk]`` scratch). Call :meth:`_dequeue_and_enqueue` afterwards.
        """
        if not isinstance(q, Tensor) or q.dim() != 2 or q.shape[1] != self.queue.shape[1]:
            got = tuple(q.shape) if isinstance(q, Tensor) else type(q).__name__
            raise ValueError(f"q must have shape [N, {self.queue.shape[1]}], got {got}")
        if not isinstance(k, Tensor):
            raise ValueError(f"k must be a tensor [N, {self.queue.shape[1]}], got {type(k).__name__}")
        return info_nce_streamed(q, k.detach(), self.queue, self.temperature, chunk)
