"""Tests for threedq.nets.view_decoder (view prediction, occupancy head, losses)."""

from __future__ import annotations

import math

import pytest
import torch

from threedq.geometry.frustum import resample_to_frustum
from threedq.geometry.grid import VoxelGridSpec
from threedq.nets import (
    OccupancyHead,
    UNet3D,
    ViewDecoder,
    balanced_l1,
    balanced_occupancy_loss,
    depth_max_pool,
    masked_l1,
    occupancy_balanced_accuracy,
)

LN2 = math.log(2.0)


class TestDepthMaxPool:
    """``depth_max_pool`` against ``F.max_pool3d`` over ``(pool, 1, 1)`` windows, the op it stands in for."""

    @staticmethod
    def reference(x: torch.Tensor, pool: int) -> torch.Tensor:
        return torch.nn.functional.max_pool3d(x, (pool, 1, 1), (pool, 1, 1))

    def test_smoke(self) -> None:
        assert depth_max_pool(torch.randn(1, 2, 8, 3, 3), 4).shape == (1, 2, 2, 3, 3)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="D divisible by pool=3"):
            depth_max_pool(torch.randn(1, 2, 8, 3, 3), 3)
        with pytest.raises(ValueError, match=r"\[B, C, D, h, w\]"):
            depth_max_pool(torch.randn(2, 8, 3, 3), 4)
        with pytest.raises(ValueError, match="pool=0"):
            depth_max_pool(torch.randn(1, 2, 8, 3, 3), 0)

    @pytest.mark.parametrize(("depth", "pool", "hw"),
                             [(16, 8, (5, 4)), (32, 8, (64, 64)), (6, 2, (1, 3)), (4, 4, (2, 2)), (5, 1, (3, 2))])
    def test_shapes(self, depth: int, pool: int, hw: tuple[int, int]) -> None:
        assert depth_max_pool(torch.randn(2, 3, depth, *hw), pool).shape == (2, 3, depth // pool, *hw)

    @pytest.mark.parametrize("memory_format", [torch.contiguous_format, torch.channels_last_3d])
    @pytest.mark.parametrize("case", ["random", "ties", "zero planes"])
    def test_bitwise_max_pool3d(self, case: str, memory_format: torch.memory_format) -> None:
        # values and gradients bit for bit, ties included: a tied group's first maximum takes the gradient
        torch.manual_seed(0)
        x = torch.randn(2, 3, 16, 5, 4)
        if case == "ties":
            x = x.round()
        if case == "zero planes":  # the frustum's samples outside the grid are exact zeros
            x[:, :, :11] = 0.0
            x[0, 1, 12:] = -1.0
        a = x.to(memory_format=memory_format).requires_grad_(True)
        b = x.to(memory_format=memory_format).requires_grad_(True)
        ya, yb = self.reference(a, 8), depth_max_pool(b, 8)
        g = torch.randn_like(ya)
        ya.backward(g)
        yb.backward(g)
        assert torch.equal(ya, yb)
        assert torch.equal(a.grad, b.grad)

    def test_nan_propagates(self) -> None:
        x = torch.zeros(1, 1, 8, 2, 2)
        x[0, 0, 5, 1, 0] = float("nan")
        out = depth_max_pool(x, 4)
        assert out.isnan().sum() == 1 and out[0, 0, 1, 1, 0].isnan()
        torch.testing.assert_close(out, self.reference(x, 4), equal_nan=True, rtol=0, atol=0)

    def test_hand_computed(self) -> None:
        x = torch.tensor([1.0, 5.0, -2.0, 3.0, -1.0, -4.0]).view(1, 1, 6, 1, 1)
        assert depth_max_pool(x, 3).flatten().tolist() == [5.0, 3.0]
        assert depth_max_pool(x, 2).flatten().tolist() == [5.0, 3.0, -1.0]

    def test_gradcheck(self) -> None:
        x = torch.randn(1, 2, 6, 2, 3, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda t: depth_max_pool(t, 3), (x,))


class TestViewDecoder:
    def test_smoke(self) -> None:
        out = ViewDecoder()(torch.randn(1, 32, 32, 8, 8))
        assert out.shape == (1, 3, 8, 8)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="divisible by pool"):
            ViewDecoder(num_planes=12, pool=8)
        dec = ViewDecoder(in_channels=4, num_planes=16)
        with pytest.raises(ValueError, match=r"frustum must have shape \[B, 4, 16, h, w\]"):
            dec(torch.randn(1, 4, 8, 5, 5))
        with pytest.raises(ValueError, match=r"frustum must have shape"):
            dec(torch.randn(4, 16, 5, 5))

    @pytest.mark.parametrize("batch", [1, 2])
    @pytest.mark.parametrize(
        ("channels", "planes", "pool", "hw"),
        [(32, 32, 8, (8, 8)), (4, 16, 8, (5, 7)), (6, 8, 2, (1, 3)), (3, 4, 4, (12, 10))],
    )
    def test_cardinality(self, batch: int, channels: int, planes: int, pool: int, hw: tuple[int, int]) -> None:
        dec = ViewDecoder(in_channels=channels, num_planes=planes, pool=pool, hidden=8, out_channels=5)
        out = dec(torch.randn(batch, channels, planes, *hw))
        assert out.shape == (batch, 5, *hw)

    def test_output_range(self) -> None:
        torch.manual_seed(0)
        out = ViewDecoder(in_channels=2, num_planes=8)(1e3 * torch.randn(2, 2, 8, 6, 6))
        assert out.abs().max() <= 0.5

    def test_depth_pooling(self) -> None:
        # Only the max over each group of `pool` planes matters: permuting planes inside a group changes nothing.
        torch.manual_seed(0)
        dec = ViewDecoder(in_channels=2, num_planes=16, pool=8, hidden=4)
        x = torch.randn(1, 2, 16, 5, 5)
        perm = torch.cat((torch.randperm(8), 8 + torch.randperm(8)))
        torch.testing.assert_close(dec(x[:, :, perm]), dec(x))
        swapped = torch.cat((x[:, :, 8:], x[:, :, :8]), dim=2)  # groups are ordered near -> far
        assert not torch.allclose(dec(swapped), dec(x))

    def test_decode_pooled(self) -> None:
        # forward is the depth max-pool, then decode_pooled: a pooled frustum from elsewhere decodes the same
        torch.manual_seed(0)
        dec = ViewDecoder(in_channels=4, num_planes=16, pool=4, hidden=8)
        x = torch.randn(2, 4, 16, 5, 6)
        assert torch.equal(dec.decode_pooled(depth_max_pool(x, 4)), dec(x))
        with pytest.raises(ValueError, match=r"pooled frustum must have shape \[B, 4, 4, h, w\]"):
            dec.decode_pooled(x)

    def test_gradient_flows(self) -> None:
        dec = ViewDecoder(in_channels=4, num_planes=16, hidden=8)
        x = torch.randn(2, 4, 16, 6, 6, requires_grad=True)
        dec(x).sum().backward()
        assert x.grad is not None and x.grad.abs().sum() > 0
        for name, p in dec.named_parameters():
            assert p.grad is not None and p.grad.abs().sum() > 0, name

    def test_channels_last_3d(self) -> None:
        dec = ViewDecoder(in_channels=4, num_planes=16, hidden=8)
        x = torch.randn(2, 4, 16, 6, 6)
        torch.testing.assert_close(dec(x.to(memory_format=torch.channels_last_3d)), dec(x), rtol=1e-4, atol=1e-6)


