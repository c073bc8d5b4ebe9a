"""Tests for threedq.nets.unet3d."""

from __future__ import annotations

import pytest
import torch
from torch.autograd.gradcheck import GradcheckError

from threedq.nets import UNet3D

# Small widths keep the functional tests fast; the paper's widths are checked by the parameter count.
SMALL = (8, 16, 32)


def small_net(**kwargs: object) -> UNet3D:
    torch.manual_seed(0)
    return UNet3D(channels=SMALL, **kwargs)  # type: ignore[arg-type]


class TestUNet3D:
    def test_smoke(self) -> None:
        out = small_net()(torch.rand(1, 4, 16, 8, 8))
        assert out.shape == (1, 32, 8, 4, 4)
        assert out.dtype == torch.float32

    def test_exception(self) -> None:
        net = small_net()
        with pytest.raises(ValueError, match="divisible by 8"):
            net(torch.rand(1, 4, 16, 12, 16))
        with pytest.raises(ValueError, match="divisible by 8"):
            net(torch.rand(1, 4, 16, 16, 4))
        with pytest.raises(ValueError, match=r"x must have shape \[B, 4, Z, Y, X\]"):
            net(torch.rand(1, 3, 16, 16, 16))
        with pytest.raises(ValueError, match=r"x must have shape"):
            net(torch.rand(4, 16, 16, 16))
        with pytest.raises(ValueError, match="channels"):
            UNet3D(channels=(8, 16))  # type: ignore[arg-type]

    @pytest.mark.parametrize("batch", [1, 2])
    @pytest.mark.parametrize("zyx", [(8, 16, 8), (32, 16, 24), (16, 24, 8)])
    def test_cardinality(self, batch: int, zyx: tuple[int, int, int]) -> None:
        out = small_net()(torch.rand(batch, 4, *zyx))
        assert out.shape == (batch, 32, zyx[0] // 2, zyx[1] // 2, zyx[2] // 2)

    def test_custom_channels(self) -> None:
        net = UNet3D(in_channels=2, out_channels=5, channels=(4, 8, 8))
        assert net(torch.rand(1, 2, 16, 8, 8)).shape == (1, 5, 8, 4, 4)

    def test_unit_norm(self) -> None:
        out = small_net()(torch.randn(2, 4, 16, 8, 24))
        torch.testing.assert_close(out.norm(dim=1), torch.ones(2, 8, 4, 12))

    def test_unnormalized(self) -> None:
        out = small_net(normalize=False)(torch.randn(1, 4, 16, 16, 16))
        assert not torch.allclose(out.norm(dim=1), torch.ones(()))

    def test_single_bottleneck_voxel_eval(self) -> None:
        # An 8^3 input has a 1-voxel bottleneck: fine in eval mode (BatchNorm needs > 1 value only when training).
        assert small_net().eval()(torch.rand(1, 4, 8, 8, 8)).shape == (1, 32, 4, 4, 4)

    def test_zero_features_stay_finite(self) -> None:
        net = small_net().eval()
        with torch.no_grad():
            for p in net.head.parameters():
                p.zero_()
        out = net(torch.randn(1, 4, 8, 8, 8))
        assert torch.isfinite(out).all() and (out == 0).all()

    def test_parameter_count(self) -> None:
        # Paper widths: 4-2-64, 4-2-128, 4-2-256, 4-0.5-128, 4-0.5-64, 1-1-32 (~5.79 M).
        count = sum(p.numel() for p in UNet3D().parameters())
        assert count == 5_788_960
        assert abs(count - 5.79e6) < 0.01e6

    def test_paper_widths(self) -> None:
        torch.manual_seed(0)
        out = UNet3D()(torch.rand(1, 4, 16, 8, 16))
        assert out.shape == (1, 32, 8, 4, 8)
        torch.testing.assert_close(out.norm(dim=1), torch.ones(1, 8, 4, 8))

    def test_gradient_flows(self) -> None:
        net = small_net()
        x = torch.randn(2, 4, 8, 16, 8, requires_grad=True)
        (net(x) * torch.randn(2, 32, 4, 8, 4)).sum().backward()
        assert x.grad is not None and x.grad.abs().sum() > 0
        for name, p in net.named_parameters():
            assert p.grad is not None and torch.isfinite(p.grad).all(), name
            assert p.grad.abs().sum() > 0, name

    def test_eval_determinism(self) -> None:
        net = small_net()
        net(torch.randn(2, 4, 16, 16, 16))  # update running stats once
        net.eval()
        x = torch.randn(1, 4, 16, 16, 16)
        with torch.no_grad():
            torch.testing.assert_close(net(x), net(x), rtol=0, atol=0)

    def test_channels_last_3d(self) -> None:
        net = small_net().eval()
        x = torch.randn(2, 4, 16, 8, 24)
        with torch.no_grad():
            expected = net(x)
            out_input_only = net(x.to(memory_format=torch.channels_last_3d))
            net_cl = net.to(memory_format=torch.channels_last_3d)
            out_both = net_cl(x.to(memory_format=torch.channels_last_3d))
        torch.testing.assert_close(out_input_only, expected, rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(out_both, expected, rtol=1e-4, atol=1e-5)

    def test_channels_last_3d_backward(self) -> None:
        net = small_net().to(memory_format=torch.channels_last_3d)
        x = torch.randn(1, 4, 8, 8, 16).to(memory_format=torch.channels_last_3d).requires_grad_()
        net(x).sum().backward()
        assert x.grad is not None and torch.isfinite(x.grad).all()

    def test_bf16_autocast(self) -> None:
        net = small_net().eval()
        x = torch.randn(1, 4, 16, 16, 16)
        with torch.no_grad():
            expected = net(x)
            with torch.autocast("cpu", dtype=torch.bfloat16):
                out = net(x)
        assert out.dtype == torch.bfloat16
        torch.testing.assert_close(out.float().norm(dim=1), torch.ones(1, 8, 8, 8), rtol=0, atol=1e-2)
        cosine = (out.float() * expected).sum(dim=1)
        assert cosine.min() > 0.95


class TestUNet3DFullResolution:
    """``output_stride=1``: one more transposed convolution and the input volume concatenated before the head."""

    def test_smoke(self) -> None:
        out = small_net(output_stride=1)(torch.rand(1, 4, 16, 8, 8))
        assert out.shape == (1, 32, 16, 8, 8)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="output_stride must be 1 or 2, got 4"):
            UNet3D(output_stride=4)

    @pytest.mark.parametrize("batch", [1, 2])
    @pytest.mark.parametrize("zyx", [(8, 16, 8), (16, 24, 8)])
    def test_cardinality(self, batch: int, zyx: tuple[int, int, int]) -> None:
        out = small_net(output_stride=1)(torch.rand(batch, 4, *zyx))
        assert out.shape == (batch, 32, *zyx)
        torch.testing.assert_close(out.norm(dim=1), torch.ones(batch, *zyx))

    def test_parameter_count(self) -> None:
        # the paper's net plus ConvTranspose3d(128 -> 32, k4, no bias) + BatchNorm3d(32), and a head over 32 + 4
        # channels instead of 128: 128*32*64 + 2*32 + (36 - 128) * 32
        extra = 128 * 32 * 64 + 2 * 32 + (36 - 128) * 32
        assert sum(p.numel() for p in UNet3D(output_stride=1).parameters()) == 5_788_960 + extra

    def test_against_the_layers_by_hand(self) -> None:
        """The forward pass is the stride-2 net's layers, then dec3, the input concatenated and the head."""
        net = small_net(output_stride=1).eval()
        x = torch.rand(1, 4, 8, 16, 8)
        with torch.no_grad():
            e1 = net.enc1(x)
            e2 = net.enc2(e1)
            d1 = torch.cat((net.dec1(net.enc3(e2)), e2), 1)
            d2 = torch.cat((net.dec2(d1), e1), 1)
            expected = torch.nn.functional.normalize(net.head(torch.cat((net.dec3(d2), x), 1)), dim=1)
            torch.testing.assert_close(net(x), expected)

    def test_the_input_reaches_every_voxel(self) -> None:
        """A change of one input voxel changes the output voxel at the same place (the skip from the input)."""
        net = small_net(output_stride=1).eval()
        x = torch.rand(1, 4, 8, 8, 8)
        y = x.clone()
        y[0, :, 5, 2, 3] += 1.0
        with torch.no_grad():
            diff = (net(x) - net(y)).abs().sum(1)[0]
        assert diff[5, 2, 3] > 0

    def test_channels_last_3d(self) -> None:
        net = small_net(output_stride=1).eval()
        x = torch.randn(1, 4, 8, 16, 8)
        with torch.no_grad():
            expected = net(x)
            out = net.to(memory_format=torch.channels_last_3d)(x.to(memory_format=torch.channels_last_3d))
        torch.testing.assert_close(out, expected, rtol=1e-4, atol=1e-5)

    @staticmethod
    def _gradcheck_net() -> tuple[UNet3D, torch.Tensor]:
        # unnormalised: the L2 norm is computed in float32 by design, which a float64 gradcheck cannot see through
        torch.manual_seed(0)
        net = UNet3D(in_channels=2, out_channels=3, channels=(2, 2, 2), output_stride=1, normalize=False)
        return net.double().eval(), torch.rand(1, 2, 8, 8, 8, dtype=torch.float64, requires_grad=True)

    def test_gradcheck(self) -> None:
        # fast_mode: the analytical and numerical Jacobians compared along random directions (one backward pass and
        # a few forward passes instead of one per input and output element: from minutes to a second on an AVX2 CPU);
        # atol 1e-6 keeps it sharp enough to see a 1% error (next test)
        net, x = self._gradcheck_net()
        assert torch.autograd.gradcheck(net, (x,), eps=1e-6, atol=1e-6, fast_mode=True)

    def test_gradcheck_sees_a_one_percent_error(self) -> None:
        class ScaledBackward(torch.autograd.Function):
            @staticmethod
            def forward(ctx, x: torch.Tensor) -> torch.Tensor:  # noqa: ARG004
                return x.clone()

            @staticmethod
            def backward(ctx, g: torch.Tensor) -> torch.Tensor:  # noqa: ARG004
                return g * 1.01

        net, x = self._gradcheck_net()
        with pytest.raises(GradcheckError, match="Jacobian mismatch"):
            torch.autograd.gradcheck(lambda v: net(ScaledBackward.apply(v)), (x,), eps=1e-6, atol=1e-6, fast_mode=True)
