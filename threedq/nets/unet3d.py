"""The 2.5D-to-3D lifting network of GIGNs / 3DQ-Nets: a small 3D encoder-decoder (U-Net).

Convention:
    Volumes are ``[B, C, Z, Y, X]`` (torch's D, H, W = z, y, x) on a cell-centred grid in the reference
    frame R. The output lives on the same bounds at half the input resolution (``VoxelGridSpec.half()``):
    output voxel ``(k, j, i)`` covers input voxels ``2k..2k+1`` (and likewise for y, x), so its centre is the
    mean of theirs. With ``output_stride=1`` (not the paper's) it lives on the input grid itself.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["UNet3D"]

#: Spatial sizes of the input must be divisible by this (three stride-2 convolutions).
DOWNSAMPLE = 8


def _block(conv: type[nn.Module], norm: type[nn.Module], c_in: int, c_out: int, slope: float) -> nn.Sequential:
    """``conv`` k4 s2 p1 (no bias) + ``norm`` + LeakyReLU: halves (a convolution) or doubles (a transposed one)
    every spatial size."""
    return nn.Sequential(conv(c_in, c_out, 4, 2, 1, bias=False), norm(c_out), nn.LeakyReLU(slope, inplace=True))


def _check_sizes(channels: tuple[int, int, int], in_channels: int, out_channels: int,
                 output_stride: int = 2) -> tuple[int, int, int]:
    if len(channels) != 3 or any(int(c) < 1 for c in channels):
        raise ValueError(f"channels must be 3 positive ints, got {channels!r}")
    if output_stride not in (1, 2):
        raise ValueError(f"output_stride must be 1 or 2, got {output_stride!r}")
    if in_channels < 1 or out_channels < 1:
        raise ValueError(f"in_channels and out_channels must be positive, got {in_channels}, {out_channels}")
    return tuple(int(c) for c in channels)  # type: ignore[return-value]


def _check_input(x: Tensor, in_channels: int, axes: str) -> None:
    if x.ndim != 2 + len(axes.split(", ")) or x.shape[1] != in_channels:
        raise ValueError(f"x must have shape [B, {in_channels}, {axes}], got {tuple(x.shape)}")
    spatial = tuple(x.shape[2:])
    if any(s <= 0 or s % DOWNSAMPLE for s in spatial):
        raise ValueError(f"the spatial size ({axes}) = {spatial} of x must be positive and divisible by {DOWNSAMPLE}")


class _UNet(nn.Module):
    """The U-Net of :class:`UNet3D` over ``dims`` spatial axes: 3 (volumes ``[B, C, Z, Y, X]``) or 2 (images)."""

    def __init__(self, dims: int, in_channels: int, out_channels: int, channels: tuple[int, int, int],
                 negative_slope: float, normalize: bool, output_stride: int) -> None:
        super().__init__()
        c1, c2, c3 = _check_sizes(channels, in_channels, out_channels, output_stride)
        self.in_channels, self.out_channels, self.channels = in_channels, out_channels, (c1, c2, c3)
        self.normalize, self.output_stride, self._axes = normalize, int(output_stride), ("H, W", "Z, Y, X")[dims - 2]
        conv, up, norm = (getattr(nn, f"{layer}{dims}d") for layer in ("Conv", "ConvTranspose", "BatchNorm"))
        self.enc1 = _block(conv, norm, in_channels, c1, negative_slope)  # 1/2
        self.enc2 = _block(conv, norm, c1, c2, negative_slope)  # 1/4
        self.enc3 = _block(conv, norm, c2, c3, negative_slope)  # 1/8
        self.dec1 = _block(up, norm, c3, c2, negative_slope)  # 1/4, concatenated with enc2
        self.dec2 = _block(up, norm, 2 * c2, c1, negative_slope)  # 1/2, concatenated with enc1
        if self.output_stride == 1:
            c0 = max(c1 // 2, 1)
            self.dec3 = _block(up, norm, 2 * c1, c0, negative_slope)  # full resolution, concatenated with the input
            self.head = conv(c0 + in_channels, out_channels, kernel_size=1)
        else:
            self.head = conv(2 * c1, out_channels, kernel_size=1)

    def forward(self, x: Tensor) -> Tensor:
        """``[B, in_channels, *S]`` -> ``[B, out_channels, *S / s]`` (unit norm per voxel when ``normalize``).

        Convention: output on the grid of the same bounds at ``1/s`` the input's resolution.
        """
        _check_input(x, self.in_channels, self._axes)
        e1 = self.enc1(x)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)
        d1 = torch.cat((self.dec1(e3), e2), dim=1)
        d2 = torch.cat((self.dec2(d1), e1), dim=1)
        if self.output_stride == 1:
            d2 = torch.cat((self.dec3(d2), x.to(d2.dtype)), dim=1)
        out = self.head(d2)
        if self.normalize:
            out = F.normalize(out.float(), p=2.0, dim=1, eps=1e-12).to(out.dtype)
        return out


class UNet3D(_UNet):
    """3D encoder-decoder lifting an unprojected RGB-D volume to a 3D feature map.

    The layer list is the paper's (``k-s-c``): 4-2-64, 4-2-128, 4-2-256, 4-0.5-128, 4-0.5-64, 1-1-F. Every layer
    but the last is followed by BatchNorm3d and LeakyReLU (the convolutions feeding a BatchNorm carry no bias). The
    output of each transposed convolution is concatenated with the encoder feature of the same resolution before
    the next layer. ``output_stride=1`` (not the paper's) adds one more transposed convolution, 4-0.5-``c1 // 2``,
    whose output is concatenated with the input volume, so that the head gives features on the input grid.

    Args:
        in_channels: input channels; 4 for ``cat[occ, occ * rgb]``.
        out_channels: feature dimension ``F`` of the output (32 in the paper).
        channels: widths ``(c1, c2, c3)`` of the three encoder levels (64, 128, 256 in the paper).
        negative_slope: LeakyReLU slope for negative inputs.
        normalize: if true, L2-normalise the output per voxel along the channel axis.
        output_stride: input voxels per output voxel along each axis: 2 (the paper's) or 1 (the input's grid).

    Shape:
        - Input: ``[B, in_channels, Z, Y, X]`` with ``Z, Y, X`` divisible by 8.
        - Output: ``[B, out_channels, Z/s, Y/s, X/s]``, ``s = output_stride``.

    Raises:
        ValueError: in ``forward``, if ``x`` is not 5-D, has the wrong channel count or a spatial size not
            divisible by 8.

    Convention:
        ``[B, C, Z, Y, X]`` volumes; the output grid has the same bounds as the input grid at ``1/s`` the resolution.
        Under autocast the output has the autocast dtype (e.g. bf16); the L2 norm is computed in float32 with
        ``eps = 1e-12`` (an all-zero voxel stays zero). ``channels_last_3d`` inputs and weights are supported.
        In training mode BatchNorm needs more than one value per channel at the 1/8 bottleneck, so
        ``B * Z * Y * X / 512 > 1`` (an 8^3 input with batch 1 only runs in eval mode).
    """

    def __init__(self, in_channels: int = 4, out_channels: int = 32, channels: tuple[int, int, int] = (64, 128, 256),
                 negative_slope: float = 0.01, normalize: bool = True, output_stride: int = 2) -> None:
        super().__init__(3, in_channels, out_channels, channels, negative_slope, normalize, output_stride)