class TestOccupancyHead:
    def test_smoke(self) -> None:
        assert OccupancyHead()(torch.randn(1, 32, 4, 6, 8)).shape == (1, 1, 4, 6, 8)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"features must have shape \[B, 8, Z, Y, X\]"):
            OccupancyHead(8)(torch.randn(1, 4, 2, 2, 2))

    @pytest.mark.parametrize("batch", [1, 3])
    def test_cardinality(self, batch: int) -> None:
        assert OccupancyHead(5)(torch.randn(batch, 5, 3, 4, 2)).shape == (batch, 1, 3, 4, 2)

    def test_feature(self) -> None:
        head = OccupancyHead(2)
        with torch.no_grad():
            head.conv.weight.copy_(torch.tensor([2.0, -1.0]).view(1, 2, 1, 1, 1))
            head.conv.bias.fill_(0.5)
        x = torch.randn(1, 2, 3, 3, 3)
        torch.testing.assert_close(head(x), 2.0 * x[:, :1] - x[:, 1:] + 0.5)


class TestMaskedL1:
    def test_feature(self) -> None:
        pred = torch.zeros(1, 3, 2, 2)
        target = torch.tensor([1.0, 2.0, 3.0]).view(1, 3, 1, 1).expand(1, 3, 2, 2).clone()
        target[0, :, 1, 1] = 100.0  # invalid pixel, must be ignored
        valid = torch.ones(1, 1, 2, 2, dtype=torch.bool)
        valid[0, 0, 1, 1] = False
        torch.testing.assert_close(masked_l1(pred, target, valid), torch.tensor(2.0))
        torch.testing.assert_close(masked_l1(pred, target, valid.float()), torch.tensor(2.0))

    def test_invalid_pixels_get_no_gradient(self) -> None:
        pred = torch.randn(2, 3, 4, 4, requires_grad=True)
        valid = torch.rand(2, 1, 4, 4) > 0.5
        masked_l1(pred, torch.randn(2, 3, 4, 4), valid).backward()
        assert pred.grad is not None
        assert (pred.grad * (~valid)).abs().sum() == 0
        assert (pred.grad * valid).abs().sum() > 0

    def test_empty_mask(self) -> None:
        pred = torch.randn(1, 3, 4, 4, requires_grad=True)
        loss = masked_l1(pred, torch.randn(1, 3, 4, 4), torch.zeros(1, 1, 4, 4))
        assert loss.item() == 0.0
        loss.backward()
        assert pred.grad is not None and torch.isfinite(pred.grad).all() and (pred.grad == 0).all()

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="same shape"):
            masked_l1(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 5), torch.ones(1, 1, 4, 4))
        with pytest.raises(ValueError, match=r"valid must have shape \(1, 1, 4, 4\)"):
            masked_l1(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4), torch.ones(1, 3, 4, 4))


