"""InfoNCE against a queue of negatives (MoCo), streamed over the queue so that no ``[P, Q]`` matrix is kept.

For queries ``q`` ``[P, D]``, positive keys ``k`` ``[P, D]`` and a queue of negatives ``[Q, D]``::

    loss = 1/P sum_p (lse_p - s_p0),   s_pj = q_p . v_pj / T,   v_p0 = k_p,  v_pj = queue_{j-1},
    lse_p = log sum_j exp(s_pj)

Gradients (``a_pj = exp(s_pj - lse_p)``, the softmax of row ``p``; ``g`` the incoming scalar gradient)::

    dL/dq_p     = g / (P T) * (sum_j a_pj v_pj - k_p)
    dL/dk_p     = g / (P T) * (a_p0 - 1) q_p
    dL/dqueue_j = g / (P T) * sum_p a_p(j+1) q_p

:func:`info_nce_streamed` walks the queue in chunks of ``chunk`` rows with an online log-sum-exp (running max
``m_p`` and running sum ``l_p``) in one reused ``[P, chunk]`` buffer. When the queue needs no gradient and
``recompute=False``, the same pass accumulates ``sum_j a_pj v_pj`` (rescaled like ``l_p``) and finishes ``dL/dq``
and ``dL/dk`` in the forward; otherwise the backward recomputes each chunk's logits from ``q``, ``k``, the queue and
the per-row log-sum-exp. :func:`info_nce_plain` is the textbook version (``torch.cat`` of the logits +
``F.cross_entropy``).

Convention:
    Rows are samples (``q``, ``k`` are ``[P, D]``, the queue ``[Q, D]``); vectors are expected to be
    L2-normalised by the caller (nothing here normalises). ``q[p]`` and ``k[p]`` are a positive pair.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.function import once_differentiable

from threedq.geometry.grid import _desc

__all__ = ["info_nce_plain", "info_nce_streamed"]


def _check(q: Tensor, k: Tensor, queue: Tensor, temperature: float) -> None:
    if not isinstance(q, Tensor) or q.dim() != 2:
        raise ValueError(f"q must have shape [P, D], got {_desc(q)}")
    if not isinstance(k, Tensor) or k.shape != q.shape:
        raise ValueError(f"k must have the shape of q {tuple(q.shape)}, got {_desc(k)}")
    if not isinstance(queue, Tensor) or queue.dim() != 2 or queue.shape[1] != q.shape[1]:
        raise ValueError(f"queue must have shape [Q, {q.shape[1]}], got {_desc(queue)}")
    if q.shape[0] == 0:
        raise ValueError("q must hold at least one query (P >= 1)")
    if not q.is_floating_point():
        raise ValueError(f"q must be floating-point, got {q.dtype}")
    if k.dtype != q.dtype or queue.dtype != q.dtype:
        raise ValueError(f"k and queue must have the dtype of q ({q.dtype}), got {k.dtype} and {queue.dtype}")
    if k.device != q.device or queue.device != q.device:
        raise ValueError(f"k and queue must be on the device of q ({q.device}), got {k.device} and {queue.device}")
    if not isinstance(temperature, (int, float)) or isinstance(temperature, bool) or not temperature > 0:
        raise ValueError(f"temperature must be a positive number, got {temperature!r}")


def info_nce_plain(q: Tensor, k: Tensor, queue: Tensor, temperature: float = 0.07) -> Tensor:
    """Reference InfoNCE: the ``[P, 1 + Q]`` logits by ``torch.cat``, then ``F.cross_entropy`` with target 0.

    Args:
        q: ``[P, D]`` queries.
        k: ``[P, D]`` positive keys (``k[p]`` is the positive of ``q[p]``).
        queue: ``[Q, D]`` negatives (``Q`` may be 0).
        temperature: ``T > 0``; logits are dot products divided by ``T``.

    Returns:
        Scalar mean loss (differentiable w.r.t. every input that requires grad).

    Convention:
        Rows are samples; vectors are expected to be L2-normalised by the caller.
    """
    _check(q, k, queue, temperature)
    pos = (q * k).sum(1, keepdim=True)  # [P, 1]
    neg = q @ queue.t()  # [P, Q]
    logits = torch.cat((pos, neg), dim=1) / temperature  # [P, 1 + Q]
    target = torch.zeros(q.shape[0], dtype=torch.long, device=q.device)
    return F.cross_entropy(logits, target)


class _StreamedInfoNCE(torch.autograd.Function):
    """Autograd function behind :func:`info_nce_streamed` (the derivation is in the module docstring)."""

    @staticmethod
    def forward(ctx: Any, q: Tensor, k: Tensor, queue: Tensor, temperature: float, chunk: int, recompute: bool,
                need: tuple) -> Tensor:
        need_q, need_k, need_queue = need
        P, Q = q.shape[0], queue.shape[0]
        inv_t = 1.0 / temperature
        qs = q * inv_t  # [P, D]: logits are qs @ v^T
        m = (qs * k).sum(1)  # [P] running max, started at the positive logit s_p0
        pos = m.clone()
        tot = torch.ones_like(m)  # [P] running sum of exp(s - m): the positive contributes exp(0)
        # fused gradient: running softmax-weighted key sum_j exp(s_pj - m_p) v_pj, rescaled like tot
        fused = (need_q or need_k) and not need_queue and not recompute
        acc = k.clone() if fused and need_q else None  # [P, D]
        c = max(1, min(chunk, Q))
        buf = torch.empty(P * c, dtype=q.dtype, device=q.device)  # [P, chunk] scratch, reused
        for start in range(0, Q, c):
            u = queue[start : start + c]  # [n, D]
            n = u.shape[0]
            s = buf[: P * n].view(P, n)
            torch.mm(qs, u.t(), out=s)  # [P, n] logits of this chunk
            m_new = torch.maximum(m, s.amax(1))
            scale = torch.exp(m - m_new)  # [P] <= 1
            s.sub_(m_new[:, None]).exp_()  # s := exp(logit - m_new), in place
            tot.mul_(scale).add_(s.sum(1))
            if acc is not None:
                acc.mul_(scale[:, None]).addmm_(s, u)  # acc := acc * scale + e @ u
            m = m_new
        lse = m + torch.log(tot)  # [P]
        loss = (lse - pos).mean()
        ctx.temperature, ctx.chunk, ctx.fused, ctx.need = temperature, c, fused, need
        if fused:
            coef = inv_t / P
            grad_q = (acc / tot[:, None] - k).mul_(coef) if need_q else None  # [P, D]
            grad_k = None
            if need_k:
                a0 = torch.exp(pos - lse)  # softmax weight of the positive
                grad_k = q * ((a0 - 1.0) * coef)[:, None]
            ctx.save_for_backward(grad_q, grad_k)
        else:
            ctx.save_for_backward(q, k, queue, lse)
        return loss

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor | None, ...]:
        need_q, need_k, need_queue = ctx.need
        none4 = (None,) * 4
        if ctx.fused:
            grad_q, grad_k = ctx.saved_tensors
            return (grad_q * grad_out if need_q else None, grad_k * grad_out if need_k else None, None, *none4)
        q, k, queue, lse = ctx.saved_tensors
        P, Q = q.shape[0], queue.shape[0]
        inv_t = 1.0 / ctx.temperature
        coef = grad_out * (inv_t / P)  # scalar tensor: g / (P T)
        qs = q * inv_t
        pos = (qs * k).sum(1)
        a0 = torch.exp(pos - lse)  # [P]
        # dL/dq accumulated unscaled: sum_j a_pj v_pj - k_p
        gq = k * (a0 - 1.0)[:, None] if need_q else None
        gqueue = torch.empty_like(queue) if need_queue else None
        c = ctx.chunk
        buf = torch.empty(P * c, dtype=q.dtype, device=q.device)
        for start in range(0, Q, c):
            u = queue[start : start + c]
            n = u.shape[0]
            a = buf[: P * n].view(P, n)
            torch.mm(qs, u.t(), out=a)
            a.sub_(lse[:, None]).exp_()  # softmax weights of this chunk
            if gq is not None:
                gq.addmm_(a, u)
            if gqueue is not None:
                torch.mm(a.t(), q, out=gqueue[start : start + n])
        grad_q = gq.mul_(coef) if gq is not None else None
        grad_k = q * ((a0 - 1.0)[:, None] * coef) if need_k else None
        grad_queue = gqueue.mul_(coef) if gqueue is not None else None
        return (grad_q, grad_k, grad_queue, *none4)


def info_nce_streamed(q: Tensor, k: Tensor, queue: Tensor, temperature: float = 0.07, chunk: int = 1024, *,
                      recompute: bool = False) -> Tensor:
    """InfoNCE with a negative queue, streamed over the queue in chunks (no ``[P, Q]`` matrix is kept).

    Same value and gradients as :func:`info_nce_plain` (up to rounding) for every input that requires grad; double
    backward is not supported.

    Args:
        q: ``[P, D]`` queries (``P >= 1``).
        k: ``[P, D]`` positive keys (``k[p]`` is the positive of ``q[p]``), same dtype and device as ``q``.
        queue: ``[Q, D]`` negatives (``Q >= 0``), same dtype and device as ``q``.
        temperature: ``T > 0``; logits are dot products divided by ``T``.
        chunk: queue rows per step (``>= 1``); the scratch is ``[P, min(chunk, Q)]``.
        recompute: if True, always recompute each chunk's logits in backward; by default the gradients of ``q``
            and ``k`` are finished in the forward pass when the queue needs no gradient.

    Returns:
        Scalar mean loss (``mean_p`` of the cross-entropy of row ``p`` with target 0).

    Convention:
        Rows are samples; vectors are expected to be L2-normalised by the caller.
    """
    _check(q, k, queue, temperature)
    if isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1:
        raise ValueError(f"chunk must be a positive int, got {chunk!r}")
    grad = torch.is_grad_enabled()
    need = (grad and q.requires_grad, grad and k.requires_grad, grad and queue.requires_grad)
    return _StreamedInfoNCE.apply(q, k, queue, float(temperature), chunk, bool(recompute), need)
