"""Tests for threedq.contrastive: the streamed InfoNCE and the MoCo module."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from threedq.contrastive import MomentumContrast, info_nce_plain, info_nce_streamed


def unit(*shape: int, dtype: torch.dtype = torch.float64, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return F.normalize(torch.randn(*shape, generator=g, dtype=dtype), dim=-1)


def triple(p: int, q: int, d: int, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, ...]:
    return unit(p, d, dtype=dtype, seed=1), unit(p, d, dtype=dtype, seed=2), unit(q, d, dtype=dtype, seed=3)


class TestInfoNCEStreamed:
    def test_smoke(self) -> None:
        q, k, queue = triple(8, 20, 4, torch.float32)
        loss = info_nce_streamed(q.requires_grad_(), k, queue)
        assert loss.shape == () and loss.dtype == torch.float32 and loss.requires_grad

    @pytest.mark.parametrize("recompute", [False, True])
    @pytest.mark.parametrize("chunk", [1, 7, 16, 50, 64, 1024])  # 7 does not divide Q = 50; 64, 1024 > Q
    def test_matches_plain_float64(self, chunk: int, recompute: bool) -> None:
        q, k, queue = triple(13, 50, 6)
        q.requires_grad_(True)
        ref = info_nce_plain(q, k, queue, 0.1)
        out = info_nce_streamed(q, k, queue, 0.1, chunk=chunk, recompute=recompute)
        torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
        (g_ref,) = torch.autograd.grad(ref, q)
        (g_out,) = torch.autograd.grad(out, q)
        torch.testing.assert_close(g_out, g_ref, rtol=1e-10, atol=1e-12)

    @pytest.mark.parametrize("chunk", [1, 3, 100])
    def test_single_query(self, chunk: int) -> None:
        q, k, queue = triple(1, 10, 3)
        q.requires_grad_(True)
        ref = info_nce_plain(q, k, queue)
        out = info_nce_streamed(q, k, queue, chunk=chunk)
        torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(torch.autograd.grad(out, q)[0], torch.autograd.grad(ref, q)[0])

    @pytest.mark.parametrize("recompute", [False, True])
    def test_grads_of_keys_and_queue(self, recompute: bool) -> None:
        q, k, queue = triple(9, 23, 5)
        for need_queue in (False, True):
            inputs = [q.clone().requires_grad_(), k.clone().requires_grad_(), queue.clone().requires_grad_(need_queue)]
            wrt = inputs if need_queue else inputs[:2]
            ref = torch.autograd.grad(info_nce_plain(*inputs, 0.2), wrt)
            out = torch.autograd.grad(info_nce_streamed(*inputs, 0.2, chunk=4, recompute=recompute), wrt)
            for a, b in zip(out, ref):
                torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)

    def test_gradcheck(self) -> None:
        q, k, queue = triple(3, 7, 4)
        q, k, queue = q.requires_grad_(), k.requires_grad_(), queue.requires_grad_()
        # all three inputs (recompute path) and q, k only (gradients finished in the forward)
        assert torch.autograd.gradcheck(lambda a, b, c: info_nce_streamed(a, b, c, 0.5, chunk=3), (q, k, queue))
        assert torch.autograd.gradcheck(lambda a, b: info_nce_streamed(a, b, queue.detach(), 0.5, chunk=3), (q, k))
        assert torch.autograd.gradcheck(
            lambda a: info_nce_streamed(a, k.detach(), queue.detach(), 0.5, chunk=2, recompute=True), (q,))

    def test_hand_computed(self) -> None:
        q = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=torch.float64, requires_grad=True)
        k = torch.tensor([[1.0, 0.0], [0.6, 0.8]], dtype=torch.float64)
        queue = torch.tensor([[0.0, 1.0], [-1.0, 0.0]], dtype=torch.float64)
        t = 0.5
        # row 0: logits [1, 0, -1] / 0.5 = [2, 0, -2]; row 1: [0.8, 1, 0] / 0.5 = [1.6, 2, 0]
        loss0 = math.log(math.exp(2) + math.exp(0) + math.exp(-2)) - 2
        loss1 = math.log(math.exp(1.6) + math.exp(2) + math.exp(0)) - 1.6
        expected = (loss0 + loss1) / 2
        out = info_nce_streamed(q, k, queue, t, chunk=1)
        assert out.item() == pytest.approx(expected, rel=1e-12)
        # dL/dq_p = (sum_j a_pj v_j - k_p) / (P T), v = [k_p, queue_0, queue_1]
        z0 = math.exp(2) + 1 + math.exp(-2)
        a0 = [math.exp(2) / z0, 1 / z0, math.exp(-2) / z0]
        z1 = math.exp(1.6) + math.exp(2) + 1
        a1 = [math.exp(1.6) / z1, math.exp(2) / z1, 1 / z1]
        g0 = [(a0[0] * 1 + a0[1] * 0 + a0[2] * -1 - 1) / (2 * t),
              (a0[0] * 0 + a0[1] * 1 + a0[2] * 0 - 0) / (2 * t)]
        g1 = [(a1[0] * 0.6 + a1[1] * 0 + a1[2] * -1 - 0.6) / (2 * t),
              (a1[0] * 0.8 + a1[1] * 1 + a1[2] * 0 - 0.8) / (2 * t)]
        (grad,) = torch.autograd.grad(out, q)
        torch.testing.assert_close(grad, torch.tensor([g0, g1], dtype=torch.float64), rtol=1e-12, atol=1e-14)

    def test_large_logits_are_stable(self) -> None:
        # unnormalised vectors: logits in the thousands; the online max keeps exp finite
        q, k, queue = triple(6, 40, 4)
        q, queue = q * 30, queue * 30
        q.requires_grad_(True)
        ref = info_nce_plain(q, k, queue, 0.01)
        out = info_nce_streamed(q, k, queue, 0.01, chunk=7)
        assert torch.isfinite(out)
        torch.testing.assert_close(out, ref, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(torch.autograd.grad(out, q)[0], torch.autograd.grad(ref, q)[0])

    def test_float32_close_to_plain(self) -> None:
        q, k, queue = triple(64, 3000, 32, torch.float32)
        q.requires_grad_(True)
        ref = info_nce_plain(q, k, queue)
        out = info_nce_streamed(q, k, queue, chunk=1000)
        torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(torch.autograd.grad(out, q)[0], torch.autograd.grad(ref, q)[0], rtol=1e-4, atol=1e-6)

    def test_empty_queue(self) -> None:
        q, k, queue = triple(4, 0, 3)
        q.requires_grad_(True)
        out = info_nce_streamed(q, k, queue)
        assert out.item() == 0.0 and info_nce_plain(q, k, queue).item() == 0.0
        assert torch.equal(torch.autograd.grad(out, q)[0], torch.zeros_like(q))

    @pytest.mark.parametrize("recompute", [False, True])
    def test_keeps_no_logit_matrix(self, recompute: bool) -> None:
        p, qn, d = 16, 200, 4
        q, k, queue = triple(p, qn, d)
        q.requires_grad_(True)
        saved: list[int] = []

        def pack(t: torch.Tensor) -> torch.Tensor:
            saved.append(t.numel())
            return t

        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            loss = info_nce_streamed(q, k, queue, chunk=8, recompute=recompute)
        assert saved and max(saved) <= qn * d < p * qn
        loss.backward()

    def test_queue_may_change_before_backward(self) -> None:
        # MoCo enqueues before backward: nothing of the queue is kept when it needs no gradient
        q, k, queue = triple(5, 12, 3)
        q.requires_grad_(True)
        expected = torch.autograd.grad(info_nce_plain(q, k, queue), q)[0]
        loss = info_nce_streamed(q, k, queue, chunk=5)
        queue.zero_()
        loss.backward()
        torch.testing.assert_close(q.grad, expected)
        # the recompute path keeps it, and autograd refuses the modified queue
        loss = info_nce_streamed(q, k, queue, chunk=5, recompute=True)
        queue.add_(1.0)
        with pytest.raises(RuntimeError, match="modified by an inplace operation"):
            loss.backward()

    def test_no_grad(self) -> None:
        q, k, queue = triple(5, 12, 3)
        with torch.no_grad():
            out = info_nce_streamed(q.requires_grad_(), k, queue)
        assert not out.requires_grad
        torch.testing.assert_close(out, info_nce_plain(q, k, queue).detach())

    def test_exception(self) -> None:
        q, k, queue = triple(4, 10, 3)
        with pytest.raises(ValueError, match=r"q must have shape \[P, D\]"):
            info_nce_streamed(q[0], k, queue)
        with pytest.raises(ValueError, match="k must have the shape of q"):
            info_nce_streamed(q, k[:3], queue)
        with pytest.raises(ValueError, match=r"queue must have shape \[Q, 3\]"):
            info_nce_streamed(q, k, queue[:, :2])
        with pytest.raises(ValueError, match="at least one query"):
            info_nce_streamed(q[:0], k[:0], queue)
        with pytest.raises(ValueError, match="dtype"):
            info_nce_streamed(q, k.float(), queue)
        with pytest.raises(ValueError, match="floating-point"):
            info_nce_streamed(q.long(), k.long(), queue.long())
        with pytest.raises(ValueError, match="temperature"):
            info_nce_streamed(q, k, queue, temperature=0.0)
        with pytest.raises(ValueError, match="chunk"):
            info_nce_streamed(q, k, queue, chunk=0)
        with pytest.raises(ValueError, match="temperature"):
            info_nce_plain(q, k, queue, temperature=-1.0)


def tiny_encoder() -> nn.Module:
    return nn.Sequential(nn.Linear(3, 2), nn.BatchNorm1d(2))


def conv_encoder(dim: int) -> nn.Module:
    return nn.Sequential(nn.Conv2d(3, 4, 3), nn.BatchNorm2d(4), nn.ReLU(), nn.AdaptiveAvgPool2d(1), nn.Flatten(),
                         nn.Linear(4, dim))


class TestMomentumContrast:
    def test_smoke(self) -> None:
        torch.manual_seed(0)
        moco = MomentumContrast(tiny_encoder(), dim=2, queue_size=10)
        assert moco.queue.shape == (10, 2) and moco.queue_ptr.dtype == torch.long and moco.queue_ptr.shape == (1,)
        torch.testing.assert_close(moco.queue.norm(dim=1), torch.ones(10))
        torch.manual_seed(0)
        assert torch.equal(MomentumContrast(tiny_encoder(), dim=2, queue_size=10).queue, moco.queue)

    def test_key_encoder_is_a_frozen_copy(self) -> None:
        enc = tiny_encoder()
        moco = MomentumContrast(enc, dim=2, queue_size=4)
        assert moco.encoder_q is enc and moco.encoder_k is not enc
        assert all(p.requires_grad for p in moco.encoder_q.parameters())
        assert not any(p.requires_grad for p in moco.encoder_k.parameters())
        for pk, pq in zip(moco.encoder_k.parameters(), moco.encoder_q.parameters()):
            assert torch.equal(pk, pq) and pk.data_ptr() != pq.data_ptr()

    def test_momentum_update(self) -> None:
        moco = MomentumContrast(tiny_encoder(), dim=2, queue_size=4, momentum=0.9)
        with torch.no_grad():
            for i, p in enumerate(moco.encoder_q.parameters()):
                p.copy_(torch.arange(p.numel(), dtype=p.dtype).reshape(p.shape) + 10.0 * i)
        before = [p.clone() for p in moco.encoder_k.parameters()]
        moco.encoder_q.train()(torch.randn(5, 3))  # moves the BatchNorm running statistics of encoder_q only
        assert not torch.equal(moco.encoder_q[1].running_mean, moco.encoder_k[1].running_mean)
        moco._momentum_update_key_encoder()
        for pk, pq, old in zip(moco.encoder_k.parameters(), moco.encoder_q.parameters(), before):
            torch.testing.assert_close(pk, 0.9 * old + 0.1 * pq)
        for name, bq in moco.encoder_q.named_buffers():
            assert torch.equal(dict(moco.encoder_k.named_buffers())[name], bq), name
        assert not any(p.requires_grad for p in moco.encoder_k.parameters())

    def test_queue_wraps_around(self) -> None:
        moco = MomentumContrast(tiny_encoder(), dim=2, queue_size=10)
        init = moco.queue.clone()
        batches = [torch.arange(8, dtype=torch.float32).reshape(4, 2) + 100.0 * (b + 1) for b in range(3)]
        moco._dequeue_and_enqueue(batches[0])
        assert moco.queue_ptr.item() == 4
        assert torch.equal(moco.queue[:4], batches[0]) and torch.equal(moco.queue[4:], init[4:])
        moco._dequeue_and_enqueue(batches[1])
        assert moco.queue_ptr.item() == 8
        assert torch.equal(moco.queue[4:8], batches[1]) and torch.equal(moco.queue[8:], init[8:])
        moco._dequeue_and_enqueue(batches[2])  # rows 8, 9, then 0, 1
        assert moco.queue_ptr.item() == 2
        expected = torch.cat((batches[2][2:], batches[0][2:], batches[1], batches[2][:2]))
        assert torch.equal(moco.queue, expected)

    def test_more_keys_than_queue_keeps_the_last(self) -> None:
        moco = MomentumContrast(tiny_encoder(), dim=2, queue_size=10)
        moco._dequeue_and_enqueue(torch.zeros(4, 2))
        keys = torch.arange(46, dtype=torch.float32).reshape(23, 2)
        moco._dequeue_and_enqueue(keys)
        assert moco.queue_ptr.item() == (4 + 23) % 10
        # as if written one by one from row 4: key i in row (4 + i) % 10, the last 10 survive
        expected = torch.empty(10, 2)
        for i in range(23):
            expected[(4 + i) % 10] = keys[i]
        assert torch.equal(moco.queue, expected)
        assert sorted(moco.queue[:, 0].tolist()) == sorted(keys[-10:, 0].tolist())
        moco._dequeue_and_enqueue(keys[:10])  # exactly Q keys: a full turn
        assert moco.queue_ptr.item() == 7 and torch.equal(moco.queue.roll(-7, 0), keys[:10])

    def test_state_dict_round_trip(self) -> None:
        torch.manual_seed(1)
        moco = MomentumContrast(tiny_encoder(), dim=2, queue_size=10)
        moco._dequeue_and_enqueue(torch.ones(3, 2))
        state = moco.state_dict()
        assert "queue" in state and "queue_ptr" in state
        torch.manual_seed(2)
        other = MomentumContrast(tiny_encoder(), dim=2, queue_size=10)
        assert not torch.equal(other.queue, moco.queue)
        other.load_state_dict(state)
        assert torch.equal(other.queue, moco.queue) and other.queue_ptr.item() == 3
        assert other.double().queue.dtype == torch.float64  # buffers follow the module

    def test_full_step(self) -> None:
        torch.manual_seed(0)
        moco = MomentumContrast(conv_encoder(8), dim=8, queue_size=32, momentum=0.99, temperature=0.1)
        x_q, x_k = torch.randn(6, 3, 8, 8), torch.randn(6, 3, 8, 8)
        q = F.normalize(moco.encoder_q(x_q), dim=1)
        with torch.no_grad():
            moco._momentum_update_key_encoder()
            k = F.normalize(moco.encoder_k(x_k), dim=1)
        loss = moco.loss(q, k)
        ref = info_nce_plain(q, k, moco.queue.clone(), 0.1)
        torch.testing.assert_close(loss, ref)
        moco._dequeue_and_enqueue(k)  # before backward, as MoCo does
        loss.backward()
        assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in moco.encoder_q.parameters())
        assert any(p.grad.abs().sum() > 0 for p in moco.encoder_q.parameters())
        assert all(p.grad is None for p in moco.encoder_k.parameters())
        assert moco.queue.grad is None and moco.queue_ptr.item() == 6 and torch.equal(moco.queue[:6], k)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="encoder_q"):
            MomentumContrast(lambda x: x)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="dim"):
            MomentumContrast(tiny_encoder(), dim=0)
        with pytest.raises(ValueError, match="queue_size"):
            MomentumContrast(tiny_encoder(), queue_size=0)
        with pytest.raises(ValueError, match="momentum"):
            MomentumContrast(tiny_encoder(), momentum=1.5)
        with pytest.raises(ValueError, match="temperature"):
            MomentumContrast(tiny_encoder(), temperature=0.0)
        moco = MomentumContrast(tiny_encoder(), dim=2, queue_size=4)
        with pytest.raises(ValueError, match=r"keys must have shape \[N, 2\]"):
            moco._dequeue_and_enqueue(torch.zeros(3, 5))
        with pytest.raises(ValueError, match=r"q must have shape \[N, 2\]"):
            moco.loss(torch.zeros(3, 5), torch.zeros(3, 5))
