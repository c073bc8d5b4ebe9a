"""The 2D encoder-decoder of 2.5DQ-Nets: UNet3D's layer list with 2D convolutions, and its autoencoding head.

:class:`UNet2D` is :class:`~threedq.nets.UNet3D` with ``Conv2d`` / ``ConvTranspose2d`` (4-2-64, 4-2-128, 4-2-256,
4-0.5-128, 4-0.5-64, 1-1-F, skip concatenations, per-pixel L2-normalised output at half resolution);
:class:`RGBDDecoder2D` maps those features back to the full-resolution RGB-D view.

Convention:
    Images ``[B, C, H, W]`` (row y down, column x right); the feature map at half resolution covers the same
    image extent: feature pixel ``(i, j)`` covers image pixels ``2i..2i+1``, ``2j..2j+1``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .unet3d import _block, _UNet

__all__ = ["RGBDDecoder2D", "UNet2D"]


class UNet2D(_UNet):
    """2D encoder-decoder over ``cat[rgb, depth]`` producing a per-pixel feature map at half resolution.

    Args:
        in_channels: input channels (4 for RGB-D).
        out_channels: feature dimension ``F`` (32, as the 3D encoder's).
        channels: widths of the three encoder levels.
        negative_slope: LeakyReLU slope.
        normalize: L2-normalise the output per pixel.

    Shape:
        - Input: ``[B, in_channels, H, W]``, ``H, W`` divisible by 8.
        - Output: ``[B, out_channels, H/2, W/2]``.

    Convention: see the module docstring.
    """

    def __init__(self, in_channels: int = 4, out_channels: int = 32, channels: tuple[int, int, int] = (64, 128, 256),
                 negative_slope: float = 0.01, normalize: bool = True) -> None:
        super().__init__(2, in_channels, out_channels, channels, negative_slope, normalize, 2)


class RGBDDecoder2D(nn.Module):
    """Half-resolution features -> the full-resolution RGB-D view (the autoencoding target).

    ConvTranspose2d k4 s2 (F -> hidden) + BatchNorm + LeakyReLU, a 3x3 conv block, and a 1x1 conv to 4
    channels: RGB as ``0.5 tanh`` (RGB in [-0.5, 0.5], as the view decoder) and normalised depth (linear).

    Shape: ``[B, F, h, w]`` -> ``rgb`` ``[B, 3, 2h, 2w]``, ``depth`` ``[B, 1, 2h, 2w]``.
    """

    def __init__(self, in_channels: int = 32, hidden: int = 64, negative_slope: float = 0.01) -> None:
        super().__init__()
        self.up = _block(nn.ConvTranspose2d, nn.BatchNorm2d, in_channels, hidden, negative_slope)
        conv = nn.Conv2d(hidden, hidden, 3, 1, 1, bias=False)
        self.conv = nn.Sequential(conv, nn.BatchNorm2d(hidden), nn.LeakyReLU(negative_slope, inplace=True))
        self.out = nn.Conv2d(hidden, 4, 1)

    def forward(self, feats: Tensor) -> tuple[Tensor, Tensor]:
        y = self.out(self.conv(self.up(feats)))
        return 0.5 * torch.tanh(y[:, :3]), y[:, 3:]