class TestBalancedL1:
    def test_feature(self) -> None:
        # 4 valid pixels: one foreground with error 6, three background with errors 1, 2, 3 (channel means)
        pred = torch.zeros(1, 1, 2, 3)
        target = torch.tensor([[6.0, 1.0, 2.0], [3.0, 50.0, 70.0]]).view(1, 1, 2, 3)
        valid = torch.tensor([[1.0, 1.0, 1.0], [1.0, 0.0, 0.0]]).view(1, 1, 2, 3)
        fg = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]).view(1, 1, 2, 3)  # (1, 1) is fg but not valid
        torch.testing.assert_close(balanced_l1(pred, target, valid, fg), torch.tensor(6.0 + 2.0))
        torch.testing.assert_close(masked_l1(pred, target, valid), torch.tensor(3.0))  # the plain mean differs

    def test_one_set_empty_is_the_plain_loss(self) -> None:
        pred, target = torch.randn(2, 3, 5, 5), torch.randn(2, 3, 5, 5)
        valid = (torch.rand(2, 1, 5, 5) > 0.3).float()
        plain = masked_l1(pred, target, valid)
        torch.testing.assert_close(balanced_l1(pred, target, valid, torch.zeros_like(valid)), plain)
        torch.testing.assert_close(balanced_l1(pred, target, valid, torch.ones_like(valid)), plain)

    def test_gradient_is_balanced(self) -> None:
        # L1 gradients are +-1/(E*N) per element: each set receives a total gradient mass of 1, however small
        pred = torch.randn(1, 3, 8, 8, requires_grad=True)
        fg = torch.zeros(1, 1, 8, 8)
        fg[..., :2, :2] = 1.0  # 4 foreground pixels vs 60 background ones
        balanced_l1(pred, torch.randn(1, 3, 8, 8) + 10.0, torch.ones(1, 1, 8, 8), fg).backward()
        g = pred.grad.abs()
        torch.testing.assert_close((g * fg).sum(), torch.tensor(1.0))
        torch.testing.assert_close((g * (1 - fg)).sum(), torch.tensor(1.0))

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match=r"foreground must have shape \(1, 1, 4, 4\)"):
            balanced_l1(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4), torch.ones(1, 1, 4, 4), torch.ones(1, 1, 4, 5))
        with pytest.raises(ValueError, match=r"valid must have shape"):
            balanced_l1(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4), torch.ones(1, 3, 4, 4), torch.ones(1, 1, 4, 4))


def occ_masks() -> tuple[torch.Tensor, torch.Tensor]:
    occupied = torch.zeros(2, 1, 3, 4, 5, dtype=torch.bool)
    free = torch.zeros(2, 1, 3, 4, 5, dtype=torch.bool)
    occupied[0, 0, 1, 1, :2] = True  # 2 occupied voxels
    free[:, 0, 2] = True  # 40 free voxels
    return occupied, free


