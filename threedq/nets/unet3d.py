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


def _down(in_channels: int, out_channels: int, negative_slope: float) -> nn.Sequential:
    """Conv3d k4 s2 p1 + BatchNorm3d + LeakyReLU: halves every spatial size."""
    return nn.Sequential(
        nn.Conv3d(in_channels, out_channels, kernel_size=4, stride=2, padding=1, bias=False),
        nn.BatchNorm3d(out_channels),
        nn.LeakyReLU(negative_slope, inplace=True),
    )


def _up(in_channels: int, out_channels: int, negative_slope: float) -> nn.Sequential:
    """ConvTranspose3d k4 s2 p1 + BatchNorm3d + LeakyReLU: doubles every spatial size."""
    return nn.Sequential(
        nn.ConvTranspose3d(in_channels, out_channels, kernel_size=4, stride=2, padding=1, bias=False),
        nn.BatchNorm3d(out_channels),
        nn.LeakyReLU(negative_slope, inplace=True),
    )


class UNet3D(nn.Module):
    """3D encoder-decoder lifting an unprojected RGB-D volume to a 3D feature map.

    The layer list is the paper's (``k-s-c``): 4-2-64, 4-2-128, 4-2-256, 4-0.5-128, 4-0.5-64, 1-1-F. Every layer
    but the last is followed by BatchNorm3d and LeakyReLU (the convolutions feeding a BatchNorm carry no bias, which
    BatchNorm would cancel). The output of each transposed convolution is concatenated with the encoder feature of
    the same resolution before the next layer. With the default arguments the network has 5,788,960 parameters.

    ``output_stride=1`` (a departure from the paper) adds one more transposed convolution, 4-0.5-``c1 // 2``, whose
    output is concatenated with the input volume itself, so that the 1-1-F head gives features on the input grid
    (twice the paper's resolution along each axis, 8x the voxels).

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

    Convention:
        ``[B, C, Z, Y, X]`` volumes; the output grid has the same bounds as the input grid at ``1/s`` the resolution.
        Under autocast the output has the autocast dtype (e.g. bf16); the L2 norm is computed in float32 with
        ``eps = 1e-12`` (an all-zero voxel stays zero). ``channels_last_3d`` inputs and weights are supported.
        In training mode BatchNorm needs more than one value per channel at the 1/8 bottleneck, so
        ``B * Z * Y * X / 512 > 1`` (an 8^3 input with batch 1 only runs in eval mode).

    Example:
        >>> net = UNet3D()
        >>> net(torch.zeros(1, 4, 16, 16, 8)).shape
        torch.Size([1, 32, 8, 8, 4])
    """

    def __init__(
        self,
        in_channels: int = 4,
        out_channels: int = 32,
        channels: tuple[int, int, int] = (64, 128, 256),
        negative_slope: float = 0.01,
        normalize: bool = True,
        output_stride: int = 2,
    ) -> None:
        super().__init__()
        if len(channels) != 3 or any(int(c) < 1 for c in channels):
            raise ValueError(f"channels must be 3 positive ints, got {channels!r}")
        if output_stride not in (1, 2):
            raise ValueError(f"output_stride must be 1 or 2, got {output_stride!r}")
        if in_channels < 1 or out_channels < 1:
            raise ValueError(f"in_channels and out_channels must be positive, got {in_channels}, {out_channels}")
        c1, c2, c3 = (int(c) for c in channels)
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.channels = (c1, c2, c3)
        self.normalize = normalize
        self.output_stride = int(output_stride)
        self.enc1 = _down(in_channels, c1, negative_slope)  # 1/2
        self.enc2 = _down(c1, c2, negative_slope)  # 1/4
        self.enc3 = _down(c2, c3, negative_slope)  # 1/8
        self.dec1 = _up(c3, c2, negative_slope)  # 1/4, concatenated with enc2
        self.dec2 = _up(2 * c2, c1, negative_slope)  # 1/2, concatenated with enc1
        if self.output_stride == 1:
            c0 = max(c1 // 2, 1)
            self.dec3 = _up(2 * c1, c0, negative_slope)  # full resolution, concatenated with the input
            self.head = nn.Conv3d(c0 + in_channels, out_channels, kernel_size=1)
        else:
            self.head = nn.Conv3d(2 * c1, out_channels, kernel_size=1)

    def forward(self, x: Tensor) -> Tensor:
        """Lift a volume to features.

        Args:
            x: ``[B, in_channels, Z, Y, X]`` input volume, ``Z, Y, X`` divisible by 8.

        Returns:
            ``[B, out_channels, Z/s, Y/s, X/s]`` features (``s = output_stride``), unit L2 norm per voxel when
            ``normalize``.

        Raises:
            ValueError: if ``x`` is not 5-D, has the wrong channel count or a spatial size not divisible by 8.

        Convention:
            ``[B, C, Z, Y, X]``; output on the grid of the same bounds at ``1/s`` the input's resolution.
        """
        if x.ndim != 5 or x.shape[1] != self.in_channels:
            raise ValueError(f"x must have shape [B, {self.in_channels}, Z, Y, X], got {tuple(x.shape)}")
        spatial = tuple(x.shape[2:])
        if any(s <= 0 or s % DOWNSAMPLE for s in spatial):
            raise ValueError(
                f"the spatial size (Z, Y, X) = {spatial} of x must be positive and divisible by {DOWNSAMPLE}"
            )
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