class TestBalancedOccupancyLoss:
    def test_zero_logits(self) -> None:
        occupied, free = occ_masks()
        loss = balanced_occupancy_loss(torch.zeros(2, 1, 3, 4, 5), occupied, free)
        torch.testing.assert_close(loss, torch.tensor(2 * LN2))

    def test_perfect_logits(self) -> None:
        occupied, free = occ_masks()
        logits = 30.0 * (occupied.float() - free.float())
        assert balanced_occupancy_loss(logits, occupied, free) < 1e-10

    def test_balancing(self) -> None:
        # 2 occupied vs 40 free: each class contributes its own mean, regardless of its size.
        occupied, free = occ_masks()
        logits = torch.zeros(2, 1, 3, 4, 5)
        logits[occupied] = 1.0
        logits[free] = -2.0
        expected = math.log1p(math.exp(-1.0)) + math.log1p(math.exp(-2.0))
        torch.testing.assert_close(balanced_occupancy_loss(logits, occupied, free), torch.tensor(expected))
        torch.testing.assert_close(
            balanced_occupancy_loss(logits, occupied.float(), free.float()), torch.tensor(expected)
        )

    def test_empty_sets(self) -> None:
        occupied, free = occ_masks()
        logits = torch.zeros(2, 1, 3, 4, 5, requires_grad=True)
        none = torch.zeros_like(occupied)
        torch.testing.assert_close(balanced_occupancy_loss(logits, none, free), torch.tensor(LN2))
        torch.testing.assert_close(balanced_occupancy_loss(logits, occupied, none), torch.tensor(LN2))
        loss = balanced_occupancy_loss(logits, none, none)
        assert loss.item() == 0.0
        loss.backward()
        assert logits.grad is not None and (logits.grad == 0).all()

    def test_gradient_sign(self) -> None:
        occupied, free = occ_masks()
        logits = torch.zeros(2, 1, 3, 4, 5, requires_grad=True)
        balanced_occupancy_loss(logits, occupied, free).backward()
        assert logits.grad is not None
        assert (logits.grad[occupied] < 0).all() and (logits.grad[free] > 0).all()
        assert (logits.grad[~(occupied | free)] == 0).all()

    def test_exception(self) -> None:
        occupied, free = occ_masks()
        with pytest.raises(ValueError, match="occupied must have shape"):
            balanced_occupancy_loss(torch.zeros(2, 1, 3, 4, 5), occupied[:, :, :2], free)
        with pytest.raises(ValueError, match="free must have shape"):
            balanced_occupancy_loss(torch.zeros(2, 1, 3, 4, 5), occupied, free[:1])


class TestOccupancyBalancedAccuracy:
    def test_feature(self) -> None:
        occupied, free = occ_masks()
        logits = -torch.ones(2, 1, 3, 4, 5)
        logits[0, 0, 1, 1, 0] = 1.0  # TPR = 1/2
        logits[0, 0, 2, :2] = 1.0  # 10 of 40 free predicted occupied: TNR = 3/4
        torch.testing.assert_close(occupancy_balanced_accuracy(logits, occupied, free), torch.tensor(0.625))

    def test_perfect_and_empty(self) -> None:
        occupied, free = occ_masks()
        logits = occupied.float() - free.float()
        assert occupancy_balanced_accuracy(logits, occupied, free).item() == 1.0
        none = torch.zeros_like(occupied)
        assert occupancy_balanced_accuracy(logits, none, free).item() == 1.0  # TNR only
        assert torch.isnan(occupancy_balanced_accuracy(logits, none, none))


def test_encoder_decoder_overfit() -> None:
    """UNet3D -> frustum resampling -> ViewDecoder fits one fixed target image (~40 Adam steps, ~1-5 s here)."""
    torch.manual_seed(0)
    grid = VoxelGridSpec((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), (16, 16, 16))
    encoder = UNet3D(channels=(16, 32, 64))
    decoder = ViewDecoder(in_channels=32, num_planes=16, pool=8, hidden=32)
    x = torch.randn(1, 4, 16, 16, 16)
    # A camera 3 m from the centre looking down at the grid; every ray of the 8x8 frustum crosses it.
    R_T_cam = torch.tensor(
        [[[0.0, 0.6, -0.8, 2.4], [1.0, 0.0, 0.0, 0.0], [0.0, -0.8, -0.6, 1.8], [0.0, 0.0, 0.0, 1.0]]]
    )
    K = torch.tensor([[[12.0, 0.0, 3.5], [0.0, 12.0, 3.5], [0.0, 0.0, 1.0]]])
    target = torch.rand(1, 3, 8, 8) * 0.8 - 0.4
    valid = torch.ones(1, 1, 8, 8)
    valid[..., :2, :2] = 0
    params = list(encoder.parameters()) + list(decoder.parameters())
    optimizer = torch.optim.Adam(params, lr=2e-3)
    losses = []
    for _ in range(150):
        features = encoder(x)
        frustum = resample_to_frustum(features, grid.half(), K, R_T_cam, (8, 8), (2.0, 4.0), 16)
        loss = masked_l1(decoder(frustum), target, valid)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
        if losses[-1] < losses[0] / 8:
            break
    assert losses[-1] < losses[0] / 5, (losses[0], losses[-1], len(losses))
